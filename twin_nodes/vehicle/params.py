"""Vehicle parameter files: schema, validation and YAML I/O.

A parameter file is ROS 2 ``ros__parameters`` YAML, so the same file can be
handed to a node with ``--ros-args --params-file``::

    /**:
      ros__parameters:
        vehicle:   {name, mass_kg, ixx_kg_m2, ..., gravity_m_s2}
        rotors:    {x_flu_m: [...], y_flu_m: [...], z_flu_m: [...], direction: [...],
                    thrust_model, kt_n_s2_rad2, km_m, omega_*_rad_s, tau_up_s, tau_down_s, ...}
        effects:   {enabled: [names...], <name>: {<param>: value}}
        controller: {...}      # law (px4: PX4-like cascade, twin_nodes.twin.control; se3: geometric SE(3), twin.control_se3) and gains
        sensors:    {...}      # noise/bias model for the simulator link
        simulation: {dt_s: 0.001}

Frames: rotor positions are body **FLU** (ROS REP-103).  ``direction`` is +1 for
a rotor spinning counter-clockwise seen from above (PX4 ``CA_ROTORn_KM > 0``)
and -1 for clockwise.  Motor order is PX4's (Motor1 = index 0).

Every value carries its unit in its name.  ``load_params`` validates everything
and raises :class:`~twin_nodes.base.errors.ParamsError` whose message names the
file, the key and what was expected.

Physical ranges (:data:`LIMITS`; anything outside is a typo or a corrupt file,
and some values would hang or overflow the simulator): mass 1e-3..1e4 kg;
principal inertia positive with a radius of gyration sqrt(I/m) of 1 mm up to
max(1 m, 3 x the farthest rotor's distance); rotor positions within 100 m of the
centre of mass, spanning roll and pitch (the RMS spread of the rotors about their
centroid along the weakest horizontal axis at least 1 mm: a layout with no moment arm
about some axis cannot be flown); 1..32 rotors; thrust per rotor at full command
1e-4..1e6 N (``thrust_max_n`` too); kt 1e-12..1e6 N s^2/rad^2; km 1e-4..1 m; rotor
speeds up to 1e5 rad/s, the top speeds (``omega_cmd_max_rad_s``, ``omega_max_rad_s``)
at least 1 rad/s; time constants 0..10 s; gravity 0.1..100 m/s^2;
``simulation.dt_s`` 1e-5..0.1 s; the ``controller`` gains in
:data:`CONTROLLER_LIMITS`; every number (also in ``sensors``) finite; effect
parameters finite and in their effect's range
(:attr:`twin_nodes.physics.effects.Effect.ranges`), motor indices within the rotor
count.  A params file must be a regular UTF-8 file of at most 1 MB, without
duplicate keys (:mod:`twin_nodes.base.yamlio`).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from twin_nodes.base.constants import G_STANDARD_M_S2
from twin_nodes.base.errors import ParamsError
from twin_nodes.base.yamlio import read_yaml_file, safe_load
from twin_nodes.physics.effects import EFFECTS

THRUST_MODELS = ("omega_squared", "thrust_factor")
GRAVITY_DEFAULT = G_STANDARD_M_S2

#: physical ranges checked on load and by :func:`validate` (see the module docstring)
LIMITS = {
    "mass_kg": (1e-3, 1e4),
    "gyration_min_m": 1e-3,        # sqrt(I/m) lower bound
    "gyration_max_floor_m": 1.0,   # sqrt(I/m) upper bound: max(this, 3 x farthest rotor)
    "position_m": 100.0,           # |rotor position| upper bound
    "rotors": (1, 32),
    "thrust_max_n": 1e6,           # per rotor, at full command
    "thrust_min_n": 1e-4,          # per rotor, at full command (and thrust_max_n)
    "kt_n_s2_rad2": (1e-12, 1e6),
    "km_m": (1e-4, 1.0),
    "omega_rad_s": 1e5,
    "omega_top_min_rad_s": 1.0,    # omega_cmd_max / omega_max lower bound (they divide)
    "span_m": 1e-3,                # rotor positions' RMS spread along the weakest horizontal axis
    "tau_s": (0.0, 10.0),
    "gravity_m_s2": (0.1, 100.0),
    "dt_s": (1e-5, 0.1),
}
#: most values in a params file's free-form blocks (controller, sensors); the largest YAML file
#: read is twin_nodes.base.yamlio.MAX_FILE_BYTES
MAX_VALUES = 10_000

#: ``controller:`` gains (twin_nodes.twin.control.ControllerGains) -> (lo, hi, lo excluded, unit):
#: PX4's own parameter ranges, widened (the twin's rate gains are physical, so they scale with the
#: vehicle); a key not listed here is checked by ControllerGains.from_params
_GAIN = (0.0, 1e5, False, "")
CONTROLLER_LIMITS: dict[str, tuple[float, float, bool, str]] = {
    "rate_hz": (1.0, 10000.0, False, "Hz"),
    **{k: _GAIN for k in ("xy_p_1_s", "z_p_1_s", "xy_vel_p_1_s", "xy_vel_i_1_s2", "xy_vel_d", "z_vel_p_1_s",
                          "z_vel_i_1_s2", "z_vel_d", "roll_p_1_s", "pitch_p_1_s", "yaw_p_1_s", "rate_p_1_s",
                          "rate_i_1_s2", "rate_d", "yawrate_p_1_s", "yawrate_i_1_s2", "rate_i_max_rad_s2",
                          "pitchrate_i_max_rad_s2", "yawrate_i_max_rad_s2",
                          "vel_i_max_m_s2", "se3_kp_xy_1_s2", "se3_kp_z_1_s2", "se3_kd_xy_1_s", "se3_kd_z_1_s",
                          "se3_kp_att_1_s2", "se3_kd_att_1_s")},
    "xy_vel_max_m_s": (0.0, 1000.0, False, "m/s"),
    "z_vel_max_up_m_s": (0.0, 1000.0, False, "m/s"),
    "z_vel_max_dn_m_s": (0.0, 1000.0, False, "m/s"),
    "tilt_max_deg": (0.0, 89.0, True, "deg"),
    "thr_min": (0.0, 1.0, False, "of full thrust"),
    "thr_max": (0.0, 1.0, True, "of full thrust"),
    "yaw_weight": (0.0, 1.0, False, ""),
    "rollrate_max_deg_s": (0.0, 36000.0, True, "deg/s"),
    "yawrate_max_deg_s": (0.0, 36000.0, True, "deg/s"),
}


@dataclass(frozen=True)
class RotorParams:
    """Propulsion: geometry, command map, lag and thrust law of the N rotors.

    ``thrust_model``:

    - ``omega_squared`` (Gazebo MulticopterMotorModel, the Búho Negro paper):
      command u in [0, 1] -> reference speed
      ``omega_ref = omega_min + u (omega_cmd_max - omega_min)`` (u = NaN: motor
      stopped, omega_ref = 0), first-order lag with tau_up/tau_down on omega,
      saturation at omega_max, ``T = kt omega^2``.
    - ``thrust_factor`` (PX4 SIH, PX4 ``THR_MDL_FAC``): the lag acts on the
      normalised command s; ``T = thrust_max (f s^2 + (1 - f) s)``.
      ``omega`` is reported as ``omega_max sqrt(T / thrust_max)``.

    In both, the rotor reaction torque is ``Q = km T``.
    """

    x_flu_m: tuple[float, ...]
    y_flu_m: tuple[float, ...]
    z_flu_m: tuple[float, ...]
    direction: tuple[int, ...]
    thrust_model: str
    kt_n_s2_rad2: float
    km_m: float
    omega_min_rad_s: float
    omega_cmd_max_rad_s: float
    omega_max_rad_s: float
    tau_up_s: float
    tau_down_s: float
    thrust_max_n: float
    thr_mdl_fac: float

    @property
    def count(self) -> int:
        return len(self.x_flu_m)

    @property
    def positions_flu_m(self) -> np.ndarray:
        """Rotor positions, shape (N, 3), body FLU [m]."""
        return np.column_stack([self.x_flu_m, self.y_flu_m, self.z_flu_m]).astype(float)

    def thrust_from_state(self, s: np.ndarray) -> np.ndarray:
        """Per-rotor thrust [N] from the lagged rotor state (omega [rad/s] or s [-])."""
        s = np.asarray(s, dtype=float)
        if self.thrust_model == "omega_squared":
            return self.kt_n_s2_rad2 * s * s
        f = self.thr_mdl_fac
        return self.thrust_max_n * (f * s * s + (1.0 - f) * s)

    def reference_from_command(self, u: np.ndarray) -> np.ndarray:
        """Steady-state rotor state for command u in [0, 1] (NaN -> stopped)."""
        u = np.asarray(u, dtype=float)
        stopped = ~np.isfinite(u)
        uc = np.clip(np.where(stopped, 0.0, u), 0.0, 1.0)
        if self.thrust_model == "omega_squared":
            ref = self.omega_min_rad_s + uc * (self.omega_cmd_max_rad_s - self.omega_min_rad_s)
            ref = np.minimum(ref, self.omega_max_rad_s)
        else:
            ref = uc
        return np.where(stopped, 0.0, ref)

    def command_from_thrust(self, thrust_n: np.ndarray) -> np.ndarray:
        """Inverse of the steady-state command -> thrust map, clipped to [0, 1]."""
        t = np.maximum(np.asarray(thrust_n, dtype=float), 0.0)
        if self.thrust_model == "omega_squared":
            omega = np.sqrt(t / self.kt_n_s2_rad2)
            u = (omega - self.omega_min_rad_s) / (self.omega_cmd_max_rad_s - self.omega_min_rad_s)
        else:
            rel = t / self.thrust_max_n
            f = self.thr_mdl_fac
            if f < 1e-9:
                u = rel
            else:
                u = (-(1.0 - f) + np.sqrt((1.0 - f) ** 2 + 4.0 * f * rel)) / (2.0 * f)
        return np.clip(u, 0.0, 1.0)

    @property
    def thrust_at_full_command_n(self) -> float:
        """Thrust of one rotor at u = 1 in steady state [N]."""
        return float(self.thrust_from_state(self.reference_from_command(np.array(1.0))))


@dataclass(frozen=True)
class VehicleParams:
    """Everything the physics needs about one vehicle (SI units, body FLU)."""

    name: str
    mass_kg: float
    inertia_kg_m2: tuple[tuple[float, float, float], ...]  # full 3x3 tensor, FLU
    gravity_m_s2: float
    rotors: RotorParams
    effects: tuple[tuple[str, tuple[tuple[str, float], ...]], ...] = ()
    controller: Mapping[str, Any] = field(default_factory=dict)
    sensors: Mapping[str, Any] = field(default_factory=dict)
    dt_s: float = 0.001
    source: str = "<memory>"

    @property
    def inertia(self) -> np.ndarray:
        return np.array(self.inertia_kg_m2, dtype=float)

    @property
    def effect_dict(self) -> dict[str, dict[str, float]]:
        return {name: dict(p) for name, p in self.effects}

    @property
    def hover_thrust_per_rotor_n(self) -> float:
        return self.mass_kg * self.gravity_m_s2 / self.rotors.count

    @property
    def hover_command(self) -> float:
        """Steady-state per-motor command that carries the weight (level, no effects)."""
        return float(self.rotors.command_from_thrust(np.array(self.hover_thrust_per_rotor_n)))

    @property
    def hover_omega_rad_s(self) -> float:
        """Rotor speed at hover, sqrt(m g / (N kt)) (omega_squared) or reported omega."""
        r = self.rotors
        t = self.hover_thrust_per_rotor_n
        if r.thrust_model == "omega_squared":
            return float(np.sqrt(t / r.kt_n_s2_rad2))
        return float(r.omega_max_rad_s * np.sqrt(t / r.thrust_max_n))

    def replace(self, **changes: Any) -> "VehicleParams":
        """A copy with top-level fields changed (validated)."""
        new = dataclasses.replace(self, **changes)
        validate(new)
        return new

    def replace_rotors(self, **changes: Any) -> "VehicleParams":
        return self.replace(rotors=dataclasses.replace(self.rotors, **changes))

    def with_effect(self, name: str, **params: float) -> "VehicleParams":
        """A copy with effect ``name`` enabled (replacing an existing one of that name).

        Raises ParamsError (``<source>: effects.<name>.<param>: ...``) for an unknown
        effect or parameter, or a parameter that is not finite and in its range."""
        _check_effect(self.source, name, params, self.rotors.count)
        eff = [e for e in self.effects if e[0] != name]
        eff.append((name, tuple((k, float(v)) for k, v in params.items())))
        if not _known_valid(self):
            return self.replace(effects=tuple(eff))
        # self passed validate() and only its effects change: every check validate() would make on the copy
        # is one it made on self, but the new effect's, made above (a fit's every evaluation comes here: the
        # full check cost more than the evaluation's model)
        new = dataclasses.replace(self, effects=tuple(eff))
        _mark_valid(new)
        return new

    def to_ros_dict(self) -> dict[str, Any]:
        """The ``ros__parameters`` mapping that ``from_ros_dict`` reads back."""
        r = self.rotors
        inertia = self.inertia
        effects: dict[str, Any] = {"enabled": [n for n, _ in self.effects]}
        for n, p in self.effects:
            effects[n] = {k: float(v) for k, v in p}
        out: dict[str, Any] = {
            "vehicle": {
                "name": self.name,
                "mass_kg": float(self.mass_kg),
                "ixx_kg_m2": float(inertia[0, 0]),
                "iyy_kg_m2": float(inertia[1, 1]),
                "izz_kg_m2": float(inertia[2, 2]),
                "ixy_kg_m2": float(inertia[0, 1]),
                "ixz_kg_m2": float(inertia[0, 2]),
                "iyz_kg_m2": float(inertia[1, 2]),
                "gravity_m_s2": float(self.gravity_m_s2),
            },
            "rotors": {
                "x_flu_m": [float(v) for v in r.x_flu_m],
                "y_flu_m": [float(v) for v in r.y_flu_m],
                "z_flu_m": [float(v) for v in r.z_flu_m],
                "direction": [int(v) for v in r.direction],
                "thrust_model": r.thrust_model,
                "kt_n_s2_rad2": float(r.kt_n_s2_rad2),
                "km_m": float(r.km_m),
                "omega_min_rad_s": float(r.omega_min_rad_s),
                "omega_cmd_max_rad_s": float(r.omega_cmd_max_rad_s),
                "omega_max_rad_s": float(r.omega_max_rad_s),
                "tau_up_s": float(r.tau_up_s),
                "tau_down_s": float(r.tau_down_s),
                "thrust_max_n": float(r.thrust_max_n),
                "thr_mdl_fac": float(r.thr_mdl_fac),
            },
            "effects": effects,
            "simulation": {"dt_s": float(self.dt_s)},
        }
        if self.controller:
            out["controller"] = _plain(self.controller)
        if self.sensors:
            out["sensors"] = _plain(self.sensors)
        return out


def _plain(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


# --------------------------------------------------------------------------- loading

_VEHICLE_KEYS = {"name", "mass_kg", "ixx_kg_m2", "iyy_kg_m2", "izz_kg_m2", "ixy_kg_m2",
                 "ixz_kg_m2", "iyz_kg_m2", "gravity_m_s2", "arm_length_m", "notes"}
_ROTOR_KEYS = {"x_flu_m", "y_flu_m", "z_flu_m", "direction", "thrust_model", "kt_n_s2_rad2",
               "km_m", "omega_min_rad_s", "omega_cmd_max_rad_s", "omega_max_rad_s",
               "tau_up_s", "tau_down_s", "thrust_max_n", "thr_mdl_fac", "notes"}
_TOP_KEYS = {"vehicle", "rotors", "effects", "controller", "sensors", "simulation", "notes"}


class _Reader:
    """Typed access to a nested mapping that reports ``file: a.b.c: expected``."""

    def __init__(self, path: str, data: Mapping[str, Any], prefix: str = ""):
        self.path = path
        self.data = data
        self.prefix = prefix

    def key(self, k: str) -> str:
        return f"{self.prefix}{k}"

    def err(self, k: str, expected: str) -> ParamsError:
        return ParamsError(self.path, self.key(k), expected)

    def sub(self, k: str, required: bool = True) -> "_Reader":
        v = self.data.get(k)
        if v is None:
            if required:
                raise self.err(k, "missing section (a mapping)")
            v = {}
        if not isinstance(v, Mapping):
            raise self.err(k, f"expected a mapping, got {type(v).__name__}")
        return _Reader(self.path, v, f"{self.key(k)}.")

    def unknown(self, allowed: set[str]) -> None:
        for k in self.data:
            if k not in allowed:
                raise self.err(str(k), f"unknown key (allowed: {', '.join(sorted(allowed))})")

    def num(self, k: str, default: float | None = None, *, gt: float | None = None,
            ge: float | None = None, le: float | None = None) -> float:
        if k not in self.data or self.data[k] is None:
            if default is None:
                raise self.err(k, "missing (a number)")
            return float(default)
        v = self.data[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.err(k, f"expected a number, got {_short(v)}")
        v = _finite(v)
        if v is None:
            raise self.err(k, f"expected a finite number, got {_short(self.data[k])}")
        if gt is not None and not v > gt:
            raise self.err(k, f"expected > {gt:g}, got {v:g}")
        if ge is not None and not v >= ge:
            raise self.err(k, f"expected >= {ge:g}, got {v:g}")
        if le is not None and not v <= le:
            raise self.err(k, f"expected <= {le:g}, got {v:g}")
        return v

    def rng(self, k: str, lo: float, hi: float, unit: str, default: float | None = None,
            lo_open: bool = False) -> float:
        """A finite number in ``lo..hi`` (``(lo..hi`` with ``lo_open``) [unit]."""
        v = self.num(k, default)
        if not ((v > lo if lo_open else v >= lo) and v <= hi):
            want = f"> {lo:g} and <= {hi:g}" if lo_open else f"{lo:g}..{hi:g}"
            raise self.err(k, f"expected {want} {unit}, got {v:g}")
        return v

    def text(self, k: str, default: str | None = None, choices: tuple[str, ...] | None = None) -> str:
        v = self.data.get(k, default)
        if v is None:
            raise self.err(k, "missing (a string)")
        if not isinstance(v, str):
            raise self.err(k, f"expected a string, got {_short(v)}")
        if choices is not None and v not in choices:
            raise self.err(k, f"expected one of {', '.join(choices)}, got {_short(v)}")
        return v

    def nums(self, k: str, n: int | None = None) -> list[float]:
        v = self.data.get(k)
        if v is None:
            raise self.err(k, "missing (a list of numbers)")
        if not isinstance(v, (list, tuple)) or not all(
                isinstance(e, (int, float)) and not isinstance(e, bool) for e in v):
            raise self.err(k, f"expected a list of numbers, got {_short(v)}")
        if n is not None and len(v) != n:
            raise self.err(k, f"expected {n} values (one per rotor), got {len(v)}")
        out = [_finite(e) for e in v]
        if any(e is None for e in out):
            raise self.err(k, f"expected finite numbers, got {_short(v)}")
        return [float(e) for e in out]  # type: ignore[arg-type]


def _finite(v: Any) -> float | None:
    """``float(v)`` when that is finite (a huge YAML integer overflows: None), else None."""
    try:
        f = float(v)
    except (OverflowError, TypeError, ValueError):
        return None
    return f if np.isfinite(f) else None


def _short(v: Any, n: int = 60) -> str:
    """``repr(v)`` cut to ``n`` characters (error messages stay one short line)."""
    try:
        r = repr(v)
    except (RecursionError, ValueError):  # a self-referencing YAML structure; huge ints
        r = f"<{type(v).__name__}>"
    r = " ".join(r.split())
    return r if len(r) <= n else r[: n - 3] + "..."


def _check_tree(path: str, key: str, v: Any, budget: list[int], depth: int = 0) -> None:
    """Every number in a free-form block (controller, sensors) is finite; at most
    MAX_VALUES values and 20 levels (YAML aliases can make exponentially large trees)."""
    budget[0] -= 1
    if budget[0] < 0 or depth > 20:
        raise ParamsError(path, key, f"expected at most {MAX_VALUES} values nested at most 20 deep")
    if isinstance(v, Mapping):
        for k, e in v.items():
            _check_tree(path, f"{key}.{k}", e, budget, depth + 1)
    elif isinstance(v, (list, tuple)):
        for i, e in enumerate(v):
            _check_tree(path, f"{key}[{i}]", e, budget, depth + 1)
    elif isinstance(v, (int, float)) and not isinstance(v, bool) and _finite(v) is None:
        raise ParamsError(path, key, f"expected a finite number, got {_short(v)}")


def _check_effect(path: str, name: str, params: Mapping[str, Any], n_rotors: int | None) -> None:
    """ParamsError unless ``name`` is a known effect and ``params`` its valid parameters."""
    if name not in EFFECTS:
        raise ParamsError(path, "effects.enabled",
                          f"unknown effect {name!r} (known: {', '.join(sorted(EFFECTS))})")
    cls = EFFECTS[name]
    for k in params:
        if k not in cls.param_names:
            raise ParamsError(path, f"effects.{name}.{k}",
                              f"unknown parameter (allowed: {', '.join(cls.param_names)})")
    bad = cls.check_params(params, n_rotors)
    if bad is not None:
        raise ParamsError(path, f"effects.{name}.{bad[0]}", bad[1])


def _check_controller(path: str, controller: Mapping[str, Any]) -> None:
    """The ``controller:`` gains of :data:`CONTROLLER_LIMITS` in their ranges, thr_min < thr_max."""
    for k, v in controller.items():
        if k == "law":
            if v not in ("px4", "se3"):
                raise ParamsError(path, "controller.law", f"expected px4 or se3, got {_short(v)}")
            continue
        lim = CONTROLLER_LIMITS.get(str(k))
        if lim is None:
            continue  # unknown keys: ControllerGains.from_params names the known ones
        lo, hi, lo_open, unit = lim
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ParamsError(path, f"controller.{k}", f"expected a number, got {_short(v)}")
        f = _finite(v)
        if f is None or not ((f > lo if lo_open else f >= lo) and f <= hi):
            want = f"> {lo:g} and <= {hi:g}" if lo_open else f"{lo:g}..{hi:g}"
            raise ParamsError(path, f"controller.{k}", f"expected {want}{' ' + unit if unit else ''}, got {_short(v)}")
    lo_thr, hi_thr = controller.get("thr_min", 0.12), controller.get("thr_max", 1.0)
    if not lo_thr < hi_thr:
        raise ParamsError(path, "controller.thr_min", f"expected < thr_max ({hi_thr:g}), got {lo_thr:g}")


def rotor_span_m(x_flu_m: Any, y_flu_m: Any) -> float:
    """RMS spread [m] of the rotor positions about their centroid along the weakest horizontal axis:
    0 when every rotor sits on one point or one line (no moment arm about some axis)."""
    xy = np.column_stack([np.asarray(x_flu_m, float), np.asarray(y_flu_m, float)])
    if len(xy) < 2 or not np.all(np.isfinite(xy)):
        return 0.0
    xy = xy - xy.mean(axis=0)
    return float(np.linalg.svd(xy, compute_uv=False)[-1] / np.sqrt(len(xy)))


def _unwrap_ros(path: str, doc: Any) -> Mapping[str, Any]:
    """Find the ``ros__parameters`` mapping (``/**`` or a node name as the key)."""
    if not isinstance(doc, Mapping):
        raise ParamsError(path, "<top>", "expected a YAML mapping '<node or /**>: {ros__parameters: {...}}'")
    if "ros__parameters" in doc:
        inner = doc["ros__parameters"]
    else:
        inner = None
        for v in doc.values():
            if isinstance(v, Mapping) and "ros__parameters" in v:
                inner = v["ros__parameters"]
                break
        if inner is None:
            raise ParamsError(path, "ros__parameters", "missing: expected '/**: {ros__parameters: {...}}'")
    if not isinstance(inner, Mapping):
        raise ParamsError(path, "ros__parameters", "expected a mapping")
    return inner


def from_ros_dict(data: Mapping[str, Any], path: str = "<memory>") -> VehicleParams:
    """Build and validate :class:`VehicleParams` from a ``ros__parameters`` mapping."""
    if not isinstance(data, Mapping):
        raise ParamsError(path, "ros__parameters", f"expected a mapping, got {type(data).__name__}")
    top = _Reader(path, data)
    top.unknown(_TOP_KEYS)
    v = top.sub("vehicle")
    v.unknown(_VEHICLE_KEYS)
    mass = v.rng("mass_kg", *LIMITS["mass_kg"], "kg")
    ixx, iyy, izz = (v.num(k, gt=0.0) for k in ("ixx_kg_m2", "iyy_kg_m2", "izz_kg_m2"))
    ixy, ixz, iyz = (v.num(k, 0.0) for k in ("ixy_kg_m2", "ixz_kg_m2", "iyz_kg_m2"))
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    with np.errstate(over="ignore", invalid="ignore"):
        eig = np.linalg.eigvalsh(inertia) if np.all(np.abs(inertia) < 1e150) else np.full(3, np.nan)
    if not np.all(eig > 0.0):
        raise v.err("ixx_kg_m2", f"inertia tensor must be positive definite, eigenvalues {eig}")
    grav = v.rng("gravity_m_s2", *LIMITS["gravity_m_s2"], "m/s^2", GRAVITY_DEFAULT)

    r = top.sub("rotors")
    r.unknown(_ROTOR_KEYS)
    xs = r.nums("x_flu_m")
    n = len(xs)
    n_lo, n_hi = LIMITS["rotors"]
    if not n_lo <= n <= n_hi:
        raise r.err("x_flu_m", f"expected {n_lo}..{n_hi} rotors, got {n}")
    ys = r.nums("y_flu_m", n)
    zs = r.nums("z_flu_m", n) if "z_flu_m" in r.data else [0.0] * n
    with np.errstate(over="ignore", invalid="ignore"):  # 1e308 squared is inf: refused below
        far = float(np.max(np.linalg.norm(np.column_stack([xs, ys, zs]), axis=1)))
    if not far <= LIMITS["position_m"]:
        raise r.err("x_flu_m", f"expected rotor positions within {LIMITS['position_m']:g} m of the centre "
                               f"of mass, got one at {far:.6g} m")
    dirs = r.nums("direction", n)
    if any(d not in (1.0, -1.0) for d in dirs):
        raise r.err("direction", f"expected +1 (CCW seen from above) or -1 (CW) per rotor, got {_short(dirs)}")
    model = r.text("thrust_model", "omega_squared", THRUST_MODELS)
    tau_up = r.rng("tau_up_s", *LIMITS["tau_s"], "s")
    tau_down = r.rng("tau_down_s", *LIMITS["tau_s"], "s")
    km = r.rng("km_m", *LIMITS["km_m"], "m")
    w_hi, w_top = LIMITS["omega_rad_s"], LIMITS["omega_top_min_rad_s"]
    kt_lo, kt_hi = LIMITS["kt_n_s2_rad2"]
    t_lo, t_hi = LIMITS["thrust_min_n"], LIMITS["thrust_max_n"]
    if model == "omega_squared":
        kt = r.rng("kt_n_s2_rad2", kt_lo, kt_hi, "N s^2/rad^2")
        wmin = r.rng("omega_min_rad_s", 0.0, w_hi, "rad/s")
        wcmd = r.rng("omega_cmd_max_rad_s", w_top, w_hi, "rad/s")
        wmax = r.rng("omega_max_rad_s", w_top, w_hi, "rad/s", wcmd)
        if not wmin < wcmd:
            raise r.err("omega_min_rad_s", f"expected omega_min_rad_s < omega_cmd_max_rad_s, got {wmin:g} >= {wcmd:g}")
        if not wcmd <= wmax:
            raise r.err("omega_cmd_max_rad_s", f"expected <= omega_max_rad_s ({wmax:g}), got {wcmd:g}")
        tmax = kt * wcmd * wcmd
        if not t_lo <= tmax <= t_hi:
            raise r.err("kt_n_s2_rad2", f"expected a thrust at full command kt*omega_cmd_max^2 of "
                                        f"{t_lo:g}..{t_hi:g} N per rotor, got {tmax:.6g} N")
        fac = r.num("thr_mdl_fac", 0.0, ge=0.0, le=1.0)
    else:
        tmax = r.rng("thrust_max_n", t_lo, t_hi, "N")
        fac = r.num("thr_mdl_fac", 0.0, ge=0.0, le=1.0)
        wmax = r.rng("omega_max_rad_s", w_top, w_hi, "rad/s", 1000.0)
        wcmd = r.rng("omega_cmd_max_rad_s", w_top, w_hi, "rad/s", wmax)
        wmin = r.rng("omega_min_rad_s", 0.0, w_hi, "rad/s", 0.0)
        kt = r.rng("kt_n_s2_rad2", kt_lo, kt_hi, "N s^2/rad^2 (default thrust_max_n / omega_max_rad_s^2)",
                   tmax / (wmax * wmax))

    rotors = RotorParams(
        x_flu_m=tuple(xs), y_flu_m=tuple(ys), z_flu_m=tuple(zs),
        direction=tuple(int(d) for d in dirs), thrust_model=model,
        kt_n_s2_rad2=kt, km_m=km, omega_min_rad_s=wmin, omega_cmd_max_rad_s=wcmd,
        omega_max_rad_s=wmax, tau_up_s=tau_up, tau_down_s=tau_down,
        thrust_max_n=tmax, thr_mdl_fac=fac,
    )

    effects = _read_effects(top.sub("effects", required=False), n)
    sim = top.sub("simulation", required=False)
    sim.unknown({"dt_s"})
    dt = sim.rng("dt_s", *LIMITS["dt_s"], "s", 0.001)
    budget = [MAX_VALUES]
    blocks = {}
    for name in ("controller", "sensors"):
        blocks[name] = dict(top.sub(name, required=False).data)
        _check_tree(path, name, blocks[name], budget)
    controller, sensors = blocks["controller"], blocks["sensors"]
    vp = VehicleParams(
        name=v.text("name", "vehicle"), mass_kg=mass,
        inertia_kg_m2=tuple(tuple(float(e) for e in row) for row in inertia),
        gravity_m_s2=grav, rotors=rotors, effects=effects,
        controller=controller, sensors=sensors, dt_s=dt, source=path,
    )
    validate(vp)
    return vp


def _read_effects(e: _Reader, n_rotors: int | None = None) -> tuple[tuple[str, tuple[tuple[str, float], ...]], ...]:
    enabled = e.data.get("enabled", [])
    if enabled is None:
        enabled = []
    if not isinstance(enabled, (list, tuple)) or not all(isinstance(x, str) for x in enabled):
        raise e.err("enabled", f"expected a list of effect names, got {_short(enabled)}")
    allowed = {"enabled"} | set(EFFECTS)
    e.unknown(allowed)
    out = []
    for name in enabled:
        if name not in EFFECTS:
            raise e.err("enabled", f"unknown effect {name!r} (known: {', '.join(sorted(EFFECTS))})")
        cls = EFFECTS[name]
        sub = e.sub(name, required=False)
        sub.unknown(set(cls.param_names))
        values = []
        for pname in cls.param_names:
            default = cls.defaults.get(pname)
            values.append((pname, sub.num(pname, default)))
        bad = cls.check_params(dict(values), n_rotors)
        if bad is not None:
            raise sub.err(bad[0], bad[1])
        out.append((name, tuple(values)))
    return tuple(out)


def _in(v: float, lo: float, hi: float) -> bool:
    return bool(np.isfinite(v) and lo <= v <= hi)


def _mark_valid(p: VehicleParams) -> None:
    """Note on ``p`` that it passed :func:`validate` (with the controller gains it had then: the one field
    that is a mutable mapping; the others are frozen)."""
    object.__setattr__(p, "_valid_controller", dict(p.controller or {}))


def _known_valid(p: VehicleParams) -> bool:
    """Whether ``p`` passed :func:`validate` and its controller gains are still those it had then."""
    seen = p.__dict__.get("_valid_controller")
    return seen is not None and seen == dict(p.controller or {})


def validate(p: VehicleParams) -> None:
    """Re-check invariants of an in-memory parameter set (used after edits): the
    physical ranges of :data:`LIMITS`, finite numbers, valid effect parameters."""
    _validate(p)
    _mark_valid(p)


#: what the pure checks of :func:`_validate` passed, keyed on everything they read (with each value's type: ``True``
#: and ``1`` are equal keys but not equal gains): a discovery fit validates a parameter set at every evaluation
#: (``replace`` in each parameter-type effect's ``apply_to_params``) whose inertia, rotor geometry, effects and
#: controller gains are those of the last one.  A check that raised is not kept (it raises again, the same error);
#: a key that cannot be hashed (None) is checked every time.
_PASSED: dict = {}


def _typed(v: Any, pairs: bool = False) -> tuple | None:
    """A hashable key of a flat sequence of values (``pairs``: of (name, value) pairs) with their types, or None."""
    items = tuple(v)
    types = tuple([(type(a), type(b)) for a, b in items] if pairs else map(type, items))
    try:
        hash(items)
    except TypeError:
        return None
    return items, types


def _passed(key: tuple) -> bool:
    return None not in key and key in _PASSED


def _keep_passed(key: tuple, value: Any) -> None:
    if None in key:
        return
    if len(_PASSED) >= 4096:
        _PASSED.clear()
    _PASSED[key] = value


def _check_geometry(path: str, r: "RotorParams") -> float:
    """The rotor positions' checks of :func:`_validate`; returns the farthest rotor's distance [m]."""
    pos = r.positions_flu_m
    with np.errstate(over="ignore", invalid="ignore"):
        far = float(np.max(np.linalg.norm(pos, axis=1))) if np.all(np.isfinite(pos)) else np.inf
    if not far <= LIMITS["position_m"]:
        raise ParamsError(path, "rotors.x_flu_m", f"expected rotor positions within {LIMITS['position_m']:g} m "
                                                  f"of the centre of mass, got one at {far:.6g} m")
    span = rotor_span_m(r.x_flu_m, r.y_flu_m)
    if not span >= LIMITS["span_m"]:
        raise ParamsError(path, "rotors.x_flu_m",
                          f"expected rotor positions that span roll and pitch (an RMS spread about their centroid "
                          f"of at least {LIMITS['span_m']:g} m along every horizontal axis: a moment arm about "
                          f"both), got {span:.3g} m")
    return far


def _validate(p: VehicleParams) -> None:
    path = p.source
    lo, hi = LIMITS["mass_kg"]
    if not _in(p.mass_kg, lo, hi):
        raise ParamsError(path, "vehicle.mass_kg", f"expected {lo:g}..{hi:g} kg, got {p.mass_kg:g}")
    inertia = p.inertia
    key = ("inertia", inertia.dtype.str, inertia.shape, inertia.tobytes())
    if not _passed(key):
        if (inertia.shape != (3, 3) or not np.all(np.abs(inertia) < 1e150) or not np.allclose(inertia, inertia.T)
                or np.any(np.linalg.eigvalsh(inertia) <= 0)):
            raise ParamsError(path, "vehicle.ixx_kg_m2", "inertia tensor must be symmetric positive definite")
        _keep_passed(key, True)
    r = p.rotors
    if not (len(r.x_flu_m) == len(r.y_flu_m) == len(r.z_flu_m) == len(r.direction)):
        raise ParamsError(path, "rotors.x_flu_m", "x/y/z/direction must have one entry per rotor")
    n_lo, n_hi = LIMITS["rotors"]
    if not n_lo <= r.count <= n_hi:
        raise ParamsError(path, "rotors.x_flu_m", f"expected {n_lo}..{n_hi} rotors, got {r.count}")
    geometry = ("geometry", _typed(r.x_flu_m), _typed(r.y_flu_m), _typed(r.z_flu_m))
    far = _PASSED.get(geometry)
    if far is None:
        far = _check_geometry(path, r)
        _keep_passed(geometry, far)
    g_lo = LIMITS["gyration_min_m"]
    g_hi = max(LIMITS["gyration_max_floor_m"], 3.0 * far)
    for i, k in enumerate(("ixx_kg_m2", "iyy_kg_m2", "izz_kg_m2")):
        i_lo, i_hi = p.mass_kg * g_lo ** 2, p.mass_kg * g_hi ** 2
        if not _in(inertia[i, i], i_lo, i_hi):
            raise ParamsError(path, f"vehicle.{k}",
                              f"expected {i_lo:.3g}..{i_hi:.3g} kg m^2 (radius of gyration {g_lo:g}..{g_hi:.3g} m "
                              f"for {p.mass_kg:g} kg and rotors up to {far:.3g} m out), got {inertia[i, i]:.6g}")
    g_lo, g_hi = LIMITS["gravity_m_s2"]
    if not _in(p.gravity_m_s2, g_lo, g_hi):
        raise ParamsError(path, "vehicle.gravity_m_s2", f"expected {g_lo:g}..{g_hi:g} m/s^2, got {p.gravity_m_s2:g}")
    t_lo, t_hi = LIMITS["tau_s"]
    for k in ("tau_up_s", "tau_down_s"):
        if not _in(getattr(r, k), t_lo, t_hi):
            raise ParamsError(path, f"rotors.{k}", f"expected {t_lo:g}..{t_hi:g} s, got {getattr(r, k):g}")
    k_lo, k_hi = LIMITS["km_m"]
    if not _in(r.km_m, k_lo, k_hi):
        raise ParamsError(path, "rotors.km_m", f"expected {k_lo:g}..{k_hi:g} m, got {r.km_m:g}")
    for k in ("omega_min_rad_s", "omega_cmd_max_rad_s", "omega_max_rad_s"):
        w_lo = 0.0 if k == "omega_min_rad_s" else LIMITS["omega_top_min_rad_s"]
        if not _in(getattr(r, k), w_lo, LIMITS["omega_rad_s"]):
            raise ParamsError(path, f"rotors.{k}", f"expected {w_lo:g}..{LIMITS['omega_rad_s']:g} rad/s, "
                                                   f"got {getattr(r, k):g}")
    kt_lo, kt_hi = LIMITS["kt_n_s2_rad2"]
    if not _in(r.kt_n_s2_rad2, kt_lo, kt_hi):
        raise ParamsError(path, "rotors.kt_n_s2_rad2", f"expected {kt_lo:g}..{kt_hi:g} N s^2/rad^2, "
                                                       f"got {r.kt_n_s2_rad2:g}")
    if not _in(r.thr_mdl_fac, 0.0, 1.0):
        raise ParamsError(path, "rotors.thr_mdl_fac", f"expected 0..1, got {r.thr_mdl_fac:g}")
    t_lo, t_hi = LIMITS["thrust_min_n"], LIMITS["thrust_max_n"]
    with np.errstate(over="ignore", invalid="ignore"):
        t_full = r.thrust_at_full_command_n
    if not (_in(t_full, t_lo, t_hi) and _in(r.thrust_max_n, t_lo, t_hi)):
        raise ParamsError(path, "rotors.thrust_max_n",
                          f"expected a thrust at full command of {t_lo:g}..{t_hi:g} N per rotor, "
                          f"got {t_full:g} N (thrust_max_n {r.thrust_max_n:g})")
    d_lo, d_hi = LIMITS["dt_s"]
    if not _in(p.dt_s, d_lo, d_hi):
        raise ParamsError(path, "simulation.dt_s", f"expected {d_lo:g}..{d_hi:g} s, got {p.dt_s:g}")
    for name, params in p.effects:
        key = ("effect", name, _typed(dict(params).items(), pairs=True), r.count)
        if not _passed(key):
            _check_effect(path, name, dict(params), r.count)
            _keep_passed(key, True)
    controller = p.controller or {}
    key = ("controller", _typed(controller.items(), pairs=True))
    if not _passed(key):
        _check_controller(path, controller)
        _keep_passed(key, True)
    if r.thrust_model == "omega_squared" and not r.omega_min_rad_s < r.omega_cmd_max_rad_s <= r.omega_max_rad_s:
        raise ParamsError(path, "rotors.omega_min_rad_s", "expected omega_min < omega_cmd_max <= omega_max")
    if p.hover_thrust_per_rotor_n >= r.thrust_at_full_command_n:
        raise ParamsError(path, "rotors.kt_n_s2_rad2",
                          f"rotors cannot lift the vehicle: {r.count} x {r.thrust_at_full_command_n:.3g} N "
                          f"at full command < weight {p.mass_kg * p.gravity_m_s2:.3g} N")


def load_params(path: str | Path) -> VehicleParams:
    """Load and validate a vehicle parameter file; raises ParamsError naming file and key."""
    path = str(path)
    doc = read_yaml_file(path, "params YAML file")
    return from_ros_dict(_unwrap_ros(path, doc), path)


def dump_params(p: VehicleParams, header: str = "") -> str:
    """YAML text (``/**: ros__parameters``) for ``p``; ``load_params`` reads it back equal."""
    body = yaml.safe_dump({"/**": {"ros__parameters": p.to_ros_dict()}}, sort_keys=False,
                          default_flow_style=None)
    if header:
        body = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines()) + body
    return body


def write_params(p: VehicleParams, path: str | Path, header: str = "") -> None:
    """Validate, then write atomically (a failed write never leaves a half file)."""
    validate(p)
    text = dump_params(p, header)
    from_ros_dict(_unwrap_ros(str(path), safe_load(text)), str(path))  # round-trip check
    tmp = Path(str(path) + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)


def params_dir() -> Path:
    """The shipped ``params/`` folder (repo checkout or installed share)."""
    here = Path(__file__).resolve().parents[2] / "params"
    return here


def shipped(name: str) -> VehicleParams:
    """Load a shipped parameter file by stem, e.g. ``shipped('px4_sih_quadx')``."""
    return load_params(params_dir() / f"{name}.yaml")


def deep_copy_dict(d: Mapping[str, Any]) -> dict[str, Any]:
    return copy.deepcopy(dict(d))
