"""The specific force where the log's accelerometer samples alias the vibration (twin_nodes.logs.imu_rate).

PX4 1.8-1.10's default logger profile keeps sensor_combined every 100 ms; a 20-30 Hz low-passed accelerometer
sampled at 10 Hz folds its vibration into the slow specific force the thrust fit reads.  There the reader
takes the specific force from the estimated velocity's derivative instead."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from twin_nodes.base import frames
from twin_nodes.identify.nominal import nominal_from_log
from twin_nodes.logs import imu_rate
from twin_nodes.logs.flyable import read_flight
from twin_nodes.logs.ulog_write import write_px4_ulog
from twin_nodes.twin.estimate_check import estimate_failures
from twin_nodes.twin.simflight import simulated_log_params

from conftest import SIM_START_US as START_US  # noqa: E402
#: a body-z vibration at twice the 10 Hz logging rate, sampled in step: it aliases to 0 Hz (+1 m/s^2)
VIB_HZ, VIB_M_S2 = 20.0, 1.0


def test_aliased_below_twice_the_accelerometer_cutoff():
    t = np.arange(0.0, 10.0, 1.0 / 8.6)
    assert imu_rate.accel_aliased(t, {"IMU_ACCEL_CUTOFF": 20.0}) == (True, pytest.approx(8.6), 20.0)
    t = np.arange(0.0, 10.0, 1.0 / 200.0)
    assert imu_rate.accel_aliased(t, {"IMU_ACCEL_CUTOFF": 30.0})[0] is False
    # no IMU_ACCEL_CUTOFF in the log: PX4's default 30 Hz, so 50 Hz aliases and 96 Hz does not
    assert imu_rate.accel_aliased(np.arange(0.0, 10.0, 0.02), {}) == (True, pytest.approx(50.0), 30.0)
    assert imu_rate.accel_aliased(np.arange(0.0, 10.0, 1 / 96.0), {})[0] is False


def test_the_specific_force_from_a_known_velocity_and_attitude():
    t = np.arange(0.0, 20.0, 0.125)                 # 8 Hz, as vehicle_local_position on a PX4 1.9 log
    t = np.concatenate([t[t < 8.0], t[t >= 10.0]])  # a 2 s gap: no derivative across it
    v = np.column_stack([np.sin(0.5 * t), 0.3 * t, 0.4 * np.cos(0.8 * t)])
    a = np.column_stack([0.5 * np.cos(0.5 * t), np.full(t.size, 0.3), -0.32 * np.sin(0.8 * t)])
    q = frames.quat_from_euler(np.full(t.size, 0.2), np.full(t.size, -0.1), 0.05 * t)
    qf = lambda tt: frames.quat_from_euler(np.full(tt.size, 0.2), np.full(tt.size, -0.1), 0.05 * tt)  # noqa: E731
    tt, f = imu_rate.specific_force_from_velocity(t, v, qf)
    assert tt.size == t.size
    truth = frames.quat_rotate(frames.quat_conjugate(q), a + np.array([0.0, 0.0, imu_rate.GRAVITY_M_S2]))
    # central differences at 8 Hz: within 3 mm/s^2 inside a stretch; one-sided at the four stretch ends
    inner = np.ones(t.size, bool)
    inner[[0, int(np.sum(t < 8.0)) - 1, int(np.sum(t < 8.0)), t.size - 1]] = False
    assert np.abs(f[inner] - truth[inner]).max() < 3e-3
    assert np.abs(f - truth).max() < 0.05
    v[5] = np.nan                                   # a NaN sample is left out, not spread
    tt, f = imu_rate.specific_force_from_velocity(t, v, qf)
    assert tt.size == t.size - 1 and np.isfinite(f).all()


@pytest.fixture(scope="module")
def flight(sih_quadx_flight):
    return sih_quadx_flight


def _decimated(topics):
    """sensor_combined every 100 ms (PX4 1.9's default profile) with a body-z vibration at 20 Hz in it."""
    topics = {k: dict(v) for k, v in topics.items()}
    sc = topics["sensor_combined"]
    t = (sc["timestamp"].astype(np.int64) - START_US) * 1e-6
    keep = np.flatnonzero(np.isclose(np.mod(t + 1e-9, 0.1), 0.0, atol=1e-6))
    sc = {k: np.asarray(v)[keep] for k, v in sc.items()}
    acc = np.array(sc["accelerometer_m_s2"], float)
    acc[:, 2] -= VIB_M_S2 * np.cos(2 * np.pi * VIB_HZ * t[keep])   # FRD z down: +1 m/s^2 of FLU specific force
    sc["accelerometer_m_s2"] = acc
    topics["sensor_combined"] = sc
    return topics


def test_a_10_hz_accelerometer_is_replaced_and_the_thrust_fit_stays_true(tmp_path, flight, monkeypatch):
    vp, topics = flight
    params = dict(simulated_log_params(vp), IMU_ACCEL_CUTOFF=20.0)
    write_px4_ulog(str(tmp_path / "full.ulg"), topics, params, {"sys_name": "test"}, start_us=START_US)
    write_px4_ulog(str(tmp_path / "dec.ulg"), _decimated(topics), params, {"sys_name": "test"}, start_us=START_US)
    full, dec = read_flight(str(tmp_path / "full.ulg")), read_flight(str(tmp_path / "dec.ulg"))
    assert full.series["specific_force_flu"].source.startswith("sensor_combined")   # 100 Hz >= 2 x 20 Hz
    src = dec.series["specific_force_flu"].source
    assert src.startswith("d/dt vehicle_local_position") and "10.0 Hz, below twice IMU_ACCEL_CUTOFF 20 Hz" in src
    assert any(w.startswith("specific_force_flu: sensor_combined.accelerometer logged at 10.0 Hz") for w in dec.warnings)
    # the derived specific force agrees with the true one below 1 Hz
    a, b = dec.airborne_intervals()[0]
    tg = np.arange(a + 2.0, b - 2.0, 0.1)
    f_dec, f_full = dec.series["specific_force_flu"].at(tg), full.series["specific_force_flu"].at(tg)
    assert abs(np.mean(f_dec[:, 2]) - np.mean(f_full[:, 2])) < 0.05
    # the estimate check compares the velocity with an IMU only: not with the velocity's own derivative
    imu_check = "the IMU's integrated acceleration"
    assert imu_check in estimate_failures(full)[1] and imu_check not in estimate_failures(dec)[1]
    sf = full.series["specific_force_flu"]
    full.series["specific_force_flu"] = replace(sf, source="d/dt vehicle_local_position.vx,vy,vz (NED) + gravity")
    assert imu_check not in estimate_failures(full)[1]
    full.series["specific_force_flu"] = sf
    t_full = nominal_from_log(full, mass_kg=1.0).params.rotors.thrust_max_n
    t_dec = nominal_from_log(dec, mass_kg=1.0).params.rotors.thrust_max_n
    assert t_full == pytest.approx(5.0, rel=0.05)
    assert t_dec == pytest.approx(t_full, rel=0.03)
    # read as logged, the aliased vibration is +1 m/s^2 on ~10 m/s^2: the thrust fit ~10 % high
    monkeypatch.setattr(imu_rate, "accel_aliased", lambda t, p: (False, 10.0, 20.0))
    raw = read_flight(str(tmp_path / "dec.ulg"))
    assert raw.series["specific_force_flu"].source.startswith("sensor_combined")
    t_raw = nominal_from_log(raw, mass_kg=1.0).params.rotors.thrust_max_n
    assert t_raw / t_full - 1.0 > 0.07
