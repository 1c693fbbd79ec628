"""Issue 28: a vehicle (PX4) restart mid-flight -- new boot time, new EKF origin -- re-syncs the twin,
and the metrics restart their rolling window (never comparing across the restart).

The scripted PX4 peer of ``tests/test_live_telemetry_graph.py`` (a real flight's MAVLink stream) is
played with a restart in it: 1 s of silence, then the boot time starts again at 2 s and the local
position is 60 m off (the new origin is where the vehicle was when it came back), as PX4 SITL does
when it is stopped and started again mid-flight.  Before the fix the twin kept its old position and
the rolling XY error stayed at 60+ m for a whole window.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import missing_shared

REPO = Path(__file__).resolve().parents[1]
LOG = REPO.parent / "shared" / "flightlogs" / "real" / "real_cubeorange_takeoff_land.ulg"
PARAMS = REPO / "params" / "quad_c_3dr.yaml"
T_RESTART = 10.0   # [s of the stream]
GAP_S = 1.0        # PX4 down
OFFSET_N = 60.0    # the new origin is 60 m North of the old one [m]
BOOT_S = 2.0       # the new boot time when data comes back [s]


def restarted_stream(seconds: float = 20.0):
    """``[(t_s, packed bytes)]``: the flight with a PX4 restart at ``T_RESTART``."""
    from pymavlink.dialects.v20 import common as mavlink2
    from test_live_telemetry_graph import _stream

    parser = mavlink2.MAVLink(None)
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    out = []
    t_boot0 = None
    for t, data in _stream(seconds):
        if T_RESTART <= t < T_RESTART + GAP_S:
            continue
        m = parser.decode(bytearray(data))
        if t >= T_RESTART:
            if hasattr(m, "time_boot_ms"):
                if t_boot0 is None:
                    t_boot0 = m.time_boot_ms
                m.time_boot_ms = int(BOOT_S * 1000) + m.time_boot_ms - t_boot0
            if m.get_type() == "LOCAL_POSITION_NED":
                m.x -= OFFSET_N
            data = m.pack(mav)
        out.append((t, bytes(data)))
    return out


def decoded(stream):
    from pymavlink.dialects.v20 import common as mavlink2

    parser = mavlink2.MAVLink(None)
    return [(t, parser.decode(bytearray(d))) for t, d in stream]


def test_restart_resyncs_the_twin_and_restarts_the_window():
    if not LOG.exists():
        missing_shared(LOG.name)
    from test_live_shadow import _telemetry_config

    from twin_nodes.live.offline import compare_telemetry
    from twin_nodes.vehicle.params import load_params

    vp = load_params(PARAMS)
    t0 = 1.7e9
    msgs = [(t0 + t, m) for t, m in decoded(restarted_stream())]
    rolling: list = []
    m = compare_telemetry(msgs, vp, config=_telemetry_config(), window_s=3.0, rolling=rolling, source="restart.tlog")
    # the restart is seen once, as a reboot, at the first message after it
    assert len(m["resets"]) == 1 and m["resets"][0]["reason"].startswith("reboot"), m["resets"]
    assert m["resets"][0]["t_s"] == pytest.approx(t0 + T_RESTART + GAP_S, abs=0.05)
    assert m["log"] == "restart.tlog" and m["system_id"] == 1
    t_r = (t0 + T_RESTART + GAP_S) * 1e9
    xy = np.array([(t, s["xy"]["rmse"]) for t, s in rolling])
    before = xy[(xy[:, 0] < t_r) & (xy[:, 0] > t_r - 3e9)]
    after = xy[xy[:, 0] > t_r]
    print("rolling xy rmse before", np.round(before[-3:, 1], 2), "after", np.round(after[:8, 1], 2),
          "totals", {k: round(m[k], 3) for k in ("xy_rmse_m", "xy_max_m", "z_rmse_m")})
    assert len(before) >= 3 and len(after) >= 8
    # the rolling window restarted: nothing from before the restart, the twin re-synced at once --
    # every window after it is as small as those before it (before the fix: 60+ m for a whole window)
    assert np.nanmax(after[:, 1]) < max(3.0, 2.0 * np.nanmax(before[:, 1])), after[:, 1]
    # and the whole-run totals never compare across it
    assert m["xy_max_m"] < 20.0, m["xy_max_m"]  # 12 m without a restart (open loop), 60+ m before the fix


def test_metrics_engine_never_interpolates_across_a_restart():
    """The real track is not interpolated across a restart, and the rolling window restarts with the
    first twin sample after it, with a note of when and why."""
    from twin_nodes.nodes.engine import NS, MetricsEngine, Track

    tr = Track()
    tr.add(0, np.array([0.0, 0.0, 0.0]))
    tr.add(NS, np.array([1.0, 0.0, 0.0]))
    tr.add(2 * NS, np.array([61.0, 0.0, 0.0]))
    tr.add_break(2 * NS - 1)
    np.testing.assert_allclose(tr.at(NS // 2), [0.5, 0, 0])
    assert tr.at(3 * NS // 2) is None

    eng = MetricsEngine(4, window_s=5.0, publish_period_ns=NS // 10, airborne_only=False)
    motors = np.full(4, 0.5)
    for k in range(0, 41):  # real: 1 m/s East, jumps by 60 m at t = 2 s (the restart)
        t = k * NS // 10
        p = np.array([k * 0.1 + (60.0 if k >= 20 else 0.0), 0.0, 5.0])
        eng.add_real("/real/odom", t, _odom(t, p))
    eng.reset(2 * NS - 1, "reboot")
    for k in range(0, 40):  # the twin: 0.5 m off before the restart, re-synced (0.1 m off) after
        t = k * NS // 10 + NS // 20
        p = np.array([k * 0.1 + 0.05 + (60.1 if t > 2 * NS else 0.5), 0.0, 5.0])
        eng.add_twin(t, p, 0.5, motors)
    out = eng.evaluate(final=True)
    assert eng.resets and eng.resets[0]["reason"] == "reboot" and eng.resets[0]["t_ns"] == 2 * NS - 1
    xy = [(t, s["xy"]["max"]) for t, s in out]
    assert max(v for t, v in xy if t > 2 * NS) == pytest.approx(0.1, abs=1e-6)  # never the 60 m
    assert max(v for t, v in xy if t < 2 * NS) == pytest.approx(0.5, abs=1e-6)
    # the twin sample between the last real sample before and the first after is not scored
    res = eng.totals(0, "open", 50.0, source="topics")
    assert res.metrics["xy_max_m"] < 1.0, res.metrics["xy_max_m"]


def _odom(t, p):
    from twin_nodes.logs import conversions as cv

    return cv.odom_msg(t, p, [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])


def test_live_tlog_json_says_what_it_watched(tmp_path):
    """``rotortwin live tlog --json``: the totals name the log, the vehicle, the span, the restart and
    the link losses (before: ``"source": "... replay ..."``, ``"log": ""``)."""
    if not LOG.exists():
        missing_shared(LOG.name)
    import json
    import struct

    from twin_nodes.cli import main

    stream = restarted_stream(20.0)
    t0 = 1.7e9
    tlog = tmp_path / "restart.tlog"
    with open(tlog, "wb") as fh:
        for t, data in stream:
            if 15.0 <= t < 19.0:  # and a 4 s silence: a link loss
                continue
            fh.write(struct.pack(">Q", int(round((t0 + t) * 1e6))) + data)
    out = tmp_path / "live.json"
    assert main(["live", "tlog", str(tlog), "--params", str(PARAMS), "--pwm-min", "1100", "--pwm-max", "1900",
                 "--motor-channels", "16,17,18,19", "--no-request-streams", "--window", "3", "--json", str(out)]) == 0
    m = json.loads(out.read_text())
    assert m["log"] == str(tlog) and "replay" not in m["source"], (m["log"], m["source"])
    assert m["system_id"] == 1 and m["component_id"] == 1
    assert m["start_s"] == pytest.approx(t0, abs=0.01) and m["end_s"] == pytest.approx(t0 + stream[-1][0], abs=0.01)
    assert [r["reason"].split()[0] for r in m["resets"]] == ["reboot"]
    assert m["resets"][0]["t_s"] == pytest.approx(t0 + T_RESTART + GAP_S, abs=0.05)
    assert len(m["link_losses"]) == 1 and m["link_losses"][0]["length_s"] == pytest.approx(4.0, abs=0.1)
    assert m["ignored"]["bad_data"] == 0 and m["messages"] > 500
