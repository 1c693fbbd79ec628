"""``rotortwin discover``, ``rotortwin finding``, ``rotortwin prove`` and ``rotortwin simulate``."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from twin_nodes.base.io import atomic_write_text
from twin_nodes.base.outputs import shown
from twin_nodes.cli.paths import declare
from twin_nodes.cli.options import WORKERS, finite_float, seed
from twin_nodes.discovery.report import json_default, summary_text, write_report
from twin_nodes.prove.grid_sih import HALVES


def register(sub) -> None:
    p = sub.add_parser("discover", help="locate the twin/real mismatch, name the missing physics, refit, "
                                        "show the held-out improvement")
    io = declare(p)
    io.input("flight", help="PX4 ULog (.ulg)")
    io.input("--params", help="nominal vehicle params YAML (default: the shipped file for the log's "
                              "airframe, else the nominal built from the log itself)")
    io.output("--json", dest="json_out", help="write the result here")
    io.output("--report", kind="dir", help="write plots and index.html into this folder")
    io.output("--out-params", help="write the refitted params YAML here (when something is accepted)")
    p.add_argument("--heldout", type=finite_float(0.05, 0.95), default=0.35,
                   help="fraction of the flight held out, 0.05..0.95 (default 0.35)")
    p.add_argument("--no-closed-loop", action="store_true", help="skip the closed-loop twin before/after metrics")
    io.output("--plan-dir", kind="dir", help="write a confirmation mission plan per 'likely' effect into this folder")
    io.input("--confirm", metavar="FOLLOWUP", help="re-judge each 'likely' effect of FLIGHT on this follow-up "
                                                         "flight (flown with the confirmation plan): confirm or drop")
    p.set_defaults(func=_discover)

    f = sub.add_parser("finding", help="the finding of a 'discover --json' result in one line: effect, "
                                       "parameters, verdict, held-out throttle RMSE before -> after")
    declare(f).input("result", metavar="DISCOVER_JSON", help="the JSON written by 'rotortwin discover --json'")
    f.set_defaults(func=_finding)

    q = sub.add_parser("prove", help="flights with one known effect each (ours, PX4 SIH, RotorPy), discovered "
                                     "blind and scored per source")
    q.add_argument("--source", choices=("ours", "px4sih", "rotorpy", "oov", "all"), default="ours",
                   help="ours: our generator; px4sih: the PX4 SIH flights in ../shared (see "
                        "missions/sih_effects/manifest.yaml); rotorpy: RotorPy flights (cached); all: the three; "
                        "oov: physics outside the effect list (twin_nodes/prove/oov_manifest.yaml; ours and "
                        "RotorPy, cached beside --cache in oov/), scored on term discovery")
    qio = declare(q)
    qio.output("--out", kind="update", default="out/prove",
               help="folder for the results and tables (one subfolder per source; kept and updated across runs)")
    qio.input("--vehicle", default="px4_sih_quadx", help="ours: shipped params name or a params YAML")
    q.add_argument("--size", choices=("full", "ci"), default="full")
    q.add_argument("--workers", type=WORKERS, default=min(2, os.cpu_count() or 1))
    qio.input("--shared", help="px4sih: the shared folder (default ../shared beside the repository)")
    qio.input("--sih-dir", action="append", default=[], metavar="DIR",
                   help="px4sih: also these flights of our own (DIR/<name>/flight.ulg + truth.json, as "
                        "launch_scripts/fly_sih.sh writes them); repeatable")
    qio.output("--cache", kind="update", default="out/cache/rotorpy",
               help="rotorpy: where the simulated flights are kept (reused across runs)")
    q.add_argument("--grid", choices=("rotorpy", "px4sih"),
                   help="issue 26's declared grid of that source instead of --source (twin_nodes/prove/grids/"
                        "rotorpy_grid.yaml, missions/sih_grid/manifest.yaml), flights read from --grid-cache")
    q.add_argument("--half", choices=HALVES, default="tuning",
                   help="--grid: the half declared in the manifest (default tuning); judgeN: the Nth, judging-only "
                        "batch (rotorpy_grid_batchN.yaml, missions/sih_grid/batchN.yaml)")
    qio.input("--grid-cache", default=str(Path.home() / ".cache" / "rotortwin" / "grids"),
              help="--grid: where tools/fly_grids.sh put the flights (rotorpy/<id>.ulg, sih/<id>/flight.ulg)")
    q.set_defaults(func=_prove)

    s = sub.add_parser("simulate", help="fly the shipped mission with our simulator (optionally with a hidden "
                                        "effect) and write it as a PX4 ULog")
    sio = declare(s)
    sio.input("--params", default="params/px4_sih_quadx.yaml", help="vehicle params YAML")
    s.add_argument("--effect", default="none",
                   help="hidden effect, e.g. 'motor_efficiency:motor=3,efficiency=0.85' (default none)")
    s.add_argument("--seed", type=seed(), default=1)
    sio.input("--plan", help="fly this mission plan (missions/*.plan.yaml format) instead of the built-in mission")
    sio.output("--out", required=True, help="output .ulg")
    s.set_defaults(func=_simulate)


def _discover(args) -> int:
    from twin_nodes.discovery.discover import discover
    from twin_nodes.identify.nominal import params_for_log
    from twin_nodes.logs.flyable import read_flight  # too short, never airborne, no GPS: one line
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.vehicle.params import load_params, write_params

    vp = load_params(args.params) if args.params else None  # a bad params file is named before the log
    log = read_flight(args.flight)
    params_file, note = params_for_log(args.flight, args.params, log=log)  # the log loaded once
    if note:
        print(f"rotortwin: {note}", file=sys.stderr)
    vp = vp or load_params(params_file)
    res = discover(log, vp, heldout_fraction=args.heldout, progress=sys.stderr.isatty(),
                   closed_loop_metrics=not args.no_closed_loop)
    series = res.pop("_series")
    if args.confirm:
        from twin_nodes.discovery.confirm import confirm
        res["confirmation"] = confirm(res, read_ulog(args.confirm), vp)
    print(summary_text(res))
    print(finding_line(res))
    from twin_nodes.fleet.vehicle_twin import read_vehicle_facts, since_twin

    ref = read_vehicle_facts(params_file)
    if ref is not None:  # a vehicle twin: name what differs on this flight
        res["since_vehicle_twin"] = since_twin(log, args.flight, ref)
        sv = res["since_vehicle_twin"]
        print(f"since the vehicle twin ({len(ref.get('flights') or [])} flights): {sv['name']}: {sv['why']}")
        for v, d in sv["differs"].items():
            print(f"  {v}: flight {d['flight']:.4g}, twin {d['twin']:.4g} (band ± {d['band']:.2g})")
    if args.plan_dir:
        from twin_nodes.discovery.plans import write_plans
        for path in write_plans(res, args.plan_dir, args.flight):
            print(f"confirmation plan: {shown(path)}")
    if args.json_out:
        atomic_write_text(args.json_out, json.dumps(res, indent=1, default=json_default))
    if args.report:
        write_report(args.report, res, series)
        print(f"report: {shown(Path(args.report) / 'index.html')}")
    if args.out_params and res["accepted"]:
        from twin_nodes.vehicle.params import from_ros_dict
        new = from_ros_dict(res["refit_params"], args.out_params)
        write_params(new, args.out_params, header=f"refitted by rotortwin discover on {args.flight}: "
                                                   f"added {', '.join(res['accepted'])}")
    return 0


def finding_line(res: dict) -> str:
    """One line: each confirmed or likely effect with its parameters and verdict, then the closed-loop
    twin's held-out throttle RMSE before -> after the refit (when discover flew it)."""
    def pretty(params: dict) -> str:
        return ", ".join(f"{k} {int(v)}" if k == "motor" else f"{k} {v:.4g}" for k, v in params.items())
    found = [e for e in res["effects"] if e.get("verdict") in ("confirmed", "likely")]
    text = "; ".join(f"{e['name']} ({pretty(e.get('params') or {})}), {e['verdict']}" for e in found) \
        or "no missing physics found"
    before = ((res.get("baseline") or {}).get("closed_loop_heldout") or {}).get("throttle_rmse")
    after = ((res.get("after") or {}).get("closed_loop_heldout") or {}).get("throttle_rmse")
    if before is not None and after is not None:
        text += f"; held-out throttle RMSE {100 * before:.2f} % -> {100 * after:.2f} %"
    elif before is not None:
        text += f"; held-out throttle RMSE {100 * before:.2f} %"
    return f"finding: {text}"


def _finding(args) -> int:
    from twin_nodes.base.errors import LogError

    try:
        res = json.loads(Path(args.result).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise LogError(args.result, "<file>", "file not found") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise LogError(args.result, "<file>", f"expected the JSON of 'rotortwin discover --json' ({exc})") from None
    if not isinstance(res, dict) or not isinstance(res.get("effects"), list) \
            or not all(isinstance(e, dict) and "name" in e for e in res["effects"]):
        raise LogError(args.result, "effects", "expected the JSON of 'rotortwin discover --json' (a list of effects)")
    print(finding_line(res))
    return 0


def _prove(args) -> int:
    from twin_nodes.prove.scoring import format_table, summary_line
    from twin_nodes.prove.sources import SOURCES, run_sources

    if args.grid:
        from twin_nodes.prove import grid_prove

        out = Path(args.out) / f"grid_{args.grid}_{args.half}"
        r = grid_prove.run(args.grid, args.half, out, Path(args.grid_cache))
        print(r["table"])
        print(f"per-flight results, table, summary: {out}/")
        return 0

    sources = SOURCES if args.source == "all" else (args.source,)
    out = Path(args.out)
    summaries = run_sources(sources, out, size=args.size, workers=args.workers, vehicle=args.vehicle,
                            shared=args.shared, cache=args.cache, sih_dirs=args.sih_dir)
    from twin_nodes.prove import oov

    tables = []
    for src, summary in summaries.items():
        table = oov.format_table(summary) if src == "oov" else format_table(summary)
        atomic_write_text(out / src / "summary.json", json.dumps(summary, indent=1, default=json_default))
        atomic_write_text(out / src / "table.txt", table + "\n")
        tables.append(f"== {src}\n{table}")
    text = "\n\n".join(tables + ["\n".join(oov.summary_line(s) if src == "oov" else summary_line(s)
                                            for src, s in summaries.items())])
    print(text)
    atomic_write_text(out / "tables.txt", text + "\n")
    atomic_write_text(out / "summary.json", json.dumps(summaries, indent=1, default=json_default))
    print(f"per-source flights, results, tables: {out}/<source>/; all tables: {out / 'tables.txt'}")
    return 0


def parse_effect(spec: str):
    """The ``--effect`` argument ('name:k=v,k=v') -> Hidden (grammar: physics.effects.parse_effect)."""
    from twin_nodes.twin.simflight import Hidden
    from twin_nodes.physics.effects import parse_effect as parse_spec

    return Hidden(*parse_spec(spec))


def _simulate(args) -> int:
    from twin_nodes.twin.simflight import write_flight
    from twin_nodes.vehicle.params import load_params

    vp = load_params(args.params)
    hidden = parse_effect(args.effect)
    if args.plan:
        from twin_nodes.discovery.plan_flight import write_plan_flight
        from twin_nodes.mavlink.mission import load_plan

        plan = load_plan(args.plan)
        wps = [(w.north_m, w.east_m, w.alt_m, w.speed_m_s, w.fly_through) for w in plan.waypoints]
        facts = write_plan_flight(args.out, vp, hidden, args.seed, wps, plan.rtl_after)
    else:
        facts = write_flight(args.out, vp, hidden, args.seed)
    print(f"{shown(args.out)}: {facts['duration_s']:.0f} s, hidden effect {hidden.name} {hidden.params}, "
          f"XY tracking RMSE {facts['xy_tracking_rmse_m']:.2f} m, Z {facts['z_tracking_rmse_m']:.2f} m")
    return 0
