"""The geometric SE(3) tracking law (Lee, Leok, McClamroch, CDC 2010), world ENU, body FLU.

The controller RotorPy flies (``rotorpy.controllers.quadrotor_control.SE3Control``), written out so that a
twin of a vehicle flown by it flies the same law (``controller: {law: se3}`` in its params; PX4's cascade is
:mod:`twin_nodes.twin.control`).  A closed-loop twin that flies another controller than the vehicle's differs
from it by the two controllers' dynamics, whatever its physics: on RotorPy flights PX4's cascade left the twin's
held-out throttle 26-28 % off with any model (issue 27).

    F_des = m (-Kp e_x - Kd e_v + a_ff + g e3),      u1 = F_des . R e3
    R_des = [b1 b2 b3], b3 = F_des / |F_des|, b2 = b3 x c1(yaw) / |.|, b1 = b2 x b3
    e_R = vee(R_des^T R - R^T R_des) / 2,  e_w = w - (0, 0, yaw_rate)
    u2 = J (-kp_att e_R - kd_att e_w) + w x J w

then rotor thrusts by the vehicle's allocation (pseudo-inverse of its effectiveness), and each rotor's command
from its thrust curve (no desaturation: RotorPy clips each rotor's speed).  The law has no integrator.

Mass and inertia are the controller's belief: the params it was given (``believed``), not the twin's fitted
physics, as RotorPy's controller believes the nominal vehicle whatever flies.
"""

from __future__ import annotations

import math

import numpy as np

from twin_nodes.physics.core import pack
from twin_nodes.twin.control import INFO_SIZE, ControllerGains, _max_rotor_thrust, _thrust_to_cmd, allocation_table
from twin_nodes.vehicle.params import VehicleParams


def _rotmat(q) -> np.ndarray:
    """Body FLU -> world ENU rotation from a unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _quat(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def _vee(S: np.ndarray) -> np.ndarray:
    return np.array([-S[1, 2], S[0, 2], -S[0, 1]])


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-12 else np.array([0.0, 0.0, 1.0])


def desired_rotation(b3: np.ndarray, yaw: float) -> np.ndarray:
    """R_des from the thrust direction ``b3`` and the heading ``yaw`` (ENU, from east)."""
    c1 = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    b2 = _unit(np.cross(b3, c1))
    return np.column_stack([np.cross(b2, b3), b2, b3])


def _yaw_of(R: np.ndarray) -> float:
    return math.atan2(R[1, 0], R[0, 0])


class SE3Controller:
    """Stateless law with :class:`twin_nodes.twin.control.Controller`'s interface:
    ``u, info = ctrl.update(x, sp, dt)``; ``info``: collective throttle (of the rotors' full thrust), thrust [N],
    attitude setpoint q (w, x, y, z), rate setpoint (FLU)."""

    law = "se3"

    def __init__(self, vp: VehicleParams, believed: VehicleParams | None = None):
        b = believed or vp
        self.params = vp
        self.gains = ControllerGains.from_params(vp)
        g = self.gains
        self.kp = np.array([g.se3_kp_xy_1_s2, g.se3_kp_xy_1_s2, g.se3_kp_z_1_s2])
        self.kd = np.array([g.se3_kd_xy_1_s, g.se3_kd_xy_1_s, g.se3_kd_z_1_s])
        self.mass = float(b.mass_kg)
        self.g = float(b.gravity_m_s2)
        self.J = np.asarray(b.inertia, float)
        self.P = pack(vp)
        self.alloc = allocation_table(vp)[:, 0:4]
        self.n = vp.rotors.count
        self.thrust_full = self.n * float(_max_rotor_thrust(self.P))

    def reset(self) -> None:
        """The law keeps no state."""

    def _motors(self, u1: float, u2: np.ndarray, qd: np.ndarray, w_sp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f = self.alloc @ np.array([u1, u2[0], u2[1], u2[2]])
        u = np.array([_thrust_to_cmd(self.P, float(fi)) for fi in f])
        info = np.empty(INFO_SIZE)
        info[0] = min(max(u1 / self.thrust_full, 0.0), 1.0)
        info[1] = u1
        info[2:6] = qd
        info[6:9] = w_sp
        return u, info

    def _moment(self, R: np.ndarray, R_des: np.ndarray, w: np.ndarray, w_des: np.ndarray) -> tuple:
        e_R = _vee(0.5 * (R_des.T @ R - R.T @ R_des))
        w_cmd = -self.gains.se3_kp_att_1_s2 * e_R - self.gains.se3_kd_att_1_s * (w - w_des)
        return self.J @ w_cmd + np.cross(w, self.J @ w), w_cmd

    def update(self, x: np.ndarray, sp: np.ndarray, dt: float, q_att: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """One step on the setpoint ``sp`` (position, velocity, acceleration, yaw, yaw rate; NaN: that term
        left out, a NaN yaw holds the current heading)."""
        R = _rotmat(x[6:10])
        p_sp, v_sp, a_sp = (np.nan_to_num(np.asarray(sp[i:i + 3], float), nan=0.0) for i in (0, 3, 6))
        e_x = np.where(np.isfinite(sp[0:3]), x[0:3] - p_sp, 0.0)
        e_v = np.where(np.isfinite(sp[3:6]) | np.isfinite(sp[0:3]), x[3:6] - v_sp, 0.0)
        F = self.mass * (-self.kp * e_x - self.kd * e_v + a_sp + np.array([0.0, 0.0, self.g]))
        u1 = float(F @ R[:, 2])
        yaw = float(sp[9]) if math.isfinite(sp[9]) else _yaw_of(R)
        R_des = desired_rotation(_unit(F), yaw)
        w_des = np.array([0.0, 0.0, float(sp[10]) if math.isfinite(sp[10]) else 0.0])
        u2, w_cmd = self._moment(R, R_des, np.asarray(x[10:13], float), w_des)
        return self._motors(u1, u2, _quat(R_des), w_cmd)

    def update_manual(self, x: np.ndarray, q_sp: np.ndarray | None, throttle: float, dt: float,
                      yawspeed: float = float("nan"), rates: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
        """An attitude (``q_sp``, w x y z) or rate (``rates``, FLU) setpoint with a collective ``throttle``
        (of full thrust), through the law's attitude loop."""
        if rates is None and q_sp is None:
            raise ValueError("update_manual: expected an attitude setpoint q_sp or a rate setpoint")
        R = _rotmat(x[6:10])
        w = np.asarray(x[10:13], float)
        if rates is not None:
            R_des, w_des = R, np.asarray(rates, float)
        else:
            R_des = _rotmat(np.asarray(q_sp, float))
            w_des = np.array([0.0, 0.0, yawspeed if math.isfinite(yawspeed) else 0.0])
        u2, w_cmd = self._moment(R, R_des, w, w_des)
        thr = float(throttle) if math.isfinite(throttle) else 0.0
        return self._motors(thr * self.thrust_full, u2, _quat(R_des), w_cmd)
