"""Read PX4 ULog flight logs into canonical, ROS-frame time series.

``read_ulog(path)`` loads only the topics rotortwin needs (pyulog
``message_name_filter_list``; well under a second for a 5 MB log), cleans the
time stamps, converts every quantity **once** to ROS frames (ENU world, FLU body,
``[w, x, y, z]`` FLU->ENU quaternions, via :mod:`twin_nodes.base.frames`) and returns a
:class:`FlightLog` of named :class:`Series`.

Time: ``Series.t_s`` is float seconds since the ULog header's start time
(``FlightLog.start_us``, PX4 hrt µs), strictly increasing.

Cleaning rules (see /work/shared/flightlogs/*/MANIFEST.md):

- A sample stamped before the log start (a small negative time, stored as a
  wrapped uint64) is dropped.  For the on-change state topics
  (``vehicle_status``, ``vehicle_land_detected``) the latest such sample is the
  state *at* log start, so it is kept and re-stamped to t = 0 instead.
- A sample absurdly later than the rest of the log (more than
  ``max(5 s, 10 %)`` after the log end, taken as the median over the loaded
  topics of each topic's 99th-percentile time) is dropped with a warning.
  Only flight topics are loaded, so the stray ``mission`` sample that makes
  pyulog report 379 s for real_s500_rcac_mission2 never enters.
- ``motors`` is NaN while ``vehicle_status`` says disarmed (PX4 logs 0 there on
  some versions and in SITL).
- Time going backwards (clock resets, GPS time jumps): within each topic the
  samples are kept in file order, and where a timestamp is earlier than one
  before it the longest run of samples that is in time order is kept (the
  longest strictly increasing subsequence in file order, of those the one that
  keeps the earliest logged samples, so a clock that steps back onto stamps it
  already used leaves every topic the same stretch of flight); the others are
  dropped with one warning line per topic, which counts the duplicate stamps.  More than one sample before the log start, or one
  more than 2 s before it, is also reported (the clock went backwards).
- Time jumps forward: a stretch of more than :data:`TIME_JUMP_S` (30 s) with no
  sample of any loaded topic (or between the header's start time and the first
  sample) is a clock jump, not a pause: the log is cut there and the longest
  consistent part is kept (one warning line per jump, one for what was kept and
  dropped).  When that part starts after the log start, times are counted from
  its first sample (``start_us`` moves with it).  Memory and run time therefore
  follow the flight's real duration, never the size of a gap (a 2**40 µs jump
  would otherwise be 275 million samples on a 250 Hz grid).  Shorter pauses of
  every topic (> 2 s) and per-topic gaps (> max(5 s, 50 sample intervals)) are
  reported in a warning line; resampling makes them NaN.
- A file cut in the middle of a record (a truncated log) is reported as
  ``file truncated`` in the warnings (pyulog reads what is there silently).
  :meth:`FlightLog.data_warnings` lists just these data-loss warnings, for a
  command to show its user; :func:`read_ulog` also sends each to the ``rotortwin.logs``
  logger (the ``rotortwin`` command prints them as ``rotortwin: warning: <file>: ...``).
- A definitions section whose formats expand beyond a ULog message's 65535
  bytes (or contain themselves) is refused before pyulog expands it.
- ``duration_s`` is the last sample time over all series.
- Duplicate times (a sample stamped like the one before it) keep the last
  sample, with a warning (not for the on-change state topics).
- Every value is checked where it enters (:func:`_check_values`): rows with
  +-inf, values out of their physical range (:data:`VALUE_LIMITS`: positions
  beyond 1e6 m, speeds beyond 200 m/s, normalised commands beyond +-1.5, ...)
  or quaternions that are not unit (all zero) are dropped with one warning per
  series; a series more than half bad is refused (:class:`LogError` naming the
  PX4 topic/field and what was expected).  NaN is left alone (unknown/stopped).
  Whether the log is a usable flight at all (too short, never airborne, no GPS)
  is :func:`twin_nodes.logs.flyable.check_flyable`'s question.
- ``vehicle_local_position`` samples with ``xy_valid``/``z_valid``/
  ``v_xy_valid``/``v_z_valid`` false are NaN in the matching components.
- EKF reset counters that change during the log and pyulog corruption flags are
  reported in ``FlightLog.warnings``.

Canonical series (units, frame) are listed in :data:`SERIES_SPEC`.  NaN always
means "unknown / not controlled / stopped", never zero.

Motor commands (``motors``, (n, N) in [0, 1], PX4 motor order, NaN = stopped):

1. ``actuator_motors.control[0..N-1]`` when logged (PX4 >= v1.14);
2. else ``actuator_outputs``.  Channels come from the output-function
   parameters (``PWM_MAIN_FUNCn``/``PWM_AUX_FUNCn`` = 101..112 = Motor1..12; MAIN
   is instance 0, AUX instance 1) scaled by the per-channel
   ``PWM_MAIN_MINn``/``MAXn``; without function parameters (PX4 <= v1.13, the
   old mixer) the lowest instance with N channels that vary while armed and drop
   to the disarm value when disarmed, scaled as that PX4 version's output driver
   did (:func:`twin_nodes.logs.legacy_topics.output_limits`: per-channel
   ``PWM_MAIN_MINn/MAXn`` where set, else ``PWM_MAIN_MIN/MAX`` (1.12+) or
   ``PWM_MIN/MAX`` (1.8-1.11); UAVCAN raw commands 0..8191; DShot; the X500 log
   has both sets, and its armed idle sits at PWM_MAIN_MIN = 1075 us, as 1.13's
   driver treats per-channel 1000/2000 as unset).  A value below the channel's
   minimum (900 us disarm, 0) or above its maximum, or a sample while disarmed
   -> NaN.  PX4 applies the inverse thrust model (``THR_MDL_FAC`` f) before
   output scaling, so the value u is mapped back with ``f u^2 + (1 - f) u`` (f =
   0 in all shared logs; on them the PWM route matches actuator_motors to a
   median 0.0005); a custom mixer file's idle speed, found in the log, is undone
   (:func:`twin_nodes.logs.legacy_topics.mixer_idle`).

``N`` (``FlightLog.n_motors``) is ``CA_ROTOR_COUNT``, else the number of motor
output functions, else from ``MAV_TYPE`` (quad 4, hexa 6, octo 8, tri 3).
``FlightLog.moving_outputs`` counts the motor outputs that move while armed
(:func:`moving_motor_outputs`), against which a layout without ``CA_*`` is checked.

Older topic sets (PX4 1.8-1.13) are read where the newer topic is missing, by
:mod:`twin_nodes.logs.legacy_topics`: body rates from ``vehicle_attitude.rollspeed..``,
torque from ``actuator_controls_0``, PX4 1.8's ``vehicle_local_position_setpoint``,
each version's setpoint field names (docs/real_logs.md has the table).
"""

from __future__ import annotations

import bisect
import contextlib
import io
import logging
import os
import warnings as _pywarnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from twin_nodes.base import frames

#: data-loss warnings of every loaded log (:meth:`FlightLog.data_warnings`) go to this logger as
#: ``<file>: <warning>``; the ``rotortwin`` command prints them on stderr, once each
LOG = logging.getLogger("rotortwin.logs")

from twin_nodes.logs import imu_rate, legacy_topics, time_sync
from twin_nodes.base.errors import LogError

__all__ = ["Series", "FlightLog", "SERIES_SPEC", "MANUAL_NAV_STATES", "read_ulog", "list_topics", "ULOG_MAGIC",
           "TIME_JUMP_S"]

ULOG_MAGIC = b"\x55\x4c\x6f\x67\x01\x12\x35"

#: no sample of any topic for longer than this [s]: a clock jump, the log is cut there
TIME_JUMP_S = 30.0
#: no sample of any topic for longer than this [s] (but < TIME_JUMP_S): reported as a pause
LOG_PAUSE_S = 2.0
#: per-topic gap reported when longer than max(this [s], 50 median sample intervals)
TOPIC_GAP_S = 5.0
#: PX4 samples stamped before the log start: one per topic, less than this [s] before it, is normal
PRE_START_OK_S = 2.0
#: largest flattened ULog message format (a message's size field is 16 bits)
_MAX_FORMAT = 0xFFFF
#: most rotors PX4 control allocation supports (CA_ROTOR_COUNT max)
_MAX_ROTORS = 12

#: canonical name -> (units, frame, interpolation kind for resampling)
SERIES_SPEC: dict[str, tuple[str, str, str]] = {
    "position_enu": ("m", "ENU", "linear"),
    "velocity_enu": ("m/s", "ENU", "linear"),
    "accel_enu": ("m/s^2", "ENU", "linear"),
    "height_agl": ("m", "up, above ground (distance sensor)", "linear"),
    "attitude_q": ("-", "q_wxyz FLU->ENU", "slerp"),
    "body_rates_flu": ("rad/s", "FLU", "linear"),
    "angular_accel_flu": ("rad/s^2", "FLU", "linear"),
    "motors": ("-", "PX4 motor order", "linear"),
    "throttle": ("-", "-", "linear"),
    "torque_setpoint_flu": ("-", "FLU", "linear"),
    "battery_v": ("V", "-", "linear"),
    "battery_a": ("A", "-", "linear"),
    "specific_force_flu": ("m/s^2", "FLU", "linear"),
    "gyro_flu": ("rad/s", "FLU", "linear"),
    "setpoint_position_enu": ("m", "ENU", "previous"),
    "setpoint_velocity_enu": ("m/s", "ENU", "previous"),
    "setpoint_accel_enu": ("m/s^2", "ENU", "previous"),
    "setpoint_yaw_enu": ("rad", "ENU yaw from East, CCW", "previous"),
    "setpoint_yawspeed": ("rad/s", "yaw-rate feed-forward about ENU up, CCW", "previous"),
    "setpoint_rates_flu": ("rad/s", "FLU", "linear"),
    "nav_state": ("-", "PX4 nav_state", "previous"),
    "attitude_setpoint_q": ("-", "q_wxyz FLU->ENU", "previous"),
    "attitude_setpoint_thrust": ("-", "-", "previous"),
    "attitude_setpoint_yawrate": ("rad/s", "yaw-rate feed-forward about ENU up, CCW", "previous"),
    "offboard_mode": ("-", "flags position, velocity, acceleration, attitude, body_rate, thrust", "previous"),
    "armed": ("-", "bool", "previous"),
    "landed": ("-", "bool", "previous"),
    "land_detector": ("-", "ground_contact, maybe_landed, landed (bool)", "previous"),
    "esc_rpm": ("rpm", "PX4 motor order", "linear"),
    "hover_thrust": ("-", "-", "linear"),
    "estimator_test_ratios": ("-", "vel, pos, hgt innovation test ratios (> 1: rejected)", "previous"),
    "gps_position_enu": ("m", "ENU, from the receiver's lat/lon about the EKF origin; NaN without a 3D fix", "linear"),
    "groundtruth_position_enu": ("m", "ENU", "linear"),
    "groundtruth_velocity_enu": ("m/s", "ENU", "linear"),
    "groundtruth_attitude_q": ("-", "q_wxyz FLU->ENU", "slerp"),
    "groundtruth_body_rates_flu": ("rad/s", "FLU", "linear"),
}

#: PX4 vehicle_status.nav_state values in which mc_pos_control does not run (MANUAL, ACRO, STAB, and
#: RATTITUDE 16 of PX4 <= 1.11, unused since): the attitude setpoint and collective thrust come from the
#: pilot's sticks
MANUAL_NAV_STATES = (0.0, 10.0, 15.0, 16.0)

#: topics read from the log (everything else is skipped by pyulog's filter)
TOPICS = (
    "vehicle_local_position",
    "vehicle_attitude",
    "vehicle_angular_velocity",
    "actuator_motors",
    "actuator_outputs",
    "actuator_controls_0",
    "vehicle_thrust_setpoint",
    "vehicle_torque_setpoint",
    "vehicle_rates_setpoint",
    "vehicle_attitude_setpoint",
    "battery_status",
    "sensor_combined",
    "trajectory_setpoint",
    "vehicle_local_position_setpoint",
    "vehicle_status",
    "offboard_control_mode",
    "vehicle_land_detected",
    "esc_status",
    "hover_thrust_estimate",
    "estimator_status",
    "vehicle_gps_position",
    "vehicle_local_position_groundtruth",
    "vehicle_attitude_groundtruth",
    "vehicle_angular_velocity_groundtruth",
)
_STATE_TOPICS = ("vehicle_status", "vehicle_land_detected")
_INT32_MAX = 2**31 - 1  # PX4 RELATIVE_TIMESTAMP_INVALID
_MOTOR_FUNC0 = 101  # OutputFunction Motor1
_MAV_TYPE_MOTORS = {2: 4, 13: 6, 14: 8, 15: 3}


@dataclass
class Series:
    """One signal: ``values[i]`` sampled at ``t_s[i]``.

    ``t_s`` (n,) float seconds since log start, strictly increasing; ``values``
    (n, k) float64; ``units``; ``frame`` (e.g. ``'ENU'``, ``'FLU'``); ``source``
    names the PX4 topic/fields it came from; ``interp`` is how
    :mod:`twin_nodes.logs.time_sync` resamples it (``'linear'``, ``'previous'``,
    ``'slerp'``)."""

    t_s: np.ndarray
    values: np.ndarray
    units: str
    frame: str
    source: str
    interp: str = "linear"

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def at(self, t_s: np.ndarray, kind: str | None = None) -> np.ndarray:
        """Values interpolated at times ``t_s`` (see :func:`time_sync.interp_to`)."""
        return time_sync.interp_to(self.t_s, self.values, t_s, kind=kind or self.interp)


#: the words a ``motors`` LogError ends with when no output channel moves while armed (the motors are driven
#: by something the log does not record: a simulator's own link, an external ESC bus); ``survey`` leaves such a
#: log out instead of counting it as a failure (:data:`twin_nodes.discovery.survey.LEFT_OUT_KINDS`)
NO_MOTOR_OUTPUTS = "this log carries no motor outputs"


@dataclass
class FlightLog:
    """A PX4 flight log in ROS frames.  See the module docstring."""

    path: str
    start_us: int
    duration_s: float
    params: dict[str, float]
    info: dict[str, str]
    series: dict[str, Series]
    warnings: list[str]
    n_motors: int
    #: parameter changes during the log: (t_s since start, name, value)
    param_changes: list[tuple[float, str, float]] = field(default_factory=list)
    #: the motor outputs that move while armed: (count, topic they were counted on), None when the
    #: log has neither ``actuator_motors`` nor ``actuator_outputs`` (:func:`moving_motor_outputs`)
    moving_outputs: tuple[int, str] | None = None

    def get(self, name: str) -> Series | None:
        """The series ``name`` or None when the log does not have it."""
        return self.series.get(name)

    def data_warnings(self) -> list[str]:
        """The warnings that mean data was dropped, cut or is missing (a truncated or corrupt
        file, clock jumps, time going backwards, logging pauses, stray samples): the ones a
        command should show its user, unlike notes such as a topic this PX4 does not log."""
        keys = ("file truncated", "file corruption", "timestamps go backwards", "duplicate stamp",
                "not finite", "out of range",
                "stamped before the log start", "far after the log end", "without samples")
        return [w for w in self.warnings if w.startswith("log: ") or any(k in w for k in keys)]

    def require(self, name: str) -> Series:
        """The series ``name``; raises :class:`LogError` naming what is missing."""
        s = self.series.get(name)
        if s is None or len(s) == 0:
            what = SERIES_SPEC.get(name)
            px4 = legacy_topics.PX4_SOURCES.get(name)
            expected = (f"expected series '{name}' ({what[0]}, {what[1]})"
                        + (f" from PX4's {px4}" if px4 else "") + ", not in this log"
                        if what else f"expected series '{name}'; known: {', '.join(SERIES_SPEC)}")
            if name == "motors" and self.moving_outputs is not None and self.moving_outputs[0] == 0:
                expected += f": no channel of {self.moving_outputs[1]} moves while armed, {NO_MOTOR_OUTPUTS}"
            raise LogError(self.path, name, expected)
        return s

    # ------------------------------------------------------------------ flight phases

    def airborne_intervals(self) -> list[tuple[float, float]]:
        """All airborne intervals [(t_takeoff, t_touchdown)] in seconds.

        From ``landed`` (land detector) when present, else from ``armed``,
        else from height: more than 1 m above the lowest ``position_enu`` z.
        An interval still open at the end of the log ends at ``duration_s``."""
        landed = self.get("landed")
        if landed is not None and len(landed):
            return _true_intervals(landed.t_s, landed.values[:, 0] < 0.5, self.duration_s)
        armed = self.get("armed")
        if armed is not None and len(armed):
            return _true_intervals(armed.t_s, armed.values[:, 0] > 0.5, self.duration_s)
        pos = self.get("position_enu")
        if pos is not None and len(pos) and np.any(np.isfinite(pos.values[:, 2])):
            z = pos.values[:, 2]
            up = np.isfinite(z) & (z > np.nanmin(z) + 1.0)
            return _true_intervals(pos.t_s, up, self.duration_s)
        return []

    def airborne_interval(self) -> tuple[float, float]:
        """(first take-off, last touchdown) [s]; see :meth:`airborne_intervals`."""
        iv = self.airborne_intervals()
        if not iv:
            raise LogError(self.path, "landed/armed/position_enu",
                           "expected at least one airborne sample (land detector, arming "
                           "state or height), found none")
        return iv[0][0], iv[-1][1]

    # ------------------------------------------------------------------ resampling

    def resample(
        self,
        names: Iterable[str],
        rate_hz: float,
        t0: float | None = None,
        t1: float | None = None,
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Put several series on one uniform grid (via :mod:`twin_nodes.logs.time_sync`).

        Each series uses its own ``interp`` kind (linear; zero-order hold for
        discrete signals; slerp for attitudes).  ``t0``/``t1`` default to the
        span common to the continuous series requested (discrete, on-change
        series hold their last value and do not shorten it).
        Returns ``(t, {name: values (m, k)})``."""
        names = list(names)
        if not names:
            raise ValueError("names: expected at least one series name")
        ss = {n: self.require(n) for n in names}
        cont = [s for s in ss.values() if s.interp != "previous"] or list(ss.values())
        lo = max(float(s.t_s[0]) for s in cont) if t0 is None else float(t0)
        if t1 is None:
            cont_only = [s for s in ss.values() if s.interp != "previous"]
            hi = (min(float(s.t_s[-1]) for s in cont_only) if cont_only else self.duration_s)
        else:
            hi = float(t1)
        t = time_sync.common_grid(lo, hi, rate_hz, source=self.path)
        return t, {n: time_sync.interp_to(s.t_s, s.values, t, kind=s.interp) for n, s in ss.items()}


def _true_intervals(t: np.ndarray, flag: np.ndarray, t_end: float) -> list[tuple[float, float]]:
    """Intervals where a sample-and-hold boolean signal is true."""
    out: list[tuple[float, float]] = []
    start = None
    for ti, f in zip(t, flag):
        if f and start is None:
            start = float(ti)
        elif not f and start is not None:
            out.append((start, float(ti)))
            start = None
    if start is not None:
        out.append((start, float(max(t_end, start))))
    return out


# =========================================================================== loading


class _ReadTracker:
    """A read-only file object for pyulog that remembers its last read.

    pyulog stops silently at a record cut short by the end of the file; the last
    read then returned fewer bytes than asked (and not the clean end of file: a
    3-byte record header read that got nothing)."""

    def __init__(self, path: Path):
        self._f = open(path, "rb")  # noqa: SIM115 - closed by pyulog (close())
        self._pos = 0
        self.last = (0, 0, 0)  # (offset, asked, got)

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        if n is not None and n >= 0:
            self.last = (self._pos, n, len(data))
        self._pos += len(data)
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        self._pos = self._f.seek(offset, whence)
        return self._pos

    def tell(self) -> int:
        return self._pos

    def close(self) -> None:
        self._f.close()

    def truncated_at(self) -> int | None:
        """File offset of the record cut short by the end of the file, or None."""
        at, asked, got = self.last
        if got < asked and not (asked == 3 and got == 0):
            return at
        return None


def _format_problem(formats: dict[str, Any]) -> str | None:
    """Why a definitions section cannot be flattened safely, or None.

    A ULog data message is at most 65535 bytes, so a format (nested types and
    arrays expanded) larger than that, or one that contains itself, is corrupt;
    pyulog would expand it field by field (minutes and gigabytes for a corrupt
    ``a[65535]`` of ``b[65535]``)."""
    from pyulog import ULog

    prim = {k: v[1] for k, v in ULog._UNPACK_TYPES.items()}
    done: dict[str, tuple[int, int]] = {}
    active: set[str] = set()

    def cost(name: str) -> tuple[int, int]:
        """(bytes, flattened nodes) of one instance of type ``name``."""
        if name in prim:
            return prim[name], 1
        if name in done:
            return done[name]
        fmt = formats.get(name)
        if fmt is None:  # unknown type: pyulog reports it as corruption itself
            return 0, 1
        if name in active:
            raise RecursionError(name)
        active.add(name)
        b, k = 0, 1
        for ftype, n, _ in getattr(fmt, "fields", ()):
            fb, fk = cost(ftype)
            m = max(int(n), 1)
            b, k = b + m * fb, k + m * fk
            if b > _MAX_FORMAT or k > _MAX_FORMAT:
                break
        active.discard(name)
        done[name] = (b, k)
        return b, k

    for name in formats:
        try:
            b, k = cost(name)
        except RecursionError:
            return f"format '{name}' contains itself"
        if b > _MAX_FORMAT or k > _MAX_FORMAT:
            return f"format '{name}' expands to more than {_MAX_FORMAT} bytes or fields"
    return None


class _BadFormats(Exception):
    pass


def _check_formats(formats: dict[str, Any]) -> None:
    problem = _format_problem(formats)
    if problem is not None:
        raise _BadFormats(problem)


_CHECKED_ULOG: Any = None


def _checked_ulog() -> Any:
    """pyulog's ULog, checking the message formats (:func:`_format_problem`) as soon as the
    definitions section is read, before any format is flattened for the data section."""
    global _CHECKED_ULOG
    if _CHECKED_ULOG is None:
        from pyulog import ULog

        class CheckedULog(ULog):
            def _read_file_definitions(self) -> None:
                super()._read_file_definitions()
                _check_formats(self.message_formats)

        _CHECKED_ULOG = CheckedULog
    return _CHECKED_ULOG


def _open_ulog(path: Path, filter_list: list[str] | None) -> tuple[Any, str, int | None]:
    """pyulog ULog of ``path`` or a LogError.

    Returns (ulog, captured pyulog output, offset of a record cut short by the
    end of the file or None)."""
    from pyulog import ULog

    p = str(path)
    try:
        if not path.exists():
            raise LogError(p, "file", "expected an existing ULog file, not found")
        if not path.is_file():
            raise LogError(p, "file", "expected a ULog file, got a directory or special file")
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as exc:
        raise LogError(p, "file", f"expected a readable ULog file ({exc.strerror or exc})") from None
    if len(head) < 16:
        raise LogError(p, "header",
                       f"expected a 16-byte ULog header, the file has only {size} bytes")
    if head[:7] != ULOG_MAGIC:
        raise LogError(p, "header",
                       f"not a ULog: bad magic {head[:7].hex(' ')} (expected {ULOG_MAGIC.hex(' ')})")
    buf = io.StringIO()
    tracker = None
    try:
        with contextlib.redirect_stdout(buf):
            if not hasattr(ULog, "_read_file_definitions"):  # another pyulog: check in a first pass
                _check_formats(ULog(p, disable_str_exceptions=True, parse_header_only=True).message_formats)
            tracker = _ReadTracker(path)
            ulog = _checked_ulog()(tracker, message_name_filter_list=filter_list, disable_str_exceptions=True)
    except _BadFormats as exc:
        raise LogError(p, "definitions", f"expected ULog message formats of at most {_MAX_FORMAT} "
                                         f"bytes: {exc} (corrupt definitions section)") from None
    except LogError:
        raise
    except OSError as exc:
        raise LogError(p, "file", f"expected a readable ULog file ({exc.strerror or exc})") from None
    except Exception as exc:  # pyulog raises many types on a corrupt definitions section
        msg = " ".join(f"{type(exc).__name__}: {exc}".split())[:200]
        raise LogError(p, "definitions", f"expected a parsable ULog definitions section: {msg}") from None
    finally:
        if tracker is not None:
            tracker.close()
    return ulog, buf.getvalue(), tracker.truncated_at()


@dataclass
class _Topic:
    """One cleaned topic instance: relative µs times and the field arrays."""

    name: str
    multi_id: int
    t_us: np.ndarray  # int64, µs since start, sorted, unique
    data: dict[str, np.ndarray]

    @property
    def t_s(self) -> np.ndarray:
        return self.t_us.astype(float) * 1e-6

    def has(self, *fields: str) -> bool:
        return all(f in self.data for f in fields)

    def col(self, name: str) -> np.ndarray:
        with np.errstate(invalid="ignore", over="ignore"):  # a corrupt field of an odd type
            return np.asarray(self.data[name], dtype=float)

    def cols(self, names: Iterable[str]) -> np.ndarray:
        return np.column_stack([self.col(n) for n in names])

    def arr(self, base: str, k: int) -> np.ndarray:
        return self.cols(f"{base}[{i}]" for i in range(k))

    def subset(self, keep: np.ndarray) -> "_Topic":
        return _Topic(self.name, self.multi_id, self.t_us[keep],
                      {k: v[keep] for k, v in self.data.items()})


_I64_MAX = np.iinfo(np.int64).max


def _rel_us(t_raw: np.ndarray, start_us: int) -> np.ndarray:
    """µs since ``start_us`` as int64.  A timestamp is the uint64 of a (possibly
    negative, wrapped) int64; differences that overflow int64 saturate (they are
    absurd either way and dropped by the jump rules)."""
    a = np.asarray(t_raw).astype(np.uint64).view(np.int64)
    s = int(start_us) % 2**64
    b = np.int64(s - 2**64 if s >= 2**63 else s)
    with np.errstate(over="ignore"):
        r = a - b
    ovf = ((a >= 0) != (b >= 0)) & ((r >= 0) != (a >= 0))
    if np.any(ovf):
        r[ovf] = np.where(a[ovf] >= 0, _I64_MAX, -_I64_MAX)
    return r


def _longest_in_order(v: np.ndarray) -> np.ndarray:
    """Indices of a longest strictly increasing subsequence of ``v`` (ascending), the one that keeps
    the earliest samples (lexicographically smallest indices).

    Strict, so a sample repeating an earlier stamp is never kept beside it; earliest first, so
    when the clock steps back onto stamps it already used (a clock reset replaying the same times,
    many equally long runs) every topic keeps the same part of the flight, the part logged first,
    and no topic splices two stretches of the flight at a point of its own."""
    vals = v.tolist()
    n = len(vals)
    run_from = [0] * n  # length of the longest strictly increasing run starting at i
    tails: list[int] = []  # over -v, scanned backwards: smallest last value of a run of each length
    for i in range(n - 1, -1, -1):
        x = -vals[i]
        j = bisect.bisect_left(tails, x)
        run_from[i] = j + 1
        if j == len(tails):
            tails.append(x)
        else:
            tails[j] = x
    need = len(tails)
    out: list[int] = []
    last = None
    for i in range(n):
        if need == 0:
            break
        if run_from[i] == need and (last is None or vals[i] > last):
            out.append(i)
            last = vals[i]
            need -= 1
    return np.array(out, dtype=np.int64)


def _clean_times(name: str, t_raw: np.ndarray, start_us: int,
                 notes: list[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(kept indices, their µs since ``start_us``, strictly increasing) after the pre-start,
    backwards and duplicate rules (the late-stray and jump rules need all topics; see
    _drop_strays, _cut_at_time_jumps).  Problems are appended to ``notes`` (one line each)."""
    notes = [] if notes is None else notes
    rel = _rel_us(t_raw, start_us)
    idx = np.arange(rel.size)
    pre = rel < 0
    state_at_start = None
    if np.any(pre):
        n_pre, lowest = int(pre.sum()), int(rel[pre].min())
        if name in _STATE_TOPICS:
            # keep the state that held at log start, re-stamped to t = 0
            state_at_start = int(idx[pre][np.argmax(rel[pre])])
        if n_pre > 1 or lowest < -PRE_START_OK_S * 1e6:
            notes.append(f"dropped {n_pre} sample(s) stamped before the log start (down to "
                         f"{lowest * 1e-6:.6g} s): the clock went backwards")
    idx = idx[~pre]
    r = rel[idx]
    if r.size > 1:
        # a sample stamped like the one before it: the last of each such run is kept
        last_of_run = np.append(r[1:] != r[:-1], True)
        n_dup = int(r.size - last_of_run.sum())
        if n_dup and name not in _STATE_TOPICS:
            notes.append(f"{n_dup} duplicate stamp(s) of {r.size} (the same time as the sample before): "
                         "kept the last of each")
        idx, r = idx[last_of_run], r[last_of_run]
    if r.size > 1:
        step = np.diff(r)
        if np.any(step < 0):
            keep = _longest_in_order(r)
            k = int(np.argmin(step))
            dropped = np.setdiff1d(np.arange(r.size), keep)
            repeats = int(np.isin(r[dropped], r[keep]).sum())
            notes.append(f"timestamps go backwards {int((step < 0).sum())} time(s) in file order "
                         f"(largest step {step[k] * 1e-6:.6g} s, at t = {r[k] * 1e-6:.6g} s): kept the "
                         f"longest run in time order (the earliest logged), dropped {r.size - keep.size} of "
                         f"{r.size} samples"
                         + (f" ({repeats} of them duplicate stamps of kept samples)" if repeats else ""))
            idx, r = idx[keep], r[keep]
    if state_at_start is not None:
        idx = np.concatenate([[state_at_start], idx])
        r = np.concatenate([np.zeros(1, np.int64), r])
    if r.size > 1:
        last_of_run = np.append(r[1:] != r[:-1], True)
        idx = idx[last_of_run]
        r = r[last_of_run]
    return idx, r


def _segments(t_list: list[np.ndarray], gap_us: float) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) of the union of the sample times in ``t_list`` (each sorted), split
    where no array has a sample for more than ``gap_us``."""
    starts, ends = [], []
    for t in t_list:
        if t.size == 0:
            continue
        br = np.flatnonzero(np.diff(t) > gap_us)
        starts.append(np.concatenate([t[:1], t[br + 1]]))
        ends.append(np.concatenate([t[br], t[-1:]]))
    if not starts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    s, e = np.concatenate(starts), np.concatenate(ends)
    order = np.argsort(s, kind="stable")
    s, e = s[order], e[order]
    reach = np.maximum.accumulate(e)
    new = np.concatenate([[True], (s[1:] - reach[:-1]) > gap_us])
    first = np.flatnonzero(new)
    return s[first], np.maximum.reduceat(e, first)


def _cut_at_time_jumps(topics: dict[tuple[str, int], _Topic], warnings: list[str]) -> int:
    """Cut the log at clock jumps (> TIME_JUMP_S without any sample) and keep the longest
    consistent part; report pauses and per-topic gaps.  Returns the µs by which times
    were shifted (the kept part's start when it is not the log start, else 0)."""
    jump = TIME_JUMP_S * 1e6
    seg_s, seg_e = _segments([tp.t_us for tp in topics.values()], jump)
    if seg_s.size == 0:
        return 0
    # the header's start time is a point of the log: data long after it is a jump too
    gap_from = np.concatenate([[0], seg_e[:-1]])
    gaps = seg_s - gap_from
    lead = bool(gaps[0] > jump)
    edges = [0] + list(range(1, seg_s.size)) + [seg_s.size]
    parts = [(int(seg_s[a]) if (a > 0 or lead) else 0, int(seg_e[b - 1]))
             for a, b in zip(edges[:-1], edges[1:])]
    shift = 0
    if len(parts) > 1 or lead:
        def count(lo: int, hi: int) -> int:
            return sum(int(np.searchsorted(tp.t_us, hi, "right") - np.searchsorted(tp.t_us, lo, "left"))
                       for tp in topics.values())

        counts = [count(lo, hi) for lo, hi in parts]
        best = max(range(len(parts)), key=lambda i: (parts[i][1] - parts[i][0], counts[i], -i))
        lo, hi = parts[best]
        jumps = np.flatnonzero(gaps > jump)
        for j in jumps[:3]:
            warnings.append(f"log: time jump of {gaps[j] * 1e-6:.9g} s with no sample of any topic "
                            f"(t = {gap_from[j] * 1e-6:.9g} s -> {seg_s[j] * 1e-6:.9g} s after the ULog "
                            "start; a clock or GPS time jump)")
        if jumps.size > 3:
            warnings.append(f"log: {jumps.size - 3} more time jump(s) longer than {TIME_JUMP_S:g} s")
        total = sum(tp.t_us.size for tp in topics.values())
        warnings.append(f"log: kept the longest consistent part, {(hi - lo) * 1e-6:.3f} s from t = "
                        f"{lo * 1e-6:.9g} s after the ULog start ({counts[best]} samples), dropped "
                        f"{total - counts[best]} samples outside it"
                        + ("; times are counted from its start" if lo > 0 else ""))
        for key, tp in list(topics.items()):
            inside = (tp.t_us >= lo) & (tp.t_us <= hi)
            if tp.name in _STATE_TOPICS and not np.any(tp.t_us == lo):
                before = np.flatnonzero(tp.t_us < lo)
                if before.size:  # the state that held when the kept part starts
                    inside[before[-1]] = True
            sub = tp.subset(inside)
            sub.t_us = np.maximum(sub.t_us, lo) - lo
            topics[key] = sub
        shift = lo
    # pauses of the whole log and gaps of single topics inside the kept part
    ps, pe = _segments([tp.t_us for tp in topics.values() if tp.t_us.size], LOG_PAUSE_S * 1e6)
    if ps.size > 1:
        pg = ps[1:] - pe[:-1]
        k = int(np.argmax(pg))
        warnings.append(f"log: {pg.size} pause(s) longer than {LOG_PAUSE_S:g} s with no sample of any "
                        f"topic, longest {pg[k] * 1e-6:.3g} s at t = {pe[k] * 1e-6:.3f} s (logging "
                        "paused): NaN there when resampled")
    _topic_gaps(topics, warnings)
    return shift


def _topic_gaps(topics: dict[tuple[str, int], _Topic], warnings: list[str]) -> None:
    for tp in topics.values():
        if tp.name in _STATE_TOPICS or tp.t_us.size < 20:
            continue
        dt = np.diff(tp.t_us)
        limit = max(TOPIC_GAP_S * 1e6, 50.0 * float(np.median(dt)))
        big = np.flatnonzero(dt > limit)
        if big.size:
            k = big[np.argmax(dt[big])]
            warnings.append(f"{tp.name}[{tp.multi_id}]: {big.size} gap(s) longer than {limit * 1e-6:.3g} s "
                            f"without samples, longest {dt[k] * 1e-6:.3g} s at t = {tp.t_us[k] * 1e-6:.3f} s "
                            "(NaN there when resampled)")


def _drop_strays(topics: dict[tuple[str, int], _Topic], warnings: list[str]) -> None:
    # robust end of each topic: its 99th-percentile sample, so a few late strays
    # inside a topic do not move it; the log end is the median over topics
    ends = [tp.t_us[int(0.99 * (tp.t_us.size - 1))] for tp in topics.values()
            if tp.t_us.size >= 10]
    if not ends:
        return
    ref = float(np.median(ends))
    limit = ref + max(5e6, 0.1 * ref)
    for key, tp in list(topics.items()):
        late = tp.t_us > limit
        if np.any(late):
            warnings.append(
                f"{tp.name}[{tp.multi_id}]: dropped {int(late.sum())} sample(s) stamped "
                f"{tp.t_us[late].min() * 1e-6:.1f} s, far after the log end (~{ref * 1e-6:.1f} s)")
            topics[key] = tp.subset(~late)


def _load_topics(ulog: Any) -> tuple[dict[tuple[str, int], _Topic], list[str], int]:
    """Cleaned topics, warnings, and the µs by which times were shifted from the
    header's start time (non-zero only when the log was cut at a clock jump)."""
    warnings: list[str] = []
    start = int(ulog.start_timestamp)
    topics: dict[tuple[str, int], _Topic] = {}
    for d in ulog.data_list:
        if "timestamp" not in d.data or len(d.data["timestamp"]) == 0:
            continue
        ts = np.asarray(d.data["timestamp"])
        if ts.dtype.kind not in "ui":
            warnings.append(f"{d.name}[{d.multi_id}]: timestamp is {ts.dtype}, expected uint64 µs: "
                            "topic skipped")
            continue
        notes: list[str] = []
        idx, rel = _clean_times(d.name, ts, start, notes)
        warnings.extend(f"{d.name}[{d.multi_id}]: {n}" for n in notes)
        if idx.size == 0:
            continue
        data = {k: v[idx] for k, v in d.data.items() if not k.startswith("_padding")}
        topics[(d.name, d.multi_id)] = _Topic(d.name, d.multi_id, rel, data)
    _drop_strays(topics, warnings)
    topics = {k: v for k, v in topics.items() if v.t_us.size}
    shift = _cut_at_time_jumps(topics, warnings)
    topics = {k: v for k, v in topics.items() if v.t_us.size}
    return topics, warnings, shift


def _first_instance(topics: dict[tuple[str, int], _Topic], name: str) -> _Topic | None:
    inst = sorted(mid for (n, mid) in topics if n == name)
    return topics[(name, inst[0])] if inst else None


def _series(name: str, t_s: np.ndarray, values: np.ndarray, source: str) -> Series:
    units, frame, interp = SERIES_SPEC[name]
    v = np.asarray(values, dtype=float)
    if v.ndim == 1:
        v = v[:, None]
    return Series(np.asarray(t_s, dtype=float), v, units, frame, source, interp)


def _float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError, OverflowError):
        return float("nan")


def _ulog_params(ulog: Any) -> dict[str, float]:
    return {str(k): _float(v) for k, v in ulog.initial_parameters.items()}


def _pint(params: dict[str, float], name: str, default: int) -> int:
    """An integer parameter; ``default`` when absent or not a finite number (corrupt log)."""
    v = params.get(name)
    return int(v) if v is not None and np.isfinite(v) and abs(v) < 2**31 else default


def _n_motors(params: dict[str, float], am: _Topic | None) -> tuple[int, str]:
    n = _pint(params, "CA_ROTOR_COUNT", 0)
    if 0 < n <= _MAX_ROTORS:
        return n, "CA_ROTOR_COUNT"
    funcs = [_pint(params, k, 0) for k in params
             if (k.startswith("PWM_MAIN_FUNC") or k.startswith("PWM_AUX_FUNC"))]
    funcs = [f for f in funcs if _MOTOR_FUNC0 <= f < _MOTOR_FUNC0 + _MAX_ROTORS]
    if funcs:
        return len(set(funcs)), "PWM_*_FUNCn motor functions"
    mt = _pint(params, "MAV_TYPE", -1)
    if mt in _MAV_TYPE_MOTORS:
        return _MAV_TYPE_MOTORS[mt], f"MAV_TYPE {mt}"
    if am is not None:
        c = am.arr("control", 12) if am.has("control[11]") else None
        if c is not None:
            used = np.flatnonzero(np.any(np.isfinite(c) & (c != 0), axis=0))
            if used.size:
                return int(used.max()) + 1, "actuator_motors channels in use"
    return 4, "default (quad)"


def _motor_channels_from_functions(params: dict[str, float], n: int) -> dict[int, tuple[str, int, int]]:
    """motor index -> (bank 'MAIN'/'AUX', instance, channel) from output functions."""
    out: dict[int, tuple[str, int, int]] = {}
    for bank, inst in (("MAIN", 0), ("AUX", 1)):
        for ch in range(1, 17):
            f = _pint(params, f"PWM_{bank}_FUNC{ch}", -1)
            if f < 0:
                continue
            m = f - _MOTOR_FUNC0
            if 0 <= m < n and m not in out:
                out[m] = (bank, inst, ch)
    return out


def _armed_at(topics: dict[tuple[str, int], _Topic], t_s: np.ndarray) -> np.ndarray | None:
    vs = _first_instance(topics, "vehicle_status")
    if vs is None or not vs.has("arming_state"):
        return None
    a = time_sync.interp_to(vs.t_s, (vs.col("arming_state") == 2).astype(float), t_s,
                            kind="previous")
    # before the first status sample the state is unknown: treat as armed (keep data)
    return np.where(np.isnan(a), 1.0, a) > 0.5


def _motors_from_pwm(
    topics: dict[tuple[str, int], _Topic], params: dict[str, float], n: int,
    warnings: list[str],
) -> Series | None:
    aos = {mid: tp for (nm, mid), tp in topics.items() if nm == "actuator_outputs"}
    if not aos:
        return None
    mapping = _motor_channels_from_functions(params, n)
    if len(mapping) == n:
        banks = {b for b, _, _ in mapping.values()}
        insts = {i for _, i, _ in mapping.values()}
        if len(insts) != 1:
            warnings.append("motors: output functions spread over MAIN and AUX; not supported, "
                            "no motors series")
            return None
        inst = insts.pop()
        bank = banks.pop()
        chans = [mapping[m][2] - 1 for m in range(n)]
        lo = np.array([params.get(f"PWM_{bank}_MIN{c + 1}", 1000.0) for c in chans])
        hi = np.array([params.get(f"PWM_{bank}_MAX{c + 1}", 2000.0) for c in chans])
        if inst not in aos or not _channels_vary(aos[inst], chans, topics):
            alt = [i for i in sorted(aos) if _channels_vary(aos[i], chans, topics)]
            if not alt:
                warnings.append(f"motors: PWM_{bank}_FUNCn name channels {chans} but no "
                                "actuator_outputs instance varies on them; no motors series")
                return None
            warnings.append(f"motors: expected PWM_{bank} on actuator_outputs[{inst}], "
                            f"used instance {alt[0]} whose channels {chans} vary")
            inst = alt[0]
        tp, lab = aos[inst], ""
        how = (f"PWM_{bank}_FUNCn; PWM_{bank}_MINn/MAXn "
               f"{'/'.join(f'{v:.0f}' for v in lo)}-{'/'.join(f'{v:.0f}' for v in hi)} us")
    else:
        inst, lab, tp, chans = _guess_motor_stream(aos, n, topics, legacy_topics.armed_floor(params), params)
        if inst is None or tp is None:
            warnings.append(f"motors: no actuator_outputs instance has {n} motor-like channels "
                            "(varying while armed, disarm value when disarmed); no motors series")
            return None
        bank = "MAIN" if inst == 0 else "AUX"
        armed = _armed_at(topics, tp.t_s)
        o = tp.arr("output", 16)[:, chans]
        # the mixer era's limits: PWM per PX4 version, or UAVCAN/DShot units
        lo, hi, how = legacy_topics.output_limits(params, bank, chans, o[armed] if armed is not None else o)
        tap = legacy_topics.tap_esc(params, o[~armed] if armed is not None else o[:0])
        if tap is not None and how.startswith("PX4 default"):
            lo, hi = (np.full(len(chans), v) for v in legacy_topics.TAP_ESC_RANGE)
            how = f"tap_esc RPMMIN-RPMMAX 1200-1900 ({tap})"
        unscaled = legacy_topics.not_driver_scaled(o[armed] if armed is not None else o, lo, hi)
        if unscaled is not None:
            lo, hi = (np.full(len(chans), v) for v in legacy_topics.PWM_DEFAULT)
            how = unscaled + f" (not {how})"
            warnings.append(f"motors: {unscaled}")
        why = (f"output-function parameters map only {len(mapping)} of {n} motors" if mapping
               else "no output-function parameters")
        warnings.append(f"motors: {why}; channels {chans} of actuator_outputs[{inst}]{lab} chosen "
                        f"as the {n} motor-like channels")
        if lab:
            warnings.append(f"motors: actuator_outputs[{inst}] carries interleaved publishers (noutputs "
                            f"differs); the motors are the samples{lab}")
    pwm = tp.arr("output", 16)[:, chans]
    u = (pwm - lo) / (hi - lo)
    stopped = (pwm < lo - 1.0) | (pwm > hi + 1.0) | ~np.isfinite(pwm)
    armed = _armed_at(topics, tp.t_s)
    if armed is not None:
        stopped |= ~armed[:, None]
    u = np.clip(u, 0.0, 1.0)
    fac = float(params.get("THR_MDL_FAC", 0.0))
    if fac != 0.0:
        # PX4 inverts the thrust model before output scaling; undo it so the value
        # is the normalised thrust command, like actuator_motors.control
        u = fac * u * u + (1.0 - fac) * u
        how += f"; THR_MDL_FAC {fac:g} undone"
    u = np.where(stopped, np.nan, u)
    src = f"actuator_outputs[{inst}]{lab}.output[{','.join(str(c) for c in chans)}] ({how})"
    return _series("motors", tp.t_s, u, src)


def _undo_mixer_idle(out: dict[str, Series], warnings: list[str]) -> None:
    """Mixer-era motor outputs of a mixer file with an idle speed (legacy_topics.mixer_idle) mapped
    back to the mixer's thrust command, ``(u - idle) / (1 - idle)``, as actuator_motors would be."""
    m, thr = out.get("motors"), out.get("throttle")
    if m is None or thr is None or not m.source.startswith("actuator_outputs"):
        return
    flag = out["landed"] if "landed" in out else out.get("armed")
    if flag is None or len(flag) == 0:
        return
    air = _true_intervals(flag.t_s, flag.values[:, 0] < 0.5 if "landed" in out else flag.values[:, 0] > 0.5,
                          float(m.t_s[-1]))
    found = legacy_topics.mixer_idle(m, thr, air)
    if found is None:
        return
    idle, how = found
    u = np.clip((m.values - idle) / (1.0 - idle), 0.0, 1.0)
    out["motors"] = Series(m.t_s, u, m.units, m.frame, f"{m.source[:-1]}; {how})", m.interp)
    warnings.append(f"motors: {how}")


# Two modules publishing one topic instance: uORB's ``orb_advertise`` is ``orb_advertise_multi`` with
# instance 0, and "any number of advertisers may publish to a topic" (uORB.h), so a custom control module
# that advertises ``actuator_outputs`` shares instance 0 with PX4's output driver and the logger writes
# both, interleaved.  PX4's drivers fill ``noutputs``; a second publisher that leaves it 0 (RflyBUAA's
# PX4 1.8 degraded-control build: its motor commands at noutputs 0 between the driver's constant
# 1500 us at noutputs 4) is told apart by it.  A publisher is a ``noutputs`` value held by at least
# PUBLISHER_MIN_FRACTION of the samples; the instance is split when such publishers alternate at least
# PUBLISHER_MIN_SWITCHES times (a driver whose noutputs changes once, at mixer load, is one publisher).
PUBLISHER_MIN_FRACTION = 0.1
PUBLISHER_MIN_SWITCHES = 10


def _output_publishers(tp: _Topic) -> list[tuple[str, _Topic]]:
    """An ``actuator_outputs`` instance as its publishers: ``[("", tp)]`` for one publisher, else one
    ``(" (noutputs k)", samples)`` per interleaved publisher (see PUBLISHER_MIN_SWITCHES)."""
    if not tp.has("noutputs") or tp.t_us.size < 2:
        return [("", tp)]
    n = tp.col("noutputs")
    vals, counts = np.unique(n[np.isfinite(n)], return_counts=True)
    pubs = vals[counts >= PUBLISHER_MIN_FRACTION * n.size]
    if pubs.size < 2:
        return [("", tp)]
    main = np.isin(n, pubs)
    if int(np.sum(np.diff(n[main]) != 0)) < PUBLISHER_MIN_SWITCHES:
        return [("", tp)]
    return [(f" (noutputs {int(v)})", tp.subset(n == v)) for v in pubs]


def _output_streams(aos: dict[int, _Topic]) -> list[tuple[int, str, _Topic]]:
    """Every publisher of every ``actuator_outputs`` instance, lowest instance first:
    ``(instance, label, samples)`` (:func:`_output_publishers`)."""
    return [(inst, lab, sub) for inst in sorted(aos) for lab, sub in _output_publishers(aos[inst])]


def moving_motor_outputs(topics: dict[tuple[str, int], _Topic]) -> tuple[int, str] | None:
    """How many motor outputs move while armed: ``actuator_motors.control[0..11]`` channels whose
    armed values range (max - min) over more than 0.001 (PX4 >= 1.13 with control allocation), else the
    channels of the ``actuator_outputs`` instance with the most of them (the mixer's outputs: channel i =
    mixer row i) whose armed value ranges over more than 5 (us of PWM; unused channels sit at the
    disarmed value).  None when neither topic is logged."""
    am = _first_instance(topics, "actuator_motors")
    if am is not None and am.has("control[0]"):
        k = next(i for i in range(17) if i == 16 or not am.has(f"control[{i}]"))
        c = am.arr("control", k)
        return _count_moving(topics, am.t_s, c, 1e-3), "actuator_motors.control"
    # the mixer era: the instance whose channels move most (MAIN is instance 0 on most boards, but on
    # Pixhawks with an IO co-processor or UAVCAN ESCs the mixer's outputs may be another instance)
    best: tuple[int, str] | None = None
    aos = {mid: tp for (name, mid), tp in topics.items() if name == "actuator_outputs"}
    for mid, lab, ao in _output_streams(aos):
        if not ao.has("output[0]"):
            continue
        k = next(i for i in range(17) if i == 16 or not ao.has(f"output[{i}]"))
        m = _count_moving(topics, ao.t_s, ao.arr("output", k), 5.0)
        if best is None or m > best[0]:
            best = (m, f"actuator_outputs[{mid}].output{lab}")
    return best


def _count_moving(topics: dict[tuple[str, int], _Topic], t: np.ndarray, c: np.ndarray, thr: float) -> int:
    armed = _armed_at(topics, t)
    if armed is not None and armed.any():
        c = c[armed]
    return int(np.sum(_keeps_moving(c, thr)))


# A motor output follows the controller: while armed it keeps changing (a motor pinned at a bound for most
# of a saturated flight still changes on a few % of the samples).  A servo or gimbal channel stepped to its
# centre (0 -> 1500 us) and held there changes on one sample (C8).
MOTOR_CHANGE_FRACTION = 0.02
MOTOR_MIN_CHANGES = 10


def _keeps_moving(c: np.ndarray, thr: float) -> np.ndarray:
    """Per column of ``c`` (samples x channels, armed samples): True where the finite values range over
    more than ``thr`` and change (by more than thr/10) at least MOTOR_MIN_CHANGES times and on at least
    MOTOR_CHANGE_FRACTION of the consecutive finite samples."""
    out = np.zeros(c.shape[1], bool)
    for j in range(c.shape[1]):
        v = c[np.isfinite(c[:, j]), j]
        if v.size < 3 or np.ptp(v) <= thr:
            continue
        ch = np.abs(np.diff(v)) > thr / 10.0
        out[j] = ch.sum() >= MOTOR_MIN_CHANGES and ch.mean() >= MOTOR_CHANGE_FRACTION
    return out


def _channels_vary(tp: _Topic, chans: list[int], topics: dict[tuple[str, int], _Topic]) -> bool:
    if not tp.has("output[15]"):
        return False
    o = tp.arr("output", 16)[:, chans]
    armed = _armed_at(topics, tp.t_s)
    if armed is not None and armed.any():
        o = o[armed]
    return bool(o.shape[0] > 1 and np.all(_keeps_moving(o, 5.0)))


def _guess_motor_stream(
    aos: dict[int, _Topic], n: int, topics: dict[tuple[str, int], _Topic], floor: float = 800.0,
    params: dict[str, float] | None = None,
) -> tuple[int | None, str, _Topic | None, list[int]]:
    """The mixer era's motor channels: in the first ``actuator_outputs`` publisher (:func:`_output_streams`)
    that has ``n`` of them, the first ``n`` channels that keep moving while armed (:func:`_keeps_moving`),
    stay at or above ``floor`` while armed and rest, while disarmed, at or below their armed range (the
    disarmed/idle value: 900 or 1000 us PWM_DISARMED, 1190 us on tap_esc; any value, not a fixed
    threshold) or exactly (1 us) at the disarmed value the log's parameters give PX4's driver for that
    channel (:func:`legacy_topics.disarmed_pwm`: a PWM_DISARMED set mid-range, a reversible ESC's 1500 us),
    wherever that lies.  Returns ``(instance, publisher label, its samples, channels)``."""
    for inst, lab, tp in _output_streams(aos):
        if not tp.has("output[15]"):
            continue
        o = tp.arr("output", 16)
        armed = _armed_at(topics, tp.t_s)
        if armed is None:
            armed = np.ones(o.shape[0], bool)
        oa = o[armed] if armed.any() else o
        od = o[~armed]
        with np.errstate(invalid="ignore"), _pywarnings.catch_warnings():
            _pywarnings.simplefilter("ignore", RuntimeWarning)
            moving = _keeps_moving(oa, 5.0)
            in_range = np.nanmin(oa, axis=0) >= floor if oa.size else np.zeros(16, bool)
            armed_low = np.nanpercentile(oa, 5, axis=0) if oa.size else np.full(16, np.nan)
            rest_high = np.nanmax(od, axis=0) if od.shape[0] else np.full(16, -np.inf)
            rests_low = ~(rest_high > armed_low + 5.0)
            if params is not None and od.shape[0]:
                dis = legacy_topics.disarmed_pwm(params, "MAIN" if inst == 0 else "AUX")[0]
                rest_low_v = np.nanmin(od, axis=0)
                rests_low |= (np.abs(rest_high - dis) <= 1.0) & (np.abs(rest_low_v - dis) <= 1.0)
        good = np.flatnonzero(moving & in_range & rests_low)
        if good.size >= n:
            return inst, lab, tp, [int(c) for c in good[:n]]
    return None, "", None, []


_EARTH_R_M = 6371000.0


def _gps_enu(gp: _Topic | None, lpos: _Topic | None) -> Series | None:
    """``vehicle_gps_position`` lat/lon (1e-7 deg ints, or ``latitude_deg``/``longitude_deg`` in PX4 >= 1.15)
    as east/north metres about ``vehicle_local_position.ref_lat/ref_lon`` (the EKF origin at each fix's time;
    equirectangular, < 0.1 % off within 10 km); up is NaN (the EKF's height is baro-referenced); NaN
    without a 3D fix (``fix_type`` < 3)."""
    if gp is None or lpos is None or not lpos.has("ref_lat", "ref_lon") or len(gp.t_us) < 2:
        return None
    if gp.has("latitude_deg", "longitude_deg"):
        lat, lon, src = gp.col("latitude_deg"), gp.col("longitude_deg"), "latitude_deg, longitude_deg"
    elif gp.has("lat", "lon"):
        lat, lon, src = gp.col("lat") * 1e-7, gp.col("lon") * 1e-7, "lat, lon"
    else:
        return None
    ref_ok = (lpos.col("ref_lat") != 0.0) | (lpos.col("ref_lon") != 0.0)
    if not ref_ok.any():
        return None
    lt, rl = lpos.t_s[ref_ok], lpos.subset(ref_ok)
    rlat = time_sync.interp_to(lt, rl.col("ref_lat"), gp.t_s, kind="previous")
    rlon = time_sync.interp_to(lt, rl.col("ref_lon"), gp.t_s, kind="previous")
    north = np.radians(lat - rlat) * _EARTH_R_M
    east = np.radians(lon - rlon) * _EARTH_R_M * np.cos(np.radians(rlat))
    fix = gp.col("fix_type") >= 3 if gp.has("fix_type") else np.ones(len(lat), bool)
    ok = fix & np.isfinite(north) & np.isfinite(east) & (np.abs(north) < 1e6) & (np.abs(east) < 1e6)
    v = np.column_stack([np.where(ok, east, np.nan), np.where(ok, north, np.nan), np.full(len(lat), np.nan)])
    return _series("gps_position_enu", gp.t_s, v, f"vehicle_gps_position.{src} about vehicle_local_position."
                                                  "ref_lat/ref_lon (fix_type >= 3)")


def _lpos_series(tp: _Topic, prefix: str, out: dict[str, Series], warnings: list[str],
                 source: str) -> None:
    t = tp.t_s
    if tp.has("x", "y", "z"):
        p = tp.cols(["x", "y", "z"])
        if tp.has("xy_valid"):
            p[tp.col("xy_valid") == 0, :2] = np.nan
        if tp.has("z_valid"):
            p[tp.col("z_valid") == 0, 2] = np.nan
        out[f"{prefix}position_enu"] = _series(f"{prefix}position_enu", t, frames.ned_to_enu(p),
                                               f"{source}.x,y,z (NED)")
    if tp.has("vx", "vy", "vz"):
        v = tp.cols(["vx", "vy", "vz"])
        if tp.has("v_xy_valid"):
            v[tp.col("v_xy_valid") == 0, :2] = np.nan
        if tp.has("v_z_valid"):
            v[tp.col("v_z_valid") == 0, 2] = np.nan
        out[f"{prefix}velocity_enu"] = _series(f"{prefix}velocity_enu", t, frames.ned_to_enu(v),
                                               f"{source}.vx,vy,vz (NED)")
    if not prefix and tp.has("dist_bottom"):
        # height above ground from the downward distance sensor (PX4 sets dist_bottom_valid)
        h = tp.col("dist_bottom").astype(float).copy()
        if tp.has("dist_bottom_valid"):
            h[tp.col("dist_bottom_valid") == 0] = np.nan
        if np.isfinite(h).sum() > 10:
            out["height_agl"] = _series("height_agl", t, h[:, None], f"{source}.dist_bottom")
    if not prefix and tp.has("ax", "ay", "az"):
        a = tp.cols(["ax", "ay", "az"])
        out["accel_enu"] = _series("accel_enu", t, frames.ned_to_enu(a), f"{source}.ax,ay,az (NED)")
    if not prefix:
        for f in ("xy_valid", "z_valid"):
            if tp.has(f):
                bad = tp.col(f) == 0
                if bad.any():
                    warnings.append(f"{source}.{f} false for {int(bad.sum())} of {bad.size} samples "
                                    f"({t[bad][0]:.1f}-{t[bad][-1]:.1f} s): NaN there")
        for f in ("xy_reset_counter", "z_reset_counter"):
            if tp.has(f):
                c = tp.col(f)
                jumps = np.flatnonzero(np.diff(c) != 0) + 1
                if jumps.size:
                    warnings.append(f"{source}.{f}: EKF reset at t = "
                                    f"{', '.join(f'{t[j]:.1f}' for j in jumps)} s (position jumps)")


def _quat_series(name: str, tp: _Topic, source: str) -> Series | None:
    if not tp.has("q[0]", "q[1]", "q[2]", "q[3]"):
        return None
    raw = tp.arr("q", 4)
    q = frames.quat_make_continuous(frames.q_ned_frd_to_enu_flu(raw))
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.linalg.norm(np.where(np.isinf(raw), 0.0, raw), axis=1)
    # the conversion normalises: a row that is no unit quaternion (all zero, +-inf, a corrupt scale)
    # keeps its raw values so that _check_values sees it and drops or refuses it
    off = np.any(np.isinf(raw), axis=1) | (np.isfinite(norm) & (np.abs(norm - 1.0) > _QUAT_NORM_TOL))
    q[off] = raw[off]
    return _series(name, tp.t_s, q, f"{source}.q (FRD->NED)")


def _yaw_from_attitude_setpoint(att: _Topic | None, ts: _Topic, out: dict[str, Series]) -> None:
    """The yaw setpoint and its feed-forward from ``vehicle_attitude_setpoint`` where it is logged
    faster than ``trajectory_setpoint`` (PX4's default logger: 20 Hz against 5 Hz).

    In the position-controlled modes ``mc_pos_control`` passes the trajectory's yaw and yawspeed
    through unchanged (``PositionControl::getAttitudeSetpoint``: ``yaw_body`` = the setpoint's yaw,
    ``yaw_sp_move_rate`` = its yawspeed); the 5 Hz subsample of a 45 deg/s yaw ramp misses where
    the ramp ends by up to 9 deg, so a twin carrying the last sample by its feed-forward turned past
    the end and back.  Used while the trajectory's own yaw is finite.

    Where the trajectory's yaw is NaN and its yawspeed finite (a rate-only yaw: the pilot's yaw stick in
    POSCTL, FlightTaskAutoFollowTarget, a take-off), ``PositionControl`` holds the heading the vehicle has
    (``_yaw_sp = _yaw``) and the vehicle turns by the feed-forward alone, at the controller rate.  The yaw
    setpoint stays NaN there (the twin holds its own heading, as PX4); its feed-forward is the mean of PX4's
    over each interval between two attitude setpoint samples: the slope of ``yaw_body`` (the heading PX4 held
    at each) to the next, where the logged feed-forward around the interval can explain it
    (:func:`_rate_only_slope`); elsewhere the vehicle turned by something else (an overloaded Quad X out of
    yaw authority spins against a zero or opposite yawspeed: ZweiterFlugtag log_30, log_38), and the logged
    feed-forward is kept.  The logged yawspeed is one instant of a
    signal that swings +-160 deg/s sample to sample on the Mantis follow flights (2.4 Hz); a twin
    integrating those samples random-walked 90 deg off its vehicle's heading (mantis_follow_00018).
    Elsewhere (both NaN) PX4 holds its last yaw setpoint, or a manual mode makes the attitude setpoint
    from the sticks."""
    if att is None or not att.has("yaw_sp_move_rate") or not ts.has("yaw") or len(att.t_us) < 2:
        return
    if att.has("yaw_body"):
        yaw_ned, field = att.col("yaw_body"), "yaw_body"
    elif att.has("q_d[0]", "q_d[1]", "q_d[2]", "q_d[3]"):  # PX4 >= 1.15 dropped yaw_body: the yaw of q_d
        yaw_ned, field = frames.euler_from_quat(att.arr("q_d", 4))[:, 2], "q_d (its yaw)"
    else:
        return
    if len(att.t_us) <= 1.5 * len(ts.t_us):
        return
    t = att.t_s
    j = np.searchsorted(ts.t_us, att.t_us, side="right") - 1
    jc = np.clip(j, 0, None)
    controlled = (j >= 0) & np.isfinite(ts.col("yaw")[jc])
    rate_only = np.zeros(t.shape, bool)
    if ts.has("yawspeed"):
        rate_only = (j >= 0) & ~controlled & np.isfinite(ts.col("yawspeed")[jc])
    heading = frames.yaw_ned_to_enu(yaw_ned)
    yaw = np.where(controlled, heading, np.nan)
    rate = np.where(controlled | rate_only, frames.yawspeed_ned_to_enu(att.col("yaw_sp_move_rate")), np.nan)
    if not (np.isfinite(yaw).any() or rate_only.any()):
        return
    n_slope = _rate_only_slope(t, heading, rate, rate_only)
    out["setpoint_yaw_enu"] = _series("setpoint_yaw_enu", t, yaw,
                                      f"vehicle_attitude_setpoint.{field} (NED heading) where "
                                      "trajectory_setpoint.yaw is finite")
    out["setpoint_yawspeed"] = _series("setpoint_yawspeed", t, rate,
                                       "vehicle_attitude_setpoint.yaw_sp_move_rate (NED heading rate) where "
                                       "trajectory_setpoint.yaw or .yawspeed is finite" + (
                                           f"; where only its yawspeed is (rate-only yaw), {n_slope} samples: the "
                                           f"slope of {field} to the next sample" if n_slope else ""))


#: a rate-only yaw's feed-forward is the slope to the next attitude setpoint sample only within this [s]
RATE_ONLY_SLOPE_MAX_S = 0.5


def _rate_only_slope(t: np.ndarray, heading: np.ndarray, rate: np.ndarray, rate_only: np.ndarray) -> int:
    """In place: ``rate`` (the logged feed-forward, ENU yaw rate, rad/s) where the yaw is rate-only (trajectory
    yaw NaN, yawspeed finite) replaced by the slope of the logged ``heading`` (ENU, rad) to the next rate-only
    sample within :data:`RATE_ONLY_SLOPE_MAX_S` (the heading change over the interval, wrapped, over its length:
    the mean of PX4's feed-forward there), where that slope lies within the range of the logged feed-forward
    at the interval's two samples and their neighbours (what PX4 fed forward can explain the turn; a vehicle
    spinning out of yaw authority against a zero or opposite yawspeed keeps the logged one).  The number of
    samples replaced."""
    if len(t) < 2:
        return 0
    dt = np.diff(t)
    dyaw = np.angle(np.exp(1j * np.diff(heading)))
    ok = rate_only[:-1] & rate_only[1:] & (dt > 0) & (dt <= RATE_ONLY_SLOPE_MAX_S) & np.isfinite(dyaw)
    k = np.flatnonzero(ok)
    slope = dyaw[k] / dt[k]
    n = len(t)
    near = np.column_stack([rate[np.clip(k + d, 0, n - 1)] for d in (-1, 0, 1, 2)])
    with np.errstate(invalid="ignore"):
        inside = (slope >= np.nanmin(near, axis=1)) & (slope <= np.nanmax(near, axis=1))
    k = k[inside]
    rate[k] = slope[inside]
    return int(k.size)


#: offboard_control_mode flags, in the order of the ``offboard_mode`` series' columns (older PX4 names
#: the last one ``actuator``; ``thrust_and_torque``/``direct_actuator`` since 1.14)
_OFFBOARD_FLAGS = ("position", "velocity", "acceleration", "attitude", "body_rate", "thrust_and_torque")


def _specific_force_not_aliased(out: dict[str, Series], params: dict[str, float], warnings: list[str]) -> None:
    """Where the logged accelerometer is sampled slower than twice PX4's accelerometer low-pass (the default
    logger profile of PX4 1.8-1.10: every 100 ms), its samples alias the vibration into the slow specific
    force every thrust fit reads; the specific force is then the estimated velocity's derivative plus gravity
    in the body (:mod:`twin_nodes.logs.imu_rate`), said in the series' source and a warning."""
    sf, vel, q = out.get("specific_force_flu"), out.get("velocity_enu"), out.get("attitude_q")
    if sf is None or vel is None or q is None:
        return
    aliased, rate, cut = imu_rate.accel_aliased(sf.t_s, params)
    if not aliased:
        return
    t, f = imu_rate.specific_force_from_velocity(vel.t_s, vel.values, q.at)
    if t.size < 10:
        return
    why = (f"sensor_combined.accelerometer logged at {rate:.1f} Hz, below twice IMU_ACCEL_CUTOFF {cut:g} Hz: "
           "aliased vibration")
    out["specific_force_flu"] = _series("specific_force_flu", t, f,
                                        f"d/dt {vel.source} + gravity, rotated by {q.source} ({why})")
    warnings.append(f"specific_force_flu: {why}; taken from the estimated velocity's derivative instead")


def _mode_setpoint_series(get: Any, out: dict[str, Series]) -> None:
    """The setpoints PX4 flies in the modes without a position controller (kept apart from the state
    and actuator reading): ``vehicle_attitude_setpoint`` (``q_d``: the pilot's attitude in
    MANUAL/STABILIZED, the stick's tilt in ALTCTL, an offboard attitude; ``thrust_body[2]``, before
    PX4 1.12 ``thrust``; ``yaw_sp_move_rate``) and ``offboard_control_mode``'s flags.  Every sample,
    whatever the mode (the twin picks by ``nav_state``); the rate setpoint is ``setpoint_rates_flu``."""
    att = get("vehicle_attitude_setpoint")
    if att is not None and att.has("q_d[0]", "q_d[1]", "q_d[2]", "q_d[3]") and len(att.t_us):
        raw = att.arr("q_d", 4)
        with np.errstate(invalid="ignore"):
            ok = np.all(np.isfinite(raw), axis=1) & (np.abs(np.linalg.norm(raw, axis=1) - 1.0) < _QUAT_NORM_TOL)
        if att.has("q_d_valid"):  # PX4 <= 1.8: q_d only meant when flagged
            ok &= att.col("q_d_valid") != 0
        if ok.any():
            q = np.full(raw.shape, np.nan)
            q[ok] = frames.q_ned_frd_to_enu_flu(raw[ok])
            out["attitude_setpoint_q"] = _series("attitude_setpoint_q", att.t_s, q,
                                                 "vehicle_attitude_setpoint.q_d (FRD->NED)")
        if att.has("thrust_body[2]"):
            out["attitude_setpoint_thrust"] = _series("attitude_setpoint_thrust", att.t_s,
                                                      -att.col("thrust_body[2]"),
                                                      "-vehicle_attitude_setpoint.thrust_body[2]")
        elif att.has("thrust"):
            out["attitude_setpoint_thrust"] = _series("attitude_setpoint_thrust", att.t_s, att.col("thrust"),
                                                      "vehicle_attitude_setpoint.thrust")
        if att.has("yaw_sp_move_rate"):
            out["attitude_setpoint_yawrate"] = _series(
                "attitude_setpoint_yawrate", att.t_s, frames.yawspeed_ned_to_enu(att.col("yaw_sp_move_rate")),
                "vehicle_attitude_setpoint.yaw_sp_move_rate (NED heading rate)")
    ocm = get("offboard_control_mode")
    if ocm is not None and ocm.has("position", "velocity") and len(ocm.t_us):
        cols = []
        for f in _OFFBOARD_FLAGS:
            alt = {"thrust_and_torque": ("actuator", "direct_actuator")}.get(f, ())
            name = next((n for n in (f,) + alt if ocm.has(n)), None)
            cols.append(ocm.col(name).astype(float) if name else np.zeros(len(ocm.t_us)))
        out["offboard_mode"] = _series("offboard_mode", ocm.t_s, np.column_stack(cols),
                                       "offboard_control_mode." + ",".join(_OFFBOARD_FLAGS))


def _build_series(
    topics: dict[tuple[str, int], _Topic], params: dict[str, float], warnings: list[str],
) -> tuple[dict[str, Series], int]:
    out: dict[str, Series] = {}
    get = lambda n: _first_instance(topics, n)  # noqa: E731

    def missing(topic: str, what: str) -> None:
        warnings.append(f"no {topic} in log: {what} unavailable")

    # --- state estimate
    lpos = get("vehicle_local_position")
    if lpos is not None:
        _lpos_series(lpos, "", out, warnings, "vehicle_local_position")
    att = get("vehicle_attitude")
    s = _quat_series("attitude_q", att, "vehicle_attitude") if att is not None else None
    if s is not None:
        out["attitude_q"] = s
    else:
        missing("vehicle_attitude", "attitude_q")
    av = get("vehicle_angular_velocity")
    if av is not None and av.has("xyz[0]"):
        out["body_rates_flu"] = _series("body_rates_flu", av.t_s, frames.frd_to_flu(av.arr("xyz", 3)),
                                        "vehicle_angular_velocity.xyz (FRD)")
        if av.has("xyz_derivative[0]"):
            out["angular_accel_flu"] = _series(
                "angular_accel_flu", av.t_s, frames.frd_to_flu(av.arr("xyz_derivative", 3)),
                "vehicle_angular_velocity.xyz_derivative (FRD)")
    elif (old := legacy_topics.attitude_rates(att)) is not None:  # PX4 <= 1.9
        out["body_rates_flu"] = _series("body_rates_flu", old[0], frames.frd_to_flu(old[1]), old[2])
    else:
        missing("vehicle_angular_velocity", "body_rates_flu")

    # --- actuators
    am = get("actuator_motors")
    n_motors, n_src = _n_motors(params, am)
    if am is not None and am.has(f"control[{n_motors - 1}]"):
        u = am.arr("control", n_motors)
        armed = _armed_at(topics, am.t_s)
        if armed is not None:
            # PX4 logs 0 (not NaN) for disarmed motors on some versions/simulators
            u[~armed] = np.nan
        out["motors"] = _series("motors", am.t_s, u,
                                f"actuator_motors.control[0..{n_motors - 1}] (NaN while disarmed)")
    else:
        s = _motors_from_pwm(topics, params, n_motors, warnings)
        if s is not None:
            out["motors"] = s
        else:
            warnings.append("motors unavailable (no actuator_motors, no usable actuator_outputs)")
    thr = get("vehicle_thrust_setpoint")
    ac0 = get("actuator_controls_0")
    if thr is not None and thr.has("xyz[2]"):
        out["throttle"] = _series("throttle", thr.t_s, -thr.col("xyz[2]"),
                                  "-vehicle_thrust_setpoint.xyz[2]")
    elif ac0 is not None and ac0.has("control[3]"):
        out["throttle"] = _series("throttle", ac0.t_s, ac0.col("control[3]"),
                                  "actuator_controls_0.control[3]")
    elif ((rsp := get("vehicle_rates_setpoint")) is not None and rsp.has("thrust")
          and float(params.get("MC_BAT_SCALE_EN", 0.0)) == 0.0):
        # PX4 1.8-1.9 without actuator_controls_0 logged: mc_att_control writes control[3] = the rate
        # setpoint's thrust, times the battery scale only where MC_BAT_SCALE_EN is set
        out["throttle"] = _series("throttle", rsp.t_s, rsp.col("thrust"),
                                  "vehicle_rates_setpoint.thrust (= actuator_controls_0.control[3], "
                                  "MC_BAT_SCALE_EN 0; actuator_controls_0 not logged)")
    else:
        missing("vehicle_thrust_setpoint/actuator_controls_0", "throttle")
    tq = get("vehicle_torque_setpoint")
    if tq is not None and tq.has("xyz[0]"):
        out["torque_setpoint_flu"] = _series("torque_setpoint_flu", tq.t_s,
                                             frames.frd_to_flu(tq.arr("xyz", 3)),
                                             "vehicle_torque_setpoint.xyz (FRD)")
    elif (old := legacy_topics.controls_torque(ac0)) is not None:  # PX4 <= 1.13
        out["torque_setpoint_flu"] = _series("torque_setpoint_flu", old[0], frames.frd_to_flu(old[1]), old[2])
    # the rate loop's setpoint: smooth (the attitude loop's output), unlike the motor commands a
    # 50 Hz log picks from a 250 Hz loop; discovery uses it as an instrument (output_error)
    rs = get("vehicle_rates_setpoint")
    if rs is not None and rs.has("roll") and rs.has("pitch") and rs.has("yaw"):
        out["setpoint_rates_flu"] = _series("setpoint_rates_flu", rs.t_s, frames.frd_to_flu(
            np.column_stack([rs.col("roll"), rs.col("pitch"), rs.col("yaw")])), "vehicle_rates_setpoint (FRD)")

    # --- battery
    bat = get("battery_status")
    if bat is not None and bat.has("voltage_v"):
        v = bat.col("voltage_v")
        out["battery_v"] = _series("battery_v", bat.t_s, np.where(v > 0.1, v, np.nan),
                                   f"battery_status[{bat.multi_id}].voltage_v")
        if bat.has("current_a"):
            c = bat.col("current_a")
            c = np.where(np.isclose(c, -1.0), np.nan, c)
            out["battery_a"] = _series("battery_a", bat.t_s, c,
                                       f"battery_status[{bat.multi_id}].current_a")
    else:
        missing("battery_status", "battery_v, battery_a")

    # --- IMU
    sc = get("sensor_combined")
    if sc is not None and sc.has("gyro_rad[0]", "accelerometer_m_s2[0]"):
        out["gyro_flu"] = _series("gyro_flu", sc.t_s, frames.frd_to_flu(sc.arr("gyro_rad", 3)),
                                  "sensor_combined.gyro_rad (FRD)")
        ta = sc.t_us.astype(np.int64)
        acc = frames.frd_to_flu(sc.arr("accelerometer_m_s2", 3))
        if sc.has("accelerometer_timestamp_relative"):
            rel = sc.data["accelerometer_timestamp_relative"].astype(np.int64)
            # PX4's relative stamp is a few ms; INT32_MAX means invalid, anything beyond 1 s is corrupt
            ok = (rel != _INT32_MAX) & (np.abs(rel) < 1_000_000)
            ta = ta[ok] + rel[ok]
            acc = acc[ok]
        order = np.argsort(ta, kind="stable")
        ta, acc = ta[order], acc[order]
        keep = np.append(ta[1:] != ta[:-1], True) & (ta >= 0)
        out["specific_force_flu"] = _series("specific_force_flu", ta[keep] * 1e-6, acc[keep],
                                            "sensor_combined.accelerometer_m_s2 (FRD)")
        _specific_force_not_aliased(out, params, warnings)
    else:
        missing("sensor_combined", "gyro_flu, specific_force_flu")

    # --- setpoints (trajectory_setpoint; PX4 1.8: vehicle_local_position_setpoint; field names per
    # version in legacy_topics.setpoint_arrays)
    ts, ts_name = legacy_topics.setpoint_topic(get)
    if ts is not None:
        t = ts.t_s
        for key, (v, src) in legacy_topics.setpoint_arrays(ts, ts_name, lpos, params).items():
            name = {"position": "setpoint_position_enu", "velocity": "setpoint_velocity_enu",
                    "acceleration": "setpoint_accel_enu"}[key]
            out[name] = _series(name, t, frames.ned_to_enu(v), src)
        if ts.has("yaw"):
            out["setpoint_yaw_enu"] = _series("setpoint_yaw_enu", t,
                                              frames.yaw_ned_to_enu(ts.col("yaw")),
                                              f"{ts_name}.yaw (NED heading)")
        if ts.has("yawspeed"):
            out["setpoint_yawspeed"] = _series("setpoint_yawspeed", t,
                                               frames.yawspeed_ned_to_enu(ts.col("yawspeed")),
                                               f"{ts_name}.yawspeed (NED heading rate)")
        _yaw_from_attitude_setpoint(get("vehicle_attitude_setpoint"), ts, out)
        for k in ("setpoint_yaw_enu", "setpoint_yawspeed"):  # name the setpoint topic this PX4 logged
            if ts_name != "trajectory_setpoint" and k in out and "trajectory_setpoint" in out[k].source:
                s = out[k]
                out[k] = Series(s.t_s, s.values, s.units, s.frame, s.source.replace("trajectory_setpoint", ts_name),
                                s.interp)
    else:
        missing("trajectory_setpoint", "setpoint_*")

    # --- modes
    vs = get("vehicle_status")
    if vs is not None and vs.has("nav_state", "arming_state"):
        out["nav_state"] = _series("nav_state", vs.t_s, vs.col("nav_state"), "vehicle_status.nav_state")
        out["armed"] = _series("armed", vs.t_s, (vs.col("arming_state") == 2).astype(float),
                               "vehicle_status.arming_state == 2")
    else:
        missing("vehicle_status", "nav_state, armed")
    ld = get("vehicle_land_detected")
    if ld is not None and ld.has("landed"):
        out["landed"] = _series("landed", ld.t_s, (ld.col("landed") != 0).astype(float),
                                "vehicle_land_detected.landed")
    else:
        missing("vehicle_land_detected", "landed")
    if ld is not None and ld.has("landed"):
        flags = [(ld.col(k) != 0) if ld.has(k) else np.zeros(ld.t_s.size, bool)
                 for k in ("ground_contact", "maybe_landed", "landed")]
        out["land_detector"] = _series("land_detector", ld.t_s, np.column_stack(flags).astype(float),
                                       "vehicle_land_detected.ground_contact/maybe_landed/landed")

    # --- ESC telemetry, mapped by output function
    esc = get("esc_status")
    if esc is not None and esc.has("esc[0].esc_rpm"):
        n_slots = sum(1 for i in range(32) if esc.has(f"esc[{i}].esc_rpm"))
        rpm = np.full((esc.t_us.size, n_motors), np.nan)
        count = esc.col("esc_count") if esc.has("esc_count") else np.full(esc.t_us.size, n_slots)
        by_func = esc.has("esc[0].actuator_function")
        if not by_func:
            warnings.append("esc_status has no actuator_function (old PX4): esc[i] taken as Motor i+1")
        for i in range(n_slots):
            r = esc.col(f"esc[{i}].esc_rpm")
            m = (esc.col(f"esc[{i}].actuator_function") - _MOTOR_FUNC0 if by_func
                 else np.full(r.shape, float(i)))
            ok = (i < count) & (m >= 0) & (m < n_motors)
            rows = np.flatnonzero(ok)
            rpm[rows, m[ok].astype(int)] = r[ok]
        src = "esc_status.esc[].esc_rpm by " + ("actuator_function" if by_func else "index")
        out["esc_rpm"] = _series("esc_rpm", esc.t_s, rpm, src)

    hte = get("hover_thrust_estimate")
    if hte is not None and hte.has("hover_thrust"):
        h = hte.col("hover_thrust")
        if hte.has("valid"):
            h = np.where(hte.col("valid") != 0, h, np.nan)
        out["hover_thrust"] = _series("hover_thrust", hte.t_s, h,
                                      "hover_thrust_estimate.hover_thrust (NaN when not valid)")

    # --- the estimator's own innovation test ratios (> 1: the measurement was rejected; C9)
    es = get("estimator_status")
    if es is not None and es.has("vel_test_ratio", "pos_test_ratio", "hgt_test_ratio"):
        out["estimator_test_ratios"] = _series(
            "estimator_test_ratios", es.t_s, es.cols(["vel_test_ratio", "pos_test_ratio", "hgt_test_ratio"]),
            "estimator_status.vel_test_ratio, pos_test_ratio, hgt_test_ratio")

    # --- the GPS receiver's own position about the estimator's origin (C9: an independent check)
    gps = _gps_enu(get("vehicle_gps_position"), lpos)
    if gps is not None:
        out["gps_position_enu"] = gps

    # --- SITL ground truth
    gl = get("vehicle_local_position_groundtruth")
    if gl is not None:
        _lpos_series(gl, "groundtruth_", out, warnings, "vehicle_local_position_groundtruth")
    ga = get("vehicle_attitude_groundtruth")
    if ga is not None:
        s = _quat_series("groundtruth_attitude_q", ga, "vehicle_attitude_groundtruth")
        if s is not None:
            out["groundtruth_attitude_q"] = s
    gw = get("vehicle_angular_velocity_groundtruth")
    if gw is not None and gw.has("xyz[0]"):
        out["groundtruth_body_rates_flu"] = _series(
            "groundtruth_body_rates_flu", gw.t_s, frames.frd_to_flu(gw.arr("xyz", 3)),
            "vehicle_angular_velocity_groundtruth.xyz (FRD)")

    _undo_mixer_idle(out, warnings)  # needs landed/armed
    _mode_setpoint_series(get, out)
    if n_src.startswith("default"):
        warnings.append(f"n_motors = {n_motors}: no CA_ROTOR_COUNT, output functions or MAV_TYPE")
    return out, n_motors


#: series -> largest physical magnitude of any component (what enters beyond it is corrupt): positions
#: within ~1e6 m of the EKF origin, speeds ~200 m/s, normalised commands within +-1 (1.5 with margin), rates
#: of a gyro's range, specific force of an IMU's
VALUE_LIMITS: dict[str, tuple[float, str]] = {
    "position_enu": (1e6, "positions within 1e6 m of the EKF origin"),
    "groundtruth_position_enu": (1e6, "positions within 1e6 m of the origin"),
    "setpoint_position_enu": (1e6, "positions within 1e6 m of the EKF origin"),
    "velocity_enu": (200.0, "speeds up to 200 m/s per axis"),
    "groundtruth_velocity_enu": (200.0, "speeds up to 200 m/s per axis"),
    "setpoint_velocity_enu": (200.0, "speeds up to 200 m/s per axis"),
    "motors": (1.5, "normalised motor outputs in [-1, 1] (NaN = stopped)"),
    "throttle": (1.5, "a normalised collective thrust in [-1, 1]"),
    "body_rates_flu": (100.0, "body rates up to 100 rad/s"),
    "groundtruth_body_rates_flu": (100.0, "body rates up to 100 rad/s"),
    "gyro_flu": (100.0, "gyro rates up to 100 rad/s"),
    "specific_force_flu": (2000.0, "specific force up to 2000 m/s^2"),
}
#: quaternion series: rows whose norm is this far from 1 (or zero) are corrupt
_QUAT_SERIES = ("attitude_q", "groundtruth_attitude_q")
_QUAT_NORM_TOL = 0.1
#: series no twin needs (a log without them flies): when corrupt they are left out with a warning, not
#: refused (PX4 1.13.2 logs battery_status.current_a = -inf without a current sensor)
_OPTIONAL_SERIES = ("battery_v", "battery_a", "esc_rpm", "height_agl", "hover_thrust", "estimator_test_ratios",
                    "gps_position_enu")
#: more than this fraction of a series' samples corrupt: the series is refused, not repaired
_MAX_BAD_FRACTION = 0.5


def _check_values(path: str, series: dict[str, Series], warnings: list[str]) -> None:
    """Every value read from the log checked where it enters: rows with +-inf, out of their physical
    range (:data:`VALUE_LIMITS`) or non-unit/zero quaternions are dropped with one warning per series;
    when more than half of a series is bad it is refused (:class:`LogError` naming the file, the PX4
    topic/field and what was expected).  NaN is left alone: it means unknown/stopped in PX4 logs."""
    for name, s in list(series.items()):
        n = len(s)
        if n == 0:
            continue
        v = s.values
        field_ = s.source.split(" (")[0]
        with np.errstate(invalid="ignore", over="ignore"):
            inf = np.any(np.isinf(v), axis=1)
            if name in _QUAT_SERIES:
                norm = np.linalg.norm(np.where(np.isinf(v), 0.0, v), axis=1)
                out = ~inf & np.isfinite(norm) & (np.abs(norm - 1.0) > _QUAT_NORM_TOL)
                expected = "unit quaternions [w, x, y, z] (norm 1)"
                worst = (f"norms {np.nanmin(norm[out]):.3g}..{np.nanmax(norm[out]):.3g}"
                         + (", all zero" if np.all(norm[out] == 0) else "")) if out.any() else ""
            elif name in VALUE_LIMITS:
                lim, expected = VALUE_LIMITS[name]
                mag = np.where(np.isfinite(v), np.abs(v), 0.0)
                out = ~inf & np.any(mag > lim, axis=1)
                worst = f"up to {float(mag[out].max()):.4g}" if out.any() else ""
            else:
                out = np.zeros(n, bool)
                expected, worst = "finite values", ""
        bad = inf | out
        n_bad = int(bad.sum())
        if n_bad == 0:
            continue
        what = []
        if inf.any():
            what.append(f"{int(inf.sum())} not finite (+-inf)")
        if out.any():
            what.append(f"{int(out.sum())} out of range ({worst})")
        if n_bad > _MAX_BAD_FRACTION * n or n - n_bad < 2:
            if name in _OPTIONAL_SERIES:  # nothing flies on it: left out, said
                warnings.append(f"{name} ({field_}): left out, {n_bad} of {n} samples are not "
                                f"{expected}: " + ", ".join(what))
                del series[name]
                continue
            raise LogError(path, field_, f"expected {expected}; {n_bad} of {n} samples are not: "
                                         + ", ".join(what))
        t = s.t_s[bad]
        warnings.append(f"{name} ({field_}): dropped {n_bad} of {n} samples, " + ", ".join(what)
                        + f", at t = {t[0]:.2f}..{t[-1]:.2f} s (expected {expected})")
        series[name] = Series(s.t_s[~bad], v[~bad], s.units, s.frame, s.source, s.interp)


def read_ulog(path: str | os.PathLike[str]) -> FlightLog:
    """Load a PX4 ULog as a :class:`FlightLog` in ROS frames (see module docstring).

    Raises :class:`LogError` (``<file>: <what>: <expected>``) when the file is
    missing, not a ULog, has an unreadable definitions section, or has no
    ``vehicle_local_position`` samples.  Missing optional topics only add a
    warning."""
    p = Path(path)
    ulog, pyulog_out, cut_at = _open_ulog(p, list(TOPICS))
    topics, warnings, shift = _load_topics(ulog)
    if ulog.file_corruption:
        warnings.insert(0, "pyulog detected file corruption; data after it may be missing")
    if cut_at is not None:
        warnings.insert(0, f"file truncated: the record at byte {cut_at} of {p.stat().st_size} is cut "
                           "short by the end of the file; anything logged after it is missing")
    for line in pyulog_out.splitlines():
        if line.strip():
            warnings.append(f"pyulog: {line.strip()}")
    if _first_instance(topics, "vehicle_local_position") is None:
        names = sorted({n for n, _ in topics})
        found = (f"found topics: {', '.join(names)}" if names else
                 f"found no data messages at all (file of {p.stat().st_size} bytes: "
                 "truncated in its definitions section or empty)")
        raise LogError(str(p), "vehicle_local_position",
                       f"expected at least one sample after the log start (a PX4 flight log); {found}")
    params = _ulog_params(ulog)
    series, n_motors = _build_series(topics, params, warnings)
    _check_values(str(p), series, warnings)
    info = {str(k): (v if isinstance(v, str) else str(v)) for k, v in ulog.msg_info_dict.items()}
    try:
        rel = ulog.get_version_info_str()
    except (TypeError, ValueError, IndexError, KeyError):  # a corrupt ver_sw_release
        rel = None
    if rel:
        info.setdefault("ver_sw_release_str", rel)
    duration = max((float(s.t_s[-1]) for s in series.values() if len(s)), default=0.0)
    start = int(ulog.start_timestamp) + shift
    changes = [(max(0.0, (int(t) - start) * 1e-6), str(n), _float(v))
               for t, n, v in ulog.changed_parameters]
    log = FlightLog(path=str(p), start_us=start, duration_s=duration, params=params, info=info,
                    series=series, warnings=warnings, n_motors=n_motors, param_changes=changes,
                    moving_outputs=moving_motor_outputs(topics))
    for w in log.data_warnings():
        LOG.warning("%s: %s", p, w)
    return log


def list_topics(path: str | os.PathLike[str]) -> list[tuple[str, int, int, float]]:
    """Every logged topic instance as ``(name, multi_id, n_msgs, rate_hz)``, sorted.

    ``n_msgs`` counts every message in the file (for replay/recording count
    checks); ``rate_hz`` = (n - 1) / span over the samples inside the log
    (pre-start and stray-late samples excluded; 0.0 for fewer than 2)."""
    p = Path(path)
    ulog, _, _ = _open_ulog(p, None)
    topics, _, _ = _load_topics(ulog)
    out = []
    for d in ulog.data_list:
        n = int(len(d.data["timestamp"])) if "timestamp" in d.data else 0
        tp = topics.get((d.name, d.multi_id))
        rate = 0.0
        if tp is not None and tp.t_us.size > 1 and tp.t_us[-1] > tp.t_us[0]:
            rate = (tp.t_us.size - 1) / ((tp.t_us[-1] - tp.t_us[0]) * 1e-6)
        out.append((d.name, int(d.multi_id), n, float(rate)))
    return sorted(out)


def read_params(path: str | os.PathLike[str]) -> dict[str, float]:
    """The log's PX4 parameters at start (header only: fast on any log size)."""
    p = Path(path)
    if not p.is_file():
        raise LogError(str(p), "<file>", "an existing PX4 ULog file")
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            from pyulog import ULog

            u = ULog(str(p), parse_header_only=True)
        except Exception as exc:  # pyulog raises anything on a bad header
            raise LogError(str(p), "<header>", f"a PX4 ULog file ({type(exc).__name__}: {exc})") from None
    return _ulog_params(u)
