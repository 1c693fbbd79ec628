"""Every benchmark (bench/bench_*.py) still runs to its end and prints its ratio lines.

Each runs as ``make bench`` runs it (its own process, no arguments), on a small size
(``ROTORTWIN_BENCH_SMOKE=1``, see bench/README.md).  Nothing here is timed and no number is
checked: the targets live in the benchmarks, measured against a reference of the same run.
A new benchmark must add the line that carries its ratio to ``RATIO_LINES``.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHES = sorted(p.name for p in (ROOT / "bench").glob("bench_*.py"))

#: per benchmark: the lines (regular expressions) that carry its ratios against the same run's reference
RATIO_LINES = {
    "bench_model.py": [r"ours, step\(\) per 1 ms\s+[\d.]+x\s+[\d.]+\s+[\d.]+x", r"RotorPy step\(\)\s+[\d.]+x"],
    "bench_lockstep.py": [r"ratio vs the first case run \(median, this run\):\s+[\d.]+x"],
    "bench_fleet.py": [r"scaling 2 workers / 1 worker: [\d.]+x", r"scaling 2 workers / 1 worker, cold: [\d.]+x",
                       r"ratio as installed / cold, 1 worker\(s\): [\d.]+x"],
    "bench_stepper.py": [r"ratio before/after \(cold, all combinations\): [\d.]+x"],
    "bench_replay.py": [r"ratio graph / offline\s+[\d.]+", r"dropped messages\s+0\b"],
    "bench_discover.py": [r"ratio before/after: wall [\d.]+x, cpu [\d.]+x", r"same result: True"],
    "bench_memory.py": [r"ratio compare: long / budget [\d.]+ \(within 2 GB\), long / short flight [\d.]+",
                        r"ratio discover: long / budget [\d.]+ \(within 2 GB\), long / short flight [\d.]+"],
}
NEEDS = {"bench_model.py": "rotorpy", "bench_replay.py": "rclpy", "bench_lockstep.py": "pymavlink"}


def test_every_bench_has_its_ratio_lines():
    assert BENCHES, "no bench/bench_*.py"
    missing = [b for b in BENCHES if b not in RATIO_LINES]
    assert not missing, f"add the ratio lines of {missing} to RATIO_LINES"


def test_make_bench_runs_every_bench():
    make = (ROOT / "Makefile").read_text()
    rule = make[make.index("\nbench:"):].split("\n\n")[0]
    assert "bench/bench_*.py" in rule and "exit 1" in rule


@pytest.mark.parametrize("bench", BENCHES)
def test_bench_smoke(bench):
    if bench in NEEDS:
        pytest.importorskip(NEEDS[bench])
    env = {**os.environ, "ROTORTWIN_BENCH_SMOKE": "1"}
    r = subprocess.run([sys.executable, str(ROOT / "bench" / bench)], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=600)
    out = r.stdout + r.stderr
    assert r.returncode == 0, f"{bench} exited {r.returncode}:\n{out[-4000:]}"
    for pattern in RATIO_LINES.get(bench, []):
        assert re.search(pattern, out), f"{bench}: no line matching {pattern!r}:\n{out[-4000:]}"


def test_sign_flip_sums_equal_the_whole_matrix():
    """The memory work (bench_memory.py): the sign-flip test's 20000 x n flips are kept as bits and
    multiplied a few rows at a time (2000 rows for small n, down to 272 here); the sums are bit for
    bit those of the whole float64 matrix made in one call, as before (n odd and even, across a
    byte's bits)."""
    import numpy as np

    from twin_nodes.discovery import discover as d

    rng = np.random.default_rng(5)
    for n in (1, 4, 7, 64, 333, 1000, 1025):
        whole = np.random.default_rng(12345).choice((-1.0, 1.0), size=(d.N_FLIPS, n))
        a = np.abs(rng.standard_normal(n)) * 10.0 ** rng.uniform(-6, 2)
        assert np.array_equal(d._flip_sums(n, a), whole @ a), n
