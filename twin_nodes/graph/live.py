"""Live views of a running graph from an in-process rclpy node: the metrics monitor, topic list, echo.

Each function spins its own short-lived node (``rclpy.init`` .. ``rclpy.shutdown``) on the
domain of the environment, or ``domain_id`` (which then becomes the process's ``ROS_DOMAIN_ID``).
"""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from twin_nodes.base.errors import TwinError


def spin_node(name: str, setup: Callable[[Any], Any], duration: float | None, until: Any = None) -> None:
    """Spin a node ``name``: ``setup(node)`` returns a tick run after every spin (or None); stop after
    ``duration`` seconds, when ``until()`` is true, or on Ctrl-C."""
    import rclpy
    from rclpy.node import Node

    from twin_nodes.nodes.common import make_executor

    rclpy.init(args=[sys.argv[0]])
    node = Node(name)
    try:
        tick = setup(node)
        ex = make_executor()
        ex.add_node(node)
        t_end = time.monotonic() + duration if duration else math.inf
        while rclpy.ok() and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
            if tick is not None:
                tick()
            if until is not None and until():
                break
    except KeyboardInterrupt:
        pass
    except Exception as exc:  # Ctrl-C: rclpy's handler shuts the context down under the spin
        if type(exc).__name__ != "ExternalShutdownException":
            raise
    finally:
        node.destroy_node()
        try:
            rclpy.shutdown()
        except Exception:
            pass


def _use_domain(domain_id: int | None) -> None:
    if domain_id is not None:
        os.environ["ROS_DOMAIN_ID"] = str(domain_id)


def format_monitor(values: dict[str, float], t_s: float | None) -> str:
    """The monitor's table: one row per channel, one column per statistic."""
    from msgs_py.topics import METRIC_STATS

    chans: list[str] = []
    for topic in values:
        ch = topic.split("/")[2]
        if ch not in chans:
            chans.append(ch)
    order = {c: i for i, c in enumerate(["xy", "z", "throttle"])}
    chans.sort(key=lambda c: (order.get(c, 3), len(c), c))
    head = f"{'channel':<13}" + "".join(f"{s:>12}" for s in METRIC_STATS)
    lines = [f"twin error, rolling window  (log time {t_s:.1f} s)" if t_s is not None else "twin error, rolling window",
             head, "-" * len(head)]
    for ch in chans:
        unit = "m" if ch in ("xy", "z") else "%"
        row = f"{ch + ' [' + unit + ']':<13}"
        for st in METRIC_STATS:
            topic = f"/twin_error/{ch}/{st}" + ("_m" if unit == "m" else "")
            v = values.get(topic, math.nan)
            v = v * 100 if unit == "%" else v
            row += f"{v:>12.3f}" if math.isfinite(v) else f"{'-':>12}"
        lines.append(row)
    return "\n".join(lines)


@dataclass
class MonitorState:
    """What the monitor saw: the latest value per ``/twin_error/...`` Float64 topic, the log time
    from ``/clock`` and the metrics node's latched final table (None until it is published)."""

    values: dict[str, float] = field(default_factory=dict)
    t_s: float | None = None
    final: str | None = None


def watch_metrics(*, once: bool = False, duration: float | None = None, domain_id: int | None = None,
                  on_draw: Callable[[MonitorState], None] | None = None) -> MonitorState:
    """Follow the ``/twin_error/...`` topics; ``on_draw(state)`` every 0.5 s (not with ``once``).

    ``once``: stop as soon as every discovered metric topic (at least 12) has a value, after 30 s
    at most unless ``duration`` says otherwise."""
    from msgs_py.topics import msg_class

    _use_domain(domain_id)
    state = MonitorState()
    subs: dict[str, Any] = {}
    last_draw = [0.0]

    def setup(node: Any) -> Any:
        f64 = msg_class("std_msgs/msg/Float64")
        from twin_nodes.nodes.common import reliable_qos
        node.create_subscription(msg_class("rosgraph_msgs/msg/Clock"), "/clock",
                                 lambda m: setattr(state, "t_s", m.clock.sec + m.clock.nanosec * 1e-9), 10)
        node.create_subscription(msg_class("std_msgs/msg/String"), "/twin_error/final_table",
                                 lambda m: setattr(state, "final", m.data), reliable_qos(1, latched=True))

        def tick() -> None:
            for topic, types in node.get_topic_names_and_types():
                if topic.startswith("/twin_error/") and types == ["std_msgs/msg/Float64"] and topic not in subs:
                    subs[topic] = node.create_subscription(
                        f64, topic, lambda m, tp=topic: state.values.__setitem__(tp, float(m.data)), 10)
            now = time.monotonic()
            if now - last_draw[0] >= 0.5:
                last_draw[0] = now
                if not once and on_draw is not None:
                    on_draw(state)
        return tick

    values = state.values
    until = (lambda: bool(values) and len(values) >= len(subs) and len(subs) >= 12) if once else None
    spin_node("rotortwin_monitor", setup, duration if duration else (30.0 if once else None), until)
    return state


def topic_types(wait: float, domain_id: int | None = None) -> dict[str, list[str]]:
    """Topic name -> types seen on the network within ``wait`` seconds."""
    _use_domain(domain_id)
    found: dict[str, list[str]] = {}

    def setup(node: Any) -> Any:
        def tick() -> None:
            for t, ty in node.get_topic_names_and_types():
                found[t] = ty
        return tick

    spin_node("rotortwin_topics", setup, wait)
    return found


def echo_topic(topic: str, on_message: Callable[[int, Any], None], *, wait: float = 1.5, count: int = 0,
               duration: float | None = None, domain_id: int | None = None) -> int:
    """Subscribe to ``topic`` with its publisher's QoS; ``on_message(n, msg)`` for message n = 1, 2, ...

    Stops after ``count`` messages (0: no limit), ``duration`` seconds or Ctrl-C; returns how many
    arrived.  TwinError if the topic is not seen within ``wait`` seconds."""
    from msgs_py.topics import msg_class

    _use_domain(domain_id)
    got = {"n": 0}

    def setup_echo(node: Any) -> None:
        from rclpy.qos import QoSProfile

        ty = None
        t_end = time.monotonic() + wait
        while ty is None and time.monotonic() < t_end:
            for t, tys in node.get_topic_names_and_types():
                if t == topic:
                    ty = tys[0]
            if ty is None:
                time.sleep(0.1)
        if ty is None:
            raise TwinError(f"{topic}: no such topic after {wait:g} s")
        pubs = node.get_publishers_info_by_topic(topic)
        qos = QoSProfile(depth=100)
        if pubs:
            qos.reliability = pubs[0].qos_profile.reliability
            qos.durability = pubs[0].qos_profile.durability

        def cb(m: Any) -> None:
            got["n"] += 1
            on_message(got["n"], m)
        node.create_subscription(msg_class(ty), topic, cb, qos)

    spin_node("rotortwin_echo", setup_echo, duration, until=lambda: count and got["n"] >= count)
    return got["n"]
