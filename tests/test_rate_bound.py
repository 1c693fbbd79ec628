"""The motor lag the flown rate gains bound, and the twin's discrete rate loop (identify/rate_bound.py)."""
from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from conftest import shared_log
from twin_nodes.identify.nominal import TAU_ASSUMED_S
from twin_nodes.identify.rate_bound import gain_margin, rate_loop_radius


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


def _nominal(path):
    from twin_nodes.identify.nominal import nominal_from_log
    from twin_nodes.logs.flyable import read_flight
    return nominal_from_log(read_flight(str(path), horizontal=False))


def _margin(text: str) -> float:
    return float(re.search(r"gain margin of ([0-9.e+]+) in the twin", text).group(1))


def test_a_cap_at_an_assumed_lag_says_so_and_gives_px4s_margin():
    # the S500 flies MC_ROLLRATE_P that converts to 27.5 1/s (with the inertia and thrust slope identified off its
    # take-off spot; 24.2 with them on it); its lag is ASSUMED 0.05 s, so 0.7/tau = 14
    nom = _nominal(shared_log("real", "real_s500_rcac_mission1.ulg"))
    c, src = nom.params.controller, nom.sources["controller (rate loop)"]
    assert nom.sources["rotors.tau_up_s/tau_down_s"].startswith(f"ASSUMED {TAU_ASSUMED_S}")
    assert c["rate_p_1_s"] == pytest.approx(0.7 / TAU_ASSUMED_S)
    assert "capped at 14 (0.7/tau for the ASSUMED lag; PX4's gains would keep a gain margin of" in src
    kp = float(re.search(r"rate_p_1_s ([0-9.]+) capped", src).group(1))
    assert kp == pytest.approx(27.5, abs=0.05)
    assert _margin(src) >= 2.0                                           # the twin's loop would hold PX4's gains


TROPIC = Path(os.path.expanduser("~/.cache/rotortwin/corpus/judging/fr_tropic_ekf_failure.ulg"))


@pytest.mark.skipif(not TROPIC.is_file(), reason="corpus not fetched (rotortwin corpus fetch)")
def test_fr_tropic_cap_and_the_margin_px4s_gains_keep():
    nom = _nominal(TROPIC)
    c, src = nom.params.controller, nom.sources["controller (rate loop)"]
    assert c["rate_p_1_s"] == pytest.approx(14.0)                       # 125 1/s capped at 0.7 / 0.05
    assert "rate_p_1_s 125 capped at 14 (0.7/tau for the ASSUMED lag" in src
    assert _margin(src) == pytest.approx(15.0, abs=0.5)                 # 125/125/1.17 at 0.05 s, 250 Hz


def test_the_margin_is_computed_at_the_twins_controller_rate():
    from twin_nodes.identify.nominal import TWIN_CONTROL_HZ
    from twin_nodes.twin.control import ControllerGains
    assert TWIN_CONTROL_HZ == ControllerGains().rate_hz
