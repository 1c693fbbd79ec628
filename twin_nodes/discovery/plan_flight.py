"""Fly a mission plan's waypoints with our simulator (as ``rotortwin simulate --plan``).

The plan is flown the way PX4 flies a mission: arm, take off to the first item's altitude above
home, then each waypoint in turn, the heading towards it (``MPC_YAW_MODE 0``: turn first, at
``YAW_RATE`` rad/s, when the direction changes by more than a few degrees), a trapezoidal speed
profile along the leg (``ACC`` m/s^2 up to the item's speed; vertical speed limited to
``MPC_Z_V_AUTO_UP``/``_DN``); a stop item ends at rest with a 0.5 s hold, a fly-through item keeps
its speed into the next leg.  After the last item: return to launch at ``RTL_ALT`` and land
(``rtl_after``) or land where it is.  The PX4-like controller flies the setpoints (250 Hz), the
plant carries the hidden effect, the log is written like :func:`twin_nodes.twin.simflight.write_flight`
does (same topics, rates and noise).

Waypoints come as ``(north_m, east_m, alt_m, speed_m_s, fly_through)`` tuples (the CLI reads the
plan file with :func:`twin_nodes.mavlink.mission.load_plan`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from twin_nodes.twin.sim import fly_closed_loop
from twin_nodes.twin.simflight import EstimateNoise, Hidden, record_to_topics
from twin_nodes.vehicle.export_px4 import simulated_log_params
from twin_nodes.vehicle.params import VehicleParams

YAW_RATE = 0.8          # rad/s (PX4 MPC_YAWRAUTO_MAX 45 deg/s)
ACC = 2.5               # m/s^2 horizontal acceleration
V_UP, V_DN = 3.0, 1.5   # m/s (MPC_Z_V_AUTO_UP / _DN)
RTL_ALT = 15.0
HOLD_S = 0.5


class _Setpoints:
    """The setpoint history being written, and where the vehicle is: :func:`plan_setpoints`' moves."""

    def __init__(self, rate_hz: float):
        self.rate_hz = rate_hz
        self.dt = 1.0 / rate_hz
        self.T, self.P, self.V, self.A, self.Y = [], [], [], [], []
        self.pos = np.zeros(3)
        self.vel = np.zeros(3)
        self.yaw = 0.0
        self.tt = 0.0

    def emit(self, p, v, a, y):
        self.T.append(self.tt)
        self.P.append(np.array(p, float))
        self.V.append(np.array(v, float))
        self.A.append(np.array(a, float))
        self.Y.append(y)
        self.tt += self.dt

    def hold(self, seconds):
        for _ in range(int(seconds * self.rate_hz)):
            self.emit(self.pos, np.zeros(3), np.zeros(3), self.yaw)

    def turn_to(self, heading):
        dt = self.dt
        while abs(_wrap(heading - self.yaw)) > YAW_RATE * dt:
            self.yaw = _wrap(self.yaw + math.copysign(YAW_RATE * dt, _wrap(heading - self.yaw)))
            self.emit(self.pos, np.zeros(3), np.zeros(3), self.yaw)
        self.yaw = heading

    def vertical(self, target):
        dt = self.dt
        while abs(target - self.pos[2]) > 0.05:
            vz = V_UP if target > self.pos[2] else -V_DN
            step = vz * dt
            if abs(step) > abs(target - self.pos[2]):
                step = target - self.pos[2]
            self.pos = self.pos + np.array([0.0, 0.0, step])
            self.emit(self.pos, np.array([0.0, 0.0, vz]), np.zeros(3), self.yaw)
        self.pos = np.array([self.pos[0], self.pos[1], target])

    def leg(self, b, cruise, stop):
        """Straight line to b; speed along it ramps at ACC, limited so the vertical part stays
        within the climb/descent limits; ends at rest when ``stop``."""
        dt = self.dt
        d = b - self.pos
        length = float(np.linalg.norm(d))
        if length < 1e-6:
            return
        u = d / length
        vmax = cruise
        if abs(u[2]) > 1e-6:
            vmax = min(vmax, (V_UP if u[2] > 0 else V_DN) / abs(u[2]))
        s = 0.0
        v = min(float(np.dot(self.vel, u)), vmax) if np.linalg.norm(self.vel) > 0 else 0.0
        v = max(v, 0.0)
        a = self.pos.copy()
        while s < length:
            remaining = length - s
            if stop and v * v / (2 * ACC) >= remaining:
                v = max(v - ACC * dt, 0.2)
                ac = -ACC
            else:
                v = min(v + ACC * dt, vmax)
                ac = ACC if v < vmax else 0.0
            s = min(s + v * dt, length)
            self.emit(a + u * s, u * v, u * ac, self.yaw)
        self.pos = b.copy()
        self.vel = np.zeros(3) if stop else u * v


def plan_setpoints(waypoints: Sequence[tuple], rtl_after: bool = True, rate_hz: float = 250.0):
    """Setpoint history (ENU) of a plan flown PX4-style: returns t, SP (T, 11), armed(t)."""
    f = _Setpoints(rate_hz)
    dt = f.dt
    armed_from = 2.0
    f.hold(3.0)
    wps = [np.array([w[1], w[0], w[2]], float) for w in waypoints]   # ENU: east, north, up
    # PX4 inserts a take-off to the first item's altitude
    f.vertical(wps[0][2])
    f.hold(1.0)
    for i, (b, w) in enumerate(zip(wps, waypoints)):
        speed, through = float(w[3]), bool(w[4])
        horiz = b[:2] - f.pos[:2]
        if np.hypot(*horiz) > 1.0:
            heading = math.atan2(horiz[1], horiz[0])
            if abs(_wrap(heading - f.yaw)) > math.radians(10) or np.linalg.norm(f.vel) < 0.1:
                if np.linalg.norm(f.vel) > 0.1:      # a fly-through corner with a big turn: PX4 slows down
                    f.vel = np.zeros(3)
                f.turn_to(heading)
            else:
                f.yaw = heading
        f.leg(b, speed, stop=not through or i == len(wps) - 1)
        if not through:
            f.hold(HOLD_S)
    if rtl_after:
        f.vertical(max(RTL_ALT, f.pos[2]))
        home = np.array([0.0, 0.0, f.pos[2]])
        if np.hypot(*(home[:2] - f.pos[:2])) > 1.0:
            f.turn_to(math.atan2(-f.pos[1], -f.pos[0]))
            f.leg(home, 5.0, stop=True)
        f.hold(1.0)
    # land: MPC_LAND_SPEED 0.7 m/s, the last 1.5 m at MPC_LAND_CRWL 0.3 m/s
    while f.pos[2] > -0.5:
        vz = -0.7 if f.pos[2] > 1.5 else -0.3
        f.pos = f.pos + np.array([0.0, 0.0, vz * dt])
        f.emit(f.pos, np.array([0.0, 0.0, vz]), np.zeros(3), f.yaw)
    armed_until = f.tt + 1.5
    f.hold(2.0)
    t = np.array(f.T)
    SP = np.full((len(t), 11), np.nan)
    SP[:, 0:3] = f.P
    SP[:, 3:6] = f.V
    SP[:, 6:9] = f.A
    SP[:, 9] = f.Y
    SP[t < armed_from] = np.nan
    return t, SP, (lambda tq, a0=armed_from, a1=armed_until: (tq >= a0) & (tq < a1))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def write_plan_flight(path: str | Path, vp: VehicleParams, hidden: Hidden, seed: int,
                      waypoints: Sequence[tuple], rtl_after: bool = True) -> dict:
    """Fly the plan with the hidden effect and write the flight as a PX4-like ULog."""
    from twin_nodes.logs.ulog_write import write_px4_ulog

    rng = np.random.default_rng(seed)
    t_sp, SP, armed = plan_setpoints(waypoints, rtl_after)
    plant = vp if hidden.name == "none" else vp.with_effect(hidden.name, **hidden.params)
    v_full, v_empty = 16.6, 14.6
    t_end = float(t_sp[-1])

    def battery(t):
        return v_full - (v_full - v_empty) * np.clip(t / t_end, 0, 1) ** 1.3

    rec = fly_closed_loop(plant, t_sp, SP, controller_params=vp, battery_v=battery,
                          estimate_noise=EstimateNoise(rng, 1.0 / 250.0), armed=armed, rng=rng)
    topics = record_to_topics(rec, vp, battery, (t_sp, SP), np.random.default_rng(seed + 7))
    params = simulated_log_params(vp)  # the rotor layout and hover command as PX4 logs them
    write_px4_ulog(str(path), topics, params, {"sys_name": "rotortwin-sim", "ver_hw": "ROTORTWIN_SIM",
                                                "sim_vehicle": vp.name})
    flying = np.isfinite(rec.u).all(1) & (rec.x[:, 2] > 0.5)
    ok = flying & np.isfinite(rec.sp[:, 0:3]).all(1)
    xy = np.hypot(*(rec.x[ok, 0:2] - rec.sp[ok, 0:2]).T)
    z = np.abs(rec.x[ok, 2] - rec.sp[ok, 2])
    return {"xy_tracking_rmse_m": float(np.sqrt(np.mean(xy ** 2))) if xy.size else float("nan"),
            "z_tracking_rmse_m": float(np.sqrt(np.mean(z ** 2))) if z.size else float("nan"),
            "duration_s": float(rec.t[-1])}


__all__ = ["plan_setpoints", "write_plan_flight"]
