"""What a PX4 flight log's own parameters say about the vehicle that flew.

PX4 logs carry the whole parameter set.  This module reads from it, with the source
of every value:

- the rotor layout: ``CA_ROTOR_COUNT``, ``CA_ROTORn_PX/PY/PZ`` [m, FRD] and the spin sign
  of ``CA_ROTORn_KM`` (> 0 = CCW) on PX4 >= v1.13; older logs (mixer files, no ``CA_*``)
  take the airframe's geometry from :data:`AIRFRAMES` by ``SYS_AUTOSTART``, else from PX4's own
  mixer geometry (:mod:`twin_nodes.vehicle.px4_geometry`: SYS_AUTOSTART -> ``set MIXER`` -> the
  mixer's ``R:`` key -> the geometry toml, PX4 1.8-1.13), else an ASSUMED generic layout of the
  ``MAV_TYPE`` class whose rotor count the moving motor outputs confirm.  Without ``CA_*`` the
  rotor count is checked against the motor outputs that move in the log.  Many PX4
  airframes give ``CA_ROTORn_PX/PY`` normalised to +-1 (only the ratios matter to the
  allocation); such a layout is scaled to the airframe's real arm length when the
  airframe is known, else the caller must supply one;
- the thrust curve ``THR_MDL_FAC`` and PX4's own hover estimate ``MPC_THR_HOVER``;
- the controller: PX4's position/velocity/attitude gains map one to one onto
  :class:`twin_nodes.twin.control.ControllerGains` (:func:`outer_loop_gains`); the rate
  gains are in PX4's normalised torque units and are converted to physical units with
  the vehicle's thrust slope and inertia (:func:`rate_gains_physical`), following PX4's
  control-allocation normalisation (``ControlAllocationPseudoInverse``: roll and pitch
  columns scaled so the mean non-zero entry has magnitude 1/sqrt(2) on a quad X, yaw so
  its largest entry is 1).

Positions come back in body FLU (REP-103); the FRD -> FLU change is the one in
:mod:`twin_nodes.base.frames`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from twin_nodes.base.constants import G_STANDARD_M_S2
from twin_nodes.base.errors import ParamsError
from twin_nodes.base.frames import frd_to_flu


@dataclass(frozen=True)
class Airframe:
    """Geometry (and a typical take-off mass) of a PX4 airframe whose parameters lack it."""

    name: str
    layout: str            # "quad_x": PX4 quad X, Motor1 front-right CCW
    arm_m: float           # centre to rotor axis [m]
    mass_kg: float         # typical take-off mass, used only when the user gives none
    source: str


#: PX4 airframes by SYS_AUTOSTART whose logs may lack a metric rotor layout.
AIRFRAMES: dict[int, Airframe] = {
    4001: Airframe("Generic Quadrotor X", "quad_x", 0.25, 1.5,
                   "generic: PX4 4001_quad_x gives no dimensions; 0.25 m arm (500 mm class) assumed"),
    4014: Airframe("Holybro S500", "quad_x", 0.24, 1.3,
                   "Holybro S500 frame, 480 mm wheelbase (vendor spec); ~1.3 kg with a 3S pack"),
    4019: Airframe("Holybro X500 V2", "quad_x", 0.25, 1.6,
                   "Holybro X500 V2 frame, 500 mm wheelbase (vendor spec); ~1.6 kg with a 4S pack"),
    10040: Airframe("PX4 SIH quadrotor X", "quad_x", 0.2 * math.sqrt(2.0), 1.0,
                    "PX4 simulator_sih quad X: arms 0.2 m along x and y (sih_params.c defaults)"),
}


@dataclass(frozen=True)
class RotorLayout:
    x_flu_m: tuple[float, ...]
    y_flu_m: tuple[float, ...]
    z_flu_m: tuple[float, ...]
    direction: tuple[int, ...]
    source: str
    #: coaxial pairs (0-based rotor indices): two rotors at one place (same x, y) spinning opposite
    #: ways; the lower one works in the upper one's wake (its own thrust loss is not identified yet)
    coaxial: tuple[tuple[int, int], ...] = ()


#: ASSUMED typical arm [m] (centre to the farthest rotor axis) by rotor count, when neither ``--arm-m``
#: nor a known airframe gives one: tri 0.30 (600 mm class), quad 0.25 (500 mm class, as 4001 above),
#: hexa 0.35, octo 0.45 (the larger frames those counts are built for)
CLASS_ARM_M = {2: 0.25, 3: 0.30, 4: 0.25, 6: 0.35, 8: 0.45}
#: MAV_TYPE -> the generic PX4 geometry key of that class (rc.vehicle_setup / rcS set MAV_TYPE from
#: the mixer: 2 quad, 13 hexa, 14 octo, 15 tri); 3 (coaxial helicopter) has no multirotor mixer
MAV_TYPE_GEOMETRY = {2: "4x", 13: "6x", 14: "8x", 15: "3y"}


def coaxial_pairs(x: np.ndarray, y: np.ndarray, direction: np.ndarray) -> tuple[tuple[int, int], ...]:
    """Pairs of rotors at one horizontal place (within 1e-6 of the largest radius) spinning opposite ways."""
    tol = 1e-6 * max(float(np.max(np.hypot(x, y))), 1e-9)
    pairs, used = [], set()
    for i in range(len(x)):
        for j in range(i + 1, len(x)):
            if (i not in used and j not in used and abs(x[i] - x[j]) <= tol and abs(y[i] - y[j]) <= tol
                    and direction[i] != direction[j]):
                pairs.append((i, j))
                used |= {i, j}
    return tuple(pairs)


def lower_rotors(layout: RotorLayout) -> tuple[tuple[int, ...], str]:
    """The lower rotor of each coaxial pair (0-based) and how it was told: the one lower on the body
    (smaller FLU z, i.e. larger ``CA_ROTORn_PZ``), else (both at one height in the log) the second of the
    pair, as PX4's coaxial geometries and airframes list the upper rotor first (ASSUMED)."""
    lower, assumed = [], 0
    for i, j in layout.coaxial:
        zi, zj = layout.z_flu_m[i], layout.z_flu_m[j]
        if abs(zi - zj) > 1e-6:
            lower.append(j if zj < zi else i)
        else:
            lower.append(j)
            assumed += 1
    how = ("by height (CA_ROTORn_PZ / the geometry's z)" if not assumed else
           f"{assumed} of {len(lower)} pairs at one height in the log: the second of each pair ASSUMED lower "
           f"(PX4 lists the upper rotor first)")
    return tuple(sorted(lower)), how


def _geometry_layout(key: str, arm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """PX4 geometry ``key`` (FRD, MAIN output order) scaled so its farthest rotor is ``arm`` [m] out."""
    from twin_nodes.vehicle.px4_geometry import GEOMETRIES
    rot = GEOMETRIES[key]["rotors"]
    pos = np.array([r[1] for r in rot], float)
    scale = arm / float(np.max(np.hypot(pos[:, 0], pos[:, 1])))
    return pos[:, 0] * scale, pos[:, 1] * scale, pos[:, 2] * scale, np.array([r[2] for r in rot])


def _check_moving(path: str, n: int, moving: tuple[int, str] | None, what: str) -> None:
    """Refuse, in one line, a rotor count that differs from the motor outputs moving in the log."""
    if moving is not None and moving[0] > 0 and moving[0] != n:
        raise ParamsError(path, moving[1].split(".")[0],
                          f"{n} rotors ({what}) but {moving[0]} motor outputs move in the log ({moving[1]}); "
                          f"supply a params file with --params")


def _arm(arm_m: float | None, n: int) -> tuple[float, str]:
    if arm_m is not None:
        return arm_m, "--arm-m"
    a = CLASS_ARM_M.get(n, 0.25)
    return a, f"ASSUMED {a:g} m arm, typical of a {n}-rotor frame; give --arm-m"


def _quad_x(arm_m: float) -> tuple[np.ndarray, np.ndarray]:
    """PX4 quad X in FRD: M1 (+,+), M2 (-,-), M3 (+,-), M4 (-,+); arms along the diagonals."""
    a = arm_m / math.sqrt(2.0)
    return np.array([a, -a, a, -a]), np.array([a, -a, -a, a])


def _shown(v: object) -> str:
    """A parameter value for a message: ``-4``, ``2.5``, ``inf``, ``1e+30``."""
    try:
        return f"{float(v):g}"  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        return repr(v)[:40]


def int_param(params: Mapping[str, float], name: str, path: str, lo: int, hi: int) -> int:
    """An integer PX4 parameter in ``lo..hi`` (absent or None: 0), else a one-line ParamsError."""
    v = params.get(name)
    if v is None:
        return 0
    try:
        f = float(v)
        ok = math.isfinite(f) and f.is_integer() and lo <= f <= hi
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise ParamsError(path, name, f"expected an integer {lo}..{hi}, got {_shown(v)}")
    return int(f)


def real_param(params: Mapping[str, float], name: str, path: str, default: float, lo: float, hi: float,
               unit: str) -> float:
    """A real PX4 parameter in ``lo..hi`` [unit] (absent: ``default``), else a one-line ParamsError."""
    v = params.get(name)
    if v is None:
        return float(default)
    try:
        f = float(v)
        ok = math.isfinite(f) and lo <= f <= hi
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise ParamsError(path, name, f"expected a finite number {lo:g}..{hi:g}{' ' + unit if unit else ''}, "
                                      f"got {_shown(v)}")
    return f


#: rotor position parameters CA_ROTORn_PX/PY/PZ [m]: within twin_nodes.vehicle.params.LIMITS["position_m"]
POSITION_M = 100.0
#: most rotors (twin_nodes.vehicle.params.LIMITS["rotors"]; PX4 has CA_ROTOR0..11)
MAX_ROTORS = 32


def rotor_layout(params: Mapping[str, float], path: str = "<log>", arm_m: float | None = None,
                 moving_outputs: tuple[int, str] | None = None) -> RotorLayout:
    """The rotor layout from a log's parameters (see the module docstring).

    ``arm_m`` [m] scales a normalised layout (or gives an unknown airframe's arm).  ``moving_outputs``
    (count, topic: ``FlightLog.moving_outputs``) is the number of motor outputs that move in the log:
    without ``CA_*`` the layout's rotor count must equal it (a one-line ParamsError naming both
    counts), and it confirms the rotor count of a ``MAV_TYPE`` generic layout.
    Raises :class:`ParamsError` naming the missing or out-of-range parameter when nothing fits:
    ``CA_ROTOR_COUNT`` an integer 0..32, each ``CA_ROTORn_PX/PY/PZ`` finite and within 100 m,
    ``CA_ROTORn_KM`` finite in -1..1, and the positions spanning roll and pitch."""
    from twin_nodes.vehicle.params import LIMITS, rotor_span_m

    autostart = int_param(params, "SYS_AUTOSTART", path, 0, 99_999_999)
    airframe = AIRFRAMES.get(autostart)
    n = int_param(params, "CA_ROTOR_COUNT", path, 0, MAX_ROTORS)
    if arm_m is not None and not (math.isfinite(arm_m) and 0.0 < arm_m <= POSITION_M):
        raise ParamsError(path, "--arm-m", f"expected a finite arm length in (0, {POSITION_M:g}] m, got {arm_m!r}")
    if n > 0:
        def pos(i: int, axis: str) -> float:
            return real_param(params, f"CA_ROTOR{i}_P{axis}", path, 0.0, -POSITION_M, POSITION_M, "m")
        px = np.array([pos(i, "X") for i in range(n)])
        py = np.array([pos(i, "Y") for i in range(n)])
        pz = np.array([pos(i, "Z") for i in range(n)])
        km = np.array([real_param(params, f"CA_ROTOR{i}_KM", path, 0.05, -1.0, 1.0, "") for i in range(n)])
        source = f"log parameters CA_ROTOR0..{n - 1}_PX/PY/PZ/KM"
        radius = np.hypot(px, py)
        if not np.all(radius > 1e-6):
            raise ParamsError(path, f"CA_ROTOR{int(np.argmin(radius))}_PX",
                              "a rotor position away from the centre (CA_ROTOR_COUNT is set but the positions "
                              "are missing or zero); supply a params file with --params")
        if np.allclose(radius, radius[0]) and abs(radius[0] - math.sqrt(2.0)) < 1e-6:
            if arm_m is not None or airframe is None:
                # an airframe outside the table (e.g. 1.14+ ids such as 4003): the class's ASSUMED arm; the
                # inertia identified on the flight is relative to it (tests/test_classes.py)
                target, how = _arm(arm_m, n)
            else:
                target, how = airframe.arm_m, airframe.source
            scale = target / radius[0]
            px, py, pz = px * scale, py * scale, pz * scale
            source += f", normalised +-1 layout scaled to a {target:.3f} m arm ({how})"
        span = rotor_span_m(px, py)
        if not span >= LIMITS["span_m"]:
            raise ParamsError(path, "CA_ROTOR0_PX",
                              f"expected rotor positions CA_ROTOR0..{n - 1}_PX/PY that span roll and pitch (an RMS "
                              f"spread of at least {LIMITS['span_m']:g} m along every horizontal axis), got "
                              f"{span:.3g} m; supply a params file with --params")
        direction = np.where(km >= 0.0, 1, -1)
    elif airframe is not None:
        px, py = _quad_x(arm_m if arm_m is not None else airframe.arm_m)
        pz = np.zeros(4)
        direction = np.array([1, 1, -1, -1])
        source = (f"airframe {autostart} ({airframe.name}, no CA_* parameters in this log): PX4 quad X "
                  f"layout, {'--arm-m' if arm_m is not None else airframe.source}")
        _check_moving(path, 4, moving_outputs, f"airframe {autostart}")
    else:
        px, py, pz, direction, source = _mixer_or_class_layout(params, path, autostart, arm_m, moving_outputs)
    flu = frd_to_flu(np.column_stack([px, py, pz]))
    return RotorLayout(tuple(float(v) for v in flu[:, 0]), tuple(float(v) for v in flu[:, 1]),
                       tuple(float(v) for v in flu[:, 2]), tuple(int(d) for d in direction), source,
                       coaxial_pairs(px, py, direction))


def _mixer_or_class_layout(params: Mapping[str, float], path: str, autostart: int, arm_m: float | None,
                           moving: tuple[int, str] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                     np.ndarray, str]:
    """A log without ``CA_*`` whose airframe is not in :data:`AIRFRAMES`: PX4's mixer geometry of the
    airframe (:mod:`twin_nodes.vehicle.px4_geometry`), else an ASSUMED generic layout of the
    ``MAV_TYPE`` class confirmed by the moving motor outputs, else a one-line ParamsError."""
    from twin_nodes.vehicle.px4_geometry import AUTOSTART, GEOMETRIES
    mav_type = int_param(params, "MAV_TYPE", path, -1, 1_000_000) if "MAV_TYPE" in params else None
    rows = AUTOSTART.get(autostart)
    if rows:
        keys = sorted({(r[3], r[4]) for r in rows})
        if len(keys) > 1:
            raise ParamsError(path, "SYS_AUTOSTART",
                              f"one mixer geometry for airframe {autostart}; PX4 changed it between versions ("
                              + ", ".join(f"{r[2]} -> {r[3]} at {r[5][0]}..{r[5][-1]}" for r in rows)
                              + "); supply a params file with --params")
        script, name, mixer, key, yaw, commits = rows[-1]
        geom = GEOMETRIES[key]
        n = len(geom["rotors"])
        if any(tuple(r[3]) != (0.0, 0.0, -1.0) for r in geom["rotors"]):
            raise ParamsError(path, "SYS_AUTOSTART", f"a multirotor with upward thrust axes; airframe {autostart}'s "
                                                     f"geometry {key} has a tilted rotor; supply --params")
        cls = MAV_TYPE_GEOMETRY.get(mav_type) if mav_type is not None else None
        expect = len(GEOMETRIES[cls]["rotors"]) if cls is not None else None
        if expect is not None and expect != n:
            raise ParamsError(path, "MAV_TYPE", f"{n} rotors (MAV_TYPE {mav_type} says {expect}) for airframe "
                                                f"{autostart}'s mixer {mixer} (geometry {key}); supply --params")
        _check_moving(path, n, moving, f"airframe {autostart}'s PX4 mixer {mixer}")
        arm, arm_src = _arm(arm_m, n)
        px, py, pz, spin = _geometry_layout(key, arm)
        source = (f"airframe {autostart} ({name}, no CA_* parameters in this log): PX4 mixer {mixer} -> geometry "
                  f"{key} ({geom['file']}.toml, {script} @ PX4 {commits[0]}..{commits[-1]})"
                  + (", yaw reversed by the mixer's R: line" if yaw < 0 else "") + f", {arm_src}")
        return px, py, pz, spin * yaw, source
    key = MAV_TYPE_GEOMETRY.get(mav_type) if mav_type is not None else None
    if key is None or moving is None or moving[0] == 0:
        if mav_type == 3:
            why = "MAV_TYPE 3 is a coaxial helicopter (rotor heads with servos), not a multirotor the twin models"
        elif key is None:
            why = f"MAV_TYPE {mav_type if mav_type is not None else '(absent)'} names no multirotor class"
        else:
            why = f"MAV_TYPE {mav_type} names a class but no motor outputs move in the log to confirm the rotor count"
        raise ParamsError(path, "CA_ROTOR_COUNT",
                          f"rotor geometry: the log has no CA_* parameters, SYS_AUTOSTART {autostart} is not a "
                          f"known airframe ({len(AUTOSTART) + len(AIRFRAMES)} PX4 1.8-1.13 ids known) and {why}; "
                          f"supply a params file with --params")
    n = len(GEOMETRIES[key]["rotors"])
    _check_moving(path, n, moving, f"MAV_TYPE {mav_type}")
    arm, arm_src = _arm(arm_m, n)
    px, py, pz, spin = _geometry_layout(key, arm)
    source = (f"ASSUMED generic PX4 {GEOMETRIES[key]['file']} layout (geometry {key}): SYS_AUTOSTART {autostart} is "
              f"not a known airframe, MAV_TYPE {mav_type} and {moving[0]} moving motor outputs ({moving[1]}); "
              f"give --params for the real one; {arm_src}")
    return px, py, pz, spin, source


def param(params: Mapping[str, float], name: str, default: float) -> tuple[float, str]:
    """A PX4 parameter with its source: the log's value, else PX4's default."""
    if name in params and params[name] is not None and math.isfinite(float(params[name])):
        return float(params[name]), f"log parameter {name}"
    return float(default), f"PX4 default {name}"


#: ControllerGains key -> (PX4 parameter(s), PX4 default); first name present wins.
OUTER_LOOP = {
    "xy_p_1_s": (("MPC_XY_P",), 0.95),
    "z_p_1_s": (("MPC_Z_P",), 1.0),
    "xy_vel_p_1_s": (("MPC_XY_VEL_P_ACC",), 1.8),
    "xy_vel_i_1_s2": (("MPC_XY_VEL_I_ACC",), 0.4),
    "xy_vel_d": (("MPC_XY_VEL_D_ACC",), 0.2),
    "z_vel_p_1_s": (("MPC_Z_VEL_P_ACC",), 4.0),
    "z_vel_i_1_s2": (("MPC_Z_VEL_I_ACC",), 2.0),
    "z_vel_d": (("MPC_Z_VEL_D_ACC",), 0.0),
    "xy_vel_max_m_s": (("MPC_XY_VEL_MAX",), 12.0),
    "z_vel_max_up_m_s": (("MPC_Z_VEL_MAX_UP",), 3.0),
    "z_vel_max_dn_m_s": (("MPC_Z_VEL_MAX_DN",), 1.5),
    "tilt_max_deg": (("MPC_TILTMAX_AIR",), 45.0),
    "thr_min": (("MPC_THR_MIN",), 0.12),
    "thr_max": (("MPC_THR_MAX",), 1.0),
    "roll_p_1_s": (("MC_ROLL_P",), 6.5),
    "pitch_p_1_s": (("MC_PITCH_P",), 6.5),
    "yaw_p_1_s": (("MC_YAW_P",), 2.8),
    "yaw_weight": (("MC_YAW_WEIGHT",), 0.4),
    "rollrate_max_deg_s": (("MC_ROLLRATE_MAX",), 220.0),
    "yawrate_max_deg_s": (("MC_YAWRATE_MAX",), 200.0),
}

#: PX4 < v1.12 velocity gains were in normalised thrust per m/s; PX4 converts them to
#: the _ACC form by multiplying with g / hover thrust (mc_pos_control's parameter migration).
LEGACY_VEL = {"xy_vel_p_1_s": "MPC_XY_VEL_P", "xy_vel_i_1_s2": "MPC_XY_VEL_I", "xy_vel_d": "MPC_XY_VEL_D",
              "z_vel_p_1_s": "MPC_Z_VEL_P", "z_vel_i_1_s2": "MPC_Z_VEL_I", "z_vel_d": "MPC_Z_VEL_D"}


def outer_loop_gains(params: Mapping[str, float], hover_thrust: float,
                     g_m_s2: float = G_STANDARD_M_S2) -> tuple[dict[str, float], dict[str, str]]:
    """Position, velocity and attitude gains and limits (ControllerGains keys) with sources."""
    gains, sources = {}, {}
    for key, (names, default) in OUTER_LOOP.items():
        name = next((nm for nm in names if nm in params), None)
        legacy = LEGACY_VEL.get(key)
        if name is None and legacy is not None and legacy in params:
            gains[key] = float(params[legacy]) * g_m_s2 / hover_thrust
            sources[key] = f"log parameter {legacy} x g / hover thrust (pre-v1.12 units)"
            continue
        gains[key], sources[key] = param(params, name or names[0], default)
    if "MC_YAW_WEIGHT" not in params and "MC_YAW_P" in params:
        _old_yaw_law(params, gains, sources)
    gains["airmode"], sources["airmode"], gains["desat_min_effect"], sources["desat_min_effect"] = allocation_kind(params)
    return gains, sources


def _old_yaw_law(params: Mapping[str, float], gains: dict[str, float], sources: dict[str, str]) -> None:
    """PX4 before 96bbc63 (2020-03, v1.11; no ``MC_YAW_WEIGHT``): the reduced-attitude mix weighs yaw by
    ``yaw_w = MC_YAW_P / ((MC_ROLL_P + MC_PITCH_P) / 2)`` (clamped to [0, 1]) and then applies
    ``MC_YAW_P`` undivided (``mc_att_control_main.cpp`` 1.8, ``AttitudeControl.cpp`` 1.9-1.10), so the
    yaw error reaches the rate setpoint with ``MC_YAW_P x yaw_w``; the twin's yaw law is that gain."""
    rp = 0.5 * (gains["roll_p_1_s"] + gains["pitch_p_1_s"])
    w = min(max(gains["yaw_p_1_s"] / rp, 0.0), 1.0) if rp > 0 else 1.0
    gains["yaw_weight"] = w
    sources["yaw_weight"] = (f"MC_YAW_P / mean(MC_ROLL_P, MC_PITCH_P) = {w:.3g} (PX4 < 1.11 has no MC_YAW_WEIGHT: "
                             "its yaw weight)")
    gains["yaw_p_1_s"] *= w
    sources["yaw_p_1_s"] = (f"log parameter MC_YAW_P x that yaw weight = {gains['yaw_p_1_s']:.3g} (PX4 < 1.11 "
                            "did not divide the yaw gain by the weight)")


#: PX4's desaturation skips outputs whose share of the direction is below this: 0.2 in the control
#: allocator (ControlAllocationSequentialDesaturation::computeDesaturationGain), FLT_EPSILON in the mixer
DESAT_MIN_EFFECT = {"allocator": 0.2, "mixer": 1.1920929e-07}


def allocation_kind(params: Mapping[str, float]) -> tuple[float, str, float, str]:
    """``MC_AIRMODE`` (0 off, 1 roll/pitch, 2 roll/pitch/yaw; anything else read as PX4 reads it: off)
    and which of PX4's two allocations flew the log: the control allocator where ``SYS_CTRL_ALLOC`` is 1
    (PX4 1.13) or, without that parameter, where ``CA_ROTOR_COUNT`` is set (PX4 >= 1.14); else the
    multirotor mixer (PX4 <= 1.13).  Both desaturate in the same sequence; they differ in the skip
    threshold (``desat_min_effect``)."""
    am, am_src = param(params, "MC_AIRMODE", 0.0)
    if am not in (0.0, 1.0, 2.0):
        am_src, am = f"log parameter MC_AIRMODE {am:g} is not 0/1/2: PX4's default branch, airmode off", 0.0
    if "SYS_CTRL_ALLOC" in params:
        kind = "allocator" if float(params["SYS_CTRL_ALLOC"]) == 1.0 else "mixer"
        why = f"SYS_CTRL_ALLOC {float(params['SYS_CTRL_ALLOC']):g}"
    else:
        kind = "allocator" if "CA_ROTOR_COUNT" in params else "mixer"
        why = "CA_ROTOR_COUNT in the log" if kind == "allocator" else "no CA_ROTOR_COUNT in the log"
    what = ("PX4 control allocator, sequential desaturation" if kind == "allocator"
            else "PX4 multirotor mixer desaturation")
    return am, am_src, DESAT_MIN_EFFECT[kind], f"{what} ({why})"


@dataclass(frozen=True)
class RateGainsPx4:
    """PX4's rate-loop gains in its normalised torque units (the K factor folded in)."""

    roll_p: float
    roll_i: float
    roll_d: float
    pitch_p: float
    pitch_i: float
    pitch_d: float
    yaw_p: float
    yaw_i: float
    sources: tuple[str, ...]
    #: the integrators' limits MC_RR/PR/YR_INT_LIM (normalised torque, PX4's default 0.3 each)
    int_lim: tuple[float, float, float] = (0.3, 0.3, 0.3)

    @classmethod
    def from_params(cls, params: Mapping[str, float]) -> "RateGainsPx4":
        vals, srcs = {}, []
        defaults = {"ROLLRATE_P": 0.15, "ROLLRATE_I": 0.2, "ROLLRATE_D": 0.003, "ROLLRATE_K": 1.0,
                    "PITCHRATE_P": 0.15, "PITCHRATE_I": 0.2, "PITCHRATE_D": 0.003, "PITCHRATE_K": 1.0,
                    "YAWRATE_P": 0.2, "YAWRATE_I": 0.1, "YAWRATE_K": 1.0}
        for k, d in defaults.items():
            vals[k], s = param(params, f"MC_{k}", d)
            srcs.append(s)
        lims = []
        for ax in ("RR", "PR", "YR"):
            v, s = param(params, f"MC_{ax}_INT_LIM", 0.3)
            lims.append(max(float(v), 0.0))
            srcs.append(s)
        k_r, k_p, k_y = vals["ROLLRATE_K"], vals["PITCHRATE_K"], vals["YAWRATE_K"]
        return cls(k_r * vals["ROLLRATE_P"], k_r * vals["ROLLRATE_I"], k_r * vals["ROLLRATE_D"],
                   k_p * vals["PITCHRATE_P"], k_p * vals["PITCHRATE_I"], k_p * vals["PITCHRATE_D"],
                   k_y * vals["YAWRATE_P"], k_y * vals["YAWRATE_I"], tuple(srcs), tuple(lims))


def normalised_mix(x_flu: np.ndarray, y_flu: np.ndarray, direction: np.ndarray, km_m: float) -> np.ndarray:
    """PX4's normalised allocation (N, 3): motor command change per unit roll, pitch, yaw torque setpoint.

    The pseudo-inverse of the effectiveness (unit thrust per motor) with PX4's scaling:
    roll and pitch columns divided by ``max(sqrt(|col|^2 / (n_nonzero / 2)))``, yaw by its
    largest entry (``ControlAllocationPseudoInverse::updateControlAllocationMatrixScale``)."""
    B = np.vstack([np.asarray(y_flu, float), -np.asarray(x_flu, float),
                   -np.asarray(direction, float) * km_m, np.ones(len(x_flu))])
    mix = np.linalg.pinv(B)[:, :3]
    scales = []
    for c in (0, 1):
        nz = int(np.sum(np.abs(mix[:, c]) > 1e-3))
        scales.append(math.sqrt(float(mix[:, c] @ mix[:, c]) / (nz / 2.0)) if nz else 1.0)
    rp = max(scales)
    mix[:, 0] /= rp
    mix[:, 1] /= rp
    ymax = float(np.max(mix[:, 2]))
    if ymax > 1e-12:
        mix[:, 2] /= ymax
    return mix


def torque_moments(x_flu: np.ndarray, y_flu: np.ndarray, direction: np.ndarray, km_m: float,
                   thrust_slope_n: float, km_physical_m: float | None = None) -> np.ndarray:
    """Roll, pitch and yaw moment [N m] of a unit roll, pitch and yaw torque setpoint: PX4's normalised
    mix (:func:`normalised_mix`, with PX4's own torque ratio ``km_m``) moves the motor commands, times
    the thrust slope dT/du [N] at hover, on the lever arms; the yaw moment with the vehicle's torque
    ratio ``km_physical_m`` (default ``km_m``)."""
    dT = thrust_slope_n * normalised_mix(x_flu, y_flu, direction, km_m)  # (N, 3) thrust per unit setpoint
    km_phys = km_m if km_physical_m is None else km_physical_m
    return np.array([float(np.asarray(y_flu) @ dT[:, 0]), float(-np.asarray(x_flu) @ dT[:, 1]),
                     float((-np.asarray(direction, float) * km_phys) @ dT[:, 2])])


def rate_gains_physical(px4: RateGainsPx4, x_flu: np.ndarray, y_flu: np.ndarray, direction: np.ndarray,
                        km_m: float, thrust_slope_n: float, inertia_kg_m2: tuple[float, float, float],
                        km_physical_m: float | None = None) -> dict[str, float]:
    """PX4's normalised rate gains as the twin's physical ones (ControllerGains keys).

    A unit torque setpoint moves the motor commands by PX4's normalised mix; times the thrust
    slope dT/du [N] at hover and the lever arms that is a moment [N m], over the inertia an
    angular acceleration.  So ``Kp [rad/s^2 per rad/s] = P_px4 * moment_per_unit / I``;
    the same factor converts I and D.  Roll and pitch share one gain set in the twin:
    the mean of the two axes.

    ``km_m`` is PX4's own torque ratio (``CA_ROTORn_KM``): it shapes PX4's mix.  The yaw moment
    those motor changes make is the *vehicle's* ratio, ``km_physical_m`` (default ``km_m``): the
    twin's km, against which its Izz was identified.  Using PX4's 0.05 there for a twin with km
    0.02 made every from-log twin's yaw rate gain 2.5x PX4's.

    The integrators' limits (``MC_*R_INT_LIM``, a normalised torque, not a gain) convert per axis by the
    same factor: PX4 holds a steady moment of up to ``INT_LIM`` times the unit torque's moment on each axis
    (a drag moment, a centre-of-mass offset), whatever that axis's inertia; one shared 10 rad/s^2 held
    0.055 N m about a 0.0055 kg m^2 pitch axis where PX4 held 1.4 N m (mantis_follow_00018)."""
    a_roll, a_pitch, a_yaw = (torque_moments(x_flu, y_flu, direction, km_m, thrust_slope_n, km_physical_m)
                              / np.asarray(inertia_kg_m2, float))
    return {
        "rate_p_1_s": 0.5 * (px4.roll_p * a_roll + px4.pitch_p * a_pitch),
        "rate_i_1_s2": 0.5 * (px4.roll_i * a_roll + px4.pitch_i * a_pitch),
        "rate_d": 0.5 * (px4.roll_d * a_roll + px4.pitch_d * a_pitch),
        "yawrate_p_1_s": px4.yaw_p * a_yaw,
        "yawrate_i_1_s2": px4.yaw_i * a_yaw,
        "rate_i_max_rad_s2": px4.int_lim[0] * a_roll,
        "pitchrate_i_max_rad_s2": px4.int_lim[1] * a_pitch,
        "yawrate_i_max_rad_s2": px4.int_lim[2] * a_yaw,
    }


@dataclass(frozen=True)
class SensorTiming:
    """How late PX4's logged signals are against what the airframe did, from the log's parameters.

    ``gyro_filter_s``: ``vehicle_angular_velocity`` is the gyro through PX4's 2nd-order Butterworth
    low-pass at ``IMU_GYRO_CUTOFF``; below the cut-off it delays by its group delay, sqrt(2)/(2 pi fc)
    (5.6 ms at PX4's default 40 Hz).  ``imu_average_s``: ``sensor_combined`` is the IMU integrated over
    one ``IMU_INTEG_RATE`` interval and stamped at its end, i.e. the interval's mean, half an interval
    late.  ``command_hold_s``: the logged motor command is held until the next rate-loop step
    (PX4 runs it on every filtered gyro sample, at most ``IMU_GYRO_RATEMAX``): against commands
    interpolated between samples that is half a step later.  A parameter the log does not carry
    counts zero (not a PX4 log: our own and RotorPy logs have unfiltered rates; where such a log states no
    rate, ``residuals.prepare`` reads the command hold from the step its stamps sit on)."""

    gyro_filter_s: float = 0.0
    imu_average_s: float = 0.0
    command_hold_s: float = 0.0
    sources: tuple[str, ...] = ()

    def describe(self) -> str:
        if not self.sources:
            return "no PX4 sensor-timing parameters in the log: signals taken at their stamps"
        return ("signals re-timed to what the airframe did: " + "; ".join(self.sources))


#: the sensor-timing rates [Hz] (0: off); a rate below 1 Hz would re-time signals by seconds to ages
TIMING_RATE_HZ = (1.0, 100_000.0)


def sensor_timing(params: Mapping[str, float], path: str = "<log parameters>") -> SensorTiming:
    """The :class:`SensorTiming` of a PX4 log from its parameters (all zero when it has none).
    Each rate must be 0 (off) or in :data:`TIMING_RATE_HZ`, else a one-line ParamsError."""
    src = []
    lo, hi = TIMING_RATE_HZ
    for name in ("IMU_GYRO_CUTOFF", "IMU_INTEG_RATE", "IMU_GYRO_RATEMAX"):
        v = param(params, name, 0.0)[0]
        if v != 0.0 and not lo <= v <= hi:
            raise ParamsError(path, name, f"expected 0 (off) or {lo:g}..{hi:g} Hz, got {v:g}")
    fc = param(params, "IMU_GYRO_CUTOFF", 0.0)[0]
    gyro = math.sqrt(2.0) / (2.0 * math.pi * fc) if fc > 0 else 0.0
    if gyro:
        src.append(f"body rates {gyro * 1e3:.1f} ms earlier (IMU_GYRO_CUTOFF {fc:g} Hz low-pass group delay)")
    integ = param(params, "IMU_INTEG_RATE", 0.0)[0]
    avg = 0.5 / integ if integ > 0 else 0.0
    if avg:
        src.append(f"sensor_combined {avg * 1e3:.1f} ms earlier (half an IMU_INTEG_RATE {integ:g} Hz interval)")
    ratemax = param(params, "IMU_GYRO_RATEMAX", 0.0)[0]
    hold = 0.5 / ratemax if ratemax > 0 else 0.0
    step = sih_lockstep_step_s(params)
    if step:
        hold = 0.5 * step
        src.append(f"motor commands {hold * 1e3:.2f} ms later (held for one {step * 1e3:g} ms PX4 SIH lockstep "
                   f"step: the lower of IMU_GYRO_RATEMAX {ratemax:g} and IMU_INTEG_RATE {integ:g} Hz)")
    elif hold:
        src.append(f"motor commands {hold * 1e3:.2f} ms later (held for one IMU_GYRO_RATEMAX {ratemax:g} Hz "
                   "rate-loop step)")
    return SensorTiming(gyro, avg, hold, tuple(src))


#: PX4's SITL airframes that start SIH (``SYS_AUTOSTART``, ROMFS init.d-posix ``100xx_sihsim_*``: quad, plane,
#: tailsitter, VTOL, hexa, rover)
SIH_SITL_AIRFRAMES = frozenset(range(10040, 10046))
#: ``SYS_HITL`` value of SIH on a flight controller (``simulator_sih``'s real-time loop, not lockstep)
SIH_ON_HARDWARE = 2


def sih_lockstep_step_s(params: Mapping[str, float]) -> float:
    """PX4 SIH's lockstep step [s] where the log is a PX4 SIH flight in SITL, else 0.

    ``simulator_sih`` in SITL (``Sih::lockstep_loop``) advances PX4's clock by one step, reads the latest
    ``actuator_outputs``, integrates over the step and publishes the IMU at the new time; PX4 then runs
    the whole rate loop at that frozen time (the lockstep waits for every work queue), so each logged
    output is stamped at a step's start and acts over the step that follows (against commands read
    linearly between samples, half a step later), whatever ``IMU_GYRO_RATEMAX`` says: the gyro arrives once
    a step.  The step is 1 / min(IMU_GYRO_RATEMAX, IMU_INTEG_RATE) (PX4's defaults 400 and 200 Hz where the
    log lacks one; 400 Hz where the lower is 0), rounded to us and kept within 500-5000 us.  A SIH log
    carries ``SIH_*`` parameters or a SIH airframe (:data:`SIH_SITL_AIRFRAMES`); SIH on a flight
    controller (``SYS_HITL`` 2) runs in real time at ``IMU_GYRO_RATEMAX``, the rule of
    :func:`sensor_timing` for every PX4 log."""
    autostart = param(params, "SYS_AUTOSTART", -1.0)[0]
    sih = any(k.startswith("SIH_") for k in params) or autostart in SIH_SITL_AIRFRAMES
    if not sih or param(params, "SYS_HITL", 0.0)[0] == SIH_ON_HARDWARE:
        return 0.0
    rate = min(param(params, "IMU_GYRO_RATEMAX", 400.0)[0], param(params, "IMU_INTEG_RATE", 200.0)[0])
    rate = rate if rate > 0 else 400.0
    return min(max(round(1e6 / rate), 500), 5000) * 1e-6
