"""Equation-error regression of the translational and rotational equations from flight data.

Reference 2, steps 2-3: rotor speeds estimated from the logged motor commands
through the (discretised) first-order motor model go into the equations of
motion together with the logged attitude, and least squares fits the model's
accelerations to the measured ones.  The translational fit is good; in the
rotational one only *combinations* of the physical parameters can be found.

Model (body FLU, rotor ``i`` at ``(x_i, y_i)``, spin ``d_i`` = +1 CCW seen from
above, ``T~_i`` the per-rotor thrust regressor, ``l`` the mean arm length)::

    f_z   = (kT/m) sum T~_i - (kd_z/m) v_z            specific force along body z
    f_x   = -(kd_x/m) v_x,   f_y = -(kd_y/m) v_y       (v = body-frame velocity)
    w'_x  = (kT l/Ixx) sum (y_i/l) T~_i + ((Iyy-Izz)/Ixx) w_y w_z - (kdw_x/Ixx) w_x
    w'_y  = (kT l/Iyy) sum (-x_i/l) T~_i + ((Izz-Ixx)/Iyy) w_z w_x - (kdw_y/Iyy) w_y
    w'_z  = (km kT/Izz) sum (-d_i) T~_i + ((Ixx-Iyy)/Izz) w_x w_y - (kdw_z/Izz) w_z

``T~_i`` is ``omega_i^2`` [rad^2/s^2] for the ``omega_squared`` model (``kT = kt``),
the relative thrust ``f s^2 + (1-f) s`` for ``thrust_factor`` (``kT = thrust_max_n``),
or the lagged normalised command itself when no parameter file is given
(``kT`` = thrust per unit command, PX4's ``actuator_motors`` being a normalised
thrust demand).  Every column's coefficient is a named combination of physical
parameters; :func:`fit_linear` reports which coefficients the data determine
(SVD of the column-scaled regressor), and :func:`structural_identifiability`
which physical parameters those coefficients determine.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping, Sequence

import numpy as np
from scipy import signal

from twin_nodes.base import frames
from twin_nodes.identify.step_response import _lag_exact

# --------------------------------------------------------------------------- generic least squares


@dataclass(frozen=True)
class Combination:
    """An estimable linear combination ``sum weights[name] * coef[name]`` of coefficients."""

    weights: dict[str, float]
    value: float
    stderr: float

    def text(self) -> str:
        parts = []
        for i, (k, w) in enumerate(self.weights.items()):
            sign = "-" if w < 0 else ("+" if i else "")
            mag = abs(w)
            parts.append(f"{sign} {k}" if math.isclose(mag, 1.0, rel_tol=1e-9) else f"{sign} {mag:.4g}*{k}")
        return " ".join(parts).strip().lstrip("+ ").strip()

    def as_dict(self) -> dict:
        return {"combination": self.text(), "weights": {k: float(v) for k, v in self.weights.items()},
                "value": float(self.value), "stderr": float(self.stderr)}


@dataclass(frozen=True)
class LinearFit:
    """Least-squares fit ``y ~ X coef`` with identifiability diagnostics.

    ``singular_values`` are those of the regressor with every column scaled to
    unit norm, so ``condition_number`` measures collinearity, not units.  A
    coefficient whose unit vector is not orthogonal to the (numerical) null space
    is not identifiable on its own: its ``stderr`` is ``inf`` and the estimable
    ``combinations`` say what the data do determine.
    """

    names: tuple[str, ...]
    coef: np.ndarray
    stderr: np.ndarray
    r2: float
    rmse: float
    n: int
    singular_values: np.ndarray
    condition_number: float
    rank: int
    identifiable: np.ndarray
    null_space: tuple[dict[str, float], ...]
    combinations: tuple[Combination, ...]
    meanings: dict[str, str] = field(default_factory=dict)
    #: covariance of ``coef`` (identifiable block; rank-deficient directions are not in it)
    cov: np.ndarray | None = None
    #: how the coefficients were estimated (``"least squares"`` or the errors-in-commands moment form)
    method: str = "least squares"

    @property
    def t_values(self) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(np.isfinite(self.stderr) & (self.stderr > 0), self.coef / self.stderr, 0.0)

    def __getitem__(self, name: str) -> float:
        return float(self.coef[self.names.index(name)])

    def se(self, name: str) -> float:
        return float(self.stderr[self.names.index(name)])

    def predict(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(X, dtype=float) @ self.coef

    def as_dict(self) -> dict:
        return {
            "coefficients": {n: {"value": float(c), "stderr": float(s), "t": float(t), "identifiable": bool(i),
                                 **({"meaning": self.meanings[n]} if n in self.meanings else {})}
                             for n, c, s, t, i in zip(self.names, self.coef, self.stderr, self.t_values,
                                                      self.identifiable)},
            "r2": float(self.r2), "rmse": float(self.rmse), "n": int(self.n),
            "singular_values_scaled": [float(v) for v in self.singular_values],
            "condition_number": float(self.condition_number), "rank": int(self.rank),
            "null_space": [{k: float(v) for k, v in d.items()} for d in self.null_space],
            "identifiable_combinations": [c.as_dict() for c in self.combinations],
            "method": self.method,
        }


def fit_linear(X: np.ndarray, y: np.ndarray, names: Sequence[str], *, rcond: float = 1e-3,
               meanings: Mapping[str, str] | None = None) -> LinearFit:
    """Least squares with an SVD identifiability analysis.

    ``X`` (n, p), ``y`` (n,).  Columns are scaled to unit norm; singular values
    below ``rcond`` times the largest count as zero (a truncated-SVD, minimum-norm
    solution).  Rows with any non-finite value are dropped.
    """
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float).ravel()
    names = tuple(names)
    if X.ndim != 2 or X.shape[0] != y.size or X.shape[1] != len(names):
        raise ValueError(f"X has shape {X.shape}, y {y.shape}, names {len(names)}: expected (n, p), (n,), p")
    ok = np.all(np.isfinite(X), axis=1) & np.isfinite(y)
    X, y = X[ok], y[ok]
    n, p = X.shape
    if n <= p:
        raise ValueError(f"need more samples than coefficients, got {n} <= {p}")
    norms = np.linalg.norm(X, axis=0)
    zero = norms == 0.0
    norms_safe = np.where(zero, 1.0, norms)
    Xs = X / norms_safe
    U, S, Vt = np.linalg.svd(Xs, full_matrices=False)
    S_full = S.copy()
    r = int(np.sum(S > rcond * S[0])) if S[0] > 0 else 0
    Ur, Sr, Vr = U[:, :r], S[:r], Vt[:r].T
    theta_s = Vr @ ((Ur.T @ y) / Sr)
    coef = theta_s / norms_safe
    coef[zero] = 0.0
    resid = y - X @ coef
    ssr = float(resid @ resid)
    sst = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - ssr / sst if sst > 0 else float("nan")
    sigma2 = ssr / max(n - r, 1)
    cov_s = (Vr / Sr ** 2) @ Vr.T * sigma2
    cov = cov_s / np.outer(norms_safe, norms_safe)
    null_s = Vt[r:].T  # (p, p-r), scaled coordinates
    tol = 0.05
    ident = np.ones(p, dtype=bool)
    if null_s.size:
        ident = np.max(np.abs(null_s), axis=1) < tol
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    se = np.where(ident, se, np.inf)

    # Null directions in coefficient units (X @ delta = 0), largest entry 1.
    null_dirs = []
    for k in range(null_s.shape[1]):
        d = null_s[:, k] / norms_safe
        d = d / d[np.argmax(np.abs(d))]
        null_dirs.append({names[i]: float(d[i]) for i in range(p) if abs(null_s[i, k]) >= tol})

    # Groups of coefficients tied together by the null space; one estimable combination each.
    combos = []
    if null_s.size:
        member = np.abs(null_s) >= tol
        groups: list[set[int]] = []
        for k in range(member.shape[1]):
            g = set(np.flatnonzero(member[:, k]).tolist())
            merged = [h for h in groups if h & g]
            for h in merged:
                g |= h
                groups.remove(h)
            groups.append(g)
        for g in groups:
            idx = sorted(g)
            ref = idx[0]
            xr = X[:, ref]
            c = np.zeros(p)
            for i in idx:
                c[i] = float(X[:, i] @ xr) / float(xr @ xr) if xr @ xr > 0 else (1.0 if i == ref else 0.0)
            # Project onto the row space so the combination is exactly estimable.
            cs = c / norms_safe
            cs = cs - null_s @ (null_s.T @ cs)
            c = cs * norms_safe
            if np.max(np.abs(c)) < 1e-12:
                continue
            c = c / c[ref] if abs(c[ref]) > 1e-12 else c / c[np.argmax(np.abs(c))]
            w = {names[i]: float(c[i]) for i in idx if abs(c[i]) > 1e-9}
            val = float(c @ coef)
            sd = float(np.sqrt(max(c @ cov @ c, 0.0)))
            combos.append(Combination(w, val, sd))
    cond = float(S_full[0] / S_full[-1]) if S_full[-1] > 0 else float("inf")
    return LinearFit(names=names, coef=coef, stderr=se, r2=r2, rmse=math.sqrt(ssr / n), n=n,
                     singular_values=S_full, condition_number=cond, rank=r, identifiable=ident,
                     null_space=tuple(null_dirs), combinations=tuple(combos),
                     meanings=dict(meanings or {}), cov=cov)


def fit_moment_form(X: np.ndarray, y: np.ndarray, names: Sequence[str], *, rcond: float = 1e-3,
                    meanings: Mapping[str, str] | None = None) -> LinearFit:
    """Fit ``y ~ X coef`` where the first column of ``X`` (the commanded input) carries the errors.

    Least squares with errors in a regressor attenuates that regressor's coefficient: the
    logged motor commands carry the controller's noise (and, logged as instantaneous
    samples, its aliasing), to which no motion responds, so regressing the angular
    acceleration on the commanded moment underestimates the control effectiveness (and
    overestimates the inertia).  The moment form puts the input on the left,
    ``X[:, 0] = c_y y + sum_k c_k X[:, k]``, whose regressors (the measured acceleration,
    rates) are low-passed measurements, and maps back: ``coef_0 = 1 / c_y``,
    ``coef_k = -c_k / c_y``, with standard errors by the delta method.  The forward fit's
    identifiability analysis is kept; where it is rank deficient, or the input does not
    drive ``y`` (``c_y`` not positive and significant), the forward least squares stands.
    ``r2`` is that of the fitted (moment) equation, ``rmse`` the forward equation's residual with
    the moment-form coefficients.
    """
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float).ravel()
    fwd = fit_linear(X, y, names, rcond=rcond, meanings=meanings)
    p = X.shape[1]
    if fwd.rank < p or not np.all(fwd.identifiable):
        return fwd
    ok = np.all(np.isfinite(X), axis=1) & np.isfinite(y)
    X, y = X[ok], y[ok]
    Z = np.column_stack([y, X[:, 1:]])
    rev = fit_linear(Z, X[:, 0], ["y", *tuple(names)[1:]], rcond=rcond)
    c = rev.coef
    if rev.rank < p or rev.cov is None or not (c[0] > 0 and c[0] > 3.0 * rev.stderr[0]):
        return fwd
    coef = np.empty(p)
    coef[0] = 1.0 / c[0]
    coef[1:] = -c[1:] / c[0]
    jac = np.zeros((p, p))  # d coef / d c
    jac[0, 0] = -1.0 / c[0] ** 2
    jac[1:, 0] = c[1:] / c[0] ** 2
    jac[1:, 1:] = -np.eye(p - 1) / c[0]
    cov = jac @ rev.cov @ jac.T
    resid = y - X @ coef
    return replace(fwd, coef=coef, stderr=np.sqrt(np.maximum(np.diag(cov), 0.0)), cov=cov, r2=rev.r2,
                   rmse=math.sqrt(float(resid @ resid) / y.size),
                   method="moment form (input regressed on the measured response; errors in the commands)")


# --------------------------------------------------------------------------- rotor states


def rotor_states_from_commands(t: np.ndarray, u: np.ndarray, *, tau_up_s: float, tau_down_s: float | None = None,
                               reference: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """Rotor states (n, N) from motor commands (n, N) through the first-order lag.

    ``reference`` maps commands to the steady-state rotor state (e.g.
    ``RotorParams.reference_from_command``: rotor speed for ``omega_squared``);
    default: the command itself, NaN (stopped) -> 0.  The command is held
    between samples and the lag integrated exactly, i.e. the ZOH-discretised
    motor model of reference 2 at the log's own (possibly uneven) sample times.
    """
    t = np.asarray(t, dtype=float)
    u = np.asarray(u, dtype=float)
    if u.ndim == 1:
        u = u[:, None]
    if u.shape[0] != t.size:
        raise ValueError(f"u has {u.shape[0]} samples, t has {t.size}")
    if reference is None:
        ref = np.where(np.isfinite(u), u, 0.0)
    else:
        ref = np.asarray(reference(u), dtype=float)
    tau_down = tau_up_s if tau_down_s is None else tau_down_s
    out = np.empty_like(ref)
    for j in range(ref.shape[1]):
        out[:, j] = _lag_exact(t, np.ascontiguousarray(ref[:, j]), float(ref[0, j]), float(tau_up_s), float(tau_down))
    return out


def thrust_regressor(states: np.ndarray, thrust_model: str = "command", thr_mdl_fac: float = 0.0) -> np.ndarray:
    """Per-rotor thrust regressor ``T~`` (n, N) so that thrust = kT * T~.

    ``"omega_squared"``: states are rotor speeds [rad/s], ``T~ = omega^2``;
    ``"thrust_factor"``: states are lagged normalised commands, ``T~ = f s^2 + (1-f) s``;
    ``"command"``: ``T~ = s`` (thrust taken proportional to the normalised command).
    """
    s = np.maximum(np.asarray(states, dtype=float), 0.0)
    if thrust_model == "omega_squared":
        return s * s
    if thrust_model == "thrust_factor":
        return thr_mdl_fac * s * s + (1.0 - thr_mdl_fac) * s
    if thrust_model == "command":
        return s
    raise ValueError(f"thrust_model must be omega_squared, thrust_factor or command, got {thrust_model!r}")


# --------------------------------------------------------------------------- helpers


def world_to_body(q_wxyz: np.ndarray, v_world: np.ndarray) -> np.ndarray:
    """``R(q)^T v`` for (n, 4) quaternions w,x,y,z (body FLU -> world ENU) and (n, 3) world vectors."""
    return frames.quat_rotate(frames.quat_conjugate(frames.quat_normalize(q_wxyz)), v_world)


def lowpass(x: np.ndarray, rate_hz: float, cutoff_hz: float, order: int = 2) -> np.ndarray:
    """Zero-phase Butterworth low-pass along axis 0 (apply the same one to both sides of a regression)."""
    if cutoff_hz >= 0.5 * rate_hz:
        return np.asarray(x, dtype=float)
    b, a = signal.butter(order, cutoff_hz / (0.5 * rate_hz))
    x = np.asarray(x, dtype=float)
    return signal.filtfilt(b, a, x, axis=0, padlen=min(3 * max(len(a), len(b)), x.shape[0] - 1))


def differentiate(t: np.ndarray, x: np.ndarray, window_s: float = 0.1) -> np.ndarray:
    """Derivative along axis 0 by a Savitzky-Golay filter (quadratic, ``window_s`` wide) on a uniform grid."""
    t = np.asarray(t, dtype=float)
    dt = float(np.median(np.diff(t)))
    w = max(5, int(round(window_s / dt)) | 1)
    if w > t.size:
        return np.gradient(np.asarray(x, dtype=float), t, axis=0)
    return signal.savgol_filter(np.asarray(x, dtype=float), w, 2, deriv=1, delta=dt, axis=0)


# --------------------------------------------------------------------------- physical models


@dataclass(frozen=True)
class RotorGeometry:
    """Rotor positions (body FLU [m]) and spin (+1 CCW seen from above), PX4 motor order."""

    x_flu_m: np.ndarray
    y_flu_m: np.ndarray
    direction: np.ndarray

    @property
    def count(self) -> int:
        return int(np.asarray(self.x_flu_m).size)

    @property
    def arm_length_m(self) -> float:
        return float(np.mean(np.hypot(self.x_flu_m, self.y_flu_m)))

    @classmethod
    def from_params(cls, vp: object) -> "RotorGeometry":
        r = vp.rotors  # type: ignore[attr-defined]
        return cls(np.asarray(r.x_flu_m, float), np.asarray(r.y_flu_m, float), np.asarray(r.direction, float))

    @classmethod
    def quad_x(cls, arm_m: float = 0.25) -> "RotorGeometry":
        """PX4 generic quad X (M1 front-right CCW, M2 rear-left CCW, M3 front-left CW, M4 rear-right CW)."""
        a = arm_m / math.sqrt(2.0)
        return cls(np.array([a, -a, a, -a]), np.array([-a, a, a, -a]), np.array([1.0, 1.0, -1.0, -1.0]))


MEANINGS = {
    "kT/m": "thrust per regressor unit / mass",
    "kd_x/m": "linear drag x / mass", "kd_y/m": "linear drag y / mass", "kd_z/m": "linear drag z / mass",
    "kT*l/Ixx": "roll moment per thrust-difference unit / Ixx",
    "kT*l/Iyy": "pitch moment per thrust-difference unit / Iyy",
    "km*kT/Izz": "yaw reaction torque per thrust-difference unit / Izz",
    "(Iyy-Izz)/Ixx": "gyroscopic coupling, roll", "(Izz-Ixx)/Iyy": "gyroscopic coupling, pitch",
    "(Ixx-Iyy)/Izz": "gyroscopic coupling, yaw",
    "kdw_x/Ixx": "angular damping roll / Ixx", "kdw_y/Iyy": "angular damping pitch / Iyy",
    "kdw_z/Izz": "angular damping yaw / Izz",
    "bias_x": "constant offset", "bias_y": "constant offset", "bias_z": "constant offset",
}


def translational_columns(thrust_units: np.ndarray, velocity_body: np.ndarray | None, *,
                          drag: bool = True, intercept: bool = False) -> dict[str, tuple[np.ndarray, list[str]]]:
    """Regressor matrices per body axis (``"x"``, ``"y"``, ``"z"``) for the specific-force equations."""
    tt = np.asarray(thrust_units, dtype=float)
    tsum = np.sum(tt, axis=1)
    out: dict[str, tuple[np.ndarray, list[str]]] = {}
    cols_z = [tsum]
    names_z = ["kT/m"]
    if drag and velocity_body is not None:
        vb = np.asarray(velocity_body, dtype=float)
        cols_z.append(-vb[:, 2])
        names_z.append("kd_z/m")
        for k, ax in ((0, "x"), (1, "y")):
            cols = [-vb[:, k]]
            nm = [f"kd_{ax}/m"]
            if intercept:
                cols.append(np.ones(tsum.size))
                nm.append(f"bias_{ax}")
            out[ax] = (np.column_stack(cols), nm)
    if intercept:
        cols_z.append(np.ones(tsum.size))
        names_z.append("bias_z")
    out["z"] = (np.column_stack(cols_z), names_z)
    return out


def rotational_columns(rates_flu: np.ndarray, thrust_units: np.ndarray, geometry: RotorGeometry, *,
                       gyroscopic: bool = True, damping: bool = True,
                       intercept: bool = False) -> dict[str, tuple[np.ndarray, list[str]]]:
    """Regressor matrices per body axis (``"roll"``, ``"pitch"``, ``"yaw"``) for the angular accelerations."""
    w = np.asarray(rates_flu, dtype=float)
    tt = np.asarray(thrust_units, dtype=float)
    if tt.shape[1] != geometry.count:
        raise ValueError(f"{tt.shape[1]} rotors in the data, {geometry.count} in the geometry")
    l = geometry.arm_length_m
    u_roll = tt @ (np.asarray(geometry.y_flu_m) / l)
    u_pitch = tt @ (-np.asarray(geometry.x_flu_m) / l)
    u_yaw = tt @ (-np.asarray(geometry.direction, dtype=float))
    spec = {
        "roll": (u_roll, "kT*l/Ixx", w[:, 1] * w[:, 2], "(Iyy-Izz)/Ixx", 0, "kdw_x/Ixx", "bias_x"),
        "pitch": (u_pitch, "kT*l/Iyy", w[:, 2] * w[:, 0], "(Izz-Ixx)/Iyy", 1, "kdw_y/Iyy", "bias_y"),
        "yaw": (u_yaw, "km*kT/Izz", w[:, 0] * w[:, 1], "(Ixx-Iyy)/Izz", 2, "kdw_z/Izz", "bias_z"),
    }
    out = {}
    for ax, (uin, nin, gyro, ngyro, k, ndamp, nbias) in spec.items():
        cols, names = [uin], [nin]
        if gyroscopic:
            cols.append(gyro)
            names.append(ngyro)
        if damping:
            cols.append(-w[:, k])
            names.append(ndamp)
        if intercept:
            cols.append(np.ones(w.shape[0]))
            names.append(nbias)
        out[ax] = (np.column_stack(cols), names)
    return out


def translational_regression(specific_force_flu: np.ndarray, thrust_units: np.ndarray,
                             velocity_body_flu: np.ndarray | None = None, *, drag: bool = True,
                             intercept: bool = False, rcond: float = 1e-3) -> dict[str, LinearFit]:
    """Fit the specific-force equations per body axis; returns ``{"x"|"y"|"z": LinearFit}``.

    ``specific_force_flu`` (n, 3) [m/s^2, accelerometer, FLU], ``thrust_units``
    (n, N) from :func:`thrust_regressor`, ``velocity_body_flu`` (n, 3) [m/s].
    """
    f = np.asarray(specific_force_flu, dtype=float)
    cols = translational_columns(thrust_units, velocity_body_flu, drag=drag, intercept=intercept)
    idx = {"x": 0, "y": 1, "z": 2}
    return {ax: fit_linear(X, f[:, idx[ax]], names, rcond=rcond, meanings=MEANINGS)
            for ax, (X, names) in cols.items()}


def rotational_regression(angular_accel_flu: np.ndarray, rates_flu: np.ndarray, thrust_units: np.ndarray,
                          geometry: RotorGeometry, *, gyroscopic: bool = True, damping: bool = True,
                          intercept: bool = False, rcond: float = 1e-3, form: str = "moment") -> dict[str, LinearFit]:
    """Fit the rotational equations per axis; returns ``{"roll"|"pitch"|"yaw": LinearFit}``.

    ``angular_accel_flu`` (n, 3) [rad/s^2], ``rates_flu`` (n, 3) [rad/s].  ``form``:
    ``"moment"`` (default) estimates with the commanded moment on the left
    (:func:`fit_moment_form`: unbiased when the commands carry the errors, as logged
    controller commands do); ``"acceleration"`` is plain least squares of the angular
    acceleration on the commands (attenuated by those errors: 19-24 % low on PX4 SIH).
    """
    if form not in ("moment", "acceleration"):
        raise ValueError(f"form must be 'moment' or 'acceleration', got {form!r}")
    a = np.asarray(angular_accel_flu, dtype=float)
    cols = rotational_columns(rates_flu, thrust_units, geometry, gyroscopic=gyroscopic, damping=damping,
                              intercept=intercept)
    idx = {"roll": 0, "pitch": 1, "yaw": 2}
    fit = fit_moment_form if form == "moment" else fit_linear
    return {ax: fit(X, a[:, idx[ax]], names, rcond=rcond, meanings=MEANINGS) for ax, (X, names) in cols.items()}


# --------------------------------------------------------------------------- structural identifiability

PHYSICAL_PARAMS = ("m", "kT", "km", "l", "Ixx", "Iyy", "Izz", "kd_x", "kd_y", "kd_z",
                   "kdw_x", "kdw_y", "kdw_z")

COEFFICIENT_FORMULAS: dict[str, Callable[[Mapping[str, float]], float]] = {
    "kT/m": lambda p: p["kT"] / p["m"],
    "kd_x/m": lambda p: p["kd_x"] / p["m"],
    "kd_y/m": lambda p: p["kd_y"] / p["m"],
    "kd_z/m": lambda p: p["kd_z"] / p["m"],
    "kT*l/Ixx": lambda p: p["kT"] * p["l"] / p["Ixx"],
    "kT*l/Iyy": lambda p: p["kT"] * p["l"] / p["Iyy"],
    "km*kT/Izz": lambda p: p["km"] * p["kT"] / p["Izz"],
    "(Iyy-Izz)/Ixx": lambda p: (p["Iyy"] - p["Izz"]) / p["Ixx"],
    "(Izz-Ixx)/Iyy": lambda p: (p["Izz"] - p["Ixx"]) / p["Iyy"],
    "(Ixx-Iyy)/Izz": lambda p: (p["Ixx"] - p["Iyy"]) / p["Izz"],
    "kdw_x/Ixx": lambda p: p["kdw_x"] / p["Ixx"],
    "kdw_y/Iyy": lambda p: p["kdw_y"] / p["Iyy"],
    "kdw_z/Izz": lambda p: p["kdw_z"] / p["Izz"],
}

GENERIC_NOMINAL = {"m": 1.5, "kT": 8.0, "km": 0.016, "l": 0.25, "Ixx": 0.03, "Iyy": 0.035, "Izz": 0.05,
                   "kd_x": 0.3, "kd_y": 0.3, "kd_z": 0.5, "kdw_x": 0.01, "kdw_y": 0.01, "kdw_z": 0.01}


@dataclass(frozen=True)
class StructuralResult:
    """Which physical parameters a set of identified coefficients determines.

    ``involved`` are the physical parameters that appear in the coefficients;
    ``rank`` is the rank of d(coefficients)/d(log parameters) at ``nominal``;
    every ``null_directions`` entry is a change of the log-parameters (largest
    entry 1) that leaves all coefficients unchanged: those parameters are not
    separately identifiable, only the coefficient combinations are.
    """

    coefficients: tuple[str, ...]
    involved: tuple[str, ...]
    rank: int
    null_directions: tuple[dict[str, float], ...]
    determined: tuple[str, ...]

    def as_dict(self) -> dict:
        return {"identified_combinations": list(self.coefficients), "physical_parameters": list(self.involved),
                "rank": self.rank, "unidentifiable_directions_log": [dict(d) for d in self.null_directions],
                "separately_identifiable": list(self.determined)}

    def describe(self) -> list[str]:
        out = []
        for d in self.null_directions:
            up = [k for k, v in d.items() if v > 0]
            dn = [k for k, v in d.items() if v < 0]
            txt = " and ".join(x for x in (", ".join(up) + " up" if up else "",
                                          ", ".join(dn) + " down" if dn else "") if x)
            out.append(f"scaling {txt} together (log weights {', '.join(f'{k} {v:+.2f}' for k, v in d.items())}) "
                       f"leaves every coefficient unchanged")
        return out


def structural_identifiability(coefficients: Sequence[str], nominal: Mapping[str, float] | None = None,
                               known: Sequence[str] = (), tol: float = 1e-6) -> StructuralResult:
    """Rank and null space of the coefficient map at ``nominal`` physical parameters.

    Uses the Jacobian of the coefficients with respect to the logarithm of the
    physical parameters (rows normalised), so a null direction reads as "scale
    these parameters by these powers together".  Parameters named in ``known``
    (e.g. the mass weighed on a scale) are held fixed.
    """
    coefficients = tuple(c for c in coefficients if c in COEFFICIENT_FORMULAS)
    p0 = dict(GENERIC_NOMINAL)
    if nominal:
        p0.update({k: float(v) for k, v in nominal.items() if k in p0 and v is not None and v > 0})
    involved = []
    for name in PHYSICAL_PARAMS:
        if name in known:
            continue
        for c in coefficients:
            f = COEFFICIENT_FORMULAS[c]
            bumped = dict(p0)
            bumped[name] *= 1.01
            if abs(f(bumped) - f(p0)) > 1e-12 * max(1.0, abs(f(p0))):
                involved.append(name)
                break
    if not coefficients or not involved:
        return StructuralResult(coefficients, tuple(involved), 0, (), ())
    J = np.empty((len(coefficients), len(involved)))
    h = 1e-6
    for j, name in enumerate(involved):
        up, dn = dict(p0), dict(p0)
        up[name] *= math.exp(h)
        dn[name] *= math.exp(-h)
        for i, c in enumerate(coefficients):
            f = COEFFICIENT_FORMULAS[c]
            J[i, j] = (f(up) - f(dn)) / (2 * h)
    J = J / np.maximum(np.linalg.norm(J, axis=1, keepdims=True), 1e-300)
    _, S, Vt = np.linalg.svd(J)
    rank = int(np.sum(S > tol * S[0]))
    null = Vt[rank:]
    # A readable basis: reduced row echelon form of the null space.
    dirs = []
    if null.shape[0]:
        basis = _rref(null)
        for row in basis:
            row = row / row[np.argmax(np.abs(row))]
            dirs.append({involved[j]: float(round(row[j], 4)) for j in range(len(involved)) if abs(row[j]) > 1e-6})
    free = set()
    for d in dirs:
        free |= set(d)
    determined = tuple(p for p in involved if p not in free)
    return StructuralResult(coefficients, tuple(involved), rank, tuple(dirs), determined)


def _rref(a: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Reduced row echelon form (rows span the same space; sparse, readable directions)."""
    a = np.array(a, dtype=float)
    rows, cols = a.shape
    r = 0
    for c in range(cols):
        if r >= rows:
            break
        piv = r + int(np.argmax(np.abs(a[r:, c])))
        if abs(a[piv, c]) < tol:
            continue
        a[[r, piv]] = a[[piv, r]]
        a[r] /= a[r, c]
        for i in range(rows):
            if i != r:
                a[i] -= a[i, c] * a[r]
        r += 1
    a[np.abs(a) < tol] = 0.0
    return a[:r]
