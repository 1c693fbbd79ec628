"""PX4 SIH flights of our own (``launch_scripts/fly_sih.sh``, :mod:`twin_nodes.mavlink.sih_flight`): the SIH_*
scrubbing of a ULog, the truth written beside it and how ``prove --source px4sih`` maps it, per-item yaw in
mission plans (M3), and ``--sih-dir`` folders read by the prove suite.  One flight against real PX4 runs only
with ``PX4_DIR`` set (a PX4-Autopilot tree built with ``make px4_sitl_default``)."""

from __future__ import annotations

import json
import os
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from pymavlink.dialects.v20 import common as mavlink2

from tests.conftest import px4_sitl_binary
from twin_nodes.base.errors import ParamsError, TwinError
from twin_nodes.prove import sih as prove_sih
from twin_nodes.logs.ulog_write import write_px4_ulog
from twin_nodes.mavlink import sih_flight as sf
from twin_nodes.mavlink.mission import load_plan, plan_from_mapping, plan_to_mission_items, upload_plan
from twin_nodes.vehicle.params import load_params

REPO = Path(__file__).resolve().parents[1]
HOME = (47.397743, 8.545594)
SHARED = prove_sih.shared_dir() / "flightlogs" / "sitl_effects"


def _q_record(name: str, value: float) -> bytes:
    key = f"float {name}".encode()
    payload = bytes([1, len(key)]) + key + struct.pack("<f", value)
    return struct.pack("<HB", len(payload), ord("Q")) + payload


def _log_with_sih(path: Path) -> Path:
    """A small ULog with SIH_* and other parameters, plus two 'Q' default-parameter messages."""
    t = np.arange(0, 2_000_000, 20_000, dtype=np.int64) + 1_000_000
    write_px4_ulog(path, {"vehicle_attitude": {"timestamp": t, "q": np.tile([1.0, 0, 0, 0], (len(t), 1))}},
                   {"SIH_MASS": 1.3, "SIH_Q_MAX": 0.1, "MPC_XY_VEL_MAX": 12.0, "SYS_AUTOSTART": 10040},
                   {"ver_sw": "02e73e3b6f4826a376d0805ee12e30b7538ada99"})
    data = bytearray(path.read_bytes())
    # insert the 'Q' messages right after the flag bits ('B'), the first message after the 16-byte header
    size = struct.unpack_from("<H", data, 16)[0]
    at = 16 + 3 + size
    data[at:at] = _q_record("SIH_MASS", 1.0) + _q_record("MPC_XY_VEL_MAX", 12.0)
    path.write_bytes(bytes(data))
    return path


def test_scrub_removes_every_sih_parameter_and_keeps_the_rest(tmp_path):
    from pyulog import ULog

    raw = _log_with_sih(tmp_path / "raw.ulg")
    assert ULog(str(raw)).initial_parameters["SIH_MASS"] == pytest.approx(1.3)
    n = sf.scrub_ulog(raw, tmp_path / "flight.ulg")
    assert n == 3  # P SIH_MASS, P SIH_Q_MAX, Q SIH_MASS
    out = (tmp_path / "flight.ulg").read_bytes()
    assert b"SIH_" not in out and b"SIH_" in raw.read_bytes()
    assert len(raw.read_bytes()) - len(out) == sum(3 + 1 + len(f"float {k}") + 4 for k in ("SIH_MASS", "SIH_Q_MAX")) \
        + 3 + 2 + len("float SIH_MASS") + 4
    u = ULog(str(tmp_path / "flight.ulg"))
    assert u.initial_parameters == {"MPC_XY_VEL_MAX": pytest.approx(12.0), "SYS_AUTOSTART": 10040}
    check = sf.check_scrubbed(raw, tmp_path / "flight.ulg")
    assert check["same_topics_and_counts"] and check["same_other_params"] and check["prefix_absent"]
    assert check["topics"] == 1


def test_scrub_refuses_appended_data_and_non_ulog(tmp_path):
    raw = _log_with_sih(tmp_path / "raw.ulg")
    data = bytearray(raw.read_bytes())
    data[16 + 3 + 8] |= 1  # incompat flag 0: appended data present
    bad = tmp_path / "appended.ulg"
    bad.write_bytes(bytes(data))
    with pytest.raises(TwinError, match=r"appended\.ulg: the log has appended data"):
        sf.scrub_ulog(bad, tmp_path / "x.ulg")
    (tmp_path / "text.ulg").write_text("hello")
    with pytest.raises(TwinError, match=r"text\.ulg: not a ULog file"):
        sf.scrub_ulog(tmp_path / "text.ulg", tmp_path / "y.ulg")


def test_logger_topics_are_the_manifests_and_the_shared_flights():
    man = sf.load_manifest()
    lines = [ln.split() for ln in sf.logger_topics_text(man).splitlines() if not ln.startswith("#")]
    assert len(lines) == 47 and lines[0] == ["sensor_combined", "10", "0"]
    assert ["actuator_motors", "20", "0"] in lines and ["vehicle_status", "0", "0"] in lines
    shared = SHARED / "logger_topics.txt"
    if shared.is_file():  # the topic list the shared flights were logged with
        theirs = [ln.split() for ln in shared.read_text().splitlines() if ln and not ln.startswith("#")]
        assert theirs == lines


HIGHRATE = ("actuator_motors", "vehicle_angular_velocity", "vehicle_torque_setpoint", "vehicle_thrust_setpoint",
            "sensor_combined")


def test_highrate_logging_profile_changes_only_its_five_topics():
    man = sf.load_manifest()
    default = [ln.split() for ln in sf.logger_topics_text(man).splitlines() if not ln.startswith("#")]
    high = [ln.split() for ln in sf.logger_topics_text(man, "highrate").splitlines() if not ln.startswith("#")]
    assert [t for t, *_ in high] == [t for t, *_ in default]  # same 47 topics, same order
    assert sf.logger_topics_text(man, "default") == sf.logger_topics_text(man)
    for (topic, iv, inst), (_, iv0, _) in zip(high, default):
        assert inst == "0"
        assert iv == ("4" if topic in HIGHRATE else iv0), topic
    assert {t: int(iv) for t, iv, _ in default}["actuator_motors"] == 20
    assert "logging profile highrate" in sf.logger_topics_text(man, "highrate").splitlines()[0]


def test_logging_profile_is_recorded_and_bad_profiles_are_one_line_errors(tmp_path):
    man = sf.load_manifest()
    lg = {"profile": "highrate", "topics_interval_ms": {t: 4 for t in HIGHRATE}}
    t = sf.truth_json({"SIH_T_TAU": 0.12}, "M4", "02e73e3b6f", lg)
    assert t["logging"] == lg and "logging" not in sf.truth_json({"SIH_T_TAU": 0.12}, "M4", "x")
    assert "logging" not in sf.truth_json({}, "M4", "x", {"profile": "default", "topics_interval_ms": {}})
    # the prove suite maps a truth.json with logging exactly as one without
    vp = load_params(prove_sih.NOMINAL)
    assert prove_sih.map_truth(t, vp).hidden.params == pytest.approx({"tau_up": 0.12, "tau_down": 0.12})
    with pytest.raises(ParamsError, match=r"manifest\.yaml: px4\.logging\.profiles\.fast: no such logging profile "
                                          r"\(known: default, highrate\)"):
        sf.logger_topics_text(man, "fast")
    bad = tmp_path / "m.yaml"
    base = "px4: {environment: {PX4_SYS_AUTOSTART: 10040}, logging: {topics_interval_ms: {a: 20}, profiles: %s}}\n"
    bad.write_text(base % "{hr: {topics_interval_ms: {a: 2.5}}}")
    with pytest.raises(ParamsError, match=r"m\.yaml: px4\.logging\.profiles\.hr\.topics_interval_ms\.a: expected an "
                                          r"integer >= 0, got 2\.5"):
        sf.load_manifest(bad)
    bad.write_text(base % "{hr: {}}")
    with pytest.raises(ParamsError, match=r"m\.yaml: px4\.logging\.profiles\.hr\.topics_interval_ms: expected a mapping"):
        sf.load_manifest(bad)
    bad.write_text((base % "{hr: {topics_interval_ms: {a: 4}}}") + "missions: {M3: {plan_file: missions/sih_effects/"
                   "M3_yaw_square.plan.yaml}}\nflights: {x1: {mission: M3, sih: {}, logging: turbo}}\n")
    with pytest.raises(ParamsError, match=r"m\.yaml: px4\.logging\.profiles\.turbo: no such logging profile"):
        sf.flights_from_manifest(sf.load_manifest(bad), ["x1"])
    px4 = tmp_path / "px4"
    (px4 / "build" / "px4_sitl_default" / "bin").mkdir(parents=True)
    (px4 / "build" / "px4_sitl_default" / "bin" / "px4").write_text("")
    # --logging: an unknown profile, or one that contradicts a manifest flight's own, is refused before flying
    assert sf.main(["--out", str(tmp_path), "--px4", str(px4), "--flight", "e09", "--logging", "turbo"]) == 1
    assert sf.main(["--out", str(tmp_path), "--px4", str(px4), "--flight", "h01", "--logging", "default"]) == 1
    assert not (tmp_path / "h01").exists() and not (tmp_path / "e09").exists()


NEW_FLIGHTS = {  # id: (mission, {param: value}, our vocabulary's effect and truth)
    "e09": ("M3", {"SIH_Q_MAX": 0.16}, ("yaw_moment", {"km": 0.032})),
    "e10": ("M4", {"SIH_T_TAU": 0.12}, ("motor_time_constant", {"tau_up": 0.12, "tau_down": 0.12})),
    "e11": ("M4", {"SIH_IXX": 0.0375, "SIH_IYY": 0.0375}, ("inertia", {"ixx": 0.0375, "iyy": 0.0375, "izz": 0.03})),
    "e12": ("M3", {"SIH_IXX": 0.0375, "SIH_IYY": 0.0375}, ("inertia", {"ixx": 0.0375, "iyy": 0.0375, "izz": 0.03})),
    "e13": ("M4", {"SIH_L_ROLL": 0.16}, ("inertia", {"ixx": 0.03125, "iyy": 0.025, "izz": 0.03})),
    "e14": ("M3", {"SIH_IZZ": 0.045}, ("inertia", {"ixx": 0.025, "iyy": 0.025, "izz": 0.045})),
    "e15": ("M4", {"SIH_MASS": 1.3}, ("mass", {"mass": 1.3})),
    "e16": ("M3", {}, ("none", {})),
    "e17": ("M4", {}, ("none", {})),
    # high-rate logging twins (logging profile highrate)
    "h01": ("M4", {"SIH_T_TAU": 0.12}, ("motor_time_constant", {"tau_up": 0.12, "tau_down": 0.12})),
    "h02": ("M4", {"SIH_IXX": 0.0375, "SIH_IYY": 0.0375}, ("inertia", {"ixx": 0.0375, "iyy": 0.0375, "izz": 0.03})),
    "h03": ("M3", {"SIH_IXX": 0.0375, "SIH_IYY": 0.0375}, ("inertia", {"ixx": 0.0375, "iyy": 0.0375, "izz": 0.03})),
    "h04": ("M3", {"SIH_Q_MAX": 0.16}, ("yaw_moment", {"km": 0.032})),
    "h05": ("M3", {}, ("none", {})),
    "h06": ("M4", {}, ("none", {})),
}


@pytest.mark.parametrize("fid", sorted(NEW_FLIGHTS))
def test_manifest_flights_of_our_own_map_to_their_truth(fid):
    """Each flight fly_sih flies from the manifest: its truth.json (as fly_sih writes it) maps onto our
    vocabulary exactly as the manifest's ``truth:`` says."""
    man = sf.load_manifest()
    mission, sih, (eff, params) = NEW_FLIGHTS[fid]
    job = sf.flights_from_manifest(man, [fid])[0]
    assert job["mission"] == mission and job["sih"] == pytest.approx(sih)
    assert job["plan"].name.startswith(mission)
    assert job["logging"] == ("highrate" if fid.startswith("h") else None)
    truth = sf.truth_json(job["sih"], mission, "02e73e3b6f")
    t = prove_sih.map_truth(truth, load_params(prove_sih.NOMINAL))
    assert t.hidden.name == eff and t.hidden.params == pytest.approx(params, rel=1e-9)
    mt = man["flights"][fid]["truth"]
    assert (mt == "none") if eff == "none" else (mt == {eff: pytest.approx(params, rel=1e-6)})
    assert man["flights"][fid]["px4_commit"] == man["px4"]["commit"]


def test_truth_json_is_the_shared_format():
    t = sf.truth_json({"SIH_Q_MAX": 0.16}, "M3", "02e73e3b6f")
    assert t["effects"] == [{"name": "yaw_moment", "params": {"km": pytest.approx(0.032), "q_max_nm": 0.16}}]
    assert t["sih_changes"] == {"SIH_Q_MAX": [0.1, 0.16]} and t["mission"] == "M3"
    e03 = SHARED / "e03" / "truth.json"
    if e03.is_file():  # the same keys and numbers the shared flight's truth uses
        theirs = json.loads(e03.read_text())
        ours = sf.truth_json({"SIH_Q_MAX": 0.14}, "M3", "x")
        assert set(ours) == set(theirs) and ours["sih_changes"] == theirs["sih_changes"]
        assert ours["effects"][0]["params"] == pytest.approx(theirs["effects"][0]["params"])
    # two parameter groups at once (issue 26's SIH grid): one effect per group, in the groups' order
    two = sf.truth_effects({"SIH_MASS": 1.2, "SIH_KDV": 2.0})
    assert [e["name"] for e in two] == ["mass", "body_drag"] and two[0]["params"] == {"mass": 1.2}
    with pytest.raises(TwinError, match="parameter groups"):
        sf.truth_effects({"SIH_MASS": 1.2, "SIH_NOT_A_PARAM": 2.0})


def test_patched_sih_changes_map_to_a_motor_and_a_centre_of_mass():
    """missions/sih_effects/px4_sih_weak_motor_com.patch: SIH's u[i] is PX4's motor i+1, its CG is FRD; ours FLU."""
    weak = sf.parse_sih(["SIH_MOT_WEAK=3", "SIH_MOT_EFF=0.85"])
    assert sf.truth_effects(weak) == [{"name": "motor_efficiency", "params": {"motor": 3, "efficiency": 0.85}}]
    cg = sf.parse_sih(["SIH_CG_X=0.02", "SIH_CG_Y=-0.01"])      # 0 and negative values are allowed here
    assert sf.truth_effects(cg) == [{"name": "com_offset", "params": {"dx": 0.02, "dy": 0.01}}]
    both = sf.truth_effects({**weak, "SIH_CG_X": 0.02})
    assert [e["name"] for e in both] == ["motor_efficiency", "com_offset"]
    # the patch adds exactly these parameters with these defaults (stock behaviour when unset)
    text = (REPO / "missions" / "sih_effects" / "px4_sih_weak_motor_com.patch").read_text()
    for name, default in sf.SIH_PATCHED.items():
        kind = "INT32" if isinstance(default, int) else "FLOAT"
        value = f"{default}" if kind == "INT32" else f"{float(default)}f"
        assert f"+PARAM_DEFINE_{kind}({name}, {value});" in text
    # the fleet proof names the declared changes of the patched fleet p01-p18 with the motor's number
    sys.path.insert(0, str(REPO / "tools"))
    import sih_fleet_proof

    ids, decl = sih_fleet_proof.declared("p")
    assert len(ids) == 18
    assert [(d["flight"], d["expect"]) for d in decl] == [("p06", ["motor 3"]), ("p10", ["motor 3"]),
                                                          ("p13", ["centre-of-mass shift"]),
                                                          ("p17", ["centre-of-mass shift"])]


@pytest.mark.parametrize("items, match", [
    (["SIH_MASS"], r"--sih: 'SIH_MASS': expected NAME=VALUE"),
    (["SIH_FOO=1"], r"--sih: SIH_FOO: expected one of SIH_MASS"),
    (["SIH_MASS=-1"], r"--sih: SIH_MASS: expected a positive number, got '-1'"),
    (["SIH_MASS=abc"], r"--sih: SIH_MASS: expected a positive number, got 'abc'"),
    (["SIH_MOT_WEAK=5", "SIH_MOT_EFF=0.8"], r"--sih: SIH_MOT_WEAK: expected an integer in \[1, 4\] \(patched"),
    (["SIH_MOT_WEAK=2.5", "SIH_MOT_EFF=0.8"], r"--sih: SIH_MOT_WEAK: expected an integer in \[1, 4\]"),
    (["SIH_MOT_WEAK=2"], r"--sih: SIH_MOT_WEAK and SIH_MOT_EFF: expected both"),
    (["SIH_CG_X=0.5"], r"--sih: SIH_CG_X: expected a number in \[-0.1, 0.1\]"),
])
def test_bad_sih_changes_are_one_line_errors(items, match):
    with pytest.raises(TwinError, match=match):
        sf.parse_sih(items)


def test_unknown_flight_and_mission_are_one_line_errors(tmp_path):
    man = sf.load_manifest()
    with pytest.raises(ParamsError, match=r"manifest\.yaml: flights\.e99: no such flight"):
        sf.flights_from_manifest(man, ["e99"])
    with pytest.raises(ParamsError, match=r"manifest\.yaml: flights\.px4sih_default_grid\.log: a shared log"):
        sf.flights_from_manifest(man, ["px4sih_default_grid"])
    with pytest.raises(ParamsError, match=r"manifest\.yaml: missions\.M9: no such mission"):
        sf.mission_plan_path(man, "M9")
    bad = tmp_path / "m.yaml"
    bad.write_text("px4: {environment: {PX4_SYS_AUTOSTART: 10040}, logging: {topics_interval_ms: {a: -1}}}\n")
    with pytest.raises(ParamsError, match=r"m\.yaml: px4\.logging\.topics_interval_ms\.a: expected an integer >= 0"):
        sf.load_manifest(bad)
    assert sf.main(["--out", str(tmp_path), "--px4", str(tmp_path), "--flight", "e09"]) == 1  # PX4 not built


# ---------------------------------------------------------------- per-item yaw (M3)


def test_m3_plan_is_the_shared_yaw_square():
    plan = load_plan(REPO / "missions" / "sih_effects" / "M3_yaw_square.plan.yaml")
    assert [w.yaw_deg for w in plan.waypoints] == [0, 0, 90, 90, 180, 180, 270, 270, 0]
    assert not any(w.fly_through for w in plan.waypoints) and {w.speed_m_s for w in plan.waypoints} == {5.0}
    assert plan.length_m() == pytest.approx(160.0)
    shared = SHARED / "M3_yaw_square.plan.yaml"
    if shared.is_file():
        items = yaml.safe_load(shared.read_text())["mission"]["items"]
        assert [[*it["ne_alt"], it["yaw_deg"]] for it in items] == \
               [[w.north_m, w.east_m, w.alt_m, w.yaw_deg] for w in plan.waypoints]
    items = plan_to_mission_items(plan, *HOME)
    assert [it.yaw_deg for it in items] == [0, 0, 90, 90, 180, 180, 270, 270, 0]


def test_yaw_is_optional_and_checked():
    plan = plan_from_mapping({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "waypoints": [
        [1, 2, 3], {"north_m": 1, "east_m": 2, "alt_m": 3, "yaw_deg": -90.0}, {"north_m": 1, "east_m": 2,
                                                                             "alt_m": 3, "yaw_deg": None}]}})
    assert [w.yaw_deg for w in plan.waypoints] == [None, -90.0, None]
    yaws = [it.yaw_deg for it in plan_to_mission_items(plan, *HOME)]
    assert np.isnan(yaws[0]) and yaws[1] == -90.0 and np.isnan(yaws[2])
    with pytest.raises(ParamsError, match=r"p\.yaml: mission\.waypoints\[0\]\.yaw_deg: expected <= 360, got 400"):
        plan_from_mapping({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "waypoints": [
            {"north_m": 1, "east_m": 2, "alt_m": 3, "yaw_deg": 400}]}}, "p.yaml")
    with pytest.raises(ParamsError, match=r"mission\.waypoints\[0\]\.yaw_deg: expected a finite number, got 'N'"):
        plan_from_mapping({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "waypoints": [
            {"north_m": 1, "east_m": 2, "alt_m": 3, "yaw_deg": "N"}]}}, "p.yaml")


def test_yaw_reaches_the_autopilot_as_param4():
    """Upload M3 to the fake autopilot of test_mavlink_mission: every NAV_WAYPOINT carries its yaw."""
    from test_mavlink_mission import FakeAutopilot, _free_udp_port

    port = _free_udp_port()
    ap = FakeAutopilot(port).start()
    try:
        plan = load_plan(REPO / "missions" / "sih_effects" / "M3_yaw_square.plan.yaml")
        upload_plan(plan, f"udpin://127.0.0.1:{port}", connect_timeout_s=5.0, home_timeout_s=5.0)
    finally:
        ap.close()
    wps = [ap.items[k] for k in sorted(ap.items) if ap.items[k].command == mavlink2.MAV_CMD_NAV_WAYPOINT]
    assert [w.param4 for w in wps] == [0, 0, 90, 90, 180, 180, 270, 270, 0]
    assert all(w.param1 == pytest.approx(0.5) for w in wps)  # stop waypoints: MAVSDK's 0.5 s hold


# ---------------------------------------------------------------- prove reads --sih-dir folders


def test_prove_reads_sih_dir_folders(tmp_path):
    own = tmp_path / "sih_flights"
    for fid, sih in (("e09", {"SIH_Q_MAX": 0.16}), ("e07", {})):
        d = own / fid
        d.mkdir(parents=True)
        _log_with_sih(d / "raw.ulg")
        sf.scrub_ulog(d / "raw.ulg", d / "flight.ulg")
        (d / "truth.json").write_text(json.dumps(sf.truth_json(sih, "M3", "x")))
    (own / "notes").mkdir()  # a folder without a flight is ignored
    fl = prove_sih.flights(tmp_path / "no_shared", sih_dirs=[own])
    assert [f["flight"] for f in fl] == ["e07", "e09"]
    assert fl[1]["truth_json"]["sih_changes"] == {"SIH_Q_MAX": [0.1, 0.16]} and fl[1]["mission"] == "M3"
    twice = prove_sih.flights(tmp_path / "no_shared", sih_dirs=[own, own])
    assert [f["flight"] for f in twice] == ["e07", "e09", "sih_flights/e07", "sih_flights/e09"]
    with pytest.raises(TwinError, match=r"--sih-dir .*nothing: not a folder"):
        prove_sih.flights(tmp_path / "no_shared", sih_dirs=[tmp_path / "nothing"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(TwinError, match=r"--sih-dir .*empty: no <name>/flight\.ulg \+ truth\.json inside"):
        prove_sih.flights(tmp_path / "no_shared", sih_dirs=[tmp_path / "empty"])
    (own / "e07" / "truth.json").write_text("{")
    with pytest.raises(TwinError, match=r"e07/truth\.json: not valid JSON"):
        prove_sih.flights(tmp_path / "no_shared", sih_dirs=[own])


# ---------------------------------------------------------------- real PX4 (PX4_DIR)


@pytest.mark.slow
def test_fly_one_sih_flight_against_real_px4(tmp_path):
    px4_sitl_binary()
    px4_dir = os.environ["PX4_DIR"]
    from pyulog import ULog

    plan = tmp_path / "hop.plan.yaml"
    plan.write_text("mission: {name: hop, speed_m_s: 4.0, acceptance_radius_m: 2.0, fly_through: false,\n"
                    "  rtl_after: true, waypoints: [{north_m: 10.0, east_m: 0.0, alt_m: 6.0, yaw_deg: 90.0}]}\n")
    r = sf.fly_sih(px4_dir, plan, {"SIH_MASS": 1.25}, tmp_path / "out", "x01", timeout_s=600.0, logging="highrate")
    d = tmp_path / "out" / "x01"
    assert {p.name for p in d.iterdir()} >= {"flight.ulg", "truth.json", "MANIFEST.md", "px4.log"}
    f = r["facts"]
    assert f["sih_params"]["SIH_MASS"] == pytest.approx(1.25) and f["mission_finished"]
    assert f["dropouts"] == 0 and f["gps_drift_warnings"] == 0 and 6.0 < f["max_alt_m"] < 16.5
    assert b"SIH_" not in (d / "flight.ulg").read_bytes()
    u = ULog(str(d / "flight.ulg"))
    assert not any(k.startswith("SIH_") for k in u.initial_parameters)
    assert u.msg_info_dict["ver_sw"] == f["ver_sw"] and len(f["ver_sw"]) == 40
    truth = json.loads((d / "truth.json").read_text())
    assert prove_sih.map_truth(truth, load_params(prove_sih.NOMINAL)).hidden.params == {"mass": 1.25}
    # a heavier vehicle: PX4's hover thrust estimate above the nominal 0.49
    assert f["hover_thrust_estimate"] > 0.55
    # the highrate logging profile: its topics every 4 ms (SIH's 250 Hz rate loop), the rest as the default list
    assert truth["logging"]["profile"] == "highrate" and "profile `highrate`" in (d / "MANIFEST.md").read_text()
    for d_ in u.data_list:
        if d_.multi_id == 0 and d_.name in HIGHRATE + ("vehicle_attitude",):
            dt_ms = float(np.median(np.diff(d_.data["timestamp"]))) * 1e-3
            assert dt_ms == pytest.approx(20.0 if d_.name == "vehicle_attitude" else 4.0, abs=0.5), d_.name


def test_a_running_px4_instance_is_refused():
    """Port 14580+N taken (a PX4 of that instance runs): refused before anything starts."""
    import socket

    for instance in range(40, 60):  # an instance number whose port is free now, then taken by us
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.bind(("0.0.0.0", 14580 + instance))
        except OSError:
            s.close()
            continue
        try:
            with pytest.raises(TwinError, match=rf"UDP port {14580 + instance} is taken: another PX4 instance "
                                                rf"{instance} is running"):
                sf._check_instance_free(instance)
        finally:
            s.close()
        sf._check_instance_free(instance)  # free again: no error
        return
    pytest.fail("no free UDP port in 14620..14639")
