"""The offline twin reads the logged setpoint trajectory between its samples; the runner's armed state may be
unknown; a setpoint taken again in a moved ground plane keeps its sample time.

Issue 27's RotorPy floor: RotorPy's SE(3) law follows its trajectory every 4 ms while the log keeps 25 Hz of
it; held, the acceleration feed-forward lagged half a logging interval and the exact plant's closed-loop twin
left 4.8 % held-out throttle RMSE, nearly all in the braking after fast descents.
"""

from __future__ import annotations

import numpy as np
import pytest

from twin_nodes.twin.control import setpoint
from twin_nodes.twin.inputs import armed_rows, bridge_setpoint_gaps
from twin_nodes.twin.runner import TwinRunner
from twin_nodes.vehicle.params import shipped


def test_the_trajectory_between_samples_is_the_line_through_them():
    """Closed form: a 5 Hz log of p(t) = (2 t, 0, 10 - t) read on a 250 Hz grid is p(t) at every grid time
    between two samples (a hold is off by up to 0.4 m); an axis NaN at either end is held; before the first
    and after the last sample nothing changes."""
    ts = np.arange(0.0, 2.01, 0.2)
    vals = np.column_stack([2.0 * ts, 0.0 * ts, 10.0 - ts])
    vals[5, 1] = np.nan
    grid = np.arange(-0.1, 2.2, 0.004)
    k = np.clip(np.searchsorted(ts, grid, side="right") - 1, 0, len(ts) - 1)
    held = np.where((grid >= 0)[:, None], vals[k], np.nan)
    out = bridge_setpoint_gaps(ts, vals, grid, held, min_gap_s=0.0)
    inside = (grid >= 0.0) & (grid <= 2.0)
    assert np.allclose(out[inside, 0], 2.0 * grid[inside], atol=1e-12)
    assert np.allclose(out[inside, 2], 10.0 - grid[inside], atol=1e-12)
    assert np.max(np.abs(held[inside, 0] - 2.0 * grid[inside])) > 0.39
    nan_side = (grid > 0.8) & (grid < 1.2)               # the samples at 0.8 and 1.0 s: y NaN at 1.0 s
    assert np.array_equal(out[nan_side, 1], held[nan_side, 1], equal_nan=True)
    assert np.isnan(out[grid < 0.0]).all()
    assert np.array_equal(out[grid > 2.0], held[grid > 2.0])


def test_the_offline_feed_reads_a_logged_ramp_exactly(tmp_path):
    """A PX4 log's 25 Hz trajectory_setpoint of a climb at 1.5 m/s: the offline feed's z setpoint equals the
    ramp at every control step inside the logged span (to float precision), velocity and acceleration too."""
    from twin_nodes.logs.ulog_io import Series
    from twin_nodes.twin import inputs

    class Log:
        def __init__(self, series):
            self.s = series

        def get(self, name):
            return self.s.get(name)

        def resample(self, names, rate_hz, t0, t1):
            grid = np.arange(0.0, 4.0, 1.0 / rate_hz)
            from twin_nodes.logs import time_sync
            return grid, {n: time_sync.interp_to(self.s[n].t_s, self.s[n].values, grid, kind=self.s[n].interp)
                          for n in names}

    t = np.arange(0.0, 4.0, 0.04)
    tf = np.arange(0.0, 4.0, 0.01)
    one = np.ones_like(tf)
    series = {
        "position_enu": Series(tf, np.column_stack([0 * tf, 0 * tf, 1.5 * tf]), "m", "ENU", "t", "linear"),
        "velocity_enu": Series(tf, np.column_stack([0 * tf, 0 * tf, 1.5 * one]), "m/s", "ENU", "t", "linear"),
        "attitude_q": Series(tf, np.column_stack([one, 0 * tf, 0 * tf, 0 * tf]), "", "FLU", "t", "linear"),
        "body_rates_flu": Series(tf, np.zeros((len(tf), 3)), "rad/s", "FLU", "t", "linear"),
        "motors": Series(tf, 0.5 * np.ones((len(tf), 4)), "", "", "t", "previous"),
        "setpoint_position_enu": Series(t, np.column_stack([0 * t, 0 * t, 1.5 * t + 0.1 * t ** 2]), "m", "ENU",
                                        "t", "previous"),
        "setpoint_velocity_enu": Series(t, np.column_stack([0 * t, 0 * t, 1.5 + 0.2 * t]), "m/s", "ENU", "t",
                                        "previous"),
        "setpoint_accel_enu": Series(t, np.column_stack([0 * t, 0 * t, 0.2 + 0.0 * t]), "m/s^2", "ENU", "t",
                                     "previous"),
    }
    feed = inputs.log_feed(Log(series), 250.0)
    m = (feed.t > 0.0) & (feed.t < t[-1])
    g = feed.t[m]
    assert np.allclose(feed.sp[m, 5], 1.5 + 0.2 * g, atol=1e-12)
    assert np.allclose(feed.sp[m, 8], 0.2, atol=1e-12)
    # the position: the chord of the parabola, at most a h^2 / 8 = 0.1 * 0.04^2 / 4 = 4e-5 m off
    assert np.max(np.abs(feed.sp[m, 2] - (1.5 * g + 0.1 * g ** 2))) < 4.1e-5
    assert not feed.repeated[m][1:].any()
    held = inputs.log_feed(Log(series), 250.0, between_samples=False)
    assert np.max(np.abs(held.sp[m, 5] - (1.5 + 0.2 * g))) == pytest.approx(0.2 * 0.04, rel=0.15)


def test_armed_state_unknown_before_the_first_armed_sample():
    """A log whose logging began in the air gets its first armed message after its first states: the rows
    before it are unknown (NaN), not disarmed; the twin flies them (a disarmed twin would be held where the
    real vehicle hovers and take that height as its ground)."""
    data = {"armed": np.array([np.nan, np.nan, 1.0, 1.0, 0.0]), "motors": np.full((5, 4), 0.5)}
    a = armed_rows(data, 5)
    assert np.isnan(a[:2]).all() and a[2:].tolist() == [1.0, 1.0, 0.0]
    assert armed_rows({"motors": np.array([[np.nan] * 4, [0.4] * 4])}, 2).tolist() == [0.0, 1.0]

    r = TwinRunner(shipped("px4_sih_quadx"))
    r.real_state(0.0, [0.0, 0.0, 12.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    r.real_motors(np.full(4, 0.5))
    r.armed(float("nan"))
    assert r.is_armed is None
    r.setpoint(setpoint(position_enu=(0.0, 0.0, 12.0)))
    r.advance_to(0.1)
    assert r.flown_as == "cascade"
    r.armed(0.0)
    r.advance_to(0.2)
    assert r.flown_as == "disarmed"


def test_a_sample_taken_again_in_a_moved_ground_frame_keeps_its_time():
    """The ground plane moved (the real vehicle below the twin's plane): the same logged sample is taken
    again in the new frame, and its trajectory is carried on from the time it was logged, shifted by the
    plane's move (before, the carry restarted at the move: a saw-tooth of up to v x 0.2 s on a 5 Hz log)."""
    r = TwinRunner(shipped("px4_sih_quadx"))
    r.real_state(0.0, [0.0, 0.0, 10.0], [0.0, 0.0, -0.7], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    r.armed(True)
    r.advance_to(0.04)
    sp = setpoint(position_enu=(0.0, 0.0, 10.0), velocity_enu=(0.0, 0.0, -0.7))
    r.setpoint(sp)
    t_sample = r.t
    r.advance_to(0.14)
    r.ground_z -= 0.5                          # the plane moved down 0.5 m
    r.setpoint(sp)                             # the same sample, taken again in the new frame
    r.advance_to(0.2)
    carried = r._carried_setpoint()
    assert carried[2] == pytest.approx(10.0 + 0.5 - 0.7 * (r.t - t_sample), abs=1e-9)
