"""Older PX4 topic sets (PX4 1.8-1.13; twin_nodes/logs/legacy_topics.py) read into the canonical
series: round trips on logs written in each old layout by the project's own ULog writer (a known
PWM with known limits gives a known 0..1; rates from vehicle_attitude equal the truth; the 1.8
position controller's setpoints give back the feed-forward), the real pyulog PX4 logs of the old
layout, and a real PX4 1.11 flight re-expressed in PX4 1.8's layout (tests/legacy_cases.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import ulog_cases as UC
from conftest import shared_log
from legacy_cases import to_px4_18_layout
from testlogs import need_testlog
from twin_nodes.base import frames as F
from twin_nodes.cli import main
from twin_nodes.logs.legacy_topics import output_limits, pwm_limits
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.logs.ulog_write import write_px4_ulog


def _old(topics: dict, drop: tuple[str, ...] = (), **extra) -> dict:
    t = {k: dict(v) for k, v in topics.items() if k not in drop}
    t.update(extra)
    return t


def _write(tmp_path, topics: dict, params: dict, name: str = "old.ulg"):
    return read_ulog(write_px4_ulog(tmp_path / name, topics, params, {"ver_sw": "legacy"},
                                    start_us=UC.T0_US))


# --------------------------------------------------------------------------- body rates (1.8-1.9)

def test_rates_from_vehicle_attitude_equal_the_truth(tmp_path):
    base = UC.small_topics()
    t = base["vehicle_attitude"]["timestamp"]
    s = (t - UC.T0_US) * 1e-6
    w = np.column_stack([0.3 * np.sin(2 * s), -0.2 * np.cos(s), 0.5 * np.sin(0.5 * s)]).astype(np.float32)
    att = dict(base["vehicle_attitude"], rollspeed=w[:, 0], pitchspeed=w[:, 1], yawspeed=w[:, 2])
    fl = _write(tmp_path, _old(base, ("vehicle_angular_velocity",), vehicle_attitude=att),
                {"CA_ROTOR_COUNT": 4})
    r = fl.require("body_rates_flu")
    assert r.source == "vehicle_attitude.rollspeed,pitchspeed,yawspeed (FRD)"
    np.testing.assert_array_equal(r.t_s, fl.require("attitude_q").t_s)
    np.testing.assert_allclose(r.values, F.frd_to_flu(w.astype(float)), atol=1e-7)
    assert r.values[:, 1] == pytest.approx(-w[:, 1], abs=1e-7)  # FRD pitch rate -> FLU: sign flips
    # a log with both (never PX4, but the newer topic wins)
    fl2 = _write(tmp_path, _old(base, vehicle_attitude=att), {"CA_ROTOR_COUNT": 4}, "both.ulg")
    assert fl2.require("body_rates_flu").source.startswith("vehicle_angular_velocity")


# --------------------------------------------------------------------------- PWM -> 0..1 per era

#: (era, parameters, expected per-channel PWM min, max, a name that must be in the motors' source)
PWM_ERAS = [
    ("1.8 PWM_MIN/MAX", {"PWM_MIN": 1075, "PWM_MAX": 1950}, [1075] * 4, [1950] * 4, "PWM_MIN"),
    ("1.9-1.10 per channel over PWM_MIN", {
        "PWM_MIN": 1100, "PWM_MAX": 1900, **{f"PWM_MAIN_MIN{c}": -1 for c in range(1, 9)},
        **{f"PWM_MAIN_MAX{c}": -1 for c in range(1, 9)}, "PWM_MAIN_MIN2": 1150, "PWM_MAIN_MAX3": 1950},
     [1100, 1150, 1100, 1100], [1900, 1900, 1950, 1900], "PWM_MAIN_MIN2"),
    ("1.11-1.12 PWM_MAIN_MIN/MAX", {
        "PWM_MAIN_MIN": 1075, "PWM_MAIN_MAX": 1950, **{f"PWM_MAIN_MIN{c}": -1 for c in range(1, 9)},
        **{f"PWM_MAIN_MAX{c}": -1 for c in range(1, 9)}}, [1075] * 4, [1950] * 4, "PWM_MAIN_MAX"),
    ("1.13 mixer (SYS_CTRL_ALLOC 0): 1000/2000 = unset", {
        "SYS_CTRL_ALLOC": 0, "PWM_MAIN_MIN": 1075, "PWM_MAIN_MAX": 1950,
        **{f"PWM_MAIN_MIN{c}": 1000 for c in range(1, 9)}, **{f"PWM_MAIN_MAX{c}": 2000 for c in range(1, 9)},
        **{f"PWM_MAIN_FUNC{c}": 0 for c in range(1, 9)}, "PWM_MAIN_MIN4": 1120},
     [1075, 1075, 1075, 1120], [1950] * 4, "PWM_MAIN_MIN4"),
    ("no limits in the log", {}, [1000] * 4, [2000] * 4, "PX4 default"),
]


@pytest.mark.parametrize("era,params,lo,hi,named", PWM_ERAS, ids=[e[0] for e in PWM_ERAS])
def test_pwm_of_each_era_maps_back_to_the_known_command(tmp_path, era, params, lo, hi, named):
    """actuator_outputs at 10 Hz (PX4's default logger rate for it in every version), no
    actuator_motors: PWM = min + u (max - min) per channel gives u back; 900 us disarmed -> NaN."""
    base = UC.small_topics()
    t = base["vehicle_local_position"]["timestamp"][::5]  # 10 Hz
    n = t.size
    u = np.clip(0.45 + 0.3 * np.sin(np.linspace(0, 6, n))[:, None] * [1, -1, 0.5, -0.5], 0, 1)
    out = np.zeros((n, 16))
    out[:, :4] = np.array(lo) + u * (np.array(hi) - np.array(lo))
    st = base["vehicle_status"]
    armed = np.searchsorted(st["timestamp"], t, side="right") - 1
    disarmed = st["arming_state"][armed] != 2
    out[disarmed, :4] = 900.0
    topics = _old(base, ("actuator_motors",), actuator_outputs={"timestamp": t, "noutputs": np.full(n, 4),
                                                                "output": out})
    fl = _write(tmp_path, topics, {"MAV_TYPE": 2, **params})
    m = fl.require("motors")
    assert named in m.source and "actuator_outputs[0].output[0,1,2,3]" in m.source, m.source
    assert np.isnan(m.values[disarmed]).all()
    np.testing.assert_allclose(m.values[~disarmed], u[~disarmed], atol=2e-6)
    assert (np.median(np.diff(m.t_s)) == pytest.approx(0.1))
    got_lo, got_hi, _ = pwm_limits({k: float(v) for k, v in params.items()}, "MAIN", [0, 1, 2, 3])
    assert list(got_lo) == lo and list(got_hi) == hi


def test_pwm_aux_bank_and_a_corrupt_pair_are_said():
    lo, hi, how = pwm_limits({"PWM_AUX_MIN": 1100.0, "PWM_AUX_MAX": 1900.0, "PWM_MIN": 1000.0}, "AUX", [0, 1])
    assert list(lo) == [1100, 1100] and list(hi) == [1900, 1900] and "PWM_AUX_MIN" in how
    lo, hi, how = pwm_limits({"PWM_MAIN_MIN": 1500.0, "PWM_MAIN_MAX": 1400.0}, "MAIN", [0])
    assert (lo[0], hi[0]) == (1000, 2000) and "max <= min" in how


def test_uavcan_and_dshot_units_per_px4():
    """UAVCAN ESC raw commands (0..8191, PX4 1.9 ``(u + 1) / 2 x 8191``) and DShot (max(1, DSHOT_MIN x
    1999)..1999, PX4 1.10-1.12) are told from PWM by their values and the log's parameters."""
    raw = np.array([[4095.5, 6000.0], [2000.0, 8191.0]])
    lo, hi, how = output_limits({"UAVCAN_ENABLE": 3.0}, "MAIN", [0, 1], raw)
    assert list(lo) == [0, 0] and list(hi) == [8191, 8191] and "UAVCAN" in how
    assert (raw[0, 0] - lo[0]) / (hi[0] - lo[0]) == pytest.approx(0.5, abs=1e-4)
    # UAVCAN enabled but the motors on PWM (values in PWM's range): PWM limits
    lo, hi, how = output_limits({"UAVCAN_ENABLE": 3.0, "PWM_MAIN_MIN": 1075.0, "PWM_MAIN_MAX": 1950.0},
                                "MAIN", [0], np.array([[1100.0], [1700.0]]))
    assert (lo[0], hi[0]) == (1075, 1950)
    lo, hi, how = output_limits({"DSHOT_CONFIG": 600.0, "DSHOT_MIN": 0.055}, "MAIN", [0, 1, 2, 3],
                                np.array([[110.0, 400, 1200, 1999]] * 2))
    assert lo[0] == pytest.approx(109.0, abs=0.5) and hi[0] == 1999 and "DShot" in how
    lo, _, _ = output_limits({"PWM_MAIN_TIM0": -3.0}, "MAIN", [0], np.array([[50.0]]))  # 1.13: DShot600
    assert lo[0] == 1.0


def test_mixer_idle_is_found_and_undone(tmp_path):
    """A mixer file with idle 0.3 (``R: 4x ... 3000``): PX4 writes 0.3 + 0.7 x out; the reader finds the
    idle from the log (mean motor against throttle) and gives back the mixer's command; with idle 0 it
    changes nothing."""
    base = UC.small_topics(dur_s=40.0)
    t = base["vehicle_attitude"]["timestamp"]
    n = t.size
    s = (t - UC.T0_US) * 1e-6
    thr = 0.45 + 0.1 * np.sin(0.7 * s)
    cmd = np.clip(thr[:, None] + 0.03 * np.sin(3 * s)[:, None] * [1, -1, 1, -1], 0, 1)
    c = np.zeros((n, 8), np.float32)
    c[:, 3] = thr
    st = base["vehicle_status"]
    k = np.searchsorted(st["timestamp"], t, side="right") - 1
    armed = st["arming_state"][k] == 2
    for idle, name in ((0.3, "idle.ulg"), (0.0, "noidle.ulg")):
        out = np.zeros((n, 16))
        out[:, :4] = 1000 + 1000 * (idle + (1 - idle) * cmd)
        out[~armed, :4] = 900.0
        topics = _old(base, ("actuator_motors", "vehicle_thrust_setpoint"),
                      actuator_outputs={"timestamp": t, "noutputs": np.full(n, 4), "output": out},
                      actuator_controls_0={"timestamp": t, "control": c})
        fl = _write(tmp_path, topics, {"MAV_TYPE": 2, "PWM_MIN": 1000, "PWM_MAX": 2000}, name)
        m = fl.require("motors")
        np.testing.assert_allclose(m.values[armed], cmd[armed], atol=1e-5)
        assert ("mixer idle 0.300 undone" in m.source) == (idle > 0), m.source


# --------------------------------------------------------------------------- torque / throttle

def test_torque_and_throttle_from_actuator_controls_0(tmp_path):
    base = UC.small_topics()
    t = base["vehicle_attitude"]["timestamp"]
    n = t.size
    c = np.zeros((n, 8), np.float32)
    c[:, 0], c[:, 1], c[:, 2], c[:, 3] = 0.02, -0.05, 0.1, 0.55
    fl = _write(tmp_path, _old(base, ("vehicle_thrust_setpoint",),
                               actuator_controls_0={"timestamp": t, "control": c}), {"CA_ROTOR_COUNT": 4})
    tq = fl.require("torque_setpoint_flu")
    assert tq.source == "actuator_controls_0.control[0..2] (FRD)"
    np.testing.assert_allclose(tq.values, np.tile([0.02, 0.05, -0.1], (n, 1)), atol=1e-7)
    np.testing.assert_allclose(fl.require("throttle").values[:, 0], 0.55, atol=1e-7)


# --------------------------------------------------------------------------- setpoints per version

def _lpsp_18(base: dict, kxy: float, kz: float) -> tuple[dict, np.ndarray, np.ndarray]:
    """PX4 1.8's vehicle_local_position_setpoint as its mc_pos_control filled it."""
    lp = base["vehicle_local_position"]
    t = lp["timestamp"][::2]
    s = (t - UC.T0_US) * 1e-6
    n = t.size
    sp = np.column_stack([2.0 * np.sin(0.3 * s), 1.0 * s / s[-1], -3.0 * np.ones(n)])
    ff = np.column_stack([0.6 * np.cos(0.3 * s), np.full(n, 1.0 / s[-1]), np.zeros(n)])
    pos = np.column_stack([lp["x"][::2], lp["y"][::2], lp["z"][::2]])
    vel_sp = (sp - pos) * [kxy, kxy, kz] + ff
    f = {"timestamp": t, "x": sp[:, 0], "y": sp[:, 1], "z": sp[:, 2], "vx": vel_sp[:, 0],
         "vy": vel_sp[:, 1], "vz": vel_sp[:, 2], "acc_x": np.zeros(n), "acc_y": np.zeros(n),
         "acc_z": np.full(n, -6.1), "yaw": np.full(n, 0.3), "yawspeed": np.zeros(n)}
    return {k: (v if k == "timestamp" else np.asarray(v, np.float32)) for k, v in f.items()}, sp, ff


def test_px4_18_position_controller_setpoints_give_back_the_feed_forward(tmp_path):
    base = UC.small_topics()
    lpsp, sp, ff = _lpsp_18(base, 0.95, 1.0)
    topics = _old(base, ("trajectory_setpoint",), vehicle_local_position_setpoint=lpsp)
    fl = _write(tmp_path, topics, {"CA_ROTOR_COUNT": 4, "MPC_XY_P": 0.95, "MPC_Z_P": 1.0})
    np.testing.assert_allclose(fl.require("setpoint_position_enu").values, F.ned_to_enu(sp), atol=1e-5)
    v = fl.require("setpoint_velocity_enu")
    assert "MPC_XY_P" in v.source and v.source.startswith("vehicle_local_position_setpoint")
    np.testing.assert_allclose(v.values, F.ned_to_enu(ff), atol=1e-5)
    assert fl.get("setpoint_accel_enu") is None  # 1.8's acc_x.. is thrust x g, not a feed-forward
    ys = fl.require("setpoint_yaw_enu")
    assert ys.values[0, 0] == pytest.approx(np.pi / 2 - 0.3, abs=1e-6)
    assert "trajectory_setpoint" not in ys.source and "vehicle_local_position_setpoint" in ys.source
    # without the gains the feed-forward cannot be separated: the position setpoint alone
    fl2 = _write(tmp_path, topics, {"CA_ROTOR_COUNT": 4}, "nogain.ulg")
    assert fl2.get("setpoint_velocity_enu") is None and fl2.get("setpoint_position_enu") is not None


@pytest.mark.parametrize("layout", ["1.9-1.10", "1.11-1.12"])
def test_trajectory_setpoint_field_names_of_old_versions(tmp_path, layout):
    """1.9-1.12 log trajectory_setpoint as a vehicle_local_position_setpoint (x,y,z, vx,vy,vz); 1.9-1.10
    add acc_x.. that their PositionControl does not fly, 1.11+ acceleration[3] that it does.  The
    controller-output vehicle_local_position_setpoint they also log is not the setpoint."""
    base = UC.small_topics()
    tsp = base["trajectory_setpoint"]
    t, n = tsp["timestamp"], tsp["timestamp"].size
    pos = np.column_stack([np.linspace(0, 5, n), np.zeros(n), np.full(n, -3.0)])
    vel = np.column_stack([np.full(n, 0.25), np.zeros(n), np.zeros(n)])
    acc = np.column_stack([np.full(n, 0.1), np.full(n, -0.2), np.zeros(n)])
    old = {"timestamp": t, "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2], "vx": vel[:, 0], "vy": vel[:, 1],
           "vz": vel[:, 2], "yaw": np.zeros(n), "yawspeed": np.zeros(n)}
    if layout == "1.9-1.10":
        old.update(acc_x=acc[:, 0], acc_y=acc[:, 1], acc_z=acc[:, 2])
    else:
        old["acceleration"] = acc
    old = {k: (v if k == "timestamp" else np.asarray(v, np.float32)) for k, v in old.items()}
    ctrl = dict(old, x=old["x"] + 7.0)
    fl = _write(tmp_path, _old(base, ("trajectory_setpoint",), trajectory_setpoint=old,
                               vehicle_local_position_setpoint=ctrl), {"CA_ROTOR_COUNT": 4})
    p = fl.require("setpoint_position_enu")
    assert p.source == "trajectory_setpoint (NED)"
    np.testing.assert_allclose(p.values, F.ned_to_enu(pos), atol=1e-5)
    np.testing.assert_allclose(fl.require("setpoint_velocity_enu").values, F.ned_to_enu(vel), atol=1e-6)
    a = fl.get("setpoint_accel_enu")
    if layout == "1.9-1.10":
        assert a is None
    else:
        np.testing.assert_allclose(a.values, F.ned_to_enu(acc), atol=1e-6)


# --------------------------------------------------------------------------- a whole PX4 1.8 layout

def test_px4_18_layout_flies_and_names_what_is_missing(tmp_path, capsys):
    """Every 1.8 substitute at once (rates, PWM_MIN/MAX at 10 Hz, actuator_controls_0, the 1.8
    setpoint topic): compare starts and flies.  Without any body-rate field the one-line error
    names what PX4 field was expected."""
    base = UC.small_topics()
    t = base["vehicle_attitude"]["timestamp"]
    n = t.size
    att = dict(base["vehicle_attitude"], rollspeed=np.zeros(n, np.float32),
               pitchspeed=np.zeros(n, np.float32), yawspeed=np.zeros(n, np.float32))
    u = base["actuator_motors"]["control"][::5, :4]
    out = np.zeros((u.shape[0], 16))
    out[:, :4] = 1075 + u * 875
    st = base["vehicle_status"]
    k = np.searchsorted(st["timestamp"], t[::5], side="right") - 1
    out[st["arming_state"][k] != 2, :4] = 900.0  # PX4's disarmed PWM
    c = np.zeros((n, 8), np.float32)
    c[:, 3] = 0.5
    lpsp, _, _ = _lpsp_18(base, 0.95, 1.0)
    topics = _old(base, ("vehicle_angular_velocity", "actuator_motors", "vehicle_thrust_setpoint",
                         "trajectory_setpoint"), vehicle_attitude=att,
                  actuator_outputs={"timestamp": t[::5], "noutputs": np.full(out.shape[0], 4), "output": out},
                  actuator_controls_0={"timestamp": t, "control": c},
                  vehicle_local_position_setpoint=lpsp)
    params = {"MAV_TYPE": 2, "SYS_AUTOSTART": 4001, "PWM_MIN": 1075, "PWM_MAX": 1950,
              "MPC_XY_P": 0.95, "MPC_Z_P": 1.0}
    p = write_px4_ulog(tmp_path / "px418.ulg", topics, params, {"ver_sw": "legacy"}, start_us=UC.T0_US)
    assert main(["compare", "--offline", str(p), "--json", str(tmp_path / "m.json")]) == 0
    m = json.loads((tmp_path / "m.json").read_text())
    assert np.isfinite(m["throttle_rmse"]) and m["n_samples"] > 100
    bad = write_px4_ulog(tmp_path / "norates.ulg", _old(topics, vehicle_attitude=base["vehicle_attitude"]),
                         params, {"ver_sw": "legacy"}, start_us=UC.T0_US)
    capsys.readouterr()
    assert main(["compare", "--offline", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0] and "vehicle_attitude.rollspeed" in err[0], err


# --------------------------------------------------------------------------- real logs

#: real logs that are not flights: each must load (its old fields read) and be refused in one line
NOT_FLIGHTS = {
    "toopazo_v5_log156": "too short",  # PX4 1.9.0-dev, armed 5 s on the ground
    "mch_v5_test2": "never airborne",  # PX4 1.13.2-dev, never armed (its -inf battery current left out)
    "pyulog_sample_appended_multiple": "never airborne",  # PX4 1.6-dev, landed throughout
    "roboto_v5_test": "never left the ground",  # PX4 1.12.3-dev, an 8 s hop without GPS (flown without GPS since 24.5; refused as no flight)
}


@pytest.mark.parametrize("name", sorted(NOT_FLIGHTS))
def test_real_old_logs_that_are_no_flights_load_and_are_refused_in_one_line(name, capsys):
    p = need_testlog(name)
    fl = read_ulog(p)
    assert fl.get("body_rates_flu") is not None and fl.get("attitude_q") is not None
    if name in ("toopazo_v5_log156", "pyulog_sample_appended_multiple"):  # PX4 <= 1.9 layout
        assert fl.require("body_rates_flu").source.startswith("vehicle_attitude.rollspeed")
        assert fl.require("torque_setpoint_flu").source.startswith("actuator_controls_0")
    if name == "toopazo_v5_log156":  # armed on the ground, motors at idle: PWM_MIN 1200 -> 0..0.05
        m = fl.require("motors")
        assert "PWM_MIN" in m.source and np.nanmax(m.values) == pytest.approx((1254 - 1200) / 750, abs=1e-3)
    if name == "mch_v5_test2":
        assert fl.get("battery_a") is None and any("battery_a" in w and "left out" in w for w in fl.warnings)
    capsys.readouterr()
    assert main(["compare", "--offline", str(p)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert NOT_FLIGHTS[name] in err[-1] and not any("Traceback" in e for e in err), err


@pytest.mark.slow
def test_real_px4_19_uavcan_mission_flies(tmp_path):
    """PX4 1.9.0-beta (the corpus' tuning half): body rates from vehicle_attitude, UAVCAN ESC raw
    commands on actuator_outputs[1] (not instance 0), the custom mixer's idle 0.30 found and undone,
    trajectory_setpoint's 1.9 field names (its acc_x.. not flown, as PX4 1.9 did not); compare flies it
    (docs/real_logs.md has the numbers it gives)."""
    p = need_testlog("auterion_v3_esc_status")
    fl = read_ulog(p)
    m = fl.require("motors")
    assert m.source.startswith("actuator_outputs[1].output[0,1,2,3] (UAVCAN ESC raw commands 0-8191")
    idle = float(m.source.split("mixer idle ")[1].split()[0])
    assert idle == pytest.approx(0.30, abs=0.01)
    assert fl.moving_outputs == (4, "actuator_outputs[1].output")
    assert fl.require("body_rates_flu").source.startswith("vehicle_attitude.rollspeed")
    assert fl.require("setpoint_position_enu").source == "trajectory_setpoint (NED)"
    assert fl.get("setpoint_accel_enu") is None
    out = tmp_path / "m.json"
    assert main(["compare", "--offline", str(p), "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["n_samples"] > 1000 and r["throttle_rmse"] < 0.12 and r["xy_rmse_m"] < 4.0


@pytest.mark.slow
def test_real_px4_111_flight_in_px4_18_layout(tmp_path):
    """S500 mission1 (PX4 1.11) rewritten as PX4 1.8 logged it: the reader's 1.8 route gives back the
    same setpoints, feed-forward, motors and throttle exactly, the rates at 1.8's attitude rate; the
    twin flies it (docs/real_logs.md: XY 1.07 m against 0.42 m on the 1.11 layout, because PX4 1.8
    logged and flew no acceleration feed-forward)."""
    src = shared_log("real", "real_s500_rcac_mission1.ulg")
    a = read_ulog(src)
    b = read_ulog(to_px4_18_layout(src, tmp_path / "s500_px418.ulg"))
    tt = np.arange(10.0, 50.0, 0.05)
    for k in ("setpoint_position_enu", "setpoint_velocity_enu", "motors", "throttle", "torque_setpoint_flu",
              "setpoint_yaw_enu"):
        np.testing.assert_allclose(b.require(k).at(tt), a.require(k).at(tt), atol=1e-5, err_msg=k)
    assert "PWM_MIN" in b.require("motors").source
    assert b.get("setpoint_accel_enu") is None and a.get("setpoint_accel_enu") is not None
    rms = np.sqrt(np.nanmean((b.require("body_rates_flu").at(tt) - a.require("body_rates_flu").at(tt)) ** 2))
    assert rms < 0.1  # 20 Hz attitude stamps against the 50 Hz angular velocity
    out = tmp_path / "m.json"
    assert main(["compare", "--offline", str(tmp_path / "s500_px418.ulg"), "--json", str(out)]) == 0
    m = json.loads(out.read_text())
    assert m["throttle_rmse"] < 0.03 and m["motor_p75_mean"] < 0.06
    assert m["xy_rmse_m"] < 1.2 and m["z_rmse_m"] < 0.5


def test_yaw_law_before_px4_111_from_its_parameters():
    """PX4 < 1.11 (no MC_YAW_WEIGHT) weighed yaw by MC_YAW_P / mean(MC_ROLL_P, MC_PITCH_P) and did not
    divide the yaw gain by it: the yaw error reaches the rate setpoint with MC_YAW_P x that weight."""
    from twin_nodes.vehicle.px4_params import outer_loop_gains

    old = {"MC_ROLL_P": 6.5, "MC_PITCH_P": 6.0, "MC_YAW_P": 2.8}
    g, src = outer_loop_gains(old, 0.5)
    w = 2.8 / 6.25
    assert g["yaw_weight"] == pytest.approx(w) and g["yaw_p_1_s"] == pytest.approx(2.8 * w)
    assert "PX4 < 1.11" in src["yaw_p_1_s"]
    g, _ = outer_loop_gains(dict(old, MC_YAW_WEIGHT=0.4), 0.5)  # 1.11+: MC_YAW_P as it is
    assert g["yaw_p_1_s"] == pytest.approx(2.8) and g["yaw_weight"] == pytest.approx(0.4)


@pytest.mark.parametrize("name", sorted(NOT_FLIGHTS) + ["auterion_v3_esc_status"])
def test_cached_test_logs_are_the_listed_blobs(name):
    """tools/fetch_testlogs.py keeps a file only when its git blob id is the listed one; the cache holds
    exactly those bytes (git hash-object)."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("fetch_testlogs", Path(__file__).parents[1] / "tools" /
                                                  "fetch_testlogs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    from testlogs import TESTLOGS

    p = need_testlog(name)
    assert mod.blob_id(p.read_bytes()) == TESTLOGS[name][3]
    assert mod.blob_id(b"") == "e69de29bb2d1d6434b8b29ae775ad8c2e48c5391"  # git's empty blob
