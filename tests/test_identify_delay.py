"""Command -> response delay by cross-correlation, resolved below one sample."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from twin_nodes.identify.delay import estimate_delay


def band_limited(rng: np.random.Generator, duration: float, cutoff_hz: float, fs: float = 2000.0):
    """A smooth random command, known everywhere (fine grid)."""
    tf = np.arange(0.0, duration, 1.0 / fs)
    b, a = signal.butter(2, cutoff_hz / (0.5 * fs))
    x = signal.lfilter(b, a, rng.normal(size=tf.size))
    return tf, x / x.std()


@pytest.mark.parametrize("delay", [0.0373, 0.0055, 0.112])
def test_fractional_delay_recovered(delay):
    rng = np.random.default_rng(7)
    tf, x = band_limited(rng, 62.0, 3.0)
    t_cmd = np.arange(1.0, 61.0, 1.0 / 100.0)                 # command at 100 Hz
    t_resp = np.arange(1.0037, 61.0, 1.0 / 50.0)              # response at 50 Hz, other clock phase
    cmd = np.interp(t_cmd, tf, x)
    resp = 2.5 * np.interp(t_resp - delay, tf, x) + rng.normal(0.0, 0.3, t_resp.size)
    e = estimate_delay(t_cmd, cmd, t_resp, resp, max_delay_s=0.3, n_boot=200)
    # 1 ms = 1/20 of the response's sample interval
    assert e.delay_s == pytest.approx(delay, abs=0.001)
    assert e.ci_low_s <= delay <= e.ci_high_s
    assert e.ci_high_s - e.ci_low_s < 0.004
    assert e.peak_corr > 0.95


def test_diff_mode_and_highpass_also_work():
    rng = np.random.default_rng(8)
    tf, x = band_limited(rng, 62.0, 4.0)
    t = np.arange(1.0, 61.0, 0.01)
    slow = 3.0 * np.sin(2 * np.pi * 0.05 * t)  # slow co-variation in the response only
    resp = np.interp(t - 0.0421, tf, x) + slow + rng.normal(0, 0.05, t.size)
    for kw in ({"mode": "diff"}, {"highpass_s": 1.0}):
        e = estimate_delay(t, np.interp(t, tf, x), t, resp, max_delay_s=0.2, n_boot=0, **kw)
        assert e.delay_s == pytest.approx(0.0421, abs=0.001), kw


def test_negative_gain_and_confidence_for_unrelated_signals():
    rng = np.random.default_rng(9)
    tf, x = band_limited(rng, 62.0, 3.0)
    t = np.arange(1.0, 61.0, 0.01)
    cmd = np.interp(t, tf, x)
    e = estimate_delay(t, cmd, t, -np.interp(t - 0.02, tf, x), max_delay_s=0.2, allow_negative_gain=True,
                       n_boot=50)
    assert e.sign == -1 and e.peak_corr < -0.99 and e.delay_s == pytest.approx(0.02, abs=0.001)
    # an unrelated response: low peak correlation, wide interval
    e2 = estimate_delay(t, cmd, t, rng.normal(size=t.size), max_delay_s=0.2, n_boot=100)
    assert abs(e2.peak_corr) < 0.1
    assert e2.ci_high_s - e2.ci_low_s > 0.05


def test_bad_inputs():
    t = np.arange(0.0, 2.0, 0.01)
    with pytest.raises(ValueError, match="too short"):
        estimate_delay(t, np.sin(t), t, np.sin(t), max_delay_s=0.5)
    t = np.arange(0.0, 20.0, 0.01)
    with pytest.raises(ValueError, match="constant"):
        estimate_delay(t, np.ones_like(t), t, np.sin(t), max_delay_s=0.5)
    with pytest.raises(ValueError, match="mode"):
        estimate_delay(t, np.sin(t), t, np.sin(t), mode="fft")
