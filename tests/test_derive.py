"""The parameter pipeline (twin_nodes.vehicle.derive) and the Gazebo/PX4 export (twin_nodes.vehicle.export_px4).

Known answers are the Búho Negro paper's numbers (shared/reference/buho-negro-paper.md)
and small hand-computed cases.
"""

from __future__ import annotations

import copy
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from twin_nodes.vehicle import derive as dv
from twin_nodes.base.errors import ParamsError
from twin_nodes.vehicle.export_px4 import (
    px4_airframe_params,
    px4_airframe_script,
    qgc_params_table,
    rotor_positions_frd_m,
    sdf_motor_plugins,
)
from twin_nodes.vehicle.params import from_ros_dict, shipped

G = 9.80665


# --------------------------------------------------------------------------- the paper's chain


def test_scale_kt_paper():
    kt2 = dv.scale_kt(1.881e-4, 22.0, 6.6, 22.4, 8.0)
    assert kt2 == pytest.approx(2.4066e-4, rel=1e-3)
    # kt ∝ D³ P: doubling D multiplies by 8, doubling P by 2.
    assert dv.scale_kt(1.0, 10, 5, 20, 5) == pytest.approx(8.0)
    assert dv.scale_kt(1.0, 10, 5, 10, 10) == pytest.approx(2.0)


def test_scale_omega_max_paper():
    kt2 = dv.scale_kt(1.881e-4, 22.0, 6.6, 22.4, 8.0)
    w2 = dv.scale_omega_max(551.0, 1.881e-4, kt2)
    assert w2 == pytest.approx(487.0, abs=1.0)
    # Same maximum thrust by construction.
    assert kt2 * w2**2 == pytest.approx(1.881e-4 * 551.0**2)


def test_time_constants_paper():
    tau_up = dv.tau_from_rise_time(0.050)
    assert tau_up == pytest.approx(0.0227, abs=5e-5)
    # The paper rounds tau_up to 0.023 s first: 1.2 x 0.023 = 0.0276 ≈ 0.028 s.
    assert dv.tau_down_from_braking(0.023, 1.2) == pytest.approx(0.028, abs=5e-4)
    # Unrounded chain: 1.2 x 0.02273 = 0.02727 s.
    assert dv.tau_down_from_braking(tau_up) == pytest.approx(0.02727, abs=1e-5)


def test_omega_limits_paper():
    wmin, wnmax = dv.omega_limits(487.0)
    assert wmin == pytest.approx(97.4)
    assert wnmax == pytest.approx(462.65)
    with pytest.raises(ValueError, match="min_frac < nmax_frac"):
        dv.omega_limits(487.0, 0.5, 0.4)


def test_hover_and_thrust_to_weight_paper():
    wh = dv.hover_omega(5.86, 2.4066e-4, 4, G)
    assert wh == pytest.approx(244.4, abs=0.1)
    assert dv.thrust_to_weight(2.4066e-4, 462.65, 5.86, 4, G) == pytest.approx(3.58, abs=0.01)
    # At hover the thrust-to-weight ratio is 1, and kt_from_hover inverts hover_omega.
    assert dv.thrust_to_weight(2.4066e-4, wh, 5.86, 4, G) == pytest.approx(1.0)
    assert dv.kt_from_hover(5.86, wh, 4, G) == pytest.approx(2.4066e-4)
    assert dv.mass_from_hover(2.4066e-4, wh, 4, G) == pytest.approx(5.86)
    u = dv.hover_throttle(wh, 97.4, 462.65)
    assert u == pytest.approx((wh - 97.4) / (462.65 - 97.4))
    assert u == pytest.approx(0.4023, abs=1e-4)


def test_propeller_coefficients():
    # kt = rho C_T D^4 / (4 pi^2); km = C_P D / (2 pi C_T)
    assert dv.kt_from_ct(0.1, 0.5, rho=1.2) == pytest.approx(1.2 * 0.1 * 0.5**4 / (4 * math.pi**2))
    assert dv.km_from_coefficients(0.1, 0.04, 0.5) == pytest.approx(0.04 * 0.5 / (2 * math.pi * 0.1))


@pytest.mark.parametrize("fn,args", [
    (dv.scale_kt, (-1.0, 22, 6.6, 22.4, 8)),
    (dv.scale_omega_max, (551.0, 0.0, 1.0)),
    (dv.tau_from_rise_time, (0.0,)),
    (dv.hover_omega, (-1.0, 1e-4)),
    (dv.kt_from_hover, (1.0, float("nan"))),
])
def test_bad_arguments_raise(fn, args):
    with pytest.raises(ValueError, match="must be a finite number > 0"):
        fn(*args)


# --------------------------------------------------------------------------- regression


def test_ols_through_origin_hand_case():
    # x = [1,2,3], y = [1,2,2]: b = 11/14, SSres = 70/196, sum y^2 = 9.
    b, r2, se = dv.ols_through_origin([1, 2, 3], [1, 2, 2])
    assert b == pytest.approx(11 / 14)
    assert r2 == pytest.approx(1 - (70 / 196) / 9)  # uncentred R²
    assert se == pytest.approx(math.sqrt((70 / 196) / 2 / 14))
    # The centred R² of the same fit would be lower; we must not report that one.
    yc = np.array([1, 2, 2]) - 5 / 3
    assert r2 > 1 - (70 / 196) / float(yc @ yc)


def test_ols_exact_and_single_point():
    b, r2, se = dv.ols_through_origin([1.0, 2.0, 4.0], [3.0, 6.0, 12.0])
    assert (b, r2, se) == (pytest.approx(3.0), pytest.approx(1.0), pytest.approx(0.0, abs=1e-12))
    b, r2, se = dv.ols_through_origin([2.0], [5.0])
    assert b == pytest.approx(2.5) and r2 == pytest.approx(1.0) and math.isnan(se)


def test_ols_bad_input():
    with pytest.raises(ValueError, match="x has 2 points and y has 3 points"):
        dv.ols_through_origin([1, 2], [1, 2, 3])
    with pytest.raises(ValueError, match="x is all zeros"):
        dv.ols_through_origin([0, 0], [1, 2])
    with pytest.raises(ValueError, match="finite"):
        dv.ols_through_origin([1, np.nan], [1, 2])


def test_kt_recovered_from_noisy_thrust_curve():
    rng = np.random.default_rng(20250101)
    kt_true = 1.881e-4
    omega = np.linspace(100.0, 551.0, 25)
    thrust = kt_true * omega**2 + rng.normal(0.0, 0.4, omega.size)  # 0.4 N noise on up to 57 N
    kt, r2, se = dv.kt_from_thrust_curve(omega, thrust)
    assert kt == pytest.approx(kt_true, rel=0.01)
    assert abs(kt - kt_true) < 4 * se
    assert 0.999 < r2 < 1.0


def test_km_recovered_from_noisy_torque_curve():
    rng = np.random.default_rng(7)
    thrust = np.linspace(2.0, 57.0, 20)
    torque = 0.0238 * thrust + rng.normal(0.0, 0.005, thrust.size)
    km, r2, se = dv.km_from_torque_curve(thrust, torque)
    assert km == pytest.approx(0.0238, rel=0.01)
    assert abs(km - 0.0238) < 4 * se
    assert r2 > 0.999


# --------------------------------------------------------------------------- geometry and inertia


def test_x_frame_positions_px4_order():
    pos, dirs = dv.x_frame_positions(0.5)
    a = 0.5 / math.sqrt(2)
    # FLU: x forward, y left.  M1 front-right, M2 rear-left, M3 front-left, M4 rear-right.
    np.testing.assert_allclose(pos, [[a, -a, 0], [-a, a, 0], [a, a, 0], [-a, -a, 0]])
    assert dirs == (1, 1, -1, -1)
    np.testing.assert_allclose(np.linalg.norm(pos, axis=1), 0.5)
    with pytest.raises(ValueError, match="only the quad X"):
        dv.x_frame_positions(0.5, n=6)


def test_inertia_from_shapes_hand_computed():
    # Stack: hollow sphere 1 kg, r 0.1 -> 2/3 * 1 * 0.01 on each axis.
    # Motors: 0.1 kg cylinders r 0.02, h 0.03 at 0.3 m on the diagonals (0.3/sqrt2 per axis):
    #   own Ixx = 0.1 (3*0.0004 + 0.0009)/12 = 1.75e-5, own Izz = 0.1*0.0004/2 = 2e-5,
    #   parallel axis: Ixx += 0.1 * 0.045, Izz += 0.1 * 0.09.
    pos, _ = dv.x_frame_positions(0.3)
    inertia = dv.inertia_from_shapes(pos, stack_mass_kg=1.0, stack_radius_m=0.1,
                                     motor_mass_kg=0.1, motor_radius_m=0.02, motor_height_m=0.03)
    ixx = 2 / 3 * 0.01 + 4 * (1.75e-5 + 0.1 * 0.045)
    izz = 2 / 3 * 0.01 + 4 * (2e-5 + 0.1 * 0.09)
    np.testing.assert_allclose(inertia, np.diag([ixx, ixx, izz]), atol=1e-12)
    assert ixx == pytest.approx(0.0247367, rel=1e-5)
    assert izz == pytest.approx(0.0427467, rel=1e-5)


def test_inertia_arms_and_props_hand_computed():
    # One arm (0.2 kg rod, centre -> motor at 0.3 m along +x) about the origin:
    # Iyy = Izz = m L^2 / 3 = 0.006, Ixx = 0.  A 0.01 kg prop D = 0.25 m at the tip:
    # own (averaged) Ixx = Iyy = m D^2/24, Izz = m D^2/12, plus m d^2 = 0.01 * 0.09 on y, z.
    pos = np.array([[0.3, 0.0, 0.0]])
    inertia_all = dv.inertia_from_shapes(pos, stack_mass_kg=0.0, stack_radius_m=0.1,
                                         motor_mass_kg=0.0, motor_radius_m=0.02, motor_height_m=0.03,
                                         arm_mass_kg=0.2, prop_mass_kg=0.01, prop_diameter_m=0.25)
    # inertia_from_shapes is about the composite CoM; shift back to the origin to compare.
    m_tot = 0.21
    com = (0.2 * 0.15 + 0.01 * 0.3) / m_tot
    about_origin = inertia_all + m_tot * com**2 * np.diag([0.0, 1.0, 1.0])
    d2 = 0.01 * 0.25**2
    expected = np.diag([d2 / 24, 0.2 * 0.09 / 3 + d2 / 24 + 0.01 * 0.09,
                        0.2 * 0.09 / 3 + d2 / 12 + 0.01 * 0.09])
    np.testing.assert_allclose(about_origin, expected, atol=1e-12)


def test_composite_inertia_two_point_masses():
    m, com, inertia = dv.composite_inertia([1.0, 3.0], np.array([[0, 0, 0], [0, 0, 4.0]]),
                                           [np.zeros((3, 3)), np.zeros((3, 3))])
    assert m == 4.0
    np.testing.assert_allclose(com, [0, 0, 3.0])
    # 1 kg at 3 m and 3 kg at 1 m from the CoM: Ixx = Iyy = 9 + 3 = 12, Izz = 0.
    np.testing.assert_allclose(inertia, np.diag([12.0, 12.0, 0.0]))


# --------------------------------------------------------------------------- derive_params


def _buho_spec():
    return dv.load_spec(Path(__file__).resolve().parent.parent / "params" / "derive_buho_negro.yaml")


def test_derive_buho_unrounded_chain():
    spec = _buho_spec()
    del spec["significant_figures"]
    d = dv.derive(spec, "buho.yaml")
    r = d.params.rotors
    assert r.kt_n_s2_rad2 == pytest.approx(2.4066e-4, rel=1e-3)
    assert r.omega_max_rad_s == pytest.approx(487.13, abs=0.01)
    assert r.tau_up_s == pytest.approx(0.0227, abs=5e-5)
    assert r.tau_down_s == pytest.approx(0.02727, abs=1e-5)
    assert r.omega_min_rad_s == pytest.approx(0.2 * 487.13, abs=0.01)
    assert d.value("omega_hover_rad_s") == pytest.approx(244.4, abs=0.1)
    assert d.value("thrust_to_weight_at_cmd_max") == pytest.approx(3.58, abs=0.01)
    assert d.params.hover_omega_rad_s == pytest.approx(d.value("omega_hover_rad_s"))


def test_derive_records_formulas():
    d = dv.derive(_buho_spec(), "buho.yaml")
    quantities = [s.quantity for s in d.steps]
    for q in ("kt_n_s2_rad2", "omega_max_rad_s", "tau_up_s", "tau_down_s", "omega_min_rad_s",
              "omega_cmd_max_rad_s", "omega_hover_rad_s", "hover_throttle", "thrust_to_weight_at_cmd_max"):
        assert q in quantities
    table = d.table()
    assert "(D2/D1)^3 (P2/P1)" in table and "t_r / 2.2" in table and "sqrt(m g / (N kt))" in table


def test_derive_thrust_curve_and_torque_curve():
    spec = _buho_spec()
    omega = np.linspace(150, 550, 9)
    spec["thrust"] = {"method": "curve", "omega_rad_s": omega.tolist(),
                      "thrust_n": (1.881e-4 * omega**2).tolist()}
    spec["speed"] = {"omega_max_rad_s": 551.0}
    thrust = np.linspace(5, 50, 6)
    spec["torque"] = {"method": "curve", "thrust_n": thrust.tolist(), "torque_nm": (0.0238 * thrust).tolist()}
    del spec["significant_figures"]
    d = dv.derive(spec, "s.yaml")
    assert d.params.rotors.kt_n_s2_rad2 == pytest.approx(1.881e-4)
    assert d.params.rotors.km_m == pytest.approx(0.0238)
    assert d.value("kt_fit_r2") == pytest.approx(1.0)
    assert d.params.rotors.omega_cmd_max_rad_s == pytest.approx(0.95 * 551.0)


def _expect(spec, key, expected_re, path="spec.yaml"):
    with pytest.raises(ParamsError, match=re.escape(f"{path}: {key}: ") + expected_re) as info:
        dv.derive(spec, path)
    assert "\n" not in str(info.value)


def test_derive_bad_specs():
    base = _buho_spec()

    s = copy.deepcopy(base)
    s["masss_kg"] = 1.0
    _expect(s, "masss_kg", "unknown key")

    s = copy.deepcopy(base)
    del s["frame"]
    _expect(s, "frame", "missing section")

    s = copy.deepcopy(base)
    s["mass_kg"] = -2.0
    _expect(s, "mass_kg", "expected > 0")

    s = copy.deepcopy(base)
    s["shapes"] = {}
    _expect(s, "inertia", "give exactly one of inertia")

    s = copy.deepcopy(base)
    s["thrust"]["method"] = "guess"
    _expect(s, "thrust.method", "expected one of reference, curve")

    s = copy.deepcopy(base)
    s["significant_figures"]["kt"] = 3
    _expect(s, "significant_figures.kt", "not a derived quantity")

    s = copy.deepcopy(base)
    s["mass_kg"] = "from_hover"
    _expect(s, "mass_kg", "from_hover needs hover")

    s = copy.deepcopy(base)
    s["command_map"]["min_frac"] = 0.96
    _expect(s, "command_map.min_frac", "expected min_frac < nmax_frac")

    s = copy.deepcopy(base)
    s["mass_kg"] = 80.0  # four 22-inch rotors cannot hover 80 kg on this command map
    _expect(s, "mass_kg", "hover needs command")

    s = copy.deepcopy(base)
    s["thrust"] = {"method": "curve", "rpm": [1000, 2000], "thrust_n": [1.0]}
    _expect(s, "thrust.thrust_n", "expected 2 values")

    # A params file handed to derive by mistake.
    _expect({"/**": {"ros__parameters": {}}}, "ros__parameters", "this is a params file")


def test_derive_shapes_mass_budget_checks():
    spec = dv.load_spec(Path(__file__).resolve().parent.parent / "params" / "derive_quad_c_3dr.yaml")
    s = copy.deepcopy(spec)
    s["shapes"]["motor"]["mass_kg"] = 0.5  # 4 x (0.5 + arm + prop) > 1.43 kg
    _expect(s, "shapes.stack.mass_kg", "remainder is")
    s = copy.deepcopy(spec)
    s["shapes"]["stack"]["components_kg"]["battery_3s_4000mah"] = 2.0
    _expect(s, "shapes.stack.components_kg", "listed stack components weigh")


# --------------------------------------------------------------------------- export


def _symmetric(arm=0.25, z=0.0, km=0.05):
    pos, dirs = dv.x_frame_positions(arm, z_m=z)
    return from_ros_dict({
        "vehicle": {"name": "sym", "mass_kg": 1.5, "ixx_kg_m2": 0.02, "iyy_kg_m2": 0.02, "izz_kg_m2": 0.04},
        "rotors": {"x_flu_m": pos[:, 0].tolist(), "y_flu_m": pos[:, 1].tolist(), "z_flu_m": pos[:, 2].tolist(),
                   "direction": list(dirs), "kt_n_s2_rad2": 8.5e-6, "km_m": km,
                   "omega_min_rad_s": 150.0, "omega_cmd_max_rad_s": 1000.0, "omega_max_rad_s": 1000.0,
                   "tau_up_s": 0.0125, "tau_down_s": 0.025},
    }, "sym.yaml")


def test_ca_rotor_frd_matches_px4_4001_quad_x():
    vp = _symmetric(arm=0.15 * math.sqrt(2))
    p = px4_airframe_params(vp)
    # conventions.md §1, PX4 4001 quad X: Motor1 (+,+) CCW, Motor2 (-,-) CCW, Motor3 (+,-) CW, Motor4 (-,+) CW
    expected = [(+0.15, +0.15, +1), (-0.15, -0.15, +1), (+0.15, -0.15, -1), (-0.15, +0.15, -1)]
    for i, (px, py, spin) in enumerate(expected):
        assert p[f"CA_ROTOR{i}_PX"] == pytest.approx(px)
        assert p[f"CA_ROTOR{i}_PY"] == pytest.approx(py)
        assert p[f"CA_ROTOR{i}_PZ"] == 0.0
        assert p[f"CA_ROTOR{i}_KM"] == pytest.approx(spin * 0.05)
        assert p[f"CA_ROTOR{i}_CT"] == pytest.approx(8.5e-6 * 1000.0**2, rel=1e-4)
    assert p["CA_ROTOR_COUNT"] == 4
    assert [p[f"SIM_GZ_EC_FUNC{j}"] for j in range(1, 5)] == [101, 102, 103, 104]
    assert all(p[f"SIM_GZ_EC_MIN{j}"] == 150 and p[f"SIM_GZ_EC_MAX{j}"] == 1000 for j in range(1, 5))
    # hover: sqrt(1.5 g / (4 kt)) on the 150..1000 map
    wh = math.sqrt(1.5 * G / (4 * 8.5e-6))
    assert p["MPC_THR_HOVER"] == pytest.approx((wh - 150) / 850, abs=1e-3)


def test_frd_z_flips_sign():
    vp = _symmetric(z=0.05)  # rotors 5 cm above the CoM (FLU z up)
    np.testing.assert_allclose(rotor_positions_frd_m(vp)[:, 2], -0.05)
    assert px4_airframe_params(vp)["CA_ROTOR0_PZ"] == pytest.approx(-0.05)


def test_px4_params_buho_negro():
    p = px4_airframe_params(shipped("buho_negro"))
    assert p["SIM_GZ_EC_MIN1"] == 97 and p["SIM_GZ_EC_MAX1"] == 463  # 97.4 and 462.65 rad/s, integer params
    assert p["MPC_THR_HOVER"] == pytest.approx(0.402, abs=1e-3)
    assert p["CA_ROTOR2_KM"] == pytest.approx(-0.0238)


# The elements gz-sim's MulticopterMotorModel::Configure reads (robotNamespace is optional).
GZ_PLUGIN_ELEMENTS = {"jointName", "linkName", "turningDirection", "timeConstantUp", "timeConstantDown",
                      "maxRotVelocity", "motorConstant", "momentConstant", "commandSubTopic", "motorNumber",
                      "rotorDragCoefficient", "rollingMomentCoefficient", "rotorVelocitySlowdownSim",
                      "motorType"}


def test_sdf_motor_plugins_buho_negro():
    vp = shipped("buho_negro")
    root = ET.fromstring(f"<model>{sdf_motor_plugins(vp)}</model>")
    plugins = root.findall("plugin")
    assert len(plugins) == 4
    for i, (pl, turning) in enumerate(zip(plugins, ["ccw", "ccw", "cw", "cw"])):
        assert pl.get("filename") == "gz-sim-multicopter-motor-model-system"
        assert pl.get("name") == "gz::sim::systems::MulticopterMotorModel"
        assert {c.tag for c in pl} == GZ_PLUGIN_ELEMENTS
        v = {c.tag: c.text for c in pl}
        assert v["jointName"] == f"rotor_{i}_joint" and v["linkName"] == f"rotor_{i}"
        assert v["turningDirection"] == turning
        assert int(v["motorNumber"]) == i
        assert float(v["motorConstant"]) == pytest.approx(2.4066e-4)
        assert float(v["momentConstant"]) == pytest.approx(0.0238)
        assert float(v["timeConstantUp"]) == pytest.approx(0.023)
        assert float(v["timeConstantDown"]) == pytest.approx(0.028)
        assert float(v["maxRotVelocity"]) == pytest.approx(487.0)
        assert v["motorType"] == "velocity"


def test_sdf_rotor_drag_from_effect():
    vp = shipped("buho_negro").with_effect("rotor_drag", k_d=8.06428e-05)
    root = ET.fromstring(f"<model>{sdf_motor_plugins(vp, robot_namespace='buho')}</model>")
    pl = root.findall("plugin")[0]
    assert float(pl.find("rotorDragCoefficient").text) == pytest.approx(8.06428e-05)
    assert pl.find("robotNamespace").text == "buho"


def test_airframe_script_and_qgc_table_agree():
    vp = shipped("buho_negro")
    params = px4_airframe_params(vp)
    script = [ln.split() for ln in px4_airframe_script(vp).splitlines() if not ln.startswith("#")]
    assert all(ln[:2] == ["param", "set-default"] for ln in script)
    assert {ln[2]: float(ln[3]) for ln in script} == pytest.approx({k: float(v) for k, v in params.items()})
    rows = [ln.split("\t") for ln in qgc_params_table(vp).splitlines() if not ln.startswith("#")]
    assert all(len(r) == 5 and r[:2] == ["1", "1"] for r in rows)
    table = {r[2]: (float(r[3]), int(r[4])) for r in rows}
    assert set(table) == set(params)
    for k, v in params.items():
        assert table[k][0] == pytest.approx(float(v))
        assert table[k][1] == (6 if isinstance(v, int) else 9)


def test_export_refuses_thrust_factor_model():
    vp = shipped("px4_sih_quadx")
    with pytest.raises(ParamsError, match=r"px4_sih_quadx\.yaml: rotors\.thrust_model: export needs"):
        sdf_motor_plugins(vp)
    with pytest.raises(ParamsError, match="rotors.thrust_model"):
        px4_airframe_params(vp)


@pytest.mark.parametrize("name", ["px4_sih_quadx", "buho_negro"])
def test_simulated_log_params_round_trip_through_the_log_reader(name):
    """What a simulated flight log carries (export_px4.simulated_log_params) is read back by the
    log-side reader (px4_params.rotor_layout) as the same rotor positions (FLU) and spins."""
    from twin_nodes.vehicle.export_px4 import simulated_log_params
    from twin_nodes.vehicle.params import shipped
    from twin_nodes.vehicle.px4_params import rotor_layout

    vp = shipped(name)
    p = simulated_log_params(vp)
    assert p["CA_ROTOR_COUNT"] == vp.rotors.count and p["SYS_AUTOSTART"] == 0
    lay = rotor_layout(p)
    np.testing.assert_allclose(lay.x_flu_m, vp.rotors.x_flu_m, atol=1e-12)
    np.testing.assert_allclose(lay.y_flu_m, vp.rotors.y_flu_m, atol=1e-12)
    np.testing.assert_allclose(lay.z_flu_m, vp.rotors.z_flu_m, atol=1e-12)
    assert tuple(lay.direction) == tuple(int(d) for d in vp.rotors.direction)
    assert p["MPC_THR_HOVER"] == pytest.approx(vp.hover_command)
