"""Lockstep rate of the simulator link: steps/s against real time (250 steps/s at 4 ms).

The server (SimLinkServer, the twin + sensors + MAVLink, unpaced: speed_factor 0) runs in this process; the
scripted PX4 stand-in (ScriptedPX4) runs in a separate process, as PX4 would, and
answers every HIL_SENSOR with HIL_ACTUATOR_CONTROLS over TCP loopback.  The rate is
taken over the lockstep part (from PX4's first reply to the last step).

    .venv/bin/python bench/bench_lockstep.py [--sim-seconds 20] [--params P.yaml] [--repeat 3]

Every case also prints its ratio against the first case run (case 1: what PX4 asks for),
measured in the same run.  ``--cases`` picks cases.  ``ROTORTWIN_BENCH_SMOKE=1``: a smoke run
(cases 1 and 2, 1 s simulated, one repeat; the numbers mean nothing).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import random
import statistics

from twin_nodes.mavlink.simlink import ScriptedPX4, SimLinkServer
from twin_nodes.vehicle.params import load_params, shipped

REAL_TIME_STEPS_PER_S = 250.0


def _peer(port: int, until_s: float, state_interval_us: int, q: mp.Queue) -> None:
    peer = ScriptedPX4(port, command=lambda t: ([0.5] * 4, True), request_state_interval_us=state_interval_us,
                       keep_times=False)
    st = peer.run(until_s, drain_s=0.05)
    peer.close()
    q.put((st.controls_tx, st.lockstep_wall_s, st.sensors_rx))


def run_once(vp, sim_seconds: float, state_interval_us: int, on_step=None, srv=None) -> tuple[float, int]:
    if srv is None:
        srv = SimLinkServer(vp, port=0, host="127.0.0.1", on_step=on_step, speed_factor=0)
        srv.start_thread()
    q: mp.Queue = mp.get_context("spawn").Queue()
    proc = mp.get_context("spawn").Process(target=_peer, args=(srv.port, sim_seconds, state_interval_us, q))
    proc.start()
    controls, wall, sensors = q.get(timeout=600)
    proc.join(30)
    srv.close()
    assert srv.stats.sensors_tx == sensors and srv.stats.controls_rx == controls, "messages lost"
    return controls / wall, controls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    from _smoke import SMOKE as smoke  # bench/ is on sys.path when a bench runs as a script
    ap.add_argument("--sim-seconds", type=float, default=1.0 if smoke else 20.0)
    ap.add_argument("--params", help="vehicle params (default shipped px4_sih_quadx)")
    ap.add_argument("--repeat", type=int, default=1 if smoke else 3)
    ap.add_argument("--cases", default="1,2" if smoke else "1,2,3,ros",
                    help="which cases: 1-3 and 'ros' (the px4_bridge node); default all (smoke: 1,2)")
    args = ap.parse_args()
    which = {c.strip() for c in args.cases.split(",")}
    vp = load_params(args.params) if args.params else shipped("px4_sih_quadx")
    print(f"rotortwin lockstep benchmark: {vp.name}, dt {vp.dt_s * 1e3:g} ms, step 4 ms, "
          f"{args.sim_seconds:g} s simulated per run, best and median of {args.repeat}; "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs")
    cases = [
        ("HIL_SENSOR + HIL_GPS 10 Hz + HIL_STATE_QUATERNION every 5 ms (what PX4 asks for)", 5000, None),
        ("HIL_SENSOR + HIL_GPS 10 Hz, no HIL_STATE_QUATERNION", 0, None),
        ("as the first, plus an on_step callback that copies the state (ROS publishing excluded)", 5000,
         lambda info: info.velocity_body_flu),
    ]
    for k, (name, interval, cb) in enumerate(cases, 1):
        if str(k) in which:
            rates = [run_once(vp, args.sim_seconds, interval, cb)[0] for _ in range(args.repeat)]
            _report(name, rates)
    if "ros" in which:
        _bench_ros(vp, args)


_REFERENCE: list[float] = []   # the first case run's median steps/s, this run


def _report(name: str, rates: list[float]) -> None:
    best, med = max(rates), statistics.median(rates)
    if not _REFERENCE:
        _REFERENCE.append(med)
    print(f"  {name}:\n    {best:7.0f} steps/s best, {med:7.0f} median "
          f"= {best / REAL_TIME_STEPS_PER_S:5.2f}x / {med / REAL_TIME_STEPS_PER_S:5.2f}x real time "
          f"({1e6 / med:5.0f} µs per step)\n    ratio vs the first case run (median, this run): "
          f"{med / _REFERENCE[0]:5.2f}x")


def _bench_ros(vp, args) -> None:
    """The px4_bridge node publishing odom/motors/imu/throttle//clock at every step."""
    try:
        import rclpy

        from twin_nodes.nodes.px4_bridge import SimBridgeNode
    except ImportError:
        print("  px4_bridge node: rclpy not importable, skipped")
        return
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(100, 200)))  # away from other graphs
    rates = []
    with rclpy.init(args=["bench", "--ros-args", "-p", "port:=0", "-p", "host:=127.0.0.1",
                          "-p", "speed_factor:=0.0"]):
        for _ in range(args.repeat):
            node = SimBridgeNode()
            try:
                rates.append(run_once(vp, args.sim_seconds, 5000, srv=node.server)[0])
            finally:
                node.close()
                node.destroy_node()
    _report("px4_bridge ROS node (shipped px4_sih_quadx), publishing 4 topics + /clock every step, "
            "no subscriber", rates)


if __name__ == "__main__":
    main()
