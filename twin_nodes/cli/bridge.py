"""``rotortwin bridge``: link the twin to PX4 SITL, or read a real vehicle, over MAVLink.

::

    rotortwin bridge sim [--params P.yaml] [--port 4560] [--host 127.0.0.1] [--step-ms 4]
                         [--speed-factor 1] [--publish-every N] [--duration S] [--no-ros] [--foxglove [PORT]]
    rotortwin bridge telemetry --url URL [--pwm-min 1000] [--pwm-max 2000] [--motors 4]
                               [--motor-channels 4,5,6,7] [--stale-after 3] [--no-request-streams]
                               [--duration S] [--no-ros] [--foxglove [PORT]]

``sim`` is the simulator PX4 SITL's ``simulator_mavlink`` connects to (TCP
server, lockstep HIL; see docs/px4_sitl.md).  It listens on loopback unless
``--host`` says otherwise (``--host 0.0.0.0`` for PX4 in another container or on
another machine: the link has no authentication), and one client flies at a time
(a second connection is refused while the first is active).  ``telemetry`` reads a vehicle's
MAVLink stream (``udpin:0.0.0.0:14550``, ``udpout:HOST:PORT``, ``tcp:HOST:PORT``,
``/dev/ttyACM0`` or ``serial:/dev/ttyUSB0:57600``).

With ROS (the default when rclpy imports) both run the ``px4_bridge`` node and
publish ``/clock`` + ``/twin/...`` or ``/real/...`` topics in the layouts of
msgs_py/topics.py (see twin_nodes/nodes/px4_bridge.py).
``--no-ros`` runs the bare link and prints a status line every second.
``--foxglove [PORT]`` also serves the node's topics to Foxglove (``ws://127.0.0.1:8765`` by
default; layout ``layouts/rotortwin.json``) on the same ROS domain, for as long as the bridge runs.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time

from twin_nodes.cli.paths import declare
from twin_nodes.cli.options import MOTORS, PWM_US, SECONDS, SPEED, finite_float, port, positive_int
from twin_nodes.live.attach import add_foxglove_option, foxglove_beside
from twin_nodes.mavlink.simlink import DEFAULT_HOST, DEFAULT_PORT, DEFAULT_STEP_S


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("bridge", help="MAVLink links: PX4 SITL simulator (sim) or vehicle telemetry",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="bridge_command", metavar="MODE")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    s = sub.add_parser("sim", help="be PX4 SITL's lockstep simulator (TCP server on 4560 + instance)")
    declare(s).input("--params", help="vehicle params YAML (default: shipped px4_sih_quadx)")
    s.add_argument("--port", type=port(), default=DEFAULT_PORT, help="TCP port 0..65535 (default 4560; 0 = any free)")
    s.add_argument("--host", default=DEFAULT_HOST,
                   help="listen address (default 127.0.0.1, loopback only; 0.0.0.0 = every interface)")
    s.add_argument("--step-ms", type=finite_float(0.01, 100.0, unit="ms"), default=DEFAULT_STEP_S * 1e3,
                   help="lockstep step in ms (default 4, what PX4 assumes)")
    s.add_argument("--speed-factor", type=SPEED,
                   default=os.environ.get("PX4_SIM_SPEED_FACTOR", "1"),
                   help="pace in multiples of real time (default $PX4_SIM_SPEED_FACTOR or 1; 0 = unpaced)")
    s.add_argument("--publish-every", type=positive_int(100000), default=1, help="ROS: publish every N steps (default 1)")
    s.add_argument("--duration", type=SECONDS, help="stop after this much simulated time [s]")
    _ros_args(s)
    s.set_defaults(func=_cmd_sim)

    t = sub.add_parser("telemetry", help="publish a real vehicle's MAVLink telemetry as /real/... topics")
    t.add_argument("--url", required=True, help="mavutil URL, e.g. udpin:0.0.0.0:14550, tcp:HOST:5760")
    t.add_argument("--pwm-min", type=PWM_US, default=1000.0, help="PWM of command 0 [µs] (default 1000)")
    t.add_argument("--pwm-max", type=PWM_US, default=2000.0, help="PWM of command 1 [µs] (default 2000)")
    t.add_argument("--motors", type=MOTORS, default=4, help="number of motors (default 4)")
    t.add_argument("--motor-channels", default="", help="0-based output channels of Motor1..N, e.g. 4,5,6,7")
    t.add_argument("--stale-after", type=SECONDS, default=3.0, help="mark the link stale after S s of silence")
    t.add_argument("--no-request-streams", action="store_true",
                   help="don't ask the autopilot for streams (SET_MESSAGE_INTERVAL)")
    t.add_argument("--duration", type=SECONDS, help="stop after S s of wall time (--no-ros)")
    _ros_args(t)
    t.set_defaults(func=_cmd_telemetry)


def _ros_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-ros", action="store_true", help="run without ROS (print status lines)")
    p.add_argument("-v", "--verbose", action="store_true", help="log the link's events")
    add_foxglove_option(p, port_type=port())


def _ros_available() -> bool:
    try:
        import rclpy  # noqa: F401
    except ImportError:
        return False
    return True


def _run_node(mode: str, params: dict, args: argparse.Namespace) -> int:
    from twin_nodes.nodes import px4_bridge

    ros = ["--ros-args"]
    for k, v in params.items():
        ros += ["-p", f"{k}:={v}"]
    with foxglove_beside(args.foxglove):  # on this process's ROS domain (the environment's)
        return px4_bridge.main(["px4_bridge", mode, *ros])


def _no_foxglove(args: argparse.Namespace) -> None:
    if args.foxglove is not None:
        from twin_nodes.base.errors import TwinError

        raise TwinError(f"bridge {args.bridge_command}: --foxglove needs ROS (rclpy); "
                        + ("drop --no-ros" if args.no_ros else "install the [ros] extra"))


def _cmd_sim(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO if args.verbose or args.no_ros else logging.WARNING,
                        format="%(asctime)s %(name)s: %(message)s")
    step_s = args.step_ms * 1e-3
    from twin_nodes.base.errors import TwinError

    if not 0 <= args.port <= 65535:
        raise TwinError(f"bridge sim: --port: expected a TCP port 0..65535, got {args.port}")
    if not args.no_ros and _ros_available():
        if args.duration is not None:
            print("rotortwin bridge sim: --duration applies to --no-ros only", file=sys.stderr)
        params = {"port": args.port, "host": args.host, "step_s": step_s, "publish_every": args.publish_every,
                  "speed_factor": float(args.speed_factor)}
        if args.params:
            params["params_file"] = args.params
        return _run_node("sim", params, args)
    _no_foxglove(args)
    from twin_nodes.mavlink.simlink import SimLinkServer
    from twin_nodes.vehicle.params import load_params, shipped

    vp = load_params(args.params) if args.params else shipped("px4_sih_quadx")
    max_steps = int(round(args.duration / step_s)) if args.duration else None
    srv = SimLinkServer(vp, port=args.port, step_s=step_s, host=args.host, max_steps=max_steps,
                        speed_factor=args.speed_factor)
    srv.bind()
    print(f"rotortwin bridge sim: {vp.name} on TCP {args.host}:{srv.port}, step {args.step_ms:g} ms "
          f"(waiting for PX4)", flush=True)
    thread = srv.start_thread()
    last = srv.stats.steps
    try:
        while thread.is_alive():
            thread.join(1.0)
            st = srv.stats
            x = srv.sim.state
            print(f"t={st.time_usec * 1e-6:9.3f} s  steps/s={st.steps - last:5d}  "
                  f"{'lockstep' if srv.lockstep else ('freewheel' if srv.connected else 'no client')}  "
                  f"z={x[2]:7.2f} m  controls={st.controls_rx} sensors={st.sensors_tx} gps={st.gps_tx} "
                  f"state={st.state_tx} timeouts={st.lockstep_timeouts}", flush=True)
            last = st.steps
    except KeyboardInterrupt:
        pass
    finally:
        srv.close()
    return 0


def _cmd_telemetry(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO if args.verbose or args.no_ros else logging.WARNING,
                        format="%(asctime)s %(name)s: %(message)s")
    from twin_nodes.base.errors import TwinError
    from twin_nodes.mavlink.telemetry import TelemetryClient, TelemetryConfig

    chans = tuple(int(c) for c in args.motor_channels.split(",")) if args.motor_channels.strip() else None
    try:
        cfg = TelemetryConfig(pwm_min_us=args.pwm_min, pwm_max_us=args.pwm_max, n_motors=args.motors,
                              motor_channels=chans, stale_after_s=args.stale_after,
                              request_streams=not args.no_request_streams)
    except ValueError as exc:
        raise TwinError(f"bridge telemetry: {exc}") from None
    if not args.no_ros and _ros_available():
        params = {"url": args.url, "pwm_min_us": args.pwm_min, "pwm_max_us": args.pwm_max,
                  "n_motors": args.motors, "motor_channels": f"'{args.motor_channels}'",
                  "stale_after_s": args.stale_after, "request_streams": str(not args.no_request_streams).lower()}
        return _run_node("telemetry", params, args)
    _no_foxglove(args)
    client = TelemetryClient(args.url, cfg)
    client.start_thread()
    t_end = time.monotonic() + args.duration if args.duration else float("inf")
    try:
        while time.monotonic() < t_end:
            time.sleep(min(1.0, max(t_end - time.monotonic(), 0.0)))
            s = client.state
            b = s.battery
            print(f"{'STALE' if s.stale else 'ok   '} sys={s.system_id} {'armed' if s.armed else 'disarmed'} "
                  f"{s.mode:14s} p_enu={_fmt(s.position_enu)} motors={_fmt(s.motors)} "
                  f"thr={s.throttle:.3f} V={b.voltage_v if b else float('nan'):.2f} msgs={s.messages_rx} "
                  f"ignored: bad={s.bad_data} foreign={s.foreign} early={s.unbound} rejected={s.n_rejected} "
                  f"resets={len(s.resets)}{' (vehicle shut down)' if s.vehicle_closed else ''}",
                  flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        client.close()
    return 0


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:.2f}" for x in v) + "]"
