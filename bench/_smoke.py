"""Shared by the benchmarks' smoke runs (``ROTORTWIN_BENCH_SMOKE=1``, tests/test_bench_smoke.py).

A smoke run checks that a benchmark still runs to its end and prints its ratio lines, on a small
size; its numbers mean nothing.  ``tiny_flight`` is the small flight the discovery benchmarks use
then: our simulator (PX4's SIH quad, params/px4_sih_quadx.yaml, the demo flight's hidden effect:
motor 3 at 85 % efficiency, seed 7) flying take-off to 6 m, 10 m north at 5 m/s and RTL (~50 s),
written once under ``out/bench/smoke/``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SMOKE = os.environ.get("ROTORTWIN_BENCH_SMOKE") == "1"
SIH = ROOT / "params" / "px4_sih_quadx.yaml"

_PLAN = """# bench/_smoke.py: the smoke runs' tiny flight
mission:
  name: bench_smoke_tiny
  speed_m_s: 5.0
  acceptance_radius_m: 2.0
  fly_through: true
  rtl_after: true
  waypoints:
    - [10.0, 0.0, 6.0]
"""


def tiny_flight(out: Path | None = None) -> Path:
    """The smoke runs' ~40 s simulated flight (made once, then reused)."""
    out = out or ROOT / "out" / "bench" / "smoke"
    out.mkdir(parents=True, exist_ok=True)
    flight = out / "tiny.ulg"
    if not flight.exists():
        plan = out / "tiny.plan.yaml"
        plan.write_text(_PLAN)
        part = out / f"tiny.{os.getpid()}.part.ulg"
        part.unlink(missing_ok=True)
        r = subprocess.run([str(Path(sys.executable).with_name("rotortwin")), "simulate", "--params", str(SIH),
                            "--effect", "motor_efficiency:motor=3,efficiency=0.85", "--seed", "7", "--plan", str(plan),
                            "--out", str(part)], capture_output=True, text=True, cwd=ROOT)
        if r.returncode != 0:
            sys.exit(f"bench: simulating the smoke flight failed (exit {r.returncode}):\n{r.stdout}{r.stderr}")
        part.replace(flight)
    return flight
