"""A RotorPy log states its own timing (issue 26, tim13): known-truth records written by
``rotorpy_flights.write_record`` and read back the way ``residuals.prepare`` reads them.

The RotorPy loops (``rotorpy_flights.fly``, ``grid_rotorpy.fly``) compute one command per 250 Hz control
step, hold it over the step and log it at the step's start, and log the IMU from the same 250 Hz record.
Two records with closed-form physics: a specific force rising linearly in time, and a motor command
rising linearly in time but held over each control step (a staircase)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from twin_nodes.discovery import residuals
from twin_nodes.logs import time_sync
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.prove import rotorpy_flights as rf
from twin_nodes.twin import simflight
from twin_nodes.twin.sim import FlightRecord
from twin_nodes.vehicle import px4_params
from twin_nodes.vehicle.params import load_params

ROOT = Path(__file__).resolve().parents[1]
DT = 1.0 / rf.CONTROL_RATE_HZ
F_SLOPE = 20.0     # specific force rise [m/s^3] (steep: the IMU noise reads as under 0.1 ms)
U_SLOPE = 0.03     # command rise [1/s]
T_END = 20.0


def _record() -> FlightRecord:
    """20 s at the control rate: armed from 1 s, airborne (z 1 m) from 2.0 to 18.0 s; the command and the
    vertical specific force rise linearly with time."""
    t = np.arange(int(T_END / DT)) * DT
    n = len(t)
    x = np.zeros((n, 17))
    x[:, 2] = np.where((t >= 2.0) & (t < 18.0), 1.0, 0.0)
    x[:, 6] = 1.0                                   # level, wxyz
    u = np.repeat((0.2 + U_SLOPE * t)[:, None], 4, axis=1)
    u[t < 1.0] = np.nan                              # disarmed
    sf = np.zeros((n, 3))
    sf[:, 2] = 9.81 + F_SLOPE * (t - 10.0)
    ext = np.zeros((n, 4))
    ext[:, 0] = np.nan
    return FlightRecord(t=t, x=x, u=u, throttle=np.full(n, 0.5), sp=np.zeros((n, 11)), specific_force=sf, ext=ext,
                        x_est=x.copy(), info={})


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """The record written by the RotorPy writer, and as the writer wrote it before tim13 (the 100 Hz IMU
    picked from the record, no stated control rate)."""
    from twin_nodes.logs.ulog_write import write_px4_ulog

    d = tmp_path_factory.mktemp("timing")
    rec = _record()
    vp = load_params(ROOT / "params" / "rotorpy_crazyflie.yaml")
    rf.write_record(d / "new.ulg", rec, vp, 3)
    topics = simflight.record_to_topics(rec, vp, lambda tt: np.full(np.shape(tt), 16.0), (rec.t, rec.sp),
                                        np.random.default_rng(10))
    write_px4_ulog(str(d / "old.ulg"), topics, {"CA_ROTOR_COUNT": 4}, {"sys_name": "rotorpy"})
    return rec, read_ulog(d / "new.ulg"), read_ulog(d / "old.ulg")


def _grid(log) -> np.ndarray:
    """``residuals.prepare``'s 50 Hz grid: from 2 s before the take-off."""
    t0, t1 = log.airborne_interval()
    lo = max(t0 - 2.0, 0.0)
    return time_sync.common_grid(lo, t1, residuals.DEFAULT_RATE_HZ)


def _imu_late_s(log) -> tuple[float, float]:
    """How late the IMU on the equation-error grid is against the physics (measured from the linear rise), and
    how late the mean stamp of each grid step's samples is (the stamps alone)."""
    s = log.require("specific_force_flu")
    t = _grid(log)
    timing = px4_params.sensor_timing(log.params)
    fz = time_sync.sensor_to_grid(s.t_s, s.values, t, timing.imu_average_s)[:, 2]
    inner = (t > t[0] + 0.05) & (t < t[-1] - 0.05)
    late = -np.mean(fz[inner] - (9.81 + F_SLOPE * (t[inner] - 10.0))) / F_SLOPE
    edges = np.concatenate([t - 0.01, [t[-1] + 0.01]])
    k = np.searchsorted(s.t_s, edges)
    stamp = np.array([s.t_s[a:b].mean() for a, b in zip(k[:-1], k[1:])])
    return float(late), float(np.mean(t[inner] - stamp[inner]))


def _held(t: np.ndarray) -> np.ndarray:
    """The command RotorPy applies at ``t``: the step's command, held over the 4 ms step."""
    return 0.2 + U_SLOPE * np.floor(t / DT + 1e-9) * DT


def _command_late_s(log, hold: float | None = None) -> float:
    """How much later the commands act in RotorPy than the log's reader has them act: the held staircase
    against the logged 50 Hz commands, linear between samples and moved by the log's stated hold
    (``residuals._fine_commands``' reading), on a 0.1 ms grid over the airborne span."""
    ms = log.require("motors")
    hold = px4_params.sensor_timing(log.params).command_hold_s if hold is None else hold
    tau = 2.1 + (np.arange(158_000) + 0.5) * 1e-4
    fin = np.isfinite(ms.values[:, 0])
    read = np.interp(tau - hold, ms.t_s[fin], ms.values[fin, 0])
    return float(-np.mean(_held(tau) - read) / U_SLOPE)


def _fine_step_late_s(log, hold: float | None = None) -> float:
    """The same for what the model applies over each step of its fine grid (``residuals.lag_states`` holds
    ``u_fine`` over the step), against RotorPy's command averaged over that step."""
    ms = log.require("motors")
    t = _grid(log)
    up = 10
    step = (t[1] - t[0]) / up
    hold = px4_params.sensor_timing(log.params).command_hold_s if hold is None else hold
    u_fine, motor_dt = residuals._fine_commands(ms, float(t[0]), len(t), t[1] - t[0], up, hold)
    assert motor_dt == pytest.approx(0.02)
    t_fine = t[0] + np.arange(len(t) * up) * step
    air = (t_fine > 2.1) & (t_fine < 17.9)
    sub = (np.arange(20) + 0.5) / 20 * step
    physics = np.mean(_held(t_fine[air, None] + sub[None, :]), axis=1)
    return float(-np.mean(physics - u_fine[air, 0]) / U_SLOPE)


def test_the_rotorpy_log_states_its_control_rate_and_the_commands_act_where_the_reader_has_them(logs):
    _, new, old = logs
    assert new.params["IMU_GYRO_RATEMAX"] == 250
    timing = px4_params.sensor_timing(new.params)
    assert timing.command_hold_s == pytest.approx(0.002)
    assert timing.gyro_filter_s == 0.0 and timing.imu_average_s == 0.0
    # RotorPy's staircase acts half a control step after its stamps: read with the stated hold, the reader's
    # command is RotorPy's to within 0.01 ms; the old log's (no stated rate) has it act 2 ms before RotorPy does
    assert abs(_command_late_s(new)) < 1e-5
    assert _command_late_s(old) == pytest.approx(0.002, abs=1e-5)
    # the model's fine grid holds each step's command over the step and reads it at the step's middle (fs13;
    # read at the step's start it acted half a fine step, 1 ms on a 50 Hz grid, late): over each fine step the
    # model applies RotorPy's mean command to within 0.01 ms on the new log, and on the old log the 2 ms the
    # log does not state
    assert abs(_fine_step_late_s(new)) < 1e-5
    assert _fine_step_late_s(old) == pytest.approx(0.002, abs=1e-5)


def test_the_rotorpy_imu_is_on_uniform_stamps_centred_in_the_grid_steps(logs):
    rec, new, old = logs
    s = new.require("specific_force_flu")
    assert np.allclose(np.diff(s.t_s), DT, atol=2e-6)  # every record sample, 4 ms apart
    late, stamp_late = _imu_late_s(new)
    assert abs(stamp_late) < 1e-6 and abs(late) < 2e-4
    # the old 100 Hz pick (stamps 8 and 12 ms apart): this take-off's phase puts each 20 ms step's samples
    # 4 ms before its centre, and the IMU reads 4 ms late against the physics, as the stamps say
    late_old, stamp_late_old = _imu_late_s(old)
    assert stamp_late_old == pytest.approx(0.004, abs=1e-6)
    assert late_old == pytest.approx(stamp_late_old, abs=3e-4)
    # the noise per second is the old log's: 250 Hz samples carry sqrt(2.5) the 100 Hz sample's
    n_new = new.require("specific_force_flu").values[:, 0]
    n_old = old.require("specific_force_flu").values[:, 0]
    assert np.std(n_new) / np.std(n_old) == pytest.approx(np.sqrt(2.5), rel=0.05)


def test_the_grid_flights_key_covers_the_writer():
    import inspect

    from twin_nodes.prove import grid_rotorpy

    src = inspect.getsource(grid_rotorpy.key)
    assert "rf.write_record" in src and "simflight.record_to_topics" in src


def _stepped_late_s(log) -> tuple[float, float]:
    """:func:`_command_late_s` and :func:`_fine_step_late_s` with the hold ``residuals.prepare`` takes (the log's
    stated one, else half the step its stamps sit on)."""
    hold = residuals._stepped_hold(px4_params.sensor_timing(log.params), log).command_hold_s
    return _command_late_s(log, hold), _fine_step_late_s(log, hold)


def test_a_log_stating_no_rate_holds_each_command_over_the_step_its_stamps_sit_on(logs):
    _, new, old = logs
    # the old writer's stamps (IMU 8/12 ms apart, motors every 20 ms) all sit on RotorPy's 4 ms control step
    assert time_sync.stamp_step_s(old.require("motors").t_s, old.require("specific_force_flu").t_s) == \
        pytest.approx(0.004, abs=1e-9)
    held = residuals._stepped_hold(px4_params.sensor_timing(old.params), old)
    assert held.command_hold_s == pytest.approx(0.002, abs=1e-9)
    assert "4 ms step every stamp sits on" in held.describe()
    # with it the old log's commands act where RotorPy's do (the 2 ms above gone), on the reader and the fine grid
    command, fine = _stepped_late_s(old)
    assert abs(command) < 1e-5 and abs(fine) < 1e-5
    # a log that states its rate keeps the stated hold
    stated = px4_params.sensor_timing(new.params)
    assert residuals._stepped_hold(stated, new) is stated


def test_stamps_on_no_fixed_step_give_no_step():
    rng = np.random.default_rng(3)
    lattice = 20.0 + np.arange(500) * 0.004
    assert time_sync.stamp_step_s(lattice[::3], lattice[::5]) == pytest.approx(0.004, abs=1e-9)
    # a flight controller's clock: microsecond jitter on the same rate (divisor ~1 us)
    jittered = lattice + rng.integers(-40, 41, len(lattice)) * 1e-6
    assert time_sync.stamp_step_s(jittered) == 0.0
    # a step outside 0.5-5 ms (PX4 SIH's lockstep range), or too few stamps, is no step
    assert time_sync.stamp_step_s(20.0 + np.arange(500) * 0.02) == 0.0
    assert time_sync.stamp_step_s(20.0 + np.arange(500) * 0.0002) == 0.0
    assert time_sync.stamp_step_s(lattice[:time_sync.MIN_STEP_STAMPS - 1]) == 0.0
