"""Identification leaves out saturated motors, ground contact, the land detector's transitions and the take-off spot
(twin_nodes.identify.fit_mask), on a simulated PX4 flight written as a ULog with such stretches edited in."""

from __future__ import annotations

import numpy as np
import pytest

from twin_nodes.identify import fit_mask as fm
from twin_nodes.identify.nominal import nominal_from_log
from twin_nodes.logs.flyable import read_flight
from twin_nodes.logs.ulog_write import write_px4_ulog
from twin_nodes.twin.simflight import simulated_log_params

from conftest import SIM_START_US as START_US  # noqa: E402
SAT = (30.0, 38.0)      # all four motors logged at 1.0 (the vehicle flew on: the log claims thrust it had not)
GROUND = (50.0, 53.0)   # the land detector says ground_contact while airborne (a touch-and-go)


@pytest.fixture(scope="module")
def flight(sih_quadx_flight):
    return sih_quadx_flight


def _write(path, vp, topics, edit: bool):
    topics = {k: dict(v) for k, v in topics.items()}
    if edit:
        mot = topics["actuator_motors"]
        s = (mot["timestamp"].astype(np.int64) - START_US) * 1e-6
        ctrl = mot["control"].copy()
        ctrl[(s >= SAT[0]) & (s < SAT[1]), :4] = 1.0
        mot["control"] = ctrl
        ld = topics["vehicle_land_detected"]
        t_us = (START_US + np.array([GROUND[0], GROUND[1]]) * 1e6).astype(np.uint64)
        ts = np.concatenate([ld["timestamp"], t_us])
        order = np.argsort(ts, kind="stable")
        landed = np.concatenate([ld["landed"], [False, False]])[order]
        gc = np.zeros(ts.size, bool)
        gc[order.argsort()[-2]] = True   # on at GROUND[0], off at GROUND[1]
        topics["vehicle_land_detected"] = {"timestamp": ts[order], "landed": landed, "ground_contact": gc}
    write_px4_ulog(str(path), topics, simulated_log_params(vp), {"sys_name": "test"}, start_us=START_US)
    return read_flight(str(path))


def test_the_mask_leaves_out_what_it_says_and_keeps_the_fit_true(tmp_path, flight, monkeypatch):
    vp, topics = flight
    clean = nominal_from_log(_write(tmp_path / "clean.ulg", vp, topics, edit=False), mass_kg=1.0)
    edited_log = _write(tmp_path / "edited.ulg", vp, topics, edit=True)
    (a, b), = [iv for iv in edited_log.airborne_intervals() if iv[0] < SAT[0] < iv[1]]
    edited = nominal_from_log(edited_log, mass_kg=1.0)
    text = edited.sources["identification: samples left out"]
    assert "none:" in clean.sources["identification: samples left out"]
    # 8 s saturated plus one 10 Hz motor sample's margin (0.1 s) on either side; 3 s on the ground; 1 s of
    # the land detector's transitions outside that stretch on either side
    got = {k: v for k, v in fm.fit_mask(edited_log, np.arange(a + 2.0, b - 2.0, 0.02), 50.0).seconds.items()}
    assert got[fm.SATURATED] == pytest.approx(8.2, abs=0.06)
    assert got["in ground contact (land detector ground_contact/maybe_landed/landed)"] == pytest.approx(3.0, abs=0.06)
    assert got["within 1 s of a land-detector transition"] == pytest.approx(2.0, abs=0.06)
    assert "8.2 s with a motor output at its bound" in text and "3.0 s in ground contact" in text
    # left out, the stretch does not move the thrust fit; fitted, it does (the log claims full thrust there)
    t_clean, t_edit = clean.params.rotors.thrust_max_n, edited.params.rotors.thrust_max_n
    assert t_edit == pytest.approx(t_clean, rel=0.01)
    assert t_clean == pytest.approx(5.0, rel=0.05)
    monkeypatch.setattr("twin_nodes.identify.nominal.fit_mask",
                        lambda log, t, hz: fm.FitMask(np.ones(len(t), bool), {}, len(t) / hz))
    unmasked = nominal_from_log(edited_log, mass_kg=1.0).params.rotors.thrust_max_n
    assert abs(unmasked / t_clean - 1.0) > 0.03


def test_a_flight_saturated_almost_throughout_is_fitted_with_its_saturation_and_says_so():
    class Log:
        def __init__(self):
            self.t = np.arange(0.0, 20.0, 0.1)
            v = np.full((self.t.size, 4), 0.5)
            v[self.t >= 4.0, 3] = 1.0        # 16 s of 20 at the upper bound
            self.series = {"motors": type("S", (), {"t_s": self.t, "values": v, "__len__": lambda s: 200})()}

        def get(self, name):
            return self.series.get(name)

    m = fm.fit_mask(Log(), np.arange(0.0, 20.0, 0.02), 50.0)
    assert m.keep.all()   # 3.9 s would remain (< 6 s): the saturated samples are fitted, and it says so
    assert m.describe().startswith("saturated samples NOT left out: only 3.9 s would remain (< 6 s); 16.1 s")
    m = fm.fit_mask(Log(), np.arange(0.0, 20.0, 0.02), 50.0, min_keep_s=3.0)
    assert m.keep.sum() == pytest.approx(3.9 * 50, abs=1)


class _SpotLog:
    """Heights (ENU z, 50 Hz) over a 2-30 s airborne interval of a log that runs 0-32 s."""

    def __init__(self, z_of_t, interval=(2.0, 30.0)):
        self.t = np.arange(0.0, 32.0, 0.02)
        z = np.array([z_of_t(t) for t in self.t])
        self.series = {"position_enu": type("S", (), {"t_s": self.t, "values": np.column_stack([0 * z, 0 * z, z]),
                                                      "__len__": lambda s: z.size})()}
        self.interval = interval

    def get(self, name):
        return self.series.get(name)

    def airborne_intervals(self):
        return [self.interval]


def _seconds(mask: np.ndarray) -> float:
    return float(mask.sum()) * 0.02


def test_the_take_off_spot_is_left_out_whatever_the_land_detector_says():
    # airborne (land detector) from 2 s; on the spot (z 0) until 6 s, up at 1 m/s to 3 m, down from 20 s at 1 m/s to
    # a touchdown height 0.3 m under the take-off one (the estimate drifted), resting there from 23.3 s to 30 s
    def z(t):
        if t < 6.0:
            return 0.0
        if t < 20.0:
            return min(t - 6.0, 3.0)
        return max(3.0 - (t - 20.0), -0.3)
    log = _SpotLog(z)
    t = np.arange(0.0, 32.0, 0.02)
    spot = fm.on_spot(log, t)
    # 2 s (airborne) .. 6.2 s (first above 0.2 m): 4.2 s; the touchdown end is the land detector's
    assert _seconds(spot) == pytest.approx(4.2, abs=0.03)
    assert not spot[t >= 6.22].any() and spot[(t >= 2.0) & (t < 6.18)].all()
    got = fm._fit_mask(log, t, 50.0, saturation=False).seconds
    assert got["on the take-off spot (not yet 0.2 m above it; the land detector said airborne)"] == \
        pytest.approx(4.2, abs=0.03)
    # a log joined in the air has no take-off spot; a vehicle that never rises 0.2 m is on its spot throughout
    assert not fm.on_spot(_SpotLog(z, (0.0, 30.0)), t).any()
    assert _seconds(fm.on_spot(_SpotLog(lambda s: 0.1, (2.0, 30.0)), t)) == pytest.approx(28.0, abs=0.03)


def test_the_fleet_vehicle_held_on_its_spot_gives_its_siblings_trims_and_thrust(tmp_path, monkeypatch):
    """ZweiterFlugtag log_20 (the overloaded Quad X fleet, ../shared) sits on its take-off spot from 4.4 to ~17 s at a
    collective of 0.4-1.0 while its land detector says airborne.  Fitted there, the ground's push and moments
    became the vehicle's: T_max 6.0 N, a centre of mass (-27, -16) mm and a yaw lever of -0.5 mm, where the same
    vehicle's other flights that day give (-6, -7) mm and +4.0-4.2 mm (log_18, log_19, log_39) and its motors on
    the spot [0.75, 0.83, 0.56, 0.99] at full collective lift nothing.  Left out, the flight gives its siblings'."""
    from conftest import shared_log

    monkeypatch.setenv("ROTORTWIN_CACHE", str(tmp_path))
    log = read_flight(shared_log("fleet_quadx_v6c/ZweiterFlugtag", "log_20_2023-6-7-10-52-56.ulg"), horizontal=False)
    nom = nominal_from_log(log)
    assert "s on the take-off spot" in nom.sources["identification: samples left out"]
    eff = nom.params.effect_dict
    assert 1e3 * eff["com_offset"]["dx"] == pytest.approx(-6.1, abs=0.5)
    assert 1e3 * eff["com_offset"]["dy"] == pytest.approx(-6.5, abs=0.5)
    assert 1e3 * eff["rotor_tilt"]["lever_m"] == pytest.approx(3.9, abs=0.2)
    assert nom.params.rotors.thrust_max_n == pytest.approx(4.74, abs=0.03)   # 6.01 N fitted on the spot
