"""One twin per vehicle across its flights (issue 25): steps beyond the scatter band, what a step means,
flight kinds and PWM ranges read from real logs, the pooled vehicle twin."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

from twin_nodes.fleet import changes as ch
from twin_nodes.fleet.facts import flight_kind, motor_pwm, param_changes
from twin_nodes.identify.vehicle_twin import pool

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "flightlogs" / "fleet_quadx_v6c"
need_shared = pytest.mark.skipif(not SHARED.is_dir() and os.environ.get("CI") != "true",
                                 reason="../shared/flightlogs/fleet_quadx_v6c not present")


def _noisy(n, level, sigma, seed):
    return list(level + np.random.default_rng(seed).normal(0.0, sigma, n))


def test_a_step_on_two_flights_is_found_at_its_first_flight_a_single_excursion_is_not():
    x = _noisy(6, 5.0, 0.03, 1) + _noisy(5, 5.0 / 1.2, 0.03, 2) + _noisy(6, 5.0, 0.03, 3)
    x[3] = 4.0  # one flight off, the next one back: an excursion, no step
    s = ch.find_steps("kt_per_mass", x)
    assert [st.first for st in s.steps] == [6, 11]
    assert s.steps[0].ratio == pytest.approx(1 / 1.2, rel=0.02)
    assert s.steps[1].new == pytest.approx(5.0, rel=0.02)
    assert s.excursions == [3]


def test_no_step_on_an_unchanged_vehicle():
    for seed in range(20):
        assert ch.find_steps("kt_per_mass", _noisy(30, 5.0, 0.05, seed)).steps == []


def test_scatter_is_robust_to_a_step():
    x = np.array(_noisy(20, 1.0, 0.01, 4) + _noisy(20, 2.0, 0.01, 5))
    assert ch.scatter(x) == pytest.approx(0.01, rel=0.4)


@pytest.mark.parametrize("ratios,name", [
    ({"kt_per_mass": (0.833, 0.01), "roll_eff": (1.01, 0.03), "pitch_eff": (0.99, 0.03)}, "mass"),
    ({"kt_per_mass": (0.90, 0.01), "roll_eff": (0.90, 0.02), "pitch_eff": (0.91, 0.02)}, "thrust"),
    ({"kt_per_mass": (1.00, 0.01), "roll_eff": (0.77, 0.02), "pitch_eff": (0.77, 0.02)}, "inertia"),
    ({"kt_per_mass": (1.00, 0.01), "roll_eff": (1.0, 0.02), "yaw_eff": (1.4, 0.02)}, "yaw moment"),
    ({"kt_per_mass": (0.85, 0.01), "roll_eff": (0.9, 0.3)}, "thrust per mass"),
    ({"kt_per_mass": (0.85, 0.01)}, "thrust per mass"),
])
def test_explain_tells_mass_from_thrust_by_the_control_effectiveness(ratios, name):
    got, why = ch.explain(ratios)
    assert got == name, why


def test_explain_names_a_pwm_range_change_and_a_weak_motor_and_a_com_shift():
    name, why = ch.explain({"kt_per_mass": (1.19, 0.02)}, pwm=(1000.0, 1200.0))
    assert name == "thrust range" and "x1.200" in why
    shares = {"motor_share_m1": (0.0, 0.01), "motor_share_m2": (0.004, 0.01), "motor_share_m3": (0.15, 0.01),
              "motor_share_m4": (-0.01, 0.01)}
    assert ch.explain({"kt_per_mass": (1.0, 0.01)}, shares)[0] == "weaker motor 3"
    assert ch.explain({"kt_per_mass": (1.0, 0.01)}, {"com_dx_m": (0.02, 0.002)})[0] == "centre-of-mass shift"


def test_file_name_dates_are_corrected_by_the_vehicles_local_offset():
    rows = [{"file_name_time": "2023-06-21T09:59:04", "date_source": "gps", "flight_time_utc": "2023-06-21T07:58:29+00:00"},
            {"file_name_time": "2023-06-21T08:28:14", "date_source": "file_name", "flight_time_utc": "2023-06-21T08:28:14"}]
    off = ch.local_offset_h(rows)
    assert off == 2.0
    assert ch.when_utc(rows[1], off) == "2023-06-21T06:28:14+00:00"


def test_motor_pwm_reads_the_outputs_assigned_to_motors():
    p = {"PWM_MAIN_FUNC1": 101, "PWM_MAIN_FUNC2": 102, "PWM_AUX_FUNC5": 101, "PWM_AUX_FUNC6": 102,
         "PWM_MAIN_MIN1": 1000, "PWM_MAIN_MAX1": 2000, "PWM_MAIN_MIN2": 1000, "PWM_MAIN_MAX2": 2000,
         "PWM_AUX_MIN5": 1000, "PWM_AUX_MAX5": 2200, "PWM_AUX_MIN6": 1000, "PWM_AUX_MAX6": 2200, "PWM_AUX_FUNC1": 430}
    m = motor_pwm(p, 2)
    assert m["text"] == "AUX5-6 1000-2200 us; MAIN1-2 1000-2000 us"
    assert math.isnan(m["max_us"])
    p2 = {k: v for k, v in p.items() if not k.startswith("PWM_MAIN")}
    assert motor_pwm(p2, 2)["max_us"] == 2200.0
    assert param_changes({"A": 1.0, "CAL_X": 1}, {"A": 2.0, "CAL_X": 2, "B": 3.0}) == {"A": [1.0, 2.0], "B": [None, 3.0]}


def test_pool_names_a_disagreeing_flight_and_leaves_it_out():
    names = [f"f{i}" for i in range(6)]
    x = [5.0, 5.05, 4.97, 5.02, 4.15, 4.99]
    p = pool("kt_per_mass", names, x, [0.01] * 6)
    assert p.n == 5 and p.disagreeing and p.disagreeing[0].startswith("f4 ")
    assert p.mean == pytest.approx(np.mean([5.0, 5.05, 4.97, 5.02, 4.99]))
    assert p.scatter == pytest.approx(np.std([5.0, 5.05, 4.97, 5.02, 4.99], ddof=1))


@need_shared
@pytest.mark.parametrize("rel,kind", [
    ("23_juni/log_11_2023-6-23-10-13-50.ulg", "ground/bench test"),   # never airborne
    ("23_juni/log_14_2023-6-23-10-20-00.ulg", "too short"),           # 4 s airborne
    ("DritterFlugtag/log_65_2023-6-21-08-36-08.ulg", "no GPS"),
    ("ZweiterFlugtag/log_30_2023-6-7-12-11-06.ulg", "free flight"),
])
def test_flight_kinds_of_the_real_fleet(rel, kind):
    from twin_nodes.fleet.facts import actuator_tests
    from twin_nodes.logs.ulog_io import read_ulog

    p = SHARED / rel
    assert flight_kind(read_ulog(p), actuator_tests(str(p)))[0] == kind


@need_shared
def test_the_pwm_range_change_of_21_june_is_read_from_the_log():
    from twin_nodes.logs.ulog_io import read_params

    before = motor_pwm(read_params(SHARED / "DritterFlugtag/log_65_2023-6-21-08-36-08.ulg"), 4)
    after = motor_pwm(read_params(SHARED / "DritterFlugtag/log_70_2023-6-21-09-59-04.ulg"), 4)
    assert (before["min_us"], before["max_us"]) == (1000.0, 2000.0)
    assert (after["min_us"], after["max_us"]) == (1000.0, 2200.0)
