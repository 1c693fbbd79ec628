"""Twin node: runs :class:`twin_nodes.twin.runner.TwinRunner` beside the real vehicle's topics.

    python -m twin_nodes.nodes.twin_node --ros-args -p params_file:=params/px4_sih_quadx.yaml \
        -p mode:=closed -p use_sim_time:=true

Subscribes ``/real/odom``, ``/real/setpoint``, ``/real/motors``, ``/real/status``,
``/real/battery``; publishes ``/twin/odom``, ``/twin/motors``, ``/twin/throttle``,
``/twin/imu`` (one of each per output sample, at ``publish_rate_hz`` of log time)
and, after the replay ended, ``/twin/done`` with the number of output samples; with
``diagnostics_period_s`` > 0 (``rotortwin live``: 1 s), ``/diagnostics`` ``twin/outputs``
(the subscriptions ``/twin/odom`` has).
``/twin/config`` (latched JSON, :func:`twin_nodes.nodes.engine.twin_config`) holds the
params file's path, text and sha256 and the twin's settings, so every recording
says which twin made it (``rotortwin regress`` flies it again).

Inputs are applied in time order through a reorder buffer (``reorder_lag_s``):
between two inputs the twin steps at its control rate with the latest values
(zero-order hold), exactly what ``TwinRunner.advance_to`` does offline.  Live (no
replay), header-less inputs are timed by their DDS source timestamp where the executor
allows it (:func:`twin_nodes.nodes.common.source_stamps`), the inputs' own times move the
watermark (:meth:`~twin_nodes.nodes.engine.TwinEngine.advance_live`), and on stop the held-back
inputs are applied and published (flushed).  The core is
:class:`twin_nodes.nodes.engine.TwinEngine` (also run in-process by ``rotortwin regress --offline``).
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

from msgs_py.topics import TOPICS, msg_class
from twin_nodes.logs import conversions as cv
from twin_nodes.nodes.common import GraphNode, declare, reliable_qos, run_node
from twin_nodes.nodes.engine import (CONFIG_TOPIC, RESET_TOPIC, TWIN_INPUTS, TWIN_OUTPUTS, TwinEngine, reset_fields,
                                     twin_config)

INPUTS = TWIN_INPUTS


class TwinNode(GraphNode):
    def __init__(self) -> None:
        super().__init__("twin")
        from twin_nodes.vehicle.params import load_params

        pfile = declare(self, "params_file", "", "vehicle parameter file (ROS 2 YAML)")
        mode = declare(self, "mode", "closed", "closed (our controller flies the setpoints) | open (real motors)")
        horizon = float(declare(self, "horizon_s", 2.0, "open loop: re-sync to the real state every ... [s]"))
        rate = float(declare(self, "publish_rate_hz", 50.0, "output rate [Hz, log time]"))
        lag = float(declare(self, "reorder_lag_s", 0.5, "inputs may arrive this much out of order [s]"))
        self.diag_period_s = float(declare(self, "diagnostics_period_s", 0.0,
                                           "publish twin/outputs on /diagnostics this often [s] (0: never)"))
        if not pfile:
            raise ValueError("parameter 'params_file': expected a vehicle parameter file")
        self.vp = load_params(pfile)
        self.engine = TwinEngine(self.vp, mode=mode, horizon_s=horizon, publish_rate_hz=rate, reorder_lag_s=lag)
        self.runner = self.engine.runner
        self.mode = mode
        self.inputs = INPUTS
        q = reliable_qos()
        self.pub = {t: self.create_publisher(msg_class(TOPICS[t].type), t, q) for t in TWIN_OUTPUTS}
        self.done_pub = self.create_publisher(msg_class("std_msgs/msg/UInt64"), "/twin/done",
                                              reliable_qos(depth=1, latched=True))
        # what this twin is (params text, mode, rates): recorded with every bag, so that
        # `rotortwin regress` flies a baseline's own params
        config_pub = self.create_publisher(msg_class("std_msgs/msg/String"), CONFIG_TOPIC,
                                           reliable_qos(depth=1, latched=True))
        config_pub.publish(cv.string_msg(json.dumps(twin_config(pfile, self.vp, mode, horizon, rate, lag))))
        for topic in INPUTS:
            self.create_subscription(msg_class(TOPICS[topic].type), topic, self._make_cb(topic), q)
        # a vehicle restart (issue 28): applied in time order; the twin starts afresh from the next
        # real state (the message carries its own time, the bridge's clock)
        self.create_subscription(msg_class("std_msgs/msg/String"), RESET_TOPIC, self._on_reset, q)
        self.done_sent = False
        self._diag_pub = None
        self._last_diag = -1e9
        self.get_logger().info(f"twin of '{self.vp.name}' ({pfile}), {mode} loop at {self.runner.rate_hz:g} Hz")

    @property
    def n_out(self) -> int:
        return self.engine.n_out

    # ------------------------------------------------------------------ inputs
    def _make_cb(self, topic: str):
        def handle(msg: Any, t: int) -> None:
            self.count(topic)
            self.n_callbacks += 1
            self.engine.push(t, topic, msg)
            if not self.timeline.has(topic) and self.clock_ns is None:
                # live (no replay clock): the inputs' own times are the watermark
                self.engine.advance_live(topic, t, time.monotonic())

        if TOPICS[topic].stamped:
            return lambda msg: handle(msg, cv.stamp_to_ns(msg.header.stamp))
        return self.header_less_callback(topic, handle)

    def _on_reset(self, msg: Any) -> None:
        t, reason = reset_fields(msg)
        self.n_callbacks += 1
        self.engine.push(t, RESET_TOPIC, msg)
        self.get_logger().warning(f"vehicle restart ({reason}): the twin starts afresh from the next real state")

    def on_clock(self, t_ns: int) -> None:
        self.engine.advance(t_ns)

    def is_ready(self) -> bool:
        return all(s.get_publisher_count() > 0 for s in self.subscriptions if s.topic_name == "/real/odom") and \
            all(p.get_subscription_count() >= len(self.get_subscriptions_info_by_topic(p.topic_name))
                for p in self.pub.values())

    def _publish(self, samples: list) -> None:
        for t_ns, s in samples:
            x = s.x
            q = x[6:10]
            self.pub["/twin/odom"].publish(cv.odom_msg(t_ns, x[0:3], q, cv.body_velocity(q, x[3:6]), x[10:13]))
            self.pub["/twin/motors"].publish(cv.motors_msg(s.motors))
            self.pub["/twin/throttle"].publish(cv.float32_msg(s.throttle))
            self.pub["/twin/imu"].publish(cv.imu_msg(t_ns, s.specific_force, x[10:13], q))

    def _live_diagnostics(self) -> None:
        """Every ``diagnostics_period_s`` on ``/diagnostics``: ``twin/outputs`` with the number of
        subscriptions matched by ``/twin/odom`` (how a live graph knows its consumers hear the twin)."""
        now = time.monotonic()
        if now - self._last_diag < self.diag_period_s:
            return
        self._last_diag = now
        if self._diag_pub is None:
            self._diag_pub = self.create_publisher(msg_class("diagnostic_msgs/msg/DiagnosticArray"), "/diagnostics", 10)
        status = msg_class("diagnostic_msgs/msg/DiagnosticStatus")
        kv = msg_class("diagnostic_msgs/msg/KeyValue")
        arr = msg_class("diagnostic_msgs/msg/DiagnosticArray")()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [status(name="twin/outputs", level=status.OK, message=f"{self.engine.n_out} samples",
                             values=[kv(key="odom_subscribers", value=str(self.pub["/twin/odom"].get_subscription_count()))])]
        self._diag_pub.publish(arr)

    def step(self) -> None:
        if self.diag_period_s > 0:
            self._live_diagnostics()
        self._publish(self.engine.pop())
        if not self.done_sent and self.inputs_complete():
            self._publish(self.engine.pop(flush=True))
            if self.engine.buf.late:
                self.get_logger().warning(f"{self.engine.buf.late} inputs arrived later than reorder_lag_s")
            # no wait_for_all_acked here: /twin/done carries the count, the metrics node waits for it
            self.done_pub.publish(cv.uint64_msg(self.n_out))
            self.done_sent = True
            self.ack_now()
            self.get_logger().info(f"replay done: {self.n_out} twin samples published")


    def close(self, interrupted: bool = False) -> None:
        # live (no replay): the inputs still held back for reordering are applied and published,
        # so that a stopped run is scored up to its last input, whatever the moment of the stop
        if self.plan is None and not self.done_sent:
            self.drain()
            self._publish(self.engine.pop(flush=True))
            for p in self.pub.values():
                p.wait_for_all_acked(_duration(5.0))
            buf = self.engine.buf
            self.get_logger().info(f"stopped: {self.n_out} twin samples published, {buf.late} inputs arrived later "
                                   f"than reorder_lag_s (by up to {buf.max_late_ns / 1e9:.3f} s)")


def _duration(s: float) -> Any:
    from rclpy.duration import Duration

    return Duration(seconds=s)


def main(args: list[str] | None = None) -> int:
    return run_node(TwinNode, args)


if __name__ == "__main__":
    sys.exit(main())
