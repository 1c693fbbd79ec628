"""A fleet run on Dask distributed: one task per flight, resumable, failures recorded, progress bar.

An embedded ``LocalCluster`` (processes, ``workers`` workers of one thread, everything listening
on 127.0.0.1 only, no dashboard unless asked for, and then on 127.0.0.1) unless a scheduler
address is given (``dask scheduler`` / ``dask worker`` started elsewhere).  Flights whose file
has an ``ok`` row in the catalog (same path and content) are skipped; a ``failed`` row is retried.
Files with identical content (sha256) are one flight: the first is done, the others are named as
duplicates.  Each task writes its own row file before it returns, so a worker killed mid-run
loses only the flight it was on, and the rerun does exactly the flights that have no ``ok`` row.
A task whose worker dies is retried by Dask (``retries``); if it still cannot finish, it is
reported and left for the rerun.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Callable

from twin_nodes.base.errors import TwinError, one_line
from twin_nodes.fleet.catalog import DONE, catalogued, file_key, is_done
from twin_nodes.fleet.flight import process_flight


def find_flights(args: list[str]) -> list[Path]:
    """ULog files named or found (recursively) in the folders named, sorted, each name once (as an
    absolute path, links not resolved: a second name of the same file is :func:`run_fleet`'s
    duplicate, named there)."""
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
        r = p.absolute()
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


def check_workers(workers) -> int:
    """``workers`` as a count >= 1 (an embedded cluster of 0 workers would wait forever)."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise TwinError(f"--workers: {workers}: expected an integer >= 1 (worker processes)")
    return workers


def _client(scheduler: str | None, workers: int, dashboard: bool = False):
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, timeout="20s"), None
        except OSError as exc:
            raise TwinError(f"{scheduler}: <scheduler>: expected a running Dask scheduler ({exc})") from None
    check_workers(workers)
    # loopback only: the scheduler, the nannies and the workers.  The scheduler always runs an HTTP
    # server (health, metrics); it gets a free port on 127.0.0.1, and the dashboard pages only when asked
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address="127.0.0.1:0" if dashboard else None, worker_dashboard_address=None,
                           scheduler_kwargs={"dashboard": dashboard, "dashboard_address": "127.0.0.1:0"},
                           silence_logs=40)
    return Client(cluster), cluster


def plan(keys: list[dict], rows: list[dict]) -> tuple[list[dict], list[dict], list[dict]]:
    """Split file keys (:func:`~twin_nodes.fleet.catalog.file_key`) against the catalog's rows
    (:func:`~twin_nodes.fleet.catalog.catalogued`) into (to do, already done, duplicates).

    Files with the same content are one flight: the one already ``ok`` in the catalog under its
    own path, else the first given, is kept; each other is a duplicate ``{"path", "same_as"}``
    (``path`` the name it was given by, ``given`` in the key, when that is a link to the other).
    A kept file whose content is ``ok`` in the catalog under another path is a duplicate of that
    path.  A ``failed`` row is not done: that flight is to do again."""
    by_path = {r["path"]: r for r in rows}
    ok_by_hash: dict[str, str] = {}
    for r in rows:
        if r.get("status") in DONE and r.get("content_sha256"):
            ok_by_hash.setdefault(r["content_sha256"], r["path"])
    groups: dict[str, list[dict]] = {}
    for k in keys:
        groups.setdefault(k["content_sha256"], []).append(k)
    todo, done, dups = [], [], []
    for k in keys:
        g = groups[k["content_sha256"]]
        keep = next((x for x in g if is_done(x, by_path.get(x["path"]))), g[0])
        if k is not keep:
            dups.append({"path": k.get("given", k["path"]), "same_as": keep["path"]})
        elif is_done(k, by_path.get(k["path"])):
            done.append(k)
        elif ok_by_hash.get(k["content_sha256"], k["path"]) != k["path"]:
            dups.append({"path": k["path"], "same_as": ok_by_hash[k["content_sha256"]]})
        else:
            todo.append(k)
    return todo, done, dups


def longest_first(todo: list[dict]) -> list[dict]:
    """The flights to do, the largest file first (a stable sort: equal sizes keep their order): the
    longest flights start first, so the last to finish is a short one and no worker idles while
    another finishes a long flight alone."""
    return sorted(todo, key=lambda k: -int(k.get("file_size") or 0))


def run_fleet(flights: list[str | os.PathLike[str]], catalog: str | os.PathLike[str], *, mode: str = "discover",
              scheduler: str | None = None, workers: int = 2, params: str | None = None,
              params_map: dict[str, str] | None = None, closed_loop_metrics: bool = True,
              progress: bool | None = None, task: Callable = process_flight, retries: int = 1,
              dashboard: bool = False) -> dict:
    """Run ``task`` (default :func:`process_flight`) on every flight without an ``ok`` row in ``catalog``.

    Returns ``{"done": [...summaries], "skipped": n, "lost": [paths whose task could not finish],
    "duplicates": [{"path", "same_as"}]}``; a summary's ``status`` is ``ok`` or ``failed``."""
    from dask.distributed import as_completed
    from tqdm import tqdm

    if mode not in ("discover", "compare"):
        raise TwinError(f"{mode}: <mode>: expected discover or compare")
    check_workers(workers)
    catalog = Path(catalog).resolve()
    catalog.mkdir(parents=True, exist_ok=True)
    keys = [{**file_key(f), "given": str(Path(f).absolute())} for f in flights]
    todo, skipped, dups = plan(keys, catalogued(catalog))
    out = {"done": [], "skipped": len(skipped), "lost": [], "duplicates": dups}
    if not todo:
        return out
    todo = longest_first(todo)
    client, cluster = _client(scheduler, workers, dashboard)
    try:
        # priority: the order of ``todo`` (largest first) is the order the workers take them in
        futs = {client.submit(task, k["path"], str(catalog), mode, params, params_map, closed_loop_metrics,
                              key=f"flight-{Path(k['path']).stem}-{k['content_sha256'][:12]}", pure=False,
                              retries=retries, priority=len(todo) - i): k["path"]
                for i, k in enumerate(todo)}
        bar = tqdm(total=len(futs), desc=f"fleet {mode}", unit="flight",
                   disable=not (sys.stderr.isatty() if progress is None else progress))
        for fut in as_completed(futs):
            try:
                out["done"].append(fut.result())
            except Exception as exc:  # the worker died (killed) or the task crashed outside process_flight
                first = one_line(str(exc).strip().splitlines()[0]) if str(exc).strip() else ""
                out["lost"].append({"path": str(futs[fut]), "error": f"{type(exc).__name__}: {first}"})
            bar.update(1)
        bar.close()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return out
