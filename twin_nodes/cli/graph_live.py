"""``rotortwin monitor`` and ``rotortwin topics``: live views of a running graph (see :mod:`twin_nodes.graph.live`)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from twin_nodes.cli.options import SECONDS, domain_id, integer, port
from twin_nodes.graph.domains import check_domain_id
from twin_nodes.graph.live import MonitorState, echo_topic, format_monitor, topic_types, watch_metrics
from twin_nodes.live.attach import add_foxglove_option, foxglove_beside

#: discovery time of ``topics list|echo`` [s]: a running ``bridge sim`` was listed after 0.5 s in 1 of
#: 2 tries and after 1-1.5 s in 4 of 4 on the loaded 2-core machine (docs/graph.md)
TOPICS_WAIT_S = 4.0


def _cmd_monitor(args: argparse.Namespace) -> int:
    def draw(state: MonitorState) -> None:
        text = format_monitor(state.values, state.t_s) if state.values else "waiting for /twin_error/... topics"
        if sys.stdout.isatty():
            sys.stdout.write("\x1b[H\x1b[2J" + text + "\n")
        else:
            sys.stdout.write(text + "\n\n")
        sys.stdout.flush()

    if args.domain_id is not None:
        check_domain_id(args.domain_id)
    with foxglove_beside(args.foxglove, args.domain_id):
        state = watch_metrics(once=args.once, duration=args.duration, domain_id=args.domain_id, on_draw=draw)
    values = state.values
    if args.once:
        print(format_monitor(values, state.t_s) if values else "no /twin_error topics seen")
    if state.final:
        print(state.final)
    return 0 if (values or not args.once) else 1


def _cmd_topics(args: argparse.Namespace) -> int:
    from msgs_py.topics import TOPICS

    domain_id = getattr(args, "domain_id", None)
    wait = getattr(args, "wait", TOPICS_WAIT_S)
    if domain_id is not None:
        check_domain_id(domain_id)
    if args.topics_command in (None, "list"):
        found = topic_types(wait, domain_id)
        if not found:
            for spec in TOPICS.values():
                print(f"{spec.name:<28} {spec.type:<38} (documented; not seen on the network)")
            return 0
        for t in sorted(found):
            note = TOPICS[t].content[:60] if t in TOPICS else ""
            print(f"{t:<34} {', '.join(found[t]):<38} {note}")
        return 0
    topic = args.topic

    def show(n: int, m: Any) -> None:
        print(f"--- {topic} #{n}\n{m}", flush=True)

    n = echo_topic(topic, show, wait=wait, count=args.count, duration=args.duration, domain_id=domain_id)
    return 0 if n else 1


def _topics_common() -> argparse.ArgumentParser:
    """--domain-id/--wait, accepted before or after the sub-command (SUPPRESS: a later parser's
    default never overwrites a value given earlier)."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--domain-id", type=domain_id(), default=argparse.SUPPRESS,
                        help="ROS_DOMAIN_ID of the graph (default: the environment's)")
    common.add_argument("--wait", type=SECONDS, default=argparse.SUPPRESS,
                        help=f"discovery time [s] (default {TOPICS_WAIT_S:g})")
    return common


def register(subparsers: argparse._SubParsersAction) -> None:
    m = subparsers.add_parser("monitor", help="live /twin_error/... metrics as a terminal table")
    m.add_argument("--once", action="store_true", help="print one table once the topics are seen, then exit")
    m.add_argument("--duration", type=SECONDS, help="stop after S seconds")
    m.add_argument("--domain-id", type=domain_id(), help="ROS_DOMAIN_ID of the graph (default: the environment's)")
    add_foxglove_option(m, port_type=port())
    m.set_defaults(func=_cmd_monitor)

    common = _topics_common()
    t = subparsers.add_parser("topics", help="list the graph's topics or echo one", parents=[common])
    ts = t.add_subparsers(dest="topics_command", metavar="list|echo")
    ts.add_parser("list", help="topics and types on the network (or the documented ones)", parents=[common])
    e = ts.add_parser("echo", help="print the messages of one topic", parents=[common])
    e.add_argument("topic")
    e.add_argument("--count", type=integer(0, 10**9), default=0, help="stop after N messages (0: no limit)")
    e.add_argument("--duration", type=SECONDS, help="stop after S seconds")
    t.set_defaults(func=_cmd_topics)
