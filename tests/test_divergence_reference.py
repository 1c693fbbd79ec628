"""A twin judged against a reference the vehicle did not fly is no divergence of the twin (issue 24.5).

Known truths on logs written with the project's own writer (``ulog_cases``):

- A reset of the height estimate (PX4 logs a step of its height that its own vertical speed does not
  explain: toopazo_x8_log83, +49 m at 19.5 s with the motors at hover) moves the estimate's frame, not the
  vehicle: :func:`height_without_resets` gives back the height before the step to the last digit, the
  pilot stand-in flies the same twin as on the log without the step, and no height run-away is found;
  with the step taken as the vehicle's, the stand-in chases it and the twin runs away.
- A twin on the ground shortly before the vehicle comes down itself (a hand-flown pass near the ground,
  a vehicle falling at its minimum thrust) has had no crash the vehicle did not have; one on the ground
  more than :data:`CRASH_NEAR_S` before the vehicle comes down has.
"""

from __future__ import annotations

import numpy as np
import pytest

import ulog_cases as C
from test_modes import PARAMS, _attitude_setpoint, _status, _twin_equal_to_real
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.twin import divergence
from twin_nodes.twin.estimate_check import RESET_M, height_without_resets
from twin_nodes.twin.flight_mode import controlled_axes
from twin_nodes.twin.runner import run_twin_on_log
from twin_nodes.vehicle.params import load_params

#: the reset: the estimated height steps up by this at T_RESET_S (NED z down by it), its velocity unchanged
RESET_STEP_M = 40.0
T_RESET_S = 15.0


def _stab_hover(tmp_path, name: str, step_m: float = 0.0):
    """STABILIZED, level, the logged collective at the SIH quad's hover throttle; the vehicle climbs to 3 m
    at 2-5 s, holds, lands at 30-33 s (``small_topics``, 35 s); from T_RESET_S its estimated height is
    ``step_m`` higher."""
    hov = load_params(PARAMS).hover_command

    def edit(topics):
        _status(15)(topics)
        _attitude_setpoint(topics, thrust=hov)
        topics["vehicle_attitude_setpoint"]["thrust_body"][:, 2] = -hov
        topics["vehicle_thrust_setpoint"]["xyz"][:, 2] = -hov
        lp = topics["vehicle_local_position"]
        s = (lp["timestamp"].astype(np.int64) - int(lp["timestamp"][0])) * 1e-6 + 0.0
        lp["z"] = lp["z"] - step_m * (s >= T_RESET_S)
    return read_ulog(C.edited_flight(tmp_path / f"{name}.ulg", edit, dur_s=35.0))


@pytest.fixture(scope="module")
def hover_pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("reset")
    return _stab_hover(d, "plain"), _stab_hover(d, "reset", RESET_STEP_M)


def _detect(run, log):
    return divergence.detect(run, log, xy_controlled=lambda tt: controlled_axes(log, tt)[0],
                             z_controlled=lambda tt: controlled_axes(log, tt)[1])


def test_a_reset_of_the_height_estimate_is_taken_out(hover_pair):
    plain, reset = hover_pair
    assert RESET_STEP_M > 10 * RESET_M
    t = np.arange(1.0, 34.0, 0.01)
    t = t[np.abs(t - T_RESET_S) > 0.05]  # the one sample interval across the step is interpolated
    z_plain = plain.get("position_enu").at(t)[:, 2]
    z_reset = reset.get("position_enu").at(t)[:, 2]
    assert np.abs((z_reset - z_plain)[t > T_RESET_S + 0.05] - RESET_STEP_M).max() < 1e-5  # the log has the step (float32)
    assert np.abs(height_without_resets(reset, t)[0] - z_plain).max() < 1e-5
    # a log without a step: its own height
    assert np.array_equal(height_without_resets(plain, t)[0], z_plain)


def test_the_pilot_stand_in_does_not_chase_a_reset(hover_pair, monkeypatch):
    plain, reset = hover_pair
    vp = load_params(PARAMS)
    run_p = run_twin_on_log(plain, vp, mode="closed")
    run_r = run_twin_on_log(reset, vp, mode="closed")
    assert run_r.info["flown_as_s"].get("attitude", 0) > 25.0
    n = min(len(run_p.t), len(run_r.t))
    fly = (run_p.t[:n] > 3.0) & (run_p.t[:n] < 29.0)  # in the air (on the ground the twin rests at the real state)
    assert np.abs(run_r.x[:n, 2] - run_p.x[:n, 2])[fly].max() < 0.05  # the same twin
    assert _detect(run_p, plain) is None and _detect(run_r, reset) is None
    # the step taken for the vehicle's (as before): the stand-in chases it, the twin climbs away
    import twin_nodes.twin.divergence as dv
    import twin_nodes.twin.runner as rn

    def raw(log, t):
        return log.get("position_enu").at(np.asarray(t, float))[:, 2], np.ones(np.shape(t), bool)
    monkeypatch.setattr(rn, "height_reset_shift", lambda log, t: np.zeros(np.shape(t)))
    monkeypatch.setattr(dv, "height_without_resets", raw)
    chased = run_twin_on_log(reset, vp, mode="closed")
    k = np.searchsorted(chased.t, T_RESET_S + 10.0)
    assert chased.x[k, 2] - run_p.x[k, 2] > 5.0
    d = _detect(chased, reset)
    assert d is not None and d["cause"] == "height run-away" and d["t_s"] > T_RESET_S, d


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """``small_flight``: 3 m from 5 to 15 s, down at 15-18 s (within 0.5 m of the ground from 17.5 s)."""
    return read_ulog(C.small_flight(tmp_path_factory.mktemp("crash") / "f.ulg"))


@pytest.mark.parametrize("t_force, crash", [(13.0, True), (14.8, False)])
def test_a_twin_down_shortly_before_the_vehicle_is_no_crash(flight, t_force, crash):
    """The twin put on its ground from ``t_force``: 4.5 s before the vehicle is within 0.5 m of its ground
    (17.5 s) it crashed, 2.7 s before it did not (CRASH_NEAR_S 3 s)."""
    assert divergence.CRASH_NEAR_S == 3.0 and divergence.VEHICLE_DOWN_M == 0.5
    run = _twin_equal_to_real(flight)
    k = run.t >= t_force
    run.x[k, 2] = run.info["ground_z"]
    d = divergence.detect(run, flight)
    if crash:
        assert d is not None and d["cause"] == "crash" and abs(d["t_s"] - t_force) < 0.05, d
    else:
        assert d is None, d


#: the synthetic vehicle stands on its take-off spot until this [s] (land detector: airborne from arming, 1 s)
T_LIFT_S = 8.0


def _held_on_ground(tmp_path):
    """STABILIZED at 1.2x the SIH quad's hover throttle from arming, level; the real vehicle stays on its
    take-off spot until T_LIFT_S (held: a hand, a tether), then climbs 3 m at 1 m/s, holds, lands at 15-18 s."""
    hov = load_params(PARAMS).hover_command

    def edit(topics):
        _status(15)(topics)
        _attitude_setpoint(topics, thrust=1.2 * hov)
        topics["vehicle_attitude_setpoint"]["thrust_body"][:, 2] = -1.2 * hov
        topics["vehicle_thrust_setpoint"]["xyz"][:, 2] = -1.2 * hov
        lp = topics["vehicle_local_position"]
        s = (lp["timestamp"].astype(np.int64) - int(lp["timestamp"][0])) * 1e-6
        h = np.clip(np.minimum(s - T_LIFT_S, 18.0 - s), 0.0, 3.0)
        lp["z"] = (-h).astype(lp["z"].dtype)
        lp["vz"] = (-np.gradient(h, s)).astype(lp["vz"].dtype)
    return read_ulog(C.edited_flight(tmp_path / "held.ulg", edit))


def test_the_twin_is_held_where_the_vehicle_is_held(tmp_path, monkeypatch):
    """Without the pilot stand-in the twin flies the logged 1.2x hover thrust: free, it climbs at
    0.2 g (less the SIH quad's 1 /s of drag: ~2 m/s) from arming while the vehicle stands; held, it stays
    on the spot until the vehicle leaves it, then flies."""
    import twin_nodes.twin.ground as gr
    log = _held_on_ground(tmp_path)
    vp = load_params(PARAMS)
    run = run_twin_on_log(log, vp, mode="closed", pilot=False)
    k = np.searchsorted(run.t, T_LIFT_S - 0.5)
    g0 = run.info["ground_z"]
    assert abs(run.x[k, 2] - g0) < 0.01 and abs(run.x[k, 5]) < 0.01
    k2 = np.searchsorted(run.t, T_LIFT_S + 2.0)
    assert run.x[k2, 2] - g0 > 1.0  # flies once the vehicle has left the ground
    monkeypatch.setattr(gr, "HELD_M", -np.inf)  # never held (as before)
    free = run_twin_on_log(log, vp, mode="closed", pilot=False)
    kf = np.searchsorted(free.t, T_LIFT_S - 0.5)
    # the closed form: 0.2 g of excess thrust against a linear drag of 1 /s: a terminal climb of 1.96 m/s
    assert abs(free.x[kf, 5] - 0.2 * 9.80665 / 1.0) < 0.05, free.x[kf, 5]
    assert free.x[kf, 2] - g0 > 10.0


def test_the_fleet_vehicle_held_on_its_spot_is_flown_held(tmp_path, monkeypatch):
    """ZweiterFlugtag log_20 (the overloaded Quad X fleet, ../shared): from 5 to 16 s its land detector says
    airborne and PX4's collective is >= 0.6 for more than 5 s (1.0 from 9 to 11.5 s), yet its height stays
    within 0.15 m of its take-off spot.  The twin built from the log stays within 0.1 m of the vehicle there;
    free (before), it climbed away more than 3 m by 12 s."""
    from conftest import shared_log
    import twin_nodes.twin.ground as gr
    from twin_nodes.identify.nominal import params_for_log
    from twin_nodes.logs.flyable import read_flight

    monkeypatch.setenv("ROTORTWIN_CACHE", str(tmp_path))
    path = shared_log("fleet_quadx_v6c/ZweiterFlugtag", "log_20_2023-6-7-10-52-56.ulg")
    log = read_flight(path, horizontal=False)
    vp = load_params(params_for_log(path, None, log=log)[0])
    (a, b), = log.airborne_intervals()
    assert a < 5.0 and b > 50.0
    run = run_twin_on_log(log, vp, mode="closed")
    z = log.get("position_enu").at(run.t)[:, 2]
    held = (run.t > 5.0) & (run.t < 16.0)
    thr = log.get("throttle").at(run.t)[held, 0]
    assert np.ptp(z[held]) < 0.15 and (thr >= 0.6).sum() * float(np.diff(run.t).mean()) > 5.0
    assert np.abs(run.x[held, 2] - z[held]).max() < 0.1
    monkeypatch.setattr(gr, "HELD_M", -np.inf)
    free = run_twin_on_log(log, vp, mode="closed")
    k = np.searchsorted(free.t, 12.0)
    assert free.x[k, 2] - log.get("position_enu").at(free.t[k:k + 1])[0, 2] > 3.0
