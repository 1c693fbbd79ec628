"""recording.McapRecorder / read_bag / topic_counts / recover (rosbag2 + MCAP, no rclpy)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader

from twin_nodes.base.errors import LogError
from twin_nodes.logs.recording import McapRecorder, read_bag, recover, topic_counts

REPO = Path(__file__).resolve().parents[1]


def sample_messages(i: int) -> dict[str, dict]:
    t = 1_700_000_000_000_000_000 + i * 10_000_000
    hdr = {"stamp": t, "frame_id": "map"}
    return {
        "/twin/odom": {"header": hdr, "child_frame_id": "base_link",
                       "pose": {"pose": {"position": {"x": float(i), "y": 2.0, "z": 3.0},
                                         "orientation": {"x": 0.0, "y": 0.0, "z": 0.6, "w": 0.8}},
                                "covariance": np.arange(36.0)},
                       "twist": {"twist": {"linear": {"x": 1.5}, "angular": {"z": -0.25}}}},
        "/twin/pose": {"header": hdr, "pose": {"position": {"x": 1.0}}},
        "/imu": {"header": {"stamp": t, "frame_id": "base_link"},
                 "angular_velocity": {"x": 0.01 * i}, "linear_acceleration": {"z": 9.81},
                 "orientation_covariance": [-1.0] + [0.0] * 8},
        "/battery": {"header": hdr, "voltage": 16.2, "current": -12.5, "percentage": 0.8,
                     "power_supply_status": 2, "present": True, "cell_voltage": [4.05] * 4,
                     "location": "slot0", "serial_number": ""},
        "/joint_states": {"header": hdr, "name": ["m1", "m2", "m3", "m4"],
                          "velocity": [1000.0, 1001.0, 1002.0, float(i)]},
        "/status": {"data": f"tick {i}"},
        "/twin/residual": {"layout": {"dim": [{"label": "xyz", "size": 3, "stride": 3}]},
                           "data": [0.1, -0.2, float(i)]},
        "/clock": {"clock": {"sec": i // 100, "nanosec": (i % 100) * 10_000_000}},
        "/diagnostics": {"header": hdr, "status": [{"level": 1, "name": "twin", "message": "drift",
                                                    "values": [{"key": "rmse_m", "value": "0.3"}]}]},
    }


TYPES = {
    "/twin/odom": "nav_msgs/msg/Odometry",
    "/twin/pose": "geometry_msgs/PoseStamped",  # short form accepted
    "/imu": "sensor_msgs/msg/Imu",
    "/battery": "sensor_msgs/msg/BatteryState",
    "/joint_states": "sensor_msgs/msg/JointState",
    "/status": "std_msgs/msg/String",
    "/twin/residual": "std_msgs/msg/Float64MultiArray",
    "/clock": "rosgraph_msgs/msg/Clock",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}


def record(path: Path, n: int = 20, **kw) -> list[int]:
    times = []
    with McapRecorder(path, **kw) as rec:
        for topic, typ in TYPES.items():
            rec.add_topic(topic, typ, qos="sensor_data" if topic == "/imu" else "reliable")
        for i in range(n):
            for j, (topic, msg) in enumerate(sample_messages(i).items()):
                t = 1_000_000_000 + i * 10_000_000 + j  # unique, increasing
                rec.write(topic, msg, t)
                times.append(t)
    return times


def test_round_trip_with_anyreader(tmp_path):
    bag = tmp_path / "bag"
    record(bag, n=20)
    assert (bag / "metadata.yaml").is_file() and (bag / "bag.mcap").is_file()
    data = read_bag(bag)
    assert set(data) == set(TYPES) and all(len(v) == 20 for v in data.values())
    t, odom = data["/twin/odom"][7]
    assert t == 1_000_000_000 + 7 * 10_000_000
    assert odom.header.stamp.sec == 1_700_000_000 and odom.header.stamp.nanosec == 70_000_000
    assert odom.header.frame_id == "map" and odom.child_frame_id == "base_link"
    p = odom.pose.pose
    assert (p.position.x, p.position.y, p.position.z) == (7.0, 2.0, 3.0)
    assert (p.orientation.z, p.orientation.w) == (0.6, 0.8)
    assert np.array_equal(odom.pose.covariance, np.arange(36.0))
    assert odom.twist.twist.linear.x == 1.5 and odom.twist.twist.angular.z == -0.25
    pose = data["/twin/pose"][0][1]
    assert pose.pose.orientation.w == 1.0  # ROS default identity quaternion
    imu = data["/imu"][3][1]
    assert imu.angular_velocity.x == pytest.approx(0.03) and imu.linear_acceleration.z == 9.81
    assert imu.orientation_covariance[0] == -1.0
    bat = data["/battery"][0][1]
    assert (bat.voltage, bat.current, bat.present, bat.location) == pytest.approx((16.2, -12.5, True, "slot0"))
    assert np.allclose(bat.cell_voltage, 4.05) and bat.power_supply_status == 2
    js = data["/joint_states"][5][1]
    assert list(js.name) == ["m1", "m2", "m3", "m4"] and js.velocity[3] == 5.0
    assert data["/status"][9][1].data == "tick 9"
    res = data["/twin/residual"][4][1]
    assert res.layout.dim[0].label == "xyz" and list(res.data) == [0.1, -0.2, 4.0]
    clk = data["/clock"][15][1]
    assert (clk.clock.sec, clk.clock.nanosec) == (0, 150_000_000)
    diag = data["/diagnostics"][0][1]
    assert diag.status[0].level == 1 and diag.status[0].values[0].key == "rmse_m"
    assert topic_counts(bag) == {k: 20 for k in TYPES}


def test_mcap_layout_matches_rosbag2(tmp_path):
    bag = tmp_path / "bag"
    record(bag, n=5)
    with open(bag / "bag.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert {s.name for s in summary.schemas.values()} == {
            t if "/msg/" in t else t.replace("/", "/msg/") for t in TYPES.values()}
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        chans = {c.topic: c for c in summary.channels.values()}
        assert {c.message_encoding for c in chans.values()} == {"cdr"}
        imu_qos = yaml.safe_load(chans["/imu"].metadata["offered_qos_profiles"])
        assert imu_qos[0]["reliability"] == "best_effort" and imu_qos[0]["depth"] == 5
        odom_qos = yaml.safe_load(chans["/twin/odom"].metadata["offered_qos_profiles"])
        assert odom_qos[0]["reliability"] == "reliable" and odom_qos[0]["durability"] == "volatile"
        assert "rosbag2" in [m.name for m in reader.iter_metadata()]
        assert summary.statistics.message_count == 5 * len(TYPES)
        # CDR little-endian encapsulation header
        _, _, msg = next(reader.iter_messages())
        assert msg.data[:4] == b"\x00\x01\x00\x00"
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    assert meta["message_count"] == 5 * len(TYPES)


def test_attribute_objects_and_typestore_objects(tmp_path):
    """rclpy-like objects (attributes, bytes 'byte' fields) and rosbags objects both work."""
    bag = tmp_path / "bag"
    with McapRecorder(bag) as rec:
        rec.add_topic("diagnostics", "diagnostic_msgs/msg/DiagnosticStatus")
        status = SimpleNamespace(level=b"\x02", name="twin", message="x", hardware_id="",
                                 values=[SimpleNamespace(key="a", value="b")])
        rec.write("/diagnostics", status, 5)
        rec.add_topic("/v", "geometry_msgs/msg/Vector3")
        from rosbags.typesys import Stores, get_typestore

        vec = get_typestore(Stores.ROS2_JAZZY).types["geometry_msgs/msg/Vector3"](1.0, 2.0, 3.0)
        rec.write("/v", vec, 6)
    data = read_bag(bag)
    assert data["/diagnostics"][0][1].level == 2 and data["/diagnostics"][0][1].values[0].value == "b"
    v = data["/v"][0][1]
    assert (v.x, v.y, v.z) == (1.0, 2.0, 3.0)


def _complete_chunk_count(mcap_file: Path, cut: int, times: list[int]) -> int:
    """Messages in chunks that end before byte ``cut`` (from the intact file's index)."""
    with open(mcap_file, "rb") as f:
        idx = make_reader(f).get_summary().chunk_indexes
    ends = [c.message_end_time for c in idx if c.chunk_start_offset + c.chunk_length <= cut]
    if not ends:
        return 0
    return sum(1 for t in times if t <= max(ends))


@pytest.fixture(scope="module")
def chunked_bag(tmp_path_factory):
    """A bag of 1350 messages in ~20 chunks, and its contents read back."""
    bag = tmp_path_factory.mktemp("chunked") / "bag"
    times = record(bag, n=150, chunk_bytes=8 * 1024)
    return bag, times, read_bag(bag)


@pytest.mark.parametrize("fraction", [0.3, 0.55, 0.8, 0.999])
def test_recover_truncated_copy(tmp_path, chunked_bag, fraction):
    bag, times, original = chunked_bag
    mcap_file = bag / "bag.mcap"
    data = mcap_file.read_bytes()
    cut = int(len(data) * fraction)
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    (crashed / "crashed.mcap").write_bytes(data[:cut])  # no metadata.yaml, no summary
    with pytest.raises(LogError, match=r"crashed: metadata\.yaml: .*run .rotortwin record recover BAG."):
        read_bag(crashed)

    report = recover(crashed)
    expected = _complete_chunk_count(mcap_file, cut, times)
    assert expected > 0
    assert report.n_messages == expected
    assert report.out_dir == tmp_path / "crashed_recovered"
    assert report.complete is False and report.bytes_used <= cut == report.bytes_total
    assert sum(topic_counts(report.out_dir).values()) == expected
    # the recovered messages are the first `expected` ones, unchanged
    got = read_bag(report.out_dir)
    for topic, msgs in got.items():
        assert [t for t, _ in msgs] == [t for t, _ in original[topic][: len(msgs)]]
    assert got["/status"][-1][1].data == original["/status"][len(got["/status"]) - 1][1].data
    assert (crashed / "crashed.mcap").stat().st_size == cut  # source untouched


def test_recover_complete_bag_keeps_everything(tmp_path):
    bag = tmp_path / "bag"
    times = record(bag, n=30)
    report = recover(bag / "bag.mcap", tmp_path / "copy")
    assert report.complete and report.n_messages == len(times) and report.error == ""
    assert topic_counts(tmp_path / "copy") == topic_counts(bag)


def test_killed_recorder_is_recoverable(tmp_path):
    """SIGKILL a recording process: everything up to the last closed chunk survives."""
    script = textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(REPO)!r})
        from twin_nodes.logs.recording import McapRecorder
        rec = McapRecorder(sys.argv[1], chunk_bytes=64 * 1024, chunk_period_s=1e6)
        rec.add_topic("/status", "std_msgs/msg/String")
        for i in range(1500):
            rec.write("/status", {{"data": "x" * 40 + str(i)}}, 1000 + i)
        rec.flush()
        for i in range(1500, 1510):   # still in memory when the process dies
            rec.write("/status", {{"data": "y"}}, 1000 + i)
        print("READY", flush=True)
        time.sleep(60)
    """)
    bag = tmp_path / "live"
    proc = subprocess.Popen([sys.executable, "-c", script, str(bag)], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == "READY"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    assert not (bag / "metadata.yaml").exists()
    report = recover(bag)
    assert report.n_messages == 1500
    msgs = read_bag(report.out_dir)["/status"]
    assert msgs[-1][0] == 1000 + 1499 and msgs[-1][1].data.endswith("1499")


def test_exception_in_with_block_still_closes(tmp_path):
    bag = tmp_path / "bag"
    with pytest.raises(RuntimeError, match="boom"):
        with McapRecorder(bag) as rec:
            rec.add_topic("/status", "std_msgs/msg/String")
            rec.write("/status", {"data": "a"}, 1)
            raise RuntimeError("boom")
    assert topic_counts(bag) == {"/status": 1}


# --------------------------------------------------------------------------- bad input


def test_bad_input(tmp_path):
    bag = tmp_path / "bag"
    with McapRecorder(bag) as rec:
        rec.add_topic("/status", "std_msgs/msg/String")
        with pytest.raises(LogError, match=r"bag: /nope: expected a topic registered with add_topic"):
            rec.write("/nope", {"data": "a"}, 1)
        with pytest.raises(LogError, match=r"bag: /x: expected a message type known to the "
                                           r"typestore, got 'px4_msgs/msg/Nope'"):
            rec.add_topic("/x", "px4_msgs/msg/Nope")
        with pytest.raises(LogError, match=r"bag: 1bad/topic: expected a ROS topic name"):
            rec.add_topic("1bad/topic", "std_msgs/msg/String")
        with pytest.raises(LogError, match=r"bag: /status2\.qos: expected one of"):
            rec.add_topic("/status2", "std_msgs/msg/String", qos="fast")
        with pytest.raises(LogError, match=r"bag: /status\.dta: expected a field of std_msgs/msg/String: data"):
            rec.write("/status", {"dta": "a"}, 1)
        with pytest.raises(LogError, match=r"bag: /status\.t_ns: expected integer nanoseconds"):
            rec.write("/status", {"data": "a"}, 1.5)
        rec.add_topic("/imu", "sensor_msgs/msg/Imu")
        with pytest.raises(LogError, match=r"bag: /imu\.orientation_covariance: expected 9 elements, got 3"):
            rec.write("/imu", {"orientation_covariance": [0.0, 0.0, 0.0]}, 1)
        rec.add_topic("/bat", "sensor_msgs/msg/BatteryState")
        with pytest.raises(LogError, match=r"bag: /bat\.power_supply_status: expected uint8 in \[0, 255\], got 300"):
            rec.write("/bat", {"power_supply_status": 300}, 1)
    with pytest.raises(LogError, match=r"bag: out_dir: expected a new directory"):
        McapRecorder(bag)
    with pytest.raises(LogError, match=r"bag: recorder: expected an open recorder"):
        rec.write("/status", {"data": "a"}, 2)
    with pytest.raises(LogError, match=r"missing: bag: expected an existing rosbag2 directory"):
        read_bag(tmp_path / "missing")
    with pytest.raises(LogError, match=r"copy: out_dir: expected a directory that does not exist"):
        (tmp_path / "copy").mkdir()
        recover(bag, tmp_path / "copy")
