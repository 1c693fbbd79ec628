"""PX4's sensor timing (issue 11): logged rates come late by the gyro low-pass' group delay, the IMU
average by half an integration interval, and the motor command acts for a whole rate-loop step.
Discovery re-times the log by what its own parameters say, or it takes PX4's sensor latency for
the motors' (on no-effect PX4 SIH flights a 6-9 ms delay and tau_up 0.063 s for 0.05 s)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import shared_log
from scipy.signal import butter, group_delay, lfilter

from twin_nodes.discovery.candidates import SYMMETRIC_LAG, build_candidates
from twin_nodes.discovery.residuals import prepare
from twin_nodes.logs import time_sync
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.vehicle import px4_params
from twin_nodes.vehicle.params import shipped


def test_timing_closed_forms_from_the_log_parameters():
    t = px4_params.sensor_timing({"IMU_GYRO_CUTOFF": 40.0, "IMU_INTEG_RATE": 200, "IMU_GYRO_RATEMAX": 800})
    assert t.gyro_filter_s == pytest.approx(math.sqrt(2) / (2 * math.pi * 40.0))   # 5.63 ms
    assert t.gyro_filter_s == pytest.approx(5.627e-3, abs=1e-6)
    assert t.imu_average_s == pytest.approx(0.5 / 200)
    assert t.command_hold_s == pytest.approx(0.5 / 800)
    assert "IMU_GYRO_CUTOFF 40 Hz" in t.describe()
    # not a PX4 log (our generator, RotorPy): nothing moves
    none = px4_params.sensor_timing({})
    assert (none.gyro_filter_s, none.imu_average_s, none.command_hold_s) == (0.0, 0.0, 0.0)
    assert "no PX4 sensor-timing" in none.describe()
    # a disabled low-pass (PX4: IMU_GYRO_CUTOFF 0) delays nothing
    assert px4_params.sensor_timing({"IMU_GYRO_CUTOFF": 0.0}).gyro_filter_s == 0.0


#: a PX4 SIH log's timing parameters in SITL (PX4's defaults there: px4-rc.simulator sets IMU_INTEG_RATE 250)
SIH_SITL = {"IMU_GYRO_CUTOFF": 40.0, "IMU_INTEG_RATE": 250, "IMU_GYRO_RATEMAX": 800, "SYS_HITL": 0,
            "SYS_AUTOSTART": 10040}


def test_px4_sih_in_sitl_holds_the_command_for_its_lockstep_step():
    """simulator_sih in SITL (Sih::lockstep_loop) steps at min(IMU_GYRO_RATEMAX, IMU_INTEG_RATE), 500-5000 us,
    and applies each step's actuator_outputs over the next step: half a 4 ms step, not half of 1/800 s."""
    assert px4_params.sih_lockstep_step_s(SIH_SITL) == pytest.approx(0.004)
    t = px4_params.sensor_timing(SIH_SITL)
    assert t.command_hold_s == pytest.approx(0.002)
    assert "4 ms PX4 SIH lockstep step" in t.describe()
    # the filter and the IMU average are as on any PX4 log
    assert (t.gyro_filter_s, t.imu_average_s) == (px4_params.sensor_timing(dict(SIH_SITL, SYS_AUTOSTART=4001))
                                                  .gyro_filter_s, 0.5 / 250)
    # a SIH log is known by its SIH_* parameters where its airframe is another
    assert px4_params.sensor_timing(dict(SIH_SITL, SYS_AUTOSTART=4001, SIH_MASS=1.0)).command_hold_s == 0.002
    # not SIH (a real or Gazebo log), or SIH on a flight controller (SYS_HITL 2, real time at IMU_GYRO_RATEMAX)
    for params in (dict(SIH_SITL, SYS_AUTOSTART=4001), dict(SIH_SITL, SYS_HITL=2), dict(SIH_SITL, SYS_HITL=2,
                                                                                          SIH_MASS=1.0)):
        assert px4_params.sih_lockstep_step_s(params) == 0.0
        assert px4_params.sensor_timing(params).command_hold_s == pytest.approx(0.5 / 800)
    # the step: the lower rate (PX4's defaults 400 and 200 Hz where the log lacks one, 400 Hz where the lower
    # is 0), rounded to us, within 500-5000 us
    base = {"SYS_AUTOSTART": 10040}
    assert px4_params.sih_lockstep_step_s(dict(base, IMU_GYRO_RATEMAX=400, IMU_INTEG_RATE=1000)) == 0.0025
    assert px4_params.sih_lockstep_step_s(dict(base, IMU_GYRO_RATEMAX=300, IMU_INTEG_RATE=400)) == 0.003333
    assert px4_params.sih_lockstep_step_s(dict(base, IMU_GYRO_RATEMAX=100, IMU_INTEG_RATE=100)) == 0.005
    assert px4_params.sih_lockstep_step_s(dict(base, IMU_GYRO_RATEMAX=4000, IMU_INTEG_RATE=4000)) == 0.0005
    assert px4_params.sih_lockstep_step_s(base) == 0.005
    assert px4_params.sih_lockstep_step_s(dict(base, IMU_GYRO_RATEMAX=0)) == 0.0025


def test_the_model_applies_a_lockstep_staircase_over_each_fine_step_with_the_stated_hold():
    """SIH's staircase (each 4 ms step's command, stamped at the step's start, acting over the step), logged
    every 20 ms: read with the stated hold at each fine step's middle (residuals._fine_commands), the
    command the model holds over a 2 ms fine step is the staircase's mean over that step, to 0.01 ms of
    the slope; read at the step's start it was 1 ms late, with the 800 Hz hold 1.4 ms early."""
    from types import SimpleNamespace

    from twin_nodes.discovery.residuals import _fine_commands

    slope, step_s = 0.03, 0.004
    stamps = np.arange(0.0, 20.0, 0.02)
    log = SimpleNamespace(t_s=stamps, values=(0.2 + slope * stamps)[:, None])

    def late_s(hold_s):
        u, motor_dt = _fine_commands(log, 2.0, 500, 0.02, 10, hold_s)
        assert motor_dt == pytest.approx(0.02)
        t_fine = 2.0 + np.arange(5000) * 0.002
        sub = t_fine[:, None] + (np.arange(40) + 0.5) / 40 * 0.002
        staircase = np.mean(0.2 + slope * np.floor(sub / step_s + 1e-9) * step_s, axis=1)
        return float(np.mean(u[:, 0] - staircase) / -slope)

    assert abs(late_s(px4_params.sensor_timing(SIH_SITL).command_hold_s)) < 1e-5
    assert late_s(0.5 / 800) == pytest.approx(-0.001375, abs=1e-5)


@pytest.mark.parametrize("fc", [30.0, 40.0, 80.0])
def test_gyro_delay_is_the_digital_butterworth_group_delay(fc):
    """PX4's LowPassFilter2p is a bilinear 2nd-order Butterworth on the gyro samples (kHz on real
    IMUs): its group delay is the closed form within 1 % below 2 Hz, 3 % at 5 Hz."""
    fs = 4000.0
    b, a = butter(2, fc, fs=fs)
    _, gd = group_delay((b, a), w=[0.5, 2.0, 5.0], fs=fs)
    closed = px4_params.sensor_timing({"IMU_GYRO_CUTOFF": fc}).gyro_filter_s
    assert gd[:2] / fs == pytest.approx(closed, rel=0.01)
    assert gd[2] / fs == pytest.approx(closed, rel=0.03)


def test_re_timing_undoes_the_gyro_filter_delay():
    """A body rate through PX4's 40 Hz low-pass on a 50 Hz grid, against the unfiltered rate sampled
    the same way: logged every 4 ms (averaged into the grid) the re-timed rate is 50x closer than
    taken at its stamps (re-timing to a fraction of a sample, not by whole samples); logged every
    40 ms (interpolated) 3x closer (linear interpolation's own error remains)."""
    fs = 1000.0
    t = np.arange(0, 20, 1 / fs)
    true = np.column_stack([np.sin(2 * np.pi * 1.3 * t) + 0.4 * np.sin(2 * np.pi * 3.7 * t + 1.0),
                            0.3 * np.sin(2 * np.pi * 0.7 * t)])
    b, a = butter(2, 40.0, fs=fs)
    filt = lfilter(b, a, true, axis=0)
    grid = np.arange(2.0, 18.0, 0.02)
    late = px4_params.sensor_timing({"IMU_GYRO_CUTOFF": 40.0}).gyro_filter_s
    for step, better in ((4, 50.0), (40, 3.0)):
        ts = t[::step]
        ref = time_sync.sensor_to_grid(ts, true[::step], grid)
        err0 = np.sqrt(np.mean((time_sync.sensor_to_grid(ts, filt[::step], grid) - ref) ** 2))
        err1 = np.sqrt(np.mean((time_sync.sensor_to_grid(ts, filt[::step], grid, late) - ref) ** 2))
        assert err1 * better < err0, (step, err0, err1)


def test_discovery_re_times_a_px4_log_and_says_so():
    """A PX4 SIH log (IMU_GYRO_CUTOFF 40 Hz, IMU_INTEG_RATE 250 Hz, IMU_GYRO_RATEMAX 800 Hz, SITL): the
    flight's ``data.info`` names every shift with its parameter (the command hold: SIH's 4 ms lockstep
    step); a log of ours names none."""
    log = read_ulog(shared_log("sitl_effects", "e07/flight.ulg"))
    vp = shipped("px4_sih_quadx")
    info = prepare(log, vp).info["timing"]
    for text in ("body rates 5.6 ms earlier (IMU_GYRO_CUTOFF 40 Hz", "sensor_combined 2.0 ms earlier (half an "
                 "IMU_INTEG_RATE 250 Hz", "motor commands 2.00 ms later (held for one 4 ms PX4 SIH lockstep step"):
        assert text in info, info


def test_symmetric_motor_lag_candidate_ties_tau_down_to_tau_up():
    """The one-time-constant lag has as many parameters as a delay; its vehicle and its reported
    parameters carry tau_down = tau_up (the joint refit builds through the same parameters)."""
    log = read_ulog(shared_log("sitl_effects", "e07/flight.ulg"))
    vp = shipped("px4_sih_quadx")
    data = prepare(log, vp)
    cands = {c.label: c for c in build_candidates(vp, data)}
    sym, full = cands[SYMMETRIC_LAG], cands["motor_time_constant"]
    assert sym.name == full.name == "motor_time_constant"
    assert sym.param_names == ("tau_up",) and full.param_names == ("tau_up", "tau_down")
    assert len(sym.param_names) == len(cands["actuator_delay"].param_names)
    assert sym.params_dict(np.array([0.12])) == {"tau_up": 0.12, "tau_down": 0.12}
    eff = dict(sym.build(np.array([0.12])).effects)["motor_time_constant"]
    assert dict(eff) == {"tau_up": 0.12, "tau_down": 0.12}
    # inside the nominal's resolution floor: one motor logging interval
    assert not sym.floor(np.array([0.05 + 0.5 * data.motor_dt_s]))
    assert sym.floor(np.array([0.05 + 2 * data.motor_dt_s]))
