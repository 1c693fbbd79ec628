"""The residuals' zero-phase low-pass: ``scipy.signal.sosfiltfilt(sos, x, axis=0)`` (odd padding of the
default length) as one numba kernel over the columns.

Discovery low-passes every candidate evaluation's residual (T, channels): ~0.6 ms each through
scipy, most of it the Python around ``_sosfilt`` (argument checks, the padding, two passes'
axis moves and copies); ~0.1-0.2 ms here.  :func:`filtfilt_rows` does the same
operations in the same order as scipy 1.17's ``sosfiltfilt`` + Cython ``_sosfilt`` (the odd
extension ``2 x0 - x[edge:0:-1]``, the initial state ``zi * x0``, each section's difference equation,
the backward pass from ``zi * y[-1]``) and returns the same memory layout (a reversed, strided view of
a (channels, T + 2 edge) buffer), so what is summed over it downstream sums in the same order.
A test checks it against ``sosfiltfilt`` bit for bit (tests/test_fleet_speed.py).
"""

from __future__ import annotations

import functools

import numpy as np
from numba import njit
from scipy.signal import butter, sosfilt_zi, sosfiltfilt


@functools.lru_cache(maxsize=32)
def butter_sos(order: int, cutoff_hz: float, rate_hz: float) -> np.ndarray:
    """The Butterworth low-pass, designed once per (order, cutoff, rate)."""
    return butter(order, cutoff_hz / (0.5 * rate_hz), output="sos")


@functools.lru_cache(maxsize=32)
def _design(order: int, cutoff_hz: float, rate_hz: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The sections, their steady-state initial condition and sosfiltfilt's default pad length."""
    sos = np.ascontiguousarray(butter_sos(order, cutoff_hz, rate_hz), dtype=np.float64)
    ntaps = 2 * sos.shape[0] + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum()))
    return sos, np.ascontiguousarray(sosfilt_zi(sos), dtype=np.float64), 3 * ntaps


@njit(cache=True)
def _sections(sos, z, y):
    """scipy's ``_sosfilt`` on each column of ``y`` (time, channels), in place, from the states ``z``
    (channels, n_sections, 2); the columns advance together (independent recursions side by side)."""
    ns = sos.shape[0]
    nc = y.shape[1]
    for n in range(y.shape[0]):
        for c in range(nc):
            x_cur = y[n, c]
            for s in range(ns):
                x_new = sos[s, 0] * x_cur + z[c, s, 0]
                z[c, s, 0] = sos[s, 1] * x_cur - sos[s, 4] * x_new + z[c, s, 1]
                z[c, s, 1] = sos[s, 2] * x_cur - sos[s, 5] * x_new
                x_cur = x_new
            y[n, c] = x_cur


@njit(cache=True)
def _filtfilt_columns(sos, zi, x, edge):
    """(channels, T + 2 edge): each column of ``x`` (T, channels) padded, filtered forward, then
    backward (stored in the backward pass's time order, as scipy leaves it)."""
    nt, nc = x.shape
    ne = nt + 2 * edge
    ns = zi.shape[0]
    buf = np.empty((ne, nc))
    for c in range(nc):
        x0 = x[0, c]
        x1 = x[nt - 1, c]
        for j in range(edge):
            buf[j, c] = 2 * x0 - x[edge - j, c]
            buf[edge + nt + j, c] = 2 * x1 - x[nt - 2 - j, c]
    buf[edge:edge + nt] = x
    z = np.empty((nc, ns, 2))
    for c in range(nc):
        for s in range(ns):
            z[c, s, 0] = zi[s, 0] * buf[0, c]
            z[c, s, 1] = zi[s, 1] * buf[0, c]
    _sections(sos, z, buf)
    back = buf[::-1].copy()
    for c in range(nc):
        for s in range(ns):
            z[c, s, 0] = zi[s, 0] * back[0, c]
            z[c, s, 1] = zi[s, 1] * back[0, c]
    _sections(sos, z, back)
    return back.T.copy()


def lowpass(x: np.ndarray, rate_hz: float, cutoff_hz: float, order: int = 2) -> np.ndarray:
    """``sosfiltfilt(butter(order, cutoff), x, axis=0)``: the same numbers in the same layout (a float64
    (T, channels) array longer than the pad; anything else goes through scipy)."""
    sos, zi, edge = _design(int(order), float(cutoff_hz), float(rate_hz))
    x = np.asarray(x)
    if x.ndim != 2 or x.dtype != np.float64 or x.shape[0] <= edge or x.shape[1] == 0:
        return sosfiltfilt(sos, x, axis=0)
    out = _filtfilt_columns(sos, zi, np.ascontiguousarray(x), edge)
    return out.T[::-1][edge:-edge]
