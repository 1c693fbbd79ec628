"""Identification leaves out saturated motors, ground contact and the land detector's transitions
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
