"""``rotortwin survey``: many flights through the whole job, one row each.

::

    rotortwin survey FLIGHT.ulg|DIR ... [--params P.yaml] [--md OUT.md] [--json OUT.json]

For each flight: params as ``discover`` resolves them (given, shipped for the airframe, or the
nominal built from the log), discovery with its physical and closed-loop guards, and the
closed-loop twin's Table-2 metrics on the held-out last 35 % before and after the refit, beside
the reference paper's Table 2; per flight also the axes PX4 controlled there (seconds), the real
throttle's own content above 0.5 Hz (the floor a still-air twin cannot follow: the throttle target is
the larger of 3 % and 1.25x it), and a divergence of the twin (cause and time).  A flight with no
flight in it (never airborne, never left the ground, too short) is a "left out" row with the reason;
one without GPS is flown on the nominal and scored on Z, throttle and motors; a flight that fails is
a row with its one-line error (exit 1); the rest go on.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from twin_nodes.base.errors import TwinError
from twin_nodes.base.io import atomic_write_text
from twin_nodes.cli.paths import declare


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("survey", help="discover on many flights; closed-loop held-out table per flight",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    io = declare(p)
    io.input("flights", nargs="+", help="PX4 ULogs or folders of them")
    io.input("--params", help="one params YAML for every flight (default: resolved per flight)")
    io.output("--md", help="write the markdown table here")
    io.output("--json", dest="json_out", help="write the rows here")
    p.set_defaults(func=_cmd_survey)


def _flights(args: list[str]) -> list[Path]:
    out = []
    for a in args:
        p = Path(a)
        if p.is_dir():
            out += sorted(p.glob("*.ulg"))
        elif p.is_file():
            out.append(p)
        else:
            raise TwinError(f"{a}: not a file or folder")
    if not out:
        raise TwinError(f"{' '.join(args)}: no .ulg files")
    return out


def _cmd_survey(args: argparse.Namespace) -> int:
    from twin_nodes.discovery.survey import markdown_table, survey_rows
    from twin_nodes.twin.metrics import to_jsonable

    rows = survey_rows(_flights(args.flights), args.params, progress=sys.stderr.isatty())
    failed = [r["error"] for r in rows if r.get("status") == "failed"]
    left_out = [r["error"] for r in rows if r.get("status") == "left_out"]
    for why in left_out:
        print(f"rotortwin: left out: {why}", file=sys.stderr)
    for why in failed:
        print(f"rotortwin: {why}", file=sys.stderr)
    if failed:
        print(f"rotortwin: {len(failed)} of {len(rows)} flights failed (each is a row of the table with its reason)",
              file=sys.stderr)
    table = markdown_table(rows)
    from twin_nodes.fleet.vehicle_twin import beside_own_nominal, beside_table, read_vehicle_facts

    if args.params and read_vehicle_facts(args.params) is not None:  # a vehicle twin: beside each own nominal
        for r in rows:
            if r.get("status") == "ok":
                try:
                    r["whole_flight"] = beside_own_nominal(r["path"], args.params)
                except TwinError as exc:
                    r["whole_flight"] = {"error": str(exc)}
        table += "\n\nWhole flight, closed loop: the vehicle twin beside each flight's own nominal\n\n" + \
            beside_table(rows)
    print(table)
    if args.md:
        atomic_write_text(args.md, table + "\n")
    if args.json_out:
        atomic_write_text(args.json_out, json.dumps(to_jsonable({"rows": rows, "failed": failed, "left_out": left_out}),
                                                    indent=1))
    return 1 if failed else 0
