"""Write PX4-like ULog files from arrays, so simulated flights look like real logs.

``write_px4_ulog(path, topics, params, info)`` writes a ULog (file format v1,
the PX4 "ULog" spec: header, flag bits, ``F`` formats, ``I`` info, ``P``
parameters, ``A`` subscriptions, ``D`` data, ``L`` log strings) that pyulog and
:func:`twin_nodes.logs.ulog_io.read_ulog` read back.

Why not ``pyulog.ULog.write_ulog``: it packs every field of every sample with a
separate ``struct.pack`` call (~1e6 calls for a 100 s simulated flight) and needs
pyulog's private ``_MessageAddLogged`` objects to be faked.  Here each topic is
one packed numpy structured array and the time-ordered data section is gathered
with one vectorised index, so a long flight writes in well under a second.
pyulog is the reference reader in the tests.

Input
-----
``topics`` maps a topic name (``"battery_status"``; a second instance is
``"battery_status:1"``) to ``{field: array}``:

- ``'timestamp'``: (n,) integer µs (PX4 hrt clock), non-decreasing, >= ``start_us``;
- scalar fields: (n,) arrays; array fields: (n, k) arrays under the base name
  (``'q'`` -> ``float[4] q``) or pyulog-style flattened keys (``'q[0]'`` …);
- nested fields (``esc_status.esc[8]`` of ``esc_report``): flattened keys
  ``'esc[0].esc_rpm'``, missing leaves are written as 0 (integers) / NaN (floats).

For the topics in :data:`PX4_FORMATS` (the PX4 field names and types of
vehicle_local_position, vehicle_attitude, vehicle_angular_velocity,
actuator_motors, actuator_outputs, vehicle_thrust_setpoint,
vehicle_torque_setpoint, sensor_combined, battery_status, trajectory_setpoint,
vehicle_status, vehicle_land_detected, hover_thrust_estimate, esc_status and the
``*_groundtruth`` topics) the values are cast to the PX4 type; a field you do not
give is left out of that topic's format (as in a PX4 version that lacks it).
Fields of other topics get their type from the array dtype (float64 -> double,
float32 -> float, bool -> bool, intN -> intN_t).

``params``: python ``int`` -> ``int32_t``, ``float`` -> ``float`` (PX4 types).
``info``: ``str`` -> ``char[n]``, ``int`` -> ``uint32_t``/``int32_t``.
``messages``: optional ``(t_us, level, text)`` log strings, level one of
``EMERGENCY ALERT CRITICAL ERROR WARNING NOTICE INFO DEBUG``.

The file is written to a temporary file in the target directory and renamed
into place, so a failure never leaves a half-written log at ``path``.
"""

from __future__ import annotations

import os
import re
import struct
import tempfile
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from twin_nodes.base.errors import LogError

__all__ = ["write_px4_ulog", "PX4_FORMATS", "LOG_LEVELS"]

_MAGIC = b"\x55\x4c\x6f\x67\x01\x12\x35"
_FILE_VERSION = 1

LOG_LEVELS = ("EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING", "NOTICE", "INFO", "DEBUG")

# ULog type -> numpy little-endian dtype
_NP = {
    "int8_t": "<i1", "uint8_t": "<u1", "int16_t": "<i2", "uint16_t": "<u2",
    "int32_t": "<i4", "uint32_t": "<u4", "int64_t": "<i8", "uint64_t": "<u8",
    "float": "<f4", "double": "<f8", "bool": "<u1",
}
_INFER = {
    np.dtype("float64"): "double", np.dtype("float32"): "float", np.dtype("bool"): "bool",
    np.dtype("int8"): "int8_t", np.dtype("uint8"): "uint8_t", np.dtype("int16"): "int16_t",
    np.dtype("uint16"): "uint16_t", np.dtype("int32"): "int32_t", np.dtype("uint32"): "uint32_t",
    np.dtype("int64"): "int64_t", np.dtype("uint64"): "uint64_t",
}

F = tuple[str, int, str]  # (type, array size (0 = scalar), name)

_LPOS: list[F] = [
    ("uint64_t", 0, "timestamp"), ("uint64_t", 0, "timestamp_sample"),
    ("uint64_t", 0, "ref_timestamp"), ("double", 0, "ref_lat"), ("double", 0, "ref_lon"),
    ("float", 0, "x"), ("float", 0, "y"), ("float", 0, "z"),
    ("float", 0, "vx"), ("float", 0, "vy"), ("float", 0, "vz"), ("float", 0, "z_deriv"),
    ("float", 0, "ax"), ("float", 0, "ay"), ("float", 0, "az"),
    ("float", 0, "heading"), ("float", 0, "ref_alt"), ("float", 0, "dist_bottom"),
    ("float", 0, "eph"), ("float", 0, "epv"), ("float", 0, "evh"), ("float", 0, "evv"),
    ("bool", 0, "xy_valid"), ("bool", 0, "z_valid"), ("bool", 0, "v_xy_valid"),
    ("bool", 0, "v_z_valid"), ("bool", 0, "dist_bottom_valid"), ("uint8_t", 0, "xy_reset_counter"),
    ("uint8_t", 0, "z_reset_counter"), ("uint8_t", 0, "vxy_reset_counter"),
    ("uint8_t", 0, "vz_reset_counter"), ("bool", 0, "xy_global"), ("bool", 0, "z_global"),
    ("bool", 0, "dead_reckoning"),
]
_ATT: list[F] = [
    ("uint64_t", 0, "timestamp"), ("uint64_t", 0, "timestamp_sample"), ("float", 4, "q"),
    ("float", 4, "delta_q_reset"), ("uint8_t", 0, "quat_reset_counter"),
]
_ANGVEL: list[F] = [
    ("uint64_t", 0, "timestamp"), ("uint64_t", 0, "timestamp_sample"), ("float", 3, "xyz"),
    ("float", 3, "xyz_derivative"),
]
_XYZ_SP: list[F] = [("uint64_t", 0, "timestamp"), ("uint64_t", 0, "timestamp_sample"),
                    ("float", 3, "xyz")]
_ESC_REPORT: list[F] = [
    ("uint64_t", 0, "timestamp"), ("uint32_t", 0, "esc_errorcount"), ("int32_t", 0, "esc_rpm"),
    ("float", 0, "esc_voltage"), ("float", 0, "esc_current"), ("float", 0, "esc_temperature"),
    ("uint16_t", 0, "failures"), ("uint8_t", 0, "esc_address"), ("uint8_t", 0, "esc_cmdcount"),
    ("uint8_t", 0, "esc_state"), ("uint8_t", 0, "actuator_function"), ("int8_t", 0, "esc_power"),
]

#: PX4 message formats (field types and names from PX4-Autopilot msg/, v1.14-v1.16).
PX4_FORMATS: dict[str, list[F]] = {
    "vehicle_local_position": _LPOS,
    "vehicle_local_position_groundtruth": _LPOS,
    "vehicle_attitude": _ATT,
    "vehicle_attitude_groundtruth": _ATT,
    "vehicle_angular_velocity": _ANGVEL,
    "vehicle_angular_velocity_groundtruth": _ANGVEL,
    "actuator_motors": [("uint64_t", 0, "timestamp"), ("uint64_t", 0, "timestamp_sample"),
                        ("float", 12, "control"), ("uint16_t", 0, "reversible_flags")],
    "actuator_outputs": [("uint64_t", 0, "timestamp"), ("uint32_t", 0, "noutputs"),
                         ("float", 16, "output")],
    "vehicle_thrust_setpoint": _XYZ_SP,
    "vehicle_torque_setpoint": _XYZ_SP,
    "sensor_combined": [
        ("uint64_t", 0, "timestamp"), ("float", 3, "gyro_rad"), ("uint32_t", 0, "gyro_integral_dt"),
        ("int32_t", 0, "accelerometer_timestamp_relative"), ("float", 3, "accelerometer_m_s2"),
        ("uint32_t", 0, "accelerometer_integral_dt"), ("uint8_t", 0, "accelerometer_clipping"),
        ("uint8_t", 0, "gyro_clipping"),
    ],
    "battery_status": [
        ("uint64_t", 0, "timestamp"), ("float", 0, "voltage_v"), ("float", 0, "current_a"),
        ("float", 0, "current_average_a"), ("float", 0, "discharged_mah"),
        ("float", 0, "remaining"), ("float", 0, "scale"), ("float", 0, "temperature"),
        ("uint8_t", 0, "cell_count"), ("bool", 0, "connected"), ("uint8_t", 0, "id"),
        ("uint8_t", 0, "warning"),
    ],
    "trajectory_setpoint": [
        ("uint64_t", 0, "timestamp"), ("float", 3, "position"), ("float", 3, "velocity"),
        ("float", 3, "acceleration"), ("float", 3, "jerk"), ("float", 0, "yaw"),
        ("float", 0, "yawspeed"),
    ],
    "vehicle_status": [
        ("uint64_t", 0, "timestamp"), ("uint64_t", 0, "armed_time"), ("uint64_t", 0, "takeoff_time"),
        ("uint64_t", 0, "nav_state_timestamp"), ("uint8_t", 0, "arming_state"),
        ("uint8_t", 0, "nav_state"), ("uint8_t", 0, "hil_state"), ("uint8_t", 0, "vehicle_type"),
        ("bool", 0, "failsafe"),
    ],
    "vehicle_land_detected": [
        ("uint64_t", 0, "timestamp"), ("bool", 0, "freefall"), ("bool", 0, "ground_contact"),
        ("bool", 0, "maybe_landed"), ("bool", 0, "landed"), ("bool", 0, "in_ground_effect"),
    ],
    "hover_thrust_estimate": [
        ("uint64_t", 0, "timestamp"), ("uint64_t", 0, "timestamp_sample"),
        ("float", 0, "hover_thrust"), ("float", 0, "hover_thrust_var"), ("bool", 0, "valid"),
    ],
    "esc_status": [
        ("uint64_t", 0, "timestamp"), ("uint16_t", 0, "counter"), ("uint8_t", 0, "esc_count"),
        ("uint8_t", 0, "esc_connectiontype"), ("uint8_t", 0, "esc_online_flags"),
        ("uint8_t", 0, "esc_armed_flags"), ("esc_report", 8, "esc"),
    ],
    "esc_report": _ESC_REPORT,
}

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_LEAF_RE = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)\])?(?:\.(.+))?$")


# --------------------------------------------------------------------------- records


def _rec(msg_type: str, payload: bytes) -> bytes:
    if len(payload) > 0xFFFF:
        raise ValueError(f"ULog message of {len(payload)} bytes exceeds 65535")
    return struct.pack("<HB", len(payload), ord(msg_type)) + payload


def _kv(key: str, value_bytes: bytes) -> bytes:
    k = key.encode("utf-8")
    if len(k) > 255:
        raise ValueError(f"key '{key[:40]}…' longer than 255 bytes")
    return struct.pack("<B", len(k)) + k + value_bytes


def _info_record(path: str, key: str, value: object) -> bytes:
    if not _NAME_RE.match(key):
        raise LogError(path, f"info.{key}", "expected a key of letters, digits and '_'")
    if isinstance(value, str):
        b = value.encode("utf-8")
        return _rec("I", _kv(f"char[{len(b)}] {key}", b))
    if isinstance(value, (bool, np.bool_)):
        return _rec("I", _kv(f"uint8_t {key}", struct.pack("<B", int(value))))
    if isinstance(value, (int, np.integer)):
        v = int(value)
        if 0 <= v < 2**32:
            return _rec("I", _kv(f"uint32_t {key}", struct.pack("<I", v)))
        if -(2**31) <= v < 2**31:
            return _rec("I", _kv(f"int32_t {key}", struct.pack("<i", v)))
        raise LogError(path, f"info.{key}", f"expected an int that fits 32 bits, got {v}")
    if isinstance(value, (float, np.floating)):
        return _rec("I", _kv(f"float {key}", struct.pack("<f", float(value))))
    raise LogError(path, f"info.{key}", f"expected str, int or float, got {type(value).__name__}")


def _param_record(path: str, name: str, value: object) -> bytes:
    if not _NAME_RE.match(name) or len(name) > 16:
        raise LogError(path, f"params.{name}",
                       "expected a PX4 parameter name (<= 16 letters, digits, '_')")
    if isinstance(value, (bool, np.bool_)) or isinstance(value, (int, np.integer)):
        v = int(value)
        if not -(2**31) <= v < 2**31:
            raise LogError(path, f"params.{name}", f"expected an int32 value, got {v}")
        return _rec("P", _kv(f"int32_t {name}", struct.pack("<i", v)))
    if isinstance(value, (float, np.floating)):
        return _rec("P", _kv(f"float {name}", struct.pack("<f", float(value))))
    raise LogError(path, f"params.{name}", f"expected int or float, got {type(value).__name__}")


def _format_record(name: str, fields: list[F]) -> bytes:
    body = "".join(f"{t}[{n}] {f};" if n else f"{t} {f};" for t, n, f in fields)
    return _rec("F", f"{name}:{body}".encode("utf-8"))


# --------------------------------------------------------------------------- topics


def _flatten_input(path: str, topic: str, fields: Mapping[str, object]) -> tuple[int, dict[str, np.ndarray]]:
    """(n, {leaf name: (n,) array}) with (n, k) arrays split into ``name[i]``."""
    if "timestamp" not in fields:
        raise LogError(path, f"{topic}.timestamp", "expected a 'timestamp' array (µs)")
    n = int(np.asarray(fields["timestamp"]).reshape(-1).shape[0])
    leaves: dict[str, np.ndarray] = {}
    for key, raw in fields.items():
        if not isinstance(key, str) or not _LEAF_RE.match(key):
            raise LogError(path, f"{topic}.{key}", "expected a field name like 'x', 'q' or 'q[0]'")
        a = np.asarray(raw)
        if a.ndim == 0 or a.shape[0] != n:
            raise LogError(path, f"{topic}.{key}",
                           f"expected {n} samples (as many as timestamp), got shape {a.shape}")
        if a.ndim == 1:
            leaves[key] = a
        elif a.ndim == 2 and "[" not in key and "." not in key:
            for i in range(a.shape[1]):
                leaves[f"{key}[{i}]"] = a[:, i]
        else:
            raise LogError(path, f"{topic}.{key}", f"expected shape (n,) or (n, k), got {a.shape}")
    return n, leaves


def _resolve_fields(path: str, topic: str, fmt_name: str, leaves: dict[str, np.ndarray]
                    ) -> tuple[list[F], dict[str, list[F]]]:
    """The topic's format fields (only those given) and nested formats it needs."""
    table = PX4_FORMATS.get(fmt_name)
    given_bases = {_LEAF_RE.match(k).group(1) for k in leaves}  # type: ignore[union-attr]
    fields: list[F] = []
    nested: dict[str, list[F]] = {}
    known: set[str] = set()
    if table is not None:
        for t, size, name in table:
            known.add(name)
            if name in given_bases or name == "timestamp":
                fields.append((t, size, name))
                if t not in _NP:
                    nested[t] = PX4_FORMATS[t]
    # fields not in the table: infer the type from the dtype
    extra: dict[str, tuple[str, int]] = {}
    for key, a in leaves.items():
        m = _LEAF_RE.match(key)
        assert m is not None
        base, idx, sub = m.group(1), m.group(2), m.group(3)
        if base in known:
            continue  # typed by the PX4 table; bad indices are caught against the wire layout
        if sub is not None:
            raise LogError(path, f"{topic}.{key}",
                           f"expected nested fields only for known formats ({', '.join(PX4_FORMATS)})")
        dt = np.asarray(a).dtype
        t = _INFER.get(dt)
        if t is None:
            raise LogError(path, f"{topic}.{key}",
                           f"expected a numeric or bool array, got dtype {dt}")
        size = int(idx) + 1 if idx is not None else 0
        prev = extra.get(base)
        if prev is not None:
            size = max(size, prev[1])
        extra[base] = (t, size)
    for base, (t, size) in extra.items():
        fields.append((t, size, base))
    if fields[0][2] != "timestamp":  # PX4 puts timestamp first; pyulog does not care
        fields.sort(key=lambda f: f[2] != "timestamp")
    return fields, nested


def _leaf_list(fields: list[F], nested: dict[str, list[F]], prefix: str = "") -> list[tuple[str, str]]:
    """Flattened (leaf name, ULog type) in wire order (pyulog's naming)."""
    out: list[tuple[str, str]] = []
    for t, size, name in fields:
        names = [f"{prefix}{name}[{i}]" for i in range(size)] if size else [f"{prefix}{name}"]
        for nm in names:
            if t in _NP:
                out.append((nm, t))
            else:
                out.extend(_leaf_list(nested[t], nested, prefix=f"{nm}."))
    return out


def _cast(path: str, where: str, a: np.ndarray, t: str) -> np.ndarray:
    dt = np.dtype(_NP[t])
    if t in ("float", "double"):
        try:
            return np.asarray(a, dtype=float).astype(dt)
        except (TypeError, ValueError) as exc:
            raise LogError(path, where, f"expected numbers for {t}: {exc}") from None
    if t == "bool":
        a = np.asarray(a)
        if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise LogError(path, where, "expected finite values for bool, got NaN/inf")
        return (a != 0).astype(dt)
    a = np.asarray(a)
    if a.dtype.kind == "f":
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise LogError(path, where, f"expected whole numbers for {t}, got non-integer values")
    info = np.iinfo(dt)
    if a.size and (a.min() < info.min or a.max() > info.max):
        raise LogError(path, where,
                       f"expected values in [{info.min}, {info.max}] for {t}, got "
                       f"[{a.min()}, {a.max()}]")
    return a.astype(dt)


def _topic_key(path: str, key: str) -> tuple[str, int]:
    name, _, inst = key.partition(":")
    if not _NAME_RE.match(name):
        raise LogError(path, key, "expected a topic name of letters, digits and '_' "
                                  "(optionally ':<instance>')")
    if inst and not inst.isdigit():
        raise LogError(path, key, "expected ':<instance>' to be an integer 0..255")
    mid = int(inst) if inst else 0
    if mid > 255:
        raise LogError(path, key, "expected an instance 0..255")
    return name, mid


def _encode_topic(path: str, key: str, fields_in: Mapping[str, object], start_us: int
                  ) -> tuple[str, int, list[F], dict[str, list[F]], np.ndarray, np.ndarray]:
    """(name, multi_id, fields, nested formats, timestamps (n,) uint64, payload rows (n, size) u1)."""
    name, mid = _topic_key(path, key)
    if not isinstance(fields_in, Mapping):
        raise LogError(path, key, f"expected a dict of field arrays, got {type(fields_in).__name__}")
    n, leaves = _flatten_input(path, key, fields_in)
    ts = np.asarray(leaves["timestamp"])
    if ts.dtype.kind == "f":
        if not np.all(np.isfinite(ts)) or np.any(ts != np.round(ts)):
            raise LogError(path, f"{key}.timestamp", "expected integer µs, got non-integer values")
    if n and (np.min(ts) < start_us):
        raise LogError(path, f"{key}.timestamp",
                       f"expected timestamps >= start_us={start_us} µs, got {int(np.min(ts))}")
    ts = ts.astype(np.int64)
    if n > 1 and np.any(np.diff(ts) < 0):
        raise LogError(path, f"{key}.timestamp", "expected non-decreasing timestamps")
    leaves["timestamp"] = ts.astype(np.uint64)
    fields, nested = _resolve_fields(path, key, name, leaves)
    wire = _leaf_list(fields, nested)
    wire_names = {w for w, _ in wire}
    unknown = [k for k in leaves if k not in wire_names]
    if unknown:
        raise LogError(path, f"{key}.{unknown[0]}",
                       "expected an index within the PX4 array size / a known nested field")
    dtype = np.dtype([(w, _NP[t]) for w, t in wire])  # packed, no alignment, like PX4
    rows = np.zeros(n, dtype=dtype)
    for w, t in wire:
        if w in leaves:
            rows[w] = _cast(path, f"{key}.{w}", leaves[w], t)
        elif t in ("float", "double"):
            rows[w] = np.nan
    payload = rows.view(np.uint8).reshape(n, dtype.itemsize) if n else np.zeros((0, dtype.itemsize), np.uint8)
    return name, mid, fields, nested, ts.astype(np.uint64), payload


def _gather(buffers: list[np.ndarray], starts: np.ndarray, sizes: np.ndarray) -> bytes:
    """Concatenate byte ranges [start, start+size) of the joined buffers, vectorised."""
    if sizes.size == 0:
        return b""
    big = np.concatenate(buffers) if len(buffers) > 1 else buffers[0]
    total = int(sizes.sum())
    offs = np.repeat(starts - np.concatenate([[0], np.cumsum(sizes)[:-1]]), sizes)
    idx = np.arange(total, dtype=np.int64) + offs
    return big[idx].tobytes()


def write_px4_ulog(
    path: str | os.PathLike[str],
    topics: Mapping[str, Mapping[str, object]],
    params: Mapping[str, float] | None = None,
    info: Mapping[str, object] | None = None,
    start_us: int | None = None,
    messages: Iterable[tuple[int, str, str]] = (),
) -> Path:
    """Write a PX4-like ULog at ``path`` atomically; returns the path.

    ``start_us`` (header timestamp, µs) defaults to the earliest timestamp of all
    topics.  See the module docstring for the input layout.  Raises
    :class:`LogError` (``<file>: <topic.field>: <expected>``) on bad input;
    nothing is written then."""
    out = Path(path)
    sp = str(out)
    if not isinstance(topics, Mapping) or not topics:
        raise LogError(sp, "topics", "expected a non-empty dict {topic: {field: array}}")
    if start_us is None:
        firsts = [int(np.min(np.asarray(f["timestamp"]))) for f in topics.values()
                  if isinstance(f, Mapping) and "timestamp" in f and np.asarray(f["timestamp"]).size]
        start_us = min(firsts) if firsts else 0
    if not 0 <= int(start_us) < 2**64:
        raise LogError(sp, "start_us", f"expected 0 <= start_us < 2**64 µs, got {start_us}")
    start_us = int(start_us)

    infos = {"sys_name": "rotortwin", "ver_hw": "ROTORTWIN_SIM"}
    infos.update(dict(info or {}))

    # ---- data topics
    encoded = [_encode_topic(sp, k, v, start_us) for k, v in topics.items()]
    formats: dict[str, list[F]] = {}
    seen: set[tuple[str, int]] = set()
    for name, mid, fields, nested, _, _ in encoded:
        if (name, mid) in seen:
            raise LogError(sp, f"{name}:{mid}", "expected each topic instance once")
        seen.add((name, mid))
        for nname, nfields in nested.items():
            formats.setdefault(nname, nfields)
        if name in formats and formats[name] != fields:
            raise LogError(sp, name, "expected the same fields in every instance of a topic")
        formats[name] = fields

    head = bytearray()
    head += _MAGIC + struct.pack("<B", _FILE_VERSION) + struct.pack("<Q", start_us)
    head += _rec("B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
    # nested formats first (readers resolve lazily, but PX4 does it this way too)
    for fname in sorted(formats, key=lambda f: f not in {t for fl in formats.values() for t, _, _ in fl}):
        head += _format_record(fname, formats[fname])
    for k, v in infos.items():
        head += _info_record(sp, str(k), v)
    for k, v in (params or {}).items():
        head += _param_record(sp, str(k), v)
    for msg_id, (name, mid, *_rest) in enumerate(encoded):
        head += _rec("A", struct.pack("<BH", mid, msg_id) + name.encode("utf-8"))

    # ---- data section: D records of all topics + L strings, merged by time
    buffers: list[np.ndarray] = []
    rec_t: list[np.ndarray] = []
    rec_key: list[np.ndarray] = []
    rec_start: list[np.ndarray] = []
    rec_size: list[np.ndarray] = []
    base = 0
    for msg_id, (_, _, _, _, ts, payload) in enumerate(encoded):
        n, size = payload.shape
        if size + 2 > 0xFFFF:
            raise LogError(sp, encoded[msg_id][0], "expected a message smaller than 64 KiB")
        hdr = np.zeros((n, 5), np.uint8)
        hdr[:, 0:2] = np.frombuffer(struct.pack("<H", size + 2), np.uint8)
        hdr[:, 2] = ord("D")
        hdr[:, 3:5] = np.frombuffer(struct.pack("<H", msg_id), np.uint8)
        rows = np.concatenate([hdr, payload], axis=1).reshape(-1)
        buffers.append(rows)
        rec_t.append(ts.astype(np.uint64))
        rec_key.append(np.full(n, msg_id, np.int64))
        rec_start.append(base + np.arange(n, dtype=np.int64) * (size + 5))
        rec_size.append(np.full(n, size + 5, np.int64))
        base += rows.size
    for j, m in enumerate(messages):
        try:
            t_us, level, text = m
        except (TypeError, ValueError):
            raise LogError(sp, f"messages[{j}]", "expected (t_us, level, text)") from None
        if str(level).upper() not in LOG_LEVELS:
            raise LogError(sp, f"messages[{j}].level", f"expected one of {LOG_LEVELS}, got {level!r}")
        lvl = ord("0") + LOG_LEVELS.index(str(level).upper())
        if int(t_us) < start_us:
            raise LogError(sp, f"messages[{j}].t_us", f"expected >= start_us={start_us}")
        b = np.frombuffer(_rec("L", struct.pack("<BQ", lvl, int(t_us)) + str(text).encode("utf-8")),
                          np.uint8)
        buffers.append(b)
        rec_t.append(np.array([int(t_us)], np.uint64))
        rec_key.append(np.array([len(encoded) + j], np.int64))
        rec_start.append(np.array([base], np.int64))
        rec_size.append(np.array([b.size], np.int64))
        base += b.size
    if buffers:
        t_all = np.concatenate(rec_t)
        k_all = np.concatenate(rec_key)
        order = np.lexsort((k_all, t_all))  # by time, then topic (stable within a topic)
        data = _gather(buffers, np.concatenate(rec_start)[order], np.concatenate(rec_size)[order])
    else:
        data = b""

    # ---- atomic write
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(head)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, out)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return out
