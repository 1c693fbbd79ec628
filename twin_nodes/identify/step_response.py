"""Motor step response: fit ``K/(tau s + 1)`` (optionally with a pure delay) to command -> rotor speed.

The model (reference 2, "Motor identification") is a first-order lag from the
command ``u`` to the rotor speed ``y``::

    tau(e) dy/dt = y_ss(u(t - d)) - y,     y_ss(u) = y_ref + K (u - u_ref)
    tau(e) = tau_up if e = y_ss - y > 0 (speeding up) else tau_down

``K`` is the DC gain around the operating point ``u_ref`` (RPM per command unit,
e.g. RPM/us for PWM), ``d`` a pure delay.  The command is treated as held
between its samples (zero-order hold), which is how an autopilot's PWM output
behaves, and the response is computed *exactly* on the merged grid of response
sample times and delayed command changes, so the fit cost is continuous in the
delay and the delay is resolved below one sample.

``discretize_zoh`` turns a fit into the difference equation the reference got
from MATLAB's ``c2d`` at the PWM logging rate (30 Hz there), which estimates rotor
speed from logged commands: ``y[k+1] = a y[k] + b0 u[k-n] + b1 u[k-n-1] + c``
with ``a = exp(-T/tau)``.

CSV format read by :func:`read_step_csv` (one header row, comma separated, ``#``
comment lines allowed, extra columns ignored)::

    time_s,command,rpm
    0.000,1425,3745
    0.005,1425,3751
    ...

``time_s`` strictly increasing [s], ``command`` in the unit the gain is wanted in
(PWM us or normalised 0..1), ``rpm`` measured rotor speed [rev/min].
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit
from scipy import optimize, signal

from twin_nodes.base.errors import LogError

CSV_COLUMNS = ("time_s", "command", "rpm")
RPM_TO_RAD_S = 2.0 * math.pi / 60.0


# --------------------------------------------------------------------------- input


def read_step_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``time_s, command, rpm`` columns from a CSV file.

    Returns ``(t_s, command, rpm)``, each shape (n,).  Raises
    :class:`~twin_nodes.base.errors.LogError` (``file: column ...: expected ...``) on a
    missing file or column, a non-numeric or non-finite cell, non-increasing time
    or fewer than 10 rows.
    """
    path = str(path)
    try:
        if not os.path.isfile(path) and os.path.exists(path):
            raise LogError(path, "<file>", "expected a CSV file, got a directory or special file")
        if os.path.getsize(path) > 100_000_000:
            raise LogError(path, "<file>", f"expected a CSV file of at most 100 MB, got {os.path.getsize(path)} bytes")
        fh = open(path, "r", encoding="utf-8", newline="")
    except FileNotFoundError:
        raise LogError(path, "<file>", "file not found") from None
    except OSError as exc:
        raise LogError(path, "<file>", f"cannot be opened ({exc.strerror})") from None
    try:
        with fh:
            rows = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
    except UnicodeDecodeError as exc:
        raise LogError(path, "<file>", f"expected UTF-8 CSV text, got byte 0x{exc.object[exc.start]:02x}") from None
    except csv.Error as exc:
        raise LogError(path, "<file>", f"expected CSV text ({' '.join(str(exc).split())[:120]})") from None
    if not rows:
        raise LogError(path, "<header>", f"empty file; expected a header row with columns {', '.join(CSV_COLUMNS)}")
    header = [h.strip().lower() for h in rows[0]]
    idx = {}
    for col in CSV_COLUMNS:
        if col not in header:
            raise LogError(path, f"column '{col}'",
                           f"missing; expected a header row with columns {', '.join(CSV_COLUMNS)} (got {', '.join(header)})")
        idx[col] = header.index(col)
    data = np.empty((len(rows) - 1, 3))
    for i, row in enumerate(rows[1:]):
        for j, col in enumerate(CSV_COLUMNS):
            k = idx[col]
            cell = row[k].strip() if k < len(row) else ""
            try:
                v = float(cell)
            except ValueError:
                raise LogError(path, f"column '{col}' row {i + 2}", f"expected a number, got {cell!r}") from None
            if not math.isfinite(v):
                raise LogError(path, f"column '{col}' row {i + 2}", f"expected a finite number, got {cell!r}")
            data[i, j] = v
    if data.shape[0] < 10:
        raise LogError(path, "<rows>", f"expected at least 10 data rows, got {data.shape[0]}")
    t = data[:, 0]
    bad = np.flatnonzero(np.diff(t) <= 0.0)
    if bad.size:
        raise LogError(path, f"column 'time_s' row {bad[0] + 3}",
                       f"expected strictly increasing time, got {t[bad[0] + 1]!r} after {t[bad[0]]!r}")
    return t, data[:, 1], data[:, 2]


# --------------------------------------------------------------------------- simulation


@njit(cache=True)
def _lag_exact(t_grid, r_grid, y0, tau_up, tau_down):  # pragma: no cover - numba
    """Exact first-order lag on a grid; ``r_grid[k]`` is held on ``[t_grid[k], t_grid[k+1])``."""
    n = t_grid.shape[0]
    y = np.empty(n)
    y[0] = y0
    for k in range(n - 1):
        h = t_grid[k + 1] - t_grid[k]
        r = r_grid[k]
        e = r - y[k]
        tau = tau_up if e > 0.0 else tau_down
        if tau <= 1e-12:
            y[k + 1] = r
        else:
            y[k + 1] = r + (y[k] - r) * math.exp(-h / tau)
    return y


def simulate_lag(t_u: np.ndarray, u: np.ndarray, t_y: np.ndarray, *, tau_up_s: float,
                 tau_down_s: float | None = None, gain: float = 1.0, u_ref: float = 0.0,
                 y_ref: float = 0.0, delay_s: float = 0.0, y0: float | None = None) -> np.ndarray:
    """Response of the (asymmetric) first-order lag plus delay at times ``t_y``.

    ``u`` (n,) is held from each ``t_u`` sample to the next (zero-order hold) and
    reaches the lag ``delay_s`` later; before its first sample it is taken as
    ``u[0]``.  ``y0`` is the state at ``t_y[0]`` (default: the steady state of
    ``u[0]``, i.e. the record starts settled).  Returns shape (len(t_y),).
    """
    t_u = np.asarray(t_u, dtype=float)
    u = np.asarray(u, dtype=float)
    t_y = np.asarray(t_y, dtype=float)
    tau_down = tau_up_s if tau_down_s is None else tau_down_s
    r = y_ref + gain * (u - u_ref)
    if u.size > 1:
        change = np.concatenate(([True], r[1:] != r[:-1]))
    else:
        change = np.ones(u.shape, dtype=bool)
    ev_t = t_u[change] + delay_s
    ev_r = r[change]
    keep = (ev_t > t_y[0]) & (ev_t < t_y[-1])
    grid = np.concatenate((t_y, ev_t[keep]))
    order = np.argsort(grid, kind="stable")
    grid = grid[order]
    # The value held from each grid point on: last command event at or before it.
    j = np.searchsorted(ev_t, grid, side="right") - 1
    held = np.where(j >= 0, ev_r[np.maximum(j, 0)], ev_r[0])
    start = r[0] if y0 is None else float(y0)
    y_grid = _lag_exact(grid, held, start, float(tau_up_s), float(tau_down))
    out = np.empty(grid.shape)
    out[order] = y_grid
    return out[: t_y.size]


# --------------------------------------------------------------------------- fitting


@dataclass(frozen=True)
class StepFit:
    """A fitted first-order (plus delay) motor model.

    ``gain`` is the DC gain [response unit / command unit] around ``u_ref``;
    ``y_ref`` the steady response at ``u_ref``.  Standard errors come from the
    Jacobian of the least-squares fit (``nan`` where not fitted).
    """

    asymmetric: bool
    tau_up_s: float
    tau_down_s: float
    gain: float
    u_ref: float
    y_ref: float
    delay_s: float
    tau_up_stderr_s: float
    tau_down_stderr_s: float
    gain_stderr: float
    delay_stderr_s: float
    r2: float
    rmse: float
    n: int
    fit_delay: bool = True
    residual_std: float = float("nan")

    @property
    def tau_s(self) -> float:
        """The single time constant of a symmetric fit (mean of up/down otherwise)."""
        return self.tau_up_s if not self.asymmetric else 0.5 * (self.tau_up_s + self.tau_down_s)

    def predict(self, t_u: np.ndarray, u: np.ndarray, t_y: np.ndarray | None = None) -> np.ndarray:
        """Model response at ``t_y`` (default ``t_u``) to command ``u`` sampled at ``t_u``."""
        t_y = t_u if t_y is None else t_y
        return simulate_lag(t_u, u, t_y, tau_up_s=self.tau_up_s, tau_down_s=self.tau_down_s,
                            gain=self.gain, u_ref=self.u_ref, y_ref=self.y_ref, delay_s=self.delay_s)

    def as_dict(self) -> dict:
        d = {
            "model": "asymmetric" if self.asymmetric else "symmetric",
            "tau_up_s": self.tau_up_s, "tau_down_s": self.tau_down_s,
            "tau_up_stderr_s": self.tau_up_stderr_s, "tau_down_stderr_s": self.tau_down_stderr_s,
            "gain": self.gain, "gain_stderr": self.gain_stderr,
            "u_ref": self.u_ref, "y_ref": self.y_ref,
            "delay_s": self.delay_s, "delay_stderr_s": self.delay_stderr_s,
            "delay_fitted": self.fit_delay, "r2": self.r2, "rmse": self.rmse, "n": self.n,
        }
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in d.items()}


def _plateau_gain(t_u: np.ndarray, u: np.ndarray, t_y: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Initial ``(gain, u_ref, y_ref)`` from the settled end of each constant-command stretch."""
    u_ref = float(np.median(u))  # the operating point, e.g. the hover command the steps go around
    edges = np.flatnonzero(np.diff(u) != 0.0) + 1
    starts = np.concatenate(([0], edges))
    ends = np.concatenate((edges, [u.size]))
    levels, means = [], []
    for s, e in zip(starts, ends):
        t0 = t_u[s]
        t1 = t_u[e] if e < u.size else t_y[-1]
        if t1 - t0 <= 0:
            continue
        sel = (t_y >= t0 + 0.6 * (t1 - t0)) & (t_y < t1)
        if np.count_nonzero(sel) >= 3:
            levels.append(u[s])
            means.append(np.mean(y[sel]))
    levels_a, means_a = np.asarray(levels), np.asarray(means)
    if levels_a.size >= 2 and np.ptp(levels_a) > 0 and len(starts) <= max(50, u.size // 20):
        k, c = np.polyfit(levels_a - u_ref, means_a, 1)
        return float(k), u_ref, float(c)
    # Continuously varying command: a plain regression (biased by the lag, only a start).
    u_at_y = np.interp(t_y, t_u, u)
    if np.ptp(u_at_y) > 0:
        k, c = np.polyfit(u_at_y - u_ref, y, 1)
        return float(k), u_ref, float(c)
    return 0.0, u_ref, float(np.mean(y))


def fit_step_response(t_u: np.ndarray, u: np.ndarray, t_y: np.ndarray | None = None,
                      y: np.ndarray | None = None, *, asymmetric: bool = False,
                      fit_delay: bool = True, max_delay_s: float = 0.5,
                      tau_bounds_s: tuple[float, float] = (1e-4, 10.0)) -> StepFit:
    """Least-squares fit of the first-order lag (plus delay) to measured responses.

    Parameters
    ----------
    t_u, u : (n,) command sample times [s] and commands (held between samples).
    t_y, y : (m,) response sample times [s] and measured response (e.g. RPM).
        ``t_y=None`` means the same times as the command.
    asymmetric : fit separate ``tau_up_s`` (response rising) and ``tau_down_s``.
    fit_delay : fit a pure delay in ``[0, max_delay_s]``; otherwise the delay is 0.

    The start is found from the settled plateaus (gain) and a coarse grid over
    (tau, delay); ``scipy.optimize.least_squares`` then refines all parameters.
    """
    t_u = np.asarray(t_u, dtype=float).ravel()
    u = np.asarray(u, dtype=float).ravel()
    if t_y is None:
        t_y = t_u
    t_y = np.asarray(t_y, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    if t_u.shape != u.shape:
        raise ValueError(f"t_u has {t_u.size} samples and u has {u.size}")
    if t_y.shape != y.shape:
        raise ValueError(f"t_y has {t_y.size} samples and y has {y.size}")
    if t_y.size < 10 or t_u.size < 2:
        raise ValueError(f"need at least 10 response samples and 2 commands, got {t_y.size} and {t_u.size}")
    for name, arr in (("t_u", t_u), ("u", u), ("t_y", t_y), ("y", y)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains non-finite values")
    if np.any(np.diff(t_u) <= 0) or np.any(np.diff(t_y) <= 0):
        raise ValueError("sample times must be strictly increasing")
    if np.ptp(u) == 0:
        raise ValueError("the command never changes: no step to fit")

    gain0, u_ref, y_ref0 = _plateau_gain(t_u, u, t_y, y)
    span = t_y[-1] - t_y[0]
    dt = float(np.median(np.diff(t_y)))
    max_delay = float(min(max_delay_s, 0.25 * span)) if fit_delay else 0.0
    lo_tau, hi_tau = tau_bounds_s
    hi_tau = float(min(hi_tau, span))

    def sse(tau_u: float, tau_d: float, k: float, c: float, d: float) -> np.ndarray:
        return simulate_lag(t_u, u, t_y, tau_up_s=tau_u, tau_down_s=tau_d, gain=k,
                            u_ref=u_ref, y_ref=c, delay_s=d) - y

    # Coarse grid for (tau, delay) with the plateau gain: avoids the local minimum
    # where a too-long tau absorbs the delay.
    taus = np.geomspace(max(lo_tau, 0.3 * dt), max(min(hi_tau, span / 4), 2 * lo_tau), 14)
    delays = np.linspace(0.0, max_delay, 13) if fit_delay and max_delay > 0 else np.array([0.0])
    best = (np.inf, taus[0], 0.0)
    for tau in taus:
        for d in delays:
            e = sse(tau, tau, gain0, y_ref0, d)
            v = float(e @ e)
            if v < best[0]:
                best = (v, tau, d)
    _, tau0, d0 = best

    # Parameter vector: log tau_up, [log tau_down], gain, y_ref, [delay]
    def unpack(p: np.ndarray) -> tuple[float, float, float, float, float]:
        i = 0
        tu = math.exp(p[i]); i += 1
        td = tu
        if asymmetric:
            td = math.exp(p[i]); i += 1
        k = p[i]; c = p[i + 1]; i += 2
        d = p[i] if fit_delay else 0.0
        return tu, td, k, c, d

    p0 = [math.log(tau0)] + ([math.log(tau0)] if asymmetric else []) + [gain0, y_ref0] + ([d0] if fit_delay else [])
    lo = [math.log(lo_tau)] + ([math.log(lo_tau)] if asymmetric else []) + [-np.inf, -np.inf] + ([0.0] if fit_delay else [])
    hi = [math.log(hi_tau)] + ([math.log(hi_tau)] if asymmetric else []) + [np.inf, np.inf] + ([max(max_delay, 1e-9)] if fit_delay else [])
    p0 = np.clip(p0, np.array(lo) + 1e-12, np.array(hi) - 1e-12)
    yscale = max(float(np.std(y)), 1e-12)

    res = optimize.least_squares(lambda p: sse(*unpack(p)) / yscale, p0, bounds=(lo, hi),
                                 x_scale="jac", method="trf")
    tu, td, k, c, d = unpack(res.x)
    r = res.fun * yscale
    n = y.size
    npar = len(p0)
    ssr = float(r @ r)
    sst = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - ssr / sst if sst > 0 else float("nan")
    sigma2 = ssr / max(n - npar, 1)
    J = res.jac * yscale
    try:
        cov = np.linalg.pinv(J.T @ J) * sigma2
        se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:  # pragma: no cover - pinv rarely fails
        se = np.full(npar, np.nan)
    i = 0
    se_tu = tu * se[i]; i += 1
    se_td = se_tu
    if asymmetric:
        se_td = td * se[i]; i += 1
    se_k = se[i]; i += 2
    se_d = se[i] if fit_delay else float("nan")
    return StepFit(asymmetric=asymmetric, tau_up_s=tu, tau_down_s=td, gain=k, u_ref=u_ref, y_ref=c,
                   delay_s=d, tau_up_stderr_s=float(se_tu), tau_down_stderr_s=float(se_td),
                   gain_stderr=float(se_k), delay_stderr_s=float(se_d), r2=r2,
                   rmse=math.sqrt(ssr / n), n=n, fit_delay=fit_delay, residual_std=math.sqrt(sigma2))


# --------------------------------------------------------------------------- discretisation


@dataclass(frozen=True)
class DiscreteLag:
    """Zero-order-hold discretisation of ``K/(tau s + 1) e^{-d s}`` at ``rate_hz``.

    Difference equation (``n = delay_samples``)::

        y[k+1] = a y[k] + b[0] u[k-n] + b[1] u[k-n-1] + c

    ``c = (1 - a)(y_ref - K u_ref)`` carries the operating point, so ``y`` is the
    absolute response (e.g. RPM) for absolute commands ``u``.  Without a
    fractional delay ``b[1] = 0`` and ``b[0] = K (1 - a)``.
    """

    a: float
    b: tuple[float, float]
    c: float
    delay_samples: int
    rate_hz: float

    def simulate(self, u: np.ndarray, y0: float | None = None) -> np.ndarray:
        """Run the difference equation over commands ``u`` (n,) sampled at ``rate_hz``."""
        u = np.asarray(u, dtype=float).ravel()
        n = self.delay_samples
        k = np.arange(u.size)
        u_n = u[np.maximum(k - n, 0)]          # u[k-n], u[j<0] taken as u[0]
        u_n1 = u[np.maximum(k - n - 1, 0)]     # u[k-n-1]
        x = self.b[0] * u_n + self.b[1] * u_n1 + self.c
        if y0 is None:
            y0 = (sum(self.b) * u[0] + self.c) / (1.0 - self.a) if self.a < 1.0 else 0.0
        y = np.empty(u.size)
        y[0] = float(y0)
        if u.size > 1:
            y[1:] = _recurse(self.a, x[:-1], float(y0))
        return y

    def as_dict(self) -> dict:
        return {"a": float(self.a), "b": [float(self.b[0]), float(self.b[1])], "c": float(self.c),
                "delay_samples": int(self.delay_samples), "rate_hz": float(self.rate_hz)}


def _recurse(a: float, x: np.ndarray, y0: float) -> np.ndarray:
    """``y[k+1] = a y[k] + x[k]`` for k = 0.., returning y[1:]."""
    out, _ = signal.lfilter([1.0], [1.0, -a], x, zi=np.array([a * y0]))
    return out


def discretize_zoh(tau_s: float, gain: float, rate_hz: float, *, delay_s: float = 0.0,
                   u_ref: float = 0.0, y_ref: float = 0.0) -> DiscreteLag:
    """Exact ZOH discretisation (closed form) of ``K/(tau s+1)`` with a pure delay.

    ``a = exp(-T/tau)``; a delay ``d = n T + eps`` (0 <= eps < T) splits the input
    weight between ``u[k-n]`` (``K (1 - exp(-(T-eps)/tau))``) and ``u[k-n-1]``
    (``K (exp(-(T-eps)/tau) - a)``), the modified z-transform of the delayed lag.
    """
    if not tau_s >= 0 or not rate_hz > 0 or not delay_s >= 0:
        raise ValueError(f"expected tau_s >= 0, rate_hz > 0, delay_s >= 0; got {tau_s}, {rate_hz}, {delay_s}")
    T = 1.0 / rate_hz
    a = math.exp(-T / tau_s) if tau_s > 0 else 0.0
    n = int(math.floor(delay_s / T + 1e-12))
    eps = delay_s - n * T
    if eps < 1e-12 * T:
        eps = 0.0
    e = math.exp(-(T - eps) / tau_s) if tau_s > 0 else 0.0
    b0 = gain * (1.0 - e)
    b1 = gain * (e - a)
    c = (1.0 - a) * (y_ref - gain * u_ref)
    return DiscreteLag(a=a, b=(b0, b1), c=c, delay_samples=n, rate_hz=float(rate_hz))


def c2d_scipy(tau_s: float, gain: float, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """``(num, den)`` of ``K/(tau s + 1)`` by ``scipy.signal.cont2discrete`` (ZOH), like MATLAB's c2d."""
    num, den, _ = signal.cont2discrete(([gain], [tau_s, 1.0]), 1.0 / rate_hz, method="zoh")
    return np.atleast_1d(np.squeeze(num)), np.atleast_1d(np.squeeze(den))
