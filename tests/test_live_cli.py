"""``rotortwin live`` from the command line: the offline ``tlog`` path, the ``--foxglove`` helper for
other commands, and a live run's start/stop with no vehicle."""

from __future__ import annotations

import json
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import missing_shared

REPO = Path(__file__).resolve().parents[1]
LOG = REPO.parent / "shared" / "flightlogs" / "real" / "real_cubeorange_takeoff_land.ulg"


def test_live_tlog_is_the_offline_computation_of_the_stream(tmp_path):
    if not LOG.exists():
        missing_shared(LOG.name)
    from test_live_shadow import PARAMS, _messages, _telemetry_config

    from twin_nodes.cli import main
    from twin_nodes.live.offline import compare_telemetry, read_tlog
    from twin_nodes.vehicle.params import load_params

    stream, msgs = _messages(6.0)
    t0 = 1.7e9
    tlog = tmp_path / "flight.tlog"
    with open(tlog, "wb") as fh:  # QGroundControl's format: big-endian µs Unix time, then the packet
        for t, data in stream:
            fh.write(struct.pack(">Q", int(round((t0 + t) * 1e6))) + data)
    back = read_tlog(tlog)
    assert len(back) == len(msgs) and back[0][0] == pytest.approx(t0, abs=1e-6)
    out = tmp_path / "m.json"
    assert main(["live", "tlog", str(tlog), "--params", str(PARAMS), "--pwm-min", "1100", "--pwm-max", "1900",
                 "--motor-channels", "16,17,18,19", "--no-request-streams", "--window", "3", "--json", str(out)]) == 0
    m = json.loads(out.read_text())
    ref = compare_telemetry([(t0 + t, msg) for t, msg in msgs], load_params(PARAMS), config=_telemetry_config(),
                            window_s=3.0)
    for k in ("xy_rmse_m", "z_rmse_m", "throttle_rmse"):
        assert m[k] == pytest.approx(ref[k], rel=1e-6), k


def test_live_tlog_errors_are_one_line(tmp_path, capsys):
    from twin_nodes.cli import main

    assert main(["live", "tlog", str(tmp_path / "missing.tlog")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"rotortwin: error: {tmp_path / 'missing.tlog'}: file not found"]
    assert main(["live"]) == 2


@pytest.mark.ros
def test_foxglove_beside_serves_and_stops(tmp_path):
    pytest.importorskip("rclpy")
    pytest.importorskip("websockets")
    from foxglove_ws import FoxgloveClient

    from twin_nodes.live.attach import foxglove_beside, free_domain

    with foxglove_beside(0, free_domain()) as url:
        assert url.startswith("ws://127.0.0.1:")
        client = FoxgloveClient(url).start()
        time.sleep(1.5)
        cap = client.close()
    assert cap.server_info is not None and cap.server_info["name"] == "rotortwin"
    # no graph: the scene (empty) and the status are served; the channels derived from graph topics
    # are advertised with their first record only, so every advertised channel carries data
    assert cap.topics() == {"/viz/scene", "/viz/status"}, cap.topics()
    assert cap.messages["/viz/status"], "the status record is sent twice a second"
    assert cap.messages["/viz/scene"] and cap.messages["/viz/status"][-1][1]["source"] == "live"
    port = int(url.rsplit(":", 1)[1])
    with pytest.raises(OSError):  # stopped: nobody listens there any more
        socket.create_connection(("127.0.0.1", port), timeout=2).close()
    with foxglove_beside(None) as nothing:
        assert nothing is None


@pytest.mark.ros
@pytest.mark.slow
def test_live_cli_starts_and_stops_cleanly_without_a_vehicle(tmp_path):
    pytest.importorskip("rclpy")
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    r = subprocess.run([sys.executable, "-m", "twin_nodes", "live", "--url", f"udpin:127.0.0.1:{port}",
                        "--duration", "8", "--run-dir", str(tmp_path / "run"), "--no-request-streams",
                        "--mcap", str(tmp_path / "bag"), "--foxglove", "0"],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "no twin sample was scored" in r.stdout
    assert "on ROS_DOMAIN_ID" in r.stderr and "Foxglove ws://127.0.0.1:" in r.stderr
    logs = {p.name: p.read_text() for p in (tmp_path / "run").glob("*.log")}
    assert set(logs) == {"bridge.log", "twin.log", "metrics.log", "link.log", "recorder.log", "foxglove.log"}
    # the recording is finalised and holds the link flag (no vehicle: lost)
    from twin_nodes.logs.recording import read_bag

    flags = read_bag(tmp_path / "bag")["/twin_error/link_lost"]
    assert flags and flags[-1][1].data is True
    for name, text in logs.items():
        assert "signal" in text and "stopping" in text, (name, text[-500:])  # stopped by SIGINT, not killed
