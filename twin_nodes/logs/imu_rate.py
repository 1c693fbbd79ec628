"""The specific force where the log's accelerometer samples alias the vibration.

PX4 low-passes the accelerometer at ``IMU_ACCEL_CUTOFF`` (20-30 Hz) and publishes ``sensor_combined`` at
the IMU rate (200-250 Hz).  The logger keeps a subsample: every sample on the high-rate and replay
profiles, but one every 100 ms on the default profile of PX4 1.8-1.10 (``logger.cpp``
``add_default_topics``: ``add_topic("sensor_combined", 100)``).  Samples taken slower than twice the
cutoff are point samples of a signal with vibration up to the cutoff, folded down into every band down
to 0 Hz: on such a log (PX4 1.9, 8.6 Hz, cutoff 20 Hz) the logged body-z specific force averaged over
the first 65 % of the flight reads 11.25 m/s^2 where the vehicle's own velocity says 10.09, and its
content below 1 Hz correlates with the vehicle's at 0.03.  Every fit of the thrust to it is then off by
the difference (the twin's thrust per command 11 % high).

There the vehicle's specific force is taken from what PX4's estimator integrated at the full IMU rate:
the derivative of ``vehicle_local_position``'s velocity, plus gravity, rotated into the body by the
attitude, ``f_FLU = R^T (dv/dt + g e_up)``.  On the tuning half and the shared real logs, whose
accelerometer is logged at 96-250 Hz, the two agree below 1 Hz within 0.1-0.4 m/s^2 RMS (the
estimator's lag and the low-pass); where the accelerometer is logged fast enough it is kept.
"""

from __future__ import annotations

import numpy as np

from twin_nodes.base import frames
from twin_nodes.base.constants import G_STANDARD_M_S2

__all__ = ["ACCEL_CUTOFF_DEFAULT_HZ", "GRAVITY_M_S2", "VELOCITY_GAP_S", "accel_aliased",
           "specific_force_from_velocity"]

#: PX4's accelerometer low-pass where the log does not record ``IMU_ACCEL_CUTOFF`` [Hz] (its default)
ACCEL_CUTOFF_DEFAULT_HZ = 30.0
GRAVITY_M_S2 = G_STANDARD_M_S2
#: a gap between two finite velocity samples longer than this [s] ends a stretch (no derivative across it)
VELOCITY_GAP_S = 1.0


def accel_aliased(t_s: np.ndarray, params: dict[str, float]) -> tuple[bool, float, float]:
    """``(aliased, logged rate [Hz], cutoff [Hz])``: the accelerometer's median logged rate is below twice
    PX4's accelerometer low-pass (``IMU_ACCEL_CUTOFF``, else its default), so its samples alias."""
    t = np.asarray(t_s, float)
    cut = params.get("IMU_ACCEL_CUTOFF", ACCEL_CUTOFF_DEFAULT_HZ)
    cut = float(cut) if cut is not None and np.isfinite(cut) and cut > 0 else ACCEL_CUTOFF_DEFAULT_HZ
    if t.size < 3:
        return False, float("nan"), cut
    dt = float(np.median(np.diff(t)))
    rate = 1.0 / dt if dt > 0 else float("inf")
    return bool(rate < 2.0 * cut), rate, cut


def specific_force_from_velocity(t_v: np.ndarray, v_enu: np.ndarray, q_at) -> tuple[np.ndarray, np.ndarray]:
    """``(t, f_FLU)``: the specific force [m/s^2] the estimated velocity ``v_enu`` (n, 3) [m/s, ENU] at
    ``t_v`` (n,) [s] implies, ``R^T (dv/dt + g e_up)``, at the velocity's finite samples (central differences
    within each stretch without a gap over VELOCITY_GAP_S; a stretch of one sample is left out).
    ``q_at(t)`` gives the attitude (m, 4) FLU->ENU wxyz at those times."""
    t = np.asarray(t_v, float)
    v = np.asarray(v_enu, float).reshape(len(t), 3)
    ok = np.isfinite(v).all(axis=1)
    t, v = t[ok], v[ok]
    if t.size < 2:
        return np.zeros(0), np.zeros((0, 3))
    cuts = np.flatnonzero(np.diff(t) > VELOCITY_GAP_S) + 1
    keep, acc = [], []
    for sl in np.split(np.arange(t.size), cuts):
        if sl.size >= 2:
            keep.append(sl)
            acc.append(np.gradient(v[sl], t[sl], axis=0))
    if not keep:
        return np.zeros(0), np.zeros((0, 3))
    idx = np.concatenate(keep)
    a = np.concatenate(acc)
    a[:, 2] += GRAVITY_M_S2
    q = frames.quat_normalize(np.asarray(q_at(t[idx]), float))
    f = frames.quat_rotate(frames.quat_conjugate(q), a)
    good = np.isfinite(f).all(axis=1)
    return t[idx][good], f[good]
