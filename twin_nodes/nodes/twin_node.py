"""Twin node: runs :class:`twin_nodes.twin.TwinRunner` beside the real vehicle's topics.

    python -m twin_nodes.nodes.twin_node --ros-args -p params_file:=params/px4_sih_quadx.yaml \
        -p mode:=closed -p use_sim_time:=true

Subscribes ``/real/odom``, ``/real/setpoint``, ``/real/motors``, ``/real/status``,
``/real/battery``; publishes ``/twin/odom``, ``/twin/motors``, ``/twin/throttle``,
``/twin/imu`` (one of each per output sample, at ``publish_rate_hz`` of log time)
and, after the replay ended, ``/twin/done`` with the number of output samples.

Inputs are applied in time order through a reorder buffer (``reorder_lag_s``):
between two inputs the twin steps at its control rate with the latest values
(zero-order hold), exactly what ``TwinRunner.advance_to`` does offline.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from msgs_py.topics import TOPICS, msg_class
from twin_nodes import conversions as cv
from twin_nodes.nodes.common import NS, GraphNode, ReorderBuffer, declare, reliable_qos, run_node

INPUTS = ("/real/odom", "/real/setpoint", "/real/motors", "/real/status", "/real/battery")
OUTPUTS = ("/twin/odom", "/twin/motors", "/twin/throttle", "/twin/imu")


class TwinNode(GraphNode):
    def __init__(self) -> None:
        super().__init__("twin")
        from twin_nodes.params import load_params
        from twin_nodes.twin import TwinRunner

        pfile = declare(self, "params_file", "", "vehicle parameter file (ROS 2 YAML)")
        mode = declare(self, "mode", "closed", "closed (our controller flies the setpoints) | open (real motors)")
        horizon = float(declare(self, "horizon_s", 2.0, "open loop: re-sync to the real state every ... [s]"))
        self.pub_period_ns = int(NS / float(declare(self, "publish_rate_hz", 50.0, "output rate [Hz, log time]")))
        lag = float(declare(self, "reorder_lag_s", 0.5, "inputs may arrive this much out of order [s]"))
        if not pfile:
            raise ValueError("parameter 'params_file': expected a vehicle parameter file")
        self.vp = load_params(pfile)
        self.runner = TwinRunner(self.vp, mode=mode, horizon_s=horizon)
        self.mode = mode
        self.buf = ReorderBuffer(int(lag * NS))
        self.inputs = INPUTS
        q = reliable_qos()
        self.pub = {t: self.create_publisher(msg_class(TOPICS[t].type), t, q) for t in OUTPUTS}
        self.done_pub = self.create_publisher(msg_class("std_msgs/msg/UInt64"), "/twin/done",
                                              reliable_qos(depth=1, latched=True))
        for topic in INPUTS:
            self.create_subscription(msg_class(TOPICS[topic].type), topic, self._make_cb(topic), q)
        self.t0_ns: int | None = None
        self.next_pub_ns: int | None = None
        self.n_out = 0
        self.done_sent = False
        self.get_logger().info(f"twin of '{self.vp.name}' ({pfile}), {mode} loop at {self.runner.rate_hz:g} Hz")

    # ------------------------------------------------------------------ inputs
    def _make_cb(self, topic: str):
        stamped = TOPICS[topic].stamped

        def cb(msg: Any) -> None:
            self.count(topic)
            t = cv.stamp_to_ns(msg.header.stamp) if stamped else self.stamp_of(topic)
            self.buf.push(t, (topic, msg))
            if not self.timeline.has(topic) and self.clock_ns is None:
                # live (no replay clock): the newest input time is the watermark
                self.buf.advance(t)
        return cb

    def on_clock(self, t_ns: int) -> None:
        self.buf.advance(t_ns)

    def is_ready(self) -> bool:
        return all(s.get_publisher_count() > 0 for s in self.subscriptions if s.topic_name == "/real/odom") and \
            all(p.get_subscription_count() >= len(self.get_subscriptions_info_by_topic(p.topic_name))
                for p in self.pub.values())

    def _apply(self, t_ns: int, topic: str, msg: Any) -> None:
        r = self.runner
        if self.t0_ns is None:
            self.t0_ns = t_ns
        t = (t_ns - self.t0_ns) / NS
        self._publish(r.advance_to(t))
        if topic == "/real/odom":
            _, p, q, v_flu, w = cv.odom_arrays(msg)
            r.real_state(t, p, cv.world_velocity(q, v_flu), q, w)
        elif topic == "/real/setpoint":
            r.setpoint(cv.setpoint_array(msg))
        elif topic == "/real/motors":
            r.real_motors(cv.motors_array(msg))
        elif topic == "/real/status":
            armed = cv.status_array(msg)[0]
            if np.isfinite(armed):
                r.armed(armed > 0.5)
        elif topic == "/real/battery":
            v = cv.battery_arrays(msg)[1]
            if np.isfinite(v):
                r.battery(v)

    def _publish(self, samples: list) -> None:
        for s in samples:
            t_ns = self.t0_ns + int(round(s.t * NS))
            if self.next_pub_ns is not None and t_ns < self.next_pub_ns:
                continue
            self.next_pub_ns = t_ns + self.pub_period_ns - NS // 10000  # tolerate float rounding
            x = s.x
            q = x[6:10]
            self.pub["/twin/odom"].publish(cv.odom_msg(t_ns, x[0:3], q, cv.body_velocity(q, x[3:6]), x[10:13]))
            self.pub["/twin/motors"].publish(cv.motors_msg(s.motors))
            self.pub["/twin/throttle"].publish(cv.float32_msg(s.throttle))
            self.pub["/twin/imu"].publish(cv.imu_msg(t_ns, s.specific_force, x[10:13], q))
            self.n_out += 1

    def step(self) -> None:
        for t_ns, (topic, msg) in self.buf.pop_ready():
            self._apply(t_ns, topic, msg)
        if not self.done_sent and self.inputs_complete():
            for t_ns, (topic, msg) in self.buf.pop_ready(flush=True):
                self._apply(t_ns, topic, msg)
            if self.buf.late:
                self.get_logger().warning(f"{self.buf.late} inputs arrived later than reorder_lag_s")
            # no wait_for_all_acked here: /twin/done carries the count, the metrics node waits for it
            self.done_pub.publish(cv.uint64_msg(self.n_out))
            self.done_sent = True
            self.ack_now()
            self.get_logger().info(f"replay done: {self.n_out} twin samples published")


def _duration(s: float) -> Any:
    from rclpy.duration import Duration

    return Duration(seconds=s)


def main(args: list[str] | None = None) -> int:
    return run_node(TwinNode, args)


if __name__ == "__main__":
    sys.exit(main())
