"""The px4_bridge node as a real subprocess: /twin/... from the simulator link and /real/... from
telemetry, received by a probe node in this process.  Each test uses its own ROS_DOMAIN_ID
(random 1..200) and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST."""

from __future__ import annotations

import math
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from msgs_py.topics import TOPICS, msg_class  # noqa: E402
from twin_nodes.logs import conversions as cv  # noqa: E402
from twin_nodes.mavlink.simlink import ScriptedPX4  # noqa: E402

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]
TWIN = ("/twin/odom", "/twin/motors", "/twin/throttle", "/twin/imu", "/clock")
REAL = ("/real/odom", "/real/imu", "/real/motors", "/real/throttle", "/real/battery", "/real/setpoint",
        "/real/setpoint_pose", "/real/status")


def _free_port(kind=socket.SOCK_STREAM) -> int:
    s = socket.socket(socket.AF_INET, kind)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class Probe:
    """A node in this process that keeps every message of the given topics."""

    def __init__(self, domain: int, topics: dict[str, type]):
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("probe", context=self.context)
        self.msgs: dict[str, list] = {t: [] for t in topics}
        for topic, mtype in topics.items():
            self.node.create_subscription(mtype, topic, lambda m, t=topic: self.msgs[t].append(m), 50)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, cond, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)
            if cond():
                return True
        return False

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture()
def ros_domain(monkeypatch, tmp_path):
    domain = random.randint(1, 200)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    procs = []

    def start(*args):
        log = open(tmp_path / f"node{len(procs)}.log", "w")
        p = subprocess.Popen([sys.executable, "-m", "twin_nodes.nodes.px4_bridge", *args], cwd=REPO,
                             env=dict(os.environ), stdout=log, stderr=subprocess.STDOUT)
        procs.append((p, log))
        return p

    yield domain, start
    for p, log in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        log.close()


def test_sim_bridge_publishes_twin_topics(ros_domain):
    domain, start = ros_domain
    port = _free_port()
    node = start("sim", "--ros-args", "-p", f"port:={port}", "-p", "host:=127.0.0.1", "-p", "publish_every:=2",
                 "-p", "speed_factor:=0.0")
    probe = Probe(domain, {t: msg_class(TOPICS[t].type) for t in TWIN})
    try:
        # a first client makes the link freewheel (and publish) until the probe has discovered the node
        dummy = ScriptedPX4(port)
        dummy.connect(timeout_s=30.0)
        assert probe.spin_until(lambda: len(probe.msgs["/clock"]) > 5 and len(probe.msgs["/twin/odom"]) > 2, 30.0), \
            "no /clock from the node"
        dummy.close()
        t_free = probe.msgs["/clock"][-1].clock.sec + probe.msgs["/clock"][-1].clock.nanosec * 1e-9
        # then the scripted PX4: armed at 0.9 for 2 s of lockstep
        peer = ScriptedPX4(port, command=lambda t: ([0.9] * 4, True))
        result = {}
        th = threading.Thread(target=lambda: result.setdefault("st", peer.run(t_free + 2.5)))
        th.start()
        probe.spin_until(lambda: not th.is_alive(), 60.0)
        th.join(1.0)
        peer.close()
        probe.spin_until(lambda: False, 0.5)
    finally:
        probe.close()
    assert node.poll() is None, "node died"
    assert result["st"].controls_tx > 400
    clock = np.array([c.clock.sec + c.clock.nanosec * 1e-9 for c in probe.msgs["/clock"]])
    assert np.all(np.diff(clock) > 0)
    np.testing.assert_allclose(np.round(clock / 0.004) * 0.004, clock, atol=1e-9)  # whole 4 ms steps
    odom = probe.msgs["/twin/odom"][-1]
    assert odom.header.frame_id == "odom" and odom.child_frame_id == "base_link"
    assert odom.pose.pose.position.z > 1.0                      # climbed (ENU z up)
    assert odom.twist.twist.linear.z > 0.5                      # body FLU: up while level
    q = odom.pose.pose.orientation
    assert abs(q.w) == pytest.approx(1.0, abs=1e-6)             # level, yaw 0 (nose East)
    assert np.allclose(probe.msgs["/twin/motors"][-1].data, 0.9, atol=1e-6)
    assert probe.msgs["/twin/throttle"][-1].data == pytest.approx(0.9, abs=1e-6)
    imu = probe.msgs["/twin/imu"][-1]
    assert imu.header.frame_id == "base_link" and imu.linear_acceleration.z > 9.0
    rest = [m for m in probe.msgs["/twin/imu"] if m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 < t_free]
    assert rest and np.mean([m.linear_acceleration.z for m in rest]) == pytest.approx(9.81, abs=0.1)


def test_telemetry_bridge_publishes_real_topics_and_goes_stale(ros_domain):
    domain, start = ros_domain
    port = _free_port(socket.SOCK_DGRAM)
    node = start("telemetry", "--ros-args", "-p", f"url:=udpin:127.0.0.1:{port}", "-p", "request_streams:=false",
                 "-p", "stale_after_s:=1.0")
    topics = {t: msg_class(TOPICS[t].type) for t in REAL}
    topics["/diagnostics"] = DiagnosticArray
    probe = Probe(domain, topics)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    mission = (4 << 16) | (4 << 24)
    stream = [
        mav.heartbeat_encode(2, 12, 1 | 128, mission, 4),
        mav.extended_sys_state_encode(0, 2),
        mav.local_position_ned_encode(1000, 1.0, 2.0, -3.0, 0.5, 0.0, 0.0),
        mav.attitude_quaternion_encode(1000, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.1),
        mav.highres_imu_encode(1000000, 0.0, 0.0, -9.8, 0.0, 0.0, 0.1, 0, 0, 0, 0, 0, 0, 0, 0),
        mav.servo_output_raw_encode(1000, 0, 1500, 1600, 1700, 1800, 0, 0, 0, 0),
        mav.battery_status_encode(0, 0, 0, 32767, [16100] + [65535] * 9, 520, -1, -1, 64),
        mav.position_target_local_ned_encode(1000, 1, 0b110111000000, 10.0, 20.0, -5.0, 1.0, 0.0, 0.0,
                                             0, 0, 0, 0.0, 0),
    ]
    try:
        got_all = False
        deadline = time.monotonic() + 30.0
        while not got_all and time.monotonic() < deadline:
            for msg in stream:
                tx.sendto(msg.pack(mav), ("127.0.0.1", port))
            probe.spin_until(lambda: False, 0.05)
            got_all = all(probe.msgs[t] for t in REAL)
        assert got_all, str({t: len(v) for t, v in probe.msgs.items()})
        n_diag = len(probe.msgs["/diagnostics"])
        assert probe.spin_until(lambda: any(d.status[0].level == DiagnosticStatus.STALE
                                            for d in probe.msgs["/diagnostics"][n_diag:]), 5.0)
    finally:
        tx.close()
        probe.close()
    assert node.poll() is None, "node died"
    m = probe.msgs
    _, p, q, v, w = cv.odom_arrays(m["/real/odom"][-1])
    np.testing.assert_allclose(p, [2.0, 1.0, 3.0])
    np.testing.assert_allclose(q, [math.sqrt(0.5), 0, 0, math.sqrt(0.5)], atol=1e-6)  # PX4 nose North
    np.testing.assert_allclose(w, [0.0, 0.0, -0.1], atol=1e-6)                        # FRD yaw rate -> FLU
    assert m["/real/odom"][-1].header.frame_id == "odom"
    _, sf, gyro, q_imu = cv.imu_arrays(m["/real/imu"][-1])
    np.testing.assert_allclose(sf, [0.0, 0.0, 9.8], atol=1e-6) and q_imu is None
    np.testing.assert_allclose(cv.motors_array(m["/real/motors"][-1]), [0.5, 0.6, 0.7, 0.8], atol=1e-6)
    assert m["/real/motors"][-1].layout.dim[0].label == "motor"
    assert cv.float_value(m["/real/throttle"][-1]) == pytest.approx(0.65, abs=1e-6)
    _, volts, amps_px4 = cv.battery_arrays(m["/real/battery"][-1])
    assert volts == pytest.approx(16.1, abs=1e-4) and amps_px4 == pytest.approx(5.2, abs=1e-4)
    assert m["/real/battery"][-1].current == pytest.approx(-5.2, abs=1e-4)
    assert m["/real/battery"][-1].percentage == pytest.approx(0.64, abs=1e-6)
    sp = cv.setpoint_array(m["/real/setpoint"][-1])
    np.testing.assert_allclose(sp[0:6], [20.0, 10.0, 5.0, 0.0, 1.0, 0.0], atol=1e-6)
    assert np.all(np.isnan(sp[6:]))                              # acceleration, yaw, yaw rate masked
    pose = m["/real/setpoint_pose"][-1].pose.position
    assert (pose.x, pose.y, pose.z) == pytest.approx((20.0, 10.0, 5.0))
    status = cv.status_array(m["/real/status"][-1])
    np.testing.assert_array_equal(status, [1.0, 3.0, 0.0])        # armed, AUTO_MISSION, in the air
    ok = [d.status[0] for d in m["/diagnostics"] if d.status[0].level == DiagnosticStatus.OK]
    assert ok and ok[-1].name == "px4_bridge/link" and ok[-1].message.startswith("armed AUTO.MISSION")
