"""The roll + pitch damping reading of PX4 SIH flights whose roll/pitch damping is SIH's, by motor log interval
(issue 26; the measurement behind ``twin_nodes.discovery.stages.yaw_pair.RP_DAMPING_READING``).

    python tools/rp_damping_reading.py FLIGHT_DIR ... [--json OUT.jsonl]

Each FLIGHT_DIR holds ``flight.ulg`` and ``truth.json`` (a prove flight, ``sih_flight``'s layout); a bare ``.ulg``
is read as a no-effect flight.  The flight is prepared as discovery prepares it, the vehicle is PX4 SIH's nominal with
the flight's true effects but the damping in it, and ``yaw_pair.roll_pitch_damping`` (the stage's own reading) gives
k on the whole flight and both folds.  Flights with ``SIH_KDW`` changed are listed, not pooled; flights whose truth
the vocabulary cannot carry (an arm length; an effect with a parameter the model rejects) are listed and left out
when they change roll/pitch.  Per log interval: the mean of k/k0 (the bias) and the RMS of k/(bias k0) - 1 (the
scatter).  Seen flights only (docs/discovery.md, "Nineteenth session (st19)").
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

import numpy as np

#: SIH changes that move the roll/pitch equation error itself (a reading without them in the model is biased)
RP_CHANGES = ("SIH_IXX", "SIH_IYY", "SIH_L_ROLL", "SIH_L_PITCH", "SIH_T_MAX", "SIH_T_TAU")
#: the parameters of truth.json that name a PX4 setting, not a model parameter
NOT_MODEL = ("q_max_nm", "t_max_n")


def read(path: Path) -> dict:
    from twin_nodes.discovery.stages.prepare import prepare_flight
    from twin_nodes.discovery.stages.yaw_pair import roll_pitch_damping
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.prove.sih import NOMINAL
    from twin_nodes.vehicle.params import load_params

    ulg, tj = (path, path.parent / "truth.json") if path.suffix == ".ulg" else (path / "flight.ulg",
                                                                               path / "truth.json")
    truth = json.loads(tj.read_text()) if tj.exists() else {"effects": [], "sih_changes": {}, "mission": "?"}
    vp = load_params(NOMINAL)
    k0 = vp.effect_dict["angular_damping"]["k_nm_s_rad"]
    fl = prepare_flight(read_ulog(str(ulg)), vp, output_error=False)
    model, modelled = vp, True
    for e in truth.get("effects") or []:
        if e["name"] in ("angular_damping", "none"):
            continue
        p = {k: v for k, v in (e.get("params") or {}).items() if k not in NOT_MODEL}
        if e["name"] == "inertia":
            i0 = np.diag(vp.inertia)
            p = {"ixx": p.get("ixx", i0[0]), "iyy": p.get("iyy", i0[1]), "izz": p.get("izz", i0[2])}
        try:
            model = model.with_effect(e["name"], **p)
        except Exception:           # an arm length, a drag form: not in the vocabulary
            modelled = False
    changes = truth.get("sih_changes") or {}
    rp = roll_pitch_damping(fl.data, vp, model, fl.fit_mask, fl.t_split2)
    return {"flight": path.stem if path.suffix == ".ulg" else path.name, "mission": truth.get("mission"),
            "changes": changes, "motor_dt_s": round(float(fl.data.motor_dt_s), 4), "k0": k0, "reading": rp,
            "pooled": "SIH_KDW" not in changes and (modelled or not any(c in RP_CHANGES for c in changes))}


def law(rows: list[dict]) -> dict:
    out = {}
    for dt in sorted({r["motor_dt_s"] for r in rows}):
        x = [r["reading"][0] / r["k0"] for r in rows if r["motor_dt_s"] == dt and r["pooled"]]
        if not x:
            continue
        bias = statistics.mean(x)
        out[dt] = {"n": len(x), "bias": round(bias, 4),
                   "scatter": round(math.sqrt(sum((v / bias - 1) ** 2 for v in x) / len(x)), 4)}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("flights", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, help="write one JSON line per flight here")
    a = ap.parse_args(argv)
    rows = []
    for f in a.flights:
        r = read(f)
        rows.append(r)
        print(f"{r['flight']:28s} {r['mission']} {r['motor_dt_s']:.3f} s  k {r['reading'][0]:.4f} "
              f"(folds {r['reading'][1]:.4f} / {r['reading'][2]:.4f})  {'pooled' if r['pooled'] else 'listed'}  "
              f"{r['changes']}", flush=True)
    if a.json:
        a.json.write_text("".join(json.dumps(r) + "\n" for r in rows))
    for dt, v in law(rows).items():
        print(f"motor log {dt} s: {v['n']} flights, bias {v['bias']}, scatter {v['scatter']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
