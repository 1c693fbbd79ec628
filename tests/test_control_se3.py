"""The geometric SE(3) law (twin_nodes.twin.control_se3) against RotorPy's own SE3Control, a closed form, the
params check, and a closed-loop twin of a RotorPy flight flying the law its vehicle was flown by."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from rotorpy.controllers.quadrotor_control import SE3Control
from scipy.spatial.transform import Rotation

from twin_nodes.base.errors import ParamsError
from twin_nodes.prove import rotorpy_flights as rp
from twin_nodes.twin.control import Controller
from twin_nodes.twin.controllers import make_controller
from twin_nodes.twin.control_se3 import SE3Controller
from twin_nodes.vehicle.params import from_ros_dict


@pytest.fixture(scope="module")
def crazyflie():
    qp = rp.rotorpy_params("crazyflie")
    return qp, rp.nominal_params(qp)


def _rotor_speeds(vp, u):
    r = vp.rotors
    return r.omega_min_rad_s + np.asarray(u) * (r.omega_cmd_max_rad_s - r.omega_min_rad_s)


def test_the_rotorpy_params_name_the_se3_law_with_rotorpys_gains(crazyflie):
    qp, vp = crazyflie
    ctrl = make_controller(vp)
    assert isinstance(ctrl, SE3Controller) and ctrl.law == "se3"
    ref = SE3Control(qp)
    assert ctrl.kp.tolist() == ref.kp_pos.tolist() and ctrl.kd.tolist() == ref.kd_pos.tolist()
    assert ctrl.gains.se3_kp_att_1_s2 == ref.kp_att and ctrl.gains.se3_kd_att_1_s == ref.kd_att
    assert ctrl.gains.rate_hz == rp.CONTROL_RATE_HZ
    assert isinstance(make_controller(dataclasses.replace(vp, controller={})), Controller)


def test_same_motor_speeds_as_rotorpys_se3control_on_random_states(crazyflie):
    """200 random states and flat outputs (tilts to 60 deg, rates to 3 rad/s, errors to 2 m): our law's rotor
    speeds equal RotorPy's SE3Control's, clipped to the rotor's range as RotorPy's flights clip them."""
    qp, vp = crazyflie
    ours, ref = SE3Controller(vp), SE3Control(qp)
    rng = np.random.default_rng(7)
    w_min, w_max = qp["rotor_speed_min"], qp["rotor_speed_max"]
    clipped = 0
    for _ in range(200):
        q_xyzw = Rotation.from_rotvec(rng.uniform(-1, 1, 3) * rng.uniform(0, np.radians(60))).as_quat()
        state = {"x": rng.uniform(-2, 2, 3), "v": rng.uniform(-2, 2, 3), "q": q_xyzw, "w": rng.uniform(-3, 3, 3)}
        flat = {"x": rng.uniform(-2, 2, 3), "x_dot": rng.uniform(-2, 2, 3), "x_ddot": rng.uniform(-3, 3, 3),
                "yaw": rng.uniform(-np.pi, np.pi), "yaw_dot": rng.uniform(-1, 1)}
        want = ref.update(0.0, state, flat)
        x = np.concatenate([state["x"], state["v"], np.roll(q_xyzw, 1), state["w"]])
        sp = np.concatenate([flat["x"], flat["x_dot"], flat["x_ddot"], [flat["yaw"], flat["yaw_dot"]]])
        u, info = ours.update(x, sp, 1.0 / 250)
        np.testing.assert_allclose(_rotor_speeds(vp, u), np.clip(want["cmd_motor_speeds"], w_min, w_max),
                                   rtol=1e-9, atol=1e-6)
        assert info[1] == pytest.approx(want["cmd_thrust"], rel=1e-12)
        clipped += int(np.any((want["cmd_motor_speeds"] < w_min) | (want["cmd_motor_speeds"] > w_max)))
    assert 0 < clipped < 200  # both the clipped and the unclipped branch were met


def test_hover_at_the_setpoint_gives_each_rotor_a_quarter_of_the_weight(crazyflie):
    _, vp = crazyflie
    ctrl = SE3Controller(vp)
    x = np.zeros(13)
    x[2], x[6] = 1.0, 1.0
    sp = np.full(11, np.nan)
    sp[0:3], sp[9] = (0.0, 0.0, 1.0), 0.0
    u, info = ctrl.update(x, sp, 0.004)
    w = _rotor_speeds(vp, u)
    np.testing.assert_allclose(vp.rotors.kt_n_s2_rad2 * w ** 2, vp.mass_kg * vp.gravity_m_s2 / 4, rtol=1e-9)
    assert info[0] == pytest.approx(vp.mass_kg * vp.gravity_m_s2 / (4 * vp.rotors.kt_n_s2_rad2
                                                                     * vp.rotors.omega_cmd_max_rad_s ** 2))


def test_an_unknown_law_is_a_one_line_params_error(crazyflie):
    _, vp = crazyflie
    doc = vp.to_ros_dict()
    doc["controller"] = {**doc.get("controller", {}), "law": "pid"}
    with pytest.raises(ParamsError) as e:
        from_ros_dict(doc, "v.yaml")
    assert "controller.law" in str(e.value) and "expected px4 or se3" in str(e.value)
    assert "\n" not in str(e.value)


def test_the_twin_of_a_rotorpy_flight_flies_its_law(crazyflie, tmp_path):
    """A RotorPy flight (RP0, nominal vehicle) and its closed-loop twin: flying RotorPy's law the twin follows
    the vehicle's throttle to a fraction of what PX4's cascade gives on the same flight."""
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.twin.compare import align
    from twin_nodes.twin.metrics import flight_metrics
    from twin_nodes.twin.runner import run_twin_on_log

    _, vp = crazyflie
    path = tmp_path / "rp0.ulg"
    rp.write_flight(path, rp.Case((), None, "RP0", 3))
    log = read_ulog(str(path))
    m = {}
    for law, v in (("se3", vp), ("px4", dataclasses.replace(vp, controller={}))):
        m[law] = flight_metrics(align(run_twin_on_log(log, v, mode="closed"), log))
    assert m["se3"]["throttle_median"] < 0.01
    assert m["se3"]["throttle_rmse"] < 0.4 * m["px4"]["throttle_rmse"]
    assert m["se3"]["xy_rmse_m"] < m["px4"]["xy_rmse_m"]
