"""conversions.py: every ROS message <-> numpy converter, both ways."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("nav_msgs.msg", reason="ROS 2 message packages (pip install -e '.[ros]')")

from msgs_py.topics import SETPOINT_LABELS, STATUS_LABELS, TOPICS, metric_topic, msg_class  # noqa: E402
from twin_nodes.logs import conversions as cv  # noqa: E402
from twin_nodes.base.frames import quat_from_euler, quat_rotate  # noqa: E402


def _serial_roundtrip(m):
    """Through CDR bytes and back, as the graph and the recorder move them."""
    from rclpy.serialization import deserialize_message, serialize_message

    return deserialize_message(serialize_message(m), type(m))


def test_stamp_roundtrip():
    for t in (0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789):
        assert cv.stamp_to_ns(cv.ns_to_stamp(t)) == t
    assert cv.clock_ns(_serial_roundtrip(cv.clock_msg(123_456_789_012))) == 123_456_789_012


def test_odom_roundtrip_and_frames():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = quat_from_euler(*rng.uniform(-1, 1, 3))
        p, v_enu, w = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
        v_flu = cv.body_velocity(q, v_enu)
        m = _serial_roundtrip(cv.odom_msg(42, p, q, v_flu, w))
        assert m.header.frame_id == "odom" and m.child_frame_id == "base_link"
        t, p2, q2, v2, w2 = cv.odom_arrays(m)
        assert t == 42
        np.testing.assert_allclose(p2, p)
        np.testing.assert_allclose(q2, q)
        np.testing.assert_allclose(v2, v_flu)
        np.testing.assert_allclose(w2, w)
        np.testing.assert_allclose(cv.world_velocity(q2, v2), v_enu, atol=1e-12)
    # yaw +90 deg (nose north in ENU): body x velocity is world +y
    q = quat_from_euler(0.0, 0.0, math.pi / 2)
    np.testing.assert_allclose(cv.body_velocity(q, [0.0, 2.0, 0.0]), [2.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(quat_rotate(q, [1.0, 0, 0]), [0, 1.0, 0], atol=1e-12)


def test_odom_keeps_nan():
    m = _serial_roundtrip(cv.odom_msg(1, [np.nan, 1, 2], [1, 0, 0, 0], [0, 0, 0], [0, 0, 0]))
    assert math.isnan(cv.odom_arrays(m)[1][0])


def test_imu_roundtrip_with_and_without_orientation():
    m = _serial_roundtrip(cv.imu_msg(7, [0.1, -0.2, 9.8], [0.01, 0.02, -0.03]))
    t, sf, g, q = cv.imu_arrays(m)
    assert t == 7 and q is None and m.orientation_covariance[0] == -1.0
    np.testing.assert_allclose(sf, [0.1, -0.2, 9.8])
    np.testing.assert_allclose(g, [0.01, 0.02, -0.03])
    qq = quat_from_euler(0.1, 0.2, 0.3)
    _, _, _, q2 = cv.imu_arrays(_serial_roundtrip(cv.imu_msg(7, sf, g, qq)))
    np.testing.assert_allclose(q2, qq)


def test_motors_layout_and_nan():
    u = [0.5, np.nan, 0.25, 1.0]
    m = _serial_roundtrip(cv.motors_msg(u))
    assert m.layout.dim[0].label == "motor" and m.layout.dim[0].size == 4
    back = cv.motors_array(m)
    assert math.isnan(back[1])
    np.testing.assert_allclose(back[[0, 2, 3]], [0.5, 0.25, 1.0], rtol=1e-7)  # float32 on the wire


def test_scalars_battery_status_setpoint():
    assert cv.float_value(_serial_roundtrip(cv.float32_msg(0.4375))) == 0.4375
    t, v, a = cv.battery_arrays(_serial_roundtrip(cv.battery_msg(5, 11.1, 12.5)))
    assert (t, round(v, 5), round(a, 5)) == (5, 11.1, 12.5)
    b = cv.battery_msg(5, 11.1, 12.5)
    assert b.current == pytest.approx(-12.5)  # ROS sign: negative while discharging
    assert math.isnan(cv.battery_arrays(cv.battery_msg(5, 11.1, np.nan))[2])
    st = _serial_roundtrip(cv.status_msg(1, 3, np.nan))
    assert [d.label for d in st.layout.dim[1:]] == list(STATUS_LABELS)
    s = cv.status_array(st)
    assert s[0] == 1 and s[1] == 3 and math.isnan(s[2])
    sp = np.arange(11.0)
    sp[[6, 7, 8, 10]] = np.nan
    m = _serial_roundtrip(cv.setpoint_msg(sp))
    assert [d.label for d in m.layout.dim[1:]] == list(SETPOINT_LABELS)
    np.testing.assert_array_equal(np.isnan(cv.setpoint_array(m)), np.isnan(sp))
    np.testing.assert_allclose(cv.setpoint_array(m)[:6], sp[:6])
    with pytest.raises(ValueError, match="11 entries"):
        cv.setpoint_msg([1.0, 2.0])
    pose = cv.setpoint_pose_msg(3, [1, 2, 3], math.pi / 2)
    assert pose.pose.orientation.z == pytest.approx(math.sqrt(0.5))


def test_diagnostics_roundtrip():
    stats = {"xy": {"rmse": 0.5, "p75": 0.4, "median": 0.3, "max": 1.0, "n": 10},
             "motor1": {"rmse": 0.01, "p75": 0.02, "median": 0.005, "max": 0.05, "n": 10}}
    vals = cv.diagnostics_values(_serial_roundtrip(cv.diagnostics_msg(9, stats)))
    assert vals["xy"] == {"rmse_m": 0.5, "p75_m": 0.4, "median_m": 0.3, "max_m": 1.0}
    assert vals["motor1"]["p75"] == 0.02


def test_topic_table_types_exist_and_names_are_valid():
    from rclpy.validate_topic_name import validate_topic_name

    for spec in TOPICS.values():
        validate_topic_name(spec.name)
        assert msg_class(spec.type) is not None
    for ch in ("xy", "z", "throttle", "motor1"):
        for st in ("rmse", "p75", "median", "max"):
            validate_topic_name(metric_topic(ch, st))
    assert metric_topic("xy", "rmse") == "/twin_error/xy/rmse_m"
    assert metric_topic("motor1", "p75") == "/twin_error/motor1/p75"
