"""A fleet run on Dask distributed: one task per flight, resumable, failures recorded, progress bar.

An embedded ``LocalCluster`` (processes, ``workers`` workers of one thread) unless a scheduler
address is given (``dask scheduler`` / ``dask worker`` started elsewhere).  Flights whose file
(path, size, mtime) is already in the catalog are skipped.  Each task writes its own row file
before it returns, so a worker killed mid-run loses only the flight it was on, and the rerun
does exactly the flights that have no row.  A task whose worker dies is retried by Dask
(``retries``); if it still cannot finish, it is reported and left for the rerun.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Callable

from twin_nodes.base.errors import TwinError
from twin_nodes.fleet.catalog import pending
from twin_nodes.fleet.flight import process_flight


def find_flights(args: list[str]) -> list[Path]:
    """ULog files named or found (recursively) in the folders named, sorted, de-duplicated."""
    out: list[Path] = []
    for a in args:
        p = Path(a)
        if p.is_dir():
            out += sorted(p.rglob("*.ulg"))
        elif p.is_file():
            out.append(p)
        else:
            raise TwinError(f"{a}: <path>: expected a ULog file or a folder of them")
    seen, uniq = set(), []
    for p in out:
        r = p.resolve()
        if r not in seen:
            seen.add(r)
            uniq.append(r)
    if not uniq:
        raise TwinError(f"{' '.join(args)}: <path>: expected at least one .ulg file")
    return uniq


def load_params_map(path: str | None) -> dict[str, str] | None:
    """``vehicle id -> params file`` from a YAML mapping (relative files are relative to it)."""
    if not path:
        return None
    from twin_nodes.base.yamlio import read_yaml_file  # one-line errors, duplicate keys refused

    p = Path(path)
    data = read_yaml_file(p, "YAML mapping vehicle id -> params file")
    if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
        raise TwinError(f"{path}: <root>: expected a mapping vehicle id -> params file path")
    out = {}
    for k, v in data.items():
        f = Path(v) if Path(v).is_absolute() else (p.parent / v)
        if not f.is_file():
            raise TwinError(f"{path}: {k}: expected an existing params file, got {v}")
        out[str(k)] = str(f.resolve())
    return out


def _client(scheduler: str | None, workers: int):
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, timeout="20s"), None
        except OSError as exc:
            raise TwinError(f"{scheduler}: <scheduler>: expected a running Dask scheduler ({exc})") from None
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                           silence_logs=40)
    return Client(cluster), cluster


def run_fleet(flights: list[str | os.PathLike[str]], catalog: str | os.PathLike[str], *, mode: str = "discover",
              scheduler: str | None = None, workers: int = 2, params: str | None = None,
              params_map: dict[str, str] | None = None, closed_loop_metrics: bool = True,
              progress: bool | None = None, task: Callable = process_flight, retries: int = 1) -> dict:
    """Run ``task`` (default :func:`process_flight`) on every flight not yet in ``catalog``.

    Returns ``{"done": [...summaries], "skipped": n, "lost": [paths whose task could not finish]}``."""
    from dask.distributed import as_completed
    from tqdm import tqdm

    if mode not in ("discover", "compare"):
        raise TwinError(f"{mode}: <mode>: expected discover or compare")
    catalog = Path(catalog).resolve()
    catalog.mkdir(parents=True, exist_ok=True)
    paths = [Path(f).resolve() for f in flights]
    todo, skipped = pending(paths, catalog)
    out = {"done": [], "skipped": len(skipped), "lost": []}
    if not todo:
        return out
    client, cluster = _client(scheduler, workers)
    try:
        futs = {client.submit(task, str(p), str(catalog), mode, params, params_map, closed_loop_metrics,
                              key=f"flight-{p.stem}-{abs(hash(str(p))) % 10**8}", pure=False, retries=retries): p
                for p in todo}
        bar = tqdm(total=len(futs), desc=f"fleet {mode}", unit="flight",
                   disable=not (sys.stderr.isatty() if progress is None else progress))
        for fut in as_completed(futs):
            try:
                out["done"].append(fut.result())
            except Exception as exc:  # the worker died (killed) or the task crashed outside process_flight
                out["lost"].append({"path": str(futs[fut]), "error": f"{type(exc).__name__}: {exc}"})
            bar.update(1)
        bar.close()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return out
