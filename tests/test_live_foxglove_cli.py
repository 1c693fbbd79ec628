"""Issue 14: ``--foxglove`` beside ``bridge`` and ``monitor``, and ``topics list|echo`` seeing a live
``bridge sim`` node.

Fast: the command lines (``--domain-id``/``--wait`` before or after the ``topics`` sub-command,
``--foxglove`` on ``bridge``/``monitor``, one-line errors).  ROS: the commands as subprocesses on a
private domain, a scripted PX4 (:class:`twin_nodes.mavlink.simlink.ScriptedPX4`) flying ``bridge sim``
or a replay graph beside ``monitor``, and a ws-protocol client (``tests/foxglove_ws.py``) that
subscribes to every advertised channel and decodes each message by its advertised schema only.
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FLIGHT = REPO / "bags" / "sim_quadx_weak_motor3.ulg"
PARAMS = REPO / "params" / "px4_sih_quadx.yaml"
SIM_TOPICS = {"/clock", "/twin/odom", "/twin/motors", "/twin/throttle", "/twin/imu"}

# ----------------------------------------------------------------------------- fast: command lines


@pytest.mark.parametrize("argv", [
    ["topics", "--domain-id", "7", "--wait", "2.5", "list"],
    ["topics", "list", "--domain-id", "7", "--wait", "2.5"],
    ["topics", "--wait", "2.5", "list", "--domain-id", "7"],
    ["topics", "--domain-id", "7", "echo", "/twin/odom", "--wait", "2.5", "--count", "3"],
    ["topics", "echo", "/twin/odom", "--count", "3", "--domain-id", "7", "--wait", "2.5"],
])
def test_topics_options_before_or_after_the_subcommand(argv):
    from twin_nodes.cli import build_parser

    a = build_parser().parse_args(argv)
    assert a.domain_id == 7 and a.wait == 2.5
    if "echo" in argv:
        assert a.topic == "/twin/odom" and a.count == 3


def test_topics_defaults():
    from twin_nodes.cli import build_parser
    from twin_nodes.cli.graph_live import TOPICS_WAIT_S

    a = build_parser().parse_args(["topics", "list"])
    assert not hasattr(a, "domain_id") and not hasattr(a, "wait")  # the handler applies the defaults
    assert TOPICS_WAIT_S == 4.0


def test_foxglove_option_on_bridge_and_monitor():
    from twin_nodes.cli import build_parser

    p = build_parser()
    assert p.parse_args(["bridge", "sim"]).foxglove is None
    assert p.parse_args(["bridge", "sim", "--foxglove"]).foxglove == 8765
    assert p.parse_args(["bridge", "telemetry", "--url", "udpin:0.0.0.0:14550", "--foxglove", "9001"]).foxglove == 9001
    assert p.parse_args(["monitor", "--foxglove", "0"]).foxglove == 0
    assert p.parse_args(["monitor"]).foxglove is None


def test_foxglove_without_ros_and_bad_domain_are_one_line_errors(capsys):
    from twin_nodes.cli import main

    assert main(["bridge", "sim", "--no-ros", "--foxglove"]) == 2
    assert main(["bridge", "telemetry", "--url", "udpin:127.0.0.1:1", "--no-ros", "--foxglove", "0"]) == 2
    assert main(["topics", "list", "--domain-id", "999"]) == 2
    assert main(["monitor", "--domain-id", "-1", "--once"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[:2] == ["rotortwin: error: bridge sim: --foxglove needs ROS (rclpy); drop --no-ros",
                       "rotortwin: error: bridge telemetry: --foxglove needs ROS (rclpy); drop --no-ros"]
    assert len(err) == 4 and all(e.startswith("rotortwin: error: --domain-id: expected an integer in [0, 232]")
                                 for e in err[2:]), err


# ----------------------------------------------------------------------------- ROS


def _free_tcp_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def _rotortwin(args: list[str], env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "twin_nodes", *args], cwd=REPO, env=env, text=True,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)


def _stop(p: subprocess.Popen, timeout_s: float = 60.0) -> tuple[int, str]:
    """SIGINT (what Ctrl-C sends), then the exit code and stdout."""
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
    try:
        out, _ = p.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        p.kill()
        out, _ = p.communicate(timeout=10)
        return -9, out
    return p.returncode, out


def _wait_for_line(lines: list[str], text: str, timeout_s: float) -> None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if any(text in ln for ln in lines):
            return
        time.sleep(0.1)
    raise AssertionError(f"{text!r} not seen within {timeout_s:g} s:\n{''.join(lines)[-3000:]}")


def _fly(port: int, seconds: float) -> object:
    """A scripted PX4 on the simulator link: 1 s armed at 0, then 0.8 (a climb)."""
    from twin_nodes.mavlink.simlink import ScriptedPX4

    peer = ScriptedPX4(port, command=lambda t: ([0.0] * 4, t > 0.5) if t < 1.0 else ([0.8] * 4, True))
    try:
        peer.connect(timeout_s=60.0)
        return peer.run(seconds)
    finally:
        peer.close()


@pytest.fixture()
def domain_env():
    pytest.importorskip("rclpy")
    from twin_nodes.graph import ros_env
    from twin_nodes.graph.domains import lease_domain

    with lease_domain() as lease:  # held for the test: no other run takes this domain meanwhile
        yield lease.domain_id, ros_env(lease.domain_id)


@pytest.mark.ros
def test_topics_list_and_echo_see_a_live_bridge_sim(domain_env, tmp_path):
    """``bridge sim`` started as users start it (its own process, the environment's domain); ``topics``
    from another process given ``--domain-id`` after the sub-command, default discovery wait."""
    domain, env = domain_env
    port = _free_tcp_port()
    sim = _rotortwin(["bridge", "sim", "--port", str(port), "--publish-every", "5"], env)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(sim.stderr), daemon=True).start()
    def fly_until_stopped() -> None:
        try:
            _fly(port, 60.0)
        except ConnectionError:  # the simulator was stopped under it: the end of the test
            pass
    flight = threading.Thread(target=fly_until_stopped, daemon=True)
    try:
        _wait_for_line(lines, "simulator link for", 120)
        flight.start()  # /clock and /twin/... flow while the commands look
        cli_env = {k: v for k, v in env.items() if k != "ROS_DOMAIN_ID"}  # the domain from the command line
        r = subprocess.run([sys.executable, "-m", "twin_nodes", "topics", "list", "--domain-id", str(domain)],
                           cwd=REPO, env=cli_env, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        rows = {ln.split()[0]: ln.split()[1] for ln in r.stdout.splitlines() if ln.strip()}
        assert "(documented;" not in r.stdout, r.stdout  # it saw the network, not the fallback list
        assert {t: rows.get(t) for t in SIM_TOPICS} == {
            "/clock": "rosgraph_msgs/msg/Clock", "/twin/odom": "nav_msgs/msg/Odometry",
            "/twin/motors": "std_msgs/msg/Float32MultiArray", "/twin/throttle": "std_msgs/msg/Float32",
            "/twin/imu": "sensor_msgs/msg/Imu"}, r.stdout
        e = subprocess.run([sys.executable, "-m", "twin_nodes", "topics", "echo", "/twin/odom", "--count", "3",
                            "--domain-id", str(domain)], cwd=REPO, env=cli_env, capture_output=True, text=True,
                           timeout=120)
        assert e.returncode == 0, e.stderr
        assert [ln for ln in e.stdout.splitlines() if ln.startswith("--- /twin/odom #")] == \
            ["--- /twin/odom #1", "--- /twin/odom #2", "--- /twin/odom #3"], e.stdout[-2000:]
    finally:
        code, _ = _stop(sim)
        flight.join(60)
    assert code == 0, "".join(lines)[-2000:]


@pytest.mark.ros
def test_bridge_sim_foxglove_serves_every_channel(domain_env):
    pytest.importorskip("websockets")
    pytest.importorskip("google.protobuf")
    from foxglove_ws import FoxgloveClient, silent_channels, url_from_stderr

    _, env = domain_env
    port = _free_tcp_port()
    sim = _rotortwin(["bridge", "sim", "--port", str(port), "--publish-every", "5", "--foxglove", "0"], env)
    client = None
    try:
        url, lines = url_from_stderr(sim)
        client = FoxgloveClient(url).start()
        _wait_for_line(lines, "simulator link for", 120)
        peer = _fly(port, 6.0)
        time.sleep(1.5)  # the last scene/status records
    finally:
        cap = client.close() if client is not None else None
        code, _ = _stop(sim)
    assert code == 0, "".join(lines)[-2000:]
    assert cap is not None and not cap.errors, cap and cap.errors
    advertised = cap.topics()
    print(f"{len(advertised)} channels, retries {cap.retries}: "
          + ", ".join(f"{t} {len(v)}" for t, v in sorted(cap.messages.items())))
    assert silent_channels(cap) == [], (silent_channels(cap), cap.other_ops[:10])
    assert SIM_TOPICS | {"/viz/transforms", "/viz/scene", "/viz/motors", "/viz/status"} <= advertised
    assert "/viz/errors" not in advertised  # no metrics run beside a bare bridge: nothing to show
    assert not {t for t in advertised if t.startswith("/real/")}
    # the scripted climb is what was served: 6 s of simulated time, the twin above its start
    clock = [m.clock.sec + m.clock.nanosec * 1e-9 for _, m in cap.messages["/clock"]]
    assert clock[-1] == pytest.approx(6.0, abs=0.1) and peer.controls_tx > 1000
    z = [m.pose.pose.position.z for _, m in cap.messages["/twin/odom"]]
    assert z[-1] > z[0] + 1.0, (z[0], z[-1])
    mot = cap.messages["/viz/motors"][-1][1]
    assert mot["twin"] == [pytest.approx(0.8)] * 4 and mot["real"] == [None] * 4
    assert {tf.child_frame_id for _, m in cap.messages["/viz/transforms"] for tf in m.transforms} == {"twin/base_link"}
    assert cap.messages["/viz/status"][-1][1]["source"] == "simulator"


@pytest.mark.ros
@pytest.mark.slow
def test_monitor_foxglove_serves_every_channel_of_a_replay():
    pytest.importorskip("rclpy")
    pytest.importorskip("websockets")
    pytest.importorskip("google.protobuf")
    from foxglove_ws import FoxgloveClient, silent_channels, url_from_stderr

    from twin_nodes.graph import ros_env, run_graph
    from twin_nodes.live.attach import free_domain

    domain = free_domain()  # run_graph leases it for the replay; the monitor only watches it
    env = ros_env(domain)
    mon = _rotortwin(["monitor", "--domain-id", str(domain), "--foxglove", "0"], env)
    client = None
    res = None
    try:
        url, lines = url_from_stderr(mon)
        client = FoxgloveClient(url).start()
        res = run_graph(FLIGHT, PARAMS, domain_id=domain, progress=False, timeout_s=900, rate=0.0)
        time.sleep(2.0)
    finally:
        cap = client.close() if client is not None else None
        code, out = _stop(mon)
    assert code == 0, "".join(lines)[-2000:]
    assert res is not None and cap is not None and not cap.errors, cap and cap.errors
    advertised = cap.topics()
    print(f"{len(advertised)} channels, retries {cap.retries}")
    assert silent_channels(cap) == [], (silent_channels(cap), cap.other_ops[:10])
    assert {"/viz/transforms", "/viz/scene", "/viz/errors", "/viz/motors", "/viz/status", "/clock", "/real/odom",
            "/twin/odom", "/twin_error/xy/rmse_m", "/twin_error/final_json"} <= advertised
    served = json.loads(cap.messages["/twin_error/final_json"][-1][1].data)
    assert served["xy_rmse_m"] == pytest.approx(res.metrics["xy_rmse_m"])
    assert cap.messages["/viz/status"][-1][1]["source"] == "replay"
    # the monitor itself saw the same run: its table and the latched final table on stdout
    assert "twin error, rolling window" in out and "Twin vs real" in out, out[-2000:]
