"""The RotorPy grid's missions (issue 26): RP1 waypoints and RP2 figure-eight (``rotorpy_flights``), and
RP3 a circle, RP4 hover with yaw (and a low hover, for ground effect), RP5 fast descents.

Each mission starts on the ground, takes off, flies, lands; pieces are RotorPy flat-output trajectories.
"""

from __future__ import annotations

import math

import numpy as np

from twin_nodes.prove.rotorpy_flights import Mission, _Hold, _landing, _leg, _rp1, _rp2, _take_off, _YawTurn


class _Circle:
    """A horizontal circle of radius r about c at angular rate w (ramped up and down over ``ramp`` s, so the
    speed starts and ends at 0), ``turns`` turns in all; yaw fixed at ``yaw`` or along the path."""

    def __init__(self, c, r, w, turns, ramp=3.0, yaw=None):
        self.c, self.r, self.w, self.ramp = np.asarray(c, float), float(r), float(w), float(ramp)
        self.yaw = yaw
        self.cruise = max(2 * math.pi * turns / abs(w) - ramp, 0.0)
        self.duration = self.cruise + 2 * ramp

    def _phase(self, t):
        w, tr = self.w, self.ramp
        if t < tr:
            return w * t * t / (2 * tr), w * t / tr, w / tr
        if t < tr + self.cruise:
            return w * (t - tr / 2), w, 0.0
        s = min(t - tr - self.cruise, tr)
        th0 = w * (self.cruise + tr / 2)
        return th0 + w * s - w * s * s / (2 * tr), w * (1 - s / tr), (-w / tr if s < tr else 0.0)

    def update(self, t):
        th, thd, thdd = self._phase(t)
        c, s = math.cos(th), math.sin(th)
        x = self.c + self.r * np.array([c, s, 0.0])
        v = self.r * thd * np.array([-s, c, 0.0])
        a = self.r * thdd * np.array([-s, c, 0.0]) - self.r * thd ** 2 * np.array([c, s, 0.0])
        if self.yaw is None:
            yaw, yaw_dot = th + math.copysign(math.pi / 2, self.w), thd
        else:
            yaw, yaw_dot = float(self.yaw), 0.0
        z = np.zeros(3)
        return {"x": x, "x_dot": v, "x_ddot": a, "x_dddot": z, "x_ddddot": z, "yaw": yaw, "yaw_dot": yaw_dot,
                "yaw_ddot": 0.0}


def _rp3() -> Mission:
    """RP3: take-off, a 2.5 m circle at 1.5 rad/s... two turns facing along the path, two turns the other way
    with a fixed heading (sideways, backwards and forwards in one turn); landing."""
    h = 1.5
    c = np.array([0.0, 0.0, h])
    p0 = c + np.array([2.5, 0.0, 0.0])
    pieces = _take_off([p0[0], p0[1], 0.0], h, math.pi / 2)
    pieces += [_Hold(p0, math.pi / 2, 1.0), _Circle(c, 2.5, 1.2, 2, yaw=None), _Hold(p0, math.pi / 2, 1.0),
               _YawTurn(p0, math.pi / 2, 0.0), _Circle(c, 2.5, -1.4, 2, yaw=0.0), _Hold(p0, 0.0, 1.0)]
    pieces += _landing(p0, 0.0)
    return Mission("RP3", pieces, 1.0, 1.0)


def _rp4() -> Mission:
    """RP4: hover with yaw: take-off to 1.5 m, full turns in place at three rates (both ways), down to a low
    hover at 0.25 m with a yaw there, back up, landing."""
    h = 1.5
    o = np.array([0.0, 0.0, h])
    pieces = _take_off([0, 0, 0], h, 0.0)
    yaw = 0.0
    for d, rate in ((2 * math.pi, 1.0), (-2 * math.pi, 2.0), (math.pi, 3.0), (-math.pi, 1.5)):
        pieces += [_YawTurn(o, yaw, yaw + d, rate), _Hold(o, yaw + d, 1.0)]
        yaw += d
    low = np.array([0.0, 0.0, 0.25])
    pieces += [_leg(o, low, yaw, yaw, 0.5), _Hold(low, yaw, 3.0), _YawTurn(low, yaw, yaw + math.pi, 1.5),
               _Hold(low, yaw + math.pi, 2.0), _leg(low, o, yaw + math.pi, yaw + math.pi, 0.8)]
    yaw += math.pi
    pieces += [_Hold(o, yaw, 1.0), _YawTurn(o, yaw, yaw - math.pi / 2, 2.0), _Hold(o, yaw - math.pi / 2, 1.0)]
    pieces += _landing(o, yaw - math.pi / 2)
    return Mission("RP4", pieces, 1.0, 1.0)


def _rp5() -> Mission:
    """RP5: fast descents: climbs to 4.5 m and fast descents (2.5 m/s average) to 1 m, with 3 m sideways moves
    between them and a yaw at the top; landing."""
    pieces = _take_off([0, 0, 0], 1.0, 0.0)
    p = np.array([0.0, 0.0, 1.0])
    yaw = 0.0
    for j, (dx, dy) in enumerate(((3.0, 0.0), (0.0, 3.0), (-3.0, 0.0))):
        top = p + np.array([0.0, 0.0, 3.5])
        pieces += [_leg(p, top, yaw, yaw, 1.2), _Hold(top, yaw, 0.5), _YawTurn(top, yaw, yaw + math.pi / 2, 1.5),
                   _Hold(top, yaw + math.pi / 2, 0.5)]
        yaw += math.pi / 2
        bottom = top + np.array([dx, dy, -3.5])
        pieces += [_leg(top, bottom, yaw, yaw, 2.5), _Hold(bottom, yaw, 1.0)]
        p = bottom
    pieces += _landing(p, yaw)
    return Mission("RP5", pieces, 1.0, 1.0)


GRID_MISSIONS = {"RP1": _rp1, "RP2": _rp2, "RP3": _rp3, "RP4": _rp4, "RP5": _rp5}
