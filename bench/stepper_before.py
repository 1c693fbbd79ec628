"""The fixed-step stepper (RK4) of a multirotor without effects, and the template of every stepper.

:mod:`twin_nodes.physics.model` makes the stepper for a set of effects from this file's text by
replacing the section between the two ``hooks`` marker lines with hooks that call each effect's
kernel, in order, on that effect's slice of ``effect_params(P)``; the rest is the same for every
set.  As it stands the file is valid on its own: the model with no effects.

Arguments: ``P`` the packed vehicle (:func:`twin_nodes.physics.core.pack`) followed by the kernel
effects' parameter vectors (none here); ``x`` a state, ``u`` motor commands (NaN = stopped),
``ext = [battery_v, wind_e, wind_n, wind_u]``; a capital letter is a series or a batch of these.
Hooks, scratch arrays and kernels are as in :mod:`twin_nodes.physics.effects`.
"""

import numpy as np
from numba import njit

from twin_nodes.physics.core import (I_G, I_MASS, I_N, I_ROT, I_TDN, I_TUP, NX_BODY, command_to_ref, limit_ref,
                                     post_step, quat_to_R, rigid_body, rotor_outputs, rotor_wrench)


@njit(cache=True, inline="always")
def effect_params(P):
    """The kernel effects' parameter vectors, concatenated: P after the rotor table."""
    return P[I_ROT + 4 * int(P[I_N]):]


# Hooks, each calling its effects' kernels in order; wrench_term(j, ...) adds the j-th wrench
# effect alone.  N_TERMS counts the wrench terms (the rotors, then one per wrench effect); the
# *_HOOKS flags say which hooks call anything: numba drops the call of one that does not (so its
# unused arguments cost no reference counting in the hot loop).
# ---- hooks: the generator replaces the lines from here to the end marker ----
N_TERMS = 1
COMMAND_HOOKS, ROTOR_HOOKS, WRENCH_HOOKS = False, False, False


@njit(cache=True, inline="always")
def command_hooks(P, ext, sref):
    pass


@njit(cache=True)
def rotor_hooks(P, x, ext, omega, T, Q):
    pass


@njit(cache=True)
def wrench_hooks(P, x, R, ext, omega, T, Fb, Mb, Fw):
    pass


@njit(cache=True)
def wrench_term(j, P, x, R, ext, omega, T, Fb, Mb, Fw):
    pass
# ---- end of hooks ----


@njit(cache=True)
def reference(P, u, ext, sref):
    command_to_ref(P, u, sref)
    if COMMAND_HOOKS:
        command_hooks(P, ext, sref)
    limit_ref(P, sref)


@njit(cache=True)
def deriv(P, x, sref, ext, dx, R, omega, T, Q, Fb, Mb, Fw):
    n = int(P[I_N])
    quat_to_R(x[6:10], R)
    rotor_outputs(P, x[NX_BODY:NX_BODY + n], omega, T, Q)
    if ROTOR_HOOKS:
        rotor_hooks(P, x, ext, omega, T, Q)
    Fb[:] = 0.0
    Mb[:] = 0.0
    Fw[:] = 0.0
    rotor_wrench(P, T, Q, Fb, Mb)
    if WRENCH_HOOKS:
        wrench_hooks(P, x, R, ext, omega, T, Fb, Mb, Fw)
    rigid_body(P, x, R, Fb, Mb, Fw, sref, dx)


@njit(cache=True, inline="always")
def rk4_step(P, x, sref, ext, dt, k1, k2, k3, k4, xt, R, omega, T, Q, Fb, Mb, Fw):
    """Not in eda17af as a function: the one RK4 step (the same statements eda17af's ``step_n`` wrote out,
    inlined into it by numba), which discovery's kernels (``twin_nodes.discovery.kernels``, built beside this
    stepper in the bench's "before" child) import since the thirteenth session."""
    nx = x.shape[0]
    deriv(P, x, sref, ext, k1, R, omega, T, Q, Fb, Mb, Fw)
    for i in range(nx):
        xt[i] = x[i] + 0.5 * dt * k1[i]
    deriv(P, xt, sref, ext, k2, R, omega, T, Q, Fb, Mb, Fw)
    for i in range(nx):
        xt[i] = x[i] + 0.5 * dt * k2[i]
    deriv(P, xt, sref, ext, k3, R, omega, T, Q, Fb, Mb, Fw)
    for i in range(nx):
        xt[i] = x[i] + dt * k3[i]
    deriv(P, xt, sref, ext, k4, R, omega, T, Q, Fb, Mb, Fw)
    for i in range(nx):
        x[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
    post_step(P, x, sref)


@njit(cache=True)
def step_n(P, x, u, ext, dt, nsub):
    """Advance x in place by nsub RK4 steps of dt with the command held."""
    n = int(P[I_N])
    nx = x.shape[0]
    sref = np.empty(n)
    reference(P, u, ext, sref)
    R = np.empty((3, 3))
    omega = np.empty(n)
    T = np.empty(n)
    Q = np.empty(n)
    Fb = np.empty(3)
    Mb = np.empty(3)
    Fw = np.empty(3)
    k1 = np.empty(nx)
    k2 = np.empty(nx)
    k3 = np.empty(nx)
    k4 = np.empty(nx)
    xt = np.empty(nx)
    for _ in range(nsub):
        rk4_step(P, x, sref, ext, dt, k1, k2, k3, k4, xt, R, omega, T, Q, Fb, Mb, Fw)


@njit(cache=True)
def simulate(P, x0, U, EXT, dt, nsub):
    """States after each command of U (T, N) held for nsub steps of dt; row 0 is x0."""
    nt = U.shape[0]
    X = np.empty((nt + 1, x0.shape[0]))
    x = x0.copy()
    X[0] = x
    for t in range(nt):
        step_n(P, x, U[t], EXT[t], dt, nsub)
        X[t + 1] = x
    return X


@njit(cache=True)
def step_batch(PB, X, U, EXT, dt, nsub):
    """Advance each row of X (K, nx) in place, vehicle k with its own parameters PB[k], EB[k]."""
    for k in range(X.shape[0]):
        step_n(PB[k], X[k], U[k], EXT[k], dt, nsub)


@njit(cache=True)
def rotor_states(P, U, EXT, dt, delay_steps, s0):
    """Rotor states (T, N) from commands U (T, N) on a uniform grid of step dt: command hooks,
    a pure delay of delay_steps samples, then the first-order lag (exact for a held reference)."""
    n = int(P[I_N])
    nt = U.shape[0]
    S = np.empty((nt, n))
    s = s0.copy()
    sref = np.empty(n)
    a_up = 1.0 - np.exp(-dt / P[I_TUP]) if P[I_TUP] > 1e-9 else 1.0
    a_dn = 1.0 - np.exp(-dt / P[I_TDN]) if P[I_TDN] > 1e-9 else 1.0
    for t in range(nt):
        S[t] = s
        k = t - delay_steps
        if k < 0:
            k = 0
        reference(P, U[k], EXT[k], sref)
        for i in range(n):
            e = sref[i] - s[i]
            s[i] += e * (a_up if e > 0.0 else a_dn)
    return S


@njit(cache=True)
def specific_force(P, x, u, ext):
    """Accelerometer reading (specific force) in body FLU [m/s^2]."""
    n = int(P[I_N])
    sref = np.empty(n)
    reference(P, u, ext, sref)
    dx = np.empty(x.shape[0])
    R = np.empty((3, 3))
    omega = np.empty(n)
    T = np.empty(n)
    Q = np.empty(n)
    Fb = np.empty(3)
    Mb = np.empty(3)
    Fw = np.empty(3)
    deriv(P, x, sref, ext, dx, R, omega, T, Q, Fb, Mb, Fw)
    out = np.empty(3)
    m = P[I_MASS]
    for c in range(3):
        out[c] = (Fb[c] + R[0, c] * Fw[0] + R[1, c] * Fw[1] + R[2, c] * Fw[2]) / m
    if x[2] <= 0.0 and dx[5] <= 0.0 and x[5] <= 0.0:
        # resting on the ground: the ground carries the rest of the weight
        for c in range(3):
            out[c] = R[2, c] * P[I_G]
    return out


@njit(cache=True)
def wrench_terms(P, X, EXT, F, M):
    """Per-term body force F (T, N_TERMS, 3) and moment M (T, N_TERMS, 3), FLU.

    Term 0 is the rotors (thrust + reaction torque, after rotor-hook effects); term j>0 is
    the j-th wrench effect; world forces are rotated into the body frame."""
    n = int(P[I_N])
    R = np.empty((3, 3))
    omega = np.empty(n)
    T = np.empty(n)
    Q = np.empty(n)
    fb = np.empty(3)
    mb = np.empty(3)
    fw = np.empty(3)
    for t in range(X.shape[0]):
        x = X[t]
        ext = EXT[t]
        quat_to_R(x[6:10], R)
        rotor_outputs(P, x[NX_BODY:NX_BODY + n], omega, T, Q)
        if ROTOR_HOOKS:
            rotor_hooks(P, x, ext, omega, T, Q)
        fb[:] = 0.0
        mb[:] = 0.0
        rotor_wrench(P, T, Q, fb, mb)
        for c in range(3):
            F[t, 0, c] = fb[c]
            M[t, 0, c] = mb[c]
        for j in range(1, N_TERMS):
            fb[:] = 0.0
            mb[:] = 0.0
            fw[:] = 0.0
            wrench_term(j, P, x, R, ext, omega, T, fb, mb, fw)
            for c in range(3):
                F[t, j, c] = fb[c] + R[0, c] * fw[0] + R[1, c] * fw[1] + R[2, c] * fw[2]
                M[t, j, c] = mb[c]
