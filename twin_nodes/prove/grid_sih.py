"""The declared PX4 SIH grid (issue 26): every SIH parameter that changes the physics at 2 magnitudes, 10
two-parameter combinations, 10 no-effect flights, on missions beyond M3/M4 and both logging profiles.

``tools/declare_sih_grid.py`` writes ``missions/sih_grid/manifest.yaml`` (the PX4 section of
``missions/sih_effects/manifest.yaml``, so that ``launch_scripts/fly_sih.sh --manifest`` flies it the same way,
the missions, and the flights with their tuning/judging half drawn per stratum by :data:`GRID_SEED`).  The file in
the repository is the declaration; prove reads the halves from it.
"""

from __future__ import annotations

from pathlib import Path

from twin_nodes.base.yamlio import read_yaml_file
import numpy as np

REPO = Path(__file__).resolve().parents[2]
GRID_SEED = 2626
GRID_PATH = REPO / "missions" / "sih_grid" / "manifest.yaml"
#: a second, judging-only batch declared 2026-11-27 (fifth session) before that session changed anything
BATCH2_SEED = 2727
BATCH2_PATH = REPO / "missions" / "sih_grid" / "batch2.yaml"
#: judging-only batches, each declared before the session that judges on it changed anything:
#: half -> (seed, manifest, id prefix, when declared)
BATCHES = {
    "judge2": (BATCH2_SEED, BATCH2_PATH, "t", "2026-11-27, before the fifth session changed anything"),
    "judge3": (2828, REPO / "missions" / "sih_grid" / "batch3.yaml", "u",
               "2026-11-27 14:57 UTC, before the sixth session changed anything"),
    "judge4": (2929, REPO / "missions" / "sih_grid" / "batch4.yaml", "y",
               "2026-11-27 17:20 UTC, before the seventh session changed anything"),
    "judge5": (3030, REPO / "missions" / "sih_grid" / "batch5.yaml", "h",
               "2026-11-27 19:57 UTC, before the eighth session changed anything"),
    "judge6": (3131, REPO / "missions" / "sih_grid" / "batch6.yaml", "m",
               "2026-11-27 22:58 UTC, before the ninth session changed anything"),
    "judge7": (3232, REPO / "missions" / "sih_grid" / "batch7.yaml", "j",
               "2026-11-28 01:47 UTC, before the tenth session changed anything"),
    "judge8": (3333, REPO / "missions" / "sih_grid" / "batch8.yaml", "z",
               "2026-11-28 04:35 UTC, before the eleventh session changed anything"),
    "judge9": (3434, REPO / "missions" / "sih_grid" / "batch9.yaml", "b",
               "2026-11-28 07:39 UTC, before the twelfth session changed anything"),
    "judge10": (3535, REPO / "missions" / "sih_grid" / "batch10.yaml", "d",
                "2026-11-28 10:25 UTC, before the thirteenth session changed anything"),
    "judge11": (3636, REPO / "missions" / "sih_grid" / "batch11.yaml", "f",
                "2026-11-28 13:40 UTC, before the fourteenth session changed anything"),
    "judge12": (3737, REPO / "missions" / "sih_grid" / "batch12.yaml", "l",
                "2026-11-28 16:35 UTC, before the fifteenth session changed anything"),
    "judge13": (3838, REPO / "missions" / "sih_grid" / "batch13.yaml", "p",
                "2026-11-28 19:40 UTC, before the sixteenth session changed anything"),
    "judge14": (3939, REPO / "missions" / "sih_grid" / "batch14.yaml", "sa",
                "2026-11-28 22:36 UTC, before the seventeenth session changed anything"),
    "judge15": (4040, REPO / "missions" / "sih_grid" / "batch15.yaml", "sb",
                "2026-11-29 01:56 UTC, before the eighteenth session changed anything"),
    "judge16": (4141, REPO / "missions" / "sih_grid" / "batch16.yaml", "sc",
                "2026-11-29 05:00 UTC, before the nineteenth session changed anything"),
}
#: the halves ``prove --grid`` takes: batch 1's two, each judging-only batch (the same names in both grids:
#: grid_rotorpy.BATCHES, tests/test_grids.py), or all
HALVES = ("tuning", "judging", *BATCHES, "all")
BASE = REPO / "missions" / "sih_effects" / "manifest.yaml"
#: each SIH parameter group that changes the physics, at two magnitudes (PX4 SIH defaults in sih_flight.SIH_DEFAULTS)
GROUPS = {
    "MASS": ({"SIH_MASS": 1.15}, {"SIH_MASS": 1.30}),
    "T_MAX": ({"SIH_T_MAX": 4.6}, {"SIH_T_MAX": 4.2}),
    "Q_MAX": ({"SIH_Q_MAX": 0.13}, {"SIH_Q_MAX": 0.17}),
    "T_TAU": ({"SIH_T_TAU": 0.08}, {"SIH_T_TAU": 0.13}),
    "IXX_IYY": ({"SIH_IXX": 0.0325, "SIH_IYY": 0.0325}, {"SIH_IXX": 0.04, "SIH_IYY": 0.04}),
    "IZZ": ({"SIH_IZZ": 0.039}, {"SIH_IZZ": 0.048}),
    "KDV": ({"SIH_KDV": 1.5}, {"SIH_KDV": 2.2}),
    "KDW": ({"SIH_KDW": 0.05}, {"SIH_KDW": 0.10}),
    "L_ROLL": ({"SIH_L_ROLL": 0.17}, {"SIH_L_ROLL": 0.15}),
    "L_PITCH": ({"SIH_L_PITCH": 0.17}, {"SIH_L_PITCH": 0.15}),
}
#: two-parameter combinations (first magnitude of each; mass with thrust left out: one force, one class)
COMBOS = (("MASS", "T_TAU"), ("T_MAX", "Q_MAX"), ("T_TAU", "KDV"), ("MASS", "KDV"), ("IXX_IYY", "Q_MAX"),
          ("IZZ", "T_TAU"), ("KDW", "MASS"), ("L_ROLL", "T_MAX"), ("KDV", "Q_MAX"), ("L_PITCH", "KDW"))
MISSIONS = {
    "M1": {"plan_file": "missions/triangle.plan.yaml", "kind": "triangle"},
    "M2": {"plan_file": "missions/grid.plan.yaml", "kind": "survey grid"},
    "M3": {"plan_file": "missions/sih_effects/M3_yaw_square.plan.yaml", "kind": "yaw square"},
    "M4": {"plan_file": "missions/sih_effects/M4_steps_zigzag.plan.yaml", "kind": "steps zigzag"},
    "M5": {"plan_file": "missions/sih_grid/M5_takeoff_land.plan.yaml", "kind": "take-off and land"},
    "M6": {"plan_file": "missions/sih_grid/M6_orbit.plan.yaml", "kind": "orbit"},
}
#: the missions the grid cycles through (M3/M4 once in six)
CYCLE = ("M1", "M2", "M5", "M6", "M1", "M2", "M5", "M6", "M3", "M4")


def declare(seed: int = GRID_SEED) -> list[dict]:
    """40 single-group flights (each group x 2 magnitudes x 2 (mission, logging) pairs), 10 combinations, 10
    no-effect flights; halves drawn per stratum (group, 'two parameters', 'none')."""
    rng = np.random.default_rng(seed)
    rows = []
    k = 0
    for g, mags in GROUPS.items():
        for m_i, sih in enumerate(mags):
            for rep in range(2):
                rows.append({"group": g, "sih": dict(sih), "mission": CYCLE[k % len(CYCLE)],
                             "logging": "highrate" if (m_i + rep) % 2 else "default"})
                k += 1
    for j, (a, b) in enumerate(COMBOS):
        rows.append({"group": f"{a}+{b}", "sih": {**GROUPS[a][0], **GROUPS[b][0]}, "mission": CYCLE[(k + j) % 10],
                     "logging": "highrate" if j % 2 else "default"})
    for j in range(10):
        rows.append({"group": "none", "sih": {}, "mission": ("M1", "M2", "M5", "M6", "M3")[j % 5],
                     "logging": "highrate" if j >= 5 else "default"})
    strata: dict[str, list[int]] = {}
    for i, r in enumerate(rows):
        strata.setdefault("two parameters" if "+" in r["group"] else r["group"], []).append(i)
    half = ["judging"] * len(rows)
    for name in sorted(strata):
        idx = strata[name]
        for i in rng.permutation(idx)[: len(idx) // 2]:
            half[int(i)] = "tuning"
    for i, r in enumerate(rows):
        r["id"] = f"s{i + 1:03d}"
        r["half"] = half[i]
        r["seed"] = int(seed * 100 + i + 1)
    return rows


def declare_batch2(seed: int = BATCH2_SEED, prefix: str = "t", half: str = "judge2") -> list[dict]:
    """A fresh judging batch: 10 single-group flights (groups drawn, magnitude, mission and logging drawn), 10
    two-group combinations not among :data:`COMBOS` (drawn from the pairs of different classes; first
    magnitude, as the grid's), 4 no-effect flights.  All judging (``half``: "judge2", "judge3")."""
    rng = np.random.default_rng(seed)
    names = list(GROUPS)
    missions = sorted(MISSIONS)
    rows = []
    for i in rng.choice(len(names), size=10, replace=False):
        g = names[int(i)]
        rows.append({"group": g, "sih": dict(GROUPS[g][int(rng.integers(2))]),
                     "mission": missions[int(rng.integers(len(missions)))],
                     "logging": ("default", "highrate")[int(rng.integers(2))]})
    same = ({"MASS", "T_MAX"}, {"IXX_IYY", "IZZ"}, {"L_ROLL", "L_PITCH"})
    pool = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]
            if {a, b} not in same and (a, b) not in COMBOS and (b, a) not in COMBOS]
    for i in rng.choice(len(pool), size=10, replace=False):
        a, b = pool[int(i)]
        rows.append({"group": f"{a}+{b}", "sih": {**GROUPS[a][0], **GROUPS[b][0]},
                     "mission": missions[int(rng.integers(len(missions)))],
                     "logging": ("default", "highrate")[int(rng.integers(2))]})
    for j in range(4):
        rows.append({"group": "none", "sih": {}, "mission": missions[int(rng.integers(len(missions)))],
                     "logging": ("default", "highrate")[j % 2]})
    for i, r in enumerate(rows):
        r["id"] = f"{prefix}{i + 1:03d}"
        r["half"] = half
        r["seed"] = int(seed * 100 + i + 1)
    return rows


def load_grid(path: str | Path | None = None, half: str = "") -> dict:
    if path is None:
        path = BATCHES[half][1] if half in BATCHES else GRID_PATH

    return read_yaml_file(path, "grid manifest")["flights"]

