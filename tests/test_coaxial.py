"""Coaxial pairs: the lower rotor's own thrust loss (physics effect ``coaxial``), identified on the flight
where the layout lets a flight show it (twin_nodes.identify.coaxial), else ASSUMED and said so."""

from __future__ import annotations

import numpy as np
import pytest

from twin_nodes.identify import coaxial as cx
from twin_nodes.physics.model import Multirotor
from twin_nodes.vehicle.params import shipped
from twin_nodes.vehicle.px4_geometry import GEOMETRIES
from twin_nodes.vehicle.px4_params import RotorLayout, coaxial_pairs, lower_rotors


def coax_vehicle(key: str, mass_kg: float):
    """PX4's coaxial geometry ``key`` on the SIH quad's rotors (5 N each), 0.28 m arm, body FLU."""
    rot = GEOMETRIES[key]["rotors"]
    pos = np.array([r[1] for r in rot]) * 0.28
    return shipped("px4_sih_quadx").replace(mass_kg=mass_kg).replace_rotors(
        x_flu_m=tuple(pos[:, 0]), y_flu_m=tuple(-pos[:, 1]), z_flu_m=tuple(-pos[:, 2]),
        direction=tuple(int(r[2]) for r in rot))


def test_the_effect_scales_only_the_lower_rotors_thrust_and_torque():
    vp = coax_vehicle("8c", 2.0)
    m0, m1 = Multirotor(vp), Multirotor(vp.with_effect("coaxial", efficiency=0.75, lower_mask=0b11110000))
    x = m0.initial_state(position_enu=(0, 0, 10), rotor_state=np.full(8, 0.5))
    (f0, mo0), (f1, mo1) = (m.wrench_terms(x)["rotors"] for m in (m0, m1))
    assert f1[0, 2] == pytest.approx(f0[0, 2] * (4 + 4 * 0.75) / 8, rel=1e-12)
    np.testing.assert_allclose(mo1[0, :2], 0.0, atol=1e-12)   # pairs at one place: still no roll/pitch moment
    # thrust and reaction torque alike (Q = km T): one lower rotor alone gives 0.75 of both, an upper one all
    for k, share in ((4, 0.75), (0, 1.0)):
        x = m0.initial_state(position_enu=(0, 0, 10), rotor_state=np.eye(8)[k] * 0.5)
        (f0, mo0), (f1, mo1) = (m.wrench_terms(x)["rotors"] for m in (m0, m1))
        assert abs(mo0[0, 2]) > 1e-3
        assert (f1[0, 2], mo1[0, 2]) == pytest.approx((share * f0[0, 2], share * mo0[0, 2]), rel=1e-12)


def test_lower_rotor_of_each_pair_by_height_else_the_second():
    vp = coax_vehicle("6c", 1.5)
    r = vp.rotors
    frd = np.column_stack([r.x_flu_m, -np.array(r.y_flu_m)])
    lay = RotorLayout(r.x_flu_m, r.y_flu_m, r.z_flu_m, r.direction, "test",
                      coaxial_pairs(frd[:, 0], frd[:, 1], np.array(r.direction)))
    assert lay.coaxial == ((0, 1), (2, 3), (4, 5))
    assert lower_rotors(lay)[0] == (1, 3, 5)                 # PX4 hexa_cox: the "bottom" rotors
    flat = RotorLayout(r.x_flu_m, r.y_flu_m, (0.0,) * 6, r.direction, "test", lay.coaxial)
    low, how = lower_rotors(flat)
    assert low == (1, 3, 5) and "ASSUMED" in how


def _synthetic(eta, n=6000, differential=0.1, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 50.0
    base = 0.5 + 0.1 * np.sin(0.3 * t)
    diff = differential * np.sin(0.13 * t + 1.0)
    tt = np.column_stack([base - diff, base + diff] * 3)      # Y6: upper/lower apart for yaw
    vz = 0.5 * np.sin(0.2 * t)
    f = 3.3 * (tt[:, ::2].sum(1) + eta * tt[:, 1::2].sum(1)) - 0.7 * vz + 0.01 * rng.standard_normal(n)
    return tt, f, vz


def test_efficiency_identified_where_the_levels_move_apart():
    tt, f, vz = _synthetic(0.72)
    fit = cx.coaxial_efficiency(tt, f, vz, (1, 3, 5))
    assert fit.identified and fit.efficiency == pytest.approx(0.72, abs=0.005)
    assert fit.source.startswith("identified: lower rotors give 0.72")


def test_efficiency_assumed_and_said_where_the_flight_does_not_show_it():
    tt, f, vz = _synthetic(0.72, differential=0.0)
    fit = cx.coaxial_efficiency(tt, f, vz, (1, 3, 5))
    assert not fit.identified and fit.efficiency == cx.ASSUMED == 0.8
    assert "not identifiable on any flight of this layout" in fit.source and "Bondyra" in fit.source


def test_x8_flight_identifies_the_pairs_thrust_and_assumes_the_split(tmp_path):
    """A simulated PX4 octo coaxial (X8: each level has both spins, so PX4 never drives the levels apart)
    with lower rotors at 0.75: the efficiency cannot show, is ASSUMED 0.8 and said so; the pairs' total
    thrust is identified (T_max (1 + 0.8) against the truth 5 N x (1 + 0.75))."""
    from twin_nodes.identify.nominal import nominal_from_log
    from twin_nodes.logs.flyable import read_flight
    from twin_nodes.logs.ulog_write import write_px4_ulog
    from twin_nodes.twin.simflight import Hidden, record_to_topics, simulate_flight
    from twin_nodes.vehicle.export_px4 import simulated_log_params

    vp = coax_vehicle("8c", 2.0)
    rec, battery, sp_hist = simulate_flight(vp, Hidden("coaxial", {"efficiency": 0.75, "lower_mask": 0b11110000}),
                                            seed=4)
    path = tmp_path / "x8.ulg"
    write_px4_ulog(str(path), record_to_topics(rec, vp, battery, sp_hist, np.random.default_rng(11)),
                   simulated_log_params(vp), {"sys_name": "test"})
    nom = nominal_from_log(read_flight(str(path)), mass_kg=2.0)
    eff = nom.params.effect_dict["coaxial"]
    assert eff == {"efficiency": 0.8, "lower_mask": float(0b11110000)}
    assert nom.sources["effects.coaxial"].startswith("ASSUMED 0.8: not identifiable on any flight of this layout")
    assert nom.params.rotors.thrust_max_n * 1.8 == pytest.approx(5.0 * 1.75, rel=0.03)


def test_x8_yaw_effectiveness_round_trips_with_a_km_unlike_the_assumed_one(tmp_path):
    """The yaw response sees km/Izz only (Izz rests on the assumed km 0.02 m).  A simulated PX4 X8 whose rotors
    have km 0.03 m (1.5x the assumed) and lower rotors at 0.75 of the upper's thrust and torque: the nominal's
    yaw acceleration per unit of yaw differential, km T_max (4 + 4 eta) / Izz with its ASSUMED eta 0.8, is
    the truth's, 0.03 x 5 N x (4 + 4 x 0.75) / Izz, within 5 % (the upper/lower split cannot show on an X8
    and does not matter to yaw: both levels move alike), and so is roll's."""
    from twin_nodes.identify.nominal import KM_ASSUMED_M, nominal_from_log
    from twin_nodes.logs.flyable import read_flight
    from twin_nodes.logs.ulog_write import write_px4_ulog
    from twin_nodes.twin.simflight import Hidden, record_to_topics, simulate_flight
    from twin_nodes.vehicle.export_px4 import simulated_log_params

    vp = coax_vehicle("8c", 2.0).replace_rotors(km_m=0.03)
    rec, battery, sp_hist = simulate_flight(vp, Hidden("coaxial", {"efficiency": 0.75, "lower_mask": 0b11110000}),
                                            seed=5)
    path = tmp_path / "x8_km.ulg"
    write_px4_ulog(str(path), record_to_topics(rec, vp, battery, sp_hist, np.random.default_rng(12)),
                   simulated_log_params(vp), {"sys_name": "test"})
    nom = nominal_from_log(read_flight(str(path)), mass_kg=2.0)
    r, inertia = nom.params.rotors, nom.params.inertia
    assert r.km_m == KM_ASSUMED_M == 0.02 and nom.params.effect_dict["coaxial"]["efficiency"] == 0.8
    truth = 0.03 * 5.0 * (4 + 4 * 0.75) / vp.inertia[2, 2]
    assert r.km_m * r.thrust_max_n * (4 + 4 * 0.8) / inertia[2, 2] == pytest.approx(truth, rel=0.05)
    assert inertia[2, 2] == pytest.approx(vp.inertia[2, 2] / 1.5, rel=0.06)   # Izz carries the km ratio
    lever = 0.28 / np.sqrt(2.0)
    roll_truth = 5.0 * lever * (4 + 4 * 0.75) / vp.inertia[0, 0]
    assert r.thrust_max_n * lever * (4 + 4 * 0.8) / inertia[0, 0] == pytest.approx(roll_truth, rel=0.08)
