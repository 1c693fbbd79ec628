"""Term discovery (issue 27): the state term's kernel against its numpy twin, the sparse fit finding a
known term in synthetic data (and none in noise), the naming rules, the plant-only physics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twin_nodes.discovery import terms as T
from twin_nodes.physics.effects import EFFECTS, STATE_TERM_FEATURES, StateTerm, state_term_features
from twin_nodes.vehicle.params import shipped


def _states(n=200, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.normal(0, 4, (n, 3))
    h = rng.uniform(0.05, 20, n)
    q = rng.normal(0, 1, (n, 4)) * [1, 0.2, 0.2, 1]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    omega = rng.uniform(200, 1000, (n, 4))
    return v, h, q, omega


def test_state_term_kernel_agrees_with_its_numpy_twin():
    v, h, q, omega = _states()
    coef = {f"c_{f}": c for f, c in zip(STATE_TERM_FEATURES, (0.03, 0.02, -0.05, -0.04, 0.01, 0.5, -0.1, 0.05, 0.1, -0.07))}
    eff = StateTerm(v_h=5.6, radius=0.12, omega_max=1000.0, c_one=0.02, **coef)
    p = eff.vector()
    F = state_term_features(v, h, q, omega, 5.6, 0.12, 1000.0)
    c = np.array([coef[f"c_{f}"] for f in STATE_TERM_FEATURES])
    want = np.clip(1.0 + 0.02 + F @ c, 0.1, 3.0)
    for i in range(len(v)):
        x = np.zeros(17)
        x[2], x[3:6], x[6:10] = h[i], v[i], q[i]
        Tt, Q = np.ones(4), np.ones(4)
        eff.rotor_kernel(p, x, np.zeros(4), omega[i], Tt, Q)
        np.testing.assert_allclose(Tt, want[i], rtol=1e-12)


def test_state_term_is_neutral_at_zero_and_registered():
    assert "state_term" in EFFECTS
    v, h, q, omega = _states(20)
    eff = StateTerm(v_h=5.0, radius=0.1, omega_max=1000.0)
    for i in range(20):
        x = np.zeros(17)
        x[2], x[3:6], x[6:10] = h[i], v[i], q[i]
        Tt = np.full(4, 2.0)
        eff.rotor_kernel(eff.vector(), x, np.zeros(4), omega[i], Tt, np.ones(4))
        assert np.all(Tt == 2.0)


def test_hover_induced_velocity_closed_form():
    vp = shipped("px4_sih_quadx")          # 1 kg, 4 rotors; 0.3 x spacing 0.4 m = 0.12 m
    r = T.rotor_radius_m(vp)
    assert r == pytest.approx(0.3 * 2 * math.hypot(0.2, 0.2) * math.sin(math.pi / 4))
    v_h = T.hover_induced_velocity(vp, 0.1)
    assert v_h == pytest.approx(math.sqrt(9.81 / (2 * 1.225 * 4 * math.pi * 0.01)), rel=1e-3)   # 5.64 m/s


def _synthetic(term: dict | None, n=3000, noise=0.002, seed=1):
    """A flight-like state history at 10 Hz, regressors = thrust-weighted features (hover thrust 0.5 of
    full output), a throttle residual made by ``term`` (feature -> coefficient) plus low-passed noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 10.0
    mu = np.clip(1.6 * np.sin(t / 13.0) ** 2 + 0.05 * rng.standard_normal(n), 0, None)
    vz = 1.2 * np.sin(t / 7.0) + 0.3 * np.sin(t / 2.3)
    u = 0.7 + 0.08 * np.sin(t / 3.1) + 0.02 * rng.standard_normal(n)
    feats = np.column_stack([mu, mu ** 2, np.maximum(vz, 0), np.maximum(-vz, 0), np.maximum(-vz, 0) ** 2,
                             np.full(n, 1e-4), u ** 2, u ** 4, 0.02 * mu, u ** 8])
    assert feats.shape[1] == len(STATE_TERM_FEATURES)
    thrust = 0.5 + 0.1 * (u - 0.7)
    X = np.column_stack([thrust, feats * thrust[:, None]])
    y = np.convolve(rng.standard_normal(n), np.ones(5) / 5, mode="same") * noise
    if term:
        for name, c in term.items():
            y += c * X[:, 1 + STATE_TERM_FEATURES.index(name)]
    return y, X, t, feats


def test_sparse_fit_finds_a_known_term_and_names_it():
    y, X, t, feats = _synthetic({"mu2": 0.04})
    s = T.find_term(y, X, t, t < t[-1] * 0.65, feats)
    assert s.best is not None and not s.why_none
    assert s.best.names == ["mu2"]
    assert s.best.coef[1] == pytest.approx(0.04, rel=0.05)
    assert T.name_term(s.best, feats)["mechanism"] == "translational_lift"


def test_descent_loss_named_vortex_ring_only_in_its_range():
    y, X, t, feats = _synthetic({"descent": -0.06})
    s = T.find_term(y, X, t, t < t[-1] * 0.65, feats)
    assert s.best is not None and "descent" in s.best.names[0]
    # the synthetic flight descends at up to 1.5 "v_h": the loss lies in the vortex-ring band
    assert T.name_term(s.best, feats)["mechanism"] == "vortex_ring"
    # the same loss where the flight never descends faster than 0.4 v_h: not the vortex-ring state
    slow = feats.copy()
    slow[:, 3] *= 0.25
    slow[:, 4] *= 0.0625
    named = T.name_term(s.best, slow)
    assert named["mechanism"] is None and "unnamed term in throttle" in named["name"]


def test_a_loss_only_near_full_output_is_named_thrust_flattening():
    """A hinge-shaped loss (none below 0.75 of the top speed, 30 % at the top; not a feature of the library)
    is found in the rotor-speed features and named the flattening of the thrust curve."""
    y, X, t, feats = _synthetic(None, seed=3)
    u = np.sqrt(feats[:, STATE_TERM_FEATURES.index("omega2")])
    loss = -0.3 * (np.clip(u - 0.75, 0, None) / 0.25) ** 2
    y = y + loss * X[:, 0]
    s = T.find_term(y, X, t, t < t[-1] * 0.65, feats)
    assert s.best is not None and not s.why_none
    assert set(s.best.names) <= {"omega2", "omega4", "omega8"}
    assert T.name_term(s.best, feats)["mechanism"] == "thrust_flattening"


def test_no_term_in_noise():
    for seed in range(5):
        y, X, t, feats = _synthetic(None, seed=10 + seed)
        s = T.find_term(y, X, t, t < t[-1] * 0.65, feats)
        assert s.why_none, (seed, s.best.names, s.best.t_stat, s.best.cut)


def test_a_flight_too_short_for_the_held_out_test_says_so():
    y, X, t, feats = _synthetic({"mu2": 0.04}, n=150)       # 15 s: two 8-s groups
    s = T.find_term(y, X, t, t < 10, feats)
    assert s.best is None and "too little airborne data" in s.why_none


def test_plant_effects_are_outside_the_vocabulary():
    from twin_nodes.prove.oov_physics import PLANT_EFFECTS, plant_gain

    assert not set(PLANT_EFFECTS) & set(EFFECTS)
    # Glauert at mu = 1: v_i/v_h = sqrt(sqrt(1.25) - 0.5) = 0.786; gain 1 + 0.5 (1 - 0.786)
    g = plant_gain("translational_lift", {"k": 0.5, "v_h": 5.0}, np.array([5.0, 0.0, 0.0]), np.ones(4))
    assert g == pytest.approx(1 + 0.5 * (1 - math.sqrt(math.sqrt(1.25) - 0.5)))
    # vortex ring: the full loss at the peak descent, none in a climb
    assert plant_gain("vortex_ring", {"k": 0.25, "v_h": 5.0}, np.array([0, 0, -5.0]), np.ones(4)) == pytest.approx(0.75)
    assert plant_gain("vortex_ring", {"k": 0.25, "v_h": 5.0}, np.array([0, 0, 2.0]), np.ones(4)) == pytest.approx(1.0)
    fl = plant_gain("thrust_flattening", {"k": 0.3, "u0": 0.7, "omega_max": 1000.0}, np.zeros(3),
                    np.array([600.0, 700.0, 850.0, 1000.0]))
    np.testing.assert_allclose(fl, [1.0, 1.0, 1 - 0.3 * 0.25, 0.7])


def test_manifest_declares_every_mechanism_and_none_on_the_same_missions():
    from twin_nodes.prove.oov import load_manifest

    flights = load_manifest()
    for gen in ("ours", "rotorpy"):
        mine = [f for f in flights if f["generator"] == gen]
        assert {f["mechanism"] for f in mine} == {"translational_lift", "vortex_ring", "thrust_flattening", "none"}
        assert len({f["mission"] for f in mine}) == 1
    assert len({f["seed"] for f in flights}) == len(flights)
    assert any(f["split"] == "judge" for f in flights)


@pytest.mark.slow
@pytest.mark.parametrize("mechanism", ["vortex_ring", "none"])
def test_term_found_named_and_flown_on_a_tune_flight(tmp_path, mechanism):
    """End to end on the manifest's tune flights (our generator): the vortex-ring flight gives a
    confirmed term named the vortex-ring state whose flown version lowers the closed-loop twin's
    held-out throttle RMSE by >= 30 %; its no-effect twin flight gives no term."""
    from twin_nodes.discovery.discover import discover
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.prove.oov import cached_flight, load_manifest, nominal_for, score_oov

    f = next(f for f in load_manifest() if f["split"] == "tune" and f["generator"] == "ours"
             and f["mechanism"] == mechanism)
    path, _ = cached_flight(f, tmp_path)
    res = discover(read_ulog(path), nominal_for(f), closed_loop_metrics=True)
    row = score_oov(f, res)
    assert row["named_right"], row
    if mechanism == "none":
        assert row["term"] is None and res["terms"]["verdict"] in ("none", "rejected")
    else:
        assert row["term_mechanism"] == "vortex_ring"
        assert row["closed_loop_throttle_cut"] >= 0.30, row
        term = next(e for e in res["effects"] if e["name"] == "state_term")
        assert term["verdict"] == "confirmed" and term["params"]["c_descent2"] < 0


def test_a_term_odd_in_vertical_speed_is_named_a_vertical_drag():
    y, X, t, feats = _synthetic({"climb": 0.05, "descent": -0.05})
    s = T.find_term(y, X, t, t < t[-1] * 0.65, feats)
    assert s.best is not None and set(s.best.names) == {"climb", "descent"}
    named = T.name_term(s.best, feats, weight_n=9.81, v_h=5.0)
    assert named["mechanism"] == "vertical_drag"
    # thrust +5 % per v_h of climb rate on a 9.81 N vehicle with v_h 5 m/s: the model's drag 0.098 N/(m/s) too strong
    assert "0.098" in named["evidence"] and "too strong" in named["evidence"]


def test_a_stage_9_term_ranks_after_the_vocabularys_findings():
    from twin_nodes.prove.scoring import findings

    res = {"effects": [{"name": "inertia", "verdict": "likely"}, {"name": "state_term", "verdict": "confirmed"}]}
    assert [e["name"] for e in findings(res)] == ["inertia", "state_term"]


def test_oov_scoring_rules():
    from twin_nodes.prove.oov import score_oov, summarise

    def res(term=None):
        found = [term] if term else []
        return {"effects": [], "terms": {"found": found, "test": {"chosen": []}}}

    lift = {"generator": "ours", "mechanism": "translational_lift", "mission": "OOV1", "seed": 1, "split": "judge"}
    none = dict(lift, mechanism="none", seed=2)
    cl = {"before": {"throttle_rmse": 0.04}, "after": {"throttle_rmse": 0.02}}
    good = {"verdict": "confirmed", "mechanism": "translational_lift", "label": "translational lift",
            "features": ["mu"], "closed_loop_heldout": cl, "closed_loop_throttle_cut": 0.5, "heldout_improvement": 0.8}
    rows = [score_oov(lift, res(good)),                                       # named right, cut 50 %
            score_oov(dict(lift, seed=3), res(dict(good, verdict="rejected"))),   # found, not kept: not named
            score_oov(dict(lift, seed=4), res(dict(good, mechanism=None, label="unnamed term"))),
            score_oov(none, res()),                                           # no term: right
            score_oov(dict(none, seed=5), res(dict(good, mechanism=None)))]   # a term on a no-effect flight
    assert [r["named_right"] for r in rows] == [True, False, False, True, False]
    s = summarise(rows)["judge"]
    assert (s["named_right"], s["flights"], s["effect_flights_cut_ge_30pct"], s["effect_flights"],
            s["terms_on_no_effect_flights"]) == (2, 5, 1, 3, 1)


def test_a_term_judged_on_a_diverged_closed_loop_twin_says_so():
    """A RotorPy flattening flight whose vehicle saturated lost its heading in the twin before and after the term
    (judge4 2813: heading at 19.1 s and 19.4 s): the term's closed-loop numbers then compare runs that left the
    flight, and the entry and the oov table say so instead of showing a bare cut."""
    from twin_nodes.discovery.stages.terms import _diverged
    from twin_nodes.prove.oov import format_table

    before = {"divergence": {"t_s": 19.08, "cause": "heading"}}
    after = {"divergence": {"t_s": 19.36, "cause": "heading"}}
    assert _diverged(before, after) == "before: heading at 19.1 s; after: heading at 19.4 s"
    assert _diverged({"divergence": None}, {}) == ""
    row = {"flight": "rotorpy_thrust_flattening_OOVR_2813", "split": "judge4", "truth": "thrust_flattening",
           "term": "thrust-curve flattening", "term_verdict": "confirmed", "named_right": True,
           "closed_loop_throttle_cut": -0.48, "vocabulary_findings": [],
           "closed_loop_diverged": _diverged(before, after)}
    text = format_table({"rows": [row]})
    assert "-48 %d" in text and "2813 (before: heading at 19.1 s; after: heading at 19.4 s)" in text


def test_a_term_must_cut_the_held_out_part_as_flown():
    """Stage 9's second, independent test: the term as flown (fitted on the fit part) must cut the flight's
    held-out part by >= 10 %, like every vocabulary effect. PX4 SIH no-effect y023 (judge4, orbit M6): the
    search's best of 8 sets, mu2 + climb, had t 3.72 over 52 blocks and a 17 % out-of-fold cut, but its flown
    version took the held-out throttle RMS from 0.02704 to 0.03136 (-16 %): rejected. A real term (ours 2721,
    translational lift: t 5.87, out-of-fold cut 70 %, held-out cut 81 %) stays confirmed; t006's ground effect
    (t 2.8, out-of-fold 31 %, held-out 29 %) stays likely."""
    from twin_nodes.discovery.stages.terms import _verdict

    def fit(t, cut, spread=0.05):
        return T.TermFit((0,), np.zeros(2), 1.0, 0.1, t_stat=t, n_blocks=52, cut=cut, gain_spread=spread)

    y023_cut = round(1.0 - 0.03136 / 0.02704, 4)
    assert y023_cut == pytest.approx(-0.1598, abs=1e-4)
    verdict, why = _verdict(fit(3.72, 0.1692), y023_cut, [])
    assert verdict == "rejected" and len(why) == 1 and "-16 % < 10 %" in why[0]
    assert _verdict(fit(5.87, 0.6992), 0.8135, []) == ("confirmed", [])
    assert _verdict(fit(2.8, 0.3102), 0.2886, [])[0] == "likely"
    # a likely term whose flown version does not cut the held-out part is not kept either
    assert _verdict(fit(2.8, 0.3102), 0.05, [])[0] == "rejected"
    # the cut bar sits at MIN_REL_IMPROVEMENT exactly
    assert _verdict(fit(3.72, 0.17), 0.10, [])[0] == "confirmed"
    assert _verdict(fit(3.72, 0.17), 0.0999, [])[0] == "rejected"
    # a closed-loop veto still rejects
    assert _verdict(fit(5.0, 0.5), 0.5, ["makes the closed-loop twin worse on the held-out part (x)"])[0] == "rejected"


def test_a_confirmed_term_carries_its_joint_refit_to_the_accepted_findings():
    """RotorPy o016 (body drag c_dz 0.0836 + ground effect 0.4 / 0.841 m): the body drag only likely, the ground
    effect fitted with the nominal vertical drag read 0.3835 / 0.9407 m (11.8 % off); the confirmed state term
    (climb multiplier -0.089) refitted jointly with it flies 0.4106 / 0.8764 m (4.2 %): the finding reports that,
    the values before the term kept; a finding the refit did not move and a likely one are left alone."""
    from twin_nodes.discovery.stages.terms import carry_to_findings

    vp = shipped("px4_sih_quadx").with_effect("ground_effect", coefficient=0.4106, height_scale=0.8764)
    vp = vp.with_effect("yaw_moment", km=0.02)
    ge = {"name": "ground_effect", "accepted": True, "params": {"coefficient": 0.3835, "height_scale": 0.9407}}
    yaw = {"name": "yaw_moment", "accepted": True, "params": {"km": 0.02}}
    drag = {"name": "body_drag", "accepted": False, "params": {"c_dx": 0.0, "c_dy": 0.047, "c_dz": 0.0829}}
    result = {"effects": [ge, yaw, drag]}
    carry_to_findings(result, vp)
    assert ge["params"] == pytest.approx({"coefficient": 0.4106, "height_scale": 0.8764})
    assert ge["params_before_term"] == {"coefficient": 0.3835, "height_scale": 0.9407}
    assert ge["refitted_jointly_with"] == "state_term"
    assert abs(ge["params"]["height_scale"] / 0.8415 - 1) == pytest.approx(0.0415, abs=1e-3)
    assert "params_before_term" not in yaw and "params_before_term" not in drag
    assert drag["params"]["c_dz"] == 0.0829
