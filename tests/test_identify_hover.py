"""Hover segments, hover throttle and kt = m g / (N omega^2)."""

from __future__ import annotations

import numpy as np
import pytest

from twin_nodes.identify.hover import (detect_hover_segments, kt_from_hover, kt_per_segment,
                                       params_from_hover_command, rpm_to_rad_s, summarize_hover)
from twin_nodes.vehicle.params import shipped


def test_kt_from_hover_reference_numbers():
    # Reference 2: ~3745 RPM at hover; N rotors share m g.
    w = float(rpm_to_rad_s(3745.0))
    kt4 = kt_from_hover(1.5, w, n_rotors=4)
    assert kt4 == pytest.approx(1.5 * 9.80665 / (4 * w * w), rel=1e-12)
    assert kt_from_hover(1.5, w, n_rotors=6) == pytest.approx(kt4 * 4 / 6, rel=1e-12)
    # per-rotor speeds: m g / sum(w_i^2)
    ws = np.array([w * 0.95, w * 1.05, w, w])
    assert kt_from_hover(1.5, ws) == pytest.approx(1.5 * 9.80665 / np.sum(ws ** 2), rel=1e-12)
    with pytest.raises(ValueError, match="n_rotors"):
        kt_from_hover(1.5, w)


def flight(rng: np.random.Generator):
    """10 Hz: on the ground (spin-up), climb, hover 8 s, fly forward, hover 6 s, descend."""
    t = np.arange(0.0, 60.0, 0.1)
    vz = np.zeros_like(t)
    vx = np.zeros_like(t)
    vz[(t >= 5) & (t < 10)] = 1.0          # climb
    vx[(t >= 18) & (t < 30)] = 3.0         # cruise
    vz[(t >= 36) & (t < 45)] = -0.8        # descent
    vel = np.column_stack([vx, np.zeros_like(t), vz]) + rng.normal(0, 0.03, (t.size, 3))
    height = np.cumsum(vz) * 0.1
    thr = np.full(t.size, 0.45) + rng.normal(0, 0.01, t.size)
    thr[(t >= 30) & (t < 36)] += 0.02      # second hover: battery sag
    airborne = t >= 1.0                    # land detector trips at spin-up, still on the ground until 5 s
    rpm = np.column_stack([np.full(t.size, 3745.0)] * 4) + rng.normal(0, 10, (t.size, 4))
    return t, vel, thr, airborne, height, rpm


def test_detects_the_two_hovers_not_the_ground():
    t, vel, thr, air, h, rpm = flight(np.random.default_rng(0))
    segs = detect_hover_segments(t, vel, thr, airborne=air, height_m=h, rpm=rpm, min_duration_s=3.0)
    assert len(segs) == 2, [(s.t_start_s, s.t_end_s) for s in segs]
    (a, b) = segs
    # climb ends at 10 s, cruise starts at 18 s; smoothing + trimming cost < 1 s at each edge
    assert 10.0 <= a.t_start_s <= 11.0 and 17.0 <= a.t_end_s <= 18.0
    assert 30.0 <= b.t_start_s <= 31.0 and 35.0 <= b.t_end_s <= 36.0
    assert a.throttle_mean == pytest.approx(0.45, abs=0.005)
    assert b.throttle_mean == pytest.approx(0.47, abs=0.005)
    s = summarize_hover(segs)
    assert s.n_segments == 2 and 0.45 < s.throttle_mean < 0.47
    assert s.between_std == pytest.approx(0.01, abs=0.003)
    assert s.within_std == pytest.approx(0.01, abs=0.003)
    kts = kt_per_segment(segs, 1.5)
    np.testing.assert_allclose(kts, kt_from_hover(1.5, rpm_to_rad_s(3745.0), 4), rtol=0.01)
    # without the height test the spin-up on the ground (1-5 s) would count as hover
    segs_no_h = detect_hover_segments(t, vel, thr, airborne=air, min_duration_s=2.0)
    assert segs_no_h[0].t_start_s < 5.0


def test_hover_command_to_params_roundtrip():
    sih = shipped("px4_sih_quadx")
    out = params_from_hover_command(sih, sih.hover_command)
    assert out["thrust_max_n"] == pytest.approx(sih.rotors.thrust_max_n, rel=1e-9)
    buho = shipped("buho_negro")
    out = params_from_hover_command(buho, buho.hover_command)
    assert out["kt_n_s2_rad2"] == pytest.approx(buho.rotors.kt_n_s2_rad2, rel=1e-9)
    with pytest.raises(ValueError, match="hover command"):
        params_from_hover_command(sih, 1.5)
