"""Fleet throughput: flights per minute through ``rotortwin fleet discover`` with 1 and 2 workers.

::

    .venv/bin/python bench/bench_fleet.py FLIGHTS_OR_DIRS... [--no-closed-loop] [--params P]  # real discovery
    .venv/bin/python bench/bench_fleet.py --synthetic [--n 8] [--task-s 3]  # a CPU-bound stand-in task

Each run writes a fresh catalog (nothing skipped) on an embedded LocalCluster (one-thread worker
processes) with an empty data cache of its own (``ROTORTWIN_CACHE``: built nominals; ``--warm`` shares the user's);
the time includes starting the cluster.  Each worker count runs twice (``--modes``): **cold**, with an empty code
cache of its own (``ROTORTWIN_CODE_CACHE``: every generated numba module compiled, as on a machine's first run),
and **as installed**, with the user's code cache as ``make setup`` leaves it (``rotortwin fleet warm`` runs first,
untimed).  Prints flights/min per run, the 2-worker / 1-worker scaling ratio of each mode and the
as-installed / cold ratio (all measured in the same run), and the flight-minutes analysed (the logs'
durations, from the catalog rows) per wall-minute per worker core; beside them the CPU seconds of the run (this
process and its ended worker processes: comparable on a shared machine, where wall time is not) and the load
average before and after it.  Without ``--params`` each flight flies the
params ``fleet discover`` picks for it (the shipped file for its airframe, else the nominal built from the log).  ``--synthetic`` measures the
runner's own overhead and scaling with a task that burns ``--task-s`` seconds of CPU and writes a
catalog row, no discovery; it is what runs without arguments (``make bench``).
``ROTORTWIN_BENCH_SMOKE=1``: a smoke run (synthetic, 2 flights of 0.2 s; the numbers mean nothing).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def burn_task(path, catalog, mode, params, params_map, closed_loop_metrics):
    """CPU-bound stand-in for discovery: numpy work for the seconds in the file, then a row."""
    import numpy as np

    from twin_nodes.fleet import catalog as cat

    secs = float(json.loads(Path(path).read_text())["task_s"])
    t0 = time.process_time()
    a = np.random.default_rng(0).standard_normal((200, 200))
    while time.process_time() - t0 < secs:
        a = np.tanh(a @ a.T / 200.0)
    row = {**cat.file_key(path), "status": "ok", "error": "", "vehicle_id": "bench",
           "flight_time_utc": "", "effects_json": "[]"}
    cat.write_row(catalog, row)
    return {"path": row["path"], "status": "ok", "error": ""}


def _cpu_s() -> float:
    """User + system CPU seconds of this process and of its ended children (the cluster's workers)."""
    import resource

    return sum(getattr(resource.getrusage(who), f) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
               for f in ("ru_utime", "ru_stime"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flights", nargs="*", help=".ulg flights or folders of them (real discovery)")
    ap.add_argument("--synthetic", action="store_true")
    from _smoke import SMOKE as smoke  # bench/ is on sys.path when a bench runs as a script
    ap.add_argument("--n", type=int, default=2 if smoke else 8, help="synthetic flights")
    ap.add_argument("--task-s", type=float, default=0.2 if smoke else 3.0, help="synthetic CPU seconds per flight")
    ap.add_argument("--params", default=None, help="one params file for every flight (default: per flight)")
    ap.add_argument("--no-closed-loop", action="store_true")
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--modes", default="cold,installed",
                    help="cold: an empty code cache (every generated module compiled); installed: the user's code "
                         "cache as make setup leaves it (warmed first, not timed); default both")
    ap.add_argument("--warm", action="store_true", help="share the user's cache between the runs (default: each run "
                    "starts with an empty cache, so the second does not reuse the nominals the first built)")
    a = ap.parse_args(argv)
    if not a.flights and not a.synthetic:
        print("bench_fleet: no FLIGHTS_DIR given: the synthetic task (--synthetic)", flush=True)
        a.synthetic = True

    from twin_nodes.fleet.run import find_flights

    tmp = Path(tempfile.mkdtemp(prefix="bench_fleet_"))
    kw = {}
    if a.synthetic:
        import cloudpickle
        cloudpickle.register_pickle_by_value(sys.modules[__name__])
        flights = []
        for k in range(a.n):
            f = tmp / f"s{k:03d}.ulg"
            # distinct contents: the fleet runner takes files with the same content for one flight
            f.write_text(json.dumps({"task_s": a.task_s, "flight": k}))
            flights.append(f)
        kw["task"] = burn_task
    elif a.flights:
        flights = find_flights(a.flights)
        kw.update(params=a.params, closed_loop_metrics=not a.no_closed_loop)
    else:
        ap.error("give FLIGHTS_DIR or --synthetic")
    import os
    import subprocess

    modes = [m.strip() for m in a.modes.split(",") if m.strip()]
    bad = [m for m in modes if m not in ("cold", "installed")]
    if bad or not modes:
        ap.error(f"--modes: expected cold and/or installed, got {a.modes!r}")
    installed_code = os.environ.get("ROTORTWIN_CODE_CACHE")  # the user's code cache (unset: the default one)
    if "installed" in modes and not a.synthetic:  # as make setup leaves it: the code cache warm (not timed)
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "twin_nodes", "fleet", "warm"], capture_output=True, text=True,
                           cwd=Path(__file__).resolve().parents[1])
        said = (r.stdout or r.stderr).strip().splitlines()
        print(f"code cache warmed as make setup does (not timed, {time.perf_counter() - t0:.1f} s): "
              f"{said[-1] if said else f'exit {r.returncode}'}", flush=True)
    rate: dict[tuple[str, int], float] = {}
    for w in [int(x) for x in a.workers.split(",")]:
        for mode in modes:
            if not a.warm:  # each run starts with an empty data cache (nominals), as a user's first run
                os.environ["ROTORTWIN_CACHE"] = str(tmp / f"cache_{mode}_w{w}")
            if mode == "cold":  # nothing compiled: an empty code cache (the tree's own numba caches stay)
                os.environ["ROTORTWIN_CODE_CACHE"] = str(tmp / f"code_cold_w{w}")
            elif installed_code is None:
                os.environ.pop("ROTORTWIN_CODE_CACHE", None)
            else:
                os.environ["ROTORTWIN_CODE_CACHE"] = installed_code
            rate[mode, w] = _run_once(a, flights, tmp, kw, mode, w)
    label = {"cold": "empty code cache", "installed": "as installed: code cache warm"}
    for mode in modes:
        if (mode, 1) in rate and (mode, 2) in rate:
            print(f"scaling 2 workers / 1 worker{'' if mode == 'installed' else ', ' + mode}: "
                  f"{rate[mode, 2] / rate[mode, 1]:.2f}x ({label[mode]})")
    for w in sorted({w for _, w in rate}):
        if ("cold", w) in rate and ("installed", w) in rate:
            print(f"ratio as installed / cold, {w} worker(s): {rate['installed', w] / rate['cold', w]:.2f}x "
                  "(flights/min, same run)")
    return 0


def _run_once(a, flights, tmp: Path, kw: dict, mode: str, w: int) -> float:
    """One timed ``run_fleet`` with ``w`` workers into a fresh catalog; prints its line, returns flights/min."""
    import os

    from twin_nodes.fleet.run import run_fleet

    load0 = os.getloadavg()[0]
    cpu0 = _cpu_s()
    t0 = time.perf_counter()
    res = run_fleet(flights, tmp / f"cat_{mode}_w{w}", workers=w, progress=False, **kw)
    dt = time.perf_counter() - t0
    cpu = _cpu_s() - cpu0
    ok = sum(d["status"] == "ok" for d in res["done"])
    rate = len(flights) / dt * 60
    fmin = 0.0
    if not a.synthetic:
        from twin_nodes.fleet.catalog import load
        fmin = sum(float(r.get("duration_s") or 0.0) for r in load(tmp / f"cat_{mode}_w{w}")) / 60.0
    print(f"{mode} workers={w}: {len(flights)} flights ({ok} ok) in {dt:.1f} s -> {rate:.2f} flights/min"
          + (f"; {fmin:.1f} flight-minutes of logs -> {fmin / (dt / 60.0) / w:.1f} flight-min per wall-min "
             f"per core" if fmin else "")
          + f"; {cpu:.1f} CPU s (this process and its workers); load average {load0:.2f} before, "
            f"{os.getloadavg()[0]:.2f} after", flush=True)
    return rate


if __name__ == "__main__":
    sys.exit(main())
