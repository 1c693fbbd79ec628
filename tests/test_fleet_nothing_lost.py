"""Issue 28, fleet and survey part: nothing lost, whatever the input.

Failed rows keep vehicle id, date, path and a one-line reason; a rerun retries failed flights and
exits 1 while any still fail; identical content counts once and the duplicate is named; a corrupt
row file does not break the catalog; the embedded cluster listens on loopback only, without a
dashboard; ``workers < 1`` is refused; ``survey`` gives every flight a row."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("dask.distributed")
pytest.importorskip("duckdb")

from conftest import shared_log  # noqa: E402

from twin_nodes.base.errors import TwinError  # noqa: E402
from twin_nodes.cli import main  # noqa: E402
from twin_nodes.fleet import catalog as cat  # noqa: E402
from twin_nodes.fleet.flight import process_flight  # noqa: E402
from twin_nodes.fleet.report import write_report  # noqa: E402
from twin_nodes.fleet.run import find_flights, run_fleet  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PARAMS = str(ROOT / "params/px4_sih_quadx.yaml")
V6C = "fleet_quadx_v6c/DritterFlugtag"
#: 11 s on the ground (MANIFEST: airborne 0.0 s), sys_uuid of the fleet's one vehicle, 21 Jun 2023
LOG61 = "log_61_2023-6-21-08-32-12.ulg"
UUID = "000600000000393334373131511800430028"


# --- 1. a failed row keeps vehicle id, date, path and a one-line reason ------------------------

def test_failed_real_flight_keeps_vehicle_and_date(tmp_path):
    log = shared_log(V6C, LOG61)
    s = process_flight(str(log), str(tmp_path / "cat"), params=PARAMS, closed_loop_metrics=False)
    [row] = cat.load(tmp_path / "cat")
    # never airborne: recognised as a ground/bench test (issue 25), a row with its kind and reason, not a failure
    assert s["status"] == row["status"] == "not_flight" and row["flight_kind"] == "ground/bench test"
    assert row["vehicle_id"] == UUID and row["vehicle_id_source"] == "sys_uuid"
    # no time_ref_utc, no GPS fix: the date and time of the file name (QGC's download name, local time)
    assert row["flight_time_utc"] == "2023-06-21T08:32:12" and row["date_source"] == "file_name"
    assert row["path"] == str(log.resolve())
    assert "\n" not in row["error"] and LOG61 in row["error"] and "airborne" in row["error"]


def test_failed_row_other_exception_keeps_identity_one_line(tmp_path, monkeypatch):
    log = shared_log(V6C, LOG61)
    import twin_nodes.logs.ulog_io as uio

    def boom(*a, **k):
        raise RuntimeError("first line\nsecond line")

    import twin_nodes.logs.flyable as fly

    monkeypatch.setattr(uio, "read_ulog", boom)
    monkeypatch.setattr(fly, "read_ulog", boom)  # the fleet loads through flyable.read_flight
    process_flight(str(log), str(tmp_path / "cat"), params=PARAMS, closed_loop_metrics=False)
    [row] = cat.load(tmp_path / "cat")
    assert row["vehicle_id"] == UUID and row["flight_time_utc"].startswith("2023-06-21")
    assert row["error"] == f"{log}: RuntimeError: first line"


def test_unreadable_header_still_has_vehicle_and_date(tmp_path):
    d = tmp_path / "quad-07"
    d.mkdir()
    f = d / "bad.ulg"
    f.write_bytes(b"not a ulog at all")
    os.utime(f, (1_780_000_000, 1_780_000_000))  # 2026-05-28T...
    process_flight(str(f), str(tmp_path / "cat"), params=PARAMS)
    [row] = cat.load(tmp_path / "cat")
    assert row["status"] == "failed" and "<header>" in row["error"] and "\n" not in row["error"]
    assert row["vehicle_id"] == "folder:quad-07" and row["vehicle_id_source"] == "folder"
    assert row["flight_time_utc"].startswith("2026-05-28") and row["date_source"] == "file_mtime"


# --- 2. the runner: failed rows retried, duplicates counted once ------------------------------

def task_ok_or_fail(path, catalog, mode, params, params_map, closed_loop_metrics):
    """Stand-in for process_flight: the file is JSON {vehicle, fail}; a failure is read from a
    marker file so a test can 'repair' a flight between runs."""
    spec = json.loads(Path(path).read_text())
    fail = (Path(catalog).parent / f"fail-{spec['name']}").exists()
    row = {**cat.file_key(path), "mode": mode, "status": "failed" if fail else "ok",
           "error": f"{path}: <log>: expected a flight" if fail else "", "vehicle_id": spec["vehicle"],
           "flight_time_utc": "2026-06-01T09:00:00+00:00", "effects_json": "[]"}
    cat.write_row(catalog, row)
    return {"path": row["path"], "status": row["status"], "error": row["error"]}


@pytest.fixture()
def by_value():
    import cloudpickle
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield
    cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


def _files(d: Path, n: int) -> list[Path]:
    d.mkdir(parents=True, exist_ok=True)
    out = []
    for k in range(n):
        f = d / f"f{k}.ulg"
        f.write_text(json.dumps({"name": f"f{k}", "vehicle": f"v{k % 2}"}))
        out.append(f)
    return out


def test_rerun_retries_failed_rows(tmp_path, by_value):
    flights = _files(tmp_path / "logs", 4)
    (tmp_path / "fail-f1").write_text("")
    (tmp_path / "fail-f3").write_text("")
    res = run_fleet(flights, tmp_path / "cat", workers=1, task=task_ok_or_fail, progress=False)
    assert sorted(d["status"] for d in res["done"]) == ["failed", "failed", "ok", "ok"]
    again = run_fleet(flights, tmp_path / "cat", workers=1, task=task_ok_or_fail, progress=False)
    assert again["skipped"] == 2  # the two ok flights only
    assert sorted(Path(d["path"]).name for d in again["done"]) == ["f1.ulg", "f3.ulg"]
    (tmp_path / "fail-f1").unlink()  # f1 repaired: the third run does it, f3 still fails
    third = run_fleet(flights, tmp_path / "cat", workers=1, task=task_ok_or_fail, progress=False)
    assert {Path(d["path"]).name: d["status"] for d in third["done"]} == {"f1.ulg": "ok", "f3.ulg": "failed"}
    rows = {Path(r["path"]).name: r["status"] for r in cat.load(tmp_path / "cat")}
    assert rows == {"f0.ulg": "ok", "f1.ulg": "ok", "f2.ulg": "ok", "f3.ulg": "failed"}


def test_identical_content_counts_once_and_is_named(tmp_path, by_value):
    flights = _files(tmp_path / "logs", 3)
    copy = tmp_path / "logs" / "sub" / "renamed.ulg"
    copy.parent.mkdir()
    shutil.copyfile(flights[1], copy)
    link = tmp_path / "logs" / "hardlink.ulg"
    os.link(flights[2], link)
    (tmp_path / "logs" / "symlink.ulg").symlink_to(flights[0])
    inputs = find_flights([str(tmp_path / "logs"), str(flights[0])])  # f0 twice by name: once
    assert len(inputs) == 6
    res = run_fleet(inputs, tmp_path / "cat", workers=1, task=task_ok_or_fail, progress=False)
    assert len(res["done"]) == 3 and len(cat.load(tmp_path / "cat")) == 3
    dups = {Path(d["path"]).name: Path(d["same_as"]).name for d in res["duplicates"]}
    assert dups == {"renamed.ulg": "f1.ulg", "hardlink.ulg": "f2.ulg", "symlink.ulg": "f0.ulg"}
    # the copy alone, later: already in the catalog under the other name -> named, not redone
    alone = run_fleet([copy], tmp_path / "cat", workers=1, task=task_ok_or_fail, progress=False)
    assert alone["done"] == [] and [Path(d["same_as"]).name for d in alone["duplicates"]] == ["f1.ulg"]
    assert len(cat.load(tmp_path / "cat")) == 3


def test_report_counts_identical_content_once(tmp_path):
    a = tmp_path / "a.ulg"
    a.write_bytes(b"same bytes")
    b = tmp_path / "b.ulg"
    b.write_bytes(b"same bytes")
    for f in (a, b):
        cat.write_row(tmp_path / "cat", {**cat.file_key(f), "status": "ok", "error": "", "vehicle_id": "v",
                                         "flight_time_utc": "2026-06-01T09:00:00+00:00", "effects_json": "[]"})
    s = write_report(tmp_path / "cat", tmp_path / "rep")
    assert s["flights"] == 1 and s["vehicles"]["v"]["flights"] == 1
    assert [(Path(d["path"]).name, Path(d["same_as"]).name) for d in s["duplicates"]] == [("b.ulg", "a.ulg")]
    assert "b.ulg" in (tmp_path / "rep" / "index.html").read_text()


# --- 3. a corrupt row file ---------------------------------------------------------------------

def _catalog_with_corrupt(tmp_path: Path) -> tuple[Path, Path, Path]:
    c = tmp_path / "cat"
    for k in range(3):
        f = tmp_path / f"g{k}.ulg"
        f.write_bytes(b"g" * (k + 1))
        cat.write_row(c, {**cat.file_key(f), "status": "ok", "error": "", "vehicle_id": "v",
                          "flight_time_utc": f"2026-06-0{k + 1}T09:00:00+00:00", "effects_json": "[]"})
    garbage = c / "garbage.parquet"
    garbage.write_bytes(b"PAR1 this is not parquet")
    truncated = sorted(c.glob("g2-*.parquet"))[0]
    truncated.write_bytes(truncated.read_bytes()[:40])
    return c, garbage, truncated


def test_corrupt_row_file_is_skipped_with_a_warning(tmp_path, caplog):
    c, garbage, truncated = _catalog_with_corrupt(tmp_path)
    with caplog.at_level(logging.WARNING, logger="rotortwin"):
        cols, rows = cat.query(c, "SELECT count(*) FROM flights")
    assert rows == [(2,)]  # g0, g1; g2's file is truncated
    msgs = [r.getMessage() for r in caplog.records]
    assert any(str(garbage) in m for m in msgs) and any(str(truncated) in m for m in msgs)
    assert all("\n" not in m for m in msgs)
    s = write_report(c, tmp_path / "rep")
    assert s["flights"] == 2
    assert sorted(Path(x["file"]).name for x in s["corrupt_files"]) == sorted([garbage.name, truncated.name])
    assert garbage.name in (tmp_path / "rep" / "index.html").read_text()


def test_cli_query_and_report_survive_a_corrupt_file(tmp_path, capsys):
    c, garbage, _ = _catalog_with_corrupt(tmp_path)
    assert main(["fleet", "query", str(c), "SELECT count(*) AS n FROM flights"]) == 0
    out, err = capsys.readouterr()
    assert out.splitlines() == ["n", "2"]
    assert f"rotortwin: warning: {garbage}" in err
    assert main(["fleet", "report", str(c), "--out", str(tmp_path / "rep")]) == 0
    out, err = capsys.readouterr()
    assert "2 flights" in out and "2 corrupt" in out and f"CORRUPT {garbage}" in out


# --- 4. loopback only, no dashboard; workers >= 1 ---------------------------------------------

def _listening() -> set[tuple[int, str, int]]:
    import psutil

    me = psutil.Process()
    out = set()
    for p in [me] + me.children(recursive=True):
        try:
            for s in p.net_connections(kind="inet"):
                if s.status == psutil.CONN_LISTEN:
                    out.add((p.pid, s.laddr.ip, s.laddr.port))
        except psutil.Error:
            pass
    return out


def test_embedded_cluster_listens_on_loopback_only_without_dashboard():
    from twin_nodes.fleet.run import _client

    before = _listening()
    client, cluster = _client(None, 1)
    try:
        client.wait_for_workers(1, timeout=60)
        new = _listening() - before
        assert new and all(ip in ("127.0.0.1", "::1") for _, ip, _ in new), new
        http = cluster.scheduler_info["services"]["dashboard"]  # the scheduler's HTTP server (health, metrics)
        assert http != 8787  # a free port, so two runs never fight over it
        import urllib.error
        import urllib.request
        with urllib.request.urlopen(f"http://127.0.0.1:{http}/health", timeout=10) as r:
            assert r.status == 200
        with pytest.raises(urllib.error.HTTPError, match="404"):  # no dashboard pages
            urllib.request.urlopen(f"http://127.0.0.1:{http}/status", timeout=10)
        assert all(w["host"] == "127.0.0.1" for w in cluster.scheduler_info["workers"].values())
    finally:
        client.close()
        cluster.close()


def test_workers_below_one_refused_not_hanging(tmp_path):
    f = tmp_path / "a.ulg"
    f.write_bytes(b"x")
    code = ("import sys; from twin_nodes.fleet.run import run_fleet\n"
            "for w in (0, -3):\n"
            "    try:\n"
            f"        run_fleet([{str(f)!r}], {str(tmp_path / 'cat')!r}, workers=w, progress=False)\n"
            "    except Exception as e:\n"
            "        print(type(e).__name__, e)\n")
    t0 = time.time()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    lines = r.stdout.splitlines()
    assert lines == ["TwinError --workers: 0: expected an integer >= 1 (worker processes)",
                     "TwinError --workers: -3: expected an integer >= 1 (worker processes)"], r.stderr[-500:]
    assert time.time() - t0 < 120
    with pytest.raises(TwinError, match="--workers"):
        run_fleet([f], tmp_path / "cat", workers=0, progress=False)


# --- 5. the CLI: failed flights counted and listed, on every run ------------------------------

def test_cli_discover_counts_failed_on_rerun_and_report_lists_them(tmp_path, capsys):
    log = shared_log(V6C, LOG61)
    bad = tmp_path / "quad-07" / "bad.ulg"
    bad.parent.mkdir()
    bad.write_bytes(b"not a ulog at all")
    argv = ["fleet", "discover", str(log), str(bad), "--catalog", str(tmp_path / "cat"), "--workers", "1",
            "--params", PARAMS, "--no-closed-loop"]
    # the log that never flew is recognised (a ground/bench test: a row, done); the unreadable file fails,
    # and the rerun retries it alone and still exits 1
    for k in range(2):
        assert main(argv) == 1
        out, err = capsys.readouterr()
        if k == 0:
            assert "2 flights: 0 done, 1 no free flight (ground/bench test 1), 1 failed" in out, out
            assert f"not a flight (ground/bench test): {log.resolve()}: " in out and "airborne" in out
        else:
            assert "2 flights: 0 done, 0 no free flight (none), 1 failed" in out and "1 already in" in out, out
        assert f"{bad}: <header>" in err
        assert "rotortwin: 1 flight(s) still failed" in err
    assert main(["fleet", "report", str(tmp_path / "cat"), "--out", str(tmp_path / "rep")]) == 0
    out, _ = capsys.readouterr()
    assert "2 flights, 2 vehicles, 1 no free flight, 1 failed" in out
    assert f"NO FREE FLIGHT {log.resolve()} [{UUID}, 2023-06-21] (ground/bench test):" in out
    assert f"FAILED {bad}" in out
    s = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert s["vehicles"][UUID]["not_flight"] == 1 and s["vehicles"]["folder:quad-07"]["failed"] == 1
    html = (tmp_path / "rep" / "index.html").read_text()
    assert "airborne" in html and UUID in html


# --- 6. survey: every flight gets a row --------------------------------------------------------

def test_survey_every_flight_gets_a_row(tmp_path, monkeypatch):
    from twin_nodes.discovery import survey

    log = shared_log(V6C, LOG61)
    bad = tmp_path / "bad.ulg"
    bad.write_bytes(b"not a ulog at all")
    other = tmp_path / "other.ulg"
    other.write_bytes(b"also not a ulog")
    real = survey.survey_flight

    def flaky(path, params=None):
        if Path(path).name == "other.ulg":
            raise ValueError("need more samples\nthan coefficients")
        return real(path, params)

    monkeypatch.setattr(survey, "survey_flight", flaky)
    rows = survey.survey_rows([log, bad, other], PARAMS)
    # a flight with no flight in it (log_61: never airborne) is left out, with its reason, not failed
    assert [(r["flight"], r["status"]) for r in rows] == [(log.stem, "left_out"), ("bad", "failed"),
                                                          ("other", "failed")]
    assert "airborne" in rows[0]["error"] and str(bad) in rows[1]["error"] and "ULog" in rows[1]["error"]
    assert rows[2]["error"] == f"{other}: ValueError: need more samples"
    md = survey.markdown_table(rows)
    assert f"| {log.stem} | left out: " in md and "never airborne" in md
    for r in rows[1:]:
        assert f"| {r['flight']} | failed: " in md
    assert all("\n" not in r["error"] for r in rows)
    assert "1 left out (no flight to fit, or no motor outputs), 2 failed" in md


def test_survey_cli_markdown_lists_failed_flights(tmp_path, capsys):
    log = shared_log(V6C, LOG61)
    bad = tmp_path / "bad.ulg"
    bad.write_bytes(b"not a ulog at all")
    md = tmp_path / "t.md"
    assert main(["survey", str(log), str(bad), "--params", PARAMS, "--md", str(md)]) == 1
    text = md.read_text()
    assert f"| {log.stem} | left out: " in text and "| bad | failed: " in text
    _, err = capsys.readouterr()
    assert "1 of 2 flights failed" in err and "rotortwin: left out: " in err
    # only left-out flights: no failure, exit 0
    assert main(["survey", str(log), "--params", PARAMS]) == 0


def test_file_date_from_name_then_mtime(tmp_path):
    from twin_nodes.fleet.identity import file_date

    assert file_date("/x/log_61_2023-6-21-08-32-12.ulg") == ("2023-06-21T08:32:12", "file_name")
    assert file_date("/x/2026-06-01/09_30_05.ulg") == ("2026-06-01T09:30:05", "file_name")
    f = tmp_path / "log_1_2023-13-40-1-1-1.ulg"  # not a date: the mtime
    f.write_bytes(b"")
    os.utime(f, (1_780_000_000, 1_780_000_000))
    assert file_date(f) == ("2026-05-28T20:26:40+00:00", "file_mtime")
    assert file_date(tmp_path / "missing.ulg") == ("", "")


def test_simulated_fleet_refuses_workers_below_one(tmp_path):
    from twin_nodes.fleet.simfleet import plan, write_fleet

    for w in (0, -1):
        with pytest.raises(TwinError, match=f"--workers: {w}: expected an integer >= 1"):
            write_fleet(tmp_path, plan(1, 1), PARAMS, workers=w)
    assert not list(tmp_path.iterdir())


def test_a_flight_with_too_little_usable_airborne_data_is_left_out_not_failed(tmp_path, monkeypatch):
    """Discovery's own refusal of a flight with under 5 s of airborne data once ground contact is taken out (the
    fleet's log_22 and Luca_uebt_Fliegen) is a flight left out with its reason, as a bench test is."""
    from twin_nodes.base.errors import LogError
    from twin_nodes.discovery import survey

    hop = tmp_path / "hop.ulg"
    hop.write_bytes(b"")

    def refuse(path, params=None):
        raise LogError(str(path), "airborne samples", "expected at least 5 s of usable airborne data")

    monkeypatch.setattr(survey, "survey_flight", refuse)
    rows = survey.survey_rows([hop], PARAMS)
    assert rows[0]["status"] == "left_out" and "usable airborne data" in rows[0]["error"]
    assert "1 left out (no flight to fit, or no motor outputs), 0 failed" in survey.markdown_table(rows)
