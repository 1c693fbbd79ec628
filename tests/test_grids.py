"""Issue 26: the declared grids, two-effect scoring, and the discovery changes (second-round pruning, the
closed-loop veto's standing and noise, pairs not told apart, wind with drag)."""

from __future__ import annotations

from collections import Counter
from types import SimpleNamespace

import numpy as np
import pytest

from twin_nodes.discovery.stages import closed_loop, selection, verdicts
from twin_nodes.prove import grid_prove, grid_rotorpy, grid_sih
from twin_nodes.prove.scoring import Truth
from twin_nodes.twin.simflight import Hidden
from twin_nodes.vehicle.params import shipped

rotorpy = pytest.importorskip("rotorpy", reason="RotorPy (dev dependency) not installed")


# ------------------------------------------------------------------ the grids as declared


def test_rotorpy_grid_manifest_is_the_declaration():
    declared = grid_rotorpy.declare()
    assert grid_rotorpy.load_grid() == declared          # the committed manifest is what the seed declares
    assert len(declared) >= 80
    strata = Counter(f.stratum for f in declared)
    assert strata["two effects"] >= 20 and strata["none"] == 10
    for e in grid_rotorpy.EFFECTS:                         # every effect at 3 magnitudes
        assert {lv for f in declared for n, lv in f.effects if n == e} == {0, 1, 2}
    assert set(f.mission for f in declared) == set(grid_rotorpy.MISSION_KINDS)
    assert set(f.vehicle for f in declared) == set(grid_rotorpy.VEHICLES)
    for name in strata:                                    # halves per stratum: sizes differ by at most one
        h = Counter(f.half for f in declared if f.stratum == name)
        assert abs(h["tuning"] - h["judging"]) <= 1
    pairs = {tuple(n for n, _ in f.effects) for f in declared if len(f.effects) == 2}
    assert set(grid_rotorpy.ISSUE_PAIRS) <= pairs


def test_second_batches_are_their_declarations_and_all_judging():
    b = grid_rotorpy.declare_batch2()
    assert grid_rotorpy.load_grid(half="judge2") == b and len(b) == 41
    assert {f.half for f in b} == {"judge2"} and not {f.id for f in b} & {f.id for f in grid_rotorpy.load_grid()}
    assert Counter(f.stratum for f in b)["two effects"] == 22 and set(grid_rotorpy.EFFECTS) <= {
        n for f in b for n, _ in f.effects}
    rows = grid_sih.declare_batch2()
    flights = grid_sih.load_grid(half="judge2")
    assert [r["id"] for r in rows] == list(flights) and {f["half"] for f in flights.values()} == {"judge2"}
    combos = [r["group"] for r in rows if "+" in r["group"]]
    assert len(combos) == 10 and not {tuple(c.split("+")) for c in combos} & set(grid_sih.COMBOS)


def test_third_batches_are_their_declarations_new_ids_all_judging():
    seed, _, prefix, _ = grid_rotorpy.BATCHES["judge3"]
    b = grid_rotorpy.declare_batch2(seed, prefix, "judge3")
    assert grid_rotorpy.load_grid(half="judge3") == b and len(b) == 41 and {f.half for f in b} == {"judge3"}
    earlier = {f.id for h in ("all", "judge2") for f in grid_rotorpy.load_grid(half=h)}
    assert not {f.id for f in b} & earlier and b != grid_rotorpy.declare_batch2()
    seed, _, prefix, _ = grid_sih.BATCHES["judge3"]
    rows = grid_sih.declare_batch2(seed, prefix, "judge3")
    flights = grid_sih.load_grid(half="judge3")
    assert [r["id"] for r in rows] == list(flights) and {f["half"] for f in flights.values()} == {"judge3"}
    assert not set(flights) & (set(grid_sih.load_grid(half="judge2")) | set(grid_sih.load_grid()))


@pytest.mark.parametrize("batch", ["judge4", "judge5", "judge6", "judge7", "judge8", "judge9", "judge10",
                                   "judge11", "judge12", "judge13", "judge14", "judge15", "judge16"])
def test_later_batches_are_their_declarations_new_ids_all_judging(batch):
    names = list(grid_rotorpy.BATCHES)
    before = ["all", *names[:names.index(batch)]]
    seed, _, prefix, _ = grid_rotorpy.BATCHES[batch]
    b = grid_rotorpy.declare_batch2(seed, prefix, batch)
    assert grid_rotorpy.load_grid(half=batch) == b and len(b) == 41 and {f.half for f in b} == {batch}
    earlier = {f.id for h in before for f in grid_rotorpy.load_grid(half=h)}
    assert not {f.id for f in b} & earlier
    seed, _, prefix, _ = grid_sih.BATCHES[batch]
    rows = grid_sih.declare_batch2(seed, prefix, batch)
    flights = grid_sih.load_grid(half=batch)
    assert [r["id"] for r in rows] == list(flights) and {f["half"] for f in flights.values()} == {batch}
    earlier = set(grid_sih.load_grid()).union(*(grid_sih.load_grid(half=h) for h in before[1:]))
    assert not set(flights) & earlier


def test_rotorpy_grid_truths_in_physical_units():
    qp = grid_rotorpy.rf.rotorpy_params("crazyflie")
    lag = grid_rotorpy.plant_change("motor_time_constant", 2, qp, 1)
    assert lag["plant"]["tau_m"] == pytest.approx(2.0 * qp["tau_m"])
    com = grid_rotorpy.plant_change("com_offset", 1, qp, 3)
    d = np.hypot(com["hidden"].params["dx"], com["hidden"].params["dy"])
    assert d == pytest.approx(0.09 * grid_rotorpy._arm(qp))
    # every rotor moved by -d (rotor positions are measured from the centre of mass)
    r0, r1 = qp["rotor_pos"]["r1"], com["plant"]["rotor_pos"]["r1"]
    assert r1[0] - r0[0] == pytest.approx(-com["hidden"].params["dx"])
    me = grid_rotorpy.plant_change("motor_efficiency", 0, qp, 6)
    assert me["hidden"].params == {"motor": 3.0, "efficiency": 0.92}   # seed 6 -> rotor index 2 -> motor 3
    assert grid_rotorpy.pack_voltage(0.0, 60.0, 0.0) == pytest.approx(16.8)
    assert grid_rotorpy.pack_voltage(60.0, 60.0, 1.0) == pytest.approx(16.8 - 1.4 - 0.9)


def test_sih_grid_manifest_is_the_declaration():
    rows = grid_sih.declare()
    flights = grid_sih.load_grid()
    assert [r["id"] for r in rows] == list(flights)
    assert all(flights[r["id"]]["half"] == r["half"] for r in rows)
    assert len(rows) >= 60
    groups = Counter(r["group"] for r in rows)
    assert sum(1 for g in groups if "+" in g) == 10 and groups["none"] == 10
    assert {r["logging"] for r in rows} == {"default", "highrate"}
    assert {"M1", "M2", "M5", "M6"} <= {r["mission"] for r in rows}


def test_a_flight_discover_stops_on_is_scored_as_a_miss(monkeypatch):
    """judge10 c028 (a weak motor beside a mass): discover stopped with a params error and the flight was left out
    of the score as 'not scored'.  The vehicle flew it: a stop is a miss, counted in every bar, its reason listed."""
    from twin_nodes.base.errors import ParamsError
    from twin_nodes.discovery import discover as disc
    from twin_nodes.logs import ulog_io

    def refuse(log, vp, **kw):
        raise ParamsError("<memory>", "effects.motor_efficiency.motor", "expected an integer motor index, got 1.001")
    monkeypatch.setattr(disc, "discover", refuse)
    monkeypatch.setattr(ulog_io, "read_ulog", lambda path: None)
    fl = {"mission": "M1", "logging": "default", "sih": {"SIH_MASS": [1.0, 1.15], "SIH_Q_MAX": [0.1, 0.13]}}
    row, res = grid_prove.run_one(("px4sih", ("d999", fl), "/nonexistent.ulg"))
    assert row["n_true"] == 2 and row["n_named"] == 0 and not row["passed"] and not row["right_class"]
    assert "effects.motor_efficiency.motor" in row["refused"] and res["effects"] == []
    s = grid_prove.summarize([row])
    assert (s["n_effect"], s["n_right_top"], s["n_two"], s["n_both_named"], s["n_passed"]) == (1, 0, 1, 0, 0)
    txt = grid_prove.table([row], [])
    assert "[discover refused it]" in txt and "scored as misses, discover stopped: d999 (" in txt


def test_sih_truths_of_two_groups():
    from twin_nodes.mavlink.sih_flight import truth_effects

    eff = truth_effects({"SIH_T_MAX": 4.6, "SIH_Q_MAX": 0.13})
    assert [e["name"] for e in eff] == ["thrust_coefficient", "yaw_moment"]
    assert eff[1]["params"]["km"] == pytest.approx(0.13 / 4.6)
    vp = shipped("px4_sih_quadx")
    tr = grid_prove._sih_truths({"sih": {"SIH_MASS": [1.0, 1.15], "SIH_KDV": [1.0, 1.5]}}, vp)
    assert [t.hidden.name for t in tr] == ["mass", "linear_drag"]
    tr = grid_prove._sih_truths({"sih": {"SIH_IXX": [0.025, 0.0325], "SIH_IYY": [0.025, 0.0325],
                                         "SIH_Q_MAX": [0.1, 0.13]}}, vp)
    assert [t.hidden.name for t in tr] == ["inertia", "yaw_moment"]


def test_separating_plan_passes_the_mission_schema():
    from twin_nodes.mavlink.mission import plan_from_mapping

    for a, b in (("wind", "rotor_drag"), ("motor_time_constant", "actuator_delay"), ("battery_sag", "mass"),
                 ("ground_effect", "thrust_coefficient"), ("yaw_moment", "inertia"), ("com_offset", "inertia")):
        pair = verdicts.not_told_apart({"name": a, "alternatives": [{"name": b, "params": {"x": 1.0}}]})
        assert pair["with"]["name"] == b and pair["plan_flyable"]
        plan_from_mapping(pair["plan"], "<test>")              # no error: the schema agrees it is flyable
    # drags among themselves, mass with thrust: one class, not a pair
    assert verdicts.not_told_apart({"name": "body_drag", "alternatives": [{"name": "rotor_drag"}]}) is None
    assert verdicts.not_told_apart({"name": "mass", "alternatives": [{"name": "thrust_coefficient"}]}) is None
    bad = {"mission": {"waypoints": [{"north_m": 0.0, "east_m": 0.0, "alt_m": 300.0, "speed_m_s": 3.0}]}}
    assert not verdicts._flyable(bad)


# ------------------------------------------------------------------ scoring two effects and pairs


def _eff(name, params, verdict="confirmed", pair=None):
    e = {"name": name, "params": params, "verdict": verdict, "heldout_channel": "throttle",
         "heldout_improvement": 0.8, "residual": "equation"}
    if pair:
        e["not_told_apart"] = pair
    return e


def test_two_effect_scoring():
    vp = shipped("px4_sih_quadx")
    truths = [Truth(Hidden("mass", {"mass": 1.2})), Truth(Hidden("yaw_moment", {"km": 0.03}))]
    both = {"effects": [_eff("mass", {"mass": 1.19}), _eff("yaw_moment", {"km": 0.0305}, "likely")]}
    r = grid_prove.score_grid_flight("f", truths, both, vp)
    assert r["right_class"] and r["n_named"] == 2 and r["passed"]
    one = {"effects": [_eff("mass", {"mass": 1.19})]}
    r = grid_prove.score_grid_flight("f", truths, one, vp)
    assert r["right_class"] and r["n_named"] == 1 and not r["passed"]
    off = {"effects": [_eff("mass", {"mass": 1.4}), _eff("yaw_moment", {"km": 0.0305})]}
    r = grid_prove.score_grid_flight("f", truths, off, vp)
    assert r["n_named"] == 2 and not r["params_ok"] and not r["passed"]     # 16.7 % off on mass


def test_a_true_effect_confirmed_on_its_own_is_scored_on_that_finding_not_a_pair_partner():
    # RotorPy w023 (battery sag 1.0 + mass 1.15), ninth session: the sag's pair partner thrust_coefficient 0.712
    # (mass~1.404) was read for the mass confirmed on its own at 1.1497
    vp = shipped("px4_sih_quadx")
    truths = [Truth(Hidden("battery_sag", {"v_ref": 16.8, "exponent": 1.0})), Truth(Hidden("mass", {"mass": 1.15}))]
    kt = {"with": {"name": "thrust_coefficient", "params": {"kt_scale": 0.7121}}, "plan_flyable": True}
    res = {"effects": [_eff("battery_sag", {"v_ref": 16.8, "exponent": 1.001}, pair=kt),
                       _eff("mass", {"mass": 1.1497})]}
    r = grid_prove.score_grid_flight("f", truths, res, vp)
    assert r["param_errors"]["mass"] == pytest.approx(0.0003, abs=1e-4) and r["passed"]
    # without the mass finding the pair partner still names it (and is scored)
    res["effects"].pop()
    r = grid_prove.score_grid_flight("f", truths, res, vp)
    assert r["named"] == ["battery_sag", "mass"] and r["param_errors"]["mass"] > 0.1


def test_pair_scoring_needs_the_truth_in_it_and_a_flyable_plan():
    vp = shipped("px4_sih_quadx")
    truth = [Truth(Hidden("actuator_delay", {"delay": 0.04}))]
    pair = {"with": {"name": "actuator_delay", "params": {"delay": 0.041}}, "plan_flyable": True}
    res = {"effects": [_eff("motor_time_constant", {"tau_up": 0.1, "tau_down": 0.1}, pair=pair)]}
    r = grid_prove.score_grid_flight("f", truth, res, vp)
    assert r["right_class"] and r["right_by_pair"] and r["param_errors"]["actuator_delay"] == pytest.approx(0.025)
    res["effects"][0]["not_told_apart"] = dict(pair, plan_flyable=False)
    assert not grid_prove.score_grid_flight("f", truth, res, vp)["right_class"]
    none = grid_prove.score_grid_flight("f", [Truth(Hidden("none", {}))], res, vp)
    assert not none["passed"]


def test_a_parameter_the_finding_holds_as_not_shown_is_named_not_scored():
    # r050 (Ixx = Iyy x1.6 on a fast descent that never commands pitch): Ixx 0.04016, Iyy held at the model's 0.025
    vp = shipped("px4_sih_quadx")
    truth = [Truth(Hidden("inertia", {"ixx": 0.04, "iyy": 0.04, "izz": 0.03}))]
    inertia = _eff("inertia", {"ixx": 0.04016, "iyy": 0.025, "izz": 0.03002})
    r = grid_prove.score_grid_flight("f", truth, {"effects": [inertia]}, vp)
    assert r["param_errors"]["inertia"] == pytest.approx(0.375) and not r["passed"]     # claimed: 37.5 % off
    inertia["held_at_nominal"] = {"iyy": "held at nominal, not identified on this flight: ..."}
    r = grid_prove.score_grid_flight("f", truth, {"effects": [inertia]}, vp)
    assert r["param_errors"]["inertia"] == pytest.approx(0.004) and r["passed"]
    assert r["param_text"]["inertia"] == "ixx 0.04016 vs 0.04; iyy not identified (held)"
    # every true parameter held: nothing identified, no parameter error, not passed
    inertia["held_at_nominal"] = {"ixx": "-", "iyy": "-", "izz": "-"}
    r = grid_prove.score_grid_flight("f", truth, {"effects": [inertia]}, vp)
    assert r["param_errors"]["inertia"] is None and not r["params_ok"] and not r["passed"]
    # a held parameter of a pair's partner is not the partner's: the pair member is scored as given
    pair = {"with": {"name": "inertia", "params": {"ixx": 0.04016, "iyy": 0.025, "izz": 0.03}},
            "plan_flyable": True}
    lag = dict(_eff("motor_time_constant", {"tau_up": 0.1, "tau_down": 0.1}, pair=pair), held_at_nominal={"iyy": "-"})
    r = grid_prove.score_grid_flight("f", truth, {"effects": [lag]}, vp)
    assert r["param_errors"]["inertia"] == pytest.approx(0.375)


def test_a_pair_whose_rival_is_confirmed_on_its_own_is_told_apart():
    # q017 (lag + inertia, both confirmed): the lag's pair carried the inertia fitted alone in its place (Ixx +11 %)
    rival = {"with": {"name": "inertia", "params": {"ixx": 2.547e-05}}, "plan_flyable": True}
    out = [_eff("motor_time_constant", {"tau_up": 0.118, "tau_down": 0.118}, pair=rival),
           _eff("inertia", {"ixx": 2.282e-05, "iyy": 2.283e-05, "izz": 2.883e-05})]
    verdicts.told_apart(out)
    assert "not_told_apart" not in out[0] and out[0]["told_apart_from"]["name"] == "inertia"
    vp = shipped("px4_sih_quadx")
    truth = [Truth(Hidden("motor_time_constant", {"tau_up": 0.1152, "tau_down": 0.1152})),
             Truth(Hidden("inertia", {"ixx": 2.288e-05, "iyy": 2.288e-05, "izz": 2.89e-05}))]
    r = grid_prove.score_grid_flight("f", truth, {"effects": out}, vp)
    assert r["param_errors"]["inertia"] == pytest.approx(0.0026, abs=1e-4) and r["passed"]
    # a rival only `likely` on its own, or none: the pair stays
    for second in ([_eff("inertia", {"ixx": 2.282e-05}, "likely")], []):
        out = [_eff("motor_time_constant", {"tau_up": 0.118, "tau_down": 0.118}, pair=rival)] + second
        verdicts.told_apart(out)
        assert out[0]["not_told_apart"] is rival
    # two collective effects of one shape both accepted are a combination, not a separation (a mass and a thrust
    # coefficient: force per unit mass): the pair stays.  A battery sag (the voltage's shape, its level held at the
    # full pack) with a thrust coefficient is told apart: tests/test_one_channel_two_effects.py
    kt = {"with": {"name": "thrust_coefficient", "params": {"kt_scale": 0.842}}, "plan_flyable": True}
    out = [_eff("mass", {"mass": 1.19}, pair=kt), _eff("thrust_coefficient", {"kt_scale": 1.10})]
    verdicts.told_apart(out)
    assert out[0]["not_told_apart"] is kt
    # a drag rival is told apart by any confirmed drag (one class)
    out = [_eff("wind", {"vx": 1.0, "vy": 0.0}, pair={"with": {"name": "body_drag", "params": {}}}),
           _eff("rotor_drag", {"k_d": 1e-6})]
    verdicts.told_apart(out)
    assert "not_told_apart" not in out[0]


def test_an_inertia_axis_the_flight_never_excites_is_held():
    from twin_nodes.discovery.candidates import build_candidates
    from twin_nodes.discovery.stages import candidates

    vp = shipped("px4_sih_quadx")
    n = 500
    data = SimpleNamespace(v=np.tile([[3.0, 0.0, 0.0]], (n, 1)), valid=np.ones(n, bool), motor_dt_s=0.004,
                           dt=0.02, height=np.full(n, 10.0), battery_v=np.full(n, np.nan))
    c = next(c for c in build_candidates(vp, data) if c.name == "inertia")
    ex = {"roll": {"blocks_flight": 18}, "pitch": {"blocks_flight": 0}, "yaw": {"blocks_flight": 12}}
    h = candidates.hold_unexcited(c, ex)
    assert h.param_names == ("ixx", "izz") and h.label == c.label
    assert "pitch rate doublets" in h.held["iyy"]
    full = h.params_dict(np.array([0.04, 0.031]))
    assert full == {"ixx": 0.04, "iyy": pytest.approx(c.x0[1]), "izz": 0.031}
    from twin_nodes.physics.effects import effective_params
    assert np.diag(effective_params(h.build(np.array([0.04, 0.031]))).inertia) == pytest.approx([0.04, c.x0[1], 0.031])
    # one excited block is enough; no excitation record (an older caller): unchanged; other effects unchanged
    assert candidates.hold_unexcited(c, {**ex, "pitch": {"blocks_flight": 1}}) is c
    assert candidates.hold_unexcited(c, {}) is c
    km = next(c for c in build_candidates(vp, data) if c.name == "yaw_moment")
    assert candidates.hold_unexcited(km, {"yaw": {"blocks_flight": 0}}) is km
    # no axis excited (a hover's roll and pitch with a yaw that never turns): no inertia candidate at all
    assert candidates.hold_unexcited(c, {a: {"blocks_flight": 0} for a in ("roll", "pitch", "yaw")}) is None
    # and the round's candidates carry the restriction
    cs = candidates.run(candidates.CandidateQuery(vp, data, 1, excitation=ex))
    assert next(c for c in cs.first if c.name == "inertia").param_names == ("ixx", "izz")


# ------------------------------------------------------------------ discovery: the second round's pruning


def test_round_one_cut_rescaled_to_the_residual_left():
    # a cut of 1 % of round 1's residual is 1.99 % of its energy; with a tenth of the energy left it is
    # 19.9 % of it: a cut of 1 - sqrt(0.801) = 10.5 %, above PRUNE_GAIN (2 %)
    g = selection._rescaled_gain({"rotor_drag": 0.01, "x": 0.0}, (10.0, 0.0), (1.0, 0.0))
    assert g["rotor_drag"] == pytest.approx(1 - np.sqrt(1 - 0.0199 * 10), rel=1e-6)
    assert g["x"] == 0.0
    assert selection._rescaled_gain({"a": 0.3}, None, (1.0, 1.0)) == {"a": 0.3}
    assert selection._rescaled_gain({"a": 0.5}, (1.0, 1.0), (0.1, 0.1))["a"] == pytest.approx(1.0)


def test_wind_offered_with_a_drag_only_where_the_vehicle_has_none():
    vp = shipped("px4_sih_quadx")
    has_drag = any(n in ("linear_drag", "rotor_drag", "body_drag") for n, _ in vp.effects)
    data = SimpleNamespace(v=np.tile([[5.0, 0.0, 0.0]], (100, 1)), valid=np.ones(100, bool))
    c = selection.wind_with_drag(vp, data)
    assert bool(c) == (not has_drag)
    bare = vp.replace(effects=tuple(e for e in vp.effects if e[0] not in ("linear_drag", "rotor_drag", "body_drag")))
    (c,) = selection.wind_with_drag(bare, data)
    v = c.build(np.array([3.0, -2.0, 0.5]))
    assert dict(dict(v.effects)["wind"])["vx"] == 3.0 and dict(dict(v.effects)["linear_drag"])["k_n_s_m"] == 0.5
    assert c.params_dict(np.array([3.0, -2.0, 0.5]))["drag_k_n_s_m"] == 0.5
    weight = bare.mass_kg * bare.gravity_m_s2
    assert c.floor(np.array([3.0, 0.0, 0.02 * weight])) and not c.floor(np.array([0.1, 0.0, 0.02 * weight]))


# ------------------------------------------------------------------ discovery: the closed-loop veto


def _log(**info):
    return SimpleNamespace(info=info)


def test_who_flew_the_log():
    assert closed_loop.controller_of(_log(ver_hw="ROTORTWIN_SIM")) == "twin"
    assert closed_loop.controller_of(_log(ver_hw="ROTORPY_SIM", sys_name="rotorpy")) == "rotorpy"
    assert closed_loop.controller_of(_log(ver_hw="GAZEBO_SIM")) == "other"
    assert closed_loop.controller_of(_log(ver_hw="PX4_SITL", ver_sw="02e73e3b")) == "px4"
    ok = {"throttle_rmse": 0.01, "xy_rmse_m": 0.5}
    assert closed_loop.veto_standing(_log(ver_sw="x", ver_hw="PX4_SITL"), ok)[0]
    assert not closed_loop.veto_standing(_log(ver_sw="x", ver_hw="PX4_SITL"), dict(ok, throttle_rmse=0.2))[0]
    assert closed_loop.veto_standing(_log(ver_hw="ROTORTWIN_SIM"), dict(ok, throttle_rmse=0.2))[0]


def test_the_twin_stands_for_a_flight_only_when_it_flies_the_flights_controller():
    """PX4's cascade stands for PX4 and our simulator's flights; the SE(3) law for RotorPy's; a twin following
    its flight (FIDELITY) is still needed for flights of another program."""
    from twin_nodes.prove import rotorpy_flights as rp

    se3 = rp.nominal_params(rp.rotorpy_params("crazyflie"))
    px4 = shipped("px4_sih_quadx")
    ok = {"throttle_rmse": 0.01, "xy_rmse_m": 0.5}
    rotorpy = _log(ver_hw="ROTORPY_SIM", sys_name="rotorpy")
    assert closed_loop.veto_standing(rotorpy, ok, se3)[0]
    assert not closed_loop.veto_standing(rotorpy, dict(ok, throttle_rmse=0.2), se3)[0]
    assert not closed_loop.veto_standing(rotorpy, ok, px4)[0]
    assert not closed_loop.veto_standing(rotorpy, ok)[0]
    assert not closed_loop.veto_standing(_log(ver_hw="ROTORTWIN_SIM"), ok, se3)[0]
    assert not closed_loop.veto_standing(_log(ver_sw="x", ver_hw="PX4_SITL"), ok, se3)[0]
    assert closed_loop.veto_standing(_log(ver_sw="x", ver_hw="PX4_SITL"), ok, px4)[0]


def _run(err, t):
    return {"throttle_rmse": float(np.sqrt(np.mean(err ** 2))), "_throttle_err": (t, err)}


def test_veto_compares_with_its_own_noise_and_needs_standing():
    rng = np.random.default_rng(1)
    t = np.arange(0, 20, 0.02)
    base = 0.0086 * rng.standard_normal(t.size)
    before = _run(base, t)
    # a rise of 1 % in RMSE that one part of the held-out flight makes and another takes back: beyond the
    # relative tolerance, not beyond the bootstrap's scatter
    wobble = _run(base * (1 + 0.2 * np.sin(2 * np.pi * t / 4.0)), t)
    assert wobble["throttle_rmse"] > (1 + closed_loop.CLOSED_LOOP_TOL_REL) * before["throttle_rmse"]
    rise, se = closed_loop.rise_significance(wobble, before)
    assert rise == pytest.approx(np.mean(wobble["_throttle_err"][1] ** 2 - base ** 2))
    assert 0 < rise < closed_loop.VETO_Z * se
    vetoed, why = closed_loop._veto(wobble, before, before, (True, "the twin's controller flew this flight"))
    assert not vetoed and "within the run's own scatter" in why
    # a real worsening: a 0.5 % throttle bias on every sample
    worse = _run(base + 0.005, t)
    vetoed, why = closed_loop._veto(worse, before, before, (True, "the twin's controller flew this flight"))
    assert vetoed and "block bootstrap" in why
    # the same worsening on a flight another controller flew: the open-loop residuals decide
    vetoed, why = closed_loop._veto(worse, before, before, (False, "another controller"))
    assert not vetoed and why.startswith("not vetoed") and "another controller" in why
    # better: no veto, nothing to say
    assert closed_loop._veto(_run(0.5 * base, t), before, before, (True, "")) == (False, None)


def test_what_the_flight_does_not_excite_is_said_with_the_manoeuvre():
    from twin_nodes.discovery import report
    from twin_nodes.discovery.stages import candidates

    n = 500
    hover = SimpleNamespace(v=np.full((n, 3), 0.1), valid=np.ones(n, bool), height=np.full(n, 10.0), dt=0.02)
    ex = {"roll": {"blocks_flight": 3}, "pitch": {"blocks_flight": 0}, "yaw": {"blocks_flight": 12}}
    out = candidates.not_excited(hover, ex)
    assert [o["effects"] for o in out] == [["rotor_drag (force)", "body_drag (horizontal)"], ["inertia (iyy)"], ["ground_effect"]]
    assert out[0]["why"].startswith("90th-percentile speed 0.17 m/s") and out[0]["fly"].startswith("fast forward legs")
    assert out[1]["fly"].startswith("pitch rate doublets")
    # 1.2 s below 3 m and 4.5 m/s: every class can show; no excitation record: no inertia line
    moving = SimpleNamespace(v=np.column_stack([np.linspace(0, 5, n), np.zeros(n), np.zeros(n)]),
                             valid=np.ones(n, bool), height=np.r_[np.full(60, 1.0), np.full(n - 60, 10.0)], dt=0.02)
    assert candidates.not_excited(moving, {**ex, "pitch": {"blocks_flight": 1}}) == []
    assert candidates.not_excited(moving, {}) == []
    res = {"log": "f.ulg", "params": "p", "method": {"fit_interval_s": [0, 1], "heldout_interval_s": [1, 2]},
           "mismatch": [], "effects": [], "accepted": [], "likely": [], "not_excited": out[1:2]}
    assert ("  not excited on this flight: inertia (iyy) (no block carries a pitch moment above its noise); to show "
            "it fly pitch rate doublets") in report.summary_text(res)


def test_a_nominal_body_drag_refitted_where_the_flight_has_airspeed():
    # RotorPy's 1-2 kg quad: the nominal carries RotorPy's parasitic drag (c 0.01 each, norm form), so the library
    # offers no body drag and a changed one was found as nothing or a state term (r010, q028)
    vp = shipped("px4_sih_quadx").replace(effects=()).with_effect("body_drag", c_dx=0.01, c_dy=0.01, c_dz=0.01,
                                                                  norm=1.0)
    n = 500
    speed = np.linspace(0.0, 5.0, n)                 # 90th percentile 4.5 m/s
    data = SimpleNamespace(v=np.column_stack([speed, np.zeros(n), np.zeros(n)]), valid=np.ones(n, bool))
    (c,) = [c for c in selection.nominal_refits(vp, vp, data) if c.name == "body_drag"]
    assert c.label == selection.BODY_DRAG_REFIT and c.param_names == ("c_dx", "c_dy", "c_dz")
    assert c.x0 == pytest.approx([0.01] * 3) and c.fixed == {"norm": 1.0}
    v90 = float(np.percentile(speed, 90))
    floor = 0.01 * vp.mass_kg * vp.gravity_m_s2 / v90 ** 2
    assert c.upper == pytest.approx([max(500 * floor, 0.2)] * 3)
    assert c.floor(np.array([0.01, 0.01, 0.01 + 1.01 * floor])) and not c.floor(np.array([0.01 + 0.99 * floor] * 3))
    built = dict(dict(c.build(np.array([0.047, 0.047, 0.084])).effects)["body_drag"])
    assert built == {"c_dx": 0.047, "c_dy": 0.047, "c_dz": 0.084, "norm": 1.0}
    assert c.params_dict(np.array([0.047, 0.047, 0.084]))["norm"] == 1.0
    # a hover (no airspeed for a drag to act on), a refitted one already accepted, no body drag: none
    hover = SimpleNamespace(v=np.zeros((n, 3)) + 0.1, valid=np.ones(n, bool))
    assert not [c for c in selection.nominal_refits(vp, vp, hover) if c.name == "body_drag"]
    assert not [c for c in selection.nominal_refits(vp, c.build(c.x0 * 3), data) if c.name == "body_drag"]
    bare = vp.replace(effects=())
    assert selection.nominal_refits(bare, bare, data) == []


def test_a_hover_s_nominal_body_drag_refitted_in_its_vertical_term_alone():
    # RotorPy's hover with yaw (RP4, 1 kg quad): 90th-percentile speed 0.30 m/s, but the take-off and landing climb
    # and descend at 1.7 m/s (99th percentile of |v_z|): the vertical term c_dz is refitted alone, c_dx/c_dy held,
    # floor 1 % of the weight at that vertical speed (a003: c_dz fitted +0.060 from 0.01 against a floor of 0.0345)
    vp = shipped("px4_sih_quadx").replace(effects=()).with_effect("body_drag", c_dx=0.01, c_dy=0.01, c_dz=0.01,
                                                                  norm=1.0)
    n = 1000
    v = np.zeros((n, 3))
    v[:, 0] = 0.1
    v[:30, 2], v[-30:, 2] = 1.7, -1.7               # 6 % of the samples climb or descend
    hover = SimpleNamespace(v=v, valid=np.ones(n, bool))
    (c,) = [c for c in selection.nominal_refits(vp, vp, hover) if c.name == "body_drag"]
    assert c.label == selection.BODY_DRAG_REFIT and c.param_names == ("c_dz",)
    assert set(c.held) == {"c_dx", "c_dy"} and "0.5" in c.held["c_dx"]
    floor = 0.01 * vp.mass_kg * vp.gravity_m_s2 / 1.7 ** 2
    assert floor == pytest.approx(0.0345, abs=0.002)
    assert c.floor(np.array([0.01 + 1.01 * floor])) and not c.floor(np.array([0.01 + 0.99 * floor]))
    assert dict(dict(c.build(np.array([0.07])).effects)["body_drag"]) == {"c_dx": 0.01, "c_dy": 0.01, "c_dz": 0.07,
                                                                          "norm": 1.0}
    assert c.params_dict(np.array([0.07])) == {"c_dx": 0.01, "c_dy": 0.01, "c_dz": 0.07, "norm": 1.0}
    # climbs slower than MIN_VERTICAL_SPEED (1 m/s): nothing offered
    slow = SimpleNamespace(v=v * np.array([1.0, 1.0, 0.5]), valid=np.ones(n, bool))
    assert selection.MIN_VERTICAL_SPEED == 1.0
    assert not [c for c in selection.nominal_refits(vp, vp, slow) if c.name == "body_drag"]


def test_nominal_law_refitted_only_where_the_nominal_has_it():
    vp = shipped("px4_sih_quadx")               # linear_drag 1.0 and angular_damping 0.025 (SIH_KDV, SIH_KDW)
    cands = {c.name: c for c in selection.nominal_refits(vp, vp)}
    assert set(cands) == {"linear_drag", "angular_damping"}
    c = cands["angular_damping"]
    assert c.x0[0] == pytest.approx(0.025) and c.upper[0] == pytest.approx(0.125)
    v = c.build(np.array([0.05]))
    assert dict(dict(v.effects)["angular_damping"])["k_nm_s_rad"] == pytest.approx(0.05)
    assert c.floor(np.array([0.05])) and not c.floor(np.array([0.026]))
    # once refitted (accepted), not offered again
    assert {c.name for c in selection.nominal_refits(vp, v)} == {"linear_drag"}
    bare = vp.replace(effects=())
    assert selection.nominal_refits(bare, bare) == []


def test_nominal_rotor_drag_refitted_by_its_k_d():
    # RotorPy's nominals carry its rotor drag; a changed k_d (batch 7's n002, x2) was only offered as a body drag
    vp = shipped("rotorpy_crazyflie")
    (c,) = [c for c in selection.nominal_refits(vp, vp) if c.name == "rotor_drag"]
    assert c.param_names == ("k_d",) and c.label == "rotor_drag (nominal refitted)"
    assert c.x0[0] == pytest.approx(1.02506e-06)
    assert c.lower[0] == pytest.approx(2.05012e-07) and c.upper[0] == pytest.approx(5.1253e-06)
    v = c.build(np.array([2.053e-06]))
    assert dict(dict(v.effects)["rotor_drag"])["k_d"] == pytest.approx(2.053e-06)
    assert c.floor(np.array([1.2e-06])) and not c.floor(np.array([1.1e-06]))   # 10 % of the nominal k_d
    assert not [c for c in selection.nominal_refits(vp, v) if c.name == "rotor_drag"]


# ------------------------------------------------------------------ discovery: confusable effects refitted jointly


def _accepted_inertia(vp, theta):
    from twin_nodes.discovery.candidates import build_candidates

    data = SimpleNamespace(v=np.tile([[5.0, 0.0, 0.0]], (100, 1)), valid=np.ones(100, bool), motor_dt_s=0.004,
                           dt=0.004, height=np.full(100, 10.0), battery_v=np.full(100, np.nan))
    cands = build_candidates(vp, data)
    inertia = next(c for c in cands if c.name == "inertia")
    f = SimpleNamespace(candidate=inertia, theta=np.array(theta), verdict_note="", vp=inertia.build(np.array(theta)))
    return f, data


def test_lag_offered_with_the_accepted_inertia_refitted():
    from twin_nodes.discovery.candidates import SYMMETRIC_LAG, build_candidates

    vp = shipped("px4_sih_quadx")
    a, data = _accepted_inertia(vp, [0.030, 0.0277, 0.0399])     # s046: the lag taken up as Ixx/Iyy
    current = a.vp
    cands = build_candidates(current, data)
    joint = selection.dynamic_refits([a], cands, current)
    labels = {c.label for c in joint}
    assert labels == {f"{SYMMETRIC_LAG} (+inertia refitted)", "actuator_delay (+inertia refitted)"}
    lag = next(c for c in joint if c.name == "motor_time_constant")
    assert lag.param_names == ("tau_up", "ixx", "iyy", "izz")
    assert lag.x0 == pytest.approx([0.05, 0.030, 0.0277, 0.0399])
    v = lag.build(np.array([0.08, 0.025, 0.025, 0.039]))
    eff = {n: dict(p) for n, p in v.effects}
    assert eff["motor_time_constant"] == {"tau_up": 0.08, "tau_down": 0.08}
    assert eff["inertia"] == pytest.approx({"ixx": 0.025, "iyy": 0.025, "izz": 0.039})
    # the effects in the plain candidate's order (the compiled stepper is the one the round uses)
    plain = next(c for c in cands if c.label == SYMMETRIC_LAG).build(np.array([0.08]))
    assert [n for n, _ in v.effects] == [n for n, _ in plain.effects]
    assert lag.params_dict(np.array([0.08, 0.025, 0.025, 0.039])) == {"tau_up": 0.08, "tau_down": 0.08}
    assert lag.floor(np.array([0.08, 0.025, 0.025, 0.039])) and not lag.floor(np.array([0.05, 0.03, 0.03, 0.03]))
    # accepted: the inertia takes the joint values
    win = SimpleNamespace(candidate=lag, theta=np.array([0.08, 0.025, 0.0251, 0.039]), vp=v)
    selection._carry_refit(win, [a])
    assert a.theta == pytest.approx([0.025, 0.0251, 0.039]) and a.vp is v
    assert a.refitted_jointly_with == "motor_time_constant" and win.joint_refit_of == "inertia"
    # not offered for what is not a dynamic rival (a drag), nor on top of a mass
    assert all(c.name in selection.CONFUSABLE for c in joint)
    assert selection.dynamic_refits([SimpleNamespace(candidate=SimpleNamespace(name="mass"))], cands, current) == []


def test_drag_offered_with_the_accepted_thrust_refitted():
    # s044: the drag beside the accepted thrust coefficient, both free (stages.joint, which every later candidate
    # goes through now); the mass is not (one kind with the thrust coefficient)
    from twin_nodes.discovery.candidates import build_candidates
    from twin_nodes.discovery.stages import joint

    vp = shipped("px4_sih_quadx")
    data = SimpleNamespace(v=np.tile([[5.0, 0.0, 0.0]], (100, 1)), valid=np.ones(100, bool), motor_dt_s=0.004,
                           dt=0.004, height=np.full(100, 10.0), battery_v=np.full(100, np.nan))
    kt = next(c for c in build_candidates(vp, data) if c.name == "thrust_coefficient")
    a = SimpleNamespace(candidate=kt, theta=np.array([0.848]), verdict_note="", vp=kt.build(np.array([0.848])),
                        kind="equation")
    cands = {c.label: c for c in build_candidates(a.vp, data) + selection.nominal_refits(vp, a.vp)}
    lin = joint.Linearized(["thrust_coefficient"], [("kt_scale",)], np.array([0.848]), kt.lower, kt.upper,
                           np.zeros((1, 1, 1)), [a])
    assert joint.partners(cands["mass"], lin) == ()
    ld = joint.variant(cands["linear_drag (nominal refitted)"], lin, [])
    assert ld.label == "linear_drag (nominal refitted) (+thrust_coefficient refitted)"
    v = ld.build(np.array([1.28, 0.87]))
    eff = {n: dict(p) for n, p in v.effects}
    # SIH's drag stays isotropic (the shipped params' ``vertical`` 1 kept through the refit)
    assert eff["linear_drag"] == {"k_n_s_m": 1.28, "vertical": 1.0} and eff["thrust_coefficient"] == {"kt_scale": 0.87}
    # the effects in the plain candidate's order (the compiled stepper is the one the round already uses)
    plain = cands["linear_drag (nominal refitted)"].build(np.array([1.28]))
    assert [n for n, _ in v.effects] == [n for n, _ in plain.effects]
    assert ld.params_dict(np.array([1.28, 0.87])) == {"k_n_s_m": 1.28}
    # accepted: the thrust coefficient takes the joint value
    win = SimpleNamespace(candidate=ld, theta=np.array([1.28, 0.8703]), vp=v)
    selection._carry_refit(win, [a])
    assert a.theta == pytest.approx([0.8703]) and a.refitted_jointly_with == "linear_drag"
    assert win.joint_refit_of == "thrust_coefficient"


def test_drag_beside_a_thrust_standing_for_a_mass_is_read_per_unit_mass():
    # s044: mass 1.15 and linear drag 1.5 on a 1 kg model; found kt 0.870 (1/1.15) and drag 1.28 per the
    # model's 1 kg = 1.472 N/(m/s) at the true mass: 1.9 % off, not 14.7 %
    vp = shipped("px4_sih_quadx")
    truths = [Truth(Hidden("mass", {"mass": 1.15})), Truth(Hidden("linear_drag", {"k_n_s_m": 1.5}))]
    res = {"effects": [_eff("thrust_coefficient", {"kt_scale": 0.8703}), _eff("linear_drag", {"k_n_s_m": 1.28})]}
    r = grid_prove.score_grid_flight("f", truths, res, vp)
    assert r["param_errors"]["linear_drag"] == pytest.approx(abs(1.28 * 1.15 / 1.5 - 1), rel=1e-9)
    assert r["passed"]
    # the mass found as a mass: the drag is the model's own, compared as it is
    res = {"effects": [_eff("mass", {"mass": 1.15}), _eff("linear_drag", {"k_n_s_m": 1.28})]}
    r = grid_prove.score_grid_flight("f", truths, res, vp)
    assert r["param_errors"]["linear_drag"] == pytest.approx(abs(1.28 / 1.5 - 1), rel=1e-9) and not r["passed"]


def test_wind_offered_on_a_hover_where_the_vehicle_has_a_drag():
    """A hovering vehicle in a steady wind has airspeed though it has no ground speed: the wind is a
    candidate wherever the nominal has a drag law (the drags themselves need the flight's own speed)."""
    from twin_nodes.discovery.candidates import build_candidates

    vp = shipped("px4_sih_quadx")
    assert any(n == "linear_drag" for n, _ in vp.effects)

    def names(speed):
        data = SimpleNamespace(v=np.tile([[speed, 0.0, 0.0]], (100, 1)), valid=np.ones(100, bool),
                               motor_dt_s=0.02, dt=0.02, height=np.full(100, 10.0), battery_v=np.full(100, np.nan))
        return {c.name for c in build_candidates(vp, data)}
    hover, cruise = names(0.1), names(5.0)
    # the rotor drag is offered on a hover too, on the yaw damping of its hubs in yaw turns (tests/test_visibility.py)
    assert "wind" in hover and "body_drag" not in hover and "rotor_drag" in hover
    assert {"wind", "rotor_drag", "body_drag"} <= cruise
    bare = vp.replace(effects=tuple(e for e in vp.effects if e[0] != "linear_drag"))
    data = SimpleNamespace(v=np.zeros((100, 3)), valid=np.ones(100, bool), motor_dt_s=0.02, dt=0.02,
                           height=np.full(100, 10.0), battery_v=np.full(100, np.nan))
    assert "wind" not in {c.name for c in build_candidates(bare, data)}
    # the wind's floor: 0.3 m/s
    w = next(c for c in build_candidates(vp, data) if c.name == "wind")
    assert w.floor(np.array([0.2, 0.25])) and not w.floor(np.array([0.2, 0.2]))


def test_a_lag_the_rate_loop_prefers_is_named_beside_a_delay():
    """On a 50 Hz PX4 log the flight's own residuals may name a delay where the motors are slow: PX4's rate loop,
    flown without that delay, reads a lag that fits its held-out windows better than an extra delay; the lag is
    then the delay's not-told-apart partner, with the manoeuvre that separates them, and the delay is kept."""
    from twin_nodes.discovery.stages.motor_lag import _beside_the_delay

    delay = {"name": "actuator_delay", "verdict": "confirmed", "verdict_note": "t=5.5 over 26 held-out blocks",
             "params": {"delay": 0.0708}, "alternatives": []}
    r = {"tau_fold1": 0.128, "tau": 0.131, "se": 0.004, "model_tau": 0.05,
         "heldout_sse": {"lag": 812.0, "delay": 955.0, "model": 1400.0}}
    out = _beside_the_delay(r, {"verdict": "likely"}, delay)
    assert out["verdict"].startswith("named beside the delay")
    assert delay["params"] == {"delay": 0.0708} and delay["verdict"] == "confirmed"
    pair = delay["not_told_apart"]
    assert pair["with"] == {"name": "motor_time_constant", "params": {"tau_up": 0.128, "tau_down": 0.128}}
    assert pair["manoeuvre"] == "rate_doublets" and pair["plan_flyable"]
    assert "0.131 +- 0.004 s" in delay["verdict_note"] and "812 vs 955" in delay["verdict_note"]


def test_a_lag_fitted_on_aliased_commands_is_read_again_by_the_rate_loop(monkeypatch):
    """On a 50 Hz PX4 log the equation error fitted SIH_T_TAU 0.13 s as 0.147/0.151 (s016); PX4's rate loop, which
    uses no motor command, reads 0.129: that value replaces the finding's (kept as own_params) and the refit
    vehicle's; a reading that moves the lag the other way, or that the closed-loop check refuses, changes nothing."""
    from twin_nodes.discovery import rate_loop
    from twin_nodes.discovery.stages import motor_lag

    vp = shipped("px4_sih_quadx")
    current = vp.with_effect("motor_time_constant", tau_up=0.147, tau_down=0.151)
    S = SimpleNamespace(data=SimpleNamespace(motor_dt_s=0.02), nominal=vp, log_params={}, t_split=1.0, t_split2=0.5)
    reading = {"flagged": True, "model_tau": vp.rotors.tau_up_s, "tau": 0.1294, "se": 0.0009, "tau_fold1": 0.1296,
               "se_fold1": 0.0012, "tau_fold2": 0.1291, "se_fold2": 0.0013, "heldout_before": 1.0, "heldout_after": 0.3,
               "heldout_sse": {"model": 10350.0, "lag": 7610.0, "delay": 9861.0}, "delay_fold1": 0.03,
               "axis_tau": {"roll": 0.121, "pitch": 0.132, "yaw": 0.121}}
    seen = {}

    def fake(d, params, base, t1, t2):
        seen["base"] = dict(base.effect_dict)["motor_time_constant"]
        return dict(reading)
    monkeypatch.setattr(rate_loop, "motor_lag", fake)

    def entry():
        return [{"name": "motor_time_constant", "verdict": "confirmed", "residual": "equation",
                 "params": {"tau_up": 0.147, "tau_down": 0.151}, "verdict_note": "t=7.3"}]
    eff = entry()
    new = motor_lag.read_finding(S, current, eff, lambda v: None)
    # read against the nominal lag, not the finding's own
    assert seen["base"] == {"tau_up": vp.rotors.tau_up_s, "tau_down": vp.rotors.tau_down_s}
    assert eff[0]["params"] == {"tau_up": 0.1296, "tau_down": 0.1296}
    assert eff[0]["own_params"] == {"tau_up": 0.147, "tau_down": 0.151}
    assert dict(new.effect_dict)["motor_time_constant"] == {"tau_up": 0.1296, "tau_down": 0.1296}
    assert "0.129 +- 0.001 s" in eff[0]["verdict_note"] and eff[0]["residuals"]["rate_loop"]["heldout_improvement"] == 0.7
    # the closed-loop check refuses it: nothing changes, the reading is shown
    eff = entry()
    assert motor_lag.read_finding(S, current, eff, lambda v: "worse in the closed loop") is None
    assert eff[0]["params"] == {"tau_up": 0.147, "tau_down": 0.151} and eff[0]["rate_loop_reading"]["tau"] == 0.1294
    # a reading faster than the model while the finding is slower: not the same lag
    reading.update(tau=0.03, tau_fold1=0.03, tau_fold2=0.03)
    eff = entry()
    assert motor_lag.read_finding(S, current, eff, lambda v: None) is None and "own_params" not in eff[0]
    # a log whose motors are logged as fast as the rate loop runs: the finding's own fit stands
    S.data.motor_dt_s = 0.004
    assert motor_lag.read_finding(S, current, entry(), lambda v: None) is None


def _sih_body_rate_dot(I: np.ndarray, arms: tuple[float, float], t_max: float, q_max: float, u: np.ndarray,
                       w: np.ndarray, kdw: float) -> np.ndarray:
    """PX4 SIH's quadrotor body-rate derivative, transcribed from simulator_sih/sih.cpp
    (generate_force_and_torques, equations_of_motion): M = (L_ROLL T_MAX (-u0+u1+u2-u3),
    L_PITCH T_MAX (u0-u1+u2-u3), Q_MAX (u0+u1-u2-u3)); w_dot = I^-1 (M - KDW w - w x I w)."""
    M = np.array([arms[0] * t_max * (-u[0] + u[1] + u[2] - u[3]), arms[1] * t_max * (u[0] - u[1] + u[2] - u[3]),
                  q_max * (u[0] + u[1] - u[2] - u[3])])
    return np.linalg.solve(I, M - kdw * w - np.cross(w, I @ w))


def test_sih_arm_length_and_inertia_map_to_one_per_axis_inertia():
    """An arm length scales its axis's moment alone: SIH with (IXX, IYY, L_ROLL, L_PITCH) turns, for any
    command, as SIH with the nominal arms and the per-axis inertia prove maps it to; an inertia and an
    arm change together are one inertia truth (t016/t018 of batch 2: IXX_IYY with L_PITCH / L_ROLL)."""
    from twin_nodes.prove import sih as prove_sih

    vp = shipped("px4_sih_quadx")
    rng = np.random.default_rng(3)
    for ch in ({"SIH_L_ROLL": 0.17}, {"SIH_L_PITCH": 0.15}, {"SIH_IXX": 0.0325, "SIH_IYY": 0.0325, "SIH_L_PITCH": 0.17},
               {"SIH_IXX": 0.0325, "SIH_IYY": 0.0325, "SIH_L_ROLL": 0.17}, {"SIH_IZZ": 0.039, "SIH_L_ROLL": 0.15}):
        t = prove_sih.map_truth({"sih_changes": {k: [0.0, v] for k, v in ch.items()}}, vp)
        assert t.hidden.name == "inertia"
        eq = t.hidden.params
        I_sih = np.diag([ch.get("SIH_IXX", 0.025), ch.get("SIH_IYY", 0.025), ch.get("SIH_IZZ", 0.030)])
        arms = (ch.get("SIH_L_ROLL", 0.2), ch.get("SIH_L_PITCH", 0.2))
        I_eq = np.diag([eq["ixx"], eq["iyy"], eq["izz"]])
        for _ in range(5):
            u = rng.uniform(0.2, 0.8, 4)
            a = _sih_body_rate_dot(I_sih, arms, 5.0, 0.1, u, np.zeros(3), 0.0)
            b = _sih_body_rate_dot(I_eq, (0.2, 0.2), 5.0, 0.1, u, np.zeros(3), 0.0)
            assert b == pytest.approx(a, rel=1e-12, abs=1e-12)
    # the closed forms, per axis
    eq = prove_sih.map_truth({"sih_changes": {"SIH_IXX": [0.025, 0.0325], "SIH_IYY": [0.025, 0.0325],
                                              "SIH_L_PITCH": [0.2, 0.17]}}, vp).hidden.params
    assert eq == pytest.approx({"ixx": 0.0325, "iyy": 0.0325 * 0.2 / 0.17, "izz": 0.030})
    tr = grid_prove._sih_truths({"sih": {"SIH_IXX": [0.025, 0.0325], "SIH_IYY": [0.025, 0.0325],
                                         "SIH_L_ROLL": [0.2, 0.17]}}, vp)
    assert [t.hidden.name for t in tr] == ["inertia"]
    assert tr[0].hidden.params == pytest.approx({"ixx": 0.0325 * 0.2 / 0.17, "iyy": 0.0325, "izz": 0.030})
    # other groups beside it stay their own truths
    tr = grid_prove._sih_truths({"sih": {"SIH_KDW": [0.025, 0.05], "SIH_L_ROLL": [0.2, 0.17]}}, vp)
    assert [t.hidden.name for t in tr] == ["angular_damping", "inertia"]


def test_a_yaw_pair_s_rotor_drag_does_not_name_a_body_drag_ra020():
    # RotorPy ra020 (batch 14, Crazyflie hover with yaw: body drag c_d 0.0011/0.0011/0.0022 + yaw moment km 0.0509):
    # the yaw moment 0.05084 confirmed, not told apart from a rotor drag's yaw damping k_d 5.209e-7 (below the
    # nominal 1.025e-6); that partner named the body drag and was scored as one, k_eq 96.3 % off
    vp = shipped("rotorpy_crazyflie")
    drag = Truth(Hidden("body_drag", {"c_dx": 0.001103625, "c_dy": 0.001103625, "c_dz": 0.00220725}))
    truths = [drag, Truth(Hidden("yaw_moment", {"km": 0.0508695652173913}))]
    pair = {"with": {"name": "rotor_drag", "params": {"k_d": 5.209e-07}}, "plan_flyable": True}
    res = {"effects": [_eff("yaw_moment", {"km": 0.05084}, pair=pair)]}
    r = grid_prove.score_grid_flight("ra020", truths, res, vp)
    assert r["named"] == ["yaw_moment"] and "body_drag" not in r["param_errors"] and r["right_class"]
    assert r["param_errors"]["yaw_moment"] == pytest.approx(1 - 0.05084 / 0.0508695652173913, rel=1e-9)
    assert not r["passed"]
    # a body drag alone: the yaw pair is not the right class by its rotor-drag partner
    assert not grid_prove.score_grid_flight("ra020", [drag], res, vp)["right_class"]
    # the same partner names a true rotor drag (its own law), and a body drag finding of its own still names it
    rotor = [Truth(Hidden("rotor_drag", {"k_d": 5.2e-07}))]
    assert grid_prove.score_grid_flight("f", rotor, res, vp)["named"] == ["rotor_drag"]
    own = {"effects": res["effects"] + [_eff("body_drag", {"c_dx": 0.0011, "c_dy": 0.0011, "c_dz": 0.0022})]}
    assert grid_prove.score_grid_flight("f", truths, own, vp)["n_named"] == 2


def test_a_yaw_pair_not_told_apart_is_scored_as_one_reading():
    # d019 (batch 10: SIH_IZZ 0.039 + SIH_KDW 0.05, M2): stage 10 reported yaw moment km 0.0155 with k_d 0.0389,
    # or inertia Izz 0.0387 with k_d 0.0502; the inertia was read from the partner and the damping from the
    # reported reading (22 % off): one reading is both, the partner's k_d 0.0502 (0.4 % off)
    vp = shipped("px4_sih_quadx")
    truths = grid_prove._sih_truths({"sih": {"SIH_IZZ": [0.03, 0.039], "SIH_KDW": [0.025, 0.05]}}, vp)
    pair = {"with": {"name": "inertia", "params": {"ixx": 0.025, "iyy": 0.025, "izz": 0.03868}},
            "plan_flyable": True, "damping_with_it": {"k_nm_s_rad": 0.05021}}
    res = {"effects": [_eff("angular_damping", {"k_nm_s_rad": 0.03895}),
                       _eff("yaw_moment", {"km": 0.01551}, pair=pair)]}
    r = grid_prove.score_grid_flight("d019", truths, res, vp)
    assert r["param_errors"]["angular_damping"] == pytest.approx(0.05021 / 0.05 - 1, rel=1e-9)
    assert r["param_errors"]["inertia"] == pytest.approx(1 - 0.03868 / 0.039, rel=1e-9) and r["passed"]
    assert "other reading" in r["param_text"]["angular_damping"]
    # the truth read from the reported finding itself (a yaw moment + damping flight): its own damping
    truths = grid_prove._sih_truths({"sih": {"SIH_Q_MAX": [0.1, 0.13], "SIH_KDW": [0.025, 0.05]}}, vp)
    pair = {"with": {"name": "inertia", "params": {"ixx": 0.025, "iyy": 0.025, "izz": 0.0231}},
            "plan_flyable": True, "damping_with_it": {"k_nm_s_rad": 0.0385}}
    res = {"effects": [_eff("angular_damping", {"k_nm_s_rad": 0.0507}), _eff("yaw_moment", {"km": 0.0262}, pair=pair)]}
    r = grid_prove.score_grid_flight("m016", truths, res, vp)
    assert r["param_errors"]["angular_damping"] == pytest.approx(0.0507 / 0.05 - 1, rel=1e-9) and r["passed"]


def test_both_grids_name_the_same_judging_batches_and_the_cli_takes_each():
    from twin_nodes.cli import build_parser

    assert set(grid_rotorpy.BATCHES) == set(grid_sih.BATCHES)
    assert grid_sih.HALVES == ("tuning", "judging", *grid_sih.BATCHES, "all")
    p = build_parser()
    for h in grid_sih.HALVES:
        assert p.parse_args(["prove", "--grid", "px4sih", "--half", h]).half == h
    with pytest.raises(SystemExit):
        p.parse_args(["prove", "--grid", "px4sih", "--half", "judge99"])


def test_a_ground_effect_on_a_low_hover_is_scored_as_the_extra_thrust_it_pins_i014():
    # i014 (batch 12: battery sag 1.0 + ground effect 0.4 / 0.1505 m, Crazyflie hover with yaw): the low hover sits
    # at 0.157 m (spread 0.154 height scales); discovery says so and reads 0.357 / 0.170 along the ridge, to
    # 0.259-0.455 / 0.120-0.220: the one reading, c exp(-0.157/h_s), 0.1415 against the truth's 0.1409
    vp = shipped("px4_sih_quadx")
    truths = [Truth(Hidden("battery_sag", {"v_ref": 16.8, "exponent": 1.0})),
              Truth(Hidden("ground_effect", {"coefficient": 0.4, "height_scale": 0.1505}))]
    gf = {"h_ref_m": 0.157, "spread_scales": 0.154, "determined": False,
          "ridge": {"coefficient_range": [0.2587, 0.4554], "height_scale_range_m": [0.1198, 0.2195]}}
    ge = {**_eff("ground_effect", {"coefficient": 0.35708, "height_scale": 0.16966}), "ground_fit": gf}
    res = {"effects": [_eff("battery_sag", {"v_ref": 16.8, "exponent": 1.0004}), ge]}
    r = grid_prove.score_grid_flight("i014", truths, res, vp)
    g_f, g_t = 0.35708 * np.exp(-0.157 / 0.16966), 0.4 * np.exp(-0.157 / 0.1505)
    assert r["param_errors"]["ground_effect"] == pytest.approx(abs(g_f / g_t - 1), rel=1e-9)   # 0.4 %
    assert r["param_errors"]["ground_effect"] < 0.01 and r["passed"]
    assert "not told apart" in r["param_text"]["ground_effect"]
    # a truth outside the range the finding states: each parameter scored (the height scale 12.7 % off)
    narrow = {**gf, "ridge": {"coefficient_range": [0.34, 0.37], "height_scale_range_m": [0.16, 0.18]}}
    r = grid_prove.score_grid_flight("i014", truths, {"effects": [res["effects"][0], {**ge, "ground_fit": narrow}]}, vp)
    assert r["param_errors"]["ground_effect"] == pytest.approx(0.16966 / 0.1505 - 1, rel=1e-9) and not r["passed"]
    # a flight that tells them apart (determined): each parameter scored, as before
    told = {**gf, "determined": True}
    r = grid_prove.score_grid_flight("i014", truths, {"effects": [res["effects"][0], {**ge, "ground_fit": told}]}, vp)
    assert r["param_errors"]["ground_effect"] == pytest.approx(0.16966 / 0.1505 - 1, rel=1e-9)


def test_a_short_take_off_and_landing_ground_effect_is_scored_by_its_ridge_range_ra016():
    # ra016 (batch 14, seen: Crazyflie fast descents, CoM offset + ground effect 0.4 / 0.1505 m), re-flown (par18):
    # 1.08 s within reach, not told apart; the whole flight read 0.4668 / 0.1365 (16.7 / 9.3 % off), the folds
    # 0.5048 / 0.1318 and 0.4510 / 0.1402.  The folds' bare half-width (c 8.5 %, h_s 6.1 %) left both truths
    # outside, so each parameter was scored (16.7 %, FAIL) beside a stated +- 8 % that did not hold; their range
    # for one degree of freedom (x1.837) holds both, and the one reading the flight gives is scored: 3.8 %
    from twin_nodes.discovery.stages import ground

    vp = shipped("rotorpy_crazyflie")
    truths = [Truth(Hidden("ground_effect", {"coefficient": 0.4, "height_scale": 0.1505}))]
    found = {"coefficient": 0.46676, "height_scale": 0.13647}
    pin = {"h_ref_m": 0.172, "spread_scales": 0.569, "determined": False}
    folds = [{"coefficient": 0.50479, "height_scale": 0.13181}, {"coefficient": 0.45100, "height_scale": 0.14015}]
    ridge = ground.along_ridge(pin, found, folds)
    assert ridge["coefficient_range"][0] < 0.4 < ridge["coefficient_range"][1]
    assert ridge["height_scale_range_m"][0] < 0.1505 < ridge["height_scale_range_m"][1]
    ge = {**_eff("ground_effect", found), "ground_fit": {**pin, "ridge": ridge}}
    r = grid_prove.score_grid_flight("ra016", truths, {"effects": [ge]}, vp)
    g_f, g_t = 0.46676 * np.exp(-0.172 / 0.13647), 0.4 * np.exp(-0.172 / 0.1505)
    assert r["param_errors"]["ground_effect"] == pytest.approx(abs(g_f / g_t - 1), rel=1e-9)   # 3.8 %
    assert 0.03 < r["param_errors"]["ground_effect"] < 0.05 and "not told apart" in r["param_text"]["ground_effect"]
    # the bare half-width (before par18): the truth outside, each parameter scored, the coefficient 16.7 % off
    bare = {"coefficient_range": [round(0.46676 * (1 - 0.085), 4), round(0.46676 * 1.085, 4)],
            "height_scale_range_m": [round(0.13647 * (1 - 0.061), 4), round(0.13647 * 1.061, 4)]}
    r = grid_prove.score_grid_flight("ra016", truths, {"effects": [{**ge, "ground_fit": {**pin, "ridge": bare}}]},
                                     vp)
    assert r["param_errors"]["ground_effect"] == pytest.approx(0.46676 / 0.4 - 1, rel=1e-9) and not r["passed"]
