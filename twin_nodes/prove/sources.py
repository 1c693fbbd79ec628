"""``rotortwin prove --source``: the prove suite per source of independent physics.

- ``ours``: our generator (:mod:`twin_nodes.prove.ours`);
- ``px4sih``: PX4 SIH flights, real firmware, one SIH parameter changed (:mod:`twin_nodes.prove.sih`);
- ``rotorpy``: RotorPy flights, one RotorPy parameter changed (:mod:`twin_nodes.prove.rotorpy_flights`).

Every source is scored by the same rules (:func:`twin_nodes.prove.scoring.score_flight`).
"""

from __future__ import annotations

from pathlib import Path

SOURCES = ("ours", "px4sih", "rotorpy")


def run_sources(sources, out_dir: str | Path, *, size: str = "full", workers: int = 2,
                vehicle: str = "px4_sih_quadx", shared: str | Path | None = None,
                cache: str | Path = "out/cache/rotorpy", progress: bool = True,
                sih_dirs: list[str | Path] | tuple = ()) -> dict[str, dict]:
    """Run the prove suite of each source; ``{source: summary}``.  Each source writes its per-flight
    results into ``out_dir/<source>/``."""
    from twin_nodes.prove import ours, rotorpy_flights, sih

    out = Path(out_dir)
    summaries: dict[str, dict] = {}
    for src in sources:
        d = out / src
        if src == "ours":
            summaries[src] = ours.run_suite(d, vehicle, size, workers, progress)
        elif src == "px4sih":
            summaries[src] = sih.run_suite(d, size, workers, shared, progress, sih_dirs=sih_dirs)
        elif src == "rotorpy":
            summaries[src] = rotorpy_flights.run_suite(d, size, workers, cache, progress)
        else:
            raise ValueError(f"unknown source {src!r}; expected one of {', '.join(SOURCES)}")
    return summaries
