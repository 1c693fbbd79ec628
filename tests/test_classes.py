"""Failure classes found on the public corpus (issue 24, /docs/real_logs.md "Corpus classes"):
motor channels with an idle output >= 1000 us (C3) or servo channels stepped to 1500 us (C8), a normalised
rotor layout of an airframe outside the table flown on an ASSUMED arm (C7), every PX4 nav_state flown (C10)."""

from __future__ import annotations

import numpy as np
import pytest

from twin_nodes.logs import ulog_io as U
from twin_nodes.vehicle.px4_params import CLASS_ARM_M, rotor_layout



def _channels(aos, n, topics):
    """:func:`ulog_io._guess_motor_stream`'s instance and channels."""
    inst, _, _, chans = U._guess_motor_stream(aos, n, topics)
    return inst, chans

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
    assert _channels(aos, 4, topics) == (0, [0, 1, 2, 3])
    assert U.moving_motor_outputs(topics) == (4, "actuator_outputs[0].output")


def test_servo_channels_stepped_to_centre_are_no_motors():
    """C8: two servo channels 0 -> 1500 us at arming, constant after: 4 motor outputs move, not 6."""
    topics = _flight(900.0, servo=True)
    assert U.moving_motor_outputs(topics) == (4, "actuator_outputs[0].output")
    aos = {0: topics[("actuator_outputs", 0)]}
    assert _channels(aos, 6, topics) == (None, [])
    assert _channels(aos, 4, topics) == (0, [0, 1, 2, 3])


def test_a_channel_resting_above_its_armed_range_is_no_motor():
    """A channel that sits higher disarmed than it ever is armed (a servo parked at full) is left out."""
    topics = _flight(1000.0, servo=False)
    tp = topics[("actuator_outputs", 0)]
    o = tp.data["output[1]"].copy()
    o[tp.t_s < 10.0] = 2000.0
    tp.data["output[1]"] = o
    assert _channels({0: tp}, 3, topics) == (0, [0, 2, 3])


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


START_US = 20_000_000


@pytest.fixture(scope="module")
def sim_flight():
    """A simulated SIH quad flight's PX4 topics and parameters."""
    from twin_nodes.twin.simflight import Hidden, record_to_topics, simulate_flight, simulated_log_params
    from twin_nodes.vehicle.params import shipped

    vp = shipped("px4_sih_quadx")
    rec, battery, sp_hist = simulate_flight(vp, Hidden("none", {}), seed=3)
    topics = record_to_topics(rec, vp, battery, sp_hist, np.random.default_rng(10), start_us=START_US)
    return topics, simulated_log_params(vp)


def _write(path, topics, params):
    from twin_nodes.logs.flyable import read_flight
    from twin_nodes.logs.ulog_write import write_px4_ulog

    write_px4_ulog(str(path), topics, params, {"sys_name": "test"}, start_us=START_US)
    return read_flight(str(path))


@pytest.fixture(scope="module")
def normalised_sih_log(sim_flight, tmp_path_factory):
    """The flight logged as PX4 >= 1.14 logs an airframe outside the table: CA_ROTORn normalised to +-1,
    SYS_AUTOSTART 4003."""
    topics, params = sim_flight
    params = dict(params)
    r = max(np.hypot(params[f"CA_ROTOR{i}_PX"], params[f"CA_ROTOR{i}_PY"]) for i in range(4))
    for i in range(4):
        for ax in "XYZ":
            params[f"CA_ROTOR{i}_P{ax}"] *= np.sqrt(2.0) / r
    params["SYS_AUTOSTART"] = 4003
    return _write(tmp_path_factory.mktemp("c7") / "normalised.ulg", topics, params)


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


DRIFT = (40.0, 55.0)  # the estimate walks away (x accelerating at 0.5 m/s^2) while the vehicle hovers on
REF = (47.39, 8.55)   # the EKF origin [deg]


def _with_gps(topics):
    """The flight's topics with the EKF origin and a GPS receiver (5 Hz, 3D fix) that sees the true track."""
    out = dict(topics)
    lp = {k: np.array(v, copy=True) for k, v in topics["vehicle_local_position"].items()}
    n = lp["timestamp"].size
    lp["ref_lat"], lp["ref_lon"] = np.full(n, REF[0]), np.full(n, REF[1])
    out["vehicle_local_position"] = lp
    k = np.arange(0, n, 5)
    r = 6371000.0
    out["vehicle_gps_position"] = {
        "timestamp": lp["timestamp"][k],
        "lat": np.round((REF[0] + np.degrees(lp["x"][k] / r)) * 1e7).astype(np.int32),
        "lon": np.round((REF[1] + np.degrees(lp["y"][k] / (r * np.cos(np.radians(REF[0]))))) * 1e7).astype(np.int32),
        "fix_type": np.full(k.size, 3, np.uint8)}
    return out


def test_a_diverging_estimate_with_valid_flags_is_found_and_left_out(sim_flight, tmp_path):
    """C9: the position estimate accelerates away (0.5 m/s^2 north for 15 s: 56 m) while its valid flags
    stay up and the IMU says nothing of it: the GPS receiver's own fix disagrees by more than 5 m from
    4.5 s into the drift; those seconds (and no others) are found, and controlled_axes leaves them out
    of xy and z.  The unedited flight, with and without GPS: nothing found."""
    from twin_nodes.twin.estimate_check import estimate_failures
    from twin_nodes.twin.flight_mode import controlled_axes

    topics, params = sim_flight
    assert estimate_failures(_write(tmp_path / "clean.ulg", topics, params))[0] == []
    topics = _with_gps(topics)
    clean = _write(tmp_path / "clean_gps.ulg", topics, params)
    iv, how = estimate_failures(clean)
    assert iv == [] and "GPS" in how and "IMU" in how
    lp = {k: np.array(v, copy=True) for k, v in topics["vehicle_local_position"].items()}
    s = (lp["timestamp"].astype(np.int64) - START_US) * 1e-6
    tau = np.clip(s - DRIFT[0], 0.0, DRIFT[1] - DRIFT[0])
    lp["x"] = lp["x"] + 0.25 * tau ** 2     # NED north
    lp["vx"] = lp["vx"] + 0.5 * tau * (s < DRIFT[1])
    log = _write(tmp_path / "drift.ulg", {**topics, "vehicle_local_position": lp}, params)
    iv, how = estimate_failures(log)
    assert iv and DRIFT[0] + 3.5 <= iv[0][0] <= DRIFT[0] + 5.0, iv
    assert all(a >= DRIFT[0] for a, _ in iv)
    assert sum(b - a for a, b in iv) >= DRIFT[1] - DRIFT[0] - 5.0, iv
    t = np.arange(DRIFT[0] + 5.0, DRIFT[1], 0.1)
    xy, z, how = controlled_axes(log, t)
    assert not xy.any() and not z.any() and "estimate failed" in how
    xy0, _, _ = controlled_axes(log, np.arange(10.0, DRIFT[0], 0.1))
    xyc, _, _ = controlled_axes(clean, np.arange(10.0, DRIFT[0], 0.1))
    assert np.array_equal(xy0, xyc)


#: PX4's vehicle_status.msg NAVIGATION_STATE_* (main, 2026; 16 was RATTITUDE up to 1.11, 6/8/9/7 were
#: AUTO_RCRECOVER/LANDENGFAIL/LANDGPSFAIL/RTGS in older releases): what the twin flies in each
PX4_NAV_STATES = {0: "MANUAL", 1: "ALTCTL", 2: "POSCTL", 3: "AUTO_MISSION", 4: "AUTO_LOITER", 5: "AUTO_RTL",
                  6: "POSITION_SLOW", 7: "FREE5", 8: "ALTITUDE_CRUISE", 9: "FREE3", 10: "ACRO", 11: "FREE2",
                  12: "DESCEND", 13: "TERMINATION", 14: "OFFBOARD", 15: "STAB", 16: "FREE1/RATTITUDE",
                  17: "AUTO_TAKEOFF", 18: "AUTO_LAND", 19: "AUTO_FOLLOW_TARGET", 20: "AUTO_PRECLAND", 21: "ORBIT",
                  22: "AUTO_VTOL_TAKEOFF", **{k: f"EXTERNAL{k - 22}" for k in range(23, 31)}}


@pytest.mark.parametrize("nav", sorted(PX4_NAV_STATES))
def test_every_px4_nav_state_is_flown_as_px4_flies_it(nav):
    """C10: the sticks' modes fly PX4's attitude (MANUAL, STAB, RATTITUDE) or rate (ACRO) setpoint; every
    other nav_state runs mc_pos_control on the logged trajectory_setpoint (FOLLOW_TARGET 19, ORBIT 21 and
    the external modes as any AUTO mode)."""
    from twin_nodes.twin.runner import TwinRunner
    from twin_nodes.vehicle.params import shipped

    r = TwinRunner(shipped("px4_sih_quadx"), "closed", 2.0)
    r.px4_mode(nav, 0.5)
    r.att_q = np.array([1.0, 0.0, 0.0, 0.0])
    r.rates_sp = np.zeros(3)
    r.sp[0:3] = [1.0, 2.0, 3.0]
    expected = {0: "attitude", 15: "attitude", 16: "attitude", 10: "rates"}.get(nav, "cascade")
    assert r._fly_mode() == expected, PX4_NAV_STATES[nav]


def test_a_log_that_starts_in_the_air_is_measured_from_its_touchdown():
    """A log started while flying (the Mantis follow flights: armed and airborne from the first sample)
    has no take-off height: the rise is measured from the lower of its first and last height (8.5 m here,
    not 0.25 m from the first sample); a hop that never rose stays a hop."""
    from twin_nodes.logs.flyable import _max_rise
    from twin_nodes.logs.ulog_io import Series

    t = np.linspace(0.0, 100.0, 1001)
    z = np.where(t < 95.0, 8.5 + 0.25 * np.sin(t), 8.5 * (100.0 - t) / 5.0)
    pos = Series(t, np.column_stack([0 * t, 0 * t, z]), "m", "ENU", "test", "linear")
    assert _max_rise(pos, [(0.0, 100.0)]) == pytest.approx(8.75, abs=0.01)
    hop = Series(t, np.column_stack([0 * t, 0 * t, 0.2 * np.sin(np.pi * t / 100.0)]), "m", "ENU", "test", "linear")
    assert _max_rise(hop, [(0.0, 100.0)]) == pytest.approx(0.2, abs=0.01)
    # a take-off in the log: its height is the ground (a bench log whose baro drifts down 1 m stays a hop)
    drift = Series(t, np.column_stack([0 * t, 0 * t, -t / 100.0]), "m", "ENU", "test", "linear")
    assert _max_rise(drift, [(5.0, 100.0)]) == pytest.approx(0.0, abs=0.01)
    assert _max_rise(drift, [(0.0, 100.0)]) == pytest.approx(1.0, abs=0.01)


def test_tap_esc_outputs_are_scaled_by_tap_esc_range():
    """C3's H480/Mantis outputs are tap_esc's: 1200..1900 is the mixer's 0..1 (drv_tap_esc.h), rest at 1190;
    the log has no PWM limits.  Known by the 1190 rest, the ESC_* parameters or the airframe; a log with
    PWM limits is PWM whatever it rests at."""
    from twin_nodes.logs import legacy_topics as L

    rest = np.full((20, 4), 1190.0)
    assert L.tap_esc({"SYS_AUTOSTART": 6021}, rest).startswith("outputs rest at")
    assert L.tap_esc({"ESC_FW_VER": 205}, rest[:0]).startswith("tap_esc parameters")
    assert L.tap_esc({"SYS_AUTOSTART": 4061}, rest[:0]) == "SYS_AUTOSTART 4061 is a tap_esc airframe"
    assert L.tap_esc({"SYS_AUTOSTART": 4001}, np.full((20, 4), 1000.0)) is None
    assert L.tap_esc({"PWM_MIN": 1075, "SYS_AUTOSTART": 6021}, rest) is None
    topics = _flight(1190.0, servo=False)
    series = U._motors_from_pwm(topics, {"SYS_AUTOSTART": 6021}, 4, [])
    pwm = topics[("actuator_outputs", 0)].arr("output", 4)
    armed = U._armed_at(topics, topics[("actuator_outputs", 0)].t_s)
    assert np.allclose(series.values[armed], np.clip((pwm[armed] - 1200.0) / 700.0, 0, 1))
    assert "tap_esc RPMMIN-RPMMAX 1200-1900" in series.source


def test_px4_18_velocity_only_axes_keep_their_velocity_setpoint():
    """PX4 1.8's vehicle_local_position_setpoint: where an axis has no position setpoint (z NaN in AUTO
    land, vz = MPC_LAND_SPEED 0.8) its vz is the setpoint itself; on position-held axes the feed-forward
    is vx - (x - position) * MPC_XY_P (the H480 RTL descent flew at 0.8 m/s; the twin got NaN)."""
    from twin_nodes.logs import legacy_topics as L

    t = np.arange(0.0, 2.0, 0.1)
    n = t.size
    sp = U._Topic("vehicle_local_position_setpoint", 0, (t * 1e6).astype(np.int64),
                  {"x": np.full(n, 1.0), "y": np.zeros(n), "z": np.full(n, np.nan),
                   "vx": np.full(n, 0.95), "vy": np.zeros(n), "vz": np.full(n, 0.8)})
    lp = U._Topic("vehicle_local_position", 0, (t * 1e6).astype(np.int64),
                  {"x": np.full(n, 0.5), "y": np.zeros(n), "z": np.full(n, -10.0)})
    out = L.setpoint_arrays(sp, "vehicle_local_position_setpoint", lp, {"MPC_XY_P": 0.9, "MPC_Z_P": 1.0})
    v = out["velocity"][0]
    assert np.allclose(v[:, 2], 0.8)
    assert np.allclose(v[:, 0], 0.95 - 0.5 * 0.9)
    assert np.isnan(out["position"][0][:, 2]).all()


def test_setpoint_gaps_longer_than_a_second_are_bridged_and_short_ones_held():
    """C10: the Mantis follow flights' trajectory_setpoint has logging gaps of up to 4.4 s while the
    target moved 9 m: across a gap > 1 s the twin flies the straight line between the logged samples
    (what PX4's 50 Hz setpoint did, near enough), not the old sample then a jump; a 0.4 s gap is held."""
    from twin_nodes.twin.inputs import bridge_setpoint_gaps

    ts = np.array([0.0, 0.4, 4.4, 4.8])
    vals = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 5.0], [8.0, -4.0, np.nan], [8.0, -4.0, 5.0]])
    grid = np.arange(0.0, 4.8, 0.1)
    k = np.searchsorted(ts, grid, side="right") - 1
    held = vals[k]
    out = bridge_setpoint_gaps(ts, vals, grid, held)
    mid = np.isclose(grid, 2.4)
    assert np.allclose(out[mid, :2], [[4.0, -2.0]])
    assert np.allclose(out[mid, 2], 5.0)                  # an axis NaN at one end: held
    assert np.allclose(out[grid < 0.4], held[grid < 0.4])  # the 0.4 s gap: held
