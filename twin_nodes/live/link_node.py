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
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

from msgs_py.topics import msg_class
from twin_nodes.nodes.common import GraphNode, declare, reliable_qos, run_node

LINK_TOPIC = "/twin_error/link_lost"


class LinkNode(GraphNode):
    def __init__(self) -> None:
        super().__init__("link_watch", consumer=False)
        self.stale_after_s = float(declare(self, "stale_after_s", 3.0, "no /real/odom for this long = link lost [s]"))
        self.summary_out = str(declare(self, "summary_out", "", "write the outages here (JSON) on exit"))
        self.step_period_s = 0.1
        self.pub = self.create_publisher(msg_class("std_msgs/msg/Bool"), LINK_TOPIC, reliable_qos(1, latched=True))
        self.create_subscription(msg_class("nav_msgs/msg/Odometry"), "/real/odom", self._on_odom, reliable_qos(50))
        self.create_subscription(msg_class("diagnostic_msgs/msg/DiagnosticArray"), "/diagnostics", self._on_diag, 10)
        self.t_start = time.monotonic()
        self.last_odom: float | None = None
        self.bridge_stale = False
        self.lost: bool | None = None
        self.outages: list[dict[str, Any]] = []
        self._lost_since: float | None = None
        self._last_pub = 0.0
        self.n_odom = 0

    def _on_odom(self, _msg: Any) -> None:
        self.last_odom = time.monotonic()
        self.n_odom += 1
        if self.lost:
            self.bridge_stale = False  # data flows again: the bridge's next diagnostic will agree
            self._update()

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            if st.name == "px4_bridge/link":
                self.bridge_stale = st.level == type(st).STALE
                self._update()

    def _update(self) -> None:
        now = time.monotonic()
        quiet = (now - (self.last_odom if self.last_odom is not None else self.t_start)) > self.stale_after_s
        fresh = self.last_odom is not None and now - self.last_odom < 0.5
        lost = quiet or (self.bridge_stale and not fresh)
        if lost != self.lost:
            if lost and self.last_odom is not None:
                self._lost_since = self.last_odom
                self.get_logger().warning(f"link lost: no /real/odom for {now - self.last_odom:.1f} s")
            elif not lost and self._lost_since is not None:
                gap = now - self._lost_since
                self.outages.append({"start_wall_s": time.time() - (now - self._lost_since), "length_s": gap})
                self.get_logger().info(f"link back after {gap:.1f} s")
                self._lost_since = None
            self.lost = lost
            self._publish(now)

    def _publish(self, now: float) -> None:
        self._last_pub = now
        self.pub.publish(msg_class("std_msgs/msg/Bool")(data=bool(self.lost)))

    def step(self) -> None:
        self._update()
        now = time.monotonic()
        if self.lost is not None and now - self._last_pub >= 1.0:
            self._publish(now)

    def close(self, interrupted: bool = False) -> None:
        if self._lost_since is not None and self.last_odom is not None:
            self.outages.append({"start_wall_s": time.time() - (time.monotonic() - self._lost_since),
                                 "length_s": time.monotonic() - self._lost_since, "open": True})
        if self.summary_out:
            from twin_nodes.base.io import atomic_write_text

            atomic_write_text(self.summary_out, json.dumps({"outages": self.outages, "odom_messages": self.n_odom,
                                                            "stale_after_s": self.stale_after_s}, indent=1))


def main(args: list[str] | None = None) -> int:
    return run_node(LinkNode, args)


if __name__ == "__main__":
    sys.exit(main())
