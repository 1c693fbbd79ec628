"""Has the closed-loop twin left the real flight's envelope?  (pure numpy; no ROS, no I/O)

A twin that flies away from the vehicle it shadows gives metrics that say nothing about the model: a
twin on the ground while the vehicle flies has "throttle errors" of its idle motors.  :func:`detect`
finds the first such divergence on the airborne part of the flight and names its time and cause:

- ``attitude``: the twin's body z axis more than :data:`ATT_ERR_DEG` from the real one, the twin the
  more tilted of the two, for :data:`ATT_SUSTAIN_S` without a break (a real vehicle flung by a gust
  that the still-air twin does not follow is the metrics' business, not a divergence of the twin);
- ``heading``: the twin's heading more than :data:`YAW_ERR_DEG` from the real one for
  :data:`YAW_SUSTAIN_S` (the vehicle spun and the twin did not, or the other way round).  Not while both
  are out of yaw control (where the log has PX4's attitude setpoint): from the first time each is more
  than :data:`YAW_ERR_DEG` from its heading until it is back within :data:`YAW_HELD_DEG` of it for
  :data:`YAW_SUSTAIN_S`.  A vehicle whose yaw authority ran out (a motor pair at full output, PX4's
  allocation giving yaw up) turns at a rate no twin can phase-match; a twin that ran out too spins with
  it and has not left the flight, one that held its heading while the vehicle spun has;
- ``motors oscillating``: a twin motor going rail to rail (below :data:`RAIL_LO`, above
  :data:`RAIL_HI`) at least :data:`RAIL_SWITCHES` times within :data:`RAIL_WINDOW_S` while the real
  motors in that window span less than :data:`REAL_SPAN_MAX` (a twin limit cycle, not the vehicle's);
- ``crash``: the twin within :data:`CRASH_H_M` of its ground (the take-off height) for
  :data:`CRASH_SUSTAIN_S` while the real vehicle is more than :data:`CRASH_REAL_H_M` above it, unless the
  vehicle itself comes down within :data:`CRASH_NEAR_S` (within :data:`VEHICLE_DOWN_M` of the ground, or its
  land detector says landed): a twin that leads the vehicle's own descent to the ground by a second or two
  has had no crash the vehicle did not have;
- ``height run-away``: the height error above :data:`RUNAWAY_Z_PILOT_M` where the pilot, not PX4, held
  the height (manual modes, flown with the pilot stand-in), for :data:`RUNAWAY_SUSTAIN_S`;
- ``position run-away``: the horizontal error above :data:`RUNAWAY_XY_M` where PX4 controlled the
  horizontal position, or the height error above :data:`RUNAWAY_Z_M` where it controlled the height,
  for :data:`RUNAWAY_SUSTAIN_S`;
- ``non-finite state``: the twin's state became NaN/inf.

The checks on the position (crash, run-aways) are not made where the vehicle's own position estimate failed
(:mod:`twin_nodes.twin.estimate_check`): the real position is not known there, and a twin "away" from it says
nothing.  Where the pilot held the height, it is compared with the estimate less its resets
(:func:`~twin_nodes.twin.estimate_check.height_without_resets`: a reset moves the estimate's frame, not the
vehicle; the pilot stand-in follows the same height).

The thresholds are outside what a twin that follows its vehicle shows.  Measured on the 8 shared real
logs (whole flights, airborne, ground phases excluded; 2026-11-27): tilt error ≤ 20°, but on climb35m,
where the vehicle itself was flung to 70° of roll at 34 s and buffeted in its own wake at 42 s (up to
85° between the two; the twin was the less tilted: no divergence); heading error ≤ 52° (climb35m 81°
for less than 2 s); XY ≤ 2.5 m, Z ≤ 2.3 m.  What they catch is a twin flying another flight.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from twin_nodes.twin.estimate_check import estimate_failed, height_without_resets

__all__ = ["detect", "ATT_ERR_DEG", "ATT_SUSTAIN_S", "RUNAWAY_XY_M", "RUNAWAY_Z_M", "YAW_HELD_DEG"]

ATT_ERR_DEG = 30.0
ATT_SUSTAIN_S = 1.0
YAW_ERR_DEG = 90.0
YAW_SUSTAIN_S = 2.0
#: a vehicle out of yaw control is back in it once within this of PX4's heading for YAW_SUSTAIN_S [deg]
YAW_HELD_DEG = 30.0
RAIL_LO, RAIL_HI = 0.05, 0.95
RAIL_SWITCHES = 3
RAIL_WINDOW_S = 1.0
REAL_SPAN_MAX = 0.6
CRASH_H_M = 0.15
CRASH_REAL_H_M = 1.0
CRASH_SUSTAIN_S = 0.5
#: the vehicle's own touchdown within this after the twin's is no crash of the twin [s]: the pilot
#: stand-in's closed-loop time constant 1 / OMEGA (2 s) plus the land detector's ~1 s
CRASH_NEAR_S = 3.0
#: the vehicle within this of its ground is down [m] (the metrics' take-off/touchdown margin)
VEHICLE_DOWN_M = 0.5
RUNAWAY_XY_M = 10.0
RUNAWAY_Z_M = 5.0
#: the height error where PX4 did not control the height but the pilot did (manual modes) [m]
RUNAWAY_Z_PILOT_M = 5.0
RUNAWAY_SUSTAIN_S = 2.0
#: the grid the checks run on [Hz]
RATE_HZ = 50.0


def _first_sustained(t: np.ndarray, flag: np.ndarray, sustain_s: float) -> float | None:
    """Time at which ``flag`` has been true without a break for ``sustain_s`` (its start), else None."""
    return _first_sustained_unless(t, flag, sustain_s, t[:0], flag[:0], 0.0)


def _first_sustained_unless(t: np.ndarray, flag: np.ndarray, sustain_s: float, t_ex: np.ndarray,
                            excuse: np.ndarray, within_s: float) -> float | None:
    """:func:`_first_sustained` for the runs of ``flag`` that have no ``excuse`` (on its own times ``t_ex``,
    which may reach past ``t``) within ``within_s`` after their start (a run that has one is skipped, the
    next one checked)."""
    idx = np.flatnonzero(flag)
    if idx.size == 0:
        return None
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    ends = np.concatenate([idx[breaks], [idx[-1]]])
    for a, b in zip(starts, ends):
        if t[b] - t[a] >= sustain_s - 1e-9 and not excuse[(t_ex >= t[a]) & (t_ex <= t[a] + within_s)].any():
            return float(t[a])
    return None


def _rail_switches(u: np.ndarray) -> np.ndarray:
    """Per sample: 1 where a motor's rail state (-1 low, +1 high) differs from its previous rail state."""
    r = np.where(u >= RAIL_HI, 1, np.where(u <= RAIL_LO, -1, 0))
    out = np.zeros(u.shape, int)
    idx = np.flatnonzero(r)
    if idx.size > 1:
        v = r[idx]
        out[idx[1:][v[1:] != v[:-1]]] = 1
    return out


def _oscillation(t: np.ndarray, u_twin: np.ndarray, u_real: np.ndarray, ok: np.ndarray) -> tuple[float, int] | None:
    """(time, motor index) of the first twin rail-to-rail oscillation the real motors do not share."""
    n_win = max(int(round(RAIL_WINDOW_S * RATE_HZ)), 2)
    best: tuple[float, int] | None = None
    for i in range(u_twin.shape[1]):
        u = np.where(ok, u_twin[:, i], 0.5)
        sw = _rail_switches(np.nan_to_num(u, nan=0.5))
        c = np.concatenate([[0], np.cumsum(sw)])
        cnt = c[n_win:] - c[:-n_win]  # switches in the window ending at each sample
        hits = np.flatnonzero(cnt >= RAIL_SWITCHES)
        for h in hits:
            lo, hi = h, h + n_win
            real = u_real[lo:hi]
            real = real[np.isfinite(real)]
            span = float(real.max() - real.min()) if real.size else 0.0
            if span < REAL_SPAN_MAX:
                # from the first sample at a rail in that window: where the oscillation begins
                at_rail = np.flatnonzero((u[lo:hi] >= RAIL_HI) | (u[lo:hi] <= RAIL_LO))
                t_hit = float(t[lo + (at_rail[0] if at_rail.size else 0)])
                if best is None or t_hit < best[0]:
                    best = (t_hit, i)
                break
    return best


def _body_z(q: np.ndarray) -> np.ndarray:
    """The body z axis in the world frame of (n, 4) quaternions w, x, y, z."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.column_stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])


def _yaw(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q.T
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def _setpoint_heading(log: Any, t: np.ndarray) -> np.ndarray:
    """The heading [rad] of PX4's own attitude setpoint (``attitude_setpoint_q``) on ``t``; NaN where the
    log has none (before its first sample, or no such series)."""
    sp = log.get("attitude_setpoint_q")
    if sp is None or not len(sp):
        return np.full(t.shape, np.nan)
    q = np.asarray(sp.at(t), float)
    ok = np.isfinite(q).all(axis=1) & (t >= float(sp.t_s[0]))
    return np.where(ok, _yaw(np.where(ok[:, None], q, [1.0, 0.0, 0.0, 0.0])), np.nan)


def _out_of_yaw_control(t: np.ndarray, q: np.ndarray, yaw_sp: np.ndarray) -> np.ndarray:
    """Where the vehicle of attitudes ``q`` is out of yaw control: from the first sample more than
    :data:`YAW_ERR_DEG` from the setpoint heading ``yaw_sp`` [rad] until it has been back within
    :data:`YAW_HELD_DEG` of it for :data:`YAW_SUSTAIN_S` (a spinning vehicle passes its setpoint
    but does not stay there).  All False where there is no setpoint."""
    with np.errstate(invalid="ignore"):
        err = np.degrees(np.abs(np.angle(np.exp(1j * (_yaw(q) - yaw_sp)))))
        off, near = err > YAW_ERR_DEG, err <= YAW_HELD_DEG
    idx = np.arange(t.size)
    # the start of the run of "near" samples each sample is in, and where such a run has lasted long enough
    starts = np.maximum.accumulate(np.where(near & ~np.r_[False, near[:-1]], idx, -1))
    back = near & (t - t[np.maximum(starts, 0)] >= YAW_SUSTAIN_S)
    # out of control since the last sample off the setpoint, unless back in control since then
    last_off = np.maximum.accumulate(np.where(off, idx, -1))
    last_back = np.maximum.accumulate(np.where(back, idx, -1))
    return (last_off >= 0) & (last_back < last_off)


def detect(run: Any, log: Any, xy_controlled=None, z_controlled=None, t0: float | None = None,
           t1: float | None = None, ground=None) -> dict | None:
    """The first divergence of the closed-loop twin ``run`` (:class:`~twin_nodes.twin.runner.TwinRun`)
    from the real ``log`` on its airborne part (between ``t0`` and ``t1`` when given):
    ``{"t_s", "cause", "detail"}``, or None.  ``xy_controlled``/``z_controlled``: callables giving
    where PX4 controlled each axis on a time grid (None: everywhere); ``ground``: a callable giving the
    samples of a time grid where the real vehicle is still on or near the ground (not checked there;
    :func:`twin_nodes.twin.compare.ground_phases`)."""
    if run.mode != "closed" or len(run.t) < 2:
        return None
    iv = log.airborne_intervals()
    lo = max(float(run.t[0]), t0 if t0 is not None else -math.inf)
    hi = min(float(run.t[-1]), t1 if t1 is not None else math.inf)
    if hi <= lo:
        return None
    t = np.arange(lo, hi, 1.0 / RATE_HZ)
    air = np.zeros(t.shape, bool)
    for a, b in iv or [(lo, hi)]:
        air |= (t >= a) & (t <= b)
    pos = log.get("position_enu")
    if ground is not None:
        # not while the real vehicle is still on or near the ground at either end (its landing gear
        # holds its yaw and height there; the twin's has none): the metrics' ground phases
        air &= ~np.asarray(ground(t), bool)
    if not air.any():
        return None

    def twin(cols):
        return np.column_stack([np.interp(t, run.t, run.x[:, c]) for c in cols])
    found: list[tuple[float, str, str]] = []
    bad = ~np.isfinite(run.x[:, :13]).all(axis=1)
    if bad.any():
        tb = float(run.t[np.argmax(bad)])
        if lo <= tb <= hi:
            found.append((tb, "non-finite state", "the twin's state became NaN/inf"))
    att = log.get("attitude_q")
    z_ground = float(run.info.get("ground_z", 0.0)) if isinstance(run.info, dict) else 0.0
    if att is not None and len(att):
        q_real, q_twin = att.at(t, "slerp"), twin(range(6, 10))
        z_real, z_twin = _body_z(q_real), _body_z(q_twin)
        tilt_err = np.degrees(np.arccos(np.clip(np.sum(z_real * z_twin, axis=1), -1.0, 1.0)))
        # the twin off level where the vehicle was not (a vehicle flung by a gust that the still-air
        # twin does not follow is no divergence of the twin: the metrics show it)
        twin_more = z_twin[:, 2] < z_real[:, 2]
        with np.errstate(invalid="ignore"):
            ts = _first_sustained(t, air & twin_more & (tilt_err > ATT_ERR_DEG), ATT_SUSTAIN_S)
        if ts is not None:
            k = np.searchsorted(t, ts)
            found.append((ts, "attitude", f"the twin tilted {tilt_err[k]:.0f} deg away from the real attitude for "
                                          f">= {ATT_SUSTAIN_S:g} s (limit {ATT_ERR_DEG:g} deg)"))
        yaw_err = np.degrees(np.abs(np.angle(np.exp(1j * (_yaw(q_twin) - _yaw(q_real))))))
        yaw_sp = _setpoint_heading(log, t)
        both_lost = _out_of_yaw_control(t, q_real, yaw_sp) & _out_of_yaw_control(t, q_twin, yaw_sp)
        with np.errstate(invalid="ignore"):
            ts = _first_sustained(t, air & (yaw_err > YAW_ERR_DEG) & ~both_lost, YAW_SUSTAIN_S)
        if ts is not None:
            k = np.searchsorted(t, ts)
            found.append((ts, "heading", f"the twin's heading {yaw_err[k]:.0f} deg from the real one for "
                                         f">= {YAW_SUSTAIN_S:g} s (limit {YAW_ERR_DEG:g} deg)"))
    mot = log.get("motors")
    if mot is not None and len(mot) and run.motors.ndim == 2:
        u_twin = np.column_stack([np.interp(t, run.t, run.motors[:, i]) for i in range(run.motors.shape[1])])
        u_real = mot.at(t, "linear")
        if u_real.shape[1] == u_twin.shape[1]:
            osc = _oscillation(t, u_twin, u_real, air)
            if osc is not None:
                found.append((osc[0], "motors oscillating",
                              f"twin motor {osc[1] + 1} rail to rail >= {RAIL_SWITCHES} times in {RAIL_WINDOW_S:g} s "
                              f"while the real motors span < {REAL_SPAN_MAX:g}"))
    if pos is not None and len(pos):
        # the position checks only where the vehicle's own estimate is trusted
        trusted = ~estimate_failed(log, t)[0]
        p_real = pos.at(t, "linear")
        p_twin = twin(range(3))
        g_t = run.info.get("ground_z_t") if isinstance(run.info, dict) else None
        if g_t is not None and len(g_t) == len(run.t) and len(g_t):
            # the twin's ground plane where it moved (a second take-off from another height)
            z_ground = np.interp(t, run.t, g_t)
        h_twin = p_twin[:, 2] - z_ground
        h_real = p_real[:, 2] - z_ground
        # whether the vehicle itself comes down: looked for up to CRASH_NEAR_S past the checked span
        t_ex = np.arange(lo, min(hi + CRASH_NEAR_S, float(pos.t_s[-1])), 1.0 / RATE_HZ)
        in_air = np.zeros(t_ex.shape, bool)
        for a, b in iv or [(lo, hi)]:
            in_air |= (t_ex >= a) & (t_ex <= b)
        g_ex = np.interp(t_ex, t, z_ground) if np.ndim(z_ground) else z_ground
        with np.errstate(invalid="ignore"):
            down = (pos.at(t_ex, "linear")[:, 2] - g_ex < VEHICLE_DOWN_M) | ~in_air
            ts = _first_sustained_unless(t, air & trusted & (h_twin < CRASH_H_M) & (h_real > CRASH_REAL_H_M),
                                         CRASH_SUSTAIN_S, t_ex, down, CRASH_NEAR_S)
        if ts is not None:
            k = np.searchsorted(t, ts)
            found.append((ts, "crash", f"the twin on the ground while the vehicle flew {h_real[k]:.1f} m above it "
                                       f"and did not come down within {CRASH_NEAR_S:g} s"))
        exy = np.linalg.norm(p_twin[:, :2] - p_real[:, :2], axis=1)
        ez = np.abs(p_twin[:, 2] - p_real[:, 2])
        # where the pilot held the height: against the vehicle's height without the resets of its estimate
        # (a reset moves the estimate's frame, not the vehicle; the pilot stand-in follows the same height)
        ez_pilot = np.abs(p_twin[:, 2] - height_without_resets(log, t)[0])
        cxy = np.ones(t.shape, bool) if xy_controlled is None else xy_controlled(t)
        cz = np.ones(t.shape, bool) if z_controlled is None else z_controlled(t)
        with np.errstate(invalid="ignore"):
            run_away = air & trusted & ((cxy & (exy > RUNAWAY_XY_M)) | (cz & (ez > RUNAWAY_Z_M)))
            # where the pilot held the height (manual modes: the twin's pilot stand-in holds the real
            # height), a twin that climbs or falls away beyond the stand-in's authority has left too
            run_away_pilot = air & ~cz & trusted & (ez_pilot > RUNAWAY_Z_PILOT_M)
        tp = _first_sustained(t, run_away_pilot, RUNAWAY_SUSTAIN_S)
        if tp is not None:
            k = np.searchsorted(t, tp)
            found.append((tp, "height run-away",
                          f"twin {ez_pilot[k]:.1f} m from the vehicle's height where the pilot held it (a manual mode: "
                          f"the pilot stand-in could not hold it; limit {RUNAWAY_Z_PILOT_M:g} m for "
                          f"{RUNAWAY_SUSTAIN_S:g} s)"))
        ts = _first_sustained(t, run_away, RUNAWAY_SUSTAIN_S)
        if ts is not None:
            k = np.searchsorted(t, ts)
            found.append((ts, "position run-away",
                          f"twin {exy[k]:.1f} m (horizontal) / {ez[k]:.1f} m (height) from the vehicle where PX4 "
                          f"held that axis (limits {RUNAWAY_XY_M:g} / {RUNAWAY_Z_M:g} m for {RUNAWAY_SUSTAIN_S:g} s)"))
    if not found:
        return None
    t_s, cause, detail = min(found, key=lambda f: f[0])
    return {"t_s": round(t_s, 2), "cause": cause, "detail": detail}
