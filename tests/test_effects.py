"""Each plug-in effect (twin_nodes.physics.effects.EFFECTS) against the closed form its docstring
states, and the on/off and reuse properties of the generated stepper.

Expected values are written out here (numpy), never read back from the kernel under test.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from twin_nodes.base.errors import ParamsError
from twin_nodes.base.frames import quat_from_euler, quat_to_rotmat
from twin_nodes.vehicle.params import dump_params, load_params, shipped
from twin_nodes.physics.effects import EFFECTS
from twin_nodes.physics.model import Multirotor, MultirotorBatch
from twin_nodes.twin.sim import Simulator, fly_closed_loop

G = 9.80665
NAN4 = np.full(4, np.nan)


@pytest.fixture(scope="module")
def buho():
    return shipped("buho_negro")


@pytest.fixture(scope="module")
def sih():
    return shipped("px4_sih_quadx")


def ext_of(volts=np.nan, wind=(0.0, 0.0, 0.0)):
    return np.array([volts, *wind], dtype=float)


def probe_state(m, rotor_state, z=20.0):
    """A tilted, yawed, moving, rotating state (rotor state given)."""
    return m.initial_state(position_enu=(1.0, 2.0, z), velocity_enu=(4.0, -2.0, 1.0),
                           q_wxyz=quat_from_euler(0.2, -0.15, 0.7), rates_flu=(0.3, -0.2, 0.4),
                           rotor_state=rotor_state)


def air_body(x, wind):
    """Air-relative velocity in body FLU: R^T (v - wind)."""
    return quat_to_rotmat(x[6:10]).T @ (x[3:6] - np.asarray(wind))


# ----------------------------------------------------------------------------- drag / damping


def test_linear_drag_terminal_velocity_is_mg_over_k(sih):
    """SIH: k = 1 N/(m/s), m = 1 kg, falling from rest in a horizontal wind:
    v_z(t) = -(m g / k)(1 - exp(-k t / m)), v_xy(t) = wind (1 - exp(-k t / m))."""
    m = Multirotor(sih)
    k, mass = 1.0, 1.0
    wind = np.array([3.0, -1.0, 0.0])
    x0 = m.initial_state(position_enu=(0.0, 0.0, 5000.0))
    X = m.simulate(x0, np.tile(NAN4, (20_000, 1)), 0.001, ext_of(wind=wind))
    t = np.arange(20_001) * 0.001
    vt = mass * G / k
    np.testing.assert_allclose(X[:, 5], -vt * (1 - np.exp(-k * t / mass)), atol=1e-9)
    np.testing.assert_allclose(X[:, 3:5], wind[:2] * (1 - np.exp(-k * t / mass))[:, None], atol=1e-9)
    assert X[-1, 5] == pytest.approx(-9.80665, rel=1e-8)


def test_a_horizontal_only_linear_drag_leaves_the_fall_free(sih):
    """``vertical`` 0 (a drag identified from the horizontal specific force alone): falling from rest in a
    horizontal wind, v_z(t) = -g t exactly while v_xy(t) = wind (1 - exp(-k t / m)) as with SIH's isotropic drag
    (k = 1 N/(m/s), m = 1 kg)."""
    vp = sih.with_effect("linear_drag", k_n_s_m=1.0, vertical=0.0)
    m = Multirotor(vp)
    wind = np.array([3.0, -1.0, 0.0])
    x0 = m.initial_state(position_enu=(0.0, 0.0, 5000.0))
    X = m.simulate(x0, np.tile(NAN4, (2_000, 1)), 0.001, ext_of(wind=wind))
    t = np.arange(2_001) * 0.001
    np.testing.assert_allclose(X[:, 5], -G * t, atol=1e-9)
    np.testing.assert_allclose(X[:, 3:5], wind[:2] * (1 - np.exp(-t))[:, None], atol=1e-9)
    # a vertical share other than none or all is refused in one line
    with pytest.raises(ParamsError, match="vertical.*expected 0 .horizontal only. or 1"):
        sih.with_effect("linear_drag", k_n_s_m=1.0, vertical=0.5)
    # every form switch (Effect.switches) is checked the same way: body drag's norm form too
    with pytest.raises(ParamsError, match=r"norm.*expected 0 \(per axis\) or 1 \(RotorPy's norm form\), got 0.3"):
        EFFECTS["body_drag"](c_dx=0.1, norm=0.3)
    assert EFFECTS["body_drag"](c_dx=0.1, norm=1).params["norm"] == 1.0
    # a params file without it keeps SIH's isotropic drag
    assert EFFECTS["linear_drag"](k_n_s_m=1.0).params["vertical"] == 1.0


def test_a_refitted_linear_drag_stays_horizontal_only(sih):
    """Discovery's refit of a nominal law's size (stages.selection.nominal_refits) keeps its other parameters:
    a horizontal-only linear drag refitted is still horizontal only."""
    from twin_nodes.discovery.stages.selection import nominal_refits

    nominal = sih.with_effect("linear_drag", k_n_s_m=0.4, vertical=0.0)
    (c,) = [c for c in nominal_refits(nominal, nominal) if c.name == "linear_drag"]
    assert c.build(np.array([0.9])).effect_dict["linear_drag"] == {"k_n_s_m": 0.9, "vertical": 0.0}


@pytest.mark.parametrize("axis, inertia", [(0, 0.025), (1, 0.025), (2, 0.030)])
def test_angular_damping_decays_rates_at_k_over_i(sih, axis, inertia):
    m = Multirotor(sih)
    rates = np.zeros(3)
    rates[axis] = 3.0
    x0 = m.initial_state(position_enu=(0.0, 0.0, 1000.0), rates_flu=rates)
    X = m.simulate(x0, np.tile(NAN4, (2000, 1)), 0.001)
    t = np.arange(2001) * 0.001
    np.testing.assert_allclose(X[:, 10 + axis], 3.0 * np.exp(-0.025 / inertia * t), rtol=1e-9)
    others = [a for a in range(3) if a != axis]
    assert np.max(np.abs(X[:, [10 + a for a in others]])) < 1e-12


def test_rotor_drag_is_minus_kd_omega_times_each_hubs_in_plane_airspeed(buho):
    """H_i = -k_d |omega_i| (u_i,x, u_i,y, 0) at hub r_i, u_i = v_air + w x r_i (body); moment r_i x H_i."""
    kd = 1e-3
    vp = buho.with_effect("rotor_drag", k_d=kd)
    m = Multirotor(vp)
    omega = np.array([300.0, 310.0, 290.0, 305.0])
    x = probe_state(m, omega)
    wind = (1.0, 0.5, 0.2)
    vb = air_body(x, wind)
    r = np.column_stack([vp.rotors.x_flu_m, vp.rotors.y_flu_m, vp.rotors.z_flu_m])
    r[:, 2] = [0.02, 0.02, -0.01, 0.03]  # hubs off the CoM plane too: roll/pitch moments
    vp = vp.replace_rotors(z_flu_m=tuple(r[:, 2]))
    m = Multirotor(vp)
    u = vb + np.cross(x[10:13], r)
    H = -kd * omega[:, None] * np.column_stack([u[:, 0], u[:, 1], np.zeros(4)])
    f, mom = m.wrench_terms(x, ext_of(wind=wind))["rotor_drag"]
    np.testing.assert_allclose(f[0], H.sum(0), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(mom[0], np.cross(r, H).sum(0), rtol=1e-12, atol=1e-15)
    assert abs(mom[0][2]) > 1e-3 and abs(mom[0][0]) > 1e-4  # both moments are there, not zero
    # the dynamics see it: the accelerometer reads (thrust + drag) / m
    thrust = buho.rotors.kt_n_s2_rad2 * np.sum(omega**2)
    np.testing.assert_allclose(m.specific_force_flu(x, np.full(4, 0.5), ext_of(wind=wind)),
                               (H.sum(0) + [0.0, 0.0, thrust]) / buho.mass_kg, rtol=1e-12)


@pytest.mark.parametrize("name", ["buho_negro", "px4_sih_quadx", "rotorpy_crazyflie"])
def test_rotor_drag_damps_a_hovering_yaw_by_kd_sum_omega_arm_squared(name):
    """Hover, no wind, yawing at r: every hub moves tangentially at r |r_i|, so the H-forces cancel
    (symmetric frame, equal speeds) and leave the yaw moment -k_d r sum|omega_i| (x_i^2 + y_i^2),
    nothing on roll and pitch; standing still in the air it is the old CoM force -k_d sum|omega| v."""
    base = shipped(name)
    base = base.replace(effects=())  # rotor_drag alone (SIH carries angular damping, RotorPy rotor drag)
    rate = 0.7
    x = Multirotor(base).initial_state(position_enu=(0.0, 0.0, 10.0), yaw_enu_rad=0.3,
                                       rates_flu=(0.0, 0.0, rate), rotor_state="hover")
    omega = Multirotor(base).rotor_speeds(x)
    arm2 = np.asarray(base.rotors.x_flu_m) ** 2 + np.asarray(base.rotors.y_flu_m) ** 2
    kd = 0.8 * base.inertia[2, 2] / np.sum(omega * arm2)  # a yaw time constant of 1.25 s
    vp = base.with_effect("rotor_drag", k_d=kd)
    m = Multirotor(vp)
    f, mom = m.wrench_terms(x)["rotor_drag"]
    np.testing.assert_allclose(mom[0][2], -kd * rate * np.sum(omega * arm2), rtol=1e-12)
    np.testing.assert_allclose(mom[0][:2], 0.0, atol=1e-14)
    np.testing.assert_allclose(f[0], 0.0, atol=1e-12)
    # the opposite rate, the opposite moment; twice the rate, twice
    x[12] = -2 * rate
    np.testing.assert_allclose(m.wrench_terms(x)["rotor_drag"][1][0][2], 2 * kd * rate * np.sum(omega * arm2),
                               rtol=1e-12)
    # left to itself (equal commands: the reaction torques cancel), the yaw rate decays as
    # exp(-t k_d sum|omega_i| |r_i|^2 / Izz)
    x[12] = rate
    X = m.simulate(x, np.tile(np.full(m.n_rotors, vp.hover_command), (200, 1)), 0.005)
    np.testing.assert_allclose(X[:, 12], rate * np.exp(-0.8 * np.arange(201) * 0.005), rtol=1e-6)
    np.testing.assert_allclose(X[:, 10:12], 0.0, atol=1e-12)


def test_body_drag_is_quadratic_per_body_axis(buho):
    c = np.array([0.05, 0.08, 0.12])
    m = Multirotor(buho.with_effect("body_drag", c_dx=c[0], c_dy=c[1], c_dz=c[2]))
    x = probe_state(m, np.full(4, 250.0))
    wind = (-2.0, 1.0, 0.0)
    vb = air_body(x, wind)
    f = m.wrench_terms(x, ext_of(wind=wind))["body_drag"][0][0]
    np.testing.assert_allclose(f, -c * np.abs(vb) * vb, rtol=1e-12)
    x2 = x.copy()
    x2[3:6] = 2 * x[3:6]
    f2 = m.wrench_terms(x2, ext_of(wind=2 * np.array(wind)))["body_drag"][0][0]
    np.testing.assert_allclose(f2, 4 * f, rtol=1e-12)  # quadratic in airspeed


def test_body_drag_in_rotorpys_norm_form(buho):
    """norm 1: -c_i |v| v_i (RotorPy's parasitic drag); along a body axis both forms agree, off it the norm form
    is stronger on each component by |v| / |v_i|; any other norm value is refused."""
    c = np.array([0.05, 0.08, 0.12])
    m = Multirotor(buho.with_effect("body_drag", c_dx=c[0], c_dy=c[1], c_dz=c[2], norm=1.0))
    x = probe_state(m, np.full(4, 250.0))
    wind = (-2.0, 1.0, 0.5)
    vb = air_body(x, wind)
    f = m.wrench_terms(x, ext_of(wind=wind))["body_drag"][0][0]
    np.testing.assert_allclose(f, -c * np.linalg.norm(vb) * vb, rtol=1e-12)
    per_axis = Multirotor(buho.with_effect("body_drag", c_dx=c[0], c_dy=c[1], c_dz=c[2]))
    g = per_axis.wrench_terms(x, ext_of(wind=wind))["body_drag"][0][0]
    np.testing.assert_allclose(f / g, np.linalg.norm(vb) / np.abs(vb), rtol=1e-12)
    with pytest.raises(ParamsError):
        buho.with_effect("body_drag", c_dx=0.1, norm=0.5)


# ----------------------------------------------------------------------------- rotor / command hooks


@pytest.mark.parametrize("volts", [11.1, 12.6, 13.5])
def test_battery_sag_scales_reference_by_voltage_ratio_power(buho, volts):
    m = Multirotor(buho.with_effect("battery_sag", v_ref=12.6, exponent=1.5))
    x0 = m.initial_state(position_enu=(0.0, 0.0, 100.0), rotor_state=np.full(4, 250.0))
    u = np.array([0.3, 0.4, 0.5, 0.6])
    ref = buho.rotors.reference_from_command(u)
    x = m.step(x0, u, 0.001, ext_of(volts), n_substeps=1000)  # 1 s >> tau
    np.testing.assert_allclose(x[13:], ref * (volts / 12.6) ** 1.5, rtol=1e-9)
    # unknown voltage (NaN): no scaling
    x = m.step(x0, u, 0.001, ext_of(np.nan), n_substeps=1000)
    np.testing.assert_allclose(x[13:], ref, rtol=1e-9)


@pytest.mark.parametrize("motor", [1, 3])
def test_motor_efficiency_scales_one_motors_thrust_and_torque(buho, motor):
    eff = 0.7
    m = Multirotor(buho.with_effect("motor_efficiency", motor=motor, efficiency=eff))
    r = buho.rotors
    omega = np.array([300.0, 280.0, 260.0, 240.0])
    x = m.initial_state(position_enu=(0.0, 0.0, 50.0), rotor_state=omega)
    thrust = r.kt_n_s2_rad2 * omega**2
    thrust[motor - 1] *= eff
    pos = r.positions_flu_m
    moment = np.sum(np.cross(pos, np.column_stack([np.zeros(4), np.zeros(4), thrust])), axis=0)
    moment[2] -= np.dot(r.direction, r.km_m * thrust)
    f, mom = m.wrench_terms(x)["rotors"]
    np.testing.assert_allclose(f[0], [0.0, 0.0, thrust.sum()], rtol=1e-12)
    np.testing.assert_allclose(mom[0], moment, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("z, gain", [(0.0, 1.4), (0.5, 1 + 0.4 * np.exp(-1.0)), (1.5, 1 + 0.4 * np.exp(-3.0)),
                                     (30.0, 1.0)])
def test_ground_effect_multiplier(buho, z, gain):
    m = Multirotor(buho.with_effect("ground_effect", coefficient=0.4, height_scale=0.5))
    omega = np.full(4, 250.0)
    x = m.initial_state(position_enu=(0.0, 0.0, z), rotor_state=omega)
    f = m.wrench_terms(x)["rotors"][0][0]
    assert f[2] == pytest.approx(gain * 4 * buho.rotors.kt_n_s2_rad2 * 250.0**2, rel=1e-12)


def test_rotor_tilt_yaw_moment_is_lever_times_total_thrust(buho):
    lever = 0.012
    m = Multirotor(buho.with_effect("rotor_tilt", lever_m=lever))
    x = m.initial_state(position_enu=(0, 0, 5), rotor_state="hover")
    tz = float(np.sum(m.rotor_thrusts(x)))
    np.testing.assert_allclose(m.wrench_terms(x)["rotor_tilt"][1][0], [0.0, 0.0, lever * tz], rtol=1e-12)


def test_com_offset_thrust_moment_is_minus_d_cross_f_as_before(buho):
    """Thrust only (no rotor drag): a CoM at (dx, dy) adds -d x F = (-dy Tz, dx Tz, 0) to the rotors' moment (the
    closed form of the former thrust-only kernel, unchanged) and leaves the force alone; it is geometry, not a
    wrench term of its own."""
    dx, dy = 0.03, -0.02
    bare = buho.replace(effects=())
    nominal, m = Multirotor(bare), Multirotor(bare.with_effect("com_offset", dx=dx, dy=dy))
    assert m.term_names == nominal.term_names == ["rotors"]
    omega = np.array([300.0, 280.0, 260.0, 240.0])
    x = probe_state(m, omega)
    (f0, m0), (f, mom) = nominal.wrench_terms(x)["rotors"], m.wrench_terms(x)["rotors"]
    tz = bare.rotors.kt_n_s2_rad2 * np.sum(omega**2)
    np.testing.assert_allclose(mom[0] - m0[0], [-dy * tz, dx * tz, 0.0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(f[0], f0[0], rtol=0, atol=0)
    # the controller's geometry is not moved (PX4's mixer does not know where the CoM is)
    assert m.params.rotors.x_flu_m == bare.rotors.x_flu_m


def test_com_offset_turns_the_rotor_drag_about_the_moved_com_in_forward_flight(buho):
    """Pure translation (no rates) through the air with rotor drag: the H-forces are the same (the hubs' airspeed
    is v_air at every hub), the force too, and about the moved CoM they add the yaw moment -(d x H)_z
    = -(dx H_y - dy H_x), H = -k_d sum|omega_i| v_air,xy; roll/pitch change by the thrust's -d x F alone."""
    kd, dx, dy = 1e-3, 0.04, 0.025
    vp = buho.replace(effects=()).with_effect("rotor_drag", k_d=kd)
    nominal, m = Multirotor(vp), Multirotor(vp.with_effect("com_offset", dx=dx, dy=dy))
    omega = np.array([300.0, 310.0, 290.0, 305.0])
    x = m.initial_state(position_enu=(0.0, 0.0, 20.0), velocity_enu=(6.0, -2.0, 0.5), yaw_enu_rad=0.7,
                        rotor_state=omega)
    wind = (1.0, 0.5, 0.2)
    vb = air_body(x, wind)
    H = -kd * np.sum(omega) * vb[:2]
    tz = vp.rotors.kt_n_s2_rad2 * np.sum(omega**2)
    t0, t1 = nominal.wrench_terms(x, ext_of(wind=wind)), m.wrench_terms(x, ext_of(wind=wind))
    np.testing.assert_allclose(t1["rotor_drag"][0][0], [H[0], H[1], 0.0], rtol=1e-12)
    np.testing.assert_allclose(t1["rotor_drag"][0][0], t0["rotor_drag"][0][0], rtol=1e-12)
    np.testing.assert_allclose(t1["rotor_drag"][1][0] - t0["rotor_drag"][1][0],
                               [0.0, 0.0, -(dx * H[1] - dy * H[0])], rtol=1e-12, atol=1e-15)
    assert abs(dx * H[1] - dy * H[0]) > 1e-3  # a moment the former thrust-only offset left out
    total = sum(v[1][0] for v in t1.values()) - sum(v[1][0] for v in t0.values())
    np.testing.assert_allclose(total, [-dy * tz, dx * tz, -(dx * H[1] - dy * H[0])], rtol=1e-12, atol=1e-15)


def test_com_offset_moves_the_hubs_yaw_airspeed_and_damping(buho):
    """Hovering, no wind, yawing at r with rotor drag, equal rotor speeds: each hub moves at w x (r_i - d), so the
    H-forces no longer cancel: their sum is k_d sum|omega_i| r (-dy, dx) (sum r_i = 0); and the yaw damping is -k_d r sum|omega_i| |r_i - d|^2."""
    kd, dx, dy, rate = 1e-3, 0.04, -0.03, 0.7
    vp = buho.replace(effects=()).with_effect("rotor_drag", k_d=kd).with_effect("com_offset", dx=dx, dy=dy)
    m = Multirotor(vp)
    omega = np.full(4, 300.0)  # equal speeds on a symmetric frame: without the offset the H-forces cancel
    x = m.initial_state(position_enu=(0.0, 0.0, 20.0), yaw_enu_rad=0.3, rates_flu=(0.0, 0.0, rate),
                        rotor_state=omega)
    f, mom = m.wrench_terms(x)["rotor_drag"]
    r = vp.rotors
    np.testing.assert_allclose([np.sum(r.x_flu_m), np.sum(r.y_flu_m)], 0.0, atol=1e-12)
    moved2 = (np.asarray(r.x_flu_m) - dx) ** 2 + (np.asarray(r.y_flu_m) - dy) ** 2
    np.testing.assert_allclose(f[0], [kd * np.sum(omega) * rate * -dy, kd * np.sum(omega) * rate * dx, 0.0],
                               rtol=1e-12)
    np.testing.assert_allclose(mom[0][2], -kd * rate * np.sum(omega * moved2), rtol=1e-12)


def test_com_offset_flies_as_the_rotors_moved_by_minus_d(buho):
    """With rotor drag, wind and rates, a vehicle with a CoM offset flies what the nominal with every rotor moved
    by (-dx, -dy) flies (RotorPy's com_offset, prove/grid_rotorpy.py), bit for bit."""
    dx, dy = 0.03, -0.02
    vp = buho.with_effect("rotor_drag", k_d=5e-4).with_effect("body_drag", c_dx=0.05, c_dy=0.05, c_dz=0.1)
    r = vp.rotors
    m = Multirotor(vp.with_effect("com_offset", dx=dx, dy=dy))
    moved = Multirotor(vp.replace_rotors(x_flu_m=tuple(np.array(r.x_flu_m) - dx),
                                         y_flu_m=tuple(np.array(r.y_flu_m) - dy)))
    x0 = probe_state(m, "hover")
    U = np.tile(np.array([0.52, 0.55, 0.5, 0.53]), (300, 1))
    ext = ext_of(wind=(2.0, -1.0, 0.0))
    X = m.simulate(x0, U, 0.002, ext)
    np.testing.assert_array_equal(X, moved.simulate(x0, U, 0.002, ext))
    assert np.ptp(X[:, 10:13]) > 0.1  # it turned


# ----------------------------------------------------------------------------- wind


DRAG_SET = ("rotor_drag", {"k_d": 1e-3}), ("body_drag", {"c_dx": 0.05, "c_dy": 0.05, "c_dz": 0.1})


def sih_with_drag_and_wind(sih, **wind):
    vp = sih
    for name, p in DRAG_SET:
        vp = vp.with_effect(name, **p)
    return vp.with_effect("wind", **wind)


def test_wind_moving_with_the_air_has_no_drag(sih):
    m = Multirotor(sih_with_drag_and_wind(sih, vx=3.0, vy=-2.0, gust_std=0.0))
    t = np.arange(5) * 0.01
    ext = m.exogenous(t)
    np.testing.assert_array_equal(ext[:, 1:4], np.tile([3.0, -2.0, 0.0], (5, 1)))
    assert np.all(np.isnan(ext[:, 0]))
    x = m.initial_state(position_enu=(0.0, 0.0, 20.0), velocity_enu=(3.0, -2.0, 0.0),
                        q_wxyz=quat_from_euler(0.1, 0.2, 1.0), rotor_state=np.full(4, 0.5))
    terms = m.wrench_terms(np.tile(x, (5, 1)), ext)
    for name in ("linear_drag", "rotor_drag", "body_drag"):
        np.testing.assert_allclose(terms[name][0], 0.0, atol=1e-15, err_msg=name)
    # at rest in the same wind, the SIH linear drag pushes downwind: R^T k wind
    x_rest = x.copy()
    x_rest[3:6] = 0.0
    f = m.wrench_terms(x_rest, ext[0])["linear_drag"][0][0]
    np.testing.assert_allclose(f, quat_to_rotmat(x[6:10]).T @ (1.0 * np.array([3.0, -2.0, 0.0])), rtol=1e-12)


def test_wind_gusts_are_reproducible_with_the_stated_spread(sih):
    m = Multirotor(sih_with_drag_and_wind(sih, vx=2.0, vy=0.0, gust_std=0.8))
    t = np.arange(200_000) * 0.01  # 2000 s = 1000 gust time constants
    ext = m.exogenous(t, np.random.default_rng(7))
    np.testing.assert_array_equal(ext, m.exogenous(t, np.random.default_rng(7)))
    gust = ext[:, 1:4] - [2.0, 0.0, 0.0]
    assert np.std(gust[:, 0]) == pytest.approx(0.8, rel=0.1)
    assert np.std(gust[:, 1]) == pytest.approx(0.8, rel=0.1)
    assert np.std(gust[:, 2]) == pytest.approx(0.3 * 0.8, rel=0.1)
    assert abs(np.mean(gust[:, 0])) < 0.15
    lag = 200  # 2 s = one time constant: autocorrelation exp(-1)
    rho = np.corrcoef(gust[:-lag, 0], gust[lag:, 0])[0, 1]
    assert rho == pytest.approx(np.exp(-1.0), abs=0.1)


def test_simulator_flies_in_the_params_file_wind(sih):
    """A ``wind`` effect in the params acts in the Simulator too, as it does in fly_closed_loop:
    SIH hovering in a 3 m/s east wind with its 1 N/(m/s) drag (tau = m/k = 1 s) drifts east."""
    sim = Simulator(sih.with_effect("wind", vx=3.0, vy=0.0, gust_std=0.0))
    sim.reset(sim.model.initial_state(position_enu=(0.0, 0.0, 20.0), rotor_state="hover"))
    for _ in range(500):
        sim.advance(np.full(4, sih.hover_command), 0.004)
    assert sim.state[3] == pytest.approx(3.0 * (1 - np.exp(-2.0)), rel=0.05)


# ----------------------------------------------------------------------------- delay


def test_actuator_delay_shifts_the_simulator_response(buho):
    delay_steps = 20
    plain = Simulator(buho)
    delayed = Simulator(buho.with_effect("actuator_delay", delay=delay_steps * 0.001))
    assert delayed.model.command_delay_s == pytest.approx(0.02)
    t = np.arange(300) * 0.001
    U = np.where(t[:, None] < 0.1, 0.9, 0.5) * np.array([1.0, 1.02, 0.98, 1.0])
    xp = np.array([plain.advance(u, 0.001).copy() for u in U])
    xd = np.array([delayed.advance(u, 0.001).copy() for u in U])
    assert np.all(xd[:delay_steps - 1, 13:] == 0.0)  # motors still stopped (NaN history)
    np.testing.assert_array_equal(xd[delay_steps:], xp[:-delay_steps])


def test_fly_closed_loop_applies_the_delay_to_the_commands(buho):
    vp = buho.with_effect("actuator_delay", delay=0.012)
    t_sp = np.array([0.0])
    sp = np.array([[0.0, 0.0, 1.0] + [np.nan] * 6 + [0.3, np.nan]])
    rec = fly_closed_loop(vp, t_sp, sp, t_end=1.0)
    model = Multirotor(vp)
    n = 3  # 0.012 s at the 250 Hz controller rate
    nsub = 4
    assert rec.t[1] - rec.t[0] == pytest.approx(0.004)

    def replay(shift):
        X = [rec.x[0]]
        for k in range(len(rec.t) - 1):
            u = rec.u[k - shift] if k >= shift else NAN4
            X.append(model.step(X[-1], u, 0.001, rec.ext[k], nsub))
        return np.array(X)

    np.testing.assert_array_equal(replay(n), rec.x)
    assert np.max(np.abs(replay(0) - rec.x)) > 1e-3
    assert rec.x[-1, 2] > 0.5


# ----------------------------------------------------------------------------- parameter effects


PARAM_EFFECTS = [
    ("mass", {"mass": 7.1}, lambda vp: vp.replace(mass_kg=7.1)),
    ("thrust_coefficient", {"kt_scale": 1.1},
     lambda vp: vp.replace_rotors(kt_n_s2_rad2=vp.rotors.kt_n_s2_rad2 * 1.1,
                                  thrust_max_n=vp.rotors.thrust_max_n * 1.1)),
    ("yaw_moment", {"km": 0.031}, lambda vp: vp.replace_rotors(km_m=0.031)),
    ("inertia", {"ixx": 0.2, "iyy": 0.21, "izz": 0.35},
     lambda vp: vp.replace(inertia_kg_m2=((0.2, 0.0, 0.0), (0.0, 0.21, 0.0), (0.0, 0.0, 0.35)))),
    ("motor_time_constant", {"tau_up": 0.05, "tau_down": 0.07},
     lambda vp: vp.replace_rotors(tau_up_s=0.05, tau_down_s=0.07)),
]


@pytest.mark.parametrize("name, params, edit", PARAM_EFFECTS, ids=[p[0] for p in PARAM_EFFECTS])
def test_parameter_effect_equals_editing_the_params(buho, name, params, edit):
    m = Multirotor(buho.with_effect(name, **params))
    ref = Multirotor(edit(buho))
    assert m.params.mass_kg == ref.params.mass_kg
    np.testing.assert_array_equal(m.params.inertia, ref.params.inertia)
    assert m.params.rotors == ref.params.rotors
    np.testing.assert_array_equal(m.P, ref.P)
    assert not np.array_equal(m.P, Multirotor(buho).P)
    x0 = m.initial_state(position_enu=(0.0, 0.0, 30.0), rotor_state=np.full(4, 200.0))
    U = np.tile([0.6, 0.4, 0.5, 0.45], (300, 1))
    np.testing.assert_array_equal(m.simulate(x0, U, 0.001), ref.simulate(x0, U, 0.001))


def test_effects_from_yaml_equal_programmatic(buho, tmp_path):
    d = buho.to_ros_dict()
    d["effects"] = {
        "enabled": ["linear_drag", "battery_sag", "wind", "mass"],
        "linear_drag": {"k_n_s_m": 0.7},
        "battery_sag": {"v_ref": 16.0, "exponent": 1.2},
        "wind": {"vx": 1.5, "vy": -0.5, "gust_std": 0.3},
        "mass": {"mass": 6.2},
    }
    path = tmp_path / "with_effects.yaml"
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": d}}))
    loaded = load_params(path)
    # a file that does not name the linear drag's ``vertical`` gets its default, SIH's isotropic drag
    prog = (buho.with_effect("linear_drag", k_n_s_m=0.7, vertical=1.0).with_effect("battery_sag", v_ref=16.0, exponent=1.2)
            .with_effect("wind", vx=1.5, vy=-0.5, gust_std=0.3).with_effect("mass", mass=6.2))
    assert loaded.effects == prog.effects
    ml, mp = Multirotor(loaded), Multirotor(prog)
    assert ml._mod is mp._mod
    np.testing.assert_array_equal(ml.P, mp.P)
    t = np.arange(400) * 0.005
    ext_l = ml.exogenous(t, np.random.default_rng(1), battery_v=np.full(400, 15.0))
    ext_p = mp.exogenous(t, np.random.default_rng(1), battery_v=np.full(400, 15.0))
    np.testing.assert_array_equal(ext_l, ext_p)
    x0 = ml.initial_state(position_enu=(0.0, 0.0, 10.0), rotor_state="hover")
    U = np.full((400, 4), 0.5)
    np.testing.assert_array_equal(ml.simulate(x0, U, 0.001, ext_l, 5), mp.simulate(x0, U, 0.001, ext_p, 5))
    # and dump -> load keeps them
    path2 = tmp_path / "round_trip.yaml"
    path2.write_text(dump_params(loaded))
    assert load_params(path2).effects == loaded.effects


# ----------------------------------------------------------------------------- switching effects on/off

# Per effect: parameters that make it act, and parameters that make it do nothing.
ACTIVE = {
    "linear_drag": {"k_n_s_m": 0.8},
    "angular_damping": {"k_nm_s_rad": 0.3},
    "rotor_drag": {"k_d": 3e-4},
    "body_drag": {"c_dx": 0.2, "c_dy": 0.2, "c_dz": 0.4},
    "battery_sag": {"v_ref": 15.0, "exponent": 1.0},
    "motor_efficiency": {"motor": 2, "efficiency": 0.8},
    "motor_time_constant": {"tau_up": 0.05, "tau_down": 0.06},
    "actuator_delay": {"delay": 0.012},
    "mass": {"mass": 6.5},
    "thrust_coefficient": {"kt_scale": 0.92},
    "yaw_moment": {"km": 0.03},
    "com_offset": {"dx": 0.01, "dy": -0.01},
    "rotor_tilt": {"lever_m": 0.01},
    "wind": {"vx": 3.0, "vy": -2.0, "gust_std": 0.5},
    "ground_effect": {"coefficient": 0.3, "height_scale": 0.5},
    "inertia": {"ixx": 0.22, "iyy": 0.2, "izz": 0.36},
    "state_term": {"v_h": 6.0, "radius": 0.2, "omega_max": 1000.0, "c_ground": 1.0, "c_mu2": 0.2},
    "coaxial": {"efficiency": 0.8, "lower_mask": 12},
}
NEUTRAL = {
    "linear_drag": {"k_n_s_m": 0.0},
    "angular_damping": {"k_nm_s_rad": 0.0},
    "rotor_drag": {"k_d": 0.0},
    "body_drag": {"c_dx": 0.0, "c_dy": 0.0, "c_dz": 0.0},
    "battery_sag": {"v_ref": 15.0, "exponent": 0.0},
    "motor_efficiency": {"motor": 2, "efficiency": 1.0},
    "motor_time_constant": {"tau_up": 0.023, "tau_down": 0.028},
    "actuator_delay": {"delay": 0.0},
    "mass": {"mass": 5.86},
    "thrust_coefficient": {"kt_scale": 1.0},
    "yaw_moment": {"km": 0.0238},
    "com_offset": {"dx": 0.0, "dy": 0.0},
    "rotor_tilt": {"lever_m": 0.0},
    "wind": {"vx": 0.0, "vy": 0.0, "gust_std": 0.0},
    "ground_effect": {"coefficient": 0.0, "height_scale": 0.5},
    "inertia": {"ixx": 0.179, "iyy": 0.180, "izz": 0.303},
    "state_term": {"v_h": 6.0, "radius": 0.2, "omega_max": 1000.0},
    "coaxial": {"efficiency": 1.0, "lower_mask": 12},
}


def test_every_registered_effect_is_covered_here():
    assert set(ACTIVE) == set(EFFECTS) == set(NEUTRAL)


def flight(vp, nominal):
    """Take off from the ground to 0.6 m (ground effect), fly sideways with a yaw turn, battery at 14 V;
    the controller believes ``nominal``."""
    t_sp = np.array([0.0, 0.6])
    sp = np.array([[0.0, 0.0, 0.6] + [np.nan] * 6 + [0.0, np.nan],
                   [2.0, 1.0, 0.6] + [np.nan] * 6 + [1.0, np.nan]])
    rec = fly_closed_loop(vp, t_sp, sp, controller_params=nominal, t_end=1.5,
                          battery_v=lambda t: np.full(len(t), 14.0), rng=np.random.default_rng(5))
    return rec.x


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_effect_alone_acts_and_is_absent_when_neutral(buho, name):
    # wind acts only through drag terms, so it gets a drag term in both runs
    base = buho.with_effect("linear_drag", k_n_s_m=0.8) if name == "wind" else buho
    x_base = flight(base, buho)
    x_on = flight(base.with_effect(name, **ACTIVE[name]), buho)
    x_neutral = flight(base.with_effect(name, **NEUTRAL[name]), buho)
    assert np.max(np.abs(x_on[:, :13] - x_base[:, :13])) > 1e-4, f"{name} changed nothing"
    np.testing.assert_array_equal(x_neutral, x_base)


def test_each_effect_switches_off_on_its_own_in_the_full_set(buho):
    """All effects on; turning any one of them to neutral changes the flight, and only that one
    (the others keep their parameters)."""
    def with_all(overrides):
        vp = buho
        for name in sorted(EFFECTS):
            vp = vp.with_effect(name, **overrides.get(name, ACTIVE[name]))
        return vp

    x_all = flight(with_all({}), buho)
    for name in sorted(EFFECTS):
        vp = with_all({name: NEUTRAL[name]})
        assert dict(vp.effect_dict)[name] == {k: float(v) for k, v in NEUTRAL[name].items()}
        assert all(vp.effect_dict[o] == {k: float(v) for k, v in ACTIVE[o].items()} for o in EFFECTS if o != name)
        assert np.max(np.abs(flight(vp, buho)[:, :13] - x_all[:, :13])) > 1e-4, name


# ----------------------------------------------------------------------------- generated stepper reuse


def test_generated_stepper_is_shared_by_effect_kinds(buho, sih):
    a = Multirotor(buho.with_effect("rotor_drag", k_d=1e-3))
    b = Multirotor(buho.replace(mass_kg=4.0).with_effect("rotor_drag", k_d=5e-3).with_effect("mass", mass=3.0))
    c = Multirotor(buho)
    d = Multirotor(buho.with_effect("body_drag", c_dx=0.1))
    # one dispatch stepper for every set of kernel effects (the set is in P's effect table)
    assert a._mod is b._mod is c._mod is d._mod
    assert len(a.P) == len(b.P) and len(c.P) < len(a.P)
    # the order of the hooks is in the table (terms are reported in that order)
    e = Multirotor(sih)
    f = Multirotor(sih.replace(effects=tuple(reversed(sih.effects))))
    assert e._mod is f._mod and e.term_names[1:] == list(reversed(f.term_names[1:]))
    assert not np.array_equal(e.P, f.P)
    # different values but the same kinds can be batched; different kinds cannot
    MultirotorBatch([a, b])
    with pytest.raises(ValueError, match="same effect kinds"):
        MultirotorBatch([a, d])
