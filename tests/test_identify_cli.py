"""``rotortwin identify ...``: outputs merge into a params file; bad input writes nothing.

The ULog cases read ../shared/flightlogs (skipped locally without it, failing under CI=true).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml
from conftest import shared_log

from twin_nodes.cli import main
from twin_nodes.identify.step_response import simulate_lag
from twin_nodes.vehicle.params import from_ros_dict, params_dir, shipped

SIH = str(params_dir() / "px4_sih_quadx.yaml")


def merged_ok(doc: dict) -> object:
    """The ros__parameters block merged into the SIH params passes the schema."""
    from twin_nodes.identify.results import merge_into_params
    block = doc["/**"]["ros__parameters"]
    return from_ros_dict(merge_into_params(shipped("px4_sih_quadx").to_ros_dict(), block))


@pytest.fixture
def steps_csv(tmp_path):
    rng = np.random.default_rng(0)
    levels = 1425.0 + np.array([0, 50, -50, 100, 0, -100, 50, 0])
    t = np.arange(0.0, 40.0, 0.005)
    u = levels[(t // 5).astype(int)]
    y = simulate_lag(t, u, t, tau_up_s=0.15, gain=6.5, u_ref=1425.0, y_ref=3745.0) + rng.normal(0, 20, t.size)
    p = tmp_path / "bench.csv"
    p.write_text("time_s,command,rpm\n" + "\n".join(f"{a:.4f},{b:.0f},{c:.1f}" for a, b, c in zip(t, u, y)))
    return p


def test_motor_csv_to_yaml_and_plot(tmp_path, steps_csv, capsys):
    out, png = tmp_path / "motor.yaml", tmp_path / "motor.png"
    rc = main(["identify", "motor", str(steps_csv), "--no-delay", "--out", str(out), "--plot", str(png),
               "--params", SIH])
    assert rc == 0
    text = capsys.readouterr().out
    assert "tau_up_s" in text and "ZOH at 30 Hz" in text
    doc = yaml.safe_load(out.read_text())
    rot = doc["/**"]["ros__parameters"]["rotors"]
    assert set(rot) == {"tau_up_s", "tau_down_s"}
    assert rot["tau_up_s"] == pytest.approx(0.15, rel=0.03) and rot["tau_down_s"] == pytest.approx(0.15, rel=0.03)
    fit = doc["identify"]["fits"]["csv"]
    assert fit["symmetric"]["gain"] == pytest.approx(6.5, rel=0.03)
    assert fit["zoh"]["a"] == pytest.approx(math.exp(-1 / (30 * fit["symmetric"]["tau_up_s"])), rel=1e-12)
    assert doc["identify"]["command"].startswith("rotortwin identify motor ")
    vp = merged_ok(doc)
    assert vp.rotors.tau_up_s == rot["tau_up_s"]
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert not list(tmp_path.glob("*.tmp*"))


def test_motor_json_output(tmp_path, steps_csv):
    out = tmp_path / "motor.json"
    assert main(["identify", "motor", str(steps_csv), "--symmetric", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    rot = doc["/**"]["ros__parameters"]["rotors"]
    assert rot["tau_up_s"] == rot["tau_down_s"]
    assert doc["identify"]["fits"]["csv"]["symmetric"]["delay_s"] < 0.003


def test_bad_csv_exits_nonzero_and_writes_nothing(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("time,command,rpm\n" + "\n".join(f"{i},1,2" for i in range(20)))
    out, png = tmp_path / "o.yaml", tmp_path / "o.png"
    rc = main(["identify", "motor", str(bad), "--out", str(out), "--plot", str(png)])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.count("\n") == 0 and "column 'time_s': missing" in err and str(bad) in err
    assert not out.exists() and not png.exists()


def test_bad_out_suffix_writes_nothing(tmp_path, steps_csv, capsys):
    out = tmp_path / "o.txt"
    assert main(["identify", "motor", str(steps_csv), "--out", str(out)]) == 2
    assert "--out: expected a file name ending in .yaml" in capsys.readouterr().err
    assert not out.exists()


def test_bad_params_file(tmp_path, steps_csv, capsys):
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    vehicle: {mass_kg: -1}\n")
    assert main(["identify", "motor", str(steps_csv), "--params", str(p), "--out", str(tmp_path / "o.yaml")]) == 2
    assert "vehicle.mass_kg" in capsys.readouterr().err
    assert not (tmp_path / "o.yaml").exists()


# ----------------------------------------------------------------------------- shared logs


def test_noise_on_sih_pre_arm_segment(tmp_path, capsys):
    log = shared_log("sitl", "px4sih_default_triangle.ulg")
    out, png = tmp_path / "n.yaml", tmp_path / "n.png"
    assert main(["identify", "noise", str(log), "--out", str(out), "--plot", str(png)]) == 0
    doc = yaml.safe_load(out.read_text())
    s = doc["/**"]["ros__parameters"]["sensors"]
    assert len(s["gyro_noise_rad_s"]) == 3 and all(1e-4 < v < 0.1 for v in s["gyro_noise_rad_s"])
    assert all(1e-3 < v < 1.0 for v in s["accel_noise_m_s2"])
    assert 50 < s["sample_rate_hz"] < 200
    seg = doc["identify"]["segment_s"]
    assert seg[0] < seg[1] < 9.0 and doc["identify"]["armed"] is False  # before arming (~9 s)
    merged_ok(doc)
    assert png.exists()


def test_noise_without_disarmed_ground_segment_fails_cleanly(tmp_path, capsys):
    log = shared_log("real", "real_cubeorange_takeoff_land.ulg")
    out = tmp_path / "n.yaml"
    assert main(["identify", "noise", str(log), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "landed and disarmed" in err and err.strip().count("\n") == 0
    assert not out.exists()


def test_regress_on_sih_recovers_translational_truth(tmp_path, capsys):
    log = shared_log("sitl", "px4sih_default_triangle.ulg")
    out = tmp_path / "r.yaml"
    assert main(["identify", "regress", str(log), "--params", SIH, "--out", str(out)]) == 0
    doc = yaml.safe_load(out.read_text())
    rep = doc["identify"]
    # SIH truth: T_MAX/m = 5.0, KDV/m = 1.0, Q_MAX/Izz = km T_MAX / Izz = 3.33
    assert rep["translational"]["z"]["coefficients"]["kT/m"]["value"] == pytest.approx(5.0, rel=0.03)
    assert rep["translational"]["x"]["coefficients"]["kd_x/m"]["value"] == pytest.approx(1.0, rel=0.05)
    # rotational coefficients by the moment form at 2.5 Hz (identify/from_log.py ROT_LOWPASS_HZ): roll and
    # pitch effectiveness T_MAX l / I = 5 * 0.2828 / 0.025 = 56.6 within 5 % (least squares of the acceleration
    # on the commands gave 43.6 / 43.5, -23 %); yaw +5.0 % (least squares +1.4 %: the yaw commands, with no
    # D-term, carry little controller noise, so there the remaining acceleration noise tips the moment form up)
    rot = rep["rotational"]
    assert rot["roll"]["coefficients"]["kT*l/Ixx"]["value"] == pytest.approx(56.57, rel=0.05)
    assert rot["pitch"]["coefficients"]["kT*l/Iyy"]["value"] == pytest.approx(56.57, rel=0.05)
    assert rot["yaw"]["coefficients"]["km*kT/Izz"]["value"] == pytest.approx(0.1 / 0.03, rel=0.06)
    assert rot["roll"]["method"].startswith("moment form")
    assert rep["structural_with_m_l_km_known"]["unidentifiable_directions_log"] == []
    vp = merged_ok(doc)
    assert vp.rotors.thrust_max_n == pytest.approx(5.0, rel=0.03)
    # SIH truth IXX = IYY = 0.025, IZZ = 0.030 kg m^2 (was 0.0328 / 0.0329 / 0.0300 by least squares)
    assert vp.inertia[0, 0] == pytest.approx(0.025, rel=0.06)
    assert vp.inertia[1, 1] == pytest.approx(0.025, rel=0.06)
    assert vp.inertia[2, 2] == pytest.approx(0.030, rel=0.06)


def test_delay_and_hover_and_motor_on_logs(tmp_path, capsys):
    sih = shared_log("sitl", "px4sih_default_triangle.ulg")
    out = tmp_path / "d.json"
    assert main(["identify", "delay", str(sih), "--pairs", "torque_roll,motor_pitch", "--boot", "50",
                 "--out", str(out)]) == 0
    d = json.loads(out.read_text())["identify"]["delays"]
    assert set(d) == {"torque_roll", "motor_pitch"}
    for e in d.values():
        assert 0.0 < e["delay_s"] < 0.1 and e["peak_corr"] > 0.5 and e["ci95_s"][0] <= e["delay_s"] <= e["ci95_s"][1]

    cube = shared_log("real", "real_cubeorange_takeoff_land.ulg")
    out = tmp_path / "h.yaml"
    assert main(["identify", "hover", str(cube), "--out", str(out)]) == 0
    rep = yaml.safe_load(out.read_text())["identify"]
    assert rep["summary"]["n_segments"] >= 1 and 0.3 < rep["summary"]["throttle_mean"] < 0.7

    iris = shared_log("real", "sitl_iris_takeoff_land.ulg")
    out = tmp_path / "m.yaml"
    assert main(["identify", "motor", str(iris), "--out", str(out)]) == 0
    rep = yaml.safe_load(out.read_text())["identify"]
    # PX4 SITL writes esc_rpm = control x 6000 with no lag
    for fit in rep["fits"].values():
        assert fit["symmetric"]["gain"] == pytest.approx(6000.0, rel=0.02)
        assert fit["symmetric"]["tau_up_s"] < 0.01


def test_motor_on_log_without_rpm_fails_cleanly(tmp_path, capsys):
    log = shared_log("sitl", "px4sih_default_triangle.ulg")
    assert main(["identify", "motor", str(log), "--out", str(tmp_path / "m.yaml")]) == 2
    assert "esc_rpm" in capsys.readouterr().err
    assert not (tmp_path / "m.yaml").exists()
