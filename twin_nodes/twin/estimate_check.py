"""Where the vehicle's own position estimate cannot be trusted, whatever its valid flags say.

PX4's EKF can diverge while ``vehicle_local_position.xy_valid``/``z_valid`` stay up (issue 24, class C9:
an estimate that wanders 87 m on a vehicle that hovered).  A twin scored against such an estimate is
judged on a position the vehicle itself did not have.  The check is independent of the estimator: the
change of the estimated velocity over a short window must match the IMU's integrated acceleration
(``sensor_combined`` specific force rotated by the attitude, less gravity), and the change of the
estimated position must match the integrated estimated velocity (a position reset or jump); and where
the log has them, the horizontal estimate must stay within GPS_TOL_M of the GPS receiver's own fix, and
the estimator's own innovation test ratios (``estimator_status``
``vel/pos/hgt_test_ratio`` > 1: the GPS/baro measurement rejected) must stay below 1.  On the 8 shared real
logs, the corpus tuning half and 20 fleet flights the largest mismatches over 2 s are 3.6 m/s and 0.85 m
and no test ratio exceeds 1.0; the tolerances below leave a margin of 1.7x and 3.5x.  Pure numpy; the seconds found are left out of XY/Z scoring
(:func:`twin_nodes.twin.flight_mode.controlled_axes`) and said.
"""

from __future__ import annotations

import numpy as np

from twin_nodes.base import frames
from twin_nodes.base.constants import G_STANDARD_M_S2

__all__ = ["WINDOW_S", "DV_TOL_M_S", "DP_TOL_M", "estimate_failures", "failed_at", "estimate_failed",
           "height_reset_shift", "height_without_resets", "RESET_M"]

#: window over which the velocity change is compared with the integrated IMU acceleration [s]
WINDOW_S = 2.0
#: largest mismatch of the velocity change over a window a healthy estimate shows [m/s] (1 m/s^2 mean:
#: ~17 deg of attitude error held for the window; healthy real flights: <= 3.6 m/s)
DV_TOL_M_S = 6.0
#: largest mismatch of the position change against the integrated velocity over a window [m]
DP_TOL_M = 3.0
#: largest horizontal distance between the estimate and the GPS receiver's own fix a healthy estimate shows
#: [m] (28 real flights with GPS: <= 1.33 m, the receiver's lag at speed included)
GPS_TOL_M = 5.0
#: an innovation test ratio above this for at least TEST_RATIO_MIN_S: the estimator rejects its measurements
TEST_RATIO_MAX = 1.0
TEST_RATIO_MIN_S = 2.0
#: the IMU check needs the specific force logged at least this fast [Hz] (a 9 Hz sensor_combined, as some
#: PX4 1.9 logs have, aliases the vibration into metres per second over a window)
MIN_IMU_HZ = 50.0
#: grid rate of the check [Hz]
RATE_HZ = 20.0
#: gravity [m/s^2]
G = G_STANDARD_M_S2


def _series(log, name: str):
    s = log.get(name)
    return s if s is not None and len(s) > 1 else None


def estimate_failures(log) -> tuple[list[tuple[float, float]], str]:
    """Intervals ``[(t0, t1), ...]`` (log seconds) where the position/velocity estimate is inconsistent
    with the IMU or with itself, and how it was checked (``""`` when the log lacks what the check needs).
    Each failing window marks all of its seconds."""
    p, v, f, q = (_series(log, n) for n in ("position_enu", "velocity_enu", "specific_force_flu", "attitude_q"))
    if p is None or v is None:
        return [], ""
    t0 = max(float(p.t_s[0]), float(v.t_s[0]))
    t1 = min(float(p.t_s[-1]), float(v.t_s[-1]))
    if t1 - t0 < 2 * WINDOW_S:
        return [], ""
    t = np.arange(t0, t1, 1.0 / RATE_HZ)
    P, V = p.at(t), v.at(t)
    k = int(round(WINDOW_S * RATE_HZ))
    dt = 1.0 / RATE_HZ
    bad = np.zeros(t.size, bool)
    # position against the integrated velocity (trapezoid), both from the estimator
    cv = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (V[1:] + V[:-1]) * dt, axis=0)])
    e_p = np.linalg.norm((P[k:] - P[:-k]) - (cv[k:] - cv[:-k]), axis=1)
    how = f"estimated position change vs integrated estimated velocity over {WINDOW_S:g} s (> {DP_TOL_M:g} m)"
    flags = [e_p > DP_TOL_M]
    # (a specific force the reader took from the estimated velocity, logs.imu_rate, checks nothing here)
    imu_ok = (f is not None and q is not None and f.source.startswith("sensor_combined")
              and float(np.median(np.diff(f.t_s))) <= 1.0 / MIN_IMU_HZ
              and float(f.t_s[0]) <= t0 + WINDOW_S and float(f.t_s[-1]) >= t1 - WINDOW_S)
    if imu_ok:
        F, Q = f.at(t), q.at(t)
        a = frames.quat_rotate(Q, F) - np.array([0.0, 0.0, G])
        a = np.where(np.isfinite(a), a, 0.0)
        ca = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (a[1:] + a[:-1]) * dt, axis=0)])
        e_v = np.linalg.norm((V[k:] - V[:-k]) - (ca[k:] - ca[:-k]), axis=1)
        flags.append(e_v > DV_TOL_M_S)
        how += (f", estimated velocity change vs the IMU's integrated acceleration (sensor_combined, attitude) "
                f"over {WINDOW_S:g} s (> {DV_TOL_M_S:g} m/s)")
    # a window across a logging gap of the estimate (interpolated, not logged) is not judged
    gap = _in_gap(p.t_s, t) | _in_gap(v.t_s, t)
    cg = np.concatenate([[0], np.cumsum(gap)])
    judged = (cg[k + 1:] - cg[:-k - 1]) == 0
    for fl in flags:
        for i in np.flatnonzero(fl & judged[:fl.size]):
            bad[i:i + k + 1] = True
    g = _series(log, "gps_position_enu")
    if g is not None:
        with np.errstate(invalid="ignore"):
            far = np.linalg.norm(P[:, :2] - g.at(t)[:, :2], axis=1) > GPS_TOL_M
        bad |= far & ~_in_gap(g.t_s, t, 2.0)
        how += f", estimate vs the GPS receiver's own fix (> {GPS_TOL_M:g} m horizontally)"
    tr = _series(log, "estimator_test_ratios")
    if tr is not None:
        with np.errstate(invalid="ignore"):
            over = np.nanmax(np.where(np.isfinite(tr.at(t)), tr.at(t), 0.0), axis=1) > TEST_RATIO_MAX
        for a, b in _intervals(t, over):
            if b - a >= TEST_RATIO_MIN_S - 1.0 / RATE_HZ:
                bad |= (t >= a) & (t <= b)
        how += f", estimator_status vel/pos/hgt test ratio > {TEST_RATIO_MAX:g} for >= {TEST_RATIO_MIN_S:g} s"
    return _intervals(t, bad), how


#: a gap between two samples of the estimate longer than this [s] (PX4 logs it at 5-50 Hz; dropouts of
#: 1-3 s happen on SD cards) makes the windows across it unjudged
MAX_GAP_S = 0.5


def _in_gap(ts: np.ndarray, t: np.ndarray, max_gap_s: float = MAX_GAP_S) -> np.ndarray:
    """True at the grid times ``t`` that fall between two samples of ``ts`` more than ``max_gap_s`` apart."""
    i = np.clip(np.searchsorted(ts, t), 1, len(ts) - 1)
    return (ts[i] - ts[i - 1]) > max_gap_s


def _intervals(t: np.ndarray, bad: np.ndarray) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    if not bad.any():
        return out
    d = np.diff(np.concatenate([[0], bad.astype(int), [0]]))
    for s, e in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
        out.append((float(t[s]), float(t[e - 1])))
    return out


def failed_at(intervals: list[tuple[float, float]], t: np.ndarray) -> np.ndarray:
    """True at the times ``t`` inside any of ``intervals``."""
    t = np.asarray(t, float)
    m = np.zeros(t.shape, bool)
    for a, b in intervals:
        m |= (t >= a) & (t <= b)
    return m


def estimate_failed(log, t: np.ndarray) -> tuple[np.ndarray, str]:
    """True at the times ``t`` where the vehicle's position estimate failed
    (:func:`estimate_failures`, computed once per log and kept on it), and how it was checked."""
    cached = getattr(log, "_estimate_failures", None)
    if cached is None:
        cached = estimate_failures(log)
        try:
            log._estimate_failures = cached
        except AttributeError:  # a log type without attributes: recomputed each call
            pass
    return failed_at(cached[0], t), cached[1]


#: a step of the estimated height between two of its samples that its own vertical speed does not explain
#: by more than this is a reset of the estimate [m] (a vehicle does not move 1 m unexplained in one 5-100 Hz
#: sample; PX4 resets the height when it changes its height source or re-aligns)
RESET_M = 1.0


def height_reset_shift(log, t: np.ndarray) -> np.ndarray:
    """The sum of the resets of the vehicle's height estimate up to each time of ``t`` [m] (0 on a log without
    any): a reset is a step between two samples of ``position_enu`` that the mean of their ``velocity_enu`` does
    not explain by more than :data:`RESET_M` (toopazo_x8_log83: +49 m at 19.5 s with the motors at hover).  A
    reset moves the estimate's frame, not the vehicle.  Pure numpy."""
    t = np.asarray(t, float)
    p, v = _series(log, "position_enu"), _series(log, "velocity_enu")
    shift = np.zeros(t.shape)
    if p is None or v is None or t.size == 0 or len(p.t_s) < 2:
        return shift
    ts, zs = np.asarray(p.t_s, float), np.asarray(p.values, float)[:, 2]
    vz = v.at(ts)[:, 2]
    with np.errstate(invalid="ignore"):
        step = np.diff(zs) - 0.5 * (vz[1:] + vz[:-1]) * np.diff(ts)
        jump = np.where(np.abs(step) > RESET_M, step, 0.0)
    if not jump.any():
        return shift
    total = np.concatenate([[0.0], np.cumsum(jump)])
    return total[np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.size - 1)]


def height_without_resets(log, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vehicle's estimated height [m, ENU up] on the times ``t`` less :func:`height_reset_shift`, and
    where it is trusted (not :func:`estimate_failed`).  Returns ``(z, trusted)``; NaN where the log has no
    height.  Pure numpy."""
    t = np.asarray(t, float)
    p = _series(log, "position_enu")
    if p is None or t.size == 0:
        return np.full(t.shape, np.nan), np.ones(t.shape, bool)
    return p.at(t)[:, 2].astype(float) - height_reset_shift(log, t), ~estimate_failed(log, t)[0]
