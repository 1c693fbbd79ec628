"""Issue 4: the twin and the metrics run live on a vehicle's MAVLink telemetry.

Three real processes on a private ROS domain: the PX4 bridge in telemetry mode, the twin node
and the metrics node.  A pymavlink sender plays a real flight's values (the CubeOrange ULog,
converted to the messages PX4 streams) at real time; the twin must fly beside it and the
rolling error topics must carry finite numbers.
"""

import math
import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import missing_shared

rclpy = pytest.importorskip("rclpy")
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402

from msgs_py.topics import TOPICS, msg_class  # noqa: E402

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]
LOG = REPO.parent / "shared" / "flightlogs" / "real" / "real_cubeorange_takeoff_land.ulg"


def _stream(seconds: float):
    """(t_s, message) of the MAVLink stream PX4 would send, for `seconds` of the airborne flight."""
    from pyulog import ULog

    ulog = ULog(str(LOG), ["vehicle_local_position", "vehicle_attitude", "vehicle_angular_velocity",
                           "actuator_outputs"])
    t0 = ulog.start_timestamp

    def ds(name, inst=0):
        d = ulog.get_dataset(name, inst).data
        keep = d["timestamp"] >= t0
        return {k: v[keep] for k, v in d.items()}

    lpos, att, angvel, ao = (ds("vehicle_local_position"), ds("vehicle_attitude"),
                             ds("vehicle_angular_velocity"), ds("actuator_outputs", 1))
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    start = t0 + 8_000_000  # in the air (take-off at ~2 s, climbing)
    end = start + int(seconds * 1e6)
    ev = []
    for i, t in enumerate(lpos["timestamp"]):
        if start <= t < end:
            ev.append((t, mav.local_position_ned_encode(int(t // 1000), *(float(lpos[k][i]) for k in
                                                                          ("x", "y", "z", "vx", "vy", "vz")))))
    for i, t in enumerate(att["timestamp"]):
        if start <= t < end:
            j = max(np.searchsorted(angvel["timestamp"], t, side="right") - 1, 0)
            ev.append((t, mav.attitude_quaternion_encode(int(t // 1000), *(float(att[f"q[{k}]"][i]) for k in range(4)),
                                                         *(float(angvel[f"xyz[{k}]"][j]) for k in range(3)))))
    for i, t in enumerate(ao["timestamp"]):
        if start <= t < end:
            pwm = [int(round(ao[f"output[{k}]"][i])) for k in range(8)]
            ev.append((t, mav.servo_output_raw_encode(int(t % 2**32), 1, *pwm)))
    for t in range(start, end, 500_000):
        ev.append((t, mav.heartbeat_encode(2, 12, 1 | 128, (4 << 16) | (4 << 24), 4)))
    ev.sort(key=lambda e: e[0])
    return [((t - start) / 1e6, m.pack(mav)) for t, m in ev]


@pytest.fixture()
def graph(tmp_path):
    if not LOG.exists():
        missing_shared(LOG.name)
    domain = random.randint(1, 200)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    params = str(REPO / "params" / "quad_c_3dr.yaml")
    cmds = [
        ["twin_nodes.nodes.px4_bridge", "telemetry", "--ros-args", "-p", f"url:=udpin:127.0.0.1:{port}",
         "-p", "request_streams:=false", "-p", "motor_channels:=16,17,18,19", "-p", "pwm_min_us:=1000.0",
         "-p", "pwm_max_us:=2000.0"],
        ["twin_nodes.nodes.twin_node", "--ros-args", "-p", f"params_file:={params}"],
        ["twin_nodes.nodes.metrics_node", "--ros-args", "-p", "window_s:=3.0", "-p", "airborne_only:=false"],
    ]
    procs = []
    for k, c in enumerate(cmds):
        log = open(tmp_path / f"node{k}.log", "w")
        procs.append((subprocess.Popen([sys.executable, "-m", *c], cwd=REPO, env=env, stdout=log,
                                       stderr=subprocess.STDOUT), log))
    yield domain, port, procs, tmp_path
    for p, log in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        log.close()


def test_twin_and_metrics_run_live_on_telemetry(graph):
    domain, port, procs, tmp_path = graph
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("live_probe", context=ctx)
    got = {"/twin/odom": [], "/real/odom": [], "/twin_error/xy/rmse_m": [], "/twin_error/throttle/rmse": []}
    types = {"/twin/odom": msg_class(TOPICS["/twin/odom"].type), "/real/odom": msg_class(TOPICS["/real/odom"].type)}
    for topic in got:
        node.create_subscription(types.get(topic, Float64), topic, lambda m, t=topic: got[t].append(m), 50)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        # let discovery settle, then play 12 s of flight at real time
        t_wait = time.monotonic() + 4.0
        while time.monotonic() < t_wait:
            ex.spin_once(timeout_sec=0.05)
        stream = _stream(12.0)
        t_start = time.monotonic()
        for t_s, data in stream:
            while time.monotonic() - t_start < t_s:
                ex.spin_once(timeout_sec=0.002)
            tx.sendto(data, ("127.0.0.1", port))
        t_wait = time.monotonic() + 3.0
        while time.monotonic() < t_wait:
            ex.spin_once(timeout_sec=0.05)
    finally:
        tx.close()
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    logs = {k: (tmp_path / f"node{k}.log").read_text()[-2000:] for k in range(3)}
    for p, _ in procs:
        assert p.poll() is None, f"a node died: {logs}"
    assert len(got["/real/odom"]) > 50, logs
    assert len(got["/twin/odom"]) > 50, logs
    xy = [m.data for m in got["/twin_error/xy/rmse_m"]]
    assert len(xy) >= 3 and all(math.isfinite(v) for v in xy[-3:]), (xy, logs)
    # the motors made it through (PWM on AUX = SERVO_OUTPUT_RAW port 1 = channels 16..19): throttle is compared
    thr = [m.data for m in got["/twin_error/throttle/rmse"]]
    assert thr and math.isfinite(thr[-1]) and 0.0 <= thr[-1] < 0.5, (thr, logs)
    print(f"live: {len(got['/real/odom'])} real odom, {len(got['/twin/odom'])} twin odom, "
          f"xy rmse {xy[-1]:.2f} m, throttle rmse {thr[-1]:.3f}")
    # the twin flies beside the vehicle: its position stays within a few metres of the real one
    tw = got["/twin/odom"][-1].pose.pose.position
    re = got["/real/odom"][-1].pose.pose.position
    assert math.dist((tw.x, tw.y, tw.z), (re.x, re.y, re.z)) < 5.0, logs
