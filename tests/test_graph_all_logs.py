"""Every shared flight log through the real multi-process graph, with report and MCAP (slow:
~10-20 s per log on 2 cores).  Run: .venv/bin/pytest -m slow tests/test_graph_all_logs.py"""

from __future__ import annotations

import json
import math

import pytest
from conftest import need_log, ulog_params

pytest.importorskip("rclpy", reason="ROS 2 wheels (pip install -e '.[ros]')")

from twin_nodes.logs.streams import replay_streams  # noqa: E402
from twin_nodes.graph import load_aligned as _load_aligned, run_graph  # noqa: E402
from twin_nodes.vehicle.params import params_dir  # noqa: E402
from twin_nodes.logs.recording import topic_counts  # noqa: E402
from twin_nodes.twin.report import write_report  # noqa: E402
from twin_nodes.logs.ulog_io import read_ulog  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.ros]


@pytest.mark.parametrize("log_path", ulog_params("real") + ulog_params("sitl"))
def test_every_log_through_the_graph(tmp_path, log_path):
    path = need_log(log_path)
    # SIH flights fly the SIH model; the real 3S quads (and jMAVSim Iris) the closest shipped airframe
    params = params_dir() / ("px4_sih_quadx.yaml" if "px4sih" in path.stem else "quad_c_3dr.yaml")
    res = run_graph(path, params, run_dir=tmp_path / "run", bag=str(tmp_path / "bag"), progress=False,
                    timeout_s=600)
    m = res.metrics
    for k in ("xy_rmse_m", "xy_p75_m", "z_rmse_m", "z_p75_m"):
        assert math.isfinite(m[k]), k
    idx = write_report(tmp_path / "report", _load_aligned(res.aligned_path), m, title=path.name)
    for f in ("xy.png", "z.png", "throttle.png", "motors.png", "errors.png"):
        assert (tmp_path / "report" / f).stat().st_size > 5000, f
    assert "Throttle RMSE" in idx.read_text()
    streams, _ = replay_streams(read_ulog(path))
    counts = topic_counts(tmp_path / "bag")
    for s in streams:
        assert counts[s.topic] == len(s), s.topic
    print(json.dumps({"log": path.name, "params": params.name, "rtf": round(res.replay_stats["real_time_factor"], 1),
                      **{k: m[k] for k in ("xy_rmse_m", "xy_p75_m", "z_rmse_m", "z_p75_m", "throttle_rmse",
                                           "throttle_median", "motor_p75")}}))
