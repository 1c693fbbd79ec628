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
from twin_nodes.fleet.vehicle_twin import pool

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


def test_a_new_level_may_scatter_by_a_fraction_of_its_step_two_unlike_excursions_stay_excursions():
    """The real fleet's 23 Jun gripper: CoM dx ~0 mm for months, then 112 and 96 mm on two flights in a row (16 mm
    apart, the band +-7.5 mm): a step of +104 mm (STEP_COHESION 0.25 of the step lets its flights differ by 26 mm);
    two same-side flights at 20 and 100 mm do not hold together as one level: excursions."""
    base = [0.001, -0.002, 0.0, 0.002, -0.001, 0.001, 0.0, -0.002]
    s = ch.find_steps("com_dx_m", base + [0.112, 0.096] + base[:3])
    assert [(st.first, st.last) for st in s.steps][:1] == [(8, 9)]
    assert s.steps[0].size == pytest.approx(0.104, abs=0.002) and s.excursions == []
    s = ch.find_steps("com_dx_m", base + [0.020, 0.100] + base[:3])
    assert s.steps == [] and s.excursions == [8, 9]


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
    # the SIH fleet's s21 (T_MAX back, x1.111): thrust per mass x1.113, effectiveness x1.046 +- 0.026, 0.010 from
    # halfway (1.0565): not told apart (it was named a mass); its s07 (mass x1.2): x1.071 +- 0.030, far from halfway
    ({"kt_per_mass": (1.113, 0.005), "rp_eff": (1.046, 0.026)}, "thrust per mass"),
    ({"kt_per_mass": (0.839, 0.006), "rp_eff": (1.071, 0.030)}, "mass"),
    ({"kt_per_mass": (1.113, 0.005), "rp_eff": (1.09, 0.026)}, "thrust"),
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
    back = {k: (-d[0], d[1]) for k, d in shares.items()}   # the same motor replaced: its share down alone
    name, why = ch.explain({"kt_per_mass": (1.0, 0.01)}, back)
    assert name == "stronger motor 3" and "x1.18" in why    # 1 / (1 - 0.15)
    # the patched SIH fleet's motor 3 at 0.85 put back (p10, shares against p06-p09): the others move together
    # by +1/3 of it, which the old "others within a fraction of it" test took for a pattern it does not name
    d = dict(zip(shares, [(0.034, 0.01), (0.026, 0.01), (-0.116, 0.01), (0.054, 0.01)]))
    name, why = ch.explain({"kt_per_mass": (1.0, 0.01)}, d)
    assert name == "stronger motor 3" and "x1.17" in why    # (1 + 0.038) / (1 - 0.116): the truth 1/0.85 = 1.18
    # a centre of mass 20 mm forward, 10 mm right (p13): every share moves, no single motor is named
    d = dict(zip(shares, [(0.16, 0.01), (-0.146, 0.01), (0.04, 0.01), (-0.06, 0.01)]))
    assert ch.explain({"kt_per_mass": (1.0, 0.01)}, d)[0] == "unexplained"
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


def test_for_flight_rescales_the_thrust_curve_by_the_pwm_span():
    from types import SimpleNamespace

    from twin_nodes.fleet.vehicle_twin import for_flight
    from twin_nodes.vehicle.params import shipped

    vp = shipped("px4_sih_quadx").replace_rotors(thr_mdl_fac=0.5)
    ref = {"pwm": {"text": "AUX5-8 1000-2000 us", "min_us": 1000.0, "max_us": 2000.0}}
    p = {f"PWM_AUX_FUNC{c}": 96 + c for c in range(5, 9)}
    p.update({f"PWM_AUX_MIN{c}": 1000.0 for c in range(5, 9)})
    p.update({f"PWM_AUX_MAX{c}": 2200.0 for c in range(5, 9)})
    log = SimpleNamespace(params=p, n_motors=4)
    out, note = for_flight(vp, ref, log)
    r = 1.2
    assert out.rotors.thrust_max_n == pytest.approx(vp.rotors.thrust_max_n * (0.5 * r * r + 0.5 * r))
    assert out.rotors.thr_mdl_fac == pytest.approx(0.5 * r * r / (0.5 * r * r + 0.5 * r))
    # the same command gives the thrust the old curve gives at r x the command
    u = 0.4
    t_new = out.rotors.thrust_max_n * (out.rotors.thr_mdl_fac * u * u + (1 - out.rotors.thr_mdl_fac) * u)
    t_old = vp.rotors.thrust_max_n * (0.5 * (r * u) ** 2 + 0.5 * r * u)
    assert t_new == pytest.approx(t_old)
    assert "span ratio 1.200" in note
    same = dict(p, **{f"PWM_AUX_MAX{c}": 2000.0 for c in range(5, 9)})
    assert for_flight(vp, ref, SimpleNamespace(params=same, n_motors=4)) == (vp, "")


@need_shared
def test_vehicle_twin_from_real_flights_and_what_changed_on_an_earlier_flight(tmp_path):
    """A twin pooled over three 26 Jun flights (PWM 1000-2200 us) carries its values with uncertainties; a
    7 Jun flight (1000-2000 us) is named a thrust-range change, read from the log's parameters."""
    from twin_nodes.fleet.vehicle_twin import build, read_vehicle_facts, since_twin
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.vehicle.params import load_params, write_params

    real = SHARED.parent / "real"
    paths = [SHARED / "LetzteTestsGerolfing/log_29_2023-6-26-13-34-56.ulg", real / "real_quadx_v6c_mission_noload.ulg",
             SHARED / "23_juni/log_11_2023-6-23-10-13-50.ulg"]
    vt = build([str(p) for p in paths])
    assert len(vt.used) == 2 and any("ground/bench test" in lo for lo in vt.left_out)
    assert vt.pwm["max_us"] == 2200.0
    kt = vt.pooled["kt_per_mass"]
    assert kt.n == 2 and kt.se > 0 and math.isfinite(kt.scatter)
    out = tmp_path / "vehicle.yaml"
    write_params(vt.params, out, vt.header)
    load_params(out)
    ref = read_vehicle_facts(out)
    assert ref["pooled"]["kt_per_mass"]["mean"] == pytest.approx(kt.mean)
    # the thrust is pooled at one pack voltage (the median of the two flights'), the sag and the trims are the
    # pooled ones, and no wind of either day's weather is kept
    at, v_ref = vt.pooled["kt_per_mass_at_v_ref"], vt.pooled["kt_v_ref"]
    assert vt.params.rotors.thrust_max_n == pytest.approx(vt.params.mass_kg * at.mean)
    eff = vt.params.to_ros_dict()["effects"]
    assert eff["battery_sag"]["v_ref"] == pytest.approx(v_ref.mean)
    assert eff["battery_sag"]["exponent"] == pytest.approx(vt.pooled["battery_exponent"].mean)
    assert eff["rotor_tilt"]["lever_m"] == pytest.approx(vt.pooled["yaw_lever_m"].mean)
    assert eff["com_offset"]["dx"] == pytest.approx(vt.pooled["com_dx_m"].mean)
    assert "wind" not in eff["enabled"]
    # measured 2026-11-28: the two flights' raw thrust per mass scatter by 0.47 m/s^2 (log_29 fitted at its own
    # pack voltage, mission_noload at its own); at 11.77 V with the pooled sag exponent 1.73 by 0.11
    assert kt.scatter == pytest.approx(0.474, abs=0.03)
    assert at.scatter == pytest.approx(0.114, abs=0.03) and at.scatter < 0.3 * kt.scatter
    assert v_ref.mean == pytest.approx(11.77, abs=0.05)
    assert at.mean == pytest.approx(5.16, rel=0.02)
    assert vt.pooled["yaw_lever_m"].mean == pytest.approx(-0.00517, abs=0.0005)
    old = SHARED / "ZweiterFlugtag/log_30_2023-6-7-12-11-06.ulg"
    got = since_twin(read_ulog(old), str(old), ref)
    assert got["name"].startswith("thrust range") and "1200 -> 1000 us" in got["why"], got
    # its motors are on MAIN1-4, the twin's on AUX5-8: another wiring, whose trims are not compared (main named a
    # centre-of-mass shift here, dy +7.7 mm)
    assert "motor outputs AUX5-8 in the twin, MAIN1-4 in this log" in got["why"]
    assert not any(k.startswith("com_") for k in got["differs"]) and "centre-of-mass" not in got["name"]
    # a flight's thrust per mass is compared at the twin's one pack voltage (11.77 V, exponent 1.73), not at its own:
    # measured 2026-11-28, 23 Jun log_20 fitted at 11.12 V reads 4.74 raw (x0.92 of the raw mean), 5.23 at 11.77 V
    # (x1.01: within the band); mission_2hops at 10.36 V reads 4.47 raw, 5.57 at 11.77 V
    p20 = SHARED / "23_juni/log_20_2023-6-23-11-05-22.ulg"
    got = since_twin(read_ulog(p20), str(p20), ref)
    assert got["values"]["kt_per_mass"] == pytest.approx(4.737, abs=0.05)
    assert got["kt_v_flight"] == pytest.approx(11.12, abs=0.05)
    assert got["kt_per_mass_at_twin_v"] == pytest.approx(4.737 * (11.77 / 11.12) ** 1.731, rel=0.02)
    assert got["kt_per_mass_at_twin_v"] == pytest.approx(5.23, abs=0.05) and "kt_per_mass" not in got["differs"]
    # the two flights' sag exponents agree within their uncertainty (chi^2 4.6 < 9; 6.6 before the take-off spot
    # was left out), so carrying log_20 0.65 V up adds the exponent's se (0.22; 0.27 before):
    # 5.23 x ln(11.77/11.12) x 0.22 = 0.066 to its band
    e = ref["pooled"]["battery_exponent"]
    assert e["consistent"] is True and e["se"] == pytest.approx(0.224, abs=0.03)
    assert got["kt_per_mass_at_twin_v_se"] == pytest.approx(
        got["kt_per_mass_at_twin_v"] * math.log(11.77 / 11.12) * e["se"], rel=0.05)
    assert got["kt_per_mass_at_twin_v_se"] == pytest.approx(0.066, abs=0.015)


def test_vehicle_report_names_a_payload_and_a_pwm_range_change_at_their_flights():
    """A synthetic vehicle: 14 flights, a payload (+20 % mass) on flights 4-7, the motor PWM range raised from
    2000 to 2200 us at flight 10 (the same command then gives x1.2 the thrust); one flight dated by its file name
    in local time (+2 h) sorts where its UTC time puts it."""
    import json as _json

    from twin_nodes.fleet import vehicle_report as vr

    rng = np.random.default_rng(7)
    rows = []
    for k in range(14):
        kt = 5.0 * (1 / 1.2 if 4 <= k <= 7 else 1.0) * (1.2 if k >= 10 else 1.0) * (1 + rng.normal(0, 0.005))
        eff = 200.0 * (1.2 if k >= 10 else 1.0) * (1 + rng.normal(0, 0.02))
        hi = 2200.0 if k >= 10 else 2000.0
        p = {f"PWM_MAIN_FUNC{c}": 100 + c for c in range(1, 5)}
        p.update({f"PWM_MAIN_MIN{c}": 1000.0 for c in range(1, 5)})
        p.update({f"PWM_MAIN_MAX{c}": hi for c in range(1, 5)})
        t = f"2023-06-{10 + k:02d}T10:00:00"
        rows.append({"path": f"/d/f{k:02d}.ulg", "status": "ok", "flight_kind": "free flight",
                     "flight_time_utc": t + "+00:00", "date_source": "gps", "file_name_time": "",
                     "params_json": _json.dumps(p), "motor_pwm": motor_pwm(p, 4)["text"],
                     "fact_kt_per_mass": kt, "fact_kt_per_mass_se": 0.01, "fact_rp_eff": eff, "fact_rp_eff_se": 3.0})
    rows[3].update(date_source="file_name", flight_time_utc="2023-06-13T12:00:00", file_name_time="2023-06-13T12:00:00")
    rows[2].update(file_name_time="2023-06-12T12:00:00")  # both dates: the local offset is +2 h
    res = vr.analyse_vehicle("v", rows)
    assert res["local_offset_h"] == 2.0
    assert [r["_utc"][:13] for r in res["rows"]][3] == "2023-06-13T10"
    got = [(c.flight, c.name) for c in res["changes"]]
    assert got == [("d/f04.ulg", "mass"), ("d/f08.ulg", "mass"), ("d/f10.ulg", "thrust range")], got
    assert "x1.200" in res["changes"][2].why
    assert [e["flight"] for e in res["events"]] == ["d/f10.ulg"]


def test_a_thrust_finding_on_a_flight_whose_values_name_a_mass_backs_no_alarm():
    """Discovery against the vehicle twin confirms kt_scale 0.85 on a payload flight (mass and thrust look alike in
    hover); the flight's values since the twin name a mass there, so only the flights that agree back an alarm."""
    import json as _json

    from twin_nodes.fleet.report import alarms

    def row(k, kt, since):
        eff = [{"name": "thrust_coefficient", "verdict": "confirmed", "params": {"kt_scale": kt}}] if kt else []
        return {"path": f"/f{k}.ulg", "status": "ok", "vehicle_id": "v", "flight_time_utc": f"2026-06-{k + 1:02d}",
                "nominal_mass_kg": 1.0, "params_is_vehicle_twin": True, "since_twin": since,
                "effects_json": _json.dumps(eff)}

    rows = [row(0, None, "none"), row(1, 0.85, "mass"), row(2, None, "none"), row(3, 0.88, "thrust")]
    [a] = alarms(rows)
    assert a.kind == "threshold" and a.flight == "f3.ulg" and a.flights == ["f3.ulg"]
    assert alarms(rows[:3]) == []


def test_prediction_rows_say_a_divergence():
    """tools/vehicle_twin_prediction.py: a twin that left the flight is said beside its numbers."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("vtp", Path(__file__).resolve().parents[1] / "tools" /
                                                  "vehicle_twin_prediction.py")
    vtp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(vtp)
    assert vtp._divergence({"divergence": {"t_s": 12.5, "cause": "attitude", "detail": "x"}}) == \
        "diverged: attitude at 12.5 s"
    assert vtp._divergence({"divergence": None}) == "" and vtp._divergence({}) == ""
    m = vtp._metrics({"throttle_rmse": 0.02, "motor_p75": [0.01, float("nan"), 0.05], "xy_rmse_m": 0.3})
    assert m["motor_p75_max"] == 0.05 and math.isnan(m["z_rmse_m"])


def _fl(k, when, pwm, kt, dx=0.0):
    return {"path": f"/v/f{k:02d}.ulg", "name": f"f{k:02d}", "when": when, "pwm": {"text": pwm},
            "facts": {"kt_per_mass": kt, "kt_per_mass_se": 0.02, "com_dx_m": dx, "com_dx_m_se": 0.001,
                      "com_dy_m": 0.0, "com_dy_m_se": 0.001}}


def test_vehicle_twin_is_the_vehicle_as_it_last_flew():
    """Eight flights on the old PWM range (the majority), then four on the new one, of which the last two carry a
    payload: 'latest' pools the two payload flights (the latest change, dated at its first flight); 'all' the
    majority's range.  Flights are ordered by date, not by the order given."""
    from twin_nodes.base.errors import TwinError
    from twin_nodes.fleet.vehicle_twin import select

    rng = np.random.default_rng(3)
    old = [_fl(k, f"2023-06-0{1 + k // 4}T10:{k:02d}:00+00:00", "MAIN1-4 1000-2000 us", 4.0 + rng.normal(0, .03))
           for k in range(8)]
    new = [_fl(8 + k, f"2023-06-2{k}T10:00:00+00:00", "MAIN1-4 1000-2200 us",
               (5.0 if k < 2 else 4.2) + rng.normal(0, .03)) for k in range(4)]
    flights = list(reversed(old + new))
    got, out, note = select(flights, "latest")
    assert [f["name"] for f in got] == ["f10", "f11"]
    assert sum("motor PWM range" in o for o in out) == 8 and sum("before the vehicle's latest change" in o
                                                                    for o in out) == 2
    assert "kt_per_mass stepped" in note and "f10" in note
    got, out, note = select(flights, "all")
    assert sorted(f["name"] for f in got) == [f"f{k:02d}" for k in range(8)] and "majority" in note
    # a trim step (a load hung off-centre) marks a change too; no step: every flight of the latest range
    trim = [_fl(k, f"2023-07-{10 + k}T10:00:00+00:00", "AUX5-8 1000-2200 us", 5.0 + rng.normal(0, .03),
                0.0 if k < 4 else 0.03) for k in range(7)]
    got, _, note = select(trim, "latest")
    assert [f["name"] for f in got] == ["f04", "f05", "f06"] and "com_dx_m" in note
    got, out, _ = select(trim[:4], "latest")
    assert len(got) == 4 and not out
    with pytest.raises(TwinError, match="expected 'latest' or 'all'"):
        select(trim, "newest")


def test_thrust_per_mass_is_pooled_at_one_pack_voltage():
    """Two flights of one vehicle, the same thrust, fitted at 10.4 V (a pack near its end) and at 12.1 V (a fresh
    one) with the sag T ~ V^1.5: brought to the median voltage (11.25 V) they agree, where the raw values scatter
    by 25 %."""
    from twin_nodes.fleet.vehicle_twin import Pooled, at_one_voltage

    t_ref, e = 5.0, 1.5
    flights = [{"name": f"f{i}", "kt_v": v, "facts": {"kt_per_mass": t_ref * (v / 11.0) ** e, "kt_per_mass_se": 0.01}}
               for i, v in enumerate((10.4, 12.1))]
    assert flights[1]["facts"]["kt_per_mass"] / flights[0]["facts"]["kt_per_mass"] == pytest.approx(1.2549, rel=1e-3)
    pooled = {"battery_exponent": Pooled("battery_exponent", e, 0.1, 0.1, 2)}
    at, vr = at_one_voltage(flights, pooled)
    assert vr.mean == pytest.approx(11.25)
    assert at.mean == pytest.approx(t_ref * (11.25 / 11.0) ** e)
    assert at.scatter == pytest.approx(0.0, abs=1e-9)
    assert at_one_voltage(flights, {}) is None  # no sag exponent pooled: nothing to bring them to one voltage with
    one = {"battery_exponent": Pooled("battery_exponent", e, 0.1, math.nan, 1)}
    assert at_one_voltage(flights, one) is None  # one flight's exponent: not enough to carry the others with


def test_the_gap_tool_swaps_one_group_of_values_and_nothing_else():
    """tools/vehicle_twin_gap.py: a group taken from the own nominal replaces the twin's values and effects of that
    group (present or absent), every other value stays the twin's."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("vehicle_twin_gap", Path(__file__).resolve().parents[1] / "tools" /
                                                  "vehicle_twin_gap.py")
    gap = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gap)
    twin = {"rotors": {"thrust_max_n": 6.1, "thr_mdl_fac": 0.0, "tau_up_s": 0.05},
            "effects": {"enabled": ["battery_sag", "rotor_tilt"], "battery_sag": {"v_ref": 11.8, "exponent": 1.7},
                        "rotor_tilt": {"lever_m": -0.0052}}, "controller": {"yaw_p_1_s": 2.0}}
    own = {"rotors": {"thrust_max_n": 8.25, "thr_mdl_fac": 0.0, "tau_up_s": 0.04},
           "effects": {"enabled": ["wind", "rotor_tilt"], "wind": {"vx": 4.1, "vy": 0.5, "gust_std": 0.0},
                       "rotor_tilt": {"lever_m": -0.0051}}, "controller": {"yaw_p_1_s": 3.0}}
    d = gap.swap(twin, own, *gap.GROUPS["thrust + sag"])
    assert d["rotors"] == {"thrust_max_n": 8.25, "thr_mdl_fac": 0.0, "tau_up_s": 0.05}
    assert d["effects"]["enabled"] == ["rotor_tilt"] and "battery_sag" not in d["effects"]  # the own has no sag
    assert d["effects"]["rotor_tilt"]["lever_m"] == -0.0052 and d["controller"]["yaw_p_1_s"] == 2.0
    d = gap.swap(twin, own, *gap.GROUPS["wind"])
    assert d["effects"]["wind"]["vx"] == 4.1 and d["effects"]["enabled"] == ["battery_sag", "rotor_tilt", "wind"]
    assert gap.swap(twin, own, *gap.GROUPS["controller"])["controller"]["yaw_p_1_s"] == 3.0
    assert twin["rotors"]["thrust_max_n"] == 6.1  # the twin itself untouched


@need_shared
def test_the_motor_configurations_of_the_real_fleet_are_read_from_the_logs():
    """Which outputs drive the motors keys a configuration: 7 Jun drives them on MAIN1-4 (until log_21 mirrored on
    AUX1-4, whose PWM maximum rose to 2200 us at log_19), 14 Jun on on AUX5-8 (another wiring: the yaw trim changed
    sign with it), 21 Jun from log_70 on AUX5-8 with 1000-2200 us (another thrust for the same command)."""
    from twin_nodes.fleet.facts import assignment_text, same_configuration, shares_outputs
    from twin_nodes.fleet.vehicle_twin import configurations
    from twin_nodes.logs.ulog_io import read_params

    pwm = {k: motor_pwm(read_params(SHARED / p), 4) for k, p in (
        ("19", "ZweiterFlugtag/log_19_2023-6-7-10-51-18.ulg"), ("23", "ZweiterFlugtag/log_23_2023-6-7-12-02-44.ulg"),
        ("41", "GripperOnCampus/log_41_2023-6-14-11-59-42.ulg"),
        ("70", "DritterFlugtag/log_70_2023-6-21-09-59-04.ulg"))}
    assert [assignment_text(pwm[k]) for k in ("19", "23", "41", "70")] == ["AUX1-4 + MAIN1-4", "MAIN1-4", "AUX5-8",
                                                                            "AUX5-8"]
    # motor 3 on the 4th output of its group
    assert pwm["19"]["outputs"]["m3"] == ["MAIN4", "AUX4"] and pwm["41"]["outputs"]["m3"] == ["AUX8"]
    assert same_configuration(pwm["23"], pwm["19"]) == (True, "")  # MAIN1-4 1000-2000 us in both
    same, why = same_configuration(pwm["23"], pwm["41"])
    assert not same and "motor outputs AUX5-8, the twin's are MAIN1-4 (another wiring)" in why
    same, why = same_configuration(pwm["41"], pwm["70"])
    assert not same and "PWM range" in why and shares_outputs(pwm["41"], pwm["70"])
    # every log of the fleet (40): three configurations (14 logs of 7 Jun, 8 on AUX5-8 1000-2000 us, 18 on 1000-2200 us)
    logs = sorted(SHARED.glob("*/*.ulg")) + sorted((SHARED.parent / "real").glob("real_quadx_v6c_*.ulg"))
    groups = configurations([{"pwm": motor_pwm(read_params(p), 4), "path": str(p)} for p in logs])
    assert sorted((len(g), assignment_text(g[0]["pwm"])) for g in groups) == [
        (8, "AUX5-8"), (14, "AUX1-4 + MAIN1-4"), (18, "AUX5-8")]


def test_a_twin_flies_another_wiring_without_its_yaw_trim():
    """The yaw trim (a rotor tilt) belongs to the wiring: a log whose motors are on other outputs is flown without
    it (the PWM range rescaled as before); the same wiring keeps it."""
    from types import SimpleNamespace

    from twin_nodes.fleet.facts import motor_pwm as mp
    from twin_nodes.fleet.vehicle_twin import _enable, for_flight
    from twin_nodes.vehicle.params import from_ros_dict, shipped

    d = shipped("px4_sih_quadx").to_ros_dict()
    _enable(d["effects"], "rotor_tilt", {"lever_m": -0.005})
    vp = from_ros_dict(d)

    def params(group, first, hi):
        p = {f"PWM_{group}_FUNC{first + k}": 101 + k for k in range(4)}
        p.update({f"PWM_{group}_MIN{first + k}": 1000.0 for k in range(4)})
        p.update({f"PWM_{group}_MAX{first + k}": hi for k in range(4)})
        return p

    ref = {"pwm": mp(params("AUX", 5, 2200.0), 4)}
    out, note = for_flight(vp, ref, SimpleNamespace(params=params("MAIN", 1, 2000.0), n_motors=4))
    assert "rotor_tilt" not in out.to_ros_dict()["effects"]["enabled"]
    assert "motor outputs AUX5-8 in the twin, MAIN1-4 in this log" in note and "span ratio 0.833" in note
    assert out.rotors.thrust_max_n < vp.rotors.thrust_max_n
    out, note = for_flight(vp, ref, SimpleNamespace(params=params("AUX", 5, 2000.0), n_motors=4))
    assert out.to_ros_dict()["effects"]["rotor_tilt"]["lever_m"] == pytest.approx(-0.005)
    assert "motor outputs" not in note and "span ratio 0.833" in note


def test_values_are_not_compared_across_a_rewiring():
    """Twelve flights; the motors move from MAIN1-4 to AUX5-8 at flight 6 and the roll trim with them (+8 mm, as a
    rewired vehicle's trims move on the real fleet): an 'outputs' event, no centre-of-mass alarm; the same trim step
    without a rewiring is one."""
    import json as _json

    from twin_nodes.fleet import vehicle_report as vr

    rng = np.random.default_rng(11)

    def rows(rewire):
        out = []
        for k in range(12):
            g, first = ("AUX", 5) if rewire and k >= 6 else ("MAIN", 1)
            p = {f"PWM_{g}_FUNC{first + c}": 101 + c for c in range(4)}
            p.update({f"PWM_{g}_MIN{first + c}": 1000.0 for c in range(4)})
            p.update({f"PWM_{g}_MAX{first + c}": 2000.0 for c in range(4)})
            out.append({"path": f"/d/f{k:02d}.ulg", "status": "ok", "flight_kind": "free flight",
                        "flight_time_utc": f"2023-06-{10 + k:02d}T10:00:00+00:00", "date_source": "gps",
                        "file_name_time": "", "params_json": _json.dumps(p), "motor_pwm": motor_pwm(p, 4)["text"],
                        "fact_kt_per_mass": 5.0 + rng.normal(0, 0.02), "fact_kt_per_mass_se": 0.01,
                        "fact_com_dx_m": (0.008 if k >= 6 else 0.0) + rng.normal(0, 0.0005),
                        "fact_com_dx_m_se": 0.0005})
        return out

    res = vr.analyse_vehicle("v", rows(True))
    assert res["rewired"] == [6] and res["changes"] == []
    assert [(e["flight"], e["outputs"]) for e in res["events"]] == [("d/f06.ulg", ["MAIN1-4", "AUX5-8"])]
    res = vr.analyse_vehicle("v", rows(False))
    assert res["rewired"] == [] and [(c.flight, c.name) for c in res["changes"]] == [
        ("d/f06.ulg", "centre-of-mass shift")]


def test_a_pooled_value_whose_flights_disagree_beyond_their_uncertainty_is_named():
    """chi^2 of the flights about their se-weighted mean against its 99.73 % quantile (two flights: 3 combined se):
    the date split's twin pools the sag exponents 1.711 ± 0.12 (7 Jun log_30) and 2.652 ± 0.14 (log_38): 5.1 se
    apart, chi^2 26.0 on 1 dof, named with both values; 26 Jun log_29 2.00 ± 0.19 and mission_noload 1.46 ± 0.09:
    2.6 se apart, chi^2 6.6, consistent."""
    from twin_nodes.fleet.vehicle_twin import agreement

    bad = pool("battery_exponent", ["log_30", "log_38"], [1.711, 2.652], [0.12, 0.14])
    assert bad.mean == pytest.approx(2.1815) and bad.scatter == pytest.approx(0.6654, abs=1e-3)
    assert bad.chi2 == pytest.approx(0.941 ** 2 / (0.12 ** 2 + 0.14 ** 2), rel=1e-6) and bad.chi2 == pytest.approx(26.0, abs=0.1)
    assert bad.dof == 1 and not bad.consistent
    assert bad.spread == ["log_30 1.711 ± 0.12", "log_38 2.652 ± 0.14"]
    assert bad.disagreeing == []  # two flights: neither can be told the odd one out, both are named in the spread
    ok = pool("battery_exponent", ["log_29", "noload"], [2.00, 1.46], [0.19, 0.09])
    assert ok.chi2 == pytest.approx(6.60, abs=0.01) and ok.consistent and ok.spread == []
    # the threshold: two flights 2.9 combined se apart agree, 3.1 apart do not; one flight is never tested
    assert agreement(np.array([0.0, 2.9 * math.sqrt(2) * 0.1]), np.array([0.1, 0.1]))[2]
    assert not agreement(np.array([0.0, 3.1 * math.sqrt(2) * 0.1]), np.array([0.1, 0.1]))[2]
    assert agreement(np.array([1.0]), np.array([0.1])) == (pytest.approx(math.nan, nan_ok=True), 0, True)
    # the se is at least the agreement floor of pool() / 3 (sag exponent: 0.2 / 3): 2.0 and 2.3 at se 0.01 are
    # chi^2 0.09 / (2 x 0.0667^2) = 10.1 apart, 2.0 and 2.2 chi^2 4.5
    assert not pool("battery_exponent", ["a", "b"], [2.0, 2.3], [0.01, 0.01]).consistent
    assert pool("battery_exponent", ["a", "b"], [2.0, 2.2], [0.01, 0.01]).consistent
    # three flights, chi^2 on 2 dof (quantile 11.83)
    c2, dof, good = agreement(np.array([1.0, 1.2, 1.4]), np.array([0.1, 0.1, 0.1]))
    assert (c2, dof, good) == (pytest.approx(8.0), 2, True)


def test_a_sag_exponent_the_flights_disagree_on_widens_the_band_it_carries_a_flight_with():
    """since_twin brings a flight's thrust per mass to the twin's voltage with the twin's exponent; what that adds
    is x |ln(V_ref/V)| sigma_e, sigma_e the exponent's se, or its scatter where its flights disagree (mission_2hops,
    4.47 at 10.36 V, against the date split's twin: 11.23 V, 2.18, se 0.47, scatter 0.67)."""
    from twin_nodes.fleet.vehicle_twin import _at_twin_voltage

    e = {"mean": 2.18, "se": 0.47, "scatter": 0.67, "consistent": False}
    pooled = {"kt_per_mass_at_v_ref": {"mean": 3.52}, "kt_v_ref": {"mean": 11.23}, "battery_exponent": e}
    at, se = _at_twin_voltage({"kt_per_mass": 4.47}, 10.36, pooled)
    assert at == pytest.approx(4.47 * (11.23 / 10.36) ** 2.18) and at == pytest.approx(5.329, abs=0.005)
    assert se == pytest.approx(at * math.log(11.23 / 10.36) * 0.67) and se == pytest.approx(0.288, abs=0.002)
    at2, se2 = _at_twin_voltage({"kt_per_mass": 4.47}, 10.36, dict(pooled, battery_exponent=dict(e, consistent=True)))
    assert at2 == at and se2 == pytest.approx(at * math.log(11.23 / 10.36) * 0.47)
    assert _at_twin_voltage({"kt_per_mass": 4.47}, math.nan, pooled) == (None, 0.0)


@need_shared
def test_the_twin_names_a_sag_exponent_its_flights_disagree_on_and_states_what_it_costs():
    """7 Jun log_30 and log_38 (one configuration, MAIN1-4): their sag exponents as identified with the take-off
    spot in disagree (1.71 ± 0.12, 2.65 ± 0.14); the header names both and states the thrust's uncertainty 1 V
    below the twin's voltage (ln(10.11/11.11) x 0.66 = 6 %); the twin still flies their mean (without a sag or
    with 1 it predicted later flights worse, docs/fleet.md sag12)."""
    from twin_nodes.fleet.vehicle_twin import from_flights, read_flights

    flights, left_out = read_flights([str(SHARED / "ZweiterFlugtag" / n) for n in ("log_30_2023-6-7-12-11-06.ulg",
                                                                                   "log_38_2023-6-7-13-54-52.ulg")])
    # since the take-off spot is left out of the identification (identify/fit_mask.on_spot, 3.6 / 5.7 s of these two
    # flights) log_30 reads 0.55 ± 0.12 and log_38 no significant sag: the two exponents measured before it (with
    # the spot's ground-carried seconds in) are put back here to test how a disagreement is pooled and stated
    got = {f["name"]: f["facts"].get("battery_exponent", math.nan) for f in flights}
    assert got["ZweiterFlugtag/log_30_2023-6-7-12-11-06.ulg"] == pytest.approx(0.55, abs=0.05)
    assert math.isnan(got["ZweiterFlugtag/log_38_2023-6-7-13-54-52.ulg"])
    for f, (x, se) in zip(flights, ((1.71, 0.12), (2.65, 0.14))):
        f["facts"]["battery_exponent"], f["facts"]["battery_exponent_se"] = x, se
    vt = from_flights(flights, left_out)
    e = vt.pooled["battery_exponent"]
    assert e.n == 2 and not e.consistent and e.chi2 == pytest.approx((2.65 - 1.71) ** 2 / (0.12 ** 2 + 0.14 ** 2))
    assert e.mean == pytest.approx(2.18, abs=0.03) and e.scatter == pytest.approx(0.67, abs=0.03)
    assert "log_30_2023-6-7-12-11-06.ulg 1.71" in vt.header and "log_38_2023-6-7-13-54-52.ulg 2.65" in vt.header
    assert "the flights disagree beyond their uncertainty (chi^2 2" in vt.header
    v_ref = vt.pooled["kt_v_ref"].mean
    # the pack voltage the thrust is pooled at: 11.68 V with the take-off spot in, 11.11 V without it
    assert v_ref == pytest.approx(11.11, abs=0.05) and vt.pooled["kt_v_ref"].consistent
    assert f"± {abs(math.log((v_ref - 1) / v_ref)) * e.scatter:.0%} 1 V below" in vt.header
    assert "± 6% 1 V below" in vt.header
    sag = vt.params.to_ros_dict()["effects"]["battery_sag"]
    assert sag["exponent"] == pytest.approx(e.mean) and sag["v_ref"] == pytest.approx(v_ref)
