#!/usr/bin/env python3
"""Write issue 26's PX4 SIH grid manifest (missions/sih_grid/manifest.yaml) from twin_nodes.prove.grid_sih.declare
and the PX4 section of missions/sih_effects/manifest.yaml (a script: prove may not import the mavlink layer)."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twin_nodes.prove.grid_sih import (BASE, BATCHES, GRID_PATH, GRID_SEED,  # noqa: E402
                                       MISSIONS, declare, declare_batch2)


def write_manifest(path: str | Path = GRID_PATH, seed: int = GRID_SEED, batch: str = "") -> Path:
    """Batch 1 (``batch`` ""), or a judging-only batch ("judge2", "judge3": seed and path from grid_sih.BATCHES)."""
    import yaml

    from twin_nodes.mavlink.sih_flight import SIH_DEFAULTS, truth_effects

    base = yaml.safe_load(BASE.read_text())
    flights = {}
    if batch:
        seed, path, prefix, when = BATCHES[batch]
    for r in (declare_batch2(seed, prefix, batch) if batch else declare(seed)):
        flights[r["id"]] = {"mission": r["mission"], "mission_kind": MISSIONS[r["mission"]]["kind"],
                            "group": r["group"], "sih": {k: [SIH_DEFAULTS[k], v] for k, v in r["sih"].items()},
                            "truth": truth_effects(r["sih"]), "logging": r["logging"], "seed": r["seed"],
                            "half": r["half"]}
    doc = {"grid": "px4sih", "issue": 26, "seed": seed, "generator": "twin_nodes/prove/grid_sih.py",
           "declared": (f"{when}; every flight judging ({batch})"
                        if batch else "before any tuning; halves drawn per stratum by the seed"),
           "px4": base["px4"],
           "fly": f"launch_scripts/fly_sih.sh --px4 PX4 --manifest {Path(path).relative_to(BASE.parents[2])} --out DIR "
                  "--instance 1 --flight ID ... (tools/fly_grids.sh sih PX4 HALF flies them all, one at a time)",
           "missions": {k: {"plan_file": v["plan_file"], "note": v["kind"]} for k, v in MISSIONS.items()},
           "flights": flights}
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text("# Declared PX4 SIH grid of issue 26, written by tools/declare_sih_grid.py (twin_nodes/prove/grid_sih.py) before\n"
                 "# any tuning. Do not edit by hand: prove reads the halves from here. Flights live outside the\n"
                 "# repository (e.g. ~/.cache/rotortwin/grids/sih/<id>/flight.ulg).\n"
                 + yaml.safe_dump(doc, sort_keys=False, width=140))
    return p



if __name__ == "__main__":
    if sys.argv[1:] == ["--batch2"]:
        print(write_manifest(batch="judge2"))
    elif len(sys.argv) == 3 and sys.argv[1] == "--batch":
        print(write_manifest(batch=sys.argv[2]))
    else:
        print(write_manifest())
