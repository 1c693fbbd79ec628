"""Metrics node: live twin-versus-real error topics and the whole-flight totals.

    python -m twin_nodes.nodes.metrics_node --ros-args -p window_s:=5.0 -p json_out:=final.json \
        -p use_sim_time:=true

Rolling window (``window_s`` of log time, incremental :class:`twin_nodes.twin.metrics.RollingStats`):
one ``std_msgs/Float64`` per channel and statistic, ``/twin_error/<channel>/<stat>``
(channels ``xy``, ``z`` [m, suffix ``_m``], ``throttle``, ``motor1..N``
[fraction]; stats ``rmse``, ``p75``, ``median``, ``max``), plus the same numbers in
one ``/twin_error/diagnostics`` array, published every ``1/publish_rate_hz`` s of
log time.  Each twin sample is compared with the real signals interpolated at its
time, counted only while airborne (``/real/status``: not landed; else armed).

End of flight (replay done, all announced inputs and ``/twin/done`` received):
the whole-flight metrics computed exactly like ``rotortwin compare``'s offline
path (:func:`twin_nodes.twin.compare.metrics_from_streams`) are published latched on
``/twin_error/final_json`` (JSON) and ``/twin_error/final_table`` (Table-2 text)
and written to ``json_out`` (and the aligned series to ``aligned_out`` .npz)
when those parameters are set.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import numpy as np

from msgs_py.topics import METRIC_STATS, TOPICS, metric_topic, msg_class
from twin_nodes.logs import conversions as cv
from twin_nodes.nodes.common import NS, GraphNode, declare, reliable_qos, run_node
from twin_nodes.nodes.engine import METRICS_RESET_TOPIC, RESET_TOPIC, MetricsEngine, reset_fields
from twin_nodes.twin.metrics import table2, to_jsonable

REAL_INPUTS = ("/real/odom", "/real/throttle", "/real/motors", "/real/status")
TWIN_INPUTS = ("/twin/odom", "/twin/throttle", "/twin/motors")


class MetricsNode(GraphNode):
    def __init__(self) -> None:
        super().__init__("metrics")
        self.window_s = float(declare(self, "window_s", 5.0, "rolling window [s of log time]"))
        self.pub_period_ns = int(NS / float(declare(self, "publish_rate_hz", 2.0, "rolling metrics rate [Hz]")))
        self.n_motors = int(declare(self, "n_motors", 4, "number of motors (metric topics are made at start)"))
        self.rate_hz = float(declare(self, "rate_hz", 50.0, "whole-flight comparison grid [Hz]"))
        self.airborne_only = bool(declare(self, "airborne_only", True, "count only airborne samples"))
        self.mode = declare(self, "mode", "closed", "label of the twin's mode in the totals")
        self.json_out = declare(self, "json_out", "", "write the whole-flight metrics here (JSON)")
        self.aligned_out = declare(self, "aligned_out", "", "write the aligned series here (.npz) for reports")
        self.twin_timeout_s = float(declare(self, "twin_timeout_s", 20.0, "wait this long for /twin/done"))
        self.source_label = str(declare(self, "source", "", "what the real data is (live: the vehicle's URL) for "
                                                           "the totals' 'log' (default: the replayed log)"))
        self.engine = MetricsEngine(self.n_motors, self.window_s, self.pub_period_ns, self.airborne_only)
        self.channels = self.engine.channels
        self.real = self.engine.real
        self.twin = self.engine.twin
        q = reliable_qos()
        latched = reliable_qos(depth=1, latched=True)
        f64 = msg_class("std_msgs/msg/Float64")
        self.metric_pubs = {(ch, st): self.create_publisher(f64, metric_topic(ch, st), q)
                            for ch in self.channels for st in METRIC_STATS}
        self.diag_pub = self.create_publisher(msg_class("diagnostic_msgs/msg/DiagnosticArray"),
                                              "/twin_error/diagnostics", q)
        self.final_json_pub = self.create_publisher(msg_class("std_msgs/msg/String"), "/twin_error/final_json",
                                                    latched)
        self.final_table_pub = self.create_publisher(msg_class("std_msgs/msg/String"), "/twin_error/final_table",
                                                     latched)
        self.inputs = REAL_INPUTS
        self.twin_q: dict[str, list] = {t: [] for t in TWIN_INPUTS}
        self.twin_done: int | None = None
        self.final: dict[str, Any] | None = None
        self.t_replay_done: float | None = None
        for topic in REAL_INPUTS + TWIN_INPUTS:
            self.create_subscription(msg_class(TOPICS[topic].type), topic, self._make_cb(topic), q)
        self.create_subscription(msg_class("std_msgs/msg/UInt64"), "/twin/done", self._on_twin_done,
                                 reliable_qos(depth=1, latched=True))
        # vehicle restarts (issue 28): the rolling window restarts, with a note on /twin_error/reset
        self.create_subscription(msg_class("std_msgs/msg/String"), RESET_TOPIC, self._on_reset, q)
        self.reset_pub = None  # made with the first restart (latched): a run without one has no such topic
        self._resets_noted = 0

    # ------------------------------------------------------------------ inputs
    def _make_cb(self, topic: str):
        if topic.startswith("/twin/"):
            def twin_cb(msg: Any) -> None:
                self.n_callbacks += 1
                self.twin_q[topic].append(msg)
                self._pair_twin()
            return twin_cb

        def handle(msg: Any, t: int) -> None:
            self.count(topic)
            self.n_callbacks += 1
            self.engine.add_real(topic, t, msg)

        if TOPICS[topic].stamped:
            return lambda msg: handle(msg, cv.stamp_to_ns(msg.header.stamp))
        return self.header_less_callback(topic, handle)

    def _on_reset(self, msg: Any) -> None:
        t, reason = reset_fields(msg)
        self.n_callbacks += 1
        self.engine.reset(t, reason)
        self._note_resets()

    def _note_resets(self) -> None:
        """``/twin_error/reset`` for every restart of the rolling window: when and why."""
        while self._resets_noted < len(self.engine.resets):
            r = self.engine.resets[self._resets_noted]
            self._resets_noted += 1
            if self.reset_pub is None:
                self.reset_pub = self.create_publisher(msg_class("std_msgs/msg/String"), METRICS_RESET_TOPIC,
                                                       reliable_qos(depth=10, latched=True))
            self.reset_pub.publish(cv.string_msg(json.dumps({"t_s": r["t_s"], "reason": r["reason"],
                                                             "count": r["count"]})))
            self.get_logger().warning(f"rolling window restarted at {r['t_s']:.3f} s: {r['reason']}")

    def _on_twin_done(self, msg: Any) -> None:
        self.twin_done = int(msg.data)

    def _pair_twin(self) -> None:
        qo, qt, qm = (self.twin_q[t] for t in TWIN_INPUTS)
        n = min(len(qo), len(qt), len(qm))
        for i in range(n):
            t_ns, p, *_ = cv.odom_arrays(qo[i])
            self.engine.add_twin(t_ns, p, cv.float_value(qt[i]), cv.motors_array(qm[i]))
        if n:
            del qo[:n], qt[:n], qm[:n]

    def is_ready(self) -> bool:
        subs_ok = all(s.get_publisher_count() > 0 for s in self.subscriptions
                      if s.topic_name in ("/real/odom", "/twin/odom"))
        pubs_ok = all(p.get_subscription_count() >= len(self.get_subscriptions_info_by_topic(p.topic_name))
                      for p in list(self.metric_pubs.values())[:1] + [self.diag_pub])
        return subs_ok and pubs_ok

    # ------------------------------------------------------------------ rolling metrics
    def _evaluate(self, final: bool = False) -> None:
        for t, stats in self.engine.evaluate(final):
            self._note_resets()  # before the first window after a restart
            self._publish_rolling(t, stats)
        self._note_resets()

    def _publish_rolling(self, t: int, stats: dict[str, dict[str, float]]) -> None:
        f64 = msg_class("std_msgs/msg/Float64")
        for (ch, st), pub in self.metric_pubs.items():
            pub.publish(f64(data=float(stats[ch][st])))
        self.diag_pub.publish(cv.diagnostics_msg(t, stats))

    # ------------------------------------------------------------------ end of flight
    def step(self) -> None:
        self._evaluate()
        if self.final is not None or not self.inputs_complete():
            return
        if self.t_replay_done is None:
            self.t_replay_done = time.monotonic()
        waited = time.monotonic() - self.t_replay_done
        twin_ok = self.twin_done is not None and len(self.twin) >= self.twin_done
        if not twin_ok and waited < self.twin_timeout_s:
            return
        if not twin_ok:
            self.get_logger().warning(f"/twin/done not complete after {self.twin_timeout_s:.0f} s "
                                      f"({len(self.twin)} twin samples, announced {self.twin_done})")
        self._evaluate(final=True)
        self._finalise()

    def close(self, interrupted: bool = False) -> None:
        # live data (no replay, so no /replay/done): the totals of what was seen, on Ctrl-C
        if self.final is None and self.plan is None:
            self.drain()  # the twin's last (flushed) samples, already delivered
        if self.final is None and self.twin and self.real["p"].t:
            self.get_logger().info("stopping before the end of a replay: totals of the data received so far")
            self._pair_twin()
            self._evaluate(final=True)
            self._finalise()

    def _finalise(self) -> None:
        start = int(self.plan.get("start_ns", 0)) if self.plan else 0
        tw = self.twin
        try:
            res = self.engine.totals(start, self.mode, self.rate_hz,
                                     source=str(self.plan.get("ulog", "topics")) if self.plan else "topics")
        except Exception as exc:  # report, don't hang the graph
            self.get_logger().error(f"whole-flight metrics failed: {exc}")
            self.final = {"error": str(exc)}
            self.exit_code = 4
            self._write(self.final)
            return
        m = res.metrics
        m["log"] = self.plan.get("ulog", "") if self.plan else self.source_label
        m["source"] = ("rotortwin graph (replay -> twin -> metrics nodes)" if self.plan else
                       "rotortwin live (vehicle telemetry -> twin -> metrics nodes)")
        if self.engine.resets:  # vehicle restarts (live); a replay's totals keep their keys
            m["resets"] = [{"t_s": r["t_s"], "reason": r["reason"]} for r in self.engine.resets]
        m["received"] = {**self.received, "/twin/*": len(tw)}
        self.final = m
        text = table2(m, title=f"Twin vs real (Table 2 layout): {m['log']}")
        self.final_json_pub.publish(cv.string_msg(json.dumps(to_jsonable(m))))
        self.final_table_pub.publish(cv.string_msg(text))
        self.get_logger().info("whole flight:\n" + text)
        if self.aligned_out:
            al = res.aligned
            np.savez_compressed(self.aligned_out, t=al.t, xy_twin=al.xy_twin, xy_real=al.xy_real, z_twin=al.z_twin,
                                z_real=al.z_real, throttle_twin=al.throttle_twin, throttle_real=al.throttle_real,
                                motors_twin=al.motors_twin, motors_real=al.motors_real, mask=al.mask,
                                mode=np.array(al.mode))
        self._write(m)

    def _write(self, m: dict[str, Any]) -> None:
        if not self.json_out:
            return
        self.final_json_pub.wait_for_all_acked(_duration(5.0))
        tmp = self.json_out + ".tmp"
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(to_jsonable(m), fh, indent=1)
        import os
        os.replace(tmp, self.json_out)  # the CLI waits for this file: write it atomically


def _duration(s: float) -> Any:
    from rclpy.duration import Duration

    return Duration(seconds=s)


def main(args: list[str] | None = None) -> int:
    return run_node(MetricsNode, args)


if __name__ == "__main__":
    sys.exit(main())
