"""Motor step response: first-order (+delay, up/down) fit and its ZOH difference equation.

Known answer from reference 2: PWM steps around the 1425 us hover command, 5 s
each, rotor speed from a photo-interrupter; tau = 0.15 s, K = 6.5 RPM/us.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from twin_nodes.base.errors import LogError
from twin_nodes.identify.step_response import (c2d_scipy, discretize_zoh, fit_step_response, read_step_csv,
                                               simulate_lag)

TAU, K, U0, Y0 = 0.15, 6.5, 1425.0, 3745.0
FS = 200.0  # photo-interrupter RPM sample rate of the synthetic bench test
REL_TOL = 0.03  # stated tolerance on tau and K (the reference quotes 2 significant digits)


def steps(rng: np.random.Generator, *, tau_up: float = TAU, tau_down: float = TAU, delay: float = 0.0,
          noise_rpm: float = 20.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PWM steps of +-25..100 us around 1425 us, 5 s each, measured RPM with white noise."""
    levels = U0 + np.array([0, 50, -50, 100, 0, -100, 25, -25, 75, 0])
    t = np.arange(0.0, 5.0 * levels.size, 1.0 / FS)
    u = levels[(t // 5.0).astype(int)]
    y = simulate_lag(t, u, t, tau_up_s=tau_up, tau_down_s=tau_down, gain=K, u_ref=U0, y_ref=Y0, delay_s=delay)
    return t, u, y + rng.normal(0.0, noise_rpm, t.size)


def test_symmetric_fit_recovers_tau_and_gain():
    t, u, y = steps(np.random.default_rng(1))
    f = fit_step_response(t, u, t, y, fit_delay=False)
    assert f.tau_s == pytest.approx(TAU, rel=REL_TOL)
    assert f.gain == pytest.approx(K, rel=REL_TOL)
    assert f.u_ref == U0 and f.y_ref == pytest.approx(Y0, abs=5.0)
    assert f.r2 > 0.99
    # the stated standard errors are honest: truth within 4 sigma
    assert abs(f.tau_s - TAU) < 4 * f.tau_up_stderr_s
    assert abs(f.gain - K) < 4 * f.gain_stderr


def test_separate_up_and_down_time_constants():
    t, u, y = steps(np.random.default_rng(2), tau_up=0.12, tau_down=0.18)
    f = fit_step_response(t, u, t, y, asymmetric=True, fit_delay=False)
    assert f.tau_up_s == pytest.approx(0.12, rel=REL_TOL)
    assert f.tau_down_s == pytest.approx(0.18, rel=REL_TOL)
    assert f.gain == pytest.approx(K, rel=REL_TOL)
    sym = fit_step_response(t, u, t, y, asymmetric=False, fit_delay=False)
    assert f.rmse < sym.rmse  # the asymmetric model explains the data better


def test_pure_delay_is_resolved_below_one_sample():
    delay = 0.0373  # 7.46 samples at 200 Hz
    t, u, y = steps(np.random.default_rng(3), delay=delay)
    f = fit_step_response(t, u, t, y, fit_delay=True, max_delay_s=0.3)
    assert f.delay_s == pytest.approx(delay, abs=0.002)
    assert f.tau_s == pytest.approx(TAU, rel=REL_TOL)
    assert f.gain == pytest.approx(K, rel=REL_TOL)
    # no delay in the data -> none fitted
    t, u, y = steps(np.random.default_rng(4))
    assert fit_step_response(t, u, t, y, max_delay_s=0.3).delay_s < 0.002


def test_response_sampled_at_other_times_than_command():
    rng = np.random.default_rng(5)
    t, u, _ = steps(rng)
    ty = np.arange(0.013, t[-1], 1.0 / 90.0)  # RPM at 90 Hz, offset from the PWM samples
    y = simulate_lag(t, u, ty, tau_up_s=TAU, gain=K, u_ref=U0, y_ref=Y0) + rng.normal(0, 20, ty.size)
    f = fit_step_response(t, u, ty, y, fit_delay=False)
    assert f.tau_s == pytest.approx(TAU, rel=REL_TOL)
    assert f.gain == pytest.approx(K, rel=REL_TOL)


def test_zoh_coefficients_equal_closed_form_and_scipy():
    rate = 30.0  # the reference's PWM logging rate
    d = discretize_zoh(TAU, K, rate)
    a = math.exp(-1.0 / (rate * TAU))
    assert d.a == pytest.approx(a, rel=1e-12)
    assert d.b[0] == pytest.approx(K * (1.0 - a), rel=1e-12)
    assert d.b[1] == 0.0 and d.delay_samples == 0
    num, den = c2d_scipy(TAU, K, rate)
    np.testing.assert_allclose(den, [1.0, -a], rtol=1e-12)
    np.testing.assert_allclose(num[-1], K * (1.0 - a), rtol=1e-12)
    assert d.a == pytest.approx(0.8007374, abs=1e-7)  # exp(-1/4.5)


@pytest.mark.parametrize("delay", [0.0, 0.05, 1.0 / 30.0, 0.0712])
def test_difference_equation_is_exact_at_the_samples(delay):
    """The ZOH difference equation reproduces the continuous lag (with delay) sample for sample."""
    rate = 30.0
    t = np.arange(0.0, 20.0, 1.0 / rate)
    u = U0 + 60.0 * np.sign(np.sin(2 * np.pi * t / 3.1)) + 10.0 * np.round(np.sin(t))
    d = discretize_zoh(TAU, K, rate, delay_s=delay, u_ref=U0, y_ref=Y0)
    y_disc = d.simulate(u)
    y_cont = simulate_lag(t, u, t, tau_up_s=TAU, gain=K, u_ref=U0, y_ref=Y0, delay_s=delay)
    np.testing.assert_allclose(y_disc, y_cont, atol=1e-8)


def write_csv(path, rows, header="time_s,command,rpm"):
    path.write_text(header + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n")
    return path


def test_read_step_csv_roundtrip(tmp_path):
    rows = [(0.01 * i, 1425 + (50 if i > 20 else 0), 3745 + i) for i in range(40)]
    p = write_csv(tmp_path / "steps.csv", rows, header="# bench test 2024\nrpm,time_s,command,extra")
    p.write_text("# bench test\nrpm,time_s,command,extra\n"
                 + "\n".join(f"{r[2]},{r[0]},{r[1]},x" for r in rows) + "\n")
    t, u, y = read_step_csv(p)
    np.testing.assert_allclose(t, [r[0] for r in rows])
    np.testing.assert_allclose(u, [r[1] for r in rows])
    np.testing.assert_allclose(y, [r[2] for r in rows])


@pytest.mark.parametrize("text, match", [
    ("time_s,command\n" + "\n".join(f"{i},1" for i in range(20)), r"column 'rpm': missing; expected a header"),
    ("time_s,command,rpm\n0,1425,abc\n" + "\n".join(f"{i},1,2" for i in range(1, 20)),
     r"column 'rpm' row 2: expected a number, got 'abc'"),
    ("time_s,command,rpm\n" + "\n".join(f"{i % 5},1,2" for i in range(20)),
     r"column 'time_s' row \d+: expected strictly increasing time"),
    ("time_s,command,rpm\n0,1,2\n1,1,2\n", r"expected at least 10 data rows"),
    ("time_s,command,rpm\n" + "\n".join(f"{i},nan,2" for i in range(20)), r"expected a finite number"),
])
def test_bad_csv_gives_one_line_error(tmp_path, text, match):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(LogError, match=match) as exc:
        read_step_csv(p)
    assert "\n" not in str(exc.value) and str(p) in str(exc.value)


def test_missing_csv(tmp_path):
    with pytest.raises(LogError, match="file not found"):
        read_step_csv(tmp_path / "nope.csv")


def test_fit_rejects_bad_arrays():
    t = np.arange(100) * 0.01
    with pytest.raises(ValueError, match="never changes"):
        fit_step_response(t, np.ones(100), t, np.ones(100))
    with pytest.raises(ValueError, match="t_y has 100 samples and y has 99"):
        fit_step_response(t, np.arange(100.0), t, np.ones(99))
