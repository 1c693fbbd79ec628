"""Vehicle parameter files: schema, validation and YAML I/O.

A parameter file is ROS 2 ``ros__parameters`` YAML, so the same file can be
handed to a node with ``--ros-args --params-file``::

    /**:
      ros__parameters:
        vehicle:   {name, mass_kg, ixx_kg_m2, ..., gravity_m_s2}
        rotors:    {x_flu_m: [...], y_flu_m: [...], z_flu_m: [...], direction: [...],
                    thrust_model, kt_n_s2_rad2, km_m, omega_*_rad_s, tau_up_s, tau_down_s, ...}
        effects:   {enabled: [names...], <name>: {<param>: value}}
        controller: {...}      # PX4-like cascade gains (twin_nodes.control)
        sensors:    {...}      # noise/bias model for the simulator link
        simulation: {dt_s: 0.001}

Frames: rotor positions are body **FLU** (ROS REP-103).  ``direction`` is +1 for
a rotor spinning counter-clockwise seen from above (PX4 ``CA_ROTORn_KM > 0``)
and -1 for clockwise.  Motor order is PX4's (Motor1 = index 0).

Every value carries its unit in its name.  ``load_params`` validates everything
and raises :class:`~twin_nodes.errors.ParamsError` whose message names the
file, the key and what was expected.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from twin_nodes.errors import ParamsError

THRUST_MODELS = ("omega_squared", "thrust_factor")
GRAVITY_DEFAULT = 9.80665


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
        """A copy with effect ``name`` enabled (replacing an existing one of that name)."""
        eff = [e for e in self.effects if e[0] != name]
        eff.append((name, tuple((k, float(v)) for k, v in params.items())))
        return self.replace(effects=tuple(eff))

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
            raise self.err(k, f"expected a number, got {v!r}")
        v = float(v)
        if not np.isfinite(v):
            raise self.err(k, f"expected a finite number, got {v!r}")
        if gt is not None and not v > gt:
            raise self.err(k, f"expected > {gt:g}, got {v:g}")
        if ge is not None and not v >= ge:
            raise self.err(k, f"expected >= {ge:g}, got {v:g}")
        if le is not None and not v <= le:
            raise self.err(k, f"expected <= {le:g}, got {v:g}")
        return v

    def text(self, k: str, default: str | None = None, choices: tuple[str, ...] | None = None) -> str:
        v = self.data.get(k, default)
        if v is None:
            raise self.err(k, "missing (a string)")
        if not isinstance(v, str):
            raise self.err(k, f"expected a string, got {v!r}")
        if choices is not None and v not in choices:
            raise self.err(k, f"expected one of {', '.join(choices)}, got {v!r}")
        return v

    def nums(self, k: str, n: int | None = None) -> list[float]:
        v = self.data.get(k)
        if v is None:
            raise self.err(k, "missing (a list of numbers)")
        if not isinstance(v, (list, tuple)) or not all(
                isinstance(e, (int, float)) and not isinstance(e, bool) for e in v):
            raise self.err(k, f"expected a list of numbers, got {v!r}")
        if n is not None and len(v) != n:
            raise self.err(k, f"expected {n} values (one per rotor), got {len(v)}")
        if not all(np.isfinite(float(e)) for e in v):
            raise self.err(k, "expected finite numbers")
        return [float(e) for e in v]


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
    top = _Reader(path, data)
    top.unknown(_TOP_KEYS)
    v = top.sub("vehicle")
    v.unknown(_VEHICLE_KEYS)
    mass = v.num("mass_kg", gt=0.0)
    ixx, iyy, izz = (v.num(k, gt=0.0) for k in ("ixx_kg_m2", "iyy_kg_m2", "izz_kg_m2"))
    ixy, ixz, iyz = (v.num(k, 0.0) for k in ("ixy_kg_m2", "ixz_kg_m2", "iyz_kg_m2"))
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    if np.any(np.linalg.eigvalsh(inertia) <= 0.0):
        raise v.err("ixx_kg_m2", f"inertia tensor must be positive definite, eigenvalues {np.linalg.eigvalsh(inertia)}")
    grav = v.num("gravity_m_s2", GRAVITY_DEFAULT, gt=0.0)

    r = top.sub("rotors")
    r.unknown(_ROTOR_KEYS)
    xs = r.nums("x_flu_m")
    n = len(xs)
    if n < 1:
        raise r.err("x_flu_m", "expected at least one rotor")
    ys = r.nums("y_flu_m", n)
    zs = r.nums("z_flu_m", n) if "z_flu_m" in r.data else [0.0] * n
    dirs = r.nums("direction", n)
    if any(d not in (1.0, -1.0) for d in dirs):
        raise r.err("direction", f"expected +1 (CCW seen from above) or -1 (CW) per rotor, got {dirs}")
    model = r.text("thrust_model", "omega_squared", THRUST_MODELS)
    tau_up = r.num("tau_up_s", ge=0.0)
    tau_down = r.num("tau_down_s", ge=0.0)
    km = r.num("km_m", ge=0.0)
    if model == "omega_squared":
        kt = r.num("kt_n_s2_rad2", gt=0.0)
        wmin = r.num("omega_min_rad_s", ge=0.0)
        wcmd = r.num("omega_cmd_max_rad_s", gt=0.0)
        wmax = r.num("omega_max_rad_s", wcmd, gt=0.0)
        if not wmin < wcmd:
            raise r.err("omega_min_rad_s", f"expected omega_min_rad_s < omega_cmd_max_rad_s, got {wmin:g} >= {wcmd:g}")
        if not wcmd <= wmax:
            raise r.err("omega_cmd_max_rad_s", f"expected <= omega_max_rad_s ({wmax:g}), got {wcmd:g}")
        tmax = kt * wcmd * wcmd
        fac = r.num("thr_mdl_fac", 0.0, ge=0.0, le=1.0)
    else:
        tmax = r.num("thrust_max_n", gt=0.0)
        fac = r.num("thr_mdl_fac", 0.0, ge=0.0, le=1.0)
        wmax = r.num("omega_max_rad_s", 1000.0, gt=0.0)
        wcmd = r.num("omega_cmd_max_rad_s", wmax, gt=0.0)
        wmin = r.num("omega_min_rad_s", 0.0, ge=0.0)
        kt = r.num("kt_n_s2_rad2", tmax / (wmax * wmax), gt=0.0)

    rotors = RotorParams(
        x_flu_m=tuple(xs), y_flu_m=tuple(ys), z_flu_m=tuple(zs),
        direction=tuple(int(d) for d in dirs), thrust_model=model,
        kt_n_s2_rad2=kt, km_m=km, omega_min_rad_s=wmin, omega_cmd_max_rad_s=wcmd,
        omega_max_rad_s=wmax, tau_up_s=tau_up, tau_down_s=tau_down,
        thrust_max_n=tmax, thr_mdl_fac=fac,
    )

    effects = _read_effects(top.sub("effects", required=False))
    sim = top.sub("simulation", required=False)
    sim.unknown({"dt_s"})
    dt = sim.num("dt_s", 0.001, gt=0.0, le=0.1)
    controller = dict(top.sub("controller", required=False).data)
    sensors = dict(top.sub("sensors", required=False).data)
    vp = VehicleParams(
        name=v.text("name", "vehicle"), mass_kg=mass,
        inertia_kg_m2=tuple(tuple(float(e) for e in row) for row in inertia),
        gravity_m_s2=grav, rotors=rotors, effects=effects,
        controller=controller, sensors=sensors, dt_s=dt, source=path,
    )
    validate(vp)
    return vp


def _read_effects(e: _Reader) -> tuple[tuple[str, tuple[tuple[str, float], ...]], ...]:
    # Imported here: the effect registry lives with the physics, and physics imports params.
    from twin_nodes.physics.effects import EFFECTS

    enabled = e.data.get("enabled", [])
    if enabled is None:
        enabled = []
    if not isinstance(enabled, (list, tuple)) or not all(isinstance(x, str) for x in enabled):
        raise e.err("enabled", f"expected a list of effect names, got {enabled!r}")
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
        out.append((name, tuple(values)))
    return tuple(out)


def validate(p: VehicleParams) -> None:
    """Re-check invariants of an in-memory parameter set (used after edits)."""
    path = p.source
    if not p.mass_kg > 0:
        raise ParamsError(path, "vehicle.mass_kg", f"expected > 0, got {p.mass_kg:g}")
    inertia = p.inertia
    if inertia.shape != (3, 3) or not np.allclose(inertia, inertia.T) or np.any(np.linalg.eigvalsh(inertia) <= 0):
        raise ParamsError(path, "vehicle.ixx_kg_m2", "inertia tensor must be symmetric positive definite")
    r = p.rotors
    if not (len(r.x_flu_m) == len(r.y_flu_m) == len(r.z_flu_m) == len(r.direction)):
        raise ParamsError(path, "rotors.x_flu_m", "x/y/z/direction must have one entry per rotor")
    if r.tau_up_s < 0 or r.tau_down_s < 0:
        raise ParamsError(path, "rotors.tau_up_s", "time constants must be >= 0")
    if r.thrust_model == "omega_squared" and not r.omega_min_rad_s < r.omega_cmd_max_rad_s <= r.omega_max_rad_s:
        raise ParamsError(path, "rotors.omega_min_rad_s", "expected omega_min < omega_cmd_max <= omega_max")
    if p.hover_thrust_per_rotor_n >= r.thrust_at_full_command_n:
        raise ParamsError(path, "rotors.kt_n_s2_rad2",
                          f"rotors cannot lift the vehicle: {r.count} x {r.thrust_at_full_command_n:.3g} N "
                          f"at full command < weight {p.mass_kg * p.gravity_m_s2:.3g} N")


def load_params(path: str | Path) -> VehicleParams:
    """Load and validate a vehicle parameter file; raises ParamsError naming file and key."""
    path = str(path)
    try:
        with open(path, "r", encoding="utf-8") as fh:
            doc = yaml.safe_load(fh)
    except FileNotFoundError:
        raise ParamsError(path, "<file>", "file not found") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "<yaml>"
        raise ParamsError(path, where, f"not valid YAML ({getattr(exc, 'problem', exc)})") from None
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
    from_ros_dict(_unwrap_ros(str(path), yaml.safe_load(text)), str(path))  # round-trip check
    tmp = Path(str(path) + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)


def params_dir() -> Path:
    """The shipped ``params/`` folder (repo checkout or installed share)."""
    here = Path(__file__).resolve().parent.parent / "params"
    return here


def shipped(name: str) -> VehicleParams:
    """Load a shipped parameter file by stem, e.g. ``shipped('px4_sih_quadx')``."""
    return load_params(params_dir() / f"{name}.yaml")


def deep_copy_dict(d: Mapping[str, Any]) -> dict[str, Any]:
    return copy.deepcopy(dict(d))
