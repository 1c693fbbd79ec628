"""Stage 12 (``discovery/stages/damping_pair.py``): an angular damping confirmed alone on the yaw axis, read against
a rotor drag's hub damping (a flight without airspeed) and against a yaw moment and a yaw inertia changed together;
roll and pitch choose, else the pair is reported."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from twin_nodes.discovery.stages import damping_pair as D
from twin_nodes.physics.model import Multirotor
from twin_nodes.prove import grid_prove
from twin_nodes.prove import rotorpy_flights as rf
from twin_nodes.vehicle.params import shipped


@pytest.fixture(scope="module")
def sih():
    return shipped("px4_sih_quadx")        # km 0.02, Ixx = Iyy 0.025, Izz 0.03, k_d 0.025 (PX4 SIH's defaults)


@pytest.fixture(scope="module")
def crazyflie():
    return rf.nominal_params(rf.rotorpy_params("crazyflie"), "rotorpy_crazyflie")   # rotor drag k_d 1.025e-6


def test_the_yaw_pair_reading_of_a_damping_closed_form(sih):
    # f017 (SIH_Q_MAX and SIH_IZZ both x1.3, M1) as reported: damping 0.019386 alone -> km and Izz x1.2896
    cur = sih.with_effect("angular_damping", k_nm_s_rad=0.019386)
    alt, s = D.yaw_scale_reading(cur, sih)
    assert s == pytest.approx(0.025 / 0.019386)
    eff = alt.effect_dict
    assert eff["yaw_moment"]["km"] == pytest.approx(0.025792, rel=1e-4)                       # truth 0.026
    assert eff["inertia"] == pytest.approx({"ixx": 0.025, "iyy": 0.025, "izz": 0.038687}, rel=1e-4)   # 0.039
    assert eff["angular_damping"]["k_nm_s_rad"] == 0.025
    # on the yaw row the two readings are one: km/Izz and k_d/Izz of the other reading are the damping's
    assert eff["yaw_moment"]["km"] / eff["inertia"]["izz"] == pytest.approx(0.02 / 0.03, rel=1e-12)
    assert 0.025 / eff["inertia"]["izz"] == pytest.approx(0.019386 / 0.03, rel=1e-12)
    # none: a yaw moment or inertia of its own (stage 10's), a model without a damping (RotorPy), a 2 % change
    assert D.yaw_scale_reading(cur.with_effect("yaw_moment", km=0.026), sih) is None
    undamped = sih.replace(effects=tuple(e for e in sih.effects if e[0] != "angular_damping"))
    assert D.yaw_scale_reading(undamped.with_effect("angular_damping", k_nm_s_rad=1e-5), undamped) is None
    assert D.yaw_scale_reading(sih.with_effect("angular_damping", k_nm_s_rad=0.0245), sih) is None


def test_in_a_yaw_turn_in_place_the_hub_damping_and_the_angular_damping_are_one_column(crazyflie):
    """Hover, yawing at r: a rotor drag change dk_d moves only the yaw moment, by -dk_d r sum|omega_i| r_i^2, the
    angular damping k by -k r: the same column (e002: 1.3605e-5 N m s/rad is dk_d 1.028e-6).  Translating, the
    rotor drag also pushes -dk_d sum|omega| v, which a damping never does."""
    m0 = Multirotor(crazyflie)
    x = m0.initial_state(position_enu=(0.0, 0.0, 1.5), rates_flu=(0.0, 0.0, 0.8), rotor_state="hover")
    omega = m0.rotor_speeds(x)
    arm2 = np.asarray(crazyflie.rotors.x_flu_m) ** 2 + np.asarray(crazyflie.rotors.y_flu_m) ** 2
    dkd = 1.028e-6
    k_eq = dkd * float(np.sum(omega * arm2))
    assert k_eq == pytest.approx(1.3605e-5, rel=0.01)

    def wrench(vp, state):
        f, mom = Multirotor(vp).wrench_terms(state)["rotor_drag"]
        return np.concatenate([f[0], mom[0]])
    kd0 = crazyflie.effect_dict["rotor_drag"]["k_d"]
    drag = wrench(crazyflie.with_effect("rotor_drag", k_d=kd0 + dkd), x) - wrench(crazyflie, x)
    np.testing.assert_allclose(drag, [0, 0, 0, 0, 0, -k_eq * 0.8], atol=1e-15, rtol=1e-9)
    moving = x.copy()
    moving[3:6] = (3.0, 0.0, 0.0)
    drag = wrench(crazyflie.with_effect("rotor_drag", k_d=kd0 + dkd), moving) - wrench(crazyflie, moving)
    assert abs(drag[0]) == pytest.approx(dkd * np.sum(omega) * 3.0, rel=1e-6) and abs(drag[0]) > 0.1 * 0.03 * 0.981


def _fake_flight(monkeypatch, nominal, n=2000, seed=1):
    """A hover with yaw as the residual sees it: yaw rate sweeps, sum|omega| r_i^2 constant, the true k_d twice
    the model's, the horizontal velocity the estimate's noise alone (true speed 0), which the drag's force columns
    carry: residual = measured - model, per channel [thr, roll, pitch, yaw, force_x, force_y]."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.02
    wz = 0.8 * np.sign(np.sin(2 * np.pi * t / 8.0))
    v_noise = 0.04 * rng.standard_normal((n, 2))
    s_sum, omega_sum, mass, kd_true = 7156.0 * 1.849e-3, 7156.0, 0.03, 2.053e-6

    def residual_channels(data, vp, nom):
        eff = vp.effect_dict
        kd = float((eff.get("rotor_drag") or {}).get("k_d", 0.0))
        k = float((eff.get("angular_damping") or {}).get("k_nm_s_rad", 0.0))
        r = np.zeros((n, 6))
        r[:, 3] = -(kd_true - kd) * s_sum * wz + k * wz
        r[:, 4:] = kd * omega_sum * v_noise / mass * 1e-3      # the model's drag on noise the IMU never saw
        return r
    monkeypatch.setattr(D, "residual_channels", residual_channels)
    monkeypatch.setattr(D, "modes", lambda R, vp: (R, None))
    return SimpleNamespace(valid=np.ones(n, bool)), np.arange(n) < 0.65 * n, residual_channels


def test_the_hub_reading_is_fitted_on_the_yaw_mode_alone(monkeypatch, crazyflie):
    data, fit, rc = _fake_flight(monkeypatch, crazyflie)
    cur = crazyflie.with_effect("angular_damping", k_nm_s_rad=1.3605e-5)
    alt = D.hub_reading(data, crazyflie, fit, cur)
    assert "angular_damping" not in alt.effect_dict                      # RotorPy's model has none: removed
    assert alt.effect_dict["rotor_drag"]["k_d"] == pytest.approx(2.053e-6, rel=1e-9)
    # every channel at once reads far less: the force columns' noise pulls k_d down (e002: x1.45, then x0.2)
    grid = np.linspace(0.2, 5.0, 481) * 1.025e-6
    rms = [np.sqrt(np.mean(rc(data, crazyflie.with_effect("rotor_drag", k_d=k), None)[fit] ** 2)) for k in grid]
    assert grid[int(np.argmin(rms))] < 0.8 * 2.053e-6


def _e002(crazyflie, hover=True):
    cur = crazyflie.with_effect("angular_damping", k_nm_s_rad=1.3605e-5)
    return {"accepted": ["angular_damping"], "likely": [], "refit_params": cur.to_ros_dict(),
            "not_excited": [{"effects": ["rotor_drag (force)", "body_drag (horizontal)"]}] if hover else [],
            "effects": [{"name": "angular_damping", "verdict": "confirmed", "params": {"k_nm_s_rad": 1.3605e-5},
                         "heldout_channel": "yaw", "verdict_note": ""},
                        {"name": "rotor_drag", "verdict": "rejected", "params": {"k_d": 2.05e-7}}]}


def _apply(monkeypatch, result, nominal, test, data=None, fit=None):
    monkeypatch.setattr(D, "roll_pitch_test", lambda *a: dict(test))
    flight = SimpleNamespace(nominal=nominal, data=data, fit_mask=fit, held_mask=None)
    return D.apply(result, flight)


def test_a_hover_damping_is_the_rotor_drag_where_roll_and_pitch_reject_the_damping(monkeypatch, crazyflie):
    """e002 (Crazyflie, rotor drag k_d 2.053e-6, hover with yaw): roll/pitch t 3.6 over 99 blocks, held-out 0.8 %
    for the reading without a roll/pitch damping -> rotor drag k_d 2.054e-6 (scored 0.0 %)."""
    data, fit, _ = _fake_flight(monkeypatch, crazyflie)
    result = _e002(crazyflie)
    alt = _apply(monkeypatch, result, crazyflie, {"t": 3.6, "blocks": 99, "heldout_cut": 0.0084}, data, fit)
    assert alt is not None and result["accepted"] == ["rotor_drag"]
    e = result["effects"][0]
    assert e["name"] == "rotor_drag" and e["params"]["k_d"] == pytest.approx(2.053e-6, rel=1e-6)
    assert e["read_as"]["was"] == "angular_damping" and "t=3.6" in e["verdict_note"]
    assert "angular_damping" not in result["refit_params"]["effects"]["enabled"]
    assert result["damping_pair"][0]["choice"] == "switch"


def test_neither_chosen_is_the_pair_with_fast_legs_and_a_translating_flight_is_not_read(monkeypatch, crazyflie):
    data, fit, _ = _fake_flight(monkeypatch, crazyflie)
    result = _e002(crazyflie)
    assert _apply(monkeypatch, result, crazyflie, {"t": 1.2, "blocks": 99, "heldout_cut": 0.001}, data, fit) is None
    e = result["effects"][0]
    assert e["name"] == "angular_damping" and result["accepted"] == ["angular_damping"]
    pair = e["not_told_apart"]
    assert pair["with"]["name"] == "rotor_drag" and pair["with"]["params"]["k_d"] == pytest.approx(2.053e-6, rel=1e-6)
    assert pair["manoeuvre"] == "fast_legs" and pair["plan_flyable"]
    assert [n for n, _ in grid_prove._members(e)] == ["angular_damping", "rotor_drag"]
    # roll/pitch want the damping: told apart, no pair
    result = _e002(crazyflie)
    _apply(monkeypatch, result, crazyflie, {"t": -3.5, "blocks": 99, "heldout_cut": -0.01}, data, fit)
    assert "not_told_apart" not in result["effects"][0] and result["damping_pair"][0]["choice"] == "kept"
    # a flight with airspeed (the drag's force excited): the rotor drag is judged on its own columns, no reading
    result = _e002(crazyflie, hover=False)
    assert _apply(monkeypatch, result, crazyflie, {"t": 9.0, "blocks": 99, "heldout_cut": 0.5}, data, fit) is None
    assert "damping_pair" not in result and "not_told_apart" not in result["effects"][0]


def _f017(sih):
    cur = sih.with_effect("angular_damping", k_nm_s_rad=0.019386)
    return {"accepted": ["angular_damping"], "likely": [], "refit_params": cur.to_ros_dict(), "not_excited": [],
            "effects": [{"name": "angular_damping", "verdict": "confirmed", "params": {"k_nm_s_rad": 0.019386},
                         "heldout_channel": "yaw", "verdict_note": ""}]}


def test_a_triangle_damping_is_the_yaw_moment_and_inertia_where_roll_and_pitch_say_so(monkeypatch, sih):
    """f017 (SIH_Q_MAX 0.13 and SIH_IZZ 0.039, M1): roll/pitch t 4.34 over 81 blocks, held-out 2.1 % for the model's
    damping -> yaw moment km 0.02579 (0.8 % off 0.026) and inertia Izz 0.03869 (0.8 % off 0.039), both named."""
    result = _f017(sih)
    alt = _apply(monkeypatch, result, sih, {"t": 4.34, "blocks": 81, "heldout_cut": 0.0212})
    assert alt is not None and result["accepted"] == ["yaw_moment", "inertia"]
    names = [(e["name"], e["verdict"]) for e in result["effects"]]
    assert names == [("yaw_moment", "confirmed"), ("inertia", "confirmed")]
    assert result["refit_params"]["effects"]["angular_damping"]["k_nm_s_rad"] == 0.025
    truths = grid_prove._sih_truths({"sih": {"SIH_Q_MAX": [0.1, 0.13], "SIH_IZZ": [0.03, 0.039]}}, sih)
    r = grid_prove.score_grid_flight("f017", truths, result, sih)
    assert r["passed"] and r["n_named"] == 2
    assert r["param_errors"]["yaw_moment"] == pytest.approx(1 - 0.025792 / 0.026, abs=2e-4)
    assert r["param_errors"]["inertia"] == pytest.approx(1 - 0.038687 / 0.039, abs=2e-4)


def test_a_yaw_pair_not_told_apart_names_both_members(monkeypatch, sih):
    result = _f017(sih)
    assert _apply(monkeypatch, result, sih, {"t": 0.4, "blocks": 81, "heldout_cut": 0.001}) is None
    pair = result["effects"][0]["not_told_apart"]
    assert pair["with"]["name"] == "yaw_moment" and pair["also"][0]["name"] == "inertia"
    assert pair["manoeuvre"] == "rate_doublets" and pair["plan_flyable"]
    truths = grid_prove._sih_truths({"sih": {"SIH_Q_MAX": [0.1, 0.13], "SIH_IZZ": [0.03, 0.039]}}, sih)
    r = grid_prove.score_grid_flight("f017", truths, result, sih)
    assert r["n_named"] == 2 and r["passed"] and r["right_by_pair"]
    # a true damping (x2) with roll/pitch silent stays the damping, the pair beside it
    truths = grid_prove._sih_truths({"sih": {"SIH_KDW": [0.025, 0.05]}}, sih)
    res = _f017(sih)
    res["effects"][0]["params"] = {"k_nm_s_rad": 0.0501}
    res["effects"][0]["heldout_improvement"] = 0.86
    r = grid_prove.score_grid_flight("f001", truths, res, sih)
    assert r["param_errors"]["angular_damping"] == pytest.approx(0.002, abs=1e-6)
    # a damping beside a yaw moment is stage 10's; one already naming a rival is left alone
    res = _f017(sih)
    res["accepted"].append("yaw_moment")
    assert _apply(monkeypatch, res, sih, {"t": 9.0, "blocks": 81, "heldout_cut": 0.5}) is None and "damping_pair" not in res
    res = _f017(sih)
    res["effects"][0]["not_told_apart"] = {"with": {"name": "rotor_drag"}}
    assert _apply(monkeypatch, res, sih, {"t": 9.0, "blocks": 81, "heldout_cut": 0.5}) is None


def _p019(sih):
    """PX4 SIH p019 (SIH_Q_MAX 0.1->0.13 and SIH_IZZ 0.03->0.039, M4, 4 ms logging) as main reported it: the damping
    0.019362 confirmed alone on the yaw axis, round 1's alternatives naming a yaw moment km 0.022004 fitted alone
    on the output error (x1.10: the inertia left out, km 15.4 % off the truth)."""
    res = _f017(sih)
    e = res["effects"][0]
    e["params"] = {"k_nm_s_rad": 0.019362}
    res["refit_params"] = sih.with_effect("angular_damping", k_nm_s_rad=0.019362).to_ros_dict()
    e["alternatives"] = [{"name": "yaw_moment", "params": {"km": 0.022004}, "residual": "output"}]
    e["not_told_apart"] = {"with": {"name": "yaw_moment", "params": {"km": 0.022004}}, "manoeuvre": "rate_doublets",
                           "plan_flyable": True}
    return res


def test_a_damping_whose_rival_is_a_yaw_moment_alone_is_read_against_the_whole_yaw_pair(monkeypatch, sih):
    """p019: the yaw moment alone is one member of the damping's other reading; stage 12 reads the whole one,
    km and Izz both x 0.025/0.019362 = x1.2912 (roll/pitch t 0.9: not told apart) -> yaw moment km 0.025824 (0.7 %
    off 0.026) and inertia Izz 0.038735 (0.7 % off 0.039), both named; as main had it, km 15.4 % off, one named."""
    truths = grid_prove._sih_truths({"sih": {"SIH_Q_MAX": [0.1, 0.13], "SIH_IZZ": [0.03, 0.039]}}, sih)
    was = grid_prove.score_grid_flight("p019", truths, _p019(sih), sih)
    assert was["n_named"] == 1 and not was["passed"]
    assert was["param_errors"]["yaw_moment"] == pytest.approx(1 - 0.022004 / 0.026, abs=2e-4)    # 15.4 %
    result = _p019(sih)
    assert _apply(monkeypatch, result, sih, {"t": 0.9, "blocks": 150, "heldout_cut": 0.002}) is None
    pair = result["effects"][0]["not_told_apart"]
    assert pair["with"]["params"]["km"] == pytest.approx(0.02 * 0.025 / 0.019362, rel=1e-9)       # 0.025824
    assert pair["also"][0]["params"]["izz"] == pytest.approx(0.03 * 0.025 / 0.019362, rel=1e-9)   # 0.038735
    assert pair["replaces"] == {"name": "yaw_moment", "params": {"km": 0.022004}}
    assert result["damping_pair"][0]["choice"] == "pair"
    r = grid_prove.score_grid_flight("p019", truths, result, sih)
    assert r["n_named"] == 2 and r["passed"] and r["right_by_pair"]
    assert r["param_errors"]["yaw_moment"] == pytest.approx(1 - 0.025824 / 0.026, abs=2e-4)        # 0.7 %
    assert r["param_errors"]["inertia"] == pytest.approx(1 - 0.038735 / 0.039, abs=2e-4)           # 0.7 %


def test_a_yaw_scale_rival_is_dropped_on_a_switch_and_kept_where_roll_and_pitch_keep_the_damping(monkeypatch, sih):
    result = _p019(sih)
    assert _apply(monkeypatch, result, sih, {"t": 4.0, "blocks": 150, "heldout_cut": 0.02}) is not None
    assert result["accepted"] == ["yaw_moment", "inertia"]
    assert all("not_told_apart" not in e for e in result["effects"])
    # a true damping x4 (b003, l009: the damping 0.1 beside a yaw moment km 0.0057 alone): roll/pitch keep it, the
    # damping stays on top with the rival it had
    result = _p019(sih)
    assert _apply(monkeypatch, result, sih, {"t": -8.0, "blocks": 150, "heldout_cut": -0.3}) is None
    e = result["effects"][0]
    assert e["name"] == "angular_damping" and e["not_told_apart"]["with"]["params"] == {"km": 0.022004}
    assert result["damping_pair"][0]["choice"] == "kept"
    # a rival of another kind (a rotor drag, a mass...) still leaves the damping alone
    for rival in ("rotor_drag", "mass"):
        result = _p019(sih)
        result["effects"][0]["not_told_apart"]["with"] = {"name": rival, "params": {}}
        assert _apply(monkeypatch, result, sih, {"t": 0.9, "blocks": 150, "heldout_cut": 0.0}) is None
        assert "damping_pair" not in result


# --- st19: the yaw pair against a damping decided by the roll/pitch damping reading's measured scatter ------------

#: roll + pitch damping readings ([whole, fold 1, fold 2]) measured on seen PX4 SIH flights (docs/discovery.md,
#: "Nineteenth session (st19)"): each with the stage's two readings' dampings, the log interval and what the
#: block test said
SB016 = dict(reading=[0.0135, 0.013884, 0.015243], k=0.019353, other=0.025, dt=0.02)     # block t -3.30: kept
L016 = dict(reading=[0.02971, 0.03087, 0.03103], k=0.01957, other=0.025, dt=0.02)        # block t +4.13: switch
L009 = dict(reading=[0.10145, 0.10156, 0.10073], k=0.10017, other=0.025, dt=0.02)        # KDW x4
SB001 = dict(reading=[0.050572, 0.050919, 0.050379], k=0.050066, other=0.025, dt=0.004)  # KDW x2, 4 ms
SB013 = dict(reading=[0.035464, 0.038948, 0.026382], k=0.049278, other=0.025, dt=0.02)   # KDW x2 + T_TAU: t +2.51
F017 = dict(reading=[0.02665, 0.02669, 0.02616], k=0.019386, other=0.025, dt=0.004)      # the class at 4 ms: t +4.34
P019 = dict(reading=[0.02529, 0.02557, 0.02573], k=0.019362, other=0.025, dt=0.004)      # the class at 4 ms: t +5.87
J007 = dict(reading=[0.04154, 0.03991, 0.04081], k=0.05004, other=0.025, dt=0.02)        # KDW x2, M2: t -1.6, pair
D012 = dict(reading=[0.030906, 0.033127, 0.026795], k=0.049317, other=0.025, dt=0.02)    # KDW x2 + T_TAU: t +1.6


def _choice(case):
    from twin_nodes.discovery.stages import yaw_pair as Y
    bias, scatter = Y.rp_damping_law(case["dt"])
    return Y.damping_choice(case["k"], case["other"], case["reading"], scatter, 0.025, bias)


def test_the_roll_pitch_damping_law_is_the_measured_table_by_log_interval():
    from twin_nodes.discovery.stages import yaw_pair as Y
    assert Y.rp_damping_law(0.004) == (0.989, 0.106) and Y.rp_damping_law(0.01) == (0.989, 0.106)
    assert Y.rp_damping_law(0.02) == (0.802, 0.369) and Y.rp_damping_law(0.1) == (0.802, 0.369)
    # two scatters of PX4 SIH's 0.025 at 20 ms: 0.01845; a Q_MAX x IZZ x1.3 pair's gap is 0.0056 (23 % of k0)
    c = _choice(SB016)
    assert c["needed"] == pytest.approx(0.01845) and c["gap"] == pytest.approx(0.005647, abs=1e-6)
    assert c["corrected"][0] == pytest.approx(0.0135 / 0.802, abs=1e-6)
    # at 4 ms two scatters are 0.0053: the class's gap (f017 0.005614, p019 0.005638) clears them, by 6 %
    assert _choice(F017)["needed"] == pytest.approx(0.0053) and _choice(F017)["gap"] > _choice(F017)["needed"]


def test_one_truth_gives_one_answer_the_yaw_pair_is_not_told_apart_at_20_ms():
    """sb016 and l016 (the same truth, M6, 20 ms): the block test said kept (wrong) and switch (right); the roll/pitch
    readings 0.0135 and 0.0297 are within two scatters of both readings' 0.0194 / 0.025 gap -> both pairs."""
    assert _choice(SB016)["choice"] == "pair" and _choice(L016)["choice"] == "pair"


def test_the_yaw_pair_is_taken_at_4_ms_where_roll_and_pitch_read_the_model_s_damping():
    """f017 and p019 (the same truth, 4 ms logs): roll/pitch read 0.0267 and 0.0253 (both folds too), nearer SIH's
    0.025 than the damping's 0.0194 -> switch to the yaw moment + inertia, as the block test had it (t +4.3, +5.9)."""
    assert _choice(F017)["choice"] == "switch" and _choice(P019)["choice"] == "switch"


def test_a_true_damping_stays_told_apart_where_its_reading_resolves_it():
    assert _choice(L009)["choice"] == "kept"           # x4 at 20 ms: gap 0.075 >> 0.018
    assert _choice(J007)["choice"] == "kept"           # x2 at 20 ms, reading 0.0415 (20 % low): the block t had a pair
    assert _choice(SB001)["choice"] == "kept"          # x2 at 4 ms: gap 0.025 >> 0.0056
    # x2 at 20 ms beside a motor lag: fold 2 reads 0.0264 (0.0329 with the bias out), nearer 0.025 than 0.049 -> pair
    c = _choice(SB013)
    assert c["gap"] > c["needed"] and c["choice"] == "pair"
    # d012 (x2 + T_TAU, the lag not in the model read): 0.0309 (folds 0.0331 / 0.0268) is nearer 0.025 as read, a
    # wrong switch; with the 20 ms bias out, 0.0385 / 0.0413 / 0.0334 disagree -> pair (the block t +1.6 had a pair)
    assert _choice(D012)["choice"] == "pair"
    from twin_nodes.discovery.stages import yaw_pair as Y
    assert Y.damping_choice(D012["k"], 0.025, D012["reading"], 0.369, 0.025)["choice"] == "switch"
    # the same reading with both folds on the damping's side is kept; a reading on the other side is a switch
    assert _choice({**SB013, "reading": [0.0436, 0.0465, 0.0400]})["choice"] == "kept"
    assert _choice({**SB001, "reading": [0.0251, 0.0262, 0.0244]})["choice"] == "switch"
    # a gap under two scatters is a pair whatever the reading says
    assert _choice({**SB001, "k": 0.0300, "reading": [0.0301, 0.0302, 0.0300]})["choice"] == "pair"


def test_the_roll_pitch_damping_reading_is_the_affine_least_squares_on_both_folds(monkeypatch, sih):
    """roll + pitch modes affine in k (a column c, the truth k_t; fold 1 before t_split2 reads 0.021, fold 2
    after it 0.031): the reading recovers each part's own k to 1e-9."""
    from twin_nodes.discovery.stages import yaw_pair as Y
    t = np.arange(0.0, 100.0, 0.02)
    rng = np.random.default_rng(3)
    c = rng.normal(size=(t.size, 2))
    k_t = np.where(t < 50.0, 0.021, 0.031)
    monkeypatch.setattr(Y, "residual_channels", lambda data, vp, nom: Y.effect_value(vp, "angular_damping",
                                                                                     "k_nm_s_rad"))
    monkeypatch.setattr(Y, "modes", lambda k, nom: (np.column_stack([0 * t, c * (k - k_t)[:, None], 0 * t]),))
    data = SimpleNamespace(t=t, valid=np.ones(t.size, bool))
    cur = sih.with_effect("angular_damping", k_nm_s_rad=0.019)
    whole, f1, f2 = Y.roll_pitch_damping(data, sih, cur, t < 60.0, 40.0)
    assert f1 == pytest.approx((0.021 * 2500 + 0.031 * 500) / 3000, abs=2e-4)   # 50 s at 0.021, 10 s at 0.031
    assert f2 == pytest.approx((0.021 * 500 + 0.031 * 2500) / 3000, abs=2e-4)
    assert whole == pytest.approx(0.026, abs=2e-4)


def _px4_flight(nominal, dt, data=None, fit=None):
    return SimpleNamespace(nominal=nominal, data=data or SimpleNamespace(motor_dt_s=dt), fit_mask=fit,
                           held_mask=None, t_split2=0.0, log_params={"MC_ROLLRATE_P": 0.15})


def test_on_a_px4_log_the_reading_decides_and_the_block_t_does_not(monkeypatch, sih):
    """sb016 as the stage saw it: block t -3.30 (kept, neither truth named); with its roll/pitch reading the yaw pair
    is reported not told apart, and prove names both (km 0.6 %, Izz 0.6 % off)."""
    from twin_nodes.discovery.stages import yaw_pair as Y
    monkeypatch.setattr(D, "roll_pitch_test", lambda *a: {"t": -3.30, "blocks": 156, "heldout_cut": -0.0055})
    monkeypatch.setattr(Y, "roll_pitch_damping", lambda *a: list(SB016["reading"]))
    result = _f017(sih)
    result["effects"][0]["params"] = {"k_nm_s_rad": 0.019353}
    result["refit_params"] = sih.with_effect("angular_damping", k_nm_s_rad=0.019353).to_ros_dict()
    assert D.apply(result, _px4_flight(sih, 0.02)) is None
    note = result["damping_pair"][0]
    assert note["choice"] == "pair" and note["roll_pitch_damping"]["reading"] == SB016["reading"]
    pair = result["effects"][0]["not_told_apart"]
    assert pair["with"]["params"]["km"] == pytest.approx(0.025836, rel=1e-4)
    assert pair["also"][0]["params"]["izz"] == pytest.approx(0.038754, rel=1e-4)
    truths = grid_prove._sih_truths({"sih": {"SIH_Q_MAX": [0.1, 0.13], "SIH_IZZ": [0.03, 0.039]}}, sih)
    r = grid_prove.score_grid_flight("sb016", truths, result, sih)
    assert r["passed"] and r["n_named"] == 2
    # f017, logged every 4 ms, roll/pitch reading 0.02665 (0.02695 with the bias out): switch to km 0.025792 and
    # Izz 0.038687, both named
    monkeypatch.setattr(Y, "roll_pitch_damping", lambda *a: list(F017["reading"]))
    result = _f017(sih)
    assert D.apply(result, _px4_flight(sih, 0.004)) is not None and result["accepted"] == ["yaw_moment", "inertia"]
    assert "0.02695" in result["effects"][0]["verdict_note"]         # 0.02665 / 0.989
    assert result["effects"][0]["params"]["km"] == pytest.approx(0.025792, rel=1e-4)
    r = grid_prove.score_grid_flight("f017", truths, result, sih)
    assert r["passed"] and r["n_named"] == 2 and not r["right_by_pair"]
    # not a PX4 log (our own, RotorPy): the block test decides, as before
    result = _f017(sih)
    flight = _px4_flight(sih, 0.02)
    flight.log_params = {}
    assert D.apply(result, flight) is None and result["damping_pair"][0]["choice"] == "kept"
    assert "roll_pitch_damping" not in result["damping_pair"][0]
