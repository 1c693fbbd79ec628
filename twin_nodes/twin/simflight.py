"""Flights with a hidden effect, flown by our simulator and logged the way PX4 logs them.

A PX4-style mission (take-off, legs with altitude changes and yaw turns, a hover, landing) flown by
the PX4-like controller, which believes the *nominal* vehicle while the plant carries one hidden
effect (:class:`Hidden`).  The flight is logged the way PX4 logs it: estimator-grade noise on
position/velocity/attitude (GPS-like random walk, :class:`EstimateNoise`), accelerometer and gyro
noise, the motor topic sampled at 50 Hz from a 250 Hz controller (aliasing included), battery at
5 Hz (:func:`record_to_topics`), written as a ULog (:func:`write_flight`).

Used by ``rotortwin simulate``, the confirmation plans' flights (:mod:`twin_nodes.discovery.plan_flight`),
the simulated fleet (:mod:`twin_nodes.fleet.simfleet`) and the prove suite's own source
(:mod:`twin_nodes.prove.ours`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin_nodes.base import frames
from twin_nodes.twin.sim import fly_closed_loop
from twin_nodes.vehicle.export_px4 import simulated_log_params
from twin_nodes.vehicle.params import VehicleParams

__all__ = ["LOG_RATES_HZ", "Hidden", "mission_setpoints", "EstimateNoise", "simulate_flight", "record_to_topics",
           "write_flight"]

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
                     start_us: int = 20_000_000, imu_stride: int = 0):
    """PX4 topics (NED/FRD, µs) sampled at LOG_RATES_HZ from a simulated flight.

    ``imu_stride``: ``sensor_combined`` is every ``imu_stride``-th record sample (uniform stamps at the
    record's rate over the stride, its noise scaled to keep the 100 Hz log's noise per second); 0: 100 Hz
    picked from the record at the next record sample, which on a 250 Hz record gives stamps 8 and 12 ms
    apart (``time_sync.bin_mean_to``'s 20 ms bins then average samples whose mean time is up to 4 ms off
    the bin's centre, by the flight's phase)."""
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
    imu_hz = float(LOG_RATES_HZ["sensor_combined"])
    if imu_stride:
        k = np.arange(0, len(t), int(imu_stride))
        imu_hz = 1.0 / (float(np.median(np.diff(t))) * int(imu_stride))
    else:
        k = idx(imu_hz)
    grade = np.sqrt(imu_hz / LOG_RATES_HZ["sensor_combined"])  # white noise: the same per second at any rate
    sf = frames.flu_to_frd(rec.specific_force[k]) + rng.standard_normal((len(k), 3)) * 0.08 * grade
    gyro = frames.flu_to_frd(rec.x[k, 10:13]) + rng.standard_normal((len(k), 3)) * 0.004 * grade
    integral_us = np.full(len(k), int(round(1e6 / imu_hz)), np.uint32)
    topics["sensor_combined"] = {"timestamp": ts(k), "gyro_rad": gyro, "accelerometer_m_s2": sf,
                                 "accelerometer_timestamp_relative": np.zeros(len(k), np.int32),
                                 "gyro_integral_dt": integral_us, "accelerometer_integral_dt": integral_us.copy()}
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
