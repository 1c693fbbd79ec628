"""Score a fleet report of the one-vehicle SIH fleet (missions/sih_effects/manifest.yaml, flights s01-s32) against
what the manifest declared before it was flown (issue 25, part 6).

    python tools/sih_fleet_proof.py REPORT_DIR/report.json [--prefix s]     # s01-s32
    python tools/sih_fleet_proof.py REPORT_DIR/report.json --prefix p       # p01-p18 (patched SIH: a motor, a CoM)

A *declared change* is a flight whose SIH parameters differ from the previous flight's (a change made or undone);
it is *found* when a ``change`` alarm starts within one flight of it and names every parameter group that changed
there (SIH_MASS -> mass, SIH_T_MAX -> thrust, SIH_IXX/IYY -> inertia, SIH_Q_MAX -> yaw moment, SIH_MOT_WEAK/EFF ->
motor i, SIH_CG_X/Y -> centre-of-mass shift).  A discovered-effect alarm (payload, threshold, new_effect) is *true*
when every flight it names carries the matching SIH change (mass -> SIH_MASS, thrust_coefficient -> SIH_T_MAX,
inertia -> SIH_IXX/IYY/IZZ, yaw_moment -> SIH_Q_MAX, motor_efficiency -> SIH_MOT_WEAK, com_offset -> SIH_CG_X/Y).
Any other alarm is a *false alarm*.  Prints one line per declared change and per alarm, then the totals.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
NAMES = {"SIH_MASS": "mass", "SIH_T_MAX": "thrust", "SIH_IXX": "inertia", "SIH_IYY": "inertia", "SIH_IZZ": "inertia",
         "SIH_Q_MAX": "yaw moment", "SIH_MOT_WEAK": "weaker motor", "SIH_MOT_EFF": "weaker motor",
         "SIH_CG_X": "centre-of-mass shift", "SIH_CG_Y": "centre-of-mass shift"}


EFFECT_SIH = {"mass": {"SIH_MASS"}, "thrust_coefficient": {"SIH_T_MAX"}, "inertia": {"SIH_IXX", "SIH_IYY", "SIH_IZZ"},
              "yaw_moment": {"SIH_Q_MAX"}, "motor_efficiency": {"SIH_MOT_WEAK"}, "com_offset": {"SIH_CG_X", "SIH_CG_Y"}}


def sih_of(prefix: str = "s") -> dict[str, dict]:
    man = yaml.safe_load((ROOT / "missions/sih_effects/manifest.yaml").read_text())
    return {k: {n: v[-1] for n, v in (f.get("sih") or {}).items()} for k, f in man["flights"].items()
            if k.startswith(prefix) and k[len(prefix):].isdigit()}


def declared(prefix: str = "s") -> tuple[list[str], list[dict]]:
    man = yaml.safe_load((ROOT / "missions/sih_effects/manifest.yaml").read_text())
    ids = sorted(k for k in man["flights"] if k.startswith(prefix) and k[len(prefix):].isdigit())
    out, prev = [], {}
    for i, fid in enumerate(ids):
        sih = {k: v[-1] for k, v in (man["flights"][fid].get("sih") or {}).items()}
        if i and sih != prev:
            keys = set(sih) ^ set(prev) | {k for k in sih if prev.get(k) != sih[k]}
            # a weaker motor (made or undone) is named with its number: "weaker motor 3", "stronger motor 3"
            motor = int(sih.get("SIH_MOT_WEAK") or prev.get("SIH_MOT_WEAK") or 0)
            groups = {f"motor {motor}" if NAMES[k] == "weaker motor" else NAMES[k] for k in keys}
            out.append({"flight": fid, "index": i, "expect": sorted(groups), "sih": sih})
        prev = sih
    return ids, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report")
    ap.add_argument("--prefix", default="s")
    a = ap.parse_args(argv)
    ids, decl = declared(a.prefix)
    rep = json.loads(Path(a.report).read_text())
    alarms = []
    for al in rep["alarms"]:
        fid = Path(al["flight"]).parent.name if "/" in al["flight"] else al["flight"]
        alarms.append({**al, "fid": fid, "index": ids.index(fid) if fid in ids else -1})
    used = set()
    found = 0
    for d in decl:
        hit = [k for k, al in enumerate(alarms) if al["kind"] == "change" and abs(al["index"] - d["index"]) <= 1
               and all(n in al["effect"] for n in d["expect"])]
        ok = bool(hit)
        found += ok
        used.update(hit)
        at = f"{alarms[hit[0]]['fid']} ({alarms[hit[0]]['effect']})" if hit else "not found"
        print(f"declared {d['flight']}: {', '.join(d['expect'])} (SIH now {d['sih'] or 'defaults'}) -> {at}")
    sih = sih_of(a.prefix)
    effect_ok = 0
    for k, al in enumerate(alarms):
        if al["kind"] == "change" or k in used:
            continue
        want = EFFECT_SIH.get(al["effect"].rsplit("_m", 1)[0] if al["effect"][-1:].isdigit() else al["effect"])
        fids = [f.split("/")[0] for f in al.get("flights") or []]
        if want and fids and all(want & set(sih.get(f, {})) for f in fids):
            used.add(k)
            effect_ok += 1
            print(f"effect alarm [{al['kind']}] {al['effect']} on {', '.join(fids)}: all carry {sorted(want)} (true)")
    false = [al for k, al in enumerate(alarms) if k not in used]
    for al in false:
        print(f"FALSE ALARM [{al['kind']}] {al['message'][:200]}")
    print(f"{found} of {len(decl)} declared changes found and dated within one flight; {len(false)} false alarm(s); "
          f"{len(ids)} flights")
    return 0 if found == len(decl) and not false else 1


if __name__ == "__main__":
    sys.exit(main())
