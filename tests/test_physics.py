"""Known-answer tests of the nominal physics (twin_nodes.physics core + model).

World ENU, body FLU, quaternion [w, x, y, z] body -> world, PX4 motor order
(M1 front-right CCW, M2 rear-left CCW, M3 front-left CW, M4 rear-right CW).
Every expected number below comes from a closed form or from r x F written out
here, never from the model itself.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from twin_nodes.base.frames import quat_from_euler, quat_to_rotmat
from twin_nodes.vehicle.params import shipped
from twin_nodes.physics.model import Multirotor, MultirotorBatch

G = 9.80665
NAN4 = np.full(4, np.nan)
# PX4 quad X spin directions, +1 = CCW seen from above (reaction torque on the body is -z).
PX4_DIRECTIONS = (1, 1, -1, -1)


@pytest.fixture(scope="module")
def buho():
    return shipped("buho_negro")


@pytest.fixture(scope="module")
def sih():
    return shipped("px4_sih_quadx")


def omega_command(vp, omega):
    """Command u that makes the omega_squared reference equal ``omega`` (the documented map)."""
    r = vp.rotors
    return (np.asarray(omega, float) - r.omega_min_rad_s) / (r.omega_cmd_max_rad_s - r.omega_min_rad_s)


def hover_command_and_state(vp):
    """Hover command written from the issue's formulas, and the matching rotor state."""
    r = vp.rotors
    if r.thrust_model == "omega_squared":
        omega_h = np.sqrt(vp.mass_kg * vp.gravity_m_s2 / (4 * r.kt_n_s2_rad2))
        return omega_command(vp, omega_h), omega_h
    assert r.thr_mdl_fac == 0.0
    s_h = vp.mass_kg * vp.gravity_m_s2 / (4 * r.thrust_max_n)
    return s_h, s_h


# ----------------------------------------------------------------------------- hover, free fall


@pytest.mark.parametrize("name", ["buho_negro", "px4_sih_quadx"])
def test_hover_holds_altitude_for_10_s(name):
    vp = shipped(name)
    m = Multirotor(vp)
    u_h, s_h = hover_command_and_state(vp)
    x0 = m.initial_state(position_enu=(3.0, -2.0, 10.0), yaw_enu_rad=0.4, rotor_state=np.full(4, s_h))
    X = m.simulate(x0, np.full((10_000, 4), u_h), 0.001)
    assert np.max(np.abs(X[:, 2] - 10.0)) < 0.01
    assert np.max(np.abs(X[:, 0:2] - [3.0, -2.0])) < 0.01
    assert np.max(np.abs(X[:, 10:13])) < 1e-9


def test_buho_hover_speed_is_sqrt_mg_over_4kt(buho):
    assert buho.hover_omega_rad_s == pytest.approx(np.sqrt(5.86 * G / (4 * 2.4066e-4)), rel=1e-12)


def test_free_fall_matches_closed_form(buho):
    m = Multirotor(buho)
    v0 = np.array([1.0, -2.0, 3.0])
    x0 = m.initial_state(position_enu=(0.0, 0.0, 500.0), velocity_enu=v0, yaw_enu_rad=1.0)
    X = m.simulate(x0, np.tile(NAN4, (5000, 1)), 0.001)
    t = np.arange(5001) * 0.001
    p = np.array([0.0, 0.0, 500.0]) + v0 * t[:, None]
    p[:, 2] -= 0.5 * G * t**2
    np.testing.assert_allclose(X[:, 0:3], p, rtol=0, atol=1e-9)
    np.testing.assert_allclose(X[:, 5], v0[2] - G * t, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(X[:, 6:10], np.tile(x0[6:10], (5001, 1)))
    assert np.all(X[:, 13:] == 0.0)


# ----------------------------------------------------------------------------- moments and signs


def test_px4_order_and_spin_in_shipped_params(buho, sih):
    for vp in (buho, sih):
        r = vp.rotors
        assert r.direction == PX4_DIRECTIONS
        # M1 front-right, M2 rear-left, M3 front-left, M4 rear-right (FLU: +x forward, +y left)
        assert np.array_equal(np.sign(r.x_flu_m), [1, -1, 1, -1])
        assert np.array_equal(np.sign(r.y_flu_m), [-1, 1, 1, -1])


@pytest.mark.parametrize("delta", [0.3, -0.3])
def test_pure_yaw_command_gives_q_over_izz_buho(buho, delta):
    """CCW rotors (M1, M2) at T(1+d), CW (M3, M4) at T(1-d): equal total thrust, pure yaw."""
    m = Multirotor(buho)
    omega_h = np.sqrt(buho.mass_kg * G / (4 * buho.rotors.kt_n_s2_rad2))
    omega = omega_h * np.sqrt(1.0 + delta * np.array(PX4_DIRECTIONS, float))
    thrust = buho.rotors.kt_n_s2_rad2 * omega**2
    assert thrust.sum() == pytest.approx(buho.mass_kg * G, rel=1e-12)
    mz = -buho.rotors.km_m * np.dot(PX4_DIRECTIONS, thrust)  # CCW reaction torque is -z
    assert np.sign(mz) == -np.sign(delta)  # faster CCW rotors turn the body clockwise
    x0 = m.initial_state(position_enu=(0.0, 0.0, 50.0), rotor_state=omega)
    X = m.simulate(x0, np.tile(omega_command(buho, omega), (500, 1)), 0.001)
    t = np.arange(501) * 0.001
    np.testing.assert_allclose(X[:, 12], mz / 0.303 * t, rtol=1e-9, atol=1e-12)
    assert np.max(np.abs(X[:, 10:12])) < 1e-12
    assert np.max(np.abs(X[:, 2] - 50.0)) < 1e-9


@pytest.mark.parametrize("delta", [0.3, -0.3])
def test_pure_yaw_command_gives_q_over_izz_sih(sih, delta):
    """SIH (thrust linear in s, with its angular damping): initial yaw acceleration Q/Izz, then
    wz(t) = Q/k (1 - exp(-k t / Izz))."""
    m = Multirotor(sih)
    s_h = sih.mass_kg * G / (4 * 5.0)
    s = s_h * (1.0 + delta * np.array(PX4_DIRECTIONS, float))
    mz = -0.02 * np.dot(PX4_DIRECTIONS, 5.0 * s)
    x0 = m.initial_state(position_enu=(0.0, 0.0, 50.0), rotor_state=s)
    h = 1e-5
    x1 = m.step(x0, s, h)
    assert x1[12] / h == pytest.approx(mz / 0.030, rel=1e-3)
    X = m.simulate(x0, np.tile(s, (1000, 1)), 0.001)
    t = np.arange(1001) * 0.001
    np.testing.assert_allclose(X[:, 12], mz / 0.025 * (1.0 - np.exp(-0.025 * t / 0.030)), rtol=1e-8, atol=1e-12)
    assert np.max(np.abs(X[:, 2] - 50.0)) < 1e-9


# Raising one rotor's thrust, FLU: +Mx lifts the left side (y toward z), +My lowers the nose
# (z toward x).  r x (0, 0, T) = (y T, -x T, 0); reaction torque -d km T on z.
#   M1 front-right (x+, y-), CCW: right side up = left wing down (-Mx), nose up (-My), yaw CW (-Mz)
#   M2 rear-left  (x-, y+), CCW: left side up (+Mx), tail up = nose down (+My), yaw CW (-Mz)
#   M3 front-left (x+, y+), CW:  left side up (+Mx), nose up (-My), yaw CCW (+Mz)
#   M4 rear-right (x-, y-), CW:  left wing down (-Mx), nose down (+My), yaw CCW (+Mz)
@pytest.mark.parametrize("motor, signs", [(0, (-1, -1, -1)), (1, (1, 1, -1)), (2, (1, -1, 1)), (3, (-1, 1, 1))])
def test_single_rotor_moment_is_r_cross_f(buho, motor, signs):
    m = Multirotor(buho)
    r = buho.rotors
    omega_h = np.sqrt(buho.mass_kg * G / (4 * r.kt_n_s2_rad2))
    omega = np.full(4, omega_h)
    omega[motor] *= 1.2
    thrust = r.kt_n_s2_rad2 * omega**2
    pos = np.column_stack([r.x_flu_m, r.y_flu_m, r.z_flu_m])
    ez = np.array([0.0, 0.0, 1.0])
    moment = sum(np.cross(pos[i], thrust[i] * ez) - PX4_DIRECTIONS[i] * r.km_m * thrust[i] * ez for i in range(4))
    assert tuple(np.sign(moment)) == signs
    x0 = m.initial_state(position_enu=(0.0, 0.0, 50.0), rotor_state=omega)
    h = 1e-6
    x1 = m.step(x0, omega_command(buho, omega), h)
    np.testing.assert_allclose(x1[10:13] / h, np.linalg.solve(buho.inertia, moment), rtol=1e-5)


def test_torque_free_spin_conserves_world_momentum_and_energy(buho):
    """Motors stopped in free fall: no moment, so L_world = R J w and w.J.w/2 are constant."""
    J = np.array([[0.21, 0.012, -0.018], [0.012, 0.16, 0.009], [-0.018, 0.009, 0.31]])
    m = Multirotor(buho.replace(inertia_kg_m2=tuple(map(tuple, J))))
    x0 = m.initial_state(position_enu=(0.0, 0.0, 1000.0), rates_flu=(2.0, -1.5, 3.0))
    X = m.simulate(x0, np.tile(NAN4, (10_000, 1)), 0.001)
    w = X[:, 10:13]
    L = np.einsum("tij,jk,tk->ti", quat_to_rotmat(X[:, 6:10]), J, w)
    E = 0.5 * np.einsum("ti,ij,tj->t", w, J, w)
    assert np.max(np.abs(w - w[0])) > 1.0  # the body rates really tumble (non-principal axis)
    assert np.max(np.linalg.norm(L - L[0], axis=1)) / np.linalg.norm(L[0]) < 1e-9
    assert np.max(np.abs(E - E[0])) / E[0] < 1e-9


# ----------------------------------------------------------------------------- rotors


def test_motor_lag_reaches_63_percent_at_tau_up_and_tau_down(buho):
    assert (buho.rotors.tau_up_s, buho.rotors.tau_down_s) == (0.023, 0.028)
    m = Multirotor(buho)
    lo, hi = 0.2, 0.8
    w_lo, w_hi = buho.rotors.reference_from_command(np.array([lo, hi]))
    x_lo = m.initial_state(position_enu=(0.0, 0.0, 100.0), rotor_state=np.full(4, w_lo))
    up = m.simulate(x_lo, np.full((23, 4), hi), 0.001)[:, 13]          # 23 ms = tau_up
    frac_up = (up - w_lo) / (w_hi - w_lo)
    assert frac_up[-1] == pytest.approx(1.0 - np.exp(-1.0), abs=1e-6)
    x_hi = m.initial_state(position_enu=(0.0, 0.0, 100.0), rotor_state=np.full(4, w_hi))
    down = m.simulate(x_hi, np.full((28, 4), lo), 0.001)[:, 13]        # 28 ms = tau_down
    frac_down = (w_hi - down) / (w_hi - w_lo)
    assert frac_down[-1] == pytest.approx(1.0 - np.exp(-1.0), abs=1e-6)
    # and the whole curves are the first-order responses (not swapped time constants)
    np.testing.assert_allclose(frac_up, 1 - np.exp(-np.arange(24) * 0.001 / 0.023), atol=1e-6)
    np.testing.assert_allclose(frac_down, 1 - np.exp(-np.arange(29) * 0.001 / 0.028), atol=1e-6)


def test_sih_lag_acts_on_normalised_command(sih):
    m = Multirotor(sih)
    x0 = m.initial_state(position_enu=(0.0, 0.0, 100.0))
    s = m.simulate(x0, np.full((50, 4), 0.6), 0.001)[:, 13]
    assert s[-1] == pytest.approx(0.6 * (1.0 - np.exp(-1.0)), abs=1e-7)


def test_command_map_and_saturation_at_omega_max(buho):
    r = buho.rotors
    m = Multirotor(buho)
    # u in [0, 1] maps linearly omega_min..omega_cmd_max; outside is clipped
    ref = r.reference_from_command(np.array([0.0, 0.5, 1.0, 1.7, -0.3]))
    np.testing.assert_allclose(ref, [97.4, 97.4 + 0.5 * (462.65 - 97.4), 462.65, 462.65, 97.4])
    x0 = m.initial_state(position_enu=(0.0, 0.0, 100.0), rotor_state=np.full(4, 300.0))
    x_full = m.step(x0, np.ones(4), 0.001, n_substeps=1000)
    x_over = m.step(x0, np.full(4, 1.7), 0.001, n_substeps=1000)
    np.testing.assert_array_equal(x_full, x_over)
    np.testing.assert_allclose(x_full[13:], 462.65, rtol=1e-12)
    # A rotor state above omega_max (set directly) gives omega_max's speed and thrust.
    x_hot = m.initial_state(position_enu=(0.0, 0.0, 100.0), rotor_state=np.full(4, 600.0))
    np.testing.assert_allclose(m.rotor_speeds(x_hot), 487.0)
    f_rotor = m.wrench_terms(x_hot)["rotors"][0][0]
    assert f_rotor[2] == pytest.approx(4 * r.kt_n_s2_rad2 * 487.0**2, rel=1e-12)


def test_rotor_state_never_exceeds_omega_max_when_battery_raises_reference(buho):
    """Gazebo's motor model clamps the reference to the maximum rotor speed before the lag.
    A battery above v_ref scales the reference past omega_max; the rotor must saturate there
    and respond at once when the command drops (no hidden wind-up above omega_max)."""
    m = Multirotor(buho.with_effect("battery_sag", v_ref=12.6, exponent=1.0))
    ext = np.array([16.8, 0.0, 0.0, 0.0])  # full 4S pack: reference x 1.33 -> 617 rad/s > 487
    x0 = m.initial_state(position_enu=(0.0, 0.0, 100.0), rotor_state=np.full(4, 400.0))
    x = m.step(x0, np.ones(4), 0.001, ext, n_substeps=500)
    assert np.all(x[13:] <= 487.0 + 1e-9), x[13:]
    x = m.step(x, np.full(4, 0.2), 0.001, ext, n_substeps=5)
    ref = (97.4 + 0.2 * (462.65 - 97.4)) * 16.8 / 12.6
    np.testing.assert_allclose(m.rotor_speeds(x), ref + (487.0 - ref) * np.exp(-0.005 / 0.028), rtol=1e-6)


def test_nan_command_stops_only_that_motor(buho, sih):
    m = Multirotor(buho)
    u_h, omega_h = hover_command_and_state(buho)
    x0 = m.initial_state(position_enu=(0.0, 0.0, 100.0), rotor_state=np.full(4, omega_h))
    u = np.array([np.nan, u_h, u_h, u_h])
    X = m.simulate(x0, np.tile(u, (100, 1)), 0.001)
    t = np.arange(101) * 0.001
    np.testing.assert_allclose(X[:, 13], omega_h * np.exp(-t / 0.028), rtol=1e-6)
    np.testing.assert_allclose(X[:, 14:17], omega_h, rtol=1e-12)
    # u = 0 is idle (omega_min), NaN is stopped (0)
    x_idle = m.step(x0, np.zeros(4), 0.001, n_substeps=1000)
    x_stop = m.step(x0, NAN4, 0.001, n_substeps=1000)
    np.testing.assert_allclose(x_idle[13:], 97.4, rtol=1e-6)
    assert np.all(x_stop[13:] < 1e-10 * omega_h)
    ms = Multirotor(sih)
    xs = ms.step(ms.initial_state(position_enu=(0, 0, 100), rotor_state=np.full(4, 0.5)), NAN4, 0.001,
                 n_substeps=1000)
    assert np.all(xs[13:] < 0.5 * np.exp(-1.0 / 0.05) * 1.001)


def test_thrust_factor_law_t_max_f_s2_plus_1_minus_f_s(sih):
    f = 0.4
    vp = sih.replace_rotors(thr_mdl_fac=f)
    m = Multirotor(vp)
    s = np.array([0.0, 0.25, 0.6, 1.0])
    x = m.initial_state(position_enu=(0.0, 0.0, 100.0), rotor_state=s)
    expected = 5.0 * (f * s**2 + (1 - f) * s)
    assert m.wrench_terms(x)["rotors"][0][0, 2] == pytest.approx(expected.sum(), rel=1e-12)
    np.testing.assert_allclose(m.rotor_speeds(x), 1000.0 * np.sqrt(expected / 5.0), rtol=1e-12)
    # hover: solve f s^2 + (1 - f) s = m g / (4 T_max) and hold altitude for 10 s
    rel = sih.mass_kg * G / (4 * 5.0)
    s_h = (-(1 - f) + np.sqrt((1 - f) ** 2 + 4 * f * rel)) / (2 * f)
    x0 = m.initial_state(position_enu=(0.0, 0.0, 10.0), rotor_state=np.full(4, s_h))
    X = m.simulate(x0, np.full((10_000, 4), s_h), 0.001)
    assert np.max(np.abs(X[:, 2] - 10.0)) < 0.01
    # the quadratic law needs a larger command than the linear one (f = 0) to carry the weight
    assert 4 * 5.0 * s_h > 1.15 * sih.mass_kg * G


# ----------------------------------------------------------------------------- batch


def test_batch_of_different_vehicles_equals_single_runs(buho):
    rng = np.random.default_rng(3)
    variants = []
    for k in range(5):
        J = np.diag([0.179, 0.180, 0.303]) * (1 + 0.2 * k)
        J[0, 1] = J[1, 0] = 0.003 * k
        variants.append(buho.replace(mass_kg=5.86 + 0.5 * k, inertia_kg_m2=tuple(map(tuple, J)))
                        .replace_rotors(kt_n_s2_rad2=2.4066e-4 * (1 + 0.05 * k), tau_up_s=0.02 + 0.005 * k))
    models = [Multirotor(v) for v in variants]
    batch = MultirotorBatch(models)
    X0 = np.stack([m.initial_state(position_enu=(k, -k, 20.0 + k), rates_flu=rng.normal(size=3),
                                   rotor_state=np.full(4, 240.0)) for k, m in enumerate(models)])
    U = rng.uniform(0.3, 0.8, size=(200, 5, 4))
    U[50:60, 2, 1] = np.nan
    ext = np.array([np.nan, 1.0, -2.0, 0.0])
    XB = X0.copy()
    XS = X0.copy()
    for t in range(200):
        XB = batch.step(XB, U[t], 0.001, ext, n_substeps=4)
        for k, m in enumerate(models):
            XS[k] = m.step(XS[k], U[t, k], 0.001, ext, n_substeps=4)
    assert not np.allclose(XB[0], XB[4])  # the vehicles really differ
    np.testing.assert_array_equal(XB, XS)
    # Multirotor.batch builds the same thing
    XB2 = models[0].batch(variants).step(X0, U[0], 0.001, ext, n_substeps=4)
    np.testing.assert_array_equal(XB2, np.stack([m.step(X0[k], U[0, k], 0.001, ext, 4) for k, m in enumerate(models)]))


# ----------------------------------------------------------------------------- ground contact


@pytest.mark.parametrize("command", [0.0, np.nan], ids=["idle", "stopped"])
def test_rests_on_ground(buho, command):
    m = Multirotor(buho)
    x0 = m.initial_state(yaw_enu_rad=0.7)
    X = m.simulate(x0, np.full((3000, 4), command), 0.001)
    assert np.all(X[:, 0:6] == 0.0)
    np.testing.assert_allclose(X[:, 6:10], np.tile(x0[6:10], (3001, 1)), atol=1e-15)
    np.testing.assert_array_equal(m.specific_force_flu(X[-1], np.full(4, command)), [0.0, 0.0, G])


def test_falls_onto_ground_and_stays(buho):
    m = Multirotor(buho)
    x0 = m.initial_state(position_enu=(0.0, 0.0, 2.0), q_wxyz=quat_from_euler(0.2, -0.1, 0.5))
    X = m.simulate(x0, np.tile(NAN4, (3000, 1)), 0.001)
    assert np.all(X[:, 2] >= 0.0)
    t_impact = np.sqrt(2 * 2.0 / G)
    after = np.arange(3001) * 0.001 > t_impact + 0.002
    assert np.all(X[after, 2] == 0.0) and np.all(X[after, 3:6] == 0.0) and np.all(X[after, 10:13] == 0.0)
    # it lands level, keeping its heading
    np.testing.assert_allclose(X[-1, 6:10], [np.cos(0.25), 0.0, 0.0, np.sin(0.25)], atol=1e-12)


def test_takes_off_from_rest_like_the_vertical_ode(buho):
    """Full command from rest on the ground.  Reference: the 1-D vertical ODE, held at z = 0 until
    kt N omega(t)^2 exceeds m g with omega(t) = omega_cmd_max (1 - exp(-t / tau_up))."""
    m = Multirotor(buho)
    X = m.simulate(m.initial_state(), np.ones((1000, 4)), 0.001)
    kt, wc, tau, mass = 2.4066e-4, 462.65, 0.023, 5.86
    t_lift = -tau * np.log(1 - np.sqrt(mass * G / (4 * kt)) / wc)

    def rhs(t, y):
        w = wc * (1 - np.exp(-t / tau))
        return [y[1], 4 * kt * w * w / mass - G]

    t = np.arange(1001) * 0.001
    sol = solve_ivp(rhs, (t_lift, 1.0), [0.0, 0.0], t_eval=t[t >= t_lift], rtol=1e-11, atol=1e-12)
    assert np.all(X[t < t_lift - 0.001, 2] == 0.0)
    np.testing.assert_allclose(X[t >= t_lift, 2], sol.y[0], atol=2e-3)
    assert X[-1, 2] > 10.0


def test_specific_force_reads_plus_g_up_at_rest_and_in_hover_and_zero_in_free_fall(buho):
    m = Multirotor(buho)
    u_h, omega_h = hover_command_and_state(buho)
    np.testing.assert_array_equal(m.specific_force_flu(m.initial_state(), NAN4), [0.0, 0.0, G])
    x_hover = m.initial_state(position_enu=(0.0, 0.0, 10.0), rotor_state=np.full(4, omega_h))
    np.testing.assert_allclose(m.specific_force_flu(x_hover, np.full(4, u_h)), [0.0, 0.0, G], atol=1e-12)
    x_fall = m.initial_state(position_enu=(0.0, 0.0, 10.0), q_wxyz=quat_from_euler(0.4, 0.3, 0.0))
    np.testing.assert_allclose(m.specific_force_flu(x_fall, NAN4), 0.0, atol=1e-15)


# ----------------------------------------------------------------------------- wrench terms, integrator


def test_wrench_terms_sum_to_the_dynamics():
    """Central differences of v and w from ``simulate`` equal what the summed per-term wrench implies."""
    vp = (shipped("px4_sih_quadx").with_effect("rotor_drag", k_d=2e-3)
          .with_effect("body_drag", c_dx=0.05, c_dy=0.08, c_dz=0.1).with_effect("com_offset", dx=0.002, dy=-0.001)
          .with_effect("ground_effect", coefficient=0.3, height_scale=1.0))
    m = Multirotor(vp)
    assert m.term_names == ["rotors", "linear_drag", "angular_damping", "rotor_drag", "body_drag"]
    h = 0.001
    t = np.arange(1000) * h
    base = 0.55 * (1.0 + 0.2 * np.sin(2 * np.pi * 0.5 * t))
    U = base[:, None] * (1 + 0.01 * np.column_stack([np.sin(3 * t), np.cos(2 * t), -np.sin(3 * t + 1), np.cos(5 * t)]))
    ext = np.tile([np.nan, 2.0, -1.0, 0.3], (len(t), 1))
    x0 = m.initial_state(position_enu=(0.0, 0.0, 0.8), velocity_enu=(3.0, 1.0, 0.0), rates_flu=(0.2, -0.1, 0.5),
                         rotor_state=np.full(4, 0.5))
    X = m.simulate(x0, U, h, ext)
    assert X[:, 2].min() > 0.3  # never on the ground, the ground effect acts throughout
    terms = m.wrench_terms(X, np.vstack([ext, ext[-1:]]))
    F = sum(f for f, _ in terms.values())
    M = sum(mm for _, mm in terms.values())
    for name, (f, mm) in terms.items():
        assert np.max(np.abs(f)) + np.max(np.abs(mm)) > 1e-3, name  # every term contributes
    R = quat_to_rotmat(X[:, 6:10])
    acc = np.einsum("tij,tj->ti", R, F) / vp.mass_kg - [0.0, 0.0, G]
    w = X[:, 10:13]
    J = vp.inertia
    wdot = np.linalg.solve(J, (M - np.cross(w, w @ J.T)).T).T
    acc_fd = (X[2:, 3:6] - X[:-2, 3:6]) / (2 * h)
    wdot_fd = (X[2:, 10:13] - X[:-2, 10:13]) / (2 * h)
    np.testing.assert_allclose(acc_fd, acc[1:-1], atol=2e-4 * np.max(np.abs(acc)))
    np.testing.assert_allclose(wdot_fd, wdot[1:-1], atol=2e-4 * np.max(np.abs(wdot)))


def test_rk4_converges_with_order_4(buho):
    m = Multirotor(buho)
    omega_h = np.sqrt(buho.mass_kg * G / (4 * buho.rotors.kt_n_s2_rad2))
    u = omega_command(buho, omega_h * np.array([1.15, 0.9, 1.05, 0.95]))
    # rotors start below their references, so the lag never switches between tau_up and tau_down
    x0 = m.initial_state(position_enu=(0.0, 0.0, 100.0), rates_flu=(0.3, -0.2, 0.5),
                         rotor_state=np.full(4, 0.5 * omega_h))

    def final(dt):
        return m.simulate(x0, u[None, :], dt, None, int(round(1.0 / dt)))[-1, :13]

    ref = final(1 / 16000)
    errs = [np.max(np.abs(final(dt) - ref)) for dt in (1 / 250, 1 / 500, 1 / 1000)]
    ratios = np.array(errs[:-1]) / np.array(errs[1:])
    assert np.all((ratios > 13.0) & (ratios < 20.0)), (errs, ratios)
