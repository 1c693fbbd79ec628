"""tools/slow_error.py: the slow per-motor error's modes, and a regression that must carry over to count."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import slow_error as se  # noqa: E402


def test_one_motor_alone_is_a_quarter_in_every_mode():
    err = np.zeros((10, 4))
    err[:, 1] = 0.04                                           # m2 (rear left, ccw) 4 % high, the others exact
    m = se.modes(err)
    assert m["common"][0] == pytest.approx(0.01)
    assert m["roll"][0] == pytest.approx(0.01)
    assert m["pitch"][0] == pytest.approx(-0.01)
    assert m["yaw"][0] == pytest.approx(0.01)
    with pytest.raises(ValueError, match=r"\(T, 4\)"):
        se.modes(np.zeros((10, 6)))


def test_lowpass_keeps_the_slow_part_only():
    t = np.arange(0.0, 60.0, 0.02)
    slow = 0.03 * np.sin(2 * np.pi * 0.05 * t)
    x = slow + 0.02 * np.sin(2 * np.pi * 3.0 * t)
    x[1000:1010] = np.nan                                      # a gap stays a gap
    y = se.lowpass(t, x)
    ok = np.isfinite(y)
    assert ok.sum() == len(t) - 10
    away = ok & (np.abs(np.arange(len(t)) - 1005) > 100)
    away[:200] = away[-200:] = False
    assert np.max(np.abs(y[away] - slow[away])) < 0.001      # a 3 Hz part 0.02 high leaves under 0.1 %
    inner = ok.copy()
    inner[:200] = inner[-200:] = False                         # the filter's ends are its own
    assert np.max(np.abs(y[inner] - slow[inner])) < 0.005    # the gap's linear fill moves its neighbours a little
    assert np.isnan(se.lowpass(t[:20], x[:20])).all()


def _parts(n=3000):
    t = np.arange(n) * 0.02
    fit, held = t < 0.65 * t[-1], t >= 0.65 * t[-1]
    return t, fit, held


def test_a_line_that_holds_in_both_parts_carries_over():
    t, fit, held = _parts()
    rng = np.random.default_rng(3)
    s = np.sin(2 * np.pi * 0.07 * t) + 0.3 * t / t[-1]         # e.g. a yaw rate, slow
    e = 0.5 + 2.0 * s + 0.05 * rng.standard_normal(len(t))     # the error follows it, as an unmodelled effect would
    r = se.transfer(e, s, fit, held)
    assert r["slope_fit"] == pytest.approx(2.0, abs=0.01)
    assert r["slope_held"] == pytest.approx(2.0, abs=0.01)
    assert r["rms_carried"] == pytest.approx(0.05, abs=0.005)  # down to the noise
    assert r["rms_held"] > 1.0
    assert se.carries_over(r)


def test_a_line_seen_only_in_the_held_out_part_does_not():
    t, fit, held = _parts()
    h = 10.0 - 8.0 * np.clip((t - 0.65 * t[-1]) / (0.35 * t[-1]), 0.0, 1.0)  # height: flat, then a descent
    h = h + 0.2 * np.sin(2 * np.pi * 0.05 * t)
    e = np.where(held, -2.0 * (h - 10.0), 0.0) + 0.1 * np.sin(2 * np.pi * 0.11 * t)  # a split that grows low down
    r = se.transfer(e, h, fit, held)
    assert abs(r["r_fit"]) < 0.2 and r["r_held"] < -0.9       # in-sample it looks like an explanation ...
    assert r["rms_in_sample"] < 0.5 * r["rms_held"]
    assert r["rms_carried"] > 0.9 * r["rms_held"]             # ... that the fit part does not carry
    assert not se.carries_over(r)


def test_slopes_of_opposite_sign_never_count():
    t, fit, held = _parts()
    s = np.sin(2 * np.pi * 0.07 * t)
    e = np.where(fit, 1.0, -1.0) * s
    r = se.transfer(e, s, fit, held)
    assert r["slope_fit"] == pytest.approx(1.0) and r["slope_held"] == pytest.approx(-1.0)
    assert not se.carries_over(r)


def test_too_few_samples_or_a_flat_signal_is_nan():
    t, fit, held = _parts(150)
    r = se.transfer(np.sin(t), np.cos(t), fit, held)
    assert all(math.isnan(v) for v in r.values())
    t, fit, held = _parts()
    r = se.transfer(np.sin(t), np.ones_like(t), fit, held)
    assert math.isnan(r["rms_carried"]) and not se.carries_over(r)
