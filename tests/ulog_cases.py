"""Bad-input ULog files for the loader tests, made from the project's own writer.

``small_flight(path)`` writes a short synthetic PX4-like flight with
:func:`twin_nodes.logs.ulog_write.write_px4_ulog`; ``retime(data, fn)`` rewrites
the timestamp of every data record in place, **in file order** (the writer sorts
records by time, so backwards time in file order needs a byte edit), which is
how GPS time jumps, clock resets and gaps are made; ``records(data)`` walks a
file's records.  Nothing here reads ``../shared``.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from twin_nodes.base import frames as F
from twin_nodes.logs.ulog_write import write_px4_ulog

T0_US = 1_000_000
HEADER = 16
_SIZES = {"int8_t": 1, "uint8_t": 1, "bool": 1, "char": 1, "int16_t": 2, "uint16_t": 2,
          "int32_t": 4, "uint32_t": 4, "float": 4, "int64_t": 8, "uint64_t": 8, "double": 8}


def _times(rate_hz: float, dur_s: float) -> np.ndarray:
    return (T0_US + np.arange(int(dur_s * rate_hz)) * int(1e6 / rate_hz)).astype(np.uint64)


def small_topics(dur_s: float = 20.0, rate_hz: float = 50.0) -> dict:
    """A hover-ish flight: climb to 3 m, hold, land; PX4 conventions (NED, FRD)."""
    rng = np.random.default_rng(1)
    t = _times(rate_hz, dur_s)
    s = (t - T0_US) * 1e-6
    h = np.clip(np.minimum(s - 2.0, dur_s - 2.0 - s), 0.0, 3.0)
    n = s.size
    z = -h
    vz = -np.gradient(h, s)
    lpos = dict(timestamp=t, x=0.02 * np.sin(s), y=np.zeros(n), z=z, vx=0.02 * np.cos(s), vy=np.zeros(n),
                vz=vz, ax=np.zeros(n), ay=np.zeros(n), az=np.zeros(n), heading=np.zeros(n),
                xy_valid=np.ones(n, bool), z_valid=np.ones(n, bool),
                v_xy_valid=np.ones(n, bool), v_z_valid=np.ones(n, bool))
    q = F.quat_from_euler(0.01 * np.sin(s), 0.01 * np.cos(s), np.zeros(n))
    u = np.full((n, 12), np.nan)
    u[:, :4] = 0.5 + 0.01 * rng.standard_normal((n, 4))
    armed_t = (T0_US + np.array([0.0, 0.05, 0.95]) * dur_s * 1e6).astype(np.uint64)
    return {
        "vehicle_local_position": lpos,
        "vehicle_attitude": {"timestamp": t, "q": q},
        "vehicle_angular_velocity": {"timestamp": t, "xyz": 0.01 * rng.standard_normal((n, 3))},
        "actuator_motors": {"timestamp": t, "control": u},
        "vehicle_thrust_setpoint": {"timestamp": t, "xyz": np.column_stack(
            [np.zeros(n), np.zeros(n), -np.nanmean(u[:, :4], axis=1)])},
        "sensor_combined": {"timestamp": t, "gyro_rad": 0.01 * rng.standard_normal((n, 3)),
                            "accelerometer_m_s2": 0.05 * rng.standard_normal((n, 3)) + [0, 0, -9.81],
                            "accelerometer_timestamp_relative": np.zeros(n, np.int32)},
        "battery_status": {"timestamp": t[::10], "voltage_v": np.linspace(16.8, 15.9, t[::10].size),
                           "current_a": np.full(t[::10].size, 10.0)},
        "trajectory_setpoint": {"timestamp": t[::2], "position": np.column_stack(
            [np.zeros(t[::2].size), np.zeros(t[::2].size), z[::2]]),
            "velocity": np.full((t[::2].size, 3), np.nan), "yaw": np.zeros(t[::2].size)},
        "vehicle_status": {"timestamp": armed_t, "arming_state": np.array([1, 2, 1]),
                           "nav_state": np.array([4, 3, 4])},
        "vehicle_land_detected": {"timestamp": (T0_US + np.array([0.0, 0.1, 0.9]) * dur_s * 1e6).astype(np.uint64),
                                  "landed": np.array([True, False, True])},
    }


def small_flight(path: str | Path, dur_s: float = 20.0, rate_hz: float = 50.0) -> Path:
    """Write :func:`small_topics` as a ULog at ``path`` (CA_ROTOR_COUNT 4)."""
    return write_px4_ulog(path, small_topics(dur_s, rate_hz),
                          {"CA_ROTOR_COUNT": 4, "MPC_THR_HOVER": 0.5}, {"ver_sw": "ulog_cases"},
                          start_us=T0_US)


def records(data: bytes) -> Iterator[tuple[int, str, int, int]]:
    """``(offset, type, payload_offset, payload_size)`` of every complete record after the header."""
    pos = HEADER
    while pos + 3 <= len(data):
        size, typ = struct.unpack_from("<HB", data, pos)
        if pos + 3 + size > len(data):
            return
        yield pos, chr(typ), pos + 3, size
        pos += 3 + size


def _formats(data: bytes) -> tuple[dict[int, str], dict[str, int]]:
    """msg_id -> topic name, topic name -> byte offset of its ``timestamp`` field."""
    ts_off: dict[str, int] = {}
    names: dict[int, str] = {}
    for _, typ, p, n in records(data):
        body = data[p:p + n]
        if typ == "F":
            name, _, fields = body.decode().partition(":")
            off = 0
            for fdef in filter(None, fields.split(";")):
                ftype, fname = fdef.split(" ")
                if fname == "timestamp":
                    ts_off[name] = off
                    break
                base, _, arr = ftype.partition("[")
                off += _SIZES[base] * (int(arr[:-1]) if arr else 1)
        elif typ == "A":
            names[struct.unpack_from("<H", body, 1)[0]] = body[3:].decode()
    return names, ts_off


def timestamp_offsets(data: bytes) -> list[tuple[str, int]]:
    """``(topic, file offset of its timestamp)`` of every data record, in file order."""
    names, ts_off = _formats(data)
    out = []
    for _, typ, p, _n in records(data):
        if typ == "D":
            name = names[struct.unpack_from("<H", data, p)[0]]
            out.append((name, p + 2 + ts_off[name]))
    return out


def retime(data: bytes, fn: Callable[[str, int, int], int]) -> bytes:
    """Rewrite each data record's timestamp to ``fn(topic, k, t_us)`` where ``k`` is the
    record's index in file order over all data records (0, 1, ...)."""
    out = bytearray(data)
    for k, (name, at) in enumerate(timestamp_offsets(data)):
        t = struct.unpack_from("<Q", data, at)[0]
        struct.pack_into("<Q", out, at, fn(name, k, t) % 2**64)
    return bytes(out)


def n_data_records(data: bytes) -> int:
    return sum(1 for _, typ, _, _ in records(data) if typ == "D")


def with_gap(data: bytes, gap_us: int, at_fraction: float = 0.5) -> bytes:
    """Every data record after ``at_fraction`` of the file (in file order) stamped ``gap_us`` later."""
    cut = int(n_data_records(data) * at_fraction)
    return retime(data, lambda name, k, t: t + gap_us if k >= cut else t)


def with_backwards(data: bytes, back_us: int, at_fraction: float = 0.5) -> bytes:
    """A clock step back of ``back_us`` after ``at_fraction`` of the file (in file order)."""
    cut = int(n_data_records(data) * at_fraction)
    return retime(data, lambda name, k, t: t - back_us if k >= cut else t)


def truncated(data: bytes, keep_fraction: float = 0.7) -> bytes:
    """The file cut in the middle of a data record."""
    recs = [r for r in records(data) if r[1] == "D"]
    off, _, p, n = recs[int(len(recs) * keep_fraction)]
    return data[: p + max(1, n // 2)]


# --------------------------------------------------------------------------- value and flyability cases
# (issue 28): every value read from a log is checked where it enters; flights a command cannot use are
# refused in one line saying why


def with_repeated_stamps(data: bytes, at_fraction: float = 0.5) -> bytes:
    """The clock steps back at ``at_fraction`` of the file onto stamps it already used: every record
    after the cut repeats a stamp of the part before it (duplicate stamps going backwards)."""
    offs = timestamp_offsets(data)
    cut = int(len(offs) * at_fraction)
    t_cut = struct.unpack_from("<Q", data, offs[cut][1])[0]
    return with_backwards(data, t_cut - T0_US, at_fraction)


#: PX4's generic quad X rotor positions and spins (CA_ROTORn_PX/PY/KM), so that ``params from-ulog`` gets past
#: the airframe to the flight itself
QUAD_X_PARAMS = {f"CA_ROTOR{i}_{k}": v for i, (x, y, km) in enumerate(
    ((0.15, 0.15, 0.05), (-0.15, -0.15, 0.05), (0.15, -0.15, -0.05), (-0.15, 0.15, -0.05)))
    for k, v in (("PX", x), ("PY", y), ("KM", km))}


def edited_flight(path: str | Path, edit: Callable[[dict], None] | None = None, dur_s: float = 20.0,
                  params: dict | None = None) -> Path:
    """:func:`small_flight` with its topics changed by ``edit(topics)`` (in place) before writing, and
    the generic quad X rotor positions (:data:`QUAD_X_PARAMS`) and ``params`` added to its parameters."""
    topics = small_topics(dur_s)
    if edit is not None:
        edit(topics)
    return write_px4_ulog(path, topics, {"CA_ROTOR_COUNT": 4, "MPC_THR_HOVER": 0.5, **QUAD_X_PARAMS, **(params or {})},
                          {"ver_sw": "ulog_cases"}, start_us=T0_US)


def _seconds(topic: dict) -> np.ndarray:
    return (topic["timestamp"].astype(np.int64) - T0_US) * 1e-6


def inf_positions(topics: dict) -> None:
    """+-inf in every position component for 2 s of the flight (10 %)."""
    lp = topics["vehicle_local_position"]
    s = _seconds(lp)
    bad = (s >= 9.0) & (s < 11.0)
    sign = np.where(np.arange(bad.sum()) % 2, 1.0, -1.0)
    for k in ("x", "y", "z"):
        lp[k] = lp[k].astype(float).copy()
        lp[k][bad] = sign * np.inf


def motors_x1000(topics: dict) -> None:
    """Motor outputs 1000 times their normalised value (a unit or scaling error)."""
    topics["actuator_motors"]["control"] = topics["actuator_motors"]["control"] * 1000.0


def zero_quaternions(topics: dict) -> None:
    """Every attitude quaternion all zero."""
    topics["vehicle_attitude"]["q"] = np.zeros_like(topics["vehicle_attitude"]["q"])


def one_sample(topics: dict) -> None:
    """Every topic cut to its first sample."""
    for name, tp in topics.items():
        topics[name] = {k: v[:1] for k, v in tp.items()}


def never_airborne(topics: dict) -> None:
    """Armed on the ground (a bench or arm/disarm test): landed throughout, no height change."""
    lp = topics["vehicle_local_position"]
    lp["z"] = np.zeros_like(lp["z"])
    lp["vz"] = np.zeros_like(lp["vz"])
    topics["vehicle_land_detected"]["landed"] = np.ones_like(topics["vehicle_land_detected"]["landed"])
    ts = topics["trajectory_setpoint"]
    ts["position"] = np.zeros_like(ts["position"])


def no_horizontal_velocity(topics: dict) -> None:
    """No GPS: the EKF's horizontal position and velocity invalid all flight (xy_valid/v_xy_valid false)."""
    lp = topics["vehicle_local_position"]
    lp["xy_valid"] = np.zeros_like(lp["xy_valid"])
    lp["v_xy_valid"] = np.zeros_like(lp["v_xy_valid"])
