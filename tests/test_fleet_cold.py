"""A cold ``fleet discover`` does each piece of work once (docs/fleet.md, Throughput (twelfth session)).

- one flight's nominal is built once, for its facts and for the params it flies (``nominal.nominal_once``),
  with the same values and the same params file as the two builds before;
- a worker compiles the numba code of a free flight's discovery ahead (``flight.warm_compiled``,
  ``kernels.warm_steps``), once per process, each entry point under its own lock in the code cache folder the
  workers share: another process compiles the entry points nobody holds, waits for the others, then loads
  that code (no compile); a log that is no free flight compiles nothing;
- the flights go to the workers largest file first (``run.longest_first``, the tasks' priorities).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import missing_shared

from twin_nodes.base.errors import TwinError
from twin_nodes.fleet import flight as fleet_flight
from twin_nodes.fleet import run as fleet_run
from twin_nodes.fleet.facts import flight_facts
from twin_nodes.fleet.flight import resolve_params
from twin_nodes.identify import nominal
from twin_nodes.logs.ulog_io import read_ulog

ROOT = Path(__file__).resolve().parents[1]
FLEET = ROOT.parent / "shared" / "flightlogs" / "fleet_quadx_v6c"


def _free_flight() -> Path:
    if not FLEET.is_dir():
        missing_shared("flightlogs/fleet_quadx_v6c")  # skips locally, fails under CI=true
    p = FLEET / "ZweiterFlugtag" / "log_19_2023-6-7-10-51-18.ulg"  # a short free flight (~40 s)
    assert p.is_file()
    return p


def test_nominal_built_once_for_facts_and_params(tmp_path, monkeypatch):
    path = _free_flight()
    calls = []
    real = nominal.nominal_from_log

    def counted(log, **kw):
        calls.append(log)
        return real(log, **kw)

    monkeypatch.setattr(nominal, "nominal_from_log", counted)
    log = read_ulog(path)
    # before: the facts and the params each built the nominal
    monkeypatch.setenv("ROTORTWIN_CACHE", str(tmp_path / "a"))
    facts_a = flight_facts(str(path), log)
    pfile_a, note_a = resolve_params(path, "v", None, None, log=log)
    assert len(calls) == 2
    # now: one build, shared
    monkeypatch.setenv("ROTORTWIN_CACHE", str(tmp_path / "b"))
    build = nominal.nominal_once(log)
    facts_b = flight_facts(str(path), log, None, build)
    pfile_b, note_b = resolve_params(path, "v", None, None, log=log, build=build)
    assert len(calls) == 3
    assert facts_b["flight_kind"] == "free flight" and "fact_kt_per_mass" in facts_b
    assert json.dumps(facts_a, sort_keys=True) == json.dumps(facts_b, sort_keys=True)
    assert pfile_a.name == pfile_b.name and pfile_a != pfile_b
    assert pfile_a.read_text() == pfile_b.read_text()
    assert note_a.replace(str(tmp_path / "a"), "") == note_b.replace(str(tmp_path / "b"), "")


def test_nominal_once_raises_the_same_error_without_building_again(monkeypatch):
    calls = []

    def failing(log, **kw):
        calls.append(log)
        raise TwinError("x.ulg: actuator_motors: cannot lift the assumed mass")

    monkeypatch.setattr(nominal, "nominal_from_log", failing)
    build = nominal.nominal_once(object())
    msgs = []
    for _ in range(3):
        with pytest.raises(TwinError) as e:
            build()
        msgs.append(str(e.value))
    assert calls and len(calls) == 1
    assert msgs == ["x.ulg: actuator_motors: cannot lift the assumed mass"] * 3


def test_longest_first_orders_by_size_stably():
    todo = [{"path": "a", "file_size": 10}, {"path": "b", "file_size": 300}, {"path": "c", "file_size": 10},
            {"path": "d", "file_size": 20}]
    assert [k["path"] for k in fleet_run.longest_first(todo)] == ["b", "d", "a", "c"]


class _Stop(Exception):
    pass


def test_tasks_get_priorities_largest_file_first(monkeypatch, tmp_path):
    prio = {}

    class FakeClient:
        def submit(self, fn, path, *a, priority=0, **k):
            prio[Path(path).name] = priority
            raise _Stop

    monkeypatch.setattr(fleet_run, "_client", lambda *a, **k: (FakeClient(), None))
    monkeypatch.setattr(FakeClient, "close", lambda self: None, raising=False)
    flights = []
    for i, n in enumerate((5, 50, 20)):
        f = tmp_path / f"f{i}.ulg"
        f.write_bytes(bytes([i]) * n)
        flights.append(f)
    with pytest.raises(_Stop):
        fleet_run.run_fleet(flights, tmp_path / "cat", workers=1)
    assert prio == {"f1.ulg": 3}  # the largest is submitted first, with the highest priority


_PROBE = """
import json, sys
from numba.core import event
compiled = []
class L(event.Listener):
    def on_start(self, e):
        pass
    def on_end(self, e):
        d = e.data["dispatcher"]
        compiled.append(d.py_func.__module__ + "." + d.py_func.__name__)
event.register("numba:compile", L())
from twin_nodes.fleet.flight import warm_compiled
warm_compiled()
warm_compiled()  # once per process
print(json.dumps({"compiled": sorted(c for c in compiled if c.startswith("rotortwin_"))}))
"""


@pytest.mark.slow
def test_code_compiled_ahead_is_loaded_not_compiled_by_another_process(tmp_path):
    env = {**os.environ, "ROTORTWIN_CACHE": str(tmp_path / "data"), "ROTORTWIN_CODE_CACHE": str(tmp_path / "cache"),
           "PYTHONPATH": str(ROOT)}

    def probe():
        r = subprocess.run([sys.executable, "-c", _PROBE], env=env, cwd=ROOT, capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout.strip().splitlines()[-1])

    first = probe()  # the first cold worker: compiles the stepper's and the kernels' entry points, once
    names = [c.rsplit(".", 1)[1] for c in first["compiled"]]
    assert {"step_n", "specific_force", "wrench_terms", "lag_states", "step_windows"} <= set(names)
    assert len(names) == len(set(names)) + 1  # each once; the stepper's reference() twice (read-only command)
    assert list((tmp_path / "cache").glob("__pycache__/rotortwin_disc_*.step_windows-*.nbi"))
    assert {p.name for p in (tmp_path / "cache").glob("compile.*.lock")} == {
        f"compile.{n}.lock" for n in ("step_n", "specific_force", "wrench_terms", "lag_states", "step_windows")}
    second = probe()  # a worker after it, sharing the cache folder: loads, compiles nothing
    assert second == {"compiled": []}


def test_warm_compiled_holds_the_lock_while_it_compiles(tmp_path, monkeypatch):
    import fcntl

    from twin_nodes.discovery import kernels

    monkeypatch.setenv("ROTORTWIN_CODE_CACHE", str(tmp_path))  # the locks live in the code cache
    monkeypatch.setattr(fleet_flight, "_WARM", [])
    calls = []

    def held_elsewhere(name):  # another open file: another process's view of that entry point's lock
        with open(tmp_path / f"compile.{name}.lock", "a") as other:
            try:
                fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            return False

    def step(name):
        def run():
            calls.append((name, held_elsewhere(name)))
            if name == "c":  # the other worker finishes "b" meanwhile
                other_b.close()
        return run

    other_b = open(tmp_path / "compile.b.lock", "a")  # "another worker" compiles "b" now
    fcntl.flock(other_b, fcntl.LOCK_EX)
    monkeypatch.setattr(kernels, "warm_steps", lambda: [(n, step(n)) for n in "abc"])
    fleet_flight.warm_compiled()
    fleet_flight.warm_compiled()  # once per process
    # each once, under its own lock; "b", held by the other worker, is left for after "c", then loaded
    assert calls == [("a", True), ("c", True), ("b", True)]
    for n in "abc":  # released after it
        assert not held_elsewhere(n)


def _warm_in_thread(tmp_path, monkeypatch, hold: str):
    """warm_compiled over entry points a, b, c in a thread while "another worker" holds ``hold``'s lock."""
    import fcntl
    import threading

    from twin_nodes.discovery import kernels

    monkeypatch.setenv("ROTORTWIN_CODE_CACHE", str(tmp_path))  # the locks live in the code cache
    monkeypatch.setattr(fleet_flight, "_WARM", [])
    other = open(tmp_path / f"compile.{hold}.lock", "a")
    fcntl.flock(other, fcntl.LOCK_EX)
    calls: list[str] = []
    monkeypatch.setattr(kernels, "warm_steps", lambda: [(n, lambda n=n: calls.append(n)) for n in "abc"])
    done = threading.Event()
    t = threading.Thread(target=lambda: (fleet_flight.warm_compiled(), done.set()))
    t.start()
    return other, calls, done, t


def test_warm_compiled_waits_for_an_entry_point_another_worker_compiles(tmp_path, monkeypatch):
    other, calls, done, t = _warm_in_thread(tmp_path, monkeypatch, "b")
    assert not done.wait(0.5)  # "a" and "c" done, "b" waited for: the other worker still holds it
    assert calls == ["a", "c"]
    other.close()
    t.join(10)
    assert done.is_set() and calls == ["a", "c", "b"]  # then loaded, once


def test_warm_compiled_waits_for_the_first_entry_point_before_any_other(tmp_path, monkeypatch):
    other, calls, done, t = _warm_in_thread(tmp_path, monkeypatch, "a")
    assert not done.wait(0.5)  # the first (the stepper's step: it compiles what the others call) comes first
    assert calls == []
    other.close()
    t.join(10)
    assert done.is_set() and calls == ["a", "b", "c"]


def test_warm_steps_are_the_entry_points_discovery_calls():
    from twin_nodes.discovery import kernels

    names = [n for n, _ in kernels.warm_steps()]
    assert names == ["step_n", "wrench_terms", "step_windows", "lag_states", "specific_force"]


def test_no_compile_for_a_log_that_is_no_free_flight(monkeypatch):
    if not FLEET.is_dir():
        missing_shared("flightlogs/fleet_quadx_v6c")
    calls = []
    monkeypatch.setattr(fleet_flight, "warm_compiled", lambda: calls.append(1))
    ground = FLEET / "23_juni" / "log_11_2023-6-23-10-13-50.ulg"  # a bench test with actuator-test commands
    with pytest.raises(fleet_flight.NotAFlight):
        fleet_flight.analyse(str(ground), "discover", None, None, True)
    assert calls == []
