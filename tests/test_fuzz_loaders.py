"""Fuzz the two file loaders every command goes through: ``read_ulog`` and ``load_params``.

Each test feeds at least 10 000 mutated inputs (Hypothesis, ``derandomize=True`` so CI
runs the same inputs every time, no example database) and accepts only two outcomes:
success, or a :class:`~twin_nodes.base.errors.TwinError` whose message is one line
that starts with the file's path.  Any other exception, and any input that takes
longer than :data:`BUDGET_S` (a hang, or memory allocated in proportion to a
corrupt size or time gap), fails the test with the minimal input that did it.

ULog inputs are bit flips, overwrites, insertions, deletions and truncations of a
small valid log written by the project's own writer, plus timestamp rewrites in
file order (backwards steps, gaps of up to 2**63 µs).  Params inputs are byte
mutations of a compact valid params file, scalar replacements by hostile values
(1e308, NaN, huge integers, aliases, nested lists) and random YAML structures.
Both run in the normal suite (about 25 s each on a 2-core machine).
"""

from __future__ import annotations

import copy
import os
import re
import signal
import struct
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import ulog_cases as C
from twin_nodes.base.errors import TwinError
from twin_nodes.logs.ulog_io import FlightLog, read_ulog
from twin_nodes.logs.ulog_write import write_px4_ulog
from twin_nodes.vehicle.params import VehicleParams, load_params

#: inputs per loader; ROTORTWIN_FUZZ_INPUTS raises it for a longer run (never below 10 000 in CI)
N_INPUTS = max(int(os.environ.get("FUZZ_MIN", "10000")), int(os.environ.get("ROTORTWIN_FUZZ_INPUTS", "10000")))
BUDGET_S = 5.0  # per input; a good small input takes a few ms
SETTINGS = dict(max_examples=N_INPUTS, deadline=None, derandomize=True, database=None,
                suppress_health_check=list(HealthCheck), print_blob=False)


class Hang(Exception):
    pass


def _alarm(signum, frame):
    raise Hang(f"one input took longer than {BUDGET_S} s")


def _call_bounded(fn, path: Path):
    """``fn(path)`` with a wall-clock budget; returns the value or the TwinError raised."""
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, BUDGET_S)
    try:
        return fn(path)
    except TwinError as exc:
        return exc
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


class _Scratch:
    """One file rewritten in place for every input (a fresh ``open(..., "wb")`` costs ~2 ms
    on some disks, more than the loaders themselves)."""

    def __init__(self, path: Path):
        self.path = path
        self._f = open(path, "wb")  # noqa: SIM115 - closed by close()

    def write(self, data: bytes) -> None:
        self._f.seek(0)
        self._f.write(data)
        self._f.truncate()
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def _check_outcome(out, path: Path, ok_type: type) -> None:
    if isinstance(out, TwinError):
        msg = str(out)
        assert "\n" not in msg, msg
        assert msg.startswith(f"{path}: "), msg
    else:
        assert isinstance(out, ok_type), type(out)


class _Bytes:
    """Reads small numbers from a Hypothesis-drawn byte string (zeros once it is used up), so
    one cheap ``st.binary`` draw decides a whole input and shrinks towards fewer, simpler edits.
    (Structured strategies cost ~3 ms of Hypothesis bookkeeping per input on a 2-core machine,
    more than the loaders; one binary draw costs ~0.7 ms.)"""

    def __init__(self, blob: bytes):
        self.blob, self.i = blob, 0

    def left(self) -> bool:
        return self.i < len(self.blob)

    def take(self, n: int) -> bytes:
        out = self.blob[self.i:self.i + n]
        self.i += n
        return out + bytes(n - len(out))

    def u(self, nbytes: int) -> int:
        return int.from_bytes(self.take(nbytes), "little")

    def pick(self, seq):
        return seq[self.u(1) % len(seq)]


def _mutate(data: bytes, ops) -> bytes:
    b = bytearray(data)
    for op in ops:
        if not b:
            break
        kind, pos = op[0], op[1] % len(b)
        if kind == "flip":
            b[pos] ^= 1 << op[2]
        elif kind == "set":
            b[pos:pos + len(op[2])] = op[2]
        elif kind == "insert":
            b[pos:pos] = op[2]
        elif kind == "delete":
            del b[pos:pos + op[2]]
        elif kind == "cut":
            del b[pos:]
    return bytes(b)


def _byte_op(r: _Bytes) -> tuple:
    kind, pos = r.pick(("flip", "flip", "set", "insert", "delete", "cut")), r.u(4)
    if kind == "flip":
        return kind, pos, r.u(1) % 8
    if kind in ("set", "insert"):
        return kind, pos, r.take(1 + r.u(1) % 8)
    if kind == "delete":
        return kind, pos, 1 + r.u(1) % 64
    return kind, pos


BLOB = st.binary(min_size=1, max_size=48)

# --------------------------------------------------------------------------- ULog


@pytest.fixture(scope="module")
def small_ulog(tmp_path_factory) -> bytes:
    keep = ("vehicle_local_position", "vehicle_attitude", "actuator_motors", "vehicle_status",
            "vehicle_land_detected", "sensor_combined")
    topics = {k: v for k, v in C.small_topics(1.0, 10.0).items() if k in keep}
    path = write_px4_ulog(tmp_path_factory.mktemp("fuzz") / "base.ulg", topics,
                          {"CA_ROTOR_COUNT": 4, "MPC_THR_HOVER": 0.5}, {"ver_sw": "fuzz"}, start_us=C.T0_US)
    data = path.read_bytes()
    assert isinstance(read_ulog(path), FlightLog)
    return data


TIMES = (0, 1, C.T0_US - 1, C.T0_US + 500_000, 2**31, 2**40, 2**62, 2**63 - 1, 2**63, 2**64 - 1)


def _ulog_bytes(base: bytes, blob: bytes) -> bytes:
    """Timestamp rewrites in file order (backwards steps, gaps, wrapped values), then byte edits."""
    r = _Bytes(blob)
    times: dict[int, int] = {}
    ops = []
    while r.left() and len(ops) + len(times) < 5:
        if r.u(1) % 3 == 0:
            k, how = r.u(2), r.u(1) % 4
            value = (r.pick(TIMES) if how == 0 else r.u(8) if how == 1
                     else C.T0_US + r.u(4) - 2**31 if how == 2 else C.T0_US + r.u(3) * 1000)
            times[k] = value
        else:
            ops.append(_byte_op(r))
    data = base
    if times:
        at = _timestamp_offsets(base)
        b = bytearray(base)
        for k, v in times.items():
            struct.pack_into("<Q", b, at[k % len(at)], v % 2**64)
        data = bytes(b)
    return _mutate(data, ops)


_OFFSETS: dict[bytes, list[int]] = {}


def _timestamp_offsets(base: bytes) -> list[int]:
    """File offsets of every data record's timestamp, in file order (what ``C.retime`` edits)."""
    if base not in _OFFSETS:
        _OFFSETS[base] = [at for _, at in C.timestamp_offsets(base)]
    return _OFFSETS[base]


def test_read_ulog_fuzz(small_ulog, tmp_path):
    scratch = _Scratch(tmp_path / "fuzz.ulg")
    path = scratch.path
    seen = {"n": 0, "ok": 0, "slowest": 0.0}

    @settings(**SETTINGS)
    @given(blob=BLOB)
    def one(blob):
        scratch.write(_ulog_bytes(small_ulog, blob))
        t = time.perf_counter()
        out = _call_bounded(read_ulog, path)
        seen["slowest"] = max(seen["slowest"], time.perf_counter() - t)
        _check_outcome(out, path, FlightLog)
        if isinstance(out, FlightLog):
            seen["ok"] += 1
            for s in out.series.values():  # the loader's promise: finite, strictly increasing times
                assert np.all(np.isfinite(s.t_s)) and np.all(np.diff(s.t_s) > 0), s.source
            assert out.duration_s < 3600.0, out.warnings  # a gap never stretches the log
        seen["n"] += 1

    try:
        one()
    finally:
        scratch.close()
    assert seen["n"] >= N_INPUTS, seen
    assert 0 < seen["ok"] < seen["n"], seen  # both outcomes were exercised
    print(f"read_ulog: {seen['n']} inputs, {seen['ok']} loaded, slowest {seen['slowest'] * 1e3:.0f} ms")


# --------------------------------------------------------------------------- params

BASE_PARAMS = """\
/**:
  ros__parameters:
    vehicle: {name: fuzz, mass_kg: 1.0, ixx_kg_m2: 0.025, iyy_kg_m2: 0.025, izz_kg_m2: 0.03, gravity_m_s2: 9.81}
    rotors:
      x_flu_m: [0.2, -0.2, 0.2, -0.2]
      y_flu_m: [-0.2, 0.2, 0.2, -0.2]
      direction: [1, 1, -1, -1]
      thrust_model: thrust_factor
      thrust_max_n: 5.0
      km_m: 0.02
      tau_up_s: 0.05
      tau_down_s: 0.05
    effects:
      enabled: [linear_drag, motor_efficiency]
      linear_drag: {k_n_s_m: 1.0}
      motor_efficiency: {motor: 3, efficiency: 0.85}
    controller: {rate_hz: 250.0}
    simulation: {dt_s: 0.001}
"""
_NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?(?:e[-+]?\d+)?")
_SCALARS = list(_NUMBER.finditer(BASE_PARAMS))
_BASE_DOC = yaml.safe_load(BASE_PARAMS)
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
HOSTILE = ("1e308", "-1e308", "1.0e-300", ".nan", ".inf", "-.inf", "0", "-1", "1e-12", "true", "null", "'1'",
           "[]", "{}", "[1, 2]", "9" * 400, "-" + "9" * 30, "0x7fffffff", "1_000", "!!float 1", "&a [*a]",
           "[[[[[[[[1]]]]]]]]", "*undefined", '"\\x00"', "9.9e99999", "!!python/object:os.system ls",
           "[" * 60, "{a: " * 30 + "1" + "}" * 30, "~", "2001-12-14", "!!binary AAAA", "<<: {}")
SECTIONS = ("vehicle", "rotors", "effects", "controller", "sensors", "simulation", "motor_efficiency",
            "x_flu_m", "direction", "enabled", "ros__parameters")
KEYS = ("mass_kg", "x_flu_m", "enabled", "motor", "dt_s", "\n", "", "ros__parameters", "a" * 300, "1")


def _tree(r: _Bytes, depth: int = 0):
    """A small random YAML value: scalars of every type, lists, mappings (3 levels at most)."""
    kind = r.u(1) % (9 if depth < 3 else 6)
    if kind == 0:
        return None
    if kind == 1:
        return bool(r.u(1) & 1)
    if kind == 2:
        return int.from_bytes(r.take(r.u(1) % 10), "little", signed=True)
    if kind == 3:
        return struct.unpack("<d", r.take(8))[0]  # NaN, inf, denormals included
    if kind == 4:
        return r.pick(HOSTILE)
    if kind == 5:
        return r.take(r.u(1) % 6).decode("latin-1")
    if kind in (6, 7):
        return [_tree(r, depth + 1) for _ in range(r.u(1) % 5)]
    return {r.pick(KEYS): _tree(r, depth + 1) for _ in range(r.u(1) % 4)}


def _params_bytes(blob: bytes) -> bytes:
    r = _Bytes(blob)
    mode = r.u(1) % 4
    if mode == 0:  # byte edits of the text
        ops = [_byte_op(r) for _ in range(1 + r.u(1) % 3)]
        return _mutate(BASE_PARAMS.encode(), ops)
    if mode == 1:  # hostile scalars where numbers were (right to left keeps offsets valid)
        edits = {r.u(1) % len(_SCALARS): _scalar(r) for _ in range(1 + r.u(1) % 3)}
        text = BASE_PARAMS
        for i in sorted(edits, reverse=True):
            m = _SCALARS[i]
            text = text[:m.start()] + edits[i] + text[m.end():]
        return text.encode()
    if mode == 2:  # a random structure as the whole file
        return _dump(_tree(r))
    doc = copy.deepcopy(_BASE_DOC)  # a random structure in place of one section or key
    inner = doc["/**"]["ros__parameters"]
    section, tree = r.pick(SECTIONS), _tree(r)
    if section == "ros__parameters":
        doc["/**"]["ros__parameters"] = tree
    elif section in inner:
        inner[section] = tree
    elif section in ("motor_efficiency", "enabled"):
        inner["effects"][section] = tree
    else:
        inner["rotors"][section] = tree
    return _dump(doc)


def _dump(doc) -> bytes:
    return yaml.dump(doc, Dumper=_DUMPER, allow_unicode=True).encode()


def _scalar(r: _Bytes) -> str:
    how = r.u(1) % 3
    if how == 0:
        return r.pick(HOSTILE)
    if how == 1:
        return repr(struct.unpack("<d", r.take(8))[0])
    return str(int.from_bytes(r.take(r.u(1) % 12), "little", signed=True))


def test_load_params_fuzz(tmp_path):
    scratch = _Scratch(tmp_path / "fuzz.yaml")
    path = scratch.path
    seen = {"n": 0, "ok": 0, "slowest": 0.0}

    @settings(**SETTINGS)
    @given(blob=BLOB)
    def one(blob):
        scratch.write(_params_bytes(blob))
        t = time.perf_counter()
        out = _call_bounded(load_params, path)
        seen["slowest"] = max(seen["slowest"], time.perf_counter() - t)
        _check_outcome(out, path, VehicleParams)
        if isinstance(out, VehicleParams):
            seen["ok"] += 1
            assert 1e-3 <= out.mass_kg <= 1e4 and 1e-5 <= out.dt_s <= 0.1
            assert np.all(np.isfinite(out.inertia)) and np.all(np.isfinite(out.rotors.positions_flu_m))
        seen["n"] += 1

    try:
        one()
    finally:
        scratch.close()
    assert seen["n"] >= N_INPUTS, seen
    assert 0 < seen["ok"] < seen["n"], seen
    print(f"load_params: {seen['n']} inputs, {seen['ok']} loaded, slowest {seen['slowest'] * 1e3:.0f} ms")
