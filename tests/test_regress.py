"""`rotortwin regress` as CI uses it: a baseline recorded with the graph is flown again by today's
twin; the unchanged twin passes, a params change that should fail (mass +10 %) fails and names the
throttle and motor metrics; `--update` accepts a new baseline; bad tolerances are refused.

The baseline is the first 30 s of the PX4 SIH triangle log (tests/graph_cases.py), recorded once
per session through the node graph (`compare --mcap`, ~25 s); the checks run the offline path
(the twin and metrics node cores in one process, a few seconds each) and the graph path once."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROTORTWIN = [sys.executable, "-m", "twin_nodes"]


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(ROTORTWIN + [str(a) for a in args], capture_output=True, text=True, timeout=timeout)


def _one_line_error(r: subprocess.CompletedProcess, *words: str) -> None:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("rotortwin: error:"), r.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])


# ----------------------------------------------------------------------------- no ROS


@pytest.mark.parametrize("opt,value", [("--abs-tolerance", "nan"), ("--tolerance", "0"), ("--tolerance", "-0.1"),
                                       ("--tolerance", "inf"), ("--abs-tolerance", "x")])
def test_bad_tolerance_is_a_one_line_error(tmp_path, opt, value):
    r = _cli("regress", tmp_path / "no_bag", opt, value, timeout=60)
    _one_line_error(r, opt, "expected a number in (0, ")  # the option's argparse type (cli/options.py)
    from twin_nodes.graph.regress import check_tolerance

    with pytest.raises(Exception, match="finite number > 0"):
        check_tolerance(value, opt)


def _m(**kw):
    base = {"xy_rmse_m": 0.5, "xy_p75_m": 0.6, "xy_median_m": 0.4, "xy_max_m": 1.0, "z_rmse_m": 0.2,
            "z_p75_m": 0.2, "z_median_m": 0.1, "z_max_m": 0.4, "throttle_rmse": 0.03, "throttle_p75": 0.02,
            "throttle_median": 0.01, "throttle_max": 0.2, "motor_rmse": [0.04, 0.04], "motor_p75": [0.03, 0.03],
            "motor_median": [0.02, 0.02], "motor_max": [0.2, 0.2], "n_samples": 1000}
    base.update(kw)
    return base


def test_comparison_is_one_sided_and_names_each_metric():
    from twin_nodes.graph.regress import compare_with_baseline, metric_values

    ch = {c.name: c for c in compare_with_baseline(_m(), _m(throttle_rmse=0.06, xy_rmse_m=0.3,
                                                          motor_p75=[0.03, None], n_samples=500))}
    assert ch["throttle/rmse"].verdict == "WORSE" and ch["throttle/rmse"].failed
    assert ch["xy/rmse_m"].verdict == "better" and not ch["xy/rmse_m"].failed     # better is not a failure
    assert ch["motor2/p75"].verdict == "LOST"                                     # computed before, not now
    assert ch["samples"].verdict == "WORSE"                                       # covering less is worse
    assert ch["motor1/p75"].verdict == "ok" and ch["z/max_m"].verdict == "ok"
    # identical values pass at any tolerance (the old check flagged 29 identical metrics at --tolerance 0)
    assert not any(c.failed for c in compare_with_baseline(_m(), _m(), 1e-12, 1e-12))
    assert set(metric_values(_m())) >= {"xy/rmse_m", "throttle/median", "motor2/max", "samples"}


# ----------------------------------------------------------------------------- with the graph


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    pytest.importorskip("rclpy", reason="ROS 2 wheels (pip install -e '.[ros]')")
    from graph_cases import recorded_baseline

    return recorded_baseline(tmp_path_factory.mktemp("regress"))


@pytest.fixture(scope="module")
def heavy(tmp_path_factory):
    from graph_cases import params_with_mass

    return params_with_mass(tmp_path_factory.mktemp("params"), 1.1)


@pytest.mark.ros
def test_baseline_records_its_params(baseline):
    from twin_nodes.graph.regress import load_baseline
    from twin_nodes.vehicle.params import params_dir

    b = load_baseline(baseline)
    pfile = params_dir() / "px4_sih_quadx.yaml"
    assert b.config["params_file"] == str(pfile.resolve())
    assert b.config["params_yaml"] == pfile.read_text(encoding="utf-8") and b.config["mode"] == "closed"
    assert b.metrics["n_samples"] > 500 and math.isfinite(b.metrics["throttle_rmse"])


@pytest.mark.ros
def test_unchanged_twin_passes_offline(baseline, tmp_path):
    out = tmp_path / "cmp.json"
    r = _cli("regress", baseline, "--offline", "--json", out)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "OK: no metric worse" in r.stderr and "recorded with the baseline" in r.stdout
    res = json.loads(out.read_text())
    assert not res["failed"] and res["path"] == "offline"
    # the offline path runs the graph's own twin and metrics cores on the same events: the same numbers
    for c in res["changes"]:
        if c["baseline"] is not None:
            assert c["now"] == pytest.approx(c["baseline"], rel=1e-6, abs=1e-9), c


@pytest.mark.ros
def test_heavier_twin_fails_naming_throttle_and_motors(baseline, heavy):
    r = _cli("regress", baseline, "--offline", "--params", heavy)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "REGRESSION:" in r.stderr and "throttle/rmse" in r.stderr
    worse = {ln.split()[0] for ln in r.stdout.splitlines() if ln.rstrip().endswith("WORSE")}
    assert {"throttle/rmse", "throttle/median"} <= worse, r.stdout
    assert {f"motor{i}/p75" for i in range(1, 5)} <= worse, r.stdout
    assert not any(n.startswith(("xy/", "z/")) for n in worse)  # the controller hides mass from position


@pytest.mark.ros
def test_unchanged_twin_passes_through_the_graph(baseline):
    r = _cli("regress", baseline, "--quiet")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "(graph)" in r.stdout and "OK: no metric worse" in r.stderr


@pytest.mark.ros
def test_update_accepts_a_new_baseline(baseline, heavy, tmp_path):
    """--update re-records the baseline with today's twin (offline here, the graph path once):
    the heavier twin then passes against it and its params travel with it."""
    from twin_nodes.graph.regress import load_baseline
    from twin_nodes.logs.recording import topic_counts

    for path in ("offline", "graph"):
        bag = tmp_path / f"baseline_{path}"
        shutil.copytree(baseline, bag)
        r = _cli("regress", bag, "--update", "--params", heavy, "--quiet",
                 *(["--offline"] if path == "offline" else []))
        assert r.returncode == 0 and "baseline updated" in r.stderr, r.stdout + r.stderr
        assert "WORSE" in r.stdout  # what was accepted is shown
        assert sorted(p.name for p in bag.iterdir()) == sorted(["metadata.yaml", f"baseline_{path}.mcap"])
        assert not list(tmp_path.glob(".*update*"))
        new = load_baseline(bag)
        assert new.config["params_yaml"] == Path(heavy).read_text(encoding="utf-8")
        counts, old = topic_counts(bag), topic_counts(baseline)
        for t in ("/real/odom", "/real/imu", "/real/motors", "/real/throttle", "/real/setpoint"):
            assert counts[t] == old[t], t
        assert counts["/twin/odom"] == counts["/twin/motors"] > 500 and counts["/twin_error/throttle/rmse"] > 10
        r2 = _cli("regress", bag, "--offline")                  # its own (heavier) params: passes
        assert r2.returncode == 0, r2.stdout + r2.stderr
        assert "px4_sih_quadx_mass1.1.yaml" in r2.stdout
    r3 = _cli("regress", tmp_path / "baseline_offline", "--offline", "--params",
              Path(__file__).resolve().parents[1] / "params" / "px4_sih_quadx.yaml")
    assert r3.returncode == 0 and "better" in r3.stdout, r3.stdout + r3.stderr


@pytest.mark.ros
def test_regress_on_a_bag_without_metrics_is_a_one_line_error(baseline, tmp_path):
    r = _cli("regress", tmp_path / "missing_bag", "--offline", timeout=60)
    _one_line_error(r, "missing_bag")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "metadata.yaml").write_text("not: a bag\n")
    r = _cli("regress", bad, "--offline", timeout=60)
    _one_line_error(r, str(bad))
