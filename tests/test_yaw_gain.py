"""The yaw setpoint at the attitude setpoint's rate, carried apart from the position, and the yaw
attitude gain the log's firmware applied, identified from its own rate setpoints."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_log
from twin_nodes.identify.yaw_gain import (REPLACE_REL, YawGainFit, applied_yaw_gain, fit_yaw_law,
                                          yaw_gain_for_twin)
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.vehicle.params import shipped


def test_fit_yaw_law_recovers_a_known_law():
    rng = np.random.default_rng(3)
    e = rng.normal(0.0, 0.1, 4000)
    ff = np.repeat(rng.choice([0.0, 0.785, -0.785], 40), 100)
    r = 1.7 * e + 0.95 * ff + rng.normal(0.0, 0.01, e.size)
    k, c, r2 = fit_yaw_law(e, ff, r)
    assert k == pytest.approx(1.7, rel=0.01) and c == pytest.approx(0.95, rel=0.01) and r2 > 0.99


def test_yaw_gain_replaces_mc_yaw_p_only_when_the_log_says_so():
    fit = YawGainFit(1.2, 1.0, 0.97, (1.15, 1.3), 2000, 40.0)
    k, why = yaw_gain_for_twin(fit, 2.8, 0.4)
    assert k == 1.2 and "MC_YAW_P x MC_YAW_WEIGHT" in why
    # within REPLACE_REL of the parameter: the parameter as flown
    assert yaw_gain_for_twin(YawGainFit(2.8 * (1 + 0.9 * REPLACE_REL), 1.0, 0.97, (3.4, 3.6), 2000, 40.0),
                             2.8, 0.4)[0] is None
    # halves that disagree (an adaptive controller at work) or a poor fit: not replaced
    assert yaw_gain_for_twin(YawGainFit(0.57, 1.0, 0.97, (0.52, 1.13), 2000, 40.0), 2.8, 0.4)[0] is None
    assert yaw_gain_for_twin(YawGainFit(1.2, 1.0, 0.3, (1.2, 1.2), 2000, 40.0), 2.8, 0.4)[0] is None
    assert yaw_gain_for_twin(None, 2.8, 0.4)[0] is None


@pytest.mark.parametrize("name, lo, hi, replaced", [
    ("real_x500v2_mission_rtl.ulg", 2.7, 3.0, False),        # stock v1.13.3, MC_YAW_P 2.8
    ("real_cubeorange_takeoff_land.ulg", 2.7, 2.9, False),   # stock v1.15-dev, MC_YAW_P 2.8
    ("real_quadx_v6c_mission_noload.ulg", 6.0, 7.0, False),  # stock v1.14-beta, MC_YAW_P 6.5
    ("real_s500_rcac_mission1.ulg", 1.1, 1.3, True),         # RCAC fork: MC_YAW_P x MC_YAW_WEIGHT = 1.12
])
def test_applied_yaw_gain_on_shared_real_logs(name, lo, hi, replaced):
    log = read_ulog(shared_log("real", name))
    fit = applied_yaw_gain(log)
    assert fit is not None and lo < fit.k_yaw < hi and fit.r2 > 0.9
    assert 0.85 < fit.c_ff < 1.2                              # the feed-forward passes through at ~1
    k, _ = yaw_gain_for_twin(fit, log.params["MC_YAW_P"], log.params["MC_YAW_WEIGHT"])
    assert (k is not None) == replaced


def test_yaw_setpoint_from_the_attitude_setpoint():
    """S500 mission1 logs trajectory_setpoint at 5 Hz and vehicle_attitude_setpoint at 20 Hz: the yaw
    setpoint and its feed-forward come from the latter (the yaw ramps' ends to 0.05 s, not 0.2 s), and
    in hover they equal the trajectory's."""
    from pyulog import ULog

    from twin_nodes.base import frames as F

    path = shared_log("real", "real_s500_rcac_mission1.ulg")
    log = read_ulog(path)
    ys, yff = log.require("setpoint_yaw_enu"), log.require("setpoint_yawspeed")
    assert ys.source.startswith("vehicle_attitude_setpoint") and yff.source.startswith("vehicle_attitude_setpoint")
    rate = (len(ys) - 1) / (ys.t_s[-1] - ys.t_s[0])
    assert 18.0 < rate < 22.0
    u = ULog(str(path), ["trajectory_setpoint"])
    ts = u.data_list[0].data
    t = (ts["timestamp"] - u.start_timestamp) * 1e-6
    still = (np.abs(ts["yawspeed"]) < 1e-3) & np.isfinite(ts["yaw"]) & (t > ys.t_s[0])
    d = F.wrap_pi(ys.at(t[still] + 0.06, kind="previous")[:, 0] - F.yaw_ned_to_enu(ts["yaw"][still]))
    assert np.isfinite(d).mean() > 0.95 and np.nanmedian(np.abs(d)) < np.radians(0.5)
    # the twin built from this log flies the yaw gain its firmware applied (1.2), not MC_YAW_P (2.8)
    from twin_nodes.identify.nominal import nominal_from_log

    nom = nominal_from_log(log)
    assert 1.1 < nom.params.controller["yaw_p_1_s"] < 1.3
    assert "MC_YAW_P x MC_YAW_WEIGHT" in nom.sources["controller.yaw_p_1_s"]


def test_yaw_sample_does_not_restart_the_carried_position():
    """A yaw sample arriving between two position samples (20 Hz against 5 Hz) carries the yaw from its
    own time and leaves the position carried from the position sample's."""
    from twin_nodes.twin.control import setpoint
    from twin_nodes.twin.runner import TwinRunner

    r = TwinRunner(shipped("px4_sih_quadx"))
    r.real_state(0.0, [0.0, 0.0, 10.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    r.armed(True)
    r.advance_to(0.1)
    r.setpoint(setpoint(position_enu=(0.0, 0.0, 10.0), velocity_enu=(2.0, 0.0, 0.0), yaw_enu=0.0, yawspeed=0.5))
    t_pos = r.t
    r.advance_to(0.2)
    r.setpoint(setpoint(position_enu=(0.0, 0.0, 10.0), velocity_enu=(2.0, 0.0, 0.0), yaw_enu=0.3, yawspeed=0.5))
    t_yaw = r.t
    r.advance_to(0.26)
    sp = r._carried_setpoint()
    assert sp[0] == pytest.approx(2.0 * (r.t - t_pos), abs=1e-9)
    assert sp[9] == pytest.approx(0.3 + 0.5 * (r.t - t_yaw), abs=1e-9)


def test_replay_sends_the_20_hz_yaw_with_the_held_position():
    """The graph's /real/setpoint carries the attitude setpoint's yaw samples too; between position
    samples the position parts repeat the last one bit for bit (the twin keeps carrying it)."""
    from twin_nodes.logs.streams import replay_streams

    log = read_ulog(shared_log("real", "real_s500_rcac_mission1.ulg"))
    streams = {s.topic: s for s in replay_streams(log)[0]}
    sp, pose = streams["/real/setpoint"], streams["/real/setpoint_pose"]
    pos = log.require("setpoint_position_enu")
    assert len(sp) > 3 * len(pos)                        # 5 Hz position + 20 Hz yaw
    assert len(pose) <= len(pos)                         # the pose stays at the position samples
    v = sp.data["sp"]
    fresh = np.isin(sp.t_s, pos.t_s)
    held = np.flatnonzero(~fresh[1:] & np.isfinite(v[1:, 0])) + 1
    assert held.size > 100
    assert all(np.array_equal(v[i, 0:9], v[i - 1, 0:9], equal_nan=True) for i in held)


@pytest.mark.parametrize("with_yaw_body", [True, False])
def test_yaw_setpoint_from_yaw_body_or_q_d(tmp_path, with_yaw_body):
    """PX4 up to 1.14 logs ``yaw_body``; later versions only ``q_d``: the yaw comes from either, where
    the trajectory's yaw is finite, and the trajectory's own 25 Hz samples are used when the attitude
    setpoint is not logged faster."""
    from test_ulog_write import INFO, PARAMS, T0_US, _times, synthetic_flight

    from twin_nodes.base import frames as F
    from twin_nodes.logs.ulog_write import write_px4_ulog

    data = synthetic_flight()
    ts = data["trajectory_setpoint"]
    s = (ts["timestamp"] - T0_US) * 1e-6
    ts["yaw"] = np.where(s < 5.0, np.nan, F.wrap_pi(0.5 + 0.8 * s))
    ts["yawspeed"] = np.full(s.size, 0.8)
    ta = _times(100)
    sa = (ta - T0_US) * 1e-6
    yaw_ned = F.wrap_pi(0.5 + 0.8 * sa)
    q = F.quat_from_euler(np.zeros(sa.size), np.zeros(sa.size), yaw_ned)
    att = {"timestamp": ta, "yaw_sp_move_rate": np.full(sa.size, 0.8)}
    att.update({f"q_d[{i}]": q[:, i] for i in range(4)})
    if with_yaw_body:
        att["yaw_body"] = yaw_ned
    data["vehicle_attitude_setpoint"] = att
    p = tmp_path / "att.ulg"
    write_px4_ulog(p, data, params=PARAMS, info=INFO)
    fl = read_ulog(p)
    ys, yff = fl.require("setpoint_yaw_enu"), fl.require("setpoint_yawspeed")
    assert ("yaw_body" if with_yaw_body else "q_d") in ys.source
    assert len(ys) > 3 * len(fl.require("setpoint_position_enu"))
    late = ys.t_s > 5.1
    assert np.all(np.isnan(ys.values[ys.t_s < 4.9, 0]))                # the trajectory's yaw is NaN there
    expect = F.yaw_ned_to_enu(F.wrap_pi(0.5 + 0.8 * ys.t_s[late]))
    assert np.max(np.abs(F.wrap_pi(ys.values[late, 0] - expect))) < 1e-5
    assert yff.values[late, 0] == pytest.approx(-0.8)

    data["vehicle_attitude_setpoint"] = {k: v[::8] for k, v in att.items()}  # 12.5 Hz: slower than 25 Hz
    write_px4_ulog(p, data, params=PARAMS, info=INFO)
    assert read_ulog(p).require("setpoint_yaw_enu").source.startswith("trajectory_setpoint")
