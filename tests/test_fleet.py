"""Fleet scale: the catalog, the report's trends and alarms, the Dask runner (resume, failures,
a killed worker, an external scheduler) and — slow — a simulated fleet discovered end to end."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("dask.distributed")
pytest.importorskip("duckdb")

from twin_nodes.fleet import catalog as cat  # noqa: E402
from twin_nodes.fleet.report import alarms, trends, write_report  # noqa: E402
from twin_nodes.fleet.run import run_fleet  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DAY = "2026-06-{:02d}T09:00:00+00:00"


def _row(path: Path, vehicle: str, day: int, effects: list[dict], status="ok", error="") -> dict:
    return {**cat.file_key(path), "mode": "discover", "status": status, "error": error, "vehicle_id": vehicle,
            "vehicle_id_source": "sys_uuid", "flight_time_utc": DAY.format(day + 1), "date_source": "time_ref_utc",
            "duration_s": 130.0, "nominal_mass_kg": 1.0, "effects_json": json.dumps(effects),
            "params_is_vehicle_twin": True,  # discovery against the given params (the vehicle twin), as simulated
            **cat.effect_columns(effects)}


def _fleet_rows(tmp: Path) -> list[dict]:
    """3 vehicles x 6 flights as discovery would report them: motor 3 of quad-00 weakening
    1.00 -> 0.80 (found from 0.96 on), quad-01 with 1.25 kg on flights 1 and 4, quad-02 healthy
    (one rejected candidate, one single 'likely' drag)."""
    rows = []
    for k in range(6):
        e = round(1.0 - 0.04 * k, 3)
        f = tmp / f"quad-00_d{k:02d}.ulg"
        f.write_bytes(b"x" * (k + 1))
        eff = [{"name": "motor_efficiency", "verdict": "confirmed", "params": {"motor": 3, "efficiency": e}}] if k else []
        rows.append(_row(f, "uuid-00", k, eff))
        f = tmp / f"quad-01_d{k:02d}.ulg"
        f.write_bytes(b"y" * (k + 1))
        eff = [{"name": "mass", "verdict": "confirmed", "params": {"mass": 1.25}}] if k in (1, 4) else []
        rows.append(_row(f, "uuid-01", k, eff))
        f = tmp / f"quad-02_d{k:02d}.ulg"
        f.write_bytes(b"z" * (k + 1))
        eff = [{"name": "linear_drag", "verdict": "rejected", "params": {"kd": 0.3}}]
        if k == 3:
            eff.append({"name": "rotor_drag", "verdict": "likely", "params": {"kd": 0.01}})
        rows.append(_row(f, "uuid-02", k, eff))
    return rows


def test_catalog_rows_atomic_query_and_resume_keys(tmp_path):
    rows = _fleet_rows(tmp_path)
    catalog = tmp_path / "cat"
    for r in rows:
        cat.write_row(catalog, r)
    assert len(list(catalog.glob("*.parquet"))) == 18 and not list(catalog.glob(".*tmp"))
    cols, res = cat.query(catalog, "SELECT vehicle_id, count(*), min(effect_motor_efficiency_m3_efficiency) "
                                   "FROM flights GROUP BY vehicle_id ORDER BY vehicle_id")
    assert res[0] == ("uuid-00", 6, pytest.approx(0.8)) and res[1][2] is None
    todo, skip = cat.pending([Path(r["path"]) for r in rows], catalog)
    assert not todo and len(skip) == 18
    f = Path(rows[0]["path"])
    f.write_bytes(b"changed!")  # a changed file is redone
    todo, _ = cat.pending([Path(r["path"]) for r in rows], catalog)
    assert todo == [f.resolve()]
    with pytest.raises(cat.TwinError, match="<sql>"):
        cat.query(catalog, "SELECT nope FROM flights")


def test_report_names_degrading_motor_payload_days_and_nothing_on_healthy(tmp_path):
    rows = _fleet_rows(tmp_path)
    catalog = tmp_path / "cat"
    for r in rows:
        cat.write_row(catalog, r)
    s = write_report(catalog, tmp_path / "rep")
    al = {(a["vehicle_id"], a["kind"]): a for a in s["alarms"]}
    assert set(al) == {("uuid-00", "threshold"), ("uuid-01", "payload")}
    deg = al[("uuid-00", "threshold")]
    # 1.00 .96 .92 .88 ...: crosses 0.9 on the 4th flight
    assert deg["effect"] == "motor_efficiency_m3" and deg["flight"] == "quad-00_d03.ulg"
    assert "motor 3 efficiency 1.00 -> 0.80" in deg["message"]
    pay = al[("uuid-01", "payload")]
    assert pay["flights"] == ["quad-01_d01.ulg", "quad-01_d04.ulg"]
    assert "2026-06-02" in pay["message"] and "2026-06-05" in pay["message"]
    html = (tmp_path / "rep" / "index.html").read_text()
    assert "quad-00_d03.ulg" in html and len(list((tmp_path / "rep").glob("trend_*.png"))) >= 2
    # issue 25: against each flight's own nominal, two payload flights that are not in a row back nothing;
    # the weakening motor (found on consecutive flights with agreeing values) still raises its alarm
    own = [dict(r, params_is_vehicle_twin=False) for r in rows]
    kinds = {(a.vehicle_id, a.kind) for a in alarms(own)}
    assert kinds == {("uuid-00", "threshold")}


def test_new_effect_alarm_needs_repeat():
    rows = [{"path": f"/f{k}.ulg", "status": "ok", "vehicle_id": "v", "flight_time_utc": DAY.format(k + 1),
             "nominal_mass_kg": 1.0,
             "effects_json": json.dumps([{"name": "battery_sag", "verdict": "confirmed",
                                          "params": {"r": 0.02}}] if k >= 2 else [])} for k in range(4)]
    al = alarms(rows)
    assert [(a.kind, a.flight) for a in al] == [("new_effect", "f2.ulg")]
    rows[3]["effects_json"] = "[]"
    assert alarms(rows) == [] and len(trends(rows)) == 1


def test_trend_of_a_term_whose_parameters_differ_between_flights():
    """A stage-9 term keeps other terms on other flights (the real fleet: c_climb on one, c_mu2 on another):
    each parameter's trend reads 'not found' where that flight's term has no such parameter (was a KeyError
    that stopped `fleet report`)."""
    terms = [{"c_one": 0.1, "c_climb": 0.05}, {"c_one": 0.2, "c_mu2": 0.3}, None]
    rows = [{"path": f"/f{k}.ulg", "status": "ok", "vehicle_id": "v", "flight_time_utc": DAY.format(k + 1),
             "nominal_mass_kg": 1.0,
             "effects_json": json.dumps([{"name": "state_term", "verdict": "confirmed", "params": tp}] if tp else [])}
            for k, tp in enumerate(terms)]
    tr = {t.param: t for t in trends(rows)}
    assert set(tr) == {"c_one", "c_climb", "c_mu2"}
    assert tr["c_climb"].verdicts == ["confirmed", "not found", "not found"] and tr["c_climb"].values[0] == 0.05
    assert tr["c_mu2"].verdicts == ["not found", "confirmed", "not found"] and tr["c_mu2"].values[1] == 0.3
    assert tr["c_one"].values[:2] == [0.1, 0.2]
    alarms(rows)


# --- the runner, with a cheap task in place of discovery (pickled by value to the workers) ----

def fake_task(path, catalog, mode, params, params_map, closed_loop_metrics):
    """Stands in for process_flight: the flight file is JSON {vehicle, day, eff, sleep, die_once}."""
    spec = json.loads(Path(path).read_text())
    time.sleep(spec.get("sleep", 0))
    marker = Path(catalog) / f"died-{Path(path).stem}"
    if spec.get("die_once") and not marker.exists():
        marker.write_text("x")
        os._exit(1)  # the worker process dies mid-task
    if spec.get("fail"):
        row = {**cat.file_key(path), "status": "failed", "error": f"{path}: <header>: expected a ULog",
               "vehicle_id": "", "flight_time_utc": ""}
    else:
        eff = [{"name": "motor_efficiency", "verdict": "confirmed", "params": {"motor": 3, "efficiency": spec["eff"]}}]
        row = _row(Path(path), spec["vehicle"], spec["day"], eff if spec["eff"] < 1 else [])
    cat.write_row(catalog, row)
    return {"path": row["path"], "status": row["status"], "error": row["error"]}


def _fake_fleet(d: Path, n=6, extra=None) -> list[Path]:
    d.mkdir(parents=True, exist_ok=True)
    out = []
    for k in range(n):
        f = d / f"f{k:02d}.ulg"
        spec = {"vehicle": f"v{k % 2}", "day": k, "eff": round(1 - 0.05 * k, 2), "sleep": 0.2}
        spec.update((extra or {}).get(k, {}))
        f.write_text(json.dumps(spec))
        out.append(f)
    return out


@pytest.fixture()
def by_value():
    import cloudpickle
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield
    cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


def test_run_fleet_resumes_and_records_failures(tmp_path, by_value):
    flights = _fake_fleet(tmp_path / "logs", 6, {2: {"fail": True}})
    res = run_fleet(flights, tmp_path / "cat", workers=2, task=fake_task, progress=False)
    assert len(res["done"]) == 6 and res["skipped"] == 0 and not res["lost"]
    assert [d["status"] for d in res["done"]].count("failed") == 1
    rows = cat.load(tmp_path / "cat")
    assert len(rows) == 6 and {r["status"] for r in rows} == {"ok", "failed"}
    assert next(r for r in rows if r["status"] == "failed")["error"].endswith("expected a ULog")
    again = run_fleet(flights, tmp_path / "cat", workers=2, task=fake_task, progress=False)
    # the ok flights are skipped; the failed one is retried (and fails again)
    assert again["skipped"] == 5 and not again["lost"] and not again["duplicates"]
    assert [(Path(d["path"]).name, d["status"]) for d in again["done"]] == [("f02.ulg", "failed")]


def test_killed_worker_loses_no_flight(tmp_path, by_value):
    flights = _fake_fleet(tmp_path / "logs", 6, {1: {"die_once": True, "sleep": 0.5}})
    res = run_fleet(flights, tmp_path / "cat", workers=2, task=fake_task, progress=False, retries=0)
    lost = {d["path"] for d in res["lost"]}
    assert lost <= {str(flights[1].resolve())}
    rerun = run_fleet(flights, tmp_path / "cat", workers=2, task=fake_task, progress=False)
    assert rerun["skipped"] == 6 - len(lost) and not rerun["lost"]
    assert len(cat.load(tmp_path / "cat")) == 6


def test_bad_logs_are_failed_rows_with_one_line_errors(tmp_path):
    d = tmp_path / "logs"
    d.mkdir()
    (d / "bad.ulg").write_bytes(b"not a ulog at all")
    res = run_fleet([d / "bad.ulg"], tmp_path / "cat", workers=1, progress=False,
                    params=str(ROOT / "params/px4_sih_quadx.yaml"))
    [row] = cat.load(tmp_path / "cat")
    assert row["status"] == "failed" and "\n" not in row["error"] and "bad.ulg" in row["error"]
    assert res["done"][0]["status"] == "failed"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_external_scheduler_and_worker(tmp_path):
    """The same run through separately started ``dask scheduler`` + ``dask worker`` (loopback)."""
    port = _free_port()
    dask = str(Path(sys.executable).parent / "dask")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests")])}  # fake_task by name
    sched = subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                              "--dashboard-address", ":0"], env=env, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    worker = None
    try:
        time.sleep(3)
        worker = subprocess.Popen([dask, "worker", f"tcp://127.0.0.1:{port}", "--nworkers", "2", "--nthreads", "1",
                                   "--host", "127.0.0.1", "--no-dashboard"], env=env, stdout=subprocess.DEVNULL, cwd=tmp_path,
                                  stderr=open(tmp_path / "worker.log", "w"))
        from dask.distributed import Client
        with Client(f"tcp://127.0.0.1:{port}", timeout="60s") as c:
            c.wait_for_workers(2, timeout=120)
        flights = _fake_fleet(tmp_path / "logs", 6)
        res = run_fleet(flights, tmp_path / "cat", scheduler=f"tcp://127.0.0.1:{port}", task=fake_task,
                        progress=False)
        assert len(res["done"]) == 6 and all(d["status"] == "ok" for d in res["done"]), res["lost"][:1]
        assert len(cat.load(tmp_path / "cat")) == 6
    finally:
        for p in (worker, sched):
            if p is not None:
                p.terminate()
                p.wait(20)


@pytest.mark.slow
def test_simulated_fleet_end_to_end(tmp_path):
    """3 vehicles x 4 real simulated flights, discovered on Dask (several minutes per flight on a
    loaded 2-core machine): the degrading motor and the payload flights are named, the healthy
    vehicle is clean."""
    from twin_nodes.fleet.simfleet import plan, write_fleet

    params = ROOT / "params/px4_sih_quadx.yaml"
    fl = plan(3, 4, eff_end=0.8, payload_every=2)
    write_fleet(tmp_path / "logs", fl, params, workers=2)
    res = run_fleet(sorted((tmp_path / "logs").glob("*.ulg")), tmp_path / "cat", workers=2, params=str(params),
                    closed_loop_metrics=False, progress=False)
    assert all(d["status"] == "ok" for d in res["done"]), res
    s = write_report(tmp_path / "cat", tmp_path / "rep")
    kinds = {(a["vehicle_id"], a["kind"]) for a in s["alarms"]}
    assert (fl[0].uuid, "threshold") in kinds and (fl[4].uuid, "payload") in kinds
    assert not [a for a in s["alarms"] if a["vehicle_id"] == fl[8].uuid]
