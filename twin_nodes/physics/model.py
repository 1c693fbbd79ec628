"""The multirotor model: nominal core + plug-in effects, fixed-step RK4, batched.

Every ``Multirotor`` steps through *one* numba module, the dispatch stepper: the stepper of
:mod:`twin_nodes.physics.stepper` with hooks that loop over the vehicle's effect table (in ``P``,
after the packed vehicle) and call each entry's kernel through an if-chain on its integer code.
The codes come from a registry of effect kinds with kernels: every such kind of
:mod:`twin_nodes.physics.effects` (in ``EFFECTS`` order), then kinds defined elsewhere (the prove
suite's plant-only effects), registered when a model first uses one, together with every other
kernel effect of its module.  So an effect is still added by writing a kernel, never by editing
the core; the stepper is compiled once per registry (not once per combination of effects) and
cached on disk: the module is written to the per-user code cache (:mod:`.codecache`) so numba's
on-disk cache works across processes and runs; what runs is the generated text itself, never what
that file holds.  A kind from outside physics makes another registry, hence one more module
(compiled once, cached too).

Commands ``u`` are PX4 ``actuator_motors`` values: normalised 0..1 per motor in
PX4 order, NaN = stopped.  ``ext`` is ``[battery_v, wind_e, wind_n, wind_u]``.
"""

from __future__ import annotations

import hashlib
import inspect
import os
import sys
import tempfile
import time
import types
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from twin_nodes.base.io import cache_dir
from twin_nodes.physics import codecache, core, effects as effects_mod, stepper
from twin_nodes.physics.core import NX_BODY, pack
from twin_nodes.physics.effects import EXT_SIZE, Effect, centre_of_mass, default_ext, effects_from_params

if TYPE_CHECKING:  # pragma: no cover - physics reads a VehicleParams but never imports vehicle/
    from twin_nodes.vehicle.params import VehicleParams

# stepper.py's hooks: the Effect attribute holding the kernel, the arguments after P, and where the
# hook's entries start in the effect table (after the three counts, in pairs: command, rotor, wrench).
_HOOKS = {"command_hooks": ("command_kernel", "ext, sref", "0"),
          "rotor_hooks": ("rotor_kernel", "x, ext, omega, T, Q", "int(P[b])"),
          "wrench_hooks": ("wrench_kernel", "x, R, ext, omega, T, Fb, Mb, Fw", "int(P[b]) + int(P[b + 1])")}
_COUNT = {"command_hooks": 0, "rotor_hooks": 1, "wrench_hooks": 2}  # where each hook's count is in the table


def _dispatch(registry: Sequence[type[Effect]], attr: str, args: str) -> list[str]:
    """The if-chain calling, for the entry ``(c, s)``, the kernel ``attr`` of kind number ``c`` on
    ``P[s:s + len(its parameters)]`` (and on ``P`` itself for a kind whose kernels read the vehicle)."""
    lines = []
    for code, cls in enumerate(registry):
        kernel = getattr(cls, attr)
        if kernel is None:
            continue
        vehicle = "P, " if cls.kernel_reads_vehicle else ""  # the packed vehicle (rotor positions)
        lines += [f"{'if' if not lines else 'elif'} c == {code}:",
                  f"    {kernel.__name__}(P[s:s + {len(cls.param_names)}], {vehicle}{args})"]
    return lines


def _generate_source(registry: Sequence[type[Effect]]) -> str:
    """stepper.py with hooks dispatching on the effect table's codes, ``registry[c]`` being kind ``c``."""
    imports = sorted({f"from {k.__module__} import {k.__name__}\n" for cls in registry
                      for k in (cls.command_kernel, cls.rotor_kernel, cls.wrench_kernel) if k is not None})
    used = {hook: any(getattr(cls, attr) is not None for cls in registry) for hook, (attr, _, _) in _HOOKS.items()}
    hooks = "".join(imports) + f"N_KINDS = {len(registry)}\n"
    hooks += "COMMAND_HOOKS, ROTOR_HOOKS, WRENCH_HOOKS = " + ", ".join(str(v) for v in used.values()) + "\n"
    defs = []
    for hook, (attr, args, first) in _HOOKS.items():
        chain = _dispatch(registry, attr, args)
        body = ["b = effect_table(P)", "e0 = b + 3" + (f" + 2 * ({first})" if first != "0" else ""),
                f"for k in range(int(P[b{f' + {_COUNT[hook]}' if _COUNT[hook] else ''}])):",
                "    c = int(P[e0 + 2 * k])", "    s = int(P[e0 + 2 * k + 1])", *(f"    {line}" for line in chain)]
        defs.append((f"{hook}(P, {args})", body if chain else []))
    chain = _dispatch(registry, "wrench_kernel", _HOOKS["wrench_hooks"][1])
    first = _HOOKS["wrench_hooks"][2]
    body = ["b = effect_table(P)", f"e = b + 3 + 2 * ({first} + j - 1)", "c = int(P[e])", "s = int(P[e + 1])",
            *chain]
    defs.append((f"wrench_term(j, P, {_HOOKS['wrench_hooks'][1]})", body if chain else []))
    for signature, body in defs:
        # the command hook runs once per (fine) step of the rotor lag loops: inlined, as its kernels are;
        # wrench_term too (called per term and sample by wrench_terms only: a call cost 6x the arithmetic of
        # the SIH quad's two drags); the other hooks stay calls (inlining them into deriv made the RK4 step slower)
        inline = ', inline="always"' if signature.startswith(("command_hooks", "wrench_term(")) else ""
        hooks += (f"\n\n@njit(cache=True{inline})\ndef {signature}:\n"
                  + "".join(f"    {line}\n" for line in (body or ["pass"])))
    lines = inspect.getsource(stepper).splitlines(keepends=True)
    begin = next(i for i, line in enumerate(lines) if line.startswith("# ---- hooks"))
    end = lines.index("# ---- end of hooks ----\n")
    return "".join(lines[:begin + 1]) + hooks + "".join(lines[end:])


def _module_name(src: str) -> str:
    """A digest of the generated text, of the kernels it calls and of what else the compiled code depends on
    (:func:`.codecache.env_key`): numba's cache checks only the file it compiles (and its own version), so an
    edited kernel, another numpy or another CPU must give another file."""
    h = hashlib.sha256(src.encode())
    for mod in (core, effects_mod):
        h.update(inspect.getsource(mod).encode())
    # kernels may live outside effects.py (the prove suite's plant-only effects): their modules too
    for line in src.splitlines():
        if line.startswith("from ") and " import " in line:
            name = line.split()[1]
            if name.startswith("twin_nodes.") and name not in (core.__name__, effects_mod.__name__):
                h.update(inspect.getsource(sys.modules[name]).encode())
    h.update(codecache.env_key().encode())  # the versions and the CPU the compiled code is for
    return f"rotortwin_gen_{h.hexdigest()[:16]}"


#: generated modules (and numba's compiled code for them) not used for this many days are removed
#: when a new one is written (``$ROTORTWIN_CACHE_KEEP_DAYS``); every edit of a kernel makes a new one
KEEP_DAYS = 30.0


def _keep_days() -> float:
    raw = os.environ.get("ROTORTWIN_CACHE_KEEP_DAYS")
    if raw is None:
        return KEEP_DAYS
    try:
        days = float(raw)
    except ValueError:
        raise ValueError(f"ROTORTWIN_CACHE_KEEP_DAYS: expected a number of days, got {raw!r}") from None
    if not days > 0:
        raise ValueError(f"ROTORTWIN_CACHE_KEEP_DAYS: expected a positive number of days, got {raw!r}")
    return days


def _mark_used(path) -> None:
    """Stamp ``<module>.used`` (not the module: numba's cache is keyed on its time stamp)."""
    try:
        path.with_suffix(".used").touch()
    except OSError:
        pass


def prune_generated(folder, keep_days: float, now: float, keep: str = "") -> list[str]:
    """Remove the generated modules of ``folder`` last used more than ``keep_days`` ago (their
    ``.used`` stamp, else the module's own time), with numba's cache files for them; ``keep`` is
    never removed.  Returns the names removed.  A file another process removes first is skipped."""
    removed = []
    for py in sorted(folder.glob("rotortwin_gen_*.py")):
        name = py.stem
        if name == keep:
            continue
        try:
            used = max((p.stat().st_mtime for p in (py, py.with_suffix(".used")) if p.exists()), default=now)
        except OSError:
            continue
        if now - used <= keep_days * 86400.0:
            continue
        for f in [py, py.with_suffix(".used"), *(folder / "__pycache__").glob(f"{name}.*")]:
            try:
                f.unlink()
            except OSError:
                pass
        removed.append(name)
    return removed


def _import_source(name: str, src: str) -> types.ModuleType:
    """Module ``name`` run from ``src``, with its file in the code cache folder.

    The file exists for numba's on-disk cache (keyed on that file's bytes, :mod:`.codecache`): it is
    used only when its bytes are ``src``, and replaced, atomically, when they differ; what runs is ``src``.
    Writing a new one prunes the modules not used for ``KEEP_DAYS`` (``prune_generated``).  Where the
    code cache (``$ROTORTWIN_CODE_CACHE``) is read-only or unusable the file goes to the data cache
    (``$ROTORTWIN_CACHE``), as before that cache existed; where neither can be written the module is
    compiled in this process only."""
    data = src.encode()
    code = codecache.code_dir()
    folders = [code] if code is not None else []
    try:
        folders.append((cache_dir(), True))
    except OSError:
        pass
    path = None
    for folder, writable in folders:
        p = folder / f"{name}.py"
        try:
            same = p.read_bytes() == data
        except OSError:
            same = False
        if not same and writable:
            try:
                _write_module(p, data, name)
                same = True
            except OSError:
                pass
        if same:
            path = p
            _mark_used(p)
            break
    on_disk = path is not None
    if path is None:  # never written: its functions compile in this process, with no disk cache
        path = (folders[0][0] if folders else Path(tempfile.gettempdir())) / f"{name}.py"
    codecache.register(path.parent)
    mod = types.ModuleType(name)
    mod.__file__ = str(path)
    sys.modules[name] = mod
    try:
        exec(compile(data, str(path), "exec"), mod.__dict__)
        codecache.adopt(mod, on_disk)
    except BaseException:
        del sys.modules[name]
        raise
    return mod


def _write_module(path: Path, data: bytes, name: str) -> None:
    """``data`` into ``path`` through a temporary file and a rename (concurrent writers: one whole file wins);
    prunes the folder's modules unused for ``KEEP_DAYS`` first."""
    prune_generated(path.parent, _keep_days(), time.time(), keep=name)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _has_kernel(cls) -> bool:
    return isinstance(cls, type) and issubclass(cls, Effect) and any(
        getattr(cls, a) is not None for a in ("command_kernel", "rotor_kernel", "wrench_kernel"))


#: kernel effect kinds of physics/effects.py, in EFFECTS order: codes 0.. of every registry
_BUILTIN: tuple[type[Effect], ...] = tuple(c for c in effects_mod.EFFECTS.values() if _has_kernel(c))
#: kernel effect kinds from elsewhere, registered as models first use them (sorted: module, name)
_EXTRA: list[type[Effect]] = []


def _registry(kinds: Sequence[type[Effect]] = ()) -> tuple[type[Effect], ...]:
    """The registry covering ``kinds``: the built-in kinds, then the extra ones.  A kind not yet
    registered is added with every kernel effect its module defines at top level (so the prove
    suite's three plant-only effects make one registry, whichever is used first)."""
    new = [k for k in kinds if k not in _BUILTIN and k not in _EXTRA]
    for cls in new:
        if cls in _EXTRA:
            continue
        module = sys.modules.get(cls.__module__)
        more = [v for v in vars(module).values() if _has_kernel(v)] if module is not None else []
        _EXTRA.extend(k for k in dict.fromkeys([cls, *more]) if k not in _BUILTIN and k not in _EXTRA)
    if new:
        _EXTRA.sort(key=lambda k: (k.__module__, k.__qualname__))
    return _BUILTIN + tuple(_EXTRA)


_MODULES: dict[tuple[type[Effect], ...], types.ModuleType] = {}


def _load_generated(registry: Sequence[type[Effect]]) -> types.ModuleType:
    """The dispatch stepper module for this registry."""
    registry = tuple(registry)
    if registry not in _MODULES:
        src = _generate_source(registry)
        name = _module_name(src)
        _MODULES[registry] = sys.modules.get(name) or _import_source(name, src)
    return _MODULES[registry]


def effect_table(kernel_effects: Sequence[Effect], registry: Sequence[type[Effect]], start: int) -> np.ndarray:
    """The effect table (stepper.effect_table) for these effects, their vectors starting at ``P[start]``
    after it: the counts, then each hook's ``(code, start)`` entries in effect order."""
    starts, at = [], start + 3 + 2 * sum(
        getattr(e, a) is not None for e in kernel_effects for a in ("command_kernel", "rotor_kernel", "wrench_kernel"))
    for e in kernel_effects:
        starts.append(at)
        at += len(e.param_names)
    code = {cls: i for i, cls in enumerate(registry)}
    rows = [[(code[type(e)], s) for e, s in zip(kernel_effects, starts) if getattr(e, a) is not None]
            for a in ("command_kernel", "rotor_kernel", "wrench_kernel")]
    return np.array([*(len(r) for r in rows), *(v for r in rows for pair in r for v in pair)], dtype=np.float64)


class Multirotor:
    """A multirotor with its effects; stateless stepping functions over state vectors.

    >>> m = Multirotor(shipped('px4_sih_quadx'))
    >>> x = m.initial_state(position_enu=(0, 0, 10))
    >>> x = m.step(x, np.full(4, m.params.hover_command), n_substeps=1000)   # 1 s
    """

    def __init__(self, vp: VehicleParams, extra_effects: Sequence[Effect] = ()):
        self.nominal_params = vp
        effs = effects_from_params(vp) + list(extra_effects)
        params = vp
        for e in effs:
            params = e.apply_to_params(params)
        self.params = params
        self.effects = effs
        self.kernel_effects = [e for e in effs if e.has_kernel]
        self._bind()
        self.E = ()  # no other kernel arguments; kept for callers passing (P, *E, ...)
        self.n_rotors = params.rotors.count
        self.nx = NX_BODY + self.n_rotors
        self.term_names = ["rotors"] + [e.name for e in self.kernel_effects if e.wrench_kernel is not None]

    def _bind(self) -> None:
        """The dispatch stepper of the current registry, and ``P``: the vehicle, the effect table,
        then the kernel effects' parameters (stepper.py)."""
        registry = _registry([type(e) for e in self.kernel_effects])
        self._mod = _load_generated(registry)
        # rotor positions relative to the (moved) centre of mass
        vehicle = pack(self.params, centre_of_mass(self.effects))
        table = effect_table(self.kernel_effects, registry, len(vehicle))
        self.P = np.concatenate([vehicle, table, *(e.vector() for e in self.kernel_effects)])

    # ----------------------------------------------------------- properties
    @property
    def dt_s(self) -> float:
        return self.params.dt_s

    @property
    def command_delay_s(self) -> float:
        return float(sum(e.command_delay_s() for e in self.effects))

    def exogenous(self, t: np.ndarray, rng: np.random.Generator | None = None,
                  battery_v: np.ndarray | None = None) -> np.ndarray:
        """Exogenous input series (T, 4) for times ``t``: battery voltage and effect-made wind."""
        rng = rng if rng is not None else np.random.default_rng(0)
        ext = np.tile(default_ext(), (len(t), 1))
        if battery_v is not None:
            ext[:, 0] = battery_v
        for e in self.effects:
            ext = e.exogenous(np.asarray(t, float), ext, rng)
        return ext

    # ----------------------------------------------------------- states
    def initial_state(self, position_enu=(0.0, 0.0, 0.0), velocity_enu=(0.0, 0.0, 0.0),
                      yaw_enu_rad: float = 0.0, q_wxyz=None, rates_flu=(0.0, 0.0, 0.0),
                      rotor_state=None) -> np.ndarray:
        """State vector; rotors at rest unless ``rotor_state`` ('hover' or an array) is given."""
        x = np.zeros(self.nx)
        x[0:3] = position_enu
        x[3:6] = velocity_enu
        if q_wxyz is None:
            q_wxyz = (np.cos(yaw_enu_rad / 2), 0.0, 0.0, np.sin(yaw_enu_rad / 2))
        q = np.asarray(q_wxyz, float)
        x[6:10] = q / np.linalg.norm(q)
        x[10:13] = rates_flu
        if isinstance(rotor_state, str) and rotor_state == "hover":
            x[NX_BODY:] = self.params.rotors.reference_from_command(np.full(self.n_rotors, self.params.hover_command))
        elif rotor_state is not None:
            x[NX_BODY:] = rotor_state
        return x

    def _ext(self, ext, batch: int | None = None) -> np.ndarray:
        if ext is None:
            e = default_ext()
            return e if batch is None else np.tile(e, (batch, 1))
        e = np.asarray(ext, dtype=np.float64)
        if e.shape[-1] != EXT_SIZE:
            raise ValueError(f"ext must have {EXT_SIZE} entries per row, got shape {e.shape}")
        if batch is not None and e.ndim == 1:
            e = np.tile(e, (batch, 1))
        return np.ascontiguousarray(e)

    def _u(self, u) -> np.ndarray:
        u = np.ascontiguousarray(u, dtype=np.float64)
        if u.shape[-1] != self.n_rotors:
            raise ValueError(f"expected {self.n_rotors} motor commands per row, got shape {u.shape}")
        return u

    # ----------------------------------------------------------- stepping
    def step(self, x: np.ndarray, u, dt: float | None = None, ext=None, n_substeps: int = 1) -> np.ndarray:
        """New state after ``n_substeps`` RK4 steps of ``dt`` with command ``u`` held.

        ``x`` (nx,) with ``u`` (N,), or a batch ``x`` (K, nx) with ``u`` (K, N).
        """
        dt = self.dt_s if dt is None else float(dt)
        u = self._u(u)
        x = np.array(x, dtype=np.float64, copy=True)
        if x.ndim == 1:
            self._mod.step_n(self.P, x, u, self._ext(ext), dt, int(n_substeps))
            return x
        k = x.shape[0]
        u = np.broadcast_to(u, (k, self.n_rotors)).copy()
        self._mod.step_batch(np.tile(self.P, (k, 1)), x, u, self._ext(ext, k), dt, int(n_substeps))
        return x

    def step_unchecked(self, x: np.ndarray, u: np.ndarray, dt: float, ext: np.ndarray, n_substeps: int) -> np.ndarray:
        """:meth:`step` for one vehicle without converting or checking its arguments (a control loop's
        hot path): ``x`` (nx,), ``u`` (N,) and ``ext`` (EXT_SIZE,) must be float64 arrays of those
        shapes already; ``dt`` a float, ``n_substeps`` an int.  The same kernel, the same numbers."""
        x = x.copy()
        self._mod.step_n(self.P, x, u, ext, dt, n_substeps)
        return x

    def specific_force_unchecked(self, x: np.ndarray, u: np.ndarray, ext: np.ndarray) -> np.ndarray:
        """:meth:`specific_force_flu` with the arguments as :meth:`step_unchecked` needs them."""
        return self._mod.specific_force(self.P, x, u, ext)

    def simulate(self, x0: np.ndarray, U: np.ndarray, dt: float | None = None, ext=None,
                 n_substeps: int = 1) -> np.ndarray:
        """States (T+1, nx) for commands U (T, N), each held for ``n_substeps`` steps of ``dt``."""
        dt = self.dt_s if dt is None else float(dt)
        U = self._u(U)
        if U.ndim != 2:
            raise ValueError(f"U must be (T, N), got {U.shape}")
        ext_arr = self._ext(ext, U.shape[0]) if (ext is None or np.ndim(ext) == 1) else self._ext(ext)
        return self._mod.simulate(self.P, np.asarray(x0, np.float64), U, ext_arr, dt, int(n_substeps))

    # ----------------------------------------------------------- outputs
    def specific_force_flu(self, x: np.ndarray, u, ext=None) -> np.ndarray:
        """What an accelerometer at the CoM reads [m/s^2], body FLU (≈ +g on z at rest)."""
        return self._mod.specific_force(self.P, np.asarray(x, np.float64), self._u(u), self._ext(ext))

    def rotor_speeds(self, x: np.ndarray) -> np.ndarray:
        """Rotor speeds [rad/s] from the rotor states in ``x``."""
        omega, _ = self._rotor(x)
        return omega

    def rotor_thrusts(self, x: np.ndarray) -> np.ndarray:
        """Per-rotor thrust [N] from the rotor states, *before* rotor-hook effects
        (``motor_efficiency``, ``ground_effect``); :meth:`wrench_terms` gives the force the
        dynamics actually use."""
        _, thrust = self._rotor(x)
        return thrust

    def _rotor(self, x):
        x = np.atleast_2d(np.asarray(x, float))
        s = np.maximum(x[:, NX_BODY:], 0.0)
        r = self.params.rotors
        if r.thrust_model == "omega_squared":
            omega = np.minimum(s, r.omega_max_rad_s)
            thrust = r.kt_n_s2_rad2 * omega ** 2
        else:
            thrust = r.thrust_from_state(s)
            omega = r.omega_max_rad_s * np.sqrt(np.maximum(thrust, 0) / r.thrust_max_n)
        if np.ndim(x) == 2 and x.shape[0] == 1:
            return omega[0], thrust[0]
        return omega, thrust

    def wrench_terms(self, X: np.ndarray, ext=None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Body force and moment of each named term along a state history X (T, nx), FLU."""
        X = np.ascontiguousarray(np.atleast_2d(X), dtype=np.float64)
        ext_arr = self._ext(ext, X.shape[0]) if (ext is None or np.ndim(ext) == 1) else self._ext(ext)
        nt = len(self.term_names)
        F = np.zeros((X.shape[0], nt, 3))
        M = np.zeros((X.shape[0], nt, 3))
        self._mod.wrench_terms(self.P, X, ext_arr, F, M)
        return {name: (F[:, j], M[:, j]) for j, name in enumerate(self.term_names)}

    def batch(self, variants: Sequence[VehicleParams]) -> "MultirotorBatch":
        return MultirotorBatch([Multirotor(v) for v in variants])


class MultirotorBatch:
    """K vehicles (same rotor count and same effect kinds, any parameter values) stepped at once."""

    def __init__(self, models: Sequence[Multirotor]):
        if not models:
            raise ValueError("empty batch")
        kinds = [tuple(type(e) for e in m.kernel_effects) for m in models]
        if len(set(kinds)) != 1 or len({m.n_rotors for m in models}) != 1:
            raise ValueError("a batch needs the same rotor count and the same effect kinds in every vehicle")
        self.models = list(models)
        if len({id(m._mod) for m in models}) > 1:  # built before and after the registry grew: the newest one
            for m in models:
                m._bind()
        self._mod = models[0]._mod
        self.PB = np.stack([m.P for m in models])
        self.EB = ()  # as Multirotor.E
        self.n_rotors = models[0].n_rotors
        self.nx = models[0].nx

    def __len__(self) -> int:
        return len(self.models)

    def step(self, X: np.ndarray, U: np.ndarray, dt: float, ext=None, n_substeps: int = 1) -> np.ndarray:
        X = np.array(X, dtype=np.float64, copy=True)
        k = X.shape[0]
        U = np.ascontiguousarray(np.broadcast_to(U, (k, self.n_rotors)), dtype=np.float64)
        e = np.tile(default_ext(), (k, 1)) if ext is None else np.ascontiguousarray(np.broadcast_to(ext, (k, EXT_SIZE)), dtype=np.float64)
        self._mod.step_batch(self.PB, X, U, e, float(dt), int(n_substeps))
        return X
