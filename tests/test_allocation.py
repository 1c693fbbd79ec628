"""PX4's allocation with sequential desaturation (twin_nodes.twin.control.px4_allocate) against cases
worked by hand through ControlAllocationSequentialDesaturation.cpp (PX4 1.14) / MultirotorMixer.cpp (1.12),
on PX4's normalised quad X mix (the mixer's own quad_x table: roll/pitch +-0.707107, yaw +-1, thrust 1)."""

from __future__ import annotations

import numpy as np
import pytest

from twin_nodes.twin.control import (C_SAT, Controller, ControllerGains, allocation_table, px4_allocate,
                                     px4_mix_directions)
from twin_nodes.vehicle.params import shipped
from twin_nodes.vehicle.px4_params import allocation_kind
from twin_nodes.physics.model import Multirotor

S = 0.707107
# PX4 quad X, motors 1..4 (MultirotorMixer mock geometry): columns thrust, roll, pitch, yaw
MIX = np.array([[1.0, -S, S, 1.0],
                [1.0, S, -S, 1.0],
                [1.0, S, S, -1.0],
                [1.0, -S, -S, -1.0]])


def alloc(thrust, roll, pitch, yaw, airmode, eps=0.2):
    parts = (MIX * np.array([thrust, roll, pitch, yaw])).T.copy()
    a = np.empty(4)
    px4_allocate(parts, MIX.T.copy(), 0.0, 1.0, float(airmode), eps, a)
    return a


def moments(a):
    """Roll, pitch and yaw the outputs give, in the setpoint's units (the mix is orthogonal)."""
    return MIX[:, 1:].T @ a / np.sum(MIX[:, 1:] ** 2, axis=0)


@pytest.mark.parametrize("airmode", [0, 1, 2])
def test_roll_saturating_at_high_thrust_keeps_roll_and_lowers_thrust(airmode):
    # thrust 0.8, roll 0.5: outputs 0.8 -+ 0.35355 -> motors 2 and 3 at 1.15355; thrust lowered by 0.15355
    a = alloc(0.8, 0.5, 0.0, 0.0, airmode)
    np.testing.assert_allclose(a, [0.8 - 0.353554 - 0.153554, 1.0, 1.0, 0.8 - 0.353554 - 0.153554], atol=1e-6)
    assert moments(a)[0] == pytest.approx(0.5, abs=1e-6)


def test_roll_saturating_at_low_thrust_without_airmode_cuts_roll_and_keeps_thrust():
    # thrust 0.2, roll 0.5: motors 1 and 4 at -0.15355. Airmode off never raises thrust: the thrust
    # step is refused (gain +0.15355 > 0), the roll step slides by -0.15355/0.707107 -> roll 0.2828
    a = alloc(0.2, 0.5, 0.0, 0.0, 0)
    np.testing.assert_allclose(a, [0.0, 0.4, 0.4, 0.0], atol=1e-6)
    assert moments(a)[0] == pytest.approx(0.4 / (2 * S), abs=1e-6)
    assert a.mean() == pytest.approx(0.2, abs=1e-9)      # thrust kept


@pytest.mark.parametrize("airmode", [1, 2])
def test_roll_saturating_at_low_thrust_with_airmode_raises_thrust_and_keeps_roll(airmode):
    a = alloc(0.2, 0.5, 0.0, 0.0, airmode)
    np.testing.assert_allclose(a, [0.0, 2 * 0.353554, 2 * 0.353554, 0.0], atol=1e-6)
    assert moments(a)[0] == pytest.approx(0.5, abs=1e-6)


@pytest.mark.parametrize("airmode", [0, 1])
def test_yaw_beyond_authority_is_given_up_roll_pitch_and_thrust_kept(airmode):
    # thrust 0.5, roll 0.2, yaw 0.8: roll/pitch fit (0.5 -+ 0.14142); adding yaw gives 1.15858, 1.44142,
    # -0.15858, -0.44142; the largest yaw step back, -0.44142, brings motor 4 to 0 (motor 2 to 1.0, under
    # the 1.15 allowed for yaw): yaw 0.35858 kept, roll, pitch and thrust untouched
    a = alloc(0.5, 0.2, 0.0, 0.8, airmode)
    np.testing.assert_allclose(a, [0.717157, 1.0, 0.282843, 0.0], atol=1e-6)
    r, p, y = moments(a)
    assert r == pytest.approx(0.2, abs=1e-6) and p == pytest.approx(0.0, abs=1e-9)
    assert y == pytest.approx(0.358579, abs=1e-6)
    assert a.mean() == pytest.approx(0.5, abs=1e-6)


def test_yaw_head_room_above_full_output_then_thrust_lowered():
    # thrust 0.95, yaw 0.4 (airmode off): yaw may push to 1.15 (MINIMUM_YAW_MARGIN): yaw 0.2, then the
    # thrust step lowers all by 0.15 so that the CCW pair sits at 1.0 -- PX4's yaw bought with thrust
    a = alloc(0.95, 0.0, 0.0, 0.4, 0)
    np.testing.assert_allclose(a, [1.0, 1.0, 0.6, 0.6], atol=1e-6)
    assert moments(a)[2] == pytest.approx(0.2, abs=1e-6)


def test_airmode_yaw_raises_thrust_for_yaw_at_low_thrust():
    # thrust 0.3, yaw 0.5: CW motors at -0.2. Airmode 2 raises thrust by 0.2 (yaw kept); off/1 cut yaw to 0.3
    np.testing.assert_allclose(alloc(0.3, 0.0, 0.0, 0.5, 2), [1.0, 1.0, 0.0, 0.0], atol=1e-6)
    for mode in (0, 1):
        np.testing.assert_allclose(alloc(0.3, 0.0, 0.0, 0.5, mode), [0.6, 0.6, 0.0, 0.0], atol=1e-6)


def test_within_limits_the_allocation_is_the_plain_mix():
    for mode in (0, 1, 2):
        np.testing.assert_allclose(alloc(0.5, 0.1, -0.05, 0.1, mode), MIX @ [0.5, 0.1, -0.05, 0.1], atol=1e-12)


def test_skip_threshold_ignores_weak_outputs_as_the_allocator_does_but_not_the_mixer():
    # a direction whose entry on the saturated output is 0.1: PX4's allocator (0.2) does not slide on it
    # (the output stays saturated), the mixer (FLT_EPSILON) does
    parts = np.array([[0.0, 0.0], [1.3, 0.5], [0.0, 0.0], [0.0, 0.0]])
    dirs = np.array([[0.1, 0.0], [0.1, 0.0], [0.1, 0.0], [0.1, 0.0]])
    a = np.empty(2)
    px4_allocate(parts, dirs, 0.0, 1.0, 2.0, 0.2, a)
    np.testing.assert_allclose(a, [1.3, 0.5])
    px4_allocate(parts, dirs, 0.0, 1.0, 2.0, 1.1920929e-07, a)
    assert a[0] == pytest.approx(1.0)


def test_mix_directions_of_a_quad_x_are_pxs_normalised_mix():
    vp = shipped("px4_sih_quadx")
    D = px4_mix_directions(allocation_table(vp)[:, :4])
    np.testing.assert_allclose(np.abs(D), np.abs(MIX), atol=1e-6)


def test_log_parameters_choose_airmode_and_allocation():
    am, _, eps, src = allocation_kind({"MC_AIRMODE": 1, "CA_ROTOR_COUNT": 4})
    assert (am, eps) == (1.0, 0.2) and "allocator" in src
    am, _, eps, src = allocation_kind({"MC_AIRMODE": 2, "SYS_CTRL_ALLOC": 0, "CA_ROTOR_COUNT": 4})
    assert (am, eps) == (2.0, 1.1920929e-07) and "mixer" in src
    am, am_src, eps, _ = allocation_kind({"MC_AIRMODE": 7})
    assert (am, eps) == (0.0, 1.1920929e-07) and "not 0/1/2" in am_src
    assert allocation_kind({})[0] == 0.0


def test_controller_gives_up_yaw_and_stops_integrating_into_it():
    """The twin's controller at full throttle with a large yaw-rate error: PX4's mix (yaw to 1.15 then
    thrust lowered: one pair at full output), and the yaw integrator held (PX4's saturation flags)."""
    vp = shipped("px4_sih_quadx")
    m = Multirotor(vp)
    ctrl = Controller(vp)
    assert ctrl.gains == ControllerGains()
    x = m.initial_state(position_enu=(0.0, 0.0, 10.0), rotor_state="hover")
    x[12] = 3.0  # spinning CCW at 3 rad/s, the setpoint is 0: the controller wants all the yaw it can get
    u, _ = ctrl.update_manual(x, x[6:10].copy(), 0.9, 0.004)
    assert ctrl.C[C_SAT + 2] == -1.0                 # the negative yaw torque asked for was not given
    hi = np.abs(u - 1.0) < 1e-9
    assert hi.sum() == 2 and len(set(np.array(vp.rotors.direction)[hi])) == 1  # one spin direction
    ri = ctrl.C[3 + 2]
    for _ in range(50):
        ctrl.update_manual(x, x[6:10].copy(), 0.9, 0.004)
    assert ctrl.C[3 + 2] == ri                       # no wind-up into the saturation


def _spinning_sih(lever_m):
    """PX4's SIH quad X (T_max 5 N, km 0.02 m, yaw damping 0.025 N m s) with tangentially tilted rotors:
    a CCW yaw moment of ``lever_m`` per newton of thrust, beyond what the rotors' reaction torque holds."""
    return shipped("px4_sih_quadx").with_effect("rotor_tilt", lever_m=lever_m)


def test_manual_flight_at_high_throttle_spins_and_climbs_as_px4_allocates():
    """Known truth worked by hand through PX4's mixYaw (airmode off) at throttle 0.9: yaw may push the CCW
    pair to 1.15 (yaw 0.25), then thrust is lowered by 0.15: CCW pair 1.0, CW pair 0.5.  Rotor yaw moment
    -0.02 * 5 * (2 - 1) = -0.1 N m against the tilt's 0.01 * 15 N = +0.15 N m: it spins at
    0.05 / 0.025 = 2.0 rad/s; thrust 15 N against 9.807 N and 1 N/(m/s) drag: it climbs at 5.19 m/s.
    (The allocation before, yaw cut to fit [0, 1] with the thrust kept: 18 N, 8.2 m/s and 5.6 rad/s.)"""
    from twin_nodes.base.frames import euler_from_quat
    vp = _spinning_sih(0.01)
    m = Multirotor(vp)
    ctrl = Controller(vp)
    x = m.initial_state(position_enu=(0.0, 0.0, 500.0), rotor_state="hover")
    dt, ext = 0.004, np.array([np.nan, 0.0, 0.0, 0.0])
    for _ in range(int(12.0 / dt)):
        yaw = euler_from_quat(x[None, 6:10])[0, 2]   # STABILIZED: level, the heading it has, no yaw rate
        u, _ = ctrl.update_manual(x, np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]), 0.9, dt)
        x = m.step(x, u, dt / 4, ext, 4)
    np.testing.assert_allclose(np.sort(u), [0.5, 0.5, 1.0, 1.0], atol=0.02)
    assert x[12] == pytest.approx(2.0, rel=0.03)
    assert x[5] == pytest.approx(15.0 - 9.80665, rel=0.03)


def test_position_hold_with_too_little_yaw_authority_spins_at_the_closed_form_rate():
    """fly_closed_loop holding a position with no yaw setpoint: the altitude loop holds the weight
    (9.807 N) and yaw takes the whole range (CW pair at 0): rotor moment -0.02 * 9.807 N m against the
    tilt's +0.03 * 9.807: steady spin (0.01 * 9.807) / 0.025 = 3.92 rad/s, the position still held."""
    from twin_nodes.twin.control import setpoint
    from twin_nodes.twin.sim import fly_closed_loop
    vp = _spinning_sih(0.03)
    x0 = Multirotor(vp).initial_state(position_enu=(0.0, 0.0, 20.0), rotor_state="hover")
    rec = fly_closed_loop(vp, np.array([0.0]), setpoint(position_enu=(0.0, 0.0, 20.0))[None, :], x0=x0,
                          t_end=15.0)
    late = rec.t >= 12.0
    assert np.mean(rec.x[late, 12]) == pytest.approx(0.01 * 9.80665 / 0.025, rel=0.03)
    assert np.max(np.abs(rec.x[late, 2] - 20.0)) < 0.3
    cw = np.array(vp.rotors.direction) < 0
    assert np.max(rec.u[late][:, cw]) < 0.02                       # the CW pair at idle: yaw given up


def test_twin_fed_the_log_of_a_spinning_vehicle_spins_too(tmp_path):
    """A PX4-style mission flown by a quad whose yaw authority runs out (the SIH quad with 0.03 m of tilt
    lever: more yaw moment at hover than its rotors' reaction torque), written as a ULog; the closed-loop
    twin of that vehicle flown on the log turns as many times as the logged vehicle (32.8 turns in its
    first airborne stretch), the twin without the tilt does not turn at all."""
    from twin_nodes.logs.flyable import read_flight
    from twin_nodes.logs.ulog_write import write_px4_ulog
    from twin_nodes.twin.runner import run_twin_on_log
    from twin_nodes.twin.simflight import Hidden, record_to_topics, simulate_flight
    from twin_nodes.vehicle.export_px4 import simulated_log_params

    vp = shipped("px4_sih_quadx")
    rec, battery, sp_hist = simulate_flight(vp, Hidden("rotor_tilt", {"lever_m": 0.03}), seed=5)
    path = tmp_path / "spin.ulg"
    write_px4_ulog(str(path), record_to_topics(rec, vp, battery, sp_hist, np.random.default_rng(1)),
                   simulated_log_params(vp), {"sys_name": "test"})
    log = read_flight(str(path))
    a, b = log.airborne_intervals()[0]

    def turns(t, q):
        k = (t > a + 2.0) & (t < b - 2.0)
        yaw = np.unwrap(np.arctan2(2 * (q[k, 0] * q[k, 3] + q[k, 1] * q[k, 2]), 1 - 2 * (q[k, 2] ** 2 + q[k, 3] ** 2)))
        return (yaw[-1] - yaw[0]) / (2 * np.pi)

    att = log.require("attitude_q")
    real = turns(att.t_s, np.asarray(att.values))
    assert real > 20.0                                         # the logged vehicle spins
    spun = run_twin_on_log(log, vp.with_effect("rotor_tilt", lever_m=0.03), mode="closed")
    assert turns(spun.t, spun.x[:, 6:10]) == pytest.approx(real, rel=0.05)
    still = run_twin_on_log(log, vp, mode="closed")
    assert abs(turns(still.t, still.x[:, 6:10])) < 0.1


def _px4_mix(params, n):
    """PX4 1.14's normalised multirotor mix (n, 6: roll, pitch, yaw torque, thrust x, y, z; FRD) from the
    log's CA_ROTOR* (ActuatorEffectivenessRotors, ControlAllocationPseudoInverse's scaling)."""
    B = np.zeros((6, n))
    for i in range(n):
        r = np.array([params.get(f"CA_ROTOR{i}_P{a}", 0.0) for a in "XYZ"])
        ax = np.array([params.get(f"CA_ROTOR{i}_AX", 0.0), params.get(f"CA_ROTOR{i}_AY", 0.0),
                       params.get(f"CA_ROTOR{i}_AZ", -1.0)])
        ct, km = params.get(f"CA_ROTOR{i}_CT", 6.5), params.get(f"CA_ROTOR{i}_KM", 0.05)
        B[0:3, i] = ct * np.cross(r, ax) - ct * km * ax
        B[3:6, i] = ct * ax
    mix = np.linalg.pinv(B)
    rp = max(np.sqrt(np.sum(mix[:, c] ** 2) / (np.sum(np.abs(mix[:, c]) > 1e-3) / 2)) for c in (0, 1))
    mix[:, :2] /= rp
    mix[:, 2] /= mix[:, 2].max()
    mix[:, 5] /= np.abs(mix[:, 5]).mean()
    mix[np.abs(mix) < 1e-3] = 0.0
    return mix


@pytest.mark.parametrize("sub,name", [("fleet_quadx_v6c/ZweiterFlugtag", "log_18_2023-6-7-10-49-22.ulg"),
                                      ("real", "real_quadx_v6c_climb35m.ulg")])
def test_px4s_own_setpoints_through_the_allocation_give_its_logged_motors(sub, name):
    """PX4 1.14 (MC_AIRMODE 0) logged what went into its allocator (vehicle_torque_setpoint,
    vehicle_thrust_setpoint) and what came out (actuator_motors): replayed through px4_allocate with PX4's
    own normalised mix, every motor sample is reproduced to float precision, the saturated ones too (the
    fleet's yaw-saturation flight: 306 of its 366 airborne samples have a motor at a bound)."""
    from pyulog import ULog
    from conftest import shared_log

    u = ULog(str(shared_log(sub, name)), ["vehicle_torque_setpoint", "vehicle_thrust_setpoint", "actuator_motors"])
    d = {x.name: x.data for x in u.data_list}
    p = u.initial_parameters
    n = int(p["CA_ROTOR_COUNT"])
    mix = _px4_mix(p, n)
    am = d["actuator_motors"]
    mot = np.column_stack([am[f"control[{i}]"] for i in range(n)])

    def latest(topic, key):
        k = np.clip(np.searchsorted(topic["timestamp_sample"], am["timestamp_sample"], side="right") - 1, 0, None)
        return topic[key][k], topic["timestamp_sample"][k] == am["timestamp_sample"]

    tq = np.column_stack([latest(d["vehicle_torque_setpoint"], f"xyz[{j}]")[0] for j in range(3)])
    up, same_t = latest(d["vehicle_thrust_setpoint"], "xyz[2]")
    up = -up
    same_q = latest(d["vehicle_torque_setpoint"], "xyz[0]")[1]
    dirs = np.ascontiguousarray(np.vstack([-mix[:, 5], mix[:, 0], mix[:, 1], mix[:, 2]]))
    # the motor samples whose allocator input was logged too (same gyro sample); at PX4's logging rates a
    # few motor samples come from a setpoint that was not logged (climb35m: 4 of 587, 21 ms apart)
    flying = np.isfinite(mot).all(axis=1) & (up > 0.05) & same_t & same_q
    a = np.empty(n)
    err, saturated = [], 0
    for k in np.flatnonzero(flying):
        parts = np.ascontiguousarray(dirs * np.array([up[k], *tq[k]])[:, None])
        px4_allocate(parts, dirs, 0.0, 1.0, float(p.get("MC_AIRMODE", 0)), 0.2, a)
        err.append(np.max(np.abs(np.clip(a, 0.0, 1.0) - mot[k])))
        saturated += bool(((mot[k] >= 0.999) | (mot[k] <= 0.001)).any())
    assert len(err) > 300 and saturated > 50, (len(err), saturated)
    assert max(err) < 1e-5
