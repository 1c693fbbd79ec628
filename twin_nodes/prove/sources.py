"""``rotortwin prove --source``: the prove suite per source of independent physics.

- ``ours``: our generator (:mod:`twin_nodes.prove.ours`);
- ``px4sih``: PX4 SIH flights, real firmware, one SIH parameter changed (:mod:`twin_nodes.prove.sih`);
- ``rotorpy``: RotorPy flights, one RotorPy parameter changed (:mod:`twin_nodes.prove.rotorpy_flights`);
- ``oov``: flights whose hidden physics is outside the effect list, ours and RotorPy's, declared in
  ``oov_manifest.yaml`` (:mod:`twin_nodes.prove.oov`): term discovery's evidence, scored by its own rules.

Every source is scored by the same rules (:func:`twin_nodes.prove.scoring.score_flight`).
"""

from __future__ import annotations

from pathlib import Path

SOURCES = ("ours", "px4sih", "rotorpy")
#: sources run only when named (``--source oov``)
EXTRA_SOURCES = ("oov",)


def run_sources(sources, out_dir: str | Path, *, size: str = "full", workers: int = 2,
                vehicle: str = "px4_sih_quadx", shared: str | Path | None = None,
                cache: str | Path = "out/cache/rotorpy", progress: bool = True,
                sih_dirs: list[str | Path] | tuple = ()) -> dict[str, dict]:
    """Run the prove suite of each source; ``{source: summary}``.  Each source writes its per-flight
    results into ``out_dir/<source>/``."""
    from twin_nodes.prove import oov, ours, rotorpy_flights, sih

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
        elif src == "oov":
            summaries[src] = oov.run_suite(d, workers, Path(cache).parent / "oov", progress)
        else:
            raise ValueError(f"unknown source {src!r}; expected one of {', '.join(SOURCES + EXTRA_SOURCES)}")
    return summaries
