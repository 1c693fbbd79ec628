"""Issue 14.2: the Foxglove WebSocket server of the graph, and the shipped layout.

Fast: the layout file is what :mod:`twin_nodes.live.layout` generates, names only graph topics and
``/viz`` channels; the scene helpers.  ROS (slow): a replay graph (replay, twin, metrics, recorder
processes) with the Foxglove node beside it and a ws-protocol client (``tests/foxglove_ws.py``,
decoding by the advertised schemas only) subscribed to every advertised channel.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest

from msgs_py.topics import METRIC_STATS, TOPICS, metric_channels, metric_topic
from twin_nodes.live.layout import LAYOUT_PATH, layout_dict, layout_panels, layout_topics
from twin_nodes.live.scene import Trail, VehicleOutline, errors_record, motors_record, status_record

REPO = Path(__file__).resolve().parents[1]
FLIGHT = REPO / "bags" / "sim_quadx_weak_motor3.ulg"
PARAMS = REPO / "params" / "px4_sih_quadx.yaml"
VIZ = {"/viz/transforms", "/viz/scene", "/viz/errors", "/viz/motors", "/viz/status"}


# ----------------------------------------------------------------------------- fast


def test_shipped_layout_is_the_generated_one():
    assert json.loads(LAYOUT_PATH.read_text()) == layout_dict()


def test_layout_names_graph_topics_and_viz_channels_only():
    lay = layout_dict()
    graph = set(TOPICS) | {metric_topic(c, s) for c in metric_channels(8) for s in METRIC_STATS}
    named = layout_topics(lay)
    assert named - graph <= VIZ, named - graph - VIZ
    # every panel in configById is on screen (directly or in the tab), and vice versa
    shown = set(layout_panels(lay["layout"]))
    tabbed = {t["layout"] for t in lay["configById"]["Tab!status"]["tabs"]}
    assert shown | tabbed == set(lay["configById"])
    # the panels the issue asks for
    kinds = {k.split("!")[0] for k in lay["configById"]}
    assert {"3D", "Plot", "Indicator", "RawMessages", "DiagnosticSummary"} <= kinds
    assert {"/real/odom", "/twin/odom", "/viz/scene", "/twin_error/xy/rmse_m", "/twin_error/z/rmse_m",
            "/twin_error/throttle/rmse", "/twin_error/motor1/rmse", "/real/motors", "/twin/motors"} <= named


def test_scene_helpers():
    from twin_nodes.vehicle.params import load_params

    o = VehicleOutline.from_params(load_params(PARAMS))
    assert o.rotors_flu_m.shape == (4, 3) and 0.05 < o.disc_radius_m < 0.3
    tr = Trail(spacing_m=0.5, max_points=100)
    for i in range(1000):
        tr.add((0.1 * i, 0.0, 1.0))
    assert len(tr.points) <= 100 and tr.points[0] == (0.0, 0.0, 1.0) and tr.points[-1][0] == pytest.approx(99.5)
    assert not tr.add((math.nan, 0, 0))
    rec = motors_record(2_000_000_000, [0.5, math.nan], [0.6, 0.4])
    assert rec["t_s"] == 2.0 and rec["real"] == [0.5, None] and rec["error"] == [pytest.approx(0.1), None]
    e = errors_record(1, {"xy": {"rmse_m": 0.2, "p75_m": math.nan}}, True)
    assert e["channels"]["xy"] == {"rmse_m": 0.2, "p75_m": None} and e["link_lost"] is True
    s = status_record(source="live", t_ns=None, status=[1, 3, 255], link="ok", link_lost=False, twin={},
                      messages={}, final=None)
    assert s["armed"] is True and s["nav_state"] == 3 and s["landed"] is None
    json.dumps([rec, e, s], allow_nan=False)  # JSON without NaN


# ----------------------------------------------------------------------------- ROS


def _foxglove_node(env, tmp_path, mcap: Path):
    from twin_nodes.live.shadow import module_command

    p = subprocess.Popen(module_command("twin_nodes.live.foxglove_node", [], {"port": 0, "mcap": str(mcap)}),
                         cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=open(tmp_path / "foxglove.log", "w"),
                         text=True, start_new_session=True)
    line: list[str] = []
    th = threading.Thread(target=lambda: line.append(p.stdout.readline()), daemon=True)
    th.start()
    th.join(120)
    assert line and line[0].startswith("FOXGLOVE ws://"), (tmp_path / "foxglove.log").read_text()[-2000:]
    return p, line[0].split()[1]


@pytest.mark.ros
@pytest.mark.slow
def test_foxglove_server_serves_every_channel_during_a_replay(tmp_path):
    pytest.importorskip("rclpy")
    pytest.importorskip("google.protobuf")
    pytest.importorskip("websockets")
    from foxglove_ws import FoxgloveClient

    from twin_nodes.graph import ros_env, run_graph
    from twin_nodes.live.attach import free_domain
    from twin_nodes.logs.recording import read_bag, topic_counts

    domain = free_domain()
    env = ros_env(domain)
    mcap = tmp_path / "served.mcap"
    node, url = _foxglove_node(env, tmp_path, mcap)
    client = None
    try:
        client = FoxgloveClient(url).start()
        res = run_graph(FLIGHT, PARAMS, bag=str(tmp_path / "bag"), domain_id=domain, progress=False,
                        timeout_s=900, rate=0.0)
        import time
        time.sleep(2.0)  # the last scene/status records
    finally:
        cap = client.close() if client is not None else None
        node.send_signal(signal.SIGINT)
        try:
            node.wait(30)
        except subprocess.TimeoutExpired:
            node.kill()
    log = (tmp_path / "foxglove.log").read_text()[-3000:]
    assert node.returncode == 0, log
    assert cap is not None and cap.server_info is not None
    advertised = cap.topics()
    print(f"{len(advertised)} channels; subscribes refused and sent again (SDK race): {cap.retries}; messages: "
          + ", ".join(f"{t} {len(v)}" for t, v in sorted(cap.messages.items())))
    assert not cap.errors, cap.errors
    assert all(n < 5 for n in cap.retries.values()), cap.retries
    # every advertised channel delivered decodable messages
    silent = sorted(t for t in advertised if not cap.messages[t])
    counts_at_node = cap.messages["/viz/status"][-1][1]["messages"] if cap.messages["/viz/status"] else {}
    assert not silent, (silent, {t: (cap.subscribed.get(t), counts_at_node.get(t)) for t in silent},
                        cap.other_ops[:10])
    assert VIZ <= advertised
    assert {"/clock", "/real/odom", "/twin/odom", "/real/motors", "/twin/motors", "/twin_error/xy/rmse_m",
            "/twin_error/diagnostics", "/twin_error/final_json"} <= advertised
    assert not {t for t in advertised if t.startswith("/replay/")}

    # forwarded unchanged: the served final metrics are the recorded ones
    bag_final = read_bag(tmp_path / "bag")["/twin_error/final_json"]
    served_final = cap.messages["/twin_error/final_json"][-1][1].data
    assert json.loads(served_final) == json.loads(bag_final[-1][1].data)
    assert json.loads(served_final)["xy_rmse_m"] == pytest.approx(res.metrics["xy_rmse_m"])
    # the derived channels: both vehicles placed, both paths drawn, errors and motors side by side
    frames = {tf.child_frame_id for _, m in cap.messages["/viz/transforms"] for tf in m.transforms}
    assert frames == {"real/base_link", "twin/base_link"}
    ents = {e.id for _, m in cap.messages["/viz/scene"][-3:] for e in m.entities}
    assert {"real_vehicle", "twin_vehicle", "real_path", "twin_path"} <= ents
    last_path = [e for e in cap.messages["/viz/scene"][-1][1].entities if e.id == "real_path"][0]
    assert len(last_path.lines[0].points) > 50
    err = cap.messages["/viz/errors"][-1][1]
    assert set(err["channels"]) >= {"xy", "z", "throttle", "motor1"} and err["channels"]["xy"]["rmse_m"] is not None
    mot = cap.messages["/viz/motors"][-1][1]
    assert len(mot["real"]) == len(mot["twin"]) == 4
    status = cap.messages["/viz/status"][-1][1]
    assert status["source"] == "replay" and status["final"] is not None
    assert status["twin"]["vehicle"] == "px4_sih_quadx"

    # the layout opens both: every topic it names is served live or in the recording ...
    counts = topic_counts(tmp_path / "bag")
    named = layout_topics(layout_dict())
    assert named <= advertised | set(counts), named - advertised - set(counts)
    # ... and all but the /viz channels are in the recording, with messages
    assert all(counts.get(t, 0) > 0 for t in named - VIZ), {t: counts.get(t, 0) for t in named - VIZ}

    # the served-view MCAP (-p mcap:=...) holds every channel, the /viz ones included
    from mcap.reader import make_reader

    with open(mcap, "rb") as fh:
        summary = make_reader(fh).get_summary()
    in_mcap = {c.topic for c in summary.channels.values()}
    assert VIZ | {"/real/odom", "/twin/odom"} <= in_mcap
    assert summary.statistics.message_count > 1000
    assert np.isfinite(res.metrics["throttle_rmse"])
