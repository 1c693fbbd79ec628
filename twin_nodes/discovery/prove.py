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

from twin_nodes import frames
from twin_nodes.control import setpoint
from twin_nodes.params import VehicleParams, load_params, shipped
from twin_nodes.physics.effects import make_effect
from twin_nodes.sim import fly_closed_loop

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
    from twin_nodes.ulog_write import write_px4_ulog

    rec, battery, sp_hist = simulate_flight(vp, hidden, seed)
    rng = np.random.default_rng(seed + 7)
    topics = record_to_topics(rec, vp, battery, sp_hist, rng)
    r = vp.rotors
    params = {"SYS_AUTOSTART": 0, "CA_ROTOR_COUNT": int(r.count), "MPC_THR_HOVER": float(vp.hover_command)}
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


def _vehicle(name_or_path: str) -> VehicleParams:
    """A params YAML path, or the stem of a shipped one (``px4_sih_quadx``)."""
    return load_params(name_or_path) if os.path.exists(name_or_path) else shipped(name_or_path)


def run_one(args) -> dict:
    vp_name, hidden, seed, out_dir = args
    from twin_nodes.discovery.discover import discover
    from twin_nodes.ulog_io import read_ulog

    vp = _vehicle(vp_name)
    tag = f"{vp.name}_{hidden.label}_{seed}"
    path = Path(out_dir) / f"{tag}.ulg"
    facts = write_flight(path, vp, hidden, seed)
    log = read_ulog(path)
    res = discover(log, vp, closed_loop_metrics=False)
    accepted = [e for e in res["effects"] if e["accepted"]]
    top = accepted[0] if accepted else None
    found_params = top["params"] if top else {}
    row = {"flight": tag, "true_effect": hidden.label, "true_params": hidden.params,
           "top_accepted": top["name"] if top else "none", "found_params": found_params,
           "n_accepted": len(accepted),
           "param_error": _param_error(hidden, found_params) if top and top["name"] == hidden.name else None,
           "heldout_before": top["heldout_before"] if top else None,
           "heldout_after": top["heldout_after"] if top else None,
           "heldout_improvement": top["heldout_improvement"] if top else None,
           "elapsed_s": res["elapsed_s"], **facts}
    res.pop("_series", None)
    with open(Path(out_dir) / f"{tag}.json", "w") as fh:
        json.dump(res, fh, indent=1, default=float)
    return row


def run_suite(out_dir: str | Path, vehicle: str = "px4_sih_quadx", size: str = "full", workers: int = 2,
              progress: bool = True) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    vp = _vehicle(vehicle)
    jobs = [(vehicle, h, seed, str(out)) for h, seed in suite(vp, size)]
    rows = []
    if workers > 1:
        with ProcessPoolExecutor(max_workers=workers) as ex:
            it = ex.map(run_one, jobs)
            if progress:
                from tqdm import tqdm
                it = tqdm(it, total=len(jobs), desc="prove", unit="flight")
            rows = list(it)
    else:
        it = jobs
        if progress:
            from tqdm import tqdm
            it = tqdm(jobs, desc="prove", unit="flight")
        rows = [run_one(j) for j in it]
    return score(rows)


def score(rows: list[dict]) -> dict:
    with_eff = [r for r in rows if r["true_effect"] != "none"]
    none = [r for r in rows if r["true_effect"] == "none"]
    right = [r for r in with_eff if r["top_accepted"] == r["true_effect"]]
    false_acc = [r for r in none if r["n_accepted"] > 0]
    improved = [r for r in right if (r["heldout_improvement"] or 0) >= 0.5]
    within = [r for r in right if r["param_error"] is not None and r["param_error"] <= 0.10]
    return {
        "rows": rows,
        "right_top_fraction": len(right) / max(len(with_eff), 1),
        "false_accepts_on_no_effect": len(false_acc),
        "heldout_improved_50pct_fraction": len(improved) / max(len(right), 1),
        "params_within_10pct_fraction": len(within) / max(len(right), 1),
        "n_flights": len(rows),
    }


def format_table(summary: dict) -> str:
    lines = [f"{'true effect':<20} {'top accepted':<20} {'param err':>9} {'held-out':>17} {'cut':>6} "
             f"{'XY trk':>7} {'Z trk':>6}"]
    for r in summary["rows"]:
        pe = "-" if r["param_error"] is None else ("wrong" if not math.isfinite(r["param_error"]) else
                                                   f"{100 * r['param_error']:.1f} %")
        ho = "-" if r["heldout_before"] is None else f"{r['heldout_before']:.3f}->{r['heldout_after']:.3f}"
        cut = "-" if r["heldout_improvement"] is None else f"{100 * r['heldout_improvement']:.0f} %"
        lines.append(f"{r['true_effect']:<20} {r['top_accepted']:<20} {pe:>9} {ho:>17} {cut:>6} "
                     f"{r['xy_tracking_rmse_m']:>6.2f}m {r['z_tracking_rmse_m']:>5.2f}m")
    lines.append(f"right effect on top: {100 * summary['right_top_fraction']:.0f} %   false accepts on no-effect "
                 f"flights: {summary['false_accepts_on_no_effect']}   held-out cut >= 50 %: "
                 f"{100 * summary['heldout_improved_50pct_fraction']:.0f} %   params within 10 %: "
                 f"{100 * summary['params_within_10pct_fraction']:.0f} %")
    return "\n".join(lines)
