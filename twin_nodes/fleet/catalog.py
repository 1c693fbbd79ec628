"""The flight catalog: one Parquet file per flight in a folder, read back with DuckDB.

A row holds the flight's file key (path, size, mtime), its vehicle identity and date from the
ULog header, its duration, the status (``ok``; ``not_flight`` for a ground/bench test, a flight too short or
without GPS, with its kind and reason; ``failed`` with the one-line error), the flight's kind, motor PWM range,
firmware parameters and identified values (``fact_*``, :mod:`twin_nodes.fleet.facts`), the Table-2
closed-loop metrics when discovery computed them, and every effect with its verdict and
parameters (flat ``effect_<name>_<param>`` columns for the accepted ones plus ``effects_json``
with all of them).  Each file is written to a temporary name and renamed, so a killed worker
leaves either the whole row or nothing.  A row file that cannot be read (damaged, foreign) is left
out of every query with a one-line warning naming it (:func:`row_files`), never fatal.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

from twin_nodes.base.errors import TwinError, one_line

#: verdicts that count as "the effect is there" (graded verdicts; ``accepted`` when absent)
PRESENT = ("confirmed", "accepted")
LOG = logging.getLogger("rotortwin.fleet")


def content_hash(path: str | os.PathLike[str]) -> str:
    """sha256 of the file's bytes (hex): the same flight under two names is one flight."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_key(path: str | os.PathLike[str]) -> dict:
    """What identifies one version of a flight file: absolute path, size, mtime (ns) and the
    sha256 of its content."""
    p = Path(path).resolve()
    st = p.stat()
    return {"path": str(p), "file_size": int(st.st_size), "file_mtime_ns": int(st.st_mtime_ns),
            "content_sha256": content_hash(p)}


def row_file(catalog: str | os.PathLike[str], path: str | os.PathLike[str]) -> Path:
    """The catalog file of one flight (named by its stem and a hash of its absolute path)."""
    p = Path(path).resolve()
    h = hashlib.sha1(str(p).encode()).hexdigest()[:10]
    return Path(catalog) / f"{p.stem}-{h}.parquet"


def _jsonable(v):
    if isinstance(v, (list, dict, tuple)):
        return json.dumps(v, default=str)
    return v


def write_row(catalog: str | os.PathLike[str], row: dict) -> Path:
    """Write one flight's row atomically (temporary file in the same folder, then rename)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    out = row_file(catalog, row["path"])
    out.parent.mkdir(parents=True, exist_ok=True)
    flat = {k: [_jsonable(v)] for k, v in row.items()}
    table = pa.table(flat)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        pq.write_table(table, tmp)
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return out


@dataclass
class RowFiles:
    """The row files of a catalog folder: the readable ones and the damaged ones with why."""
    good: list[Path] = field(default_factory=list)
    corrupt: list[dict] = field(default_factory=list)  # {"file", "error"}


def _read_error(f: Path) -> str | None:
    """None when ``f`` reads as a Parquet table with a ``path`` column, else why not (one line)."""
    import pyarrow.parquet as pq

    try:
        t = pq.read_table(f)
    except Exception as exc:  # pyarrow raises several types on damaged files
        text = (str(exc).splitlines() or [""])[0].replace(f"'{f}'", "").replace(str(f), "").replace("  ", " ")
        return f"{type(exc).__name__}: {one_line(text.strip())}"
    if "path" not in t.column_names:
        return "no path column (not a flight row)"
    return None


def row_files(catalog: str | os.PathLike[str], warn: bool = True) -> RowFiles:
    """Every ``*.parquet`` in the catalog, split into readable and damaged; each damaged one is
    logged once as ``<file>: <parquet>: expected a readable flight row file (...); skipped``."""
    d = Path(catalog)
    out = RowFiles()
    if not d.is_dir():
        return out
    for f in sorted(d.glob("*.parquet")):
        err = _read_error(f)
        if err is None:
            out.good.append(f)
            continue
        out.corrupt.append({"file": str(f.resolve()), "error": err})
        if warn:
            LOG.warning("%s: <parquet>: expected a readable flight row file (%s); skipped", f.resolve(), err)
    return out


def _files(catalog: str | os.PathLike[str]) -> list[Path]:
    return row_files(catalog).good


def connect(catalog: str | os.PathLike[str], files: list[Path] | None = None):
    """A DuckDB connection with the view ``flights`` over every readable row file of the catalog
    (damaged ones are skipped with a warning, see :func:`row_files`)."""
    import duckdb

    files = _files(catalog) if files is None else files
    if not files:
        raise TwinError(f"{catalog}: <catalog>: expected a folder of flight .parquet files (none readable)")
    con = duckdb.connect()
    lst = ", ".join("'" + str(Path(f).resolve()).replace("'", "''") + "'" for f in files)
    con.execute(f"CREATE VIEW flights AS SELECT * FROM read_parquet([{lst}], union_by_name=true)")
    return con


def query(catalog: str | os.PathLike[str], sql: str,
          files: list[Path] | None = None) -> tuple[list[str], list[tuple]]:
    """Run ``sql`` against the catalog (the table is ``flights``); column names and rows."""
    import duckdb

    con = connect(catalog, files)
    try:
        cur = con.execute(sql)
    except duckdb.Error as exc:
        raise TwinError(f"{catalog}: <sql>: {one_line(str(exc).splitlines()[0])}") from None
    return [d[0] for d in cur.description], cur.fetchall()


def load(catalog: str | os.PathLike[str], files: list[Path] | None = None) -> list[dict]:
    """Every row of the readable row files, ordered by vehicle, flight date and path."""
    files = _files(catalog) if files is None else files
    if not files:
        return []
    cols, rows = query(catalog, "SELECT * FROM flights ORDER BY vehicle_id, flight_time_utc, path", files)
    return [dict(zip(cols, r)) for r in rows]


def catalogued(catalog: str | os.PathLike[str]) -> list[dict]:
    """path, file_size, file_mtime_ns, status and content_sha256 (None in rows written before it
    was recorded) of every readable row; damaged row files are skipped (their flight is redone)."""
    import pyarrow.parquet as pq

    want = ("path", "file_size", "file_mtime_ns", "status", "content_sha256")
    out = []
    for f in row_files(catalog, warn=False).good:
        t = pq.read_table(f)
        for r in t.select([c for c in want if c in t.column_names]).to_pylist():
            out.append({k: r.get(k) for k in want})
    return out


#: row statuses that need no rerun: analysed, or recognised as no free flight (ground test, too short, no GPS)
DONE = ("ok", "not_flight")


def is_done(key: dict, row: dict | None) -> bool:
    """Whether the catalog ``row`` of a path covers this version of the file: an ``ok`` row with
    the same content (sha256; size and mtime for rows without a hash)."""
    if not row or row.get("status") not in DONE or row.get("path") != key["path"]:
        return False
    if row.get("content_sha256") and key.get("content_sha256"):
        return row["content_sha256"] == key["content_sha256"]
    return (row.get("file_size"), row.get("file_mtime_ns")) == (key["file_size"], key["file_mtime_ns"])


def pending(paths: list[Path], catalog: str | os.PathLike[str]) -> tuple[list[Path], list[Path]]:
    """Split flights into (to do, already done): done is an ``ok`` row for the same path and
    content; a ``failed`` row, a changed file or a damaged row file means to do."""
    rows = {r["path"]: r for r in catalogued(catalog)}
    todo, skip = [], []
    for p in paths:
        k = file_key(p)
        (skip if is_done(k, rows.get(k["path"])) else todo).append(p)
    return todo, skip


def effect_columns(effects: list[dict]) -> dict:
    """Flat columns for the effects that are present (verdict confirmed/accepted; ``likely`` too,
    with its verdict): ``effect_<name>[_m<motor>]_<param>`` and ``effect_<name>[_m<motor>]_verdict``."""
    out = {}
    for e in effects:
        v = verdict(e)
        if v == "rejected":
            continue
        key = effect_key(e)
        out[f"effect_{key}_verdict"] = v
        for p, x in (e.get("params") or {}).items():
            if p == "motor":
                continue
            if isinstance(x, (int, float)):
                out[f"effect_{key}_{p}"] = float(x)
    return out


def verdict(e: dict) -> str:
    """``confirmed`` / ``likely`` / ``rejected`` where discovery grades; else accepted/rejected."""
    v = e.get("verdict")
    if v:
        return str(v)
    return "accepted" if e.get("accepted") else "rejected"


def effect_key(e: dict) -> str:
    """The effect's name, with the motor for per-motor effects: ``motor_efficiency_m3``."""
    p = e.get("params") or {}
    if "motor" in p:
        return f"{e['name']}_m{int(p['motor'])}"
    return str(e["name"])


def now_utc() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
