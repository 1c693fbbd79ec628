"""A whole log's real-vehicle inputs to the twin, on the twin's control grid.

:func:`log_inputs` resamples the series the twin needs onto one uniform grid (the log's resampler; long
gaps in the position setpoint bridged by :func:`bridge_setpoint_gaps`); :func:`log_feed` turns them into
the per-step rows :func:`~twin_nodes.twin.runner.run_twin_on_log` feeds to the
:class:`~twin_nodes.twin.runner.TwinRunner`, the per-sample work done once, vectorized.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin_nodes.logs import time_sync
from twin_nodes.twin.control import SP_SIZE

__all__ = ["MODE_INPUTS", "SETPOINT_GAP_S", "log_inputs", "bridge_setpoint_gaps", "setpoint_rows", "armed_rows", "LogFeed",
           "log_feed"]

#: the series the modes without a position controller fly (:func:`twin_nodes.twin.flight_mode.fly_mode`)
MODE_INPUTS = ("attitude_setpoint_q", "attitude_setpoint_thrust", "attitude_setpoint_yawrate", "setpoint_rates_flu",
               "offboard_mode")
#: a gap between two logged position setpoints longer than this [s] is bridged linearly (PX4 published the
#: setpoint at 50 Hz; a logger that dropped it for seconds, as on the Mantis follow flights' 4.4 s gaps
#: with the target 9 m on, would have the twin hold the old one and then jump)
SETPOINT_GAP_S = 1.0
#: the setpoint series the offline twin reads between their samples (``log_inputs(between_samples=True)``;
#: the yaw is carried by its rate in the runner)
SETPOINT_BETWEEN_KEYS = ("setpoint_position_enu", "setpoint_velocity_enu", "setpoint_accel_enu")


def log_inputs(log, rate_hz: float, t0: float | None = None, t1: float | None = None,
               between_samples: bool = True) -> dict[str, np.ndarray]:
    """The real-vehicle inputs the twin needs, on one uniform grid (uses the log's resampler).
    ``between_samples``: the setpoint trajectory read between its logged samples (the straight line between
    two); False: each sample held until the next (gaps over SETPOINT_GAP_S in the position bridged), as the
    live twin in the graph receives them."""
    names = ["position_enu", "velocity_enu", "attitude_q", "body_rates_flu", "motors"]
    optional = ["setpoint_position_enu", "setpoint_velocity_enu", "setpoint_accel_enu", "setpoint_yaw_enu",
                "setpoint_yawspeed", "armed", "battery_v", "nav_state", "throttle"]
    present = names + [n for n in optional if log.get(n) is not None]
    grid, data = log.resample(present, rate_hz, t0, t1)
    data["t"] = grid
    # the setpoint trajectory between its logged samples: PX4's (and RotorPy's) controller followed it at its own
    # rate, the log keeps a 5-50 Hz subsample, so the offline twin reads the straight line between two samples
    # (between_samples) where a sample-and-hold would lag it by half a logging interval (on RotorPy's fast
    # descents, 25 Hz, the held acceleration left the twin's braking 0.2-0.5 of full throttle off for a fraction
    # of a second: 4.8 % held-out throttle RMSE with the exact plant).  Long gaps (SETPOINT_GAP_S) were
    # bridged so before.  The live twin, which has no next sample, carries the last one (TwinRunner).
    for key in SETPOINT_BETWEEN_KEYS if between_samples else ("setpoint_position_enu",):
        s = log.get(key)
        if s is not None and len(s) > 1 and key in data:
            data[key] = bridge_setpoint_gaps(s.t_s, s.values, grid, data[key],
                                             min_gap_s=0.0 if between_samples else SETPOINT_GAP_S
                                             ).reshape(np.shape(data[key]))
    # PX4's own attitude/rate setpoints and offboard flags, for the modes without a position
    # controller: on the same grid (they do not shorten it), NaN before their first sample
    for n in MODE_INPUTS:
        s = log.get(n)
        if s is not None and len(s):
            data[n] = time_sync.interp_to(s.t_s, s.values, grid, kind=s.interp)
    return data


def bridge_setpoint_gaps(ts: np.ndarray, values: np.ndarray, grid: np.ndarray, held: np.ndarray,
                         min_gap_s: float = SETPOINT_GAP_S) -> np.ndarray:
    """``held`` (a setpoint on ``grid``, held from each logged sample) with every gap longer than ``min_gap_s``
    between two logged samples finite in an axis replaced there by the straight line between them; shorter
    gaps and everything else unchanged (``min_gap_s`` 0: every gap, the trajectory between its samples)."""
    out = np.array(held, float, copy=True).reshape(len(grid), -1)
    ts = np.asarray(ts, float)
    vals = np.asarray(values, float).reshape(len(ts), -1)
    g = np.asarray(grid, float)
    if len(ts) < 2 or not len(g):
        return out
    k = np.searchsorted(ts, g, side="right") - 1
    inside = (k >= 0) & (k < len(ts) - 1)
    kk = np.clip(k, 0, len(ts) - 2)
    a, b = ts[kk], ts[kk + 1]
    inside &= (g > a) & (g < b) & ((b - a) > min_gap_s)
    if not inside.any():
        return out
    i = np.flatnonzero(inside)
    w = ((g[i] - a[i]) / (b[i] - a[i]))[:, None]
    va, vb = vals[kk[i]], vals[kk[i] + 1]
    line = va * (1.0 - w) + vb * w
    ok = np.isfinite(va) & np.isfinite(vb)
    out[i] = np.where(ok, line, out[i])
    return out


def setpoint_rows(data: dict[str, np.ndarray], n: int) -> np.ndarray:
    """The twin's setpoint (n, SP_SIZE) from :func:`log_inputs`' ``data`` on its ``n`` grid times: position,
    velocity, acceleration (ENU), yaw and yaw rate; NaN where the log has none."""
    sp = np.full((n, SP_SIZE), np.nan)
    for key, sl in (("setpoint_position_enu", slice(0, 3)), ("setpoint_velocity_enu", slice(3, 6)),
                    ("setpoint_accel_enu", slice(6, 9)), ("setpoint_yaw_enu", slice(9, 10)),
                    ("setpoint_yawspeed", slice(10, 11))):
        if key in data:
            sp[:, sl] = np.asarray(data[key]).reshape(n, -1)[:, : sl.stop - sl.start]
    return sp


def armed_rows(data: dict[str, np.ndarray], n: int) -> np.ndarray:
    """The armed state on the grid (n,): 1.0 armed, 0.0 disarmed, NaN not known (before the log's first
    armed sample: a log whose logging started in the air must not make a flying vehicle "disarmed");
    a log without the topic: armed wherever a motor command is finite."""
    if "armed" not in data:
        return np.isfinite(np.asarray(data["motors"])).any(axis=1).astype(float)
    a = np.asarray(data["armed"], float).reshape(n)
    return np.where(np.isfinite(a), (a > 0.5).astype(float), np.nan)


@dataclass
class LogFeed:
    """A log's inputs as the runner's loop reads them, one row per grid time ``t`` (n,) [s]."""

    t: np.ndarray
    x: np.ndarray            # (n, 13) real state [p, v ENU, q FLU->ENU wxyz, w FLU]
    finite: np.ndarray       # (n,) bool: the row of x is all finite
    motors: np.ndarray       # (n, N) real motor commands (0..1)
    sp: np.ndarray           # (n, SP_SIZE) setpoint rows (:func:`setpoint_rows`)
    repeated: np.ndarray     # (n,) bool: the setpoint row repeats the previous one bit for bit
    armed: np.ndarray        # (n,) 1.0 armed, 0.0 disarmed, NaN not known yet (before the log's first armed
                             # sample: a log started in the air); where not logged: any motor command finite
    battery_v: np.ndarray    # (n,) [V], NaN unknown
    nav_state: np.ndarray    # (n,) PX4 nav_state, NaN unknown
    throttle: np.ndarray     # (n,) PX4's collective thrust setpoint (0..1), NaN unknown
    att_q: np.ndarray        # (n, 4) PX4's attitude setpoint (FLU->ENU), NaN where not logged
    att_thrust: np.ndarray   # (n,) its collective thrust
    att_yawrate: np.ndarray  # (n,) its yaw-rate feed-forward [rad/s]
    rates_sp: np.ndarray     # (n, 3) PX4's rate setpoint (FLU rad/s)
    offboard: np.ndarray     # (n, 6) offboard_control_mode flags


def log_feed(log, rate_hz: float, t0: float | None = None, t1: float | None = None,
             between_samples: bool = True) -> LogFeed:
    """The rows the offline twin reads at ``rate_hz`` between ``t0`` and ``t1`` (:func:`log_inputs`)."""
    data = log_inputs(log, rate_hz, t0, t1, between_samples)
    t = data["t"]
    n = len(t)
    sp = setpoint_rows(data, n)
    armed = armed_rows(data, n)
    batt = np.asarray(data["battery_v"]).reshape(n) if "battery_v" in data else np.full(n, np.nan)
    nav = np.asarray(data["nav_state"]).reshape(n) if "nav_state" in data else np.full(n, np.nan)
    thr = np.asarray(data["throttle"]).reshape(n) if "throttle" in data else np.full(n, np.nan)
    def col(name: str, k: int) -> np.ndarray:
        return np.asarray(data[name], float).reshape(n, k) if name in data else np.full((n, k), np.nan)
    att_q, att_thr, att_yr = col("attitude_setpoint_q", 4), col("attitude_setpoint_thrust", 1)[:, 0], col(
        "attitude_setpoint_yawrate", 1)[:, 0]
    rates_sp, offb = col("setpoint_rates_flu", 3), col("offboard_mode", 6)
    P, V, Q, W, U = (np.asarray(data[k]) for k in ("position_enu", "velocity_enu", "attitude_q",
                                                     "body_rates_flu", "motors"))
    # the real state rows and whether each is finite, and whether each setpoint sample repeats the
    # previous one bit for bit (the runner then skips it)
    X = np.concatenate([np.asarray(a, float).reshape(n, -1) for a in (P, V, Q, W)], axis=1)
    finite = np.isfinite(X).all(axis=1)
    sp_bits = np.ascontiguousarray(sp).view(np.uint64)
    repeated = np.zeros(n, bool)
    repeated[1:] = (sp_bits[1:] == sp_bits[:-1]).all(axis=1)
    return LogFeed(t=t, x=X, finite=finite, motors=U, sp=sp, repeated=repeated, armed=armed, battery_v=batt,
                   nav_state=nav, throttle=thr, att_q=att_q, att_thrust=att_thr, att_yawrate=att_yr,
                   rates_sp=rates_sp, offboard=offb)
