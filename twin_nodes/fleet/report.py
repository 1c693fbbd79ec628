"""Per-vehicle trends of every discovered effect parameter, alarms, and the fleet HTML report.

A trend is one effect parameter of one vehicle over its flights in date order; a flight where
the effect was not found carries the nominal value (efficiency 1.0, the params' mass...), so a
motor that weakens shows as 1.00 -> 0.97 -> ... -> 0.82.  Alarms:

- ``threshold``: a trend crosses its rule (:data:`RULES`) — named with the first flight past it;
- ``payload``: the mass differs from the nominal by more than its rule — the flights (days) listed;
- ``new_effect``: an effect not seen on the vehicle's first flight is found (``confirmed`` /
  ``accepted``) on at least :data:`NEW_EFFECT_MIN_FLIGHTS` later flights and no rule fired for it.

Nothing is lost from the report: every failed flight is counted and listed with its vehicle,
date and one-line reason; rows of identical content (sha256) count once and the others are listed
as duplicates; damaged row files are skipped and listed.
"""

from __future__ import annotations

import html
import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

from twin_nodes.base.io import atomic_write_text
from twin_nodes.fleet.catalog import PRESENT, effect_key, load, row_files

#: effect -> (parameter, kind, limit, nominal): ``below`` alarms when value < limit; ``relative``
#: when |value / nominal_mass - 1| > limit (nominal from the row's params)
RULES = {
    "motor_efficiency": ("efficiency", "below", 0.90, 1.0),
    "thrust_coefficient": ("kt_scale", "below", 0.90, 1.0),
    "mass": ("mass", "relative", 0.10, None),
}
NEW_EFFECT_MIN_FLIGHTS = 2


@dataclass
class Trend:
    vehicle_id: str
    effect: str  # effect key: name, with _m<motor> for per-motor effects
    param: str
    flights: list[str] = field(default_factory=list)
    dates: list[str] = field(default_factory=list)
    values: list[float] = field(default_factory=list)
    verdicts: list[str] = field(default_factory=list)
    nominal: float | None = None
    #: per flight: discovery ran against a vehicle twin (params given or mapped), not the flight's own nominal
    vehicle_twin: list[bool] = field(default_factory=list)
    #: per flight: what differs since the vehicle twin, as the flight's values name it ('' where not compared)
    since: list[str] = field(default_factory=list)

    @property
    def label(self) -> str:
        name, _, m = self.effect.rpartition("_m")
        if _ and m.isdigit():
            return f"motor {m} {self.param}"
        return f"{self.effect} {self.param}"


@dataclass
class Alarm:
    vehicle_id: str
    kind: str
    effect: str
    message: str
    flight: str = ""
    flights: list[str] = field(default_factory=list)
    dates: list[str] = field(default_factory=list)


def _effects(row: dict) -> list[dict]:
    try:
        return json.loads(row.get("effects_json") or "[]")
    except (TypeError, ValueError):
        return []


def _against_twin(r: dict) -> bool:
    v = r.get("params_is_vehicle_twin")
    if v is not None:
        return bool(v)
    note = str(r.get("params_note") or "")
    return note == "given" or note.startswith("params map")


#: effect -> the words of a since-the-vehicle-twin name that agree with it (mass and thrust look alike in hover:
#: a finding of one where the flight's values name the other backs nothing)
AGREES = {"mass": ("mass", "thrust per mass"), "thrust_coefficient": ("thrust",),
          "motor_efficiency": ("weaker motor", "thrust"), "yaw_moment": ("yaw",), "inertia": ("inertia",)}


def agrees(t: Trend, i: int) -> bool:
    """Whether flight ``i``'s finding agrees with what its values name since the vehicle twin (True where the
    flight was not compared, or the effect has no counterpart there)."""
    name = t.effect.rpartition("_m")[0] if t.effect.rpartition("_m")[2].isdigit() else t.effect
    since = t.since[i] if i < len(t.since) else ""
    words = AGREES.get(name)
    if not since or since in ("not compared",) or words is None:
        return True
    return any(w in since for w in words)


def backed(t: Trend, idx: list[int]) -> tuple[bool, str]:
    """Whether findings at ``idx`` back an alarm, and how: confirmed by discovery against a vehicle twin on
    one of them, or found on at least two flights in a row whose values agree within 30 %."""
    for i in idx:
        if t.verdicts[i] in PRESENT and (t.vehicle_twin[i] if i < len(t.vehicle_twin) else False):
            return True, f"confirmed against the vehicle twin on {t.flights[i]}"
    for a, b in zip(idx, idx[1:]):
        va, vb = t.values[a], t.values[b]
        if b == a + 1 and va and vb and max(va, vb) / min(va, vb) <= 1.3 and min(va, vb) > 0:
            return True, f"found on {t.flights[a]} and {t.flights[b]} in a row ({va:.3g}, {vb:.3g})"
    return False, "a single flight, or flights that disagree, against each flight's own nominal"


def trends(rows: list[dict]) -> list[Trend]:
    """Every (vehicle, effect, parameter) seen present on any flight, over all the vehicle's ok flights."""
    by_v: dict[str, list[dict]] = {}
    for r in rows:
        if r.get("status") == "ok" and r.get("mode", "discover") == "discover":
            by_v.setdefault(r["vehicle_id"], []).append(r)
    out = []
    for vid, rs in sorted(by_v.items()):
        rs.sort(key=lambda r: (r.get("flight_time_utc") or "", r["path"]))
        plain = [Path(r["path"]).name for r in rs]  # folder/file where file names repeat (PX4's flight.ulg...)
        names = {r["path"]: (f"{Path(r['path']).parent.name}/{n}" if plain.count(n) > 1 else n)
                 for r, n in zip(rs, plain)}
        found: dict[tuple[str, str], dict] = {}
        for r in rs:
            for e in _effects(r):
                if e.get("verdict") == "rejected":
                    continue
                for p, x in (e.get("params") or {}).items():
                    if p != "motor" and isinstance(x, (int, float)):
                        found.setdefault((effect_key(e), p), {})
        for (key, p) in sorted(found):
            name = key.rpartition("_m")[0] if key.rpartition("_m")[2].isdigit() else key
            t = Trend(vid, key, p)
            for r in rs:
                hit = next((e for e in _effects(r) if effect_key(e) == key and e.get("verdict") != "rejected"), None)
                rule = RULES.get(name)
                if name == "mass":
                    t.nominal = float(r.get("nominal_mass_kg") or 0) or None
                elif rule and rule[0] == p:
                    t.nominal = rule[3]
                # an effect whose parameters differ from flight to flight (a stage-9 term's terms: c_climb on one
                # flight, c_mu2 on the next) has this parameter on some flights only: not found on the others
                x = (hit.get("params") or {}).get(p) if hit else None
                has = isinstance(x, (int, float))
                val = float(x) if has else t.nominal
                t.flights.append(names[r["path"]])
                t.dates.append(r.get("flight_time_utc") or "")
                t.values.append(float("nan") if val is None else val)
                t.verdicts.append(hit["verdict"] if has else "not found")
                t.vehicle_twin.append(_against_twin(r))
                t.since.append(str(r.get("since_twin") or ""))
            out.append(t)
    return out


def alarms(rows: list[dict], tr: list[Trend] | None = None) -> list[Alarm]:
    """Threshold, payload and new-effect alarms (see the module docstring)."""
    tr = trends(rows) if tr is None else tr
    out: list[Alarm] = []
    fired: set[tuple[str, str]] = set()
    for t in tr:
        name = t.effect.rpartition("_m")[0] if t.effect.rpartition("_m")[2].isdigit() else t.effect
        rule = RULES.get(name)
        if not rule or rule[0] != t.param:
            continue
        _, kind, limit, _nom = rule
        if kind == "below":
            idx = [i for i, v in enumerate(t.values) if v < limit and t.verdicts[i] in PRESENT + ("likely",)
                   and agrees(t, i)]
            ok, how = backed(t, idx)
            if idx and ok:
                i = idx[0]
                out.append(Alarm(t.vehicle_id, "threshold", t.effect,
                                 f"{t.label} {t.nominal if t.nominal is not None else t.values[0]:.2f} -> "
                                 f"{t.values[idx[-1]]:.2f}: below {limit:.2f} since "
                                 f"{t.flights[i]} ({t.dates[i][:10]}, {t.values[i]:.3f}); {how}",
                                 flight=t.flights[i], flights=[t.flights[j] for j in idx],
                                 dates=[t.dates[j] for j in idx]))
                fired.add((t.vehicle_id, t.effect))
        elif kind == "relative" and t.nominal:
            idx = [i for i, v in enumerate(t.values)
                   if abs(v / t.nominal - 1) > limit and t.verdicts[i] in PRESENT + ("likely",) and agrees(t, i)]
            ok, how = backed(t, idx)
            if idx and ok:
                days = sorted({t.dates[j][:10] for j in idx})
                out.append(Alarm(t.vehicle_id, "payload", t.effect,
                                 f"mass off nominal {t.nominal:.2f} kg by more than {100 * limit:.0f} % on "
                                 f"{len(idx)} flight(s) ("
                                 + ", ".join(f"{t.flights[j]} {t.values[j]:.2f} kg" for j in idx)
                                 + f"); days: {', '.join(days)}; {how}",
                                 flight=t.flights[idx[0]], flights=[t.flights[j] for j in idx],
                                 dates=[t.dates[j] for j in idx]))
                fired.add((t.vehicle_id, t.effect))
    seen: set[tuple[str, str]] = set()
    for t in tr:
        if (t.vehicle_id, t.effect) in fired or (t.vehicle_id, t.effect) in seen:
            continue
        seen.add((t.vehicle_id, t.effect))
        present = [i for i, v in enumerate(t.verdicts) if v in PRESENT and agrees(t, i)]
        ok, how = backed(t, present)
        if len(present) >= NEW_EFFECT_MIN_FLIGHTS and present[0] > 0 and t.verdicts[0] not in PRESENT and ok:
            i = present[0]
            out.append(Alarm(t.vehicle_id, "new_effect", t.effect,
                             f"new effect {t.effect} from {t.flights[i]} ({t.dates[i][:10]}), found on "
                             f"{len(present)} flights; {how}", flight=t.flights[i],
                             flights=[t.flights[j] for j in present], dates=[t.dates[j] for j in present]))
    return out


def _plot(t: Trend, out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 2.6))
    ax = fig.add_subplot(1, 1, 1)
    x = list(range(1, len(t.values) + 1))
    ax.plot(x, t.values, "-", color="0.6")
    for v in ("confirmed", "accepted", "likely", "not found"):
        pts = [(i, y) for i, y, w in zip(x, t.values, t.verdicts) if w == v]
        if pts:
            ax.plot(*zip(*pts), "o", label=v, ms=4)
    name = t.effect.rpartition("_m")[0] if t.effect.rpartition("_m")[2].isdigit() else t.effect
    rule = RULES.get(name)
    if rule and rule[0] == t.param:
        if rule[1] == "below":
            ax.axhline(rule[2], color="r", ls="--", lw=1, label=f"alarm < {rule[2]}")
        elif t.nominal:
            for s in (1 - rule[2], 1 + rule[2]):
                ax.axhline(t.nominal * s, color="r", ls="--", lw=1)
    ax.set_xlabel("flight (date order)")
    ax.set_ylabel(t.param)
    ax.set_title(f"{t.vehicle_id}: {t.label}", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=90)


def dedupe(rows: list[dict]) -> tuple[list[dict], list[dict]]:
    """Rows with the same ``content_sha256`` are one flight: keep an ``ok`` one (else the first),
    the others as duplicates ``{"path", "same_as"}``.  Rows without a hash are all kept."""
    groups: dict[str, list[dict]] = {}
    for r in rows:
        if r.get("content_sha256"):
            groups.setdefault(r["content_sha256"], []).append(r)
    keep_ids = {id(next((r for r in g if r.get("status") == "ok"), g[0])): g for g in groups.values()}
    kept, dups = [], []
    for r in rows:
        h = r.get("content_sha256")
        if not h or id(r) in keep_ids:
            kept.append(r)
            continue
        same = next(x for x in groups[h] if id(x) in keep_ids)
        dups.append({"path": r["path"], "same_as": same["path"]})
    return kept, dups


def failed_flights(rows: list[dict]) -> list[dict]:
    """Every row that is not ``ok``: path, vehicle, date and the one-line reason."""
    return [{"path": r["path"], "vehicle_id": r.get("vehicle_id") or "", "date": (r.get("flight_time_utc") or "")[:10],
             "error": r.get("error") or f"status {r.get('status')!r} without a reason"}
            for r in rows if r.get("status") not in ("ok", "not_flight")]


def not_flights(rows: list[dict]) -> list[dict]:
    """Every log recognised as no free flight: path, vehicle, date, kind and reason."""
    return [{"path": r["path"], "vehicle_id": r.get("vehicle_id") or "", "date": (r.get("flight_time_utc") or "")[:10],
             "kind": r.get("flight_kind") or "", "reason": r.get("error") or ""}
            for r in rows if r.get("status") == "not_flight"]


def _vehicle_sections(rows: list[dict], out: Path, al: list[Alarm]) -> list[dict]:
    """Per vehicle: its values across flights (dated trends, scatter band, events), the steps and what they
    mean; each step is appended to ``al`` as a ``change`` alarm.  Returns ``[{"html", "json"}]``."""
    from twin_nodes.fleet import vehicle_report as vr

    e = html.escape
    by_v: dict[str, list[dict]] = {}
    for r in rows:
        by_v.setdefault(r.get("vehicle_id") or "(unknown)", []).append(dict(r))
    out_secs = []
    for k, (vid, rs) in enumerate(sorted(by_v.items())):
        res = vr.analyse_vehicle(vid, rs)
        for c in res["changes"]:
            al.append(Alarm(vid, "change", c.name, vr.alarm_message(c), flight=c.flight, flights=c.flights,
                            dates=[c.date]))
        off = res["local_offset_h"]
        parts = [f"<h2>Vehicle {e(vid)}</h2><p>{len(res['rows'])} logs, {len(res['free'])} free flights with "
                 "identified values" + (f"; file-name dates (downloader's local time) corrected by {off:+g} h "
                                        "from the logs with both" if off else "") + "</p>"]
        parts.append("<table border=1 cellpadding=2><tr><th>UTC</th><th>log</th><th>kind</th><th>motor PWM</th>"
                     "<th>thrust/mass</th><th>hover throttle</th><th>roll/pitch eff.</th><th>battery V</th>"
                     "<th>since the vehicle twin</th></tr>")
        for r in res["rows"]:
            def g(c, fmt="{:.3g}"):
                v = r.get(c)
                return fmt.format(v) if isinstance(v, (int, float)) and v == v else ""
            parts.append(f"<tr><td>{e(r['_utc'][:16])}</td><td>{e(Path(r['path']).name)}</td>"
                         f"<td>{e(r.get('flight_kind') or r.get('status') or '')}</td><td>{e(r.get('motor_pwm') or '')}</td>"
                         f"<td>{g('fact_kt_per_mass')} ± {g('fact_kt_per_mass_se', '{:.2g}')}</td>"
                         f"<td>{g('fact_hover_throttle')}</td><td>{g('fact_roll_eff')} / {g('fact_pitch_eff')}</td>"
                         f"<td>{g('fact_battery_v_start')}</td>"
                         f"<td title='{e(str(r.get('since_twin_why') or ''))}'>{e(str(r.get('since_twin') or ''))}</td></tr>")
        parts.append("</table><h3>Firmware parameter changes (events)</h3><ul>" + "".join(
            f"<li>{e(ev['date'][:16])} {e(ev['flight'])}: " + e("; ".join(
                ([f"motor outputs {ev['outputs'][0]} -> {ev['outputs'][1]} (another wiring: values not compared "
                  "across it)"] if ev.get("outputs") else [])
                + ([f"motor PWM {ev['pwm'][0]} -> {ev['pwm'][1]}"] if ev["pwm"] else [])
                + [", ".join(f"{n} {a} -> {b}" for n, (a, b) in sorted(ev["changes"].items()))])) + "</li>"
            for ev in res["events"]) + "</ul>")
        parts.append("<h3>Changes (beyond the scatter band on two flights in a row)</h3>" + (
            "<ul>" + "".join(f"<li>{e(vr.alarm_message(c))}</li>" for c in res["changes"]) + "</ul>"
            if res["changes"] else "<p>none</p>"))
        exc = {v: [vr._name(res["free"][i]["path"]) for i in sr.excursions]
               for v, sr in res["series"].items() if getattr(sr, "excursions", None)}
        if exc:
            parts.append("<p>Single-flight excursions (not alarms): " + e("; ".join(
                f"{v}: {', '.join(f)}" for v, f in exc.items())) + "</p>")
        for v in res["series"]:
            png = f"vehicle_{k:02d}_{v}.png"
            vr.plot_series(vid, res, v, out / png)
            sr = res["series"][v]
            parts.append(f"<h4>{e(v)}</h4><p>{e(vr.FACTS[v][1])}; flight-to-flight scatter "
                         f"{sr.scatter:.3g}</p><img src='{png}'>")
        js = {"vehicle_id": vid, "local_offset_h": off, "events": res["events"],
              "rewired_at": [vr._name(res["free"][i]["path"]) for i in res.get("rewired", [])],
              "changes": [asdict(c) for c in res["changes"]],
              "flights": [{"path": r["path"], "utc": r["_utc"], "kind": r.get("flight_kind") or r.get("status"),
                           "motor_pwm": r.get("motor_pwm"),
                           **{k_: r[k_] for k_ in r if k_.startswith("fact_") and r[k_] is not None}}
                          for r in res["rows"]],
              "scatter": {v: sr.scatter for v, sr in res["series"].items()},
              "excursions": exc}
        out_secs.append({"html": "\n".join(parts), "json": js})
    return out_secs


def write_report(catalog: str | os.PathLike[str], out_dir: str | os.PathLike[str]) -> dict:
    """Trends, alarms and ``index.html`` (+ one PNG per trend, ``report.json``) in ``out_dir``."""
    files = row_files(catalog)
    rows, dups = dedupe(load(catalog, files.good))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tr = trends(rows)
    al = alarms(rows, tr)
    vehicles: dict[str, dict] = {}
    for r in rows:
        vid = r.get("vehicle_id") or "(unknown)"  # rows of catalogs written before failed rows kept it
        v = vehicles.setdefault(vid, {"flights": 0, "failed": 0, "not_flight": 0, "first": None, "last": None})
        v["flights"] += 1
        v["failed"] += r.get("status") not in ("ok", "not_flight")
        v["not_flight"] += r.get("status") == "not_flight"
        d = (r.get("flight_time_utc") or "")[:10]
        v["first"] = min(filter(None, [v["first"], d]), default=d)
        v["last"] = max(filter(None, [v["last"], d]), default=d)
    pngs = []
    for k, t in enumerate(tr):
        name = f"trend_{k:03d}.png"
        _plot(t, out / name)
        pngs.append(name)
    failed = failed_flights(rows)
    nf = not_flights(rows)
    per_vehicle = _vehicle_sections(rows, out, al)
    summary = {"catalog": str(catalog), "flights": len(rows), "vehicles": vehicles,
               "alarms": [asdict(a) for a in al], "trends": [asdict(t) | {"label": t.label} for t in tr],
               "failed": failed, "not_flights": nf, "duplicates": dups, "corrupt_files": files.corrupt,
               "vehicle_changes": [s_["json"] for s_ in per_vehicle]}
    atomic_write_text(out / "report.json", json.dumps(summary, indent=1, default=str))
    e = html.escape
    parts = ["<html><head><meta charset='utf-8'><title>fleet report</title></head><body>",
             f"<h1>Fleet report</h1><p>{len(rows)} logs, {len(vehicles)} vehicles, {len(nf)} no free flight "
             f"(ground/bench tests, too short, no GPS), {len(failed)} failed, "
             f"{len(dups)} duplicate(s), {len(files.corrupt)} corrupt row file(s); "
             f"catalog {e(str(catalog))}</p><h2>Alarms</h2>"]
    parts.append("<ul>" + "".join(f"<li><b>{e(a.vehicle_id)}</b> [{a.kind}] {e(a.message)}</li>" for a in al)
                 + "</ul>" if al else "<p>none</p>")
    parts.append("<h2>Vehicles</h2><table border=1 cellpadding=3><tr><th>vehicle</th><th>flights</th>"
                 "<th>failed</th><th>dates</th><th>alarms</th></tr>")
    for vid, v in sorted(vehicles.items()):
        n = sum(a.vehicle_id == vid for a in al)
        parts.append(f"<tr><td>{e(vid)}</td><td>{v['flights']}</td><td>{v['failed']}</td>"
                     f"<td>{e(str(v['first']))} .. {e(str(v['last']))}</td><td>{n or 'none'}</td></tr>")
    parts.append("</table>")
    for sec in per_vehicle:
        parts.append(sec["html"])
    parts.append("<h2>Discovered effects (per flight)</h2>")
    for t, png in zip(tr, pngs):
        n_found = sum(v != "not found" for v in t.verdicts)
        parts.append(f"<h3>{e(t.vehicle_id)}: {e(t.label)}</h3><p>found on {n_found} of {len(t.values)} flights "
                     f"(first {t.values[0]:.3f}, last {t.values[-1]:.3f}; a flight without it carries the nominal)"
                     f"</p><img src='{png}'>")
    if failed:
        parts.append("<h2>Failed flights</h2><table border=1 cellpadding=3><tr><th>flight</th><th>vehicle</th>"
                     "<th>date</th><th>reason</th></tr>" + "".join(
                         f"<tr><td>{e(f['path'])}</td><td>{e(f['vehicle_id'])}</td><td>{e(f['date'])}</td>"
                         f"<td>{e(f['error'])}</td></tr>" for f in failed) + "</table>")
    if nf:
        parts.append("<h2>Logs that are no free flight</h2><table border=1 cellpadding=3><tr><th>log</th>"
                     "<th>vehicle</th><th>date</th><th>kind</th><th>reason</th></tr>" + "".join(
                         f"<tr><td>{e(f['path'])}</td><td>{e(f['vehicle_id'])}</td><td>{e(f['date'])}</td>"
                         f"<td>{e(f['kind'])}</td><td>{e(f['reason'])}</td></tr>" for f in nf) + "</table>")
    if dups:
        parts.append("<h2>Duplicates (identical content, counted once)</h2><ul>" + "".join(
            f"<li>{e(d['path'])}: same content as {e(d['same_as'])}</li>" for d in dups) + "</ul>")
    if files.corrupt:
        parts.append("<h2>Corrupt row files (skipped)</h2><ul>" + "".join(
            f"<li>{e(c['file'])}: {e(c['error'])}</li>" for c in files.corrupt) + "</ul>")
    parts.append("</body></html>")
    atomic_write_text(out / "index.html", "\n".join(parts))
    return summary
