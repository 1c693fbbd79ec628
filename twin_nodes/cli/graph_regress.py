"""``rotortwin regress``: fly a baseline recording with today's twin and fail if a metric got worse
(:func:`twin_nodes.graph.regress.regress_baseline`).

::

    rotortwin regress BASELINE_BAG [--params P.yaml] [--tolerance REL] [--abs-tolerance ABS]
                                   [--offline] [--update] [--json OUT.json] [--domain-id N]
    rotortwin regress BAG --self-check        (the stored metrics recompute from the bag's own topics)

The baseline is a bag recorded by ``rotortwin compare FLIGHT --mcap BAG``.  Its ``/real``
messages are replayed through today's twin (the node graph, or with ``--offline`` the same
twin and metrics code in one process) with the params recorded in the baseline
(``/twin/config``) unless ``--params`` is given, and every whole-flight metric (XY, Z,
throttle, each motor: RMSE, P75, median, max) is compared with the baseline's
``/twin_error/final_json``.  A metric that got worse by more than
``max(ABS, REL * |baseline|)`` fails the run: exit 1 and the table of what moved.
``--update`` accepts today's result as the new baseline (the bag is re-recorded).
Exit 0: no metric worse; 1: regression; 2: bad input.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from twin_nodes.cli.paths import declare
from twin_nodes.cli.options import domain_id, positive_float
from twin_nodes.graph.regress import format_changes, regress_bag, regress_baseline


def _cmd_regress(args: argparse.Namespace) -> int:
    from twin_nodes.base.io import atomic_write_text
    from twin_nodes.twin.metrics import table2, to_jsonable

    rel, abs_ = args.tolerance, args.abs_tolerance  # range-checked by their argparse types
    if args.self_check:
        stored, fresh, problems = regress_bag(args.bag, rel, abs_)
        print(table2(fresh, title=f"Recomputed from {args.bag}"))
        if problems:
            print(f"REGRESSION: {len(problems)} stored metric(s) do not recompute from the recording:",
                  file=sys.stderr)
            for line in problems:
                print(f"  {line}", file=sys.stderr)
            return 1
        print(f"OK: every stored metric recomputes from the recording within rel {rel:g} / abs {abs_:g}",
              file=sys.stderr)
        return 0
    if args.domain_id is not None:
        from twin_nodes.graph.domains import check_domain_id
        check_domain_id(args.domain_id)
    res = regress_baseline(args.bag, args.params, offline=args.offline, rel_tol=rel, abs_tol=abs_,
                           update=args.update, domain_id=args.domain_id, progress=not args.quiet)
    print(f"regress {res.bag} ({res.path}); params {res.params}")
    print(format_changes(res.changes, only_moved=args.only_moved))
    if args.json:
        atomic_write_text(args.json, json.dumps(to_jsonable({
            "baseline": str(res.bag), "params": res.params, "path": res.path, "failed": res.failed,
            "updated": res.updated, "tolerance": rel, "abs_tolerance": abs_,
            "changes": [{"metric": c.name, "baseline": c.baseline, "now": c.now, "tolerance": c.tolerance,
                         "verdict": c.verdict} for c in res.changes], "metrics": res.metrics}), indent=1))
    worse = res.worse
    if res.updated:
        print(f"baseline updated: {res.bag} now holds today's twin"
              + (f" ({len(worse)} metric(s) worse than the old baseline accepted)" if worse else ""),
              file=sys.stderr)
        return 0
    if worse:
        names = ", ".join(f"{c.name} {c.baseline:.4g} -> {c.now:.4g}" for c in worse[:6])
        print(f"REGRESSION: {len(worse)} metric(s) worse than the baseline beyond tolerance "
              f"(rel {rel:g}, abs {abs_:g}): {names}{' ...' if len(worse) > 6 else ''}", file=sys.stderr)
        return 1
    better = [c.name for c in res.changes if c.verdict == "better"]
    print(f"OK: no metric worse than the baseline (rel {rel:g}, abs {abs_:g})"
          + (f"; better: {', '.join(better)} (accept with --update)" if better else ""), file=sys.stderr)
    return 0


def _bag_folder(value: str) -> list[str]:
    """The rosbag2 folder an ``.mcap`` lies in (an input too); none for a single ``.mcap`` file."""
    folder = os.path.dirname(os.path.abspath(value))
    return [folder] if value.endswith(".mcap") and os.path.isfile(os.path.join(folder, "metadata.yaml")) else []


def register(subparsers: argparse._SubParsersAction) -> None:
    r = subparsers.add_parser("regress", help="fly a baseline recording with today's twin; exit 1 if a metric "
                                              "got worse", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    io = declare(r)
    io.input("bag", also=_bag_folder,
             help="baseline recorded by 'rotortwin compare --mcap': a bag directory, its .mcap, or one .mcap file")
    io.input("--params", help="vehicle params YAML (default: the ones recorded with the baseline)")
    r.add_argument("--tolerance", type=positive_float(1e6), default="0.05", help="relative tolerance, finite > 0 (default 0.05)")
    r.add_argument("--abs-tolerance", type=positive_float(1e6), default="1e-3",
                   help="absolute tolerance in the metric's unit (m, or fraction 0..1), finite > 0 (default 1e-3)")
    r.add_argument("--offline", action="store_true", help="no ROS graph: the same twin and metrics code in-process")
    r.add_argument("--update", action="store_true", help="accept today's result: re-record the baseline")
    r.add_argument("--self-check", action="store_true",
                   help="only check that the stored metrics recompute from the bag's own /real and /twin topics")
    r.add_argument("--only-moved", action="store_true", help="list only the metrics that moved beyond tolerance")
    io.output("--json", help="write the comparison here (JSON)")
    r.add_argument("--domain-id", type=domain_id(), help="ROS_DOMAIN_ID for the graph (default: a free one)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=_cmd_regress)
