"""ulog_io.read_ulog on every shared log, bad input, and time_sync (the clock-alignment module).

The frame conversions are checked on real data through physics: the specific
force rotated to ENU by the attitude, minus gravity, equals d(velocity)/dt; on
the ground it is +g up; d(position)/dt equals velocity; the mean PWM-derived
motor command equals the collective thrust command.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import need_log, shared_log, ulog_params

from twin_nodes.base import frames as F
from twin_nodes.logs import time_sync as TS
from twin_nodes.logs import ulog_io as U
from twin_nodes.base.errors import LogError
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.logs.ulog_write import write_px4_ulog

ALL_LOGS = ulog_params("real") + ulog_params("sitl")
AM = "actuator_motors.control[0..3]"
PWM0 = "actuator_outputs[0].output[0,1,2,3]"
#: file stem -> (duration from MANIFEST [s], motor source prefix)
EXPECTED = {
    "real_x500v2_mission_rtl": (80.0, PWM0),
    "real_s500_rcac_mission1": (58.4, PWM0),
    "real_s500_rcac_mission2": (40.5, PWM0),
    "real_quadx_v6c_climb35m": (70.4, AM),
    "real_quadx_v6c_mission_noload": (62.6, AM),
    "real_quadx_v6c_mission_2hops": (60.6, AM),
    "real_cubeorange_takeoff_land": (32.8, AM),
    "sitl_iris_takeoff_land": (31.1, AM),
    "px4sih_default_triangle": (104.9, AM),
    "px4sih_default_grid": (139.9, AM),
}
CORE = ("position_enu", "velocity_enu", "accel_enu", "attitude_q", "body_rates_flu", "motors",
        "throttle", "battery_v", "battery_a", "specific_force_flu", "gyro_flu",
        "setpoint_position_enu", "setpoint_velocity_enu", "setpoint_yaw_enu", "nav_state",
        "armed", "landed", "hover_thrust")

_CACHE: dict[Path, U.FlightLog] = {}


def load(path: Path) -> U.FlightLog:
    if path not in _CACHE:
        _CACHE[path] = read_ulog(path)
    return _CACHE[path]


# --------------------------------------------------------------------------- shared logs


@pytest.mark.parametrize("log", ALL_LOGS)
def test_reads_every_shared_log(log):
    path = need_log(log)
    t0 = time.perf_counter()
    fl = read_ulog(path)
    assert time.perf_counter() - t0 < 3.0
    _CACHE[path] = fl
    dur, motor_src = EXPECTED[path.stem]
    assert abs(fl.duration_s - dur) < 1.0, (fl.duration_s, dur)
    assert fl.n_motors == 4
    assert fl.require("motors").source.startswith(motor_src)
    assert fl.info["sys_name"] == "PX4" and "ver_sw" in fl.info
    assert isinstance(fl.params["MPC_THR_HOVER"], float)
    for name in CORE:
        s = fl.require(name)
        assert s.values.dtype == np.float64 and s.values.ndim == 2
        assert s.values.shape[0] == s.t_s.shape[0] > 0
        assert np.all(np.diff(s.t_s) > 0), name
        assert s.t_s[0] >= 0 and s.t_s[-1] <= fl.duration_s + 1e-9
        units, frame, _ = U.SERIES_SPEC[name]
        assert (s.units, s.frame) == (units, frame)
    q = fl.require("attitude_q").values
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    m = fl.require("motors").values
    assert np.all((m[np.isfinite(m)] >= 0) & (m[np.isfinite(m)] <= 1))
    assert fl.require("motors").values.shape[1] == 4


@pytest.mark.parametrize("log", ALL_LOGS)
def test_frames_and_scaling_consistent_with_physics(log):
    fl = load(need_log(log))
    a0, a1 = fl.airborne_interval()
    assert 0 <= a0 < a1 <= fl.duration_s
    t, d = fl.resample(["motors", "throttle", "position_enu", "velocity_enu", "attitude_q",
                        "specific_force_flu"], 10.0, a0 + 3, a1 - 3)
    # ENU z is up: the vehicle climbed more than 2 m above its lowest point
    z = fl.require("position_enu").values[:, 2]
    assert np.nanmax(d["position_enu"][:, 2]) - np.nanmin(z) > 2.0
    # d(position)/dt = velocity (same frame conversion for both)
    dpos = np.gradient(d["position_enu"], t, axis=0)
    assert np.all(np.nanmedian(np.abs(dpos - d["velocity_enu"]), axis=0) < 0.3)
    # specific force rotated FLU->ENU by the attitude, minus gravity = d(velocity)/dt
    f_enu = F.quat_rotate(d["attitude_q"], d["specific_force_flu"])
    resid = f_enu - [0.0, 0.0, 9.81] - np.gradient(d["velocity_enu"], t, axis=0)
    assert np.all(np.abs(np.nanmedian(resid, axis=0)) < 0.5)
    # the mean motor command is the collective thrust command
    mean_motor = np.nanmean(d["motors"], axis=1)
    assert abs(np.nanmedian(mean_motor - d["throttle"][:, 0])) < 0.02
    # on the ground before take-off the accelerometer reads +g up
    if a0 > 1.5:
        _, g = fl.resample(["attitude_q", "specific_force_flu"], 10.0, 0.5, a0 - 0.5)
        up = np.nanmedian(F.quat_rotate(g["attitude_q"], g["specific_force_flu"]), axis=0)
        assert np.allclose(up, [0, 0, 9.81], atol=0.3)


def test_stray_late_sample_does_not_inflate_duration():
    fl = load(shared_log("real", "real_s500_rcac_mission2.ulg"))
    assert 39.5 < fl.duration_s < 41.5  # pyulog's last_timestamp says 379 s
    topics = dict(((n, m), (c, r)) for n, m, c, r in
                  U.list_topics(shared_log("real", "real_s500_rcac_mission2.ulg")))
    assert topics[("mission", 0)][0] == 1
    assert 9.0 < topics[("vehicle_local_position", 0)][1] < 11.0
    assert 45 < topics[("vehicle_angular_velocity", 0)][1] < 55


def test_pwm_motor_channels_from_output_functions():
    """flugdrohne: PWM_AUX_FUNC5..8 = 101,102,104,103 -> ao[1] ch 4,5,7,6; the PWM route
    agrees with actuator_motors (median 0.0005)."""
    path = shared_log("real", "real_quadx_v6c_climb35m.ulg")
    ulog, _, _ = U._open_ulog(path, list(U.TOPICS))
    topics, _, _ = U._load_topics(ulog)
    warnings: list[str] = []
    s = U._motors_from_pwm(topics, U._ulog_params(ulog), 4, warnings)
    assert s is not None and warnings == []
    assert s.source.startswith("actuator_outputs[1].output[4,5,7,6] (PWM_AUX_FUNCn")
    am = load(path).require("motors").at(s.t_s)
    assert np.nanmedian(np.abs(s.values - am)) < 0.002


def test_sitl_airborne_groundtruth_and_esc():
    fl = load(shared_log("sitl", "px4sih_default_triangle.ulg"))
    a0, a1 = fl.airborne_interval()
    assert abs(a0 - 9.0) < 0.3 and abs(a1 - 101.9) < 0.3  # MANIFEST: take-off 9.0, landed 101.9
    t, d = fl.resample(["position_enu", "groundtruth_position_enu", "attitude_q",
                        "groundtruth_attitude_q"], 5.0, a0, a1)
    assert np.nanmax(np.linalg.norm(d["position_enu"] - d["groundtruth_position_enu"], axis=1)) < 1.5
    # tilt agrees closely (body up axis in ENU); EKF heading is off by ~4 deg (median)
    up_est = F.quat_rotate(d["attitude_q"], [0.0, 0.0, 1.0])
    up_true = F.quat_rotate(d["groundtruth_attitude_q"], [0.0, 0.0, 1.0])
    tilt_err = np.degrees(np.arccos(np.clip(np.sum(up_est * up_true, axis=1), -1, 1)))
    tilt_true = np.degrees(np.arccos(np.clip(up_true[:, 2], -1, 1)))
    assert np.percentile(tilt_true, 90) > 20.0  # the vehicle really tilts ...
    assert np.median(tilt_err) < 2.5 and np.percentile(tilt_err, 90) < 4.0  # ... and we agree
    assert np.degrees(np.median(F.quat_angle_between(d["attitude_q"],
                                                     d["groundtruth_attitude_q"]))) < 8.0

    iris = load(shared_log("real", "sitl_iris_takeoff_land.ulg"))
    esc = iris.require("esc_rpm")
    m = iris.require("motors").at(esc.t_s)
    ok = np.isfinite(m) & (m > 0.2)
    assert np.allclose(esc.values[ok] / m[ok], 6000.0, rtol=0.05)  # SITL rpm = control * 6000
    assert iris.airborne_intervals() == [pytest.approx((16.74, 28.13), abs=0.05)]


def test_two_hop_log_has_two_airborne_intervals_and_reset_warning():
    fl = load(shared_log("real", "real_quadx_v6c_mission_2hops.ulg"))
    iv = fl.airborne_intervals()
    assert len(iv) == 2 and iv[0][1] < iv[1][0]
    assert fl.airborne_interval() == (iv[0][0], iv[1][1])
    assert any("EKF reset" in w for w in fl.warnings)


def test_resample_holds_discrete_and_interpolates():
    fl = load(shared_log("real", "real_cubeorange_takeoff_land.ulg"))
    t, d = fl.resample(["position_enu", "landed", "armed", "attitude_q"], 20.0)
    assert np.allclose(np.diff(t), 0.05)
    assert set(np.unique(d["landed"][np.isfinite(d["landed"])])) <= {0.0, 1.0}
    assert np.isfinite(d["landed"]).all()  # re-stamped initial state + hold
    assert np.allclose(np.linalg.norm(d["attitude_q"], axis=1), 1.0)
    with pytest.raises(LogError, match=r"groundtruth_position_enu: expected series"):
        fl.resample(["groundtruth_position_enu"], 10.0)


# --------------------------------------------------------------------------- bad input


def test_missing_file(tmp_path):
    with pytest.raises(LogError, match=r"nope\.ulg: file: expected an existing ULog file"):
        read_ulog(tmp_path / "nope.ulg")


def test_not_a_ulog(tmp_path):
    p = tmp_path / "x.ulg"
    p.write_bytes(b"this is a CSV, not a ULog\n" * 3)
    with pytest.raises(LogError, match=r"x\.ulg: header: not a ULog: bad magic 74 68 69 73"):
        read_ulog(p)
    p.write_bytes(b"ULo")
    with pytest.raises(LogError, match=r"header: expected a 16-byte ULog header"):
        read_ulog(p)


def _synthetic(tmp_path: Path, name: str = "s.ulg", **extra) -> Path:
    n = 200
    t = (np.arange(n) * 10_000 + 5_000_000).astype(np.uint64)
    topics = {
        "vehicle_local_position": {"timestamp": t, "x": np.zeros(n), "y": np.zeros(n),
                                   "z": -np.linspace(0, 5, n), "vx": np.zeros(n),
                                   "vy": np.zeros(n), "vz": np.zeros(n)},
        "battery_status": {"timestamp": t[::10], "voltage_v": np.full(n // 10, 12.0),
                           "current_a": np.full(n // 10, -1.0)},
    }
    topics.update(extra)
    return write_px4_ulog(tmp_path / name, topics, {"MAV_TYPE": 2}, {})


def test_missing_topics_are_warnings(tmp_path):
    fl = read_ulog(_synthetic(tmp_path))
    assert "position_enu" in fl.series and "attitude_q" not in fl.series
    assert any(w.startswith("no vehicle_attitude in log: attitude_q unavailable") for w in fl.warnings)
    assert fl.n_motors == 4  # from MAV_TYPE 2
    assert np.all(np.isnan(fl.require("battery_a").values))  # -1 = unknown
    # height fallback for the airborne interval
    assert fl.airborne_interval()[0] > 0
    with pytest.raises(LogError, match=r"s\.ulg: attitude_q: expected series 'attitude_q'"):
        fl.require("attitude_q")


def test_no_local_position_is_an_error(tmp_path):
    p = write_px4_ulog(tmp_path / "b.ulg", {"battery_status": {
        "timestamp": np.arange(10, dtype=np.uint64) * 1000, "voltage_v": np.ones(10)}}, {}, {})
    with pytest.raises(LogError, match=r"b\.ulg: vehicle_local_position: expected at least one "
                                       r"sample .* found topics: battery_status"):
        read_ulog(p)


def test_truncated_real_log(tmp_path):
    src = shared_log("real", "real_cubeorange_takeoff_land.ulg")
    data = src.read_bytes()
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(data[: len(data) // 2])
    fl = read_ulog(cut)  # a cut data section loses the tail only
    assert 5.0 < fl.duration_s < load(src).duration_s - 5.0
    tiny = tmp_path / "tiny.ulg"
    tiny.write_bytes(data[:3000])  # inside the definitions section
    with pytest.raises(LogError, match=r"tiny\.ulg: vehicle_local_position: .*found no data "
                                       r"messages at all \(file of 3000 bytes: truncated"):
        read_ulog(tiny)


def test_prestart_and_stray_samples(tmp_path):
    """A sample before the header start is dropped (state topics: re-stamped to 0);
    one absurdly late sample is dropped with a warning."""
    n = 100
    t = (np.arange(n) * 100_000 + 1_000_000).astype(np.uint64)
    lpos_t = t.copy()
    lpos_t[-1] = 900_000_000  # stray: 900 s
    p = write_px4_ulog(tmp_path / "p.ulg", {
        "vehicle_local_position": {"timestamp": lpos_t, "x": np.arange(n, dtype=float),
                                   "y": np.zeros(n), "z": np.zeros(n)},
        "vehicle_status": {"timestamp": np.array([1_000_000, 3_000_000], np.uint64),
                           "arming_state": np.array([2, 1]), "nav_state": np.array([4, 3])},
        "vehicle_land_detected": {"timestamp": np.array([1_000_000, 2_000_000], np.uint64),
                                  "landed": np.array([True, False])},
    }, {}, {}, start_us=1_000_000)
    raw = bytearray(p.read_bytes())
    raw[8:16] = struct.pack("<Q", 1_500_000)  # move the log start after the first samples
    p.write_bytes(bytes(raw))
    fl = read_ulog(p)
    pos = fl.require("position_enu")
    assert pos.t_s[0] == 0.0 and len(pos) == n - 5 - 1  # 1.0..1.4 s and the stray dropped
    assert pos.t_s[-1] < 10.0 and fl.duration_s < 10.0
    assert any("far after the log end" in w for w in fl.warnings)
    armed = fl.require("armed")
    assert armed.t_s[0] == 0.0 and armed.values[0, 0] == 1.0  # state at log start kept
    landed = fl.require("landed")
    assert landed.t_s.tolist() == [0.0, 0.5] and landed.values[:, 0].tolist() == [1.0, 0.0]


def test_duplicate_timestamps_keep_last(tmp_path):
    t = np.array([1_000_000, 1_100_000, 1_100_000, 1_200_000], np.uint64)
    p = write_px4_ulog(tmp_path / "d.ulg", {"vehicle_local_position": {
        "timestamp": t, "x": np.array([0.0, 1.0, 2.0, 3.0]), "y": np.zeros(4), "z": np.zeros(4)}},
        {}, {})
    fl = read_ulog(p)
    pos = fl.require("position_enu")
    assert pos.t_s.tolist() == pytest.approx([0.0, 0.1, 0.2])
    assert pos.values[:, 1].tolist() == [0.0, 2.0, 3.0]  # NED x -> ENU y
    # said, not silent (issue 28)
    assert fl.data_warnings() == ["vehicle_local_position[0]: 1 duplicate stamp(s) of 4 (the same time as the "
                                  "sample before): kept the last of each"]


# --------------------------------------------------------------------------- time_sync


def test_common_grid():
    g = TS.common_grid(1.0, 2.0, 10.0)
    assert len(g) == 11 and g[0] == 1.0 and g[-1] == pytest.approx(2.0)
    with pytest.raises(ValueError, match=r"rate_hz: expected a finite rate > 0 Hz, got 0"):
        TS.common_grid(0, 1, 0)
    with pytest.raises(ValueError, match=r"t1: expected t1 >= t0"):
        TS.common_grid(2, 1, 10)


def test_interp_linear_nan_and_gaps():
    t = np.array([0.0, 1.0, 2.0, 3.0, 40.0, 41.0])
    v = np.array([0.0, 1.0, np.nan, 3.0, 40.0, 41.0])
    out = TS.interp_to(t, v, np.array([-1.0, 0.5, 1.0, 1.5, 3.0, 5.0, 40.5, 42.0]), max_gap_s=2.0)
    assert np.isnan(out[0]) and np.isnan(out[-1])  # outside
    assert out[1] == 0.5 and out[2] == 1.0  # on a sample next to a NaN: the sample
    assert np.isnan(out[3])  # next to NaN
    assert out[4] == 3.0
    assert np.isnan(out[5])  # inside the 37 s gap
    assert out[6] == 40.5
    # default gap threshold: 10 x median dt
    assert np.isnan(TS.interp_to(t, v, np.array([5.0]))[0])
    assert TS.interp_to(t, v, np.array([5.0]), max_gap_s=np.inf)[0] == pytest.approx(5.0)


def test_bin_mean_uses_every_sample_without_delay():
    """A 250 Hz signal onto a 50 Hz grid: each step is the mean of its five samples, so white noise
    drops by sqrt(5) (picking one sample per step keeps it all); a 2 Hz sine keeps its phase and
    sinc(2 Hz x 20 ms) of its amplitude; NaN samples are skipped, an empty step is interpolated."""
    rng = np.random.default_rng(3)
    ts = np.arange(0.0, 60.0, 0.004)
    noise = rng.normal(0.0, 1.7, ts.size)
    t = TS.common_grid(1.0, 59.0, 50.0)
    picked = TS.interp_to(ts, noise, t)
    mean = TS.bin_mean_to(ts, noise, t)
    assert np.std(picked) == pytest.approx(1.7, rel=0.05)
    assert np.std(mean) == pytest.approx(1.7 / np.sqrt(5), rel=0.05)
    sine = np.sin(2 * np.pi * 2.0 * ts)
    got = TS.bin_mean_to(ts, np.column_stack([sine, 2 * sine]), t)
    ref = np.sin(2 * np.pi * 2.0 * t)
    gain = float(got[:, 0] @ ref / (ref @ ref))
    assert gain == pytest.approx(np.sinc(2.0 * 0.02), abs=2e-3) and gain > 0.99
    assert np.max(np.abs(got[:, 0] - gain * ref)) < 0.01     # no delay: in phase
    assert np.allclose(got[:, 1], 2 * got[:, 0])
    # a NaN sample is left out of its step; a step with no sample falls back to linear interpolation
    v = ts.copy()
    v[(ts > 10.0) & (ts < 10.005)] = np.nan
    keep = ~((ts > 20.0) & (ts < 20.03))
    out = TS.bin_mean_to(ts[keep], v[keep], t)
    assert np.all(np.isfinite(out))
    assert np.allclose(out, t, atol=0.0041)     # a line: on it, or one sample step off where samples are missing
    with pytest.raises(ValueError, match=r"t_dst: expected an increasing grid"):
        TS.bin_mean_to(ts, v, np.array([1.0]))


def test_interp_previous_and_nearest_2d():
    t = np.array([0.0, 1.0, 5.0])
    v = np.array([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0]])
    prev = TS.interp_to(t, v, np.array([-0.5, 0.0, 0.9, 4.9, 7.0]), kind="previous")
    assert np.isnan(prev[0]).all()
    assert prev[1:, 0].tolist() == [1.0, 1.0, 2.0, 3.0]  # holds after the last sample
    near = TS.interp_to(t, v, np.array([0.4, 0.6]), kind="nearest")
    assert near[:, 1].tolist() == [10.0, 20.0]
    with pytest.raises(ValueError, match=r"kind: expected one of"):
        TS.interp_to(t, v, t, kind="cubic")
    with pytest.raises(ValueError, match=r"t_src: expected strictly increasing"):
        TS.interp_to(np.array([0.0, 0.0]), np.zeros(2), t)
    with pytest.raises(ValueError, match=r"values: expected shape \(3,\) or \(3, k\)"):
        TS.interp_to(t, np.zeros(4), t)


@pytest.mark.parametrize("kind", ["slerp", "nlerp"])
def test_interp_quaternion_sign_consistent(kind):
    q0 = F.quat_from_euler(0.0, 0.0, 0.0)
    q1 = -F.quat_from_euler(0.0, 0.0, 1.0)  # same as yaw 1 rad, opposite sign
    out = TS.interp_to(np.array([0.0, 1.0]), np.vstack([q0, q1]), np.linspace(0, 1, 5), kind=kind)
    yaw = F.euler_from_quat(out)[:, 2]
    assert np.all(np.diff(yaw) > 0) and yaw[-1] == pytest.approx(1.0)  # shortest path
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", out[1:], out[:-1]) > 0)  # continuous sign
    if kind == "slerp":
        assert yaw[2] == pytest.approx(0.5)


def test_align_series_overlap():
    a = U.Series(np.linspace(0, 10, 101), np.arange(101.0)[:, None], "m", "ENU", "a")
    b = (np.linspace(5, 20, 16), np.arange(16.0), "previous")
    t, va, vb = TS.align(a, b, 2.0)
    assert t[0] == 5.0 and t[-1] == 10.0
    assert va[:, 0].tolist() == pytest.approx((t * 10).tolist())
    assert vb.tolist() == pytest.approx(np.floor(t - 5).tolist())
    with pytest.raises(ValueError, match=r"do not overlap"):
        TS.align((np.array([0.0, 1.0]), np.zeros(2)), (np.array([2.0, 3.0]), np.zeros(2)), 1.0)


def test_pwm_route_with_functions_and_thrust_model(tmp_path):
    """No actuator_motors: Motor1..4 on AUX channels 3,4,2,1 (PWM_AUX_FUNCn), per-channel
    MIN/MAX, THR_MDL_FAC 0.3 undone, 900 us and disarmed samples -> NaN."""
    n = 50
    t = (np.arange(n) * 20_000 + 1_000_000).astype(np.uint64)
    u = np.linspace(0.1, 0.9, n)  # normalised thrust we expect back
    f = 0.3
    s_out = (-(1 - f) + np.sqrt((1 - f) ** 2 + 4 * f * u)) / (2 * f)  # PX4's inverse model
    out = np.zeros((n, 16))
    lo = {3: 1100.0, 4: 1000.0, 2: 1050.0, 1: 1000.0}  # 1-based AUX channel -> PWM_AUX_MINn
    for motor, ch in enumerate((3, 4, 2, 1)):
        out[:, ch - 1] = lo[ch] + (2000.0 - lo[ch]) * s_out
    out[:5, :4] = 900.0  # disarm value
    out[:, 7] = 1500.0  # a servo
    params = {"PWM_AUX_FUNC3": 101, "PWM_AUX_FUNC4": 102, "PWM_AUX_FUNC2": 103,
              "PWM_AUX_FUNC1": 104, "THR_MDL_FAC": f, "CA_ROTOR_COUNT": 4}
    for ch, v in lo.items():
        params[f"PWM_AUX_MIN{ch}"] = int(v)
        params[f"PWM_AUX_MAX{ch}"] = 2000
    p = write_px4_ulog(tmp_path / "pwm.ulg", {
        "vehicle_local_position": {"timestamp": t, "x": np.zeros(n), "y": np.zeros(n), "z": np.zeros(n)},
        "actuator_outputs:1": {"timestamp": t, "noutputs": np.full(n, 8), "output": out},
        "vehicle_status": {"timestamp": t[[0, 3, 45]], "arming_state": np.array([1, 2, 1]),
                           "nav_state": np.array([4, 4, 4])},
    }, params, {})
    fl = read_ulog(p)
    m = fl.require("motors")
    assert m.source.startswith("actuator_outputs[1].output[2,3,1,0] (PWM_AUX_FUNCn")
    assert "THR_MDL_FAC 0.3 undone" in m.source
    assert np.isnan(m.values[:5]).all() and np.isnan(m.values[45:]).all()
    np.testing.assert_allclose(m.values[5:45], np.repeat(u[5:45, None], 4, axis=1), atol=2e-6)


# --------------------------------------------------------------------------- damaged time (issue 12)
# Logs from the project's own writer, byte-edited in file order (tests/ulog_cases.py).

import signal  # noqa: E402

import ulog_cases as UC  # noqa: E402

DAMAGE_MARKERS = ("time jump", "go backwards", "before the log start", "truncated", "pause", "gap(s)")


@pytest.fixture()
def small(tmp_path) -> tuple[bytes, U.FlightLog]:
    p = UC.small_flight(tmp_path / "good.ulg")
    fl = read_ulog(p)
    assert not any(m in w for w in fl.warnings for m in DAMAGE_MARKERS), fl.warnings
    return p.read_bytes(), fl


def _write(tmp_path: Path, data: bytes, name: str = "bad.ulg") -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


@pytest.mark.parametrize("gap_us", [3600 * 10**6, 2**40, 2**62], ids=["1h", "2^40us", "2^62us"])
def test_time_jump_keeps_the_longest_part(tmp_path, small, gap_us):
    """A clock jump (seen after GPS time jumps) cuts the log; the longer part is kept and its
    times re-based, so grids follow the flight's 20 s, not the gap (the old loader spanned
    the gap: `compare --offline` asked for 24 GB)."""
    data, good = small
    for frac, after in ((0.3, True), (0.7, False)):
        fl = read_ulog(_write(tmp_path, UC.with_gap(data, gap_us, frac)))
        jumps = [w for w in fl.warnings if w.startswith("log: time jump of ")]
        assert len(jumps) == 1, fl.warnings
        assert float(jumps[0].split()[4]) == pytest.approx(gap_us * 1e-6, rel=1e-5, abs=0.05)
        assert sum(w.startswith("log: kept the longest consistent part") for w in fl.warnings) == 1
        assert 12.0 < fl.duration_s < 15.0, fl.duration_s
        pos, ref = fl.require("position_enu"), good.require("position_enu")
        assert np.all(np.diff(pos.t_s) > 0) and pos.t_s[0] < 0.05
        if after:  # the last 70 %, re-based to the first sample of any topic after the jump
            np.testing.assert_array_equal(pos.values, ref.values[-len(pos):])
            assert fl.start_us == UC.T0_US + gap_us + int(round((ref.t_s[-len(pos)] - pos.t_s[0]) * 1e6))
        else:
            np.testing.assert_array_equal(pos.values, ref.values[:len(pos)])
            assert fl.start_us == UC.T0_US
        assert fl.require("armed").values[:, 0].max() == 1.0  # the state at the cut is carried over
        t, _ = fl.resample(["position_enu", "attitude_q", "motors"], 250.0)
        assert t.size <= 250 * 15


def test_backwards_time_keeps_samples_in_order(tmp_path, small):
    """A clock step back: the longest run in time order is kept, the rest dropped with one
    warning per topic (the old loader sorted them into each other, silently)."""
    data, good = small
    fl = read_ulog(_write(tmp_path, UC.with_backwards(data, 5_000_000)))
    back = [w for w in fl.warnings if "timestamps go backwards" in w]
    assert any(w.startswith("vehicle_local_position[0]: timestamps go backwards 1 time(s)") for w in back)
    assert all("dropped" in w for w in back)
    pos, ref = fl.require("position_enu"), good.require("position_enu")
    assert np.all(np.diff(pos.t_s) > 0) and 600 <= len(pos) < len(ref)
    # every kept sample is an original sample, in file order (east = 0.02 sin(t) is unique)
    rows = [int(np.flatnonzero(np.all(ref.values == v, axis=1))[0]) for v in pos.values]
    assert np.all(np.diff(rows) > 0)
    # one splice where the clock stepped back, not samples of two seconds mixed (the old sort: 250 jumps)
    assert np.count_nonzero(np.abs(np.diff(pos.values[:, 1])) > 0.002) <= 1


def test_backwards_before_the_log_start_is_reported(tmp_path, small):
    data, _ = small
    fl = read_ulog(_write(tmp_path, UC.with_backwards(data, 30_000_000)))
    pre = [w for w in fl.warnings if "stamped before the log start" in w]
    assert any(w.startswith("vehicle_local_position[0]: dropped 500 sample(s)") for w in pre), fl.warnings
    assert fl.duration_s < 10.0


def test_truncated_log_is_named_truncated(tmp_path, small):
    data, good = small
    fl = read_ulog(_write(tmp_path, UC.truncated(data, 0.7)))
    assert fl.warnings[0].startswith("file truncated: the record at byte "), fl.warnings
    assert 10.0 < fl.duration_s < good.duration_s
    at = [r for r in UC.records(data) if r[1] == "D"][300][0]
    fl = read_ulog(_write(tmp_path, data[: at + 2]))  # cut inside a record header
    assert fl.warnings[0].startswith(f"file truncated: the record at byte {at} of {at + 2} is cut short")
    fl = read_ulog(_write(tmp_path, data[:at]))  # cut between records: indistinguishable from a whole log
    assert not any("truncated" in w for w in fl.warnings)


def test_corrupt_format_definitions_are_refused_fast(tmp_path, small):
    """A format nesting a 65535-array in a 65535-array made pyulog expand 4e9 fields (hang)."""
    data, _ = small
    recs = list(UC.records(data))
    f_off = next(r[0] for r in recs if r[1] == "F")
    a_off = next(r[0] for r in recs if r[1] == "A")

    def rec(t, payload):
        return struct.pack("<HB", len(payload), ord(t)) + payload

    bomb = rec("F", b"bomb_a:uint64_t timestamp;bomb_b[65535] x;") + rec("F", b"bomb_b:float[65535] y;")
    sub = rec("A", struct.pack("<BH", 0, 999) + b"bomb_a")
    p = _write(tmp_path, data[:f_off] + bomb + data[f_off:a_off] + sub + data[a_off:])

    def alarm(*_):
        raise TimeoutError("read_ulog took more than 10 s")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(10)
    try:
        with pytest.raises(LogError, match=r"bad\.ulg: definitions: expected ULog message formats of at most "
                                           r"65535 bytes: format 'bomb_a' expands"):
            read_ulog(p)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def test_pauses_and_topic_gaps_are_reported(tmp_path, small):
    data, _ = small
    fl = read_ulog(_write(tmp_path, UC.with_gap(data, 10_000_000)))  # 10 s: a pause, not a jump
    assert any(w.startswith("log: 1 pause(s) longer than 2 s") for w in fl.warnings), fl.warnings
    assert not any("time jump" in w for w in fl.warnings) and 29.0 < fl.duration_s < 31.0
    topics = UC.small_topics()
    lp = topics["vehicle_local_position"]
    s = (lp["timestamp"] - UC.T0_US) * 1e-6
    keep = (s < 5.0) | (s > 12.0)
    topics["vehicle_local_position"] = {k: v[keep] for k, v in lp.items()}
    p = write_px4_ulog(tmp_path / "hole.ulg", topics, {"CA_ROTOR_COUNT": 4}, {}, start_us=UC.T0_US)
    fl = read_ulog(p)
    assert any(w.startswith("vehicle_local_position[0]: 1 gap(s) longer than 5 s without samples, "
                            "longest 7.04 s at t = 4.980 s") for w in fl.warnings), fl.warnings


def test_a_gap_sized_grid_is_refused_with_the_file_named():
    """The shared guard: no uniform grid of more than MAX_GRID_POINTS samples, whoever asks."""
    with pytest.raises(LogError, match=r"^f\.ulg: time grid: expected at most 10000000 samples "
                                       r"\(11\.1 h at 250 Hz\), the data spans 0\.\.1\.09951e\+06 s"):
        TS.common_grid(0.0, 2.0**40 * 1e-6, 250.0, source="f.ulg")
    assert TS.check_grid(0.0, 10.0, 250.0) == 2501
    log = U.FlightLog(path="g.ulg", start_us=0, duration_s=2.0**40 * 1e-6, params={}, info={}, warnings=[],
                      n_motors=4, series={"position_enu": U.Series(np.array([0.0, 2.0**40 * 1e-6]),
                                                                   np.zeros((2, 3)), "m", "ENU", "test")})
    with pytest.raises(LogError, match=r"^g\.ulg: time grid: "):
        log.resample(["position_enu"], 250.0)


@pytest.mark.parametrize("log", ALL_LOGS)
def test_shared_logs_have_no_time_damage(log):
    """Guard: the repairs never fire on real flights (their warnings are unchanged)."""
    fl = read_ulog(need_log(log))
    assert not [w for w in fl.warnings if any(m in w for m in DAMAGE_MARKERS)]


def test_data_warnings_are_the_damage_reports(tmp_path, small):
    data, good = small
    assert good.data_warnings() == []
    fl = read_ulog(_write(tmp_path, UC.truncated(UC.with_gap(data, 2**40), 0.9)))
    dw = fl.data_warnings()
    assert dw[0].startswith("file truncated") and any(w.startswith("log: time jump") for w in dw)
    assert all(w in fl.warnings for w in dw) and not any(w.startswith("no ") for w in dw)


# --------------------------------------------------------------------------- issue 28: every value checked where it enters


def test_repeated_stamps_keep_the_same_stretch_in_every_topic(tmp_path, small):
    """The clock steps back onto stamps it already used (every stamp of the second half repeats one of
    the first): each topic keeps the part logged first, so all topics describe the same stretch of
    flight, and says so.  The old longest-run rule spliced each topic at a point of its own (equal
    runs), mixing climb and landing: motors P75 36.7 % instead of 4 %."""
    data, good = small
    fl = read_ulog(_write(tmp_path, UC.with_repeated_stamps(data)))
    back = [w for w in fl.data_warnings() if "timestamps go backwards" in w]
    assert any(w.startswith("vehicle_local_position[0]: timestamps go backwards 1 time(s)") and
               "duplicate stamps of kept samples" in w for w in back), fl.warnings
    for name in ("position_enu", "attitude_q", "motors", "body_rates_flu", "throttle"):
        s, ref = fl.require(name), good.require(name)
        assert 0.4 * len(ref) < len(s) < 0.6 * len(ref), name
        # the first half as logged (a few samples stamped past its end may follow, the longest run; so
        # may the on-change disarm state, stamped 9 s, which makes the motors NaN from there)
        k = int(np.searchsorted(ref.t_s, 8.9))
        np.testing.assert_array_equal(s.t_s[:k], ref.t_s[:k], err_msg=name)
        np.testing.assert_array_equal(s.values[:k], ref.values[:k], err_msg=name)
        assert np.all(np.diff(s.t_s) > 0) and len(s) - k <= 60, name


def test_inf_positions_are_dropped_with_a_warning(tmp_path):
    """+-inf positions for 2 s: those samples are dropped and said (they gave Z RMSE 5.7e36 m)."""
    fl = read_ulog(UC.edited_flight(tmp_path / "inf.ulg", UC.inf_positions))
    pos = fl.require("position_enu")
    assert np.all(np.isfinite(pos.values)) and len(pos) == 900
    w = [w for w in fl.data_warnings() if w.startswith("position_enu (vehicle_local_position.x,y,z): dropped 100 "
                                                       "of 1000 samples, 100 not finite (+-inf), at t = 9.00..10.98 s")]
    assert len(w) == 1, fl.warnings


def test_out_of_range_values_are_refused_or_repaired(tmp_path):
    """Motor outputs x1000 (P75 56 358 %) and all-zero quaternions are refused in one line naming the
    file, the PX4 field and what was expected; a few such samples are dropped with a warning."""
    p = UC.edited_flight(tmp_path / "m.ulg", UC.motors_x1000)
    with pytest.raises(LogError, match=r"m\.ulg: actuator_motors\.control\[0\.\.3\]: expected normalised motor "
                                       r"outputs in \[-1, 1\] \(NaN = stopped\); 900 of 1000 samples are not"):
        read_ulog(p)
    p = UC.edited_flight(tmp_path / "q.ulg", UC.zero_quaternions)
    with pytest.raises(LogError, match=r"q\.ulg: vehicle_attitude\.q: expected unit quaternions .*all zero"):
        read_ulog(p)

    def some(topics):
        c = topics["actuator_motors"]["control"]
        c[100:110] *= 1000.0
        topics["vehicle_attitude"]["q"][200:205] = 0.0
        topics["vehicle_local_position"]["vx"][300:303] = 1e4

    fl = read_ulog(UC.edited_flight(tmp_path / "s.ulg", some))
    assert len(fl.require("motors")) == 990 and np.nanmax(fl.require("motors").values) < 1.0
    assert len(fl.require("attitude_q")) == 995 and len(fl.require("velocity_enu")) == 997
    dw = fl.data_warnings()
    assert any(w.startswith("motors (actuator_motors.control[0..3]): dropped 10 of 1000 samples, 10 out of range")
               for w in dw), dw
    assert any(w.startswith("attitude_q (vehicle_attitude.q): dropped 5 of 1000 samples") for w in dw), dw
    assert any(w.startswith("velocity_enu (vehicle_local_position.vx,vy,vz): dropped 3 of 1000") for w in dw), dw
