"""Recorder node: every topic of the graph into one MCAP (rosbag2 layout).

    python -m twin_nodes.nodes.recorder_node --ros-args -p out:=run_bag -p use_sim_time:=true

Discovers topics continuously (``get_topic_names_and_types``) and subscribes to
each with serialized (``raw=True``) messages, matching the publishers' QoS
(reliable or best effort; transient-local when a publisher is latched, so
``/replay/plan``, ``/replay/done`` and ``/twin_error/final_json`` are kept).
The CDR bytes go to the bag unchanged through :class:`twin_nodes.logs.recording.McapRecorder`
(``rosbags`` writer: ``metadata.yaml`` + ``<out>/<out>.mcap``; an ``out`` ending in ``.mcap`` is that one
file, the rosbag2 metadata inside it).

Message time in the bag (every message at its own time, never wall-clock time on a replay):

- messages with a header (and ``/clock``): their own stamp;
- header-less replayed ``/real`` topics: their exact log time from ``/replay/timeline``;
- ``/twin/motors``, ``/twin/throttle``: the stamp of the ``/twin/odom`` message with the
  same index; each ``/twin_error/<channel>/<stat>``: that of the ``/twin_error/diagnostics``
  array published with it;
- the rest (``/replay/*``, ``/twin/done``, ``/twin_error/final_*``): the latest ``/clock``,
  before the first ``/clock`` the replay's first message time (``t0_ns`` of its plan).

Messages are held for ``reorder_lag_s`` (2 s) of message time behind the replay's clock, or behind the
slowest ``/twin*`` stream still publishing where that is later (the twin's outputs come up to a second
behind the replay, more when its node is starved of CPU), and written in time order, so the MCAP chunks
do not overlap in time.  ``exclude`` (regex) skips topics, default ``/rosout`` and
``/parameter_events``.

Stopping: SIGINT/SIGTERM (and the death of the process that started it, see
:mod:`twin_nodes.nodes.common`) drain what is queued and finalise the bag. The drain waits, up to
``drain_timeout_s`` (20 s), for every message the graph announced (the replay plan's counts, ``/twin/done``'s
sample count for each twin output); if some never come the bag is still finalised and kept, one line on stderr
names each short topic ("/twin/odom 1243 of 1254") and the node exits 3 (``run_graph`` stops the recorder before
the other nodes, so their reliable writers still hold what it has not yet taken). After a
``kill -9`` the chunks already written survive (the messages held for ordering and the
open chunk are lost) and ``rotortwin record recover
<out>`` rebuilds a valid bag (:func:`twin_nodes.logs.recording.recover`).
"""

from __future__ import annotations

import re
import struct
import sys
import time
from collections import deque
from typing import Any

from msgs_py.topics import DEPTH, msg_class
from twin_nodes.logs.recording import INCOMPLETE_EXIT, McapRecorder, cdr_header_stamp
from twin_nodes.nodes.common import NS, GraphNode, ReorderBuffer, declare, run_node
from twin_nodes.nodes.engine import TWIN_OUTPUTS, FollowerWatermark

TWIN_DONE = "/twin/done"
#: empty polls in a row (0.05 s each) that say nothing more is queued for the recorder
DRAIN_EMPTY_POLLS = 6
#: with nothing announced still to come, the longest drain [s] (a live stream never pauses)
DRAIN_LIVE_S = 3.0

#: streams computed from the replay, which run behind its clock: the twin's and the metrics' outputs
FOLLOWER_PREFIX = "/twin"


#: header-less topics published one-to-one with a stamped one: message k takes the stamp of message k there
INDEX_STAMPS = {"/twin/motors": "/twin/odom", "/twin/throttle": "/twin/odom"}
_METRIC = re.compile(r"^/twin_error/(?!diagnostics$|final_)[^/]+/[^/]+$")


class RecorderNode(GraphNode):
    def __init__(self) -> None:
        super().__init__("recorder")
        out = declare(self, "out", "", "recording to create: a bag directory (rosbag2 layout) or one .mcap file")
        self.exclude = re.compile(declare(self, "exclude", r"^/(rosout|parameter_events)$",
                                          "regex of topics not to record"))
        fsync = bool(declare(self, "fsync", False, "fsync every chunk (power-loss safety)"))
        chunk_s = float(declare(self, "chunk_period_s", 1.0, "close an MCAP chunk every ... s of message time"))
        lag_s = float(declare(self, "reorder_lag_s", 2.0, "write messages in time order, holding them this "
                                                          "long [s of message time]"))
        self.drain_timeout_s = float(declare(self, "drain_timeout_s", 20.0,
                                             "on stop, wait up to this long [s] for messages announced but not yet "
                                             "received (the replay's plan counts, /twin/done)"))
        if not out:
            raise ValueError("parameter 'out': expected a bag directory or .mcap file to create")
        self.bag = McapRecorder(out, chunk_period_s=chunk_s, fsync_chunks=fsync)
        self.subs: dict[str, Any] = {}
        self.kind: dict[str, str] = {}
        self.skipped: set[str] = set()
        self.n = 0
        self.received: dict[str, int] = {}
        self.twin_done: int | None = None
        self.last_msg_wall = time.monotonic()
        self.t_start_wall = time.monotonic()
        self.buf = ReorderBuffer(int(lag_s * NS))
        self.followers = FollowerWatermark()
        self.pending: dict[str, deque] = {}
        self.index_stamps: dict[str, list[int]] = {src: [] for src in set(INDEX_STAMPS.values())}
        self.index_stamps["/twin_error/diagnostics"] = []
        self.index_next: dict[str, int] = {}
        self.max_t = -(2 ** 62)
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
            self.kind[topic] = _stamp_kind(topic, cls)
            self.pending[topic] = deque()
            self.index_next[topic] = 0
            self.subs[topic] = self.create_subscription(cls, topic, self._make_cb(topic), qos, raw=True)

    # ------------------------------------------------------------------ message times
    def _make_cb(self, topic: str):
        def cb(data: bytes) -> None:
            self.last_msg_wall = time.monotonic()
            self.received[topic] = self.received.get(topic, 0) + 1
            if topic == TWIN_DONE:
                self.twin_done = _uint64_cdr(data)
            if self.kind[topic] == "header":
                t = cdr_header_stamp(data)
                if topic in self.index_stamps:
                    self.index_stamps[topic].append(t)
                if topic.startswith(FOLLOWER_PREFIX):
                    self.followers.seen(topic, t, self.last_msg_wall)
                self._push(topic, t, data)
                return
            if self.kind[topic] == "plain" and self.timeline.has(topic) and not self.pending[topic]:
                # a replayed header-less topic: its exact time from /replay/timeline
                self._push(topic, self.timeline.take(topic), data)
                return
            self.pending[topic].append(data)
            self._resolve(topic)
        return cb

    def _time_of(self, topic: str, final: bool = False) -> int | None:
        """The time of the next pending message of a header-less topic, or None (not yet known)."""
        kind = self.kind[topic]
        if kind.startswith("index:") and (self.plan is not None or final):
            stamps = self.index_stamps[kind[6:]]
            i = self.index_next[topic]
            if i < len(stamps):
                self.index_next[topic] = i + 1
                return stamps[i]
            if not final:
                return None
        if self.clock_ns is not None:
            return self.clock_ns
        if self.plan is not None:
            return int(self.plan.get("t0_ns", self.plan.get("start_ns", 0)))
        if topic.startswith("/replay/") and not final:
            return None  # a replay's topics: wait for its plan, never wall-clock time
        if final or time.monotonic() - self.t_start_wall > 2.0:
            # live data without /clock or replay: the node's clock
            return int(self.get_clock().now().nanoseconds) if self.max_t < 0 else self.max_t
        return None

    def _resolve(self, topic: str, final: bool = False) -> None:
        q = self.pending[topic]
        while q:
            t = self._time_of(topic, final)
            if t is None:
                return
            self._push(topic, t, q.popleft())

    def _push(self, topic: str, t: int, data: bytes) -> None:
        t = max(int(t), 0)
        self.max_t = max(self.max_t, t)
        self.buf.push(t, (topic, data))

    def _write_ready(self, flush: bool = False) -> None:
        # the replay's clock, held back to the slowest stream still computed from it (FollowerWatermark)
        clock = self.clock_ns if self.clock_ns is not None else self.max_t
        self.buf.advance(self.followers.limit(clock, time.monotonic()))
        for t, (topic, data) in self.buf.pop_ready(flush=flush):
            self.bag.write_raw(topic, data, t)
            self.n += 1

    def step(self) -> None:
        for topic, q in self.pending.items():
            if q:
                self._resolve(topic)
        self._write_ready()

    # ------------------------------------------------------------------ life cycle
    def is_ready(self) -> bool:
        # every topic that has a publisher is subscribed (a topic with subscribers only, e.g. a
        # log without motors, never gets one: it does not hold the replay up) ...
        for t, _ in self.get_topic_names_and_types():
            if t not in self.subs and t not in self.skipped and not self.exclude.search(t) and \
                    self.get_publishers_info_by_topic(t):
                return False
        # ... including everything the replay's plan announces
        if self.plan is not None and any(t not in self.subs for t in self.plan.get("counts", {})):
            return False
        for t, s in self.subs.items():
            if s.get_publisher_count() < len(self.get_publishers_info_by_topic(t)):
                return False
        return True

    def announced(self) -> dict[str, int]:
        """Messages each recorded topic is known to carry in all: the replay's plan counts and, once
        ``/twin/done`` came, its sample count for every twin output."""
        want = {t: int(n) for t, n in (self.plan or {}).get("counts", {}).items() if t in self.subs}
        if self.twin_done is not None:
            want.update({t: self.twin_done for t in TWIN_OUTPUTS if t in self.subs})
        return want

    def missing(self) -> dict[str, tuple[int, int]]:
        """Announced topics short of their count: topic -> (received, announced)."""
        return {t: (self.received.get(t, 0), n) for t, n in self.announced().items() if self.received.get(t, 0) < n}

    def _drain(self) -> None:
        """Take what the middleware still holds: until every announced message is here and nothing more is
        ready (a few empty polls in a row, counted in polls rather than wall time, so that a process starved of
        CPU does not mistake its own pause for a quiet graph), at most ``drain_timeout_s``. A live stream that
        never pauses and announced nothing is cut after ``DRAIN_LIVE_S``."""
        ex = self.executor_ref
        if ex is None:
            return
        t0 = time.monotonic()
        empty = 0
        while time.monotonic() - t0 < self.drain_timeout_s:
            before = sum(self.received.values())
            ex.spin_once(timeout_sec=0.05)
            empty = empty + 1 if sum(self.received.values()) == before else 0
            if (empty >= DRAIN_EMPTY_POLLS or time.monotonic() - t0 > DRAIN_LIVE_S) and not self.missing():
                return

    def close(self, interrupted: bool = False) -> None:
        # drain what is queued and announced, then write everything in time order and finalise the bag
        self._drain()
        short = self.missing()
        for topic in self.pending:
            self._resolve(topic, final=True)
        self._write_ready(flush=True)
        self.bag.close()
        self.get_logger().info(f"{self.bag.path}: {self.n} messages on {len(self.subs)} topics")
        print(f"recorded {self.n} messages on {len(self.subs)} topics to {self.bag.path}", flush=True)
        if short:
            # never a silent gap: the bag is valid and kept, but it lacks messages the graph announced
            gaps = ", ".join(f"{t} {got} of {want}" for t, (got, want) in sorted(short.items()))
            print(f"rotortwin recorder: {self.bag.path}: incomplete after {self.drain_timeout_s:.0f} s of draining: "
                  f"{gaps}", file=sys.stderr, flush=True)
            self.exit_code = INCOMPLETE_EXIT


def _uint64_cdr(data: bytes) -> int:
    """A serialized ``std_msgs/UInt64``: 4-byte encapsulation header (its first two bytes name the byte
    order), then the value, 8-byte aligned from the payload's start, i.e. at offset 4."""
    order = "<" if data[1] in (1, 3) else ">"
    return int(struct.unpack_from(order + "Q", data, 4)[0])


def _stamp_kind(topic: str, cls: Any) -> str:
    """How a topic's messages are timed in the bag: ``header`` (the message's own stamp: a
    ``std_msgs/Header`` or ``builtin_interfaces/Time`` first field, e.g. ``/clock``),
    ``index:<topic>`` (the stamp of the message with the same index there) or ``plain``
    (the replay timeline, else the latest ``/clock``)."""
    try:
        first = next(iter(cls.get_fields_and_field_types().values()), "")
    except Exception:
        first = ""
    if first in ("std_msgs/Header", "builtin_interfaces/Time"):
        return "header"
    if topic in INDEX_STAMPS:
        return "index:" + INDEX_STAMPS[topic]
    if _METRIC.match(topic):
        return "index:/twin_error/diagnostics"  # published one each right before the diagnostics array
    return "plain"


def main(args: list[str] | None = None) -> int:
    return run_node(RecorderNode, args)


if __name__ == "__main__":
    sys.exit(main())
