"""The graph's pure parts: replay streams vs the ULog, timelines, reorder buffer, params choice,
topic-data metrics equal to the offline compare, node parameters that stay strings."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import need_log, shared_log, ulog_params

from twin_nodes.logs.streams import HEADERLESS, event_order, replay_streams
from twin_nodes.twin.compare import compare_log, metrics_from_streams
from twin_nodes.base.errors import TwinError
from twin_nodes.nodes.common import ReorderBuffer, Timeline
from twin_nodes.vehicle.params import params_dir, shipped
from twin_nodes.logs.ulog_io import list_topics, read_ulog

SOURCE = {"/real/odom": ["vehicle_local_position"], "/real/imu": ["sensor_combined"],
          "/real/battery": ["battery_status"], "/real/setpoint": ["trajectory_setpoint"],
          "/real/throttle": ["vehicle_thrust_setpoint", "actuator_controls_0"],
          "/real/motors": ["actuator_motors", "actuator_outputs"]}


@pytest.mark.parametrize("log_path", ulog_params("real") + ulog_params("sitl"))
def test_replay_streams_match_ulog_counts(log_path):
    """One message per logged sample of the source topic (less pre-start samples read_ulog drops)."""
    path = need_log(log_path)
    log = read_ulog(path)
    streams, warns = replay_streams(log)
    counts = {s.topic: len(s) for s in streams}
    raw = {}
    for name, mid, n, _ in list_topics(path):
        raw.setdefault(name, {})[mid] = n
    for topic, sources in SOURCE.items():
        assert topic in counts, (topic, warns)
        src = next(s for s in sources if s in raw)
        series_src = [s for s in streams if s.topic == topic][0].source
        mid = 1 if "[1]" in series_src else 0
        n = counts[topic]
        ys = log.get("setpoint_yaw_enu")
        if topic == "/real/setpoint" and ys is not None and ys.source.startswith("vehicle_attitude_setpoint"):
            # the trajectory's samples and, between them, the 20 Hz attitude setpoint's yaw samples
            tp = log.require("setpoint_position_enu").t_s
            inner = ys.t_s[(ys.t_s > tp[0]) & (ys.t_s <= tp[-1])]
            assert n == len(np.union1d(tp, inner)), (topic, n)
            assert raw[src][0] < n <= raw[src][0] + raw["vehicle_attitude_setpoint"][0] + 1
            n = len(tp)
        assert abs(n - raw[src][mid]) <= 1, (topic, n, src, raw[src])
    assert counts["/real/odom"] == len(log.get("position_enu"))
    assert counts["/real/imu"] == len(log.get("specific_force_flu"))
    t, si, _ = event_order(streams)
    assert np.all(np.diff(t) >= 0) and len(t) == sum(counts.values())


def test_event_order_is_stable_for_ties():
    from twin_nodes.logs.streams import Stream

    a = Stream("/a", np.array([0.0, 1.0]))
    b = Stream("/b", np.array([0.0, 0.5, 1.0]))
    t, si, row = event_order([a, b])
    assert t.tolist() == [0.0, 0.0, 0.5, 1.0, 1.0]
    assert si.tolist() == [0, 1, 1, 0, 1] and row.tolist() == [0, 0, 1, 1, 2]


def test_headerless_set_matches_topic_table():
    from msgs_py.topics import TOPICS

    for name in HEADERLESS:
        assert not TOPICS[name].stamped
    for name, spec in TOPICS.items():
        if name.startswith("/real/") and not spec.stamped:
            assert name in HEADERLESS


def test_timeline_takes_in_order_and_refuses_extra():
    tl = Timeline()
    assert tl.take("/x") is None and not tl.has("/x")
    tl.set("/x", np.array([5, 7], dtype=np.int64))
    assert (tl.take("/x"), tl.take("/x")) == (5, 7)
    with pytest.raises(IndexError, match="beyond the 2 announced"):
        tl.take("/x")


def test_reorder_buffer_releases_in_time_order_after_lag():
    rb = ReorderBuffer(lag_ns=10)
    for t in (5, 1, 3, 20, 3):
        rb.push(t, t)
    rb.advance(14)
    assert [t for t, _ in rb.pop_ready()] == [1, 3, 3]
    rb.push(2, "late")
    assert rb.late == 1
    assert [t for t, _ in rb.pop_ready(flush=True)] == [2, 5, 20]


def test_default_params_from_sys_autostart():
    from twin_nodes.graph import default_params_for

    p = default_params_for(shared_log("sitl", "px4sih_default_triangle.ulg"))
    assert p == params_dir() / "px4_sih_quadx.yaml"
    # no shipped file for SYS_AUTOSTART 4014: the nominal built from the log itself (issue 10)
    nominal = default_params_for(shared_log("real", "real_s500_rcac_mission1.ulg"))
    assert nominal.is_file() and nominal.parent != params_dir() and nominal.suffix == ".yaml"
    with pytest.raises(TwinError, match="params YAML"):
        default_params_for(shared_log("real", "real_s500_rcac_mission1.ulg"), str(params_dir() / "missing.yaml"))
    explicit = params_dir() / "quad_c_3dr.yaml"
    assert default_params_for(shared_log("real", "real_s500_rcac_mission1.ulg"), str(explicit)) == explicit


def test_metrics_from_topic_data_equal_offline_compare():
    """The metrics node's end-of-flight path (topic data -> FlightLog/TwinRun -> align) gives the
    offline compare_log numbers when fed the same data."""
    log = read_ulog(shared_log("sitl", "px4sih_default_triangle.ulg"))
    res = compare_log(log, shipped("px4_sih_quadx"))
    pos, thr, mot = log.get("position_enu"), log.get("throttle"), log.get("motors")
    st_t = np.unique(np.concatenate([log.get("armed").t_s, log.get("landed").t_s]))
    status = np.column_stack([log.get("armed").at(st_t, "previous")[:, 0], np.full(len(st_t), np.nan),
                              log.get("landed").at(st_t, "previous")[:, 0]])
    real = {"position_enu": (pos.t_s, pos.values), "throttle": (thr.t_s, thr.values[:, 0]),
            "motors": (mot.t_s, mot.values), "status": (st_t, status)}
    run = res.run
    twin = {"t": run.t, "p": run.x[:, :3], "throttle": run.throttle, "motors": run.motors}
    m2 = metrics_from_streams(real, twin, "closed", 4).metrics
    for k in ("xy_rmse_m", "z_p75_m", "throttle_rmse", "throttle_median", "n_samples"):
        assert m2[k] == pytest.approx(res.metrics[k], rel=1e-9), k
    np.testing.assert_allclose(m2["motor_p75"], res.metrics["motor_p75"], rtol=1e-9)


def test_monitor_table_format():
    from twin_nodes.graph.live import format_monitor

    vals = {"/twin_error/xy/rmse_m": 0.5, "/twin_error/throttle/p75": 0.012, "/twin_error/motor2/max": 0.1,
            "/twin_error/motor10/max": 0.2}
    text = format_monitor(vals, 12.0)
    lines = text.splitlines()
    assert "12.0 s" in lines[0]
    assert lines[3].startswith("xy [m]") and "0.500" in lines[3]
    assert any(line.startswith("throttle [%]") and "1.200" in line for line in lines)
    assert [ln.split()[0] for ln in lines[3:]] == ["xy", "throttle", "motor2", "motor10"]


def test_node_command_keeps_string_parameters_strings():
    """A flight file named `12345` or `true` reaches the node as a string (ROS parses -p values as YAML)."""
    from twin_nodes.graph import node_command

    cmd = node_command("replay", {"ulog": "12345", "rate": 0.0, "wait_for": ["twin", "it's"], "progress": True})
    assert "ulog:='12345'" in cmd and "rate:=0.0" in cmd and "progress:=true" in cmd
    assert "wait_for:=['twin','it''s']" in cmd
    assert "ulog:='true'" in node_command("replay", {"ulog": "true"})


def test_twin_engine_flies_px4_manual_modes_from_status_and_throttle():
    """The graph's twin gets PX4's nav_state (/real/status) and the logged collective thrust
    (/real/throttle) as the offline runner does: in MANUAL (nav_state 0) it flies the pilot's thrust
    (on the real climb35m log this took the graph's Z RMSE from 2.42 m to 1.24 m, offline 1.21 m)."""
    from twin_nodes.logs import conversions as cv
    from twin_nodes.nodes.engine import TWIN_INPUTS, TwinEngine

    assert "/real/throttle" in TWIN_INPUTS
    eng = TwinEngine(shipped("px4_sih_quadx"))
    r = eng.runner
    eng._apply(0, "/real/odom", cv.odom_msg(0, np.array([0.0, 0.0, 5.0]), np.array([1.0, 0, 0, 0]),
                                             np.zeros(3), np.zeros(3)))
    eng._apply(1_000_000, "/real/status", cv.status_msg(1.0, 2.0, 0.0))   # armed, POSCTL
    eng._apply(2_000_000, "/real/throttle", cv.float32_msg(0.3))
    assert r.nav_state == 2.0 and r.real_throttle == pytest.approx(0.3) and not r.manual
    eng._apply(3_000_000, "/real/status", cv.status_msg(1.0, 0.0, 0.0))   # armed, MANUAL
    assert r.manual and r.real_throttle == pytest.approx(0.3)
    eng._apply(4_000_000, "/real/status", cv.status_msg(float("nan"), float("nan"), float("nan")))
    assert not r.manual


def test_the_recorder_watermark_waits_for_the_slowest_live_follower():
    """The replay's clock at 10 s, the twin's outputs at 7.5 s (a CPU-starved twin node, more than the 2 s
    reorder lag behind): the recorder releases only up to the twin's stamp, so its next message (7.6 s) is not
    late (before, released up to 8 s: it landed in a later MCAP chunk than 8 s of replay data, 1 overlap of 31
    chunks on a clean-clone CI run); a follower silent for 1 s of wall time stops holding it back."""
    from twin_nodes.nodes.engine import FollowerWatermark

    s = 1_000_000_000
    fw = FollowerWatermark(stale_s=1.0)
    assert fw.limit(10 * s, wall_s=0.0) == 10 * s              # no follower yet: the clock
    fw.seen("/twin/odom", int(7.5 * s), wall_s=100.0)
    fw.seen("/twin_error/diagnostics", int(9.0 * s), wall_s=100.0)
    assert fw.limit(10 * s, wall_s=100.2) == int(7.5 * s)
    rb = ReorderBuffer(lag_ns=2 * s)
    for t in (int(5.4 * s), int(7.0 * s), int(9.9 * s)):
        rb.push(t, t)
    rb.advance(fw.limit(10 * s, wall_s=100.2))
    assert [t for t, _ in rb.pop_ready()] == [int(5.4 * s)]    # up to 7.5 - 2 s
    rb.push(int(7.6 * s), "twin")
    assert rb.late == 0
    assert fw.limit(10 * s, wall_s=101.5) == 10 * s             # both silent for 1.5 s: the clock again
    fw.seen("/twin/odom", int(6.0 * s), wall_s=102.0)           # stamps never go back
    assert fw.limit(10 * s, wall_s=102.1) == int(7.5 * s)
