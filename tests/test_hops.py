"""Two hops in one log: take-off, touchdown, a second take-off (issue 24: a touch-and-go, a payload
picked up or set down).  PX4 commands zero thrust before its take-off ramp and with ground contact
(``mc_pos_control``: ``not_taken_off || flying_but_ground_contact``: no thrust, integrators reset); while
it does, the vehicle stands on the ground (or in a hand) wherever its EKF says it is.

Known truth, a log written with the project's own writer: hop 1 climbs 2 m and lands; on the ground, at
zero thrust for 6 s, the EKF's height (and PX4's setpoint, which follows it while landed) drifts 0.4 m
down, as a barometer does; hop 2 climbs 2 m from there.  The twin must fly both hops: before, it sat on
its first ground plane with the setpoint below it, wound its height integrators down and lagged hop 2.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import ulog_cases as C
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.twin import divergence
from twin_nodes.twin.runner import run_twin_on_log
from twin_nodes.vehicle.params import load_params

ROOT = Path(__file__).resolve().parents[1]
PARAMS = ROOT / "params" / "px4_sih_quadx.yaml"
DUR_S = 30.0
DRIFT_M = 0.4
RAMP_S = 1.0  # PX4's take-off ramp (MPC_TKO_RAMP_T) in this log


def _height(s: np.ndarray) -> np.ndarray:
    """Real height (ENU up, EKF frame) and whether PX4 commands thrust there."""
    h = np.interp(s, [0, 2, 4, 8, 10, 16, 18, 26, 28, 30],
                  [0, 0, 2, 2, 0, -DRIFT_M, 2 - DRIFT_M, 2 - DRIFT_M, -DRIFT_M, -DRIFT_M])
    return h


def _flying(s: np.ndarray) -> np.ndarray:
    return ((s > 2.0) & (s < 10.0)) | ((s > 16.0) & (s < 28.0))


def _two_hops(topics, hover: float) -> None:
    lp = topics["vehicle_local_position"]
    s = C._seconds(lp)
    h = _height(s)
    lp["x"], lp["vx"] = np.zeros(s.size), np.zeros(s.size)
    lp["z"], lp["vz"] = -h, -np.gradient(h, s)
    air = _flying(s)
    u = topics["actuator_motors"]["control"]
    u[:, :4] = np.where(air, hover, 0.0)[:, None]
    topics["vehicle_thrust_setpoint"]["xyz"][:, 2] = -np.where(air, hover, 0.0)
    tp = topics["trajectory_setpoint"]
    st = C._seconds(tp)
    tp["position"][:, 2] = -_height(st)
    topics["vehicle_land_detected"] = {
        "timestamp": (C.T0_US + np.array([0.0, 2.5, 10.5, 16.5, 28.5]) * 1e6).astype(np.uint64),
        "landed": np.array([True, False, True, False, True])}


def _fly(tmp_path):
    vp = load_params(PARAMS)
    p = C.edited_flight(tmp_path / "hops.ulg", lambda t: _two_hops(t, vp.hover_command), dur_s=DUR_S,
                        params={"MPC_TKO_RAMP_T": RAMP_S})
    log = read_ulog(p)
    return log, run_twin_on_log(log, vp, mode="closed")


def _z(run, t: float) -> float:
    return float(np.interp(t, run.t, run.x[:, 2]))


def test_the_twin_flies_both_hops_from_where_the_vehicle_stands(tmp_path):
    log, run = _fly(tmp_path)
    real = log.get("position_enu")
    # on the ground at zero thrust the twin is where the real vehicle is (the EKF's drifted height)
    for t in (12.0, 15.5):
        assert abs(_z(run, t) - real.at(np.array([t]))[0, 2]) < 0.02, t
    assert abs(run.info["ground_z_t"][-1] - (run.info["ground_z"] - DRIFT_M)) < 0.02
    # both hops: the twin holds each hop's height (2 m, then 1.6 m in the EKF frame)
    assert abs(_z(run, 7.5) - 2.0) < 0.15, _z(run, 7.5)
    for t in (20.0, 23.0, 25.5):
        assert abs(_z(run, t) - (2.0 - DRIFT_M)) < 0.15, (t, _z(run, t))
    assert divergence.detect(run, log) is None
    assert run.info["flown_as_s"].get("grounded", 0.0) > 6.0
    # PX4's take-off ramp: the upward velocity limit starts where the velocity loop asks for no thrust, so
    # the twin's collective rises from zero over the ramp rather than jumping to a climb
    thr = np.interp([16.0 + 0.02, 16.0 + 0.1 * RAMP_S], run.t, run.throttle)
    assert thr[0] < 0.15 and thr[0] < thr[1], thr  # MPC_THR_MIN (0.12), rising  # 10-16 s and the 0.5 s between arming and hop 1


def _below_takeoff(topics, hover: float) -> None:
    """One flight that takes off, climbs 2 m and descends to 3 m below its take-off spot (a hillside,
    a baro drifting down), flying throughout after take-off."""
    lp = topics["vehicle_local_position"]
    s = C._seconds(lp)
    h = np.interp(s, [0, 2, 6, 10, 20, 30], [0, 0, 2, 2, -3, -3])
    lp["x"], lp["vx"] = np.zeros(s.size), np.zeros(s.size)
    lp["z"], lp["vz"] = -h, -np.gradient(h, s)
    air = s > 2.0
    topics["actuator_motors"]["control"][:, :4] = np.where(air, hover, 0.0)[:, None]
    topics["vehicle_thrust_setpoint"]["xyz"][:, 2] = -np.where(air, hover, 0.0)
    tp = topics["trajectory_setpoint"]
    tp["position"][:, 2] = -np.interp(C._seconds(tp), [0, 2, 6, 10, 20, 30], [0, 0, 2, 2, -3, -3])
    topics["vehicle_land_detected"] = {
        "timestamp": (C.T0_US + np.array([0.0, 2.5]) * 1e6).astype(np.uint64), "landed": np.array([True, False])}


def test_the_twin_follows_a_vehicle_below_its_take_off_height(tmp_path):
    """The ground plane is below wherever the real vehicle flies: before, the twin sat on the take-off
    height while the vehicle flew on down (a corpus flight: Z 3.1 m, throttle 27 % on its held-out part)."""
    vp = load_params(PARAMS)
    p = C.edited_flight(tmp_path / "below.ulg", lambda t: _below_takeoff(t, vp.hover_command), dur_s=DUR_S,
                        params={"MPC_TKO_RAMP_T": RAMP_S})
    log = read_ulog(p)
    run = run_twin_on_log(log, vp, mode="closed")
    real = log.get("position_enu")
    for t in (24.0, 28.0):  # 3 m below the take-off spot, held
        assert abs(_z(run, t) - real.at(np.array([t]))[0, 2]) < 0.3, (t, _z(run, t))
    assert run.info["ground_z_t"][-1] < run.info["ground_z_t"][0] - 2.9
