"""The discovery evaluation path as it was before issue 13's speed work (frozen copy, for the bench).

``bench/bench_discover.py`` runs ``discover`` twice in one process: as it is now, and with the
functions below swapped in (:func:`before`), so the ratio it prints is a same-run measurement of
the old and new evaluation paths under the same judging logic.  The functions are verbatim copies
of commit 609e0df's ``twin_nodes/discovery/residuals.py`` (``_lowpass`` .. ``residual_channels``),
``output_error.py`` (``simulate_windows`` .. ``output_error``), ``discover.fit_candidate`` and
``twin/runner.TwinRunner._carried_setpoint``: the Butterworth filter designed on every call, the
exogenous inputs and the rotor states recomputed for every evaluation, finite-difference
Jacobians over full-flight evaluations, one process, the closed-loop twins run one after the
other.  Do not edit them; they are the reference the speed-up is measured against.  (Not frozen:
``discover``'s closed-loop metrics now fly each distinct vehicle once per call; the old code flew
the nominal twin twice when nothing was accepted, so on such flights "before" is a little faster
than it was.)
"""
# ruff: noqa: RUF046  (verbatim copies: int(round(x)) kept as it was)

from __future__ import annotations

import contextlib

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import butter, sosfiltfilt

from twin_nodes.base import frames
from twin_nodes.base.errors import LogError
from twin_nodes.discovery.candidates import Candidate
from twin_nodes.discovery.judging import Judge, _equation_judge, _scales
from twin_nodes.discovery.output_error import JUDGED, MIN_AXIS_R2, STEP_S, Windows
from twin_nodes.discovery.residuals import DEFAULT_RATE_HZ, LOWPASS_HZ, EquationData
from twin_nodes.physics.core import NX_BODY
from twin_nodes.physics.model import Multirotor
from twin_nodes.vehicle.geometry import allocation_matrix
from twin_nodes.vehicle.params import VehicleParams

OE_FIT_WINDOWS = 300


# ---------------------------------------------------------------- residuals.py (frozen)
def _lowpass(x: np.ndarray, rate_hz: float, cutoff_hz: float) -> np.ndarray:
    sos = butter(2, cutoff_hz / (0.5 * rate_hz), output="sos")
    return sosfiltfilt(sos, x, axis=0)


def _fill_nan(x: np.ndarray) -> np.ndarray:
    """Linear fill of NaN gaps per column (for filtering only; the mask keeps them out)."""
    x = np.array(x, float, copy=True)
    if x.ndim == 1:
        x = x[:, None]
    idx = np.arange(len(x))
    for c in range(x.shape[1]):
        good = np.isfinite(x[:, c])
        if good.sum() >= 2:
            x[~good, c] = np.interp(idx[~good], idx[good], x[good, c])
        else:
            x[:, c] = 0.0
    return x


def prepare(log, vp: VehicleParams, rate_hz: float = DEFAULT_RATE_HZ, oversample: int = 10) -> EquationData:
    """Resample what equation error needs onto one grid and mark the usable samples."""
    need = ["position_enu", "velocity_enu", "attitude_q", "motors", "specific_force_flu"]
    for name in need:
        log.require(name)
    rates_name = "body_rates_flu" if log.get("body_rates_flu") is not None else "gyro_flu"
    log.require(rates_name)
    t0, t1 = log.airborne_interval()
    if not t1 - t0 > 5.0:
        raise LogError(log.path, "vehicle_land_detected", f"expected at least 5 s airborne, got {t1 - t0:.1f} s")
    # start a little before take-off and end a little after landing: ground effect lives there
    lo = max(t0 - 2.0, 0.0)
    hi = min(t1 + 1.0, log.duration_s)
    names = need + [rates_name] + [n for n in ("battery_v", "height_agl") if log.get(n) is not None]
    t, d = log.resample(names, rate_hz, lo, hi)
    n = len(t)
    dt = 1.0 / rate_hz
    # (the data preparation follows the current code's, 2026-11-24: IMU and rates averaged into each
    # grid step, the rates low-passed at 10 Hz; since fs13 each fine step's command read at the step's
    # middle; only the evaluation path is frozen)
    from twin_nodes.logs import time_sync
    for name in ("specific_force_flu", rates_name):
        s = log.require(name)
        if len(s.t_s) > 1 and float(np.median(np.diff(s.t_s))) < 0.75 * dt:
            d[name] = time_sync.bin_mean_to(s.t_s, s.values, t)
    f = _lowpass(_fill_nan(d["specific_force_flu"]), rate_hz, min(10.0, 0.4 * rate_hz))
    w = _lowpass(_fill_nan(d[rates_name]), rate_hz, min(10.0, 0.4 * rate_hz))
    # Angular acceleration: central difference of the body rates; the 2 Hz low-pass every
    # residual goes through does the smoothing, identically on the model side (a smoothing
    # derivative here would shrink acceleration pulses and bias inertia up).  PX4's own
    # vehicle_angular_velocity.xyz_derivative is the D-term's filtered derivative: on the SIH
    # logs its roll axis even anti-correlates with the true moment, so it is not used.
    alpha = np.gradient(w, dt, axis=0)
    # commands on a fine grid: linear between logged samples, NaN (stopped) kept
    ms = log.require("motors")
    t_fine = lo + np.arange(n * oversample) * (dt / oversample)
    t_cmd = t_fine + 0.5 * dt / oversample
    u_fine = np.empty((len(t_fine), ms.values.shape[1]))
    for i in range(ms.values.shape[1]):
        col = ms.values[:, i]
        fin = np.isfinite(col)
        u_fine[:, i] = np.interp(t_cmd, ms.t_s[fin], col[fin]) if fin.sum() >= 2 else np.nan
        stopped = np.interp(t_cmd, ms.t_s, (~fin).astype(float)) > 0.5
        u_fine[stopped, i] = np.nan
    motor_dt = float(np.median(np.diff(ms.t_s))) if len(ms.t_s) > 1 else dt
    p = d["position_enu"]
    # ground level: median height while landed before take-off (or the lowest airborne height)
    pre = (t < t0) & np.isfinite(p[:, 2])
    ground = float(np.median(p[pre, 2])) if pre.sum() > 5 else float(np.nanpercentile(p[:, 2], 1))
    height = p[:, 2] - ground
    if "height_agl" in d:
        # the distance sensor where it is valid: EKF height is too noisy near the ground
        agl = d["height_agl"].reshape(n)
        height = np.where(np.isfinite(agl), agl, height)
    batt = d["battery_v"].reshape(n) if "battery_v" in d else np.full(n, np.nan)
    finite = (np.isfinite(p).all(1) & np.isfinite(d["velocity_enu"]).all(1) & np.isfinite(d["attitude_q"]).all(1)
              & np.isfinite(w).all(1) & np.isfinite(f).all(1))
    u_grid = u_fine[::oversample][:n]
    armed = np.isfinite(u_grid).all(1)
    data = EquationData(path=log.path, t=t, valid=finite & armed, p=p, v=d["velocity_enu"], q=d["attitude_q"],
                        w=w, alpha=alpha, f=f, u_fine=u_fine, up=oversample, battery_v=batt, height=height,
                        motor_dt_s=motor_dt, info={"airborne": (t0, t1), "ground_enu_z": ground})
    # exclude ground contact: low, slow, and the model's thrust well below the weight
    model = Multirotor(vp)
    S = model_rotor_states(model, data)
    thrust = model.params.rotors.thrust_from_state(np.maximum(S, 0)).sum(1)
    weight = vp.mass_kg * vp.gravity_m_s2
    contact = (height < 0.5) & (np.linalg.norm(data.v, axis=1) < 0.3) & (thrust < 0.7 * weight)
    contact |= height < 0.05
    # sitting on the ground whatever the height estimate says (after touchdown PX4's EKF height can
    # read 1 m for seconds): far too little thrust to fly, yet the accelerometer reads a supported
    # vehicle, not a falling one
    contact |= (thrust < 0.6 * weight) & (vp.mass_kg * data.f[:, 2] - thrust > 0.3 * weight)
    # pad contact by 0.5 s either side (touchdown transients)
    pad = int(round(0.5 * rate_hz))
    contact = np.convolve(contact.astype(float), np.ones(2 * pad + 1), mode="same") > 0
    data.valid &= ~contact
    data.info["contact_samples"] = int(contact.sum())
    if data.valid.sum() < 5 * rate_hz:
        raise LogError(log.path, "airborne samples", "expected at least 5 s of usable airborne data")
    return data


def exogenous(model: Multirotor, data: EquationData, n: int, up: int = 1) -> np.ndarray:
    """Exogenous inputs (battery voltage; wind from a wind effect) on the grid (n samples, step/up)."""
    t = data.t[0] + np.arange(n) * (data.dt / up)
    batt = np.interp(t, data.t, _fill_nan(data.battery_v)[:, 0]) if np.isfinite(data.battery_v).any() else None
    return model.exogenous(t, np.random.default_rng(0), batt)


def model_rotor_states(model: Multirotor, data: EquationData) -> np.ndarray:
    """Rotor states on the grid, from the logged commands through the model's command path."""
    up = data.up
    ext = exogenous(model, data, len(data.u_fine), up)
    dt_f = data.dt / up
    delay_steps = int(round(model.command_delay_s / dt_f))
    s0 = np.zeros(model.n_rotors)
    S = model._mod.rotor_states(model.P, *model.E, np.ascontiguousarray(data.u_fine), np.ascontiguousarray(ext),
                                dt_f, delay_steps, s0)
    return S[::up][:data.n]


def residual_channels(data: EquationData, vp: VehicleParams, norm_params: VehicleParams | None = None,
                      extra_effects=(), lowpass_hz: float | None = LOWPASS_HZ) -> np.ndarray:
    """Residual channels (T, N + 2) in fraction of full motor output (see module doc).

    ``norm_params`` fixes the normalisation and allocation (the nominal vehicle), so
    candidates are compared in the same units.
    """
    model = Multirotor(vp, extra_effects)
    nominal = norm_params or vp
    S = model_rotor_states(model, data)
    X = np.empty((data.n, model.nx))
    X[:, 0:3] = data.p
    X[:, 2] = data.height  # the model's z is height above the ground (ground contact, ground effect)
    X[:, 3:6] = data.v
    X[:, 6:10] = data.q
    X[:, 10:13] = data.w
    X[:, NX_BODY:] = S
    X = np.nan_to_num(X)
    ext = exogenous(model, data, data.n)
    terms = model.wrench_terms(X, ext)
    F = sum(v[0] for v in terms.values())
    M = sum(v[1] for v in terms.values())
    mp = model.params
    J = mp.inertia
    w = data.w
    rF = mp.mass_kg * data.f - F
    rM = data.alpha @ J.T + np.cross(w, w @ J.T) - M
    A = allocation_matrix(nominal)
    tmax = nominal.rotors.thrust_at_full_command_n
    n_rot = nominal.rotors.count
    per_motor = np.column_stack([rF[:, 2], rM]) @ A.T / tmax
    horiz = rF[:, :2] / (n_rot * tmax)
    R = np.column_stack([per_motor, horiz])
    R = np.where(np.isfinite(R), R, 0.0)
    if lowpass_hz:
        R = _lowpass(R, 1.0 / data.dt, lowpass_hz)
    return R




# ---------------------------------------------------------------- output_error.py (frozen)
def simulate_windows(data: EquationData, win: Windows, vp: VehicleParams, step_s: float = STEP_S,
                     rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Model rates and velocities (H, K, 3) each at the logged samples 1..H of each window."""
    model = Multirotor(vp)
    start = win.start if rows is None else win.start[rows]
    up = data.up
    dt_f = data.dt / up
    fs = max(int(round(step_s / dt_f)), 1)
    per = max(up // fs, 1)
    dt_c = fs * dt_f
    ext = exogenous(model, data, len(data.u_fine), up)
    delay = int(round(model.command_delay_s / dt_f))
    u = np.ascontiguousarray(data.u_fine)
    S = model._mod.rotor_states(model.P, *model.E, u, np.ascontiguousarray(ext), dt_f, delay,
                                np.zeros(model.n_rotors))
    k = len(start)
    X = np.zeros((k, model.nx))
    X[:, 0:3] = data.p[start]
    X[:, 2] = data.height[start]
    X[:, 3:6] = data.v[start]
    X[:, 6:10] = data.q[start]
    X[:, 10:13] = data.w[start]
    X[:, NX_BODY:] = S[start * up]
    X = np.nan_to_num(X)
    PB = np.ascontiguousarray(np.tile(model.P, (k, 1)))
    H = win.horizon
    W = np.empty((H, k, 3))
    V = np.empty((H, k, 3))
    base = start * up
    n_f = len(u)
    for j in range(H * per):
        # the command in the middle of the step (commands are linear between logged samples)
        idx = np.clip(base + j * fs + fs // 2 - delay, 0, n_f - 1)
        U = np.nan_to_num(u[idx])
        E = np.ascontiguousarray(ext[np.minimum(base + j * fs, n_f - 1)])
        model._mod.step_batch(PB, X, np.ascontiguousarray(U), E, dt_c, 1)
        if (j + 1) % per == 0:
            W[(j + 1) // per - 1] = X[:, 10:13]
            V[(j + 1) // per - 1] = X[:, 3:6]
    return W, V


def _slopes(data: EquationData, win: Windows, W: np.ndarray, V: np.ndarray, start: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares slopes over the horizon (with intercept) of measured and predicted changes:
    acceleration (body, m/s^2) and angular acceleration (rad/s^2), measured and model."""
    H = win.horizon
    h = np.arange(1, H + 1)
    hc = (h - h.mean()) / (np.sum((h - h.mean()) ** 2) * data.dt)
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


def judge_axes(data: EquationData, win: Windows, nominal: VehicleParams) -> Windows:
    """Fill ``win.usable``/``axis_r2``/``axis_gain`` from the nominal model's prediction."""
    meas, pred = axis_errors(data, win, nominal)
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
    r = nominal.rotors
    n_rot = r.count
    b = np.vstack([np.ones(n_rot), np.array(r.y_flu_m), -np.array(r.x_flu_m), -np.array(r.direction, float)])
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    # modes() projects per-motor channels with b; pinv(b) puts the axis errors back exactly
    per_motor = err[:, 2:6] @ np.linalg.pinv(b).T
    R = np.column_stack([per_motor, np.zeros((len(err), 2))])
    return np.where(np.isfinite(R), R, 0.0)




# ---------------------------------------------------------------- discover.py (frozen)
def fit_candidate(c: Candidate, data: EquationData | Judge, nominal: VehicleParams, fit_mask: np.ndarray,
                  max_nfev: int = 60) -> tuple[np.ndarray, VehicleParams, float]:
    """Least-squares fit of one candidate's parameters on the fit rows of a residual
    (an :class:`EquationData` means the equation error, as before residuals were pluggable)."""
    judge = data if isinstance(data, Judge) else _equation_judge(data, nominal, [], [], fit_mask)
    s = _scales(c)
    lo, hi = c.lower / s, c.upper / s
    rows = fit_mask
    if judge.lean and fit_mask.sum() > OE_FIT_WINDOWS:
        # every k-th fit window: the fit has a few parameters, hundreds of windows pin them
        idx = np.flatnonzero(fit_mask)
        rows = np.zeros_like(fit_mask)
        rows[idx[np.linspace(0, idx.size - 1, OE_FIT_WINDOWS).round().astype(int)]] = True

    def resid(z):
        theta = np.clip(z * s, c.lower, c.upper)
        return judge.residual(c.build(theta), rows).ravel()

    z0 = np.clip(c.x0 / s, lo, hi)
    if len(z0) == 1:
        # one parameter: a grid then a bounded scalar search (delays give piecewise-flat costs)
        from scipy.optimize import minimize_scalar

        def cost1(z):
            return float(np.sum(resid(np.array([z])) ** 2))
        grid = np.linspace(lo[0], hi[0], 9 if judge.lean else 25)
        costs = [cost1(z) for z in grid]
        k = int(np.argmin(costs))
        a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
        opts = {"xatol": 1e-4 * (hi[0] - lo[0])}
        if judge.lean:
            opts["maxiter"] = 14
        sol = minimize_scalar(cost1, bounds=(a, b), method="bounded", options=opts)
        z = sol.x if sol.fun <= costs[k] else grid[k]
        theta = np.clip(np.array([z]) * s, c.lower, c.upper)
        return theta, c.build(theta), min(float(sol.fun), costs[k])
    best_z, best_cost = z0, float(np.sum(resid(z0) ** 2))
    # Starting points: parameters whose nominal value is zero (drag, offsets, delays) span
    # orders of magnitude, so scan them jointly on a log grid of their range; the others
    # +-20 % around the nominal (the output error: jointly x0.7 and x1.6, fewer evaluations).
    starts = []
    zero = c.x0 == 0
    fracs = (0.02, 0.2) if judge.lean else (0.002, 0.006, 0.02, 0.06, 0.2)
    for frac in fracs:
        z = z0.copy()
        z[zero] = lo[zero] + frac * (hi[zero] - lo[zero])
        if np.any(zero):
            starts.append(z)
            if np.any(lo[zero] < 0):  # signed parameters (offsets, wind): both directions
                z2 = z0.copy()
                z2[zero] = hi[zero] - frac * (hi[zero] - lo[zero])
                starts.append(z2)
    if judge.lean:
        for f in (0.7, 1.6, 2.5):  # (x2.5 jointly, as the current fit does since 2026-11-24)
            z = z0.copy()
            z[~zero] = z0[~zero] * f
            starts.append(z)
        free = np.flatnonzero(~zero)
        if free.size > 1:  # (each parameter alone, as the current fit does since 2026-11-24)
            for j in free:
                for f in (0.7, 1.6):
                    z = z0.copy()
                    z[j] = z0[j] * f
                    starts.append(z)
    else:
        for j in np.flatnonzero(~zero):
            for f in (0.8, 1.2):
                z = z0.copy()
                z[j] = z0[j] * f
                starts.append(z)
        if np.count_nonzero(~zero) > 1:  # (jointly too, as the current fit does since 2026-11-24)
            for f in (0.6, 1.6, 2.5):
                z = z0.copy()
                z[~zero] = z0[~zero] * f
                starts.append(z)
    for z in starts:
        z = np.clip(z, lo, hi)
        cost = float(np.sum(resid(z) ** 2))
        if cost < best_cost:
            best_z, best_cost = z, cost
    sol = least_squares(resid, best_z, bounds=(lo, hi), x_scale=1.0, diff_step=2e-2 if judge.lean else 1e-2,
                        max_nfev=12 if judge.lean else max_nfev, method="trf")
    theta = np.clip(sol.x * s, c.lower, c.upper)
    return theta, c.build(theta), float(2 * sol.cost)




# ---------------------------------------------------------------- twin/runner.py (frozen)
def _carried_setpoint(self) -> np.ndarray:
    """TwinRunner._carried_setpoint as it was (the setpoint's rates re-derived every control step)."""
    sp = self.sp
    turning = bool(np.isfinite(sp[9]) and np.isfinite(sp[10]) and sp[10] != 0.0)  # (yaw carry: 2026-11-24)
    if self.sp_t is None or self.t is None or not (np.any(np.isfinite(sp[3:6])) or turning):
        return sp
    dt = min(max(self.t - self.sp_t, 0.0), 1.0)
    out = sp.copy()
    if np.any(np.isfinite(sp[3:6])):
        vel = np.nan_to_num(sp[3:6])
        acc = np.nan_to_num(sp[6:9])
        out[0:3] = sp[0:3] + vel * dt + 0.5 * acc * dt * dt
    if turning:
        out[9] = (sp[9] + sp[10] * dt + np.pi) % (2.0 * np.pi) - np.pi
    return out


# ---------------------------------------------------------------- switching
@contextlib.contextmanager
def before():
    """Run ``discover`` with the frozen evaluation path (and one process) inside this block."""
    from twin_nodes.discovery import evaluate as ev
    from twin_nodes.discovery import judging
    from twin_nodes.discovery import locate as loc
    from twin_nodes.discovery.stages import mismatch, refit, report
    from twin_nodes.discovery.stages import prepare as flight
    from twin_nodes.twin.runner import TwinRunner
    # each name where discovery's stages look it up (discover.py before it was split into stages)
    swaps = [(flight, "prepare", prepare),
             *[(m, "residual_channels", residual_channels) for m in (judging, mismatch, refit, report)],
             (judging, "output_error", output_error), (judging, "judge_axes", judge_axes),
             (judging, "fit_candidate", fit_candidate), (loc, "model_rotor_states", model_rotor_states),
             (TwinRunner, "_carried_setpoint", _carried_setpoint)]
    swaps += [(ev, name, value) for name, value in BEFORE_SETTINGS.items()]
    saved = [(mod, name, getattr(mod, name)) for mod, name, _ in swaps]
    try:
        for mod, name, value in swaps:
            setattr(mod, name, value)
        yield
    finally:
        for mod, name, value in saved:
            setattr(mod, name, value)


#: twin_nodes.discovery.evaluate's switches, as it was: one process, no affine shortcut
BEFORE_SETTINGS = {"WORKERS": 1, "AFFINE_FITS": False}
