"""The live graph as real processes (rclpy, Fast DDS) on a private ROS_DOMAIN_ID with
localhost-only discovery: topics flow, counts in the MCAP match the replayed log, the
stored metrics reproduce, a killed recorder's bag is recoverable, bad files fail cleanly."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import shared_log

pytest.importorskip("rclpy", reason="ROS 2 wheels (pip install -e '.[ros]')")

from twin_nodes.logs.streams import replay_streams  # noqa: E402
from twin_nodes.graph import node_command, regress_bag, ros_env, run_graph  # noqa: E402
from twin_nodes.twin.compare import compare_log  # noqa: E402
from twin_nodes.vehicle.params import load_params, params_dir  # noqa: E402
from twin_nodes.logs.recording import topic_counts  # noqa: E402
from twin_nodes.logs.ulog_io import read_ulog  # noqa: E402

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]
# (folder, log, params, replay rate): the short real log is paced at 5x so that the monitor sees it live
CASES = [("sitl", "px4sih_default_triangle.ulg", "px4_sih_quadx", 0.0),
         ("real", "real_cubeorange_takeoff_land.ulg", "quad_c_3dr", 5.0)]


@pytest.mark.parametrize("sub,name,params,rate", CASES, ids=[c[1] for c in CASES])
def test_graph_end_to_end(tmp_path, sub, name, params, rate):
    log_path = shared_log(sub, name)
    pfile = params_dir() / f"{params}.yaml"
    from twin_nodes.graph.domains import lease_domain

    with lease_domain() as lease:  # a free domain (released: run_graph leases it itself)
        domain = lease.domain_id
    env = ros_env(domain)
    # a live viewer on the same private domain while the graph runs
    mon = subprocess.Popen([sys.executable, "-m", "twin_nodes", "monitor", "--once", "--duration", "60"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                           start_new_session=True)
    try:
        res = run_graph(log_path, pfile, run_dir=tmp_path / "run", bag=str(tmp_path / "bag"), domain_id=domain,
                        progress=False, timeout_s=300, rate=rate)
    finally:
        try:
            out, _ = mon.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            mon.send_signal(signal.SIGINT)
            out, _ = mon.communicate(timeout=10)
    m = res.metrics
    print(f"{name}: graph {res.replay_stats.get('real_time_factor', 0):.1f}x real time; "
          f"throttle RMSE {m['throttle_rmse'] * 100:.2f} %, XY RMSE {m['xy_rmse_m']:.2f} m")
    assert all(c in (0, None) for c in res.exit_codes.values()), res.exit_codes
    for k in ("xy_rmse_m", "xy_p75_m", "z_rmse_m", "z_p75_m", "throttle_rmse", "throttle_median"):
        assert math.isfinite(m[k]), k
    assert len(m["motor_p75"]) == 4 and all(math.isfinite(v) for v in m["motor_p75"])
    # topics flowed to an outside subscriber
    assert "xy [m]" in out and "throttle [%]" in out, out

    # every replayed message is in the MCAP, and the replay published what the log holds
    log = read_ulog(log_path)
    streams, _ = replay_streams(log)
    counts = topic_counts(tmp_path / "bag")
    for s in streams:
        assert counts[s.topic] == len(s) == res.replay_stats["counts"][s.topic], s.topic
    n_twin = counts["/twin/odom"]
    assert n_twin > 100 and counts["/twin/motors"] == counts["/twin/throttle"] == counts["/twin/imu"] == n_twin
    assert counts["/twin_error/final_json"] == 1 and counts["/replay/done"] == 1
    assert counts["/twin_error/xy/rmse_m"] > 3

    # the numbers stored at record time are reproduced from the recorded topics
    stored, fresh, problems = regress_bag(tmp_path / "bag")
    assert problems == [], problems
    assert stored["throttle_rmse"] == pytest.approx(m["throttle_rmse"], rel=1e-9)

    # the graph computes what the offline path computes (same engine, event-driven inputs; the graph's twin
    # gets each setpoint sample as it comes, so the offline path holds them too: setpoint_between_samples)
    off = compare_log(log, load_params(pfile), setpoint_between_samples=False).metrics
    for k in ("xy_rmse_m", "z_rmse_m", "throttle_rmse"):
        assert m[k] == pytest.approx(off[k], rel=0.05, abs=0.002), k
    if sub == "sitl":
        assert m["throttle_rmse"] < 0.03


def test_regress_self_check_detects_a_changed_result(tmp_path):
    """A recording whose stored numbers no longer match its topics fails `regress --self-check` (exit 1)."""
    import shutil

    from twin_nodes.logs.recording import McapRecorder, read_bag

    log_path = shared_log("real", "real_cubeorange_takeoff_land.ulg")
    run_graph(log_path, params_dir() / "quad_c_3dr.yaml", run_dir=tmp_path / "run", bag=str(tmp_path / "bag"),
              progress=False, timeout_s=300)
    msgs = read_bag(tmp_path / "bag")
    stored = json.loads(msgs["/twin_error/final_json"][-1][1].data)
    stored["throttle_rmse"] *= 1.5
    # rewrite the bag with a doctored final message
    out = tmp_path / "doctored"
    with McapRecorder(out) as rec:
        for topic, rows in msgs.items():
            if not rows:
                continue
            rec.add_topic(topic, type(rows[0][1]).__msgtype__)
            for t, msg in rows:
                if topic == "/twin_error/final_json":
                    msg = {"data": json.dumps(stored)}
                rec.write(topic, msg, t)
    r = subprocess.run([sys.executable, "-m", "twin_nodes", "regress", "--self-check", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, r.stderr
    assert "REGRESSION" in r.stderr and "throttle_rmse" in r.stderr
    shutil.rmtree(out)


def test_bad_ulog_is_a_one_line_error(tmp_path):
    bad = tmp_path / "bad.ulg"
    bad.write_bytes(b"not a ulog at all" * 10)
    env = ros_env()
    r = subprocess.run(node_command("replay", {"ulog": str(bad)}), env=env, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2
    err = [ln for ln in r.stderr.splitlines() if ln.strip() and "RTPS" not in ln]
    assert len(err) == 1 and err[0].startswith("rotortwin node: error:") and "bad.ulg" in err[0], r.stderr
    cli = subprocess.run([sys.executable, "-m", "twin_nodes", "compare", str(bad), "--params",
                          str(params_dir() / "px4_sih_quadx.yaml"), "--quiet"], env=env, capture_output=True,
                         text=True, timeout=120)
    assert cli.returncode != 0 and "bad.ulg" in cli.stderr


def test_killed_recorder_is_recoverable(tmp_path):
    """kill -9 the recorder mid-replay; `rotortwin record recover` rebuilds a readable bag."""
    log_path = shared_log("real", "real_cubeorange_takeoff_land.ulg")
    env = ros_env()
    bag = tmp_path / "bag"
    rec = subprocess.Popen(node_command("recorder", {"out": str(bag), "chunk_period_s": 0.5}), env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    rp = subprocess.Popen(node_command("replay", {"ulog": str(log_path), "rate": 5.0, "wait_for": ["recorder"],
                                                  "progress": True}),
                          env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                          start_new_session=True)
    try:
        t_end = time.monotonic() + 90
        progressed = 0.0
        while time.monotonic() < t_end and progressed < 12.0:
            line = rp.stdout.readline()
            if line.startswith("PROGRESS"):
                progressed = float(line.split()[1])
        assert progressed >= 12.0, "the replay did not get going"
        os.kill(rec.pid, signal.SIGKILL)
        rec.wait(10)
    finally:
        for p in (rp, rec):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
    assert not (bag / "metadata.yaml").exists()
    r = subprocess.run([sys.executable, "-m", "twin_nodes", "record", "recover", str(bag)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    counts = topic_counts(Path(str(bag) + "_recovered"))
    assert counts.get("/real/odom", 0) > 20 and counts.get("/real/imu", 0) > 100, counts


_ANNOUNCER = r"""
import json, sys, time
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float32, String

first, rest, total = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
rclpy.init()
node = rclpy.create_node("announcer")
latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
plan = node.create_publisher(String, "/replay/plan", latched)
thr = node.create_publisher(Float32, "/real/throttle", QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
t_end = time.monotonic() + 60
while time.monotonic() < t_end and (plan.get_subscription_count() < 1 or thr.get_subscription_count() < 1):
    rclpy.spin_once(node, timeout_sec=0.05)
plan.publish(String(data=json.dumps({"counts": {"/real/throttle": total}, "t0_ns": 1_000_000_000})))
for i in range(first):
    thr.publish(Float32(data=float(i)))
print("FIRST", flush=True)
time.sleep(2.0)  # the recorder is told to stop in this gap
for i in range(rest):
    thr.publish(Float32(data=float(first + i)))
print("REST", flush=True)
time.sleep(4.0)
"""


@pytest.mark.parametrize("rest,drain_s,code,recorded", [(6, 20.0, 0, 10), (0, 1.0, 3, 4)], ids=["late", "never"])
def test_recorder_drains_what_was_announced(tmp_path, rest, drain_s, code, recorded):
    """Told to stop while 6 of the 10 messages the plan announced are still to come, the recorder waits for
    them (its drain counts announced messages, not quiet time); when they never come it finalises and keeps
    the bag, names the gap in one line and exits 3."""
    from twin_nodes.graph.domains import lease_domain
    from twin_nodes.logs.recording import INCOMPLETE_EXIT

    with lease_domain() as lease:
        env = ros_env(lease.domain_id)
        bag = tmp_path / "bag"
        rec = subprocess.Popen(node_command("recorder", {"out": str(bag), "drain_timeout_s": drain_s}), env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
        pub = subprocess.Popen([sys.executable, "-c", _ANNOUNCER, "4", str(rest), "10"], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, start_new_session=True)
        try:
            assert pub.stdout.readline().strip() == "FIRST"
            time.sleep(0.5)
            rec.send_signal(signal.SIGINT)
            _, err = rec.communicate(timeout=60)
        finally:
            for p in (pub, rec):
                if p.poll() is None:
                    p.kill()
                    p.wait()
    assert rec.returncode == code == (INCOMPLETE_EXIT if recorded < 10 else 0), err
    assert topic_counts(bag)["/real/throttle"] == recorded
    said = [ln for ln in err.splitlines() if "incomplete" in ln]
    if recorded < 10:
        assert len(said) == 1 and "/real/throttle 4 of 10" in said[0] and str(bag) in said[0], err
    else:
        assert not said, err
