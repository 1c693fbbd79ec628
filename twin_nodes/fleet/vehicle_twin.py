"""One twin per vehicle: the identification pooled over several of its flights (issue 25).

``rotortwin params from-ulog A.ulg B.ulg ... --out vehicle.yaml``: every log is classified
(:func:`twin_nodes.fleet.facts.flight_kind`); each free flight gets its nominal
(:func:`twin_nodes.identify.nominal.nominal_from_log`, one mass for all: the one given, else the airframe's
assumed mass) and its values (:func:`twin_nodes.fleet.facts.identified`).  Per value:

- the twin is the vehicle *as it last flew*: the flights are put in date order (UTC; a file-name date corrected by
  the vehicle's local offset, as the fleet report does), a flight of another motor configuration than the latest
  flight's is left out of every value (named; :func:`twin_nodes.fleet.facts.same_configuration`: its motors on other
  outputs, another wiring whose trims are another's, or another PWM range, where the same command is another
  thrust), and so is every flight
  before the vehicle's latest change (a step of the thrust per mass or of a trim on at least two flights in a row,
  :func:`twin_nodes.fleet.changes.find_all`; named with the value that stepped).  ``state="all"`` pools every
  flight of the majority's configuration instead (the earlier behaviour); ``like`` the flights of a given one;
- a flight beyond ``max(3 x 1.4826 MAD, 3 se, floor)`` of the median is *disagreeing*: named, not averaged in;
- where the flights kept disagree beyond their own uncertainty (:func:`agreement`: chi^2 about their se-weighted
  mean above its 99.73 % quantile), the header names every flight's value ± se and the JSON says ``consistent``
  false; a sag exponent so pooled is still flown (its mean: without one, or with 1, the twin predicted the shared
  fleet's later flights worse, docs/fleet.md sag12), with the thrust uncertainty it carries per volt stated, and
  :func:`since_twin` widens its band by it;
- the pooled value is the mean of the others, its uncertainty the scatter / sqrt(n) (at least the mean se),
  and the flight-to-flight scatter is reported beside it.

The params are those of the flight closest to the pooled thrust per mass, with the pooled thrust (brought to one
pack voltage with the pooled sag where that exponent comes from two flights or more, :func:`at_one_voltage`),
inertia, lag, drag and trims (centre of mass and yaw lever) put in and no wind (that flight's weather); the header lists every value with its uncertainty, scatter and the flights it
came from, and one machine-readable line (:data:`MARK`) that ``discover --params`` reads back
(:func:`read_vehicle_facts`).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twin_nodes.base.errors import ParamsError, TwinError
from twin_nodes.fleet.facts import shares_outputs
from twin_nodes.identify.from_log import airborne_mask
from twin_nodes.vehicle.params import VehicleParams, from_ros_dict

#: header line prefix of the pooled values (JSON after it)
MARK = "vehicle-twin-facts: "
#: pooled values: name -> absolute floor of the disagreement threshold (relative floor 5 % for all)
POOLED = {"kt_per_mass": 0.0, "hover_throttle": 0.0, "rp_eff": 0.0, "roll_eff": 0.0, "pitch_eff": 0.0, "yaw_eff": 0.0,
          "drag_per_mass": 0.02, "com_dx_m": 0.004, "com_dy_m": 0.004, "yaw_lever_m": 0.002, "tau_s": 0.02,
          "battery_exponent": 0.2, "hover_thrust_px4": 0.0}
REL_FLOOR = 0.05


@dataclass
class Pooled:
    value: str
    mean: float
    se: float
    scatter: float
    n: int
    flights: list[str] = field(default_factory=list)
    disagreeing: list[str] = field(default_factory=list)  # "name (value)"
    #: chi^2 of the pooled flights about their se-weighted mean and its degrees of freedom (n - 1); ``consistent``
    #: False where the flights disagree beyond their uncertainty (:func:`agreement`)
    chi2: float = math.nan
    dof: int = 0
    consistent: bool = True
    spread: list[str] = field(default_factory=list)  # "name x ± se" of each flight where not consistent


@dataclass
class VehicleTwin:
    params: VehicleParams
    pooled: dict[str, Pooled]
    used: list[str]
    left_out: list[str]  # "path: why"
    pwm: dict
    header: str


def pool(value: str, names: list[str], x: list[float], se: list[float]) -> Pooled | None:
    """Pool one value over flights (see the module docstring); None with fewer than one finite value."""
    x_ = np.asarray(x, float)
    se_ = np.asarray(se, float)
    ok = np.isfinite(x_)
    if not ok.any():
        return None
    med = float(np.median(x_[ok]))
    mad = 1.4826 * float(np.median(np.abs(x_[ok] - med)))
    out = Pooled(value, math.nan, math.nan, math.nan, 0)
    keep = []
    for i in np.flatnonzero(ok):
        lim = max(3 * mad, 3 * (se_[i] if math.isfinite(se_[i]) else 0.0), REL_FLOOR * abs(med),
                  POOLED.get(value, 0.0))
        if abs(x_[i] - med) > lim and ok.sum() >= 3:
            out.disagreeing.append(f"{names[i]} ({x_[i]:.4g} vs {med:.4g})")
        else:
            keep.append(i)
    v = x_[keep]
    out.mean = float(v.mean())
    out.scatter = float(v.std(ddof=1)) if v.size > 1 else math.nan
    mean_se = float(np.nanmean(se_[keep])) if np.isfinite(se_[keep]).any() else 0.0
    out.se = max(out.scatter / math.sqrt(v.size) if v.size > 1 else math.nan, mean_se / math.sqrt(v.size)) \
        if v.size > 1 else (mean_se or math.nan)
    out.n = int(v.size)
    out.flights = [names[i] for i in keep]
    floor = max(REL_FLOOR * abs(med), POOLED.get(value, 0.0)) / 3.0
    out.chi2, out.dof, out.consistent = agreement(v, se_[keep], floor)
    if not out.consistent:
        out.spread = [f"{names[i]} {x_[i]:.4g} ± {se_[i]:.2g}" for i in keep]
    return out


#: the flights of a pooled value disagree beyond their uncertainty where the chi^2 about their weighted mean
#: exceeds its quantile at this probability (3 sigma two-sided: two flights 3 combined se apart)
AGREE_P = 0.9973


def agreement(x: np.ndarray, se: np.ndarray, se_floor: float = 0.0) -> tuple[float, int, bool]:
    """(chi^2, dof, consistent): whether values of several flights agree within their uncertainties ``se`` (each
    at least ``se_floor``, the agreement floor of :func:`pool` / 3).  chi^2 = sum((x - x_w)^2 / se^2) about the
    se-weighted mean x_w on n - 1 degrees of freedom, consistent while below its :data:`AGREE_P` quantile (two
    flights: |x1 - x2| <= 3 sqrt(se1^2 + se2^2)).  One value, or no finite se: (NaN, 0, True), nothing to test."""
    from scipy.stats import chi2 as chi2_dist

    x = np.asarray(x, float)
    s = np.maximum(np.asarray(se, float), se_floor)
    ok = np.isfinite(x) & np.isfinite(s) & (s > 0)
    if ok.sum() < 2:
        return math.nan, 0, True
    w = 1.0 / s[ok] ** 2
    xw = float((w * x[ok]).sum() / w.sum())
    c2 = float((w * (x[ok] - xw) ** 2).sum())
    dof = int(ok.sum()) - 1
    return c2, dof, bool(c2 <= chi2_dist.ppf(AGREE_P, dof))


#: the values whose step marks a change of the vehicle for :func:`select` (thrust per mass: payload, propulsion,
#: PWM range; the roll/pitch trims: where the load hangs)
STATE_VALUES = ("kt_per_mass", "com_dx_m", "com_dy_m")


def select(flights: list[dict], state: str = "latest", like: dict | None = None) -> tuple[list[dict], list[str], str]:
    """The flights to pool (see the module docstring), the left-out lines ("path: why") and one line on the choice.
    ``flights``: dicts with ``path``, ``name``, ``when`` (UTC ISO text, '' unknown), ``pwm``
    (:func:`~twin_nodes.fleet.facts.motor_pwm`) and ``facts``.  The configuration (which outputs drive the motors
    and their PWM limits, :func:`~twin_nodes.fleet.facts.same_configuration`) is the latest flight's, the
    majority's (``state="all"``), or that of ``like`` (a motor_pwm dict: the twin of that configuration)."""
    from twin_nodes.fleet.facts import same_configuration

    if state not in ("latest", "all"):
        raise TwinError(f"vehicle twin: state {state!r}: expected 'latest' or 'all'")
    flights = sorted(flights, key=lambda f: (f.get("when") or "", f["path"]))
    if like is not None:
        key = like
        note = f"the flights of the configuration {key['text']}"
    elif state == "all":
        configs = configurations(flights)
        key = max(configs, key=lambda c: (len(c), c[-1].get("when") or ""))[-1]["pwm"]
        note = f"every flight of the majority's configuration ({key['text']})"
    else:
        key = flights[-1]["pwm"]
        note = f"the vehicle as it last flew ({flights[-1]['name']}, {flights[-1].get('when') or 'undated'})"
    out, same = [], []
    for f in flights:
        ok, why = same_configuration(key, f["pwm"])
        if ok:
            same.append(f)
        else:
            out.append(f"{f['path']}: {why}")
    if state == "latest" and len(same) >= 3:
        from twin_nodes.fleet.changes import find_all

        series = find_all({v: ([f["facts"].get(v, math.nan) for f in same],
                               [f["facts"].get(f"{v}_se", math.nan) for f in same]) for v in STATE_VALUES})
        starts = [(st.first, v) for v, ser in series.items() for st in ser.steps]
        if starts:
            first, value = max(starts)
            out += [f"{f['path']}: before the vehicle's latest change ({value} stepped at {same[first]['name']})"
                    for f in same[:first]]
            note += f"; since its latest change at {same[first]['name']} ({value} stepped)"
            same = same[first:]
    return same, out, note


def configurations(flights: list[dict]) -> list[list[dict]]:
    """The flights grouped by configuration (:func:`~twin_nodes.fleet.facts.same_configuration` with each
    group's first flight), in the order met."""
    from twin_nodes.fleet.facts import same_configuration

    groups: list[list[dict]] = []
    for f in flights:
        g = next((g for g in groups if same_configuration(g[0]["pwm"], f["pwm"])[0]), None)
        if g is None:
            groups.append([f])
        else:
            g.append(f)
    return groups


def date_flights(flights: list[dict]) -> None:
    """Each flight's UTC time (``when``) from its header (or GPS, or file name corrected by the local offset)."""
    from twin_nodes.fleet.changes import local_offset_h, when_utc
    from twin_nodes.fleet.identity import identity

    rows = []
    for f in flights:
        try:
            rows.append(identity(f["path"]))
        except TwinError:
            rows.append({})
    off = local_offset_h(rows)
    for f, r in zip(flights, rows):
        f["when"] = when_utc(r, off) if r else ""


def build(paths: list[str | os.PathLike[str]], *, mass_kg: float | None = None, arm_m: float | None = None,
          name: str | None = None, state: str = "latest", like: dict | None = None) -> VehicleTwin:
    """The vehicle twin of the free flights among ``paths`` (see the module docstring; ``like``: the twin of
    that motor configuration, :func:`select`)."""
    flights, left_out = read_flights(paths, mass_kg=mass_kg, arm_m=arm_m, name=name)
    return from_flights(flights, left_out, state=state, like=like)


def read_flights(paths: list[str | os.PathLike[str]], *, mass_kg: float | None = None, arm_m: float | None = None,
                 name: str | None = None) -> tuple[list[dict], list[str]]:
    """Every free flight among ``paths`` identified (one dict each, dated) and the left-out lines; refuses logs of
    more than one vehicle."""
    from twin_nodes.fleet.facts import actuator_tests, flight_kind, identified, motor_pwm
    from twin_nodes.identify.nominal import nominal_from_log
    from twin_nodes.logs.ulog_io import read_ulog

    flights, left_out, ids = [], [], set()
    for p in paths:
        log = read_ulog(p)
        ids.add((log.info.get("sys_uuid") or "", log.info.get("ver_hw") or "", log.params.get("SYS_AUTOSTART")))
        kind, why = flight_kind(log, actuator_tests(p))
        if kind != "free flight":
            left_out.append(f"{p}: {kind}: {why}")
            continue
        try:
            nom = nominal_from_log(log, mass_kg=mass_kg, arm_m=arm_m, name=name)
        except TwinError as exc:
            left_out.append(f"{p}: not identified: {exc}")
            continue
        flights.append({"path": str(p), "name": f"{Path(p).parent.name}/{Path(p).name}", "nom": nom, "facts": identified(log, nom),
                        "pwm": motor_pwm(log.params, int(log.n_motors)), "kt_v": thrust_voltage(log, nom)})
    if len(ids) > 1:
        raise TwinError("params from-ulog: the logs come from more than one vehicle (sys_uuid, ver_hw, "
                        f"SYS_AUTOSTART): {sorted(map(str, ids))}; pool the flights of one vehicle")
    if not flights:
        raise TwinError("params from-ulog: no free flight among the logs to identify on: "
                        + " | ".join(left_out))
    date_flights(flights)
    return flights, left_out


def from_flights(flights: list[dict], left_out: list[str], *, state: str = "latest",
                 like: dict | None = None) -> VehicleTwin:
    """The vehicle twin pooled over the flights :func:`select` keeps of ``flights`` (from :func:`read_flights`)."""
    flights, dropped, state_note = select(flights, state, like)
    left_out = left_out + dropped
    if not flights:
        raise TwinError("params from-ulog: no free flight of the configuration " + (like or {}).get("text", "?"))
    pooled = {}
    for v in POOLED:
        res = pool(v, [f["name"] for f in flights], [f["facts"].get(v, math.nan) for f in flights],
                   [f["facts"].get(f"{v}_se", math.nan) for f in flights])
        if res is not None:
            pooled[v] = res
    pwm = flights[-1]["pwm"]
    at_v = at_one_voltage(flights, pooled)
    if at_v is not None:
        pooled["kt_per_mass_at_v_ref"], pooled["kt_v_ref"] = at_v
    vp = _params(flights, pooled)
    return VehicleTwin(vp, pooled, [f["path"] for f in flights], left_out, pwm,
                       _header(vp, pooled, flights, left_out, pwm, state_note))


def _params(flights: list[dict], pooled: dict[str, Pooled]) -> VehicleParams:
    kt = pooled["kt_per_mass"].mean
    rep = min(flights, key=lambda f: abs(f["facts"]["kt_per_mass"] - kt))["nom"]
    d = rep.params.to_ros_dict()
    m = float(d["vehicle"]["mass_kg"])
    eff = d["effects"]
    if "kt_per_mass_at_v_ref" in pooled:  # the thrust at one pack voltage, with the pooled sag (at_one_voltage)
        kt = pooled["kt_per_mass_at_v_ref"].mean
        _enable(eff, "battery_sag", {"v_ref": pooled["kt_v_ref"].mean, "exponent": pooled["battery_exponent"].mean})
    # the wind the representative flight met is that day's weather, not the vehicle's: the twin flies in still air
    _enable(eff, "wind", None)
    t_max = m * kt
    d["rotors"]["thrust_max_n"] = t_max
    for ax, key in (("roll_eff", "ixx_kg_m2"), ("pitch_eff", "iyy_kg_m2")):
        if ax in pooled and pooled[ax].mean > 0:
            i = t_max / pooled[ax].mean
            arm = float(np.median(np.hypot(d["rotors"]["x_flu_m"], d["rotors"]["y_flu_m"])))
            if 0.05 * m * arm ** 2 <= i <= 0.6 * m * arm ** 2:  # the rigid-frame range nominal_from_log accepts
                d["vehicle"][key] = float(i)
    if "tau_s" in pooled and math.isfinite(pooled["tau_s"].mean):
        d["rotors"]["tau_up_s"] = d["rotors"]["tau_down_s"] = pooled["tau_s"].mean
    if "linear_drag" in eff and "drag_per_mass" in pooled:
        eff["linear_drag"]["k_n_s_m"] = pooled["drag_per_mass"].mean * m
    # the static trims are the pooled ones (roll/pitch as a centre of mass, yaw as a rotor tilt), not the
    # representative flight's: on this fleet its yaw lever alone cost up to 5 points of per-motor P75
    if "com_dx_m" in pooled and "com_dy_m" in pooled:
        _enable(eff, "com_offset", {"dx": pooled["com_dx_m"].mean, "dy": pooled["com_dy_m"].mean})
    if "yaw_lever_m" in pooled and math.isfinite(pooled["yaw_lever_m"].mean):
        _enable(eff, "rotor_tilt", {"lever_m": pooled["yaw_lever_m"].mean})
    d["vehicle"]["name"] = f"vehicle_twin_{len(flights)}_flights"
    return from_ros_dict(d, "<vehicle twin>")


def _enable(eff: dict, name: str, values: dict | None) -> None:
    """Put the effect ``name`` with ``values`` into the effects dict ``eff`` (None: take it out)."""
    eff.pop(name, None)
    if name in eff["enabled"]:
        eff["enabled"].remove(name)
    if values is not None:
        eff["enabled"].append(name)
        eff[name] = dict(values)


def thrust_voltage(log, nom) -> float:
    """The pack voltage a flight's thrust per mass refers to: the nominal's battery-sag reference where it has one
    (T = T_max (V/V_ref)^e), else the median pack voltage while airborne (a thrust fit without a sag term averages
    over the flight), NaN without a voltage trace."""
    eff = nom.params.to_ros_dict()["effects"] if nom is not None else {}
    if "battery_sag" in eff.get("enabled", ()):
        return float(eff["battery_sag"]["v_ref"])
    bv = log.get("battery_v")
    if bv is None or not len(bv):
        return math.nan
    v = bv.values[:, 0]
    v = v[airborne_mask(log, bv.t_s) & np.isfinite(v) & (v > 0.1)]
    return float(np.median(v)) if v.size else math.nan


#: the pooled sag exponent is used (the thrust brought to one voltage, the twin's sag) from this many flights on
SAG_MIN_FLIGHTS = 2


def at_one_voltage(flights: list[dict], pooled: dict[str, Pooled]) -> tuple[Pooled, Pooled] | None:
    """The thrust per mass of every flight brought to one pack voltage before pooling: each flight's value refers to
    its own voltage (:func:`thrust_voltage`: 10.4 V on a flight that ends its pack, 12.1 V on a fresh one), and at
    the pooled sag exponent e the thrust scales as (V/V_ref)^e, so a pooled mean of raw values is the thrust at no
    voltage in particular.  Returns (thrust per mass at ``V_ref``, ``V_ref`` = the median of the flights' voltages)
    as :class:`Pooled` values, None where the sag exponent is pooled from fewer than :data:`SAG_MIN_FLIGHTS`
    flights (one flight's exponent, e.g. 2.65 where this fleet's flights read 0.7-2.1, flown on a pack 1 V below its reference,
    lost a 26 Jun mission its height) or no flight has a voltage."""
    e = pooled.get("battery_exponent")
    v = np.array([f.get("kt_v", math.nan) for f in flights], float)
    if e is None or not math.isfinite(e.mean) or e.n < SAG_MIN_FLIGHTS or not np.isfinite(v).any():
        return None
    v_ref = float(np.median(v[np.isfinite(v)]))
    kt = [f["facts"].get("kt_per_mass", math.nan) * (v_ref / vi) ** e.mean if math.isfinite(vi) else math.nan
          for f, vi in zip(flights, v)]
    se = [f["facts"].get("kt_per_mass_se", math.nan) for f in flights]
    at = pool("kt_per_mass_at_v_ref", [f["name"] for f in flights], kt, se)
    vr = pool("kt_v_ref", [f["name"] for f in flights], list(v), [0.0] * len(flights))
    if at is None or vr is None:
        return None
    vr.mean = v_ref
    vr.chi2, vr.dof, vr.consistent, vr.spread = math.nan, 0, True, []  # a reference voltage, not a measured value
    return at, vr


def _header(vp: VehicleParams, pooled: dict[str, Pooled], flights: list[dict], left_out: list[str],
            pwm: dict, state_note: str = "") -> str:
    lines = [f"Vehicle twin pooled over {len(flights)} free flight(s) by 'rotortwin params from-ulog'"
             + (f": {state_note}." if state_note else "."),
             f"Motor PWM range of these flights: {pwm['text']}.",
             f"Mass {vp.mass_kg:g} kg (given or the airframe's assumed mass; thrust and inertia scale with it).",
             "Pooled values (mean ± uncertainty, flight-to-flight scatter, flights):"]
    for v, p in pooled.items():
        lines.append(f"  {v}: {p.mean:.5g} ± {p.se:.2g}, scatter {p.scatter:.2g}, n {p.n}"
                     + (f"; disagreeing, not averaged in: {', '.join(p.disagreeing)}" if p.disagreeing else "")
                     + ("" if p.consistent else f"; the flights disagree beyond their uncertainty (chi^2 {p.chi2:.3g} "
                        f"on {p.dof} dof: {', '.join(p.spread)})"))
    e, vr = pooled.get("battery_exponent"), pooled.get("kt_v_ref")
    if e is not None and vr is not None and not e.consistent:
        one_v = abs(math.log((vr.mean - 1.0) / vr.mean)) * e.scatter
        lines.append(f"The sag exponent's flights disagree: the twin flies their mean {e.mean:.3g} (without a sag, "
                     f"or with 1, it predicted later flights worse, docs/fleet.md sag12); a flight's thrust per mass at "
                     f"a pack voltage V carries ± |ln(V/{vr.mean:.2f} V)| x {e.scatter:.2g} (the exponent's scatter) "
                     f"of it, ± {one_v:.0%} 1 V below; discover --params widens its band by that")
    lines.append("Flights: " + ", ".join(f["path"] for f in flights))
    for lo in left_out:
        lines.append(f"Left out: {lo}")
    lines.append("Params of the flight closest to the pooled thrust per mass, with the pooled thrust (at one pack "
                 "voltage where kt_per_mass_at_v_ref is listed), inertia, lag, drag and trims, and no wind. Its own "
                 "sources:")
    rep = min(flights, key=lambda f: abs(f["facts"]["kt_per_mass"] - pooled["kt_per_mass"].mean))["nom"]
    lines += [f"  {k}: {s}" for k, s in rep.sources.items()]
    facts = {v: {"mean": p.mean, "se": p.se, "scatter": p.scatter, "n": p.n, "consistent": p.consistent}
             for v, p in pooled.items()}
    lines.append(MARK + json.dumps({"pooled": facts, "pwm": pwm, "flights": [f["path"] for f in flights],
                                    "motor_share": _shares(flights)}, default=float, allow_nan=True))
    return "\n".join(lines)


def _shares(flights: list[dict]) -> dict[str, float]:
    keys = sorted({k for f in flights for k in f["facts"] if k.startswith("motor_share_m")})
    return {k: float(np.nanmedian([f["facts"].get(k, math.nan) for f in flights])) for k in keys}


def read_vehicle_facts(path: str | os.PathLike[str]) -> dict | None:
    """The pooled values a vehicle twin's params file carries (:data:`MARK`), None for other params files."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError:  # not text: no vehicle twin (load_params names what is wrong with it)
        return None
    except OSError as exc:
        raise ParamsError(str(path), "<file>", f"a readable params file ({exc.strerror or exc})") from None
    for line in text.splitlines():
        if line.startswith("# " + MARK):
            try:
                return json.loads(line[2 + len(MARK):])
            except ValueError:
                raise ParamsError(str(path), MARK.strip(), "expected the JSON line written by params from-ulog") from None
        if not line.startswith("#"):
            break
    return None


#: a value differs from the vehicle twin beyond this many sigmas (scatter and the flight's se together)
DIFF_SIGMA = 3.0


def since_twin(log, path: str, ref: dict) -> dict:
    """What differs on the flight ``log`` from the vehicle twin's pooled values ``ref`` (as
    :func:`read_vehicle_facts` returns them): ``{"name", "why", "differs": {value: {...}}, "pwm": [...]}``,
    named by :func:`twin_nodes.fleet.changes.explain`; ``name`` is ``none`` when nothing differs."""
    from twin_nodes.fleet.changes import TRACKED, explain, half_width
    from twin_nodes.fleet.facts import actuator_tests, flight_kind, identified, motor_pwm

    kind, why = flight_kind(log, actuator_tests(path))
    if kind != "free flight":
        return {"name": "not compared", "why": f"{kind}: {why}", "differs": {}, "pwm": None}
    from twin_nodes.identify.nominal import nominal_from_log

    try:
        nom = nominal_from_log(log)
    except TwinError:  # params that fail validation: identified() keeps the fits, the voltage is the median's
        nom = None
    new = identified(log, nom)
    pwm_new = motor_pwm(log.params, int(log.n_motors))
    pwm_ref = ref.get("pwm") or {}
    pooled = dict(ref.get("pooled") or {})
    v_flight = thrust_voltage(log, nom)
    values = {k: v for k, v in new.items() if not k.endswith("_se")}
    at_v, at_v_se = _at_twin_voltage(new, v_flight, pooled)
    if at_v is not None:  # compared at the twin's one pack voltage, not at the flight's own, with what that costs
        se0 = new.get("kt_per_mass_se", math.nan)
        new = dict(new, kt_per_mass=at_v, kt_per_mass_se=math.hypot(se0 if math.isfinite(se0) else 0.0, at_v_se))
        pooled["kt_per_mass"] = pooled["kt_per_mass_at_v_ref"]
    wiring = ""
    if pwm_ref.get("outputs") and pwm_new["outputs"] and not shares_outputs(pwm_ref, pwm_new):
        from twin_nodes.fleet.facts import assignment_text

        # another wiring: its trims and motor shares are another configuration's, not compared as if unchanged
        wiring = (f"motor outputs {assignment_text(pwm_ref)} in the twin, {assignment_text(pwm_new)} in this log "
                  "(another wiring: trims and motor shares not compared)")
        pooled = {k: v for k, v in pooled.items() if not k.startswith(("com_", "yaw_lever"))}
    pwm = None
    if pwm_ref.get("text") and pwm_new["text"] != pwm_ref["text"]:
        a, b = (pwm_ref.get("max_us", math.nan) - pwm_ref.get("min_us", math.nan),
                pwm_new["max_us"] - pwm_new["min_us"])
        pwm = (a, b) if math.isfinite(a) and math.isfinite(b) and a != b else None
    ratios, deltas, differs = {}, {}, {}
    for v, p in pooled.items():
        x = new.get(v)
        if x is None or not math.isfinite(x) or not math.isfinite(p.get("mean", math.nan)):
            continue
        sc = p["scatter"] if math.isfinite(p.get("scatter", math.nan)) else 0.0
        se = math.hypot(sc, new.get(f"{v}_se", 0.0) if math.isfinite(new.get(f"{v}_se", math.nan)) else 0.0)
        h = half_width(p["mean"], se, 0.0, TRACKED.get(v, (0.05, 0.0))) * DIFF_SIGMA / 3.0
        if v.startswith("com_"):
            deltas[v] = (x - p["mean"], se)
        elif p["mean"]:
            ratios[v] = (x / p["mean"], se / abs(p["mean"]))
        if abs(x - p["mean"]) > h and v in TRACKED:
            differs[v] = {"twin": p["mean"], "flight": x, "band": h}
    for k, s in ({} if wiring else ref.get("motor_share") or {}).items():
        if k in new and math.isfinite(new[k]) and math.isfinite(s):
            deltas[k] = (new[k] - s, 0.01)
    name, why = explain(ratios, deltas, pwm, stepped=set(differs))
    if not differs and pwm is None and name in ("unexplained",):
        name, why = "none", "every value within the vehicle twin's flight-to-flight scatter"
    if wiring:
        why = f"{why}; {wiring}"
    return {"name": name, "why": why, "differs": differs, "pwm": [pwm_ref.get("text"), pwm_new["text"]],
            "kt_per_mass_at_twin_v": at_v, "kt_per_mass_at_twin_v_se": at_v_se, "kt_v_flight": v_flight, "values": values}


def _at_twin_voltage(new: dict, v: float, pooled: dict) -> tuple[float | None, float]:
    """A flight's thrust per mass (at its own pack voltage ``v``) brought to the twin's one voltage with the twin's
    sag exponent (as :func:`at_one_voltage` pooled it), and the uncertainty that carrying adds: x |ln(V_ref/v)|
    sigma_e, sigma_e the exponent's se, or its flight-to-flight scatter where its flights disagree beyond their
    uncertainty (a new flight's exponent may lie anywhere in that spread).  (None, 0) where the twin has no such
    voltage or the flight no voltage."""
    at, vr, e = (pooled.get(k) or {} for k in ("kt_per_mass_at_v_ref", "kt_v_ref", "battery_exponent"))
    x = new.get("kt_per_mass", math.nan)
    vals = (at.get("mean", math.nan), vr.get("mean", math.nan), e.get("mean", math.nan), v, x)
    if not all(math.isfinite(a) for a in vals) or v <= 0:
        return None, 0.0
    at = float(x * (vr["mean"] / v) ** e["mean"])
    sig = e.get("scatter", math.nan) if e.get("consistent") is False else e.get("se", math.nan)
    return at, (abs(at * math.log(vr["mean"] / v)) * sig if math.isfinite(sig) else 0.0)


def for_flight(vp: VehicleParams, ref: dict | None, log) -> tuple[VehicleParams, str]:
    """The vehicle twin ``vp`` as it flies ``log``: where the log's motor PWM range differs from the twin's
    (``ref["pwm"]``), the same command reaches another PWM, so the thrust curve is rescaled by the span ratio
    ``r``: T(u) = T_max (f (r u)^2 + (1 - f) r u), i.e. ``thrust_max_n`` x (f r^2 + (1 - f) r) and ``thr_mdl_fac``
    f r^2 / (f r^2 + (1 - f) r).  Where the log's motors are on other outputs (another wiring,
    :func:`~twin_nodes.fleet.facts.same_configuration`), the twin's yaw trim (a rotor tilt) is taken out: it
    belongs to the wiring (on the shared real fleet it changed sign with it), and none is nearer than the other's.
    Returns the params and a one-line note ('' when unchanged)."""
    from twin_nodes.fleet.facts import assignment_text, motor_pwm

    if not ref or not ref.get("pwm"):
        return vp, ""
    new = motor_pwm(log.params, int(log.n_motors))
    old = ref["pwm"]
    notes = []
    if old.get("outputs") and new["outputs"] and not shares_outputs(old, new):
        if "rotor_tilt" in vp.to_ros_dict()["effects"].get("enabled", ()):
            d = vp.to_ros_dict()
            _enable(d["effects"], "rotor_tilt", None)
            vp = from_ros_dict(d, "<vehicle twin>")
        notes.append(f"motor outputs {assignment_text(old)} in the twin, {assignment_text(new)} in this log: "
                     "another wiring, flown without the twin's yaw trim")
    a = old.get("max_us", math.nan) - old.get("min_us", math.nan)
    b = new["max_us"] - new["min_us"]
    if new["text"] != old.get("text") and math.isfinite(a) and math.isfinite(b) and a != b:
        r = b / a
        f = float(vp.rotors.thr_mdl_fac)
        scale = f * r * r + (1 - f) * r
        f_new = f * r * r / scale if scale > 0 else f
        vp = vp.replace_rotors(thrust_max_n=float(vp.rotors.thrust_max_n) * scale, thr_mdl_fac=float(f_new))
        notes.append(f"motor PWM range {old.get('text')} in the twin, {new['text']} in this log: thrust curve "
                     f"rescaled by the span ratio {r:.3f} (T_max x{scale:.3f})")
    return vp, "; ".join(notes)


#: whole-flight metrics shown for a vehicle twin beside a flight's own nominal
WHOLE = ("throttle_rmse", "motor_p75_mean", "xy_rmse_m", "z_rmse_m")


def beside_own_nominal(path: str, params_file: str) -> dict:
    """The whole flight flown closed loop by the vehicle twin (rescaled to the log's PWM range) and by the flight's
    own nominal: ``{"twin": {metric: value}, "own_nominal": {...}, "note"}`` (:data:`WHOLE`)."""
    from twin_nodes.identify.nominal import params_for_log
    from twin_nodes.logs.flyable import read_flight
    from twin_nodes.twin.compare import compare_log
    from twin_nodes.vehicle.params import load_params

    log = read_flight(path)
    vp, note = for_flight(load_params(params_file), read_vehicle_facts(params_file), log)
    own, _ = params_for_log(path, None, log=log)
    mt = compare_log(log, vp, mode="closed").metrics
    mo = compare_log(log, load_params(own), mode="closed").metrics
    return {"twin": {k: mt.get(k) for k in WHOLE}, "own_nominal": {k: mo.get(k) for k in WHOLE}, "note": note}


def beside_table(rows: list[dict]) -> str:
    """Markdown: per flight, the vehicle twin's whole-flight metrics beside its own nominal's."""
    out = ["| flight | vehicle twin: throttle RMSE % | per-motor P75 % (mean) | XY RMSE m | Z RMSE m | own nominal: "
           "throttle | P75 | XY | Z |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w = r.get("whole_flight")
        if not w:
            continue
        if "error" in w:
            out.append(f"| {r['flight']} | failed: {w['error']} | | | | | | | |")
            continue
        t, o = w["twin"], w["own_nominal"]
        f = lambda d, k, s: f"{d[k] * s:.1f}" if isinstance(d.get(k), float) and d[k] == d[k] else "n/a"  # noqa: E731
        out.append(f"| {r['flight']} | {f(t, 'throttle_rmse', 100)} | {f(t, 'motor_p75_mean', 100)} | "
                   f"{f(t, 'xy_rmse_m', 1)} | {f(t, 'z_rmse_m', 1)} | {f(o, 'throttle_rmse', 100)} | "
                   f"{f(o, 'motor_p75_mean', 100)} | {f(o, 'xy_rmse_m', 1)} | {f(o, 'z_rmse_m', 1)} |")
    return "\n".join(out)
