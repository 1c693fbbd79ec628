"""Stage 1, the flight prepared once: equation-error data from the log through the nominal (PX4's
sensor timing taken out first), the 2-fold split, held-out blocks, both residuals' judges and the
excitation per channel (``FlightInput`` -> ``PreparedFlight``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from twin_nodes.discovery.judging import (BLOCK_S, HELDOUT_FRACTION, Judge, _blocks, _equation_judge, _judged_windows,
                                          _output_judge)
from twin_nodes.discovery.locate import excitation
from twin_nodes.discovery.output_error import Windows
from twin_nodes.discovery.residuals import EquationData, channel_names, prepare
from twin_nodes.vehicle.params import VehicleParams


@dataclass
class FlightInput:
    """A flight log and the nominal vehicle it is judged against."""

    log: object                       # a FlightLog
    nominal: VehicleParams
    heldout_fraction: float = HELDOUT_FRACTION
    output_error: bool = True         # also the output error (False: the equation error only)


@dataclass
class PreparedFlight:
    """What discovery needs about one flight: data, splits, both judges, excitation."""

    data: EquationData
    names: list[str]
    fit_mask: np.ndarray
    held_mask: np.ndarray
    t_split: float
    t_end: float
    eq: Judge
    oe: Judge | None
    excitation: dict
    #: the output error's judged windows, also where no axis is usable (the instrumented gains)
    windows: Windows | None = None
    #: the second fold's split: fit on the part after it, judge on the part before
    t_split2: float = math.nan
    #: the log's own parameters (PX4's rate-loop gains and filters for :mod:`rate_loop`)
    log_params: dict = field(default_factory=dict)
    #: the nominal vehicle the judges measure against
    nominal: VehicleParams | None = None
    #: the closed-loop twin's held-out window [s] (:func:`scored_window`); NaN: ``t_split``, ``t_end``
    cl_t_split: float = math.nan
    cl_t_end: float = math.nan

    @property
    def scored(self) -> tuple[float, float]:
        """The closed-loop twin's held-out window (start, end) [s]."""
        if math.isfinite(self.cl_t_split) and math.isfinite(self.cl_t_end):
            return self.cl_t_split, self.cl_t_end
        return self.t_split, self.t_end


#: the name it had in ``discover.py``


def run(inp: FlightInput) -> PreparedFlight:
    """Prepare a flight: equation-error data, the 2-fold splits, both judges, per-channel excitation."""
    log, vp, heldout_fraction, output_error = inp.log, inp.nominal, inp.heldout_fraction, inp.output_error
    data = prepare(log, vp)
    names = channel_names(vp.rotors.count)
    # the splits where the attitude channels are read (the longer ground-contact pad): the vertical force's
    # extra samples after a lift-off fall before the first split, into fold 1's fit and fold 2's held-out part
    valid_t = data.t[data.valid_attitude]
    t_split = valid_t[0] + (1.0 - heldout_fraction) * (valid_t[-1] - valid_t[0])
    fit_mask = data.valid & (data.t < t_split)
    held_mask = data.valid & (data.t >= t_split)
    # second fold: fit on the last part, judge on the first (disjoint from fold 1's test part)
    t_split2 = valid_t[0] + heldout_fraction * (valid_t[-1] - valid_t[0])
    held2 = data.valid & (data.t < t_split2)
    folds = [(fit_mask, held_mask), (data.valid & (data.t >= t_split2), held2)]
    held_blocks = _blocks(data.t, held_mask, BLOCK_S) + _blocks(data.t, held2, BLOCK_S)
    eq = _equation_judge(data, vp, folds, held_blocks, held_mask)
    win = _judged_windows(data, vp) if output_error else None
    oe = _output_judge(data, vp, t_split, t_split2, win) if win is not None else None
    ex = excitation(data, vp, names, _blocks(data.t, data.valid, BLOCK_S), held_blocks)
    cl_split, cl_end = scored_window(data, heldout_fraction)
    return PreparedFlight(data, names, fit_mask, held_mask, float(t_split), float(valid_t[-1]), eq, oe, ex, win,
                          float(t_split2), dict(getattr(log, "params", None) or {}), vp, cl_split, cl_end)


def scored_window(data: EquationData, heldout_fraction: float = HELDOUT_FRACTION) -> tuple[float, float]:
    """The closed-loop twin's held-out window [s]: the last ``heldout_fraction`` of the span where its throttle
    and motors can be scored (``data.attitude_scored``: airborne, armed, off the ground, attitude, rates,
    specific force and height logged), whether or not the horizontal velocity is.

    The fits need the horizontal velocity (drag, wind), the twin's throttle and motors do not.  A flight
    whose GPS velocity becomes valid only mid-flight (jangminhyuk's Pixhawk 3, hand-flown in STABILIZED:
    valid from 17-21 s of 25 s airborne) was scored on the last 35 % of the part with velocity: 1.8 s of
    a 25 s flight, its landing (jmh_v3_kus_11_1, 23.9-25.8 s).  Where the velocity is valid all flight
    the two spans are the same samples and so is the window."""
    m = data.attitude_scored if data.attitude_scored is not None else data.attitude_valid
    if m is None or not np.any(m):
        m = data.valid
    ts = data.t[m]
    return float(ts[0] + (1.0 - heldout_fraction) * (ts[-1] - ts[0])), float(ts[-1])


def prepare_flight(log, vp: VehicleParams, heldout_fraction: float = HELDOUT_FRACTION,
                   output_error: bool = True) -> PreparedFlight:
    """:func:`run` with the input spelled out."""
    return run(FlightInput(log, vp, heldout_fraction, output_error))
