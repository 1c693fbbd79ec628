"""ulog_write.write_px4_ulog: round trip through read_ulog and pyulog, atomicity, bad input."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from conftest import shared_log
from pyulog import ULog

from twin_nodes.base import frames as F
from twin_nodes.logs import ulog_write as W
from twin_nodes.base.errors import LogError
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.logs.ulog_write import write_px4_ulog

T0_US = 2_000_000  # PX4 hrt time of the first sample


def _times(rate_hz: float, dur_s: float = 20.0) -> np.ndarray:
    return (T0_US + np.arange(int(dur_s * rate_hz)) * int(1e6 / rate_hz)).astype(np.uint64)


def synthetic_flight() -> dict[str, dict[str, np.ndarray]]:
    """A 20 s helix in PX4 conventions (NED, FRD, q FRD->NED)."""
    rng = np.random.default_rng(0)
    tl = _times(50)
    s = (tl - T0_US) * 1e-6
    x, y, z = 5 * np.cos(0.3 * s), 5 * np.sin(0.3 * s), -0.5 * s
    lpos = dict(timestamp=tl, x=x, y=y, z=z, vx=-1.5 * np.sin(0.3 * s), vy=1.5 * np.cos(0.3 * s),
                vz=np.full(s.size, -0.5), ax=-0.45 * np.cos(0.3 * s), ay=-0.45 * np.sin(0.3 * s),
                az=np.zeros(s.size), heading=F.wrap_pi(0.3 * s + np.pi / 2),
                xy_valid=np.ones(s.size, bool), z_valid=np.ones(s.size, bool),
                v_xy_valid=np.ones(s.size, bool), v_z_valid=np.ones(s.size, bool))
    ta = _times(100)
    sa = (ta - T0_US) * 1e-6
    q = F.quat_from_euler(0.2 * np.sin(sa), 0.1 * np.cos(0.5 * sa), F.wrap_pi(0.3 * sa + 3.0))
    tm = _times(50)
    ctrl = np.full((tm.size, 12), np.nan)
    ctrl[:, :4] = 0.5 + 0.05 * rng.standard_normal((tm.size, 4))
    tsc = _times(200)
    n_tr = _times(25).size
    traj_pos = np.column_stack([np.full(n_tr, 1.0), np.full(n_tr, 2.0), np.full(n_tr, -3.0)])
    traj_pos[: n_tr // 2] = np.nan  # not controlled in the first half
    tb = _times(5)
    te = _times(10)
    esc = {"timestamp": te, "esc_count": np.full(te.size, 4)}
    for i, f in enumerate((101, 102, 104, 103)):  # wired out of order: map by function
        esc[f"esc[{i}].esc_rpm"] = np.full(te.size, 1000 * (f - 100))
        esc[f"esc[{i}].actuator_function"] = np.full(te.size, f)
    return {
        "vehicle_local_position": lpos,
        "vehicle_local_position_groundtruth": {k: lpos[k] for k in ("timestamp", "x", "y", "z",
                                                                    "vx", "vy", "vz")},
        "vehicle_attitude": {"timestamp": ta, "q": q},
        "vehicle_attitude_groundtruth": {"timestamp": ta, "q": q},
        "vehicle_angular_velocity": {"timestamp": ta, "xyz": rng.normal(size=(ta.size, 3)),
                                     "xyz_derivative": rng.normal(size=(ta.size, 3))},
        "actuator_motors": {"timestamp": tm, "control": ctrl},
        "vehicle_thrust_setpoint": {"timestamp": tm, "xyz": np.column_stack(
            [np.zeros(tm.size), np.zeros(tm.size), -np.nanmean(ctrl[:, :4], axis=1)])},
        "sensor_combined": {
            "timestamp": tsc, "gyro_rad": rng.normal(size=(tsc.size, 3)),
            "accelerometer_m_s2": rng.normal(size=(tsc.size, 3)) + [0, 0, -9.81],
            "accelerometer_timestamp_relative": np.zeros(tsc.size, np.int32),
            "gyro_integral_dt": np.full(tsc.size, 5000), "accelerometer_integral_dt": np.full(tsc.size, 5000)},
        "battery_status": {"timestamp": tb, "voltage_v": np.linspace(16.8, 15.9, tb.size),
                           "current_a": np.full(tb.size, 12.5), "remaining": np.linspace(1, 0.8, tb.size)},
        "trajectory_setpoint": {"timestamp": _times(25), "position": traj_pos,
                                "velocity": np.zeros((n_tr, 3)), "acceleration": np.full((n_tr, 3), np.nan),
                                "yaw": np.full(n_tr, 0.0), "yawspeed": np.full(n_tr, np.nan)},
        "vehicle_status": {"timestamp": np.array([T0_US, T0_US + 1_000_000, T0_US + 19_000_000], np.uint64),
                           "arming_state": np.array([1, 2, 1]), "nav_state": np.array([4, 3, 4])},
        "vehicle_land_detected": {"timestamp": np.array([T0_US, T0_US + 2_000_000, T0_US + 18_000_000],
                                                        np.uint64),
                                  "landed": np.array([True, False, True])},
        "hover_thrust_estimate": {"timestamp": tb, "hover_thrust": np.full(tb.size, 0.48),
                                  "valid": np.ones(tb.size, bool)},
        "esc_status": esc,
    }


PARAMS = {"CA_ROTOR_COUNT": 4, "MPC_THR_HOVER": 0.5, "THR_MDL_FAC": 0.0}
INFO = {"ver_sw": "rotortwin-test", "sys_name": "PX4"}


def f32(a):
    return np.asarray(a, dtype=np.float32).astype(float)


def test_round_trip_through_read_ulog(tmp_path):
    topics = synthetic_flight()
    path = write_px4_ulog(tmp_path / "sim.ulg", topics, PARAMS, INFO,
                          messages=[(T0_US + 5_000_000, "INFO", "Takeoff detected")])
    fl = read_ulog(path)
    assert fl.start_us == T0_US and fl.n_motors == 4
    assert fl.params["CA_ROTOR_COUNT"] == 4.0 and fl.params["MPC_THR_HOVER"] == pytest.approx(0.5)
    assert fl.info["ver_sw"] == "rotortwin-test"
    assert not any("corrupt" in w for w in fl.warnings)
    lp = topics["vehicle_local_position"]

    pos = fl.require("position_enu")
    assert np.allclose(pos.t_s, (lp["timestamp"] - T0_US) * 1e-6)
    np.testing.assert_allclose(pos.values, F.ned_to_enu(f32(np.column_stack([lp["x"], lp["y"], lp["z"]]))))
    np.testing.assert_allclose(fl.require("velocity_enu").values,
                               F.ned_to_enu(f32(np.column_stack([lp["vx"], lp["vy"], lp["vz"]]))))
    np.testing.assert_allclose(fl.require("groundtruth_position_enu").values, pos.values)
    # ENU z up: the helix climbs (NED z = -0.5 t)
    assert pos.values[-1, 2] > pos.values[0, 2] + 9.0

    q_expect = F.q_ned_frd_to_enu_flu(f32(topics["vehicle_attitude"]["q"]))
    assert F.quat_angle_between(fl.require("attitude_q").values, q_expect).max() < 1e-6
    assert F.quat_angle_between(fl.require("groundtruth_attitude_q").values, q_expect).max() < 1e-6
    av = topics["vehicle_angular_velocity"]
    np.testing.assert_allclose(fl.require("body_rates_flu").values, F.frd_to_flu(f32(av["xyz"])))
    np.testing.assert_allclose(fl.require("angular_accel_flu").values,
                               F.frd_to_flu(f32(av["xyz_derivative"])))
    sc = topics["sensor_combined"]
    np.testing.assert_allclose(fl.require("gyro_flu").values, F.frd_to_flu(f32(sc["gyro_rad"])))
    np.testing.assert_allclose(fl.require("specific_force_flu").values,
                               F.frd_to_flu(f32(sc["accelerometer_m_s2"])))

    m = fl.require("motors")
    ctrl = f32(topics["actuator_motors"]["control"][:, :4])
    armed = (m.t_s >= 1.0) & (m.t_s < 19.0)  # vehicle_status: armed 1 s .. 19 s
    np.testing.assert_allclose(m.values[armed], ctrl[armed])
    assert np.isnan(m.values[~armed]).all()
    np.testing.assert_allclose(fl.require("throttle").values[:, 0],
                               -f32(topics["vehicle_thrust_setpoint"]["xyz"][:, 2]))

    sp = fl.require("setpoint_position_enu").values
    half = sp.shape[0] // 2
    assert np.isnan(sp[:half]).all() and np.allclose(sp[half:], [2.0, 1.0, 3.0])
    assert np.isnan(fl.require("setpoint_accel_enu").values).all()
    assert np.allclose(fl.require("setpoint_yaw_enu").values, np.pi / 2)  # North -> +90 deg
    np.testing.assert_allclose(fl.require("battery_v").values[:, 0],
                               f32(topics["battery_status"]["voltage_v"]))
    assert fl.require("nav_state").values[:, 0].tolist() == [4, 3, 4]
    assert fl.require("armed").values[:, 0].tolist() == [0, 1, 0]
    assert fl.airborne_interval() == pytest.approx((2.0, 18.0))
    assert np.allclose(fl.require("esc_rpm").values, [1000, 2000, 3000, 4000])
    assert np.allclose(fl.require("hover_thrust").values, 0.48)


def test_pyulog_reads_it_exactly(tmp_path):
    topics = synthetic_flight()
    path = write_px4_ulog(tmp_path / "sim.ulg", topics, PARAMS, INFO,
                          messages=[(T0_US + 5_000_000, "WARNING", "low battery")])
    u = ULog(str(path))
    assert not u.file_corruption
    assert u.start_timestamp == T0_US
    assert u.initial_parameters == {"CA_ROTOR_COUNT": 4, "MPC_THR_HOVER": 0.5, "THR_MDL_FAC": 0.0}
    assert isinstance(u.initial_parameters["CA_ROTOR_COUNT"], int)
    assert u.msg_info_dict["ver_sw"] == "rotortwin-test" and u.msg_info_dict["ver_hw"] == "ROTORTWIN_SIM"
    assert [(m.log_level_str(), m.message) for m in u.logged_messages] == [("WARNING", "low battery")]
    fields = u.message_formats["vehicle_local_position"].fields
    assert ("float", 0, "x") in fields and ("bool", 0, "xy_valid") in fields
    assert ("float", 12, "control") in u.message_formats["actuator_motors"].fields
    assert ("esc_report", 8, "esc") in u.message_formats["esc_status"].fields
    assert ("uint8_t", 0, "arming_state") in u.message_formats["vehicle_status"].fields
    d = u.get_dataset("vehicle_attitude")
    assert d.data["q[2]"].dtype == np.float32
    assert np.array_equal(d.data["q[2]"], topics["vehicle_attitude"]["q"][:, 2].astype(np.float32))
    assert np.array_equal(d.data["timestamp"], topics["vehicle_attitude"]["timestamp"])
    e = u.get_dataset("esc_status")
    assert e.data["esc[2].esc_rpm"].tolist()[:2] == [4000, 4000]
    assert np.isnan(e.data["esc[5].esc_voltage"]).all()  # missing float leaves -> NaN
    # data messages are in time order across topics (as PX4 writes them)
    counts = {(x.name, x.multi_id): len(x.data["timestamp"]) for x in u.data_list}
    assert counts[("sensor_combined", 0)] == 4000
    # and pyulog's own writer re-writes it without loss
    u.write_ulog(str(tmp_path / "again.ulg"))
    v = ULog(str(tmp_path / "again.ulg"))
    assert v.get_dataset("vehicle_attitude") == d


def test_rewrite_real_log_reads_the_same():
    """Real pyulog data (flattened keys, PX4 types) -> write_px4_ulog -> same series."""
    src = shared_log("real", "sitl_iris_takeoff_land.ulg")
    names = ["vehicle_local_position", "vehicle_attitude", "vehicle_angular_velocity",
             "sensor_combined", "battery_status", "vehicle_thrust_setpoint", "esc_status"]
    u = ULog(str(src), message_name_filter_list=names)
    topics = {}
    for d in u.data_list:
        keep = d.data["timestamp"] >= u.start_timestamp
        topics[d.name] = {k: v[keep] for k, v in d.data.items() if "_padding" not in k}
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = write_px4_ulog(os.path.join(tmp, "re.ulg"), topics,
                             dict(u.initial_parameters), {}, start_us=u.start_timestamp)
        a, b = read_ulog(src), read_ulog(out)
    for name in ("position_enu", "velocity_enu", "attitude_q", "body_rates_flu", "gyro_flu",
                 "specific_force_flu", "battery_v", "throttle", "esc_rpm"):
        sa, sb = a.require(name), b.require(name)
        assert np.array_equal(sa.t_s, sb.t_s), name
        np.testing.assert_array_equal(sa.values, sb.values, err_msg=name)


def test_multi_instance_and_custom_topic(tmp_path):
    t = np.arange(5, dtype=np.uint64) * 1000 + 10
    path = write_px4_ulog(tmp_path / "m.ulg", {
        "battery_status": {"timestamp": t, "voltage_v": np.full(5, 12.0)},
        "battery_status:1": {"timestamp": t, "voltage_v": np.full(5, 24.0)},
        "twin_residual": {"timestamp": t, "force_n": np.ones((5, 3)), "ok": np.ones(5, bool)},
    }, {}, {})
    u = ULog(str(path))
    assert u.get_dataset("battery_status", 1).data["voltage_v"][0] == 24.0
    assert ("double", 3, "force_n") in u.message_formats["twin_residual"].fields
    assert ("bool", 0, "ok") in u.message_formats["twin_residual"].fields
    assert u.start_timestamp == 10


def test_long_flight_writes_fast(tmp_path):
    n = 100_000  # 100 s of sensor_combined at 1 kHz
    t = (np.arange(n) * 1000 + 1000).astype(np.uint64)
    t0 = time.perf_counter()
    write_px4_ulog(tmp_path / "long.ulg", {"sensor_combined": {
        "timestamp": t, "gyro_rad": np.zeros((n, 3)), "accelerometer_m_s2": np.zeros((n, 3))},
        "vehicle_attitude": {"timestamp": t[::4], "q": np.tile([1.0, 0, 0, 0], (n // 4, 1))}}, {}, {})
    assert time.perf_counter() - t0 < 3.0
    assert len(ULog(str(tmp_path / "long.ulg")).get_dataset("sensor_combined").data["timestamp"]) == n


# --------------------------------------------------------------------------- atomic + bad input


def _no_temp_left(d):
    return [p.name for p in d.iterdir() if p.name.endswith(".tmp")] == []


def test_failure_leaves_nothing(tmp_path, monkeypatch):
    target = tmp_path / "x.ulg"
    target.write_bytes(b"old contents")
    bad = {"vehicle_attitude": {"timestamp": np.arange(3, dtype=np.uint64), "q": np.zeros((2, 4))}}
    with pytest.raises(LogError):
        write_px4_ulog(target, bad, {}, {})
    assert target.read_bytes() == b"old contents" and _no_temp_left(tmp_path)

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(W.os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        write_px4_ulog(target, synthetic_flight(), PARAMS, INFO)
    assert target.read_bytes() == b"old contents" and _no_temp_left(tmp_path)
    assert not (tmp_path / "new.ulg").exists()


T = np.arange(3, dtype=np.uint64) * 1000 + 1000


@pytest.mark.parametrize("topics, params, match", [
    ({}, {}, r"topics: expected a non-empty dict"),
    ({"vehicle_attitude": {"q": np.zeros((3, 4))}}, {},
     r"vehicle_attitude\.timestamp: expected a 'timestamp' array"),
    ({"vehicle_attitude": {"timestamp": T[::-1], "q": np.zeros((3, 4))}}, {},
     r"vehicle_attitude\.timestamp: expected non-decreasing timestamps"),
    ({"vehicle_attitude": {"timestamp": T, "q": np.zeros((2, 4))}}, {},
     r"vehicle_attitude\.q: expected 3 samples \(as many as timestamp\), got shape \(2, 4\)"),
    ({"vehicle_attitude": {"timestamp": T, "q": np.zeros((3, 5))}}, {},
     r"vehicle_attitude\.q\[4\]: expected an index within the PX4 array size"),
    ({"vehicle_status": {"timestamp": T, "nav_state": np.array([1, 2, 300])}}, {},
     r"vehicle_status\.nav_state: expected values in \[0, 255\] for uint8_t, got \[1, 300\]"),
    ({"vehicle_status": {"timestamp": T, "nav_state": np.array([1.0, 2.5, 3.0])}}, {},
     r"vehicle_status\.nav_state: expected whole numbers for uint8_t"),
    ({"bad-name": {"timestamp": T}}, {}, r"bad-name: expected a topic name of letters"),
    ({"x": {"timestamp": T, "s": np.array(["a", "b", "c"])}}, {},
     r"x\.s: expected a numeric or bool array, got dtype <U1"),
    ({"x": {"timestamp": T}}, {"MPC_THR_HOVER": "0.5"},
     r"params\.MPC_THR_HOVER: expected int or float, got str"),
    ({"x": {"timestamp": T}}, {"A_VERY_LONG_PARAMETER_NAME": 1},
     r"params\.A_VERY_LONG_PARAMETER_NAME: expected a PX4 parameter name"),
])
def test_bad_input(tmp_path, topics, params, match):
    with pytest.raises(LogError, match=r"bad\.ulg: " + match):
        write_px4_ulog(tmp_path / "bad.ulg", topics, params, {})
    assert not (tmp_path / "bad.ulg").exists() and _no_temp_left(tmp_path)


def test_timestamps_before_start_rejected(tmp_path):
    with pytest.raises(LogError, match=r"x\.timestamp: expected timestamps >= start_us=5000 µs, got 1000"):
        write_px4_ulog(tmp_path / "s.ulg", {"x": {"timestamp": T}}, {}, {}, start_us=5000)
