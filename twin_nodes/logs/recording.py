"""MCAP recording in rosbag2 layout, without rclpy.

:class:`McapRecorder` writes a rosbag2 directory (``metadata.yaml`` + one
``<dir>.mcap``) through ``rosbags.rosbag2.Writer(dir, version=9,
storage_plugin=StoragePlugin.MCAP)`` and the rosbags typestore's CDR
serialiser; given a path ending in ``.mcap`` it writes that one file instead
(no folder: the rosbag2 metadata is inside it, the ``rosbag2`` metadata record
``ros2 bag``'s MCAP storage writes, so ``rosbags`` ``AnyReader``, the ``mcap``
library and Foxglove read it as it is), so it runs in plain tests and produces what ``ros2 bag`` writes:
profile ``ros2``, schemas ``pkg/msg/Type`` with encoding ``ros2msg``, channels
with message encoding ``cdr`` and ``offered_qos_profiles`` metadata, and a
``rosbag2`` metadata record (conventions.md §4).  Messages are rosbags typestore
objects, plain dicts (missing fields take ROS defaults; ``builtin_interfaces``
Time/Duration also accept integer nanoseconds) or any object with the message's
attributes (an rclpy message works without importing rclpy here).

Crash safety
------------
rosbags keeps the open MCAP chunk in memory and writes the summary, the
message-count statistics and ``metadata.yaml`` only in ``close()``.  The recorder
therefore closes the chunk itself when it holds ``chunk_bytes`` of data or spans
``chunk_period_s`` of message time, and flushes it to the OS right away.  If the
process is killed (SIGKILL, crash, power cut after the OS wrote the pages):

- ``<dir>/<dir>.mcap`` holds the header and every chunk closed so far — each a
  self-contained record with its schema and channel definitions before the first
  message that uses them — followed by at most one partial chunk;
- ``metadata.yaml`` and the MCAP summary/footer are missing, so
  ``AnyReader``/``ros2 bag`` refuse the directory (``read_bag`` says so).

:func:`recover` reads the MCAP sequentially with the ``mcap`` library
(``StreamReader``, which does not need the summary) on a stream that raises at
the first short read, keeps every record up to the last complete chunk, and
writes them to a new, valid bag directory (``<dir>_recovered`` by default) with
``metadata.yaml`` regenerated.  Messages of the partial last chunk — at most
``chunk_bytes`` / ``chunk_period_s`` of data — are lost.  ``mcap recover`` (the
Go CLI) does the same for the ``.mcap`` alone.  Power-loss safety needs
``flush(fsync=True)`` (or ``fsync_chunks=True``), which forces each chunk to disk.
"""

from __future__ import annotations

import io
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from twin_nodes.base.errors import LogError

__all__ = ["McapRecorder", "open_bag_writer", "close_bag_writer", "single_file", "QOS_PRESETS", "read_bag", "read_bag_raw", "BagTopic", "cdr_header_stamp",
           "topic_counts", "recover", "RecoveryReport", "default_typestore", "MCAP_MAGIC"]

#: the first bytes of every MCAP file
MCAP_MAGIC = b"\x89MCAP0\r\n"

_TOPIC_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_NUMPY_OF = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "uint8": np.uint8, "int8": np.int8,
    "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
    "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64,
}
_TIME_TYPES = ("builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration")
#: the recorder node's exit code when messages the graph announced never reached it (the bag is finalised and kept)
INCOMPLETE_EXIT = 3


def default_typestore() -> Any:
    """The rosbags typestore for ROS 2 Jazzy (std/geometry/nav/sensor/diagnostic/rosgraph msgs)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def single_file(path: str | os.PathLike[str]) -> bool:
    """A recording path ending in ``.mcap`` is one MCAP file; any other path a rosbag2 folder."""
    return Path(path).suffix == ".mcap"


def open_bag_writer(out: str | os.PathLike[str]) -> Any:
    """An open rosbags MCAP ``Writer`` for the recording ``out``: a rosbag2 folder (``metadata.yaml`` +
    ``<out>/<out>.mcap``), or, for a path ending in ``.mcap``, that single file.

    The single file is written in place from the first byte (a recording cut short by a kill can be
    recovered from it): the writer opens its MCAP in a private folder beside ``out`` (same file system),
    which is linked to ``out`` (refused when ``out`` exists) and removed at once.  Close it with
    :func:`close_bag_writer`.  Raises rosbags' ``WriterError`` when ``out`` exists."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.errors import WriterError

    out = Path(out)
    if not single_file(out):
        w = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP)
        w.open()
        return w
    if os.path.lexists(out):
        raise WriterError(f"{out} exists already, not overwriting.")
    out.parent.mkdir(parents=True, exist_ok=True)
    import tempfile
    work = Path(tempfile.mkdtemp(prefix=".rotortwin-rec-", dir=out.parent))
    try:
        w = Writer(work / out.stem, version=9, storage_plugin=StoragePlugin.MCAP)
        w.open()
        st = w.storage
        try:
            os.link(st.path, out)  # exclusive: fails when out exists
        except FileExistsError:
            w.abort()
            raise WriterError(f"{out} exists already, not overwriting.") from None
        os.unlink(st.path)
        st.path = out  # the name the rosbag2 metadata inside the file gives it
    finally:
        import shutil
        shutil.rmtree(work, ignore_errors=True)
    w._rotortwin_single = out
    return w


def close_bag_writer(writer: Any) -> None:
    """Finish a writer of :func:`open_bag_writer`: summary, footer and the rosbag2 metadata (inside the
    single file; a folder also gets ``metadata.yaml``)."""
    single = getattr(writer, "_rotortwin_single", None)
    if single is None:
        writer.close()
        return
    import shutil
    import tempfile
    meta = Path(tempfile.mkdtemp(prefix="rotortwin-meta-"))
    writer.metapath = meta / "metadata.yaml"  # the rosbags writer also writes it beside: not for one file
    try:
        writer.close()
    finally:
        shutil.rmtree(meta, ignore_errors=True)


def _qos(history: str, depth: int, reliability: str, durability: str) -> Any:
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)

    zero = QosTime(0, 0)  # 0 = rmw default (infinite deadline/lifespan/lease)
    return Qos(QosHistory[history], depth, QosReliability[reliability], QosDurability[durability],
               zero, zero, QosLiveliness.AUTOMATIC, zero, False)


#: offered QoS presets: rclpy's default profile, qos_profile_sensor_data, a latched topic
QOS_PRESETS = {
    "reliable": ("KEEP_LAST", 10, "RELIABLE", "VOLATILE"),
    "sensor_data": ("KEEP_LAST", 5, "BEST_EFFORT", "VOLATILE"),
    "transient_local": ("KEEP_LAST", 1, "RELIABLE", "TRANSIENT_LOCAL"),
}


def _normalise_msgtype(msgtype: str) -> str:
    parts = msgtype.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return msgtype


def _normalise_topic(where: str, name: str) -> str:
    if not isinstance(name, str) or not name:
        raise LogError(where, "topic", f"expected a non-empty ROS topic name, got {name!r}")
    full = name if name.startswith("/") else "/" + name
    tokens = full[1:].split("/")
    if any(not _TOPIC_TOKEN.match(t) for t in tokens):
        raise LogError(where, name, "expected a ROS topic name: '/'-separated tokens of letters, "
                                    "digits and '_', none starting with a digit, no '//'")
    return full


# --------------------------------------------------------------------------- message building


class _Builder:
    """Builds rosbags typestore message objects from dicts / attribute objects."""

    def __init__(self, typestore: Any, where: str):
        self.ts = typestore
        self.where = where

    def build(self, value: Any, msgtype: str, path: str) -> Any:
        cls = self.ts.types.get(msgtype)
        if cls is None:
            raise LogError(self.where, path, f"expected a type known to the typestore, "
                                             f"got {msgtype!r}")
        if isinstance(value, cls):
            return value
        if msgtype in _TIME_TYPES and isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            ns = int(value)
            return cls(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        _, fields = self.ts.fielddefs[msgtype]
        names = [f for f, _ in fields]
        if isinstance(value, Mapping):
            unknown = set(value) - set(names)
            if unknown:
                raise LogError(self.where, f"{path}.{sorted(unknown)[0]}",
                               f"expected a field of {msgtype}: {', '.join(names)}")
            get = lambda f: value.get(f, _MISSING)  # noqa: E731
        elif value is None:
            get = lambda f: _MISSING  # noqa: E731
        else:
            get = lambda f: getattr(value, f, _MISSING)  # noqa: E731
        kwargs = {}
        for fname, desc in fields:
            v = get(fname)
            kwargs[fname] = self.field(v, desc, f"{path}.{fname}", msgtype, fname)
        return cls(**kwargs)

    def field(self, v: Any, desc: Any, path: str, msgtype: str, fname: str) -> Any:
        from rosbags.interfaces import Nodetype

        kind, spec = desc
        if kind == Nodetype.BASE:
            base = spec[0]
            if v is _MISSING:
                if msgtype == "geometry_msgs/msg/Quaternion" and fname == "w":
                    return 1.0  # ROS IDL default: identity orientation
                return "" if base == "string" else (False if base == "bool" else
                                                     (0.0 if base.startswith("float") else 0))
            return self.scalar(v, base, path)
        if kind == Nodetype.NAME:
            return self.build(None if v is _MISSING else v, spec, path)
        sub, size = spec
        skind, sspec = sub
        if v is _MISSING:
            v = [] if kind == Nodetype.SEQUENCE else None
        if skind == Nodetype.BASE and sspec[0] in _NUMPY_OF:
            dt = _NUMPY_OF[sspec[0]]
            if v is None:
                return np.zeros(size, dtype=dt)
            if isinstance(v, (bytes, bytearray)):
                arr = np.frombuffer(bytes(v), dtype=np.uint8).astype(dt)
            else:
                try:
                    arr = np.asarray(v, dtype=dt).reshape(-1)
                except (TypeError, ValueError) as exc:
                    raise LogError(self.where, path, f"expected a {sspec[0]} array: {exc}") from None
            if kind == Nodetype.ARRAY and arr.size != size:
                raise LogError(self.where, path, f"expected {size} elements, got {arr.size}")
            if 0 < size < arr.size and kind == Nodetype.SEQUENCE:
                raise LogError(self.where, path, f"expected at most {size} elements, got {arr.size}")
            return arr
        items = list(v) if v is not None else [_MISSING] * size
        if kind == Nodetype.ARRAY and len(items) != size:
            raise LogError(self.where, path, f"expected {size} elements, got {len(items)}")
        return [self.field(it, sub, f"{path}[{i}]", msgtype, fname) for i, it in enumerate(items)]

    def scalar(self, v: Any, base: str, path: str) -> Any:
        if base == "string":
            if not isinstance(v, str):
                raise LogError(self.where, path, f"expected a str, got {type(v).__name__}")
            return v
        if isinstance(v, (bytes, bytearray)) and len(v) == 1:  # rclpy 'byte' fields
            v = v[0]
        if base == "bool":
            return bool(v)
        if base.startswith("float"):
            try:
                return float(v)
            except (TypeError, ValueError):
                raise LogError(self.where, path, f"expected a number for {base}, got {v!r}") from None
        try:
            iv = int(v)
        except (TypeError, ValueError):
            raise LogError(self.where, path, f"expected an integer for {base}, got {v!r}") from None
        if isinstance(v, float) and iv != v:
            raise LogError(self.where, path, f"expected an integer for {base}, got {v!r}")
        info = np.iinfo(_NUMPY_OF[base])
        if not info.min <= iv <= info.max:
            raise LogError(self.where, path, f"expected {base} in [{info.min}, {info.max}], got {iv}")
        return iv


class _Missing:
    def __repr__(self) -> str:
        return "<missing>"


_MISSING = _Missing()


# --------------------------------------------------------------------------- recorder


class McapRecorder:
    """Record ROS 2 messages to a rosbag2/MCAP directory without rclpy.

    Parameters
    ----------
    out_dir : the recording to create (must not exist): a rosbag2 directory, or one MCAP file when the
        path ends in ``.mcap`` (:func:`open_bag_writer`).
    typestore : rosbags typestore; default :func:`default_typestore` (Jazzy).
    chunk_bytes : close and flush the MCAP chunk at this uncompressed size.
    chunk_period_s : … or when its messages span this much message time [s].
    fsync_chunks : also ``os.fsync`` after each chunk (power-loss safety).

    Use as a context manager, or call :meth:`close`.  ``write`` takes the
    message time in integer nanoseconds (for ULog replay: ULog µs × 1000).
    """

    def __init__(
        self,
        out_dir: str | os.PathLike[str],
        *,
        typestore: Any = None,
        chunk_bytes: int = 256 * 1024,
        chunk_period_s: float = 1.0,
        fsync_chunks: bool = False,
    ):
        from rosbags.rosbag2.errors import WriterError

        self.path = Path(out_dir)
        if chunk_bytes <= 0 or not chunk_period_s > 0:
            raise LogError(str(self.path), "chunk_bytes/chunk_period_s", "expected values > 0")
        self._ts = typestore if typestore is not None else default_typestore()
        self._builder = _Builder(self._ts, str(self.path))
        self._chunk_bytes = int(chunk_bytes)
        self._chunk_period_ns = int(chunk_period_s * 1e9)
        self._fsync = bool(fsync_chunks)
        try:
            self._writer = open_bag_writer(self.path)
        except WriterError as exc:
            what = "a new .mcap file" if single_file(self.path) else "a new directory"
            raise LogError(str(self.path), "out_dir", f"expected {what}: {exc}") from None
        self._conns: dict[str, Any] = {}
        self._types: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self._closed = False

    @property
    def mcap_path(self) -> Path:
        """The ``.mcap`` file: the recording itself, or the one inside the bag directory."""
        return self.path if single_file(self.path) else self.path / f"{self.path.name}.mcap"

    def add_topic(self, name: str, msgtype: str, qos: Any = "reliable") -> str:
        """Register topic ``name`` of type ``msgtype`` (``pkg/msg/Type``); returns the
        absolute topic name.  ``qos``: a key of :data:`QOS_PRESETS`, a rosbags
        ``Qos`` or a list of them (the publishers' offered profiles)."""
        from rosbags.interfaces import Qos

        self._check_open()
        topic = _normalise_topic(str(self.path), name)
        mt = _normalise_msgtype(msgtype)
        if mt not in self._ts.types:
            raise LogError(str(self.path), topic,
                           f"expected a message type known to the typestore, got {msgtype!r}")
        if topic in self._conns:
            if self._types[topic] != mt:
                raise LogError(str(self.path), topic,
                               f"already added with type {self._types[topic]}, not {mt}")
            return topic
        if isinstance(qos, str):
            if qos not in QOS_PRESETS:
                raise LogError(str(self.path), f"{topic}.qos",
                               f"expected one of {sorted(QOS_PRESETS)}, got {qos!r}")
            profiles = [_qos(*QOS_PRESETS[qos])]
        elif isinstance(qos, Qos):
            profiles = [qos]
        else:
            profiles = list(qos)
            if not all(isinstance(q, Qos) for q in profiles):
                raise LogError(str(self.path), f"{topic}.qos",
                               "expected a preset name, a rosbags Qos or a list of Qos")
        self._conns[topic] = self._writer.add_connection(topic, mt, typestore=self._ts,
                                                         offered_qos_profiles=profiles)
        self._types[topic] = mt
        self.counts[topic] = 0
        return topic

    def _target(self, topic: str, t_ns: int) -> tuple[Any, str]:
        """The connection of a registered topic, after checking the time stamp."""
        self._check_open()
        full = topic if topic.startswith("/") else "/" + topic
        conn = self._conns.get(full)
        if conn is None:
            raise LogError(str(self.path), topic, "expected a topic registered with add_topic()")
        if isinstance(t_ns, bool) or not isinstance(t_ns, (int, np.integer)) or not 0 <= int(t_ns) < 2**63:
            raise LogError(str(self.path), f"{full}.t_ns",
                           f"expected integer nanoseconds in [0, 2**63), got {t_ns!r}")
        return conn, full

    def _put(self, conn: Any, full: str, t_ns: int, data: bytes) -> None:
        self._writer.write(conn, int(t_ns), data)
        self.counts[full] += 1
        self._maybe_close_chunk(int(t_ns))

    def write(self, topic: str, msg: Any, t_ns: int) -> None:
        """Serialise ``msg`` (typestore object, dict or attribute object) at time ``t_ns``."""
        conn, full = self._target(topic, t_ns)
        mt = self._types[full]
        obj = self._builder.build(msg, mt, full)
        try:
            data = self._ts.serialize_cdr(obj, mt)
        except Exception as exc:  # rosbags raises several types for a malformed object
            raise LogError(str(self.path), full, f"expected a serialisable {mt}: {exc}") from None
        self._put(conn, full, t_ns, data)

    def write_raw(self, topic: str, data: bytes, t_ns: int) -> None:
        """Write already-serialised CDR bytes (rclpy ``raw=True``) at ``t_ns``.

        rclpy's and rosbags' CDR encodings are byte-identical (conventions.md §4), so the
        bytes are written as they came."""
        conn, full = self._target(topic, t_ns)
        self._put(conn, full, t_ns, bytes(data))

    def _storage(self) -> Any:
        st = getattr(self._writer, "storage", None)
        if st is None or not all(hasattr(st, a) for a in ("chunk", "close_chunk", "bio")):
            return None  # another rosbags version: fall back to its own 1 MiB chunks
        return st

    def _maybe_close_chunk(self, t_ns: int) -> None:
        st = self._storage()
        if st is None:
            return
        ch = st.chunk
        if not ch.msgs:
            return
        if ch.bio.tell() >= self._chunk_bytes or t_ns - ch.message_start_time >= self._chunk_period_ns:
            self._close_chunk(st, fsync=self._fsync)

    def _close_chunk(self, st: Any, fsync: bool) -> None:
        if st.chunk.msgs:
            st.close_chunk()
        st.bio.flush()
        if fsync:
            os.fsync(st.bio.fileno())

    def flush(self, fsync: bool = False) -> None:
        """Close the open chunk (if it has messages) and hand everything to the OS."""
        self._check_open()
        st = self._storage()
        if st is not None:
            self._close_chunk(st, fsync=fsync)

    def close(self) -> None:
        """Write the summary, footer and ``metadata.yaml``.  Idempotent."""
        if self._closed:
            return
        self._closed = True
        close_bag_writer(self._writer)

    def _check_open(self) -> None:
        if self._closed:
            raise LogError(str(self.path), "recorder", "expected an open recorder, it is closed")

    def __enter__(self) -> "McapRecorder":
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        # keep what was recorded even when the body raised
        try:
            self.close()
        except Exception:
            if exc_type is None:
                raise


# --------------------------------------------------------------------------- reading


def _bag_paths(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    if not p.exists():
        raise LogError(str(p), "bag", "expected an existing rosbag2 directory or .mcap file")
    if p.is_dir() and not (p / "metadata.yaml").exists():
        raise LogError(str(p), "metadata.yaml",
                       "expected a rosbag2 directory with metadata.yaml; a recording cut short "
                       "by a crash has none: run 'rotortwin record recover BAG' on it")
    return p


def _any_reader(p: Path) -> Any:
    from rosbags.highlevel import AnyReader

    return AnyReader([p], default_typestore=default_typestore())


def read_bag(path: str | os.PathLike[str]) -> dict[str, list[tuple[int, Any]]]:
    """All messages of a rosbag2 directory or bare ``.mcap`` as
    ``{topic: [(t_ns, msg), …]}`` in time order (rosbags ``AnyReader``; messages
    are rosbags dataclasses, types from the schemas embedded in the MCAP)."""
    p = _bag_paths(path)
    out: dict[str, list[tuple[int, Any]]] = {}
    try:
        with _any_reader(p) as reader:
            for c in reader.connections:
                out.setdefault(c.topic, [])
            for conn, t, raw in reader.messages():
                out[conn.topic].append((int(t), reader.deserialize(raw, conn.msgtype)))
    except LogError:
        raise
    except Exception as exc:
        raise LogError(str(p), "bag", f"expected a readable rosbag2/MCAP recording: "
                                      f"{type(exc).__name__}: {exc}; if it was cut short, "
                                      "run 'rotortwin record recover BAG'") from None
    return out


@dataclass
class BagTopic:
    """One topic of a recording, undecoded: its type and its messages in file order."""

    topic: str
    msgtype: str
    log_ns: list[int] = field(default_factory=list)
    raw: list[bytes] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.raw)

    def decode(self, typestore: Any = None) -> list[Any]:
        """The messages as rosbags dataclasses (same field names as the rclpy messages)."""
        ts = typestore if typestore is not None else default_typestore()
        return [ts.deserialize_cdr(r, self.msgtype) for r in self.raw]


def read_bag_raw(path: str | os.PathLike[str], topics: Any = None) -> dict[str, BagTopic]:
    """The CDR bytes of every message of a finalised recording, per topic in **file order**
    (the order the recorder received them: per-topic publish order), with the log times;
    ``topics`` (a predicate on the name) selects topics.  The MCAP library reads it, so
    message types need not be known to the typestore."""
    from mcap.reader import make_reader

    p = _bag_paths(path)
    mcap_file = _find_mcap(p)
    out: dict[str, BagTopic] = {}
    try:
        with open(mcap_file, "rb") as fh:
            reader = make_reader(fh)
            summary = reader.get_summary()
            if summary is not None:
                for ch in summary.channels.values():
                    if topics is None or topics(ch.topic):
                        sc = summary.schemas.get(ch.schema_id)
                        out.setdefault(ch.topic, BagTopic(ch.topic, sc.name if sc else ""))
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if topics is not None and not topics(channel.topic):
                    continue
                bt = out.get(channel.topic)
                if bt is None:
                    bt = out[channel.topic] = BagTopic(channel.topic, schema.name if schema else "")
                bt.log_ns.append(int(message.log_time))
                bt.raw.append(bytes(message.data))
    except LogError:
        raise
    except Exception as exc:
        raise LogError(str(p), "bag", f"expected a readable rosbag2/MCAP recording: "
                                      f"{type(exc).__name__}: {exc}") from None
    return out


def cdr_header_stamp(raw: bytes) -> int:
    """``header.stamp`` [ns] of a CDR-serialised message whose first field is a
    ``std_msgs/Header`` (or a ``builtin_interfaces/Time``, e.g. ``rosgraph_msgs/Clock``),
    without deserialising it: int32 sec and uint32 nanosec after the 4-byte
    encapsulation header."""
    import struct

    if len(raw) < 12:
        raise ValueError(f"expected a CDR message of at least 12 bytes, got {len(raw)}")
    fmt = "<iI" if raw[1] & 1 else ">iI"  # encapsulation id: CDR_LE = 0x0001, CDR_BE = 0x0000
    sec, nsec = struct.unpack_from(fmt, raw, 4)
    return int(sec) * 1_000_000_000 + int(nsec)


def topic_counts(path: str | os.PathLike[str]) -> dict[str, int]:
    """``{topic: message count}`` from the bag's metadata / MCAP summary."""
    p = _bag_paths(path)
    try:
        with _any_reader(p) as reader:
            counts: dict[str, int] = {}
            for c in reader.connections:
                counts[c.topic] = counts.get(c.topic, 0) + int(c.msgcount)
            return counts
    except Exception as exc:
        raise LogError(str(p), "bag", f"expected a readable rosbag2/MCAP recording: "
                                      f"{type(exc).__name__}: {exc}") from None


# --------------------------------------------------------------------------- recovery


class _ExactReader:
    """File wrapper whose ``read(n)`` raises at a short read, so a chunk cut by a
    truncation is never handed to the parser half-filled."""

    def __init__(self, f: io.BufferedReader):
        self._f = f
        self.pos = 0

    def read(self, n: int = -1) -> bytes:
        from mcap.exceptions import EndOfFile

        data = self._f.read(n)
        if n is not None and n >= 0 and len(data) < n:
            raise EndOfFile()
        self.pos += len(data)
        return data


@dataclass
class RecoveryReport:
    """What :func:`recover` salvaged."""

    source: Path
    out_dir: Path
    n_messages: int
    counts: dict[str, int] = field(default_factory=dict)
    complete: bool = False  # the source had its footer: nothing was lost
    bytes_used: int = 0  # bytes of the source parsed into complete records
    bytes_total: int = 0
    error: str = ""  # why reading stopped, if it stopped early


def _find_mcap(p: Path) -> Path:
    if p.is_file():
        return p
    if p.is_dir():
        files = sorted(p.glob("*.mcap"))
        if len(files) == 1:
            return files[0]
        raise LogError(str(p), "*.mcap", f"expected exactly one .mcap file in the bag, "
                                         f"found {len(files)}")
    raise LogError(str(p), "bag", "expected a bag directory or an .mcap file")


def _rihs01(msgtype: str, encoding: str, text: str) -> str:
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    if encoding == "ros2idl":
        sep = "=" * 80 + "\n"
        types: dict[str, Any] = {}
        parts = text.split(sep)[1:] if text.startswith(sep + "IDL: ") else [text]
        for part in parts:
            idl = part.split("\n", 1)[1] if part.startswith("IDL: ") else part
            types.update(get_types_from_idl(idl))
    else:
        types = get_types_from_msg(text, msgtype)
    store.register(types)
    return store.hash_rihs01(msgtype)


def recover(path: str | os.PathLike[str], out_dir: str | os.PathLike[str] | None = None
            ) -> RecoveryReport:
    """Rewrite a (possibly truncated) recording into a valid rosbag2/MCAP directory (or one ``.mcap``
    file, when ``out_dir`` ends in ``.mcap``).

    ``path`` is a bag directory or an ``.mcap`` file; the source is never
    modified.  ``out_dir`` defaults to ``<path>_recovered`` (for a file:
    ``<stem>_recovered`` beside it) and must not exist.  Every message of every
    complete chunk is kept; the partial chunk at the cut is dropped.  See the
    module docstring."""
    from mcap.records import Channel, Footer, Message, Schema
    from mcap.stream_reader import StreamReader
    from rosbags.rosbag2.metadata import parse_qos

    src = Path(path)
    mcap_file = _find_mcap(src)
    if out_dir is None:
        base = src if src.is_dir() else src.with_suffix("")
        out = base.parent / f"{base.name}_recovered"
    else:
        out = Path(out_dir)
    if out.exists():
        raise LogError(str(out), "out_dir", "expected a directory that does not exist yet")

    total = mcap_file.stat().st_size
    try:
        with open(mcap_file, "rb") as fh:
            head = fh.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise LogError(str(mcap_file), "file", f"expected a readable file: {exc.strerror or exc}") from None
    if head != MCAP_MAGIC:
        raise LogError(str(mcap_file), "magic", "expected an MCAP recording (it starts with \\x89MCAP0); "
                                                "nothing to recover")
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    conns: dict[int, Any] = {}
    counts: dict[str, int] = {}
    pending: list[Any] = []  # messages read before the writer knew their channel
    complete = False
    error = ""
    used = 0
    writer = open_bag_writer(out)
    try:
        with open(mcap_file, "rb") as fh:
            stream = _ExactReader(fh)  # type: ignore[arg-type]
            reader = StreamReader(stream, skip_magic=False, emit_chunks=False)  # type: ignore[arg-type]
            try:
                for rec in reader.records:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        if rec.id not in channels:
                            channels[rec.id] = rec
                    elif isinstance(rec, Message):
                        pending.append(rec)
                    elif isinstance(rec, Footer):
                        complete = True
                    # flush what we can: write messages whose channel is known
                    if pending:
                        for m in pending:
                            conn = conns.get(m.channel_id)
                            if conn is None:
                                conn = _recover_conn(writer, schemas, channels, m.channel_id,
                                                     str(mcap_file), parse_qos)
                                conns[m.channel_id] = conn
                            writer.write(conn, m.log_time, m.data)
                            counts[conn.topic] = counts.get(conn.topic, 0) + 1
                        pending.clear()
                    used = stream.pos
            except LogError:
                raise
            except Exception as exc:  # truncation / corruption: stop at the last good record
                error = f"{type(exc).__name__}: {exc}".strip(": ")
        # channels with no surviving messages still appear in the recovered bag
        for cid in sorted(channels):
            if cid not in conns and channels[cid].schema_id in schemas:
                conns[cid] = _recover_conn(writer, schemas, channels, cid, str(mcap_file), parse_qos)
                counts.setdefault(conns[cid].topic, 0)
        if not sum(counts.values()):
            raise LogError(str(mcap_file), "messages",
                           "expected at least one complete chunk with messages; nothing to recover"
                           + (f" ({error})" if error and not complete else ""))
        close_bag_writer(writer)
    except BaseException:
        writer.abort()
        import shutil
        if single_file(out):
            out.unlink(missing_ok=True)
        else:
            shutil.rmtree(out, ignore_errors=True)  # a failed recovery leaves nothing behind
        raise
    return RecoveryReport(source=mcap_file, out_dir=out, n_messages=sum(counts.values()),
                          counts=counts, complete=complete, bytes_used=used, bytes_total=total,
                          error="" if complete else (error or "no footer"))


def _recover_conn(writer: Any, schemas: dict[int, Any], channels: dict[int, Any], cid: int,
                  where: str, parse_qos: Any) -> Any:
    ch = channels.get(cid)
    if ch is None:
        raise LogError(where, f"channel {cid}", "expected the channel record before its messages")
    sc = schemas.get(ch.schema_id)
    if sc is None:
        raise LogError(where, f"schema {ch.schema_id}", "expected the schema before its channel")
    text = sc.data.decode("utf-8")
    try:
        digest = _rihs01(sc.name, sc.encoding, text)
    except Exception as exc:
        raise LogError(where, sc.name, f"expected a parsable {sc.encoding} schema: {exc}") from None
    qos_text = ch.metadata.get("offered_qos_profiles", "")
    try:
        qos = parse_qos(qos_text) if qos_text else []
    except Exception:
        qos = []
    return writer.add_connection(ch.topic, sc.name, msgdef=text, rihs01=digest,
                                 serialization_format=ch.message_encoding,
                                 offered_qos_profiles=qos)
