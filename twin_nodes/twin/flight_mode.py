"""Which PX4 flight mode flies the twin how, and where PX4 controlled the position.

PX4 runs its position controller (``mc_pos_control``) in every ``nav_state`` but the stick modes:
MANUAL/STAB/RATTITUDE fly PX4's attitude setpoint, ACRO its rate setpoint, OFFBOARD what its
``offboard_control_mode`` flags say.  :func:`fly_mode` makes that decision for one control step of the
closed-loop twin (:class:`~twin_nodes.twin.runner.TwinRunner`); :func:`controlled_axes` says, over a whole
log, where PX4 held the horizontal position and the height (there only are they scored).
"""

from __future__ import annotations

import math

import numpy as np

from twin_nodes.logs.ulog_io import MANUAL_NAV_STATES
from twin_nodes.twin.estimate_check import estimate_failed

__all__ = ["ACRO_NAV_STATE", "ALTCTL_NAV_STATE", "OFFBOARD_NAV_STATE", "FLOWN_AS", "fly_mode", "decide_mode", "fly_modes", "controlled_axes"]

#: PX4 nav_state values with their own setpoint: ACRO flies the rate setpoint, OFFBOARD what its flags say
ACRO_NAV_STATE = 10.0
ALTCTL_NAV_STATE = 1.0
OFFBOARD_NAV_STATE = 14.0
#: how a closed-loop control step was flown: PX4's attitude setpoint (MANUAL/STAB, offboard attitude),
#: its rate setpoint (ACRO), the real attitude (a manual mode in a log without an attitude setpoint),
#: the position/velocity cascade (ALTCTL/POSCTL/AUTO/offboard trajectories), or not at all (disarmed)
FLOWN_AS = ("attitude", "rates", "real_attitude", "cascade", "grounded", "disarmed")


def fly_mode(nav: float, real_throttle: float, att_q: np.ndarray, att_thrust: float, rates_sp: np.ndarray,
             offboard_flags: np.ndarray, sp: np.ndarray, has_real_state: bool) -> str:
    """What PX4 flies now (:data:`FLOWN_AS`, armed and not grounded), by its ``nav`` state and what the log
    carries: its collective thrust setpoint ``real_throttle`` (0..1, NaN: not logged), attitude setpoint
    ``att_q`` (4,) with its thrust ``att_thrust``, rate setpoint ``rates_sp`` (3,) FLU, offboard flags (6,)
    (position, velocity, acceleration, attitude, body_rate, thrust; NaN: not logged) and the twin's setpoint
    ``sp`` (SP_SIZE,); ``has_real_state``: a real state has been received."""
    f = offboard_flags
    f_ok = bool(np.isfinite(f).all())
    return decide_mode(nav, math.isfinite(real_throttle), bool(np.isfinite(att_q).all()), math.isfinite(att_thrust),
                       bool(np.isfinite(rates_sp).all()), f_ok, f_ok and bool((f[0:3] > 0).any()),
                       f_ok and bool(f[3] > 0), f_ok and bool(f[4] > 0), bool(np.isfinite(sp[0:9]).any()),
                       has_real_state)


def decide_mode(nav: float, thr_ok: bool, q_ok: bool, att_thr_ok: bool, w_ok: bool, f_ok: bool, f_pos: bool,
                f_att: bool, f_rate: bool, traj: bool, has_real_state: bool) -> str:
    """:func:`fly_mode` on what it reads of its inputs: the thrust setpoint finite (``thr_ok``), the attitude
    setpoint all finite (``q_ok``) and its thrust (``att_thr_ok``), the rate setpoint all finite (``w_ok``),
    the offboard flags all finite (``f_ok``) and then a position/velocity/acceleration flag, the attitude
    flag and the body-rate flag set (``f_pos``, ``f_att``, ``f_rate``), a trajectory setpoint (``traj``:
    any of sp[0:9] finite).  The offline run decides these once per log row (:func:`fly_modes`)."""
    if nav == ACRO_NAV_STATE:
        if w_ok and thr_ok:
            return "rates"
    elif nav in MANUAL_NAV_STATES:
        if q_ok and thr_ok:
            return "attitude"
    elif nav == OFFBOARD_NAV_STATE:
        if f_ok:
            if f_pos and traj:
                return "cascade"
            if f_att and q_ok and (thr_ok or att_thr_ok):
                return "attitude"
            if f_rate and w_ok and thr_ok:
                return "rates"
        elif not traj:
            if q_ok and (thr_ok or att_thr_ok):
                return "attitude"
            if w_ok and thr_ok:
                return "rates"
        return "cascade"
    else:
        return "cascade"
    # a manual mode without the setpoint this log would need: the pilot's throttle and the real attitude
    return "real_attitude" if thr_ok and has_real_state else "cascade"


def fly_modes(nav: np.ndarray, real_throttle: np.ndarray, att_q: np.ndarray, att_thrust: np.ndarray,
              rates_sp: np.ndarray, offboard_flags: np.ndarray, sp: np.ndarray) -> tuple[list[str], list[bool]]:
    """:func:`fly_mode` for each of n rows of the same inputs ((n,), (n, 4), (n, 3), (n, 6), (n, SP_SIZE)),
    with a real state received, and whether each row's attitude setpoint is all finite: the per-row tests
    vectorised once instead of per control step."""
    fin = np.isfinite
    f = np.asarray(offboard_flags, float)
    f_ok = fin(f).all(axis=1)
    q_ok = fin(att_q).all(axis=1).tolist()
    rows = zip(np.asarray(nav, float).tolist(), fin(real_throttle).tolist(), q_ok, fin(att_thrust).tolist(),
               fin(rates_sp).all(axis=1).tolist(), f_ok.tolist(), (f_ok & (f[:, 0:3] > 0).any(axis=1)).tolist(),
               (f_ok & (f[:, 3] > 0)).tolist(), (f_ok & (f[:, 4] > 0)).tolist(),
               fin(sp[:, 0:9]).any(axis=1).tolist())
    return [decide_mode(*r, True) for r in rows], q_ok


def controlled_axes(log, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """Where PX4 controlled the horizontal position (``xy``) and the height (``z``) on the times ``t``:
    a position or velocity setpoint finite in that axis (``trajectory_setpoint``; NaN = not controlled,
    as PX4's ``PositionControl`` reads it) while ``mc_pos_control`` runs (not MANUAL/STAB/ACRO; in
    OFFBOARD only with the position or velocity flag where ``offboard_control_mode`` is logged).
    Returns ``(xy, z, how)``; a log without any position/velocity setpoint counts every axis as
    controlled (the twin then holds the real position) and ``how`` says so."""
    t = np.asarray(t, float)
    sp_p, sp_v = log.get("setpoint_position_enu"), log.get("setpoint_velocity_enu")
    how = "trajectory_setpoint position/velocity finite per axis, nav_state not MANUAL/STAB/ACRO"
    if (sp_p is None or not len(sp_p)) and (sp_v is None or not len(sp_v)):
        xy, z = np.ones(t.shape, bool), np.ones(t.shape, bool)
        how = ("no trajectory_setpoint in the log: every axis scored where nav_state is no manual mode (the twin "
               "holds the real position there), the height only in ALTCTL")
        nav = log.get("nav_state")
        if nav is not None and len(nav):
            xy &= nav.at(t, "previous")[:, 0] != ALTCTL_NAV_STATE
    else:
        def at(s, k):
            return s.at(t, "previous") if s is not None and len(s) else np.full((len(t), k), np.nan)
        p, v = at(sp_p, 3), at(sp_v, 3)
        xy = np.isfinite(p[:, :2]).all(axis=1) | np.isfinite(v[:, :2]).all(axis=1)
        z = np.isfinite(p[:, 2]) | np.isfinite(v[:, 2])
    nav = log.get("nav_state")
    if nav is not None and len(nav):
        ns = nav.at(t, "previous")[:, 0]
        running = ~np.isin(ns, MANUAL_NAV_STATES)
        ocm = log.get("offboard_mode")
        if ocm is not None and len(ocm):
            f = ocm.at(t, "previous")
            traj_flag = np.nan_to_num(f[:, 0]) + np.nan_to_num(f[:, 1]) > 0
            running &= (ns != OFFBOARD_NAV_STATE) | traj_flag
        xy &= running
        z &= running
    bad, bad_how = estimate_failed(log, t)
    if bad.any():
        xy &= ~bad
        z &= ~bad
        how += f"; not where the vehicle's own position estimate failed ({bad_how})"
    return xy, z, how
