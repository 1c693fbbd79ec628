"""``rotortwin fleet``: discovery over a fleet's flights on Dask, the flight catalog, the fleet report.

::

    rotortwin fleet discover|compare LOGS_OR_DIRS... --catalog DIR [--scheduler ADDRESS]
                   [--params P.yaml | --params-map MAP.yaml] [--workers N] [--no-closed-loop]
    rotortwin fleet query CATALOG "SELECT ... FROM flights ..."
    rotortwin fleet report CATALOG --out DIR
    rotortwin fleet simulate OUT_DIR [--vehicles 5] [--flights 10] [--workers N]
    rotortwin fleet warm

``warm`` compiles the generated numba code a fleet flight runs into the per-user code cache
(``$ROTORTWIN_CODE_CACHE``, else ``~/.cache/rotortwin/numba``); ``make setup`` runs it, so that a run
after installing loads that code instead of compiling it.

``discover``/``compare`` run one Dask task per flight (an embedded LocalCluster of N one-thread
worker processes, or the scheduler at ADDRESS); flights with an ok row for the same file content
are skipped, failed ones are retried (exit 1 while any still fail); identical files count once (the
duplicate is named); a failed flight is a catalog row with its vehicle, date and one-line error.
"""

from __future__ import annotations

import argparse
import sys

from twin_nodes.base.outputs import shown
from twin_nodes.cli.paths import declare
from twin_nodes.cli.options import WORKERS, positive_int


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("fleet", help="fleet scale: discovery on Dask, flight catalog, trends report",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="fleet_command", metavar="FLEET_COMMAND")
    for mode in ("discover", "compare"):
        q = sub.add_parser(mode, help=f"{mode} every flight into the catalog (one Dask task each)")
        io = declare(q)
        io.input("flights", nargs="+", help="PX4 ULogs or folders of them (searched recursively)")
        io.output("--catalog", kind="update", required=True,
                  help="catalog folder (one Parquet file per flight; an existing one is resumed)")
        q.add_argument("--scheduler", help="a running Dask scheduler (tcp://host:8786); default: embedded cluster")
        g = q.add_mutually_exclusive_group()
        io.input("--params", group=g, help="one params YAML for every flight")
        io.input("--params-map", group=g, help="YAML: vehicle id -> params file (others: built from the log)")
        q.add_argument("--workers", type=WORKERS, default=2, help="embedded cluster worker processes (default 2)")
        q.add_argument("--no-closed-loop", action="store_true",
                       help="discover: skip the closed-loop Table-2 metrics (faster)")
        q.set_defaults(func=_cmd_run, mode=mode)
    q = sub.add_parser("query", help="SQL on the catalog with DuckDB (the table is `flights`)")
    declare(q).input("catalog", help="catalog folder")
    q.add_argument("sql", help="the query, e.g. 'SELECT vehicle_id, count(*) FROM flights GROUP BY 1'")
    q.set_defaults(func=_cmd_query)
    q = sub.add_parser("report", help="per-vehicle trends, alarms, HTML with plots")
    io = declare(q)
    io.input("catalog", help="catalog folder")
    io.output("--out", kind="dir", required=True, help="report folder (index.html, report.json, PNGs)")
    q.set_defaults(func=_cmd_report)
    q = sub.add_parser("simulate", help="write the simulated demo fleet (degrading motor, payload days, healthy)")
    io = declare(q)
    io.output("out", kind="dir", help="folder for the simulated flights")
    io.input("--params", default="params/px4_sih_quadx.yaml", help="vehicle params YAML")
    q.add_argument("--vehicles", type=positive_int(1000), default=5)
    q.add_argument("--flights", type=positive_int(10000), default=10, help="flights per vehicle")
    q.add_argument("--workers", type=WORKERS, default=2)
    q.set_defaults(func=_cmd_simulate)
    q = sub.add_parser("warm", help="compile the fleet's generated numba code into the per-user code cache "
                       "(make setup runs it)")
    q.set_defaults(func=_cmd_warm)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])


def _cmd_run(args: argparse.Namespace) -> int:
    from twin_nodes.fleet.run import find_flights, load_params_map, run_fleet

    flights = find_flights(args.flights)
    pmap = load_params_map(args.params_map)
    res = run_fleet(flights, args.catalog, mode=args.mode, scheduler=args.scheduler, workers=args.workers,
                    params=args.params, params_map=pmap, closed_loop_metrics=not args.no_closed_loop)
    failed = [d for d in res["done"] if d["status"] not in ("ok", "not_flight")]
    nf = [d for d in res["done"] if d["status"] == "not_flight"]
    for d in nf:
        print(f"not a flight ({d.get('flight_kind') or '?'}): {d['error']}")
    for d in res["done"]:
        if d.get("discover_error"):
            print(f"values identified, {args.mode} refused: {d['discover_error']}")
    for d in failed:
        print(f"rotortwin: {d['error']}", file=sys.stderr)
    for d in res["lost"]:
        print(f"rotortwin: {d['path']}: not finished ({d['error']}); rerun to complete the catalog", file=sys.stderr)
    for d in res["duplicates"]:
        print(f"duplicate: {d['path']}: same content as {d['same_as']} (counted once)")
    kinds = {}
    for d in nf:
        kinds[d.get("flight_kind") or "?"] = kinds.get(d.get("flight_kind") or "?", 0) + 1
    print(f"fleet {args.mode}: {len(flights)} flights: {len(res['done']) - len(failed) - len(nf)} done, "
          f"{len(nf)} no free flight ({', '.join(f'{k} {v}' for k, v in sorted(kinds.items())) or 'none'}), "
          f"{len(failed)} failed, "
          f"{len(res['lost'])} not finished, {len(res['duplicates'])} duplicate(s), "
          f"{res['skipped']} already in {args.catalog}")
    if failed or res["lost"]:
        print(f"rotortwin: {len(failed)} flight(s) still failed, {len(res['lost'])} not finished (reasons above; "
              "failed ones are catalog rows with status failed); a rerun retries them", file=sys.stderr)
        return 1
    return 0


def _cmd_query(args: argparse.Namespace) -> int:
    from twin_nodes.fleet.catalog import query

    cols, rows = query(args.catalog, args.sql)
    print("\t".join(cols))
    for r in rows:
        print("\t".join("" if v is None else str(v) for v in r))
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from twin_nodes.fleet.report import write_report

    s = write_report(args.catalog, args.out)
    print(f"{s['flights']} flights, {len(s['vehicles'])} vehicles, {len(s['not_flights'])} no free flight, "
          f"{len(s['failed'])} failed, "
          f"{len(s['duplicates'])} duplicate(s), {len(s['corrupt_files'])} corrupt row file(s)")
    for f in s["failed"]:
        why = f["error"][len(f["path"]) + 2:] if f["error"].startswith(f"{f['path']}: ") else f["error"]
        print(f"FAILED {f['path']} [{f['vehicle_id']}, {f['date']}]: {why}")
    for f in s["not_flights"]:
        why = f["reason"][len(f["path"]) + 2:] if f["reason"].startswith(f"{f['path']}: ") else f["reason"]
        print(f"NO FREE FLIGHT {f['path']} [{f['vehicle_id']}, {f['date']}] ({f['kind']}): {why}")
    for d in s["duplicates"]:
        print(f"DUPLICATE {d['path']}: same content as {d['same_as']} (counted once)")
    for c in s["corrupt_files"]:
        print(f"CORRUPT {c['file']}: {c['error']} (skipped)")
    for a in s["alarms"]:
        print(f"ALARM {a['vehicle_id']} [{a['kind']}] {a['message']}")
    if not s["alarms"]:
        print("no alarms")
    print(f"report: {shown(args.out)}/index.html")
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from twin_nodes.fleet.simfleet import plan, write_fleet
    from twin_nodes.vehicle.params import load_params

    fl = plan(args.vehicles, args.flights, nominal_mass_kg=load_params(args.params).mass_kg)
    paths = write_fleet(args.out, fl, args.params, workers=args.workers)
    for f in fl:
        if f.effect != "none":
            print(f"{f.name}: {f.effect} {dict(f.params)}")
    print(f"simulated {len(paths)} flights into {shown(args.out)}")
    return 0


def _cmd_warm(args: argparse.Namespace) -> int:
    import time

    from twin_nodes.fleet.flight import warm_installed
    from twin_nodes.physics.codecache import code_dir

    t0 = time.perf_counter()
    names = warm_installed()
    d = code_dir()
    where = "not cached (no usable code cache folder)" if d is None else f"{d[0]}{'' if d[1] else ' (read-only)'}"
    print(f"compiled code of {', '.join(names)}: {where} ({time.perf_counter() - t0:.1f} s)")
    return 0
