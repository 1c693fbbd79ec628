"""The prove suite on physics we did not write: PX4 SIH flights (real firmware) and RotorPy flights.

- px4sih: the truth of every ../shared SIH flight maps onto our effect vocabulary as the manifest says, and the
  no-effect flights are scored with zero findings (runs, never skips, under CI=true: conftest.missing_shared).
- rotorpy: the nominal params file is RotorPy's Crazyflie; a RotorPy no-effect flight, logged as a PX4 ULog,
  has a small equation-error residual with that nominal (and a large one with a wrong nominal); a RotorPy
  flight with 20 % more mass is found as mass/thrust within 10 % (slow).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import shared_log

from twin_nodes.prove import scoring
from twin_nodes.prove import sih as prove_sih
from twin_nodes.prove.scoring import DragContext, Truth, compare, findings, score, score_flight
from twin_nodes.twin.simflight import Hidden
from twin_nodes.vehicle.params import load_params, shipped

ROOT = Path(__file__).resolve().parents[1]
EFFECT_IDS = [f"e0{i}" for i in range(1, 9)]


# ---------------------------------------------------------------- scoring rules (no data needed)


def _res(*effects):
    return {"effects": [dict(e) for e in effects], "elapsed_s": 1.0}


def test_findings_use_verdicts_confirmed_before_likely_and_fall_back_to_accepted():
    res = _res({"name": "inertia", "verdict": "likely", "params": {}},
               {"name": "mass", "verdict": "confirmed", "params": {}},
               {"name": "wind", "verdict": "rejected", "accepted": True, "params": {}})
    assert [e["name"] for e in findings(res)] == ["mass", "inertia"]
    old = _res({"name": "mass", "accepted": True, "params": {}}, {"name": "wind", "accepted": False, "params": {}})
    assert [e["name"] for e in findings(old)] == ["mass"]


def test_mass_and_thrust_coefficient_are_one_class_compared_as_thrust_per_mass():
    vp = shipped("px4_sih_quadx")
    t = Truth(Hidden("mass", {"mass": 1.2}))
    err, text = compare(t, "thrust_coefficient", {"kt_scale": 1 / 1.2 * 1.05}, vp)
    assert err == pytest.approx(0.05, abs=1e-9) and "mass" in text
    err, _ = compare(Truth(Hidden("thrust_coefficient", {"kt_scale": 0.9})), "mass", {"mass": 1 / 0.9}, vp)
    assert err == pytest.approx(0.0, abs=1e-12)
    assert compare(t, "yaw_moment", {"km": 0.03}, vp)[0] == math.inf


def test_a_co_flown_effect_is_scored_in_the_mass_or_thrust_reading_the_findings_chose():
    """RotorPy r070: thrust coefficient 0.87 with the yaw factor 1.5 (km 0.0345 in our torque per thrust) found as
    mass 1.15 beside a yaw moment: the twin kept its thrust, so its km reads the real torque per the model's thrust,
    0.0345 x 0.87 = 0.030, and an inertia x1.15; a true mass found as a thrust coefficient reads them the other way
    (x m / m0).  Without a swap nothing is translated."""
    from twin_nodes.prove.grid_prove import score_grid_flight

    vp = shipped("px4_sih_quadx")
    kt = Truth(Hidden("thrust_coefficient", {"kt_scale": 0.87}))
    yaw = Truth(Hidden("yaw_moment", {"km": 0.0345}))
    res = _res({"name": "mass", "verdict": "confirmed", "params": {"mass": vp.mass_kg / 0.87}},
               {"name": "yaw_moment", "verdict": "confirmed", "params": {"km": 0.0345 * 0.87}})
    row = score_grid_flight("r070", [kt, yaw], res, vp)
    assert row["named"] == ["thrust_coefficient", "yaw_moment"] and row["passed"]
    assert row["param_errors"]["yaw_moment"] == pytest.approx(0.0, abs=1e-12)
    # the same km found beside a thrust-coefficient finding is 13 % off (no swap, no translation)
    res2 = _res({"name": "thrust_coefficient", "verdict": "confirmed", "params": {"kt_scale": 0.87}},
                {"name": "yaw_moment", "verdict": "confirmed", "params": {"km": 0.0345 * 0.87}})
    row2 = score_grid_flight("r070", [kt, yaw], res2, vp)
    assert row2["param_errors"]["yaw_moment"] == pytest.approx(0.13, abs=1e-9) and not row2["passed"]
    # a true mass 1.2 found as kt_scale 1/1.2 beside an inertia: the inertia reads / 1.2
    i0 = vp.inertia
    ine = Truth(Hidden("inertia", {"ixx": 1.3 * i0[0, 0], "iyy": 1.3 * i0[1, 1], "izz": i0[2, 2]}))
    mass = Truth(Hidden("mass", {"mass": 1.2 * vp.mass_kg}))
    res3 = _res({"name": "thrust_coefficient", "verdict": "confirmed", "params": {"kt_scale": 1 / 1.2}},
                {"name": "inertia", "verdict": "likely",
                 "params": {"ixx": 1.3 / 1.2 * i0[0, 0], "iyy": 1.3 / 1.2 * i0[1, 1], "izz": i0[2, 2] / 1.2}})
    row3 = score_grid_flight("x", [mass, ine], res3, vp)
    assert row3["param_errors"]["inertia"] == pytest.approx(0.0, abs=1e-9) and row3["passed"]
    assert scoring.in_reading(ine, 1.0) is ine


def test_a_com_offset_reads_as_itself_in_a_mass_or_thrust_reading():
    """RotorPy o034: mass x1.15 with a CoM offset (3.79, -0.79) mm, found as kt_scale 0.8698 beside a CoM offset
    (3.789, -0.791) mm. The offset only moves the rotors' levers (``core.pack``: r_i - d), so the hover trim the
    flight shows (no moment about the CoM) puts the same d under any common thrust scale: the thrusts that
    trim d at the true mass trim it at the model's mass and kt_scale 1/1.15 too. Scored as itself: 0.0 %, not
    the 13.0 % of reading it x1.15 (4.36, -0.91 mm)."""
    from twin_nodes.physics.core import pack, rotor_wrench
    from twin_nodes.prove.grid_prove import score_grid_flight

    vp = shipped("rotorpy_crazyflie")
    d = (0.00379, -0.00079, 0.0)
    P = pack(vp, d)
    n = vp.rotors.count
    x, y = P[31:31 + n], P[31 + n:31 + 2 * n]
    # hover trim at the true mass (1.15 m0): total thrust = weight, no roll/pitch moment about the CoM
    A = np.vstack([np.ones(n), y, -x, [1.0, -1.0, 1.0, -1.0][:n]])
    T_true = np.linalg.lstsq(A, [1.15 * vp.mass_kg * 9.81, 0.0, 0.0, 0.0], rcond=None)[0]
    for scale in (1.0, 1 / 1.15):   # the same commands in the mass reading and in the thrust reading
        Fb, Mb = np.zeros(3), np.zeros(3)
        rotor_wrench(P, T_true * scale, np.zeros(n), Fb, Mb)
        assert Mb[:2] == pytest.approx([0.0, 0.0], abs=1e-12)
    # the trim's thrusts read the offset back as sum T_i r_i / sum T_i, whatever scales them
    r_x = np.asarray(vp.rotors.x_flu_m)
    assert float(np.sum(T_true * r_x) / np.sum(T_true)) == pytest.approx(0.00379, rel=1e-9)
    mass = Truth(Hidden("mass", {"mass": 1.15 * vp.mass_kg}))
    com = Truth(Hidden("com_offset", {"dx": 0.00379, "dy": -0.00079}))
    res = _res({"name": "thrust_coefficient", "verdict": "confirmed", "params": {"kt_scale": 0.8698}},
               {"name": "com_offset", "verdict": "confirmed", "params": {"dx": 0.003789, "dy": -0.000791}})
    row = score_grid_flight("o034", [mass, com], res, vp)
    assert row["param_errors"]["com_offset"] == pytest.approx(3.65e-4, rel=0.01) and row["passed"]
    assert scoring.in_reading(com, 1.15) is com


def test_a_wind_and_a_com_offset_are_scored_as_vectors():
    vp = shipped("px4_sih_quadx")
    # a 3.5 m/s wind 6.4 degrees off the y axis, found 0.26 m/s off: 7.4 % of its speed, although its small x
    # component is 57 % off
    t = Truth(Hidden("wind", {"vx": 0.39, "vy": 3.48, "gust_std": 0.35}))
    err, text = compare(t, "wind", {"vx": 0.167, "vy": 3.61, "gust_std": 0.0}, vp)
    assert err == pytest.approx(math.hypot(0.223, 0.13) / math.hypot(0.39, 3.48), rel=1e-9)
    assert err < 0.10 and "|error|/|truth|" in text
    # the gust level is reported, not scored; a missing component is no finding of the vector
    assert compare(t, "wind", {"vx": 0.39, "vy": 3.48, "gust_std": 3.0}, vp)[0] == pytest.approx(0.0, abs=1e-12)
    assert compare(t, "wind", {"vx": 0.39}, vp)[0] == math.inf
    # a CoM offset: |(3, 4) mm off| over |(30, 40) mm| = 10 %
    c = Truth(Hidden("com_offset", {"dx": 0.03, "dy": 0.04}))
    assert compare(c, "com_offset", {"dx": 0.033, "dy": 0.044}, vp)[0] == pytest.approx(0.1, rel=1e-9)
    # other effects keep the largest relative error over their parameters
    i = Truth(Hidden("inertia", {"ixx": 0.025, "iyy": 0.03, "izz": 0.03}))
    assert compare(i, "inertia", {"ixx": 0.0275, "iyy": 0.03, "izz": 0.03}, vp)[0] == pytest.approx(0.1, rel=1e-9)


def test_drag_laws_are_one_class_compared_by_the_work_they_do_on_the_flight():
    vp = shipped("px4_sih_quadx")  # nominal linear_drag 1.0
    rng = np.random.default_rng(0)
    v = rng.normal(0, 3, (500, 3))
    drag = DragContext(v, np.full(500, 2800.0))
    truth = Truth(Hidden("linear_drag", {"k_n_s_m": 1.8}))
    # a rotor drag that does exactly the missing 0.8 N/(m/s) of work
    vv = np.sum(v ** 2)
    k_d = 0.8 * vv / (2800.0 * np.sum(v[:, :2] ** 2))
    err, text = compare(truth, "rotor_drag", {"k_d": k_d}, vp, drag)
    assert err == pytest.approx(0.0, abs=1e-9) and "k_eq" in text
    err, _ = compare(truth, "body_drag", {"c_dx": 0.0, "c_dy": 0.0, "c_dz": 0.0}, vp, drag)
    assert err == pytest.approx(0.8 / 1.8, rel=1e-9)  # nothing found beyond the nominal 1.0


def test_score_rules_no_effect_and_effect_rows():
    vp = shipped("px4_sih_quadx")
    none_row = score_flight("n", Truth(Hidden("none", {})), _res({"name": "mass", "verdict": "likely",
                                                                    "params": {"mass": 1.1}}), vp)
    assert not none_row["passed"] and none_row["n_findings"] == 1
    ok = score_flight("m", Truth(Hidden("mass", {"mass": 1.2})), _res(
        {"name": "mass", "verdict": "confirmed", "params": {"mass": 1.15}, "heldout_improvement": 0.8,
         "heldout_before": 0.1, "heldout_after": 0.02}), vp)
    assert ok["passed"] and ok["param_error"] == pytest.approx(0.05 / 1.2)
    low_cut = score_flight("m", Truth(Hidden("mass", {"mass": 1.2})), _res(
        {"name": "mass", "verdict": "confirmed", "params": {"mass": 1.2}, "heldout_improvement": 0.3,
         "heldout_before": 0.1, "heldout_after": 0.07}), vp)
    assert not low_cut["passed"]
    s = score([none_row, ok, low_cut], "x")
    assert (s["n_right_top"], s["false_accepts_on_no_effect"], s["n_passed"]) == (2, 1, 1)
    table = scoring.format_table(s)
    assert "mass (confirmed)" in table and table.splitlines()[-1].startswith("x: right effect on top 2/2")

    assert scoring.breakdown(s, "logging") == []  # rows without the key: no breakdown
    # per logging profile and per change, the same four numbers (px4sih rows carry both keys)
    none_row.update(logging="default", sih_change="none")
    ok.update(logging="highrate", sih_change="SIH_MASS")
    low_cut.update(logging="default", sih_change="SIH_MASS")
    lines = scoring.format_table(score([none_row, ok, low_cut], "px4sih")).splitlines()
    assert lines[-4].startswith("px4sih [logging default]: right effect on top 1/1 (100 %); findings on no-effect "
                                "flights 1/1; params within 10 % 1/1; held-out cut >= 50 % 0/1; flights passing "
                                "every rule 0/2")
    assert lines[-3].startswith("px4sih [logging highrate]: right effect on top 1/1") and lines[-3].endswith("1/1")
    assert lines[-2].startswith("px4sih [sih_change SIH_MASS]: right effect on top 2/2")
    assert lines[-1].startswith("px4sih [sih_change none]: right effect on top 0/0")


def test_a_true_effect_named_only_as_the_top_findings_alternative_is_shown_not_scored():
    """SIH_T_TAU 0.05 -> 0.12 s on a 50 Hz log: the delay is named, the lag is its not-told-apart
    alternative.  The row stays wrong (the issue's rule), the summary says how often this happens."""
    vp = shipped("px4_sih_quadx")
    truth = Truth(Hidden("motor_time_constant", {"tau_up": 0.12, "tau_down": 0.12}))
    top = {"name": "actuator_delay", "verdict": "confirmed", "params": {"delay": 0.066},
           "heldout_improvement": 0.3, "heldout_before": 1.0, "heldout_after": 0.7,
           "alternatives": [{"name": "motor_time_constant", "params": {"tau_up": 0.13, "tau_down": 0.11},
                             "cv_improvement": 0.2}]}
    row = score_flight("t", truth, _res(top), vp)
    assert not row["right_class"] and row["true_is_alternative"] and not row["passed"]
    alone = score_flight("t", truth, _res(dict(top, alternatives=[])), vp)
    assert not alone["true_is_alternative"]
    s = score([row, alone], "x")
    assert s["n_right_top"] == 0 and s["n_true_is_alternative"] == 1
    assert scoring.summary_line(s).endswith("(not scored: on 1 more the true effect is the top finding's "
                                          "not-told-apart alternative)")
    assert "not scored" not in scoring.summary_line(score([alone], "x"))


# ---------------------------------------------------------------- px4sih


def _sih_flights() -> dict:
    fl = {f["flight"]: f for f in prove_sih.flights()}
    for name in EFFECT_IDS:
        if name not in fl:
            shared_log("sitl_effects", f"{name}/flight.ulg")  # skips, or fails under CI=true
    return fl


def test_px4sih_truth_maps_onto_our_vocabulary_as_the_manifest_says():
    fl = _sih_flights()
    vp = load_params(prove_sih.NOMINAL)
    manifest = yaml.safe_load((ROOT / "missions" / "sih_effects" / "manifest.yaml").read_text())
    expected = {"e01": ("mass", {"mass": 1.2}), "e02": ("thrust_coefficient", {"kt_scale": 0.9}),
                "e03": ("yaw_moment", {"km": 0.028}),
                "e04": ("motor_time_constant", {"tau_up": 0.09, "tau_down": 0.09}),
                "e05": ("inertia", {"ixx": 0.0325, "iyy": 0.0325, "izz": 0.030}),
                "e06": ("linear_drag", {"k_n_s_m": 1.8}), "e07": ("none", {}), "e08": ("none", {})}
    for name, (eff, params) in expected.items():
        f = fl[name]
        tj = f["truth_json"]
        t = prove_sih.map_truth(tj, vp)
        assert t.hidden.name == eff, name
        assert t.hidden.params == pytest.approx(params, rel=1e-6), name
        # the same numbers truth.json states in its own effect names
        own = tj["effects"][0]
        for k, v in own["params"].items():
            if k in t.hidden.params:
                assert t.hidden.params[k] == pytest.approx(v, rel=1e-6), (name, k)
        if own["name"] == "body_drag":  # SIH_KDV: truth.json's linear body drag is our linear_drag
            assert own["params"]["c_dx"] == pytest.approx(t.hidden.params["k_n_s_m"])
        # the manifest describes the same flight
        m = manifest["flights"][name]
        assert m["mission"] == tj["mission"]
        assert {k: list(map(float, v)) for k, v in m["sih"].items()} == \
               {k: list(map(float, v)) for k, v in tj["sih_changes"].items()}
        mt = m["truth"]
        assert (mt == "none") if eff == "none" else (mt == {eff: pytest.approx(params, rel=1e-6)})
    assert {"px4sih_default_triangle", "px4sih_default_grid"} <= set(fl)
    assert manifest["px4"]["commit"] == "02e73e3b6f4826a376d0805ee12e30b7538ada99"


def test_every_manifest_flight_states_the_truth_its_sih_change_maps_to():
    """Our own flights (e09.., h.., the balanced grid g..) are declared in the manifest before they are flown:
    the truth written beside each SIH change is what prove_sih.map_truth makes of that change."""
    vp = load_params(prove_sih.NOMINAL)
    manifest = yaml.safe_load((ROOT / "missions" / "sih_effects" / "manifest.yaml").read_text())
    flights = manifest["flights"]
    assert {f"g{i:02d}" for i in range(1, 37)} <= set(flights)
    for name, m in flights.items():
        t = prove_sih.map_truth({"sih_changes": m["sih"]}, vp)
        if m["truth"] == "none":
            assert t.hidden.name == "none", name
            continue
        (eff, params), = m["truth"].items()
        assert t.hidden.name == eff, name
        assert t.hidden.params == pytest.approx(params, rel=1e-6), name
        assert m["mission"] in manifest["missions"], name
        assert m.get("logging", "default") in ("default", *manifest["px4"]["logging"].get("profiles", {})), name


@pytest.mark.parametrize("name", ["e07", "e08"])
def test_px4sih_no_effect_flight_scores_zero_findings(name, tmp_path):
    """Real PX4 firmware, nominal SIH vehicle, missions M3/M4: no confirmed or likely finding."""
    fl = _sih_flights()
    row = prove_sih.run_one((fl[name], str(tmp_path)))
    assert row["true_effect"] == "none"
    assert row["n_findings"] == 0 and row["passed"], row["findings"]
    res = json.loads((tmp_path / f"{name}.json").read_text())
    assert res["effects"], "discover wrote its candidates"


def test_px4sih_without_shared_folder_is_a_one_line_error(tmp_path):
    from twin_nodes.base.errors import TwinError

    with pytest.raises(TwinError, match="px4sih"):
        prove_sih.run_suite(tmp_path / "o", shared=tmp_path / "nothing", progress=False)


# ---------------------------------------------------------------- rotorpy

from twin_nodes.prove import rotorpy_flights as prp  # noqa: E402  (imports rotorpy lazily)


@pytest.fixture(autouse=True)
def _rotorpy_installed(request):
    if request.node.name.startswith("test_rotorpy"):
        pytest.importorskip("rotorpy")  # a dev dependency (pyproject [dev])


def test_rotorpy_nominal_params_file_is_rotorpys_crazyflie():
    qp = prp.rotorpy_params("crazyflie")
    vp = prp.nominal_params(qp)
    shipped_vp = load_params(ROOT / "params" / "rotorpy_crazyflie.yaml")
    assert shipped_vp.to_ros_dict() == vp.to_ros_dict()
    assert vp.rotors.kt_n_s2_rad2 == qp["k_eta"] and vp.rotors.km_m == pytest.approx(qp["k_m"] / qp["k_eta"])
    assert vp.hover_omega_rad_s == pytest.approx(np.sqrt(qp["mass"] * 9.81 / (4 * qp["k_eta"])))
    # yaw moment per rotor: RotorPy +dir*k_m*w^2 about body +z; ours -direction*km*T
    from twin_nodes.vehicle.geometry import allocation_matrix
    A = np.linalg.pinv(allocation_matrix(vp))  # rows: thrust, Mx, My, Mz per unit rotor thrust
    assert np.allclose(A[3], qp["rotor_directions"] * qp["k_m"] / qp["k_eta"])
    pos = np.array(list(qp["rotor_pos"].values()))
    assert np.allclose(A[1], pos[:, 1]) and np.allclose(A[2], -pos[:, 0])


@pytest.fixture(scope="module")
def rp_none(tmp_path_factory):
    """A short RotorPy no-effect flight (mission RP0), written as a PX4 ULog."""
    d = tmp_path_factory.mktemp("rp")
    case = prp.Case((), None, "RP0", 5, "crazyflie", "none")
    rec, vp = prp.fly(case)
    path = d / "rp0.ulg"
    prp.write_record(path, rec, vp, case.seed)
    return path, rec, vp


def test_rotorpy_flight_converts_to_a_ulog_in_our_frames(rp_none):
    from twin_nodes.base import frames
    from twin_nodes.logs.ulog_io import read_ulog

    path, rec, vp = rp_none
    log = read_ulog(path)
    t0 = 0.0  # the log's time axis starts at its first sample, the flight's t = 0
    att = log.require("attitude_q")
    k = np.searchsorted(rec.t, att.t_s - t0).clip(0, len(rec.t) - 1)
    ang = frames.quat_angle_between(att.values, rec.x[k, 6:10])
    assert np.percentile(ang, 95) < 0.02  # estimator-grade noise only, no frame error
    vel = log.require("velocity_enu")
    k = np.searchsorted(rec.t, vel.t_s - t0).clip(0, len(rec.t) - 1)
    assert np.sqrt(np.mean((vel.values - rec.x[k, 3:6]) ** 2)) < 0.1
    assert np.ptp(rec.x[:, 0]) > 3.0 and rec.x[:, 2].max() > 2.0  # it flew the mission


def test_rotorpy_no_effect_flight_has_a_small_equation_error_with_the_nominal(rp_none):
    from twin_nodes.discovery.residuals import modes, prepare, residual_channels
    from twin_nodes.logs.ulog_io import read_ulog

    path, _, vp = rp_none
    data = prepare(read_ulog(path), vp)
    R = residual_channels(data, vp, vp)[data.valid]
    M, names = modes(R, vp)
    rms = dict(zip(names, np.sqrt(np.mean(M ** 2, axis=0))))
    # fraction of full motor output; our own generator's no-effect flights sit at about 0.005
    assert rms["throttle"] < 0.004, rms
    assert max(rms["roll"], rms["pitch"], rms["yaw"]) < 0.002, rms
    assert max(rms["force_x"], rms["force_y"]) < 0.003, rms
    # and the same check is sensitive: a nominal 20 % too light leaves a large throttle residual
    wrong = vp.replace(mass_kg=vp.mass_kg / 1.2)
    Rw = residual_channels(data, wrong, wrong)[data.valid]
    Mw, _ = modes(Rw, wrong)
    assert np.sqrt(np.mean(Mw[:, 0] ** 2)) > 10 * rms["throttle"]


@pytest.mark.slow
def test_rotorpy_mass_plus_20_percent_is_found_as_mass_or_thrust_within_10_percent(tmp_path):
    case = next(c for c in prp.suite("full") if c.label == "mass")
    row = prp.run_one((case, str(tmp_path), str(tmp_path / "cache")))
    assert row["top_finding"] in ("mass", "thrust_coefficient"), row["findings"]
    assert row["top_verdict"] in ("confirmed", "likely")
    assert row["param_error"] is not None and row["param_error"] <= 0.10, row["param_text"]
    assert row["heldout_improvement"] >= 0.5, row


def test_rotorpy_body_wrench_equals_our_rotors_plus_rotor_drag_at_the_hubs():
    """RotorPy's own compute_body_wrench (rotor drag at each hub, v + w x r_i) against our terms, on
    a moving, rotating state with unequal rotor speeds: forces and all three moments."""
    from rotorpy.vehicles.multirotor import Multirotor as RPMultirotor

    from twin_nodes.physics.model import Multirotor

    qp = prp.rotorpy_params("crazyflie")
    qp.update(prp.UNMODELLED)
    qp.update({"c_Dx": 0.0, "c_Dy": 0.0, "c_Dz": 0.0})  # parasitic drag: our body_drag, not this test
    rp = RPMultirotor(qp, control_abstraction="cmd_motor_speeds", aero=True)
    vp = prp.nominal_params(qp)
    assert dict(vp.effects)["rotor_drag"] == (("k_d", qp["k_d"]),)
    m = Multirotor(vp)
    rates = np.array([1.5, -2.0, 3.0])
    speeds = np.array([2100.0, 2300.0, 1900.0, 2250.0])
    air = np.array([1.2, -0.7, 0.4])  # body = world at identity attitude, no wind
    f_rp, m_rp = rp.compute_body_wrench(rates, speeds, air)
    x = m.initial_state(position_enu=(0.0, 0.0, 5.0), velocity_enu=air, rates_flu=rates, rotor_state=speeds)
    terms = m.wrench_terms(x)
    assert set(terms) == {"rotors", "rotor_drag"}
    f = terms["rotors"][0][0] + terms["rotor_drag"][0][0]
    mom = terms["rotors"][1][0] + terms["rotor_drag"][1][0]
    np.testing.assert_allclose(f, f_rp, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(mom, m_rp, rtol=1e-9, atol=1e-13)
    # the old law (a force at the CoM, no moment) would miss by the hub moment, far above the tolerance
    assert abs(terms["rotor_drag"][1][0][2]) > 1e-5  # (its roll/pitch parts are zero: hubs at z = 0)


def test_rotorpy_parasitic_drag_equals_our_body_drag_in_its_norm_form():
    """RotorPy's compute_body_wrench with its parasitic drag -|v| C v (its px4_sihsim_quadx: c_D 0.01, no rotor
    drag) against our rotors plus body drag with norm 1, on an airspeed off every body axis; the per-axis form
    would miss the force by |v| / |v_i| on each component."""
    from rotorpy.vehicles.multirotor import Multirotor as RPMultirotor

    from twin_nodes.physics.model import Multirotor

    qp = prp.rotorpy_params("px4_sihsim_quadx")
    qp.update(prp.UNMODELLED)
    rp = RPMultirotor(qp, control_abstraction="cmd_motor_speeds", aero=True)
    vp = prp.nominal_params(qp, "rotorpy_px4_sihsim_quadx")
    assert dict(vp.effects)["body_drag"] == (("c_dx", 0.01), ("c_dy", 0.01), ("c_dz", 0.01), ("norm", 1.0))
    m = Multirotor(vp)
    rates = np.array([0.5, -0.3, 0.8])
    speeds = np.full(4, 0.6 * qp["rotor_speed_max"])
    air = np.array([4.0, -2.5, 0.6])
    f_rp, m_rp = rp.compute_body_wrench(rates, speeds, air)
    x = m.initial_state(position_enu=(0.0, 0.0, 5.0), velocity_enu=air, rates_flu=rates, rotor_state=speeds)
    terms = m.wrench_terms(x)
    f = sum(t[0][0] for t in terms.values())
    np.testing.assert_allclose(f, f_rp, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(terms["body_drag"][0][0], -0.01 * np.linalg.norm(air) * air, rtol=1e-12)
