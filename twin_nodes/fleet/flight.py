"""One flight -> one catalog row: identity and date from the ULog header, params, discovery or the twin.

:func:`process_flight` never raises for a bad flight: it returns a ``failed`` row carrying the
one-line error (the :class:`~twin_nodes.base.errors.TwinError` message; any other exception as
``<file>: <Type>: <message>``), so one bad log never stops a fleet run.  The identity and date are
read first and kept on a failed row; when even the header cannot be read they come from the
folder and the file mtime (:func:`fallback_identity`).  It runs on a Dask worker; everything it
needs is imported inside it.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re
import time
from pathlib import Path
from typing import Any

from twin_nodes.base.errors import TwinError
from twin_nodes.discovery.survey import failure_reason as reason
from twin_nodes.fleet.catalog import effect_columns, file_key, now_utc, verdict, write_row


def identity(path: str | os.PathLike[str]) -> dict:
    """Vehicle identity and flight date from the ULog header (pyulog, header only).

    ``vehicle_id``: ``sys_uuid`` if logged, else the hardware id (``ver_hw`` + ``ver_hw_subtype``)
    with ``sys_name``, else the file's folder; ``vehicle_id_source`` says which.  Date:
    ``time_ref_utc`` (info), else the first GPS fix time, else the date and time in the file name,
    else the file mtime (``date_source``, see :func:`file_date`)."""
    from pyulog import ULog

    try:
        u = ULog(str(path), parse_header_only=True)
    except Exception as exc:  # pyulog raises bare exceptions on damaged files
        raise TwinError(f"{path}: <header>: expected a readable ULog header ({type(exc).__name__}: {exc})"
                        ) from None
    info = u.msg_info_dict
    out = {"sys_uuid": str(info.get("sys_uuid", "") or ""), "ver_hw": str(info.get("ver_hw", "") or ""),
           "sys_name": str(info.get("sys_name", "") or "")}
    hw = "/".join(x for x in (out["ver_hw"], str(info.get("ver_hw_subtype", "") or "")) if x)
    if out["sys_uuid"]:
        out["vehicle_id"], out["vehicle_id_source"] = out["sys_uuid"], "sys_uuid"
    elif hw and out["sys_name"]:
        out["vehicle_id"], out["vehicle_id_source"] = f"{out['sys_name']}:{hw}", "sys_name+ver_hw"
    else:
        out["vehicle_id"], out["vehicle_id_source"] = f"folder:{Path(path).resolve().parent.name}", "folder"
    ref = info.get("time_ref_utc")
    t = None
    if isinstance(ref, (int, float)) and ref > 0:
        t, src = float(ref), "time_ref_utc"
    else:
        t, src = _gps_time(path), "gps"
    named, nsrc = file_date(path)
    out["file_name_time"] = named if nsrc == "file_name" else ""  # local time of the downloader: see report
    if t is None:
        out["flight_time_utc"], out["date_source"] = file_date(path)
    else:
        out["flight_time_utc"] = _dt.datetime.fromtimestamp(t, _dt.timezone.utc).isoformat(timespec="seconds")
        out["date_source"] = src
    return out


#: QGroundControl's download name ``log_<n>_<Y>-<M>-<D>-<h>-<m>-<s>.ulg`` (local time of the
#: computer that downloaded it); PX4's own ``<Y>-<M>-<D>/<h>_<m>_<s>.ulg`` on the SD card
_QGC_NAME = re.compile(r"(\d{4})-(\d{1,2})-(\d{1,2})-(\d{1,2})-(\d{1,2})-(\d{1,2})$")
_PX4_DIR, _PX4_STEM = re.compile(r"^(\d{4})-(\d{2})-(\d{2})$"), re.compile(r"^(\d{2})_(\d{2})_(\d{2})$")


def file_date(path: str | os.PathLike[str]) -> tuple[str, str]:
    """``(flight time, date_source)`` from the file alone: the date and time in its name
    (``file_name``; written without a zone: QGroundControl names downloads in local time), else its
    mtime in UTC (``file_mtime``), else ``("", "")``."""
    p = Path(path)
    m = _QGC_NAME.search(p.stem)
    parts = m.groups() if m else None
    if parts is None and _PX4_DIR.match(p.parent.name) and _PX4_STEM.match(p.stem):
        parts = _PX4_DIR.match(p.parent.name).groups() + _PX4_STEM.match(p.stem).groups()
    if parts is not None:
        try:
            return _dt.datetime(*map(int, parts)).isoformat(timespec="seconds"), "file_name"
        except ValueError:  # not a date after all (month 13...)
            pass
    try:
        t = p.stat().st_mtime
    except OSError:
        return "", ""
    return _dt.datetime.fromtimestamp(t, _dt.timezone.utc).isoformat(timespec="seconds"), "file_mtime"


def fallback_identity(path: str | os.PathLike[str]) -> dict:
    """Identity and date of a file whose header cannot be read: its folder, and the date of
    :func:`file_date` (its name, else its mtime)."""
    p = Path(path).resolve()
    when, src = file_date(p)
    return {"sys_uuid": "", "ver_hw": "", "sys_name": "", "vehicle_id": f"folder:{p.parent.name}",
            "vehicle_id_source": "folder", "flight_time_utc": when, "date_source": src,
            "file_name_time": when if src == "file_name" else ""}


def _gps_time(path) -> float | None:
    """The first valid GPS UTC time in the log [s], or None."""
    from pyulog import ULog

    try:
        u = ULog(str(path), ["vehicle_gps_position", "sensor_gps"])
    except Exception:
        return None
    for d in u.data_list:
        t = d.data.get("time_utc_usec")
        if t is not None:
            ok = t[t > 1_000_000_000_000_000]
            if ok.size:
                return float(ok[0]) / 1e6
    return None


def resolve_params(path: str | os.PathLike[str], vehicle_id: str, params: str | None,
                   params_map: dict[str, str] | None, log: Any = None) -> tuple[Path, str]:
    """The params file for one flight: ``--params``, else the per-vehicle map, else from the log."""
    from twin_nodes.identify.nominal import params_for_log

    if params:
        return Path(params), "given"
    if params_map and vehicle_id in params_map:
        return Path(params_map[vehicle_id]), f"params map: {vehicle_id}"
    p, note = params_for_log(path, None, log=log)
    return p, (note or "from log").split(";")[0]


def _num(v):
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(float(v)) else None


def metric_columns(prefix: str, m: dict | None) -> dict:
    """Table-2 scalars as ``<prefix>_<metric>`` columns (per-motor lists as ``_m<i>``)."""
    out = {}
    for k, v in (m or {}).items():
        if isinstance(v, list):
            for i, x in enumerate(v):
                if _num(x) is not None:
                    out[f"{prefix}_{k}_m{i}"] = _num(x)
        elif _num(v) is not None:
            out[f"{prefix}_{k}"] = _num(v)
    return out


class NotAFlight(Exception):
    """The log is no free flight (a ground/bench test, too short, no GPS): its row so far, kind and reason."""

    def __init__(self, row: dict):
        super().__init__(row.get("kind_reason", ""))
        self.row = row


def analyse(path: str, mode: str, params: str | None, params_map: dict | None,
            closed_loop_metrics: bool, ident: dict | None = None) -> dict:
    """The row of one flight (raises TwinError on a bad flight); ``ident`` as :func:`identity`
    returns it, read here when not given."""
    from twin_nodes.fleet.facts import flight_facts
    from twin_nodes.logs.flyable import check_flyable
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.vehicle.params import load_params

    ident = identity(path) if ident is None else ident
    log = read_ulog(path)  # loaded once
    row = {**ident, "duration_s": float(log.duration_s), **flight_facts(path, log)}
    if row["flight_kind"] != "free flight":  # a ground test, too short, no GPS: a row saying so, not a failure
        raise NotAFlight(row)
    try:
        check_flyable(log)
        pfile, note = resolve_params(path, ident["vehicle_id"], params, params_map, log=log)
        vp = load_params(pfile)
    except TwinError as exc:  # a free flight the twin cannot fly (too little usable data, no nominal): its
        row["discover_error"] = str(exc)  # identified values are kept, the row is ok, the reason is recorded
        return row
    row.update({"params_file": str(pfile), "params_note": note, "nominal_mass_kg": float(vp.mass_kg),
                "params_is_vehicle_twin": bool(params or (params_map and ident["vehicle_id"] in params_map))})
    if mode == "compare":
        from twin_nodes.twin.compare import compare_log

        row.update(metric_columns("closed", compare_log(log, vp, mode="closed").metrics))
        return row
    from twin_nodes.discovery.discover import discover
    from twin_nodes.fleet.vehicle_twin import read_vehicle_facts, since_twin

    ref = read_vehicle_facts(pfile)
    if ref is not None:  # a vehicle twin: what differs on this flight, named (discover's "since the vehicle twin")
        sv = since_twin(log, path, ref)
        row.update(since_twin=sv["name"], since_twin_why=sv["why"], since_twin_values=",".join(sorted(sv["differs"])))
    try:
        res = discover(log, vp, closed_loop_metrics=closed_loop_metrics)
    except TwinError as exc:  # discovery refuses this flight (e.g. too little usable airborne data)
        row["discover_error"] = str(exc)
        return row
    effects = [{"name": e.get("name"), "verdict": verdict(e), "params": e.get("params") or {},
                "evidence": e.get("evidence", "")} for e in res.get("effects", [])]
    row["effects_json"] = json.dumps(effects, default=float)
    row["effects_present"] = ",".join(sorted({f"{e['name']}" for e in effects if e["verdict"] != "rejected"}))
    row.update(effect_columns(effects))
    for side in ("baseline", "after"):
        row.update(metric_columns(f"{side}_closed", (res.get(side) or {}).get("closed_loop_heldout")))
    return row


def process_flight(path: str, catalog: str, mode: str = "discover", params: str | None = None,
                   params_map: dict | None = None, closed_loop_metrics: bool = True) -> dict:
    """Analyse one flight and write its catalog row; returns a short summary (never raises on a
    bad flight: the row is ``failed`` with the one-line error)."""
    t0 = time.time()
    key = file_key(path)
    row = {**key, "mode": mode, "status": "ok", "error": ""}
    try:
        ident = identity(path)
    except Exception as exc:  # unreadable header: the row still says which vehicle (folder) and when (mtime)
        row.update(fallback_identity(path), status="failed", error=reason(path, exc))
    else:
        row.update(ident)
        try:
            row.update(analyse(path, mode, params, params_map, closed_loop_metrics, ident))
        except NotAFlight as nf:  # recognised, recorded with its kind and reason; done (not retried)
            row.update(nf.row, status="not_flight", error=nf.row.get("kind_reason", ""))
        except Exception as exc:  # a bad flight, or a bug on one flight: recorded, one line; the fleet goes on
            row.update(status="failed", error=reason(path, exc))
    row["elapsed_s"] = round(time.time() - t0, 2)
    row["processed_at"] = now_utc()
    write_row(catalog, row)
    return {"path": key["path"], "status": row["status"], "error": row["error"], "vehicle_id": row["vehicle_id"],
            "flight_time_utc": row["flight_time_utc"], "elapsed_s": row["elapsed_s"],
            "effects": row.get("effects_present", ""), "flight_kind": row.get("flight_kind", ""),
            "discover_error": row.get("discover_error", "")}
