"""The node graph under the failures of issue 12 and issue 14 (item 3), each as a user meets it:
a log without a subscribed topic, `kill -9` of the CLI, two runs on one ROS domain, message times
in the MCAP, outputs in missing or read-only folders, files left by failures, a logger dropout
longer than the flow-control window.  Flights are cut from the PX4 SIH triangle log
(tests/graph_cases.py)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import shared_log

from twin_nodes.base.errors import TwinError
from twin_nodes.vehicle.params import params_dir

ROTORTWIN = [sys.executable, "-m", "twin_nodes"]
PARAMS = params_dir() / "px4_sih_quadx.yaml"


def _cli(*args: object, timeout: float = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(ROTORTWIN + [str(a) for a in args], capture_output=True, text=True, timeout=timeout,
                          env=env)


def _one_line_error(r: subprocess.CompletedProcess, *words: str) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("rotortwin: error:"), r.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    from graph_cases import cut_ulog, short_flight

    d = tmp_path_factory.mktemp("flights")
    src = shared_log("sitl", "px4sih_default_triangle.ulg")
    return {"short": short_flight(d),
            "no_motors": cut_ulog(src, d / "no_motors.ulg", t1_s=30.0, drop=("actuator_motors", "actuator_outputs")),
            "dropout": cut_ulog(src, d / "dropout.ulg", t1_s=30.0, gap=(15.0, 18.0))}


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(") ", 1)[1][0] not in "ZX"  # a zombie has exited
    except (FileNotFoundError, ProcessLookupError):
        return False


# ============================================================================ no ROS needed


@pytest.mark.parametrize("domain", ["-1", "233", "500"])
def test_domain_id_out_of_range_is_refused(flights, domain):
    r = _cli("compare", flights["short"], "--params", PARAMS, "--domain-id", domain, "--quiet", timeout=120)
    _one_line_error(r, "--domain-id", "[0, 232]", domain)


def test_domain_leased_by_another_run_is_refused_and_skipped(flights):
    from twin_nodes.graph.domains import lease_domain, participant_port_busy

    with lease_domain() as held:
        d = held.domain_id
        r = _cli("compare", flights["short"], "--params", PARAMS, "--domain-id", d, timeout=60)
        _one_line_error(r, f"ROS domain {d} is in use by another rotortwin run", f"pid {os.getpid()}")
        # automatic choice: never a leased domain, never one with a DDS participant on it
        other = next(i for i in range(60, 100) if i != d and not participant_port_busy(i))
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("0.0.0.0", 7400 + 250 * other + 10))  # what a first DDS participant on `other` binds
        try:
            free = next(i for i in range(60, 100) if i not in (d, other) and not participant_port_busy(i))
            with lease_domain(candidates=[d, other, free]) as got:
                assert got.domain_id == free
        finally:
            s.close()
    with lease_domain(d) as again:  # released with the run (and by the kernel if it is killed)
        assert again.domain_id == d


def test_json_into_a_file_or_unwritable_folder_fails_before_running(tmp_path):
    flight = shared_log("sitl", "px4sih_default_triangle.ulg")
    t0 = time.monotonic()
    (tmp_path / "a_file").write_text("x")  # a missing folder is made; a path through a file cannot be
    r = _cli("compare", flight, "--params", PARAMS, "--json", tmp_path / "a_file" / "m.json", timeout=60)
    _one_line_error(r, "--json", "is a file")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as root: a read-only folder is writable")  # the missing folder case ran
        r = _cli("compare", flight, "--params", PARAMS, "--json", ro / "m.json", timeout=60)
        _one_line_error(r, "--json", "not writable")
    finally:
        ro.chmod(0o700)
    assert time.monotonic() - t0 < 60  # refused before the graph (or the offline twin) ran


def test_unwritable_output_folder_is_refused_even_as_root(tmp_path, monkeypatch):
    """The unwritable-folder check itself, with the permission answer forced (as root a read-only
    folder is writable, so the CLI case above can only skip there)."""
    import argparse

    from twin_nodes.base import outputs
    from twin_nodes.base.errors import TwinError

    ro = tmp_path / "ro"
    ro.mkdir()
    real_access = os.access
    monkeypatch.setattr(outputs.os, "access", lambda p, mode: False if Path(p) == ro else real_access(p, mode))
    spec = [outputs.Output("json", "--json")]
    with pytest.raises(TwinError, match=r"m\.json: --json: expected a path in a writable folder; .* is not writable"):
        outputs.check(spec, argparse.Namespace(json=str(ro / "m.json")), [])
    assert outputs.check(spec, argparse.Namespace(json=str(tmp_path / "m.json")), [])[0].final == tmp_path / "m.json"


def test_output_equal_to_input_is_refused_and_json_is_written_whole(tmp_path):
    flight = tmp_path / "f.ulg"
    flight.write_bytes(shared_log("sitl", "px4sih_default_triangle.ulg").read_bytes())
    before = flight.read_bytes()
    r = _cli("compare", flight, "--offline", "--params", PARAMS, "--json", flight, timeout=120)
    _one_line_error(r, "--json", "not an input")
    assert flight.read_bytes() == before
    out = tmp_path / "m.json"
    r = _cli("compare", flight, "--offline", "--params", PARAMS, "--json", out, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(out.read_text())["n_samples"] > 1000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.ulg", "m.json"]  # no temporary file left


@pytest.mark.parametrize("content", [b"", b"\x00" * 64, os.urandom(4096), b"\x89MCAP0\r\n" + b"\x01" * 40])
def test_record_recover_on_garbage_is_a_one_line_error(tmp_path, content):
    bag = tmp_path / "junk"
    bag.mkdir()
    (bag / "junk.mcap").write_bytes(content)
    r = _cli("record", "recover", bag, timeout=60)
    _one_line_error(r, "junk.mcap")
    assert not (tmp_path / "junk_recovered").exists()
    loose = tmp_path / "loose.bin"
    loose.write_bytes(content)
    _one_line_error(_cli("record", "recover", loose, timeout=60), "loose.bin")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk", "loose.bin"]


# ============================================================================ with the graph


@pytest.fixture(scope="module")
def ros():
    pytest.importorskip("rclpy", reason="ROS 2 wheels (pip install -e '.[ros]')")


@pytest.mark.ros
def test_log_without_motors_is_refused_before_the_graph_starts(ros, flights, tmp_path):
    """No motor topic in the log: the graph used to fly and score it (exit 0) where offline refused it
    (exit 2; issue 28); now both refuse it in one line before any node starts, and nothing is written."""
    t0 = time.monotonic()
    r = _cli("compare", flights["no_motors"], "--params", PARAMS, "--mcap", tmp_path / "bag", "--quiet",
             timeout=55)
    _one_line_error(r, "no_motors.ulg", "motors")
    assert time.monotonic() - t0 < 50
    assert not (tmp_path / "bag").exists()
    off = _cli("compare", flights["no_motors"], "--params", PARAMS, "--offline", "--quiet", timeout=55)
    assert off.returncode == 2 and off.stderr.strip().splitlines()[-1] == r.stderr.strip().splitlines()[-1]


@pytest.mark.ros
def test_dropout_longer_than_the_window_does_not_stall(ros, flights, tmp_path):
    """A 3 s gap in every topic (a logger dropout; the flow-control window is 0.5 s) used to stall the
    replay for good (issue 14, item 3); a successful run also leaves no /tmp/rotortwin_run_* folder."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {**os.environ, "TMPDIR": str(tmp)}
    r = _cli("compare", flights["dropout"], "--params", PARAMS, "--json", tmp_path / "m.json", "--quiet",
             timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["n_samples"] > 800 and m["throttle_rmse"] < 0.2
    assert not list(tmp.glob("rotortwin_run_*"))


@pytest.mark.ros
def test_mcap_messages_at_their_own_times(ros, tmp_path_factory):
    """Every message at its own stamp: header topics at their header stamp, header-less /real topics
    at their log time, /twin motors/throttle at their /twin/odom's, /replay/* inside the flight (never
    wall-clock time), and chunks that do not overlap in time."""
    import struct

    from graph_cases import recorded_baseline
    from mcap.reader import make_reader

    bag = recorded_baseline(tmp_path_factory.mktemp("stamps"))
    log_ns: dict[str, list[int]] = {}
    stamp: dict[str, list[int]] = {}
    plan = {}
    with open(next(Path(bag).glob("*.mcap")), "rb") as fh:
        for _, ch, msg in make_reader(fh).iter_messages(log_time_order=False):
            log_ns.setdefault(ch.topic, []).append(msg.log_time)
            if len(msg.data) >= 12:  # header.stamp (or Clock.clock) of a CDR message: int32 sec, uint32 nanosec
                sec, nsec = struct.unpack_from("<iI", msg.data, 4)
                stamp.setdefault(ch.topic, []).append(sec * 1_000_000_000 + nsec)
            if ch.topic == "/replay/plan":
                n = struct.unpack_from("<I", msg.data, 4)[0]
                plan = json.loads(msg.data[8:8 + n - 1])
    t0, t1 = plan["t0_ns"], plan["t1_ns"]
    for name in ("/real/odom", "/real/imu", "/real/battery", "/real/setpoint_pose", "/twin/odom", "/twin/imu",
                 "/twin_error/diagnostics", "/clock"):
        assert stamp[name] == log_ns[name], name
    assert len(set(log_ns["/real/imu"])) == len(log_ns["/real/imu"]) > 2000
    for name in ("/twin/motors", "/twin/throttle"):
        assert log_ns[name] == log_ns["/twin/odom"], name
    assert log_ns["/twin_error/xy/rmse_m"] == log_ns["/twin_error/diagnostics"]
    for name, ts in log_ns.items():
        assert all(t0 <= t <= t1 for t in ts), (name, min(ts), max(ts), t0, t1)
    with open(next(Path(bag).glob("*.mcap")), "rb") as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    overlaps = sum(b.message_start_time < a.message_end_time for a, b in zip(chunks, chunks[1:]))
    assert len(chunks) > 10 and overlaps == 0, (overlaps, len(chunks))


@pytest.mark.ros
def test_failed_run_leaves_no_files(ros, flights, tmp_path, monkeypatch):
    """A run that fails after the recorder started removes its bag and its temporary run folder."""
    import tempfile

    from twin_nodes.graph import run_graph

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    bag = tmp_path / "bag"
    with pytest.raises(TwinError, match="replay node failed"):
        run_graph(flights["short"], PARAMS, bag=str(bag), progress=False, timeout_s=120,
                  replay_params={"wait_for": ["twin", "metrics", "recorder", "nobody"], "start_timeout_s": 4.0})
    assert not bag.exists() and not list(tmp_path.glob("rotortwin_run_*")), list(tmp_path.iterdir())


@pytest.mark.ros
def test_kill_9_of_the_cli_stops_every_node(ros, flights, tmp_path):
    """`kill -9` of `rotortwin compare`: the nodes see their parent die and stop (the recorder
    finalises the bag) instead of running on forever."""
    run, bag = tmp_path / "run", tmp_path / "bag"
    cli = subprocess.Popen(ROTORTWIN + ["compare", str(flights["short"]), "--params", str(PARAMS), "--rate", "1",
                                        "--mcap", str(bag), "--run-dir", str(run), "--quiet"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    pids: dict[str, int] = {}
    try:
        t_end = time.monotonic() + 90
        while time.monotonic() < t_end:
            pids = {p.stem: int(p.read_text()) for p in run.glob("*.pid")} if run.is_dir() else {}
            log = run / "replay.log"
            if len(pids) == 4 and log.is_file() and "rate 1" in log.read_text(errors="replace"):
                break
            time.sleep(0.5)
        assert len(pids) == 4, pids
        # the bag is staged (renamed into place only by a CLI that finishes): it is in the stage beside it
        t_end = time.monotonic() + 60
        mcap = Path("/nonexistent")
        while time.monotonic() < t_end and (not mcap.exists() or mcap.stat().st_size < 150_000):
            found = list(tmp_path.glob(".rotortwin-stage-*/bag/bag.mcap"))
            mcap = found[0] if found else mcap
            time.sleep(0.5)  # flying at real time: wait for a few chunks in the bag
        assert all(_alive(p) for p in pids.values())
        os.kill(cli.pid, signal.SIGKILL)
        cli.wait(10)
        t_end = time.monotonic() + 30
        while time.monotonic() < t_end and any(_alive(p) for p in pids.values()):
            time.sleep(0.5)
        left = {n: p for n, p in pids.items() if _alive(p)}
        assert not left, f"still running after the CLI died: {left}"
    finally:
        for pid in pids.values():
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        if cli.poll() is None:
            cli.kill()
    from twin_nodes.logs.recording import topic_counts

    counts = topic_counts(mcap.parent)  # finalised (metadata.yaml, summary) by the recorder on its way out
    assert counts["/real/odom"] > 20 and "/twin/odom" in counts
    assert not bag.exists()  # the CLI never finished: nothing appeared where the user looks
