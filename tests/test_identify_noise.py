"""IMU noise: bias, white-noise std, Allan deviation and the params ``sensors`` block."""

from __future__ import annotations

import numpy as np
import pytest

from twin_nodes.identify.noise import (BIAS_INSTABILITY_FACTOR, allan_deviation, analyse_allan, imu_noise,
                                       sensors_block, stationary_runs)
from twin_nodes.vehicle.params import from_ros_dict, shipped

FS = 100.0
SIGMA_G = np.array([0.01, 0.02, 0.005])   # rad/s white noise per axis
BIAS_G = np.array([0.002, -0.001, 0.0005])
SIGMA_A = 0.04                             # m/s^2
BIAS_A = np.array([0.05, -0.03, 0.08])


@pytest.fixture(scope="module")
def record():
    rng = np.random.default_rng(42)
    n = int(600 * FS)  # 10 min at 100 Hz, as in the reference
    gyro = BIAS_G + rng.normal(size=(n, 3)) * SIGMA_G
    accel = np.array([0.0, 0.0, 9.80665]) + BIAS_A + rng.normal(0.0, SIGMA_A, (n, 3))
    return gyro, accel


def test_allan_deviation_of_white_noise_follows_sigma_over_sqrt_tau_fs(record):
    gyro, _ = record
    taus, adev = allan_deviation(gyro, FS)
    theory = SIGMA_G / np.sqrt(taus[:, None] * FS)
    short = taus <= 1.0
    np.testing.assert_allclose(adev[short], theory[short], rtol=0.05)
    # fitted slope of log adev vs log tau is -1/2 over two decades
    sel = (taus >= 0.05) & (taus <= 5.0)
    for k in range(3):
        slope = np.polyfit(np.log10(taus[sel]), np.log10(adev[sel, k]), 1)[0]
        assert slope == pytest.approx(-0.5, abs=0.03)
    res = analyse_allan(taus, adev, FS)
    np.testing.assert_allclose(res.random_walk, SIGMA_G / np.sqrt(FS), rtol=0.03)


def test_rate_random_walk_gives_plus_half_slope():
    rng = np.random.default_rng(7)
    n = int(600 * FS)
    k_rrw = 2e-3  # rate random walk [rad/s/sqrt(s)]
    sigma = 0.002
    x = sigma * rng.normal(size=n) + np.cumsum(k_rrw / np.sqrt(FS) * rng.normal(size=n))
    taus, adev = allan_deviation(x, FS)
    theory = np.sqrt(sigma ** 2 / (taus * FS) + k_rrw ** 2 * taus / 3.0)
    mid = (taus >= 0.01) & (taus <= 30.0)
    np.testing.assert_allclose(adev[mid, 0], theory[mid], rtol=0.25)
    long = (taus >= 1.0) & (taus <= 30.0)  # rate random walk dominates above ~0.2 s here
    slope = np.polyfit(np.log10(taus[long]), np.log10(adev[long, 0]), 1)[0]
    assert slope == pytest.approx(0.5, abs=0.15)
    res = analyse_allan(taus, adev, FS)
    # the minimum sits between the two slopes: B = min / 0.664, with a minimum inside the range
    assert res.bias_instability_bounded[0]
    assert res.bias_instability[0] == pytest.approx(adev[:, 0].min() / BIAS_INSTABILITY_FACTOR)
    tmin = res.bias_instability_tau_s[0]
    t_cross = np.sqrt(3.0 * sigma ** 2 / (FS * k_rrw ** 2))  # where the two slopes meet (~0.17 s)
    assert t_cross / 3 < tmin < 3 * t_cross
    assert res.random_walk[0] == pytest.approx(sigma / np.sqrt(FS), rel=0.05)


def test_imu_noise_bias_std_and_sensors_block(record):
    gyro, accel = record
    res = imu_noise(gyro, accel, FS, accel_reference="level")
    np.testing.assert_allclose(res.gyro_bias_rad_s, BIAS_G, atol=4 * SIGMA_G.max() / np.sqrt(gyro.shape[0]))
    np.testing.assert_allclose(res.gyro_noise_rad_s, SIGMA_G, rtol=0.01)
    np.testing.assert_allclose(res.accel_bias_m_s2, BIAS_A, atol=1e-3)
    np.testing.assert_allclose(res.accel_noise_m_s2, SIGMA_A, rtol=0.01)
    # mean_direction: only the along-gravity error is bias (tilt and horizontal bias are one thing)
    res2 = imu_noise(gyro, accel, FS)
    g_dir = res2.accel_mean_m_s2 / np.linalg.norm(res2.accel_mean_m_s2)
    assert np.cross(res2.accel_bias_m_s2, g_dir) == pytest.approx(np.zeros(3), abs=1e-9)
    block = sensors_block(res)
    assert set(block) == {"gyro_noise_rad_s", "gyro_bias_rad_s", "accel_noise_m_s2", "accel_bias_m_s2",
                          "gyro_arw_rad_s_sqrt_hz", "accel_vrw_m_s2_sqrt_hz", "gyro_bias_instability_rad_s",
                          "accel_bias_instability_m_s2", "sample_rate_hz"}
    for k in ("gyro_noise_rad_s", "gyro_bias_rad_s", "accel_noise_m_s2", "accel_bias_m_s2"):
        assert isinstance(block[k], list) and len(block[k]) == 3 and all(isinstance(v, float) for v in block[k])
    assert block["gyro_arw_rad_s_sqrt_hz"] == pytest.approx(np.mean(SIGMA_G) / np.sqrt(FS), rel=0.03)
    assert block["sample_rate_hz"] == FS
    # merged into a params file, the schema accepts it
    base = shipped("px4_sih_quadx").to_ros_dict()
    base["sensors"] = block
    vp = from_ros_dict(base)
    assert vp.sensors["gyro_noise_rad_s"] == block["gyro_noise_rad_s"]


def test_stationary_runs_skip_handling():
    rng = np.random.default_rng(3)
    t = np.arange(0, 30, 0.01)
    g = rng.normal(0, 0.003, (t.size, 3))
    a = np.array([0, 0, 9.81]) + rng.normal(0, 0.02, (t.size, 3))
    moved = (t > 10) & (t < 14)
    g[moved] += 0.5 * np.sin(3 * t[moved])[:, None]
    a[moved] += 2.0 * np.sin(5 * t[moved])[:, None]
    runs = stationary_runs(t, g, a)
    assert len(runs) == 2
    (a0, b0), (a1, b1) = runs
    assert t[b0 - 1] < 10.0 and t[a1] > 14.0
    assert t[b0 - 1] - t[a0] > 8.5 and t[b1 - 1] - t[a1] > 14.5


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        imu_noise(np.zeros((10, 2)), np.zeros((10, 2)), 100.0)
    with pytest.raises(ValueError, match="at least 8"):
        allan_deviation(np.zeros(5), 100.0)
