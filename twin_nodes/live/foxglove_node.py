"""Foxglove WebSocket server of the graph: its topics live in Foxglove, beside any running graph.

    python -m twin_nodes.live.foxglove_node --ros-args -p port:=8765 [-p host:=127.0.0.1] [-p mcap:=view.mcap]
    rotortwin live foxglove [--port 8765] [--domain-id D]

Open Foxglove, "Open connection" -> Foxglove WebSocket ``ws://127.0.0.1:8765`` and import
``layouts/rotortwin.json``.  The same layout opens the graph's MCAP recordings: the forwarded
channels carry the bag's topic names and messages.

What is served (foxglove-sdk, ws-protocol):

- every graph topic matching ``topics`` (default ``/real/...``, ``/twin/...``, ``/twin_error/...``,
  ``/clock``, ``/diagnostics``), discovered continuously, **unchanged**: the CDR bytes with the
  ``ros2msg`` schema of the type (``cdr`` encoding, as in the rosbag2 MCAP). Latched topics (and
  ``/real/status``, ``/twin_error/link_lost``) are sent again when a client subscribes.
- ``/viz/transforms`` (``foxglove.FrameTransforms``): ``odom`` -> ``real/base_link`` and
  ``odom`` -> ``twin/base_link`` from ``/real/odom`` and ``/twin/odom``;
- ``/viz/scene`` (``foxglove.SceneUpdate``): both vehicles (arms and rotor discs from the twin's
  params, ``/twin/config``; real blue, twin orange), their paths, the position setpoint;
- ``/viz/errors`` (JSON): every channel's rolling statistics from ``/twin_error/diagnostics`` and the
  link-loss flag; ``/viz/motors`` (JSON): real and twin motor commands side by side and their
  difference (either alone when only one side runs, e.g. ``bridge``); these two and
  ``/viz/transforms`` are advertised with their first record (a graph without metrics has no
  ``/viz/errors``, one without odometry no ``/viz/transforms``); ``/viz/status`` (JSON, 2 Hz):
  source (``replay``, ``simulator`` or ``live``), time, armed/mode/landed, link, twin, message
  counts, the final metrics once published.

Message times (``log_time``): a message's header stamp, else the latest ``/clock`` (replay), else
the wall clock (live), as the recorder times them.  The node subscribes best-effort (a viewer never
holds the graph up) and is not part of the replay's flow control.

Parameters: ``port`` (8765; 0 = any free), ``host`` ("127.0.0.1"; "0.0.0.0" to serve other
machines: the server has no authentication), ``topics`` (regex), ``scene_rate_hz`` (5),
``tf_rate_hz`` (30), ``path_spacing_m`` (0.1), ``max_rate_hz`` (0 = every message; else per topic),
``params_file`` (vehicle outline when no ``/twin/config`` is seen), ``mcap`` (also write everything
served into this MCAP file).  On start it prints ``FOXGLOVE ws://HOST:PORT`` on stdout.
"""

from __future__ import annotations

import json
import re
import sys
import threading
import time
from typing import Any

import numpy as np

from msgs_py.topics import DEPTH, msg_class
from twin_nodes.base.errors import TwinError
from twin_nodes.live.scene import (
    ERRORS_SCHEMA,
    MOTORS_SCHEMA,
    STATUS_SCHEMA,
    Trail,
    VehicleOutline,
    errors_record,
    frame_transforms,
    motors_record,
    scene_update,
    status_record,
    vehicle_from_config,
)
from twin_nodes.nodes.common import GraphNode, declare, run_node

DEFAULT_TOPICS = r"^/(real|twin|twin_error)/|^/(clock|diagnostics)$"
#: derived channels (Foxglove schemas / JSON), served beside the forwarded topics
VIZ_CHANNELS = ("/viz/transforms", "/viz/scene", "/viz/errors", "/viz/motors", "/viz/status")
JSON_SCHEMAS = {"/viz/errors": ERRORS_SCHEMA, "/viz/motors": MOTORS_SCHEMA, "/viz/status": STATUS_SCHEMA}
#: not latched, but sent on change only: a new subscriber gets the last one
STICKY = ("/real/status", "/twin_error/link_lost")
#: event topics (a vehicle restart, issue 28): advertised with their first message only, so that every
#: advertised channel carries data (most runs have none)
ON_FIRST = ("/real/reset", "/twin_error/reset")
#: forwarded topics the node also reads (deserialised) for the derived channels
DECODED = ("/real/odom", "/twin/odom", "/real/motors", "/twin/motors", "/real/status", "/real/setpoint_pose",
           "/twin_error/diagnostics", "/twin_error/link_lost", "/twin_error/final_json", "/twin/config",
           "/diagnostics", "/clock")


class FoxgloveNode(GraphNode):
    def __init__(self) -> None:
        super().__init__("foxglove", consumer=False)
        import foxglove
        from foxglove.channels import FrameTransformsChannel, SceneUpdateChannel

        port = int(declare(self, "port", 8765, "WebSocket port (0 = any free)"))
        host = str(declare(self, "host", "127.0.0.1", "listen address (0.0.0.0 = every interface, no auth)"))
        self.topic_re = re.compile(str(declare(self, "topics", DEFAULT_TOPICS, "regex of the topics to serve")))
        self.scene_period_s = 1.0 / max(float(declare(self, "scene_rate_hz", 5.0, "/viz/scene rate [Hz]")), 0.1)
        self.tf_period_s = 1.0 / max(float(declare(self, "tf_rate_hz", 30.0, "/viz/transforms rate [Hz]")), 0.1)
        spacing = float(declare(self, "path_spacing_m", 0.1, "path point spacing [m]"))
        max_rate = float(declare(self, "max_rate_hz", 0.0, "forward at most this rate per topic (0 = all)"))
        params_file = str(declare(self, "params_file", "", "vehicle params for the outline (else /twin/config)"))
        mcap = str(declare(self, "mcap", "", "also write everything served into this MCAP file"))
        self.min_gap_s = 1.0 / max_rate if max_rate > 0 else 0.0
        self.step_period_s = 0.05
        self._lock = threading.Lock()
        self._resend: set[str] = set()
        try:
            self.server = foxglove.start_server(name="rotortwin", host=host, port=port,
                                                server_listener=_Listener(self._resend, self._lock))
        except RuntimeError as exc:  # FoxgloveError: port in use, bad host ...
            raise TwinError(f"Foxglove server on {host}:{port}: {exc}") from None
        self.port = int(self.server.port)
        self.mcap_writer = foxglove.open_mcap(mcap, allow_overwrite=True) if mcap else None
        self._tf_channel_cls = FrameTransformsChannel
        self._ch_tf: Any = None  # advertised with the first pose
        self.ch_scene = SceneUpdateChannel("/viz/scene")
        # the JSON channels are advertised with their first record: a bridge alone has no errors to show
        self.ch_json: dict[str, Any] = {}
        self.channels: dict[str, Any] = {}
        self._channel_args: dict[str, tuple[Any, dict[str, str]]] = {}  # topic -> (schema, metadata)
        self.subs: dict[str, Any] = {}
        self.skipped: set[str] = set()
        self.sticky: set[str] = set(STICKY)
        self.last: dict[str, tuple[Any, int]] = {}      # topic -> (payload, log_time) to send again
        self.counts: dict[str, int] = {}
        self._last_fwd: dict[str, float] = {}
        self._typestore: Any = None
        # what the derived channels show
        self.clock_ns: int | None = None
        default = VehicleOutline.default()
        if params_file:
            from twin_nodes.vehicle.params import load_params
            default = VehicleOutline.from_params(load_params(params_file))
        self.outline: dict[str, VehicleOutline] = {"real": default, "twin": default}
        self.trails = {"real": Trail(spacing), "twin": Trail(spacing)}
        self.poses: dict[str, tuple[int, Any, Any]] = {}
        self._tf_due = {"real": 0.0, "twin": 0.0}
        self._motors_due = 0.0
        self.real_motors: Any = None
        self.twin_motors: Any = None
        self.status: Any = None
        self.setpoint: Any = None
        self.errors: dict[str, dict[str, float]] = {}
        self.link = "unknown"
        self.link_lost: bool | None = None
        self.twin_info: dict[str, Any] = {}
        self.final: dict[str, Any] | None = None
        self._scene_due = 0.0
        self._status_due = 0.0
        self._discover()
        self.wall_timer(0.5, self._discover)
        print(f"FOXGLOVE ws://{host}:{self.port}", flush=True)
        self.get_logger().info(f"Foxglove WebSocket server on ws://{host}:{self.port}")

    # ------------------------------------------------------------------ discovery and forwarding
    def _schema(self, type_name: str) -> Any:
        import foxglove

        if self._typestore is None:
            from twin_nodes.logs.recording import default_typestore
            self._typestore = default_typestore()
        text, _ = self._typestore.generate_msgdef(type_name, ros_version=2)
        return foxglove.Schema(name=type_name, encoding="ros2msg", data=text.encode("utf-8"))

    def _discover(self) -> None:
        import foxglove
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        for topic, types in self.get_topic_names_and_types():
            if topic in self.subs or topic in self.skipped or not self.topic_re.search(topic):
                continue
            pubs = self.get_publishers_info_by_topic(topic)
            if not pubs:
                continue
            if len(types) != 1:
                self.get_logger().warning(f"{topic}: {len(types)} types {types}, not served")
                self.skipped.add(topic)
                continue
            latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
            reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
            if latched:
                qos = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
                self.sticky.add(topic)
            else:  # a viewer never holds the graph up
                qos = QoSProfile(depth=min(DEPTH, 200), history=HistoryPolicy.KEEP_LAST,
                                 reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
            try:
                cls = msg_class(types[0])
                schema = self._schema(types[0])
            except Exception as exc:
                self.get_logger().warning(f"{topic} ({types[0]}): not served: {exc}")
                self.skipped.add(topic)
                continue
            meta = {"ros_type": types[0], "reliable": str(reliable).lower()}
            self.channels[topic] = None if topic in ON_FIRST else \
                foxglove.Channel(topic, schema=schema, message_encoding="cdr", metadata=meta)
            self._channel_args[topic] = (schema, meta)
            self.counts[topic] = 0
            self.subs[topic] = self.create_subscription(cls, topic, self._make_cb(topic, cls), qos, raw=True)

    def _make_cb(self, topic: str, cls: Any):
        from twin_nodes.logs.recording import cdr_header_stamp

        try:
            first = next(iter(cls.get_fields_and_field_types().values()), "")
        except Exception:
            first = ""
        stamped = first in ("std_msgs/Header", "builtin_interfaces/Time")
        decode = topic in DECODED
        sticky = topic in self.sticky

        def cb(data: bytes) -> None:
            self.counts[topic] += 1
            t = cdr_header_stamp(data) if stamped else (self.clock_ns if self.clock_ns is not None else time.time_ns())
            if decode:
                self._on_message(topic, cls, data, t)
            if sticky:
                self.last[topic] = (data, t)
            if self.min_gap_s and not sticky:
                now = time.monotonic()
                if now - self._last_fwd.get(topic, -1e9) < self.min_gap_s:
                    return
                self._last_fwd[topic] = now
            ch = self.channels[topic]
            if ch is None:  # an ON_FIRST topic: advertised now
                import foxglove

                schema, meta = self._channel_args[topic]
                ch = self.channels[topic] = foxglove.Channel(topic, schema=schema, message_encoding="cdr",
                                                             metadata=meta)
            ch.log(data, log_time=t)
        return cb

    # ------------------------------------------------------------------ derived channels
    def _on_message(self, topic: str, cls: Any, data: bytes, t: int) -> None:
        from rclpy.serialization import deserialize_message

        from twin_nodes.logs import conversions as cv

        m = deserialize_message(data, cls)
        if topic == "/clock":
            self.clock_ns = t if self.clock_ns is None else max(self.clock_ns, t)
        elif topic in ("/real/odom", "/twin/odom"):
            name = topic.split("/")[1]
            _, p, q, _, _ = cv.odom_arrays(m)
            if np.all(np.isfinite(p)) and np.all(np.isfinite(q)):
                self.poses[name] = (t, p, q)
                self.trails[name].add(p)
                now = time.monotonic()
                if now >= self._tf_due[name]:
                    self._tf_due[name] = now + self.tf_period_s
                    self._log_tf(frame_transforms({name: self.poses[name]}), t)
        elif topic in ("/real/motors", "/twin/motors"):
            if topic == "/real/motors":
                self.real_motors = cv.motors_array(m)
            else:
                self.twin_motors = cv.motors_array(m)
            now = time.monotonic()
            if now >= self._motors_due:  # either side alone (a bridge) is shown too
                self._motors_due = now + 0.05
                twin = self.twin_motors if self.twin_motors is not None else []
                self._log_json("/viz/motors", motors_record(t, self.real_motors, twin), t)
        elif topic == "/real/status":
            self.status = cv.status_array(m)
        elif topic == "/real/setpoint_pose":
            p = m.pose.position
            self.setpoint = (p.x, p.y, p.z)
        elif topic == "/twin_error/diagnostics":
            self.errors = cv.diagnostics_values(m)
            self._log_json("/viz/errors", errors_record(t, self.errors, self.link_lost), t)
        elif topic == "/twin_error/link_lost":
            self.link_lost = bool(m.data)
            self.link = "lost" if m.data else "ok"
        elif topic == "/diagnostics":
            for st in m.status:
                if st.name == "px4_bridge/link":
                    self.link = "stale" if st.level == type(st).STALE else "ok"
        elif topic == "/twin/config":
            try:
                cfg = json.loads(m.data)
            except ValueError:
                return
            self.twin_info = {k: cfg.get(k) for k in ("vehicle", "mode", "horizon_s", "params_file")}
            outline = vehicle_from_config(cfg)
            if outline is not None:
                self.outline = {"real": outline, "twin": outline}
        elif topic == "/twin_error/final_json":
            try:
                self.final = json.loads(m.data)
            except ValueError:
                pass

    def _log_tf(self, transforms: Any, t: int) -> None:
        if self._ch_tf is None:
            self._ch_tf = self._tf_channel_cls("/viz/transforms")
        self._ch_tf.log(transforms, log_time=t)

    def _log_json(self, topic: str, record: dict[str, Any], t: int) -> None:
        ch = self.ch_json.get(topic)
        if ch is None:
            import foxglove

            ch = self.ch_json[topic] = foxglove.Channel(topic, schema=JSON_SCHEMAS[topic])
        ch.log(record, log_time=t)
        self.last[topic] = (record, t)

    def _now_ns(self) -> int:
        return self.clock_ns if self.clock_ns is not None else time.time_ns()

    def _source(self) -> str:
        """``replay`` (/clock and /real), ``simulator`` (/clock, /twin only: ``bridge sim``), ``live``."""
        if self.clock_ns is None:
            return "live"
        return "replay" if self.counts.get("/real/odom") else "simulator"

    def step(self) -> None:
        now = time.monotonic()
        t = self._now_ns()
        if now >= self._scene_due:
            self._scene_due = now + self.scene_period_s
            sp = np.asarray(self.setpoint, float) if self.setpoint is not None else None
            self.ch_scene.log(scene_update(t, self.outline, self.trails, sp), log_time=t)
            if self.poses:
                self._log_tf(frame_transforms(self.poses), t)
        if now >= self._status_due:
            self._status_due = now + 0.5
            rec = status_record(source=self._source(), t_ns=t,
                                status=self.status, link=self.link, link_lost=self.link_lost, twin=self.twin_info,
                                messages=self.counts, final=self.final)
            self._log_json("/viz/status", rec, t)
        with self._lock:
            again = set(self._resend)
            self._resend.clear()
        for topic in again:
            if topic in self.last:
                payload, t_last = self.last[topic]
                ch = self.ch_json.get(topic) or self.channels.get(topic)
                if ch is not None:
                    ch.log(payload, log_time=t_last)

    def close(self, interrupted: bool = False) -> None:
        try:
            self.server.stop()
        finally:
            if self.mcap_writer is not None:
                self.mcap_writer.close()
        self.get_logger().info(f"served {sum(self.counts.values())} messages on {len(self.channels)} topics")


class _Listener:
    """foxglove ServerListener: remembers which topics were just subscribed (their last latched
    message is sent again from the node's loop, never from inside the server's callback)."""

    def __init__(self, resend: set[str], lock: threading.Lock):
        self._resend = resend
        self._lock = lock

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            self._resend.add(channel.topic)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        pass


def main(args: list[str] | None = None) -> int:
    return run_node(FoxgloveNode, args)


if __name__ == "__main__":
    sys.exit(main())
