"""The PX4-like cascade (twin_nodes.twin.control) flying the physics model through sim.fly_closed_loop."""

from __future__ import annotations

import numpy as np
import pytest

from twin_nodes.twin.control import Controller, ControllerGains, setpoint
from twin_nodes.vehicle.geometry import allocation_matrix
from twin_nodes.base.frames import euler_from_quat, wrap_pi
from twin_nodes.vehicle.params import shipped
from twin_nodes.physics.model import Multirotor
from twin_nodes.twin.sim import fly_closed_loop

VEHICLES = ["buho_negro", "px4_sih_quadx"]


def fly(vp, sp, x0_pos, t_end, yaw0=0.0):
    m = Multirotor(vp)
    x0 = m.initial_state(position_enu=x0_pos, yaw_enu_rad=yaw0, rotor_state="hover")
    return fly_closed_loop(vp, np.array([0.0]), sp[None, :], x0=x0, t_end=t_end)


def tilt_deg(x):
    """Angle between body z and world z [deg]: R22 = 1 - 2 (qx^2 + qy^2)."""
    return np.degrees(np.arccos(np.clip(1 - 2 * (x[:, 7] ** 2 + x[:, 8] ** 2), -1, 1)))


@pytest.mark.parametrize("name", VEHICLES)
def test_hover_settles_from_a_displaced_start(name):
    vp = shipped(name)
    rec = fly(vp, setpoint(position_enu=(0.0, 0.0, 5.0)), (1.0, -0.8, 4.5), 10.0)
    err = np.linalg.norm(rec.x[:, 0:3] - [0.0, 0.0, 5.0], axis=1)
    assert err[0] > 1.0
    assert np.max(err[rec.t >= 9.0]) < 0.05
    assert np.max(tilt_deg(rec.x)) < 30.0


@pytest.mark.parametrize("name", VEHICLES)
def test_10_m_step_in_x_settles_with_less_than_20_percent_overshoot(name):
    vp = shipped(name)
    rec = fly(vp, setpoint(position_enu=(10.0, 0.0, 5.0)), (0.0, 0.0, 5.0), 15.0)
    x = rec.x[:, 0]
    assert np.max(x) - 10.0 < 2.0
    assert np.max(x) > 9.9  # it got there
    assert np.max(np.abs(x[rec.t >= 14.0] - 10.0)) < 0.2
    assert np.max(np.abs(rec.x[:, 1])) < 0.1
    assert np.max(np.abs(rec.x[:, 2] - 5.0)) < 0.5


@pytest.mark.parametrize("name", VEHICLES)
def test_yaw_step_reaches_target_turning_counter_clockwise(name):
    vp = shipped(name)
    rec = fly(vp, setpoint(position_enu=(0.0, 0.0, 5.0), yaw_enu=np.pi / 2), (0.0, 0.0, 5.0), 6.0)
    yaw = euler_from_quat(rec.x[:, 6:10])[:, 2]
    assert np.min(yaw) > -np.radians(1.0)  # ENU yaw +90 deg is a CCW turn; it never goes the long way
    assert np.max(np.abs(wrap_pi(yaw[rec.t >= 5.0] - np.pi / 2))) < np.radians(2.0)
    assert np.max(np.linalg.norm(rec.x[:, 0:3] - [0.0, 0.0, 5.0], axis=1)) < 0.2


@pytest.mark.parametrize("name", VEHICLES)
@pytest.mark.parametrize("target", [(30.0, 0.0, 5.0), (40.0, -30.0, 8.0)], ids=["level", "climbing"])
def test_tilt_stays_within_tilt_max_plus_10_deg_on_a_large_step(name, target):
    """A climbing diagonal step saturates the SIH rotors: roll/pitch authority must be kept
    (the collective gives way, PX4 sequential desaturation), or the tilt overshoots."""
    vp = shipped(name)
    rec = fly(vp, setpoint(position_enu=target), (0.0, 0.0, 5.0), 6.0)
    tilt_max = ControllerGains.from_params(vp).tilt_max_deg
    assert np.max(tilt_deg(rec.x)) > tilt_max - 5.0  # the limit is really reached
    assert np.max(tilt_deg(rec.x)) <= tilt_max + 10.0


@pytest.mark.parametrize("name", VEHICLES)
def test_allocation_inverts_the_physical_rotor_effectiveness(name):
    """B (from the model's own wrench: one rotor at 1 N at a time) maps rotor thrusts to
    [T, Mx, My, Mz]; the controller's allocation A must satisfy B @ A = I."""
    vp = shipped(name).replace(effects=())
    m = Multirotor(vp)
    r = vp.rotors
    cols = []
    for i in range(r.count):
        thrust = np.zeros(r.count)
        thrust[i] = 1.0
        state = np.sqrt(thrust / r.kt_n_s2_rad2) if r.thrust_model == "omega_squared" else thrust / r.thrust_max_n
        f, mom = m.wrench_terms(m.initial_state(position_enu=(0, 0, 10), rotor_state=state))["rotors"]
        cols.append([f[0, 2], *mom[0]])
    B = np.array(cols).T
    A = allocation_matrix(vp)
    np.testing.assert_allclose(B @ A, np.eye(4), atol=1e-12)
    # yaw row sign: a CCW rotor (direction +1) turns the body clockwise (-Mz)
    assert np.all(np.sign(B[3]) == -np.array(r.direction))


@pytest.mark.parametrize("name", VEHICLES)
def test_controller_at_the_setpoint_commands_hover(name):
    vp = shipped(name)
    m = Multirotor(vp)
    x = m.initial_state(position_enu=(1.0, 2.0, 3.0), yaw_enu_rad=0.5)
    u, info = Controller(vp).update(x, setpoint(position_enu=(1.0, 2.0, 3.0), yaw_enu=0.5), 0.004)
    np.testing.assert_allclose(u, vp.hover_command, rtol=1e-9)
    assert info[1] == pytest.approx(vp.mass_kg * vp.gravity_m_s2, rel=1e-12)


def test_auto_gains_keep_fast_vehicles_at_defaults_and_slow_motors_stable():
    """Default gains scale with the motor lag: exact defaults for fast motors, a stable
    cascade for the 3DR Quad-C's 0.15 s motors (which the fast defaults drive unstable)."""
    from twin_nodes.twin.control import ControllerGains, setpoint
    from twin_nodes.vehicle.params import shipped
    from twin_nodes.twin.sim import fly_closed_loop

    assert ControllerGains.from_params(shipped("px4_sih_quadx")) == ControllerGains()
    assert ControllerGains.from_params(shipped("buho_negro")) == ControllerGains()
    qc = shipped("quad_c_3dr")
    g = ControllerGains.from_params(qc)
    assert g.rate_p_1_s * qc.rotors.tau_up_s <= 0.7 + 1e-9
    t_sp = np.array([0.0, 1.0, 8.0])
    sp = np.stack([setpoint(position_enu=(0, 0, 5), yaw_enu=0.0), setpoint(position_enu=(0, 0, 5), yaw_enu=0.0),
                   setpoint(position_enu=(10, 0, 8), yaw_enu=1.0)])
    rec = fly_closed_loop(qc, t_sp, sp, t_end=35.0)
    tilt = np.degrees(np.arccos(np.clip(1 - 2 * (rec.x[:, 7] ** 2 + rec.x[:, 8] ** 2), -1, 1)))
    assert tilt.max() < 35.0
    assert np.linalg.norm(rec.x[-1, :3] - [10, 0, 8]) < 0.3
    assert np.nanstd(rec.u[-250:], axis=0).max() < 0.01  # no limit cycle
    # the fast defaults forced onto the slow motors oscillate: the scaling is what keeps it flying
    fast = qc.replace(controller={k: v for k, v in vars(ControllerGains()).items()})
    rec_fast = fly_closed_loop(fast, t_sp, sp, t_end=20.0)
    assert np.nanstd(rec_fast.u[-250:], axis=0).max() > 0.05


@pytest.mark.parametrize("name", VEHICLES)
def test_manual_mode_flies_the_pilots_thrust_and_attitude(name):
    """PX4 MANUAL/STAB: no position controller; the collective is the pilot's throttle (what the log's
    vehicle_thrust_setpoint holds) and the attitude loops hold the given attitude."""
    vp = shipped(name)
    m = Multirotor(vp)
    ctrl = Controller(vp)
    x = m.initial_state(position_enu=(0.0, 0.0, 30.0), yaw_enu_rad=0.3, rotor_state="hover")
    q_level = x[6:10].copy()
    # hover throttle: the collective equals the hover command, motors equal
    u, info = ctrl.update_manual(x, q_level, vp.hover_command, 0.004)
    np.testing.assert_allclose(u, vp.hover_command, rtol=1e-9)
    assert info[0] == pytest.approx(vp.hover_command, rel=1e-9)
    assert info[1] == pytest.approx(vp.mass_kg * vp.gravity_m_s2, rel=1e-6)
    # throttle near idle: the vehicle falls (as the climb35m log's 0.5 s in MANUAL at 8 % thrust)
    dt = 0.004
    for _ in range(int(0.5 / dt)):
        u, info = ctrl.update_manual(x, q_level, 0.08, dt)
        x = m.step(x, u, dt / 4, np.array([np.nan, 0.0, 0.0, 0.0]), 4)
    assert x[5] < -2.5 and x[2] < 29.4                      # falling: thrust far below the weight
    assert tilt_deg(x[None, :])[0] < 2.0                    # attitude held level meanwhile
    assert np.all(np.asarray(info[0]) == pytest.approx(0.08))


def test_vertical_integrator_does_not_wind_up_at_the_thrust_limit():
    """PX4 PositionControl::_velocityControl: no vertical integration of an error that pushes further
    into the thrust limit the setpoint already sits at."""
    from twin_nodes.twin.control import C_VI

    vp = shipped("px4_sih_quadx")
    m = Multirotor(vp)
    x = m.initial_state(position_enu=(0.0, 0.0, 10.0), rotor_state="hover")
    ctrl = Controller(vp)
    sp = setpoint(velocity_enu=(0.0, 0.0, 20.0))  # far beyond what full thrust gives
    for _ in range(200):
        _, info = ctrl.update(x, sp, 0.004)
    assert info[1] == pytest.approx(ctrl.gains.thr_max * vp.rotors.count * vp.rotors.thrust_max_n)  # at the limit
    assert ctrl.C[C_VI + 2] == 0.0  # saturated from the first step: nothing integrated
    sp_ok = setpoint(velocity_enu=(0.0, 0.0, 0.5))
    for _ in range(200):
        ctrl.update(x, sp_ok, 0.004)
    assert ctrl.C[C_VI + 2] > 0.0   # unsaturated: integrates again
