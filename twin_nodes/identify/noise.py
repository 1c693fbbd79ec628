"""IMU noise from a stationary recording: bias, white noise, Allan deviation.

Reference 2 models each gyro and accelerometer axis as ``true + bias + white
Gaussian noise`` and estimates bias and noise std from a stationary recording
(10 min at 100 Hz there).  On top of that this module computes the overlapping
Allan deviation per axis and reads off

- angle / velocity random walk ``N``: the value of the ``-1/2``-slope line at
  ``tau = 1 s`` (white noise of std ``sigma`` sampled at ``fs`` gives
  ``adev(tau) = sigma / sqrt(tau fs)``, so ``N = sigma / sqrt(fs)``), in
  rad/s/sqrt(Hz) or m/s^2/sqrt(Hz);
- bias instability ``B = min(adev) / 0.664`` (the flat bottom of the curve).
  If the curve is still falling at the longest tau the record is too short to
  show the floor; ``B`` is then an upper bound and ``bias_instability_bounded``
  says so.

The accelerometer measures specific force, so at rest its mean is ``bias + g``
along body up.  With one stationary orientation a horizontal bias cannot be told
from a small tilt: ``accel_reference="mean_direction"`` (default) removes ``g``
along the measured mean direction, which attributes only the magnitude error to
bias; ``"level"`` assumes the body is level (FLU: ``(0, 0, +g)``).

The output of :func:`sensors_block` is the ``sensors:`` block of a parameter file
(per-axis lists in body FLU).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin_nodes.base.constants import G_STANDARD_M_S2

GRAVITY_DEFAULT = G_STANDARD_M_S2
BIAS_INSTABILITY_FACTOR = 0.664  # adev floor = sqrt(2 ln 2 / pi) B


@dataclass(frozen=True)
class AllanResult:
    """Overlapping Allan deviation of one signal; ``adev`` shape (n_tau, k) for k axes."""

    taus_s: np.ndarray
    adev: np.ndarray
    rate_hz: float
    random_walk: np.ndarray        # N per axis [unit/sqrt(Hz)]
    bias_instability: np.ndarray   # B per axis [unit]
    bias_instability_tau_s: np.ndarray
    bias_instability_bounded: np.ndarray  # True where a minimum was found inside the tau range


def allan_deviation(x: np.ndarray, rate_hz: float, taus_s: np.ndarray | None = None,
                    n_taus: int = 40, max_fraction: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of rate samples ``x`` (n,) or (n, k) at ``rate_hz``.

    ``sigma^2(tau) = 1 / (2 tau^2 (n - 2m)) sum_k (theta[k+2m] - 2 theta[k+m] + theta[k])^2``
    with ``theta`` the integrated signal and ``tau = m / rate_hz``.  Default taus:
    ``n_taus`` log-spaced cluster sizes from 1 sample to ``max_fraction`` of the record.
    Returns ``(taus_s (n_tau,), adev (n_tau, k))`` (``k = 1`` for 1-D input).
    """
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    n = x.shape[0]
    if n < 8:
        raise ValueError(f"need at least 8 samples for an Allan deviation, got {n}")
    if not np.all(np.isfinite(x)):
        raise ValueError("samples contain non-finite values")
    fs = float(rate_hz)
    if taus_s is None:
        m_max = max(1, int(max_fraction * n))
        ms = np.unique(np.round(np.geomspace(1, m_max, n_taus)).astype(int))
    else:
        ms = np.unique(np.round(np.asarray(taus_s) * fs).astype(int))
        ms = ms[(ms >= 1) & (2 * ms < n)]
    theta = np.concatenate((np.zeros((1, x.shape[1])), np.cumsum(x, axis=0) / fs))
    adev = np.empty((ms.size, x.shape[1]))
    for i, m in enumerate(ms):
        d = theta[2 * m:] - 2.0 * theta[m:-m] + theta[:-2 * m]
        tau = m / fs
        adev[i] = np.sqrt(np.sum(d * d, axis=0) / (2.0 * tau * tau * d.shape[0]))
    return ms / fs, adev


def analyse_allan(taus_s: np.ndarray, adev: np.ndarray, rate_hz: float) -> AllanResult:
    """Random walk (``-1/2`` line at tau = 1 s) and bias instability per axis."""
    taus = np.asarray(taus_s, dtype=float)
    adev = np.asarray(adev, dtype=float)
    if adev.ndim == 1:
        adev = adev[:, None]
    k = adev.shape[1]
    n_rw = np.empty(k)
    b = np.empty(k)
    b_tau = np.empty(k)
    bounded = np.zeros(k, dtype=bool)
    lt = np.log10(taus)
    for j in range(k):
        la = np.log10(adev[:, j])
        slope = np.gradient(la, lt) if taus.size > 2 else np.full(taus.size, -0.5)
        white = np.abs(slope + 0.5) <= 0.15
        if not np.any(white):
            white = np.zeros(taus.size, dtype=bool)
            white[: max(1, taus.size // 5)] = True
        # log N = log adev + 0.5 log tau on the -1/2 segment (geometric mean)
        n_rw[j] = 10 ** np.median(la[white] + 0.5 * lt[white])
        i = int(np.argmin(adev[:, j]))
        b[j] = adev[i, j] / BIAS_INSTABILITY_FACTOR
        b_tau[j] = taus[i]
        bounded[j] = 0 < i < taus.size - 1
    return AllanResult(taus_s=taus, adev=adev, rate_hz=float(rate_hz), random_walk=n_rw,
                       bias_instability=b, bias_instability_tau_s=b_tau, bias_instability_bounded=bounded)


@dataclass(frozen=True)
class ImuNoise:
    """Bias, white-noise std and Allan analysis of a stationary gyro + accelerometer record (FLU)."""

    rate_hz: float
    n: int
    duration_s: float
    gyro_bias_rad_s: np.ndarray
    gyro_noise_rad_s: np.ndarray
    accel_mean_m_s2: np.ndarray
    accel_bias_m_s2: np.ndarray
    accel_noise_m_s2: np.ndarray
    gyro_allan: AllanResult
    accel_allan: AllanResult
    accel_reference: str

    def as_dict(self) -> dict:
        def lst(a: np.ndarray) -> list:
            return [float(v) for v in np.ravel(a)]

        return {
            "rate_hz": self.rate_hz, "n": self.n, "duration_s": self.duration_s,
            "accel_reference": self.accel_reference,
            "gyro_bias_rad_s": lst(self.gyro_bias_rad_s), "gyro_noise_rad_s": lst(self.gyro_noise_rad_s),
            "accel_mean_m_s2": lst(self.accel_mean_m_s2), "accel_bias_m_s2": lst(self.accel_bias_m_s2),
            "accel_noise_m_s2": lst(self.accel_noise_m_s2),
            "gyro_arw_rad_s_sqrt_hz": lst(self.gyro_allan.random_walk),
            "accel_vrw_m_s2_sqrt_hz": lst(self.accel_allan.random_walk),
            "gyro_bias_instability_rad_s": lst(self.gyro_allan.bias_instability),
            "gyro_bias_instability_tau_s": lst(self.gyro_allan.bias_instability_tau_s),
            "gyro_bias_instability_bounded": [bool(v) for v in self.gyro_allan.bias_instability_bounded],
            "accel_bias_instability_m_s2": lst(self.accel_allan.bias_instability),
            "accel_bias_instability_tau_s": lst(self.accel_allan.bias_instability_tau_s),
            "accel_bias_instability_bounded": [bool(v) for v in self.accel_allan.bias_instability_bounded],
        }


def imu_noise(gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, rate_hz: float, *,
              gravity_m_s2: float = GRAVITY_DEFAULT,
              accel_reference: str | np.ndarray = "mean_direction") -> ImuNoise:
    """Per-axis bias and white-noise std, plus Allan analysis, of stationary IMU samples.

    ``gyro_rad_s`` and ``accel_m_s2`` (n, 3) body FLU, uniformly sampled at
    ``rate_hz``.  Noise std is taken after removing a linear trend (slow
    temperature drift is not white noise).  ``accel_reference`` is
    ``"mean_direction"``, ``"level"`` or the expected specific force (3,).
    """
    g = np.asarray(gyro_rad_s, dtype=float)
    a = np.asarray(accel_m_s2, dtype=float)
    if g.ndim != 2 or g.shape[1] != 3 or a.shape != g.shape:
        raise ValueError(f"gyro and accel must both be (n, 3); got {g.shape} and {a.shape}")
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    n = g.shape[0]
    gb = g.mean(axis=0)
    am = a.mean(axis=0)
    if isinstance(accel_reference, str):
        if accel_reference == "mean_direction":
            ref = gravity_m_s2 * am / np.linalg.norm(am)
        elif accel_reference == "level":
            ref = np.array([0.0, 0.0, gravity_m_s2])
        else:
            raise ValueError(f"accel_reference must be 'mean_direction', 'level' or a 3-vector, got {accel_reference!r}")
        ref_name = accel_reference
    else:
        ref = np.asarray(accel_reference, dtype=float).reshape(3)
        ref_name = "given"

    def detrended_std(x: np.ndarray) -> np.ndarray:
        k = np.arange(x.shape[0], dtype=float)
        coef = np.polyfit(k, x, 1)
        return (x - (np.outer(k, coef[0]) + coef[1])).std(axis=0, ddof=1)

    taus, gad = allan_deviation(g, rate_hz)
    taus_a, aad = allan_deviation(a, rate_hz)
    return ImuNoise(rate_hz=float(rate_hz), n=n, duration_s=n / float(rate_hz),
                    gyro_bias_rad_s=gb, gyro_noise_rad_s=detrended_std(g),
                    accel_mean_m_s2=am, accel_bias_m_s2=am - ref, accel_noise_m_s2=detrended_std(a),
                    gyro_allan=analyse_allan(taus, gad, rate_hz),
                    accel_allan=analyse_allan(taus_a, aad, rate_hz), accel_reference=ref_name)


def sensors_block(res: ImuNoise) -> dict:
    """The ``sensors:`` block of a parameter file (a simulator adds bias + white noise per axis).

    Per-axis keys are lists [x, y, z] (body FLU); the Allan quantities are the
    mean over the three axes (per-axis values are in ``ImuNoise.as_dict``).
    """
    def lst(v: np.ndarray) -> list[float]:
        return [float(e) for e in v]

    return {
        "gyro_noise_rad_s": lst(res.gyro_noise_rad_s),
        "gyro_bias_rad_s": lst(res.gyro_bias_rad_s),
        "accel_noise_m_s2": lst(res.accel_noise_m_s2),
        "accel_bias_m_s2": lst(res.accel_bias_m_s2),
        "gyro_arw_rad_s_sqrt_hz": float(np.mean(res.gyro_allan.random_walk)),
        "accel_vrw_m_s2_sqrt_hz": float(np.mean(res.accel_allan.random_walk)),
        "gyro_bias_instability_rad_s": float(np.mean(res.gyro_allan.bias_instability)),
        "accel_bias_instability_m_s2": float(np.mean(res.accel_allan.bias_instability)),
        "sample_rate_hz": float(res.rate_hz),
    }


def stationary_runs(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, *, window_s: float = 1.0,
                    gyro_std_max: float = 0.02, accel_std_max: float = 0.15,
                    gyro_abs_max: float = 0.1, min_duration_s: float = 2.0) -> list[tuple[int, int]]:
    """Index runs ``[a, b)`` where the IMU looks stationary (handled/moved stretches excluded).

    A sample is stationary when the moving std over ``window_s`` of every gyro
    axis is below ``gyro_std_max`` [rad/s], of the accelerometer magnitude below
    ``accel_std_max`` [m/s^2], and the gyro magnitude below ``gyro_abs_max``.
    """
    from scipy.ndimage import uniform_filter1d

    t = np.asarray(t, dtype=float)
    g = np.asarray(gyro, dtype=float)
    a = np.asarray(accel, dtype=float)
    if t.size < 3:
        return []
    dt = float(np.median(np.diff(t)))
    w = max(3, int(round(window_s / dt)))

    def mstd(x: np.ndarray) -> np.ndarray:
        m = uniform_filter1d(x, w, axis=0, mode="nearest")
        m2 = uniform_filter1d(x * x, w, axis=0, mode="nearest")
        return np.sqrt(np.maximum(m2 - m * m, 0.0))

    ok = np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(a), axis=1)
    gz = np.where(ok[:, None], g, 0.0)
    az = np.where(ok[:, None], a, 0.0)
    ok &= np.all(mstd(gz) <= gyro_std_max, axis=1)
    ok &= mstd(np.linalg.norm(az, axis=1)) <= accel_std_max
    ok &= np.linalg.norm(gz, axis=1) <= gyro_abs_max
    runs = []
    start = None
    gap = np.zeros(t.size, dtype=bool)
    gap[1:] = np.diff(t) > 5 * dt
    for i in range(t.size):
        if start is not None and (not ok[i] or gap[i]):
            runs.append((start, i))
            start = None
        if ok[i] and start is None:
            start = i
    if start is not None:
        runs.append((start, t.size))
    return [(a0, b0) for a0, b0 in runs if t[b0 - 1] - t[a0] >= min_duration_s]
