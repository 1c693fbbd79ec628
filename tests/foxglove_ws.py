"""A minimal Foxglove WebSocket (ws-protocol) client for the tests, independent of the server's code.

It subscribes to every channel the server advertises (also ones advertised later), and decodes
every message by the channel's encoding alone.  foxglove-sdk 0.30 has a race: a subscribe that
arrives within microseconds of the channel's advertisement is refused with a status "Unknown
channel ID: N" (about 2 in 300 channels created while a client is connected; a person's Foxglove
app subscribes far later than this client does); the client subscribes again 50 ms later, as a
ws-protocol client may, and counts it in ``retries``.  Encodings: ``cdr`` with the ``ros2msg`` schema text
(mcap_ros2's dynamic decoder, no rclpy), ``protobuf`` with the base64 ``FileDescriptorSet``
(google.protobuf), ``json``.
"""

from __future__ import annotations

import base64
import json
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


def decoder_for(channel: dict[str, Any]):
    """``payload -> decoded object`` for an advertised channel (raises if it cannot be built)."""
    enc = channel["encoding"]
    if enc == "cdr":
        from mcap_ros2._dynamic import generate_dynamic

        return generate_dynamic(channel["schemaName"], channel["schema"])[channel["schemaName"]]
    if enc == "protobuf":
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
        pool = descriptor_pool.DescriptorPool()
        for f in fds.file:
            pool.Add(f)
        cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
        return cls.FromString
    if enc == "json":
        return lambda b: json.loads(b.decode("utf-8"))
    raise ValueError(f"{channel['topic']}: unknown encoding {enc!r}")


@dataclass
class Capture:
    channels: dict[int, dict[str, Any]] = field(default_factory=dict)   # channel id -> advertisement
    messages: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)  # topic -> [(log_time, decoded)]
    errors: dict[str, str] = field(default_factory=dict)              # topic -> first decode error
    server_info: dict[str, Any] | None = None
    other_ops: list[dict[str, Any]] = field(default_factory=list)  # status, unadvertise, ... as sent
    retries: dict[str, int] = field(default_factory=dict)           # topic -> subscribes sent again
    subscribed: dict[str, int] = field(default_factory=dict)        # topic -> subscription id

    def topics(self) -> set[str]:
        return {c["topic"] for c in self.channels.values()}


class FoxgloveClient:
    """Connect in a thread, subscribe to everything, decode everything, until :meth:`close`."""

    def __init__(self, url: str, connect_timeout_s: float = 30.0):
        self.url = url
        self.cap = Capture()
        self._stop = threading.Event()
        self._connected = threading.Event()
        self._connect_timeout_s = connect_timeout_s
        self._thread = threading.Thread(target=self._run, daemon=True)
        self.exc: BaseException | None = None

    def start(self) -> "FoxgloveClient":
        self._thread.start()
        if not self._connected.wait(self._connect_timeout_s + 5):
            raise TimeoutError(f"no connection to {self.url}: {self.exc}")
        return self

    def close(self) -> Capture:
        self._stop.set()
        self._thread.join(10)
        return self.cap

    def _connect(self):
        from websockets.sync.client import connect

        deadline = time.monotonic() + self._connect_timeout_s
        while True:
            try:
                return connect(self.url, subprotocols=SUBPROTOCOLS, max_size=None, open_timeout=5)
            except OSError as exc:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{self.url}: {exc}") from exc
                time.sleep(0.2)

    def _run(self) -> None:
        try:
            ws = self._connect()
        except BaseException as exc:  # reported by start()
            self.exc = exc
            return
        self._connected.set()
        subs: dict[int, int] = {}       # subscription id -> channel id
        decoders: dict[int, Any] = {}
        next_sub = 1
        again: list[tuple[float, int]] = []  # (when, channel id) to subscribe to again
        with ws:
            while not self._stop.is_set():
                due = [c for t, c in again if t <= time.monotonic()]
                if due:
                    again = [(t, c) for t, c in again if t > time.monotonic()]
                    new = []
                    for cid in due:
                        subs[next_sub] = cid
                        new.append({"id": next_sub, "channelId": cid})
                        topic = self.cap.channels[cid]["topic"]
                        self.cap.subscribed[topic] = next_sub
                        self.cap.retries[topic] = self.cap.retries.get(topic, 0) + 1
                        next_sub += 1
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                try:
                    data = ws.recv(timeout=0.1)
                except TimeoutError:
                    continue
                except Exception as exc:  # closed by the server
                    self.exc = exc
                    return
                if isinstance(data, str):
                    msg = json.loads(data)
                    op = msg.get("op")
                    if op == "serverInfo":
                        self.cap.server_info = msg
                    elif op != "advertise":
                        self.cap.other_ops.append(msg)
                        text = str(msg.get("message", ""))
                        if op == "status" and text.startswith("Unknown channel ID: "):
                            cid = int(text.rsplit(" ", 1)[1])
                            if cid in self.cap.channels and self.cap.retries.get(
                                    self.cap.channels[cid]["topic"], 0) < 5:
                                again.append((time.monotonic() + 0.05, cid))
                    elif op == "advertise":
                        new = []
                        for ch in msg["channels"]:
                            self.cap.channels[ch["id"]] = ch
                            self.cap.messages.setdefault(ch["topic"], [])
                            try:
                                decoders[ch["id"]] = decoder_for(ch)
                            except Exception as exc:
                                self.cap.errors.setdefault(ch["topic"], f"schema: {exc!r}")
                            subs[next_sub] = ch["id"]
                            self.cap.subscribed[ch["topic"]] = next_sub
                            new.append({"id": next_sub, "channelId": ch["id"]})
                            next_sub += 1
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    continue
                if not data or data[0] != 0x01:  # only MessageData
                    continue
                sub_id, log_time = struct.unpack_from("<IQ", data, 1)
                cid = subs.get(sub_id)
                if cid is None:
                    continue
                topic = self.cap.channels[cid]["topic"]
                try:
                    obj = decoders[cid](bytes(data[13:]))
                except Exception as exc:
                    self.cap.errors.setdefault(topic, f"decode: {exc!r}")
                    continue
                self.cap.messages[topic].append((log_time, obj))


def silent_channels(cap: Capture) -> list[str]:
    """Advertised channels that delivered no decodable message."""
    return sorted(t for t in cap.topics() if not cap.messages[t])


def url_from_stderr(proc, timeout_s: float = 120.0, marker: str = "rotortwin: Foxglove: open ") -> tuple[str, list[str]]:
    """The ``ws://`` URL a ``--foxglove`` command prints on stderr, and the lines read so far; the
    rest of stderr keeps being collected into that list in a thread."""
    lines: list[str] = []
    found = threading.Event()

    def reader() -> None:
        for line in proc.stderr:
            lines.append(line)
            if line.startswith(marker):
                found.set()
        found.set()

    threading.Thread(target=reader, daemon=True).start()
    found.wait(timeout_s)
    for line in lines:
        if line.startswith(marker):
            return line[len(marker):].split()[0], lines
    raise AssertionError(f"no Foxglove URL on stderr within {timeout_s:g} s:\n{''.join(lines)[-3000:]}")
