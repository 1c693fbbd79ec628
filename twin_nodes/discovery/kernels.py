"""Discovery's two hot loops as numba kernels built next to each model's stepper.

The model's numba module (:mod:`twin_nodes.physics.model`: the stepper with the vehicle's effect
hooks) steps one batch of vehicles per call and integrates the rotor states with its generic
per-sample machinery.  Discovery calls these thousands of times on the same shapes:

- ``step_windows``: every output-error window (:mod:`twin_nodes.discovery.output_error`) flown
  over its whole horizon in one call, the command looked up per step inside the kernel; the
  same RK4 steps as ``step_batch`` (the stepper's own ``reference`` and ``rk4_step``), without a
  Python round trip and fresh scratch arrays per step and window;
- ``lag_states``: the rotor states through the model's command path *with* its command hooks
  (battery sag), keeping only every ``up``-th sample (the stepper's ``rotor_states`` writes all).

The source below is compiled once per stepper module (its name carries the digest of the
effect set, the core and the effects: a changed kernel gives another module) and cached on
disk as the stepper is.  Results are bit for bit the stepper's (tests/test_discovery_speed.py).
"""

from __future__ import annotations

import hashlib
import inspect
import sys
import types
from collections.abc import Callable

from twin_nodes.physics.model import Multirotor, _import_source

_SOURCE = '''
import numpy as np
from numba import njit

from twin_nodes.physics.core import I_MODE, I_N, I_TDN, I_TUP, I_WCMD, I_WMAX, I_WMIN
from {stepper} import COMMAND_HOOKS, command_hooks, reference, rk4_step


@njit(cache=True)
def lag_states(P, U, EXT, dt, delay_steps, s0, up, n_out):
    n = int(P[I_N])
    nt = U.shape[0]
    S = np.empty((n_out, n))
    s = s0.copy()
    sref = np.empty(n)
    a_up = 1.0 - np.exp(-dt / P[I_TUP]) if P[I_TUP] > 1e-9 else 1.0
    a_dn = 1.0 - np.exp(-dt / P[I_TDN]) if P[I_TDN] > 1e-9 else 1.0
    mode0 = P[I_MODE] == 0.0
    ne = EXT.shape[1]
    ext = np.empty(ne)
    wmin = P[I_WMIN]
    wcmd = P[I_WCMD]
    wmax = P[I_WMAX]
    for t in range(nt):
        if t % up == 0 and t // up < n_out:
            for i in range(n):
                S[t // up, i] = s[i]
        k = max(t - delay_steps, 0)
        # the stepper's reference(): core.command_to_ref inline, the effects' command hooks, limit_ref
        for i in range(n):
            ui = U[k, i]
            if np.isnan(ui):
                sref[i] = 0.0
                continue
            if ui < 0.0:
                ui = 0.0
            elif ui > 1.0:
                ui = 1.0
            sref[i] = min(wmin + ui * (wcmd - wmin), wmax) if mode0 else ui
        if COMMAND_HOOKS:
            for c in range(ne):
                ext[c] = EXT[k, c]
            command_hooks(P, ext, sref)
        if mode0:
            for i in range(n):
                sref[i] = min(sref[i], wmax)
        for i in range(n):
            e = sref[i] - s[i]
            s[i] += e * (a_up if e > 0.0 else a_dn)
    return S


@njit(cache=True)
def step_windows(P, X, U, EXT, base, fs, delay, dt, nsteps, per, W, V):
    n = int(P[I_N])
    nx = X.shape[1]
    nf = U.shape[0]
    sref = np.empty(n)
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
    for w in range(X.shape[0]):
        x = X[w]
        for j in range(nsteps):
            iu = min(max(base[w] + j * fs + fs // 2 - delay, 0), nf - 1)
            ie = min(base[w] + j * fs, nf - 1)
            ext = EXT[ie]
            reference(P, U[iu], ext, sref)
            rk4_step(P, x, sref, ext, dt, k1, k2, k3, k4, xt, R, omega, T, Q, Fb, Mb, Fw)
            if (j + 1) % per == 0:
                h = (j + 1) // per - 1
                for c in range(3):
                    W[h, w, c] = x[10 + c]
                    V[h, w, c] = x[3 + c]
'''

_KERNELS: dict[str, types.ModuleType] = {}


def kernels(model: Multirotor) -> types.ModuleType:
    """The kernels for ``model``'s stepper module (compiled, or loaded from the cache, once)."""
    stepper = model._mod.__name__
    if stepper not in _KERNELS:
        src = _SOURCE.replace("{stepper}", stepper)
        name = "rotortwin_disc_" + hashlib.sha256((src + inspect.getsource(sys.modules[__name__])).encode()
                                                  ).hexdigest()[:16]
        _KERNELS[stepper] = sys.modules.get(name) or _import_source(name, src)
    return _KERNELS[stepper]


def _discovery_calls(model: Multirotor) -> dict[str, Callable[[], None]]:
    """``name -> call`` of each entry point discovery calls on ``model``, on a tiny input with the argument types
    discovery calls it with (the command series read-only): what :func:`warm` and :func:`warm_steps` compile."""
    import numpy as np

    from twin_nodes.physics.effects import default_ext
    x = model.initial_state(position_enu=(0.0, 0.0, 1.0))[None, :]
    ext = default_ext()[None, :]
    u = np.full((2, model.n_rotors), 0.5)
    u.setflags(write=False)  # discovery's command series are read-only views
    ext2 = np.repeat(ext, 2, axis=0)
    w = np.empty((1, 1, 3))
    return {
        "wrench_terms": lambda: model.wrench_terms(x, ext),
        "step_windows": lambda: kernels(model).step_windows(model.P, x.copy(), u, ext2, np.zeros(1, np.int64), 1, 0,
                                                            0.002, 1, 1, w, w.copy()),
        "lag_states": lambda: kernels(model).lag_states(model.P, u, ext2, 0.002, 0, np.zeros(model.n_rotors), 1, 2),
    }


def warm(model: Multirotor, windows: bool, lag: bool = False) -> None:
    """Load (or compile) now what evaluating ``model`` calls (:func:`_discovery_calls`): done in the parent before
    worker processes are forked, so they inherit it instead of each loading it again (``lag``: the rotor-state
    kernel even where no effect hooks the command path)."""
    calls = _discovery_calls(model)
    calls["wrench_terms"]()
    if lag or any(e.command_kernel is not None for e in model.kernel_effects):
        calls["lag_states"]()
    if windows:
        calls["step_windows"]()


def warm_steps() -> list[tuple[str, Callable[[], None]]]:
    """Every compiled entry point a fleet flight's discovery calls (:func:`warm` with both kernels, and the
    stepper's own steps) as ``(name, compile or load it on a tiny input)``: the stepper's step first (it
    compiles the functions the others call: the hooks, ``reference``, ``deriv``), then costliest first: a fleet
    worker runs each once, each under its own lock in the cache folder (``$ROTORTWIN_CACHE``) the workers
    share, so two cold workers compile different entry points side by side and each loads what the other
    wrote instead of compiling it again (:func:`twin_nodes.fleet.flight.warm_compiled`).  The stepper and
    these kernels are one module per effect registry, whatever the vehicle: the shipped SIH quad stands in."""
    import numpy as np

    from twin_nodes.physics.effects import default_ext
    from twin_nodes.vehicle.params import load_params, params_dir

    m = Multirotor(load_params(params_dir() / "px4_sih_quadx.yaml"))
    x = m.initial_state(position_enu=(0.0, 0.0, 1.0))
    ext = default_ext()
    u1 = np.full(m.n_rotors, 0.5)
    calls = _discovery_calls(m)
    return [("step_n", lambda: m.step_unchecked(x.copy(), u1.copy(), 0.002, ext.copy(), 1)),
            *((k, calls[k]) for k in ("wrench_terms", "step_windows", "lag_states")),
            ("specific_force", lambda: m.specific_force_unchecked(x, u1, ext))]


def warm_all() -> list[str]:
    """Compile (or load from the on-disk cache) every entry point of :func:`warm_steps`, in this process.
    Returns the names of the modules (stepper, kernels)."""
    from twin_nodes.vehicle.params import load_params, params_dir

    for _, step in warm_steps():
        step()
    m = Multirotor(load_params(params_dir() / "px4_sih_quadx.yaml"))
    return [m._mod.__name__, kernels(m).__name__]
