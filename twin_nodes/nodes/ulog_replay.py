"""ULog replay node: publishes a flight log as typed ``/real/...`` topics with the log's timing.

    python -m twin_nodes.nodes.ulog_replay --ros-args -p ulog:=FLIGHT.ulg -p rate:=20.0 \
        -p "wait_for:=['twin','metrics','recorder']"

Parameters: ``ulog`` (path of a ``.ulg``; or of a recorded bag directory / ``.mcap``, whose
``/real`` messages are republished byte for byte at their recorded times: how
``rotortwin regress`` replays a baseline), ``rate`` (1 = real time, 20 = 20x, 0 = as fast as the
``wait_for`` consumers keep up), ``wait_for`` (node names that must acknowledge;
see :mod:`twin_nodes.nodes.common`), ``window_s`` (how far ahead of the slowest
consumer the replay may run, log time), ``clock_period_s`` (``/clock`` spacing),
``stats_file`` (JSON with per-topic counts and throughput, written at the end),
``progress`` (print ``PROGRESS <t> <T>`` lines for the CLI's progress bar).

Topics and layouts: :mod:`msgs_py.topics`; which log series feed which topic:
:mod:`twin_nodes.logs.streams`.  ``/clock`` is the log time: PX4 hrt µs × 1000
(``start_ns`` in ``/replay/plan`` is the log start).  A topic the log cannot fill
is skipped with a warning; an unreadable file is a one-line error and exit 2.

A stretch with no message longer than ``window_s`` (a logger dropout) does not stall
the flow control: the replay moves ``/clock`` on to the edge of the window, the
consumers acknowledge it, and the window moves across the gap.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from twin_nodes.logs.streams import HEADERLESS, Stream, event_order, replay_streams
from msgs_py.topics import ACK_READY, TOPICS, msg_class
from twin_nodes.logs import conversions as cv
from twin_nodes.nodes.common import NS, GraphNode, declare, reliable_qos, run_node


def _builders() -> dict[str, Any]:
    """topic -> f(stream, row, t_ns) -> message."""
    return {
        "/real/odom": lambda s, i, t: cv.odom_msg(t, s.data["p"][i], s.data["q"][i], s.data["v_flu"][i],
                                                  s.data["w"][i]),
        "/real/imu": lambda s, i, t: cv.imu_msg(t, s.data["sf"][i], s.data["gyro"][i]),
        "/real/motors": lambda s, i, t: cv.motors_msg(s.data["v"][i]),
        "/real/esc_rpm": lambda s, i, t: cv.motors_msg(s.data["v"][i]),
        "/real/throttle": lambda s, i, t: cv.float32_msg(s.data["v"][i, 0]),
        "/real/battery": lambda s, i, t: cv.battery_msg(t, s.data["v"][i], s.data["a"][i]),
        "/real/setpoint": lambda s, i, t: cv.setpoint_msg(s.data["sp"][i]),
        "/real/setpoint_pose": lambda s, i, t: cv.setpoint_pose_msg(t, s.data["p"][i], s.data["yaw"][i]),
        "/real/status": lambda s, i, t: cv.status_msg(*s.data["v"][i]),
    }


class UlogReplay(GraphNode):
    def __init__(self) -> None:
        super().__init__("ulog_replay", consumer=False)
        from twin_nodes.logs.ulog_io import read_ulog

        path = declare(self, "ulog", "", "PX4 ULog file to replay")
        self.rate = float(declare(self, "rate", 1.0, "replay speed: 1 real time, 20 = 20x, 0 = as fast as "
                                                      "the wait_for consumers keep up"))
        self.wait_for = [n for n in declare(self, "wait_for", [""], "consumer node names to wait for") if n]
        self.window_ns = int(float(declare(self, "window_s", 0.5, "max log time ahead of the slowest "
                                                                  "consumer [s]")) * NS)
        self.clock_period_ns = int(float(declare(self, "clock_period_s", 0.05, "/clock spacing [s]")) * NS)
        self.stats_file = declare(self, "stats_file", "", "write per-topic counts and throughput here (JSON)")
        self.progress = bool(declare(self, "progress", False, "print PROGRESS lines on stdout"))
        self.start_timeout_s = float(declare(self, "start_timeout_s", 60.0, "give up waiting for consumers"))
        self.end_timeout_s = float(declare(self, "end_timeout_s", 120.0, "give up waiting for final acks"))
        if not path:
            raise ValueError("parameter 'ulog': expected the path of a .ulg file (or a recorded bag)")
        if self.rate < 0:
            raise ValueError(f"parameter 'rate': expected >= 0, got {self.rate}")
        self.log_path = path
        self.build = _builders()
        if _is_bag(path):
            streams, warns, self.start_ns, extra = _bag_streams(path)
            self.build = {s.topic: (lambda s, i, t: s.data["raw"][i]) for s in streams}
            n_motors, autostart = extra["n_motors"], extra["sys_autostart"]
        else:
            log = read_ulog(path)
            streams, warns = replay_streams(log)
            self.start_ns = int(log.start_us) * 1000
            n_motors, autostart = int(log.n_motors), log.params.get("SYS_AUTOSTART")
            extra = {"ulog": str(path)}
        for w in warns:
            self.get_logger().warning(w)
        if not streams:
            raise ValueError(f"{path}: nothing to replay")
        self.streams = streams
        self.ev_t, self.ev_s, self.ev_r = event_order(streams)
        self.ev_ns = self.start_ns + np.round(self.ev_t * NS).astype(np.int64)
        self.n_ev = len(self.ev_t)
        self.k = 0
        q = reliable_qos()
        latched = reliable_qos(depth=50, latched=True)
        self.pubs = [self.create_publisher(msg_class(TOPICS[s.topic].type), s.topic, q) for s in streams]
        self.clock_pub = self.create_publisher(msg_class("rosgraph_msgs/msg/Clock"), "/clock", q)
        self.done_pub = self.create_publisher(msg_class("std_msgs/msg/Bool"), "/replay/done", latched)
        plan_pub = self.create_publisher(msg_class("std_msgs/msg/String"), "/replay/plan", latched)
        tl_pub = self.create_publisher(msg_class("std_msgs/msg/Float64MultiArray"), "/replay/timeline", latched)
        self._latched = [self.done_pub, plan_pub, tl_pub]
        self.create_subscription(msg_class("diagnostic_msgs/msg/KeyValue"), "/replay/ack", self._on_ack, q)
        self.acks: dict[str, int | None] = {n: None for n in self.wait_for}
        self.counts = {s.topic: 0 for s in streams}
        self.counts["/clock"] = 0
        headerless = [s for s in streams if s.topic in HEADERLESS]
        self.plan = {**extra, "start_ns": self.start_ns,
                     "t0_ns": int(self.ev_ns[0]) if self.n_ev else self.start_ns,
                     "t1_ns": int(self.ev_ns[-1]) if self.n_ev else self.start_ns,
                     "counts": {s.topic: len(s) for s in streams},
                     "sources": {s.topic: s.source for s in streams},
                     "headerless": [s.topic for s in headerless], "n_motors": int(n_motors),
                     "sys_autostart": autostart, "warnings": warns}
        plan_pub.publish(cv.string_msg(json.dumps(self.plan)))
        for s in headerless:
            m = msg_class("std_msgs/msg/Float64MultiArray")()
            m.layout.dim = [msg_class("std_msgs/msg/MultiArrayDimension")(label=s.topic, size=len(s), stride=len(s))]
            m.data = ((self.start_ns + np.round(s.t_s * NS).astype(np.int64)) / NS).tolist()
            tl_pub.publish(m)
        self.state = "waiting"
        self.t_state = time.monotonic()
        self.last_clock = -(2 ** 62)
        self.wall0 = 0.0
        self.last_progress = 0.0
        self.step_period_s = 0.001
        self.get_logger().info(f"{path}: {self.n_ev} messages on {len(streams)} topics, "
                               f"{(self.ev_t[-1] - self.ev_t[0]) if self.n_ev else 0:.1f} s of log, "
                               f"rate {self.rate:g}, waiting for {self.wait_for or 'nobody'}")

    # ------------------------------------------------------------------ acks
    def _on_ack(self, msg: Any) -> None:
        if msg.key not in self.acks:
            return
        if msg.value == ACK_READY:
            if self.acks[msg.key] is None:
                self.acks[msg.key] = -1
            return
        self.acks[msg.key] = max(int(msg.value), self.acks[msg.key] or -1)

    def _all_ready(self) -> bool:
        if any(v is None for v in self.acks.values()):
            return False
        for p in self.pubs + [self.clock_pub]:
            want = len(self.get_subscriptions_info_by_topic(p.topic_name))
            if p.get_subscription_count() < want:
                return False
        return True

    def _min_ack(self) -> int:
        vals = [v for v in self.acks.values() if v is not None]
        if not vals:
            return 2 ** 62
        return min(max(v, int(self.ev_ns[0]) if self.n_ev else 0) for v in vals)

    # ------------------------------------------------------------------ loop
    def step(self) -> None:
        now = time.monotonic()
        if self.state == "waiting":
            if self._all_ready():
                self.state, self.t_state = "settling", now
            elif now - self.t_state > self.start_timeout_s:
                missing = [n for n, v in self.acks.items() if v is None]
                self.get_logger().error(f"consumers not ready after {self.start_timeout_s:.0f} s: {missing}")
                self.exit_code, self.finished = 3, True
        elif self.state == "settling":
            if now - self.t_state > 0.3:
                self.state, self.wall0 = "running", now
        elif self.state == "running":
            self._publish_batch(now)
        elif self.state == "ending":
            if self._min_ack() >= int(self.ev_ns[-1]) or now - self.t_state > self.end_timeout_s:
                if self._min_ack() < int(self.ev_ns[-1]):
                    self.get_logger().warning("final acknowledgements missing; publishing /replay/done anyway")
                self.wall_end = now
                self.done_pub.publish(cv.bool_msg(True))
                self.state, self.t_state = "lingering", now
        elif self.state == "lingering":
            if now - self.t_state > 0.5:
                self._write_stats()
                self.finished = True

    def _publish_batch(self, now: float) -> None:
        limit = self._min_ack() + self.window_ns if self.wait_for else 2 ** 62
        t_batch_end = now + 0.005
        ev_ns, ev_s, ev_r, ev_t = self.ev_ns, self.ev_s, self.ev_r, self.ev_t
        while self.k < self.n_ev:
            t = int(ev_ns[self.k])
            if t > limit:
                # the next message is beyond the window (a logger dropout longer than window_s):
                # move the clock on to the window's edge so that the consumers acknowledge it
                # and the window moves; nothing is published early
                if limit - self.last_clock >= self.clock_period_ns:
                    self._pub_clock(limit)
                break
            if self.rate > 0:
                due = self.wall0 + (ev_t[self.k] - ev_t[0]) / self.rate
                if due > time.monotonic():
                    break  # not due yet: step() runs again in step_period_s
            s_i = int(ev_s[self.k])
            stream = self.streams[s_i]
            if t - self.last_clock >= self.clock_period_ns:
                self._pub_clock(t)
            self.pubs[s_i].publish(self.build[stream.topic](stream, int(ev_r[self.k]), t))
            self.counts[stream.topic] += 1
            self.k += 1
            if (self.k & 63) == 0 and time.monotonic() > t_batch_end:
                break
        if self.progress and now - self.last_progress > 0.5:
            self.last_progress = now
            span = ev_t[-1] - ev_t[0]
            done_t = (ev_t[min(self.k, self.n_ev - 1)] - ev_t[0])
            print(f"PROGRESS {done_t:.3f} {span:.3f}", flush=True)
        if self.k >= self.n_ev:
            self._pub_clock(int(ev_ns[-1]))
            self.state, self.t_state = "ending", time.monotonic()
            if self.progress:
                print(f"PROGRESS {ev_t[-1] - ev_t[0]:.3f} {ev_t[-1] - ev_t[0]:.3f}", flush=True)

    def _pub_clock(self, t: int) -> None:
        self.clock_pub.publish(cv.clock_msg(t))
        self.counts["/clock"] += 1
        self.last_clock = t

    def _write_stats(self) -> None:
        wall = max(getattr(self, "wall_end", time.monotonic()) - self.wall0, 1e-9)
        span = float(self.ev_t[-1] - self.ev_t[0]) if self.n_ev else 0.0
        n = sum(self.counts.values())
        stats = {"ulog": self.log_path, "counts": self.counts, "messages": n, "wall_s": wall, "log_s": span,
                 "real_time_factor": span / wall, "messages_per_s": n / wall, "rate": self.rate,
                 "plan_counts": self.plan["counts"]}
        self.get_logger().info(f"replayed {n} messages ({span:.1f} s of log) in {wall:.2f} s: "
                               f"{span / wall:.1f}x real time, {n / wall:.0f} msg/s")
        if self.stats_file:
            with open(self.stats_file, "w", encoding="utf-8") as fh:
                json.dump(stats, fh, indent=1)

    def close(self, interrupted: bool = False) -> None:
        if interrupted and self.state not in ("lingering",):
            self.exit_code = 130


def _is_bag(path: str) -> bool:
    p = Path(path)
    return p.is_dir() or p.suffix == ".mcap"


def _bag_streams(path: str) -> tuple[list[Stream], list[str], int, dict[str, Any]]:
    """The ``/real`` topics of a recording as streams of their recorded CDR bytes (republished
    unchanged): time = header stamp for stamped topics, the recorded (timeline) time for the
    others; the topic order and ``start_ns`` of the recording's own ``/replay/plan``."""
    from twin_nodes.logs.recording import cdr_header_stamp, read_bag_raw

    bag = read_bag_raw(path, lambda t: t.startswith("/real/") or t == "/replay/plan")
    plan = json.loads(cv_string(bag["/replay/plan"])) if len(bag.get("/replay/plan") or []) else {}
    order = [t for t in plan.get("counts", {}) if t in bag] + sorted(t for t in bag if t.startswith("/real/")
                                                                     and t not in plan.get("counts", {}))
    warns: list[str] = []
    times: dict[str, np.ndarray] = {}
    for topic in order:
        bt = bag[topic]
        if topic not in TOPICS:
            warns.append(f"{topic}: not a topic of the replay, not published")
            continue
        if TOPICS[topic].stamped:
            t = np.array([cdr_header_stamp(r) for r in bt.raw], dtype=np.int64)
        else:
            t = np.asarray(bt.log_ns, dtype=np.int64)
        times[topic] = t
        want = plan.get("counts", {}).get(topic)
        if want is not None and int(want) != len(bt):
            warns.append(f"{topic}: the recording holds {len(bt)} of the {want} messages its replay announced")
    if not times:
        raise ValueError(f"{path}: /real: expected a recording of a replay or a live vehicle (no /real topic)")
    start = int(plan.get("start_ns", min(int(t.min()) for t in times.values() if t.size)))
    streams = []
    for topic, t in times.items():
        k = np.argsort(t, kind="stable")  # per-topic time order (older bags logged some at the latest /clock)
        raw = bag[topic].raw
        streams.append(Stream(topic, (t[k] - start) / NS, {"raw": [raw[i] for i in k]}, f"{path}:{topic}"))
    n_motors = plan.get("n_motors")
    if n_motors is None:
        n_motors = len(bag["/real/motors"].decode()[0].data) if len(bag.get("/real/motors") or []) else 4
    extra = {"ulog": plan.get("ulog", ""), "bag": str(path), "n_motors": int(n_motors),
             "sys_autostart": plan.get("sys_autostart")}
    return streams, warns, start, extra


def cv_string(bt: Any) -> str:
    """The text of the last message of a recorded ``std_msgs/String`` topic."""
    return str(bt.decode()[-1].data)


def main(args: list[str] | None = None) -> int:
    return run_node(UlogReplay, args)


if __name__ == "__main__":
    sys.exit(main())
