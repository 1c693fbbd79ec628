"""The flight catalog: one Parquet file per flight in a folder, read back with DuckDB.

A row holds the flight's file key (path, size, mtime), its vehicle identity and date from the
ULog header, its duration, the status (``ok`` / ``failed`` with the one-line error), the Table-2
closed-loop metrics when discovery computed them, and every effect with its verdict and
parameters (flat ``effect_<name>_<param>`` columns for the accepted ones plus ``effects_json``
with all of them).  Each file is written to a temporary name and renamed, so a killed worker
leaves either the whole row or nothing.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
from pathlib import Path

from twin_nodes.base.errors import TwinError

#: verdicts that count as "the effect is there" (graded verdicts; ``accepted`` when absent)
PRESENT = ("confirmed", "accepted")


def file_key(path: str | os.PathLike[str]) -> dict:
    """What identifies one version of a flight file: absolute path, size and mtime (ns)."""
    p = Path(path).resolve()
    st = p.stat()
    return {"path": str(p), "file_size": int(st.st_size), "file_mtime_ns": int(st.st_mtime_ns)}


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


def _files(catalog: str | os.PathLike[str]) -> list[Path]:
    d = Path(catalog)
    if not d.is_dir():
        return []
    return sorted(d.glob("*.parquet"))


def connect(catalog: str | os.PathLike[str]):
    """A DuckDB connection with the view ``flights`` over every row file of the catalog."""
    import duckdb

    con = duckdb.connect()
    files = _files(catalog)
    if not files:
        raise TwinError(f"{catalog}: <catalog>: expected a folder of flight .parquet files (none found)")
    glob = str(Path(catalog).resolve() / "*.parquet").replace("'", "''")
    con.execute(f"CREATE VIEW flights AS SELECT * FROM read_parquet('{glob}', union_by_name=true)")
    return con


def query(catalog: str | os.PathLike[str], sql: str) -> tuple[list[str], list[tuple]]:
    """Run ``sql`` against the catalog (the table is ``flights``); column names and rows."""
    import duckdb

    con = connect(catalog)
    try:
        cur = con.execute(sql)
    except duckdb.Error as exc:
        raise TwinError(f"{catalog}: <sql>: {str(exc).splitlines()[0]}") from None
    return [d[0] for d in cur.description], cur.fetchall()


def load(catalog: str | os.PathLike[str]) -> list[dict]:
    """Every row of the catalog as a dict, ordered by vehicle, flight date and path."""
    if not _files(catalog):
        return []
    cols, rows = query(catalog, "SELECT * FROM flights ORDER BY vehicle_id, flight_time_utc, path")
    return [dict(zip(cols, r)) for r in rows]


def done_keys(catalog: str | os.PathLike[str]) -> dict[str, tuple[int, int]]:
    """path -> (size, mtime_ns) of every flight already in the catalog (``ok`` or ``failed``)."""
    out = {}
    for f in _files(catalog):
        import pyarrow.parquet as pq
        try:
            t = pq.read_table(f, columns=["path", "file_size", "file_mtime_ns"]).to_pylist()
        except Exception:  # a foreign or damaged file: that flight is simply redone
            continue
        for r in t:
            out[r["path"]] = (int(r["file_size"]), int(r["file_mtime_ns"]))
    return out


def pending(paths: list[Path], catalog: str | os.PathLike[str]) -> tuple[list[Path], list[Path]]:
    """Split flights into (to do, already catalogued with the same size and mtime)."""
    done = done_keys(catalog)
    todo, skip = [], []
    for p in paths:
        k = file_key(p)
        (skip if done.get(k["path"]) == (k["file_size"], k["file_mtime_ns"]) else todo).append(p)
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
