"""Why a vehicle twin misses a flight its own nominal flies (issue 25): the gap taken apart value by value.

    python tools/vehicle_twin_gap.py FLIGHTS_OR_DIRS... [--seed 25 | --split date] [--pool latest|all]
                                     [--twin vehicle_twin.yaml] [--out DIR]

The same split as ``tools/vehicle_twin_prediction.py`` (declared before anything is fitted); the twin is built on the
build half (or read from ``--twin``).  For each predict flight, one group of values (:data:`GROUPS`) of the flight's
own nominal is put into the twin (as :func:`~twin_nodes.fleet.vehicle_twin.for_flight` flies it) **alone**, and the
whole flight flown closed loop.  The own nominal is fitted on the flight's own motor outputs: the swaps measure what
each value costs, they are no prediction.  Prints one markdown row per flight (throttle RMSE % / per-motor P75 max %)
and writes ``DIR/gap.json``.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

#: group -> (params paths "section.key" or "section", effect names): what is swapped together
GROUPS = {
    "thrust + sag": (["rotors.thrust_max_n", "rotors.thr_mdl_fac"], ["battery_sag"]),
    "CoM": ([], ["com_offset"]),
    "yaw trim": ([], ["rotor_tilt"]),
    "inertia": (["vehicle.ixx_kg_m2", "vehicle.iyy_kg_m2", "vehicle.izz_kg_m2"], []),
    "lag": (["rotors.tau_up_s", "rotors.tau_down_s"], []),
    "wind": ([], ["wind"]),
    "drag": (["rotors.z_flu_m"], ["rotor_drag", "body_drag", "linear_drag", "angular_damping"]),
    "controller": (["controller"], []),
}


def swap(into: dict, src: dict, keys: list[str], effects: list[str]) -> dict:
    """A copy of the params dict ``into`` with ``keys`` ("section" or "section.key") and the effects ``effects``
    (present or absent, enabled or not) taken from ``src``."""
    d = copy.deepcopy(into)
    for k in keys:
        sec, _, key = k.partition(".")
        if key:
            d[sec][key] = copy.deepcopy(src[sec][key])
        else:
            d[sec] = copy.deepcopy(src[sec])
    enabled = [e for e in d["effects"]["enabled"] if e not in effects]
    for e in effects:
        d["effects"].pop(e, None)
        if e in src["effects"]["enabled"]:
            enabled.append(e)
            d["effects"][e] = copy.deepcopy(src["effects"][e])
    d["effects"]["enabled"] = enabled
    return d


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", nargs="+")
    ap.add_argument("--seed", type=int, default=25)
    ap.add_argument("--split", choices=("seed", "date"), default="seed")
    ap.add_argument("--pool", choices=("latest", "all"), default="latest")
    ap.add_argument("--twin", help="a vehicle twin params file to take apart instead of building one")
    ap.add_argument("--out", default="out/vehicle_twin_gap")
    a = ap.parse_args(argv)
    from vehicle_twin_prediction import _metrics, split_free

    from twin_nodes.fleet.vehicle_twin import build, for_flight, read_vehicle_facts
    from twin_nodes.identify.nominal import params_for_log
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.twin.compare import compare_log
    from twin_nodes.vehicle.params import from_ros_dict, load_params, write_params

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    build_set, predict_set = split_free(a.flights, a.split, a.seed)
    twin = Path(a.twin) if a.twin else out / "vehicle_twin.yaml"
    if not a.twin:
        vt = build(build_set, state=a.pool)
        write_params(vt.params, twin, vt.header)
    ref, vp = read_vehicle_facts(twin), load_params(twin)

    def fly(log, d):
        return _metrics(compare_log(log, from_ros_dict(d, "<swapped>"), mode="closed").metrics)

    def cell(m):
        return f"{100 * m['throttle_rmse']:.1f} / {100 * m['motor_p75_max']:.1f}"

    print("| flight | twin | own nominal | " + " | ".join(GROUPS) + " | all but the controller |")
    print("|---" * (len(GROUPS) + 4) + "|")
    rows = []
    for p in predict_set:
        log = read_ulog(p)
        dt = for_flight(vp, ref, log)[0].to_ros_dict()
        do = load_params(params_for_log(p, None, log=log)[0]).to_ros_dict()
        r = {"flight": p, "twin": fly(log, dt), "own_nominal": fly(log, do),
             "swapped": {g: fly(log, swap(dt, do, k, e)) for g, (k, e) in GROUPS.items()}}
        rest = [(k, e) for g, (k, e) in GROUPS.items() if g != "controller"]
        r["swapped"]["all but the controller"] = fly(log, swap(dt, do, sum((k for k, _ in rest), []),
                                                                sum((e for _, e in rest), [])))
        rows.append(r)
        print(f"| {Path(p).parent.name}/{Path(p).name} | {cell(r['twin'])} | {cell(r['own_nominal'])} | "
              + " | ".join(cell(m) for m in r["swapped"].values()) + " |", flush=True)
    (out / "gap.json").write_text(json.dumps({"split": a.split, "seed": a.seed, "twin": str(twin), "build": build_set,
                                              "predict": predict_set, "rows": rows}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
