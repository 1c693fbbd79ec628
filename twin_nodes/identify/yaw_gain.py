"""The yaw attitude gain the log's firmware applied, identified from its own setpoints.

PX4 logs both sides of its yaw attitude loop: the yaw setpoint and its feed-forward
(``vehicle_attitude_setpoint.yaw_body``/``yaw_sp_move_rate``, or the trajectory's), the attitude, and
the loop's output, the body yaw-rate setpoint (``vehicle_rates_setpoint``).  For small tilts
``AttitudeControl::update`` gives

    r_sp = k_yaw * wrap(yaw_sp - yaw) + c * yawspeed_sp

with ``k_yaw = MC_YAW_P`` since PX4 96bbc63 (2020-03), which divides the yaw gain by ``MC_YAW_WEIGHT``
to undo the reduced-attitude mix; a firmware without that division applies ``MC_YAW_P * MC_YAW_WEIGHT``.
The parameters do not say which: the fit does.  On the shared logs stock PX4 v1.13/v1.14 reads
``k_yaw`` within 6 % of ``MC_YAW_P`` (X500 2.87 for 2.8, Quad X 6.1 for 6.5), the S500's RCAC fork
(v1.11 branch) 1.20 for ``MC_YAW_P`` 2.8, i.e. ``MC_YAW_P * MC_YAW_WEIGHT`` (1.12): its yaw lags a
45 deg/s ramp by 9 deg, where PX4's own law would lag by 2.5.

Pure numpy on :class:`~twin_nodes.logs.ulog_io.FlightLog` series; no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin_nodes.base import frames
from twin_nodes.logs.ulog_io import MANUAL_NAV_STATES

#: the yaw setpoint must be logged at least this often [Hz]: a 5 Hz held sample of a 45 deg/s ramp
#: is up to 9 deg stale, which reads as a yaw error the controller never saw
MIN_SETPOINT_HZ = 15.0
#: larger yaw errors [rad] are turns the rate limit clips (MC_YAWRATE_MAX), not the linear law
MAX_ERROR_RAD = 0.5
#: at least this many seconds of usable samples, and this much yaw-error excitation [rad, std]
MIN_SECONDS = 10.0
MIN_ERROR_STD_RAD = 0.01
#: the identified gain replaces MC_YAW_P only when it differs by more than this fraction, the two
#: halves of the flight agree within HALVES_TOL and the fit explains the rate setpoint (R^2)
REPLACE_REL = 0.3
HALVES_TOL = 0.2
MIN_R2 = 0.5


@dataclass(frozen=True)
class YawGainFit:
    """``r_sp = k_yaw e + c_ff yawspeed``: the fit, its halves and its sample count."""

    k_yaw: float
    c_ff: float
    r2: float
    halves: tuple[float, float]
    n: int
    seconds: float

    @property
    def halves_agree(self) -> bool:
        a, b = self.halves
        return abs(a - b) <= HALVES_TOL * max(abs(self.k_yaw), 1e-9)


def fit_yaw_law(error_rad: np.ndarray, yawspeed: np.ndarray, rate_sp: np.ndarray) -> tuple[float, float, float]:
    """Least squares ``rate_sp = k e + c yawspeed`` -> ``(k, c, R^2)`` (finite rows only)."""
    e, f, y = (np.asarray(a, float).ravel() for a in (error_rad, yawspeed, rate_sp))
    ok = np.isfinite(e) & np.isfinite(f) & np.isfinite(y)
    X = np.column_stack([e[ok], f[ok]])
    coef, *_ = np.linalg.lstsq(X, y[ok], rcond=None)
    res = y[ok] - X @ coef
    var = float(np.var(y[ok]))
    r2 = 1.0 - float(np.var(res)) / var if var > 0 else 0.0
    return float(coef[0]), float(coef[1]), r2


def applied_yaw_gain(log) -> YawGainFit | None:
    """The yaw attitude law the log's controller applied, or None where the log cannot show it
    (no rate setpoints, a yaw setpoint logged slower than :data:`MIN_SETPOINT_HZ`, too little yaw
    error or too few samples)."""
    rs, ys, yff, att = (log.get(k) for k in ("setpoint_rates_flu", "setpoint_yaw_enu", "setpoint_yawspeed",
                                             "attitude_q"))
    if rs is None or ys is None or yff is None or att is None or len(ys) < 2:
        return None
    span = float(ys.t_s[-1] - ys.t_s[0])
    if span <= 0 or (len(ys) - 1) / span < MIN_SETPOINT_HZ:
        return None
    t = rs.t_s[(rs.t_s > ys.t_s[0]) & (rs.t_s < min(ys.t_s[-1], att.t_s[-1])) & (rs.t_s > att.t_s[0])]
    if t.size < 10:
        return None
    keep = np.ones(t.size, bool)
    for name, bad in (("landed", lambda v: v > 0.5), ("armed", lambda v: v < 0.5),
                      ("nav_state", lambda v: np.isin(v, MANUAL_NAV_STATES))):
        s = log.get(name)
        if s is not None:
            keep &= ~bad(s.at(t, kind="previous")[:, 0])
    t = t[keep]
    if t.size < 10:
        return None
    yaw_sp = ys.at(t, kind="previous")[:, 0]
    ff = yff.at(t, kind="previous")[:, 0]
    e = frames.wrap_pi(yaw_sp - frames.euler_from_quat(att.at(t))[:, 2])
    r_sp = rs.at(t)[:, 2]
    ok = np.isfinite(e) & np.isfinite(ff) & np.isfinite(r_sp) & (np.abs(e) < MAX_ERROR_RAD)
    t, e, ff, r_sp = t[ok], e[ok], ff[ok], r_sp[ok]
    dt = float(np.median(np.diff(rs.t_s))) if len(rs) > 1 else 0.0
    seconds = t.size * dt
    if seconds < MIN_SECONDS or float(np.std(e)) < MIN_ERROR_STD_RAD:
        return None
    k, c, r2 = fit_yaw_law(e, ff, r_sp)
    half = t < np.median(t)
    k1 = fit_yaw_law(e[half], ff[half], r_sp[half])[0]
    k2 = fit_yaw_law(e[~half], ff[~half], r_sp[~half])[0]
    return YawGainFit(k, c, r2, (k1, k2), int(t.size), seconds)


def yaw_gain_for_twin(fit: YawGainFit | None, yaw_p_param: float, yaw_weight: float) -> tuple[float | None, str]:
    """``(gain, why)``: the identified yaw gain where it replaces ``MC_YAW_P`` (else None) and the
    sentence for the params header."""
    if fit is None:
        return None, "the log does not show its yaw law (no 15 Hz yaw setpoint, rate setpoints or yaw error)"
    said = (f"the log's rate setpoints follow {fit.k_yaw:.2f} x yaw error + {fit.c_ff:.2f} x feed-forward "
            f"(R^2 {fit.r2:.2f}, halves {fit.halves[0]:.2f}/{fit.halves[1]:.2f}, {fit.seconds:.0f} s)")
    if not (fit.r2 >= MIN_R2 and fit.halves_agree and fit.k_yaw > 0):
        return None, said + ": not consistent enough to replace MC_YAW_P"
    if abs(fit.k_yaw - yaw_p_param) <= REPLACE_REL * yaw_p_param:
        return None, said + f": MC_YAW_P {yaw_p_param:.3g} as flown"
    note = ""
    if yaw_weight > 0 and abs(fit.k_yaw - yaw_p_param * yaw_weight) <= REPLACE_REL * yaw_p_param * yaw_weight:
        note = (f"; that is MC_YAW_P x MC_YAW_WEIGHT ({yaw_p_param * yaw_weight:.3g}): a firmware that does not "
                f"divide the yaw gain by the weight (PX4 before 96bbc63, 2020-03, or a fork)")
    return fit.k_yaw, said + f", not MC_YAW_P {yaw_p_param:.3g}: the twin flies {fit.k_yaw:.3g}" + note
