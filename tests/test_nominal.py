"""``rotortwin params from-ulog``: the nominal twin built from a PX4 log's own parameters and flight.

Checked on PX4 SIH flights (real PX4 firmware) whose truth is known: the layout and spin must be
exact, the maximum thrust within 5 %, the motor lag and drag close to SIH's; no SIH_* entry is read
(the sitl_effects logs have them removed, and the code never looks for them)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from conftest import shared_log
from twin_nodes.cli import main
from twin_nodes.identify.nominal import nominal_from_log
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.logs.ulog_write import write_px4_ulog
from twin_nodes.vehicle.params import load_params, shipped
from twin_nodes.vehicle.px4_params import normalised_mix, rotor_layout

SIH_FLIGHTS = [("sitl", "px4sih_default_triangle.ulg"), ("sitl", "px4sih_default_grid.ulg"),
               ("sitl_effects", "e07/flight.ulg"), ("sitl_effects", "e08/flight.ulg")]


@pytest.fixture(scope="module", params=SIH_FLIGHTS, ids=lambda p: p[1].split("/")[0].replace(".ulg", ""))
def sih_nominal(request):
    sub, name = request.param
    log = read_ulog(shared_log(sub, name))
    assert not any(k.startswith("SIH_") for k in log.params) or sub == "sitl"
    # the code never reads SIH_*: drop them so the test proves it
    log.params = {k: v for k, v in log.params.items() if not k.startswith("SIH_")}
    return nominal_from_log(log, mass_kg=1.0)


def test_sih_geometry_and_spin_exact(sih_nominal):
    truth = shipped("px4_sih_quadx").rotors
    r = sih_nominal.params.rotors
    np.testing.assert_allclose(r.x_flu_m, truth.x_flu_m, atol=1e-6)
    np.testing.assert_allclose(r.y_flu_m, truth.y_flu_m, atol=1e-6)
    assert tuple(r.direction) == tuple(truth.direction)


def test_sih_max_thrust_within_5_percent(sih_nominal):
    assert sih_nominal.params.rotors.thrust_max_n == pytest.approx(5.0, rel=0.05)


def test_sih_motor_lag_and_drag(sih_nominal):
    r = sih_nominal.params.rotors
    assert abs(r.tau_up_s - 0.05) <= 0.02                     # SIH_T_TAU 0.05 s, scan step 0.01 s
    effects = dict(sih_nominal.params.effects)
    assert "linear_drag" in effects                           # SIH_KDV 1.0 N/(m/s)
    assert dict(effects["linear_drag"])["k_n_s_m"] == pytest.approx(1.0, rel=0.2)
    # isotropic, as SIH's (pm18's horizontal-only nominal drag was taken back: it moved the twin's yaw split on
    # real_cubeorange_takeoff_land to 0.23 % of full output, test_static_trims' bar is 0.1 %; docs/corpus.md)
    assert dict(effects["linear_drag"]).get("vertical", 1.0) == 1.0
    # SIH's drag acts at the centre of mass on the ground velocity, in still air: no drag height, no wind
    assert "rotor_drag" not in effects and "wind" not in effects
    assert list(r.z_flu_m) == [0.0] * r.count
    assert "h " in sih_nominal.sources["effects.linear_drag"] and "not included" in sih_nominal.sources["effects.wind"]


def _level_flight(seed: int, n: int = 6000, rate: float = 50.0):
    """Level flight turning through 360 deg while flying 0-5 m/s: body-frame unit vectors of east and
    north, the ground velocity (ENU) and its body-frame view."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    yaw = 2 * np.pi * t / t[-1] + 0.3 * np.sin(0.7 * t)
    q = np.column_stack([np.cos(yaw / 2), 0 * t, 0 * t, np.sin(yaw / 2)])
    v = np.column_stack([4 * np.sin(0.21 * t) + rng.normal(0, 0.05, n), 3 * np.cos(0.13 * t), 0 * t])
    return t, q, v


def test_wind_and_drag_height_recovered_on_synthetic_flight():
    """f_b = -(k/m) R^T (v - w) + bias with the heading turning: the steady wind is found; the roll and
    pitch moments holding the drag moment h k v_air give its height h."""
    from twin_nodes.identify.nominal import _drag_height, _wind
    from twin_nodes.identify.regression import RotorGeometry, fit_linear, world_to_body

    t, q, v = _level_flight(1)
    n = t.size
    rng = np.random.default_rng(2)
    m, k, w = 1.5, 0.45, np.array([2.0, -1.0, 0.0])
    e_b = world_to_body(q, np.tile([1.0, 0, 0], (n, 1)))
    n_b = world_to_body(q, np.tile([0, 1.0, 0], (n, 1)))
    v_b = world_to_body(q, v)
    v_air = world_to_body(q, v - w)
    f = -(k / m) * v_air[:, :2] + [0.05, -0.03] + rng.normal(0, 0.05, (n, 2))
    z, o = np.zeros(n), np.ones(n)
    X = np.vstack([np.column_stack([-v_b[:, 0], e_b[:, 0], n_b[:, 0], o, z]),
                   np.column_stack([-v_b[:, 1], e_b[:, 1], n_b[:, 1], z, o])])
    hfit = fit_linear(X, np.concatenate([f[:, 0], f[:, 1]]), ["kd/m", "kd/m*w_e", "kd/m*w_n", "bias_x", "bias_y"])
    we, wn, wse = _wind(hfit)
    assert (we, wn) == (pytest.approx(2.0, abs=0.05), pytest.approx(-1.0, abs=0.05)) and wse < 0.05
    assert hfit["kd/m"] == pytest.approx(k / m, rel=0.02)
    # still air: nothing found
    f0 = -(k / m) * v_b[:, :2] + rng.normal(0, 0.05, (n, 2))
    assert _wind(fit_linear(X, np.concatenate([f0[:, 0], f0[:, 1]]), list(hfit.names))) is None

    # rotational: I alpha = M_cmd + M_aero, M_aero = (h k va_y, -h k va_x); commands carry white noise
    geom = RotorGeometry.quad_x(0.25)
    h, ixx, iyy, t_max = 0.12, 0.03, 0.035, 8.0
    alpha = np.column_stack([np.sin(1.3 * t), np.cos(0.9 * t), 0 * t]) * 2.0
    rates = np.column_stack([np.sin(0.5 * t), np.cos(0.4 * t), 0 * t]) * 0.3
    m_cmd = np.column_stack([ixx * alpha[:, 0] - h * k * v_air[:, 1], iyy * alpha[:, 1] + h * k * v_air[:, 0]])
    # per-rotor thrust units that produce these moments about a hover thrust (quad X: y_i/l, -x_i/l)
    A = np.column_stack([geom.y_flu_m, -geom.x_flu_m]).T  # (2, 4)
    T = 0.25 * m * 9.81 + m_cmd @ np.linalg.pinv(A).T
    units = T / t_max + rng.normal(0, 0.002, T.shape)
    got, note = _drag_height(alpha, rates, units, geom, t_max, v_air, k, geom.arm_length_m)
    assert got == pytest.approx(h, rel=0.05) and "mm" in note
    # no drag moment: not significant (or below 5 % of the arm), nothing returned
    m0 = np.column_stack([ixx * alpha[:, 0], iyy * alpha[:, 1]])
    units0 = (0.25 * m * 9.81 + m0 @ np.linalg.pinv(A).T) / t_max + rng.normal(0, 0.002, T.shape)
    assert _drag_height(alpha, rates, units0, geom, t_max, v_air, k, geom.arm_length_m)[0] is None


def test_sih_inertia_within_15_percent(sih_nominal):
    """SIH_IXX/IYY/IZZ 0.025/0.025/0.030; Izz rests on the assumed km 0.02 m (SIH's Q_MAX/T_MAX is
    0.02, stated as an assumption in the header)."""
    ixx, iyy, izz = np.diag(sih_nominal.params.inertia)
    assert ixx == pytest.approx(0.025, rel=0.15)
    assert iyy == pytest.approx(0.025, rel=0.15)
    assert izz == pytest.approx(0.030, rel=0.15)
    assert "identified" in sih_nominal.sources["vehicle.ixx_kg_m2"]
    assert "ASSUMED" in sih_nominal.sources["rotors.km_m"]


def test_sih_inertia_change_is_seen():
    """e05 flies SIH_IXX/IYY 0.0325 (x1.3): the nominal built from it must say so within 15 %."""
    log = read_ulog(shared_log("sitl_effects", "e05/flight.ulg"))
    ixx, iyy, _ = np.diag(nominal_from_log(log, mass_kg=1.0).params.inertia)
    assert ixx == pytest.approx(0.0325, rel=0.15) and iyy == pytest.approx(0.0325, rel=0.15)


def test_every_value_has_a_source(sih_nominal):
    s = sih_nominal.sources
    for key in ("vehicle.mass_kg", "rotors.thrust_max_n", "rotors.tau_up_s/tau_down_s", "vehicle.ixx_kg_m2",
                "vehicle.izz_kg_m2", "rotors.km_m", "controller (rate loop)"):
        assert s[key]
    assert "--mass-kg" in s["vehicle.mass_kg"]


def test_controller_uses_the_logs_gains(sih_nominal):
    c = sih_nominal.params.controller
    assert c["roll_p_1_s"] == pytest.approx(4.0)              # MC_ROLL_P in the SIH airframe (default 6.5)
    assert c["xy_p_1_s"] == pytest.approx(0.95)
    assert c["rate_p_1_s"] > 0 and c["yawrate_p_1_s"] > 0


def test_normalised_mix_matches_px4_quad_x():
    """PX4's allocation on a square quad X: unit roll/pitch torque moves each motor by 1/sqrt(2),
    unit yaw by 1 (ControlAllocationPseudoInverse normalisation)."""
    a = 0.2
    mix = normalised_mix(np.array([a, -a, a, -a]), np.array([-a, a, a, -a]), np.array([1, 1, -1, -1]), 0.05)
    np.testing.assert_allclose(np.abs(mix[:, 0]), 1 / math.sqrt(2), atol=1e-12)
    np.testing.assert_allclose(np.abs(mix[:, 1]), 1 / math.sqrt(2), atol=1e-12)
    np.testing.assert_allclose(np.abs(mix[:, 2]), 1.0, atol=1e-12)
    # roll right (FLU -x moment is left-wing-down...): the left motors (y > 0) push harder for +Mx
    assert np.all(np.sign(mix[:, 0]) == np.sign([-a, a, a, -a]))


def test_normalised_layout_of_an_unknown_airframe_takes_the_class_arm():
    """(issue 24 C7; was: asks for --arm-m) the quad class's ASSUMED arm, said; --arm-m wins."""
    params = {"SYS_AUTOSTART": 4321, "CA_ROTOR_COUNT": 4}
    for i, (x, y) in enumerate([(1, 1), (-1, -1), (1, -1), (-1, 1)]):
        params.update({f"CA_ROTOR{i}_PX": x, f"CA_ROTOR{i}_PY": y})
    lay = rotor_layout(params, "x.ulg")
    assert math.hypot(lay.x_flu_m[0], lay.y_flu_m[0]) == pytest.approx(0.25)
    assert "ASSUMED 0.25 m arm" in lay.source
    lay = rotor_layout(params, "x.ulg", arm_m=0.3)
    assert math.hypot(lay.x_flu_m[0], lay.y_flu_m[0]) == pytest.approx(0.3)


def _tiny_log(path, params):
    t = np.arange(0, 5e6, 2e4, dtype=np.uint64) + 1_000_000
    z = np.zeros(t.size)
    topics = {"vehicle_attitude": {"timestamp": t, "q[0]": np.ones(t.size), "q[1]": z, "q[2]": z, "q[3]": z},
              "vehicle_local_position": {"timestamp": t, "x": z, "y": z, "z": -np.linspace(0, 5, t.size),
                                         "vx": z, "vy": z, "vz": z}}
    write_px4_ulog(str(path), topics, params, {"sys_name": "test"})


def test_from_ulog_unknown_airframe_is_one_line_exit_2(tmp_path, capsys):
    log = tmp_path / "old.ulg"
    _tiny_log(log, {"SYS_AUTOSTART": 9999, "MAV_TYPE": 2})
    out = tmp_path / "p.yaml"
    assert main(["params", "from-ulog", str(log), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "CA_ROTOR_COUNT" in err and "--params" in err and "9999" in err
    assert not out.exists()


def test_from_ulog_refuses_to_overwrite_its_input(tmp_path, capsys):
    log = tmp_path / "f.ulg"
    _tiny_log(log, {"SYS_AUTOSTART": 4001})
    before = log.read_bytes()
    assert main(["params", "from-ulog", str(log), "--out", str(log)]) == 2
    assert "not an input of the command" in capsys.readouterr().err
    assert log.read_bytes() == before


def test_from_ulog_cli_writes_a_valid_file(tmp_path):
    out = tmp_path / "sih.yaml"
    assert main(["params", "from-ulog", str(shared_log("sitl", "px4sih_default_grid.ulg")), "--mass-kg", "1.0",
                 "--out", str(out)]) == 0
    vp = load_params(out)
    assert vp.rotors.count == 4
    text = out.read_text()
    assert "ASSUMED" in text and "identified" in text and "log parameter" in text
    assert yaml.safe_load(text)["/**"]["ros__parameters"]["controller"]["roll_p_1_s"] == pytest.approx(4.0)


def test_yaw_rate_gain_uses_the_vehicles_km_and_pxs_mix():
    """PX4's mix is shaped by its CA_ROTORn_KM (0.05 on every shared log); the yaw moment those motor
    changes make is the vehicle's km (the from-log twin's 0.02, which its Izz was identified against).
    The yaw gain scales with the physical km alone; roll/pitch do not depend on it."""
    from twin_nodes.vehicle.px4_params import RateGainsPx4, rate_gains_physical
    a = 0.25 / np.sqrt(2)
    x, y = np.array([a, -a, a, -a]), np.array([a, -a, -a, a])
    d = np.array([-1, -1, 1, 1])
    px4 = RateGainsPx4.from_params({"MC_YAWRATE_P": 0.2, "MC_ROLLRATE_P": 0.15, "MC_PITCHRATE_P": 0.15})
    args = (px4, x, y, d, 0.05, 6.0, (0.02, 0.02, 0.03))
    same = rate_gains_physical(*args)
    twin = rate_gains_physical(*args, km_physical_m=0.02)
    assert twin["yawrate_p_1_s"] == pytest.approx(same["yawrate_p_1_s"] * 0.02 / 0.05, rel=1e-9)
    assert twin["yawrate_i_1_s2"] == pytest.approx(same["yawrate_i_1_s2"] * 0.4, rel=1e-9)
    assert twin["rate_p_1_s"] == same["rate_p_1_s"] and twin["rate_d"] == same["rate_d"]


def test_a_log_that_is_no_flight_is_refused_in_one_line(tmp_path):
    """nominal_from_log checks the flight first (issue 28): a log that never left the ground names which, in
    one LogError line.  A log without GPS (the fleet's 21 Jun log_59 and log_65 ended in ``ValueError: need
    more samples than coefficients``) is built on what it has since issue 24.5: no horizontal drag or wind,
    each said in the header."""
    import ulog_cases as C
    from twin_nodes.base.errors import LogError

    p = C.edited_flight(tmp_path / "never_airborne.ulg", C.never_airborne)  # with the quad X rotor positions
    with pytest.raises(LogError, match=r"vehicle_land_detected\.landed: never airborne"):
        nominal_from_log(read_ulog(p), mass_kg=1.5)
    p = C.edited_flight(tmp_path / "no_gps.ulg", C.no_horizontal_velocity)
    nom = nominal_from_log(read_ulog(p), mass_kg=1.5)
    assert "no horizontal velocity" in nom.sources["effects.wind"]
    assert not {"linear_drag", "rotor_drag", "wind"} & set(nom.params.effect_dict)


def test_a_flight_whose_velocity_is_unknown_for_a_while_still_builds():
    """PX4 logs NaN velocity while its horizontal estimate is invalid (here 91 of 1079 airborne samples
    of a fleet flight): those stretches are left out, not spread over the flight by the low-pass
    (before: ValueError 'need more samples than coefficients, got 0 <= 1')."""
    from twin_nodes.logs.ulog_io import read_ulog

    log = read_ulog(shared_log("fleet_quadx_v6c/ZweiterFlugtag", "log_39_2023-6-7-13-55-54.ulg"))
    nom = nominal_from_log(log, mass_kg=1.5)
    r = nom.params.rotors
    assert r.count == 4
    assert 2.0 < r.thrust_max_n < 20.0  # a ~1.5 kg quad: 4 rotors lifting it with margin


def test_a_large_com_offset_held_the_whole_flight_is_recovered_as_a_trim(tmp_path):
    """Known truth: the simulator flies the SIH quad (arm 0.283 m) with its centre of mass 110 mm forward and
    40 mm left (41 % of the arm, beyond the 30 % that needs no further evidence); the nominal built from that
    log recovers it within 3 % and puts it into the twin, saying the flight's halves show it held."""
    from twin_nodes.twin.simflight import Hidden, write_flight

    vp = shipped("px4_sih_quadx")
    path = tmp_path / "com.ulg"
    write_flight(path, vp, Hidden("com_offset", {"dx": 0.11, "dy": 0.04}), 7)
    nom = nominal_from_log(read_ulog(str(path)), mass_kg=vp.mass_kg)
    com = dict(nom.params.effect_dict["com_offset"])
    assert com["dx"] == pytest.approx(0.11, rel=0.03) and com["dy"] == pytest.approx(0.04, rel=0.03)
    assert "held the whole flight" in nom.sources["effects.com_offset"]


def _heavy_sim(tmp_path, fac: float, mass: float):
    from twin_nodes.twin.simflight import Hidden, write_flight

    vp = shipped("px4_sih_quadx")
    vp = vp.replace_rotors(thr_mdl_fac=fac).replace(mass_kg=mass)
    path = tmp_path / f"top_{fac}_{mass}.ulg"
    write_flight(path, vp, Hidden("none", {}), 3)
    return vp, path


def test_thrust_at_the_top_of_the_command_range_is_checked_against_the_accelerometer(tmp_path):
    """Known truth: the simulator flies the SIH quad at 1.6 kg (hover at 0.88 of full command, THR_MDL_FAC
    0.8), so that it spends seconds at a steady height with a motor >= 0.9.  Told the true map, the nominal's
    check of the thrust there reads 1.000 (within 0.5 %); told a linear map (THR_MDL_FAC 0, the fit then
    matches the bulk of the flight), it reads the true map's thrust at the top over the linear one's (the same
    two-scale fit of the true thrust on the linear map's, at a steady height) within 0.5 %, above 1 by more
    than 3 standard errors."""
    from twin_nodes.identify.nominal import GRID_HZ, TOP_COMMAND, TOP_VZ_MAX, _airborne_grid, _per_segment, _segments
    from twin_nodes.identify.regression import lowpass, rotor_states_from_commands, world_to_body

    vp, path = _heavy_sim(tmp_path, 0.8, 1.6)
    log = read_ulog(str(path))
    exact = nominal_from_log(log, mass_kg=1.6)
    assert exact.fits["top_seconds"] > 5.0
    assert exact.fits["top_thrust_ratio"] == pytest.approx(1.0, abs=0.005)
    assert "checked on" in exact.sources["rotors.thrust at the top of the command range"]

    log.params["THR_MDL_FAC"] = 0.0
    lin = nominal_from_log(log, mass_kg=1.6)
    # the truth at the check's samples: the true map over the linear one, through the same lag and low-pass
    t = _airborne_grid(log, GRID_HZ)
    u = np.clip(np.nan_to_num(log.require("motors").at(t)), 0.0, 1.0)
    segs = _segments(t, GRID_HZ)
    tau = lin.params.rotors.tau_up_s
    s = _per_segment(lambda tt, x: rotor_states_from_commands(tt, x, tau_up_s=tau), t, u, segs)
    lp = lambda x: _per_segment(lambda _t, y: lowpass(y, GRID_HZ, 2.5), t, x, segs)  # noqa: E731
    true_t = lp((vp.rotors.thrust_max_n * (0.8 * s * s + 0.2 * s)).sum(axis=1))
    lin_t = lp((lin.params.rotors.thrust_max_n * s).sum(axis=1))
    v_z = lp(world_to_body(log.require("attitude_q").at(t), np.nan_to_num(log.require("velocity_enu").at(t)))[:, 2])
    sel = np.abs(v_z) < TOP_VZ_MAX
    w = (lp(s.max(axis=1)) >= TOP_COMMAND)[sel].astype(float)
    (c_bulk, c_top), *_ = np.linalg.lstsq(np.column_stack([lin_t[sel] * (1 - w), lin_t[sel] * w]), true_t[sel],
                                          rcond=None)
    truth = c_top
    got, se = lin.fits["top_thrust_ratio"], lin.fits["top_thrust_ratio_se"]
    assert got == pytest.approx(truth, abs=0.005) and got - 1.0 > 3 * se


def test_a_flight_that_never_reaches_the_top_says_so(tmp_path):
    """The SIH quad at its own 1.0 kg hovers at 0.59 of full command: its commands never reach 0.9 for 2 s,
    and the nominal says the thrust above is the map extrapolated."""
    _vp, path = _heavy_sim(tmp_path, 0.4, 1.0)
    nom = nominal_from_log(read_ulog(str(path)), mass_kg=1.0)
    text = nom.sources["rotors.thrust at the top of the command range"]
    assert text.startswith("not reached") and "extrapolated" in text
    assert nom.fits["top_seconds"] < 2.0 and nom.fits["top_command_p99"] < 0.9
