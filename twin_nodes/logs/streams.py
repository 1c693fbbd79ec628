"""Which log series become which ``/real/...`` topic on replay (pure numpy).

:func:`replay_streams` maps a :class:`twin_nodes.logs.ulog_io.FlightLog` to one
:class:`Stream` per topic: the sample times and the arrays each message is built
from.  One message per sample of the *source* ULog topic (after
:func:`read_ulog`'s time cleaning), so message counts can be checked against
the log:

============================  =========================================  ====================
topic                         samples of                                 other series, at those times
============================  =========================================  ====================
``/real/odom``                ``vehicle_local_position`` (position_enu)  attitude (slerp), body rates (linear)
``/real/imu``                 ``sensor_combined``                        -
``/real/motors``              ``actuator_motors`` / ``actuator_outputs``  -
``/real/throttle``            thrust setpoint / ``actuator_controls_0``   -
``/real/battery``             ``battery_status[0]``                      -
``/real/setpoint``            ``trajectory_setpoint``, and between its   the others held (previous)
                              samples ``vehicle_attitude_setpoint``'s
                              where it carries the yaw (20 Hz)
``/real/setpoint_pose``       ``trajectory_setpoint`` with a position    -
``/real/status``              changes of armed / nav_state / landed      zero-order hold of the others
``/real/esc_rpm``             ``esc_status`` (when logged)               -
============================  =========================================  ====================
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twin_nodes.logs.conversions import body_velocity

__all__ = ["Stream", "replay_streams", "event_order", "HEADERLESS"]

#: topics whose messages have no header (their time travels via /clock, see msgs_py.topics)
HEADERLESS = frozenset({"/real/motors", "/real/throttle", "/real/setpoint", "/real/status", "/real/esc_rpm"})


@dataclass
class Stream:
    topic: str
    t_s: np.ndarray                       # (n,) seconds since the log start
    data: dict[str, np.ndarray] = field(default_factory=dict)  # arrays with leading dimension n
    source: str = ""

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


def _at(log: Any, name: str, t: np.ndarray) -> np.ndarray | None:
    s = log.get(name)
    if s is None or len(s) == 0:
        return None
    return s.at(t)


def replay_streams(log: Any) -> tuple[list[Stream], list[str]]:
    """``(streams, warnings)``: the ``/real`` topics this log can fill, in publishing order;
    a warning names each topic left out and the series it lacks."""
    out: list[Stream] = []
    warn: list[str] = []

    def missing(topic: str, what: str) -> None:
        warn.append(f"{topic}: not published, the log has no {what}")

    pos = log.get("position_enu")
    if pos is None or len(pos) == 0:
        missing("/real/odom", "vehicle_local_position (position_enu)")
    else:
        t = pos.t_s
        q = _at(log, "attitude_q", t)
        if q is None:
            missing("/real/odom", "vehicle_attitude: orientation is NaN")
            q = np.full((len(t), 4), np.nan)
        vel = _at(log, "velocity_enu", t)
        vel = np.full((len(t), 3), np.nan) if vel is None else vel
        w = _at(log, "body_rates_flu", t)
        w = np.full((len(t), 3), np.nan) if w is None else w
        out.append(Stream("/real/odom", t, {"p": pos.values, "q": q, "v_flu": body_velocity(q, vel), "w": w},
                          pos.source))

    sf, gy = log.get("specific_force_flu"), log.get("gyro_flu")
    if sf is None or gy is None or len(sf) == 0:
        missing("/real/imu", "sensor_combined")
    else:
        g = gy.values if len(gy) == len(sf) and np.array_equal(gy.t_s, sf.t_s) else gy.at(sf.t_s)
        out.append(Stream("/real/imu", sf.t_s, {"sf": sf.values, "gyro": g}, sf.source))

    for topic, name, what in (("/real/motors", "motors", "actuator_motors or actuator_outputs"),
                              ("/real/throttle", "throttle", "vehicle_thrust_setpoint or actuator_controls_0")):
        s = log.get(name)
        if s is None or len(s) == 0:
            missing(topic, what)
        else:
            out.append(Stream(topic, s.t_s, {"v": s.values}, s.source))

    bv = log.get("battery_v")
    if bv is None or len(bv) == 0:
        missing("/real/battery", "battery_status")
    else:
        ba = _at(log, "battery_a", bv.t_s)
        ba = np.full((len(bv), 1), np.nan) if ba is None else ba
        out.append(Stream("/real/battery", bv.t_s, {"v": bv.values[:, 0], "a": ba[:, 0]}, bv.source))

    spp = log.get("setpoint_position_enu")
    if spp is None or len(spp) == 0:
        missing("/real/setpoint", "trajectory_setpoint")
    else:
        t = spp.t_s
        # a yaw setpoint logged faster than the trajectory (the 20 Hz attitude setpoint) is sent at its
        # own times too: the position parts are held there (the twin carries them from their own sample)
        ys = log.get("setpoint_yaw_enu")
        t_all = t
        if ys is not None and len(ys) and not np.array_equal(ys.t_s, t):
            extra = ys.t_s[(ys.t_s > t[0]) & (ys.t_s <= t[-1])]
            t_all = np.union1d(t, extra)
        sp = np.full((len(t_all), 11), np.nan)
        sp[:, 0:3] = spp.values if t_all is t else spp.at(t_all, kind="previous")
        for name, sl in (("setpoint_velocity_enu", slice(3, 6)), ("setpoint_accel_enu", slice(6, 9)),
                         ("setpoint_yaw_enu", slice(9, 10)), ("setpoint_yawspeed", slice(10, 11))):
            s = log.get(name)
            if s is not None and len(s):
                v = s.values if np.array_equal(s.t_s, t_all) else s.at(t_all)
                sp[:, sl] = v[:, : sl.stop - sl.start]
        out.append(Stream("/real/setpoint", t_all, {"sp": sp}, spp.source))
        pos_t = np.isin(t_all, t)
        ok = np.all(np.isfinite(sp[:, 0:3]), axis=1) & pos_t
        out.append(Stream("/real/setpoint_pose", t_all[ok], {"p": sp[ok, 0:3], "yaw": sp[ok, 9]},
                          spp.source + " (finite positions)"))

    parts = {n: log.get(n) for n in ("armed", "nav_state", "landed")}
    have = {n: s for n, s in parts.items() if s is not None and len(s)}
    if not have:
        missing("/real/status", "vehicle_status or vehicle_land_detected")
    else:
        t = np.unique(np.concatenate([s.t_s for s in have.values()]))
        vals = np.full((len(t), 3), np.nan)
        for i, n in enumerate(("armed", "nav_state", "landed")):
            if n in have:
                vals[:, i] = have[n].at(t, "previous")[:, 0]
        out.append(Stream("/real/status", t, {"v": vals}, "vehicle_status, vehicle_land_detected (changes)"))

    rpm = log.get("esc_rpm")
    if rpm is not None and len(rpm):
        out.append(Stream("/real/esc_rpm", rpm.t_s, {"v": rpm.values}, rpm.source))
    return out, warn


def event_order(streams: list[Stream]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All samples of all streams in time order: ``(t_s, stream_index, row)``; ties keep
    the stream order (stable sort)."""
    if not streams:
        return np.zeros(0), np.zeros(0, int), np.zeros(0, int)
    t = np.concatenate([s.t_s for s in streams])
    si = np.concatenate([np.full(len(s), i, int) for i, s in enumerate(streams)])
    row = np.concatenate([np.arange(len(s)) for s in streams])
    order = np.lexsort((si, t))
    return t[order], si[order], row[order]
