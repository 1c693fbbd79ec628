"""The parameter pipeline of the Búho Negro paper, as plain functions.

Everything here is numpy only (no ROS, no file I/O except :func:`load_spec`).
Units are SI unless a name says otherwise (``_in`` inches, ``_rpm``, ``_us``).

The building blocks (reference 1 = the Búho Negro paper, reference 2 = the
3DR Quad-C model-verification write-up; see ``shared/reference/``):

==============================  ============================================================
function                        formula
==============================  ============================================================
:func:`ols_through_origin`      slope = Σxy/Σx², uncentred R² = 1 − SSres/Σy²
:func:`kt_from_thrust_curve`    T = kt ω²  (OLS of T on x = ω²)            [ref 1]
:func:`km_from_torque_curve`    Q = km T   (OLS of Q on T)                 [ref 1]
:func:`scale_kt`                kt2 = kt1 (D2/D1)³ (P2/P1)                 [ref 1]
:func:`scale_omega_max`         ω2 = ω1 sqrt(kt1/kt2)  (same max thrust)   [ref 1]
:func:`tau_from_rise_time`      τ = t_r / 2.2  (10→90 % rise of a 1st-order lag) [ref 1]
:func:`tau_down_from_braking`   τ_down = factor τ_up                       [ref 1]
:func:`omega_limits`            ω_min = 0.20 ω_max, ω_nmax = 0.95 ω_max    [ref 1]
:func:`hover_omega`             ω_h = sqrt(m g / (N kt))
:func:`hover_throttle`          u_h = (ω_h − ω_min)/(ω_cmd_max − ω_min)
:func:`thrust_to_weight`        N kt ω² / (m g)
:func:`kt_from_hover`           kt = m g / (N ω_h²)                        [ref 2]
:func:`kt_from_ct`              kt = ρ C_T D⁴ / (4π²)                      [ref 1]
:func:`km_from_coefficients`    km = C_P D / (2π C_T)
:func:`inertia_from_shapes`     hollow-sphere stack + cylinder motors (+ arms, props),
                                parallel-axis theorem                      [ref 2]
:func:`x_frame_positions`       PX4 quad-X rotor order in body FLU
==============================  ============================================================

:func:`derive` / :func:`derive_params` chain them from a YAML *derivation
spec* into a validated :class:`~twin_nodes.vehicle.params.VehicleParams`, and record
every step (quantity, value, unit, formula with numbers) so the CLI can print
it.  Commented examples: ``params/derive_buho_negro.yaml`` (paper inputs) and
``params/derive_quad_c_3dr.yaml`` (reference 2).  Spec sections:

- ``name``, ``gravity_m_s2`` (9.80665), ``dt_s`` (0.001), ``notes`` (free text
  copied into the params file header);
- ``mass_kg``: a number, or ``from_hover`` = N kt ω_h² / g;
- ``hover``: measured hover speed, ``rpm`` or ``omega_rad_s`` (optional);
- ``frame``: ``type: quad_x``, ``arm_length_m``, ``rotor_z_m`` (0);
- ``propeller``: ``diameter_in``, ``pitch_in``;
- ``thrust.method``: ``reference`` (``kt_ref_n_s2_rad2``, ``diameter_ref_in``,
  ``pitch_ref_in``, optional ``omega_max_ref_rad_s``: similarity scaling),
  ``curve`` (``omega_rad_s`` or ``rpm``, ``thrust_n`` or ``thrust_g``: OLS),
  ``given`` (``kt_n_s2_rad2``) or ``from_hover`` (needs a numeric mass);
- ``speed``: ``rpm_max`` or ``omega_max_rad_s`` (unless the reference gives it);
- ``torque.method``: ``given`` (``km_m``), ``curve`` (``thrust_n``/``thrust_g``,
  ``torque_nm``: OLS) or ``coefficients`` (``ct``, ``cp``);
- ``motor_dynamics``: ``rise_time_s`` or ``tau_up_s``; ``braking_factor`` (1.0)
  or ``tau_down_s``;
- ``command_map.type``: ``fractions`` (``min_frac`` 0.20, ``nmax_frac`` 0.95 of
  ω_max) or ``pwm_linear`` (``pwm_min_us``, ``pwm_max_us``, ``pwm_hover_us``,
  ``gain_rpm_per_us`` around the measured hover speed);
- exactly one of ``inertia`` (``ixx_kg_m2``... off-diagonals default 0) or
  ``shapes`` (``stack: {mass_kg | remainder, radius_m, components_kg}``,
  ``motor: {mass_kg, radius_m, height_m}``, optional ``arm: {mass_kg}``,
  ``prop: {mass_kg, diameter_m}``);
- ``significant_figures``: ``{quantity: digits}`` rounds a derived quantity
  where it is produced, so later steps use the rounded value (as the paper
  does with ω_max = 487 and τ_up = 0.023).

Pure functions raise ``ValueError`` on bad arguments; ``derive`` raises
:class:`~twin_nodes.base.errors.ParamsError` naming the spec file and key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from twin_nodes.base.errors import ParamsError
from twin_nodes.base.yamlio import read_yaml_file
from twin_nodes.vehicle.params import GRAVITY_DEFAULT, VehicleParams, _Reader, from_ros_dict

RPM_TO_RAD_S = 2.0 * math.pi / 60.0
INCH_M = 0.0254
#: 10→90 % rise time of a first-order lag is ln(9) τ = 2.197 τ; the paper uses 2.2.
RISE_TIME_FACTOR = 2.2
RHO_AIR_KG_M3 = 1.225


# =========================================================================== regression


def _as_1d(name: str, v: Any) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite")
    return a


def ols_through_origin(x: Sequence[float] | np.ndarray,
                       y: Sequence[float] | np.ndarray) -> tuple[float, float, float]:
    """Least squares of ``y = b x`` (no intercept), as the paper fits kt and km.

    Parameters
    ----------
    x, y : array_like, shape (n,)
        Regressor and response (any consistent units).

    Returns
    -------
    slope : float
        ``b = Σ x y / Σ x²`` [units of y / units of x].
    r2 : float
        **Uncentred** coefficient of determination, ``R² = 1 − SSres / Σ y²``,
        the definition that goes with a model without intercept (it is what
        R's ``lm(y ~ 0 + x)`` and statsmodels report).  It compares the fit
        with ``y = 0``, not with ``y = mean(y)``, so it is higher than the
        centred R² of the same data.
    stderr : float
        Standard error of the slope, ``sqrt(SSres / (n − 1) / Σ x²)``;
        NaN for a single point (n − 1 = 0 degrees of freedom).
    """
    xa, ya = _as_1d("x", x), _as_1d("y", y)
    if xa.shape != ya.shape:
        raise ValueError(f"x has {xa.size} points and y has {ya.size} points")
    if xa.size < 1:
        raise ValueError("need at least one point")
    sxx = float(xa @ xa)
    syy = float(ya @ ya)
    if sxx <= 0.0:
        raise ValueError("x is all zeros: the slope through the origin is undefined")
    slope = float(xa @ ya) / sxx
    resid = ya - slope * xa
    ss_res = float(resid @ resid)
    r2 = 1.0 - ss_res / syy if syy > 0.0 else float("nan")
    dof = xa.size - 1
    stderr = math.sqrt(ss_res / dof / sxx) if dof > 0 else float("nan")
    return slope, r2, stderr


def kt_from_thrust_curve(omega_rad_s: Sequence[float] | np.ndarray,
                         thrust_n: Sequence[float] | np.ndarray) -> tuple[float, float, float]:
    """Thrust coefficient from (ω, T) points: OLS of T [N] on x = ω² [(rad/s)²].

    Returns ``(kt [N/(rad/s)²], uncentred R², stderr of kt)``.
    """
    w = _as_1d("omega_rad_s", omega_rad_s)
    return ols_through_origin(w * w, thrust_n)


def km_from_torque_curve(thrust_n: Sequence[float] | np.ndarray,
                         torque_nm: Sequence[float] | np.ndarray) -> tuple[float, float, float]:
    """Moment coefficient from (T, Q) points: OLS of Q [N·m] on T [N].

    Returns ``(km [m], uncentred R², stderr of km)``.
    """
    return ols_through_origin(thrust_n, torque_nm)


# =========================================================================== propulsion


def _pos(name: str, v: float) -> float:
    v = float(v)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    return v


def scale_kt(kt1: float, d1_in: float, p1_in: float, d2_in: float, p2_in: float) -> float:
    """Similarity scaling of kt [N/(rad/s)²] to another prop of the same family.

    ``C_T = T/(ρ n² D⁴)``, ``kt = ρ C_T D⁴/(4π²)`` and ``C_T ∝ P/D`` give
    ``kt ∝ D³ P``, so ``kt2 = kt1 (D2/D1)³ (P2/P1)``.  Diameters and pitches in
    inches (only ratios matter).
    """
    kt1, d1, p1, d2, p2 = (_pos(n, v) for n, v in
                           (("kt1", kt1), ("d1_in", d1_in), ("p1_in", p1_in),
                            ("d2_in", d2_in), ("p2_in", p2_in)))
    return kt1 * (d2 / d1) ** 3 * (p2 / p1)


def scale_omega_max(omega_max1: float, kt1: float, kt2: float) -> float:
    """Max rotor speed [rad/s] for the same max thrust with the new prop: ``ω1 sqrt(kt1/kt2)``."""
    return _pos("omega_max1", omega_max1) * math.sqrt(_pos("kt1", kt1) / _pos("kt2", kt2))


def tau_from_rise_time(t_r_s: float) -> float:
    """First-order time constant [s] from a 10→90 % rise time [s]: ``τ = t_r / 2.2``."""
    return _pos("t_r_s", t_r_s) / RISE_TIME_FACTOR


def tau_down_from_braking(tau_up: float, factor: float = 1.2) -> float:
    """Slow-down time constant [s] = ``factor · τ_up`` (paper: braking 20 % slower)."""
    return _pos("factor", factor) * _pos("tau_up", tau_up)


def omega_limits(omega_max: float, min_frac: float = 0.20,
                 nmax_frac: float = 0.95) -> tuple[float, float]:
    """``(ω_min, ω_nmax)`` [rad/s]: where rotation starts and the normal-operation top.

    These are PX4's ``SIM_GZ_EC_MIN`` / ``SIM_GZ_EC_MAX`` (command 0 and 1).
    """
    omega_max = _pos("omega_max", omega_max)
    if not 0.0 <= min_frac < nmax_frac <= 1.0:
        raise ValueError(f"expected 0 <= min_frac < nmax_frac <= 1, got {min_frac}, {nmax_frac}")
    return min_frac * omega_max, nmax_frac * omega_max


def hover_omega(mass: float, kt: float, n_rotors: int = 4, g: float = GRAVITY_DEFAULT) -> float:
    """Rotor speed [rad/s] at which N rotors carry the weight: ``sqrt(m g / (N kt))``."""
    return math.sqrt(_pos("mass", mass) * _pos("g", g) / (int(n_rotors) * _pos("kt", kt)))


def hover_throttle(omega_hover: float, omega_min: float, omega_cmd_max: float) -> float:
    """Command u in [0, 1] that gives ``omega_hover`` on the linear map
    ``ω_ref = ω_min + u (ω_cmd_max − ω_min)`` (PX4 ``MPC_THR_HOVER`` with ``THR_MDL_FAC`` 0).
    """
    if not omega_cmd_max > omega_min:
        raise ValueError(f"expected omega_cmd_max > omega_min, got {omega_cmd_max} <= {omega_min}")
    return (float(omega_hover) - omega_min) / (omega_cmd_max - omega_min)


def thrust_to_weight(kt: float, omega: float, mass: float, n_rotors: int = 4,
                     g: float = GRAVITY_DEFAULT) -> float:
    """Thrust-to-weight ratio [-] with all N rotors at ``omega`` [rad/s]: ``N kt ω² / (m g)``."""
    return int(n_rotors) * _pos("kt", kt) * float(omega) ** 2 / (_pos("mass", mass) * _pos("g", g))


def kt_from_hover(mass: float, omega_hover: float, n_rotors: int = 4,
                  g: float = GRAVITY_DEFAULT) -> float:
    """Thrust coefficient [N/(rad/s)²] from the hover speed: ``kt = m g / (N ω_h²)`` (ref 2)."""
    w = _pos("omega_hover", omega_hover)
    return _pos("mass", mass) * _pos("g", g) / (int(n_rotors) * w * w)


def mass_from_hover(kt: float, omega_hover: float, n_rotors: int = 4,
                    g: float = GRAVITY_DEFAULT) -> float:
    """The mass [kg] that N rotors with ``kt`` carry at ``omega_hover``: ``N kt ω_h² / g``."""
    w = _pos("omega_hover", omega_hover)
    return int(n_rotors) * _pos("kt", kt) * w * w / _pos("g", g)


def kt_from_ct(ct: float, diameter_m: float, rho: float = RHO_AIR_KG_M3) -> float:
    """kt [N/(rad/s)²] from the propeller thrust coefficient ``C_T = T/(ρ n² D⁴)`` (n in rev/s)."""
    return _pos("rho", rho) * _pos("ct", ct) * _pos("diameter_m", diameter_m) ** 4 / (4.0 * math.pi ** 2)


def km_from_coefficients(ct: float, cp: float, diameter_m: float) -> float:
    """km = Q/T [m] from the propeller coefficients: ``Q = P/(2π n)`` gives ``km = C_P D/(2π C_T)``."""
    return _pos("cp", cp) * _pos("diameter_m", diameter_m) / (2.0 * math.pi * _pos("ct", ct))


def rpm_to_rad_s(rpm: float) -> float:
    """Revolutions per minute -> rad/s."""
    return float(rpm) * RPM_TO_RAD_S


# =========================================================================== geometry and inertia


def x_frame_positions(arm_length_m: float, n: int = 4,
                      z_m: float = 0.0) -> tuple[np.ndarray, tuple[int, ...]]:
    """Rotor positions of a symmetric X frame in PX4 motor order, body **FLU**.

    Returns ``(positions (n, 3) [m], directions)``: Motor1 front-right,
    Motor2 rear-left, Motor3 front-left, Motor4 rear-right, each at 45° and
    ``arm_length_m`` from the centre; directions +1 (CCW seen from above,
    ``CA_ROTORn_KM > 0``), +1, −1, −1 as PX4 airframe 4001 quad X.  Only
    quadrotors (n = 4) are supported.
    """
    if int(n) != 4:
        raise ValueError(f"only the quad X (n=4) layout is implemented, got n={n}")
    a = _pos("arm_length_m", arm_length_m) / math.sqrt(2.0)
    # (x forward, y left): front-right has y < 0 in FLU.
    pos = np.array([[a, -a, z_m], [-a, a, z_m], [a, a, z_m], [-a, -a, z_m]], dtype=float)
    return pos, (1, 1, -1, -1)


def composite_inertia(masses: Sequence[float], positions_m: np.ndarray,
                      own_inertias: Sequence[np.ndarray]) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass [kg], centre of mass (3,) [m] and inertia (3, 3) [kg m²] about it.

    Each part i has mass ``m_i``, centre ``r_i`` and inertia ``I_i`` about its
    own centre (body axes); parallel-axis (Huygens–Steiner) theorem:
    ``I = Σ I_i + m_i (|d_i|² E − d_i d_iᵀ)`` with ``d_i = r_i − r_com``.
    """
    m = np.asarray(masses, dtype=float)
    r = np.asarray(positions_m, dtype=float).reshape(-1, 3)
    if m.shape[0] != r.shape[0] or len(own_inertias) != m.shape[0]:
        raise ValueError("masses, positions and own inertias must have one entry per part")
    if np.any(m < 0) or m.sum() <= 0:
        raise ValueError("masses must be >= 0 with a positive total")
    total = float(m.sum())
    com = (m[:, None] * r).sum(axis=0) / total
    inertia = np.zeros((3, 3))
    for mi, ri, ii in zip(m, r, own_inertias):
        d = ri - com
        inertia += np.asarray(ii, dtype=float) + mi * (float(d @ d) * np.eye(3) - np.outer(d, d))
    return total, com, inertia


def hollow_sphere_inertia(mass: float, radius: float) -> np.ndarray:
    """Thin spherical shell about its centre: ``2/3 m r²`` on every axis."""
    return np.eye(3) * (2.0 / 3.0) * mass * radius * radius


def solid_cylinder_inertia(mass: float, radius: float, height: float) -> np.ndarray:
    """Solid cylinder with its axis along body z: ``Izz = m r²/2``, ``Ixx = Iyy = m (3r² + h²)/12``."""
    ixx = mass * (3.0 * radius * radius + height * height) / 12.0
    return np.diag([ixx, ixx, 0.5 * mass * radius * radius])


def thin_rod_inertia(mass: float, vector_m: np.ndarray) -> np.ndarray:
    """Thin rod along ``vector_m`` (its full length and direction) about its midpoint:
    ``m ℓ²/12 (E − d dᵀ)``."""
    v = np.asarray(vector_m, dtype=float)
    length = float(np.linalg.norm(v))
    if length == 0.0:
        return np.zeros((3, 3))
    d = v / length
    return mass * length * length / 12.0 * (np.eye(3) - np.outer(d, d))


def spinning_prop_inertia(mass: float, diameter: float) -> np.ndarray:
    """Two-blade prop as a thin rod of length D spinning about body z, averaged over the
    blade angle: ``Izz = m D²/12``, ``Ixx = Iyy = m D²/24``."""
    izz = mass * diameter * diameter / 12.0
    return np.diag([izz / 2.0, izz / 2.0, izz])


def inertia_from_shapes(rotor_positions_m: np.ndarray, *, stack_mass_kg: float,
                        stack_radius_m: float, motor_mass_kg: float, motor_radius_m: float,
                        motor_height_m: float, arm_mass_kg: float = 0.0,
                        prop_mass_kg: float = 0.0, prop_diameter_m: float = 0.0,
                        stack_center_m: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Inertia tensor (3, 3) [kg m², body axes] from simple shapes (reference 2).

    - central stack (autopilot, battery, ESCs, ...): hollow sphere, mass
      ``stack_mass_kg``, radius ``stack_radius_m``, centred at ``stack_center_m``;
    - each motor: solid cylinder with a vertical axis, moved to its rotor
      position (``rotor_positions_m``, shape (N, 3)) by the parallel-axis theorem;
    - optional arms: thin rods (``arm_mass_kg`` each) from the stack centre to each motor;
    - optional props: ``prop_mass_kg`` each, a spinning thin rod of length
      ``prop_diameter_m`` at each rotor (:func:`spinning_prop_inertia`).

    The tensor is about the composite centre of mass (the origin for a
    symmetric frame with the stack in the rotor plane).
    """
    rotors = np.asarray(rotor_positions_m, dtype=float).reshape(-1, 3)
    for name, v in (("stack_mass_kg", stack_mass_kg), ("stack_radius_m", stack_radius_m),
                    ("motor_mass_kg", motor_mass_kg), ("motor_radius_m", motor_radius_m),
                    ("motor_height_m", motor_height_m), ("arm_mass_kg", arm_mass_kg),
                    ("prop_mass_kg", prop_mass_kg), ("prop_diameter_m", prop_diameter_m)):
        if not (math.isfinite(float(v)) and float(v) >= 0.0):
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    c = np.asarray(stack_center_m, dtype=float).reshape(3)
    masses: list[float] = [stack_mass_kg]
    positions: list[np.ndarray] = [c]
    own: list[np.ndarray] = [hollow_sphere_inertia(stack_mass_kg, stack_radius_m)]
    for r in rotors:
        masses.append(motor_mass_kg)
        positions.append(r)
        own.append(solid_cylinder_inertia(motor_mass_kg, motor_radius_m, motor_height_m))
        if arm_mass_kg > 0.0:
            masses.append(arm_mass_kg)
            positions.append(0.5 * (c + r))
            own.append(thin_rod_inertia(arm_mass_kg, r - c))
        if prop_mass_kg > 0.0:
            masses.append(prop_mass_kg)
            positions.append(r)
            own.append(spinning_prop_inertia(prop_mass_kg, prop_diameter_m))
    _, _, inertia = composite_inertia(masses, np.array(positions), own)
    return inertia


def round_sig(x: float, digits: int) -> float:
    """``x`` rounded to ``digits`` significant figures."""
    if x == 0.0 or not math.isfinite(x):
        return x
    return round(x, digits - 1 - int(math.floor(math.log10(abs(x)))))


# =========================================================================== the spec pipeline


@dataclass(frozen=True)
class Step:
    """One derived quantity: value, unit and the formula with its numbers."""

    quantity: str
    value: float
    unit: str
    formula: str


@dataclass(frozen=True)
class Derivation:
    """What :func:`derive` returns: the validated params, every step, and notes."""

    params: VehicleParams
    steps: tuple[Step, ...]
    notes: tuple[str, ...] = ()

    def table(self) -> str:
        """The steps as an aligned text table (quantity, value, unit, formula)."""
        return format_steps(self.steps, self.notes)

    def value(self, quantity: str) -> float:
        """The final value of ``quantity`` (the last step that recorded it)."""
        for s in reversed(self.steps):
            if s.quantity == quantity:
                return s.value
        raise KeyError(quantity)


def format_steps(steps: Sequence[Step], notes: Sequence[str] = ()) -> str:
    rows = [(s.quantity, f"{s.value:.6g}", s.unit, s.formula) for s in steps]
    head = ("quantity", "value", "unit", "formula")
    w = [max(len(r[i]) for r in rows + [head]) for i in range(3)]
    lines = [f"{head[0]:<{w[0]}}  {head[1]:>{w[1]}}  {head[2]:<{w[2]}}  {head[3]}",
             f"{'-' * w[0]}  {'-' * w[1]}  {'-' * w[2]}  {'-' * 7}"]
    lines += [f"{q:<{w[0]}}  {v:>{w[1]}}  {u:<{w[2]}}  {f}" for q, v, u, f in rows]
    lines += [f"note: {n}" for n in notes]
    return "\n".join(lines)


SPEC_KEYS = {"name", "gravity_m_s2", "mass_kg", "hover", "inertia", "shapes", "frame",
             "propeller", "thrust", "speed", "torque", "motor_dynamics", "command_map",
             "significant_figures", "dt_s", "notes"}


def load_spec(path: str | Path) -> dict[str, Any]:
    """Read a derivation spec (a plain YAML mapping); ParamsError naming the file otherwise."""
    path = str(path)
    doc = read_yaml_file(path, "derivation spec YAML file")
    if not isinstance(doc, Mapping):
        raise ParamsError(path, "<top>", "expected a YAML mapping (a derivation spec)")
    return dict(doc)


class _Pipeline:
    """One run of the derivation over a spec; records steps as it goes."""

    def __init__(self, spec: Mapping[str, Any], path: str):
        self.path = path
        self.top = _Reader(path, spec)
        self.steps: list[Step] = []
        self.notes: list[str] = []
        sig = self.top.sub("significant_figures", required=False)
        self.sig: dict[str, int] = {}
        for k, v in sig.data.items():
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 15:
                raise sig.err(str(k), f"expected an integer number of significant figures 1..15, got {v!r}")
            self.sig[str(k)] = v

    def rec(self, quantity: str, value: float, unit: str, formula: str) -> float:
        """Record a step; round to the spec's significant figures if asked (downstream
        steps then use the rounded value, as the paper does)."""
        value = float(value)
        if quantity in self.sig:
            rounded = round_sig(value, self.sig[quantity])
            if rounded != value:
                formula = f"{formula} = {value:.6g}, rounded to {self.sig[quantity]} s.f."
            value = rounded
        self.steps.append(Step(quantity, value, unit, formula))
        return value

    def fail(self, reader: _Reader, key: str, exc: Exception) -> ParamsError:
        return reader.err(key, str(exc))

    # ------------------------------------------------------------------ sections

    def curve(self, r: _Reader, xkeys: tuple[tuple[str, float], ...],
              ykeys: tuple[tuple[str, float], ...]) -> tuple[np.ndarray, np.ndarray, str, str]:
        """Read one x list and one y list, each given under exactly one unit key."""
        def pick(options: tuple[tuple[str, float], ...]) -> tuple[np.ndarray, str]:
            present = [k for k, _ in options if k in r.data]
            if len(present) != 1:
                raise r.err(options[0][0], f"expected exactly one of {', '.join(k for k, _ in options)}")
            k = present[0]
            scale = dict(options)[k]
            return np.array(r.nums(k), dtype=float) * scale, k
        x, kx = pick(xkeys)
        y, ky = pick(ykeys)
        if x.size != y.size:
            raise r.err(ky, f"expected {x.size} values (one per {kx} point), got {y.size}")
        if x.size < 1:
            raise r.err(kx, "expected at least one data point")
        return x, y, kx, ky

    def run(self) -> Derivation:
        top = self.top
        top.unknown(SPEC_KEYS)
        name = top.text("name", "vehicle")
        top.text("notes", "")  # free text for the params file header; only its type is checked
        g = top.num("gravity_m_s2", GRAVITY_DEFAULT, gt=0.0)

        # ---- frame
        fr = top.sub("frame")
        fr.unknown({"type", "arm_length_m", "rotor_z_m"})
        fr.text("type", "quad_x", ("quad_x",))
        arm = self.rec("arm_length_m", fr.num("arm_length_m", gt=0.0), "m", "spec (centre to rotor axis)")
        rotor_z = fr.num("rotor_z_m", 0.0)
        positions, directions = x_frame_positions(arm, 4, rotor_z)
        n = len(directions)

        # ---- propeller (needed for similarity scaling, coefficients and prop inertia)
        pr = top.sub("propeller", required=False)
        pr.unknown({"diameter_in", "pitch_in"})
        d_in = pr.num("diameter_in", gt=0.0) if "diameter_in" in pr.data else None
        p_in = pr.num("pitch_in", gt=0.0) if "pitch_in" in pr.data else None

        # ---- measured hover speed (optional)
        hv = top.sub("hover", required=False)
        hv.unknown({"rpm", "omega_rad_s"})
        omega_h_meas = None
        if "rpm" in hv.data and "omega_rad_s" in hv.data:
            raise hv.err("rpm", "give either rpm or omega_rad_s, not both")
        if "rpm" in hv.data:
            rpm = hv.num("rpm", gt=0.0)
            omega_h_meas = self.rec("omega_hover_measured_rad_s", rpm * RPM_TO_RAD_S, "rad/s",
                                    f"{rpm:g} rpm × 2π/60")
        elif "omega_rad_s" in hv.data:
            omega_h_meas = self.rec("omega_hover_measured_rad_s", hv.num("omega_rad_s", gt=0.0),
                                    "rad/s", "spec")

        # ---- mass (a number, or derived from kt and the hover speed further down)
        mass_from_hover_flag = top.data.get("mass_kg") == "from_hover"
        mass = None if mass_from_hover_flag else self.rec("mass_kg", top.num("mass_kg", gt=0.0), "kg", "spec")

        # ---- speed limit given directly (optional)
        sp = top.sub("speed", required=False)
        sp.unknown({"omega_max_rad_s", "rpm_max"})
        if "omega_max_rad_s" in sp.data and "rpm_max" in sp.data:
            raise sp.err("rpm_max", "give either rpm_max or omega_max_rad_s, not both")
        omega_max = None
        if "rpm_max" in sp.data:
            rpm_max = sp.num("rpm_max", gt=0.0)
            omega_max = self.rec("omega_max_rad_s", rpm_max * RPM_TO_RAD_S, "rad/s", f"{rpm_max:g} rpm × 2π/60")
        elif "omega_max_rad_s" in sp.data:
            omega_max = self.rec("omega_max_rad_s", sp.num("omega_max_rad_s", gt=0.0), "rad/s", "spec")

        # ---- thrust coefficient
        th = top.sub("thrust")
        method = th.text("method", None, ("reference", "curve", "given", "from_hover"))
        if method == "reference":
            th.unknown({"method", "kt_ref_n_s2_rad2", "diameter_ref_in", "pitch_ref_in",
                        "omega_max_ref_rad_s"})
            if d_in is None or p_in is None:
                raise top.err("propeller", "thrust.method reference needs propeller.diameter_in and pitch_in")
            kt1 = th.num("kt_ref_n_s2_rad2", gt=0.0)
            d1 = th.num("diameter_ref_in", gt=0.0)
            p1 = th.num("pitch_ref_in", gt=0.0)
            kt = self.rec("kt_n_s2_rad2", scale_kt(kt1, d1, p1, d_in, p_in), "N/(rad/s)^2",
                          f"kt1 (D2/D1)^3 (P2/P1) = {kt1:g} ({d_in:g}/{d1:g})^3 ({p_in:g}/{p1:g})")
            if "omega_max_ref_rad_s" in th.data:
                if omega_max is not None:
                    raise th.err("omega_max_ref_rad_s", "speed limit given twice (also in speed:)")
                w1 = th.num("omega_max_ref_rad_s", gt=0.0)
                omega_max = self.rec("omega_max_rad_s", scale_omega_max(w1, kt1, kt), "rad/s",
                                     f"w1 sqrt(kt1/kt2) = {w1:g} sqrt({kt1:g}/{kt:.5g})")
        elif method == "curve":
            th.unknown({"method", "omega_rad_s", "rpm", "thrust_n", "thrust_g"})
            w, t, kx, ky = self.curve(th, (("omega_rad_s", 1.0), ("rpm", RPM_TO_RAD_S)),
                                      (("thrust_n", 1.0), ("thrust_g", g / 1000.0)))
            try:
                kt_fit, r2, se = kt_from_thrust_curve(w, t)
            except ValueError as exc:
                raise self.fail(th, kx, exc) from None
            kt = self.rec("kt_n_s2_rad2", kt_fit, "N/(rad/s)^2",
                          f"OLS through origin of T on w^2, {w.size} point(s) from {kx}/{ky}")
            if w.size > 1:
                self.rec("kt_fit_r2", r2, "-", "uncentred R^2 = 1 - SSres/sum(T^2)")
                self.rec("kt_fit_stderr", se, "N/(rad/s)^2", "sqrt(SSres/(n-1)/sum(w^4))")
        elif method == "given":
            th.unknown({"method", "kt_n_s2_rad2"})
            kt = self.rec("kt_n_s2_rad2", th.num("kt_n_s2_rad2", gt=0.0), "N/(rad/s)^2", "spec")
        else:  # from_hover
            th.unknown({"method"})
            if mass is None or omega_h_meas is None:
                raise th.err("method", "from_hover needs a numeric mass_kg and hover.rpm or hover.omega_rad_s")
            kt = self.rec("kt_n_s2_rad2", kt_from_hover(mass, omega_h_meas, n, g), "N/(rad/s)^2",
                          f"m g / (N w_h^2) = {mass:g}·{g:g} / ({n}·{omega_h_meas:.5g}^2)")

        if mass is None:
            if omega_h_meas is None:
                raise top.err("mass_kg", "from_hover needs hover.rpm or hover.omega_rad_s")
            if method == "from_hover":
                raise top.err("mass_kg", "from_hover needs a thrust.method other than from_hover")
            mass = self.rec("mass_kg", mass_from_hover(kt, omega_h_meas, n, g), "kg",
                            f"N kt w_h^2 / g = {n}·{kt:.5g}·{omega_h_meas:.5g}^2 / {g:g}")

        # ---- reaction torque coefficient
        tq = top.sub("torque")
        tmethod = tq.text("method", None, ("given", "curve", "coefficients"))
        if tmethod == "given":
            tq.unknown({"method", "km_m"})
            km = self.rec("km_m", tq.num("km_m", ge=0.0), "m", "spec")
        elif tmethod == "curve":
            tq.unknown({"method", "thrust_n", "thrust_g", "torque_nm"})
            t, q, kx, _ = self.curve(tq, (("thrust_n", 1.0), ("thrust_g", g / 1000.0)),
                                     (("torque_nm", 1.0),))
            try:
                km_fit, r2, se = km_from_torque_curve(t, q)
            except ValueError as exc:
                raise self.fail(tq, kx, exc) from None
            km = self.rec("km_m", km_fit, "m", f"OLS through origin of Q on T, {t.size} point(s)")
            if t.size > 1:
                self.rec("km_fit_r2", r2, "-", "uncentred R^2 = 1 - SSres/sum(Q^2)")
                self.rec("km_fit_stderr", se, "m", "sqrt(SSres/(n-1)/sum(T^2))")
        else:
            tq.unknown({"method", "ct", "cp"})
            if d_in is None:
                raise top.err("propeller", "torque.method coefficients needs propeller.diameter_in")
            ct, cp = tq.num("ct", gt=0.0), tq.num("cp", gt=0.0)
            km = self.rec("km_m", km_from_coefficients(ct, cp, d_in * INCH_M), "m",
                          f"C_P D / (2π C_T) = {cp:g}·{d_in * INCH_M:.4g} / (2π·{ct:g})")
            self.rec("kt_from_ct_check_n_s2_rad2", kt_from_ct(ct, d_in * INCH_M), "N/(rad/s)^2",
                     f"cross-check only: rho C_T D^4 / (4π^2), rho {RHO_AIR_KG_M3}")

        # ---- rotor lag
        md = top.sub("motor_dynamics")
        md.unknown({"rise_time_s", "braking_factor", "tau_up_s", "tau_down_s"})
        if "rise_time_s" in md.data:
            if "tau_up_s" in md.data:
                raise md.err("tau_up_s", "give either rise_time_s or tau_up_s, not both")
            tr = md.num("rise_time_s", gt=0.0)
            tau_up = self.rec("tau_up_s", tau_from_rise_time(tr), "s", f"t_r / 2.2 = {tr:g} / 2.2")
        else:
            tau_up = self.rec("tau_up_s", md.num("tau_up_s", gt=0.0), "s", "spec")
        if "tau_down_s" in md.data:
            if "braking_factor" in md.data:
                raise md.err("braking_factor", "give either braking_factor or tau_down_s, not both")
            tau_down = self.rec("tau_down_s", md.num("tau_down_s", gt=0.0), "s", "spec")
        else:
            f = md.num("braking_factor", 1.0, gt=0.0)
            tau_down = self.rec("tau_down_s", tau_down_from_braking(tau_up, f), "s",
                                f"{f:g} tau_up = {f:g}·{tau_up:g}")

        # ---- command map u in [0, 1] -> omega_ref
        cm = top.sub("command_map")
        ctype = cm.text("type", None, ("fractions", "pwm_linear"))
        if ctype == "fractions":
            cm.unknown({"type", "min_frac", "nmax_frac"})
            if omega_max is None:
                raise cm.err("type", "fractions need omega_max (speed.rpm_max, speed.omega_max_rad_s "
                             "or thrust.omega_max_ref_rad_s)")
            fmin = cm.num("min_frac", 0.20, ge=0.0)
            fmax = cm.num("nmax_frac", 0.95, le=1.0)
            if not fmin < fmax:
                raise cm.err("min_frac", f"expected min_frac < nmax_frac, got {fmin:g} >= {fmax:g}")
            wmin, wcmd = omega_limits(omega_max, fmin, fmax)
            wmin = self.rec("omega_min_rad_s", wmin, "rad/s", f"{fmin:g} omega_max = {fmin:g}·{omega_max:g}")
            wcmd = self.rec("omega_cmd_max_rad_s", wcmd, "rad/s", f"{fmax:g} omega_max = {fmax:g}·{omega_max:g}")
        else:
            cm.unknown({"type", "pwm_min_us", "pwm_max_us", "pwm_hover_us", "gain_rpm_per_us"})
            if omega_h_meas is None:
                raise cm.err("type", "pwm_linear needs hover.rpm or hover.omega_rad_s (the speed at pwm_hover_us)")
            pmin = cm.num("pwm_min_us", gt=0.0)
            pmax = cm.num("pwm_max_us", gt=0.0)
            phov = cm.num("pwm_hover_us", gt=0.0)
            gain = cm.num("gain_rpm_per_us", gt=0.0)
            if not pmin < phov < pmax:
                raise cm.err("pwm_hover_us", f"expected pwm_min_us < pwm_hover_us < pwm_max_us, "
                             f"got {pmin:g}, {phov:g}, {pmax:g}")
            k = gain * RPM_TO_RAD_S
            wmin = omega_h_meas + k * (pmin - phov)
            if wmin < 0.0:
                raise cm.err("gain_rpm_per_us",
                             f"the linear map gives a negative speed at pwm_min_us ({wmin:.4g} rad/s)")
            wmin = self.rec("omega_min_rad_s", wmin, "rad/s",
                            f"w_h + gain (pwm_min - pwm_h) = {omega_h_meas:.5g} + {gain:g}·2π/60·({pmin:g} - {phov:g})")
            wcmd = self.rec("omega_cmd_max_rad_s", omega_h_meas + k * (pmax - phov), "rad/s",
                            f"w_h + gain (pwm_max - pwm_h) = {omega_h_meas:.5g} + {gain:g}·2π/60·({pmax:g} - {phov:g})")
            if omega_max is None:
                omega_max = self.rec("omega_max_rad_s", wcmd, "rad/s", "= omega_cmd_max (no separate limit given)")
            elif wcmd > omega_max:
                self.notes.append(
                    f"the linear PWM map reaches {wcmd:.5g} rad/s at pwm_max_us, {100 * (wcmd / omega_max - 1):.2g} % "
                    f"above the stated maximum {omega_max:.5g} rad/s; omega_max raised to the map's top "
                    f"(the params schema needs omega_cmd_max <= omega_max)")
                omega_max = self.rec("omega_max_rad_s", wcmd, "rad/s", "= omega_cmd_max (map top above stated max)")

        if omega_max is None:  # pragma: no cover - every branch above sets it or raises
            raise top.err("speed", "missing omega_max")
        if not wmin < wcmd <= omega_max:
            raise cm.err("type", f"expected omega_min < omega_cmd_max <= omega_max, got "
                         f"{wmin:.5g}, {wcmd:.5g}, {omega_max:.5g} rad/s")

        # ---- inertia
        inertia = self.inertia(top, positions, mass, d_in)

        # ---- derived checks
        wh = self.rec("omega_hover_rad_s", hover_omega(mass, kt, n, g), "rad/s",
                      f"sqrt(m g / (N kt)) = sqrt({mass:.5g}·{g:g} / ({n}·{kt:.5g}))")
        self.rec("omega_hover_rpm", wh / RPM_TO_RAD_S, "rpm", "omega_hover × 60/2π")
        if omega_h_meas is not None and not mass_from_hover_flag and method != "from_hover":
            dev = wh / omega_h_meas - 1.0
            self.notes.append(f"computed hover speed {wh:.5g} rad/s vs measured {omega_h_meas:.5g} rad/s "
                              f"({100 * dev:+.2g} %)")
        uh = self.rec("hover_throttle", hover_throttle(wh, wmin, wcmd), "-",
                      f"(w_h - w_min)/(w_cmd_max - w_min) = ({wh:.5g} - {wmin:g})/({wcmd:g} - {wmin:g})")
        if not 0.0 < uh < 1.0:
            raise top.err("mass_kg", f"hover needs command {uh:.3g}, outside (0, 1): the rotors cannot "
                          "hover this vehicle on this command map")
        self.rec("thrust_to_weight_at_cmd_max", thrust_to_weight(kt, wcmd, mass, n, g), "-",
                 f"N kt w_cmd_max^2 / (m g) = {n}·{kt:.5g}·{wcmd:.5g}^2 / ({mass:.5g}·{g:g})")

        unused = set(self.sig) - {s.quantity for s in self.steps}
        if unused:
            k = sorted(unused)[0]
            raise ParamsError(self.path, f"significant_figures.{k}",
                              f"not a derived quantity (derived: {', '.join(s.quantity for s in self.steps)})")

        ros = {
            "vehicle": {
                "name": name, "mass_kg": mass,
                "ixx_kg_m2": float(inertia[0, 0]), "iyy_kg_m2": float(inertia[1, 1]),
                "izz_kg_m2": float(inertia[2, 2]), "ixy_kg_m2": float(inertia[0, 1]),
                "ixz_kg_m2": float(inertia[0, 2]), "iyz_kg_m2": float(inertia[1, 2]),
                "gravity_m_s2": g, "arm_length_m": arm,
            },
            "rotors": {
                "x_flu_m": [float(v) for v in positions[:, 0]],
                "y_flu_m": [float(v) for v in positions[:, 1]],
                "z_flu_m": [float(v) for v in positions[:, 2]],
                "direction": list(directions), "thrust_model": "omega_squared",
                "kt_n_s2_rad2": kt, "km_m": km, "omega_min_rad_s": wmin,
                "omega_cmd_max_rad_s": wcmd, "omega_max_rad_s": omega_max,
                "tau_up_s": tau_up, "tau_down_s": tau_down,
            },
            "effects": {"enabled": []},
            "simulation": {"dt_s": top.num("dt_s", 0.001, gt=0.0, le=0.1)},
        }
        vp = from_ros_dict(ros, self.path)
        return Derivation(vp, tuple(self.steps), tuple(self.notes))

    def inertia(self, top: _Reader, positions: np.ndarray, mass: float, d_in: float | None) -> np.ndarray:
        has_i, has_s = "inertia" in top.data, "shapes" in top.data
        if has_i == has_s:
            raise top.err("inertia", "give exactly one of inertia (ixx/iyy/izz...) or shapes")
        keys = ("ixx_kg_m2", "iyy_kg_m2", "izz_kg_m2", "ixy_kg_m2", "ixz_kg_m2", "iyz_kg_m2")
        if has_i:
            ir = top.sub("inertia")
            ir.unknown(set(keys))
            vals = {}
            for k in keys:
                diagonal = k in ("ixx_kg_m2", "iyy_kg_m2", "izz_kg_m2")
                v = ir.num(k, gt=0.0) if diagonal else ir.num(k, 0.0)
                vals[k] = self.rec(k, v, "kg m^2", "spec")
        else:
            sh = top.sub("shapes")
            sh.unknown({"stack", "motor", "arm", "prop"})
            st = sh.sub("stack")
            st.unknown({"mass_kg", "radius_m", "components_kg"})
            mo = sh.sub("motor")
            mo.unknown({"mass_kg", "radius_m", "height_m"})
            ar = sh.sub("arm", required=False)
            ar.unknown({"mass_kg"})
            pp = sh.sub("prop", required=False)
            pp.unknown({"mass_kg", "diameter_m"})
            n = positions.shape[0]
            m_motor = mo.num("mass_kg", gt=0.0)
            m_arm = ar.num("mass_kg", 0.0, ge=0.0)
            m_prop = pp.num("mass_kg", 0.0, ge=0.0)
            d_prop = pp.num("diameter_m", d_in * INCH_M if d_in is not None else 0.0, ge=0.0)
            if m_prop > 0.0 and d_prop <= 0.0:
                raise pp.err("diameter_m", "prop mass given but no diameter (prop.diameter_m or propeller.diameter_in)")
            others = n * (m_motor + m_arm + m_prop)
            if st.data.get("mass_kg") == "remainder":
                m_stack = mass - others
                if m_stack <= 0.0:
                    raise st.err("mass_kg", f"remainder is {m_stack:.4g} kg: motors, arms and props "
                                 f"({others:.4g} kg) weigh more than the vehicle ({mass:.4g} kg)")
                m_stack = self.rec("stack_mass_kg", m_stack, "kg",
                                   f"m - N (m_motor + m_arm + m_prop) = {mass:.5g} - "
                                   f"{n}·({m_motor:g} + {m_arm:g} + {m_prop:g})")
            else:
                m_stack = self.rec("stack_mass_kg", st.num("mass_kg", gt=0.0), "kg", "spec")
                total = m_stack + others
                if abs(total / mass - 1.0) > 0.05:
                    raise st.err("mass_kg", f"shapes weigh {total:.4g} kg but mass_kg is {mass:.4g} kg "
                                 "(more than 5 % apart); use mass_kg: remainder or fix the masses")
            if "components_kg" in st.data:
                comp = st.sub("components_kg")
                listed = 0.0
                for k in comp.data:
                    listed += comp.num(str(k), ge=0.0)
                if listed > m_stack * 1.02:
                    raise st.err("components_kg",
                                 f"listed stack components weigh {listed:.4g} kg, more than the stack "
                                   f"mass {m_stack:.4g} kg")
                self.rec("stack_unlisted_kg", m_stack - listed, "kg",
                         f"stack mass - listed components = {m_stack:.4g} - {listed:.4g}")
            r_stack = st.num("radius_m", gt=0.0)
            try:
                t = inertia_from_shapes(positions, stack_mass_kg=m_stack, stack_radius_m=r_stack,
                                        motor_mass_kg=m_motor, motor_radius_m=mo.num("radius_m", gt=0.0),
                                        motor_height_m=mo.num("height_m", gt=0.0), arm_mass_kg=m_arm,
                                        prop_mass_kg=m_prop, prop_diameter_m=d_prop)
            except ValueError as exc:
                raise sh.err("stack", str(exc)) from None
            formula = ("hollow sphere 2/3 m r^2 + cylinder motors (3r^2+h^2)/12, r^2/2 "
                       "+ parallel axis m d^2" + (" + rod arms" if m_arm else "") + (" + props" if m_prop else ""))
            vals = {}
            for k, (i, j) in zip(keys, ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
                v = float(t[i, j])
                if abs(v) < 1e-15:
                    v = 0.0
                vals[k] = self.rec(k, v, "kg m^2", formula if i == j else "off-diagonal of the same sum")
        return np.array([[vals["ixx_kg_m2"], vals["ixy_kg_m2"], vals["ixz_kg_m2"]],
                         [vals["ixy_kg_m2"], vals["iyy_kg_m2"], vals["iyz_kg_m2"]],
                         [vals["ixz_kg_m2"], vals["iyz_kg_m2"], vals["izz_kg_m2"]]])


def derive(spec: Mapping[str, Any], path: str = "<spec>") -> Derivation:
    """Run the pipeline on a derivation spec mapping; see the module docstring.

    Raises :class:`ParamsError` ``"<path>: <key>: <expected>"`` on bad input.
    """
    if not isinstance(spec, Mapping):
        raise ParamsError(path, "<top>", "expected a mapping (a derivation spec)")
    if "ros__parameters" in spec or any(isinstance(v, Mapping) and "ros__parameters" in v
                                        for v in spec.values()):
        raise ParamsError(path, "ros__parameters", "this is a params file, not a derivation spec "
                          "(use `rotortwin params check` / `export` on it)")
    return _Pipeline(spec, str(path)).run()


def derive_params(spec: Mapping[str, Any], path: str = "<spec>") -> VehicleParams:
    """Like :func:`derive` but only the validated :class:`VehicleParams`."""
    return derive(spec, path).params


def derive_file(path: str | Path) -> Derivation:
    """:func:`load_spec` then :func:`derive`."""
    return derive(load_spec(path), str(path))


def derivation_header(d: Derivation, spec_path: str, notes: str = "") -> str:
    """Comment header for a derived params file: origin, free-text notes, the step table."""
    lines = [f"Derived by `rotortwin params derive {spec_path}`; do not edit by hand, edit the spec and re-run.", ""]
    if notes:
        lines += notes.rstrip().splitlines() + [""]
    lines += d.table().splitlines()
    return "\n".join(lines)


__all__ = [
    "Derivation", "Step", "composite_inertia", "derivation_header", "derive", "derive_file",
    "derive_params", "format_steps", "hollow_sphere_inertia", "hover_omega", "hover_throttle",
    "inertia_from_shapes", "kt_from_ct", "kt_from_hover", "kt_from_thrust_curve",
    "km_from_coefficients", "km_from_torque_curve", "load_spec", "mass_from_hover",
    "ols_through_origin", "omega_limits", "round_sig", "rpm_to_rad_s", "scale_kt",
    "scale_omega_max", "solid_cylinder_inertia", "spinning_prop_inertia", "tau_down_from_braking",
    "tau_from_rise_time", "thin_rod_inertia", "thrust_to_weight", "x_frame_positions",
]
