"""One vehicle across its flights, from the catalog's per-flight values (``fact_*`` columns): dated trends
with the flight-to-flight scatter band, firmware parameter changes as events, steps and what they mean
(:mod:`twin_nodes.fleet.changes`), and the alarms they back (issue 25).

An alarm here is a step: beyond the band on at least two flights in a row; it names the first flight,
the size with its uncertainty and the evidence (the values that stepped, the events at that flight).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twin_nodes.fleet import changes as ch
from twin_nodes.fleet.facts import FACTS, assignment_text, is_event, motor_pwm, param_changes, shares_outputs

#: values drawn per vehicle (tracked ones carry steps and alarms; the others are context)
SHOWN = ("kt_per_mass", "hover_throttle", "hover_thrust_px4", "rp_eff", "roll_eff", "pitch_eff", "yaw_eff",
         "drag_per_mass",
         "com_dx_m", "com_dy_m", "tau_s", "battery_v_start")


@dataclass
class Change:
    vehicle_id: str
    flight: str
    date: str
    name: str
    why: str
    values: list[dict] = field(default_factory=list)
    events: list[str] = field(default_factory=list)
    flights: list[str] = field(default_factory=list)


def _name(path: str) -> str:
    """A flight as the report names it: its folder and file name (``23_juni/log_15_...ulg``, ``s07/flight.ulg``)."""
    p = Path(path)
    return f"{p.parent.name}/{p.name}"


def _f(r: dict, k: str) -> float:
    v = r.get(k)
    try:
        return float(v) if v is not None else math.nan
    except (TypeError, ValueError):
        return math.nan


def ordered(rows: list[dict]) -> tuple[list[dict], float | None]:
    """One vehicle's rows (every status) in UTC order, a file-name date corrected by the vehicle's local
    offset (``_utc`` set on each row), and that offset [h]."""
    off = ch.local_offset_h(rows)
    for r in rows:
        r["_utc"] = ch.when_utc(r, off)
    return sorted(rows, key=lambda r: (r["_utc"], r["path"])), off


def events(rows: list[dict]) -> list[dict]:
    """Firmware parameter changes between consecutive logs of a vehicle (every log, flights or not):
    ``{"index", "flight", "date", "changes": {name: [before, after]}, "pwm": [old, new] or None}``; only the
    parameters of :func:`~twin_nodes.fleet.facts.is_event`."""
    out, prev, prev_pwm, prev_outs = [], None, None, None
    for i, r in enumerate(rows):
        try:
            p = json.loads(r.get("params_json") or "null")
        except (TypeError, ValueError):
            p = None
        if p is None:
            continue
        d = {k: v for k, v in param_changes(prev, p).items() if is_event(k)}
        pwm = r.get("motor_pwm") or ""
        outs = motor_pwm(p, MAX_MOTORS)
        moved = prev_pwm is not None and pwm != prev_pwm
        rewired = prev_outs is not None and not shares_outputs(prev_outs, outs)
        if d or moved or rewired:
            out.append({"index": i, "flight": _name(r["path"]), "date": r["_utc"], "changes": d,
                        "pwm": [prev_pwm, pwm] if moved else None,
                        "outputs": [assignment_text(prev_outs), assignment_text(outs)] if rewired else None})
        prev, prev_pwm, prev_outs = p, pwm, outs
    return out


#: motor functions read from a catalog row's parameters (PX4: Motor 1..8 = 101..108)
MAX_MOTORS = 8


def rewired_at(rows: list[dict], free: list[dict], ev: list[dict]) -> frozenset[int]:
    """The free flights (indices in ``free``) whose motors are on other outputs than the previous free flight's (an
    ``outputs`` event since it): another configuration, the values' references start again there."""
    out = set()
    for k in range(1, len(free)):
        a, b = rows.index(free[k - 1]), rows.index(free[k])
        if any(e.get("outputs") and a < e["index"] <= b for e in ev):
            out.add(k)
    return frozenset(out)


def _span(text: str) -> float | None:
    """Span [us] of a motor PWM text with one range for all motors, else None."""
    rng = {seg.rsplit(" ", 2)[1] for seg in text.split("; ") if seg.endswith(" us")}
    if len(rng) != 1:
        return None
    lo, hi = rng.pop().split("-")
    return float(hi) - float(lo)


def analyse_vehicle(vid: str, rows: list[dict]) -> dict:
    """Series, steps, changes and events of one vehicle (``rows``: all its catalog rows)."""
    rows, off = ordered(rows)
    ev = events(rows)
    free = [r for r in rows if r.get("flight_kind") == "free flight" and math.isfinite(_f(r, "fact_kt_per_mass"))]
    series, tracked = {}, {}
    for v in SHOWN:
        x = [_f(r, f"fact_{v}") for r in free]
        if sum(math.isfinite(a) for a in x) >= 2:
            if v in ch.TRACKED:
                tracked[v] = (x, [_f(r, f"fact_{v}_se") for r in free])
            else:
                series[v] = ch.Series(v, x, [_f(r, f"fact_{v}_se") for r in free], ch.scatter(np.asarray(x)))
    rewired = rewired_at(rows, free, ev)
    series.update(ch.find_all(tracked, rewired))
    series = {v: series[v] for v in SHOWN if v in series}
    starts = sorted({s.first for v, s_ in series.items() for s in s_.steps})
    groups: list[int] = []
    for s in starts:
        if not groups or s - groups[-1] > 1:
            groups.append(s)
    out_changes = [_change(vid, free, rows, series, ev, g, max([groups[k - 1] if k else 0]
                                                                + [r for r in rewired if r <= g]))
                   for k, g in enumerate(groups)]
    return {"vehicle_id": vid, "local_offset_h": off, "rows": rows, "free": free, "series": series,
            "events": ev, "changes": out_changes, "rewired": sorted(rewired)}


def _change(vid: str, free: list[dict], rows: list[dict], series: dict, ev: list[dict], g: int, prev: int) -> Change:
    """The change whose steps start at flight ``g`` (± 1); ``prev``: the first flight of the previous change
    (the reference is the state since then, at most :data:`~twin_nodes.fleet.changes.REF_FLIGHTS` flights)."""
    steps = [s for v, sr in series.items() for s in sr.steps if abs(s.first - g) <= 1]
    first = min(s.first for s in steps)
    last = max(s.last for s in steps)
    ref_idx = list(range(max(0, prev if prev < first else 0, first - ch.REF_FLIGHTS), first))
    new_idx = list(range(first, last + 1))
    ratios, deltas, vals = {}, {}, []
    for v in list(ch.TRACKED) + [f"motor_share_m{i}" for i in range(1, 9)]:
        a = np.array([_f(free[i], f"fact_{v}") for i in ref_idx])
        b = np.array([_f(free[i], f"fact_{v}") for i in new_idx])
        a, b = a[np.isfinite(a)], b[np.isfinite(b)]
        if not a.size or not b.size:
            continue
        sig = series[v].scatter if v in series else ch.scatter(np.array([_f(r, f"fact_{v}") for r in free]))
        if not math.isfinite(sig):
            sig = float(np.std(np.concatenate([a - a.mean(), b - b.mean()])))
        ra, rb = float(np.median(a)), float(np.median(b))
        se = sig * math.sqrt(1 / a.size + 1 / b.size)
        if v.startswith(("com_", "motor_share")):
            deltas[v] = (rb - ra, se)
        elif ra:
            ratios[v] = (rb / ra, abs(se / ra))
    pwm = None
    prev_row = rows.index(free[first - 1]) if first > 0 else -1
    here = rows.index(free[first])
    at = [e for e in ev if prev_row < e["index"] <= here]
    for e in at:
        if e["pwm"]:
            a, b = (_span(t or "") for t in e["pwm"])
            if a and b and a != b:
                pwm = (a, b)
    name, why = ch.explain(ratios, deltas, pwm, stepped={st.value for st in steps})
    for s in steps:
        vals.append({"value": s.value, "from": s.ref, "to": s.new, "size": s.size, "size_se": s.size_se,
                     "band": s.band, "flights": [_name(free[i]["path"]) for i in range(s.first, s.last + 1)]})
    evs = []
    for e in at:
        pwm_txt = [f"motor PWM {e['pwm'][0]} -> {e['pwm'][1]}"] if e["pwm"] else []
        if e.get("outputs"):
            pwm_txt.append(f"motor outputs {e['outputs'][0]} -> {e['outputs'][1]} (another wiring)")
        others = sorted(k for k in e["changes"] if not k.startswith(("PWM_MAIN_M", "PWM_AUX_M")))
        more = [f"also changed: {', '.join(others[:8])}" + (f" and {len(others) - 8} more" if len(others) > 8 else "")] \
            if others else []
        if pwm_txt or more:
            evs.append(f"{e['flight']}: " + "; ".join(pwm_txt + more))
    r0 = free[first]
    return Change(vid, _name(r0["path"]), r0["_utc"], name, why, vals, evs,
                  [_name(free[i]["path"]) for i in new_idx])


def alarm_message(c: Change) -> str:
    """One line: what, from which flight and date, the size ± uncertainty, the evidence."""
    ev = "; ".join(f"{v['value']} {v['from']:.4g} -> {v['to']:.4g} ({v['size']:+.3g} ± {v['size_se']:.2g}, band "
                   f"± {v['band']:.2g}, on {len(v['flights'])} flights in a row)" for v in c.values)
    extra = f"; firmware parameters changed at that flight: {' | '.join(c.events)}" if c.events else ""
    return f"{c.name} from {c.flight} ({c.date[:16]}): {c.why}. Evidence: {ev}{extra}"


def plot_series(vid: str, res: dict, value: str, out: Path) -> None:
    """Dated trend of one value: points with error bars, the scatter band around the reference, the
    firmware events as vertical lines, the steps' first flights marked."""
    import matplotlib
    matplotlib.use("Agg")
    import datetime as _dt

    from matplotlib.figure import Figure

    sr = res["series"][value]
    free = res["free"]
    when = [_dt.datetime.fromisoformat(r["_utc"]).replace(tzinfo=None) for r in free]
    fig = Figure(figsize=(7.5, 2.8))
    ax = fig.add_subplot(1, 1, 1)
    x = np.array(sr.x)
    ax.errorbar(when, x, yerr=np.nan_to_num(np.array(sr.se)), fmt="o", ms=3, color="C0", lw=0.8)
    if sr.bands:
        ref = np.array([b[0] for b in sr.bands])
        h = np.array([b[1] for b in sr.bands])
        ok = np.isfinite(ref)
        if ok.any():
            w = [when[i] for i in np.flatnonzero(ok)]
            ax.fill_between(w, (ref - h)[ok], (ref + h)[ok], color="C0", alpha=0.15, step="mid",
                            label="scatter band")
    for s in getattr(sr, "steps", []):
        ax.plot([when[s.first]], [x[s.first]], "s", color="r", ms=7, mfc="none", label="step (first flight)")
    for e in res["events"]:
        d = _dt.datetime.fromisoformat(e["date"]).replace(tzinfo=None) if e["date"] else None
        if d is not None and (e["pwm"] or e["changes"]):
            ax.axvline(d, color="0.5", ls=":", lw=1)
            ax.annotate("outputs" if e.get("outputs") else "PWM" if e["pwm"] else "params", (d, 1.0),
                        xycoords=("data", "axes fraction"),
                        fontsize=6, rotation=90, va="top")
    unit = FACTS.get(value, ("", ""))[0]
    ax.set_ylabel(f"{value} [{unit}]", fontsize=8)
    ax.set_title(f"{vid}: {value}", fontsize=9)
    h_, l_ = ax.get_legend_handles_labels()
    if h_:
        seen = dict(zip(l_, h_))
        ax.legend(seen.values(), seen.keys(), fontsize=6)
    fig.autofmt_xdate()
    fig.tight_layout()
    fig.savefig(out, dpi=90)
