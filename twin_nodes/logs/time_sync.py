"""Clock alignment: the one place in rotortwin that puts signals on a common time base.

All times are float seconds on one clock (for ULog data: seconds since the log
start, see :mod:`twin_nodes.logs.ulog_io`).  Values are ``(n,)`` or ``(n, k)`` arrays.

Interpolation kinds (``kind=``):

``'linear'``
    linear between the two neighbouring samples; NaN if either neighbour is NaN
    (NaN means "unknown / not controlled" and must not be invented).
``'previous'``
    zero-order hold (sample-and-hold) of the last sample at or before the time;
    for discrete signals (nav_state, armed, landed) that are logged on change,
    so by default it holds past the last sample and ignores gaps.
``'nearest'``
    the closest sample in time.
``'slerp'`` / ``'nlerp'``
    unit quaternions ``[w, x, y, z]`` (n, 4): the neighbour pair is made
    sign-consistent (``q ≡ -q``) before interpolating, the output is unit and
    continuous in sign.

Outside ``[t_src[0], t_src[-1]]`` the result is NaN (except ``'previous'``
after the last sample).  A destination time strictly inside a gap between two
source samples that is longer than ``max_gap_s`` is NaN: by default the gap
threshold is ``max(10 * median sample interval, 0.05 s)`` for the continuous
kinds and none for ``'previous'``; pass ``np.inf`` to disable.

Every uniform grid built from log times goes through :func:`common_grid` (or,
for code that builds its own ``arange``, :func:`check_grid`): a grid of more
than :data:`MAX_GRID_POINTS` samples is refused with a one-line
:class:`~twin_nodes.base.errors.LogError` instead of allocating memory in
proportion to a time gap (a 2**40 µs clock jump at 250 Hz would be 275 million
samples).  :func:`twin_nodes.logs.ulog_io.read_ulog` already cuts logs at such
jumps; this guard catches any other source of times.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from twin_nodes.base.errors import LogError
from twin_nodes.base.frames import quat_make_continuous, quat_normalize

__all__ = ["KINDS", "MAX_GRID_POINTS", "common_grid", "check_grid", "interp_to", "align", "auto_max_gap"]

KINDS = ("linear", "previous", "nearest", "slerp", "nlerp")

#: the most samples a uniform grid may have: 10 million = 11 h at 250 Hz (one float
#: column is 80 MB); a longer grid is a time gap or jump in the data, not a flight
MAX_GRID_POINTS = 10_000_000


def check_grid(t0: float, t1: float, rate_hz: float, source: str = "<time grid>") -> int:
    """Number of samples of the uniform grid ``t0 .. t1`` at ``rate_hz`` (both ends included).

    Raises ``ValueError`` for a non-finite/non-positive rate or times, or ``t1 < t0``
    (programming errors), and :class:`LogError` (``<source>: time grid: ...``) when the
    grid would have more than :data:`MAX_GRID_POINTS` samples."""
    if not np.isfinite(rate_hz) or rate_hz <= 0:
        raise ValueError(f"rate_hz: expected a finite rate > 0 Hz, got {rate_hz}")
    if not (np.isfinite(t0) and np.isfinite(t1)):
        raise ValueError(f"t0, t1: expected finite times, got {t0}, {t1}")
    if t1 < t0:
        raise ValueError(f"t1: expected t1 >= t0, got t0={t0} s, t1={t1} s")
    n = float(np.floor((t1 - t0) * rate_hz + 1e-9)) + 1.0
    if n > MAX_GRID_POINTS:
        raise LogError(source, "time grid",
                       f"expected at most {MAX_GRID_POINTS} samples ({MAX_GRID_POINTS / rate_hz / 3600:.1f} h "
                       f"at {rate_hz:g} Hz), the data spans {t0:.6g}..{t1:.6g} s = {n:.3g} samples "
                       "(a time gap or clock jump in the log?)")
    return int(n)


def common_grid(t0: float, t1: float, rate_hz: float, source: str = "<time grid>") -> np.ndarray:
    """Uniform grid ``t0, t0 + 1/rate, …`` up to and including ``t1`` (within 1e-9 s).

    ``source`` (the file the times come from) names it in the :class:`LogError`
    raised when the grid would exceed :data:`MAX_GRID_POINTS` (see :func:`check_grid`)."""
    n = check_grid(t0, t1, rate_hz, source)
    return t0 + np.arange(n, dtype=float) / rate_hz


def auto_max_gap(t_src: np.ndarray) -> float:
    """Default gap threshold: ``max(10 * median(dt), 0.05 s)`` (inf for < 2 samples)."""
    t = np.asarray(t_src, dtype=float)
    if t.size < 2:
        return np.inf
    return float(max(10.0 * np.median(np.diff(t)), 0.05))


def _check_src(t_src: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    t = np.asarray(t_src, dtype=float)
    v = np.asarray(values, dtype=float)
    if t.ndim != 1:
        raise ValueError(f"t_src: expected shape (n,), got {t.shape}")
    squeeze = v.ndim == 1
    if squeeze:
        v = v[:, None]
    if v.ndim != 2 or v.shape[0] != t.shape[0]:
        raise ValueError(f"values: expected shape ({t.shape[0]},) or ({t.shape[0]}, k) to match "
                         f"t_src, got {np.asarray(values).shape}")
    if t.size and not np.all(np.isfinite(t)):
        raise ValueError("t_src: expected finite times, got NaN/inf")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        raise ValueError("t_src: expected strictly increasing times")
    return t, v, squeeze


def interp_to(
    t_src: np.ndarray,
    values: np.ndarray,
    t_dst: np.ndarray,
    kind: str = "linear",
    max_gap_s: float | None = None,
) -> np.ndarray:
    """Resample ``values`` sampled at ``t_src`` onto ``t_dst``.

    Parameters
    ----------
    t_src : (n,) strictly increasing times [s].
    values : (n,) or (n, k); NaN marks unknown samples.
    t_dst : (m,) times [s], any order.
    kind : one of :data:`KINDS`.
    max_gap_s : destination times inside a source gap longer than this are NaN;
        ``None`` = the default described in the module docstring.

    Returns
    -------
    (m,) or (m, k) float array, matching the shape of ``values``.
    """
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    t, v, squeeze = _check_src(t_src, values)
    td = np.asarray(t_dst, dtype=float)
    if td.ndim != 1:
        raise ValueError(f"t_dst: expected shape (m,), got {td.shape}")
    if kind in ("slerp", "nlerp") and v.shape[1] != 4:
        raise ValueError(f"values: expected quaternions (n, 4) for kind={kind!r}, got {v.shape}")
    k = v.shape[1]
    out = np.full((td.size, k), np.nan)
    n = t.size
    if n == 0 or td.size == 0:
        return out[:, 0] if squeeze else out

    if max_gap_s is None:
        max_gap_s = np.inf if kind == "previous" else auto_max_gap(t)

    if kind == "previous":
        i = np.searchsorted(t, td, side="right") - 1
        ok = i >= 0
        out[ok] = v[i[ok]]
        if np.isfinite(max_gap_s) and n > 1:
            # inside a long gap: the held value is stale
            nxt = np.minimum(i + 1, n - 1)
            gap = (t[nxt] - t[np.maximum(i, 0)]) > max_gap_s
            inside = ok & (i < n - 1) & gap & (td > t[np.maximum(i, 0)])
            out[inside] = np.nan
        return out[:, 0] if squeeze else out

    inside = (td >= t[0]) & (td <= t[-1])
    if n == 1:
        out[inside] = v[0]
        return out[:, 0] if squeeze else out

    # i0 = index of the left neighbour, clamped so that i0 + 1 exists
    i0 = np.clip(np.searchsorted(t, td, side="right") - 1, 0, n - 2)
    i1 = i0 + 1
    dt = t[i1] - t[i0]
    w = np.clip((td - t[i0]) / dt, 0.0, 1.0)
    v0 = v[i0]
    v1 = v[i1]

    if kind == "nearest":
        res = np.where((w <= 0.5)[:, None], v0, v1)
    elif kind == "linear":
        res = v0 + (v1 - v0) * w[:, None]
        # exactly on a sample: take it even if the other neighbour is NaN
        res = np.where((w == 0.0)[:, None], v0, res)
        res = np.where((w == 1.0)[:, None], v1, res)
    else:
        res = _quat_interp(v0, v1, w, kind)
        res = np.where((w == 0.0)[:, None], quat_normalize(v0), res)
        res = np.where((w == 1.0)[:, None], quat_normalize(v1), res)

    gap = dt > max_gap_s
    on_sample = (w == 0.0) | (w == 1.0)
    res[gap & ~on_sample] = np.nan
    out[inside] = res[inside]
    if kind in ("slerp", "nlerp"):
        order = np.argsort(td, kind="stable")
        out[order] = quat_make_continuous(out[order])
    return out[:, 0] if squeeze else out


#: the fixed step [s] :func:`stamp_step_s` reports (a simulator's 0.5-5 ms control step, PX4 SIH's lockstep range)
STAMP_STEP_S = (5e-4, 5e-3)
#: the fewest stamps :func:`stamp_step_s` reads a step from
MIN_STEP_STAMPS = 100


def stamp_step_s(*stamps_s: np.ndarray) -> float:
    """The one fixed step [s] every stamp sits on, else 0: the greatest common divisor of the stamps' whole
    microseconds from the earliest, where it lies in :data:`STAMP_STEP_S` over at least :data:`MIN_STEP_STAMPS`
    stamps.  A simulator that steps its controller at a fixed rate stamps every logged sample on that step
    (RotorPy's and our own 250 Hz records: 4 ms, the IMU 8/12 ms apart and the motors every 20 ms); a flight
    controller's clock stamps with microsecond jitter, whose divisor is about 1 us (0 here)."""
    us = np.concatenate([np.round(np.asarray(s, dtype=float) * 1e6) for s in stamps_s])
    us = us[np.isfinite(us)].astype(np.int64)
    if len(us) < MIN_STEP_STAMPS:
        return 0.0
    step = float(np.gcd.reduce(us - us.min())) * 1e-6
    return step if STAMP_STEP_S[0] <= step <= STAMP_STEP_S[1] else 0.0


def bin_mean_to(t_src: np.ndarray, values: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    """Resample onto a uniform grid ``t_dst`` by averaging, for a signal sampled faster than the grid.

    Each destination time ``t_k`` gets the mean of the finite source samples in
    ``[t_k - dt/2, t_k + dt/2)`` (``dt`` the grid step): every sample is used once, so white
    noise drops by the square root of the samples per step, where picking one sample per step
    (:func:`interp_to`) keeps all of it.  The centred box delays nothing; its gain at frequency
    ``f`` is ``sinc(f dt)`` (0.997 at 2 Hz on a 50 Hz grid).  A step with no finite sample falls
    back to linear interpolation (a gap longer than :func:`auto_max_gap` stays NaN)."""
    t, v, squeeze = _check_src(t_src, values)
    td = np.asarray(t_dst, dtype=float)
    if td.ndim != 1 or td.size < 2 or np.any(np.diff(td) <= 0):
        raise ValueError(f"t_dst: expected an increasing grid of >= 2 times, got shape {td.shape}")
    dt = float(np.median(np.diff(td)))
    edges = np.concatenate([td - 0.5 * dt, [td[-1] + 0.5 * dt]])
    idx = np.searchsorted(t, edges, side="left")
    fin = np.isfinite(v)
    csum = np.vstack([np.zeros((1, v.shape[1])), np.cumsum(np.where(fin, v, 0.0), axis=0)])
    ccnt = np.vstack([np.zeros((1, v.shape[1])), np.cumsum(fin, axis=0)])
    sums = csum[idx[1:]] - csum[idx[:-1]]
    cnts = ccnt[idx[1:]] - ccnt[idx[:-1]]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = sums / cnts
    empty = cnts == 0
    if empty.any():
        lin = interp_to(t, v, td, kind="linear")
        out[empty] = lin[empty]
    return out[:, 0] if squeeze else out


def sensor_to_grid(t_src: np.ndarray, values: np.ndarray, t_dst: np.ndarray, late_s: float = 0.0,
                   kind: str = "linear") -> np.ndarray:
    """A sensor signal on the uniform grid ``t_dst``, re-timed to when it happened.

    ``late_s``: how much later than the event the signal is stamped (a filter's group delay,
    half an averaging interval: :func:`twin_nodes.vehicle.px4_params.sensor_timing`), so sample
    ``i`` is taken to describe ``t_src[i] - late_s``.  A source sampled faster than the grid is
    averaged into it (:func:`bin_mean_to`), a slower one interpolated (:func:`interp_to`)."""
    t = np.asarray(t_src, dtype=float)
    td = np.asarray(t_dst, dtype=float)
    if len(t) > 1 and td.size > 1 and float(np.median(np.diff(t))) < 0.75 * float(np.median(np.diff(td))):
        if late_s:
            # what happened at each sample's own time (the signal ``late_s`` later), then averaged:
            # moving the stamps instead would shift which samples fall in a step by whole samples
            values = interp_to(t, values, t + float(late_s), kind=kind)
        return bin_mean_to(t, values, td)
    return interp_to(t - float(late_s), values, td, kind=kind)


def _quat_interp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray, kind: str) -> np.ndarray:
    q0 = quat_normalize(q0)
    q1 = quat_normalize(q1)
    d = np.sum(q0 * q1, axis=1)
    q1 = np.where((d < 0)[:, None], -q1, q1)  # shortest path: q ≡ -q
    d = np.abs(d)
    ww = w[:, None]
    if kind == "nlerp":
        return quat_normalize(q0 * (1.0 - ww) + q1 * ww)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    s = np.sin(theta)
    small = s < 1e-6
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(small, 1.0 - w, np.sin((1.0 - w) * theta) / s)
        b = np.where(small, w, np.sin(w * theta) / s)
    return quat_normalize(q0 * a[:, None] + q1 * b[:, None])


def _series_parts(s: Any, name: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(t_s, values, kind) of a Series-like object or a ``(t, values[, kind])`` tuple."""
    if hasattr(s, "t_s") and hasattr(s, "values"):
        return np.asarray(s.t_s, float), np.asarray(s.values, float), getattr(s, "interp", "linear")
    if isinstance(s, tuple) and len(s) in (2, 3):
        kind = s[2] if len(s) == 3 else "linear"
        return np.asarray(s[0], float), np.asarray(s[1], float), kind
    raise TypeError(f"{name}: expected a Series (t_s, values) or a (t, values[, kind]) tuple")


def align(
    series_a: Any,
    series_b: Any,
    rate_hz: float,
    t0: float | None = None,
    t1: float | None = None,
    source: str = "<time grid>",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Put two signals on one uniform grid over their common time span.

    ``series_a``/``series_b`` are :class:`twin_nodes.logs.ulog_io.Series` (their
    ``interp`` attribute picks the kind) or ``(t, values[, kind])`` tuples.
    ``t0``/``t1`` default to the overlap ``[max(starts), min(ends)]``; ``source``
    names the data in the error raised for an oversized grid (:func:`check_grid`).

    Returns ``(t, a_on_t, b_on_t)``.
    """
    ta, va, ka = _series_parts(series_a, "series_a")
    tb, vb, kb = _series_parts(series_b, "series_b")
    if ta.size == 0 or tb.size == 0:
        raise ValueError("align: expected two non-empty series")
    lo = max(ta[0], tb[0]) if t0 is None else t0
    hi = min(ta[-1], tb[-1]) if t1 is None else t1
    if hi < lo:
        raise ValueError(f"align: the series do not overlap in time "
                         f"([{ta[0]:.3f}, {ta[-1]:.3f}] s vs [{tb[0]:.3f}, {tb[-1]:.3f}] s)")
    t = common_grid(lo, hi, rate_hz, source)
    return t, interp_to(ta, va, t, kind=ka), interp_to(tb, vb, t, kind=kb)
