"""Issue 28, live: the link watchdog and the live graph, whatever the input.

- :class:`twin_nodes.live.link_node.LinkWatch`: a clean stop of the bridge and the vehicle's own
  clean shutdown are not link losses; a real silence is;
- ``rotortwin bridge telemetry --no-ros`` on random UDP bytes says STALE and counts them;
- ``rotortwin live``'s graph (:func:`run_live`) with the scripted PX4 peer: PX4 restarts mid-flight
  (the twin re-syncs, the rolling window restarts with a note on ``/twin_error/reset``), then shuts
  down cleanly and ``live`` is stopped normally: no link loss, and the totals say what was watched.
"""

from __future__ import annotations

import json
import random
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import missing_shared

from twin_nodes.live.link_node import LinkWatch

REPO = Path(__file__).resolve().parents[1]
LOG = REPO.parent / "shared" / "flightlogs" / "real" / "real_cubeorange_takeoff_land.ulg"


def _run(watch: LinkWatch, events, until: float, dt: float = 0.1) -> None:
    """Feed ``events`` [(t, kind, args)] and tick every ``dt`` up to ``until``."""
    events = sorted(events, key=lambda e: e[0])
    t, k = 0.0, 0
    while t <= until + 1e-9:
        while k < len(events) and events[k][0] <= t + 1e-9:
            _, kind, args = events[k]
            getattr(watch, kind)(events[k][0], *args)
            k += 1
        watch.update(t)
        t += dt


def test_link_watch_real_silence_is_an_outage():
    w = LinkWatch(3.0, 0.0)
    _run(w, [(0.1 * i, "odom", ()) for i in range(1, 50)] + [(10.0 + 0.1 * i, "odom", ()) for i in range(20)], 12.0)
    w.close(12.0)
    assert len(w.outages) == 1 and w.outages[0]["start_s"] == pytest.approx(4.9)
    assert w.outages[0]["length_s"] == pytest.approx(5.1, abs=0.11) and not w.outages[0].get("open")
    # silent at the end without a clean stop: an open outage
    w2 = LinkWatch(3.0, 0.0)
    _run(w2, [(0.1 * i, "odom", ()) for i in range(1, 50)], 10.0)
    w2.close(10.0)
    assert len(w2.outages) == 1 and w2.outages[0]["open"]


def test_link_watch_clean_stop_is_not_a_loss():
    """The bridge announced its stop, then the watchdog ran on for 10 s (the twin and metrics
    stopping): no outage.  Before: an open outage 'at the end' of every normal stop."""
    w = LinkWatch(3.0, 0.0)
    _run(w, [(0.1 * i, "odom", ()) for i in range(1, 50)] + [(5.0, "bridge", (False, True, False))], 15.0)
    w.close(15.0)
    assert w.outages == [] and w.lost is False
    assert [e["reason"] for e in w.ends] == ["bridge stopped"]


def test_link_watch_vehicle_shutdown_is_not_a_loss_and_a_restart_is_watched_again():
    w = LinkWatch(3.0, 0.0)
    ev = [(0.1 * i, "odom", ()) for i in range(1, 50)]
    ev += [(4.95, "bridge", (False, False, True))]                          # MAV_STATE_POWEROFF heartbeat
    ev += [(8.0, "bridge", (True, False, True))]                            # then silence: stale
    ev += [(12.0 + 0.1 * i, "odom", ()) for i in range(20)]                 # it came back (restarted)
    _run(w, ev, 20.0)
    assert w.outages == [] and [e["reason"] for e in w.ends] == ["vehicle shut down"]
    assert w.lost is True  # watched again after the restart: its silence from 14 s on is a loss
    w.close(20.0)
    assert len(w.outages) == 1 and w.outages[0]["open"]


def test_bridge_telemetry_no_ros_says_stale_on_garbage():
    """``rotortwin bridge telemetry --no-ros`` fed only random bytes: every status line says STALE,
    and the ignored bytes are counted (before: 'ok' with msgs > 0)."""
    import threading

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    p = subprocess.Popen([sys.executable, "-m", "twin_nodes", "bridge", "telemetry", "--no-ros", "--url",
                          f"udpin:127.0.0.1:{port}", "--no-request-streams", "--stale-after", "0.5",
                          "--duration", "6"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    first = threading.Event()

    def reader() -> None:
        assert p.stdout is not None
        for line in p.stdout:
            if line.strip():
                lines.append(line.strip())
                first.set()
    th = threading.Thread(target=reader, daemon=True)
    th.start()
    assert first.wait(120), p.stderr.read() if p.poll() is not None else "no status line"
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rng = random.Random(7)
    t_end = time.monotonic() + 3.0  # the link is open (a status line came): garbage only
    while time.monotonic() < t_end and p.poll() is None:
        tx.sendto(bytes(rng.getrandbits(8) for _ in range(300)), ("127.0.0.1", port))
        time.sleep(0.005)
    tx.close()
    err = p.communicate(timeout=60)[1]
    th.join(5)
    assert p.returncode == 0, err[-2000:]
    assert len(lines) >= 3 and all(ln.startswith("STALE") for ln in lines), lines
    assert "msgs=0" in lines[-1] and int(lines[-1].split("bad=")[1].split()[0]) > 20, lines[-1]


# ----------------------------------------------------------------------------- live graph (ROS)


@pytest.mark.ros
def test_live_vehicle_restart_and_clean_shutdown(tmp_path):
    """The scripted PX4 peer flies 20 s with a PX4 restart at 10 s (1 s down, boot time back to 2 s,
    the local position 60 m off), then sends a MAV_STATE_POWEROFF heartbeat and goes quiet for 5 s
    (longer than the 3 s stale limit) before ``live`` is stopped normally."""
    if not LOG.exists():
        missing_shared(LOG.name)
    pytest.importorskip("rclpy")
    from pymavlink.dialects.v20 import common as mavlink2
    from std_msgs.msg import String
    from test_live_restart import GAP_S, T_RESTART, restarted_stream
    from test_live_shadow import _Live

    from twin_nodes.nodes.common import reliable_qos

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    stream = restarted_stream(20.0)
    t_end = stream[-1][0]
    stream.append((t_end + 0.05, mav.heartbeat_encode(2, 12, 1, (4 << 16) | (6 << 24), mavlink2.MAV_STATE_POWEROFF)
                   .pack(mav)))
    notes: list[dict] = []
    with _Live(tmp_path, ("/twin_error/link_lost", "/twin_error/xy/rmse_m")) as live:
        live.node.create_subscription(String, "/twin_error/reset", lambda m: notes.append(json.loads(m.data)),
                                      reliable_qos(1, latched=True))
        t0 = live.play(stream)
        time.sleep(5.0)  # the vehicle is gone (it said so)
    res = live.result
    assert live.error is None and res is not None, live.error
    assert all(c == 0 for c in res.exit_codes.values()), (res.exit_codes, live.logs())
    m = res.metrics
    rel = {t: [(w - t0, v) for w, v in live.got[t]] for t in live.got}
    xy = [(t, v) for t, v in rel["/twin_error/xy/rmse_m"] if np.isfinite(v)]
    t_r = T_RESTART + GAP_S
    before = [v for t, v in xy if t_r - 3.0 < t < t_r]
    after = [v for t, v in xy if t_r < t < t_end]
    print("outages", res.outages, "ends", m.get("ends"), "resets", m.get("resets"), "notes", notes,
          "xy before", np.round(before[-3:], 2), "after", np.round(after[:8], 2),
          "totals", {k: round(m[k], 3) for k in ("xy_rmse_m", "xy_max_m")})
    # no link loss: the 1 s restart gap is shorter than stale_after, the end was announced and clean
    assert res.outages == [] and m["link_losses"] == [], (res.outages, live.logs())
    assert [e["reason"] for e in m["ends"]][:1] == ["vehicle shut down"], m["ends"]
    assert not [v for t, v in rel["/twin_error/link_lost"] if v == 1.0 and t > 1.0], rel["/twin_error/link_lost"]
    # the restart: seen once by the bridge, noted by the metrics, the twin re-synced at once
    assert len(m["resets"]) == 1 and m["resets"][0]["reason"].startswith("reboot"), m["resets"]
    assert notes and notes[-1]["reason"].startswith("reboot") and notes[-1]["count"] == 1, notes
    assert abs(notes[-1]["t_s"] - (live.t0_unix + t_r)) < 0.5, (notes, live.t0_unix)
    assert len(before) >= 3 and len(after) >= 8, (before, after)
    assert max(after) < max(3.0, 2.0 * max(before)), after
    assert m["xy_max_m"] < 20.0, m["xy_max_m"]
    # the totals say what was watched
    assert m["log"] == live.cfg.url and m["system_id"] == 1 and m["vehicle_closed"] is True
    assert m["start_s"] == pytest.approx(live.t0_unix, abs=1.0) and m["end_s"] > m["start_s"] + 15.0
    assert "replay" not in m["source"]


@pytest.mark.ros
def test_live_normal_stop_is_not_a_link_loss(tmp_path):
    """``live`` stopped normally while the vehicle still streams, with a 1 s stale limit: no outage,
    the link flag never rises.  Before: the watchdog was stopped last, after the twin and the metrics,
    and called the silence after the bridge's stop a link loss "at the end"."""
    if not LOG.exists():
        missing_shared(LOG.name)
    pytest.importorskip("rclpy")
    from test_live_shadow import _Live, _messages

    stream, _ = _messages(6.0)
    with _Live(tmp_path, ("/twin_error/link_lost",), stale_after_s=1.0) as live:
        t0 = live.play(stream)
    res = live.result
    assert live.error is None and res is not None, live.error
    assert all(c == 0 for c in res.exit_codes.values()), (res.exit_codes, live.logs())
    flags = [(w - t0, v) for w, v in live.got["/twin_error/link_lost"]]
    link = json.loads((live.run_dir / "link.json").read_text()) if (live.run_dir / "link.json").exists() else None
    print("outages", res.outages, "flags", flags[-3:], "link.json", link)
    assert res.outages == [] and res.metrics["link_losses"] == [], (res.outages, live.logs())
    assert not [v for t, v in flags if v == 1.0 and t > 0.5], flags
    assert res.watched["log"] == live.cfg.url and res.watched["system_id"] == 1 and res.watched["messages"] > 100
