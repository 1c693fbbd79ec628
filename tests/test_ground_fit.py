"""The ground effect's law, its truth's parameterization on the RotorPy grid and its whole-flight fit
(twin_nodes/discovery/stages/ground.py, issue 26)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from twin_nodes.discovery.stages import ground
from twin_nodes.physics.model import Multirotor

GRID_CACHE = Path.home() / ".cache" / "rotortwin" / "grids" / "rotorpy"


@pytest.mark.parametrize("h, expected", [(0.0, 1.4), (0.15, 1 + 0.4 * math.exp(-1.0)), (-0.2, 1.4),
                                         (0.45, 1 + 0.4 * math.exp(-3.0))])
def test_gain_closed_form_matches_the_twin_kernel(h, expected):
    from twin_nodes.vehicle.params import shipped

    assert ground.gain(0.4, 0.15, h) == pytest.approx(expected, rel=1e-12)
    vp = shipped("rotorpy_crazyflie")
    m0, m1 = Multirotor(vp), Multirotor(vp.with_effect("ground_effect", coefficient=0.4, height_scale=0.15))
    omega = np.full(vp.rotors.count, 0.8 * vp.hover_omega_rad_s)
    f = [m.wrench_terms(m.initial_state(position_enu=(0.0, 0.0, h), rotor_state=omega))["rotors"][0][0][2]
         for m in (m0, m1)]
    assert f[1] / f[0] == pytest.approx(expected, rel=1e-12)


def test_rotorpy_grid_truth_is_the_twin_law_in_the_same_parameters():
    """The grid multiplies RotorPy's k_eta by 1 + c exp(-h/h_s) (h: the CoM's z over the ground plane z = 0,
    clipped at 0) and states (coefficient c, height_scale h_s): the twin's law, coefficient at zero height."""
    pytest.importorskip("rotorpy", reason="RotorPy (dev dependency) not installed")
    from twin_nodes.prove import grid_rotorpy as g

    qp = g.rf.rotorpy_params("crazyflie")
    change = g.plant_change("ground_effect", 1, qp, seed=7)
    c, hs = change["ground"]
    assert change["hidden"].params == {"coefficient": c, "height_scale": hs}
    assert c == 0.4 and hs == pytest.approx(3.5 * g._arm(qp), rel=1e-12)


def test_pinned_tells_a_low_hover_from_a_sweep():
    rng = np.random.default_rng(3)
    hover = 0.15 + 0.005 * rng.standard_normal(500)          # 10 s at one low height
    out = ground.pinned(hover, 0.4, 0.15, 0.02)
    assert out["determined"] is False and out["low_s"] == pytest.approx(10.0) and out["spread_scales"] < 0.05
    assert out["gain_at_h_ref"] == pytest.approx(0.4 * math.exp(-out["h_ref_m"] / 0.15), abs=1e-3)
    assert "two low heights" in out["note"]
    sweep = np.linspace(0.0, 0.6, 300)                        # a climb through the whole reach
    out = ground.pinned(sweep, 0.4, 0.15, 0.02)
    assert out["determined"] is True and out["low_s"] == pytest.approx(0.02 * (sweep < 0.45).sum())
    assert 0.45 < out["spread_scales"] < 0.55       # exp(-2h/h_s)-weighted: an exponential of std h_s / 2
    none = ground.pinned(np.full(10, 2.0), 0.4, 0.15, 0.02)
    assert none["determined"] is False and none["low_s"] == 0.0


def test_seen_crazyflie_flight_whole_flight_fit_r044():
    """r044 (batch 1, seen): Crazyflie, ground effect 0.4 / 0.15 m.  Fold 1 holds little low flight and
    slides along the ridge (0.487 / 0.138 until the eighth session; 0.373 / 0.156 since its climb-out is read,
    ``residuals.contact_pads``); the whole flight's fit is within 5 % on both."""
    path = GRID_CACHE / "r044.ulg"
    if not path.is_file():
        pytest.skip(f"RotorPy grid flight not fetched: {path} (tools/fly_grids.sh)")
    pytest.importorskip("rotorpy", reason="RotorPy (dev dependency) not installed")
    from twin_nodes.discovery.candidates import build_candidates
    from twin_nodes.discovery.judging import Fit, fit_candidate
    from twin_nodes.discovery.stages.prepare import prepare_flight
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.prove import rotorpy_flights as rf

    vp = rf.nominal_params(rf.rotorpy_params("crazyflie"), "rotorpy_crazyflie")
    flight = prepare_flight(read_ulog(path), vp, output_error=False)
    c = next(c for c in build_candidates(vp, flight.data) if c.name == "ground_effect")
    fold1, _, _ = fit_candidate(c, flight.eq, vp, flight.eq.folds[0][0])
    f = Fit(c, fold1, c.build(fold1), 0.0, 0.0, np.zeros(1), 0.0, 0, 0.0, True, accepted=True)
    f.fold_thetas = [fold1]
    out = ground.refit_accepted(flight, [f], vp)
    p = f.candidate.params_dict(f.theta)
    assert abs(p["coefficient"] / 0.4 - 1) < 0.05 and abs(p["height_scale"] / 0.1505 - 1) < 0.05
    assert fold1[0] == pytest.approx(0.373, abs=0.005)   # what fold 1 alone reports: 6.8 % low
    assert abs(p["coefficient"] / 0.4 - 1) < abs(fold1[0] / 0.4 - 1)
    assert f.ground_fit["fold_params"][0]["coefficient"] == pytest.approx(fold1[0])
    assert dict(dict(out.effects)["ground_effect"])["coefficient"] == pytest.approx(p["coefficient"])


def test_a_low_hover_reads_the_ridge_with_its_uncertainty_i014():
    # i014 (batch 12: Crazyflie sag + ground effect 0.4 / 0.1505 m, hover with yaw): 11 s within reach, the low
    # hover at 0.16 m (spread 0.154 height scales): the whole flight read 0.357 / 0.170 (10.7 / 12.7 % off), the
    # folds 0.394 / 0.146 and 0.349 / 0.173; their extra thrust at 0.157 m 0.1346 / 0.1409 (4.5 % apart)
    pin = {"h_ref_m": 0.157, "spread_scales": 0.154}
    folds = [{"coefficient": 0.39369, "height_scale": 0.14633}, {"coefficient": 0.34911, "height_scale": 0.17300}]
    r = ground.along_ridge(pin, {"coefficient": 0.35708, "height_scale": 0.16966}, folds)
    assert r["gain_rel"] == pytest.approx(0.0452, abs=5e-4)
    t = ground.RIDGE_T                                  # two folds: one degree of freedom (x1.837, par18)
    assert r["height_scale_rel"] == pytest.approx(t * 0.0452 / 0.154, abs=0.01)       # 29 % bare, 54 %
    assert r["coefficient_rel"] == pytest.approx(t * math.hypot(0.0452, 0.157 / 0.16966 * 0.294), abs=0.01)  # 51 %
    lo, hi = r["coefficient_range"]
    assert lo < 0.4 < hi and hi == pytest.approx(0.5378, abs=2e-3)                     # the truth inside
    lo, hi = r["height_scale_range_m"]
    assert lo < 0.1505 < hi and lo == pytest.approx(0.0781, abs=2e-3)
    # folds on the same reading, agreeing on the extra thrust: a narrow range; no folds: nothing said
    same = [{"coefficient": 0.4, "height_scale": 0.15}, {"coefficient": 0.4, "height_scale": 0.15}]
    assert ground.along_ridge(pin, {"coefficient": 0.4, "height_scale": 0.15}, same)["height_scale_rel"] < 1e-3
    # q030 (batch 2, the same class): the folds agree on the extra thrust (0.4 %) but slid along the ridge
    q = ground.along_ridge({"h_ref_m": 0.155, "spread_scales": 0.167}, {"coefficient": 0.35801, "height_scale": 0.16770},
                           [{"coefficient": 0.41671, "height_scale": 0.14347},
                            {"coefficient": 0.35188, "height_scale": 0.16930}])
    assert q["gain_rel"] < 0.005 and q["height_scale_rel"] == pytest.approx(t * (1 - 0.14347 / 0.16770), abs=2e-3)
    assert q["coefficient_rel"] == pytest.approx(t * (0.41671 / 0.35801 - 1), abs=2e-3)          # 16 % bare, 30 %
    assert q["coefficient_range"][0] < 0.4 < q["coefficient_range"][1]
    assert q["height_scale_range_m"][0] < 0.1505 < q["height_scale_range_m"][1]
    assert ground.along_ridge(pin, {"coefficient": 0.4, "height_scale": 0.15}, []) is None
