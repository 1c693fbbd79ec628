"""The stepper as it was before the dispatch stepper (main eda17af): one generated numba module per
ordered set of effect kinds, each hook calling its effects' kernels directly.

Kept verbatim (``bench/stepper_before.py`` is the template of that time; the generator below is the
old ``twin_nodes.physics.model._generate_source``/``_load_generated``) so that
``tests/test_stepper_dispatch.py`` can fly the same vehicles through both paths and
``bench/bench_compile.py`` can time both compiles in one run.  Its modules are named
``rotortwin_genold_*`` and written to the same private cache folder as the model's.
"""

from __future__ import annotations

import hashlib
import inspect
import sys
import types
from pathlib import Path
from typing import Sequence

import numpy as np

from twin_nodes.physics import core, effects as effects_mod
from twin_nodes.physics.core import NX_BODY, pack
from twin_nodes.physics.effects import Effect, centre_of_mass, effects_from_params
from twin_nodes.physics.model import _import_source

_TEMPLATE = (Path(__file__).resolve().parent / "stepper_before.py").read_text()

_HOOKS = {"command_hooks": ("command_kernel", "ext, sref"),
          "rotor_hooks": ("rotor_kernel", "x, ext, omega, T, Q"),
          "wrench_hooks": ("wrench_kernel", "x, R, ext, omega, T, Fb, Mb, Fw")}


def generate_source(kinds: Sequence[type[Effect]]) -> str:
    imports, calls, start = set(), {hook: [] for hook in _HOOKS}, 0
    for cls in kinds:
        vec = f"E[{start}:{start + len(cls.param_names)}]"
        start += len(cls.param_names)
        for hook, (attr, args) in _HOOKS.items():
            kernel = getattr(cls, attr)  # an @njit function or None
            if kernel is not None:
                imports.add(f"from {kernel.__module__} import {kernel.__name__}\n")
                vehicle = "P, " if cls.kernel_reads_vehicle else ""  # the packed vehicle (rotor positions)
                calls[hook].append(f"{kernel.__name__}({vec}, {vehicle}{args})")
    terms = calls["wrench_hooks"]
    defs = [(f"{hook}(P, {args})", calls[hook]) for hook, (_, args) in _HOOKS.items()]
    defs.append((f"wrench_term(j, P, {_HOOKS['wrench_hooks'][1]})",
                 [line for j, call in enumerate(terms, 1) for line in (f"if j == {j}:", f"    {call}")]))
    used = ", ".join(str(bool(calls[hook])) for hook in _HOOKS)
    hooks = "".join(sorted(imports))
    hooks += f"N_TERMS = {1 + len(terms)}\nCOMMAND_HOOKS, ROTOR_HOOKS, WRENCH_HOOKS = {used}\n"
    for signature, body in defs:
        body = ["E = effect_params(P)", *body] if body else ["pass"]
        inline = ', inline="always"' if signature.startswith("command_hooks") else ""
        hooks += f"\n\n@njit(cache=True{inline})\ndef {signature}:\n" + "".join(f"    {line}\n" for line in body)
    lines = _TEMPLATE.splitlines(keepends=True)
    begin = next(i for i, line in enumerate(lines) if line.startswith("# ---- hooks"))
    end = lines.index("# ---- end of hooks ----\n")
    return "".join(lines[:begin + 1]) + hooks + "".join(lines[end:])


def _module_name(src: str) -> str:
    h = hashlib.sha256(src.encode())
    for mod in (core, effects_mod):
        h.update(inspect.getsource(mod).encode())
    for line in src.splitlines():
        if line.startswith("from ") and " import " in line:
            name = line.split()[1]
            if name.startswith("twin_nodes.") and name not in (core.__name__, effects_mod.__name__):
                h.update(inspect.getsource(sys.modules[name]).encode())
    return f"rotortwin_genold_{h.hexdigest()[:16]}"


_MODULES: dict[tuple, types.ModuleType] = {}


def load(kinds: Sequence[type[Effect]]) -> types.ModuleType:
    kinds = tuple(kinds)
    if kinds not in _MODULES:
        src = generate_source(kinds)
        name = _module_name(src)
        _MODULES[kinds] = sys.modules.get(name) or _import_source(name, src)
    return _MODULES[kinds]


class OldModel:
    """What the old ``Multirotor`` handed its stepper: the module, ``P`` and the term names."""

    def __init__(self, vp, extra_effects=()):
        effs = effects_from_params(vp) + list(extra_effects)
        params = vp
        for e in effs:
            params = e.apply_to_params(params)
        self.params = params
        kernel_effects = [e for e in effs if e.has_kernel]
        self.mod = load([type(e) for e in kernel_effects])
        # the vehicle packed as today's Multirotor packs it (rotor positions about a com_offset's centre of
        # mass, since the ninth session): this file keeps the old *generator*, the physics is today's
        self.P = np.concatenate([pack(params, centre_of_mass(effs)), *(e.vector() for e in kernel_effects)])
        self.n_rotors = params.rotors.count
        self.nx = NX_BODY + self.n_rotors
        self.term_names = ["rotors"] + [e.name for e in kernel_effects if e.wrench_kernel is not None]
