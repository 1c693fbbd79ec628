"""The live node graph from the command line.

::

    rotortwin compare FLIGHT.ulg [--params P.yaml] [--mode closed|open] [--rate R] [--json OUT.json]
                                 [--mcap OUT_BAG] [--report DIR] [--window S] [--offline]
    rotortwin monitor [--once] [--duration S] [--domain-id N]
    rotortwin topics list | echo TOPIC [--count N]
    rotortwin regress BASELINE_BAG [--params P] [--tolerance REL] [--abs-tolerance ABS] [--offline]
                                   [--update] [--self-check]
    rotortwin replay FLIGHT.ulg [--rate R] [--wait-for NODE ...]       (one node, in the foreground)
    rotortwin twin --params P.yaml [--mode closed|open]
    rotortwin metrics [--window S] [--json OUT.json]
    rotortwin record OUT_BAG | rotortwin record recover BAG [--out DIR]

``compare`` starts the same four processes as ``launch_scripts/replay_compare.sh``
(ulog_replay, twin, metrics and, with ``--mcap``, recorder) on a private
``ROS_DOMAIN_ID`` with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, waits for
``/replay/done`` and the metrics node's whole-flight JSON, stops everything
with SIGINT and prints the Table-2 summary.  The domain is leased for the run
(a free one of 1..101, or ``--domain-id`` 0..232 if no other run holds it), the
nodes die with the CLI, outputs are checked before anything runs and a failed
run leaves no files (docs/graph.md).  ``--offline`` computes the same
metrics without ROS (``twin_nodes.twin.compare.compare_log``).  When the closed-loop twin leaves the
real flight (``divergence`` in the metrics: attitude, heading, motors rail to rail, a crash, a
run-away; checked offline, the graph's streamed twin has no attitude to check) the metrics are
still printed and written, one line on stderr names the time and cause, and the exit status is 3.

Without ``--params`` the vehicle file is the shipped one for the log's
``SYS_AUTOSTART``, else the nominal built from the log itself (``rotortwin params
from-ulog``), said in one line.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from twin_nodes.base.errors import TwinError
from twin_nodes.base.outputs import shown
from twin_nodes.cli.paths import declare
from twin_nodes.cli.options import SPEED, WINDOW_S, domain_id, port
from twin_nodes.live.attach import add_foxglove_option, foxglove_beside, free_domain
from twin_nodes.graph import bag_dir, default_params_for, run_graph


def _cmd_compare(args: argparse.Namespace) -> int:
    from twin_nodes.base.io import atomic_write_text
    from twin_nodes.graph.domains import check_domain_id
    from twin_nodes.twin.metrics import table2, to_jsonable

    # the outputs were checked and staged by the CLI's guard (cli/paths.py) before this runs
    if args.domain_id is not None:
        check_domain_id(args.domain_id)
    from twin_nodes.twin.compare import load_flight

    # the flight loaded and checked here, in this process, for both modes: the loader's warnings are
    # printed and an unusable flight is refused (one line, exit 2) before any node starts
    log = load_flight(args.flight)
    params_file = default_params_for(args.flight, args.params, log=log)
    report_dir = Path(args.report) if args.report else None
    if args.offline:
        from twin_nodes.twin.compare import compare_log
        from twin_nodes.vehicle.params import load_params

        if args.mcap:
            raise TwinError("--mcap needs the ROS graph; drop --offline")
        if args.foxglove is not None:
            raise TwinError("--foxglove needs the ROS graph; drop --offline")
        from twin_nodes.fleet.vehicle_twin import for_flight, read_vehicle_facts

        vp = load_params(params_file)  # a bad params file: its one-line error first
        ref = read_vehicle_facts(params_file)
        vp, note = for_flight(vp, ref, log)
        if note:
            print(f"rotortwin: {note}", file=sys.stderr)
        res = compare_log(log, vp, mode=args.mode, horizon_s=args.horizon, progress=True)
        metrics, aligned = res.metrics, res.aligned
        metrics["source"] = "offline (twin_nodes.twin.compare.compare_log)"
        if ref is not None:  # a vehicle twin: the flight's own nominal beside it
            from twin_nodes.identify.nominal import params_for_log

            own, _ = params_for_log(args.flight, None, log=log)
            mo = compare_log(log, load_params(own), mode=args.mode, horizon_s=args.horizon).metrics
            metrics["own_nominal"] = {k: mo[k] for k in ("throttle_rmse", "motor_p75_mean", "xy_rmse_m", "z_rmse_m")
                                      if k in mo}
            print("vehicle twin vs the flight's own nominal: " + ", ".join(
                f"{k} {metrics.get(k, float('nan')):.3g} vs {v:.3g}" for k, v in metrics["own_nominal"].items()))
    else:
        del log  # the replay node loads it again in its own process
        bag = bag_dir(args.mcap) if args.mcap else None
        run_dir = Path(args.run_dir) if args.run_dir else (report_dir / "run" if report_dir else None)
        domain = args.domain_id if (args.domain_id is not None or args.foxglove is None) else free_domain()
        with foxglove_beside(args.foxglove, domain) as url:
            if url:
                print(f"foxglove: {url} (layout: layouts/rotortwin.json)", file=sys.stderr)
            res_g = run_graph(args.flight, params_file, mode=args.mode, rate=args.rate, run_dir=run_dir,
                              bag=str(bag) if bag else None, window_s=args.window, horizon_s=args.horizon,
                              domain_id=domain, progress=not args.quiet)
        metrics = res_g.metrics
        aligned = res_g.aligned
        st = res_g.replay_stats
        if st:
            print(f"graph: ROS_DOMAIN_ID {res_g.domain_id}, {st.get('messages', 0)} messages replayed in "
                  f"{st.get('wall_s', 0):.1f} s ({st.get('real_time_factor', 0):.1f}x real time)"
                  + (f"; run dir {shown(res_g.run_dir)}" if res_g.run_dir_kept else ""), file=sys.stderr)
        if bag:
            print(f"recording: {shown(bag)}" + ("" if bag.suffix == ".mcap" else
                                                f" (MCAP {shown(bag / (bag.name + '.mcap'))})"), file=sys.stderr)
    metrics["params_file"] = str(params_file)
    print(table2(metrics, title=f"Twin vs real (Table 2 layout): {Path(args.flight).name}, "
                                f"params {Path(params_file).name}"))
    if args.json:
        atomic_write_text(args.json, json.dumps(to_jsonable(metrics), indent=1))
    if report_dir:
        from twin_nodes.twin.report import write_report
        idx = write_report(report_dir, aligned, metrics, title=Path(args.flight).name)
        print(f"report: {shown(idx)}", file=sys.stderr)
    div = metrics.get("divergence")
    if div:
        # never a silent wrong twin: the metrics are printed and written, the exit status says they
        # describe a twin that left the real flight (3; 2 is bad input)
        print(f"rotortwin: the twin DIVERGED from the real flight at {div['t_s']:.2f} s: {div['cause']} "
              f"({div['detail']}); exit 3", file=sys.stderr)
        return EXIT_DIVERGED
    return 0


#: ``compare``'s exit status when the closed-loop twin left the real flight's envelope
EXIT_DIVERGED = 3


def register(subparsers: argparse._SubParsersAction) -> None:
    raw = argparse.RawDescriptionHelpFormatter
    c = subparsers.add_parser("compare", help="replay a ULog through the node graph and print Table-2 metrics",
                              description=__doc__, formatter_class=raw)
    io = declare(c)
    io.input("flight", help="PX4 ULog (.ulg)")
    io.input("--params", help="vehicle params YAML (default: from the log's SYS_AUTOSTART)")
    c.add_argument("--mode", choices=("closed", "open"), default="closed",
                   help="closed: our controller flies the setpoints; open: real motor commands, re-synced")
    c.add_argument("--rate", type=SPEED, default=0.0,
                   help="replay speed: 0 = as fast as the nodes keep up (default), 1 = real time, 20 = 20x")
    c.add_argument("--horizon", type=WINDOW_S, default=2.0, help="open loop: re-sync period [s] (default 2)")
    c.add_argument("--window", type=WINDOW_S, default=5.0, help="rolling metrics window [s] (default 5)")
    io.output("--json", help="write the whole-flight metrics here")
    io.output("--mcap", kind="bag", help="record every topic: OUT.mcap writes that one MCAP file (the rosbag2 "
                                         "metadata inside it), any other OUT a rosbag2 bag directory")
    io.output("--report", kind="dir", help="write PNG plots and index.html here")
    io.output("--run-dir", kind="update", help="node logs and pid files (default: REPORT/run or a temp dir)")
    c.add_argument("--domain-id", type=domain_id(), help="ROS_DOMAIN_ID 0..232 (default: a free one of 1..101); "
                                                 "refused while another rotortwin run holds it")
    c.add_argument("--offline", action="store_true", help="no ROS: the same metrics via compare_log")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    add_foxglove_option(c, port_type=port())
    c.set_defaults(func=_cmd_compare)
