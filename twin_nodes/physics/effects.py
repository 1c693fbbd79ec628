"""Plug-in physical effects.

An effect is a small class with named, SI-unit parameters.  It acts through one
or more of these hooks, each an ``@njit`` kernel with a fixed signature, which
:mod:`twin_nodes.physics.model` composes into the stepper at build time (the
core is never edited to add an effect):

``command_kernel(p, ext, sref)``
    change the per-rotor reference (rotor state the lag converges to) in place.
``rotor_kernel(p, x, ext, omega, T, Q)``
    change per-rotor thrust ``T`` [N] / reaction torque ``Q`` [N m] in place.
``wrench_kernel(p, x, R, ext, omega, T, Fb, Mb, Fw)``
    add a body-frame force ``Fb`` [N, FLU], body moment ``Mb`` [N m, FLU] about the
    centre of mass, and/or a world force ``Fw`` [N, ENU].

Other effects are parameter changes (``apply_to_params``: mass, thrust
coefficient, inertia...), a command delay (``command_delay_s``), an
exogenous input (``exogenous``: wind velocity) or a displaced centre of mass
(``com_flu_m``: the model packs every rotor position relative to it, so each
rotor-force term -- thrust, rotor drag and its hub airspeed ``w x r`` -- acts
about the moved centre of mass; the controller keeps the nominal geometry).

Arguments: ``p`` the effect's parameter vector (order of ``param_names``), then, for an
effect with ``kernel_reads_vehicle``, ``P`` the packed vehicle (:func:`twin_nodes.physics.core.pack`:
rotor positions and directions);
``x`` the state ``[p_enu(3), v_enu(3), q_wxyz(4) FLU->ENU, w_flu(3), s(N)]``;
``R`` the body->world rotation; ``ext = [battery_v, wind_e, wind_n, wind_u]``
(NaN voltage = unknown); ``omega`` rotor speeds [rad/s].
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, ClassVar, Mapping

import numpy as np
from numba import njit

from twin_nodes.base.errors import ParamsError
from twin_nodes.physics.core import I_N, I_ROT

if TYPE_CHECKING:  # pragma: no cover - the catalogue is read by vehicle/params, never the reverse
    from twin_nodes.vehicle.params import VehicleParams

EXT_SIZE = 4
EXT_VOLTAGE, EXT_WIND = 0, 1


def default_ext() -> np.ndarray:
    """Exogenous inputs with nothing known: voltage NaN, no wind."""
    e = np.zeros(EXT_SIZE)
    e[EXT_VOLTAGE] = np.nan
    return e


class Effect:
    """Base class; subclasses set the class attributes and the hooks they use.

    ``ranges`` gives each parameter's physical range ``(lo, hi)``, inclusive, in
    the parameter's ``units``; every parameter must be a finite number inside it
    (:meth:`check_params`, applied on construction, by ``VehicleParams.with_effect``
    and when a params file is loaded, where the rotor count is known too)."""

    name: ClassVar[str] = ""
    param_names: ClassVar[tuple[str, ...]] = ()
    defaults: ClassVar[dict[str, float]] = {}
    units: ClassVar[dict[str, str]] = {}
    ranges: ClassVar[dict[str, tuple[float, float]]] = {}
    description: ClassVar[str] = ""
    command_kernel: ClassVar[Any] = None
    rotor_kernel: ClassVar[Any] = None
    wrench_kernel: ClassVar[Any] = None
    #: the kernels take the packed vehicle ``P`` right after ``p`` (for rotor positions)
    kernel_reads_vehicle: ClassVar[bool] = False
    #: parameters that are whole numbers (an index, a bit mask): chosen, never varied by a fit
    discrete: ClassVar[tuple[str, ...]] = ()
    #: parameters that are a form's switch, 0 or 1 -> (what 0 means, what 1 means), checked by :meth:`check_params`
    switches: ClassVar[dict[str, tuple[str, str]]] = {}

    def __init__(self, **params: float):
        unknown = set(params) - set(self.param_names)
        if unknown:
            raise ValueError(f"effect {self.name}: unknown parameter(s) {sorted(unknown)}; "
                             f"expected {list(self.param_names)}")
        values = {}
        for k in self.param_names:
            if k in params:
                values[k] = params[k]
            elif k in self.defaults:
                values[k] = self.defaults[k]
            else:
                raise ValueError(f"effect {self.name}: parameter {k!r} is required")
        bad = self.check_params(values)
        if bad is not None:
            raise ParamsError(f"effect {self.name}", *bad)
        self.params = {k: float(v) for k, v in values.items()}

    @classmethod
    def check_params(cls, params: Mapping[str, Any], n_rotors: int | None = None) -> tuple[str, str] | None:
        """``(parameter, what was expected)`` for the first parameter in ``params`` that is
        not a finite number in its physical range (see ``ranges``), else None.
        ``n_rotors`` (when known) bounds rotor indices."""
        for k in cls.param_names:
            if k not in params:
                continue
            v = params[k]
            lo, hi = cls.ranges.get(k, (-math.inf, math.inf))
            unit = cls.units.get(k, "")
            want = f"a finite number in {lo:g}..{hi:g}" + (f" [{unit}]" if unit else "")
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                return k, f"expected {want}, got {v!r}"
            try:
                f = float(v)
            except OverflowError:
                return k, f"expected {want}, got an integer of {len(str(v))} digits"
            if not (math.isfinite(f) and lo <= f <= hi):
                return k, f"expected {want}, got {f:g}"
            if k in cls.switches and f not in (0.0, 1.0):
                off, on = cls.switches[k]
                return k, f"expected 0 ({off}) or 1 ({on}), got {f:g}"
        return None

    def vector(self) -> np.ndarray:
        """Parameters as the float64 vector the kernels read (``param_names`` order)."""
        return np.array([self.params[k] for k in self.param_names], dtype=np.float64)

    def apply_to_params(self, vp: "VehicleParams") -> "VehicleParams":
        """Parameter-type effects return a changed copy; others return ``vp``."""
        return vp

    def command_delay_s(self) -> float:
        return 0.0

    def com_flu_m(self) -> tuple[float, float, float]:
        """Where this effect puts the centre of mass [m, body FLU] relative to the point the rotor positions
        are given about (summed over the effects; :func:`twin_nodes.physics.core.pack`)."""
        return (0.0, 0.0, 0.0)

    def exogenous(self, t: np.ndarray, ext: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Fill/modify the exogenous input series ``ext`` (shape (T, EXT_SIZE)) for times ``t``."""
        return ext

    @property
    def has_kernel(self) -> bool:
        return any(k is not None for k in (self.command_kernel, self.rotor_kernel, self.wrench_kernel))

    def __repr__(self) -> str:
        inner = ", ".join(f"{k}={v:g}" for k, v in self.params.items())
        return f"{type(self).__name__}({inner})"


# ---------------------------------------------------------------- kernels


@njit(cache=True)
def _air_body(x, R, ext):
    """Air-relative velocity in body FLU [m/s] (vehicle velocity minus wind)."""
    va0 = x[3] - ext[1]
    va1 = x[4] - ext[2]
    va2 = x[5] - ext[3]
    # R^T v
    return (R[0, 0] * va0 + R[1, 0] * va1 + R[2, 0] * va2,
            R[0, 1] * va0 + R[1, 1] * va1 + R[2, 1] * va2,
            R[0, 2] * va0 + R[1, 2] * va1 + R[2, 2] * va2)


@njit(cache=True)
def _k_linear_drag(p, x, R, ext, omega, T, Fb, Mb, Fw):
    k = p[0]
    Fw[0] -= k * (x[3] - ext[1])
    Fw[1] -= k * (x[4] - ext[2])
    Fw[2] -= p[1] * k * (x[5] - ext[3])


@njit(cache=True)
def _k_angular_damping(p, x, R, ext, omega, T, Fb, Mb, Fw):
    k = p[0]
    Mb[0] -= k * x[10]
    Mb[1] -= k * x[11]
    Mb[2] -= k * x[12]


@njit(cache=True)
def _k_rotor_drag(p, P, x, R, ext, omega, T, Fb, Mb, Fw):
    # Each rotor's H-force acts at its hub r_i (body FLU) against the hub's in-plane airspeed
    # u_i = v_air + w x r_i:  H_i = -k_d |omega_i| (u_ix, u_iy, 0), moment r_i x H_i.  Summed:
    # the force -k_d sum|omega_i| v_air,xy (+ a w x r_i part that cancels on a symmetric frame at
    # equal speeds) and, from the yaw rate r, the yaw damping -k_d sum|omega_i| (x_i^2 + y_i^2) r
    # (plus -k_d sum|omega_i| (x_i v_y - y_i v_x), zero at equal speeds).
    k = p[0]
    n = int(P[I_N])
    vb0, vb1, _ = _air_body(x, R, ext)
    wx, wy, wz = x[10], x[11], x[12]
    for i in range(n):
        rx = P[I_ROT + i]
        ry = P[I_ROT + n + i]
        rz = P[I_ROT + 2 * n + i]
        c = k * abs(omega[i])
        h0 = -c * (vb0 + wy * rz - wz * ry)
        h1 = -c * (vb1 + wz * rx - wx * rz)
        Fb[0] += h0
        Fb[1] += h1
        # r x (h0, h1, 0)
        Mb[0] -= rz * h1
        Mb[1] += rz * h0
        Mb[2] += rx * h1 - ry * h0


@njit(cache=True)
def _k_body_drag(p, x, R, ext, omega, T, Fb, Mb, Fw):
    vb0, vb1, vb2 = _air_body(x, R, ext)
    if p[3] > 0.5:
        # RotorPy's parasitic drag: the airspeed's norm times each body component (-|v| C v)
        s = math.sqrt(vb0 * vb0 + vb1 * vb1 + vb2 * vb2)
        s0, s1, s2 = s, s, s
    else:
        s0, s1, s2 = abs(vb0), abs(vb1), abs(vb2)
    Fb[0] -= p[0] * s0 * vb0
    Fb[1] -= p[1] * s1 * vb1
    Fb[2] -= p[2] * s2 * vb2


@njit(cache=True)
def _k_rotor_tilt(p, x, R, ext, omega, T, Fb, Mb, Fw):
    # Rotor axes tilted tangentially by delta (twisted arms, mounts): each thrust has an
    # in-plane component T sin(delta) at lever l, all in one sense: Mz = (l sin(delta)) sum T.
    tz = 0.0
    for i in range(T.shape[0]):
        tz += T[i]
    Mb[2] += p[0] * tz


# inlined into the command hook (numba IR): called once per fine step by the lag loops, the call
# itself cost 3x the arithmetic (same operations, same numbers)
@njit(cache=True, inline="always")
def _k_battery_sag(p, ext, sref):
    v = ext[0]
    if v == v and v > 0.0 and p[0] > 0.0:  # v == v: not NaN
        scale = (v / p[0]) ** p[1]
        for i in range(sref.shape[0]):
            sref[i] *= scale


@njit(cache=True)
def _k_motor_efficiency(p, x, ext, omega, T, Q):
    i = int(p[0]) - 1
    if 0 <= i < T.shape[0]:
        T[i] *= p[1]
        Q[i] *= p[1]


@njit(cache=True)
def _k_coaxial(p, x, ext, omega, T, Q):
    mask = int(p[1])
    for i in range(T.shape[0]):
        if (mask >> i) & 1:
            T[i] *= p[0]
            Q[i] *= p[0]


@njit(cache=True)
def _k_ground_effect(p, x, ext, omega, T, Q):
    h = x[2]
    if h < 0.0:
        h = 0.0
    gain = 1.0 + p[0] * np.exp(-h / p[1])
    for i in range(T.shape[0]):
        T[i] *= gain


# the state-dependent thrust multiplier that term discovery (discovery/terms.py) fits and flies: the
# features of STATE_TERM_FEATURES, each normalised to the vehicle (v_h: the hover induced velocity,
# R: the rotor radius, omega_max: the top rotor speed); the numpy twin is state_term_features
@njit(cache=True)
def _k_state_term(p, x, ext, omega, T, Q):
    v_h, radius, w_max = p[0], p[1], p[2]
    va0 = x[3] - ext[1]
    va1 = x[4] - ext[2]
    va2 = x[5] - ext[3]
    mu = math.sqrt(va0 * va0 + va1 * va1) / v_h
    climb = max(va2, 0.0) / v_h
    descent = max(-va2, 0.0) / v_h
    z = max(x[2], radius)
    ground = (radius / (4.0 * z)) ** 2
    tilt = 2.0 * (x[7] * x[7] + x[8] * x[8])
    common = (1.0 + p[3] + p[4] * mu + p[5] * mu * mu + p[6] * climb + p[7] * descent + p[8] * descent * descent
              + p[9] * ground + p[12] * tilt)
    for i in range(T.shape[0]):
        u = omega[i] / w_max
        u4 = u * u * u * u
        gain = common + p[10] * u * u + p[11] * u4 + p[13] * u4 * u4
        T[i] *= min(max(gain, 0.1), 3.0)


# ---------------------------------------------------------------- effect classes


class LinearDrag(Effect):
    name = "linear_drag"
    param_names = ("k_n_s_m", "vertical")
    defaults = {"k_n_s_m": 0.0, "vertical": 1.0}
    units = {"k_n_s_m": "N/(m/s)", "vertical": "0 or 1"}
    ranges = {"k_n_s_m": (0.0, 1e4), "vertical": (0.0, 1.0)}
    description = ("drag linear in air-relative velocity, world frame: isotropic as PX4 SIH_KDV (``vertical`` 1, the "
                   "default), or horizontal only (``vertical`` 0: a drag identified from the horizontal specific "
                   "force alone, which says nothing of the vertical)")
    wrench_kernel = staticmethod(_k_linear_drag)
    discrete = ("vertical",)
    switches = {"vertical": ("horizontal only", "isotropic, PX4 SIH_KDV")}


class AngularDamping(Effect):
    name = "angular_damping"
    param_names = ("k_nm_s_rad",)
    defaults = {"k_nm_s_rad": 0.0}
    units = {"k_nm_s_rad": "N m/(rad/s)"}
    ranges = {"k_nm_s_rad": (0.0, 1e4)}
    description = "moment opposing body rates (PX4 SIH_KDW)"
    wrench_kernel = staticmethod(_k_angular_damping)


class RotorDrag(Effect):
    name = "rotor_drag"
    param_names = ("k_d",)
    defaults = {"k_d": 0.0}
    units = {"k_d": "N/((rad/s)(m/s))"}
    ranges = {"k_d": (0.0, 1e4)}
    description = ("in-plane rotor H-force drag at each hub: -k_d |omega_i| x the hub's in-plane airspeed "
                   "(v + w x r_i); its moment damps yaw by k_d sum|omega_i| (x_i^2 + y_i^2)")
    wrench_kernel = staticmethod(_k_rotor_drag)
    kernel_reads_vehicle = True


class BodyDrag(Effect):
    name = "body_drag"
    param_names = ("c_dx", "c_dy", "c_dz", "norm")
    defaults = {"c_dx": 0.0, "c_dy": 0.0, "c_dz": 0.0, "norm": 0.0}
    units = {"c_dx": "N/(m/s)^2", "c_dy": "N/(m/s)^2", "c_dz": "N/(m/s)^2", "norm": "0 or 1"}
    ranges = {"c_dx": (0.0, 1e7), "c_dy": (0.0, 1e7), "c_dz": (0.0, 1e7), "norm": (0.0, 1.0)}
    description = ("parasitic drag quadratic in air-relative velocity per body axis: -c_i |v_i| v_i, or with "
                   "norm 1 RotorPy's form -c_i |v| v_i (the airspeed's norm times the component)")
    wrench_kernel = staticmethod(_k_body_drag)
    switches = {"norm": ("per axis", "RotorPy's norm form")}


class BatterySag(Effect):
    name = "battery_sag"
    param_names = ("v_ref", "exponent")
    defaults = {"v_ref": 12.6, "exponent": 1.0}
    units = {"v_ref": "V", "exponent": "-"}
    ranges = {"v_ref": (0.1, 1000.0), "exponent": (-10.0, 10.0)}
    description = "rotor speed reached at a given command scales with (V/v_ref)^exponent"
    command_kernel = staticmethod(_k_battery_sag)


class MotorEfficiency(Effect):
    name = "motor_efficiency"
    param_names = ("motor", "efficiency")
    defaults = {"motor": 1.0, "efficiency": 1.0}
    units = {"motor": "1-based PX4 index", "efficiency": "thrust ratio"}
    discrete = ("motor",)
    ranges = {"motor": (1.0, 32.0), "efficiency": (0.0, 2.0)}
    description = "one motor gives a fraction of the thrust (and torque) it should"
    rotor_kernel = staticmethod(_k_motor_efficiency)

    @classmethod
    def check_params(cls, params, n_rotors=None):
        bad = super().check_params({k: v for k, v in params.items() if k == "motor"}, n_rotors)
        if bad is None and "motor" in params:
            m = float(params["motor"])
            top = int(n_rotors) if n_rotors is not None else int(cls.ranges["motor"][1])
            if m != int(m) or not 1 <= m <= top:
                what = f"this vehicle has {n_rotors} rotors" if n_rotors is not None else "1-based PX4 index"
                return "motor", f"expected an integer motor index 1..{top} ({what}), got {m:g}"
        return bad or super().check_params(params, n_rotors)


class Coaxial(Effect):
    name = "coaxial"
    param_names = ("efficiency", "lower_mask")
    defaults = {"efficiency": 0.8, "lower_mask": 0.0}
    units = {"efficiency": "lower/upper thrust ratio at equal command",
             "lower_mask": "bit i set: rotor i (0-based, PX4 motor i+1) is the lower rotor of a coaxial pair"}
    ranges = {"efficiency": (0.1, 1.5), "lower_mask": (0.0, 2.0 ** 31 - 1)}
    discrete = ("lower_mask",)
    description = ("coaxial pairs: the lower rotor works in the upper one's wake and gives ``efficiency`` of "
                   "the thrust (and, Q = km T, of the torque) the same command gives the upper one")
    rotor_kernel = staticmethod(_k_coaxial)

    @classmethod
    def check_params(cls, params, n_rotors=None):
        bad = super().check_params(params, n_rotors)
        if bad is None and "lower_mask" in params:
            m = float(params["lower_mask"])
            top = 2 ** int(n_rotors) - 1 if n_rotors is not None else 2 ** 31 - 1
            if m != int(m) or not 0 <= m <= top:
                return "lower_mask", (f"expected an integer bit mask of rotors 0..{(n_rotors or 31) - 1} "
                                      f"(0..{top}), got {m:g}")
        return bad


class GroundEffect(Effect):
    name = "ground_effect"
    param_names = ("coefficient", "height_scale")
    defaults = {"coefficient": 0.0, "height_scale": 0.5}
    units = {"coefficient": "-", "height_scale": "m"}
    ranges = {"coefficient": (0.0, 10.0), "height_scale": (1e-3, 100.0)}
    description = "thrust multiplied by 1 + coefficient*exp(-height/height_scale) near the ground"
    rotor_kernel = staticmethod(_k_ground_effect)


def centre_of_mass(effects) -> np.ndarray:
    """Where ``effects`` put the centre of mass together [m, body FLU] (the sum of their :meth:`Effect.com_flu_m`;
    zero for none), for :func:`twin_nodes.physics.core.pack`."""
    return np.sum([e.com_flu_m() for e in effects], axis=0) if effects else np.zeros(3)


class ComOffset(Effect):
    name = "com_offset"
    param_names = ("dx", "dy")
    defaults = {"dx": 0.0, "dy": 0.0}
    units = {"dx": "m (body forward)", "dy": "m (body left)"}
    ranges = {"dx": (-100.0, 100.0), "dy": (-100.0, 100.0)}
    description = ("centre of mass displaced from the geometric centre the rotors are placed about: every rotor "
                   "sits at r_i - d from it, so the thrust (-d x F), the rotor drag's H-forces (-d x H, and the "
                   "hubs' airspeed w x (r_i - d)) all act about the moved centre of mass")

    def com_flu_m(self) -> tuple[float, float, float]:
        return (self.params["dx"], self.params["dy"], 0.0)


class RotorTilt(Effect):
    name = "rotor_tilt"
    param_names = ("lever_m",)
    defaults = {"lever_m": 0.0}
    units = {"lever_m": "m (l sin(delta): yaw moment per newton of total thrust, + = CCW seen from above)"}
    ranges = {"lever_m": (-1.0, 1.0)}
    description = ("rotor axes tilted tangentially (twisted arms or mounts): a yaw moment proportional to "
                   "the total thrust, which the yaw controller trims out with a static motor differential")
    wrench_kernel = staticmethod(_k_rotor_tilt)


class Wind(Effect):
    name = "wind"
    param_names = ("vx", "vy", "gust_std")
    defaults = {"vx": 0.0, "vy": 0.0, "gust_std": 0.0}
    units = {"vx": "m/s (ENU east)", "vy": "m/s (ENU north)", "gust_std": "m/s"}
    ranges = {"vx": (-100.0, 100.0), "vy": (-100.0, 100.0), "gust_std": (0.0, 50.0)}
    description = "steady wind plus first-order (2 s) gusts; acts through the model's drag terms"
    gust_time_constant_s: ClassVar[float] = 2.0

    def exogenous(self, t, ext, rng):
        ext = ext.copy()
        n = len(t)
        gust = np.zeros((n, 3))
        if self.params["gust_std"] > 0 and n > 1:
            dt = float(np.median(np.diff(t)))
            a = np.exp(-dt / self.gust_time_constant_s)
            w = rng.standard_normal((n, 3)) * self.params["gust_std"] * np.sqrt(1 - a * a)
            g = rng.standard_normal(3) * self.params["gust_std"]
            for i in range(n):
                g = a * g + w[i]
                gust[i] = g
            gust[:, 2] *= 0.3  # vertical gusts are weaker
        ext[:, EXT_WIND] += self.params["vx"] + gust[:, 0]
        ext[:, EXT_WIND + 1] += self.params["vy"] + gust[:, 1]
        ext[:, EXT_WIND + 2] += gust[:, 2]
        return ext


class ActuatorDelay(Effect):
    name = "actuator_delay"
    param_names = ("delay",)
    defaults = {"delay": 0.0}
    units = {"delay": "s"}
    ranges = {"delay": (0.0, 2.0)}
    description = "pure delay between motor command and rotor response"

    def command_delay_s(self) -> float:
        return self.params["delay"]


class MotorTimeConstant(Effect):
    name = "motor_time_constant"
    param_names = ("tau_up", "tau_down")
    units = {"tau_up": "s", "tau_down": "s"}
    ranges = {"tau_up": (0.0, 10.0), "tau_down": (0.0, 10.0)}
    description = "rotor lag time constants differ from the model"

    def apply_to_params(self, vp):
        return vp.replace_rotors(tau_up_s=self.params["tau_up"], tau_down_s=self.params["tau_down"])


class Mass(Effect):
    name = "mass"
    param_names = ("mass",)
    units = {"mass": "kg"}
    ranges = {"mass": (1e-3, 1e4)}
    description = "vehicle heavier or lighter than modelled (payload)"

    def apply_to_params(self, vp):
        return vp.replace(mass_kg=self.params["mass"])


class ThrustCoefficient(Effect):
    name = "thrust_coefficient"
    param_names = ("kt_scale",)
    defaults = {"kt_scale": 1.0}
    units = {"kt_scale": "ratio"}
    ranges = {"kt_scale": (0.01, 100.0)}
    description = "every rotor gives more/less thrust per command than modelled"

    def apply_to_params(self, vp):
        r = vp.rotors
        s = self.params["kt_scale"]
        # Q = km T, so the reaction torque scales with the thrust too.
        return vp.replace_rotors(kt_n_s2_rad2=r.kt_n_s2_rad2 * s, thrust_max_n=r.thrust_max_n * s)


class YawMoment(Effect):
    name = "yaw_moment"
    param_names = ("km",)
    units = {"km": "m"}
    ranges = {"km": (0.0, 1.0)}
    description = "rotor reaction-torque constant differs (Q = km T)"

    def apply_to_params(self, vp):
        return vp.replace_rotors(km_m=self.params["km"])


class Inertia(Effect):
    name = "inertia"
    param_names = ("ixx", "iyy", "izz")
    units = {"ixx": "kg m^2", "iyy": "kg m^2", "izz": "kg m^2"}
    ranges = {"ixx": (1e-9, 1e6), "iyy": (1e-9, 1e6), "izz": (1e-9, 1e6)}
    description = "principal moments of inertia differ"

    def apply_to_params(self, vp):
        inertia = vp.inertia.copy()
        inertia[0, 0], inertia[1, 1], inertia[2, 2] = (self.params[k] for k in ("ixx", "iyy", "izz"))
        return vp.replace(inertia_kg_m2=tuple(tuple(float(e) for e in row) for row in inertia))


#: the state term's features, in its coefficient order (see ``state_term_features``)
STATE_TERM_FEATURES = ("mu", "mu2", "climb", "descent", "descent2", "ground", "omega2", "omega4", "tilt", "omega8")
#: what each feature is, in words (normalised to the vehicle)
STATE_TERM_MEANING = {
    "mu": "horizontal airspeed / v_h", "mu2": "(horizontal airspeed / v_h)^2", "climb": "climb rate / v_h",
    "descent": "descent rate / v_h", "descent2": "(descent rate / v_h)^2", "ground": "(R / 4z)^2",
    "omega2": "(omega / omega_max)^2", "omega4": "(omega / omega_max)^4", "tilt": "1 - cos(tilt)",
    "omega8": "(omega / omega_max)^8"}


def state_term_features(v_air_enu: np.ndarray, height_m: np.ndarray, q_wxyz: np.ndarray, omega: np.ndarray,
                        v_h: float, radius: float, omega_max: float) -> np.ndarray:
    """The state term's features (T, N, 10) in ``STATE_TERM_FEATURES`` order, per sample and rotor.

    ``v_air_enu`` (T, 3) air-relative velocity ENU [m/s], ``height_m`` (T,) above ground, ``q_wxyz``
    (T, 4) FLU->ENU, ``omega`` (T, N) rotor speeds [rad/s].  The numpy twin of ``_k_state_term``
    (a test checks both agree)."""
    v = np.asarray(v_air_enu, float)
    mu = np.hypot(v[:, 0], v[:, 1]) / v_h
    climb = np.maximum(v[:, 2], 0.0) / v_h
    descent = np.maximum(-v[:, 2], 0.0) / v_h
    ground = (radius / (4.0 * np.maximum(np.asarray(height_m, float), radius))) ** 2
    q = np.asarray(q_wxyz, float)
    tilt = 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2)
    u = np.asarray(omega, float) / omega_max
    n = u.shape[1]
    common = np.stack([mu, mu ** 2, climb, descent, descent ** 2, ground], axis=1)
    out = np.empty((len(mu), n, len(STATE_TERM_FEATURES)))
    out[:, :, 0:6] = common[:, None, :]
    out[:, :, 6] = u ** 2
    out[:, :, 7] = u ** 4
    out[:, :, 8] = tilt[:, None]
    out[:, :, 9] = u ** 8
    return out


class StateTerm(Effect):
    name = "state_term"
    param_names = ("v_h", "radius", "omega_max", "c_one") + tuple(f"c_{f}" for f in STATE_TERM_FEATURES)
    defaults = {"v_h": 5.0, "radius": 0.1, "omega_max": 1000.0, "c_one": 0.0,
                **{f"c_{f}": 0.0 for f in STATE_TERM_FEATURES}}
    units = {"v_h": "m/s (hover induced velocity)", "radius": "m (rotor radius)", "omega_max": "rad/s",
             "c_one": "thrust fraction (a constant part, the thrust scale that comes with the shape)",
             **{f"c_{f}": f"thrust fraction per unit of {STATE_TERM_MEANING[f]}" for f in STATE_TERM_FEATURES}}
    ranges = {"v_h": (0.1, 100.0), "radius": (1e-3, 10.0), "omega_max": (1.0, 1e5), "c_one": (-0.9, 2.0),
              **{f"c_{f}": (-10.0, 10.0) for f in STATE_TERM_FEATURES}}
    description = ("a state-dependent thrust multiplier found by term discovery: every rotor's thrust times "
                   "1 + c_one + sum_k c_k f_k(state), f_k the normalised features of STATE_TERM_FEATURES "
                   "(the multiplier clipped to 0.1..3)")
    rotor_kernel = staticmethod(_k_state_term)


EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (LinearDrag, AngularDamping, RotorDrag, BodyDrag, BatterySag, MotorEfficiency,
                MotorTimeConstant, ActuatorDelay, Mass, ThrustCoefficient, YawMoment, ComOffset,
                RotorTilt, Wind, GroundEffect, Inertia, StateTerm, Coaxial)
}


def make_effect(name: str, **params: float) -> Effect:
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(sorted(EFFECTS))}")
    return EFFECTS[name](**params)


def effects_from_params(vp: "VehicleParams") -> list[Effect]:
    return [make_effect(n, **dict(p)) for n, p in vp.effects]


def effective_params(vp: "VehicleParams") -> "VehicleParams":
    """Apply every parameter-type effect in ``vp.effects`` and return the result."""
    out = vp
    for eff in effects_from_params(vp):
        out = eff.apply_to_params(out)
    return out


def replace_params(eff: Effect, **changes: float) -> Effect:
    new = dict(eff.params)
    new.update(changes)
    return type(eff)(**new)


__all__ = ["Effect", "EFFECTS", "EXT_SIZE", "default_ext", "make_effect", "effects_from_params",
           "effective_params", "replace_params"]


def parse_effect(spec: str) -> tuple[str, dict[str, float]]:
    """``'name:k=v,k=v'`` -> ``(name, {k: v})`` checked against :data:`EFFECTS`; ``''`` or ``'none'`` ->
    ``('none', {})``.  Raises TwinError (worded for an ``--effect`` option) on a bad spec."""
    from twin_nodes.base.errors import TwinError

    if spec in ("", "none"):
        return "none", {}
    name, _, rest = spec.partition(":")
    if name not in EFFECTS:
        raise TwinError(f"--effect: {name!r}: expected one of {', '.join(sorted(EFFECTS))}")
    params: dict[str, float] = {}
    for item in filter(None, rest.split(",")):
        k, eq, v = item.partition("=")
        if not eq or k not in EFFECTS[name].param_names:
            raise TwinError(f"--effect: {item!r}: expected k=v with k in {list(EFFECTS[name].param_names)}")
        try:
            params[k] = float(v)
        except ValueError:
            raise TwinError(f"--effect: {k}: expected a number, got {v!r}") from None
    return name, params
