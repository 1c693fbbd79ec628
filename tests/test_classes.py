"""Failure classes found on the public corpus (issue 24, /docs/real_logs.md "Corpus classes"):
motor channels with an idle output >= 1000 us (C3) or servo channels stepped to 1500 us (C8), a normalised
rotor layout of an airframe outside the table flown on an ASSUMED arm (C7), every PX4 nav_state flown (C10)."""

from __future__ import annotations

import numpy as np
import pytest

from twin_nodes.logs import ulog_io as U
from twin_nodes.vehicle.px4_params import CLASS_ARM_M, rotor_layout


def _outputs(pwm: np.ndarray, t_s: np.ndarray, inst: int = 0) -> U._Topic:
    data = {f"output[{i}]": (pwm[:, i] if i < pwm.shape[1] else np.zeros(len(t_s))) for i in range(16)}
    return U._Topic("actuator_outputs", inst, (t_s * 1e6).astype(np.int64), data)


def _status(t_armed: tuple[float, float], t_end: float) -> U._Topic:
    t = np.array([0.0, t_armed[0], t_armed[1]])
    return U._Topic("vehicle_status", 0, (t * 1e6).astype(np.int64),
                    {"arming_state": np.array([1, 2, 1]), "nav_state": np.array([2, 2, 2])})


def _flight(idle_us: float, servo: bool, seed: int = 0):
    """100 s at 10 Hz, armed 10-90 s: n motors idle at ``idle_us`` disarmed and follow a noisy thrust
    while armed; with ``servo`` two more channels step 0 -> 1500 us at arming and stay there."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 100.0, 0.1)
    armed = (t >= 10.0) & (t < 90.0)
    thrust = 1450.0 + 80.0 * np.sin(0.3 * t)[:, None] + rng.normal(0.0, 20.0, (t.size, 4))
    motors = np.where(armed[:, None], np.maximum(thrust, idle_us + 10.0), idle_us)
    cols = [motors]
    if servo:
        cols.append(np.where(armed[:, None], 1500.0, 0.0) * np.ones((1, 2)))
    pwm = np.concatenate(cols, axis=1)
    topics = {("actuator_outputs", 0): _outputs(pwm, t), ("vehicle_status", 0): _status((10.0, 90.0), 100.0)}
    return topics


@pytest.mark.parametrize("idle", [900.0, 1000.0, 1190.0])
def test_motor_channels_found_whatever_the_idle_output(idle):
    """C3: PWM_DISARMED 900 or 1000, tap_esc's 1190 us (Typhoon H480): the four motors are found."""
    topics = _flight(idle, servo=False)
    aos = {0: topics[("actuator_outputs", 0)]}
    assert U._guess_motor_channels(aos, 4, topics) == (0, [0, 1, 2, 3])
    assert U.moving_motor_outputs(topics) == (4, "actuator_outputs[0].output")


def test_servo_channels_stepped_to_centre_are_no_motors():
    """C8: two servo channels 0 -> 1500 us at arming, constant after: 4 motor outputs move, not 6."""
    topics = _flight(900.0, servo=True)
    assert U.moving_motor_outputs(topics) == (4, "actuator_outputs[0].output")
    aos = {0: topics[("actuator_outputs", 0)]}
    assert U._guess_motor_channels(aos, 6, topics) == (None, [])
    assert U._guess_motor_channels(aos, 4, topics) == (0, [0, 1, 2, 3])


def test_a_channel_resting_above_its_armed_range_is_no_motor():
    """A channel that sits higher disarmed than it ever is armed (a servo parked at full) is left out."""
    topics = _flight(1000.0, servo=False)
    tp = topics[("actuator_outputs", 0)]
    o = tp.data["output[1]"].copy()
    o[tp.t_s < 10.0] = 2000.0
    tp.data["output[1]"] = o
    assert U._guess_motor_channels({0: tp}, 3, topics) == (0, [0, 2, 3])


def _normalised_params(autostart: int) -> dict[str, float]:
    p = {"SYS_AUTOSTART": autostart, "CA_ROTOR_COUNT": 4}
    for i, (x, y, km) in enumerate([(1, 1, 0.05), (-1, -1, 0.05), (1, -1, -0.05), (-1, 1, -0.05)]):
        p.update({f"CA_ROTOR{i}_PX": x, f"CA_ROTOR{i}_PY": y, f"CA_ROTOR{i}_PZ": 0.0, f"CA_ROTOR{i}_KM": km})
    return p


def test_normalised_layout_of_an_unknown_airframe_gets_the_class_arm_and_says_assumed():
    """C7: SYS_AUTOSTART 4003 (not in the 1.8-1.13 table) with CA_ROTORn_PX/PY = +-1: the quad class's
    ASSUMED arm, said in the layout's source (the nominal's header); --arm-m still wins."""
    lay = rotor_layout(_normalised_params(4003))
    r = np.hypot(lay.x_flu_m, lay.y_flu_m)
    assert np.allclose(r, CLASS_ARM_M[4])
    assert "ASSUMED 0.25 m arm" in lay.source and "--arm-m" in lay.source
    lay2 = rotor_layout(_normalised_params(4003), arm_m=0.4)
    assert np.allclose(np.hypot(lay2.x_flu_m, lay2.y_flu_m), 0.4)
    assert lay.direction == lay2.direction == (1, 1, -1, -1)


@pytest.fixture(scope="module")
def normalised_sih_log(tmp_path_factory):
    """A simulated SIH quad flight logged as PX4 >= 1.14 logs an airframe outside the table: CA_ROTORn
    normalised to +-1, SYS_AUTOSTART 4003."""
    from twin_nodes.logs.flyable import read_flight
    from twin_nodes.logs.ulog_write import write_px4_ulog
    from twin_nodes.twin.simflight import Hidden, record_to_topics, simulate_flight, simulated_log_params
    from twin_nodes.vehicle.params import shipped

    vp = shipped("px4_sih_quadx")
    rec, battery, sp_hist = simulate_flight(vp, Hidden("none", {}), seed=3)
    topics = record_to_topics(rec, vp, battery, sp_hist, np.random.default_rng(10), start_us=20_000_000)
    params = simulated_log_params(vp)
    r = max(np.hypot(params[f"CA_ROTOR{i}_PX"], params[f"CA_ROTOR{i}_PY"]) for i in range(4))
    for i in range(4):
        for ax in "XYZ":
            params[f"CA_ROTOR{i}_P{ax}"] *= np.sqrt(2.0) / r
    params["SYS_AUTOSTART"] = 4003
    path = tmp_path_factory.mktemp("c7") / "normalised.ulg"
    write_px4_ulog(str(path), topics, params, {"sys_name": "test"}, start_us=20_000_000)
    return read_flight(str(path))


def test_the_assumed_arm_is_absorbed_by_the_identified_inertia(normalised_sih_log):
    """C7: the same flight built on two assumed arms (0.2 and 0.35 m) flies the same closed loop: the
    identified inertia scales with the arm (the moment is arm x thrust: I/l within 10 %) and the held-out metrics agree within
    0.5 % throttle/motors and 0.1 m XY/Z."""
    from twin_nodes.discovery.stages.closed_loop import _closed_loop_twin
    from twin_nodes.identify.nominal import nominal_from_log

    log = normalised_sih_log
    a, b = log.airborne_intervals()[0][0], log.airborne_intervals()[-1][1]
    t_split = a + 0.65 * (b - a)
    out = {}
    for arm in (0.2, 0.35):
        vp = nominal_from_log(log, mass_kg=1.0, arm_m=arm).params
        m = _closed_loop_twin(log, vp, t_split, b)
        out[arm] = (np.diag(vp.inertia)[:2] / arm, m)
    (i1, m1), (i2, m2) = out[0.2], out[0.35]
    print(i1, i2, {k: (m1[k], m2[k]) for k in ("throttle_rmse", "motor_p75_mean", "xy_rmse_m", "z_rmse_m")})
    assert np.allclose(i1, i2, rtol=0.10), (i1, i2)
    assert abs(m1["throttle_rmse"] - m2["throttle_rmse"]) < 0.005
    assert abs(m1["motor_p75_mean"] - m2["motor_p75_mean"]) < 0.005
    assert abs(m1["xy_rmse_m"] - m2["xy_rmse_m"]) < 0.1
    assert abs(m1["z_rmse_m"] - m2["z_rmse_m"]) < 0.1
