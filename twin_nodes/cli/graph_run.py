"""``rotortwin replay | twin | metrics | record``: one graph node in the foreground, and ``record recover``."""

from __future__ import annotations

import argparse
from typing import Any

from twin_nodes.base.errors import TwinError
from twin_nodes.base.outputs import shown
from twin_nodes.cli.paths import declare
from twin_nodes.cli.options import MOTORS, SPEED, WINDOW_S
from twin_nodes.graph import run_node


def _cmd_replay(args: argparse.Namespace) -> int:
    return run_node("replay", {"ulog": args.flight, "rate": float(args.rate), "use_sim_time": False,
                             **({"wait_for": args.wait_for} if args.wait_for else {})}, args.ros_args)


def _cmd_twin(args: argparse.Namespace) -> int:
    return run_node("twin", {"params_file": args.params, "mode": args.mode, "use_sim_time": not args.wall_time},
                    args.ros_args)


def _cmd_metrics(args: argparse.Namespace) -> int:
    p: dict[str, Any] = {"window_s": args.window, "use_sim_time": not args.wall_time, "n_motors": args.motors}
    if args.json:
        p["json_out"] = args.json
    return run_node("metrics", p, args.ros_args)


def _cmd_record(args: argparse.Namespace) -> int:
    if args.out == "recover":
        if not args.bag:
            raise TwinError("record recover: expected the bag directory or .mcap to recover")
        from twin_nodes.logs.recording import recover
        rep = recover(args.bag, args.recover_out)
        print(f"recovered {rep.n_messages} messages into {shown(rep.out_dir)}"
              + ("" if rep.complete else f" (the source was cut short: {rep.error or 'no footer'})"))
        for t, c in sorted(rep.counts.items()):
            print(f"  {t:<34} {c}")
        return 0
    return run_node("recorder", {"out": args.out, "use_sim_time": not args.wall_time}, args.ros_args)


def _recovered_dir(args: argparse.Namespace) -> str | None:
    """``record recover``'s default output: ``BAG_recovered`` (a file's: ``<stem>_recovered`` beside it)."""
    if not args.bag:
        return None
    from pathlib import Path

    p = Path(args.bag)
    base = p.with_suffix("") if p.is_file() else p
    return str(base.parent / f"{base.name}_recovered")


def register(subparsers: argparse._SubParsersAction) -> None:
    def ros_extra(p: argparse.ArgumentParser) -> None:
        p.add_argument("--wall-time", action="store_true", help="use wall time instead of /clock")
        p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[],
                       help="further ROS arguments, passed after the node's own")

    rp = subparsers.add_parser("replay", help="run the ULog replay node in the foreground")
    declare(rp).input("flight", help="PX4 ULog (.ulg)")
    rp.add_argument("--rate", type=SPEED, default=1.0, help="1 real time (default), 20 = 20x, 0 = flow-controlled")
    rp.add_argument("--wait-for", nargs="*", default=[], help="consumer node names to wait for")
    rp.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[])
    rp.set_defaults(func=_cmd_replay)

    tw = subparsers.add_parser("twin", help="run the twin node in the foreground")
    declare(tw).input("--params", required=True, help="vehicle params YAML")
    tw.add_argument("--mode", choices=("closed", "open"), default="closed")
    ros_extra(tw)
    tw.set_defaults(func=_cmd_twin)

    me = subparsers.add_parser("metrics", help="run the metrics node in the foreground")
    me.add_argument("--window", type=WINDOW_S, default=5.0, help="rolling window [s]")
    me.add_argument("--motors", type=MOTORS, default=4, help="number of motors")
    # written by the node itself when it is stopped (SIGINT): checked here, not staged
    declare(me).output("--json", staged=False, help="write the whole-flight metrics here at the end")
    ros_extra(me)
    me.set_defaults(func=_cmd_metrics)

    rc = subparsers.add_parser("record", help="record every graph topic to MCAP, or 'record recover BAG'",
                               description="rotortwin record OUT_BAG   |   rotortwin record recover BAG [--out DIR]")
    io = declare(rc)
    recovering = lambda a: a.out == "recover"  # noqa: E731
    # a live recording is not staged: what it recorded must survive a kill (record recover)
    io.output("out", kind="bag", staged=False, skip=recovering,
              help="recording to create (OUT.mcap: one MCAP file; any other OUT: a bag directory), or 'recover'")
    io.input("bag", nargs="?", help="with 'recover': the cut-short bag directory or .mcap")
    io.output("--out", dest="recover_out", kind="bag", skip=lambda a: not recovering(a), fallback=_recovered_dir,
              help="with 'recover': the recovered recording (X.mcap: one MCAP file; any other: a bag directory; "
                   "default BAG_recovered)")
    ros_extra(rc)
    rc.set_defaults(func=_cmd_record)
