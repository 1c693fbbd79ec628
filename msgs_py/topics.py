"""The rotortwin topic graph: every topic name, its message type and what is in it.

This is the one place where message mappings are defined (standard ROS 2 types
only, so no interface package has to be built).  The ULog replay node and the
PX4 MAVLink bridge publish the same ``/real/...`` topics; the twin node the
``/twin/...`` topics; the metrics node ``/twin_error/...``.  Frames follow
REP-103/105: world ENU (``frame_id`` ``odom``), body FLU (``base_link``).

Time of a message
-----------------
- Messages with a ``header`` carry their sample time in ``header.stamp``.
- ``std_msgs`` messages have no header.  Their time is the (sim) time at which
  they were **published**: on replay the replay node publishes ``/clock`` with
  the sample's log time immediately before every header-less message whose
  time differs from the last ``/clock``, and consumers map the message's DDS
  source timestamp to the latest ``/clock`` published before it
  (:class:`twin_nodes.nodes.common.SourceTimeMap`), so the mapping is exact
  whatever order callbacks run in.  Live (PX4 bridge, wall time) the source
  timestamp itself is the time.
- The twin publishes one message on each of ``/twin/odom``, ``/twin/motors``,
  ``/twin/throttle``, ``/twin/imu`` per output sample, in that order; the
  header-less ``/twin/motors`` and ``/twin/throttle`` take the time of the
  ``/twin/odom`` message with the same index (per-topic order is preserved by
  reliable QoS).

Flow control on replay (``rate`` 0 = as fast as the consumers keep up)
----------------------------------------------------------------------
Consumers publish ``/replay/ack`` (``diagnostic_msgs/KeyValue``: ``key`` = node
name, ``value`` = ``"ready"`` before data flows, then the latest ``/clock``
they processed in integer nanoseconds).  The replay node starts only when every
node named in its ``wait_for`` parameter is ready and all its publishers are
matched, and never runs more than ``window_s`` of log time ahead of the slowest
acknowledged consumer; queue depths (:data:`DEPTH`) are far larger than what a
window holds, so reliable QoS never has to drop.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

__all__ = ["TopicSpec", "TOPICS", "DEPTH", "SETPOINT_LABELS", "STATUS_LABELS", "METRIC_STATS",
           "metric_topic", "metric_channels", "msg_class", "FRAME_WORLD", "FRAME_BODY", "ACK_READY"]

#: history depth of every reliable graph topic (a flow-control window holds far fewer)
DEPTH = 2000
FRAME_WORLD = "odom"
FRAME_BODY = "base_link"
ACK_READY = "ready"


@dataclass(frozen=True)
class TopicSpec:
    name: str
    type: str           # pkg/msg/Type
    stamped: bool       # has a header with the sample time
    source: str         # where the data comes from (ULog topic / node)
    content: str        # what the fields hold (units, frames, NaN rules)
    latched: bool = False  # transient-local durability (late joiners get the last message)


#: 11-entry setpoint vector (twin_nodes.twin.control.SP_SIZE), ENU, NaN = not controlled
SETPOINT_LABELS = ("pos_x_m", "pos_y_m", "pos_z_m", "vel_x_m_s", "vel_y_m_s", "vel_z_m_s",
                   "acc_x_m_s2", "acc_y_m_s2", "acc_z_m_s2", "yaw_rad", "yawspeed_rad_s")
#: /real/status entries
STATUS_LABELS = ("armed", "nav_state", "landed")
#: statistics published per error channel, in display order
METRIC_STATS = ("rmse", "p75", "median", "max")

_T = [
    TopicSpec("/clock", "rosgraph_msgs/msg/Clock", False, "replay node",
              "log time (ULog µs × 1000 since the log start); nodes run with use_sim_time:=true"),
    TopicSpec("/real/odom", "nav_msgs/msg/Odometry", True, "vehicle_local_position (+ attitude, rates)",
              "frame_id odom (ENU), child_frame_id base_link (FLU); pose = EKF position [m] and attitude "
              "(q FLU->ENU, slerped to the position time); twist in base_link: linear = body velocity [m/s] "
              "(ENU velocity rotated into FLU), angular = body rates [rad/s] (interpolated); NaN where the "
              "log marks the estimate invalid; one message per vehicle_local_position sample"),
    TopicSpec("/real/imu", "sensor_msgs/msg/Imu", True, "sensor_combined",
              "frame_id base_link; angular_velocity = gyro [rad/s, FLU]; linear_acceleration = specific "
              "force [m/s^2, FLU] (+9.81 z at rest); orientation unknown: orientation_covariance[0] = -1"),
    TopicSpec("/real/motors", "std_msgs/msg/Float32MultiArray", False, "actuator_motors (or actuator_outputs PWM)",
              "N motor commands 0..1 in PX4 motor order (data[0] = Motor1), NaN = stopped; "
              "layout.dim[0] = {label 'motor', size N, stride N}"),
    TopicSpec("/real/throttle", "std_msgs/msg/Float32", False, "vehicle_thrust_setpoint (or actuator_controls_0[3])",
              "collective throttle 0..1 = |thrust setpoint z| (PX4 normalised)"),
    TopicSpec("/real/battery", "sensor_msgs/msg/BatteryState", True, "battery_status[0]",
              "voltage [V]; current [A] with the ROS sign (negative while discharging, i.e. -PX4 current_a), "
              "NaN unknown; percentage NaN (unknown); present true"),
    TopicSpec("/real/setpoint", "std_msgs/msg/Float64MultiArray", False, "trajectory_setpoint",
              "11 entries [pos xyz m, vel xyz m/s, acc xyz m/s^2, yaw rad, yawspeed rad/s], ENU, yaw from East "
              "CCW, NaN = not controlled; layout.dim[0] = {label 'setpoint', size 11}, then one dim per entry "
              "with size 1 whose label names it (see SETPOINT_LABELS)"),
    TopicSpec("/real/setpoint_pose", "geometry_msgs/msg/PoseStamped", True, "trajectory_setpoint",
              "the position setpoint and yaw for viewers (frame odom); only samples with a finite position"),
    TopicSpec("/real/status", "std_msgs/msg/UInt8MultiArray", False, "vehicle_status, vehicle_land_detected",
              "[armed 0/1, nav_state (PX4 numbering), landed 0/1] whenever one changes (and at the start); "
              "labelled dims like /real/setpoint; 255 = unknown"),
    TopicSpec("/real/esc_rpm", "std_msgs/msg/Float32MultiArray", False, "esc_status (when logged)",
              "rotor speed [rpm] per motor, PX4 motor order; layout.dim[0] label 'motor'"),
    TopicSpec("/replay/done", "std_msgs/msg/Bool", False, "replay node",
              "true once every message has been published (and acknowledged by the wait_for nodes)", True),
    TopicSpec("/replay/ack", "diagnostic_msgs/msg/KeyValue", False, "consumer nodes",
              "flow control: key = node name, value = 'ready' or the latest processed /clock [ns]"),
    TopicSpec("/twin/odom", "nav_msgs/msg/Odometry", True, "twin node", "twin state, same layout as /real/odom"),
    TopicSpec("/twin/motors", "std_msgs/msg/Float32MultiArray", False, "twin node",
              "the twin's motor commands, same layout as /real/motors"),
    TopicSpec("/twin/throttle", "std_msgs/msg/Float32", False, "twin node",
              "the twin's collective throttle (closed loop: controller thrust; open loop: mean real command)"),
    TopicSpec("/twin/imu", "sensor_msgs/msg/Imu", True, "twin node",
              "the twin's accelerometer (specific force) and gyro, FLU, with its orientation"),
    TopicSpec("/twin/done", "std_msgs/msg/UInt64", False, "twin node",
              "number of output samples published, sent once after the replay ended", True),
    TopicSpec("/twin_error/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", True, "metrics node",
              "one DiagnosticStatus per channel (name 'twin_error/<channel>'), values = the four statistics "
              "over the rolling window, keys like 'rmse_m'"),
    TopicSpec("/twin_error/final_json", "std_msgs/msg/String", False, "metrics node",
              "whole-flight metrics as JSON (twin_nodes.twin.metrics.flight_metrics keys), once at the end", True),
    TopicSpec("/twin_error/final_table", "std_msgs/msg/String", False, "metrics node",
              "whole-flight metrics in the Table-2 layout (plain text), once at the end", True),
]
TOPICS: dict[str, TopicSpec] = {t.name: t for t in _T}


def metric_channels(n_motors: int) -> list[str]:
    """Error channels: ``xy``, ``z``, ``throttle``, ``motor1`` .. ``motorN``."""
    return ["xy", "z", "throttle"] + [f"motor{i + 1}" for i in range(n_motors)]


def metric_topic(channel: str, stat: str) -> str:
    """Rolling-window metric topic (``std_msgs/Float64``), e.g. ``/twin_error/xy/rmse_m``,
    ``/twin_error/motor1/p75``.  Position channels carry the ``_m`` unit suffix; throttle and
    motor errors are fractions (0.01 = 1 %)."""
    unit = "_m" if channel in ("xy", "z") else ""
    return f"/twin_error/{channel}/{stat}{unit}"


def msg_class(type_name: str) -> Any:
    """The rclpy message class of ``pkg/msg/Type`` (imported on demand)."""
    parts = type_name.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3:
        raise ValueError(f"type_name: expected 'pkg/msg/Type', got {type_name!r}")
    mod = importlib.import_module(f"{parts[0]}.{parts[1]}")
    return getattr(mod, parts[2])
