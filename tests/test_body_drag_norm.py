"""candidates: the body drag offered in both forms, per body axis (-c_i |v_i| v_i) and along the airspeed
(-c_i |v| v_i, RotorPy's parasitic drag), where the nominal has none."""

from types import SimpleNamespace

import numpy as np

from twin_nodes.discovery.candidates import BODY_DRAG_NORM, build_candidates
from twin_nodes.prove import rotorpy_flights as rf
from twin_nodes.prove.scoring import DragContext


def _cf_flight(speed_m_s: float):
    vp = rf.nominal_params(rf.rotorpy_params("crazyflie"), "rotorpy_crazyflie")
    n = 2000
    v = np.zeros((n, 3))
    v[:, 0] = speed_m_s
    data = SimpleNamespace(v=v, valid=np.ones(n, bool), motor_dt_s=0.02, dt=0.02, height=np.full(n, 1.5),
                           battery_v=np.full(n, np.nan))
    return vp, build_candidates(vp, data)


def test_both_forms_are_offered_with_the_same_floor_where_the_flight_has_airspeed():
    vp, cands = _cf_flight(2.0)
    drags = [c for c in cands if c.name == "body_drag"]
    assert [c.label for c in drags] == ["body_drag", BODY_DRAG_NORM]
    per_axis, norm = drags
    # two variants of one effect share its name and parameters: a candidate is itself only (list membership in the
    # selection compared their arrays and raised)
    assert norm not in [per_axis] and norm in [per_axis, norm] and per_axis != norm
    assert np.array_equal(per_axis.upper, norm.upper) and np.array_equal(per_axis.x0, norm.x0)
    floor = 0.01 * vp.mass_kg * vp.gravity_m_s2 / 2.0 ** 2        # 1 % of the weight at the 2 m/s flown
    for th in (0.9 * floor, 1.1 * floor):
        assert per_axis.floor(np.array([th, 0, 0])) == norm.floor(np.array([th, 0, 0])) == (th > floor)
    theta = np.array([0.0011, 0.0011, 0.0022])                    # RotorPy c003's truth
    assert norm.params_dict(theta)["norm"] == 1.0 and "norm" not in per_axis.params_dict(theta)
    assert dict(norm.build(theta).effect_dict["body_drag"])["norm"] == 1.0
    # a hover (no airspeed) is offered neither
    assert not [c for c in _cf_flight(0.2)[1] if c.name == "body_drag"]


def test_off_a_body_axis_the_two_forms_differ_in_the_thrust_axis():
    """A Crazyflie at 2 m/s tilted 6 degrees: the body z airspeed is 0.21 m/s.  Along it the norm form pushes
    c_dz |v| w = 0.0022 x 2.0 x 0.21 = 9.2e-4 N, the per-axis form c_dz w |w| = 9.6e-5 N: on RotorPy c003 (body drag,
    figure-eight) the per-axis fit left the throttle residual at 0.00245 per motor, the norm form at 0.00092 (the
    no-effect c038's 0.00093), c_dz 0.00272 and 0.00218 for 0.00221."""
    tilt = np.radians(6.0)
    vb = np.array([[2.0 * np.cos(tilt), 0.0, 2.0 * np.sin(tilt)]])
    ctx = DragContext(vb, np.zeros(1))
    c = {"c_dx": 0.0011, "c_dy": 0.0011, "c_dz": 0.0022}
    fz_axis = ctx.force("body_drag", {**c, "norm": 0.0})[0, 2]
    fz_norm = ctx.force("body_drag", {**c, "norm": 1.0})[0, 2]
    assert abs(fz_norm - (-9.20e-4)) < 0.01e-4
    assert abs(fz_axis - (-9.62e-5)) < 0.01e-5
