"""Nominal rigid-body + rotor dynamics as numba kernels (world ENU, body FLU).

State vector ``x`` (length 13 + N)::

    x[0:3]   position, world ENU [m]
    x[3:6]   velocity, world ENU [m/s]
    x[6:10]  attitude quaternion (w, x, y, z), rotates body FLU -> world ENU
    x[10:13] body rates, FLU [rad/s]
    x[13:]   rotor states: rotor speed [rad/s] (omega_squared) or lagged
             normalised command [-] (thrust_factor)

The vehicle is packed once into a float64 vector ``P`` (``pack``) so the
kernels need no Python objects.  Effects are composed around these kernels by
:mod:`twin_nodes.physics.model`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit

if TYPE_CHECKING:  # pragma: no cover - physics reads a VehicleParams but never imports vehicle/
    from twin_nodes.vehicle.params import VehicleParams


NX_BODY = 13
POS, VEL, QUAT, RATES = slice(0, 3), slice(3, 6), slice(6, 10), slice(10, 13)
ROTORS = slice(13, None)

# Layout of the packed vehicle vector P.
I_MASS, I_G, I_J, I_JINV, I_MODE, I_KT, I_KM, I_WMIN, I_WCMD, I_WMAX, I_TUP, I_TDN, I_TMAX, I_FAC, I_N = (
    0, 1, 2, 11, 20, 21, 22, 23, 24, 25, 26, 27, 28, 29, 30)
I_ROT = 31  # then x[N], y[N], z[N] (relative to the centre of mass), direction[N]


def pack(vp: VehicleParams, com_flu_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Pack a (validated) parameter set into the kernel vector ``P``.

    ``com_flu_m``: where the centre of mass is [m, body FLU] relative to the point the rotor positions
    of ``vp`` are given about (a ``com_offset`` effect).  ``P`` holds the rotor positions relative to the
    centre of mass, so every kernel that reads them (the thrust's moment, the rotor drag's hub airspeed
    ``w x r`` and its moment) acts about the centre of mass.  The controllers pack the nominal geometry
    (PX4's mixer does not know where the centre of mass is)."""
    r = vp.rotors
    n = r.count
    p = np.zeros(I_ROT + 4 * n)
    p[I_MASS] = vp.mass_kg
    p[I_G] = vp.gravity_m_s2
    j = vp.inertia
    p[I_J:I_J + 9] = j.ravel()
    p[I_JINV:I_JINV + 9] = np.linalg.inv(j).ravel()
    p[I_MODE] = 0.0 if r.thrust_model == "omega_squared" else 1.0
    p[I_KT] = r.kt_n_s2_rad2
    p[I_KM] = r.km_m
    p[I_WMIN] = r.omega_min_rad_s
    p[I_WCMD] = r.omega_cmd_max_rad_s
    p[I_WMAX] = r.omega_max_rad_s
    p[I_TUP] = r.tau_up_s
    p[I_TDN] = r.tau_down_s
    p[I_TMAX] = r.thrust_max_n
    p[I_FAC] = r.thr_mdl_fac
    p[I_N] = n
    cx, cy, cz = (float(c) for c in com_flu_m)
    p[I_ROT:I_ROT + n] = np.asarray(r.x_flu_m, float) - cx
    p[I_ROT + n:I_ROT + 2 * n] = np.asarray(r.y_flu_m, float) - cy
    p[I_ROT + 2 * n:I_ROT + 3 * n] = np.asarray(r.z_flu_m, float) - cz
    p[I_ROT + 3 * n:I_ROT + 4 * n] = r.direction
    return p


@njit(cache=True)
def quat_to_R(q, R):
    w, x, y, z = q[0], q[1], q[2], q[3]
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@njit(cache=True)
def command_to_ref(P, u, sref):
    """Per-rotor reference (steady-state rotor state) for commands ``u`` (NaN = stopped)."""
    n = int(P[I_N])
    for i in range(n):
        ui = u[i]
        if ui != ui:  # NaN: motor stopped / disarmed
            sref[i] = 0.0
            continue
        if ui < 0.0:
            ui = 0.0
        elif ui > 1.0:
            ui = 1.0
        if P[I_MODE] == 0.0:
            w = P[I_WMIN] + ui * (P[I_WCMD] - P[I_WMIN])
            if w > P[I_WMAX]:
                w = P[I_WMAX]
            sref[i] = w
        else:
            sref[i] = ui


@njit(cache=True)
def limit_ref(P, sref):
    """Clamp the reference to omega_max after the command hooks (battery_sag may raise it)."""
    if P[I_MODE] == 0.0:
        for i in range(int(P[I_N])):
            if sref[i] > P[I_WMAX]:
                sref[i] = P[I_WMAX]


@njit(cache=True)
def rotor_outputs(P, s, omega, T, Q):
    """Rotor speed [rad/s], thrust [N] and reaction torque magnitude [N m] from rotor states."""
    n = int(P[I_N])
    for i in range(n):
        si = s[i]
        if si < 0.0:
            si = 0.0
        if P[I_MODE] == 0.0:
            if si > P[I_WMAX]:
                si = P[I_WMAX]
            omega[i] = si
            T[i] = P[I_KT] * si * si
        else:
            f = P[I_FAC]
            t = P[I_TMAX] * (f * si * si + (1.0 - f) * si)
            T[i] = t
            omega[i] = P[I_WMAX] * np.sqrt(t / P[I_TMAX]) if t > 0.0 else 0.0
        Q[i] = P[I_KM] * T[i]


@njit(cache=True)
def rotor_wrench(P, T, Q, Fb, Mb):
    """Add thrust along body +z and the moments of thrust and rotor reaction torque (FLU)."""
    n = int(P[I_N])
    for i in range(n):
        x = P[I_ROT + i]
        y = P[I_ROT + n + i]
        d = P[I_ROT + 3 * n + i]
        Fb[2] += T[i]
        # r x (0, 0, T) = (y T, -x T, 0); reaction torque of a CCW (d=+1) rotor is -z.
        Mb[0] += y * T[i]
        Mb[1] -= x * T[i]
        Mb[2] -= d * Q[i]


@njit(cache=True)
def rigid_body(P, x, R, Fb, Mb, Fw, sref, dx):
    """Fill ``dx`` with the state derivative given the total wrench."""
    m = P[I_MASS]
    n = int(P[I_N])
    dx[0] = x[3]
    dx[1] = x[4]
    dx[2] = x[5]
    for k in range(3):
        dx[3 + k] = (R[k, 0] * Fb[0] + R[k, 1] * Fb[1] + R[k, 2] * Fb[2] + Fw[k]) / m
    dx[5] -= P[I_G]
    qw, qx, qy, qz = x[6], x[7], x[8], x[9]
    wx, wy, wz = x[10], x[11], x[12]
    dx[6] = 0.5 * (-qx * wx - qy * wy - qz * wz)
    dx[7] = 0.5 * (qw * wx + qy * wz - qz * wy)
    dx[8] = 0.5 * (qw * wy - qx * wz + qz * wx)
    dx[9] = 0.5 * (qw * wz + qx * wy - qy * wx)
    J = P[I_J:I_J + 9]
    Ji = P[I_JINV:I_JINV + 9]
    hx = J[0] * wx + J[1] * wy + J[2] * wz
    hy = J[3] * wx + J[4] * wy + J[5] * wz
    hz = J[6] * wx + J[7] * wy + J[8] * wz
    # w x (J w)
    cx = wy * hz - wz * hy
    cy = wz * hx - wx * hz
    cz = wx * hy - wy * hx
    ax = Mb[0] - cx
    ay = Mb[1] - cy
    az = Mb[2] - cz
    dx[10] = Ji[0] * ax + Ji[1] * ay + Ji[2] * az
    dx[11] = Ji[3] * ax + Ji[4] * ay + Ji[5] * az
    dx[12] = Ji[6] * ax + Ji[7] * ay + Ji[8] * az
    for i in range(n):
        s = x[NX_BODY + i]
        e = sref[i] - s
        tau = P[I_TUP] if e > 0.0 else P[I_TDN]
        dx[NX_BODY + i] = e / tau if tau > 1e-9 else 0.0


@njit(cache=True)
def post_step(P, x, sref):
    """Renormalise the quaternion, apply instantaneous rotors and ground contact (z = 0)."""
    n = int(P[I_N])
    if P[I_TUP] <= 1e-9 or P[I_TDN] <= 1e-9:
        for i in range(n):
            s = x[NX_BODY + i]
            if (sref[i] > s and P[I_TUP] <= 1e-9) or (sref[i] <= s and P[I_TDN] <= 1e-9):
                x[NX_BODY + i] = sref[i]
    qn = np.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8] + x[9] * x[9])
    for k in range(6, 10):
        x[k] /= qn
    if x[2] <= 0.0:
        x[2] = 0.0
        if x[5] < 0.0:
            x[5] = 0.0
        # Vertical thrust vs weight: if the rotors cannot lift it, the vehicle sits level
        # on its legs (yaw kept), as PX4 SIH and Gazebo's ground contact do.
        omega = np.empty(n)
        T = np.empty(n)
        Q = np.empty(n)
        rotor_outputs(P, x[NX_BODY:NX_BODY + n], omega, T, Q)
        tz = 0.0
        for i in range(n):
            tz += T[i]
        r22 = 1.0 - 2.0 * (x[7] * x[7] + x[8] * x[8])
        if tz * r22 <= P[I_MASS] * P[I_G]:
            for k in range(3, 6):
                x[k] = 0.0
            for k in range(10, 13):
                x[k] = 0.0
            yaw = np.arctan2(2.0 * (x[6] * x[9] + x[7] * x[8]), 1.0 - 2.0 * (x[8] * x[8] + x[9] * x[9]))
            x[6] = np.cos(0.5 * yaw)
            x[7] = 0.0
            x[8] = 0.0
            x[9] = np.sin(0.5 * yaw)
