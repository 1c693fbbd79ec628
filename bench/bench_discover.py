"""Discovery speed: seconds of wall time per flight-minute, now and before issue 13's speed work.

::

    .venv/bin/python bench/bench_discover.py                       # the shipped 134 s demo flight
    .venv/bin/python bench/bench_discover.py FLIGHT.ulg [--params P.yaml] [--repeat 2] [--strict]

One process runs ``discover`` on the flight with the evaluation path as it is now, and with the
frozen previous one (:mod:`discover_before`: its residual functions and fit, one process, no
affine shortcut) under the same judging logic, and prints for each the wall time, the CPU time
(this process and its worker processes) and seconds per flight-minute, then the ratio
before/after.  A warm-up run (untimed) first loads every compiled model from numba's cache, so
neither side pays for it.  ``--repeat N`` alternates the two N times and keeps each side's best.

It also checks that both give the same result: accepted effects, every effect's verdict, the
parameters (largest relative difference, over the confirmed/likely effects and over all), the
likely list, and the closed-loop twin's held-out numbers.  ``--strict`` exits 1 if the results
differ (verdicts, accepted, or a confirmed/likely parameter by more than 1e-3 relative) or the
new path is slower than ``--target`` s per flight-minute (default 3).

``ROTORTWIN_BENCH_SMOKE=1``: a smoke run (no flight given: bench/_smoke.py's ~1-minute simulated
flight, no warm-up, no closed-loop twin; the numbers mean nothing).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import discover_before  # bench/: the frozen previous evaluation path
from _smoke import SIH, SMOKE, tiny_flight

DEMO = ROOT / "bags" / "sim_quadx_weak_motor3.ulg"
DEMO_PARAMS = ROOT / "params" / "px4_sih_quadx.yaml"


def _cpu() -> float:
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def timed(fn) -> tuple[dict, float, float]:
    c0, t0 = _cpu(), time.perf_counter()
    res = fn()
    return res, time.perf_counter() - t0, _cpu() - c0


def _key(e: dict) -> str:
    motor = e["params"].get("motor")
    return e["name"] + (f"(motor {int(motor)})" if motor is not None else "")


def _rel(a: float, b: float) -> float:
    return abs(a - b) / max(abs(a), abs(b), 1e-12)


def compare(before: dict, after: dict) -> dict:
    """Differences between two discover results (JSON dicts)."""
    eb = {_key(e): e for e in before["effects"]}
    ea = {_key(e): e for e in after["effects"]}
    out = {"accepted_same": before["accepted"] == after["accepted"],
           "likely_same": before["likely"] == after["likely"],
           "effects_same": sorted(eb) == sorted(ea),
           "verdicts_differ": sorted(k for k in eb if k in ea and eb[k]["verdict"] != ea[k]["verdict"]),
           "param_rel_kept": 0.0, "param_rel_all": 0.0, "worst_param": "", "cv_improvement_abs": 0.0}
    for k in eb.keys() & ea.keys():
        b, a = eb[k], ea[k]
        out["cv_improvement_abs"] = max(out["cv_improvement_abs"], abs(a["cv_improvement"] - b["cv_improvement"]))
        for p in b["params"].keys() & a["params"].keys():
            r = _rel(a["params"][p], b["params"][p])
            if r > out["param_rel_all"]:
                out["param_rel_all"], out["worst_param"] = r, f"{k}.{p}: {b['params'][p]:.6g} -> {a['params'][p]:.6g}"
            if b["verdict"] in ("confirmed", "likely"):
                out["param_rel_kept"] = max(out["param_rel_kept"], r)
    cl_b = before["after"].get("closed_loop_heldout") or {}
    cl_a = after["after"].get("closed_loop_heldout") or {}
    out["closed_loop_rel"] = max((_rel(cl_a[k], cl_b[k]) for k in cl_b.keys() & cl_a.keys()
                                  if isinstance(cl_b[k], (int, float)) and isinstance(cl_a[k], (int, float))),
                                 default=0.0)
    out["same"] = (out["accepted_same"] and out["likely_same"] and out["effects_same"] and not out["verdicts_differ"]
                   and out["param_rel_kept"] <= 1e-3)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flight", nargs="?", default=str(DEMO), help="PX4 ULog (default: the shipped demo flight)")
    ap.add_argument("--params", help="nominal params YAML (default: the demo's for the demo flight, else as "
                                     "`rotortwin discover` chooses)")
    ap.add_argument("--repeat", type=int, default=1, help="alternate before/after this many times, keep the best")
    ap.add_argument("--no-warmup", action="store_true", help="skip the untimed warm-up run")
    ap.add_argument("--no-closed-loop", action="store_true", help="skip the closed-loop twin metrics")
    ap.add_argument("--target", type=float, default=3.0, help="s per flight-minute for --strict (default 3)")
    ap.add_argument("--strict", action="store_true", help="exit 1 if the results differ or the target is missed")
    ap.add_argument("--json", help="write the timings and the comparison here")
    a = ap.parse_args(argv)
    if SMOKE and a.flight == str(DEMO):
        a.flight, a.params, a.no_warmup, a.no_closed_loop = str(tiny_flight()), a.params or str(SIH), True, True

    from twin_nodes.discovery import evaluate
    from twin_nodes.discovery.discover import discover
    from twin_nodes.discovery.report import json_default
    from twin_nodes.identify.nominal import params_for_log
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.vehicle.params import load_params

    params = a.params or (str(DEMO_PARAMS) if Path(a.flight).resolve() == DEMO.resolve() else None)
    params_file, note = params_for_log(a.flight, params)
    if note:
        print(f"bench_discover: {note}", file=sys.stderr)
    vp = load_params(params_file)
    log = read_ulog(a.flight)
    minutes = log.duration_s / 60.0
    kw = {"closed_loop_metrics": not a.no_closed_loop}

    def run_after():
        return json.loads(json.dumps(_strip(discover(log, vp, **kw)), default=json_default))

    def run_before():
        with discover_before.before():
            return json.loads(json.dumps(_strip(discover(log, vp, **kw)), default=json_default))

    if not a.no_warmup:
        timed(run_after)
    best = {"before": None, "after": None}
    results = {}
    for _ in range(max(a.repeat, 1)):
        for side, fn in (("before", run_before), ("after", run_after)):
            res, wall, cpu = timed(fn)
            results[side] = res
            if best[side] is None or wall < best[side][0]:
                best[side] = (wall, cpu)
    cmp = compare(results["before"], results["after"])
    wb, cb = best["before"]
    wa, ca = best["after"]
    print(f"flight: {a.flight} ({log.duration_s:.1f} s = {minutes:.2f} flight-minutes), workers: {evaluate.workers()}")
    print(f"{'':8s} {'wall s':>8s} {'cpu s':>8s} {'s/flight-min':>13s}")
    print(f"{'before':8s} {wb:8.2f} {cb:8.2f} {wb / minutes:13.2f}")
    print(f"{'after':8s} {wa:8.2f} {ca:8.2f} {wa / minutes:13.2f}")
    print(f"ratio before/after: wall {wb / wa:.2f}x, cpu {cb / ca:.2f}x")
    print(f"same result: {cmp['same']}  (accepted {results['after']['accepted']}, verdicts differ: "
          f"{cmp['verdicts_differ'] or 'none'}, largest parameter change {cmp['param_rel_kept']:.2e} on "
          f"confirmed/likely effects, {cmp['param_rel_all']:.2e} on all [{cmp['worst_param']}], "
          f"closed-loop metrics {cmp['closed_loop_rel']:.2e})")
    if a.json:
        Path(a.json).write_text(json.dumps({"flight": a.flight, "flight_minutes": minutes, "workers": evaluate.workers(),
                                            "before": {"wall_s": wb, "cpu_s": cb}, "after": {"wall_s": wa, "cpu_s": ca},
                                            "comparison": cmp, "result_before": results["before"],
                                            "result_after": results["after"]}, indent=1))
    if a.strict and (not cmp["same"] or wa / minutes > a.target):
        print(f"strict: {'results differ' if not cmp['same'] else ''} "
              f"{'target missed' if wa / minutes > a.target else ''}".strip(), file=sys.stderr)
        return 1
    return 0


def _strip(res: dict) -> dict:
    res = dict(res)
    res.pop("_series", None)
    res.pop("elapsed_s", None)
    return res


if __name__ == "__main__":
    sys.exit(main())
