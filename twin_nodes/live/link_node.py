"""Link watchdog of a live run: ``/twin_error/link_lost`` beside the error topics.

    python -m twin_nodes.live.link_node --ros-args -p stale_after_s:=3.0 [-p summary_out:=link.json]

The twin and the metrics only see the vehicle through ``/real/...``; when the telemetry link goes
quiet their error topics simply stop.  This node says why: ``/twin_error/link_lost``
(``std_msgs/Bool``, latched, on every change and once a second) is true when

- the PX4 bridge reports its link ``STALE`` on ``/diagnostics`` (``px4_bridge/link``), or
- no ``/real/odom`` arrived for ``stale_after_s`` seconds of wall time (also before the first one),

and false again with the first ``/real/odom`` after the link is back (the bridge reconnects by
itself: UDP listeners just wait, TCP/serial links are reopened).  Every outage is logged with its
wall-clock start and length, and ``summary_out`` (JSON) lists them when the node stops.

A clean end is not a link loss (issue 28): once the bridge says it stopped (``shutdown: true`` in
its diagnostic, sent when ``rotortwin live`` or Ctrl-C stops it) or the vehicle announced its own
shutdown (``vehicle_closed: true``: a ``MAV_STATE_POWEROFF`` heartbeat), the silence that follows
is recorded as that end (``ends`` in the summary), not as an outage.  The decisions are
:class:`LinkWatch` (pure, no ROS).
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

from msgs_py.topics import msg_class
from twin_nodes.nodes.common import GraphNode, declare, reliable_qos, run_node

LINK_TOPIC = "/twin_error/link_lost"


class LinkWatch:
    """The watchdog's decisions, on a monotonic clock ``now`` [s] (wall time for the node).

    ``odom(now)``: a ``/real/odom`` arrived; ``bridge(now, stale, shutdown, vehicle_closed)``: the
    bridge's link diagnostic; ``update(now)`` -> the new ``lost`` flag when it changed, else None;
    ``close(now)``: the end of the run.  ``outages``: ``{"start_s", "length_s"[, "open"]}`` (start
    on the clock of ``now`` until the node converts it), ``ends``: clean ends seen."""

    def __init__(self, stale_after_s: float, t_start: float):
        self.stale_after_s = float(stale_after_s)
        self.t_start = float(t_start)
        self.last_odom: float | None = None
        self.bridge_stale = False
        self.lost: bool | None = None
        self.lost_since: float | None = None
        self.outages: list[dict[str, Any]] = []
        self.ends: list[dict[str, Any]] = []
        self.ended: str | None = None  # "bridge stopped" / "vehicle shut down": the silence is no loss
        self.n_odom = 0

    def odom(self, now: float) -> bool | None:
        self.last_odom = now
        self.n_odom += 1
        if self.ended == "vehicle shut down":  # it came back (a restart): watch it again
            self.ended = None
        if self.lost:
            self.bridge_stale = False  # data flows again: the bridge's next diagnostic will agree
            return self.update(now)
        return None

    def bridge(self, now: float, stale: bool, shutdown: bool = False, vehicle_closed: bool = False) -> bool | None:
        self.bridge_stale = stale
        if shutdown and self.ended != "bridge stopped":
            self._end(now, "bridge stopped")
        elif vehicle_closed and self.ended is None:
            self._end(now, "vehicle shut down")
        return self.update(now)

    def _end(self, now: float, why: str) -> None:
        self.ended = why
        self.ends.append({"at_s": now, "reason": why})

    def update(self, now: float) -> bool | None:
        if self.ended is not None:
            lost = False  # a clean end: the silence after it is not a loss
            if self.lost_since is not None and self.last_odom is not None and self.lost_since < self.last_odom:
                self.lost_since = None
        else:
            quiet = (now - (self.last_odom if self.last_odom is not None else self.t_start)) > self.stale_after_s
            fresh = self.last_odom is not None and now - self.last_odom < 0.5
            lost = quiet or (self.bridge_stale and not fresh)
        if lost == self.lost:
            return None
        if lost and self.last_odom is not None:
            self.lost_since = self.last_odom
        elif not lost and self.lost_since is not None:
            self.outages.append({"start_s": self.lost_since, "length_s": now - self.lost_since})
            self.lost_since = None
        self.lost = lost
        return lost

    def close(self, now: float) -> None:
        if self.lost_since is not None and self.last_odom is not None and self.ended is None:
            self.outages.append({"start_s": self.lost_since, "length_s": now - self.lost_since, "open": True})
            self.lost_since = None


class LinkNode(GraphNode):
    def __init__(self) -> None:
        super().__init__("link_watch", consumer=False)
        self.stale_after_s = float(declare(self, "stale_after_s", 3.0, "no /real/odom for this long = link lost [s]"))
        self.summary_out = str(declare(self, "summary_out", "", "write the outages here (JSON) on exit"))
        self.step_period_s = 0.1
        self.pub = self.create_publisher(msg_class("std_msgs/msg/Bool"), LINK_TOPIC, reliable_qos(1, latched=True))
        self.create_subscription(msg_class("nav_msgs/msg/Odometry"), "/real/odom", self._on_odom, reliable_qos(50))
        self.create_subscription(msg_class("diagnostic_msgs/msg/DiagnosticArray"), "/diagnostics", self._on_diag, 10)
        self.watch = LinkWatch(self.stale_after_s, time.monotonic())
        self._last_pub = 0.0

    def _changed(self, lost: bool | None) -> None:
        if lost is None:
            return
        now = time.monotonic()
        w = self.watch
        if lost:
            self.get_logger().warning(f"link lost: no /real/odom for {now - (w.last_odom or w.t_start):.1f} s")
        elif w.outages:
            self.get_logger().info(f"link back after {w.outages[-1]['length_s']:.1f} s")
        self._publish(now)

    def _on_odom(self, _msg: Any) -> None:
        self._changed(self.watch.odom(time.monotonic()))

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            if st.name == "px4_bridge/link":
                kv = {v.key: v.value for v in st.values}
                was = self.watch.ended
                self._changed(self.watch.bridge(time.monotonic(), st.level == type(st).STALE,
                                                kv.get("shutdown") == "true", kv.get("vehicle_closed") == "true"))
                if self.watch.ended != was and self.watch.ended:
                    self.get_logger().info(f"{self.watch.ended}: the silence from here is not a link loss")

    def _publish(self, now: float) -> None:
        self._last_pub = now
        self.pub.publish(msg_class("std_msgs/msg/Bool")(data=bool(self.watch.lost)))

    def step(self) -> None:
        self._changed(self.watch.update(time.monotonic()))
        now = time.monotonic()
        if self.watch.lost is not None and now - self._last_pub >= 1.0:
            self._publish(now)

    def close(self, interrupted: bool = False) -> None:
        now = time.monotonic()
        self.watch.close(now)
        if self.summary_out:
            from twin_nodes.base.io import atomic_write_text

            to_wall = time.time() - now  # monotonic -> Unix time

            def wall(d: dict[str, Any], key: str, out: str) -> dict[str, Any]:
                d = dict(d)
                d[out] = d.pop(key) + to_wall
                return d
            outages = [wall(o, "start_s", "start_wall_s") for o in self.watch.outages]
            ends = [wall(e, "at_s", "at_wall_s") for e in self.watch.ends]
            atomic_write_text(self.summary_out, json.dumps({"outages": outages, "ends": ends,
                                                            "odom_messages": self.watch.n_odom,
                                                            "stale_after_s": self.stale_after_s}, indent=1))


def main(args: list[str] | None = None) -> int:
    return run_node(LinkNode, args)


if __name__ == "__main__":
    sys.exit(main())
