"""Recorder node: every topic of the graph into one MCAP (rosbag2 layout).

    python -m twin_nodes.nodes.recorder_node --ros-args -p out:=run_bag -p use_sim_time:=true

Discovers topics continuously (``get_topic_names_and_types``) and subscribes to
each with serialized (``raw=True``) messages, matching the publishers' QoS
(reliable or best effort; transient-local when a publisher is latched, so
``/replay/plan``, ``/replay/done`` and ``/twin_error/final_json`` are kept).
The CDR bytes go to the bag unchanged through :class:`twin_nodes.recording.McapRecorder`
(``rosbags`` writer: ``metadata.yaml`` + ``<out>/<out>.mcap``).

Message time in the bag: header-less replayed ``/real`` topics get their exact log
time from ``/replay/timeline``; everything else the (sim) time at which it was
received.  ``exclude`` (regex) skips topics, default ``/rosout`` and
``/parameter_events``.

Stopping: SIGINT/SIGTERM drain what is queued and finalise the bag; after a
``kill -9`` the chunks already written survive and ``rotortwin record recover
<out>`` rebuilds a valid bag (:func:`twin_nodes.recording.recover`).
"""

from __future__ import annotations

import re
import sys
import time
from typing import Any

from msgs_py.topics import DEPTH, msg_class
from twin_nodes.nodes.common import GraphNode, declare, run_node
from twin_nodes.recording import McapRecorder


class RecorderNode(GraphNode):
    def __init__(self) -> None:
        super().__init__("recorder")
        out = declare(self, "out", "", "bag directory to create (rosbag2 layout, one .mcap)")
        self.exclude = re.compile(declare(self, "exclude", r"^/(rosout|parameter_events)$",
                                          "regex of topics not to record"))
        fsync = bool(declare(self, "fsync", False, "fsync every chunk (power-loss safety)"))
        chunk_s = float(declare(self, "chunk_period_s", 1.0, "close an MCAP chunk every ... s of message time"))
        if not out:
            raise ValueError("parameter 'out': expected a bag directory to create")
        self.bag = McapRecorder(out, chunk_period_s=chunk_s, fsync_chunks=fsync)
        self.subs: dict[str, Any] = {}
        self.skipped: set[str] = set()
        self.n = 0
        self.last_msg_wall = time.monotonic()
        self._discover()
        self.wall_timer(0.2, self._discover)
        self.get_logger().info(f"recording to {self.bag.path}")

    def _discover(self) -> None:
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        for topic, types in self.get_topic_names_and_types():
            if topic in self.subs or topic in self.skipped or self.exclude.search(topic):
                continue
            if len(types) != 1:
                self.get_logger().warning(f"{topic}: {len(types)} types {types}, not recorded")
                self.skipped.add(topic)
                continue
            pubs = self.get_publishers_info_by_topic(topic)
            if not pubs:
                continue  # only subscribers so far: wait for a publisher to learn its QoS
            best_effort = any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in pubs)
            latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
            qos = QoSProfile(depth=DEPTH, history=HistoryPolicy.KEEP_LAST,
                             reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
            try:
                cls = msg_class(types[0])
                self.bag.add_topic(topic, types[0],
                                   "sensor_data" if best_effort else ("transient_local" if latched else "reliable"))
            except Exception as exc:
                self.get_logger().warning(f"{topic} ({types[0]}): not recorded: {exc}")
                self.skipped.add(topic)
                continue
            self.subs[topic] = self.create_subscription(cls, topic, self._make_cb(topic), qos, raw=True)

    def _make_cb(self, topic: str):
        def cb(data: bytes) -> None:
            t = self.timeline.take(topic) if self.timeline.has(topic) else None
            if t is None:
                if self.clock_ns is not None:
                    t = self.clock_ns
                elif self.plan is not None:
                    t = int(self.plan.get("t0_ns", 0))
                else:
                    t = int(time.time() * 1e9)
            self.bag.write_raw(topic, data, t)
            self.n += 1
            self.last_msg_wall = time.monotonic()
        return cb

    def is_ready(self) -> bool:
        names = {t for t, _ in self.get_topic_names_and_types() if not self.exclude.search(t)}
        if any(t not in self.subs and t not in self.skipped for t in names):
            return False
        if "/real/odom" not in self.subs and "/replay/plan" in self.subs:
            return False
        for t, s in self.subs.items():
            if s.get_publisher_count() < len(self.get_publishers_info_by_topic(t)):
                return False
        return True

    def close(self, interrupted: bool = False) -> None:
        # drain what is already queued, then finalise the bag
        ex = self.executor_ref
        t_end = time.monotonic() + 3.0
        while ex is not None and time.monotonic() < t_end and time.monotonic() - self.last_msg_wall < 0.3:
            ex.spin_once(timeout_sec=0.05)
        self.bag.close()
        self.get_logger().info(f"{self.bag.path}: {self.n} messages on {len(self.subs)} topics")
        print(f"recorded {self.n} messages on {len(self.subs)} topics to {self.bag.path}", flush=True)


def main(args: list[str] | None = None) -> int:
    return run_node(RecorderNode, args)


if __name__ == "__main__":
    sys.exit(main())
