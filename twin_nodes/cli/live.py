"""``rotortwin live``: the twin shadowing a live vehicle (or PX4 SITL), and the Foxglove view.

::

    rotortwin live --url URL [--params P.yaml] [--mcap BAG] [--foxglove [PORT]] [--duration S]
                   [--json OUT.json] [--window S] [--horizon S] [--stale-after S] [--domain-id D]
                   [--pwm-min 1000] [--pwm-max 2000] [--motor-channels 4,5,6,7] [--no-request-streams]
    rotortwin live foxglove [--port 8765] [--host 127.0.0.1] [--domain-id D] [--mcap FILE]
    rotortwin live tlog FLIGHT.tlog [--params P.yaml] [--json OUT.json] [...]   (offline, no ROS)
    rotortwin live layout [--out FILE]

``live --url`` runs, on a private ROS domain: the PX4 bridge in telemetry mode (``/real/...``), the
twin in open loop (the real motor commands drive it, re-synced to the real state every
``--horizon`` s), the metrics (``/twin_error/...``), the link watchdog (``/twin_error/link_lost``)
and, with ``--mcap`` / ``--foxglove``, the recorder and the Foxglove server.  Ctrl-C (or
``--duration``) stops it and prints the Table-2 totals of what was seen.  For PX4 SITL use
``--url udpin:0.0.0.0:14550`` (PX4's ground-station link; 14540 is MAVSDK's, used by
``rotortwin mission``).

``live foxglove`` serves a running graph's topics to Foxglove (``ws://127.0.0.1:8765``; import
``layouts/rotortwin.json``).  ``live tlog`` is the offline twin beside a recorded telemetry log
(QGroundControl ``.tlog``), computed as ``live`` computes it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from twin_nodes.base.errors import TwinError
from twin_nodes.base.outputs import shown
from twin_nodes.cli.paths import declare
from twin_nodes.cli.options import PWM_US, SECONDS, WINDOW_S, domain_id, port


def _params(args: argparse.Namespace) -> str:
    if args.params:
        return args.params
    from twin_nodes.vehicle.params import params_dir

    p = params_dir() / "px4_sih_quadx.yaml"
    print(f"rotortwin: no --params: flying the twin as {p.name} (PX4's SIH quad; `rotortwin bridge sim`'s "
          f"default)", file=sys.stderr)
    return str(p)


def _telemetry_config(args: argparse.Namespace, n_motors: int):
    from twin_nodes.mavlink.telemetry import TelemetryConfig

    chans = tuple(int(c) for c in args.motor_channels.split(",")) if args.motor_channels.strip() else None
    try:
        return TelemetryConfig(pwm_min_us=args.pwm_min, pwm_max_us=args.pwm_max, n_motors=n_motors,
                               motor_channels=chans, stale_after_s=args.stale_after,
                               request_streams=not args.no_request_streams)
    except ValueError as exc:
        raise TwinError(f"live: {exc}") from None


def _print_totals(metrics: dict | None, json_out: str | None, title: str) -> None:
    from twin_nodes.base.io import atomic_write_text
    from twin_nodes.twin.metrics import table2, to_jsonable

    if not metrics:
        print("no twin sample was scored (no telemetry with position, attitude and motors arrived)")
        return
    print(table2(metrics, title=title))
    if json_out:
        atomic_write_text(json_out, json.dumps(to_jsonable(metrics), indent=1))


def _cmd_live(args: argparse.Namespace) -> int:
    if not args.url:
        raise TwinError("live: --url: expected the vehicle's MAVLink URL, e.g. udpin:0.0.0.0:14550 "
                        "(or a subcommand: foxglove, tlog, layout)")
    from twin_nodes.graph import bag_dir
    from twin_nodes.graph.domains import check_domain_id
    from twin_nodes.live.shadow import LiveConfig, run_live
    from twin_nodes.vehicle.params import load_params

    if args.domain_id is not None:
        check_domain_id(args.domain_id)
    params = _params(args)
    _telemetry_config(args, load_params(params).rotors.count)  # one-line errors before anything starts
    cfg = LiveConfig(url=args.url, params_file=params, bag=str(bag_dir(args.mcap)) if args.mcap else None,
                     foxglove_port=args.foxglove, window_s=args.window, horizon_s=args.horizon,
                     stale_after_s=args.stale_after, pwm_min_us=args.pwm_min, pwm_max_us=args.pwm_max,
                     motor_channels=args.motor_channels, request_streams=not args.no_request_streams)

    def started(info: dict) -> None:
        fox = f"; Foxglove {info['foxglove_url']} (layout layouts/rotortwin.json)" if info["foxglove_url"] else ""
        print(f"live: twin of {Path(params).name} beside {args.url} on ROS_DOMAIN_ID {info['domain_id']}{fox}; "
              f"Ctrl-C stops", file=sys.stderr, flush=True)

    res = run_live(cfg, domain_id=args.domain_id, run_dir=args.run_dir, duration_s=args.duration, on_start=started)
    for o in res.outages:
        print(f"link lost for {o['length_s']:.1f} s{' (at the end)' if o.get('open') else ''}", file=sys.stderr)
    if res.bag_path:
        print(f"recording: {res.bag_path}", file=sys.stderr)
    _print_totals(res.metrics, args.json, f"Twin vs live vehicle (Table 2 layout): {args.url}")
    return 0


def _cmd_foxglove(args: argparse.Namespace) -> int:
    from twin_nodes.graph.domains import check_domain_id
    from twin_nodes.live import foxglove_node

    if args.domain_id is not None:
        os.environ["ROS_DOMAIN_ID"] = str(check_domain_id(args.domain_id))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ros = ["--ros-args", "-p", f"port:={args.port}", "-p", f"host:={args.host}"]
    if args.mcap:
        ros += ["-p", f"mcap:={args.mcap}"]
    return foxglove_node.main(["foxglove", *ros])


def _cmd_tlog(args: argparse.Namespace) -> int:
    from twin_nodes.live.offline import compare_telemetry, read_tlog
    from twin_nodes.vehicle.params import load_params

    if not Path(args.tlog).is_file():
        raise TwinError(f"{args.tlog}: " + ("expected a telemetry log file, got a directory"
                                            if Path(args.tlog).is_dir() else "file not found"))
    msgs = read_tlog(args.tlog)
    if not msgs:
        raise TwinError(f"{args.tlog}: no MAVLink messages (expected a MAVLink telemetry log, e.g. a .tlog)")
    vp = load_params(_params(args))
    m = compare_telemetry(msgs, vp, config=_telemetry_config(args, vp.rotors.count), horizon_s=args.horizon,
                          window_s=args.window, source=str(args.tlog))  # live.json says what it watched
    _print_totals(m, args.json, f"Twin vs telemetry log (Table 2 layout): {Path(args.tlog).name}")
    return 0


def _cmd_layout(args: argparse.Namespace) -> int:
    from twin_nodes.live.layout import LAYOUT_PATH, write_layout

    print(shown(write_layout(Path(args.out))) if args.out else LAYOUT_PATH)
    return 0


def _link_args(p: argparse.ArgumentParser) -> None:
    io = declare(p)
    io.input("--params", help="vehicle params YAML (default: shipped px4_sih_quadx)")
    io.output("--json", help="write the totals here")
    p.add_argument("--window", type=WINDOW_S, default=5.0, help="rolling metrics window [s] (default 5)")
    p.add_argument("--horizon", type=WINDOW_S, default=2.0, help="re-sync the twin every S s (default 2)")
    p.add_argument("--stale-after", type=SECONDS, default=3.0, help="link lost after S s of silence (default 3)")
    p.add_argument("--pwm-min", type=PWM_US, default=1000.0, help="PWM of motor command 0 [µs] (default 1000)")
    p.add_argument("--pwm-max", type=PWM_US, default=2000.0, help="PWM of motor command 1 [µs] (default 2000)")
    p.add_argument("--motor-channels", default="", help="0-based output channels of Motor1..N, e.g. 4,5,6,7")
    p.add_argument("--no-request-streams", action="store_true", help="don't ask the autopilot for streams")


def register(subparsers: argparse._SubParsersAction) -> None:
    raw = argparse.RawDescriptionHelpFormatter
    p = subparsers.add_parser("live", help="the twin beside a live vehicle / PX4 SITL; Foxglove view",
                              description=__doc__, formatter_class=raw)
    p.add_argument("--url", help="the vehicle's MAVLink URL (udpin:0.0.0.0:14550, tcp:HOST:5760, /dev/ttyACM0)")
    _link_args(p)
    # a live recording is not staged: what it recorded must survive a kill (record recover)
    declare(p).output("--mcap", kind="bag", staged=False,
                      help="record every topic: OUT.mcap one MCAP file, any other OUT a rosbag2 bag directory")
    p.add_argument("--foxglove", nargs="?", type=port(), const=8765, default=None, metavar="PORT",
                   help="serve Foxglove on ws://127.0.0.1:PORT (default 8765)")
    p.add_argument("--duration", type=SECONDS, help="stop after S s (default: Ctrl-C)")
    p.add_argument("--domain-id", type=domain_id(), help="ROS_DOMAIN_ID (default: a free one)")
    declare(p).output("--run-dir", kind="update", help="node logs and pid files (default: a temp dir, removed)")
    p.set_defaults(func=_cmd_live)
    sub = p.add_subparsers(dest="live_command", metavar="foxglove|tlog|layout")
    f = sub.add_parser("foxglove", help="serve a running graph's topics to Foxglove (WebSocket)")
    f.add_argument("--port", type=port(), default=8765, help="WebSocket port (default 8765; 0 = any free)")
    f.add_argument("--host", default="127.0.0.1", help="listen address (0.0.0.0: every interface, no auth)")
    f.add_argument("--domain-id", type=domain_id(), help="ROS_DOMAIN_ID of the graph (default: the environment's)")
    declare(f).output("--mcap", staged=False, help="also write everything served into this MCAP file")
    f.set_defaults(func=_cmd_foxglove)
    t = sub.add_parser("tlog", help="offline: the twin beside a recorded telemetry log (.tlog)")
    declare(t).input("tlog", help="MAVLink telemetry log (QGroundControl .tlog)")
    _link_args(t)
    t.set_defaults(func=_cmd_tlog)
    lay = sub.add_parser("layout", help="print (or write) the Foxglove layout file")
    declare(lay).output("--out", help="write the layout here")
    lay.set_defaults(func=_cmd_layout)
