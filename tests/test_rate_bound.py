"""The motor lag the flown rate gains bound, and the twin's discrete rate loop (identify/rate_bound.py)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from twin_nodes.identify.nominal import TAU_ASSUMED_S, _lag_for_flown_gains
from twin_nodes.identify.rate_bound import gain_margin, lag_bound, rate_loop_radius

ASSUMED_SRC = f"ASSUMED {TAU_ASSUMED_S} s (typical motor + ESC): the flight does not determine it"


def test_lag_bound_is_the_tighter_of_roll_and_yaw():
    assert lag_bound(125.0, 51.6) == pytest.approx(0.7 / 125.0)      # roll/pitch binds: 0.0056 < 0.3/51.6
    assert lag_bound(20.0, 30.0) == pytest.approx(0.3 / 30.0)        # yaw binds: 0.01 < 0.7/20
    assert lag_bound(0.0, 0.0) == float("inf")


def test_instant_motor_p_loop_radius_is_one_minus_kp_dt():
    # with a negligible lag the loop is w <- (1 - kp dt) w: radius |1 - kp dt|, unstable past kp dt = 2
    for kp_dt in (0.5, 1.5, 2.5):
        assert rate_loop_radius(kp_dt / 0.004, 0.0, 0.0, 1e-7, 0.004) == pytest.approx(abs(1 - kp_dt), abs=2e-3)  # 1e-6 s floor
    assert gain_margin(100.0, 0.0, 0.0, 1e-7, 0.004) == pytest.approx(5.0, rel=0.011)   # 2 / (100 * 0.004)
    assert gain_margin(600.0, 0.0, 0.0, 1e-7, 0.004) == 0.0                             # kp dt 2.4: unstable


def test_lag_and_d_term_change_the_margin_as_expected():
    # a slower motor lowers the margin of a P loop; PX4's D term (an added inertia) raises it at a slow lag
    assert gain_margin(125.0, 0.0, 0.0, 0.02, 0.004) < gain_margin(125.0, 0.0, 0.0, 0.002, 0.004)
    assert gain_margin(125.0, 125.0, 1.17, 0.05, 0.004) > 2 * gain_margin(125.0, 125.0, 0.0, 0.05, 0.004)


def _rate(kp, kp_yaw=1.0):
    return {"rate_p_1_s": kp, "rate_i_1_s2": kp, "rate_d": 0.01 * kp, "yawrate_p_1_s": kp_yaw,
            "yawrate_i_1_s2": 0.1 * kp_yaw}


def test_an_assumed_lag_keeps_px4s_gains_where_the_twins_loop_holds_them():
    src = {"rotors.tau_up_s/tau_down_s": ASSUMED_SRC}
    # 125 1/s at the assumed 0.05 s (Kp tau 6.25 > 0.7): the twin's 250 Hz loop still has a margin >= 2
    assert gain_margin(125.0, 125.0, 1.25, TAU_ASSUMED_S, 0.004) >= 2.0
    assert _lag_for_flown_gains(TAU_ASSUMED_S, _rate(125.0), src, 250.0) == (TAU_ASSUMED_S, None)
    assert "PX4's rate gains kept (roll/pitch 125" in src["rotors.tau_up_s/tau_down_s"]
    # gains the assumed lag holds anyway: nothing said, nothing capped
    src = {"rotors.tau_up_s/tau_down_s": ASSUMED_SRC}
    assert _lag_for_flown_gains(TAU_ASSUMED_S, _rate(10.0), src, 250.0) == (TAU_ASSUMED_S, "assumed lag")
    assert src["rotors.tau_up_s/tau_down_s"] == ASSUMED_SRC


def test_an_identified_lag_is_kept_and_absurd_gains_still_capped():
    src = {"rotors.tau_up_s/tau_down_s": "identified: lag explaining roll/pitch acceleration best, 0.050 s"}
    assert _lag_for_flown_gains(0.05, _rate(125.0), src, 250.0) == (0.05, "identified lag")
    # a conversion gone wrong (1.5e4 1/s, a prior inertia far off): the twin's 250 Hz loop cannot hold it
    src = {"rotors.tau_up_s/tau_down_s": ASSUMED_SRC}
    assert _lag_for_flown_gains(TAU_ASSUMED_S, _rate(1.46e4), src, 250.0) == (TAU_ASSUMED_S, "assumed lag")
    assert "gain margin of only 0 (< 2): they are capped" in src["rotors.tau_up_s/tau_down_s"]


TROPIC = Path(os.path.expanduser("~/.cache/rotortwin/corpus/judging/fr_tropic_ekf_failure.ulg"))


@pytest.mark.skipif(not TROPIC.is_file(), reason="corpus not fetched (rotortwin corpus fetch)")
def test_fr_tropic_keeps_px4s_rate_gains():
    from twin_nodes.identify.nominal import nominal_from_log
    from twin_nodes.logs.flyable import read_flight
    nom = nominal_from_log(read_flight(str(TROPIC), horizontal=False))
    c, r = nom.params.controller, nom.params.rotors
    assert c["rate_p_1_s"] == pytest.approx(125.0, rel=0.01)          # MC_ROLLRATE_P converted, not 14
    assert c["yawrate_p_1_s"] == pytest.approx(51.6, rel=0.01)
    assert r.tau_up_s == TAU_ASSUMED_S                                  # the lag is still the assumed one
    assert "capped" not in nom.sources["controller (rate loop)"]
