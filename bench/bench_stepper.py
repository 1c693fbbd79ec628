"""The dispatch stepper (one module) vs one module per effect set (before): compile time and hot-path speed.

::

    .venv/bin/python bench/bench_stepper.py [--combos 12] [--paths before,after] [--hot-seconds 5] [--repeat 5]

**Compile time.**
Each path runs in a fresh process with an empty ``ROTORTWIN_CACHE`` and ``ROTORTWIN_CODE_CACHE`` (so numba
compiles the model's generated modules, as in a user's first run or a cold ``bench_fleet.py`` worker), then once more in
another fresh process on that cache (loading what the first compiled).  Each process builds
``--combos`` vehicles, ``params/px4_sih_quadx.yaml`` (linear drag, angular damping) plus one or two
kernel effects each (what discovery's candidates add), and for each calls what a flight's discovery
calls: one step, ``simulate``, ``wrench_terms``, ``specific_force``, ``rotor_states`` and discovery's
``kernels.warm`` (its output-error and lag kernels).  ``before`` flies the stepper of main eda17af
(``bench/model_before.py``, its module swapped into the same ``Multirotor``).  Prints seconds to the
end of the first combination and of all, per path, and the **ratio before / after** (cold, all).
The static numba functions (core, effects, control) are cached beside their sources and are not
part of either number.  CPU seconds (the child's ``process_time``) beside wall seconds: the machine may
be shared.

**Hot path**, then, in this process (both modules loaded first; the two paths alternate, best of
``--repeat``): ``step() per 1 ms`` of the Búho Negro without kernel effects (as ``bench_model.py``),
``simulate()`` of the SIH quad with eight kernel effects (tests/test_model_generator.py's set), and
discovery's output-error kernel (``kernels.step_windows``: 200 windows of 0.4 s at 2 ms) on that
vehicle and on the SIH quad with one motor's efficiency (its two drags and one candidate: what discovery
flies most); each row prints the **ratio after / before** of the speeds (1.0: as fast; below: slower).
``ROTORTWIN_BENCH_SMOKE=1``: 1 combination, 0.2 s, one repeat.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))

KINDS = [("battery_sag", {"v_ref": 12.6, "exponent": 1.0}), ("motor_efficiency", {"motor": 3, "efficiency": 0.9}),
         ("ground_effect", {"coefficient": 0.2, "height_scale": 0.5}),
         ("body_drag", {"c_dx": 0.01, "c_dy": 0.01, "c_dz": 0.02}), ("rotor_drag", {"k_d": 1e-4}),
         ("com_offset", {"dx": 0.01, "dy": 0.0}), ("rotor_tilt", {"lever_m": 0.002}),
         ("state_term", {"c_mu": 0.02}), ("coaxial", {"efficiency": 0.9, "lower_mask": 3})]


def combos(n: int) -> list[list[tuple[str, dict]]]:
    """n effect sets: each kind alone, then pairs of neighbours (battery sag + motor efficiency, ...)."""
    out = [[k] for k in KINDS] + [[KINDS[i], KINDS[i + 1]] for i in range(len(KINDS) - 1)]
    return out[:n]


def child(path: str, n: int) -> dict:
    import numpy as np

    from twin_nodes.discovery.kernels import warm
    from twin_nodes.physics.effects import default_ext
    from twin_nodes.physics.model import Multirotor
    from twin_nodes.vehicle.params import load_params

    base = load_params(ROOT / "params" / "px4_sih_quadx.yaml")
    t0 = time.perf_counter()
    c0 = time.process_time()
    marks, cpu = [], []
    for effs in combos(n):
        vp = base
        for name, p in effs:
            vp = vp.with_effect(name, **p)
        m = Multirotor(vp)
        if path == "before":
            from model_before import OldModel
            old = OldModel(vp)
            m._mod, m.P = old.mod, old.P
        x = m.initial_state(position_enu=(0.0, 0.0, 5.0), rotor_state="hover")
        u = np.full(m.n_rotors, m.params.hover_command)
        x = m.step(x, u, n_substeps=4)
        X = m.simulate(x, np.tile(u, (5, 1)))
        m.wrench_terms(X)
        m.specific_force_flu(x, u)
        m._mod.rotor_states(m.P, np.tile(u, (5, 1)), np.tile(default_ext(), (5, 1)), 0.002, 1, np.zeros(m.n_rotors))
        warm(m, True)
        marks.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {"first": marks[0], "all": marks[-1], "n": len(marks), "cpu_first": cpu[0], "cpu_all": cpu[-1]}


def run(path: str, n: int, cache: Path) -> dict:
    env = dict(os.environ, ROTORTWIN_CACHE=str(cache), ROTORTWIN_CODE_CACHE=str(cache))  # data and code cache: cold
    r = subprocess.run([sys.executable, __file__, "--child", path, "--combos", str(n)], env=env, cwd=ROOT,
                       capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"bench_compile: the {path} child failed:\n{r.stdout}{r.stderr}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    from _smoke import SMOKE as smoke

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--combos", type=int, default=1 if smoke else 12)
    ap.add_argument("--paths", default="before,after")
    ap.add_argument("--hot-seconds", type=float, default=0.2 if smoke else 5.0)
    ap.add_argument("--repeat", type=int, default=1 if smoke else 5)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.child, a.combos)))
        return 0
    tmp = Path(tempfile.mkdtemp(prefix="bench_compile_"))
    cold = {}
    print(f"{a.combos} effect combinations; load average {os.getloadavg()[0]:.2f}", flush=True)
    for path in a.paths.split(","):
        cache = tmp / path
        c = run(path, a.combos, cache)
        w = run(path, a.combos, cache)
        cold[path] = c["all"]
        print(f"{path:6s}: cold {c['first']:6.1f} s ({c['cpu_first']:.1f} CPU s) to the first combination, "
              f"{c['all']:6.1f} s ({c['cpu_all']:.1f} CPU s) to all {c['n']}; warm (cache on disk) "
              f"{w['first']:5.1f} s / {w['all']:5.1f} s; modules {len(list(cache.glob('rotortwin_*.py')))}",
              flush=True)
    if {"before", "after"} <= set(cold):
        print(f"ratio before/after (cold, all combinations): {cold['before'] / cold['after']:.2f}x "
              f"(load average {os.getloadavg()[0]:.2f})", flush=True)
        hot(a.hot_seconds, a.repeat)
    return 0


def hot(seconds: float, repeat: int) -> None:
    import numpy as np

    from model_before import OldModel
    from test_model_generator import effect_vehicle, scenario

    from twin_nodes.discovery.kernels import kernels
    from twin_nodes.physics.effects import default_ext
    from twin_nodes.physics.model import Multirotor
    from twin_nodes.vehicle.params import shipped

    def pair(vp):
        new, old = Multirotor(vp), Multirotor(vp)
        o = OldModel(vp)
        old._mod, old.P = o.mod, o.P
        return {"before": old, "after": new}

    bare = pair(shipped("buho_negro"))
    rich = pair(effect_vehicle("px4_sih_quadx"))
    # what discovery flies most: the SIH quad's two drags and one candidate (the demo flight's weak motor)
    typical = pair(shipped("px4_sih_quadx").with_effect("motor_efficiency", motor=3, efficiency=0.85))
    n = max(int(round(seconds / 0.001)), 10)
    x0 = bare["after"].initial_state(position_enu=(0.0, 0.0, 50.0), rotor_state="hover")
    u = np.full(4, bare["after"].params.hover_command)
    Us = u * (1.0 + 0.05 * np.sin(np.arange(n) * 0.01))[:, None]
    ext1 = default_ext()
    xr0, UR, EXT = scenario(rich["after"], "px4_sih_quadx")
    nr = max(int(round(seconds / 0.004)), 10)
    UR = np.ascontiguousarray(np.resize(UR, (nr, 4)))
    EXT = np.ascontiguousarray(np.resize(EXT, (nr, 4)))
    k = 200
    X = np.tile(xr0, (k, 1))
    base = np.arange(k, dtype=np.int64) * 2
    W, V = np.empty((20, k, 3)), np.empty((20, k, 3))
    uw = np.ascontiguousarray(np.resize(np.nan_to_num(UR), (2 * k + 400, 4)))
    ew = np.ascontiguousarray(np.resize(EXT, (2 * k + 400, 4)))

    def step_1ms(m):
        x = x0
        for j in range(n):
            x = m.step_unchecked(x, Us[j], 0.001, ext1, 1)

    def windows(m):
        kernels(m).step_windows(m.P, X.copy(), uw, ew, base, 1, 0, 0.002, 200, 10, W, V)

    rows = {"step() per 1 ms, no kernel effects": (bare, step_1ms, n * 0.001),
            "simulate(), 8 kernel effects": (rich, lambda m: m.simulate(xr0, UR, 0.002, EXT, 2), nr * 0.004),
            "step_windows, 8 kernel effects": (rich, windows, k * 0.4),
            "step_windows, SIH + motor efficiency": (typical, windows, k * 0.4)}
    print(f"hot path (best of {repeat}, alternating; load average {os.getloadavg()[0]:.2f}):")
    for name, (models, fn, sim_s) in rows.items():
        for m in models.values():
            fn(m)  # compile / load
        best = {p: float("inf") for p in models}
        for _ in range(repeat):
            for p, m in models.items():
                t0 = time.perf_counter()
                fn(m)
                best[p] = min(best[p], time.perf_counter() - t0)
        print(f"  {name:<38} before {sim_s / best['before']:8.1f}x  after {sim_s / best['after']:8.1f}x real time"
              f"  ratio after/before {best['before'] / best['after']:.3f}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
