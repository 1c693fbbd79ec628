"""Who flew a log and when: the vehicle identity and the flight date from the ULog header (pyulog, header only),
else the GPS fix, the file name or the file mtime.  Used by the per-flight runner (:mod:`twin_nodes.fleet.flight`)
and by the vehicle twin (:mod:`twin_nodes.fleet.vehicle_twin`), which orders a vehicle's flights by date."""

from __future__ import annotations

import contextlib
import datetime as _dt
import functools
import io
import os
import re
from pathlib import Path
from typing import Any, Callable

from twin_nodes.base.errors import TwinError


#: the topics of a log's side pass: the first GPS fix time (:func:`identity`) and the actuator-test commands
#: (:func:`twin_nodes.fleet.facts.actuator_tests`), read in one pyulog pass by the fleet runner
SIDE_TOPICS = ("vehicle_gps_position", "sensor_gps", "vehicle_command")
GPS_TOPICS = ("vehicle_gps_position", "sensor_gps")


def side_reader(path: str | os.PathLike[str]) -> Callable[[], Any]:
    """A function giving the pyulog ULog of the log's :data:`SIDE_TOPICS`, read on its first call, or None
    where that read fails or finds the file corrupt (each reader then reads its own topics alone, as it does
    without a side reader): one pass over the file instead of two."""
    from pyulog import ULog

    @functools.cache
    def side():
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # pyulog prints what it finds corrupt
                u = ULog(str(path), list(SIDE_TOPICS))
        except Exception:
            return None
        return None if u.file_corruption else u
    return side


def identity(path: str | os.PathLike[str], side: Callable[[], Any] | None = None) -> dict:
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
        t, src = _gps_time(path, side), "gps"
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


def _gps_time(path, side: Callable[[], Any] | None = None) -> float | None:
    """The first valid GPS UTC time in the log [s], or None (``side``: :func:`side_reader`'s)."""
    from pyulog import ULog

    u = side() if side is not None else None
    if u is None:
        try:
            u = ULog(str(path), list(GPS_TOPICS))
        except Exception:
            return None
    for d in u.data_list:  # sorted by name (pyulog): the same order whatever else was read
        if d.name not in GPS_TOPICS:
            continue
        t = d.data.get("time_utc_usec")
        if t is not None:
            ok = t[t > 1_000_000_000_000_000]
            if ok.size:
                return float(ok[0]) / 1e6
    return None
