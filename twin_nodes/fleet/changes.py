"""Changes of one vehicle across its flights: the flight-to-flight scatter, steps beyond it, and what a
step means (issue 25).

Pure functions on plain lists.  A *step* is a value beyond the scatter band around the vehicle's current
reference on at least :data:`MIN_RUN` flights in a row (a single flight beyond it is an *excursion*, listed,
never an alarm).  :func:`explain` names what changed from the ratios of the values that stepped together:

- thrust per mass ``kt_per_mass`` down with the roll/pitch effectiveness ``T_max/I`` unchanged: **mass**
  (a payload near the centre of mass: the thrust is the same, the mass is not);
- both down by the same factor: **thrust** (weaker propulsion: propellers, motors, a lower T_max);
- the effectiveness down with the thrust per mass unchanged: **inertia** (mass hung away from the centre);
- the yaw effectiveness alone: **yaw moment** (other propellers);
- the trims: **centre-of-mass shift**; one motor's share of the thrust alone: **a weaker motor**;
- a change of the motor PWM range in the firmware parameters at that flight: **thrust range** (read from
  the log, compared with the step it predicts).

Where the flight cannot tell mass from thrust (the effectiveness too uncertain), the step is reported as
**thrust per mass** with the reason.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field

import numpy as np

#: flights in a row beyond the band that make a step
MIN_RUN = 2
#: how far a new level's flights may lie from its median, as a fraction of the step from the old level (beside the
#: band): a change the size of a payload seldom comes back to the same millimetre or percent (the fleet's 23 Jun
#: gripper: CoM dx 112 and 96 mm against ~0 before, a band of 7.5 mm), while its flights still sit on one side of
#: the old level, far beyond its band
STEP_COHESION = 0.25
#: band half-width in scatter sigmas
BAND_SIGMA = 3.0
#: flights the reference is the median of
REF_FLIGHTS = 5
#: values followed for steps: name -> (relative floor of the band, absolute floor of the band)
TRACKED = {
    "kt_per_mass": (0.03, 0.0),
    "rp_eff": (0.06, 0.0),
    "yaw_eff": (0.06, 0.0),
    "drag_per_mass": (0.15, 0.02),
    "com_dx_m": (0.0, 0.004),
    "com_dy_m": (0.0, 0.004),
}


@dataclass
class Step:
    value: str
    first: int          # index of the first flight of the step
    last: int           # index of the last flight of the run that made it
    ref: float
    new: float
    size: float
    size_se: float
    band: float

    @property
    def ratio(self) -> float:
        return self.new / self.ref if self.ref else math.nan


@dataclass
class Series:
    value: str
    x: list[float]
    se: list[float]
    scatter: float
    steps: list[Step] = field(default_factory=list)
    excursions: list[int] = field(default_factory=list)
    bands: list[tuple[float, float]] = field(default_factory=list)  # (reference, half-width) per flight


#: the most precise value: where it steps, the vehicle changed, and every other value's reference restarts
PRIMARY = "kt_per_mass"


def find_all(values: dict[str, tuple[list[float], list[float]]], rewired: frozenset[int] = frozenset()
             ) -> dict[str, Series]:
    """:func:`find_steps` for every value ``{name: (x, se)}`` of one vehicle; the references of the others
    restart where :data:`PRIMARY` stepped (a payload also moves the effectiveness a little), every value's where
    the vehicle was ``rewired`` (flight indices whose motors are on other outputs: another configuration, not
    compared with the one before as if nothing changed)."""
    out = {}
    if PRIMARY in values:
        out[PRIMARY] = find_steps(PRIMARY, *values[PRIMARY], resets=rewired)
    resets = frozenset(rewired) | (frozenset(st.first for st in out[PRIMARY].steps) if PRIMARY in out
                                   else frozenset())
    for v, (x, se) in values.items():
        if v != PRIMARY:
            out[v] = find_steps(v, x, se, resets)
    return out


def scatter(x: np.ndarray) -> float:
    """Flight-to-flight scatter (sigma) of a series with steps in it: 1.4826 x the median absolute
    difference of consecutive values / sqrt(2) (a step is one large difference, it barely moves this)."""
    x = x[np.isfinite(x)]
    if x.size < 3:
        return math.nan
    return float(1.4826 * np.median(np.abs(np.diff(x))) / math.sqrt(2.0))


def half_width(ref: float, se: float, sigma: float, floors: tuple[float, float]) -> float:
    s2 = (sigma if math.isfinite(sigma) else 0.0) ** 2 + (se if math.isfinite(se) else 0.0) ** 2
    return max(BAND_SIGMA * math.sqrt(s2), floors[0] * abs(ref), floors[1])


def find_steps(value: str, x: list[float], se: list[float] | None = None, resets: set[int] | frozenset = frozenset()
               ) -> Series:
    """Steps and excursions of one value over a vehicle's flights in date order (NaN: no value there).
    ``resets``: flights where the vehicle changed (a step of another value): the reference starts again there."""
    xs = np.asarray(x, float)
    ses = np.asarray(se if se is not None else [math.nan] * len(x), float)
    sig = scatter(xs)
    floors = TRACKED.get(value, (0.05, 0.0))
    out = Series(value, list(map(float, xs)), list(map(float, ses)), sig)
    state: list[float] = []
    idx = [i for i in range(xs.size) if math.isfinite(xs[i])]
    out.bands = [(math.nan, math.nan)] * xs.size
    k = 0
    while k < len(idx):
        i = idx[k]
        if i in resets:
            state = []
        if not state:
            state.append(xs[i])
            k += 1
            continue
        ref = float(np.median(state[-REF_FLIGHTS:]))
        h = half_width(ref, ses[i], sig, floors)
        out.bands[i] = (ref, h)
        if abs(xs[i] - ref) <= h:
            state.append(xs[i])
            k += 1
            continue
        sign = np.sign(xs[i] - ref)
        run = [i]
        for j in idx[k + 1:]:
            level = float(np.median(xs[run]))  # the new state must hold together, not only be off the old one
            if np.sign(xs[j] - ref) == sign and abs(xs[j] - ref) > half_width(ref, ses[j], sig, floors) \
                    and abs(xs[j] - level) <= max(half_width(level, ses[j], sig, floors),
                                                  STEP_COHESION * abs(level - ref)):
                run.append(j)
                out.bands[j] = (ref, half_width(ref, ses[j], sig, floors))
            else:
                break
        if len(run) < MIN_RUN:
            out.excursions.append(i)
            k += 1
            continue
        new = float(np.median(xs[run]))
        s = sig if math.isfinite(sig) else float(np.nanmean(ses[run]))
        size_se = s * math.sqrt(1.0 / len(run) + 1.0 / min(len(state), REF_FLIGHTS))
        out.steps.append(Step(value, run[0], run[-1], ref, new, new - ref, size_se, h))
        for j in run:  # drawn around the new state (the step's first flight keeps the old band it left)
            if j != run[0]:
                out.bands[j] = (new, half_width(new, ses[j], sig, floors))
        state = [float(xs[j]) for j in run]
        k += len(run)
    return out


def ratio_se(a: float, a_se: float, b: float, b_se: float) -> float:
    """Standard error of a/b from independent errors."""
    if not (a and b):
        return math.nan
    return abs(a / b) * math.hypot((a_se or 0.0) / a, (b_se or 0.0) / b)


def explain(ratios: dict[str, tuple[float, float]], deltas: dict[str, tuple[float, float]] | None = None,
            pwm: tuple[float, float] | None = None, stepped: set[str] | None = None) -> tuple[str, str]:
    """``(name, why)`` of one change from the values' new/old ``ratios`` ``{value: (ratio, se)}`` (only those
    measured on both sides), the trims' ``deltas`` ``{value: (delta, se)}`` and a PWM range ``(old span, new span)``
    [us] when the firmware's motor range changed there.  Names (several joined by " + " when they changed
    together): ``thrust range``, ``mass``, ``thrust``, ``thrust per mass``, ``inertia``, ``yaw moment``,
    ``centre-of-mass shift``, ``weaker motor <i>``, ``stronger motor <i>`` (a weak one replaced); ``unexplained``
    when none fits.  ``stepped``: the values that stepped (beyond their band on two flights in a row); when given, a change is named only from those (the others
    still tell mass from thrust)."""
    if stepped is not None:
        keep = set(stepped) | ({"kt_per_mass"} if pwm else set())
        if "kt_per_mass" not in keep:
            ratios = {k: v for k, v in ratios.items() if k != "kt_per_mass"}
        if not keep & {"rp_eff", "roll_eff", "pitch_eff", "kt_per_mass"}:
            ratios = {k: v for k, v in ratios.items() if k not in ("rp_eff", "roll_eff", "pitch_eff")}
        if "yaw_eff" not in keep:
            ratios = {k: v for k, v in ratios.items() if k != "yaw_eff"}
        deltas = {k: v for k, v in (deltas or {}).items() if k in keep or k.startswith("motor_share")}
    found = [_thrust_or_mass(ratios, pwm), _yaw(ratios), _motor_or_com(deltas or {})]
    found = [f for f in found if f is not None]
    if not found:
        return "unexplained", "values beyond their band without a pattern this table names"
    return " + ".join(n for n, _ in found), "; ".join(w for _, w in found)


def _changed(ratio: tuple[float, float] | None, value: str) -> bool:
    """A ratio beyond 3 se and beyond the value's relative band floor (:data:`TRACKED`)."""
    return bool(ratio) and abs(ratio[0] - 1.0) > max(3 * ratio[1], TRACKED.get(value, (0.05, 0.0))[0])


def _eff(ratios: dict) -> tuple[float, float] | None:
    if "rp_eff" in ratios and math.isfinite(ratios["rp_eff"][0]):
        return ratios["rp_eff"]
    effs = [ratios[k] for k in ("roll_eff", "pitch_eff") if k in ratios and math.isfinite(ratios[k][0])]
    if not effs:
        return None
    w = np.array([1.0 / max(s, 1e-6) ** 2 for _, s in effs])
    return float(np.sum(w * np.array([r for r, _ in effs])) / w.sum()), float(1.0 / math.sqrt(w.sum()))


def _thrust_or_mass(ratios: dict, pwm) -> tuple[str, str] | None:
    kt, eff = ratios.get("kt_per_mass"), _eff(ratios)
    if pwm is not None and pwm[0] > 0:
        r_pwm = pwm[1] / pwm[0]
        got = f", measured thrust per mass x{kt[0]:.3f} ± {kt[1]:.3f}" if kt else ""
        name, why = "thrust range", (f"motor PWM range {pwm[0]:.0f} -> {pwm[1]:.0f} us in the firmware parameters: the "
                                     f"same command gives up to x{r_pwm:.3f} the thrust{got}")
        if kt:  # what the range does not explain: the same reading on the ratios divided by it
            rest = {"kt_per_mass": (kt[0] / r_pwm, kt[1] / r_pwm)}
            if eff is not None:
                rest["rp_eff"] = (eff[0] / r_pwm, eff[1] / r_pwm)
            more = _thrust_or_mass(rest, None)
            if more is not None:
                name, why = f"{name} + {more[0]}", f"{why}; beyond the range: {more[1]}"
        return name, why
    if _changed(kt, "kt_per_mass"):
        r = kt[0]
        # a heavier vehicle keeps T_max/I (x1), changed propulsion moves it with the thrust (x r): told apart only
        # where the effectiveness is known to better than half their distance and lies more than one se from
        # halfway (the SIH fleet's s21, T_MAX back x1.111: x1.046 +- 0.026, 0.010 from halfway, was named a mass)
        if eff is None or eff[1] > abs(r - 1.0) / 2.0 or abs(eff[0] - (1.0 + r) / 2.0) <= eff[1]:
            why = ("no roll/pitch effectiveness on both sides" if eff is None else
                   f"the roll/pitch effectiveness x{eff[0]:.3f} ± {eff[1]:.3f} is too uncertain to tell a heavier "
                   f"vehicle (x1) from weaker propulsion (x{r:.3f})" if eff[1] > abs(r - 1.0) / 2.0 else
                   f"the roll/pitch effectiveness x{eff[0]:.3f} ± {eff[1]:.3f} lies within one se of halfway "
                   f"between a heavier vehicle (x1) and changed propulsion (x{r:.3f})")
            return "thrust per mass", f"thrust per mass x{r:.3f} ± {kt[1]:.3f}; mass and thrust not told apart: {why}"
        if abs(eff[0] - 1.0) < abs(eff[0] - r):
            return "mass", (f"thrust per mass x{r:.3f} ± {kt[1]:.3f} with the roll/pitch effectiveness T_max/I "
                            f"unchanged (x{eff[0]:.3f} ± {eff[1]:.3f}): mass x{1 / r:.3f} "
                            f"({100 * (1 / r - 1):+.0f} %), the thrust is the same")
        return "thrust", (f"thrust per mass x{r:.3f} ± {kt[1]:.3f} and roll/pitch effectiveness x{eff[0]:.3f} ± "
                          f"{eff[1]:.3f} together: the thrust changed (x{r:.3f}), not the mass")
    if _changed(eff, "rp_eff"):
        return "inertia", (f"roll/pitch effectiveness T_max/I x{eff[0]:.3f} ± {eff[1]:.3f} with the thrust per mass "
                           f"unchanged: inertia x{1 / eff[0]:.3f} (mass hung away from the centre of mass?)")
    return None


def _yaw(ratios: dict) -> tuple[str, str] | None:
    """The yaw effectiveness T_max km/Izz, where a thrust change does not explain it."""
    y, kt, eff = ratios.get("yaw_eff"), ratios.get("kt_per_mass"), _eff(ratios)
    if not _changed(y, "yaw_eff"):
        return None
    if _changed(kt, "kt_per_mass") and eff and abs(eff[0] - kt[0]) < abs(eff[0] - 1) \
            and abs(y[0] - kt[0]) < 3 * math.hypot(y[1], kt[1]):
        return None  # the thrust changed and the yaw moment with it
    return "yaw moment", f"yaw effectiveness x{y[0]:.3f} ± {y[1]:.3f}: the rotors' yaw moment (propellers)"


def _motor_or_com(deltas: dict) -> tuple[str, str] | None:
    shares = {k: d for k, d in deltas.items() if k.startswith("motor_share_m")}
    if len(shares) >= 3:
        # the shares are normalised to a mean of 1: one motor's change moves each other share by -1/(n-1) of it,
        # so a single motor stands out as its change against the others' mean, the others moving together
        v = np.array([d[0] for d in shares.values()])
        contrast = np.array([v[i] - np.delete(v, i).mean() for i in range(v.size)])
        i = int(np.argmax(np.abs(contrast)))
        others = np.delete(v, i)
        spread = float(np.abs(others - others.mean()).max())
        if abs(contrast[i]) > 0.05 and spread < abs(contrast[i]) / 4:
            motor = list(shares)[i].rsplit("_m", 1)[1]
            factor = (1 + others.mean()) / (1 + v[i])   # its thrust per command, new over old
            why = (f"motor {motor}'s share of the steady-flight thrust command {'up' if contrast[i] > 0 else 'down'} "
                   f"by {100 * abs(contrast[i]):.1f} % against the others' (which moved together, within "
                   f"{100 * spread:.1f} %): ")
            if contrast[i] > 0:
                return f"weaker motor {motor}", why + f"it gives less thrust per command (efficiency about {factor:.2f})"
            return f"stronger motor {motor}", why + (f"it gives more thrust per command than before (x{factor:.2f}: a "
                                                     "weak motor or propeller replaced?)")
    com = [(k, d) for k, d in deltas.items() if k.startswith("com_") and abs(d[0]) > 3 * max(d[1], 1e-9)]
    if com:
        return "centre-of-mass shift", "; ".join(f"{k[4:6]} {1000 * d[0]:+.1f} ± {1000 * d[1]:.1f} mm" for k, d in com)
    return None


def local_offset_h(rows: list[dict]) -> float | None:
    """Hours between the file-name time (QGroundControl's downloader, local time) and UTC, the median over
    the rows that have both a UTC date (header or GPS) and a file-name time; None when none has both."""
    offs = []
    for r in rows:
        if r.get("file_name_time") and r.get("date_source") in ("time_ref_utc", "gps"):
            try:
                a = _dt.datetime.fromisoformat(r["file_name_time"])
                b = _dt.datetime.fromisoformat(r["flight_time_utc"]).replace(tzinfo=None)
            except (TypeError, ValueError):
                continue
            offs.append((a - b).total_seconds() / 3600.0)
    return round(float(np.median(offs)) * 4) / 4 if offs else None


def when_utc(row: dict, offset_h: float | None) -> str:
    """The flight's UTC time: a file-name date is corrected by the vehicle's ``offset_h`` (stated)."""
    t = row.get("flight_time_utc") or ""
    if row.get("date_source") == "file_name" and offset_h is not None and t:
        try:
            d = _dt.datetime.fromisoformat(t) - _dt.timedelta(hours=offset_h)
            return d.replace(tzinfo=_dt.timezone.utc).isoformat(timespec="seconds")
        except ValueError:
            return t
    return t
