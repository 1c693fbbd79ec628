"""One flight -> one catalog row: identity and date from the ULog header, params, discovery or the twin.

:func:`process_flight` never raises for a bad flight: it returns a ``failed`` row carrying the
one-line error (the :class:`~twin_nodes.base.errors.TwinError` message; any other exception as
``<file>: <Type>: <message>``), so one bad log never stops a fleet run.  The identity and date are
read first and kept on a failed row; when even the header cannot be read they come from the
folder and the file mtime (:func:`fallback_identity`).  It runs on a Dask worker; everything it
needs is imported inside it.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

from twin_nodes.base.errors import TwinError
from twin_nodes.discovery.survey import failure_reason as reason
from twin_nodes.fleet.catalog import effect_columns, file_key, now_utc, verdict, write_row
from twin_nodes.fleet.identity import fallback_identity, identity, side_reader


def resolve_params(path: str | os.PathLike[str], vehicle_id: str, params: str | None,
                   params_map: dict[str, str] | None, log: Any = None, build: Any = None) -> tuple[Path, str]:
    """The params file for one flight: ``--params``, else the per-vehicle map, else from the log (``build``:
    its nominal, :func:`~twin_nodes.identify.nominal.nominal_once`, when already built for the facts)."""
    from twin_nodes.identify.nominal import params_for_log

    if params:
        return Path(params), "given"
    if params_map and vehicle_id in params_map:
        return Path(params_map[vehicle_id]), f"params map: {vehicle_id}"
    p, note = params_for_log(path, None, log=log, build=build)
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


#: this process has its compiled code (see :func:`warm_compiled`)
_WARM: list[bool] = []


def warm_compiled() -> None:
    """Compile, or load, the numba code a flight's twin and discovery call (the effect registry's stepper
    and discovery's kernels, :func:`~twin_nodes.discovery.kernels.warm_steps`), once per process, each
    entry point under an exclusive lock of its own in the code cache folder (``$ROTORTWIN_CODE_CACHE``, or
    ``$ROTORTWIN_CACHE`` where that is read-only: ``compile.<entry point>.lock``); after ``make setup`` (which
    fills the code cache) each entry point is only loaded: on a cold start the first worker compiles the
    stepper's step (and with it the functions every entry point calls) while another waits, then the two compile
    the other entry
    points side by side (one whose lock another worker holds is left for later) and each loads what the other
    wrote, waiting for an entry point still being compiled (waiting costs no CPU) instead of compiling the
    same code a second time; until a worker reaches a free flight it handles logs that need no compiled code.  A
    failure here is left to the flight's own calls (they compile what they need, as before)."""
    if _WARM:
        return
    _WARM.append(True)
    try:
        import fcntl  # POSIX; elsewhere each flight compiles what it needs, as before

        from twin_nodes.discovery.kernels import warm_steps
        from twin_nodes.physics.codecache import lock_dir

        # each pass waits for its first entry point (the first of all, the stepper's step, compiles the functions
        # every other one calls: those are then loaded, not compiled by both), then takes each other one no
        # other worker is compiling now; those are left for the next pass
        todo = warm_steps()
        while todo:
            left = []
            for k, (name, step) in enumerate(todo):
                with open(lock_dir() / f"compile.{name}.lock", "a") as f:  # released when closed, or on death
                    try:
                        fcntl.flock(f, fcntl.LOCK_EX | (fcntl.LOCK_NB if k else 0))
                    except BlockingIOError:  # another worker compiles it: its cache file, loaded later
                        left.append((name, step))
                        continue
                    step()
            todo = left
    except Exception as exc:  # noqa: BLE001 - the flight's own calls compile what they need, as before
        import logging

        logging.getLogger("rotortwin.fleet").warning("compiling ahead failed (%s: %s)", type(exc).__name__, exc)


def warm_installed() -> list[str]:
    """Compile ahead, as ``make setup`` does (``rotortwin fleet warm``), the numba code a fleet flight runs: the
    generated stepper and discovery's kernels into the per-user code cache
    (:func:`~twin_nodes.discovery.kernels.warm_all`), and the package's own numba functions a flight calls
    directly (the low-pass filter, the unhooked rotor states, the motor lag) into numba's cache beside their
    files, each with the argument types a flight calls it with.  Returns the generated modules' names."""
    import numpy as np

    from twin_nodes.discovery.kernels import warm_all
    from twin_nodes.discovery.lowpass import lowpass
    from twin_nodes.discovery.residuals import lag_states
    from twin_nodes.identify.step_response import simulate_lag
    from twin_nodes.physics.model import Multirotor
    from twin_nodes.vehicle.params import load_params, params_dir

    names = warm_all()
    lowpass(np.zeros((64, 3)), 100.0, 10.0)
    m = Multirotor(load_params(params_dir() / "px4_sih_quadx.yaml"))
    u = np.full((4, m.n_rotors), 0.5)
    u.setflags(write=False)  # discovery's command series are read-only views
    lag_states(m.P, u, 0.002, 0, np.zeros(m.n_rotors), 1, 2)
    t = np.linspace(0.0, 1.0, 11)
    simulate_lag(t, np.where(t < 0.5, 0.2, 0.6), t, tau_up_s=0.05)
    return names


class NotAFlight(Exception):
    """The log is no free flight (a ground/bench test, too short, no GPS): its row so far, kind and reason."""

    def __init__(self, row: dict):
        super().__init__(row.get("kind_reason", ""))
        self.row = row


def analyse(path: str, mode: str, params: str | None, params_map: dict | None,
            closed_loop_metrics: bool, ident: dict | None = None, side=None) -> dict:
    """The row of one flight (raises TwinError on a bad flight); ``ident`` as :func:`identity`
    returns it, read here when not given; ``side``: a :func:`~twin_nodes.fleet.identity.side_reader`."""
    from twin_nodes.fleet.facts import flight_facts
    from twin_nodes.identify.nominal import nominal_once
    from twin_nodes.logs.flyable import check_flyable
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.vehicle.params import load_params

    ident = identity(path, side) if ident is None else ident
    log = read_ulog(path)  # loaded once
    build = nominal_once(log)  # the nominal built from the log, once: for the facts and for the params it flies
    row = {**ident, "duration_s": float(log.duration_s), **flight_facts(path, log, side, build)}
    if row["flight_kind"] != "free flight":  # a ground test, too short, no GPS: a row saying so, not a failure
        raise NotAFlight(row)
    if mode == "discover":  # its compiled code, once per process: one cold worker compiles, the others load it
        warm_compiled()
    try:
        check_flyable(log)
        pfile, note = resolve_params(path, ident["vehicle_id"], params, params_map, log=log, build=build)
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
    side = side_reader(path)  # the GPS time and the actuator tests: one pass over the file
    try:
        ident = identity(path, side)
    except Exception as exc:  # unreadable header: the row still says which vehicle (folder) and when (mtime)
        row.update(fallback_identity(path), status="failed", error=reason(path, exc))
    else:
        row.update(ident)
        try:
            row.update(analyse(path, mode, params, params_map, closed_loop_metrics, ident, side))
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
