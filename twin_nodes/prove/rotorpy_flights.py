"""``rotortwin prove --source rotorpy``: flights flown in RotorPy, an independent simulator, found blind.

RotorPy (a dev dependency) has its own vehicle models, rotor dynamics (first-order ``tau_m`` on the rotor
speed), aerodynamics (rotor drag ``k_d``, parasitic drag ``c_D``, induced inflow ``k_z``, translational lift
``k_h``), wind models and its own SE(3) geometric controller.  Each flight here is RotorPy's own Crazyflie
(``rotorpy.vehicles.crazyflie_params``) flown by RotorPy's ``SE3Control``, which believes the nominal vehicle,
while RotorPy's ``Multirotor`` carries one changed physical parameter (or a RotorPy wind).  The flight is then
logged the way PX4 logs (the ours suite's :func:`~twin_nodes.twin.simflight.record_to_topics`: estimator-grade
noise, 50 Hz motor topic from a 250 Hz controller whose rate the log states as ``IMU_GYRO_RATEMAX``, the
IMU every 4 ms) and discovered blind with the nominal
``params/rotorpy_crazyflie.yaml`` (:func:`nominal_params` of RotorPy's parameters).

Frames.  RotorPy's world frame is z-up with x east and y north (its PX4 bridge treats it as ENU) and its body
frame is x forward, z along the thrust (FLU); quaternions are scipy's ``[x, y, z, w]``.  The attitude goes
through its rotation matrix into :func:`twin_nodes.base.frames.quat_from_rotmat`, and every PX4-side
conversion is the ours suite's (``frames.*``).  A RotorPy rotor direction ``+1`` adds ``+k_m w^2`` about body
+z; in our parameters ``direction`` +1 (CCW, PX4 ``KM > 0``) gives ``-km T`` about FLU z, so ours = -RotorPy's.

Commands.  The controller commands rotor speeds; RotorPy clips them to ``[rotor_speed_min, rotor_speed_max]``.
The log's ``actuator_motors`` is ``(w_cmd - w_min) / (w_max - w_min)``, which our ``omega_squared`` model
maps back (``omega_min_rad_s`` .. ``omega_cmd_max_rad_s`` = ``omega_max_rad_s``), lags with ``tau_m`` and turns
into ``T = k_eta w^2``, ``Q = k_m w^2 = (k_m / k_eta) T``.

Flights are deterministic (RotorPy's global NumPy seed and our generators' seeds are set per flight) and
kept under ``--cache`` (default ``out/cache/rotorpy``) keyed by the flight's definition, the RotorPy version and
:data:`GENERATOR_VERSION` and the source of the code that makes a flight: a second run only discovers.
"""

from __future__ import annotations

import copy
import hashlib
import importlib
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from twin_nodes.base import frames
from twin_nodes.prove.scoring import DragContext, Truth, effect_class, map_jobs, score, score_flight, write_result
from twin_nodes.twin.simflight import EstimateNoise, Hidden, record_to_topics
from twin_nodes.vehicle.params import VehicleParams, from_ros_dict

GENERATOR_VERSION = 2
CONTROL_RATE_HZ = 250.0
VEHICLE = "crazyflie"
REPO = Path(__file__).resolve().parents[2]
#: RotorPy terms with no counterpart in our effect vocabulary, switched off in the flown vehicle so that a
#: no-effect flight has no effect: the induced-inflow drag k_z (vertical rotor drag, linear in the rotor speed
#: and the vertical airspeed; the Crazyflie's own 7.55e-7 is found on a no-effect flight as body_drag c_dz,
#: see docs/prove_results.md), translational lift k_h and flapping moment k_flap (0 on the Crazyflie).
UNMODELLED = {"k_z": 0.0, "k_h": 0.0, "k_flap": 0.0}
#: Kept as RotorPy flies it: its rotor drag acts at each hub with the hub's own airspeed v + w x r_i, so a yaw
#: rate adds the yaw damping k_d * sum(w_i) * |r_i|^2 (1.36e-5 N m/(rad/s) at hover on the Crazyflie, Izz / that
#: = 2.1 s).  Our rotor_drag is the same law (physics/effects.py, since 2026-11-23; before, a force at the centre
#: of mass without that moment, which left a yaw residual during yaw turns: docs/prove_results.md).


def rotorpy_params(vehicle: str = VEHICLE) -> dict:
    """A copy of RotorPy's ``quad_params`` for ``vehicle`` (``crazyflie``, ``hummingbird``)."""
    mod = importlib.import_module(f"rotorpy.vehicles.{vehicle}_params")
    return copy.deepcopy(mod.quad_params)


def nominal_params(qp: dict, name: str = f"rotorpy_{VEHICLE}") -> VehicleParams:
    """Our nominal params for a RotorPy vehicle: geometry, omega_squared thrust, lag, drag as effects."""
    pos = np.array([np.asarray(v, float) for v in qp["rotor_pos"].values()])  # body FLU, RotorPy's order
    direction = [-int(np.sign(d)) for d in qp["rotor_directions"]]
    w_min, w_max = float(qp["rotor_speed_min"]), float(qp["rotor_speed_max"])
    effects: dict = {"enabled": []}
    if qp.get("k_d", 0.0) > 0:
        # RotorPy's rotor drag H_i = -w_i k_d v_local,i (in-plane part) is our rotor_drag with the same k_d
        effects["enabled"].append("rotor_drag")
        effects["rotor_drag"] = {"k_d": float(qp["k_d"])}
    c = [float(qp.get(k, 0.0)) for k in ("c_Dx", "c_Dy", "c_Dz")]
    if any(c):
        # RotorPy's parasitic drag -|v| C v: our body drag in its norm form (the per-axis form -c_i |v_i| v_i
        # is equal along a body axis only: off it, a wind read through it came out 10-20 % too strong)
        effects["enabled"].append("body_drag")
        effects["body_drag"] = {"c_dx": c[0], "c_dy": c[1], "c_dz": c[2], "norm": 1.0}
    doc = {
        "vehicle": {"name": name, "mass_kg": float(qp["mass"]), "ixx_kg_m2": float(qp["Ixx"]),
                    "iyy_kg_m2": float(qp["Iyy"]), "izz_kg_m2": float(qp["Izz"]), "ixy_kg_m2": float(qp["Ixy"]),
                    "ixz_kg_m2": float(qp["Ixz"]), "iyz_kg_m2": float(qp["Iyz"]), "gravity_m_s2": 9.81},
        "rotors": {"x_flu_m": [float(v) for v in pos[:, 0]], "y_flu_m": [float(v) for v in pos[:, 1]],
                   "z_flu_m": [float(v) for v in pos[:, 2]], "direction": direction,
                   "thrust_model": "omega_squared", "kt_n_s2_rad2": float(qp["k_eta"]),
                   "km_m": float(qp["k_m"] / qp["k_eta"]), "omega_min_rad_s": w_min,
                   "omega_cmd_max_rad_s": w_max, "omega_max_rad_s": w_max,
                   "tau_up_s": float(qp["tau_m"]), "tau_down_s": float(qp["tau_m"])},
        "effects": effects,
        # the controller RotorPy flies its vehicles with (SE3Control, its own gains): a closed-loop twin of a
        # RotorPy flight flies the same law (twin_nodes.twin.control_se3)
        "controller": se3_controller(qp),
        "simulation": {"dt_s": 0.001},
    }
    return from_ros_dict(doc, f"<rotorpy {name}>")


def se3_controller(qp: dict) -> dict:
    """The ``controller:`` block of RotorPy's ``SE3Control`` for the vehicle ``qp``: the law, its rate here
    (:data:`CONTROL_RATE_HZ`) and the gains read from RotorPy's own controller."""
    from rotorpy.controllers.quadrotor_control import SE3Control

    c = SE3Control(qp)
    return {"law": "se3", "rate_hz": CONTROL_RATE_HZ,
            "se3_kp_xy_1_s2": float(c.kp_pos[0]), "se3_kp_z_1_s2": float(c.kp_pos[2]),
            "se3_kd_xy_1_s": float(c.kd_pos[0]), "se3_kd_z_1_s": float(c.kd_pos[2]),
            "se3_kp_att_1_s2": float(c.kp_att), "se3_kd_att_1_s": float(c.kd_att)}


# ------------------------------------------------------------------ flights


@dataclass(frozen=True)
class Case:
    """One RotorPy flight: which RotorPy parameters differ from the vehicle's own, and the wind."""

    change: tuple = ()                 # ((rotorpy key, new value), ...)
    wind: tuple | None = None          # RotorPy ConstantWind (wx, wy, wz) [m/s], world (ENU)
    mission: str = "RP1"
    seed: int = 0
    vehicle: str = VEHICLE
    label: str = field(default="", compare=False)

    @property
    def tag(self) -> str:
        return f"{self.vehicle}_{self.label or 'none'}_{self.mission}_{self.seed}"

    def key(self) -> str:
        import rotorpy

        d = {"case": asdict(self), "generator": GENERATOR_VERSION, "unmodelled": UNMODELLED,
             "rotorpy": getattr(rotorpy, "__version__", None) or _dist_version("rotorpy"),
             "code": _generator_code_hash(self.mission)}
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=float).encode()).hexdigest()[:16]


def _generator_code_hash(mission_name: str) -> str:
    """A hash of the code that makes a flight (missions, the loop, logging): an edit there makes new flights."""
    import inspect

    from twin_nodes.twin import simflight

    parts = [MISSIONS[mission_name], fly, write_record, _leg, _take_off, _landing, _shortest, _Hold, _YawTurn, _Timed,
             Mission, nominal_params, simflight.record_to_topics, simflight.EstimateNoise]
    return hashlib.sha256("".join(inspect.getsource(o) for o in parts).encode()).hexdigest()


def _dist_version(name: str) -> str:
    from importlib.metadata import version
    return version(name)


def suite(size: str = "full", vehicle: str = VEHICLE) -> list[Case]:
    """One changed physical parameter per flight at realistic strengths, plus no-effect flights, on two
    missions (RP1 waypoints with yaw turns in place and vertical steps, RP2 Lissajous figure-eight)."""
    qp = rotorpy_params(vehicle)
    c_h = round(0.05 * qp["mass"] * 9.81 / 2.5 ** 2, 6)
    items = [
        Case((), None, "RP1", 11, vehicle, "none"),
        Case((), None, "RP2", 12, vehicle, "none"),
        Case((("mass", 1.2 * qp["mass"]),), None, "RP1", 13, vehicle, "mass"),
        Case((("k_eta", 0.87 * qp["k_eta"]),), None, "RP2", 14, vehicle, "thrust_coefficient"),
        Case((("k_m", 1.5 * qp["k_m"]),), None, "RP1", 15, vehicle, "yaw_moment"),
        Case((("tau_m", 2.0 * qp["tau_m"]),), None, "RP2", 16, vehicle, "motor_time_constant"),
        Case((("Ixx", 1.5 * qp["Ixx"]), ("Iyy", 1.5 * qp["Iyy"])), None, "RP2", 17, vehicle, "inertia"),
        Case((("k_d", 2.0 * qp["k_d"]),), None, "RP2", 18, vehicle, "rotor_drag"),
        # parasitic drag worth 5 % of the weight at 2.5 m/s (RotorPy's form -|v| C v)
        Case((("c_Dx", c_h), ("c_Dy", c_h), ("c_Dz", 2 * c_h)), None, "RP1", 19, vehicle, "body_drag"),
        Case((), (1.5, -1.0, 0.0), "RP1", 20, vehicle, "wind"),
    ]
    if size == "ci":
        items = [c for c in items if (c.label, c.mission) in {("none", "RP1"), ("mass", "RP1"), ("wind", "RP1")}]
    return items


def truth(case: Case, qp: dict, nominal: VehicleParams) -> Truth:
    """The flight's truth in our effect vocabulary (what discovery should name, and its parameters)."""
    ch = dict(case.change)
    text = ", ".join(f"{k} {qp[k]:.4g}->{v:.4g}" for k, v in ch.items())
    if case.wind is not None:
        wind_text = f"ConstantWind {tuple(float(w) for w in case.wind)}"
        if ch:
            raise ValueError("one change per flight")
        return Truth(Hidden("wind", {"vx": float(case.wind[0]), "vy": float(case.wind[1])}), wind_text)
    if not ch:
        return Truth(Hidden("none", {}), "RotorPy's own vehicle")
    keys = set(ch)
    inertia = nominal.inertia
    if keys == {"mass"}:
        return Truth(Hidden("mass", {"mass": ch["mass"]}), text)
    if keys == {"k_eta"}:
        return Truth(Hidden("thrust_coefficient", {"kt_scale": ch["k_eta"] / qp["k_eta"]}), text)
    if keys == {"k_m"}:
        return Truth(Hidden("yaw_moment", {"km": ch["k_m"] / qp["k_eta"]}), text)
    if keys == {"tau_m"}:
        return Truth(Hidden("motor_time_constant", {"tau_up": ch["tau_m"], "tau_down": ch["tau_m"]}), text)
    if keys <= {"Ixx", "Iyy", "Izz"}:
        return Truth(Hidden("inertia", {"ixx": ch.get("Ixx", inertia[0, 0]), "iyy": ch.get("Iyy", inertia[1, 1]),
                                        "izz": ch.get("Izz", inertia[2, 2])}), text)
    if keys == {"k_d"}:
        return Truth(Hidden("rotor_drag", {"k_d": ch["k_d"]}), text)
    if keys <= {"c_Dx", "c_Dy", "c_Dz"}:
        c = {"c_dx": ch.get("c_Dx", qp["c_Dx"]), "c_dy": ch.get("c_Dy", qp["c_Dy"]), "c_dz": ch.get("c_Dz", qp["c_Dz"])}
        return Truth(Hidden("body_drag", c), text, drag_law=("rotorpy_parasitic", c))
    raise ValueError(f"no mapping for RotorPy change {sorted(keys)}")


# ------------------------------------------------------------------ missions (RotorPy trajectories)


class _Hold:
    def __init__(self, p, yaw, duration):
        self.p, self.yaw, self.duration = np.asarray(p, float), float(yaw), float(duration)

    def update(self, t):
        z = np.zeros(3)
        return {"x": self.p.copy(), "x_dot": z, "x_ddot": z, "x_dddot": z, "x_ddddot": z,
                "yaw": self.yaw, "yaw_dot": 0.0, "yaw_ddot": 0.0}


class _YawTurn(_Hold):
    """A yaw in place with a minimum-jerk profile (peak rate ``rate``)."""

    def __init__(self, p, yaw0, yaw1, rate=1.5):
        self.d = float(yaw1 - yaw0)
        super().__init__(p, yaw0, max(1.875 * abs(self.d) / rate, 0.2))

    def update(self, t):
        out = super().update(t)
        s = min(max(t / self.duration, 0.0), 1.0)
        out["yaw"] = self.yaw + self.d * (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)
        out["yaw_dot"] = self.d * (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / self.duration
        return out


class _Timed:
    """A RotorPy trajectory object limited to ``duration`` (MinSnap, TwoDLissajous...)."""

    def __init__(self, traj, duration):
        self.traj, self.duration = traj, float(duration)

    def update(self, t):
        return self.traj.update(min(t, self.duration))


class Mission:
    """Pieces flown one after the other; motors armed from ``t_arm`` to ``t_disarm``."""

    def __init__(self, name: str, pieces: list, t_arm: float, disarm_before_end: float):
        self.name, self.pieces = name, pieces
        self.starts = np.concatenate([[0.0], np.cumsum([p.duration for p in pieces])])
        self.duration = float(self.starts[-1])
        self.t_arm, self.t_disarm = t_arm, self.duration - disarm_before_end

    def update(self, t):
        k = int(np.clip(np.searchsorted(self.starts, t, side="right") - 1, 0, len(self.pieces) - 1))
        return self.pieces[k].update(t - self.starts[k])

    def armed(self, t) -> bool:
        return self.t_arm <= t < self.t_disarm


def _leg(a, b, yaw_a, yaw_b, v_avg, v_start=(0, 0, 0), v_end=(0, 0, 0)):
    from rotorpy.trajectories.minsnap import MinSnap

    ms = MinSnap(np.array([a, b], float), yaw_angles=np.array([yaw_a, yaw_b], float), v_max=2.5 * v_avg + 1,
                 v_avg=v_avg, v_start=list(v_start), v_end=list(v_end), verbose=False)
    return _Timed(ms, ms.t_keyframes[-1])


def _take_off(p_ground, h, yaw):
    g = np.array([p_ground[0], p_ground[1], -0.1])  # pushed into the ground while armed on it
    return [_Hold(g, yaw, 1.0), _Hold(g, yaw, 1.0), _leg(g, [g[0], g[1], h], yaw, yaw, 0.8), _Hold([g[0], g[1], h], yaw, 2.0)]


def _landing(p, yaw):
    return [_leg(p, [p[0], p[1], 0.05], yaw, yaw, 0.5), _Hold([p[0], p[1], -0.1], yaw, 1.5), _Hold([p[0], p[1], -0.1], yaw, 1.0)]


def _shortest(yaw_from, yaw_to):
    return yaw_from + (yaw_to - yaw_from + math.pi) % (2 * math.pi) - math.pi


def _rp1() -> Mission:
    """RP1: take-off, a 4 m square twice, climbing on one leg, with a 90 deg yaw in place at every corner:
    first slow, facing each leg, then fast the other way round with the heading 90 deg off each leg (sideways
    legs); vertical steps with a yaw in place at the top and the bottom; landing."""
    h = 1.5
    pieces = _take_off([0, 0, 0], h, 0.0)
    yaw = 0.0
    corners = [np.array(c, float) for c in ([0, 0, h], [4, 0, h], [4, 4, h + 1.0], [0, 4, h], [0, 0, h])]
    # lap 1 slow, facing each leg; lap 2 fast the other way round, turning +90 deg at every corner as well,
    # so that every leg of lap 2 is flown sideways (roll, body-y drag)
    for lap, v_avg, facing in ((corners, 1.2, True), (corners[::-1], 2.0, False)):
        for a, b in zip(lap[:-1], lap[1:]):
            heading = _shortest(yaw, math.atan2(b[1] - a[1], b[0] - a[0])) if facing else yaw + math.pi / 2
            pieces += [_YawTurn(a, yaw, heading), _Hold(a, heading, 0.5)]
            yaw = heading
            pieces += [_leg(a, b, yaw, yaw, v_avg), _Hold(b, yaw, 0.5)]
    o = corners[0]
    # vertical steps, with a yaw in place at the top and at the bottom
    for z, v, turn in ((h + 1.5, 1.0, -math.pi / 2), (0.8, 0.8, math.pi / 2), (h, 0.8, 0.0)):
        pieces += [_leg(o, [o[0], o[1], z], yaw, yaw, v)]
        o = np.array([o[0], o[1], z])
        if turn:
            pieces += [_YawTurn(o, yaw, yaw + turn)]
            yaw += turn
        pieces += [_Hold(o, yaw, 1.0)]
    pieces += _landing(o, yaw)
    return Mission("RP1", pieces, 1.0, 1.0)


def _rp2() -> Mission:
    """RP2: take-off, a Lissajous figure-eight (RotorPy TwoDLissajous, 2.5 x 1.5 m, yaw along the path) for
    four periods, vertical steps; landing."""
    h = 1.5
    from rotorpy.trajectories.lissajous_traj import TwoDLissajous

    A, B, a, b = 2.5, 1.5, 0.8, 1.6
    p0 = np.array([-2.0, 0.0, h])
    pieces = _take_off(p0[:2].tolist() + [0.0], h, 0.0)
    v0 = np.array([a * A, b * B, 0.0])
    yaw_l = math.atan2(v0[1], v0[0])
    liss = TwoDLissajous(A=A, B=B, a=a, b=b, delta=0.0, height=h, yaw_traj="forward")
    t_liss = 4 * 2 * math.pi / a
    o = np.array([0.0, 0.0, h])
    p1 = np.array([1.5, 1.5, h])
    pieces += [_YawTurn(p0, 0.0, yaw_l), _leg(p0, o, yaw_l, yaw_l, 1.2, v_end=v0), _Timed(liss, t_liss),
               _leg(o, p1, yaw_l, yaw_l, 1.2, v_start=v0), _Hold(p1, yaw_l, 1.0)]
    for z, v in ((h + 1.5, 1.0), (0.8, 0.8), (h, 0.8)):
        pieces += [_leg(p1, [p1[0], p1[1], z], yaw_l, yaw_l, v), _Hold([p1[0], p1[1], z], yaw_l, 1.0)]
        p1 = np.array([p1[0], p1[1], z])
    pieces += _landing(p1, yaw_l)
    return Mission("RP2", pieces, 1.0, 1.0)


def _rp0() -> Mission:
    """RP0: a short check flight (tests): out and back with a yaw in place, a step, landing."""
    h = 1.5
    o = np.array([0.0, 0.0, h])
    e = np.array([4.0, 0.0, h])
    pieces = _take_off([0, 0, 0], h, 0.0)
    pieces += [_leg(o, e, 0.0, 0.0, 1.5), _Hold(e, 0.0, 0.5), _YawTurn(e, 0.0, math.pi / 2),
               _leg(e, o + [0, 0, 1.0], math.pi / 2, math.pi / 2, 1.5), _Hold(o + [0, 0, 1.0], math.pi / 2, 0.5),
               _leg(o + [0, 0, 1.0], o, math.pi / 2, math.pi / 2, 0.8), _Hold(o, math.pi / 2, 0.5)]
    pieces += _landing(o, math.pi / 2)
    return Mission("RP0", pieces, 1.0, 1.0)


def _oovr() -> Mission:
    """OOVR (``prove --source oov``): take-off; twice: a 20 m leg at about 4 m/s, a climb to 9 m, a descent to
    1.5 m at about 3.5 m/s, the leg back, a climb to 9 m, a descent at about 4.5 m/s; landing (legs and
    vertical manoeuvres interleaved so that the last 35 % of the flight holds each)."""
    h, top = 1.5, 9.0
    o, far = np.array([0.0, 0.0, h]), np.array([20.0, 0.0, h])
    up, far_up = np.array([0.0, 0.0, top]), np.array([20.0, 0.0, top])
    pieces = _take_off([0, 0, 0], h, 0.0)
    for _ in range(2):
        pieces += [_leg(o, far, 0.0, 0.0, 4.0), _Hold(far, 0.0, 1.5),
                   _leg(far, far_up, 0.0, 0.0, 3.0), _Hold(far_up, 0.0, 1.0), _leg(far_up, far, 0.0, 0.0, 3.5),
                   _Hold(far, 0.0, 1.5), _leg(far, o, 0.0, 0.0, 4.0), _Hold(o, 0.0, 1.5),
                   _leg(o, up, 0.0, 0.0, 3.0), _Hold(up, 0.0, 1.0), _leg(up, o, 0.0, 0.0, 4.5), _Hold(o, 0.0, 1.5)]
    pieces += _landing(o, 0.0)
    return Mission("OOVR", pieces, 1.0, 1.0)


#: the missions by name
MISSIONS = {"RP0": _rp0, "RP1": _rp1, "RP2": _rp2, "OOVR": _oovr}


def mission(name: str) -> Mission:
    """A RotorPy mission by name (:data:`MISSIONS`)."""
    if name not in MISSIONS:
        raise ValueError(f"unknown RotorPy mission {name!r}; expected one of {', '.join(MISSIONS)}")
    return MISSIONS[name]()


def fly(case: Case, vehicle_cls=None):
    """Fly ``case`` in RotorPy; returns (FlightRecord in ENU/FLU at the control rate, nominal params).

    The loop is ``rotorpy.simulate.simulate``'s (wind update, controller on the true state, IMU from
    ``statedot``, ``Multirotor.step``), with motors stopped outside the armed interval.  ``vehicle_cls``:
    a subclass of RotorPy's ``Multirotor`` to fly instead (physics in the plant only: ``prove.oov``)."""
    from rotorpy.controllers.quadrotor_control import SE3Control
    from rotorpy.vehicles.multirotor import Multirotor
    from rotorpy.wind.default_winds import ConstantWind, NoWind

    from twin_nodes.twin.sim import FlightRecord

    qp = rotorpy_params(case.vehicle)
    vp = nominal_params(qp, f"rotorpy_{case.vehicle}")
    plant = copy.deepcopy(qp)
    plant.update(UNMODELLED)
    plant.update(dict(case.change))
    np.random.seed(case.seed)  # RotorPy draws its noise from NumPy's global generator
    m = mission(case.mission)
    n_rot = int(qp["num_rotors"])
    start = m.update(0.0)["x"]
    x0 = {"x": np.array([start[0], start[1], 0.0]), "v": np.zeros(3), "q": np.array([0, 0, 0, 1.0]),
          "w": np.zeros(3), "wind": np.zeros(3), "rotor_speeds": np.zeros(n_rot)}
    vehicle = (vehicle_cls or Multirotor)(plant, initial_state=x0, control_abstraction="cmd_motor_speeds", aero=True,
                         enable_ground=True)
    ctrl = SE3Control(qp)  # the controller believes the vehicle's own (nominal) parameters
    wind = ConstantWind(*case.wind) if case.wind is not None else NoWind()
    dt = 1.0 / CONTROL_RATE_HZ
    n = int(m.duration / dt)
    w_min, w_max = float(plant["rotor_speed_min"]), float(plant["rotor_speed_max"])
    T = np.arange(n) * dt
    X = np.zeros((n, 13 + n_rot))
    U = np.full((n, n_rot), np.nan)
    thr = np.zeros(n)
    SP = np.full((n, 11), np.nan)
    SF = np.zeros((n, 3))
    EXT = np.zeros((n, 4))
    EXT[:, 0] = np.nan
    state = copy.deepcopy(x0)
    tmax_total = n_rot * qp["k_eta"] * w_max ** 2
    for k in range(n):
        t = T[k]
        state["wind"] = np.asarray(wind.update(t, state["x"]), float)
        flat = m.update(t)
        control = ctrl.update(t, state, flat)
        armed = m.armed(t)
        cmd = np.clip(control["cmd_motor_speeds"], w_min, w_max) if armed else np.zeros(n_rot)
        used = dict(control, cmd_motor_speeds=cmd)
        sdot = vehicle.statedot(state, used, dt)
        record_row(k, (X, SF, EXT, U, thr, SP), state, sdot["vdot"], vehicle.g, control, flat,
                   cmd if armed else None, (w_min, w_max), tmax_total)
        state = vehicle.step(state, used, dt)
        if not np.all(np.isfinite(state["x"])) or np.linalg.norm(state["v"]) > 50:
            raise RuntimeError(f"RotorPy flight {case.tag} diverged at t={t:.2f} s")
    rng = np.random.default_rng(case.seed)
    noise = EstimateNoise(rng, dt)
    x_est = np.array([noise(X[k, :13], rng) for k in range(n)])
    rec = FlightRecord(t=T, x=X, u=U, throttle=thr, sp=SP, specific_force=SF, ext=EXT, x_est=x_est,
                       info={"rotorpy_case": asdict(case)})
    return rec, vp



def record_row(k: int, rows: tuple, state: dict, vdot, g: float, control: dict, flat: dict, cmd, w_range: tuple,
               tmax_total: float) -> None:
    """One control step of a RotorPy flight into its record's rows ``(X, SF, EXT, U, thr, SP)``: the state
    (position, velocity, quaternion, rates, rotor speeds), the body specific force from the state derivative
    ``vdot``, the wind, and where armed (``cmd`` not None) the normalised motor commands and collective."""
    from scipy.spatial.transform import Rotation

    X, SF, EXT, U, thr, SP = rows
    R = Rotation.from_quat(state["q"]).as_matrix()
    X[k, 0:3], X[k, 3:6] = state["x"], state["v"]
    X[k, 6:10] = frames.quat_from_rotmat(R)
    X[k, 10:13], X[k, 13:] = state["w"], state["rotor_speeds"]
    SF[k] = R.T @ (np.asarray(vdot) + np.array([0.0, 0.0, g]))
    EXT[k, 1:4] = state["wind"]
    if cmd is not None:
        w_min, w_max = w_range
        U[k] = (cmd - w_min) / (w_max - w_min)
        thr[k] = float(np.clip(control["cmd_thrust"] / tmax_total, 0.0, 1.0))
    SP[k, 0:3], SP[k, 3:6], SP[k, 6:9] = flat["x"], flat["x_dot"], flat["x_ddot"]
    SP[k, 9], SP[k, 10] = flat["yaw"], flat["yaw_dot"]


def write_flight(path: str | Path, case: Case) -> dict:
    """Fly ``case`` and write it as a PX4-like ULog at ``path``; facts about the flight."""
    rec, vp = fly(case)
    return write_record(path, rec, vp, case.seed)


def write_record(path: str | Path, rec, vp: VehicleParams, seed: int, battery_v=None) -> dict:
    """Write a flown RotorPy record as a PX4-like ULog (the ours suite's logging model); facts about it.
    ``battery_v(t)``: the pack voltage logged; default a steady 16 V (RotorPy has no battery, so our
    battery_sag candidate is then not offered).

    The log states its own timing the way a PX4 log does: every record step is one control step whose
    command is held over the step and logged at its start, so ``IMU_GYRO_RATEMAX`` is the record's rate
    (``px4_params.sensor_timing``: commands act half a step, 2 ms at 250 Hz, after their stamps); and
    ``sensor_combined`` is every record sample (uniform 4 ms stamps, PX4's high-rate IMU logging), whose
    centred 20 ms bins (``time_sync.bin_mean_to``) are centred on their grid times."""
    from twin_nodes.logs.ulog_write import write_px4_ulog

    rng = np.random.default_rng(seed + 7)
    battery = battery_v or (lambda t: np.full(np.shape(t), 16.0))
    topics = record_to_topics(rec, vp, battery, (rec.t, rec.sp), rng, imu_stride=1)
    r = vp.rotors
    control_hz = 1.0 / float(np.median(np.diff(rec.t)))
    params = {"SYS_AUTOSTART": 0, "CA_ROTOR_COUNT": int(r.count), "MPC_THR_HOVER": float(vp.hover_command),
              "IMU_GYRO_RATEMAX": int(round(control_hz))}
    frd = frames.flu_to_frd(np.column_stack([r.x_flu_m, r.y_flu_m, r.z_flu_m]))
    for i in range(r.count):
        params.update({f"CA_ROTOR{i}_PX": float(frd[i, 0]), f"CA_ROTOR{i}_PY": float(frd[i, 1]),
                       f"CA_ROTOR{i}_PZ": float(frd[i, 2]), f"CA_ROTOR{i}_KM": float(r.direction[i]) * r.km_m})
    info = {"sys_name": "rotorpy", "ver_hw": "ROTORPY_SIM", "sim_vehicle": vp.name}
    write_px4_ulog(str(path), topics, params, info)
    air = np.isfinite(rec.u).all(1) & (rec.x[:, 2] > 0.3) & np.isfinite(rec.sp[:, 0:3]).all(1)
    xy = np.hypot(*(rec.x[air, 0:2] - rec.sp[air, 0:2]).T)
    z = rec.x[air, 2] - rec.sp[air, 2]
    return {"xy_tracking_rmse_m": float(np.sqrt(np.mean(xy ** 2))), "z_tracking_rmse_m": float(np.sqrt(np.mean(z ** 2))),
            "duration_s": float(rec.t[-1]), "max_speed_m_s": float(np.max(np.linalg.norm(rec.x[:, 3:6], axis=1)))}


def cached_flight(case: Case, cache: str | Path) -> tuple[Path, dict]:
    """The flight's ULog from the cache, flown first when absent or made by another definition."""
    from twin_nodes.prove.flight_cache import keyed_flight

    return keyed_flight(cache, case.tag, case.key(), lambda tmp: write_flight(tmp, case), {"case": asdict(case)})


def run_one(args) -> dict:
    """Fly (or take from the cache) one RotorPy flight, discover blind with the nominal, score it."""
    case, out_dir, cache = args
    from twin_nodes.discovery.discover import discover
    from twin_nodes.logs.ulog_io import read_ulog

    path, facts = cached_flight(case, cache)
    qp = rotorpy_params(case.vehicle)
    vp = nominal_params(qp, f"rotorpy_{case.vehicle}")
    tr = truth(case, qp, vp)
    log = read_ulog(path)
    res = discover(log, vp, closed_loop_metrics=False)
    res.pop("_series", None)
    drag = DragContext.from_log(log, vp) if effect_class(tr.hidden.name) == "drag" else None
    write_result(Path(out_dir) / f"{case.tag}.json", res)
    return score_flight(f"{case.label or 'none'} ({case.mission})", tr, res, vp, drag, source="rotorpy",
                        log=str(path), **facts)


def run_suite(out_dir: str | Path, size: str = "full", workers: int = 2, cache: str | Path = "out/cache/rotorpy",
              progress: bool = True) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(c, str(out), str(cache)) for c in suite(size)]
    return score(map_jobs(run_one, jobs, workers, "prove rotorpy", progress), source="rotorpy")
