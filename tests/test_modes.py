"""Every flight mode flown as PX4 flies it, and a twin that leaves the flight is said so (issue 24.3, 24.5).

Known truths on logs written with the project's own writer (``ulog_cases.edited_flight``): the real
vehicle in them hovers level; what PX4 logged as its setpoint is a step.  A twin that flies PX4's setpoint
follows the step; one that flew the real attitude (before) stays level.

- STABILIZED: ``vehicle_attitude_setpoint.q_d`` steps to 10 deg of roll: the twin rolls 10 deg.
- ACRO: ``vehicle_rates_setpoint`` 0.5 rad/s of roll for 0.5 s: the twin rolls the integral, 14.3 deg.
- ALTCTL: no horizontal setpoint (NaN), 5 deg of pitch in ``q_d``, the height held by the z setpoint:
  the twin accelerates at g tan(5 deg) = 0.86 m/s^2 and holds its height (PX4's PositionControl adds no
  velocity control on an axis whose position and velocity setpoints are NaN).
- XY and Z are scored only where PX4 controlled them.
- A twin forced off the flight (tilted, on the ground, motors rail to rail, run away) is detected at
  the time it was forced, with that cause; a twin that follows is not.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import ulog_cases as C
from twin_nodes.base import frames as F
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.twin import divergence
from twin_nodes.twin.compare import align
from twin_nodes.twin.metrics import flight_metrics
from twin_nodes.twin.flight_mode import controlled_axes
from twin_nodes.twin.runner import TwinRun, run_twin_on_log
from twin_nodes.vehicle.params import load_params

ROOT = Path(__file__).resolve().parents[1]
PARAMS = ROOT / "params" / "px4_sih_quadx.yaml"
STEP_S = 10.0


def _status(nav: int):
    def edit(topics):
        vs = topics["vehicle_status"]
        vs["nav_state"] = np.full(vs["nav_state"].shape, nav)
    return edit


def _thrust_profile(s: np.ndarray, hover: float) -> np.ndarray:
    """8 % above the hover thrust from 2 s on: the twin lifts off and climbs slowly (clear of the ground,
    which would hold its attitude)."""
    return hover * (1.0 + 0.08 * (s >= 2.0))


def _hover_thrust(topics, vp) -> None:
    t = topics["vehicle_thrust_setpoint"]
    t["xyz"][:, 2] = -_thrust_profile(C._seconds(t), vp.hover_command)


def _attitude_setpoint(topics, roll_deg: float = 0.0, pitch_deg: float = 0.0, thrust: float = 0.5) -> None:
    t = topics["vehicle_attitude"]["timestamp"]
    s = C._seconds(topics["vehicle_attitude"])
    after = s >= STEP_S
    q = F.quat_from_euler(np.where(after, np.radians(roll_deg), 0.0), np.where(after, np.radians(pitch_deg), 0.0),
                          np.zeros(s.size))  # FRD->NED, heading north
    thrust_body = np.column_stack([np.zeros(s.size), np.zeros(s.size), -_thrust_profile(s, thrust)])
    topics["vehicle_attitude_setpoint"] = {"timestamp": t, "q_d": q.astype(np.float32),
                                           "thrust_body": thrust_body.astype(np.float32),
                                           "yaw_sp_move_rate": np.zeros(s.size, np.float32)}


def _euler_enu(run: TwinRun, t: float) -> np.ndarray:
    k = int(np.searchsorted(run.t, t))
    return np.degrees(F.euler_from_quat(run.x[k:k + 1, 6:10])[0])


def _fly(tmp_path, name, edit):
    vp = load_params(PARAMS)

    def full(topics):
        _hover_thrust(topics, vp)
        edit(topics, vp)
    p = C.edited_flight(tmp_path / f"{name}.ulg", full)
    log = read_ulog(p)
    return log, run_twin_on_log(log, vp, mode="closed")


def test_stabilized_flies_the_attitude_setpoint(tmp_path):
    def edit(topics, vp):
        _status(15)(topics)
        _attitude_setpoint(topics, roll_deg=10.0, thrust=vp.hover_command)
    log, run = _fly(tmp_path, "stab", edit)
    assert run.info["flown_as_s"].get("attitude", 0) > 15.0
    assert abs(_euler_enu(run, STEP_S - 0.5)[0]) < 0.5          # level before the step
    # PX4's roll right 10 deg (FRD->NED) is the same roll in FLU->ENU (right side down, left side up)
    after = _euler_enu(run, STEP_S + 1.5)[0]
    assert abs(after - 10.0) < 1.0, after
    # the real vehicle stayed level: a twin flying the real attitude would be at 0
    real = np.degrees(F.euler_from_quat(log.get("attitude_q").at(np.array([STEP_S + 1.5])))[0])
    assert abs(real[0]) < 1.0


def test_acro_flies_the_rate_setpoint(tmp_path):
    def edit(topics, vp):
        _status(10)(topics)
        t = topics["vehicle_attitude"]["timestamp"]
        s = C._seconds(topics["vehicle_attitude"])
        rate = np.where((s >= STEP_S) & (s < STEP_S + 0.5), 0.5, 0.0)
        topics["vehicle_rates_setpoint"] = {"timestamp": t, "roll": rate.astype(np.float32),
                                            "pitch": np.zeros(s.size, np.float32),
                                            "yaw": np.zeros(s.size, np.float32)}
    _, run = _fly(tmp_path, "acro", edit)
    assert run.info["flown_as_s"].get("rates", 0) > 15.0
    assert abs(_euler_enu(run, STEP_S - 0.5)[0]) < 0.5
    # 0.5 rad/s for 0.5 s = 14.3 deg of roll right; the rate loop's lag and integrator leave a degree
    after = _euler_enu(run, STEP_S + 1.5)[0]
    assert abs(after - 14.3) < 1.5, after


def test_altctl_flies_the_tilt_and_holds_the_height(tmp_path):
    def edit(topics, vp):
        _status(1)(topics)
        _attitude_setpoint(topics, pitch_deg=-5.0, thrust=vp.hover_command)  # FRD pitch down = nose down
        ts = topics["trajectory_setpoint"]
        ts["position"][:, 0:2] = np.nan
        ts["velocity"] = np.full(ts["position"].shape, np.nan)
    log, run = _fly(tmp_path, "altctl", edit)
    assert run.info["flown_as_s"].get("cascade", 0) > 15.0
    k0, k1 = np.searchsorted(run.t, [STEP_S - 0.5, STEP_S + 3.0])
    # accelerates north (ENU y) at g tan(5 deg) against the SIH quad's drag (k/m = 1/s): 0.858 m/s at
    # the end, 0.80 m/s after 3 s less the attitude loop's lag; the old twin held the velocity at 0
    assert abs(run.x[k0, 4]) < 0.1
    assert 0.65 < run.x[k1, 4] < 0.86, run.x[k1, 4]
    # the height: the altitude loop holds the logged z setpoint (3 m) while the vehicle tilts
    z_sp = 3.0
    assert abs(run.x[k1, 2] - z_sp) < 0.15, run.x[k1, 2]
    assert abs(run.x[k1, 0]) < 0.1  # no east motion: PX4's attitude setpoint points north
    xy, z, _ = controlled_axes(log, np.array([STEP_S + 2.0]))
    assert not xy[0] and z[0]


def test_axes_scored_only_where_px4_controlled_them(tmp_path):
    def edit(topics, vp):
        vs = topics["vehicle_status"]
        vs["nav_state"] = np.array([4, 15, 15])  # STABILIZED once armed: no axis controlled
        _attitude_setpoint(topics, thrust=vp.hover_command)
    log, run = _fly(tmp_path, "stab_axes", edit)
    m = flight_metrics(align(run, log))
    assert m["controlled_s"] == {"xy": 0.0, "z": 0.0}
    assert np.isnan(m["xy_rmse_m"]) and np.isnan(m["z_rmse_m"])
    assert np.isfinite(m["throttle_rmse"]) and m["controlled_axes"] == []
    # the same flight in AUTO: both axes scored for the whole airborne part but its ends
    log2, run2 = _fly(tmp_path, "auto_axes", lambda topics, vp: None)
    m2 = flight_metrics(align(run2, log2))
    assert m2["controlled_s"]["xy"] > 10.0 and m2["controlled_s"]["z"] > 10.0


# ---------------------------------------------------------------------------------------- divergence

def _twin_equal_to_real(log) -> TwinRun:
    """A 'twin' that is the real flight itself, on a 250 Hz grid (no divergence)."""
    t = np.arange(0.5, log.duration_s - 0.5, 0.004)
    x = np.zeros((t.size, 13))
    x[:, 0:3] = log.get("position_enu").at(t)
    x[:, 3:6] = log.get("velocity_enu").at(t)
    x[:, 6:10] = log.get("attitude_q").at(t)
    u = log.get("motors").at(t)
    return TwinRun(t=t, x=x, motors=u, throttle=u.mean(axis=1), specific_force=np.zeros((t.size, 3)),
                   mode="closed", info={"ground_z": float(log.get("position_enu").at(np.array([0.6]))[0, 2])})


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    return read_ulog(C.small_flight(tmp_path_factory.mktemp("div") / "f.ulg"))


def test_a_twin_that_follows_does_not_diverge(flight):
    assert divergence.detect(_twin_equal_to_real(flight), flight) is None


@pytest.mark.parametrize("cause", ["attitude", "heading", "crash", "motors oscillating", "position run-away"])
def test_a_forced_divergence_is_found_at_its_time(flight, cause):
    run = _twin_equal_to_real(flight)
    t_force = 9.0
    k = run.t >= t_force
    if cause == "attitude":
        run.x[k, 6:10] = F.quat_from_euler(np.full(k.sum(), np.radians(50.0)), np.zeros(k.sum()), np.zeros(k.sum()))
    elif cause == "heading":
        e = F.euler_from_quat(run.x[k, 6:10])
        run.x[k, 6:10] = F.quat_from_euler(e[:, 0], e[:, 1], e[:, 2] + np.radians(150.0))
    elif cause == "crash":
        run.x[k, 2] = run.info["ground_z"]
    elif cause == "motors oscillating":
        run.motors[k, 1] = np.where(np.sin(2 * np.pi * 4.0 * run.t[k]) > 0, 1.0, 0.0)
    else:
        run.x[k, 0] += 12.0 + (run.t[k] - t_force)
    d = divergence.detect(run, flight)
    assert d is not None and d["cause"] == cause, d
    assert abs(d["t_s"] - t_force) < 0.05, d
    # the metrics say so, and the table's divergence line names it
    al = align(run, flight)
    assert al.divergence == d and flight_metrics(al)["divergence"] == d


@pytest.mark.parametrize("flags, flown", [((0, 0, 0, 1, 0, 0), "attitude"), ((1, 0, 0, 0, 0, 0), "cascade")],
                         ids=["attitude", "position"])
def test_offboard_flies_what_its_flags_say(tmp_path, flags, flown):
    """OFFBOARD (nav_state 14): ``offboard_control_mode`` says what the companion computer controls.  With the
    attitude flag the twin flies the logged attitude setpoint (10 deg roll step); with the position flag the
    cascade on the trajectory setpoint (level: the position setpoint is still)."""
    names = ("position", "velocity", "acceleration", "attitude", "body_rate", "thrust_and_torque")

    def edit(topics, vp):
        _status(14)(topics)
        _attitude_setpoint(topics, roll_deg=10.0, thrust=vp.hover_command)
        t = topics["vehicle_attitude"]["timestamp"][::10]
        topics["offboard_control_mode"] = {"timestamp": t,
                                           **{n: np.full(t.size, bool(f)) for n, f in zip(names, flags)}}
    log, run = _fly(tmp_path, f"offboard_{flown}", edit)
    assert run.info["flown_as_s"].get(flown, 0) > 15.0, run.info["flown_as_s"]
    roll = _euler_enu(run, STEP_S + 1.5)[0]
    assert abs(roll - (10.0 if flown == "attitude" else 0.0)) < 1.0, roll
    xy, z, _ = controlled_axes(log, np.array([STEP_S]))
    assert bool(xy[0]) == bool(z[0]) == (flown == "cascade")


def test_altctl_without_a_trajectory_setpoint_holds_the_real_height(tmp_path):
    """A log with no trajectory_setpoint (older topic sets) in ALTCTL: the twin flies the pilot's tilt (q_d) with
    its altitude loop on the real height, not the real position (which would hold it where the vehicle is);
    only the height is scored."""
    def edit(topics, vp):
        _status(1)(topics)
        _attitude_setpoint(topics, pitch_deg=-5.0, thrust=vp.hover_command)
        del topics["trajectory_setpoint"]
    log, run = _fly(tmp_path, "altctl_old", edit)
    k0, k1 = np.searchsorted(run.t, [STEP_S - 0.5, STEP_S + 3.0])
    assert abs(run.x[k0, 4]) < 0.1 and 0.65 < run.x[k1, 4] < 0.86, run.x[[k0, k1], 4]
    z_real = log.get("position_enu").at(np.array([STEP_S + 3.0]))[0, 2]
    assert abs(run.x[k1, 2] - z_real) < 0.15
    xy, z, _ = controlled_axes(log, np.array([STEP_S]))
    assert not xy[0] and z[0]


# ---------------------------------------------------------------------------------------- pilot stand-in

@pytest.fixture(scope="module")
def hover_log(tmp_path_factory):
    """STABILIZED, level, the logged collective thrust constant at the SIH quad's hover throttle (0.4903); the
    real vehicle climbs to 3 m at 2-5 s, holds until 30 s, lands (``small_topics``)."""
    vp = load_params(PARAMS)
    hov = vp.hover_command

    def edit(topics):
        _status(15)(topics)
        _attitude_setpoint(topics, thrust=hov)
        topics["vehicle_attitude_setpoint"]["thrust_body"][:, 2] = -hov
        topics["vehicle_thrust_setpoint"]["xyz"][:, 2] = -hov
    return read_ulog(C.edited_flight(tmp_path_factory.mktemp("pilot") / "stab_hover.ulg", edit, dur_s=35.0))


def _strong(vp, factor: float):
    import dataclasses
    return dataclasses.replace(vp, rotors=dataclasses.replace(vp.rotors, thrust_max_n=vp.rotors.thrust_max_n * factor))


def test_pilot_stand_in_holds_the_height_and_shows_the_thrust_model_error(hover_log):
    """A twin whose thrust is 10 % too strong (SIH_T_MAX 5.5 N instead of 5.0, thrust linear in the command).
    Without the stand-in it flies the logged hover throttle and climbs away (0.98 m/s^2 up against 1 /s of drag:
    ~1 m/s).  With it the height follows the real one, and the twin's throttle settles where 1.1 T(thr) = m g:
    thr = 0.4903 / 1.1 = 0.4458, i.e. a throttle error of 0.4903 (1 - 1/1.1) = 0.0446 against the real logged
    one -- the model's error, where it read 0.0 by construction before."""
    vp = load_params(PARAMS)
    strong = _strong(vp, 1.1)
    expected = vp.hover_command * (1.0 - 1.0 / 1.1)
    assert abs(expected - 0.04458) < 1e-4
    bare = run_twin_on_log(hover_log, strong, mode="closed", pilot=False)
    run = run_twin_on_log(hover_log, strong, mode="closed")
    assert run.info["flown_as_s"].get("attitude", 0) > 30.0
    for r in (bare, run):
        r.z_real = hover_log.get("position_enu").at(r.t)[:, 2]
        r.thr_real = hover_log.get("throttle").at(r.t)[:, 0]
    k20 = np.searchsorted(bare.t, 20.0)
    assert bare.x[k20, 2] - bare.z_real[k20] > 10.0          # climbed away
    assert np.allclose(bare.throttle[(bare.t > 5.0) & (bare.t < 30.0)], vp.hover_command, atol=1e-6)  # 0 throttle error by construction
    err = np.abs(run.x[:, 2] - run.z_real)
    # the climb at 2-5 s, which the logged constant throttle does not explain, plus the model's 0.98 m/s^2 of bias:
    # a transient of 0.99 m at ~8 s (the loop's triple pole at 0.5 rad/s settles in ~15 s), then the real height
    assert err[(run.t > 5.0) & (run.t < 30.0)].max() < 1.1
    assert err[(run.t > 20.0) & (run.t < 30.0)].max() < 0.15
    hold = (run.t > 20.0) & (run.t < 28.0)
    rmse = float(np.sqrt(np.mean((run.throttle[hold] - run.thr_real[hold]) ** 2)))
    assert abs(rmse - expected) < 0.004, rmse
    assert abs(run.info["pilot"]["s"] - 31.5) < 0.5
    # the scored throttle (whole airborne flight) says the same, and the notes say the stand-in flew
    m = flight_metrics(align(run, hover_log))
    assert abs(m["throttle_rmse"] - expected) < 0.006, m["throttle_rmse"]
    assert any(n.startswith("manual modes: a pilot stand-in held the real height, 31.5 s; its mean correction -")
               for n in m["notes"]), m["notes"]


def test_pilot_stand_in_is_idle_with_a_correct_model(hover_log):
    """The twin's own model: in the hold the correction is ~0 (the climb, which the constant logged throttle
    does not explain, is what it corrects there); without the stand-in that same twin stays on the ground."""
    vp = load_params(PARAMS)
    run = run_twin_on_log(hover_log, vp, mode="closed")
    thr_real = hover_log.get("throttle").at(run.t)[:, 0]
    hold = (run.t > 20.0) & (run.t < 28.0)
    assert np.abs(run.throttle[hold] - thr_real[hold]).max() < 0.003
    assert abs(run.info["pilot"]["mean_correction_of_hover"]) < 0.01
    z_real = hover_log.get("position_enu").at(run.t)[:, 2]
    assert np.abs(run.x[hold, 2] - z_real[hold]).max() < 0.15
    bare = run_twin_on_log(hover_log, vp, mode="closed", pilot=False)
    assert bare.x[np.searchsorted(bare.t, 20.0), 2] < 0.05  # never left the ground: the crash divergence


def test_a_twin_that_climbs_away_in_a_manual_mode_is_a_divergence(hover_log):
    """Z is not PX4's in STABILIZED, so the position run-away check does not look at it; the pilot held it.
    The 10 %-too-strong twin without the stand-in climbs > 10 m away: a height run-away (limit 5 m for 2 s,
    reached at ~13 s: ~1 m/s from 5 s, after the climb it does not follow); with the stand-in, none."""
    strong = _strong(load_params(PARAMS), 1.1)

    def detect(run):
        return divergence.detect(run, hover_log, xy_controlled=lambda tt: controlled_axes(hover_log, tt)[0],
                                 z_controlled=lambda tt: controlled_axes(hover_log, tt)[1])
    d = detect(run_twin_on_log(hover_log, strong, mode="closed", pilot=False))
    assert d is not None and d["cause"] == "height run-away" and 8.0 < d["t_s"] < 20.0, d
    assert detect(run_twin_on_log(hover_log, strong, mode="closed")) is None


def _spun(log, t_force: float, rate_rad_s: float, t_stop: float = np.inf, setpoint: bool = True):
    """``log`` with its vehicle turning at ``rate_rad_s`` about the vertical from ``t_force`` to ``t_stop``
    (yaw authority gone, then back) and PX4's attitude setpoint the attitude it flew before, taken again at
    the heading it stopped at (PX4 locks the heading it finds); none: ``setpoint`` False."""
    import dataclasses

    from twin_nodes.logs.ulog_io import Series

    att = log.get("attitude_q")
    t = np.asarray(att.t_s, float)
    e = F.euler_from_quat(np.asarray(att.values, float))
    turned = rate_rad_s * np.clip(np.minimum(t, t_stop) - t_force, 0.0, None)
    series = dict(log.series)
    if setpoint:
        relocked = np.where(t >= t_stop, turned, 0.0)
        series["attitude_setpoint_q"] = Series(t, F.quat_from_euler(e[:, 0], e[:, 1], e[:, 2] + relocked), "-",
                                               att.frame, att.source, "previous")
    series["attitude_q"] = Series(t, F.quat_from_euler(e[:, 0], e[:, 1], e[:, 2] + turned), att.units, att.frame,
                                  att.source, att.interp)
    return dataclasses.replace(log, series=series)


def _twin_spun(log, t_force: float, rate_rad_s: float) -> TwinRun:
    run = _twin_equal_to_real(log)
    k = run.t >= t_force
    e = F.euler_from_quat(run.x[k, 6:10])
    run.x[k, 6:10] = F.quat_from_euler(e[:, 0], e[:, 1], e[:, 2] + rate_rad_s * (run.t[k] - t_force))
    return run


def test_a_twin_spinning_with_a_vehicle_out_of_yaw_authority_is_no_heading_divergence(flight):
    """Issue 24.4/24.5: a vehicle whose yaw authority ran out turns away from PX4's heading setpoint (0.5
    rad/s from 8 s: 90 deg off at 8 + pi s); a twin that ran out too spins with it at its own rate (0.3
    rad/s: 90 deg off at 13.24 s, 90 deg from the vehicle at 8 + (pi/2)/0.2 = 15.85 s) and has not left
    the flight.  One that held its heading while the vehicle spun has (at 8 + pi s), and so has one that
    spun while the vehicle held; without PX4's attitude setpoint every heading gap counts, as before."""
    t0 = 8.0
    assert divergence.detect(_twin_spun(flight, t0, 0.3), _spun(flight, t0, 0.5)) is None
    for run, log, t_expected in ((_twin_equal_to_real(flight), _spun(flight, t0, 0.5), t0 + np.pi),
                                 (_twin_spun(flight, t0, 0.5), _spun(flight, t0, 0.0), t0 + np.pi),
                                 (_twin_spun(flight, t0, 0.3), _spun(flight, t0, 0.5, setpoint=False),
                                  t0 + np.pi / 2 / 0.2)):
        d = divergence.detect(run, log)
        assert d is not None and d["cause"] == "heading" and abs(d["t_s"] - t_expected) < 0.05, (d, t_expected)


def test_a_twin_still_spinning_after_the_vehicle_took_its_heading_back_has_diverged(flight):
    """The vehicle spins at +1 rad/s from 6 to 9.5 s and holds the heading it stopped at (PX4 locks it):
    back in yaw control at 11.5 s (YAW_SUSTAIN_S within YAW_HELD_DEG).  The twin spins the other way at
    0.8 rad/s from 6 s, out of control from 6 + (pi/2)/0.8 = 7.96 s: the headings more than 90 deg apart
    from 6.87 s (1.1 s before the twin lost its own: not sustained) are no divergence while both spin,
    and one from the moment the vehicle has its heading back (11.5 s), the gap then 93 deg."""
    d = divergence.detect(_twin_spun(flight, 6.0, -0.8), _spun(flight, 6.0, 1.0, t_stop=9.5))
    assert d is not None and d["cause"] == "heading" and abs(d["t_s"] - 11.5) < 0.05, d
