"""ROS 2 messages <-> numpy: the one home of message conversions.

Every function here builds a message from arrays or reads arrays back from a
message, with the layouts documented in :mod:`msgs_py.topics` (ENU world, FLU
body, quaternions ``[w, x, y, z]`` FLU->ENU in arrays, x/y/z/w in
``geometry_msgs/Quaternion``).  Message classes are imported on first use, so
importing this module does not load rclpy.  Times are integer nanoseconds.

NaN conventions survive the round trip (float fields carry NaN); a header-less
``std_msgs`` message carries no time (see :mod:`msgs_py.topics`).
"""

from __future__ import annotations

import array
import math
from functools import lru_cache
from typing import Any, Mapping, Sequence

import numpy as np

from msgs_py.topics import FRAME_BODY, FRAME_WORLD, SETPOINT_LABELS, STATUS_LABELS, msg_class
from twin_nodes.base.frames import quat_conjugate, quat_rotate

__all__ = [
    "ns_to_stamp", "stamp_to_ns", "clock_msg", "clock_ns",
    "odom_msg", "odom_arrays", "body_velocity", "world_velocity",
    "imu_msg", "imu_arrays", "motors_msg", "motors_array", "float32_msg", "float_value",
    "battery_msg", "battery_arrays", "setpoint_msg", "setpoint_array", "setpoint_pose_msg",
    "status_msg", "status_array", "ack_msg", "diagnostics_msg", "diagnostics_values",
    "string_msg", "bool_msg", "uint64_msg",
]


@lru_cache(maxsize=None)
def _cls(name: str) -> Any:
    return msg_class(name)


# --------------------------------------------------------------------------- time

def ns_to_stamp(t_ns: int, stamp: Any | None = None) -> Any:
    """``builtin_interfaces/Time`` of integer nanoseconds (filled into ``stamp`` if given)."""
    t_ns = int(t_ns)
    st = stamp if stamp is not None else _cls("builtin_interfaces/msg/Time")()
    st.sec = t_ns // 1_000_000_000
    st.nanosec = t_ns % 1_000_000_000
    return st


def stamp_to_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def clock_msg(t_ns: int) -> Any:
    m = _cls("rosgraph_msgs/msg/Clock")()
    ns_to_stamp(t_ns, m.clock)
    return m


def clock_ns(msg: Any) -> int:
    return stamp_to_ns(msg.clock)


# --------------------------------------------------------------------------- odometry

def body_velocity(q_wxyz: np.ndarray, v_enu: np.ndarray) -> np.ndarray:
    """World (ENU) velocity -> body (FLU) velocity: ``q* ⊗ v ⊗ q``. Shapes (…,4), (…,3)."""
    return quat_rotate(quat_conjugate(np.asarray(q_wxyz, float)), np.asarray(v_enu, float))


def world_velocity(q_wxyz: np.ndarray, v_flu: np.ndarray) -> np.ndarray:
    """Body (FLU) velocity -> world (ENU) velocity."""
    return quat_rotate(np.asarray(q_wxyz, float), np.asarray(v_flu, float))


def odom_msg(t_ns: int, p_enu: Sequence[float], q_wxyz: Sequence[float], v_flu: Sequence[float],
             w_flu: Sequence[float], frame_id: str = FRAME_WORLD, child_frame_id: str = FRAME_BODY) -> Any:
    """``nav_msgs/Odometry``: pose (ENU position, FLU->ENU attitude) in ``frame_id``, twist
    (body velocity and rates, FLU) in ``child_frame_id`` (REP-105)."""
    m = _cls("nav_msgs/msg/Odometry")()
    ns_to_stamp(t_ns, m.header.stamp)
    m.header.frame_id = frame_id
    m.child_frame_id = child_frame_id
    p, o = m.pose.pose.position, m.pose.pose.orientation
    p.x, p.y, p.z = float(p_enu[0]), float(p_enu[1]), float(p_enu[2])
    o.w, o.x, o.y, o.z = float(q_wxyz[0]), float(q_wxyz[1]), float(q_wxyz[2]), float(q_wxyz[3])
    lin, ang = m.twist.twist.linear, m.twist.twist.angular
    lin.x, lin.y, lin.z = float(v_flu[0]), float(v_flu[1]), float(v_flu[2])
    ang.x, ang.y, ang.z = float(w_flu[0]), float(w_flu[1]), float(w_flu[2])
    return m


def odom_arrays(m: Any) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(t_ns, p_enu (3,), q_wxyz (4,), v_flu (3,), w_flu (3,))`` of an Odometry message."""
    p, o = m.pose.pose.position, m.pose.pose.orientation
    lin, ang = m.twist.twist.linear, m.twist.twist.angular
    return (stamp_to_ns(m.header.stamp), np.array([p.x, p.y, p.z]), np.array([o.w, o.x, o.y, o.z]),
            np.array([lin.x, lin.y, lin.z]), np.array([ang.x, ang.y, ang.z]))


# --------------------------------------------------------------------------- imu

def imu_msg(t_ns: int, specific_force_flu: Sequence[float], gyro_flu: Sequence[float],
            q_wxyz: Sequence[float] | None = None, frame_id: str = FRAME_BODY) -> Any:
    """``sensor_msgs/Imu``; without ``q_wxyz`` the orientation is marked unknown
    (``orientation_covariance[0] = -1``, REP-145)."""
    m = _cls("sensor_msgs/msg/Imu")()
    ns_to_stamp(t_ns, m.header.stamp)
    m.header.frame_id = frame_id
    a, g = m.linear_acceleration, m.angular_velocity
    a.x, a.y, a.z = float(specific_force_flu[0]), float(specific_force_flu[1]), float(specific_force_flu[2])
    g.x, g.y, g.z = float(gyro_flu[0]), float(gyro_flu[1]), float(gyro_flu[2])
    if q_wxyz is None:
        m.orientation_covariance[0] = -1.0
    else:
        o = m.orientation
        o.w, o.x, o.y, o.z = float(q_wxyz[0]), float(q_wxyz[1]), float(q_wxyz[2]), float(q_wxyz[3])
    return m


def imu_arrays(m: Any) -> tuple[int, np.ndarray, np.ndarray, np.ndarray | None]:
    """``(t_ns, specific_force_flu, gyro_flu, q_wxyz or None when unknown)``."""
    a, g, o = m.linear_acceleration, m.angular_velocity, m.orientation
    q = None if m.orientation_covariance[0] == -1.0 else np.array([o.w, o.x, o.y, o.z])
    return stamp_to_ns(m.header.stamp), np.array([a.x, a.y, a.z]), np.array([g.x, g.y, g.z]), q


# --------------------------------------------------------------------------- arrays

def _labelled(msg: Any, label: str, n: int, entry_labels: Sequence[str] | None = None) -> Any:
    dim_cls = _cls("std_msgs/msg/MultiArrayDimension")
    dims = [dim_cls(label=label, size=n, stride=n)]
    if entry_labels:
        dims += [dim_cls(label=lab, size=1, stride=1) for lab in entry_labels]
    msg.layout.dim = dims
    return msg


def motors_msg(u: Sequence[float], label: str = "motor") -> Any:
    """``std_msgs/Float32MultiArray`` of N motor values (PX4 order, NaN = stopped)."""
    a = np.asarray(u, dtype=np.float32).ravel()
    m = _cls("std_msgs/msg/Float32MultiArray")()
    _labelled(m, label, int(a.size))
    m.data = array.array("f", a.tobytes())
    return m


def motors_array(m: Any) -> np.ndarray:
    return np.asarray(m.data, dtype=float)


def float32_msg(x: float) -> Any:
    return _cls("std_msgs/msg/Float32")(data=float(x))


def float_value(m: Any) -> float:
    return float(m.data)


def string_msg(s: str) -> Any:
    return _cls("std_msgs/msg/String")(data=str(s))


def bool_msg(b: bool) -> Any:
    return _cls("std_msgs/msg/Bool")(data=bool(b))


def uint64_msg(n: int) -> Any:
    return _cls("std_msgs/msg/UInt64")(data=int(n))


def battery_msg(t_ns: int, voltage_v: float, current_a_px4: float) -> Any:
    """``sensor_msgs/BatteryState``: ``current = -current_a_px4`` (ROS: negative while
    discharging); NaN = unknown; percentage NaN."""
    m = _cls("sensor_msgs/msg/BatteryState")()
    ns_to_stamp(t_ns, m.header.stamp)
    m.voltage = float(voltage_v)
    m.current = -float(current_a_px4) if math.isfinite(float(current_a_px4)) else math.nan
    m.percentage = math.nan
    m.charge = m.capacity = m.design_capacity = math.nan
    m.temperature = math.nan
    m.present = True
    m.power_supply_status = m.POWER_SUPPLY_STATUS_DISCHARGING
    return m


def battery_arrays(m: Any) -> tuple[int, float, float]:
    """``(t_ns, voltage_v, current_a_px4)`` (PX4 sign: positive while discharging)."""
    c = float(m.current)
    return stamp_to_ns(m.header.stamp), float(m.voltage), (-c if math.isfinite(c) else math.nan)


def setpoint_msg(sp: Sequence[float]) -> Any:
    """``std_msgs/Float64MultiArray`` of the 11-entry setpoint (see ``SETPOINT_LABELS``)."""
    a = np.asarray(sp, dtype=float).ravel()
    if a.size != len(SETPOINT_LABELS):
        raise ValueError(f"sp: expected {len(SETPOINT_LABELS)} entries, got {a.size}")
    m = _cls("std_msgs/msg/Float64MultiArray")()
    _labelled(m, "setpoint", a.size, SETPOINT_LABELS)
    m.data = array.array("d", a.tobytes())
    return m


def setpoint_array(m: Any) -> np.ndarray:
    a = np.asarray(m.data, dtype=float)
    if a.size != len(SETPOINT_LABELS):
        raise ValueError(f"/real/setpoint: expected {len(SETPOINT_LABELS)} entries, got {a.size}")
    return a


def setpoint_pose_msg(t_ns: int, pos_enu: Sequence[float], yaw_enu: float, frame_id: str = FRAME_WORLD) -> Any:
    """``geometry_msgs/PoseStamped`` of a position setpoint and yaw (NaN yaw -> identity attitude)."""
    m = _cls("geometry_msgs/msg/PoseStamped")()
    ns_to_stamp(t_ns, m.header.stamp)
    m.header.frame_id = frame_id
    p, o = m.pose.position, m.pose.orientation
    p.x, p.y, p.z = float(pos_enu[0]), float(pos_enu[1]), float(pos_enu[2])
    y = float(yaw_enu) if math.isfinite(float(yaw_enu)) else 0.0
    o.w, o.x, o.y, o.z = math.cos(y / 2), 0.0, 0.0, math.sin(y / 2)
    return m


def status_msg(armed: float, nav_state: float, landed: float) -> Any:
    """``std_msgs/UInt8MultiArray`` [armed, nav_state, landed]; NaN -> 255 (unknown)."""
    vals = []
    for v in (armed, nav_state, landed):
        v = float(v)
        vals.append(255 if not math.isfinite(v) else int(min(max(round(v), 0), 254)))
    m = _cls("std_msgs/msg/UInt8MultiArray")()
    _labelled(m, "status", 3, STATUS_LABELS)
    m.data = bytes(vals)
    return m


def status_array(m: Any) -> np.ndarray:
    """``[armed, nav_state, landed]`` as floats, NaN = unknown."""
    raw = m.data
    vals = list(raw) if not isinstance(raw, (bytes, bytearray)) else list(raw)
    out = np.array([float(v) if not isinstance(v, bytes) else float(v[0]) for v in vals])
    out[out == 255] = np.nan
    return out


def ack_msg(node_name: str, value: str) -> Any:
    return _cls("diagnostic_msgs/msg/KeyValue")(key=str(node_name), value=str(value))


def diagnostics_msg(t_ns: int, stats: Mapping[str, Mapping[str, float]], hardware_id: str = "rotortwin") -> Any:
    """``diagnostic_msgs/DiagnosticArray``: one status per channel (``twin_error/<channel>``),
    key/values = statistic name (with the channel's unit suffix) -> value."""
    arr = _cls("diagnostic_msgs/msg/DiagnosticArray")()
    st_cls = _cls("diagnostic_msgs/msg/DiagnosticStatus")
    kv_cls = _cls("diagnostic_msgs/msg/KeyValue")
    ns_to_stamp(t_ns, arr.header.stamp)
    out = []
    for ch, s in stats.items():
        st = st_cls()
        st.level = st_cls.OK
        st.name = f"twin_error/{ch}"
        st.hardware_id = hardware_id
        st.message = f"n={int(s.get('n', 0))}"
        unit = "_m" if ch in ("xy", "z") else ""
        st.values = [kv_cls(key=f"{k}{unit}", value=repr(float(s[k]))) for k in ("rmse", "p75", "median", "max")]
        out.append(st)
    arr.status = out
    return arr


def diagnostics_values(arr: Any) -> dict[str, dict[str, float]]:
    """``{channel: {key: value}}`` of a :func:`diagnostics_msg` message."""
    out: dict[str, dict[str, float]] = {}
    for st in arr.status:
        ch = st.name.split("/", 1)[-1]
        out[ch] = {kv.key: float(kv.value) for kv in st.values}
    return out
