"""Issue 26, two effects at once: what the forward selection re-offers after the first acceptance (round 2 refits
every candidate, round 1's output-error cuts rescaled to the residual left, a fit that moved and failed
cross-validation is not pruned), with numbers; and, where the declared RotorPy grid's flights are cached, two of
its two-effect flights found whole."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from twin_nodes.discovery.judging import PRUNE_GAIN
from twin_nodes.discovery.stages import candidates, selection


def _fit(cut: float, above_floor: bool = True, at_bound: bool = False):
    return SimpleNamespace(rel_improvement=cut, above_floor=above_floor, at_bound=at_bound)


def test_a_fit_that_moved_and_failed_is_not_pruned():
    # r057 (rotor drag beside a 13 % thrust deficit): the drag fitted the throttle error with its vertical
    # term, moved above its floor and lost 23 % on held-out data: kept for the rounds after the first acceptance
    assert selection._first_gain([_fit(-0.231)]) == PRUNE_GAIN
    # one that stayed at nominal (below its floor) explained nothing: its own cut, pruned
    assert selection._first_gain([_fit(-0.001, above_floor=False)]) == -0.001
    # one pinned at the edge of the physical range is not a fit that moved: pruned
    assert selection._first_gain([_fit(-0.2, at_bound=True)]) == -0.2
    # a real cut is its own, the best over the residuals
    assert selection._first_gain([_fit(0.05), _fit(0.30, above_floor=False)]) == 0.30


def test_output_error_cut_read_against_the_output_error_left():
    # r071's numbers (battery sag with a 1.5x yaw moment): round 1's yaw-moment output-error cut 1.11 %, the
    # output error's mean square 2240.16 before the sag, 349.99 after it: 2.2 % of the energy then is 14.1 %
    # now, a cut of 1 - sqrt(1 - 0.1418) = 7.36 %, above the 2 % the judge refits on
    g = selection._oe_gain_now({"yaw_moment": 0.0111, "actuator_delay": 0.0}, (0.0158, 2240.16), (0.0016, 349.99))
    e1 = 1 - (1 - 0.0111) ** 2
    assert g["yaw_moment"] == pytest.approx(1 - np.sqrt(1 - e1 * 2240.16 / 349.99), rel=1e-9)
    assert g["yaw_moment"] == pytest.approx(0.0736, abs=5e-4) and g["yaw_moment"] > 0.02
    assert g["actuator_delay"] == 0.0
    # the equation error's energy ratio (10x here) does not enter the output error's
    assert selection._oe_gain_now({"a": 0.01}, (1.0, 5.0), (0.1, 5.0))["a"] == pytest.approx(0.01)


def test_round_two_refits_every_candidate_round_three_prunes():
    from twin_nodes.vehicle.params import shipped

    vp = shipped("px4_sih_quadx")
    n = 500
    data = SimpleNamespace(v=np.tile([[3.0, 0.0, 0.0]], (n, 1)), valid=np.ones(n, bool), motor_dt_s=0.004,
                           dt=0.02, height=np.full(n, 10.0), battery_v=np.full(n, np.nan))
    everything = candidates.run(candidates.CandidateQuery(vp, data, 1))
    labels = {c.label for c in everything.first + everything.richer}
    assert "body_drag" in labels and "mass" in labels
    nothing = {lab: 0.0 for lab in labels}
    r2 = candidates.run(candidates.CandidateQuery(vp, data, 2, {"mass"}, nothing))
    assert {c.label for c in r2.first + r2.richer} == labels - {"mass"}
    r3 = candidates.run(candidates.CandidateQuery(vp, data, 3, {"mass"}, {**nothing, "body_drag": 0.05}))
    assert {c.label for c in r3.first + r3.richer} == {"body_drag"}


def _cand(name: str):
    from twin_nodes.discovery.candidates import build_candidates
    from twin_nodes.vehicle.params import shipped

    vp = shipped("px4_sih_quadx")
    n = 500
    data = SimpleNamespace(v=np.tile([[3.0, 0.0, 0.0]], (n, 1)), valid=np.ones(n, bool), motor_dt_s=0.004,
                           dt=0.02, height=np.full(n, 10.0), battery_v=np.full(n, np.nan))
    return next(c for c in build_candidates(vp, data) if c.name == name)


def test_parameters_moved_are_counted_per_own_parameter():
    # r070's two explanations: inertia (Ixx x1.151, Iyy at nominal, Izz x0.667) with mass x1.149 moves three
    # parameters; thrust coefficient 0.870 with a yaw moment moves two
    inertia, mass, kt, yaw = (_cand(n) for n in ("inertia", "mass", "thrust_coefficient", "yaw_moment"))
    f_in = SimpleNamespace(candidate=inertia, theta=inertia.x0 * np.array([1.151, 1.0, 0.667]))
    f_m = SimpleNamespace(candidate=mass, theta=mass.x0 * 1.149)
    f_kt = SimpleNamespace(candidate=kt, theta=np.array([0.870]))
    f_y = SimpleNamespace(candidate=yaw, theta=yaw.x0 * 1.72)
    assert selection._moved([f_in, f_m]) == 3 and selection._moved([f_kt, f_y]) == 2
    # within 3 % of nominal is not moved
    assert selection._moved([SimpleNamespace(candidate=mass, theta=mass.x0 * 1.02)]) == 0


def test_rival_path_only_beside_another_effect_with_the_rival_tied():
    mass = _cand("mass")
    lone = SimpleNamespace(candidate=mass, theta=mass.x0 * 1.1, alternatives=[{"name": "thrust_coefficient"}])
    other = SimpleNamespace(candidate=_cand("inertia"), theta=np.ones(3), alternatives=[])
    # one accepted effect: nothing to re-explain; the rival not tied: not offered (the selection is not rerun:
    # inp is never read)
    assert selection._rival_path(None, SimpleNamespace(accepted=[lone])) is None
    untied = SimpleNamespace(candidate=mass, theta=mass.x0 * 1.1, alternatives=[{"name": "battery_sag"}])
    assert selection._rival_path(None, SimpleNamespace(accepted=[other, untied])) is None


def test_a_rotorpy_yaw_moment_truth_is_torque_per_thrust_as_flown():
    pytest.importorskip("rotorpy", reason="RotorPy (dev dependency) not installed")
    from twin_nodes.prove import grid_prove, grid_rotorpy, rotorpy_flights

    flights = {f.id: f for f in grid_rotorpy.load_grid(half="all")}
    qp = rotorpy_flights.rotorpy_params("px4_sihsim_quadx")
    km0 = qp["k_m"] / qp["k_eta"]
    # r070: thrust coefficient 0.87 then yaw moment 1.5x: k_eta x0.87, k_m x1.5 (the yaw moment's replaces the
    # thrust's x0.87): km 1.5 / 0.87 of the nominal
    t = {tr.hidden.name: tr.hidden.params for tr in grid_prove.rotorpy_truths(flights["r070"])}
    assert t["thrust_coefficient"]["kt_scale"] == pytest.approx(0.87)
    assert t["yaw_moment"]["km"] == pytest.approx(km0 * 1.5 / 0.87, rel=1e-9)
    # a yaw moment alone: the declared factor (r047: level 2, 2x)
    (y,) = grid_prove.rotorpy_truths(flights["r047"])
    assert y.hidden.params["km"] == pytest.approx(km0 * 2.0, rel=1e-9)


def _rival(c, theta, cut, t, **kw):
    f = SimpleNamespace(candidate=c, theta=np.array(theta), kind="equation", rel_improvement=cut, t_stat=t,
                        above_floor=True, at_bound=False, unphysical=None, closed_loop=None, mode_cut=cut,
                        explains=cut, folds_agree=True, stats={"n": 8, "n_pos": 8})
    for k, v in kw.items():
        setattr(f, k.rstrip("_"), np.array(v) if k == "theta_" else v)
    return f


def test_a_rival_that_explains_more_but_is_not_yet_significant_is_listed():
    # q005's numbers (battery sag on a 10 s figure-eight): the rival cut 98 % at t 2.7, the winner 71 % at t 3.9
    from twin_nodes.discovery.candidates import build_candidates
    from twin_nodes.vehicle.params import shipped

    vp = shipped("px4_sih_quadx")
    n = 500
    data = SimpleNamespace(v=np.tile([[3.0, 0.0, 0.0]], (n, 1)), valid=np.ones(n, bool), motor_dt_s=0.004,
                           dt=0.02, height=np.full(n, 10.0), battery_v=np.full(n, np.nan))
    cands = {c.name: c for c in build_candidates(vp, data)}
    winner = _rival(cands["thrust_coefficient"], [0.869], 0.711, 3.89)
    rival = _rival(cands["mass"], [1.15], 0.984, 2.66)
    (alt,) = selection._better_but_unproven(winner, [winner, rival])
    assert alt["name"] == "mass" and alt["params"] == {"mass": 1.15} and alt["cv_improvement"] == 0.984
    assert alt["significant"] is False and alt["heldout_t_stat"] == 2.66
    # not listed: a smaller cut, a significant one (a plain alternative), another residual, the folds disagreeing,
    # blocks that do not favour it, a size still near nominal (half the change under the floor)
    for kw in ({"rel_improvement": 0.70}, {"t_stat": 3.2}, {"kind": "output"}, {"folds_agree": False},
               {"t_stat": 1.2}, {"theta_": [1.04]}):
        assert selection._better_but_unproven(winner, [winner, _rival(cands["mass"], [1.15], 0.984, 2.66, **kw)]) == []


# ------------------------------------------------------------------ the declared grid's flights (the cache's, flown where absent)

CACHE = Path.home() / ".cache" / "rotortwin" / "grids" / "rotorpy"


def _grid_flight(fid: str):
    pytest.importorskip("rotorpy", reason="RotorPy (dev dependency) not installed")
    from twin_nodes.prove import grid_prove, grid_rotorpy

    # flown into the cache first where absent or made by other code (7-25 s in RotorPy), never skipped;
    # batch 1 (r*) is the grid's "all", batch 2 (q*) its own manifest
    half = "judge2" if fid.startswith("q") else "all"
    grid_rotorpy.cached_flight(next(f for f in grid_rotorpy.load_grid(half=half) if f.id == fid), CACHE)
    jobs, _ = grid_prove.rotorpy_jobs(half, CACHE)
    return grid_prove.run_one(next(j for j in jobs if j[1].id == fid))


@pytest.mark.slow
@pytest.mark.parametrize("fid,truth", [("r057", {"rotor_drag", "mass"}), ("r071", {"battery_sag", "yaw_moment"}),
                                       ("r070", {"thrust_coefficient", "yaw_moment"}),
                                       ("q017", {"motor_time_constant", "inertia"}),
                                       ("q034", {"battery_sag", "inertia"})])
def test_both_effects_of_a_two_effect_grid_flight(fid, truth):
    # r057: rotor drag + mass 1.15x (found as thrust coefficient 0.87 and body drag: drag class, k_eq within 10 %);
    # r071: battery sag + yaw moment 1.5x (before: the yaw moment was read as an inertia with izz alone);
    # r070: thrust coefficient 0.87 + yaw moment 1.5x, found as the mass reading (mass 1.15, km 0.030 scored in that
    #   reading: scoring.in_reading; before: inertia + mass; then an inertia whose never-excited
    #   Iyy moved to a third of nominal won the rival path; now that axis is held: the rival path);
    # q017: lag + inertia x1.6, both confirmed (the lag's stale pair carried the inertia fitted alone, Ixx +11 %);
    # q034: battery sag + inertia on a fast descent that never commands pitch (Iyy was read at 15 % of nominal)
    row, res = _grid_flight(fid)
    assert set(row["named"]) == truth, row["findings"]
    assert all(e is not None and e <= 0.10 for e in row["param_errors"].values()), row["param_errors"]
    assert row["passed"]
