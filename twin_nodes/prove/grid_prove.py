"""``prove`` on issue 26's declared grids: one half (tuning or judging) of the RotorPy or PX4 SIH grid, with
one or two true effects per flight, scored by the rules every source shares plus two more:

- **two effects**: the top finding is right when it is in either true effect's class; the flight's effects
  are *named* when each true effect's class is among the findings (a reported pair counts for its members);
  each named effect's parameters are compared with its truth (:func:`scoring.compare`);
- **a pair not told apart** (a finding with ``not_told_apart``: both members, the manoeuvre that separates
  them and its plan): right only when the true effect is one of the two and the plan is flyable
  (``plan_flyable``); its parameters are the member's own.

Flights come from the cache the grid's fly scripts fill (``tools/fly_grids.sh``); a declared flight absent
there is listed as not flown, never scored.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

from twin_nodes.prove.scoring import (DragContext, Truth, compare, effect_class, findings, heldout_cut,
                                      ridge_reading, verdict, write_result)
from twin_nodes.twin.simflight import Hidden

CACHE = Path.home() / ".cache" / "rotortwin" / "grids"


def _members(effect: dict) -> list[tuple[str, dict]]:
    """(name, params) a finding stands for: itself, and its pair partner when it reports one flyably."""
    out = [(effect["name"], effect.get("params") or {})]
    pair = effect.get("not_told_apart")
    if pair and pair.get("plan_flyable"):
        # a member that is two effects together (stage 12: a yaw moment and a yaw inertia) lists the second under also
        out += [(m["name"], m.get("params") or {}) for m in [pair["with"]] + list(pair.get("also") or [])]
    return out


def _stands_for(member: str, finding: str, truth: str) -> bool:
    """Whether a finding's member ``member`` (the finding itself, or its pair partner) names the true effect
    ``truth``: one of its class, except that a pair partner in the drag class names only its own law.  A pair
    partner is read from the channel its finding explains: a rotor drag that is a yaw moment's rival is its hub
    yaw damping (RotorPy ra020: k_d 5.2e-7, below the nominal 1.03e-6), which says nothing of a body drag's force
    (no moment; 96 % off as a k_eq).  On every seen batch a drag truth named through a partner was its own law."""
    if effect_class(member) != effect_class(truth):
        return False
    return member == finding or effect_class(truth) != "drag" or member == truth


def score_grid_flight(flight: str, truths: list[Truth], result: dict, nominal, drag=None, **facts) -> dict:
    """One row: top finding right, every true effect named, parameters, held-out cut, pass."""
    found = findings(result)
    top = found[0] if found else None
    real = [t for t in truths if t.hidden.name != "none"]
    none = not real
    row: dict = {"flight": flight, "true_effect": "+".join(t.hidden.name for t in real) or "none",
                 "n_true": len(real), "truth_text": "; ".join(t.text for t in real),
                 "top_finding": top["name"] if top else "none", "top_verdict": verdict(top) if top else "-",
                 "findings": [f"{e['name']} ({verdict(e)})" + (f" ~ {e['not_told_apart']['with']['name']}"
                                                              if e.get("not_told_apart") else "") for e in found],
                 "n_findings": len(found), "elapsed_s": result.get("elapsed_s"), **facts}
    if none:
        row.update(passed=not found, right_class=False, named=[], n_named=0, param_errors={})
        return row
    classes = {effect_class(t.hidden.name): t for t in real}
    right = bool(top) and any(_stands_for(n, top["name"], t.hidden.name) for n, _ in _members(top) for t in real)
    right_by_pair = bool(top) and right and effect_class(top["name"]) not in classes
    named, errs, texts = [], {}, {}
    other_reading = None    # a yaw pair's other reading (its damping and partner), where a truth was read from it
    read_from: dict = {}    # truth -> (the finding it was read from, the member read)
    per_mass = _per_mass(real, found, nominal)
    for t in real:
        c = effect_class(t.hidden.name)
        # a finding of the effect's own class first, a pair partner only where none names it (RotorPy w023: the
        # battery sag's pair partner thrust_coefficient 0.712 read for the mass confirmed on its own, 1.150)
        for e in sorted(found, key=lambda e, c=c: effect_class(e["name"]) != c):
            hit = sorted(((n, p) for n, p in _members(e) if _stands_for(n, e["name"], t.hidden.name)),
                         key=lambda m: m[0] != e["name"])
            if hit:
                named.append(t.hidden.name)
                # the finding's own parameters it says the flight does not show (held at the model's value)
                held = frozenset(e.get("held_at_nominal") or {}) if hit[0][0] == e["name"] else frozenset()
                err, text = compare(t, hit[0][0], hit[0][1], nominal, drag, per_mass, held)
                # a ground effect whose flight pins only its extra thrust near one low height: that one reading
                ridge = ridge_reading(t, hit[0][1], e.get("ground_fit")) if hit[0][0] == e["name"] else None
                err, text = ridge if ridge is not None else (err, text)
                errs[t.hidden.name], texts[t.hidden.name] = err, text
                if hit[0][0] != e["name"] and (e.get("not_told_apart") or {}).get("damping_with_it"):
                    other_reading = e["not_told_apart"]
                read_from[t.hidden.name] = (e["name"], hit[0][0])
                break
    # a yaw pair not told apart (stage 10: km x s with k_d, or Izz / s with k_d / s) is scored as one reading: where
    # a truth was read from the partner, a true damping is read with the damping that reading asks for, and a truth
    # read from the damping's own pair partner (a rotor drag's hub damping) with that partner at the reading (i032)
    if other_reading is not None:
        at = {"angular_damping": other_reading["damping_with_it"]}
        if other_reading.get("damping_partner_with_it"):
            at[other_reading["damping_partner_with_it"]["name"]] = other_reading["damping_partner_with_it"]["params"]
        for t in real:
            if t.hidden.name not in read_from:
                continue
            finding, member = read_from[t.hidden.name]
            # a true damping at the reading's damping; a truth read from the damping's entry, at its partner's
            name = "angular_damping" if t.hidden.name == "angular_damping" else \
                (member if finding == "angular_damping" else None)
            if name in at:
                err, text = compare(t, name, at[name], nominal, drag, per_mass)
                errs[t.hidden.name], texts[t.hidden.name] = err, text + " (the pair's other reading)"
    ho = heldout_cut(top) if top else {}
    params_ok = all(errs.get(t.hidden.name) is not None and errs[t.hidden.name] <= 0.10 for t in real
                    if t.hidden.name in named)
    if len(real) == 1:
        passed = right and params_ok and bool(named) and (ho.get("improvement") or 0) >= 0.5
    else:
        passed = len(named) == len(real) and params_ok
    row.update(right_class=right, right_by_pair=right_by_pair, named=named, n_named=len(named),
               param_errors=errs, param_text=texts, heldout_improvement=ho.get("improvement"),
               heldout_channel=ho.get("channel"), params_ok=params_ok, passed=passed,
               first_candidate=(result.get("effects") or [{}])[0].get("name") if not top else None)
    return row


def _per_mass(real: list[Truth], found: list[dict], nominal) -> float:
    """The real thrust per command over the findings' reading's, where a true mass change was found as a
    thrust coefficient (the true mass over the model's: the model kept its mass) or a true thrust coefficient
    as a mass (its kt_scale: the model kept its thrust), else 1; what the flight's other findings are read at
    (:func:`scoring.compare`)."""
    names = {e["name"] for e in found}
    for t in real:
        if t.hidden.name == "mass" and "thrust_coefficient" in names and "mass" not in names:
            return float(t.hidden.params["mass"]) / nominal.mass_kg
        if t.hidden.name == "thrust_coefficient" and "mass" in names and "thrust_coefficient" not in names:
            return float(t.hidden.params["kt_scale"])
    return 1.0


def summarize(rows: list[dict]) -> dict:
    eff = [r for r in rows if r["n_true"] > 0]
    two = [r for r in rows if r["n_true"] > 1]
    none = [r for r in rows if r["n_true"] == 0]
    named_eff = [(r, n) for r in eff for n in r["named"]]
    return {"n_flights": len(rows), "n_effect": len(eff), "n_right_top": sum(r["right_class"] for r in eff),
            "n_right_by_pair": sum(bool(r.get("right_by_pair")) for r in eff),
            "n_two": len(two), "n_both_named": sum(r["n_named"] == 2 for r in two),
            "n_none": len(none), "n_false": sum(r["n_findings"] > 0 for r in none),
            "n_named": len(named_eff),
            "n_params_ok": sum(1 for r, n in named_eff if r["param_errors"].get(n) is not None
                               and r["param_errors"][n] <= 0.10),
            "n_passed": sum(bool(r["passed"]) for r in rows)}


def summary_line(name: str, s: dict) -> str:
    pct = (lambda a, b: f"{100 * a / b:.0f} %" if b else "-")
    return (f"{name}: right effect on top {s['n_right_top']}/{s['n_effect']} ({pct(s['n_right_top'], s['n_effect'])}"
            f"{', ' + str(s['n_right_by_pair']) + ' as a pair' if s['n_right_by_pair'] else ''}); both effects named "
            f"{s['n_both_named']}/{s['n_two']}; findings on no-effect flights {s['n_false']}/{s['n_none']}; "
            f"params within 10 % {s['n_params_ok']}/{s['n_named']} named effects; passing every rule "
            f"{s['n_passed']}/{s['n_flights']}")


def table(rows: list[dict], not_flown: list[str]) -> str:
    lines = []
    for r in rows:
        pe = ", ".join(f"{k} {'-' if v is None else ('wrong' if not math.isfinite(v) else f'{100 * v:.1f} %')}"
                       for k, v in (r.get("param_errors") or {}).items())
        top = r["top_finding"] + (f" ({r['top_verdict']})" if r["top_finding"] != "none" else
                                  " [discover refused it]" if r.get("refused") else
                                  f" [1st: {r.get('first_candidate')}]" if r.get("first_candidate") else "")
        cut = r.get("heldout_improvement")
        lines.append(f"{r['flight']:<44} {r['true_effect']:<38} {top:<40} +{max(r['n_findings'] - 1, 0)} "
                     f"named {r.get('n_named', 0)}/{r['n_true']}  {pe:<34} cut {'-' if cut is None else f'{100 * cut:.0f} %':>5}"
                     f"  {'pass' if r['passed'] else 'FAIL'}")
    by_effect, by_mission = defaultdict(list), defaultdict(list)
    for r in rows:
        by_effect[r["true_effect"] if r["n_true"] < 2 else "two effects"].append(r)
        by_mission[r.get("mission_kind", "?")].append(r)
    lines.append(summary_line("all", summarize(rows)))
    for name, rs in sorted(by_effect.items()):
        lines.append("  [effect " + summary_line(name, summarize(rs)) + "]")
    for name, rs in sorted(by_mission.items()):
        lines.append("  [mission " + summary_line(name, summarize(rs)) + "]")
    refused = [f"{r['flight'].split()[0]} ({r['refused']})" for r in rows if r.get("refused")]
    if refused:
        lines.append("scored as misses, discover stopped: " + "; ".join(refused))
    if not_flown:
        lines.append("declared, not scored: " + "; ".join(not_flown))
    return "\n".join(lines)


# ------------------------------------------------------------------ the two grids


def rotorpy_jobs(half: str, cache: Path) -> tuple[list, list[str]]:
    from twin_nodes.prove import grid_rotorpy as g

    jobs, missing = [], []
    for f in g.load_grid(half=half):
        if half != "all" and f.half != half:
            continue
        p, meta = cache / f"{f.id}.ulg", cache / f"{f.id}.meta.json"
        if not (p.is_file() and meta.is_file()):
            missing.append(f.id)
            continue
        jobs.append(("rotorpy", f, str(p)))
    return jobs, missing


def sih_jobs(half: str, cache: Path) -> tuple[list, list[str]]:
    from twin_nodes.prove import grid_sih as g

    jobs, missing = [], []
    for fid, fl in g.load_grid(half=half).items():
        if half != "all" and fl["half"] != half:
            continue
        p = cache / fid / "flight.ulg"
        if not (p.is_file() and (cache / fid / "truth.json").is_file()):
            missing.append(fid)
            continue
        jobs.append(("px4sih", (fid, fl), str(p)))
    return jobs, missing


def _sih_truths(fl: dict, nominal) -> list[Truth]:
    from twin_nodes.prove.sih import INERTIA_GROUP, map_truth

    ch = fl.get("sih") or {}
    groups: list[dict] = []
    for k, v in ch.items():
        # an inertia and an arm length act on the same thing (each axis's turn rate per command): one
        # inertia truth, per axis (prove.sih.inertia_equivalent)
        g = next((gr for gr in groups if {k, *gr} <= INERTIA_GROUP), None)
        if g is None:
            groups.append({k: v})
        else:
            g[k] = v
    if not groups:
        return [Truth(Hidden("none", {}), "no SIH change")]
    out = []
    for g in groups:
        t = map_truth({"sih_changes": g}, nominal)
        if t.hidden.name == "yaw_moment" and "SIH_T_MAX" in ch:   # km = Q_MAX / T_MAX of the flight
            t = Truth(Hidden("yaw_moment", {"km": g["SIH_Q_MAX"][1] / ch["SIH_T_MAX"][1]}), t.text)
        out.append(t)
    return out


def rotorpy_truths(f) -> list[Truth]:
    """A RotorPy grid flight's true effects as scored.  A yaw moment's ``km`` is our torque per thrust, so its
    truth is ``k_m / k_eta`` of the plant as flown: beside a thrust coefficient (which scales both), the yaw
    moment's ``k_m`` replaces the thrust coefficient's, and the flight's km is the yaw factor over ``kt`` (r070:
    1.5 / 0.87 of the nominal, 0.0345, where the declared truth reads 0.030), as the PX4 SIH grid reads
    ``Q_MAX / T_MAX`` (:func:`_sih_truths`)."""
    from twin_nodes.prove import grid_rotorpy as g

    flown: dict = {}      # the plant keys as flown: a later change's k_m replaces an earlier one's
    for c in g.changes(f):
        flown.update(c.get("plant") or {})
    truths = []
    for c in g.changes(f):
        h = c["hidden"]
        if h.name == "yaw_moment" and "k_eta" in flown:
            h = Hidden("yaw_moment", {"km": float(flown["k_m"]) / float(flown["k_eta"])})
        truths.append(Truth(h, f"{h.name} {h.params}", drag_law=c.get("drag_law")))
    return truths or [Truth(Hidden("none", {}), "RotorPy's own vehicle")]


def run_one(job, reuse: Path | None = None) -> dict:
    """Discover blind on one grid flight and score it; ``reuse``: a result JSON of this flight written by an
    earlier run of the same code, re-scored instead of discovered again."""
    source, spec, path = job
    from twin_nodes.base.errors import TwinError
    from twin_nodes.discovery.discover import discover
    from twin_nodes.logs.ulog_io import read_ulog

    log = read_ulog(path)
    if source == "rotorpy":
        from twin_nodes.prove import grid_rotorpy as g
        from twin_nodes.prove import rotorpy_flights as rf

        f = spec
        vp = rf.nominal_params(rf.rotorpy_params(f.vehicle), f"rotorpy_{f.vehicle}")
        truths = rotorpy_truths(f)
        name, facts = f"{f.id} {f.vehicle[:9]} {f.mission}", {"mission_kind": g.MISSION_KINDS[f.mission],
                                                               "vehicle": f.vehicle, "id": f.id}
    else:
        from twin_nodes.prove.grid_sih import MISSIONS
        from twin_nodes.prove.sih import NOMINAL
        from twin_nodes.vehicle.params import load_params

        fid, fl = spec
        vp = load_params(NOMINAL)
        truths = _sih_truths(fl, vp)
        name = f"{fid} {fl['mission']} {fl['logging'][:4]}"
        facts = {"mission_kind": MISSIONS[fl["mission"]]["kind"], "logging": fl["logging"], "id": fid}
    if reuse is not None and reuse.is_file():
        res = json.loads(reuse.read_text())
    else:
        try:
            res = discover(log, vp, closed_loop_metrics=False)
        except TwinError as exc:
            # the vehicle flew the flight: discovery stopping on it is a miss, scored as one, never left out
            res = {"effects": [], "refused": f"discover refused it: {exc}"}
        res.pop("_series", None)
    drag = DragContext.from_log(log, vp) if any(effect_class(t.hidden.name) == "drag" or t.hidden.name == "wind"
                                                 for t in truths) else None
    row = score_grid_flight(name, truths, res, vp, drag, **facts)
    if res.get("refused"):
        row["refused"] = res["refused"]
    return row, res


#: a RotorPy grid flight whose airborne tracking is worse than this did not fly its mission (RotorPy's SE(3)
#: controller lost control: on the ground, tumbling): declared, flown, not scored, listed with its numbers
LOST_CONTROL = {"z_tracking_rmse_m": 0.5, "xy_tracking_rmse_m": 2.0}


def lost_control(meta_path: Path) -> str | None:
    facts = json.loads(meta_path.read_text()).get("facts") or {}
    bad = [f"{k} {facts[k]:.2f} > {v}" for k, v in LOST_CONTROL.items() if not facts.get(k, 0.0) <= v]
    return ", ".join(bad) or None


def sih_unfinished(flight_dir: Path) -> str | None:
    md = (flight_dir / "MANIFEST.md").read_text() if (flight_dir / "MANIFEST.md").is_file() else ""
    return None if "| mission finished | True" in md else "mission not finished (MANIFEST.md)"


def run(source: str, half: str, out: Path, cache: Path = CACHE, progress: bool = True, reuse: bool = False,
        ids: list[str] | None = None) -> dict:
    """``ids``: only these flights of the half (a subset to measure on; the rest are left out, not listed)."""
    out.mkdir(parents=True, exist_ok=True)
    jobs, missing = (rotorpy_jobs(half, cache / "rotorpy") if source == "rotorpy" else sih_jobs(half, cache / "sih"))
    if ids:
        want = set(ids)
        jobs = [j for j in jobs if (j[1].id if source == "rotorpy" else j[1][0]) in want]
        missing = [m for m in missing if m.split()[0] in want]
    rows = []
    for j in jobs:
        key = j[1].id if source == "rotorpy" else j[1][0]
        why = (lost_control(cache / "rotorpy" / f"{key}.meta.json") if source == "rotorpy"
               else sih_unfinished(cache / "sih" / key))
        if why is None:
            row, res = run_one(j, out / f"{key}.json" if reuse else None)
        if why is not None:
            missing.append(f"{key} (flown, not scored: {why})")
            if progress:
                print(f"{key}: not scored: {why}", flush=True)
            continue
        write_result(out / f"{key}.json", res)
        rows.append(row)
        if progress:
            print(table([row], [])[: 220].splitlines()[0], flush=True)
    txt = table(rows, missing)
    (out / "table.txt").write_text(txt + "\n")
    s = summarize(rows)
    (out / "summary.json").write_text(json.dumps({"source": source, "half": half, **s, "not_flown": missing,
                                                  "rows": rows}, indent=1, default=float))
    return {"table": txt, **s}


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m twin_nodes.prove.grid_prove")
    ap.add_argument("--source", choices=["rotorpy", "px4sih"], required=True)
    from twin_nodes.prove.grid_sih import HALVES

    ap.add_argument("--half", choices=HALVES, required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--cache", default=str(CACHE))
    ap.add_argument("--reuse", action="store_true", help="re-score a flight's result already in --out")
    ap.add_argument("--ids", nargs="*", help="only these flights of the half")
    a = ap.parse_args(argv)
    r = run(a.source, a.half, Path(a.out), Path(a.cache), reuse=a.reuse, ids=a.ids)
    print(r["table"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
