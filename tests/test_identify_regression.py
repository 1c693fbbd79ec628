"""Equation-error regression: recovered coefficients and (un)identifiable combinations.

The synthetic flight is generated here from a params-schema vehicle: smooth
random motor commands go through the params file's command map and the first-
order lag (the reference's discretised motor model) to rotor speeds; body rates
and body velocities are smooth random signals; specific force and angular
acceleration follow the model equations exactly, plus white sensor noise.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from twin_nodes.base import frames
from twin_nodes.identify.regression import (RotorGeometry, fit_linear, fit_moment_form, rotational_regression,
                                            rotor_states_from_commands, structural_identifiability,
                                            thrust_regressor, translational_regression, world_to_body)
from twin_nodes.identify.step_response import discretize_zoh
from twin_nodes.vehicle.params import from_ros_dict

ARM = 0.25 / math.sqrt(2.0)
VEHICLE = {
    "vehicle": {"name": "synthetic", "mass_kg": 1.5, "ixx_kg_m2": 0.03, "iyy_kg_m2": 0.035, "izz_kg_m2": 0.05},
    "rotors": {"x_flu_m": [ARM, -ARM, ARM, -ARM], "y_flu_m": [-ARM, ARM, ARM, -ARM], "direction": [1, 1, -1, -1],
               "thrust_model": "omega_squared", "kt_n_s2_rad2": 1.0e-5, "km_m": 0.016,
               "omega_min_rad_s": 100.0, "omega_cmd_max_rad_s": 1000.0, "omega_max_rad_s": 1050.0,
               "tau_up_s": 0.04, "tau_down_s": 0.06},
}
KD = np.array([0.3, 0.35, 0.5])      # N/(m/s) linear drag per body axis
KDW = np.array([0.004, 0.005, 0.006])  # N m/(rad/s) angular damping per axis


def smooth(rng: np.random.Generator, n: int, k: int, fs: float, cutoff: float, scale: float) -> np.ndarray:
    b, a = signal.butter(2, cutoff / (0.5 * fs))
    x = signal.filtfilt(b, a, rng.normal(size=(n, k)), axis=0)
    return scale * x / x.std(axis=0)


@pytest.fixture(scope="module")
def synthetic():
    vp = from_ros_dict(VEHICLE)
    rng = np.random.default_rng(11)
    fs = 100.0
    t = np.arange(0.0, 60.0, 1.0 / fs)
    n = t.size
    u = np.clip(0.6 + smooth(rng, n, 4, fs, 3.0, 0.06), 0.0, 1.0)
    r = vp.rotors
    omega = rotor_states_from_commands(t, u, tau_up_s=r.tau_up_s, tau_down_s=r.tau_down_s,
                                       reference=r.reference_from_command)
    tt = thrust_regressor(omega, "omega_squared")
    w = smooth(rng, n, 3, fs, 2.0, 1.0)
    vb = smooth(rng, n, 3, fs, 0.3, 3.0)
    m, I = vp.mass_kg, np.diag(vp.inertia)
    T = r.kt_n_s2_rad2 * tt
    f = np.column_stack([-KD[0] * vb[:, 0], -KD[1] * vb[:, 1], T.sum(axis=1) - KD[2] * vb[:, 2]]) / m
    x, y, d = np.array(r.x_flu_m), np.array(r.y_flu_m), np.array(r.direction, float)
    M = np.column_stack([T @ y, -(T @ x), -r.km_m * (T @ d)])
    gyro = np.column_stack([(I[1] - I[2]) * w[:, 1] * w[:, 2], (I[2] - I[0]) * w[:, 2] * w[:, 0],
                            (I[0] - I[1]) * w[:, 0] * w[:, 1]])
    wd = (M + gyro - KDW * w) / I
    f_meas = f + rng.normal(0, 0.05, f.shape)
    wd_meas = wd + rng.normal(0, 0.5, wd.shape)
    return vp, t, u, omega, tt, w, vb, f_meas, wd_meas, wd


def test_rotor_states_are_the_discretised_motor_model(synthetic):
    vp, t, u, omega, *_ = synthetic
    r = vp.rotors
    sym = rotor_states_from_commands(t, u[:, :1], tau_up_s=0.05, reference=r.reference_from_command)[:, 0]
    ref = r.reference_from_command(u[:, 0])
    d = discretize_zoh(0.05, 1.0, 100.0)
    y = np.empty_like(ref)
    y[0] = ref[0]
    for k in range(ref.size - 1):
        y[k + 1] = d.a * y[k] + d.b[0] * ref[k]
    np.testing.assert_allclose(sym, y, rtol=1e-10)
    assert np.all(omega >= r.omega_min_rad_s) and np.all(omega <= r.omega_max_rad_s)


def test_translational_coefficients_recovered(synthetic):
    vp, t, u, omega, tt, w, vb, f, wd, _ = synthetic
    res = translational_regression(f, tt, vb)
    m = vp.mass_kg
    assert res["z"]["kT/m"] == pytest.approx(vp.rotors.kt_n_s2_rad2 / m, rel=0.01)
    assert res["z"]["kd_z/m"] == pytest.approx(KD[2] / m, rel=0.02)
    assert res["x"]["kd_x/m"] == pytest.approx(KD[0] / m, rel=0.02)
    assert res["y"]["kd_y/m"] == pytest.approx(KD[1] / m, rel=0.02)
    z = res["z"]
    assert z.r2 > 0.9 and z.rank == 2 and not z.combinations and np.all(z.identifiable)
    # standard errors are honest
    assert abs(z["kT/m"] - vp.rotors.kt_n_s2_rad2 / m) < 4 * z.se("kT/m")


def test_rotational_coefficients_recovered(synthetic):
    """Errors in the measured response only (white noise on the angular acceleration, exact
    commands): plain least squares of the acceleration on the commands is the right estimator."""
    vp, t, u, omega, tt, w, vb, f, wd, _ = synthetic
    geo = RotorGeometry.from_params(vp)
    res = rotational_regression(wd, w, tt, geo, form="acceleration")
    kt, km, l = vp.rotors.kt_n_s2_rad2, vp.rotors.km_m, geo.arm_length_m
    Ixx, Iyy, Izz = np.diag(vp.inertia)
    assert l == pytest.approx(0.25)
    assert res["roll"]["kT*l/Ixx"] == pytest.approx(kt * l / Ixx, rel=0.01)
    assert res["pitch"]["kT*l/Iyy"] == pytest.approx(kt * l / Iyy, rel=0.01)
    assert res["yaw"]["km*kT/Izz"] == pytest.approx(km * kt / Izz, rel=0.02)
    assert res["roll"]["(Iyy-Izz)/Ixx"] == pytest.approx((Iyy - Izz) / Ixx, abs=0.02)
    assert res["yaw"]["kdw_z/Izz"] == pytest.approx(KDW[2] / Izz, rel=0.05)
    for ax, fit in res.items():
        assert fit.r2 > (0.9 if ax != "yaw" else 0.4) and fit.condition_number < 10  # yaw: small signal


def test_collinear_regressors_are_flagged_with_their_combination(synthetic):
    vp, t, u, omega, tt, w, vb, f, wd, _ = synthetic
    # Vertical body velocity made proportional to the summed rotor speed^2: drag and thrust collinear.
    c = 2e-6
    vb2 = vb.copy()
    vb2[:, 2] = c * tt.sum(axis=1)
    m = vp.mass_kg
    fz = (vp.rotors.kt_n_s2_rad2 * tt.sum(axis=1) - KD[2] * vb2[:, 2]) / m
    f2 = f.copy()
    f2[:, 2] = fz + np.random.default_rng(3).normal(0, 0.05, fz.size)
    z = translational_regression(f2, tt, vb2)["z"]
    assert z.rank == 1 and z.condition_number > 1e6
    assert not z.identifiable.any() and np.all(np.isinf(z.stderr))
    assert set(z.null_space[0]) == {"kT/m", "kd_z/m"}
    (combo,) = z.combinations
    # only kT/m - c kd_z/m is determined, and it is right
    assert combo.weights["kT/m"] == 1.0 and combo.weights["kd_z/m"] == pytest.approx(-c, rel=1e-6)
    truth = vp.rotors.kt_n_s2_rad2 / m - c * KD[2] / m
    assert combo.value == pytest.approx(truth, rel=0.01)
    assert np.isfinite(combo.stderr) and combo.stderr < 0.01 * truth
    assert "kT/m" in combo.text() and "kd_z/m" in combo.text()


def test_hover_only_thrust_and_intercept_not_separable():
    """Constant rotor speeds (pure hover): kT/m and an accelerometer bias are one number."""
    rng = np.random.default_rng(5)
    n = 2000
    tt = np.full((n, 4), 400.0 ** 2)
    f = np.column_stack([np.zeros(n), np.zeros(n), np.full(n, 9.81)]) + rng.normal(0, 0.05, (n, 3))
    z = translational_regression(f, tt, None, intercept=True)["z"]
    assert z.rank == 1 and not z.identifiable.any()
    (combo,) = z.combinations
    assert set(combo.weights) == {"kT/m", "bias_z"}
    assert combo.value * (4 * 400.0 ** 2 if combo.weights["kT/m"] == 1.0 else 1.0) == pytest.approx(9.81, rel=0.01)


def test_fit_linear_generic_collinearity():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(500, 3))
    X[:, 2] = 2.0 * X[:, 1]
    y = X @ np.array([1.0, 2.0, 3.0]) + rng.normal(0, 0.01, 500)
    fit = fit_linear(X, y, ["a", "b", "c"])
    assert fit.identifiable.tolist() == [True, False, False]
    assert fit["a"] == pytest.approx(1.0, abs=0.01)
    (combo,) = fit.combinations
    assert combo.weights == pytest.approx({"b": 1.0, "c": 2.0})
    assert combo.value == pytest.approx(2.0 + 2.0 * 3.0, rel=1e-3)
    with pytest.raises(ValueError, match="expected"):
        fit_linear(X, y[:-1], ["a", "b", "c"])


def test_structural_identifiability_of_the_rotational_coefficients():
    coefs = ["kT/m", "kT*l/Ixx", "kT*l/Iyy", "km*kT/Izz"]
    s = structural_identifiability(coefs)
    assert s.rank == 4 and len(s.null_directions) == len(s.involved) - 4
    assert not s.determined  # nothing is separately identifiable from these alone
    tied = [set(d) for d in s.null_directions]
    assert any({"km", "Izz"} <= d for d in tied)  # yaw: only km kT / Izz
    assert any({"m", "kT"} <= d for d in tied)
    # with mass, arm length and km measured, every remaining parameter follows
    s2 = structural_identifiability(coefs, known=("m", "l", "km"))
    assert not s2.null_directions and set(s2.determined) == {"kT", "Ixx", "Iyy", "Izz"}


def test_world_to_body_matches_frames():
    rng = np.random.default_rng(1)
    q = frames.quat_normalize(rng.normal(size=(50, 4)))
    v = rng.normal(size=(50, 3))
    vb = world_to_body(q, v)
    np.testing.assert_allclose(frames.quat_rotate(q, vb), v, atol=1e-12)


def test_quad_x_geometry_matches_px4_order():
    g = RotorGeometry.quad_x(0.25)
    assert g.arm_length_m == pytest.approx(0.25)
    # Motor1 front-right CCW, Motor3 front-left CW (FLU: right = -y)
    assert g.x_flu_m[0] > 0 and g.y_flu_m[0] < 0 and g.direction[0] == 1
    assert g.x_flu_m[2] > 0 and g.y_flu_m[2] > 0 and g.direction[2] == -1


def test_errors_in_the_commands_need_the_moment_form(synthetic):
    """The logged commands carry noise no motion follows (controller noise, aliasing of an
    instantaneous 50 Hz sample): least squares of the acceleration on them is attenuated by
    var(signal) / (var(signal) + var(noise)); the moment form (commands on the left) is not."""
    vp, _, _, omega, _, w, _, _, _, wd_true = synthetic
    r = vp.rotors
    # rotor speeds reconstructed from the logged commands: white errors of ~ half the signal's spread
    omega_logged = omega + np.random.default_rng(7).normal(0.0, 30.0, omega.shape)
    tt_logged = thrust_regressor(omega_logged, "omega_squared")
    wd_clean = wd_true + np.random.default_rng(8).normal(0, 0.05, wd_true.shape)  # a small measurement noise remains
    geo = RotorGeometry.from_params(vp)
    kt, km, l = r.kt_n_s2_rad2, r.km_m, geo.arm_length_m
    Ixx, Iyy, Izz = np.diag(vp.inertia)
    truth = {"roll": ("kT*l/Ixx", kt * l / Ixx), "pitch": ("kT*l/Iyy", kt * l / Iyy),
             "yaw": ("km*kT/Izz", km * kt / Izz)}
    ls = rotational_regression(wd_clean, w, tt_logged, geo, form="acceleration")
    mom = rotational_regression(wd_clean, w, tt_logged, geo)  # default: moment form
    for ax, (nm, val) in truth.items():
        assert ls[ax][nm] < 0.9 * val  # attenuated by the command errors
        assert mom[ax][nm] == pytest.approx(val, rel=0.03)
        assert abs(mom[ax][nm] - val) < 4 * mom[ax].se(nm) + 0.01 * val  # honest standard errors
        assert mom[ax].method.startswith("moment form") and ls[ax].method == "least squares"
    for ax, nm, val in (("roll", "kdw_x/Ixx", KDW[0] / Ixx), ("yaw", "kdw_z/Izz", KDW[2] / Izz)):
        assert abs(mom[ax][nm] - val) < 4 * mom[ax].se(nm)  # the other terms: within their errors
    with pytest.raises(ValueError, match="form"):
        rotational_regression(wd_clean, w, tt_logged, geo, form="tls")


def test_moment_form_falls_back_where_the_input_does_not_drive_the_output():
    rng = np.random.default_rng(4)
    X = rng.normal(size=(400, 2))
    y = 0.5 * X[:, 1] + rng.normal(0, 0.1, 400)  # the first column has no effect
    fit = fit_moment_form(X, y, ["b", "c"])
    assert fit.method == "least squares" and abs(fit["b"]) < 0.05
