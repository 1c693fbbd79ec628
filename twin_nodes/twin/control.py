"""A PX4-like cascaded multirotor controller (world ENU, body FLU).

position P -> velocity PID -> thrust vector (tilt limit) -> attitude P (quaternion,
reduced yaw weight) -> body-rate PID -> control allocation -> motor commands.

The outer loops use PX4's multicopter defaults (MPC_*, MC_*_P).  The rate loop
works in physical units (angular acceleration per rate error), and the
allocation uses the vehicle's own geometry and thrust curve, so one gain set
flies vehicles from 1 kg to 6 kg; PX4's normalised rate gains depend on each
airframe's effectiveness matrix and would not.  Gains come from the params
file's ``controller:`` section (keys below, unit in the name).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np
from numba import njit

from twin_nodes.base.errors import ParamsError
from twin_nodes.vehicle.geometry import allocation_matrix
from twin_nodes.vehicle.params import VehicleParams
from twin_nodes.physics.core import I_FAC, I_G, I_KT, I_MASS, I_MODE, I_N, I_TMAX, I_WCMD, I_WMAX, I_WMIN


@dataclass(frozen=True)
class ControllerGains:
    rate_hz: float = 250.0
    xy_p_1_s: float = 0.95              # MPC_XY_P
    z_p_1_s: float = 1.0                # MPC_Z_P
    xy_vel_p_1_s: float = 1.8           # MPC_XY_VEL_P_ACC
    xy_vel_i_1_s2: float = 0.4          # MPC_XY_VEL_I_ACC
    xy_vel_d: float = 0.2               # MPC_XY_VEL_D_ACC
    z_vel_p_1_s: float = 4.0            # MPC_Z_VEL_P_ACC
    z_vel_i_1_s2: float = 2.0           # MPC_Z_VEL_I_ACC
    z_vel_d: float = 0.0                # MPC_Z_VEL_D_ACC
    xy_vel_max_m_s: float = 12.0        # MPC_XY_VEL_MAX
    z_vel_max_up_m_s: float = 3.0       # MPC_Z_VEL_MAX_UP
    z_vel_max_dn_m_s: float = 1.5       # MPC_Z_VEL_MAX_DN
    tilt_max_deg: float = 45.0          # MPC_TILTMAX_AIR
    thr_min: float = 0.12               # MPC_THR_MIN (fraction of max collective thrust)
    thr_max: float = 1.0                # MPC_THR_MAX
    roll_p_1_s: float = 6.5             # MC_ROLL_P
    pitch_p_1_s: float = 6.5            # MC_PITCH_P
    yaw_p_1_s: float = 2.8              # MC_YAW_P
    yaw_weight: float = 0.4             # MC_YAW_WEIGHT
    rollrate_max_deg_s: float = 220.0   # MC_ROLLRATE_MAX
    yawrate_max_deg_s: float = 200.0    # MC_YAWRATE_MAX
    rate_p_1_s: float = 14.0            # angular accel [rad/s^2] per rate error [rad/s], roll/pitch
    rate_i_1_s2: float = 8.0
    rate_d: float = 0.12
    yawrate_p_1_s: float = 6.0
    yawrate_i_1_s2: float = 2.0
    #: the rate integrators' limits (PX4's MC_RR/PR/YR_INT_LIM, normalised torque, as angular acceleration:
    #: a from-log nominal converts them per axis; pitch and yaw default to the roll value where not given)
    rate_i_max_rad_s2: float = 10.0
    pitchrate_i_max_rad_s2: float = 10.0
    yawrate_i_max_rad_s2: float = 10.0
    vel_i_max_m_s2: float = 4.0
    airmode: float = 0.0                # MC_AIRMODE: 0 off, 1 roll/pitch, 2 roll/pitch/yaw
    #: desaturation skips rotors whose share of the desaturation direction is below this: 0.2 in PX4's
    #: control allocator (>= 1.13, ControlAllocationSequentialDesaturation), FLT_EPSILON in the mixer
    desat_min_effect: float = 0.2
    #: the geometric SE(3) law (``law: se3``, :mod:`twin_nodes.twin.control_se3`; Lee, Leok, McClamroch 2010,
    #: as RotorPy's SE3Control): position and velocity gains per axis, attitude and rate gains; the defaults
    #: are RotorPy 3's
    se3_kp_xy_1_s2: float = 6.5
    se3_kp_z_1_s2: float = 15.0
    se3_kd_xy_1_s: float = 4.0
    se3_kd_z_1_s: float = 9.0
    se3_kp_att_1_s2: float = 310.0
    se3_kd_att_1_s: float = 57.0

    @classmethod
    def from_params(cls, vp: VehicleParams) -> "ControllerGains":
        cfg: Mapping[str, Any] = vp.controller or {}
        names = {f.name for f in fields(cls)}
        kwargs = {}
        for k, v in cfg.items():
            if k == "law":
                continue  # which control law (controller_law), not a gain
            if k not in names:
                raise ParamsError(vp.source, f"controller.{k}", f"unknown gain (known: {', '.join(sorted(names))})")
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ParamsError(vp.source, f"controller.{k}", f"expected a number, got {v!r}")
            kwargs[k] = float(v)
        for axis in ("pitchrate_i_max_rad_s2", "yawrate_i_max_rad_s2"):
            if "rate_i_max_rad_s2" in kwargs and axis not in kwargs:
                kwargs[axis] = kwargs["rate_i_max_rad_s2"]
        g = cls(**{**cls.auto_defaults(vp), **kwargs})
        if g.rate_hz <= 0:
            raise ParamsError(vp.source, "controller.rate_hz", "expected > 0")
        if g.airmode not in (0.0, 1.0, 2.0):
            raise ParamsError(vp.source, "controller.airmode", f"expected 0, 1 or 2 (MC_AIRMODE), got {g.airmode:g}")
        if not 0.0 <= g.desat_min_effect < 1.0:
            raise ParamsError(vp.source, "controller.desat_min_effect", f"expected 0..1, got {g.desat_min_effect:g}")
        return g

    @classmethod
    def auto_defaults(cls, vp: VehicleParams) -> dict[str, float]:
        """Gains that keep the cascade stable for this vehicle's motor lag.

        With a first-order motor lag tau the rate loop's phase margin is about
        90 deg - atan(Kp tau), so Kp <= 0.7 / tau keeps it near 55 deg; each outer loop
        is kept a factor ~2-3.5 slower than the loop inside it.  The values are capped at
        the class defaults, so fast-motor vehicles (SIH tau 0.05 s, Búho Negro 0.028 s)
        get exactly those; slow motors (the 3DR Quad-C, tau 0.15 s) get gentler loops.
        Keys given in the params file's ``controller:`` section override these."""
        d = cls()
        tau = max(vp.rotors.tau_up_s, vp.rotors.tau_down_s, 1e-3)

        def cap(default, value):  # the default wherever the limit does not bind (float-exact)
            return default if value >= default * (1 - 1e-9) else value
        rate_p = cap(d.rate_p_1_s, 0.7 / tau)
        s = rate_p / d.rate_p_1_s  # exactly 1 when the cap does not bind
        att_p = cap(d.roll_p_1_s, rate_p / 2.0)
        yawrate_p = cap(d.yawrate_p_1_s, 0.3 / tau)
        xy_vel_p = cap(d.xy_vel_p_1_s, 0.28 * att_p)
        sv = xy_vel_p / d.xy_vel_p_1_s
        return {
            "rate_p_1_s": rate_p, "rate_i_1_s2": d.rate_i_1_s2 * s, "rate_d": d.rate_d * s,
            "roll_p_1_s": att_p, "pitch_p_1_s": att_p,
            "yawrate_p_1_s": yawrate_p,
            "yawrate_i_1_s2": d.yawrate_i_1_s2 * (yawrate_p / d.yawrate_p_1_s),
            "yaw_p_1_s": cap(d.yaw_p_1_s, yawrate_p / 2.0),
            "xy_vel_p_1_s": xy_vel_p, "xy_vel_i_1_s2": d.xy_vel_i_1_s2 * sv, "xy_vel_d": d.xy_vel_d * sv,
            "xy_p_1_s": cap(d.xy_p_1_s, 0.53 * xy_vel_p),
            "z_vel_p_1_s": cap(d.z_vel_p_1_s, 0.6 / tau),
        }

    def vector(self) -> np.ndarray:
        return np.array([getattr(self, f.name) for f in fields(self)], dtype=np.float64)


_G = {f.name: i for i, f in enumerate(fields(ControllerGains))}
(G_XY_P, G_Z_P, G_XYV_P, G_XYV_I, G_XYV_D, G_ZV_P, G_ZV_I, G_ZV_D, G_XYV_MAX, G_ZV_UP, G_ZV_DN, G_TILT,
 G_THR_MIN, G_THR_MAX, G_ROLL_P, G_PITCH_P, G_YAW_P, G_YAW_W, G_RR_MAX, G_YR_MAX, G_R_P, G_R_I, G_R_D,
 G_YR_P, G_YR_I, G_R_IMAX, G_P_IMAX, G_Y_IMAX, G_V_IMAX, G_AIRMODE, G_DESAT_EPS) = (
    _G[k] for k in ("xy_p_1_s", "z_p_1_s", "xy_vel_p_1_s", "xy_vel_i_1_s2", "xy_vel_d", "z_vel_p_1_s",
                    "z_vel_i_1_s2", "z_vel_d", "xy_vel_max_m_s", "z_vel_max_up_m_s", "z_vel_max_dn_m_s",
                    "tilt_max_deg", "thr_min", "thr_max", "roll_p_1_s", "pitch_p_1_s", "yaw_p_1_s", "yaw_weight",
                    "rollrate_max_deg_s", "yawrate_max_deg_s", "rate_p_1_s", "rate_i_1_s2", "rate_d",
                    "yawrate_p_1_s", "yawrate_i_1_s2", "rate_i_max_rad_s2", "pitchrate_i_max_rad_s2",
                    "yawrate_i_max_rad_s2", "vel_i_max_m_s2",
                    "airmode", "desat_min_effect"))

#: PX4 RateControl::updateIntegral's I-gain reduction: the rate error [rad/s] at which it reaches 0
I_FACTOR_RATE = float(np.radians(400.0))

# Controller memory: vel integrator (3), rate integrator (3), previous velocity (3), previous rates (3), init flag,
# the allocation's torque saturation per axis (+1 / -1: the last step could not give more / less; 0: achieved)
C_VI, C_RI, C_VPREV, C_WPREV, C_INIT, C_SAT = 0, 3, 6, 9, 12, 13
C_SIZE = 16
# Columns of the allocation table ``A`` (N, 12) the kernels read: the pseudo-inverse [T, Mx, My, Mz] -> rotor
# thrust (0:4), PX4's normalised mix columns, the desaturation directions (4:8), the effectiveness B^T (8:12)
A_DIR, A_EFF = 4, 8
# Setpoint vector: position (3), velocity (3), acceleration (3), yaw (1), yawspeed (1); NaN = not controlled
SP_SIZE = 11
# Info vector: collective throttle, thrust [N], attitude setpoint q (4), rate setpoint (3)
INFO_SIZE = 9


@njit(cache=True)
def _thrust_to_cmd(P, t):
    if t <= 0.0:
        return 0.0
    if P[I_MODE] == 0.0:
        w = np.sqrt(t / P[I_KT])
        u = (w - P[I_WMIN]) / (P[I_WCMD] - P[I_WMIN])
    else:
        rel = t / P[I_TMAX]
        f = P[I_FAC]
        if f < 1e-9:
            u = rel
        else:
            u = (-(1.0 - f) + np.sqrt((1.0 - f) ** 2 + 4.0 * f * rel)) / (2.0 * f)
    return min(max(u, 0.0), 1.0)


@njit(cache=True)
def _max_rotor_thrust(P):
    if P[I_MODE] == 0.0:
        w = min(P[I_WCMD], P[I_WMAX])
        return P[I_KT] * w * w
    return P[I_TMAX]


@njit(cache=True)
def _min_rotor_thrust(P):
    if P[I_MODE] == 0.0:
        return P[I_KT] * P[I_WMIN] * P[I_WMIN]
    return 0.0


@njit(cache=True)
def _cmd_to_rotor_thrust(P, s):
    """Steady rotor thrust [N] at normalised command ``s`` (inverse of ``_thrust_to_cmd``)."""
    s = min(max(s, 0.0), 1.0)
    if P[I_MODE] == 0.0:
        w = P[I_WMIN] + s * (P[I_WCMD] - P[I_WMIN])
        return P[I_KT] * w * w
    f = P[I_FAC]
    return P[I_TMAX] * (f * s * s + (1.0 - f) * s)


@njit(cache=True)
def _init_memory(C, x):
    if C[C_INIT] == 0.0:
        for k in range(3):
            C[C_VPREV + k] = x[3 + k]
            C[C_WPREV + k] = x[10 + k]
        C[C_INIT] = 1.0


@njit(cache=True)
def manual_update(G, C, P, J, A, x, q_sp, throttle, yawspeed, w_sp, dt, u, info):
    """One control step of PX4's modes without a position controller: the attitude setpoint ``q_sp``
    (w, x, y, z; FLU->ENU; MANUAL/STABILIZED: the pilot's ``vehicle_attitude_setpoint.q_d``) with its
    yaw-rate feed-forward ``yawspeed`` (NaN none), or, where ``w_sp[0]`` is finite, the body-rate setpoint
    ``w_sp`` (FLU, rad/s; ACRO: ``vehicle_rates_setpoint``) straight to the rate loop; and the collective
    ``throttle`` (PX4's normalised thrust setpoint, 0..1).  The velocity loop's memory is left as it is
    (PX4 does not run it) but its derivative state follows the vehicle."""
    n = int(P[I_N])
    _init_memory(C, x)
    for k in range(3):
        C[C_VPREV + k] = x[3 + k]
    thrust = n * _cmd_to_rotor_thrust(P, throttle)
    _attitude_to_motors(G, C, P, J, A, x, thrust, q_sp, yawspeed, w_sp, dt, u, info)


@njit(cache=True)
def controller_update(G, C, P, J, A, x, sp, q_att, dt, u, info):
    """One control step.  ``x`` holds the estimate [p, v, q, w] (ENU/FLU); writes ``u`` (N,) and ``info``.

    As PX4's ``PositionControl``: an axis whose position and velocity setpoints are both NaN gets no
    velocity control (``addIfNotNanVector3f``), only the acceleration setpoint (NaN: none); there the
    horizontal attitude comes from ``q_att`` (w, x, y, z; FLU->ENU; NaN: none) where given: PX4's own
    attitude setpoint in ALTCTL (the stick's tilt and the yaw), the collective from the altitude loop
    projected on its body z (``_accelerationControl``: thrust_z / cos(tilt))."""
    n = int(P[I_N])
    m = P[I_MASS]
    g = P[I_G]
    _init_memory(C, x)
    # ---- position -> velocity setpoint
    vsp = np.zeros(3)
    for k in range(3):
        kp = G[G_XY_P] if k < 2 else G[G_Z_P]
        if sp[k] == sp[k]:
            vsp[k] = kp * (sp[k] - x[k])
        if sp[3 + k] == sp[3 + k]:
            vsp[k] += sp[3 + k]
    vxy = np.sqrt(vsp[0] ** 2 + vsp[1] ** 2)
    if vxy > G[G_XYV_MAX]:
        vsp[0] *= G[G_XYV_MAX] / vxy
        vsp[1] *= G[G_XYV_MAX] / vxy
    # the limits bound what the position loop asks for; a velocity setpoint PX4's own flight task
    # produced (the log's feed-forward) is already limited for its mode and is never cut below itself
    vz_dn, vz_up = G[G_ZV_DN], G[G_ZV_UP]
    if sp[5] == sp[5]:
        vz_dn = max(vz_dn, -sp[5])
        vz_up = max(vz_up, sp[5])
    vsp[2] = min(max(vsp[2], -vz_dn), vz_up)
    # ---- velocity PID -> acceleration setpoint (derivative on measured velocity, as PX4)
    asp = np.zeros(3)
    verr = np.zeros(3)
    for k in range(3):
        kp = G[G_XYV_P] if k < 2 else G[G_ZV_P]
        ki = G[G_XYV_I] if k < 2 else G[G_ZV_I]
        kd = G[G_XYV_D] if k < 2 else G[G_ZV_D]
        e = vsp[k] - x[3 + k]
        dv = (x[3 + k] - C[C_VPREV + k]) / dt
        C[C_VPREV + k] = x[3 + k]
        free = sp[k] != sp[k] and sp[3 + k] != sp[3 + k]  # not controlled: no velocity PID (PX4)
        if free:
            e = 0.0
        else:
            asp[k] = kp * e + C[C_VI + k] - kd * dv
        if sp[6 + k] == sp[6 + k]:
            asp[k] += sp[6 + k]
        verr[k] = e
    # ---- thrust vector with tilt limit (PX4 keeps altitude first)
    fz = asp[2] + g
    if fz < 0.1 * g:
        fz = 0.1 * g
    tilt_max = np.tan(G[G_TILT] * np.pi / 180.0)
    axy = np.sqrt(asp[0] ** 2 + asp[1] ** 2)
    if axy > fz * tilt_max:
        asp[0] *= fz * tilt_max / axy
        asp[1] *= fz * tilt_max / axy
    tvec = np.array([asp[0], asp[1], fz])
    tnorm = np.sqrt(tvec[0] ** 2 + tvec[1] ** 2 + tvec[2] ** 2)
    thrust = m * tnorm
    tmax_all = n * _max_rotor_thrust(P)
    thr_lo, thr_hi = G[G_THR_MIN] * tmax_all, G[G_THR_MAX] * tmax_all
    # vertical anti-windup as PX4 PositionControl::_velocityControl: no integration of a vertical
    # velocity error that pushes further into the thrust limit the setpoint already sits at
    if (m * fz <= thr_lo and verr[2] <= 0.0) or (m * fz >= thr_hi and verr[2] >= 0.0):
        verr[2] = 0.0
    for k in range(3):
        ki = G[G_XYV_I] if k < 2 else G[G_ZV_I]
        C[C_VI + k] = min(max(C[C_VI + k] + ki * verr[k] * dt, -G[G_V_IMAX]), G[G_V_IMAX])
    thrust = min(max(thrust, thr_lo), thr_hi)
    zb = tvec / tnorm
    # ---- desired attitude from body z and yaw
    yaw = sp[9]
    if yaw != yaw:  # keep current heading
        yaw = np.arctan2(2.0 * (x[6] * x[9] + x[7] * x[8]), 1.0 - 2.0 * (x[8] ** 2 + x[9] ** 2))
    yc = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    xb = np.cross(yc, zb)
    xb /= np.sqrt(xb[0] ** 2 + xb[1] ** 2 + xb[2] ** 2)
    yb = np.cross(zb, xb)
    qd = _rotmat_to_quat(xb, yb, zb)
    yawspeed = sp[10]
    xy_free = sp[0] != sp[0] and sp[1] != sp[1] and sp[3] != sp[3] and sp[4] != sp[4]
    if xy_free and q_att[0] == q_att[0]:
        # ALTCTL: PX4's own attitude setpoint (stick tilt and yaw), the collective from the z loop
        qd = q_att.copy()
        cz = max(_qrot(qd, np.array([0.0, 0.0, 1.0]))[2], 0.2)
        thrust = min(max(m * fz / cz, thr_lo), thr_hi)
    w_none = np.full(3, np.nan)
    _attitude_to_motors(G, C, P, J, A, x, thrust, qd, yawspeed, w_none, dt, u, info)


@njit(cache=True)
def _desat_gain(v, a, lo, hi, eps):
    """PX4 computeDesaturationGain: the multiple of ``v`` that takes the most saturated output back
    to its bound (both bounds crossed: the sum, which balances them)."""
    k_min = 0.0
    k_max = 0.0
    for i in range(a.shape[0]):
        if abs(v[i]) < eps:  # an output the direction hardly moves would ask for a huge gain
            continue
        if a[i] < lo:
            k = (lo - a[i]) / v[i]
            k_min = min(k_min, k)
            k_max = max(k_max, k)
        if a[i] > hi:
            k = (hi - a[i]) / v[i]
            k_min = min(k_min, k)
            k_max = max(k_max, k)
    return k_min + k_max


@njit(cache=True)
def _desaturate(a, v, lo, hi, eps, reduce_only):
    """PX4 desaturateActuators / MultirotorMixer::minimize_saturation: slide ``a`` along ``v`` by the
    desaturation gain, then by half the gain that is left.  ``reduce_only``: only a negative multiple
    of ``v`` (for the thrust direction: thrust is never raised to unsaturate)."""
    g = _desat_gain(v, a, lo, hi, eps)
    if reduce_only and g > 0.0:
        return
    for i in range(a.shape[0]):
        a[i] += g * v[i]
    g = 0.5 * _desat_gain(v, a, lo, hi, eps)
    for i in range(a.shape[0]):
        a[i] += g * v[i]


@njit(cache=True)
def px4_allocate(parts, dirs, lo, hi, airmode, eps, a):
    """PX4's multirotor allocation with sequential desaturation, into ``a`` (N,), not yet clipped.

    ``parts`` (4, N): each axis's share of the outputs, [thrust, roll, pitch, yaw] (mix column times
    its setpoint); ``dirs`` (4, N): the same mix columns normalised as PX4 does (thrust positive up),
    the directions outputs are slid along.  ``lo``/``hi``: the output range.  ``airmode`` (MC_AIRMODE):
    0 thrust only lowered, then roll and pitch cut, to fit; 1 thrust raised or lowered for roll/pitch;
    2 the same for yaw too.  In 0 and 1 yaw is mixed last and given up where it does not fit (15 % of
    the range of head-room above ``hi`` for it, then thrust lowered).  Line for line
    ControlAllocationSequentialDesaturation (PX4 >= 1.13, ``eps`` 0.2) and MultirotorMixer
    mix_airmode_* (PX4 <= 1.13, ``eps`` FLT_EPSILON)."""
    n = a.shape[0]
    mode = int(airmode)
    for i in range(n):
        a[i] = parts[0, i] + parts[1, i] + parts[2, i]
    if mode == 2:
        for i in range(n):
            a[i] += parts[3, i]
        _desaturate(a, dirs[0], lo, hi, eps, False)
        _desaturate(a, dirs[3], lo, hi, eps, False)
        return
    if mode == 1:
        _desaturate(a, dirs[0], lo, hi, eps, False)
    else:
        _desaturate(a, dirs[0], lo, hi, eps, True)
        _desaturate(a, dirs[1], lo, hi, eps, False)
        _desaturate(a, dirs[2], lo, hi, eps, False)
    # mixYaw / mix_yaw
    for i in range(n):
        a[i] += parts[3, i]
    _desaturate(a, dirs[3], lo, hi + 0.15 * (hi - lo), eps, False)
    _desaturate(a, dirs[0], lo, hi, eps, True)


@njit(cache=True)
def _attitude_to_motors(G, C, P, J, A, x, thrust, qd, yawspeed, w_sp, dt, u, info):
    """Attitude P -> rate PID -> allocation, for collective ``thrust`` [N] and attitude setpoint ``qd``;
    a finite ``w_sp[0]`` is a body-rate setpoint (FLU, rad/s) that replaces the attitude loop (ACRO)."""
    n = int(P[I_N])
    zb = _qrot(qd, np.array([0.0, 0.0, 1.0]))
    # ---- attitude error as PX4 AttitudeControl::update: tilt first (reduced attitude),
    # yaw mixed in with MC_YAW_WEIGHT, yaw gain divided by the weight to compensate.
    q = x[6:10]
    ez = _qrot(q, np.array([0.0, 0.0, 1.0]))
    qd_red = _quat_between(ez, zb)
    if abs(qd_red[1]) > 1.0 - 1e-5 or abs(qd_red[2]) > 1.0 - 1e-5:
        qd_red = qd.copy()
    else:
        qd_red = _qmul(qd_red, q)
    q_mix = _qmul(_qconj(qd_red), qd)
    if q_mix[0] < 0.0:
        q_mix = -q_mix
    yw = G[G_YAW_W]
    a0 = np.arccos(min(max(q_mix[0], -1.0), 1.0))
    a3 = np.arcsin(min(max(q_mix[3], -1.0), 1.0))
    qd_mixed = _qmul(qd_red, np.array([np.cos(yw * a0), 0.0, 0.0, np.sin(yw * a3)]))
    qe = _qmul(_qconj(q), qd_mixed)
    if qe[0] < 0.0:
        qe = -qe
    wsp = np.zeros(3)
    wsp[0] = 2.0 * qe[1] * G[G_ROLL_P]
    wsp[1] = 2.0 * qe[2] * G[G_PITCH_P]
    wsp[2] = 2.0 * qe[3] * (G[G_YAW_P] / yw if yw > 1e-4 else 0.0)
    if w_sp[0] == w_sp[0]:
        # ACRO (or an offboard rate setpoint): the rate setpoint is given, no attitude loop
        wsp[:] = np.nan_to_num(w_sp)
    elif not np.isnan(yawspeed):
        # yaw-rate feed-forward about world z, expressed in the body frame
        zw = _qrot(_qconj(q), np.array([0.0, 0.0, 1.0]))
        for k in range(3):
            wsp[k] += zw[k] * yawspeed
    if w_sp[0] != w_sp[0]:
        # the attitude loop's output limits (MC_*RATE_MAX); a given rate setpoint (ACRO) is PX4's own,
        # already limited by its mode (MC_ACRO_*_MAX may exceed these)
        rmax = G[G_RR_MAX] * np.pi / 180.0
        ymax = G[G_YR_MAX] * np.pi / 180.0
        for k in range(2):
            wsp[k] = min(max(wsp[k], -rmax), rmax)
        wsp[2] = min(max(wsp[2], -ymax), ymax)
    # ---- rate PID -> angular acceleration -> torque (J alpha + w x J w)
    alpha = np.zeros(3)
    for k in range(3):
        kp = G[G_R_P] if k < 2 else G[G_YR_P]
        ki = G[G_R_I] if k < 2 else G[G_YR_I]
        kd = G[G_R_D] if k < 2 else 0.0
        e = wsp[k] - x[10 + k]
        dw = (x[10 + k] - C[C_WPREV + k]) / dt
        C[C_WPREV + k] = x[10 + k]
        alpha[k] = kp * e + C[C_RI + k] - kd * dw
        # PX4 RateControl::updateIntegral: no integration further into a torque the allocation could not give,
        # the I gain reduced with the rate error (i_factor: 1 - (e / 400 deg/s)^2), each axis's own limit
        if C[C_SAT + k] > 0.0:
            e = min(e, 0.0)
        elif C[C_SAT + k] < 0.0:
            e = max(e, 0.0)
        i_factor = max(0.0, 1.0 - (e / I_FACTOR_RATE) ** 2)
        lim = G[G_R_IMAX] if k == 0 else (G[G_P_IMAX] if k == 1 else G[G_Y_IMAX])
        C[C_RI + k] = min(max(C[C_RI + k] + i_factor * ki * e * dt, -lim), lim)
    w = x[10:13]
    Jw = J @ w
    tau = J @ alpha + np.cross(w, Jw)
    # ---- allocation as PX4 (sequential desaturation: roll/pitch first, then thrust, yaw given up),
    # in rotor thrust [N] between the idle and the full-command thrust
    tmin_r = _min_rotor_thrust(P)
    tmax_r = _max_rotor_thrust(P)
    parts = np.empty((4, n))
    dirs = np.empty((4, n))
    for i in range(n):
        parts[0, i] = A[i, 0] * thrust
        for k in range(3):
            parts[1 + k, i] = A[i, 1 + k] * tau[k]
        for j in range(4):
            dirs[j, i] = A[i, A_DIR + j]
    t_rot = np.empty(n)
    px4_allocate(parts, dirs, tmin_r, tmax_r, G[G_AIRMODE], G[G_DESAT_EPS], t_rot)
    # what the clipped rotor thrusts give against what was asked: PX4's unallocated torque, whose
    # sign stops the rate integrators (MulticopterRateControl: control_allocator_status)
    lever = 0.0
    for i in range(n):
        t_rot[i] = min(max(t_rot[i], tmin_r), tmax_r)
        for k in range(3):
            lever = max(lever, abs(A[i, A_EFF + 1 + k]))
    tol = 1e-6 * max(tmax_r, 1e-9) * max(lever, 1e-9)
    for k in range(3):
        got = 0.0
        for i in range(n):
            got += A[i, A_EFF + 1 + k] * t_rot[i]
        miss = tau[k] - got
        C[C_SAT + k] = 1.0 if miss > tol else (-1.0 if miss < -tol else 0.0)
    for i in range(n):
        u[i] = _thrust_to_cmd(P, t_rot[i])
    info[0] = _thrust_to_cmd(P, thrust / n)
    info[1] = thrust
    for k in range(4):
        info[2 + k] = qd[k]
    for k in range(3):
        info[6 + k] = wsp[k]


@njit(cache=True)
def _qmul(a, b):
    return np.array([
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]])


@njit(cache=True)
def _qrot(q, v):
    """Rotate vector v by quaternion q (body -> world for the attitude)."""
    qv = np.array([0.0, v[0], v[1], v[2]])
    r = _qmul(_qmul(q, qv), _qconj(q))
    return r[1:4]


@njit(cache=True)
def _quat_between(a, b):
    """Shortest-arc quaternion rotating unit vector a onto b."""
    c = np.cross(a, b)
    d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    q = np.array([1.0 + d, c[0], c[1], c[2]])
    nq = np.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
    if nq < 1e-9:
        return np.array([0.0, 1.0, 0.0, 0.0])
    return q / nq


@njit(cache=True)
def _qconj(q):
    return np.array([q[0], -q[1], -q[2], -q[3]])


@njit(cache=True)
def _rotmat_to_quat(xb, yb, zb):
    # columns of R are the body axes in world coordinates
    r00, r10, r20 = xb[0], xb[1], xb[2]
    r01, r11, r21 = yb[0], yb[1], yb[2]
    r02, r12, r22 = zb[0], zb[1], zb[2]
    tr = r00 + r11 + r22
    if tr > 0.0:
        s = np.sqrt(tr + 1.0) * 2.0
        q = np.array([0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s])
    elif r00 > r11 and r00 > r22:
        s = np.sqrt(1.0 + r00 - r11 - r22) * 2.0
        q = np.array([(r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s])
    elif r11 > r22:
        s = np.sqrt(1.0 + r11 - r00 - r22) * 2.0
        q = np.array([(r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s])
    else:
        s = np.sqrt(1.0 + r22 - r00 - r11) * 2.0
        q = np.array([(r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s])
    return q / np.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)


_NO_Q = np.full(4, np.nan)
_NO_W = np.full(3, np.nan)


def px4_mix_directions(A: np.ndarray) -> np.ndarray:
    """PX4's normalised mix columns (N, 4: thrust, roll, pitch, yaw) from the allocation ``A`` (N, 4):
    roll and pitch divided by one scale, the larger ``sqrt(|col|^2 / (n_nonzero / 2))``, yaw by its
    largest entry, thrust by its mean magnitude, entries below 1e-3 zeroed
    (ControlAllocationPseudoInverse::updateControlAllocationMatrixScale / normalizeControlAllocationMatrix).
    Only the desaturation's skip threshold reads their size; their directions are A's."""
    D = np.array(A[:, :4], dtype=np.float64)
    scales = []
    for c in (1, 2):
        nz = int(np.sum(np.abs(D[:, c]) > 1e-3 * np.max(np.abs(D[:, c]), initial=0.0)))
        scales.append(float(np.sqrt(D[:, c] @ D[:, c] / (nz / 2.0))) if nz else 1.0)
    rp = max(scales)
    if rp > 0:
        D[:, 1:3] /= rp
    ymax = float(np.max(D[:, 3]))
    if ymax > 1e-12:
        D[:, 3] /= ymax
    nz = np.abs(D[:, 0]) > 1e-12
    if nz.any():
        D[:, 0] /= float(np.mean(np.abs(D[nz, 0])))
    D[np.abs(D) < 1e-3] = 0.0
    return D


def allocation_table(vp: VehicleParams) -> np.ndarray:
    """The (N, 12) table the controller kernels allocate with: pseudo-inverse, PX4's normalised mix
    directions, and the effectiveness B^T (rotor thrust -> [T, Mx, My, Mz], FLU)."""
    A = allocation_matrix(vp)
    r = vp.rotors
    Bt = np.column_stack([np.ones(r.count), np.array(r.y_flu_m), -np.array(r.x_flu_m),
                          -np.array(r.direction, float) * r.km_m])
    return np.ascontiguousarray(np.hstack([A, px4_mix_directions(A), Bt]))


class Controller:
    """Stateful wrapper: ``u, info = ctrl.update(x_est, setpoint, dt)``."""

    law = "px4"

    def __init__(self, vp: VehicleParams, gains: ControllerGains | None = None):
        from twin_nodes.physics.core import pack

        self.params = vp
        self.gains = gains or ControllerGains.from_params(vp)
        self.G = self.gains.vector()
        self.P = pack(vp)
        self.J = vp.inertia.copy()
        self.A = allocation_table(vp)
        self.C = np.zeros(C_SIZE)
        self.n = vp.rotors.count

    def reset(self) -> None:
        self.C[:] = 0.0

    def update_manual(self, x: np.ndarray, q_sp: np.ndarray | None, throttle: float, dt: float,
                      yawspeed: float = float("nan"), rates: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
        """PX4's modes without a position controller: attitude setpoint ``q_sp`` (w, x, y, z) with its
        yaw-rate feed-forward ``yawspeed``, or the body-rate setpoint ``rates`` (FLU, ACRO; it wins when
        given), and the collective ``throttle`` (0..1)."""
        u = np.empty(self.n)
        info = np.empty(INFO_SIZE)
        q = _NO_Q if q_sp is None else np.ascontiguousarray(q_sp, dtype=np.float64)
        w = _NO_W if rates is None else np.ascontiguousarray(rates, dtype=np.float64)
        if rates is None and q_sp is None:
            raise ValueError("update_manual: expected an attitude setpoint q_sp or a rate setpoint")
        manual_update(self.G, self.C, self.P, self.J, self.A, np.ascontiguousarray(x[:13], dtype=np.float64),
                      q, float(throttle), float(yawspeed), w, float(dt), u, info)
        return u, info

    def update(self, x: np.ndarray, sp: np.ndarray, dt: float, q_att: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """The position/velocity cascade on ``sp`` (see :func:`controller_update`; ``q_att``: PX4's attitude
        setpoint, flown where the horizontal axes are not controlled)."""
        u = np.empty(self.n)
        info = np.empty(INFO_SIZE)
        q = _NO_Q if q_att is None else np.ascontiguousarray(q_att, dtype=np.float64)
        controller_update(self.G, self.C, self.P, self.J, self.A, np.ascontiguousarray(x[:13], dtype=np.float64),
                          np.ascontiguousarray(sp, dtype=np.float64), q, float(dt), u, info)
        return u, info

    def update_unchecked(self, x13: np.ndarray, sp: np.ndarray, dt: float, q_att: np.ndarray | None
                         ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`update` without converting its arguments (a control loop's hot path): ``x13`` (13,), ``sp``
        (SP_SIZE,) and ``q_att`` (4,) float64 arrays already, ``dt`` a float.  The same kernel, the same numbers."""
        u = np.empty(self.n)
        info = np.empty(INFO_SIZE)
        controller_update(self.G, self.C, self.P, self.J, self.A, x13, sp, _NO_Q if q_att is None else q_att, dt,
                          u, info)
        return u, info


def setpoint(position_enu=None, velocity_enu=None, accel_enu=None, yaw_enu=None, yawspeed=None) -> np.ndarray:
    """Build a setpoint vector; anything left None is not controlled (NaN)."""
    sp = np.full(SP_SIZE, np.nan)
    if position_enu is not None:
        sp[0:3] = position_enu
    if velocity_enu is not None:
        sp[3:6] = velocity_enu
    if accel_enu is not None:
        sp[6:9] = accel_enu
    if yaw_enu is not None:
        sp[9] = yaw_enu
    if yawspeed is not None:
        sp[10] = yawspeed
    return sp
