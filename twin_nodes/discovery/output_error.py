"""Output-error residuals: the model flown open loop over short re-synced horizons.

The equation-error residual (:mod:`twin_nodes.discovery.residuals`) compares forces sample by
sample and has to be low-passed at 2 Hz to survive the differentiated gyro; whatever acts through
the dynamics (rotor lag, inertia, reaction torque in a yaw manoeuvre) is mostly filtered away.
Here the model itself integrates: from the logged state at the start of each window (position,
velocity, attitude, body rates; rotor state from the model's own command path over the whole
flight), the model is driven by the logged motor commands for ``HORIZON_S`` and its body rates and
velocity are compared with the log at every logged sample of the horizon.  All windows are flown
in one call (:mod:`twin_nodes.discovery.kernels`: the stepper's RK4 steps over every window and
step), so a candidate costs one batched integration, not one per window.

Per window the error trajectory ``e(h)`` of each axis is reduced to its least-squares slope over
the horizon, with an intercept: the intercept absorbs the noise of the logged start state, the
slope is the mean acceleration error over the window (velocity errors in the start attitude's
body frame).  Each axis is divided by the nominal model's typical error on it, and the axes are
laid into the equation error's channels (``motor1..N``, ``force_x``, ``force_y``) so that the same
mode projection (throttle, roll, pitch, yaw) reads them back.

Judged axes: vertical velocity and the three body rates (horizontal velocity is left to the
equation error: drag and wind act there, and its open-loop drift would dilute the dynamics).
Usable axes: on 50 Hz PX4 motor logs the roll and pitch commands are a 50 Hz sample of a 250 Hz
rate loop; their aliasing acts like input noise, and an open-loop prediction of roll/pitch rates
from them is attenuated (errors in variables): on the PX4 SIH flights the nominal model explains
<= 60 % of the roll/pitch rate changes, on our own flights logged at 50 Hz 60 %, at 250 Hz 93 %.
A fit on such an axis makes the vehicle look sluggish (more inertia, more lag) on *every*
flight.  So an axis takes part only where the nominal model's prediction correlates with the
measured change at r^2 >= ``MIN_AXIS_R2`` (gain-free: a true parameter change scales the
prediction but keeps the correlation); the others are reported and left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from twin_nodes.base import frames
from twin_nodes.discovery.kernels import kernels
from twin_nodes.discovery.residuals import EquationData, exogenous, fine_commands, mode_basis, model_rotor_states
from twin_nodes.physics.core import NX_BODY
from twin_nodes.physics.effects import effective_params
from twin_nodes.physics.model import Multirotor
from twin_nodes.vehicle.params import VehicleParams

HORIZON_S = 0.4
STRIDE_S = 0.2
STEP_S = 0.01
MIN_AXIS_R2 = 0.8
MIN_HEIGHT_M = 0.3
AXES = ("force_x", "force_y", "force_z", "roll", "pitch", "yaw")
#: the axes the output error judges: the dynamics (body rates and vertical velocity); horizontal
#: velocity is the equation error's (drag, wind), its open-loop drift would only dilute these
JUDGED = np.array([False, False, True, True, True, True])


@dataclass
class Windows:
    """The re-synced windows of one flight and which axes are usable."""

    start: np.ndarray          # (K,) grid index of each window's start
    t: np.ndarray              # (K,) window start time [s]
    t_end: np.ndarray          # (K,) window end time [s]
    horizon: int               # samples (data grid) per window
    usable: np.ndarray = field(default_factory=lambda: np.ones(6, bool))   # per AXES
    axis_r2: np.ndarray = field(default_factory=lambda: np.ones(6))        # nominal prediction r^2 per axis
    axis_gain: np.ndarray = field(default_factory=lambda: np.ones(6))      # measured/predicted slope gain
    scale: np.ndarray = field(default_factory=lambda: np.ones(6))          # nominal error level per axis
    #: per axis, the rate setpoint as instrument (:func:`instrumented_gains`; NaN: no instrument)
    iv_gain: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))
    iv_se: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))
    iv_r: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))

    @property
    def n(self) -> int:
        return len(self.start)

    def describe(self) -> dict:
        axes = {}
        for i, (a, r, g, u, j) in enumerate(zip(AXES, self.axis_r2, self.axis_gain, self.usable, JUDGED)):
            if not j:
                continue
            axes[a] = {"r2": round(float(r), 3), "gain": round(float(g), 3), "used": bool(u)}
            if np.isfinite(self.iv_gain[i]):
                axes[a].update(iv_gain=round(float(self.iv_gain[i]), 3), iv_se=round(float(self.iv_se[i]), 3),
                               instrument_r=round(float(self.iv_r[i]), 3))
        return {"horizon_s": None, "windows": int(self.n), "axes": axes}


def make_windows(data: EquationData, horizon_s: float = HORIZON_S, stride_s: float = STRIDE_S) -> Windows:
    """Windows whose whole horizon is valid and flown (logged height above ``MIN_HEIGHT_M``)."""
    h = max(int(round(horizon_s / data.dt)), 2)
    stride = max(int(round(stride_s / data.dt)), 1)
    # the attitude's samples: the windows integrate the rates, which the ground holds until after a lift-off
    ok = data.valid_attitude & (data.height > MIN_HEIGHT_M)
    bad = np.concatenate([[0], np.cumsum(~ok)])
    k = np.arange(0, data.n - h - 1, stride)
    keep = k[(bad[k + h + 1] - bad[k]) == 0]
    return Windows(start=keep, t=data.t[keep], t_end=data.t[keep + h], horizon=h)


def simulate_windows(data: EquationData, win: Windows, vp: VehicleParams, step_s: float = STEP_S,
                     rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Model rates and velocities (H, K, 3) each at the logged samples 1..H of each window."""
    model = Multirotor(vp)
    start = win.start if rows is None else win.start[rows]
    up = data.up
    dt_f = data.dt / up
    # fine steps per RK4 step: the largest divisor of ``up`` whose step is <= step_s, so that a whole
    # number of RK4 steps ends on every grid sample (with round(step_s / dt_f) a finer grid, e.g.
    # 250 Hz, read the 10 ms predictions as 4 ms samples; the same value at 50 Hz)
    fs = max([d for d in range(1, up + 1) if up % d == 0 and d * dt_f <= step_s + 1e-12] or [1])
    per = up // fs
    dt_c = fs * dt_f
    ext = exogenous(model, data, len(data.u_fine), up)
    delay = int(round(model.command_delay_s / dt_f))
    u = fine_commands(data, nan_as_zero=True)
    # the rotor states at the window starts (grid samples) from the model's command path over the
    # whole flight: the equation error's series (kept per flight, shared by most candidates)
    S = model_rotor_states(model, data)
    k = len(start)
    X = np.zeros((k, model.nx))
    X[:, 0:3] = data.p[start]
    X[:, 2] = data.height[start]
    X[:, 3:6] = data.v[start]
    X[:, 6:10] = data.q[start]
    X[:, 10:13] = data.w[start]
    X[:, NX_BODY:] = S[start]
    X = np.nan_to_num(X)
    H = win.horizon
    W = np.empty((H, k, 3))
    V = np.empty((H, k, 3))
    base = np.ascontiguousarray(start * up, dtype=np.int64)
    # every window over the whole horizon in one call: RK4 steps of dt_c, each with the command in
    # the middle of the step (commands are linear between logged samples); rates and velocities
    # at the logged samples
    kernels(model).step_windows(model.P, X, u, np.ascontiguousarray(ext), base, fs, delay, dt_c, H * per, per, W, V)
    return W, V


def _slope_weights(horizon: int, dt: float) -> np.ndarray:
    """Weights over samples 1..H whose dot product with a series is its least-squares slope (with
    intercept) per second."""
    h = np.arange(1, horizon + 1)
    return (h - h.mean()) / (np.sum((h - h.mean()) ** 2) * dt)


def _slopes(data: EquationData, win: Windows, W: np.ndarray, V: np.ndarray, start: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares slopes over the horizon (with intercept) of measured and predicted changes:
    acceleration (body, m/s^2) and angular acceleration (rad/s^2), measured and model."""
    H = win.horizon
    h = np.arange(1, H + 1)
    hc = _slope_weights(H, data.dt)
    idx = start[None, :] + h[:, None]
    Rt = frames.quat_to_rotmat(data.q[start])
    # world -> body of the start attitude: v_b = R^T v_w
    vm = np.einsum("kji,hkj->hki", Rt, data.v[idx])
    vp_ = np.einsum("kji,hkj->hki", Rt, V)
    am = np.einsum("h,hkc->kc", hc, vm)
    ap = np.einsum("h,hkc->kc", hc, vp_)
    wm = np.einsum("h,hkc->kc", hc, data.w[idx])
    wp = np.einsum("h,hkc->kc", hc, W)
    return am, ap, wm, wp


def axis_errors(data: EquationData, win: Windows, vp: VehicleParams, rows: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Measured and predicted mean accelerations per window: (K, 6) each, order ``AXES``
    (linear in body axes [m/s^2], then angular [rad/s^2])."""
    start = win.start if rows is None else win.start[rows]
    W, V = simulate_windows(data, win, vp, rows=rows)
    am, ap, wm, wp = _slopes(data, win, W, V, start)
    return np.column_stack([am, wm]), np.column_stack([ap, wp])


def instrumented_gains(meas: np.ndarray, pred: np.ndarray, z: np.ndarray, cluster: int = 3
                       ) -> tuple[float, float, float, float]:
    """How the measured change follows the predicted one, per window: the least-squares gain
    cov(p, m) / var(p), the instrumental-variable gain cov(z, m) / cov(z, p), its standard error
    (robust, clustered over ``cluster`` neighbouring windows, which overlap), and the instrument's
    correlation with the prediction.

    Noise in the prediction (the aliased 50 Hz motor commands it integrates) pulls the
    least-squares gain towards zero; an instrument that drives the true signal but is independent of
    that noise (the rate setpoint's change over the window) does not: with ``m = g s + e``,
    ``p = s + n`` and ``z`` correlated with ``s`` only, cov(z, m) / cov(z, p) -> g."""
    ok = np.isfinite(meas) & np.isfinite(pred) & np.isfinite(z)
    m, p, zz = meas[ok], pred[ok], z[ok]
    if m.size < 10:
        return math.nan, math.nan, math.nan, math.nan
    mc, pc, zc = m - m.mean(), p - p.mean(), zz - zz.mean()
    ols = float(np.sum(pc * mc) / max(np.sum(pc * pc), 1e-30))
    szp = float(np.sum(zc * pc))
    if abs(szp) < 1e-30 or np.sum(zc * zc) < 1e-30:
        return ols, math.nan, math.nan, math.nan
    iv = float(np.sum(zc * mc) / szp)
    e = mc - iv * pc
    contrib = zc * e
    k = contrib.size // cluster * cluster
    clusters = np.add.reduceat(contrib[:k], np.arange(0, k, cluster)) if k else contrib
    se = float(np.sqrt(np.sum(clusters ** 2)) / abs(szp))
    r = float(np.corrcoef(zc, pc)[0, 1])
    return ols, iv, se, r


def setpoint_slopes(data: EquationData, win: Windows) -> np.ndarray | None:
    """(K, 3) the rate setpoint's least-squares slope over each window, FLU (None: not logged)."""
    if data.w_sp is None:
        return None
    h = np.arange(1, win.horizon + 1)
    return np.einsum("h,hkc->kc", _slope_weights(win.horizon, data.dt), data.w_sp[win.start[None, :] + h[:, None]])


#: an instrumented gain is reported as a mismatch when it is this far from 1 and ``AUTHORITY_MIN_SE``
#: standard errors away, with an instrument at least this correlated with the prediction.  On the 12
#: PX4 SIH no-effect flights roll reads 0.83-1.08 and pitch 0.94-1.01; the clustered standard error
#: understates roll's spread from flight to flight (a drag-only flight: roll 0.83 +- 0.05), hence 4
AUTHORITY_MIN_CHANGE = 0.15
AUTHORITY_MIN_SE = 4.0
AUTHORITY_MIN_R = 0.3


def authority_mismatch(win: Windows) -> list[dict]:
    """The rotational axes the output error leaves out whose instrumented gain says the vehicle
    turns more or less per command than the nominal model: a located mismatch (not an effect: which
    physics -- inertia, moment arm, rotor thrust split -- needs the fit, on a log that resolves the axis)."""
    out = []
    for i in (3, 4, 5):
        g, se, r = win.iv_gain[i], win.iv_se[i], win.iv_r[i]
        if win.usable[i] or not np.isfinite(g) or not np.isfinite(se) or r < AUTHORITY_MIN_R:
            continue
        if abs(g - 1.0) > max(AUTHORITY_MIN_CHANGE, AUTHORITY_MIN_SE * se):
            out.append({"axis": AXES[i], "iv_gain": round(float(g), 3), "iv_se": round(float(se), 3),
                        "ols_gain": round(float(win.axis_gain[i]), 3), "instrument_r": round(float(r), 3),
                        "note": (f"{AXES[i]}: the vehicle's angular acceleration per command is {g:.2f} +- {se:.2f} "
                                 f"x the nominal's (rate setpoint as instrument; the output error leaves this "
                                 f"axis out, r^2 {win.axis_r2[i]:.2f}): {'more' if g < 1 else 'less'} inertia "
                                 f"(x{1 / g:.2f}), {'less' if g < 1 else 'more'} moment per command"
                                 + (", or slower motors (a lag or delay spreads the response past the "
                                    "window)" if g < 1 else "") + "; a log with motors every 4 ms lets the fit "
                                 "tell which")})
    return out


def projected_error(meas: np.ndarray, pred: np.ndarray, z: np.ndarray) -> float:
    """RMS of the output error projected on the (centred) instrument: ``|cov(z, m - p)| / sd(z)``.

    The part of the error the rate setpoint explains; the aliasing noise in the prediction and the
    measurement noise, independent of the instrument, drop out of it (unlike the plain RMS, which
    a more sluggish model always lowers on a 50 Hz log)."""
    ok = np.isfinite(meas) & np.isfinite(pred) & np.isfinite(z)
    if ok.sum() < 10:
        return math.nan
    e = meas[ok] - pred[ok]
    zc = z[ok] - z[ok].mean()
    sz = float(np.sqrt(np.mean(zc * zc)))
    return abs(float(np.mean(zc * (e - e.mean())))) / sz if sz > 0 else math.nan


#: the rotational axes the instrument estimates an inertia on: axis -> (parameter, index in the diagonal)
IV_AXIS_PARAM = {"roll": ("ixx", 0), "pitch": ("iyy", 1)}
#: an instrumented inertia is held back when the yaw axis reads this much off the model the same
#: way (beyond 3 standard errors): the motors (a lag or a delay, thrust or moment per command)
#: act on every axis, an inertia change of roll or pitch leaves yaw alone (PX4 SIH SIH_T_TAU 0.09 at 50 Hz: yaw 0.89 +- 0.01;
#: SIH_IXX/IYY x1.3: yaw 1.00 +- 0.01)
MOTOR_YAW_SLOW = 0.03
#: the instrumented gain's physical range: an inertia within x0.2..x5 of the model's
IV_GAIN_RANGE = (0.2, 5.0)
#: an axis's inertia is estimated from the instrument only where the instrument is strong: a weak
#: one biases the gain towards least squares' (down, on 50 Hz logs).  PX4 SIH roll on the yaw-square
#: mission M3 (instrument r 0.31-0.44): no-effect flights read 0.78-0.93, Ixx x1.5 reads 0.51-0.59
#: for 0.67; at r >= 0.55 (mission M4, 4 ms logs) no-effect flights read 0.89-1.04 and Ixx x1.5 reads
#: 0.57-0.68.  Below this the axis is only a located mismatch (:func:`authority_mismatch`)
IV_MIN_R_ESTIMATE = 0.5


def projected_view(data: EquationData, win: Windows, before: VehicleParams, after: VehicleParams,
                   held: np.ndarray) -> dict | None:
    """A finding's held-out cut on the rotational axes in the instrument-projected error
    (:func:`projected_error`), each axis with a strong instrument (``win.iv_r`` >=
    ``IV_MIN_R_ESTIMATE``): the part of the output error the rate setpoint explains, where the
    aliasing of 50 Hz motor commands drops out.  ``None`` without a rate setpoint or a strong axis.

    A motor lag or delay acts on every rotational axis; on a 50 Hz log its plain held-out RMS cut is
    bounded by the aliasing noise no model explains (PX4 SIH T_TAU 0.12 s: 29-31 % in yaw), its
    projected cut is not (82-93 % on roll, pitch and yaw; a wrong lag on a no-effect flight makes the
    projected error 1.3-13x larger while the plain RMS of roll and pitch falls)."""
    z = setpoint_slopes(data, win)
    rows = np.asarray(held, bool)
    if z is None or rows.sum() < 10:
        return None
    axes = [i for i in (3, 4, 5) if np.isfinite(win.iv_r[i]) and win.iv_r[i] >= IV_MIN_R_ESTIMATE]
    if not axes:
        return None
    m0, p0 = axis_errors(data, win, before, rows)
    m1, p1 = axis_errors(data, win, after, rows)
    zz = z[rows]
    per = {}
    for i in axes:
        b = projected_error(m0[:, i], p0[:, i], zz[:, i - 3])
        a = projected_error(m1[:, i], p1[:, i], zz[:, i - 3])
        if np.isfinite(a) and np.isfinite(b) and b > 0:
            per[AXES[i]] = {"before": round(b, 5), "after": round(a, 5), "cut": round(1.0 - a / b, 4),
                            "instrument_r": round(float(win.iv_r[i]), 3)}
    if not per:
        return None
    main = max(per, key=lambda a: per[a]["before"])
    return {"residual": "instrumented", "heldout_channel": main, "heldout_before": per[main]["before"],
            "heldout_after": per[main]["after"], "heldout_improvement": per[main]["cut"], "axes": per,
            "heldout_units": "RMS of the output error projected on the rate setpoint's change (rad/s^2), "
                             "held-out windows; reported, not graded"}


def instrumented_inertia(data: EquationData, win: Windows, vp: VehicleParams, fold1: tuple[np.ndarray, np.ndarray],
                         fold2: tuple[np.ndarray, np.ndarray], build=None,
                         axes_allowed: tuple[str, ...] = ("roll", "pitch")) -> dict | None:
    """Roll/pitch inertia from the rate setpoint as instrument, on the axes the output error
    leaves out (50 Hz motor logs: the aliased commands make its least-squares fit see a sluggish
    vehicle on every flight).

    For each such axis with a strong instrument (correlation with the prediction >=
    ``IV_MIN_R_ESTIMATE``) where the instrumented gain g of measured on predicted angular acceleration
    (model ``vp``, all windows) is ``AUTHORITY_MIN_SE`` standard errors and ``AUTHORITY_MIN_CHANGE``
    away from 1, the inertia the fit part asks for is ``I / g_fit`` (fold 1's fit windows); it is
    judged on fold 1's held-out windows by the instrument-projected error (:func:`projected_error`)
    with ``vp`` and with the changed vehicle (``build(ixx, iyy)``), and fold 2 must move the same
    axis the same way.  ``None`` when no axis is usable for this (no rate setpoint, every axis
    already judged by the output error, or too few windows).  Only ``axes_allowed`` are looked at
    (a confirmed inertia: the axes it held at the model's value).  The caller grades the result."""
    z = setpoint_slopes(data, win)
    if z is None or win.n < 20:
        return None
    meas, pred = axis_errors(data, win, vp)
    (fit1, test1), (fit2, _test2) = fold1, fold2
    inertia = np.diag(effective_params(vp).inertia).astype(float)
    axes = {}
    for i in (3, 4):
        if AXES[i] not in axes_allowed:
            continue
        m, p, zz = meas[:, i], pred[:, i], z[:, i - 3]
        _, g, se, r = instrumented_gains(m, p, zz)
        if not (np.isfinite(g) and np.isfinite(se)) or r < IV_MIN_R_ESTIMATE:
            continue
        _, g1, se1, _ = instrumented_gains(m[fit1], p[fit1], zz[fit1])
        _, g2, se2, _ = instrumented_gains(m[fit2], p[fit2], zz[fit2])
        axes[AXES[i]] = {"index": i, "gain": g, "se": se, "instrument_r": r, "gain_fold1": g1, "se_fold1": se1,
                         "gain_fold2": g2, "se_fold2": se2,
                         "flagged": bool(abs(g - 1.0) > max(AUTHORITY_MIN_CHANGE, AUTHORITY_MIN_SE * se))}
    if not axes:
        return None
    _, gy, sey, ry = instrumented_gains(meas[:, 5], pred[:, 5], z[:, 2])
    out = {"axes": axes, "yaw_gain": gy, "yaw_se": sey}
    flagged = [a for a, d in axes.items() if d["flagged"]]
    out["flagged"] = flagged
    if not flagged:
        return out
    # the yaw axis off the same way: a change common to every axis (the motors' lag or delay, the
    # thrust or moment per command), not a roll/pitch inertia
    same = [a for a in flagged if np.sign(axes[a]["gain"] - 1.0) == np.sign(gy - 1.0)]
    out["motor_signature"] = bool(same and np.isfinite(gy) and abs(gy - 1.0) > max(MOTOR_YAW_SLOW, 3.0 * sey))
    if build is None:
        return out
    new = inertia.copy()
    for a in flagged:
        d = axes[a]
        j = IV_AXIS_PARAM[a][1]
        new[j] = inertia[j] / d["gain_fold1"] if np.isfinite(d["gain_fold1"]) and d["gain_fold1"] > 0 else math.nan
    out["params"] = {"ixx": float(new[0]), "iyy": float(new[1]), "izz": float(inertia[2])}
    if not np.all(np.isfinite(new)):
        return out
    vp1 = build(float(new[0]), float(new[1]))
    meas1, pred1 = axis_errors(data, win, vp1)
    for a in flagged:
        d = axes[a]
        i = d["index"]
        zz = z[:, i - 3]
        d["heldout_before"] = projected_error(meas[test1, i], pred[test1, i], zz[test1])
        d["heldout_after"] = projected_error(meas1[test1, i], pred1[test1, i], zz[test1])
        _, gt0, st0, _ = instrumented_gains(meas[test1, i], pred[test1, i], zz[test1])
        _, gt1, st1, _ = instrumented_gains(meas1[test1, i], pred1[test1, i], zz[test1])
        d["heldout_gain_before"], d["heldout_gain_after"] = gt0, gt1
        # significance on the held-out part: how many standard errors the model's gain is from 1
        d["heldout_t"] = abs(gt0 - 1.0) / st0 if np.isfinite(st0) and st0 > 0 else math.nan
        d["heldout_t_after"] = abs(gt1 - 1.0) / st1 if np.isfinite(st1) and st1 > 0 else math.nan
    return out


def judge_axes(data: EquationData, win: Windows, nominal: VehicleParams) -> Windows:
    """Fill ``win.usable``/``axis_r2``/``axis_gain`` from the nominal model's prediction, and the
    rotational axes' instrumented gains (``iv_gain``, ``iv_se``, ``iv_r``) where the log has the
    rate setpoint."""
    meas, pred = axis_errors(data, win, nominal)
    z = setpoint_slopes(data, win)
    if z is not None:
        for ax in range(3):
            _, iv, se, r = instrumented_gains(meas[:, 3 + ax], pred[:, 3 + ax], z[:, ax])
            win.iv_gain[3 + ax], win.iv_se[3 + ax], win.iv_r[3 + ax] = iv, se, r
    dm = meas - meas.mean(0)
    dp = pred - pred.mean(0)
    cov = np.sum(dm * dp, 0)
    r2 = cov ** 2 / np.maximum(np.sum(dm ** 2, 0) * np.sum(dp ** 2, 0), 1e-30)
    gain = cov / np.maximum(np.sum(dp ** 2, 0), 1e-30)
    win.axis_r2 = r2
    win.axis_gain = gain
    err = meas - pred
    mad = 1.4826 * np.median(np.abs(err - np.median(err, 0)), 0)
    win.scale = np.maximum(mad, 1e-9)
    win.usable = (r2 >= MIN_AXIS_R2) & JUDGED
    return win


def output_error(data: EquationData, win: Windows, vp: VehicleParams, nominal: VehicleParams,
                 rows: np.ndarray | None = None) -> np.ndarray:
    """Output-error residual (K, N + 2) in the equation error's channels (``motor1..N``,
    ``force_x``, ``force_y``), built so that :func:`~twin_nodes.discovery.residuals.modes` returns
    the per-window mean acceleration error of the judged axes (vertical, roll, pitch, yaw), each
    in units of the nominal model's typical error on that axis (robust sd over the windows): the
    axes differ in noise by an order of magnitude, and a yaw effect must not drown in the
    vertical channel's noise.  Unused axes contribute nothing."""
    meas, pred = axis_errors(data, win, vp, rows)
    err = (meas - pred) * win.usable[None, :] / win.scale[None, :]
    b = mode_basis(nominal.rotors)
    # modes() projects per-motor channels with b; pinv(b) puts the axis errors back exactly
    per_motor = err[:, 2:6] @ np.linalg.pinv(b).T
    R = np.column_stack([per_motor, np.zeros((len(err), 2))])
    return np.where(np.isfinite(R), R, 0.0)


__all__ = ["AUTHORITY_MIN_CHANGE", "AUTHORITY_MIN_R", "AUTHORITY_MIN_SE", "AXES", "HORIZON_S", "IV_GAIN_RANGE",
           "MIN_AXIS_R2", "MOTOR_YAW_SLOW", "Windows", "authority_mismatch", "axis_errors", "instrumented_gains",
           "instrumented_inertia", "IV_AXIS_PARAM", "IV_MIN_R_ESTIMATE", "judge_axes", "projected_error",
           "make_windows", "output_error", "setpoint_slopes", "simulate_windows"]
