"""The real motors' own content above 0.5 Hz in the per-motor metric's terms (metrics.motors_highpass_p75):
known truths."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twin_nodes.twin.metrics import highpass_rms, motors_highpass_p75


def test_p75_of_a_fast_sine_is_its_amplitude_times_sin_3pi_8_and_the_slow_part_is_not_counted():
    t = np.arange(0.0, 60.0, 0.02)
    amp = np.array([0.01, 0.02, 0.03, 0.04])
    # a steady split, a slow 0.05 Hz swing (a twin can follow both) and a 3.07 Hz part (it cannot; not a
    # divisor of the 50 Hz grid, so its samples cover the phase evenly)
    m = (0.5 + np.array([0.01, -0.02, 0.03, 0.0]) + 0.05 * np.sin(2 * np.pi * 0.05 * t)[:, None]
         + amp * np.sin(2 * np.pi * 3.07 * t)[:, None])
    mask = (t > 5.0) & (t < 55.0)
    # |A sin| <= x with probability (2/pi) asin(x/A): its 75th percentile is A sin(3 pi/8)
    assert motors_highpass_p75(t, m, mask) == pytest.approx(float(amp.mean()) * math.sin(3 * math.pi / 8), rel=0.02)
    # the same filter as the throttle's floor: RMS of a sine is A / sqrt(2)
    assert highpass_rms(t, m[:, 1], mask) == pytest.approx(0.02 / math.sqrt(2), rel=0.02)


def test_nothing_to_filter_is_nan():
    t = np.arange(0.0, 0.2, 0.02)
    assert math.isnan(motors_highpass_p75(t, np.ones((t.size, 4)), np.ones(t.size, bool)))
