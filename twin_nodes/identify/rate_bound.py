"""The twin's own discrete rate loop against PX4's flown rate gains.

The continuous rule of thumb (Kp tau <= 0.7 for ~55 deg of phase margin, yaw 0.3) is what
ControllerGains.auto_defaults uses and what caps the converted PX4 gains in nominal.py.  It ignores
PX4's D term (which acts as added inertia) and the controller's sample time; :func:`rate_loop_radius`
and :func:`gain_margin` give the single-axis discrete loop the twin really flies (control.py's PID at
the controller rate, zero-order hold, a first-order motor lag, a rigid-body integrator), so a cap can
say what margin PX4's own gains would have kept.  Pure numpy/scipy."""
from __future__ import annotations

import numpy as np
from scipy.linalg import expm


def rate_loop_radius(kp: float, ki: float, kd: float, tau_s: float, dt_s: float) -> float:
    """Spectral radius of one axis of the twin's rate loop: every ``dt_s`` the controller sets
    alpha_cmd = kp e + I - kd (w - w_prev) / dt_s (e = -w), held over the step; the rotors follow it
    with the first-order lag ``tau_s``; w integrates the achieved angular acceleration; then
    I += ki e dt_s (control.py's order).  Below 1: stable."""
    tau = max(float(tau_s), 1e-6)
    ac = np.array([[0.0, 1.0], [0.0, -1.0 / tau]])
    bc = np.array([[0.0], [1.0 / tau]])
    # exact zero-order-hold discretisation via the augmented exponential
    m = np.zeros((3, 3))
    m[:2, :2], m[:2, 2:] = ac * dt_s, bc * dt_s
    e = expm(m)
    phi, gam = e[:2, :2], e[:2, 2]
    # state [w, a, w_prev, I]; u = -(kp + kd/dt) w + (kd/dt) w_prev + I
    u = np.array([-(kp + kd / dt_s), 0.0, kd / dt_s, 1.0])
    a = np.zeros((4, 4))
    a[:2, :] = np.hstack([phi, np.zeros((2, 2))]) + np.outer(gam, u)
    a[2, 0] = 1.0
    a[3, 0], a[3, 3] = -ki * dt_s, 1.0
    if ki == 0.0:
        a = a[:3, :3]  # no integral action: the integrator is a constant, not a mode of the loop
    return float(np.max(np.abs(np.linalg.eigvals(a))))


def gain_margin(kp: float, ki: float, kd: float, tau_s: float, dt_s: float, g_max: float = 64.0) -> float:
    """The factor by which the whole PID (kp, ki, kd together) can grow before the twin's discrete rate
    loop (:func:`rate_loop_radius`) goes unstable; ``g_max`` where it never does up to there, 0 where it
    is unstable as given.  Bisection on the radius, to 1 %."""
    def unstable(g: float) -> bool:
        return rate_loop_radius(g * kp, g * ki, g * kd, tau_s, dt_s) >= 1.0
    if unstable(1.0):
        return 0.0
    if not unstable(g_max):
        return float(g_max)
    lo, hi = 1.0, g_max
    while hi / lo > 1.01:
        mid = float(np.sqrt(lo * hi))
        lo, hi = (lo, mid) if unstable(mid) else (mid, hi)
    return lo
