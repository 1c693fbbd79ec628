"""Which airborne samples an identification may fit, and how many seconds it left out, and why.

The equations the fits use hold for a free rigid body driven by rotors that do what they are told.
Four kinds of sample break that and are left out:

- **a saturated motor**: an output at its bound (within :data:`SAT_TOL` of 0 or 1) — the rotor cannot
  follow the controller there, the ESC and PWM limits are not the thrust curve, and PX4's allocation is
  giving something up; kept out :data:`SAT_MARGIN_S` either side (one 10 Hz motor sample);
- **ground contact**: the land detector's ``ground_contact``, ``maybe_landed`` or ``landed`` — the
  ground pushes back, which no equation here has;
- **the land detector's transitions**: :data:`LAND_MARGIN_S` either side of each change of one of
  those flags (its 1-3 s of hysteresis: a vehicle touching down, bouncing or lifting off);
- **the take-off spot**: at the start of an airborne interval, until the vehicle first rose :data:`SPOT_M`
  above the height where the interval began, whatever the land detector says.  An overloaded, held or
  caught vehicle sits on its take-off spot at a high collective for seconds while the land detector
  already calls it airborne (fleet ZweiterFlugtag log_20: 4.4-17 s); there the ground carries part of the
  weight and all of the moments, so thrust, trims and inertia fitted there describe the ground, not the
  vehicle.

Pure numpy on a :class:`~twin_nodes.logs.ulog_io.FlightLog`; a log without the land detector or motors
simply has nothing to leave out for that reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twin_nodes.base.constants import LEFT_GROUND_M

#: an output within this of 0 or 1 (normalised) is at its bound
SAT_TOL = 1e-3
#: seconds left out on either side of a saturated motor sample (one sample of PX4's 10 Hz motor log)
SAT_MARGIN_S = 0.1
#: seconds left out on either side of a change of the land detector's flags
LAND_MARGIN_S = 1.0
#: a vehicle has left its spot once this far above the height its airborne interval began at [m] (the twin's
#: rule too: ``base.constants``)
SPOT_M = LEFT_GROUND_M
#: an airborne interval that begins within this of the first height sample began in the air [s]
_JOINED_AIRBORNE_S = 0.5
#: at least this much must remain to fit [s] (the shortest airborne interval the nominal accepts is 6 s)
MIN_KEEP_S = 6.0


@dataclass
class FitMask:
    """``keep`` (n,) bool over the grid; ``seconds`` left out per reason (each sample counted once, under
    the first reason that applies, in the order saturated, ground contact, land-detector transition)."""

    keep: np.ndarray
    seconds: dict[str, float] = field(default_factory=dict)
    total_s: float = 0.0
    #: what was not left out after all, and why (too little would remain); empty when nothing
    fallback: str = ""

    def describe(self) -> str:
        if self.fallback:
            return self.fallback + ("; left out: " + self._listed() if any(self.seconds.values()) else "")
        if not self.seconds or sum(self.seconds.values()) == 0.0:
            return ("none: no saturated motor, ground contact or land-detector transition in the airborne "
                    "samples")
        return self._listed()

    def _listed(self) -> str:
        parts = [f"{v:.1f} s {k}" for k, v in self.seconds.items() if v > 0]
        return "; ".join(parts) + f" (of {self.total_s:.1f} s airborne samples)"


def _near(t: np.ndarray, events: np.ndarray, margin: float) -> np.ndarray:
    """(n,) bool: ``t`` within ``margin`` of one of the sorted ``events``."""
    if events.size == 0:
        return np.zeros(t.size, bool)
    i = np.clip(np.searchsorted(events, t), 1, events.size - 1) if events.size > 1 else np.zeros(t.size, int)
    d = np.abs(t - events[i])
    if events.size > 1:
        d = np.minimum(d, np.abs(t - events[i - 1]))
    return d <= margin


def saturated_times(log) -> np.ndarray:
    """Times [s] of the log's own motor samples with an output at its bound (0 or 1)."""
    mot = log.get("motors")
    if mot is None or len(mot) == 0:
        return np.zeros(0)
    v = np.asarray(mot.values, float)
    finite = np.isfinite(v).all(axis=1)
    at_bound = ((v <= SAT_TOL) | (v >= 1.0 - SAT_TOL)).any(axis=1)
    return np.asarray(mot.t_s, float)[finite & at_bound]


def fit_mask(log, t: np.ndarray, rate_hz: float, min_keep_s: float = MIN_KEEP_S) -> FitMask:
    """The samples of the grid ``t`` [s] (at ``rate_hz``) an identification may fit (see the module).

    Where leaving them all out would keep less than ``min_keep_s`` (a flight saturated most of the
    time), the saturated samples are kept after all, and where even that is too little, everything:
    the fit then says so (``FitMask.fallback``) rather than fitting a second of data."""
    full = _fit_mask(log, t, rate_hz, saturation=True)
    if full.keep.sum() / rate_hz >= min_keep_s:
        return full
    part = _fit_mask(log, t, rate_hz, saturation=False)
    kept = full.keep.sum() / rate_hz
    if part.keep.sum() / rate_hz >= min_keep_s:
        part.fallback = (f"saturated samples NOT left out: only {kept:.1f} s would remain (< {min_keep_s:g} s); "
                         f"{full.seconds.get(SATURATED, 0.0):.1f} s with a motor at its bound are fitted")
        return part
    everything = FitMask(np.ones(np.asarray(t).size, bool), {}, float(np.asarray(t).size) / rate_hz)
    everything.fallback = (f"nothing left out: {kept:.1f} s would remain (< {min_keep_s:g} s), "
                           f"{part.keep.sum() / rate_hz:.1f} s with the saturated samples kept; all airborne samples "
                           f"are fitted, among them {full._listed()}; and, saturation aside, {part._listed()}")
    return everything


def contact_mask(log, t: np.ndarray, rate_hz: float) -> np.ndarray:
    """``t`` samples free of ground contact and land-detector transitions, saturated samples kept (for an
    equation that holds with a motor at its bound: the thrust of a saturated command is still its thrust)."""
    return _fit_mask(log, t, rate_hz, saturation=False).keep


SATURATED = "with a motor output at its bound (saturated)"


def _fit_mask(log, t: np.ndarray, rate_hz: float, saturation: bool) -> FitMask:
    t = np.asarray(t, float)
    keep = np.ones(t.size, bool)
    seconds: dict[str, float] = {}

    def drop(reason: str, hit: np.ndarray) -> None:
        new = hit & keep
        seconds[reason] = float(new.sum()) / rate_hz
        keep[new] = False

    if saturation:
        drop(SATURATED, _near(t, saturated_times(log), SAT_MARGIN_S))
    ld = log.get("land_detector")
    if ld is not None and len(ld):
        flags = np.asarray(ld.values, float) > 0.5
        on = ld.at(t, kind="previous") > 0.5 if t.size else np.zeros((0, flags.shape[1]), bool)
        drop("in ground contact (land detector ground_contact/maybe_landed/landed)",
             np.asarray(on, bool).reshape(t.size, -1).any(axis=1))
        changes = np.asarray(ld.t_s, float)[1:][(flags[1:] != flags[:-1]).any(axis=1)]
        drop(f"within {LAND_MARGIN_S:g} s of a land-detector transition", _near(t, changes, LAND_MARGIN_S))
    drop(f"on the take-off spot (not yet {SPOT_M:g} m above it; the land detector said airborne)",
         on_spot(log, t))
    return FitMask(keep, seconds, float(t.size) / rate_hz)


def on_spot(log, t: np.ndarray, margin_m: float = SPOT_M) -> np.ndarray:
    """(n,) bool: ``t`` at the start of an airborne interval while the vehicle has not yet risen ``margin_m``
    above the height the interval began at.  An interval that begins with the height data (a log joined in
    the air) has no take-off spot; one the vehicle never rises ``margin_m`` in is all spot.  The touchdown end
    is left to the land detector (its flags and their transitions): there a height estimate that drifted in
    the air would put a hover at the spot (jmh_v3_maymun_20_2 touches down 1.1 m above its take-off height)."""
    t = np.asarray(t, float)
    out = np.zeros(t.size, bool)
    pos = log.get("position_enu")
    if pos is None or len(pos) == 0:
        return out
    ft = np.asarray(pos.t_s, float)
    fz = np.asarray(pos.values, float)[:, 2]
    for a, b in log.airborne_intervals():
        idx = np.flatnonzero((ft >= a) & (ft <= b) & np.isfinite(fz))
        if idx.size < 2 or a <= ft[0] + _JOINED_AIRBORNE_S:
            continue
        up = np.flatnonzero(fz[idx] > fz[idx[0]] + margin_m)
        out |= (t >= a) & (t <= b) & (t < (ft[idx[up[0]]] if up.size else np.inf))
    return out
