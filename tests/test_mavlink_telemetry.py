"""Telemetry link: pure parsers (known answers) and a real ULog replayed as MAVLink over UDP loopback."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import missing_shared
from pymavlink.dialects.v20 import common as mavlink2

from twin_nodes.base import frames
from twin_nodes.mavlink.telemetry import (
    TelemetryAggregator,
    TelemetryClient,
    TelemetryConfig,
    motors_from_actuator_output_status,
    motors_from_pwm,
    normalise_url,
    parse_attitude_quaternion,
    parse_battery_status,
    parse_local_position_ned,
    landed_from_extended_sys_state,
    parse_highres_imu,
    parse_position_target_local_ned,
    px4_mode_name,
    px4_nav_state,
)

LOG = Path(__file__).resolve().parents[2] / "shared" / "flightlogs" / "real" / "real_cubeorange_takeoff_land.ulg"
MAV = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
UINT16_MAX = 65535
# PX4 nav_state -> (main, sub) custom mode, as PX4's mavlink get_px4_custom_mode() maps them
NAV_TO_CUSTOM = {0: (1, 0), 1: (2, 0), 2: (3, 0), 3: (4, 4), 4: (4, 3), 5: (4, 5), 14: (6, 0), 15: (7, 0),
                 17: (4, 2), 18: (4, 6)}


def custom_mode(main: int, sub: int) -> int:
    return (main << 16) | (sub << 24)


def decoded(msg, mav=MAV):
    """Encode (as system ``mav``) and decode, as the message would arrive from the wire."""
    buf = msg.pack(mav)
    rx = mavlink2.MAVLink(None)
    return rx.parse_buffer(buf)[0]


# --------------------------------------------------------------------------- pure parsers


def test_local_position_ned_to_enu():
    t, p, v = parse_local_position_ned(decoded(MAV.local_position_ned_encode(1500, 1.0, 2.0, -3.0, 0.5, -0.25, 1.0)))
    assert t == 1.5
    np.testing.assert_array_equal(p, [2.0, 1.0, 3.0])
    np.testing.assert_array_equal(v, [-0.25, 0.5, -1.0])


def test_attitude_quaternion_to_ros():
    # level, nose North in PX4 -> ROS yaw +90 deg; rates FRD -> FLU
    t, q, w = parse_attitude_quaternion(decoded(MAV.attitude_quaternion_encode(20, 1.0, 0.0, 0.0, 0.0,
                                                                               0.1, 0.2, 0.3)))
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)], atol=1e-7)
    np.testing.assert_allclose(w, [0.1, -0.2, -0.3], atol=1e-7)
    qn = frames.quat_from_euler(0.1, -0.2, 0.7)  # an FRD->NED attitude
    _, q2, _ = parse_attitude_quaternion(decoded(MAV.attitude_quaternion_encode(0, *qn, 0, 0, 0)))
    np.testing.assert_allclose(frames.quat_angle_between(q2, frames.q_ned_frd_to_enu_flu(qn)), 0.0, atol=1e-6)


def test_motors_from_pwm():
    np.testing.assert_array_equal(motors_from_pwm([900, 1000, 1500, 2100, 985]), [np.nan, 0.0, 0.5, 1.0, 0.0])
    assert np.all(np.isnan(motors_from_pwm([1500] * 4, armed=False)))
    np.testing.assert_allclose(motors_from_pwm([1075, 1950], 1075, 1950), [0.0, 1.0])
    # ACTUATOR_OUTPUT_STATUS: PX4 puts the output *count* in `active`; channels chosen by config
    aos = decoded(MAV.actuator_output_status_encode(0, 8, [1000, 1100, 1200, 1300, 1400, 1500, 1600, 1700]
                                                    + [0] * 24))
    np.testing.assert_allclose(motors_from_actuator_output_status(aos, TelemetryConfig()), [0, .1, .2, .3])
    cfg = TelemetryConfig(motor_channels=(4, 5, 6, 9))
    np.testing.assert_allclose(motors_from_actuator_output_status(aos, cfg), [.4, .5, .6, np.nan])


def test_battery_status_units_and_unknowns():
    cells = [4012, 4008, 4010] + [UINT16_MAX] * 7
    b = parse_battery_status(decoded(MAV.battery_status_encode(0, 0, 0, 2510, cells, 1234, 500, -1, 76)))
    assert b.voltage_v == pytest.approx(12.030)
    assert b.current_a == pytest.approx(12.34)
    assert b.remaining == pytest.approx(0.76)
    assert b.temperature_c == pytest.approx(25.10)
    assert b.cell_voltages_v == pytest.approx((4.012, 4.008, 4.010))
    u = parse_battery_status(decoded(MAV.battery_status_encode(0, 0, 0, 32767, [16100] + [UINT16_MAX] * 9,
                                                               -1, -1, -1, -1)))
    assert u.voltage_v == pytest.approx(16.1) and np.isnan(u.current_a) and np.isnan(u.remaining)
    assert np.isnan(u.temperature_c) and u.cell_voltages_v == ()


def test_position_target_to_setpoint_vector():
    msg = decoded(MAV.position_target_local_ned_encode(3000, 1, 0, 10.0, 20.0, -5.0, 1.0, 0.5, -0.2,
                                                       0.1, 0.2, 0.3, 0.0, 0.4))
    t, sp = parse_position_target_local_ned(msg)
    assert t == 3.0
    np.testing.assert_allclose(sp[0:3], [20.0, 10.0, 5.0])
    np.testing.assert_allclose(sp[3:6], [0.5, 1.0, 0.2], atol=1e-7)
    np.testing.assert_allclose(sp[6:9], [0.2, 0.1, -0.3], atol=1e-7)
    assert sp[9] == pytest.approx(np.pi / 2)    # heading North -> ROS yaw +90 deg
    assert sp[10] == pytest.approx(-0.4)        # yaw rate about Down -> about Up
    # velocity-only setpoint (position, acceleration, yaw masked): NaN = not controlled
    vel_only = decoded(MAV.position_target_local_ned_encode(0, 1, 0b111 | 0b111000000 | 1 << 10 | 1 << 11,
                                                            1, 2, 3, 4, 5, 6, 0, 0, 0, 0, 0))
    _, sp2 = parse_position_target_local_ned(vel_only)
    assert np.all(np.isnan(sp2[[0, 1, 2, 6, 7, 8, 9, 10]]))
    np.testing.assert_allclose(sp2[3:6], [5.0, 4.0, -6.0])
    nothing = decoded(MAV.position_target_local_ned_encode(0, 1, 0xFFF, 1, 2, 3, 0, 0, 0, 0, 0, 0, 0, 0))
    assert parse_position_target_local_ned(nothing) is None


def test_highres_imu_landed_and_nav_state():
    t, sf, w = parse_highres_imu(decoded(MAV.highres_imu_encode(2_000_000, 0.1, 0.2, -9.8, 0.01, 0.02, 0.03,
                                                                 0, 0, 0, 0, 0, 0, 0, 0)))
    assert t == 2.0
    np.testing.assert_allclose(sf, [0.1, -0.2, 9.8], atol=1e-6)
    np.testing.assert_allclose(w, [0.01, -0.02, -0.03], atol=1e-7)
    assert landed_from_extended_sys_state(decoded(MAV.extended_sys_state_encode(0, 1))) == 1.0
    assert landed_from_extended_sys_state(decoded(MAV.extended_sys_state_encode(0, 2))) == 0.0
    assert np.isnan(landed_from_extended_sys_state(decoded(MAV.extended_sys_state_encode(0, 0))))
    # the inverse of PX4's get_px4_custom_mode(): nav_state numbers of conventions.md §2
    for nav, (main, sub) in NAV_TO_CUSTOM.items():
        assert px4_nav_state(custom_mode(main, sub), 1) == nav
    assert np.isnan(px4_nav_state(custom_mode(4, 1), 1))      # AUTO.READY: no nav_state
    assert np.isnan(px4_nav_state(custom_mode(4, 4), 1, autopilot=3))


def test_px4_mode_names():
    assert px4_mode_name(custom_mode(4, 4), 1) == "AUTO.MISSION"
    assert px4_mode_name(custom_mode(4, 5), 129) == "AUTO.RTL"
    assert px4_mode_name(custom_mode(3, 0), 1) == "POSCTL"
    assert px4_mode_name(custom_mode(6, 0), 1) == "OFFBOARD"
    assert px4_mode_name(7, 1, autopilot=3) == "custom:7"  # not PX4


@pytest.mark.parametrize("url, device, kwargs", [
    ("udpin:0.0.0.0:14550", "udpin:0.0.0.0:14550", {}),
    ("udp://:14540", "udpin:0.0.0.0:14540", {}),
    ("udpin://0.0.0.0:14540", "udpin:0.0.0.0:14540", {}),
    ("udp::14550", "udpin:0.0.0.0:14550", {}),
    ("tcp:127.0.0.1:5760", "tcp:127.0.0.1:5760", {}),
    ("serial:/dev/ttyUSB0:57600", "/dev/ttyUSB0", {"baud": 57600}),
    ("/dev/ttyACM0", "/dev/ttyACM0", {}),
])
def test_normalise_url(url, device, kwargs):
    assert normalise_url(url) == (device, kwargs)


def test_aggregator_ignores_gcs_and_other_systems_and_goes_stale():
    agg = TelemetryAggregator(TelemetryConfig(stale_after_s=1.0))
    gcs = decoded(mavlink2.MAVLink(None, srcSystem=255).heartbeat_encode(6, 8, 0, 0, 0))
    assert agg.update(gcs, 0.0) == [] and agg.state.system_id is None
    hb = decoded(MAV.heartbeat_encode(2, 12, 129 | 0, custom_mode(4, 4), 4))
    kinds = agg.update(hb, 0.0)
    assert kinds == ["link", "status", "heartbeat"]
    assert agg.state.armed and agg.state.mode == "AUTO.MISSION" and not agg.state.stale
    assert agg.state.status[:2] == (1.0, 3.0) and np.isnan(agg.state.status[2])
    assert agg.update(hb, 0.05) == ["heartbeat"]                      # unchanged: no status
    assert agg.update(decoded(MAV.extended_sys_state_encode(0, 2)), 0.05) == ["status"]
    other = mavlink2.MAVLink(None, srcSystem=2, srcComponent=1)
    assert agg.update(decoded(other.local_position_ned_encode(0, 1, 1, 1, 0, 0, 0)), 0.1) == []
    assert agg.update(decoded(MAV.local_position_ned_encode(0, 1, 1, 1, 0, 0, 0)), 0.1) == []  # no attitude yet
    assert agg.update(decoded(MAV.attitude_quaternion_encode(0, 1, 0, 0, 0, 0, 0, 0)), 0.2) == ["odom"]
    assert not agg.check_stale(0.5)
    assert agg.check_stale(1.5) and agg.state.stale
    assert not agg.check_stale(2.0)  # reported once
    assert agg.update(hb, 3.0) == ["link", "status", "heartbeat"] and not agg.state.stale


# --------------------------------------------------------------------------- ULog replay over UDP


def _free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.fixture(scope="module")
def replay():
    if not LOG.exists():
        missing_shared(LOG.name)
    from pyulog import ULog

    ulog = ULog(str(LOG), ["vehicle_local_position", "vehicle_attitude", "vehicle_angular_velocity",
                           "actuator_outputs", "battery_status", "vehicle_status"])
    t0 = ulog.start_timestamp

    def ds(name, inst=0):
        d = ulog.get_dataset(name, inst).data
        keep = d["timestamp"] >= t0
        return {k: v[keep] for k, v in d.items()}

    lpos, att, angvel = ds("vehicle_local_position"), ds("vehicle_attitude"), ds("vehicle_angular_velocity")
    ao, bat, vs = ds("actuator_outputs", 1), ds("battery_status"), ds("vehicle_status")
    assert len(bat["timestamp"]) > 100
    # the MAVLink stream PX4 would send for this flight, in time order
    events = []
    for i, t in enumerate(lpos["timestamp"]):
        events.append((t, "lpos", MAV.local_position_ned_encode(
            int(t // 1000), *(lpos[k][i] for k in ("x", "y", "z", "vx", "vy", "vz")))))
    for i, t in enumerate(att["timestamp"]):
        j = max(np.searchsorted(angvel["timestamp"], t, side="right") - 1, 0)
        events.append((t, "att", MAV.attitude_quaternion_encode(
            int(t // 1000), *(att[f"q[{k}]"][i] for k in range(4)), *(angvel[f"xyz[{k}]"][j] for k in range(3)))))
    for i, t in enumerate(ao["timestamp"]):  # CubeOrange: motors on actuator_outputs instance 1 = AUX = port 1
        pwm = [int(round(ao[f"output[{k}]"][i])) for k in range(16)]
        events.append((t, "servo", MAV.servo_output_raw_encode(int(t % 2**32), 1, *pwm)))
    for i, t in enumerate(bat["timestamp"]):  # as PX4's streams/BATTERY_STATUS.hpp fills it
        n_cells = int(bat["cell_count"][i])
        if n_cells == 0 or bat["voltage_cell_v[0]"][i] < 1e-4:  # cells unknown: the total in voltages[0]
            cells = [int(bat["voltage_v"][i] * 1000)]
        else:
            cells = [int(bat[f"voltage_cell_v[{k}]"][i] * 1000) for k in range(n_cells)]
        cells += [UINT16_MAX] * (10 - len(cells))
        events.append((t, "bat", MAV.battery_status_encode(
            0, 0, 0, 32767, cells, int(bat["current_filtered_a"][i] * 100), -1, -1,
            int(round(bat["remaining"][i] * 100)))))
    # heartbeats from the first message on: data from before the vehicle's first heartbeat is not used
    # (whose it is cannot be known: issue 28)
    t_first = min(d["timestamp"][0] for d in (lpos, att, ao, bat))
    for t in np.arange(t_first, lpos["timestamp"][-1], 1_000_000):
        j = max(np.searchsorted(vs["timestamp"], t, side="right") - 1, 0)
        armed = vs["arming_state"][j] == 2
        main, sub = NAV_TO_CUSTOM.get(int(vs["nav_state"][j]), (4, 3))
        events.append((t, "hb", MAV.heartbeat_encode(2, 12, 1 | (128 if armed else 0), custom_mode(main, sub), 4)))
    events.sort(key=lambda e: (e[0], e[1] != "hb"))

    port = _free_udp_port()
    cfg = TelemetryConfig(motor_channels=(16, 17, 18, 19), request_streams=False, stale_after_s=0.5)
    got = {"odom": [], "motors": [], "battery": [], "status": [], "throttle": []}

    def on_update(kinds, st):
        if "odom" in kinds:
            got["odom"].append((st.t_position_s, st.position_enu.copy(), st.t_attitude_s, st.q_enu_flu.copy(),
                                st.rates_flu.copy()))
        if "motors" in kinds:
            got["motors"].append((st.armed, st.motors.copy()))
        if "throttle" in kinds:
            got["throttle"].append(st.throttle)
        if "battery" in kinds:
            got["battery"].append(st.battery)
        if "status" in kinds or "link" in kinds:
            got["status"].append((st.stale, st.armed, st.mode))

    client = TelemetryClient(f"udpin:127.0.0.1:{port}", cfg, on_update=on_update)
    client.start_thread()
    deadline = time.monotonic() + 5.0
    while not client.state.link_open and time.monotonic() < deadline:
        time.sleep(0.01)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for k, (_, _, msg) in enumerate(events):
        tx.sendto(msg.pack(MAV), ("127.0.0.1", port))
        if k % 20 == 19:  # stay within the socket buffer even on a loaded machine: let the client catch up
            wait_until = time.monotonic() + 2.0
            while client.state.messages_rx < k + 1 - 40 and time.monotonic() < wait_until:
                time.sleep(0.0005)
    deadline = time.monotonic() + 5.0
    while client.state.messages_rx < len(events) and time.monotonic() < deadline:
        time.sleep(0.01)
    received = client.state.messages_rx
    time.sleep(0.8)  # silence: the link goes stale
    stale_after_silence = client.state.stale
    client.close()
    tx.close()
    return dict(events=events, got=got, received=received, lpos=lpos, att=att, angvel=angvel, ao=ao, bat=bat,
                stale=stale_after_silence, start_us=t0)


def test_replay_nothing_lost(replay):
    assert replay["received"] == len(replay["events"])


def test_replay_odometry_matches_log_in_ros_frames(replay):
    lpos, att, angvel = replay["lpos"], replay["att"], replay["angvel"]
    odom = replay["got"]["odom"]
    by_pos = {}
    for t_pos, p, t_att, q, w in odom:
        by_pos[round(t_pos * 1000)] = p
    t_ms = (lpos["timestamp"] // 1000).astype(np.int64)
    expected = frames.ned_to_enu(np.column_stack([lpos["x"], lpos["y"], lpos["z"]]).astype(float))
    parsed = np.array([by_pos[t] for t in t_ms[1:]])  # odom starts once both position and attitude arrived
    np.testing.assert_array_equal(parsed, expected[1:])
    # attitude and rates: each ATTITUDE_QUATERNION becomes one odom update
    att_updates = [(t_att, q, w) for (_, _, t_att, q, w) in odom]
    t_att_ms = {round(t * 1000): (q, w) for t, q, w in att_updates}
    q_log = np.column_stack([att[f"q[{k}]"] for k in range(4)]).astype(float)
    q_exp = frames.q_ned_frd_to_enu_flu(q_log)
    n_checked = 0
    for i, t in enumerate((att["timestamp"] // 1000).astype(np.int64)):
        if t in t_att_ms and t_att_ms[t][0] is not None:
            q, w = t_att_ms[t]
            np.testing.assert_allclose(q, q_exp[i], atol=1e-7)
            j = max(np.searchsorted(angvel["timestamp"], att["timestamp"][i], side="right") - 1, 0)
            w_exp = frames.frd_to_flu(np.array([angvel[f"xyz[{k}]"][j] for k in range(3)], dtype=float))
            np.testing.assert_allclose(w, w_exp, atol=1e-7)
            n_checked += 1
    assert n_checked >= len(q_log) - 2


def test_replay_motors_battery_status(replay):
    got, ao, bat = replay["got"], replay["ao"], replay["bat"]
    motors = got["motors"]
    assert len(motors) == len(ao["timestamp"])
    for (armed, u), i in zip(motors, range(len(motors))):
        pwm = np.array([ao[f"output[{k}]"][i] for k in range(4)], dtype=float)
        exp = np.where(armed & (pwm >= 980.0), np.clip((pwm - 1000.0) / 1000.0, 0, 1), np.nan)
        np.testing.assert_allclose(u, exp, atol=1e-12)
    flying = np.array([u for a, u in motors if a])
    assert flying.size and np.nanmax(flying) > 0.4  # the climb
    thr = np.array(got["throttle"])
    assert len(thr) == len(motors)
    volts = np.array([b.voltage_v for b in got["battery"]])
    np.testing.assert_allclose(volts, bat["voltage_v"], atol=0.0011)    # mV on the wire
    np.testing.assert_allclose([b.current_a for b in got["battery"]], bat["current_filtered_a"], atol=0.011)
    np.testing.assert_allclose([b.remaining for b in got["battery"]], bat["remaining"], atol=0.006)
    modes = {m for _, _, m in got["status"]}
    assert {"AUTO.TAKEOFF", "AUTO.LAND"} <= modes
    assert got["status"][0][0] is False  # first status: link up
    assert replay["stale"] and got["status"][-1][0] is True


def test_replay_matches_ulog_replay_series(replay):
    """The telemetry topics carry the same numbers the ULog replay (twin_nodes.logs.ulog_io) publishes."""
    from twin_nodes.logs import ulog_io

    log = ulog_io.read_ulog(LOG)
    pos = log.get("position_enu")
    assert pos is not None, "read_ulog gave no position_enu"
    odom = replay["got"]["odom"]
    lpos = replay["lpos"]
    t_rel = (lpos["timestamp"] - replay["start_us"]) * 1e-6
    by_pos = {round(t_pos * 1000): p for t_pos, p, *_ in odom}
    ours = np.array([by_pos[int(t // 1000)] for t in lpos["timestamp"][1:]])
    theirs = pos.at(t_rel[1:])
    ok = np.all(np.isfinite(theirs), axis=1)
    assert ok.sum() > 0.9 * len(ok)
    np.testing.assert_allclose(ours[ok], theirs[ok], atol=1e-4)


# --------------------------------------------------------------------------- issue 28: nothing lost, whatever the input


def _free_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_garbage_and_other_systems_never_keep_the_link_alive():
    """Random UDP bytes (which pymavlink partly decodes as messages of unknown ids, whose checksum it
    cannot check) and a second vehicle's valid MAVLink keep arriving after our vehicle went silent:
    the link goes stale all the same, and what was ignored is counted.  (Before: the garbage alone
    kept the link "ok", so the watchdog never fired.)"""
    import random

    port = _free_port()
    client = TelemetryClient(f"udpin:127.0.0.1:{port}", TelemetryConfig(stale_after_s=0.5, request_streams=False))
    client.start_thread()
    deadline = time.monotonic() + 5.0
    while not client.state.link_open and time.monotonic() < deadline:
        time.sleep(0.01)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other = mavlink2.MAVLink(None, srcSystem=2, srcComponent=1)
    rng = random.Random(28)
    try:
        # garbage before anything: never a vehicle
        for _ in range(50):
            tx.sendto(bytes(rng.getrandbits(8) for _ in range(200)), ("127.0.0.1", port))
            time.sleep(0.002)
        time.sleep(0.3)
        assert client.state.stale and client.state.system_id is None and client.state.messages_rx == 0
        # our vehicle (system 1) speaks once, then only garbage and system 2 for 1.5 s
        tx.sendto(MAV.heartbeat_encode(2, 12, 129, custom_mode(4, 4), 4).pack(MAV), ("127.0.0.1", port))
        time.sleep(0.2)
        assert not client.state.stale and client.state.system_id == 1
        t_end = time.monotonic() + 1.5
        k = 0
        while time.monotonic() < t_end:
            tx.sendto(bytes(rng.getrandbits(8) for _ in range(200)), ("127.0.0.1", port))
            tx.sendto(other.heartbeat_encode(2, 12, 129, 0, 4).pack(other), ("127.0.0.1", port))
            tx.sendto(other.local_position_ned_encode(k, 1, 2, 3, 0, 0, 0).pack(other), ("127.0.0.1", port))
            k += 10
            time.sleep(0.01)
        time.sleep(0.2)
        st = client.state
        assert st.stale, "garbage or another system kept the link alive"
        assert st.messages_rx == 1 and st.system_id == 1 and st.component_id == 1
        assert st.bad_data > 50 and st.foreign > 100
        assert np.all(np.isnan(st.position_enu))  # system 2's position was never taken
    finally:
        tx.close()
        client.close()


def test_expected_system_id_from_config():
    """``TelemetryConfig(system_id=3)``: the first autopilot heartbeat of system 1 is not our vehicle."""
    agg = TelemetryAggregator(TelemetryConfig(system_id=3))
    assert agg.update(decoded(MAV.heartbeat_encode(2, 12, 129, custom_mode(4, 4), 4)), 0.0) == []
    three = mavlink2.MAVLink(None, srcSystem=3, srcComponent=1)
    assert agg.update(decoded(three.heartbeat_encode(2, 12, 1, custom_mode(4, 3), 4), three), 0.1)[0] == "link"
    assert (agg.state.system_id, agg.state.component_id, agg.state.foreign, agg.state.messages_rx) == (3, 1, 1, 1)
    # another component of system 3 (e.g. a gimbal sending its own attitude) is not the autopilot
    gimbal = mavlink2.MAVLink(None, srcSystem=3, srcComponent=154)
    assert agg.update(decoded(gimbal.attitude_quaternion_encode(0, 1, 0, 0, 0, 0, 0, 0), gimbal), 0.2) == []
    assert agg.state.foreign == 2


def _bound_aggregator() -> TelemetryAggregator:
    agg = TelemetryAggregator(TelemetryConfig())
    agg.update(decoded(MAV.heartbeat_encode(2, 12, 129, custom_mode(4, 4), 4)), 0.0)
    agg.update(decoded(MAV.attitude_quaternion_encode(1000, 1, 0, 0, 0, 0, 0, 0)), 0.0)
    agg.update(decoded(MAV.local_position_ned_encode(1000, 1, 2, -3, 0, 0, 0)), 0.0)
    return agg


@pytest.mark.parametrize("bad", [
    MAV.local_position_ned_encode(1100, float("inf"), 0, -3, 0, 0, 0),
    MAV.local_position_ned_encode(1100, 1e38, 0, -3, 0, 0, 0),
    MAV.local_position_ned_encode(1100, 1, 2, float("nan"), 0, 0, 0),
    MAV.local_position_ned_encode(1100, 2e6, 0, -3, 0, 0, 0),
    MAV.local_position_ned_encode(1100, 1, 2, -3, 150.0, 0, 0),
    MAV.attitude_quaternion_encode(1100, 0.9, 0.0, 0.0, 0.0, 0, 0, 0),
    MAV.attitude_quaternion_encode(1100, float("nan"), 0.0, 0.0, 0.0, 0, 0, 0),
    MAV.attitude_quaternion_encode(1100, 1.0, 0.0, 0.0, 0.0, float("inf"), 0, 0),
    MAV.highres_imu_encode(1_100_000, 1e38, 0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
    MAV.position_target_local_ned_encode(1100, 1, 0, float("inf"), 0, -5, 0, 0, 0, 0, 0, 0, 0, 0),
], ids=["pos_inf", "pos_1e38", "pos_nan", "pos_2e6", "vel_150", "q_norm_0.9", "q_nan", "rate_inf", "imu_1e38",
        "setpoint_inf"])
def test_absurd_values_are_dropped_at_the_edge(bad, caplog):
    """Non-finite or physically absurd telemetry is dropped (counted, one warning), never passed on:
    the state keeps its last good values and nothing is announced."""
    agg = _bound_aggregator()
    before = (agg.state.position_enu.copy(), agg.state.q_enu_flu.copy(), agg.state.messages_rx)
    with caplog.at_level("WARNING", logger="rotortwin.telemetry"):
        assert agg.update(decoded(bad), 1.0) == []
        assert agg.update(decoded(bad), 1.1) == []
    st = agg.state
    assert st.rejected == {bad.get_type(): 2} and st.n_rejected == 2
    np.testing.assert_array_equal(st.position_enu, before[0])
    np.testing.assert_array_equal(st.q_enu_flu, before[1])
    assert st.messages_rx == before[2]
    assert np.all(np.isnan(st.setpoint)) and np.all(np.isnan(st.imu_specific_force_flu))
    assert len([r for r in caplog.records if "dropping" in r.getMessage()]) == 1  # one warning
    # good values still pass
    assert agg.update(decoded(MAV.local_position_ned_encode(1200, 1, 2, -3.5, 0, 0, -0.5)), 1.2) == ["odom"]


def test_vehicle_restart_is_detected():
    """A reboot (boot time going back), a new EKF origin and a local-position jump are each one
    ``reset``; ordinary flight is not."""
    agg = _bound_aggregator()
    t = 1.0
    for k in range(1, 50):  # 5 m/s East for 5 s: no reset
        assert "reset" not in agg.update(decoded(MAV.local_position_ned_encode(1000 + 100 * k, 1, 2 + 0.5 * k, -3,
                                                                               0, 5.0, 0)), t + 0.1 * k)
    assert agg.state.resets == []
    # PX4 restarted: boot time back to 3 s, the new origin where the vehicle is (60 m away)
    kinds = agg.update(decoded(MAV.attitude_quaternion_encode(3000, 1, 0, 0, 0, 0, 0, 0)), 10.0)
    assert "reset" in kinds and len(agg.state.resets) == 1 and "reboot" in agg.state.reset_reason
    assert agg.update(decoded(MAV.local_position_ned_encode(3010, 0, 0, -0.1, 0, 0, 0)), 10.01) == ["odom"]
    # a local-position reset: 60 m in 0.1 s while standing still
    kinds = agg.update(decoded(MAV.local_position_ned_encode(3110, 60.0, 0, -0.1, 0, 0, 0)), 10.1)
    assert kinds == ["reset", "odom"] and "position jump" in agg.state.reset_reason
    # a new EKF origin
    agg.update(decoded(MAV.gps_global_origin_encode(473977418, 85455939, 488000)), 10.2)
    assert agg.update(decoded(MAV.gps_global_origin_encode(473977418, 85455939, 488000)), 10.3) == []
    assert agg.update(decoded(MAV.gps_global_origin_encode(473980000, 85455939, 488000)), 10.4) == ["reset"]
    assert [r["reason"].split()[0] for r in agg.state.resets] == ["reboot", "position", "new"]


def test_vehicle_clean_shutdown_is_seen():
    agg = _bound_aggregator()
    assert not agg.state.vehicle_closed
    agg.update(decoded(MAV.heartbeat_encode(2, 12, 1, custom_mode(4, 3), mavlink2.MAV_STATE_POWEROFF)), 2.0)
    assert agg.state.vehicle_closed
    agg.update(decoded(MAV.heartbeat_encode(2, 12, 1, custom_mode(4, 3), 4)), 3.0)
    assert not agg.state.vehicle_closed


def test_position_change_across_a_link_gap_is_not_a_restart():
    """After 5 s without data the vehicle may simply be 30 m further on: not a restart."""
    agg = _bound_aggregator()
    assert agg.update(decoded(MAV.local_position_ned_encode(1100, 1, 2, -3, 0, 0, 0)), 1.1) == ["odom"]
    assert agg.update(decoded(MAV.local_position_ned_encode(6100, 31, 2, -3, 0, 0, 0)), 6.1) == ["odom"]
    assert agg.state.resets == []
