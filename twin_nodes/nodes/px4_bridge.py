"""PX4 MAVLink bridge: thin rclpy shells around :mod:`twin_nodes.mavlink` (two modes).

``python -m twin_nodes.nodes.px4_bridge sim [--ros-args ...]`` — the twin as PX4 SITL's
lockstep simulator (:class:`~twin_nodes.mavlink.simlink.SimLinkServer`), publishing what it
exchanges with PX4 in the layouts of :mod:`msgs_py.topics`, with simulated time:

- ``/clock`` (rosgraph_msgs/Clock): the simulated time, every step, before the others;
- ``/twin/odom``, ``/twin/motors``, ``/twin/throttle``, ``/twin/imu``, in that order, every
  ``publish_every`` steps: the twin's true state; the commands PX4 sent (0..1, PX4 order, NaN
  = stopped); their mean (0 when all stopped); the accel/gyro sent to PX4 (bias + noise)
  in FLU with the true orientation and the noise variances.

Parameters: ``params_file`` (default: shipped ``px4_sih_quadx``), ``port`` (4560), ``host``
("127.0.0.1": loopback; "0.0.0.0" for PX4 on another machine or container), ``step_s`` (0.004), ``speed_factor`` (multiples of real time; default
``$PX4_SIM_SPEED_FACTOR`` or 1; <= 0 unpaced), ``publish_every`` (1), ``lockstep_timeout_s`` (1.0).

``python -m twin_nodes.nodes.px4_bridge telemetry --ros-args -p url:=udpin:0.0.0.0:14550`` —
a real vehicle's MAVLink telemetry (:class:`~twin_nodes.mavlink.telemetry.TelemetryClient`) as
the same ``/real/...`` topics the ULog replay publishes (:mod:`msgs_py.topics`): ``/real/odom``,
``/real/imu`` (HIGHRES_IMU), ``/real/motors``, ``/real/throttle``, ``/real/battery``,
``/real/setpoint`` (11 entries), ``/real/setpoint_pose``, ``/real/status`` ([armed, nav_state,
landed] on change and once a second for late joiners).  Stamps are this node's clock at
reception (consumers in ``rotortwin live`` time the header-less messages by their DDS source
timestamp: this node's clock when it published them).  The link state goes to ``/diagnostics``
(``px4_bridge/link``: OK, or STALE after ``stale_after_s`` of silence, with the numbers of
subscriptions matched by ``/real/odom`` and ``/real/motors``) once a second and on change.
Parameters: ``url``, ``pwm_min_us`` (1000), ``pwm_max_us`` (2000), ``n_motors`` (4),
``motor_channels`` ("" or e.g. "4,5,6,7", 0-based), ``stale_after_s`` (3.0),
``request_streams`` (true), ``system_id`` (0: the first autopilot heartbeat's), ``summary_out``
("": a JSON file written on stop with what was watched).

Issue 28: only valid MAVLink from the vehicle counts; what was ignored (``bad_data``, ``foreign``,
``before_heartbeat``, ``rejected``) is in the link diagnostic.  A vehicle restart is published on
``/real/reset`` (:data:`twin_nodes.nodes.engine.RESET_TOPIC`, JSON with the time and the reason)
just before the first message after it.  On a normal stop the link diagnostic says
``shutdown: true`` (a clean stop, not a link loss), and ``vehicle_closed: true`` while the vehicle
announces its own shutdown (``MAV_STATE_POWEROFF``).

Both run through :func:`twin_nodes.nodes.common.run_node` (SIGINT/SIGTERM stop them cleanly).
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any

import numpy as np

from msgs_py.topics import TOPICS, msg_class
from twin_nodes.logs import conversions as cv
from twin_nodes.mavlink.simlink import DEFAULT_HOST, DEFAULT_PORT, DEFAULT_STEP_S, SimLinkServer, StepInfo
from twin_nodes.mavlink.telemetry import TelemetryClient, TelemetryConfig, TelemetryState
from twin_nodes.nodes.common import GraphNode, declare, reliable_qos, run_node
from twin_nodes.nodes.engine import RESET_TOPIC, reset_msg

SIM_OUTPUTS = ("/twin/odom", "/twin/motors", "/twin/throttle", "/twin/imu")
REAL_OUTPUTS = ("/real/odom", "/real/imu", "/real/motors", "/real/throttle", "/real/battery", "/real/setpoint",
                "/real/setpoint_pose", "/real/status")
NS = 1_000_000_000


class SimBridgeNode(GraphNode):
    """The twin as PX4's lockstep simulator, publishing what it exchanges."""

    def __init__(self) -> None:
        super().__init__("px4_sim_bridge", consumer=False)
        from twin_nodes.vehicle.params import load_params, shipped

        params_file = declare(self, "params_file", "", "vehicle params YAML (default: shipped px4_sih_quadx)")
        port = int(declare(self, "port", DEFAULT_PORT, "TCP port PX4 connects to (4560 + instance)"))
        host = declare(self, "host", DEFAULT_HOST, "listen address (default loopback; 0.0.0.0 = every interface)")
        step_s = float(declare(self, "step_s", DEFAULT_STEP_S, "lockstep step [s]"))
        speed = float(declare(self, "speed_factor", float(os.environ.get("PX4_SIM_SPEED_FACTOR", 1.0)),
                              "pace in multiples of real time (<= 0: as fast as PX4 answers)"))
        self.publish_every = max(int(declare(self, "publish_every", 1, "publish /twin/... every N steps")), 1)
        timeout = float(declare(self, "lockstep_timeout_s", 1.0, "step anyway after this much PX4 silence [s]"))
        self.step_period_s = 0.1
        vp = load_params(params_file) if params_file else shipped("px4_sih_quadx")
        q = reliable_qos()
        self.pub = {t: self.create_publisher(msg_class(TOPICS[t].type), t, q) for t in SIM_OUTPUTS}
        self.pub_clock = self.create_publisher(msg_class("rosgraph_msgs/msg/Clock"), "/clock", q)
        self.server = SimLinkServer(vp, port=port, step_s=step_s, on_step=self._on_step, host=host,
                                    lockstep_timeout_s=timeout, speed_factor=speed)
        c = self.server.sensor_config
        self.var_accel = [float(v) ** 2 for v in c.accel_noise_m_s2]
        self.var_gyro = [float(v) ** 2 for v in c.gyro_noise_rad_s]
        self._n = 0
        self.server.start_thread()
        self.get_logger().info(f"simulator link for {vp.name} on TCP {host}:{self.server.port}, "
                               f"step {step_s * 1e3:g} ms, speed x{speed:g}")

    def _on_step(self, info: StepInfo) -> None:
        # runs in the link's thread; rclpy publishers may be used from any thread
        t_ns = info.time_usec * 1000
        self.pub_clock.publish(cv.clock_msg(t_ns))
        self._n += 1
        if self._n % self.publish_every:
            return
        running = info.u[np.isfinite(info.u)]
        self.pub["/twin/odom"].publish(cv.odom_msg(t_ns, info.position_enu, info.q_enu_flu,
                                                   info.velocity_body_flu, info.rates_flu))
        self.pub["/twin/motors"].publish(cv.motors_msg(info.u))
        self.pub["/twin/throttle"].publish(cv.float32_msg(float(running.mean()) if running.size else 0.0))
        imu = cv.imu_msg(t_ns, info.accel_flu, info.gyro_flu, info.q_enu_flu)
        imu.linear_acceleration_covariance[0::4] = self.var_accel
        imu.angular_velocity_covariance[0::4] = self.var_gyro
        self.pub["/twin/imu"].publish(imu)

    def close(self, interrupted: bool = False) -> None:
        self.server.close()


class TelemetryBridgeNode(GraphNode):
    """A real vehicle's MAVLink telemetry as the ``/real/...`` topics."""

    def __init__(self) -> None:
        super().__init__("px4_telemetry_bridge", consumer=False)
        url = declare(self, "url", "udpin:0.0.0.0:14550", "mavutil URL of the vehicle link")
        chans = str(declare(self, "motor_channels", "", "0-based output channels of Motor1..N, e.g. 4,5,6,7"))
        cfg = TelemetryConfig(
            pwm_min_us=float(declare(self, "pwm_min_us", 1000.0, "PWM of command 0 [µs]")),
            pwm_max_us=float(declare(self, "pwm_max_us", 2000.0, "PWM of command 1 [µs]")),
            n_motors=int(declare(self, "n_motors", 4, "number of motors")),
            motor_channels=tuple(int(c) for c in chans.split(",")) if chans.strip() else None,
            stale_after_s=float(declare(self, "stale_after_s", 3.0, "link stale after this much silence [s]")),
            request_streams=bool(declare(self, "request_streams", True, "ask the autopilot for the streams")),
            system_id=int(declare(self, "system_id", 0, "the vehicle's MAVLink system id (0: the first "
                                                        "autopilot heartbeat's)")) or None,
        )
        self.url = str(url)
        self.summary_out = str(declare(self, "summary_out", "", "write what was watched here (JSON) on stop"))
        self.t_start_unix = time.time()
        self.step_period_s = 0.2  # step(): the once-a-second link diagnostic (rate-limited inside)
        self._last_step = -1e9
        q = reliable_qos()
        self.pub = {t: self.create_publisher(msg_class(TOPICS[t].type), t, q) for t in REAL_OUTPUTS}
        self.pub_diag = self.create_publisher(msg_class("diagnostic_msgs/msg/DiagnosticArray"), "/diagnostics", 10)
        self.pub_reset = self.create_publisher(msg_class("std_msgs/msg/String"), RESET_TOPIC, q)
        self.t_first_rx_unix: float | None = None
        self.t_last_rx_unix: float | None = None
        self.shutting_down = False
        self.client = TelemetryClient(url, cfg, on_update=self._on_update)
        self.client.start_thread()
        self.get_logger().info(f"telemetry from {self.client.device}")

    def _now_ns(self) -> int:
        return int(self.get_clock().now().nanoseconds)

    def _on_update(self, kinds: list[str], st: TelemetryState) -> None:
        # runs in the client's thread
        t = self._now_ns()
        p = self.pub
        self.t_last_rx_unix = t / NS
        if self.t_first_rx_unix is None:
            self.t_first_rx_unix = t / NS
        if "reset" in kinds:  # before the message that showed it: the twin starts afresh from that one
            self.pub_reset.publish(reset_msg(t - 1, st.reset_reason, len(st.resets)))
            st.resets[-1]["t_s"] = (t - 1) / NS
            self.get_logger().warning(f"vehicle restart: {st.reset_reason}")
        if "odom" in kinds:
            p["/real/odom"].publish(cv.odom_msg(t, st.position_enu, st.q_enu_flu, st.velocity_body_flu(),
                                                st.rates_flu))
        if "imu" in kinds:
            p["/real/imu"].publish(cv.imu_msg(t, st.imu_specific_force_flu, st.imu_gyro_flu))
        if "motors" in kinds:
            p["/real/motors"].publish(cv.motors_msg(st.motors))
        if "throttle" in kinds:
            p["/real/throttle"].publish(cv.float32_msg(st.throttle))
        if "battery" in kinds and st.battery is not None:
            b = st.battery
            msg = cv.battery_msg(t, b.voltage_v, b.current_a)
            msg.percentage = float(b.remaining)
            msg.temperature = float(b.temperature_c)
            msg.cell_voltage = [float(v) for v in b.cell_voltages_v]
            p["/real/battery"].publish(msg)
        if "setpoint" in kinds:
            p["/real/setpoint"].publish(cv.setpoint_msg(st.setpoint))
            if st.setpoint_has_position:
                p["/real/setpoint_pose"].publish(cv.setpoint_pose_msg(t, st.setpoint[0:3], st.setpoint[9]))
        if "status" in kinds:
            p["/real/status"].publish(cv.status_msg(*st.status))
        if "link" in kinds:
            self._publish_link(st, t)

    def _publish_link(self, st: TelemetryState, t_ns: int) -> None:
        arr = msg_class("diagnostic_msgs/msg/DiagnosticArray")()
        status_cls = msg_class("diagnostic_msgs/msg/DiagnosticStatus")
        kv = msg_class("diagnostic_msgs/msg/KeyValue")
        s = status_cls()
        s.name = "px4_bridge/link"
        s.hardware_id = f"mavlink system {st.system_id}" if st.system_id is not None else "mavlink"
        s.level = status_cls.STALE if st.stale and not self.shutting_down else status_cls.OK
        s.message = ("bridge stopped (clean shutdown)" if self.shutting_down else
                     f"{'armed' if st.armed else 'disarmed'} {st.mode} (link {'stale' if st.stale else 'ok'})")
        s.values = [kv(key="stale", value=str(st.stale).lower()), kv(key="mode", value=st.mode),
                    kv(key="armed", value=str(st.armed).lower()), kv(key="messages", value=str(st.messages_rx)),
                    kv(key="shutdown", value=str(self.shutting_down).lower()),
                    kv(key="vehicle_closed", value=str(st.vehicle_closed).lower()),
                    kv(key="bad_data", value=str(st.bad_data)), kv(key="foreign", value=str(st.foreign)),
                    kv(key="before_heartbeat", value=str(st.unbound)), kv(key="rejected", value=str(st.n_rejected)),
                    kv(key="resets", value=str(len(st.resets)))]
        # who listens: the subscriptions matched by /real/odom and /real/motors (a live graph is
        # ready for a vehicle's first message once its twin, metrics and watchdog are counted here)
        s.values += [kv(key=f"{t.split('/')[-1]}_subscribers", value=str(self.pub[t].get_subscription_count()))
                     for t in ("/real/odom", "/real/motors")]
        cv.ns_to_stamp(t_ns, arr.header.stamp)
        arr.status = [s]
        self.pub_diag.publish(arr)

    def step(self) -> None:
        # once a second: the link state, and /real/status again for late joiners (live, nothing
        # is latched; a repeated status changes nothing for a consumer)
        now = time.monotonic()
        if now - self._last_step < 1.0:
            return
        self._last_step = now
        st = self.client.state
        t = self._now_ns()
        self._publish_link(st, t)
        if st.system_id is not None:
            self.pub["/real/status"].publish(cv.status_msg(*st.status))

    def close(self, interrupted: bool = False) -> None:
        self.client.close()
        # a clean stop: say so before going quiet, so that a link watchdog does not call it a loss
        self.shutting_down = True
        try:
            self._publish_link(self.client.state, self._now_ns())
            self.pub_diag.wait_for_all_acked(_duration(2.0))
        except Exception as exc:  # the context may already be going down
            self.get_logger().warning(f"could not announce the shutdown: {exc}")
        if self.summary_out:
            import json

            from twin_nodes.base.io import atomic_write_text
            from twin_nodes.mavlink.telemetry import watched

            st = self.client.state
            w = watched(self.url, st, self.t_first_rx_unix, self.t_last_rx_unix, [])
            w.update(url=self.url, bridge_start_s=self.t_start_unix, bridge_end_s=time.time(),
                     vehicle_closed=st.vehicle_closed)
            atomic_write_text(self.summary_out, json.dumps(w, indent=1))


def _duration(s: float) -> Any:
    from rclpy.duration import Duration

    return Duration(seconds=s)


def main(argv: list[str] | None = None) -> int:
    """``px4_bridge {sim|telemetry} [--ros-args ...]``."""
    from rclpy.utilities import remove_ros_args

    argv = list(sys.argv if argv is None else argv)
    plain = remove_ros_args(argv)
    mode = plain[1] if len(plain) > 1 else "sim"
    factories: dict[str, Any] = {"sim": SimBridgeNode, "telemetry": TelemetryBridgeNode}
    if mode not in factories:
        print(f"px4_bridge: unknown mode {mode!r} (expected sim or telemetry)", file=sys.stderr)
        return 2
    # The bridge subscribes to nothing and publishes from its link thread, so the executor only
    # runs step(); the classic executor is plenty (and its wall-clock timer is what run_node uses).
    os.environ.setdefault("ROTORTWIN_EXECUTOR", "single")
    return run_node(factories[mode], argv)


if __name__ == "__main__":
    sys.exit(main())
