"""``rotortwin prove``: flights with one hidden effect, flown by our simulator, found blind.

Each flight is a PX4-style mission (take-off, legs with altitude changes and
yaw turns, a hover, landing) flown by the PX4-like controller, which believes
the *nominal* vehicle while the plant carries one hidden effect at a realistic
strength.  The flight is logged the way PX4 logs it — estimator-grade noise on
position/velocity/attitude (GPS-like random walk), accelerometer and gyro
noise, the motor topic sampled at 50 Hz from a 250 Hz controller (aliasing
included), battery at 5 Hz — and written as a ULog.  Then ``discover`` runs on
the ULog with only the nominal params, and the result is scored.
"""

from __future__ import annotations

import json
import math
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin_nodes.base import frames
from twin_nodes.vehicle.export_px4 import simulated_log_params
from twin_nodes.vehicle.params import VehicleParams, load_params, shipped
from twin_nodes.twin.sim import fly_closed_loop

LOG_RATES_HZ = {"vehicle_local_position": 25, "vehicle_attitude": 50, "vehicle_angular_velocity": 50,
                "actuator_motors": 50, "vehicle_thrust_setpoint": 50, "sensor_combined": 100,
                "battery_status": 5, "trajectory_setpoint": 25}


@dataclass(frozen=True)
class Hidden:
    """One hidden effect: name and parameters (as in the discovery vocabulary)."""

    name: str
    params: dict

    @property
    def label(self) -> str:
        return self.name if self.name != "none" else "none"


def suite(vp: VehicleParams, size: str = "full") -> list[tuple[Hidden, int]]:
    """The suite for vehicle ``vp``: realistic strengths, scaled to the vehicle.

    Strengths are what flying vehicles show: a 15-20 % payload, a worn prop
    (10-15 % thrust), a tired ESC (15 %), slow ESCs, 40 ms of extra delay, a
    3 m/s breeze, a 2 cm CoM offset on a 0.28 m arm...  The controller hides
    each from position (checked by the suite: XY/Z tracking stays GPS-grade).
    """
    r = vp.rotors
    arm = float(np.median(np.hypot(r.x_flu_m, r.y_flu_m)))
    inertia = vp.inertia
    omega_h = vp.hover_omega_rad_s
    weight = vp.mass_kg * vp.gravity_m_s2
    items = [
        Hidden("mass", {"mass": 1.2 * vp.mass_kg}),
        Hidden("thrust_coefficient", {"kt_scale": 0.87}),
        Hidden("motor_efficiency", {"motor": 3.0, "efficiency": 0.85}),
        Hidden("motor_time_constant", {"tau_up": 2.0 * max(r.tau_up_s, 0.02), "tau_down": 2.5 * max(r.tau_down_s, 0.02)}),
        Hidden("actuator_delay", {"delay": 0.04}),
        Hidden("yaw_moment", {"km": 1.5 * r.km_m}),
        Hidden("com_offset", {"dx": 0.08 * arm, "dy": -0.06 * arm}),
        Hidden("inertia", {"ixx": 1.6 * inertia[0, 0], "iyy": 1.6 * inertia[1, 1], "izz": 1.5 * inertia[2, 2]}),
        Hidden("rotor_drag", {"k_d": 0.06 * weight / (r.count * omega_h * 5.0)}),
        Hidden("body_drag", {"c_dx": 0.004 * weight, "c_dy": 0.004 * weight, "c_dz": 0.008 * weight}),
        Hidden("wind", {"vx": 3.0, "vy": -2.0, "gust_std": 0.3}),
        Hidden("ground_effect", {"coefficient": 0.4, "height_scale": 0.4}),
        Hidden("battery_sag", {"v_ref": 16.8, "exponent": 1.0}),
        Hidden("none", {}),
        Hidden("none", {}),
    ]
    if size == "ci":
        keep = {"mass", "motor_efficiency", "actuator_delay", "wind", "none"}
        items = [h for h in items if h.name in keep][:5]
    return [(h, 1000 + i) for i, h in enumerate(items)]


def mission_setpoints(rng: np.random.Generator, rate_hz: float = 25.0):
    """A PX4-like mission as a trajectory_setpoint history (ENU): returns t, SP (T, 11), armed(t)."""
    alt1, alt2 = 8.0 + rng.uniform(-1, 1), 14.0 + rng.uniform(-1, 1)
    wps = [np.array([0.0, 0.0, alt1]), np.array([40.0, 0.0, alt1]), np.array([40.0, 30.0, alt2]),
           np.array([0.0, 30.0, alt2]), np.array([0.0, 0.0, alt1])]
    seg: list[tuple[str, object]] = [("ground", 3.0), ("climb", alt1), ("hover", 4.0)]
    # missions fly legs at different speeds (MPC_XY_CRUISE or per-item speed changes)
    # two legs keep their heading (PX4 yaw-hold) and so fly sideways or backwards; after the
    # second leg the mission lands and takes off again (a two-hop mission, like the shared
    # real flugdrohne logs)
    for k, ((a, b), speed, hold) in enumerate(zip(zip(wps[:-1], wps[1:]), (3.0, 6.0, 8.0, 4.5),
                                                  (False, True, False, True))):
        seg.append(("leg", (a, b, speed, hold)))
        seg.append(("hover", 2.0))
        if k == 1:
            seg += [("land", None), ("ground", 2.0), ("climb", alt2), ("hover", 2.0)]
    seg += [("yaw", math.pi), ("hover", 3.0), ("descend", 1.5), ("hover", 3.0), ("land", None), ("ground", 2.0)]
    dt = 1.0 / rate_hz
    t, P, V, A, Y = [], [], [], [], []
    pos = np.zeros(3)
    yaw = 0.0
    tt = 0.0
    armed_until = None
    armed_from = 2.0

    def emit(p, v, a, y):
        nonlocal tt
        t.append(tt)
        P.append(p.copy())
        V.append(v.copy())
        A.append(a.copy())
        Y.append(y)
        tt += dt

    for kind, arg in seg:
        if kind == "ground":
            for _ in range(int(arg * rate_hz)):
                emit(np.array([pos[0], pos[1], -1.0 if armed_until is None and tt > armed_from else pos[2]]),
                     np.zeros(3), np.zeros(3), yaw)
        elif kind in ("climb", "descend"):
            target = arg if kind == "climb" else arg
            vz = 1.5 if target > pos[2] else -1.0
            while abs(target - pos[2]) > abs(vz) * dt:
                pos[2] += vz * dt
                emit(pos, np.array([0, 0, vz]), np.zeros(3), yaw)
            pos[2] = target
        elif kind == "hover":
            for _ in range(int(arg * rate_hz)):
                emit(pos, np.zeros(3), np.zeros(3), yaw)
        elif kind == "yaw":
            # a yaw turn at 45 deg/s (PX4 MPC_YAWRAUTO_MAX), there and back
            for target in (yaw + arg, yaw):
                while abs(target - yaw) > 0.8 * dt:
                    yaw += math.copysign(0.8 * dt, target - yaw)
                    emit(pos, np.zeros(3), np.zeros(3), yaw)
        elif kind == "leg":
            a, b, cruise, hold = arg
            d = b - a
            length = float(np.linalg.norm(d))
            u = d / length
            heading = math.atan2(d[1], d[0]) if np.hypot(d[0], d[1]) > 1 and not hold else yaw
            # turn first, then fly with a trapezoidal speed profile (accel 2 m/s^2)
            while abs(_wrap(heading - yaw)) > 0.8 * dt:
                yaw += math.copysign(0.8 * dt, _wrap(heading - yaw))
                emit(pos, np.zeros(3), np.zeros(3), yaw)
            yaw = heading
            acc = 2.0
            s, v = 0.0, 0.0
            while s < length:
                remaining = length - s
                if v * v / (2 * acc) >= remaining:
                    v = max(v - acc * dt, 0.3)
                    ac = -acc
                else:
                    v = min(v + acc * dt, cruise)
                    ac = acc if v < cruise else 0.0
                s = min(s + v * dt, length)
                pos = a + u * s
                emit(pos, u * v, u * ac, yaw)
            pos = b.copy()
        elif kind == "land":
            # PX4 lands at MPC_LAND_SPEED, then crawls (MPC_LAND_CRWL 0.3 m/s) the last 1.5 m
            while pos[2] > -0.5:
                vz = -0.7 if pos[2] > 1.5 else -0.3
                pos[2] += vz * dt
                emit(pos, np.array([0, 0, vz]), np.zeros(3), yaw)
            armed_until = tt + 1.5
    t = np.array(t)
    SP = np.full((len(t), 11), np.nan)
    SP[:, 0:3] = P
    SP[:, 3:6] = V
    SP[:, 6:9] = A
    SP[:, 9] = Y
    # before arming: nothing controlled
    pre = t < armed_from
    SP[pre] = np.nan
    end = armed_until if armed_until is not None else t[-1]
    return t, SP, (lambda tq, a0=armed_from, a1=end: (tq >= a0) & (tq < a1))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class EstimateNoise:
    """Estimator-grade noise on the state the controller and the log see (seeded)."""

    def __init__(self, rng: np.random.Generator, dt: float, pos_sigma=0.15, pos_tau=8.0, vel_sigma=0.05,
                 vel_tau=1.0, att_sigma_rad=0.004, gyro_sigma=0.002):
        self.dt, self.pos_sigma, self.pos_tau = dt, pos_sigma, pos_tau
        self.vel_sigma, self.vel_tau = vel_sigma, vel_tau
        self.att_sigma, self.gyro_sigma = att_sigma_rad, gyro_sigma
        self.pos_err = rng.standard_normal(3) * pos_sigma
        self.vel_err = np.zeros(3)
        self.att_err = np.zeros(3)

    def __call__(self, x13: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        a = math.exp(-self.dt / self.pos_tau)
        self.pos_err = a * self.pos_err + rng.standard_normal(3) * self.pos_sigma * math.sqrt(1 - a * a)
        b = math.exp(-self.dt / 2.0)
        self.att_err = b * self.att_err + rng.standard_normal(3) * self.att_sigma * math.sqrt(1 - b * b)
        out = np.array(x13, float, copy=True)
        out[0:3] += self.pos_err * np.array([1.0, 1.0, 1.5])
        # EKF velocity is smooth: a correlated error, not white noise at the loop rate
        c = math.exp(-self.dt / self.vel_tau)
        self.vel_err = c * self.vel_err + rng.standard_normal(3) * self.vel_sigma * math.sqrt(1 - c * c)
        out[3:6] += self.vel_err
        dq = np.concatenate([[1.0], 0.5 * self.att_err])
        out[6:10] = frames.quat_normalize(frames.quat_multiply(out[6:10], dq))
        out[10:13] += rng.standard_normal(3) * self.gyro_sigma
        return out


def simulate_flight(vp: VehicleParams, hidden: Hidden, seed: int):
    """Fly one mission with the hidden effect; returns the FlightRecord and the battery trace function."""
    rng = np.random.default_rng(seed)
    # PX4 generates trajectory setpoints at the controller rate (it only logs them at 25 Hz); a
    # 25 Hz staircase would put 25 Hz harmonics into the commands that 50 Hz logging samples at
    # a fixed phase (it biased the yaw-differential mean by 21 %)
    t_sp, SP, armed = mission_setpoints(rng, rate_hz=250.0)
    plant = vp if hidden.name == "none" else vp.with_effect(hidden.name, **hidden.params)
    v_full, v_empty = 16.6, 14.6
    t_end = float(t_sp[-1])

    def battery(t):
        return v_full - (v_full - v_empty) * np.clip(t / t_end, 0, 1) ** 1.3

    noise = EstimateNoise(rng, 1.0 / 250.0)
    rec = fly_closed_loop(plant, t_sp, SP, controller_params=vp, battery_v=battery, estimate_noise=noise,
                          armed=armed, rng=rng)
    return rec, battery, (t_sp, SP)


def record_to_topics(rec, vp: VehicleParams, battery, sp_hist, rng: np.random.Generator,
                     start_us: int = 20_000_000):
    """PX4 topics (NED/FRD, µs) sampled at LOG_RATES_HZ from a simulated flight."""
    t = rec.t
    topics = {}

    def idx(rate):
        tt = np.arange(t[0], t[-1], 1.0 / rate)
        return np.clip(np.searchsorted(t, tt), 0, len(t) - 1)

    def ts(k):
        return (start_us + np.round(t[k] * 1e6)).astype(np.uint64)

    k = idx(LOG_RATES_HZ["vehicle_local_position"])
    xe = rec.x_est
    p = frames.enu_to_ned(xe[k, 0:3])
    v = frames.enu_to_ned(xe[k, 3:6])
    acc = np.gradient(rec.x[:, 3:6], t, axis=0)
    yaw_ned = frames.yaw_enu_to_ned(np.arctan2(2 * (xe[k, 6] * xe[k, 9] + xe[k, 7] * xe[k, 8]),
                                               1 - 2 * (xe[k, 8] ** 2 + xe[k, 9] ** 2)))
    ones = np.ones(len(k), bool)
    topics["vehicle_local_position"] = {"timestamp": ts(k), "x": p[:, 0], "y": p[:, 1], "z": p[:, 2],
                                        "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2],
                                        "ax": frames.enu_to_ned(acc[k])[:, 0], "ay": frames.enu_to_ned(acc[k])[:, 1],
                                        "az": frames.enu_to_ned(acc[k])[:, 2], "heading": yaw_ned,
                                        "xy_valid": ones, "z_valid": ones, "v_xy_valid": ones, "v_z_valid": ones,
                                        # downward distance sensor (as SIH simulates one): 2 cm noise, 0..20 m
                                        "dist_bottom": rec.x[k, 2] + rng.standard_normal(len(k)) * 0.02,
                                        "dist_bottom_valid": rec.x[k, 2] < 20.0}
    k = idx(LOG_RATES_HZ["vehicle_attitude"])
    topics["vehicle_attitude"] = {"timestamp": ts(k), "q": frames.q_enu_flu_to_ned_frd(xe[k, 6:10])}
    k = idx(LOG_RATES_HZ["vehicle_angular_velocity"])
    topics["vehicle_angular_velocity"] = {"timestamp": ts(k), "xyz": frames.flu_to_frd(xe[k, 10:13])}
    k = idx(LOG_RATES_HZ["actuator_motors"])
    ctrl = np.full((len(k), 12), np.nan)
    ctrl[:, :vp.rotors.count] = rec.u[k]
    topics["actuator_motors"] = {"timestamp": ts(k), "control": ctrl.astype(np.float32)}
    thr = np.zeros((len(k), 3))
    thr[:, 2] = -np.nan_to_num(rec.throttle[k])
    topics["vehicle_thrust_setpoint"] = {"timestamp": ts(k), "xyz": thr}
    k = idx(LOG_RATES_HZ["sensor_combined"])
    sf = frames.flu_to_frd(rec.specific_force[k]) + rng.standard_normal((len(k), 3)) * 0.08
    gyro = frames.flu_to_frd(rec.x[k, 10:13]) + rng.standard_normal((len(k), 3)) * 0.004
    topics["sensor_combined"] = {"timestamp": ts(k), "gyro_rad": gyro, "accelerometer_m_s2": sf,
                                 "accelerometer_timestamp_relative": np.zeros(len(k), np.int32),
                                 "gyro_integral_dt": np.full(len(k), 10000, np.uint32),
                                 "accelerometer_integral_dt": np.full(len(k), 10000, np.uint32)}
    k = idx(LOG_RATES_HZ["battery_status"])
    volts = battery(t[k]) + rng.standard_normal(len(k)) * 0.01
    topics["battery_status"] = {"timestamp": ts(k), "voltage_v": volts, "current_a": np.full(len(k), 12.0),
                                "remaining": np.clip((volts - 14.6) / 2.0, 0, 1)}
    t_sp, SP = sp_hist
    ksp = idx(LOG_RATES_HZ["trajectory_setpoint"])
    spk = rec.sp[ksp]
    topics["trajectory_setpoint"] = {"timestamp": ts(ksp), "position": frames.enu_to_ned(spk[:, 0:3]),
                                     "velocity": frames.enu_to_ned(spk[:, 3:6]),
                                     "acceleration": frames.enu_to_ned(spk[:, 6:9]),
                                     "yaw": frames.yaw_enu_to_ned(spk[:, 9]), "yawspeed": np.full(len(ksp), np.nan)}
    armed = np.isfinite(rec.u).all(1)
    changes = np.flatnonzero(np.diff(armed.astype(int))) + 1
    kk = np.concatenate([[0], changes])
    topics["vehicle_status"] = {"timestamp": ts(kk), "arming_state": np.where(armed[kk], 2, 1).astype(np.uint8),
                                "nav_state": np.where(armed[kk], 3, 4).astype(np.uint8)}
    landed = rec.x[:, 2] < 0.05
    ch = np.flatnonzero(np.diff(landed.astype(int))) + 1
    kl = np.concatenate([[0], ch])
    topics["vehicle_land_detected"] = {"timestamp": ts(kl), "landed": landed[kl]}
    k = idx(10)
    topics["vehicle_local_position_groundtruth"] = {
        "timestamp": ts(k), "x": frames.enu_to_ned(rec.x[k, 0:3])[:, 0], "y": frames.enu_to_ned(rec.x[k, 0:3])[:, 1],
        "z": frames.enu_to_ned(rec.x[k, 0:3])[:, 2], "vx": frames.enu_to_ned(rec.x[k, 3:6])[:, 0],
        "vy": frames.enu_to_ned(rec.x[k, 3:6])[:, 1], "vz": frames.enu_to_ned(rec.x[k, 3:6])[:, 2]}
    return topics


def write_flight(path: str | Path, vp: VehicleParams, hidden: Hidden, seed: int) -> dict:
    """Simulate and write one flight as a ULog; returns facts about it (truth, tracking)."""
    from twin_nodes.logs.ulog_write import write_px4_ulog

    rec, battery, sp_hist = simulate_flight(vp, hidden, seed)
    rng = np.random.default_rng(seed + 7)
    topics = record_to_topics(rec, vp, battery, sp_hist, rng)
    params = simulated_log_params(vp)  # the rotor layout and hover command as PX4 logs them
    info = {"sys_name": "rotortwin-sim", "ver_hw": "ROTORTWIN_SIM", "sim_vehicle": vp.name}
    write_px4_ulog(str(path), topics, params, info)
    armed = np.isfinite(rec.u).all(1) & (rec.x[:, 2] > 0.5)
    sp = rec.sp[:, 0:3]
    ok = armed & np.isfinite(sp).all(1)
    xy_err = np.hypot(*(rec.x[ok, 0:2] - sp[ok, 0:2]).T)
    z_err = np.abs(rec.x[ok, 2] - sp[ok, 2])
    return {"xy_tracking_rmse_m": float(np.sqrt(np.mean(xy_err ** 2))),
            "z_tracking_rmse_m": float(np.sqrt(np.mean(z_err ** 2))), "duration_s": float(rec.t[-1])}


def _param_error(hidden: Hidden, found: dict) -> float | None:
    """Largest relative error over the hidden effect's identified parameters (motor index exact)."""
    if hidden.name == "none":
        return None
    errs = []
    for k, true in hidden.params.items():
        if k == "gust_std":
            continue  # a noise level, not a physical constant: reported, not scored
        if k not in found:
            return float("inf")
        if k == "motor":
            if int(round(found[k])) != int(true):
                return float("inf")
            continue
        errs.append(abs(found[k] - true) / max(abs(true), 1e-9))
    return max(errs) if errs else 0.0


# ------------------------------------------------------------------ scoring, shared by every source
#
# The rules (issue 11, part 5): the true effect is the top `confirmed` or `likely` finding
# (drag names are one class, and mass with thrust coefficient: each pair changes the same force in a
# way one flight may not tell apart); no finding of either grade on a no-effect flight; the parameter
# within 10 % of the truth; the held-out cut >= 50 % in the channel where the effect acts.

#: grades that count as a finding, best first
FINDING_GRADES = ("confirmed", "likely")
EFFECT_CLASS = {"linear_drag": "drag", "body_drag": "drag", "rotor_drag": "drag",
                "mass": "mass/thrust", "thrust_coefficient": "mass/thrust"}


def verdict(effect: dict) -> str:
    """The graded verdict of one effect of ``discover()``'s result (``accepted`` before grading existed)."""
    v = effect.get("verdict")
    if v:
        return str(v)
    return "confirmed" if effect.get("accepted") else "rejected"


def findings(result: dict) -> list[dict]:
    """The effects graded ``confirmed`` or ``likely``, confirmed first (discover's order within a grade)."""
    eff = [e for e in result.get("effects", []) if verdict(e) in FINDING_GRADES]
    return sorted(eff, key=lambda e: FINDING_GRADES.index(verdict(e)))


def effect_class(name: str) -> str:
    return EFFECT_CLASS.get(name, name)


_MOTORS = ("throttle", "roll", "pitch", "yaw")
_FORCE = ("force_x", "force_y", "throttle")
#: the physical modes (residuals.modes) each effect acts in: its held-out cut is read there
EFFECT_CHANNELS = {"mass": ("throttle",), "thrust_coefficient": ("throttle",), "battery_sag": ("throttle",),
                   "ground_effect": ("throttle",), "motor_efficiency": _MOTORS, "motor_time_constant": _MOTORS,
                   "actuator_delay": _MOTORS, "yaw_moment": ("yaw",), "rotor_tilt": ("yaw",),
                   "inertia": ("roll", "pitch", "yaw"), "angular_damping": ("roll", "pitch", "yaw"),
                   "com_offset": ("roll", "pitch"), "linear_drag": _FORCE, "rotor_drag": _FORCE,
                   "body_drag": _FORCE, "wind": _FORCE}


def heldout_cut(effect: dict) -> dict:
    """The held-out cut of a finding in the effect's own channel.

    discover() reports, per residual it judged on (equation error; output error where it has one), the mode
    with the largest held-out drop.  The cut scored is the largest over those residuals whose mode is one the
    effect acts in (:data:`EFFECT_CHANNELS`); when none is, discover's own headline number, flagged."""
    chans = EFFECT_CHANNELS.get(effect["name"])
    per = [(k, r) for k, r in (effect.get("residuals") or {}).items() if isinstance(r, dict)]
    if not per:
        per = [(effect.get("residual", "equation"), effect)]
    own = [(k, r) for k, r in per if chans is None or r.get("heldout_channel") in chans]
    kind, r = max(own, key=lambda kr: kr[1].get("heldout_improvement") or -math.inf) if own else \
        (effect.get("residual", "equation"), effect)
    return {"residual": kind, "channel": r.get("heldout_channel"), "before": r.get("heldout_before"),
            "after": r.get("heldout_after"), "improvement": r.get("heldout_improvement"), "in_channel": bool(own)}


@dataclass(frozen=True)
class DragContext:
    """What a drag comparison needs from the flight: body-frame airspeed and summed rotor speed on the
    airborne samples (wind-free flights: the ground velocity is the airspeed)."""

    v_body: np.ndarray      # (n, 3) FLU m/s
    sum_omega: np.ndarray   # (n,) rad/s, steady state of the logged commands through the nominal

    @classmethod
    def from_log(cls, log, vp: VehicleParams, rate_hz: float = 10.0) -> "DragContext":
        t0, t1 = log.airborne_interval()
        t, d = log.resample(["velocity_enu", "attitude_q", "motors"], rate_hz, t0, t1)
        ok = np.isfinite(d["velocity_enu"]).all(1) & np.isfinite(d["attitude_q"]).all(1) & \
            np.isfinite(d["motors"]).all(1)
        vb = frames.quat_rotate(frames.quat_conjugate(d["attitude_q"][ok]), d["velocity_enu"][ok])
        ref = vp.rotors.reference_from_command(d["motors"][ok])
        if vp.rotors.thrust_model == "omega_squared":
            omega = ref
        else:  # the reported rotor speed of the thrust-factor model: omega_max sqrt(T / T_max)
            omega = vp.rotors.omega_max_rad_s * np.sqrt(np.maximum(vp.rotors.thrust_from_state(ref), 0)
                                                        / vp.rotors.thrust_max_n)
        return cls(vb, omega.sum(1))

    def force(self, name: str, params: dict) -> np.ndarray:
        """Body force (n, 3) [N] of one drag law on this flight's samples."""
        v = self.v_body
        F = np.zeros_like(v)
        if name == "linear_drag":
            F = -params["k_n_s_m"] * v
        elif name == "rotor_drag":
            F[:, :2] = -params["k_d"] * self.sum_omega[:, None] * v[:, :2]
        elif name == "body_drag":
            c = np.array([params["c_dx"], params["c_dy"], params["c_dz"]])
            F = -c * np.abs(v) * v
        elif name == "rotorpy_parasitic":  # RotorPy's D = -|v| C v (norm times component)
            c = np.array([params["c_dx"], params["c_dy"], params["c_dz"]])
            F = -np.linalg.norm(v, axis=1, keepdims=True) * c * v
        else:
            raise ValueError(f"not a drag law: {name}")
        return F

    def linear_equivalent(self, laws: list[tuple[str, dict]]) -> float:
        """The isotropic linear drag coefficient [N/(m/s)] that does the same work on this flight's airspeeds
        as the sum of ``laws``: -sum(F . v) / sum(|v|^2)."""
        F = sum((self.force(n, p) for n, p in laws), np.zeros_like(self.v_body))
        den = float(np.sum(self.v_body ** 2))
        return float(-np.sum(F * self.v_body) / den) if den > 0 else 0.0


@dataclass(frozen=True)
class Truth:
    """One flight's truth in our effect vocabulary, with what scoring needs beyond the parameters."""

    hidden: Hidden
    text: str = ""                       # how the source states it (e.g. 'SIH_KDV 1.0 -> 1.8')
    drag_law: tuple | None = None        # (name, params) of the true drag law when its form is not ours


def _drag_laws(vp: VehicleParams) -> list[tuple[str, dict]]:
    return [(n, p) for n, p in vp.effect_dict.items() if effect_class(n) == "drag"]


def compare(truth: Truth, found_name: str, found: dict, nominal: VehicleParams,
            drag: DragContext | None = None) -> tuple[float | None, str]:
    """Relative parameter error of a finding against the truth, and the comparison as text.

    Same effect: the largest relative error over the truth's parameters (as the ours suite always scored).
    Mass against thrust coefficient: thrust per unit mass (kt_scale against m0/m), shown in the truth's
    parameter.  Drag against drag (any law): the isotropic linear coefficient that does the same work on this
    flight's airspeeds, nominal drag included (the truth's total against the nominal plus the finding).
    Another class: ``(inf, 'wrong effect')``."""
    h = truth.hidden
    if h.name == "none":
        return None, "-"
    if effect_class(found_name) != effect_class(h.name):
        return float("inf"), "wrong effect"
    if effect_class(h.name) == "drag" and (found_name != h.name or truth.drag_law is not None):
        if drag is None:
            return None, "no airspeed data"
        nominal_laws = _drag_laws(nominal)
        true_laws = [law for law in nominal_laws if law[0] != h.name]
        true_laws.append(truth.drag_law or (h.name, h.params))
        found_laws = [law for law in nominal_laws if law[0] != found_name] + [(found_name, found)]
        k_true = drag.linear_equivalent(true_laws)
        k_found = drag.linear_equivalent(found_laws)
        err = abs(k_found - k_true) / max(abs(k_true), 1e-12)
        return err, f"k_eq {k_found:.4g} vs {k_true:.4g} N/(m/s)"
    if found_name != h.name:  # mass <-> thrust coefficient: thrust per unit mass
        m0 = nominal.mass_kg

        def ratio(name, p):
            return p["kt_scale"] if name == "thrust_coefficient" else m0 / p["mass"]
        r_true, r_found = ratio(h.name, h.params), ratio(found_name, found)
        err = abs(r_found / r_true - 1.0)
        if h.name == "mass":
            return err, f"mass~{m0 / r_found:.4g} vs {h.params['mass']:.4g}"
        return err, f"kt_scale~{r_found:.4g} vs {h.params['kt_scale']:.4g}"
    err = _param_error(h, found)
    worst, worst_e = None, -1.0
    for k, true in h.params.items():
        if k in ("gust_std", "motor") or k not in found:
            continue
        e = abs(found[k] - true) / max(abs(true), 1e-9)
        if e > worst_e:
            worst, worst_e = k, e
    if err is None or not math.isfinite(err) or worst is None:
        return err, "motor index wrong" if err is not None and not math.isfinite(err) else "-"
    return err, f"{worst} {found[worst]:.4g} vs {h.params[worst]:.4g}"


def score_flight(flight: str, truth: Truth, result: dict, nominal: VehicleParams,
                 drag: DragContext | None = None, **facts) -> dict:
    """One row of a prove table from a discover() result (see the rules above)."""
    h = truth.hidden
    found = findings(result)
    top = found[0] if found else None
    right = top is not None and h.name != "none" and effect_class(top["name"]) == effect_class(h.name)
    # not scored: the true effect is the top finding's alternative, one the flight cannot tell apart
    # from it (e.g. a motor lag and a pure delay on a 50 Hz log); shown beside the score
    tied = bool(top is not None and not right and h.name != "none" and any(
        effect_class(a.get("name", "")) == effect_class(h.name) for a in top.get("alternatives") or []))
    err, text = (compare(truth, top["name"], top["params"], nominal, drag) if right else (None, "-"))
    ho = heldout_cut(top) if top else {}
    cut = ho.get("improvement")
    if h.name == "none":
        passed = not found
    else:
        passed = bool(right and err is not None and err <= 0.10 and cut is not None and cut >= 0.5)
    return {"flight": flight, "true_effect": h.label, "true_params": h.params, "truth_text": truth.text,
            "top_finding": top["name"] if top else "none", "top_verdict": verdict(top) if top else "-",
            "findings": [f"{e['name']} ({verdict(e)})" for e in found], "n_findings": len(found),
            "right_class": right, "true_is_alternative": tied, "found_params": top["params"] if top else {},
            "param_error": err, "param_text": text,
            "heldout_channel": ho.get("channel"), "heldout_residual": ho.get("residual"),
            "heldout_before": ho.get("before"), "heldout_after": ho.get("after"),
            "heldout_improvement": cut, "passed": passed,
            # the names the ours suite has always used (tests and older summaries read them)
            "top_accepted": top["name"] if top else "none", "n_accepted": len(found),
            # what discovery ranked first when nothing was found (a rejected candidate): shown, never scored
            "first_candidate": (result.get("effects") or [{}])[0].get("name") if not top else None,
            "elapsed_s": result.get("elapsed_s"), **facts}


def _vehicle(name_or_path: str) -> VehicleParams:
    """A params YAML path, or the stem of a shipped one (``px4_sih_quadx``)."""
    is_path = os.path.exists(name_or_path) or os.sep in name_or_path or name_or_path.endswith((".yaml", ".yml"))
    return load_params(name_or_path) if is_path else shipped(name_or_path)


def run_one(args) -> dict:
    """Fly one of our flights, discover blind, score it (a row of the ours table)."""
    vp_name, hidden, seed, out_dir = args
    from twin_nodes.discovery.discover import discover
    from twin_nodes.logs.ulog_io import read_ulog

    vp = _vehicle(vp_name)
    tag = f"{vp.name}_{hidden.label}_{seed}"
    path = Path(out_dir) / f"{tag}.ulg"
    facts = write_flight(path, vp, hidden, seed)
    log = read_ulog(path)
    res = discover(log, vp, closed_loop_metrics=False)
    res.pop("_series", None)
    drag = DragContext.from_log(log, vp) if effect_class(hidden.name) == "drag" else None
    row = score_flight(tag, Truth(hidden, f"{hidden.name} {hidden.params}" if hidden.params else ""), res, vp,
                       drag, source="ours", **facts)
    write_result(Path(out_dir) / f"{tag}.json", res)
    return row


def write_result(path: Path, res: dict) -> None:
    from twin_nodes.base.io import atomic_write_text

    atomic_write_text(path, json.dumps(res, indent=1, default=_json_default))


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return float(o)


def map_jobs(fn, jobs: list, workers: int, desc: str, progress: bool = True) -> list:
    """``[fn(j) for j in jobs]``, over ``workers`` processes when more than one, with a progress bar."""
    if workers > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as ex:
            it = ex.map(fn, jobs)
            if progress:
                from tqdm import tqdm
                it = tqdm(it, total=len(jobs), desc=desc, unit="flight")
            return list(it)
    it = jobs
    if progress:
        from tqdm import tqdm
        it = tqdm(jobs, desc=desc, unit="flight")
    return [fn(j) for j in it]


def run_suite(out_dir: str | Path, vehicle: str = "px4_sih_quadx", size: str = "full", workers: int = 2,
              progress: bool = True) -> dict:
    """Our generator's suite (source ``ours``): flights written and judged in ``out_dir``."""
    vp = _vehicle(vehicle)          # bad --vehicle: the error comes before anything is written
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(vehicle, h, seed, str(out)) for h, seed in suite(vp, size)]
    return score(map_jobs(run_one, jobs, workers, "prove ours", progress), source="ours")


def score(rows: list[dict], source: str = "ours") -> dict:
    """Per-source accuracy: the issue's four numbers and the flights that pass every rule."""
    with_eff = [r for r in rows if r["true_effect"] != "none"]
    none = [r for r in rows if r["true_effect"] == "none"]
    right = [r for r in with_eff if r.get("right_class", r["top_accepted"] == r["true_effect"])]
    false_acc = [r for r in none if r["n_accepted"] > 0]
    improved = [r for r in right if (r["heldout_improvement"] or 0) >= 0.5]
    within = [r for r in right if r["param_error"] is not None and r["param_error"] <= 0.10]
    passed = [r for r in rows if r.get("passed")]
    tied = [r for r in with_eff if r.get("true_is_alternative")]
    return {
        "source": source,
        "rows": rows,
        "n_effect_flights": len(with_eff),
        "n_no_effect_flights": len(none),
        "n_right_top": len(right),
        "right_top_fraction": len(right) / max(len(with_eff), 1),
        "false_accepts_on_no_effect": len(false_acc),
        "heldout_improved_50pct_fraction": len(improved) / max(len(right), 1),
        "params_within_10pct_fraction": len(within) / max(len(right), 1),
        "n_heldout_50pct": len(improved),
        "n_params_within_10pct": len(within),
        "n_passed": len(passed),
        "n_true_is_alternative": len(tied),
        "n_flights": len(rows),
    }


def breakdown(summary: dict, key: str) -> list[str]:
    """The summary line of each group of rows that share ``row[key]`` (e.g. the PX4 SIH flights'
    ``logging`` profile or ``sih_change``); nothing when no row has ``key`` or there is one group."""
    groups: dict[str, list[dict]] = {}
    for r in summary["rows"]:
        if key in r:
            groups.setdefault(str(r[key]), []).append(r)
    if len(groups) < 2:
        return []
    return [summary_line(score(rows, source=f"{summary.get('source', 'ours')} [{key} {name}]"))
            for name, rows in sorted(groups.items())]


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f} %"


def format_table(summary: dict) -> str:
    """One source's table: flight, true effect, top finding + verdict, parameter vs truth, held-out cut,
    pass/fail; then the summary line."""
    rows = summary["rows"]
    track = any("xy_tracking_rmse_m" in r for r in rows)
    fw = max([len("flight")] + [len(r["flight"]) for r in rows])
    head = (f"{'flight':<{fw}}  {'true effect':<20} {'top finding (verdict)':<32} {'parameter vs truth':<36} "
            f"{'param err':>9} {'held-out':>15} {'cut':>5} {'in':<14} {'result':<6}")
    if track:
        head += f" {'XY trk':>7} {'Z trk':>6}"
    lines = [head]
    for r in rows:
        top = "none" if r["top_accepted"] == "none" else f"{r['top_accepted']} ({r.get('top_verdict', 'confirmed')})"
        if top == "none" and r["true_effect"] != "none" and r.get("first_candidate"):
            top = f"none [1st: {r['first_candidate']}]"
        if r.get("n_findings", r["n_accepted"]) > 1:
            top += f" +{r.get('n_findings', r['n_accepted']) - 1}"
        pe = r["param_error"]
        pe_s = "-" if pe is None else ("wrong" if not math.isfinite(pe) else f"{100 * pe:.1f} %")
        ho = "-" if r["heldout_before"] is None else f"{r['heldout_before']:.3f}->{r['heldout_after']:.3f}"
        ok = "pass" if r.get("passed") else "FAIL"
        where = "-" if not r.get("heldout_channel") else \
            f"{r['heldout_channel']} ({str(r.get('heldout_residual') or 'equation')[:3]})"
        line = (f"{r['flight']:<{fw}}  {r['true_effect']:<20} {top:<32} {r.get('param_text', '-'):<36} {pe_s:>9} "
                f"{ho:>15} {_pct(r['heldout_improvement']):>5} {where:<14} {ok:<6}")
        if track:
            line += f" {r.get('xy_tracking_rmse_m', math.nan):>6.2f}m {r.get('z_tracking_rmse_m', math.nan):>5.2f}m"
        lines.append(line.rstrip())
    lines.append(summary_line(summary))
    lines += breakdown(summary, "logging") + breakdown(summary, "sih_change")
    return "\n".join(lines)


def summary_line(summary: dict) -> str:
    s = summary
    return (f"{s.get('source', 'ours')}: right effect on top {s['n_right_top']}/{s['n_effect_flights']} "
            f"({_pct(s['right_top_fraction'])}); findings on no-effect flights "
            f"{s['false_accepts_on_no_effect']}/{s['n_no_effect_flights']}; params within 10 % "
            f"{s['n_params_within_10pct']}/{s['n_right_top']}; held-out cut >= 50 % "
            f"{s['n_heldout_50pct']}/{s['n_right_top']}; flights passing every rule {s['n_passed']}/{s['n_flights']}"
            + (f" (not scored: on {s['n_true_is_alternative']} more the true effect is the top finding's "
               "not-told-apart alternative)" if s.get("n_true_is_alternative") else ""))

