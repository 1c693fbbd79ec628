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


def trends(rows: list[dict]) -> list[Trend]:
    """Every (vehicle, effect, parameter) seen present on any flight, over all the vehicle's ok flights."""
    by_v: dict[str, list[dict]] = {}
    for r in rows:
        if r.get("status") == "ok" and r.get("mode", "discover") == "discover":
            by_v.setdefault(r["vehicle_id"], []).append(r)
    out = []
    for vid, rs in sorted(by_v.items()):
        rs.sort(key=lambda r: (r.get("flight_time_utc") or "", r["path"]))
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
                val = float(hit["params"][p]) if hit else t.nominal
                t.flights.append(Path(r["path"]).name)
                t.dates.append(r.get("flight_time_utc") or "")
                t.values.append(float("nan") if val is None else val)
                t.verdicts.append(hit["verdict"] if hit else "not found")
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
            idx = [i for i, v in enumerate(t.values) if v < limit and t.verdicts[i] in PRESENT + ("likely",)]
            if idx:
                i = idx[0]
                out.append(Alarm(t.vehicle_id, "threshold", t.effect,
                                 f"{t.label} {t.values[0]:.2f} -> {t.values[-1]:.2f}: below {limit:.2f} since "
                                 f"{t.flights[i]} ({t.dates[i][:10]}, {t.values[i]:.3f})",
                                 flight=t.flights[i], flights=[t.flights[j] for j in idx],
                                 dates=[t.dates[j] for j in idx]))
                fired.add((t.vehicle_id, t.effect))
        elif kind == "relative" and t.nominal:
            idx = [i for i, v in enumerate(t.values)
                   if abs(v / t.nominal - 1) > limit and t.verdicts[i] in PRESENT + ("likely",)]
            if idx:
                days = sorted({t.dates[j][:10] for j in idx})
                out.append(Alarm(t.vehicle_id, "payload", t.effect,
                                 f"mass off nominal {t.nominal:.2f} kg by more than {100 * limit:.0f} % on "
                                 f"{len(idx)} flight(s) ("
                                 + ", ".join(f"{t.flights[j]} {t.values[j]:.2f} kg" for j in idx)
                                 + f"); days: {', '.join(days)}",
                                 flight=t.flights[idx[0]], flights=[t.flights[j] for j in idx],
                                 dates=[t.dates[j] for j in idx]))
                fired.add((t.vehicle_id, t.effect))
    seen: set[tuple[str, str]] = set()
    for t in tr:
        if (t.vehicle_id, t.effect) in fired or (t.vehicle_id, t.effect) in seen:
            continue
        seen.add((t.vehicle_id, t.effect))
        present = [i for i, v in enumerate(t.verdicts) if v in PRESENT]
        if len(present) >= NEW_EFFECT_MIN_FLIGHTS and present[0] > 0 and t.verdicts[0] not in PRESENT:
            i = present[0]
            out.append(Alarm(t.vehicle_id, "new_effect", t.effect,
                             f"new effect {t.effect} from {t.flights[i]} ({t.dates[i][:10]}), found on "
                             f"{len(present)} flights", flight=t.flights[i],
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
            for r in rows if r.get("status") != "ok"]


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
        v = vehicles.setdefault(vid, {"flights": 0, "failed": 0, "first": None, "last": None})
        v["flights"] += 1
        v["failed"] += r.get("status") != "ok"
        d = (r.get("flight_time_utc") or "")[:10]
        v["first"] = min(filter(None, [v["first"], d]), default=d)
        v["last"] = max(filter(None, [v["last"], d]), default=d)
    pngs = []
    for k, t in enumerate(tr):
        name = f"trend_{k:03d}.png"
        _plot(t, out / name)
        pngs.append(name)
    failed = failed_flights(rows)
    summary = {"catalog": str(catalog), "flights": len(rows), "vehicles": vehicles,
               "alarms": [asdict(a) for a in al], "trends": [asdict(t) | {"label": t.label} for t in tr],
               "failed": failed, "duplicates": dups, "corrupt_files": files.corrupt}
    atomic_write_text(out / "report.json", json.dumps(summary, indent=1, default=str))
    e = html.escape
    parts = ["<html><head><meta charset='utf-8'><title>fleet report</title></head><body>",
             f"<h1>Fleet report</h1><p>{len(rows)} flights, {len(vehicles)} vehicles, {len(failed)} failed, "
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
    parts.append("</table><h2>Trends</h2>")
    for t, png in zip(tr, pngs):
        parts.append(f"<h3>{e(t.vehicle_id)}: {e(t.label)}</h3><p>{t.values[0]:.3f} -> {t.values[-1]:.3f} over "
                     f"{len(t.values)} flights</p><img src='{png}'>")
    if failed:
        parts.append("<h2>Failed flights</h2><table border=1 cellpadding=3><tr><th>flight</th><th>vehicle</th>"
                     "<th>date</th><th>reason</th></tr>" + "".join(
                         f"<tr><td>{e(f['path'])}</td><td>{e(f['vehicle_id'])}</td><td>{e(f['date'])}</td>"
                         f"<td>{e(f['error'])}</td></tr>" for f in failed) + "</table>")
    if dups:
        parts.append("<h2>Duplicates (identical content, counted once)</h2><ul>" + "".join(
            f"<li>{e(d['path'])}: same content as {e(d['same_as'])}</li>" for d in dups) + "</ul>")
    if files.corrupt:
        parts.append("<h2>Corrupt row files (skipped)</h2><ul>" + "".join(
            f"<li>{e(c['file'])}: {e(c['error'])}</li>" for c in files.corrupt) + "</ul>")
    parts.append("</body></html>")
    atomic_write_text(out / "index.html", "\n".join(parts))
    return summary
