"""Is this log a flight a command can use?  One check, shared by every command that loads a flight.

:func:`check_flyable` refuses, with one :class:`~twin_nodes.base.errors.LogError` line saying which,
the logs that load but are no usable flight:

- **too short**: fewer than 2 position samples, or less than :data:`MIN_LOG_S` of them (a log cut
  right after its start, a 1-sample log), or airborne for less than :data:`MIN_AIRBORNE_S` in all;
- **never airborne**: no airborne interval (land detector, else arming state, else height; see
  :meth:`FlightLog.airborne_intervals`): bench and arm/disarm tests;
- **never left the ground**: "airborne" by the land detector but never :data:`MIN_RISE_M` above where it
  took off (a hop in ground effect, a held or tethered vehicle: the fleet's 7 Jun log_13 sits at full
  throttle 0.25 m up; a twin flown on it climbs away, and none of it could be scored);
- **held still**: "airborne" by the land detector, rose less than :data:`HELD_RISE_M`, and its tilt never
  moved (standard deviation under :data:`HELD_TILT_SD_DEG`): a vehicle on a stand, tethered or held for a
  motor run (batch 4 of the corpus: 15 such runs, one rose 0.50 m on its baro drift alone);
- **without GPS** / **without horizontal velocity**: the EKF's horizontal position and/or velocity
  (``vehicle_local_position.xy_valid`` / ``v_xy_valid``) invalid in more than
  ``1 - MIN_HORIZONTAL_FRACTION`` of the airborne samples (the fleet's 21 Jun log_59 and log_65:
  no GPS, ``v_xy_valid`` false all flight).  The twin flies the horizontal setpoints against the real
  horizontal state, and the identification fits horizontal forces: neither exists without it.

:func:`read_flight` is :func:`~twin_nodes.logs.ulog_io.read_ulog` followed by this check: what
``compare`` (offline and graph), ``discover``, ``params from-ulog`` and ``identify`` call.  The
ground-only methods (``identify noise``: the pre-arm segment; ``identify motor``: command/RPM steps,
a bench test is fine) ask only for ``airborne=False, horizontal=False`` (the length check stays).
"""

from __future__ import annotations

import os

import numpy as np

from twin_nodes.base.errors import LogError
from twin_nodes.logs.ulog_io import FlightLog, read_ulog

__all__ = ["check_flyable", "read_flight", "tilt_sd_deg", "MIN_LOG_S", "MIN_AIRBORNE_S", "MIN_RISE_M",
           "HELD_TILT_SD_DEG", "HELD_RISE_M", "MIN_HORIZONTAL_FRACTION"]

#: a log whose position samples span less than this [s] is too short for any command
MIN_LOG_S = 5.0
#: airborne for less than this [s] in all: too short a flight
MIN_AIRBORNE_S = 2.0
#: rose less than this [m] above its take-off height in all (the metrics' ground margin): never left the ground
MIN_RISE_M = 0.5
#: a vehicle whose tilt stays this still while "airborne" (standard deviation [deg]) and that rose less than
#: HELD_RISE_M was held (a stand, a tether, weights): real hand-flown and mission flights of the corpus measure
#: 0.46-15 deg, held motor runs 0.01-0.09 deg (docs/corpus.md, batch 4; tools/corpus_describe.py, same rule)
HELD_TILT_SD_DEG = 0.2
HELD_RISE_M = 1.5
#: horizontal position/velocity finite in less than this fraction of the airborne samples: refused
MIN_HORIZONTAL_FRACTION = 0.25


def _airborne_source(log: FlightLog) -> tuple[str, str]:
    if log.get("landed") is not None and len(log.get("landed")):
        return "vehicle_land_detected.landed", "the land detector says landed throughout"
    if log.get("armed") is not None and len(log.get("armed")):
        return "vehicle_status.arming_state", "never armed"
    return "vehicle_local_position.z", "never more than 1 m above its lowest point"


#: an airborne interval starting this close to the log's first height sample started before the log [s]
LOG_START_S = 1.0


def _max_rise(pos, intervals: list[tuple[float, float]]) -> float | None:
    """Highest rise [m] above the ground over the airborne intervals: above the take-off height (each
    interval's first height), or, for an interval the log starts in (within LOG_START_S of the first
    height sample: no take-off in the log, or one just after it starts), above the lower of its first and
    last height (its touchdown, or its take-off where the log also ends in the air); None when the height
    is unknown there."""
    best = None
    for a, b in intervals:
        inside = (pos.t_s >= a) & (pos.t_s <= b)
        z = pos.values[inside, 2]
        z = z[np.isfinite(z)]
        if z.size < 2:
            continue
        # a log started in the air has no take-off height; its first height is the ground where the take-off
        # came within LOG_START_S of the first sample and the log ends in the air (jmh_v3_p232_003_1: took off
        # at -6.7 m, the log cut at -5.45 m in flight for its audio): the lower of the two
        ground = min(z[0], z[-1]) if a <= float(pos.t_s[0]) + LOG_START_S else z[0]
        r = float(z.max() - ground)
        best = r if best is None else max(best, r)
    return best


def tilt_sd_deg(log: FlightLog, intervals: list[tuple[float, float]]) -> float | None:
    """Standard deviation of the tilt [deg] (body up from world up) over the intervals; None without attitude."""
    q = log.get("attitude_q")
    if q is None or len(q) < 2:
        return None
    inside = np.zeros(len(q), bool)
    for a, b in intervals:
        inside |= (q.t_s >= a) & (q.t_s <= b)
    v = q.values[inside]
    v = v[np.all(np.isfinite(v), axis=1)]
    if len(v) < 2:
        return None
    c = 1.0 - 2.0 * (v[:, 1] ** 2 + v[:, 2] ** 2)   # cos(tilt) of a w-x-y-z quaternion between z-up frames
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))).std())


def _finite_fraction(log: FlightLog, name: str, cols: slice, intervals: list[tuple[float, float]]) -> float:
    s = log.get(name)
    if s is None or len(s) == 0:
        return 0.0
    inside = np.zeros(len(s), bool)
    for a, b in intervals:
        inside |= (s.t_s >= a) & (s.t_s <= b)
    if not inside.any():
        inside[:] = True
    return float(np.mean(np.all(np.isfinite(s.values[inside][:, cols]), axis=1)))


def check_flyable(log: FlightLog, *, airborne: bool = True, horizontal: bool = True) -> FlightLog:
    """``log`` if it is a usable flight, else a one-line :class:`LogError` saying which kind it is not
    (too short, never airborne, without GPS, without horizontal velocity; see the module docstring).
    ``airborne=False`` / ``horizontal=False`` skip those checks for ground-only methods."""
    path = log.path
    pos = log.get("position_enu")
    n = len(pos) if pos is not None else 0
    span = float(pos.t_s[-1] - pos.t_s[0]) if n >= 2 else 0.0
    if n < 2 or span < MIN_LOG_S:
        raise LogError(path, "vehicle_local_position",
                       f"too short: expected at least {MIN_LOG_S:g} s of flight, the log has {n} position "
                       f"sample(s) over {span:.2f} s")
    if not airborne:
        return log
    iv = log.airborne_intervals()
    if not iv:
        field, why = _airborne_source(log)
        raise LogError(path, field, f"never airborne: expected a flight, {why} (a bench or arm/disarm test?)")
    air = sum(b - a for a, b in iv)
    if air < MIN_AIRBORNE_S:
        raise LogError(path, _airborne_source(log)[0],
                       f"too short: expected at least {MIN_AIRBORNE_S:g} s airborne, the flight was airborne "
                       f"for {air:.2f} s")
    rise = _max_rise(pos, iv)
    if rise is not None and rise < MIN_RISE_M:
        raise LogError(path, "vehicle_local_position.z",
                       f"never left the ground: expected it to rise at least {MIN_RISE_M:g} m above where it took "
                       f"off (or landed, for a log started in the air), it rose {rise:.2f} m in the {air:.1f} s "
                       f"'{_airborne_source(log)[0]}' calls "
                       f"airborne "
                       f"(a hop in ground effect, a held or tethered vehicle, a bench test, or a height estimate that "
                       f"never moved)")
    tilt = tilt_sd_deg(log, iv)
    if tilt is not None and tilt < HELD_TILT_SD_DEG and not (rise is not None and rise >= HELD_RISE_M):
        raise LogError(path, "vehicle_attitude.q",
                       f"never left the ground: held still, expected a vehicle in free flight to tilt, its tilt "
                       f"varied by {tilt:.2f} deg (s.d.; flights measure 0.46 deg and more) over the {air:.1f} s "
                       f"'{_airborne_source(log)[0]}' calls airborne, and it rose "
                       f"{'an unknown height' if rise is None else f'{rise:.2f} m'} (a stand, tether or held motor run)")
    if not horizontal:
        return log
    p_ok = _finite_fraction(log, "position_enu", slice(0, 2), iv)
    v_ok = _finite_fraction(log, "velocity_enu", slice(0, 2), iv)
    if p_ok < MIN_HORIZONTAL_FRACTION and v_ok < MIN_HORIZONTAL_FRACTION:
        raise LogError(path, "vehicle_local_position.xy_valid,v_xy_valid",
                       f"without GPS (no horizontal position or velocity): expected both in flight, valid in "
                       f"{100 * p_ok:.0f} % / {100 * v_ok:.0f} % of the {air:.1f} s airborne")
    if v_ok < MIN_HORIZONTAL_FRACTION:
        raise LogError(path, "vehicle_local_position.vx,vy (v_xy_valid)",
                       f"without horizontal velocity: expected it in flight, valid in {100 * v_ok:.0f} % of the "
                       f"{air:.1f} s airborne (no GPS?)")
    if p_ok < MIN_HORIZONTAL_FRACTION:
        raise LogError(path, "vehicle_local_position.x,y (xy_valid)",
                       f"without horizontal position: expected it in flight, valid in {100 * p_ok:.0f} % of the "
                       f"{air:.1f} s airborne (no GPS?)")
    return log


def read_flight(path: str | os.PathLike[str], *, airborne: bool = True, horizontal: bool = True) -> FlightLog:
    """:func:`~twin_nodes.logs.ulog_io.read_ulog` then :func:`check_flyable`."""
    return check_flyable(read_ulog(path), airborne=airborne, horizontal=horizontal)
