"""Cross-flight prediction (issue 25): a vehicle twin built from some flights of one vehicle flies its other
flights whole, closed loop, beside each flight's own nominal.

    python tools/vehicle_twin_prediction.py FLIGHTS_OR_DIRS... [--seed 25 | --split date] [--pool latest|all]
        [--twins per-configuration|one] [--out DIR]

The free flights (:func:`twin_nodes.fleet.facts.flight_kind`) are split by ``--seed`` (or by date) into a build half and a
predict half *before* anything is fitted; one twin is pooled per motor configuration of the build half
(:func:`twin_nodes.fleet.vehicle_twin.from_flights`), then every predict flight is flown by the twin of its
configuration, else of its wiring, else the ``--pool`` one (rescaled to the flight's motor PWM range, without
the yaw trim across a rewiring, :func:`~twin_nodes.fleet.vehicle_twin.for_flight`) and by its own nominal
(:func:`twin_nodes.identify.nominal.params_for_log`).  Prints one markdown row per predict flight, as it came
out, and writes ``DIR/vehicle_twin.yaml`` and ``DIR/prediction.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: the issue's bar per metric (whole flight, closed loop)
BAR = {"throttle_rmse": 0.04, "motor_p75_max": 0.06, "xy_rmse_m": 1.0, "z_rmse_m": 0.5}


def _metrics(m: dict) -> dict:
    p75 = [v for v in m.get("motor_p75", []) if isinstance(v, float) and math.isfinite(v)]
    return {"throttle_rmse": m.get("throttle_rmse", math.nan), "motor_p75_max": max(p75) if p75 else math.nan,
            "xy_rmse_m": m.get("xy_rmse_m", math.nan), "z_rmse_m": m.get("z_rmse_m", math.nan)}


def _divergence(m: dict) -> str:
    """The twin's divergence from the flight (time and cause), '' when none: a twin that left the flight's envelope
    is said beside its numbers, never passed off as a plain prediction."""
    d = m.get("divergence")
    return f"diverged: {d.get('cause')} at {float(d.get('t_s', math.nan)):.1f} s" if d else ""


def split_free(flights: list[str], split: str, seed: int) -> tuple[list[str], list[str]]:
    """The free flights among ``flights`` split into (build, predict) halves by ``seed`` or by date, before anything
    is fitted; prints one line on the split."""
    from twin_nodes.fleet.facts import actuator_tests, flight_kind
    from twin_nodes.fleet.run import find_flights
    from twin_nodes.logs.ulog_io import read_ulog

    free = [p for p in sorted(map(str, find_flights(flights)))
            if flight_kind(read_ulog(p), actuator_tests(p))[0] == "free flight"]
    half = len(free) // 2
    if split == "date":
        from twin_nodes.fleet.vehicle_twin import date_flights

        rows = [{"path": p} for p in free]
        date_flights(rows)
        order = [r["path"] for r in sorted(rows, key=lambda r: (r["when"] or "", r["path"]))]
        build_set, predict_set = order[:half], order[half:]
        how = f"by date (build up to {Path(build_set[-1]).name})"
    else:
        perm = np.random.default_rng(seed).permutation(len(free))
        build_set = sorted(free[i] for i in perm[:half])
        predict_set = sorted(free[i] for i in perm[half:])
        how = f"seed {seed}"
    print(f"{len(free)} free flights; {how}: build {len(build_set)}, predict {len(predict_set)}")
    return build_set, predict_set


def _twins(flights: list[dict], left_out: list[str], pool: str, how: str, out: Path, write_params) -> list[tuple]:
    """The twins the predict half is flown with: [(params, facts, name)], the --pool twin first, then (per
    configuration) one per motor configuration of the build half; each written to ``out`` and read back."""
    from twin_nodes.fleet.vehicle_twin import configurations, from_flights, read_vehicle_facts
    from twin_nodes.vehicle.params import load_params

    made = [("vehicle_twin", from_flights(flights, left_out, state=pool))]
    if how == "per-configuration":
        for k, g in enumerate(configurations(sorted(flights, key=lambda f: (f.get("when") or "", f["path"])))):
            made.append((f"vehicle_twin_config{k + 1}", from_flights(flights, left_out, like=g[-1]["pwm"])))
    res = []
    for name, vt in made:
        path = out / f"{name}.yaml"
        write_params(vt.params, path, vt.header)
        print(f"twin {name}: {vt.pwm['text']}: {len(vt.used)} flights ({', '.join(Path(u).name for u in vt.used)})")
        res.append((load_params(path), read_vehicle_facts(path), name))
    return res


def _twin_for(twins: list[tuple], log) -> tuple:
    """The twin of the log's configuration, else of its wiring (the latest such), else the --pool twin."""
    from twin_nodes.fleet.facts import motor_pwm, same_configuration
    from twin_nodes.fleet.vehicle_twin import shares_outputs

    pwm = motor_pwm(log.params, int(log.n_motors))
    for vp, ref, name in twins[1:]:
        if same_configuration(ref["pwm"], pwm)[0]:
            return vp, ref, f"{name} (its configuration)"
    for vp, ref, name in reversed(twins[1:]):
        if shares_outputs(ref["pwm"], pwm):
            return vp, ref, f"{name} (its wiring)"
    vp, ref, name = twins[0]
    return vp, ref, name if len(twins) > 1 else ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", nargs="+")
    ap.add_argument("--seed", type=int, default=25)
    ap.add_argument("--split", choices=("seed", "date"), default="seed",
                    help="seed: build and predict halves drawn by --seed; date: build on the earlier half by date, "
                         "predict the later half (the twin of last week predicts today)")
    ap.add_argument("--pool", choices=("latest", "all"), default="latest",
                    help="the vehicle twin as it last flew in the build half (default) or the majority's motor configuration")
    ap.add_argument("--twins", choices=("per-configuration", "one"), default="per-configuration",
                    help="per-configuration (default): one twin per motor configuration of the build half (which "
                         "outputs drive the motors and their PWM limits); each predict flight is flown by the twin of "
                         "its configuration, else of its wiring (PWM rescaled), else the --pool twin (rescaled, no yaw "
                         "trim); one: the --pool twin flies every flight (the earlier behaviour)")
    ap.add_argument("--out", default="out/vehicle_twin")
    a = ap.parse_args(argv)
    from twin_nodes.identify.nominal import params_for_log
    from twin_nodes.fleet.vehicle_twin import for_flight, read_flights
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.twin.compare import compare_log
    from twin_nodes.vehicle.params import load_params, write_params

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    build_set, predict_set = split_free(a.flights, a.split, a.seed)
    flights, left_out = read_flights(build_set)
    twins = _twins(flights, left_out, a.pool, a.twins, out, write_params)
    rows = []
    print("| flight | twin: throttle RMSE | motor P75 (max) | XY RMSE m | Z RMSE m | own nominal: throttle | "
          "motor P75 | XY | Z | note |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for p in predict_set:
        log = read_ulog(p)
        t0 = time.time()
        try:
            vp, ref, which = _twin_for(twins, log)
            v, note = for_flight(vp, ref, log)
            note = "; ".join(x for x in (which, note) if x)
            full_t = compare_log(log, v, mode="closed").metrics
            mt = _metrics(full_t)
            own, _ = params_for_log(p, None, log=log)
            full_o = compare_log(log, load_params(own), mode="closed").metrics
            mo = _metrics(full_o)
            div = "; ".join(f"{who} {d}" for who, d in (("twin", _divergence(full_t)),
                                                          ("own nominal", _divergence(full_o))) if d)
            note = "; ".join(x for x in (note, div) if x)
            err = ""
        except Exception as exc:  # one flight's failure is a row, the others go on
            mt, mo, note, err = {k: math.nan for k in BAR}, {k: math.nan for k in BAR}, "", f"{type(exc).__name__}: {exc}"
        row = {"flight": p, "twin": mt, "own_nominal": mo, "note": note, "error": err, "wall_s": time.time() - t0,
               "passes": {k: bool(mt[k] <= BAR[k]) for k in BAR}}
        rows.append(row)
        f = lambda d, k, s=100: f"{d[k] * s:.1f}" if math.isfinite(d[k]) else "n/a"  # noqa: E731
        print(f"| {Path(p).parent.name}/{Path(p).name} | {f(mt, 'throttle_rmse')} % | {f(mt, 'motor_p75_max')} % | "
              f"{f(mt, 'xy_rmse_m', 1)} | {f(mt, 'z_rmse_m', 1)} | {f(mo, 'throttle_rmse')} % | "
              f"{f(mo, 'motor_p75_max')} % | {f(mo, 'xy_rmse_m', 1)} | {f(mo, 'z_rmse_m', 1)} | {note or err} |",
              flush=True)
    n = len(rows)
    summary = {k: sum(r["passes"][k] for r in rows) for k in BAR}
    print("passing the bar (of " + str(n) + "): " + ", ".join(f"{k} <= {v:g}: {summary[k]}" for k, v in BAR.items()))
    (out / "prediction.json").write_text(json.dumps({"seed": a.seed, "split": a.split, "pool": a.pool, "build": build_set, "predict": predict_set,
                                                     "rows": rows, "passing": summary, "bar": BAR},
                                                    indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
