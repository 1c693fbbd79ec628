"""What every rotortwin node shares: QoS, the run loop, flow control, time of messages.

Pure helpers (no rclpy at import time): :class:`Timeline` (time of header-less
replayed messages), :class:`ReorderBuffer` (process inputs in time order).
rclpy is imported inside the functions that need it.

The graph protocol (see :mod:`msgs_py.topics` for the topics):

1. The replay node publishes the latched ``/replay/plan`` (JSON: the message count
   of every topic it will publish, the log span) and ``/replay/timeline`` (one
   ``Float64MultiArray`` per header-less topic: the times of all its messages),
   then waits until every node in its ``wait_for`` list says ``ready`` on
   ``/replay/ack`` and all its publishers are matched.
2. Consumers time header-less message *k* of topic X as ``timeline[X][k]``
   (per-topic order is kept by reliable QoS with deep queues), header messages by
   their stamp; they acknowledge the ``/clock`` they processed every
   ``ack_period_s`` of log time; the replay never gets more than ``window_s``
   ahead of the slowest one.
3. ``/replay/done`` ends the replay; a consumer finishes once it also holds every
   message the plan announced for the topics it subscribes to.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from typing import Any, Callable

import numpy as np

from msgs_py.topics import ACK_READY, DEPTH
from twin_nodes.nodes.engine import NS, ReorderBuffer, Timeline  # noqa: F401  (re-exported)

__all__ = ["Timeline", "ReorderBuffer", "reliable_qos", "make_executor", "run_node", "GraphNode",
           "NS", "declare", "source_stamps"]

# ============================================================================ rclpy parts


def reliable_qos(depth: int = DEPTH, latched: bool = False) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def _events_executor() -> Any:
    """rclpy's EventsExecutor class, or None (``ROTORTWIN_EXECUTOR=single``, or an older rclpy)."""
    if os.environ.get("ROTORTWIN_EXECUTOR", "events") == "single":
        return None
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:  # older rclpy
        return None
    return EventsExecutor


def make_executor() -> Any:
    """rclpy's EventsExecutor (several times faster than the SingleThreadedExecutor for
    high-rate topics); ``ROTORTWIN_EXECUTOR=single`` selects the classic one."""
    events = _events_executor()
    if events is not None:
        return events()
    from rclpy.executors import SingleThreadedExecutor
    return SingleThreadedExecutor()


def source_stamps() -> bool:
    """Whether subscriptions get the message info (callbacks ``(msg, info)``), so that header-less
    live messages are timed by their DDS source timestamp: the publisher's clock when it published,
    the same for every consumer however late each one runs.  Only with the classic executor: rclpy
    9's EventsExecutor fails on such callbacks ("null argument to internal routine"); ``rotortwin
    live`` runs its nodes with ``ROTORTWIN_EXECUTOR=single``."""
    return _events_executor() is None


def declare(node: Any, name: str, default: Any, description: str = "") -> Any:
    """Declare a parameter with a description and return its value.

    A float parameter also accepts an integer on the command line (``rate:=0``)."""
    from rcl_interfaces.msg import ParameterDescriptor

    is_float = isinstance(default, float)
    desc = ParameterDescriptor(description=description, dynamic_typing=is_float)
    value = node.declare_parameter(name, default, desc).value
    if is_float:
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ValueError(f"parameter '{name}': expected a number, got {value!r}") from None
    return value


def run_node(factory: Callable[[], Any], args: list[str] | None = None) -> int:
    """Run a node (see :func:`_run_node`); ``ROTORTWIN_PROFILE=DIR`` writes a cProfile to
    ``DIR/<pid>.prof`` for benchmarking."""
    prof_dir = os.environ.get("ROTORTWIN_PROFILE")
    if not prof_dir:
        return _run_node(factory, args)
    import cProfile

    pr = cProfile.Profile()
    try:
        return pr.runcall(_run_node, factory, args)
    finally:
        pr.dump_stats(os.path.join(prof_dir, f"{getattr(factory, '__name__', 'node')}_{os.getpid()}.prof"))


def _run_node(factory: Callable[[], Any], args: list[str] | None = None) -> int:
    """Init rclpy, build the node, spin until it finishes or SIGINT/SIGTERM, clean up.

    Signals only set a flag (rclpy's own handlers are disabled), so the node's
    ``close()`` runs with the context still alive (the recorder drains and finalises
    its bag there).  Returns the node's ``exit_code``."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    argv = sys.argv if args is None else args
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    stop = {"sig": 0}

    def on_signal(signum: int, _frame: Any) -> None:
        stop["sig"] = signum

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGHUP, on_signal)
    parent = _parent_pid()
    last_parent_check = [time.monotonic()]
    node = None
    code = 0
    try:
        try:
            node = factory()
        except Exception as exc:  # a clear one-line error, not a traceback
            from twin_nodes.base.errors import TwinError
            if isinstance(exc, (TwinError, ValueError, FileNotFoundError)):
                print(f"rotortwin node: error: {exc}", file=sys.stderr, flush=True)
                return 2
            raise
        from rclpy.task import Future

        done = Future()

        def tick() -> None:
            # the node's periodic work; also how a signal or `finished` ends the spin
            if parent and time.monotonic() - last_parent_check[0] > 0.5:
                last_parent_check[0] = time.monotonic()
                if os.getppid() != parent and not stop["sig"]:
                    # the process that started the graph died (kill -9): stop like on SIGTERM
                    node.get_logger().warning(f"parent process {parent} is gone: stopping")
                    stop["sig"] = signal.SIGTERM
            if stop["sig"] or node.finished or not rclpy.ok():
                if not done.done():
                    done.set_result(True)
                return
            node.step()
            if node.finished and not done.done():
                done.set_result(True)

        node.create_timer(node.step_period_s, tick, clock=node.wall_clock)
        ex = make_executor()
        ex.add_node(node)  # after every entity the node creates up front
        node.executor_ref = ex
        while not done.done():
            # with a timeout: rclpy's EventsExecutor never returns from an untimed call
            ex.spin_until_future_complete(done, timeout_sec=1.0)
        if stop["sig"]:
            node.get_logger().info(f"signal {stop['sig']}: stopping")
        node.close(interrupted=bool(stop["sig"]))
        node.get_logger().info(f"cpu {time.process_time():.2f} s")
        code = int(node.exit_code)
    finally:
        if node is not None:
            try:
                node.destroy_node()
            except Exception:
                pass
        try:
            rclpy.shutdown()
        except Exception:
            pass
    return code


def _parent_pid() -> int:
    """``$ROTORTWIN_PARENT_PID``: the orchestrator that started this node (0 = no watchdog).
    The node stops once its parent process is no longer that one."""
    try:
        return max(int(os.environ.get("ROTORTWIN_PARENT_PID", "0") or 0), 0)
    except ValueError:
        return 0


def _node_base() -> type:
    from rclpy.node import Node

    return Node


class GraphNode(_node_base()):  # type: ignore[misc]
    """Base of the rotortwin nodes: replay flow control, timelines, plan, done handling.

    Subclasses set ``self.inputs`` (the /real topics they count against the plan),
    implement ``on_clock(t_ns)`` / ``on_finish()`` as needed and may override
    ``is_ready()``.  ``finished`` ends the run loop, ``exit_code`` is returned."""

    def __init__(self, name: str, consumer: bool = True, **kw: Any):
        from rclpy.clock import Clock, ClockType

        super().__init__(name, **kw)
        from msgs_py.topics import msg_class

        self.finished = False
        self.exit_code = 0
        self.step_period_s = 0.005  # how often step() runs [s of wall time]
        self.executor_ref: Any = None
        self.consumer = consumer
        self.timeline = Timeline()
        self.plan: dict[str, Any] | None = None
        self.replay_done = False
        self.received: dict[str, int] = {}
        self.n_callbacks = 0  # input callbacks run (see drain())
        self.inputs: tuple[str, ...] = ()
        self.clock_ns: int | None = None
        self._last_ack = -(2 ** 62)
        self.ack_period_ns = int(declare(self, "ack_period_s", 0.1,
                                         "acknowledge the replay clock every this much log time [s]") * NS)
        self.wall_clock = Clock(clock_type=ClockType.STEADY_TIME)
        if consumer:
            q = reliable_qos()
            latched = reliable_qos(depth=50, latched=True)
            self._ack_pub = self.create_publisher(msg_class("diagnostic_msgs/msg/KeyValue"), "/replay/ack", q)
            self.create_subscription(msg_class("rosgraph_msgs/msg/Clock"), "/clock", self._on_clock, q)
            self.create_subscription(msg_class("std_msgs/msg/String"), "/replay/plan", self._on_plan, latched)
            self.create_subscription(msg_class("std_msgs/msg/Float64MultiArray"), "/replay/timeline",
                                     self._on_timeline, latched)
            self.create_subscription(msg_class("std_msgs/msg/Bool"), "/replay/done", self._on_done, latched)
            self.create_timer(0.2, self._ready_tick, clock=self.wall_clock)

    # ------------------------------------------------------------------ protocol
    def wall_timer(self, period_s: float, cb: Callable[[], None]) -> Any:
        return self.create_timer(period_s, cb, clock=self.wall_clock)

    def is_ready(self) -> bool:
        return True

    def plan_received(self) -> bool:
        """The replay's plan and the timelines of all its header-less topics are here."""
        return self.plan is not None and all(self.timeline.has(t) for t in self.plan.get("headerless", []))

    def _ready_tick(self) -> None:
        if self.clock_ns is None and self.plan_received() and self.is_ready():
            from twin_nodes.logs.conversions import ack_msg
            self._ack_pub.publish(ack_msg(self.get_name(), ACK_READY))

    def _on_clock(self, msg: Any) -> None:
        from twin_nodes.logs.conversions import ack_msg, clock_ns

        t = clock_ns(msg)
        self.clock_ns = t if self.clock_ns is None else max(self.clock_ns, t)
        self.on_clock(t)
        last = self.plan is not None and t >= int(self.plan.get("t1_ns", 2 ** 62))
        if t - self._last_ack >= self.ack_period_ns or last:
            self._last_ack = t
            self._ack_pub.publish(ack_msg(self.get_name(), str(t)))

    def ack_now(self) -> None:
        """Acknowledge the latest clock immediately (used at the end of the replay)."""
        from twin_nodes.logs.conversions import ack_msg

        if self.clock_ns is not None:
            self._ack_pub.publish(ack_msg(self.get_name(), str(self.clock_ns)))

    def _on_plan(self, msg: Any) -> None:
        self.plan = json.loads(msg.data)

    def _on_timeline(self, msg: Any) -> None:
        topic = msg.layout.dim[0].label
        if not self.timeline.has(topic):
            self.timeline.set(topic, np.round(np.asarray(msg.data) * NS).astype(np.int64))

    def _on_done(self, msg: Any) -> None:
        if msg.data:
            self.replay_done = True

    def count(self, topic: str) -> None:
        self.received[topic] = self.received.get(topic, 0) + 1

    def inputs_complete(self) -> bool:
        """The replay is done and every announced message of ``self.inputs`` arrived."""
        if not self.replay_done or self.plan is None:
            return False
        counts = self.plan.get("counts", {})
        return all(self.received.get(t, 0) >= int(counts.get(t, 0)) for t in self.inputs)

    def stamp_of(self, topic: str, info: Any = None) -> int:
        """Time [ns] of the next header-less message of ``topic``: its timeline entry on
        replay; live, its DDS source timestamp when the callback got the message ``info``
        (:func:`source_stamps`), else the node's clock now (when the callback runs)."""
        t = self.timeline.take(topic)
        if t is None:
            src = int(info["source_timestamp"]) if info is not None else 0
            return src if src > 0 else int(self.get_clock().now().nanoseconds)
        return t

    def header_less_callback(self, topic: str, handle: Callable[[Any, int], None]) -> Callable[..., None]:
        """A subscription callback that times each message with :meth:`stamp_of` and calls
        ``handle(msg, t_ns)``: ``(msg, info)`` where :func:`source_stamps`, else ``(msg)``."""
        if source_stamps():
            def cb_info(msg: Any, info: Any) -> None:
                handle(msg, self.stamp_of(topic, info))
            return cb_info

        def cb(msg: Any) -> None:
            handle(msg, self.stamp_of(topic))
        return cb

    def drain(self, quiet_s: float = 0.15, max_s: float = 3.0) -> None:
        """On stop: run the callbacks of messages already delivered (until ``n_callbacks`` stays
        unchanged for ``quiet_s``, ``max_s`` at most), so the last inputs are not left unread."""
        ex = self.executor_ref
        if ex is None:
            return
        t_end = time.monotonic() + max_s
        last, t_quiet = self.n_callbacks, time.monotonic()
        while time.monotonic() < t_end and time.monotonic() - t_quiet < quiet_s:
            ex.spin_once(timeout_sec=0.02)
            if self.n_callbacks != last:
                last, t_quiet = self.n_callbacks, time.monotonic()

    # ------------------------------------------------------------------ hooks
    def on_clock(self, t_ns: int) -> None:
        pass

    def step(self) -> None:
        """Called every ``step_period_s`` of wall time."""

    def close(self, interrupted: bool = False) -> None:
        pass
