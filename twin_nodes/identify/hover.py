"""Hover: steady-hover segments of a flight, hover throttle, and the thrust coefficient.

Reference 2: in hover each of the N rotors carries ``m g / N`` at the hover speed
``omega_h``, so ``kt = m g / (N omega_h^2)`` (with per-rotor speeds,
``kt = m g / sum_i omega_i^2``).  Where rotor speed is not logged, the hover
throttle is reported instead and, given a parameter file, turned into the
parameter its thrust model needs (``thrust_max_n`` or ``kt`` through the file's
command map).

A sample is "steady hover" when the vehicle is airborne, its vertical speed and
(smoothed) vertical acceleration are small, its horizontal speed is small and,
if an attitude is given, it is nearly level; runs of such samples lasting at
least ``min_duration_s`` are the segments.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d

from twin_nodes.base.constants import G_STANDARD_M_S2

GRAVITY_DEFAULT = G_STANDARD_M_S2


@dataclass(frozen=True)
class HoverSegment:
    """One steady-hover stretch.  ``*_mean``/``*_std`` are over its samples.

    ``motors_*`` and ``rpm_*`` are per rotor (shape (N,)) or ``None`` when not given.
    """

    t_start_s: float
    t_end_s: float
    n: int
    throttle_mean: float
    throttle_std: float
    motors_mean: np.ndarray | None
    motors_std: np.ndarray | None
    rpm_mean: np.ndarray | None
    rpm_std: np.ndarray | None
    vz_rms_m_s: float
    vxy_mean_m_s: float

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s

    def as_dict(self) -> dict:
        def lst(a: np.ndarray | None) -> list[float] | None:
            return None if a is None else [float(v) for v in a]

        return {"t_start_s": float(self.t_start_s), "t_end_s": float(self.t_end_s),
                "duration_s": float(self.duration_s), "n": int(self.n),
                "throttle_mean": float(self.throttle_mean), "throttle_std": float(self.throttle_std),
                "motors_mean": lst(self.motors_mean), "motors_std": lst(self.motors_std),
                "rpm_mean": lst(self.rpm_mean), "rpm_std": lst(self.rpm_std),
                "vz_rms_m_s": float(self.vz_rms_m_s), "vxy_mean_m_s": float(self.vxy_mean_m_s)}


def tilt_deg(q_wxyz: np.ndarray) -> np.ndarray:
    """Angle between body z and world z [deg] for quaternions (n, 4) w,x,y,z (body -> world)."""
    q = np.asarray(q_wxyz, dtype=float)
    r22 = 1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2)
    return np.degrees(np.arccos(np.clip(r22, -1.0, 1.0)))


def hover_mask(t: np.ndarray, velocity_enu: np.ndarray, *, airborne: np.ndarray | None = None,
               attitude_q: np.ndarray | None = None, height_m: np.ndarray | None = None,
               min_height_m: float = 1.0, max_vz_m_s: float = 0.3,
               max_az_m_s2: float = 0.5, max_vxy_m_s: float = 0.5, max_tilt_deg: float | None = 10.0,
               smooth_s: float = 0.5) -> np.ndarray:
    """Per-sample steady-hover flag (n,) bool.

    ``t`` (n,) [s] increasing; ``velocity_enu`` (n, 3) [m/s]; ``airborne`` (n,) bool;
    ``attitude_q`` (n, 4) w,x,y,z body FLU -> world ENU; ``height_m`` (n,) height
    above the take-off point, which must exceed ``min_height_m`` (a land detector
    reports "airborne" while the vehicle still sits on its legs spinning up, and
    ground reaction would then carry part of the weight).  The vertical acceleration
    is the derivative of ``v_z`` after a ``smooth_s`` moving average; vertical and
    horizontal speeds are smoothed the same way.
    """
    t = np.asarray(t, dtype=float)
    v = np.asarray(velocity_enu, dtype=float)
    if v.shape != (t.size, 3):
        raise ValueError(f"velocity_enu has shape {v.shape}, expected ({t.size}, 3)")
    if t.size < 3:
        return np.zeros(t.size, dtype=bool)
    dt = float(np.median(np.diff(t)))
    w = max(1, int(round(smooth_s / dt)))
    finite = np.all(np.isfinite(v), axis=1)
    vf = np.where(finite[:, None], v, 0.0)
    vs = uniform_filter1d(vf, w, axis=0, mode="nearest")
    az = np.gradient(vs[:, 2], t)
    az = uniform_filter1d(az, w, mode="nearest")
    ok = finite & (np.abs(vs[:, 2]) <= max_vz_m_s) & (np.abs(v[:, 2]) <= 2 * max_vz_m_s)
    ok &= np.abs(az) <= max_az_m_s2
    ok &= np.hypot(vs[:, 0], vs[:, 1]) <= max_vxy_m_s
    if airborne is not None:
        ok &= np.asarray(airborne, dtype=bool)
    if attitude_q is not None and max_tilt_deg is not None:
        ok &= tilt_deg(attitude_q) <= max_tilt_deg
    if height_m is not None:
        h = np.asarray(height_m, dtype=float)
        ok &= np.isfinite(h) & (h >= min_height_m)
    return ok


def _runs(mask: np.ndarray, t: np.ndarray, max_gap_s: float) -> list[tuple[int, int]]:
    """[start, stop) index runs of True, broken also at time gaps > ``max_gap_s``."""
    brk = np.zeros(mask.size, dtype=bool)
    brk[1:] = np.diff(t) > max_gap_s
    runs = []
    start = None
    for i, m in enumerate(mask):
        if start is not None and (not m or brk[i]):
            runs.append((start, i))
            start = None
        if m and start is None:
            start = i
    if start is not None:
        runs.append((start, mask.size))
    return runs


def detect_hover_segments(t: np.ndarray, velocity_enu: np.ndarray, throttle: np.ndarray, *,
                          airborne: np.ndarray | None = None, attitude_q: np.ndarray | None = None,
                          motors: np.ndarray | None = None, rpm: np.ndarray | None = None,
                          min_duration_s: float = 3.0, trim_s: float = 0.3,
                          **mask_kw: float) -> list[HoverSegment]:
    """Steady-hover segments of at least ``min_duration_s`` (after trimming ``trim_s`` each end).

    ``throttle`` (n,) collective command [0..1]; ``motors`` (n, N) per-motor
    commands; ``rpm`` (n, N) rotor speeds [rev/min].  Other keywords go to
    :func:`hover_mask`.
    """
    t = np.asarray(t, dtype=float)
    thr = np.asarray(throttle, dtype=float).reshape(-1)
    if thr.size != t.size:
        raise ValueError(f"throttle has {thr.size} samples, t has {t.size}")
    mask = hover_mask(t, velocity_enu, airborne=airborne, attitude_q=attitude_q, **mask_kw)  # type: ignore[arg-type]
    mask &= np.isfinite(thr)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    v = np.asarray(velocity_enu, dtype=float)
    out = []
    for a, b in _runs(mask, t, 3 * dt):
        ta, tb = t[a] + trim_s, t[b - 1] - trim_s
        sel = np.arange(a, b)[(t[a:b] >= ta) & (t[a:b] <= tb)]
        if sel.size < 3 or t[sel[-1]] - t[sel[0]] < min_duration_s:
            continue

        def stats(x: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
            if x is None:
                return None, None
            xs = np.asarray(x, dtype=float)[sel]
            return np.nanmean(xs, axis=0), np.nanstd(xs, axis=0)

        mm, ms = stats(motors)
        rm, rs = stats(rpm)
        out.append(HoverSegment(
            t_start_s=float(t[sel[0]]), t_end_s=float(t[sel[-1]]), n=int(sel.size),
            throttle_mean=float(np.mean(thr[sel])), throttle_std=float(np.std(thr[sel])),
            motors_mean=mm, motors_std=ms, rpm_mean=rm, rpm_std=rs,
            vz_rms_m_s=float(np.sqrt(np.mean(v[sel, 2] ** 2))),
            vxy_mean_m_s=float(np.mean(np.hypot(v[sel, 0], v[sel, 1])))))
    return out


@dataclass(frozen=True)
class HoverSummary:
    """Duration-weighted hover throttle over all segments and its spread.

    ``between_std`` is the duration-weighted std of the segment means (how much
    hover throttle moved during the flight, e.g. battery sag); ``within_std`` the
    pooled std inside segments (control activity).
    """

    n_segments: int
    total_s: float
    throttle_mean: float
    between_std: float
    within_std: float

    def as_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def summarize_hover(segments: list[HoverSegment]) -> HoverSummary:
    if not segments:
        raise ValueError("no hover segments")
    w = np.array([s.duration_s for s in segments])
    m = np.array([s.throttle_mean for s in segments])
    sd = np.array([s.throttle_std for s in segments])
    mean = float(np.average(m, weights=w))
    between = float(np.sqrt(np.average((m - mean) ** 2, weights=w)))
    within = float(np.sqrt(np.average(sd ** 2, weights=w)))
    return HoverSummary(len(segments), float(w.sum()), mean, between, within)


def kt_from_hover(mass_kg: float, omega_rad_s: float | np.ndarray, n_rotors: int | None = None,
                  gravity_m_s2: float = GRAVITY_DEFAULT) -> float:
    """Thrust coefficient [N/(rad/s)^2] from hover: ``m g / (N omega^2)``.

    ``omega_rad_s`` is either the common hover speed (then ``n_rotors`` is needed)
    or the per-rotor speeds (N,), giving ``m g / sum omega_i^2``.
    """
    if not mass_kg > 0:
        raise ValueError(f"mass_kg must be > 0, got {mass_kg}")
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    if w.size == 1:
        if n_rotors is None or n_rotors < 1:
            raise ValueError("a single hover speed needs n_rotors >= 1")
        # The common-speed form is the parameter pipeline's (one home for the formula).
        from twin_nodes.vehicle.derive import kt_from_hover as _kt_common
        return float(_kt_common(mass_kg, float(w[0]), n_rotors, gravity_m_s2))
    denom = float(np.sum(w ** 2))
    if not denom > 0:
        raise ValueError("hover rotor speeds must not all be 0")
    return mass_kg * gravity_m_s2 / denom


def rpm_to_rad_s(rpm: np.ndarray | float) -> np.ndarray | float:
    return np.asarray(rpm, dtype=float) * (2.0 * math.pi / 60.0)


def kt_per_segment(segments: list[HoverSegment], mass_kg: float,
                   gravity_m_s2: float = GRAVITY_DEFAULT) -> np.ndarray:
    """``kt`` for each segment that has per-rotor RPM (NaN for the others)."""
    out = np.full(len(segments), np.nan)
    for i, s in enumerate(segments):
        if s.rpm_mean is not None and np.all(np.isfinite(s.rpm_mean)) and np.all(s.rpm_mean > 0):
            out[i] = kt_from_hover(mass_kg, rpm_to_rad_s(s.rpm_mean), gravity_m_s2=gravity_m_s2)
    return out


def params_from_hover_command(params: object, u_hover: float) -> dict[str, float]:
    """Rotor parameters that make ``params`` hover at per-motor command ``u_hover``.

    ``params`` is a :class:`twin_nodes.vehicle.params.VehicleParams`.  For the
    ``thrust_factor`` model this is ``thrust_max_n = m g / (N rel(u))`` with
    ``rel(u) = f u^2 + (1 - f) u``; for ``omega_squared`` it is
    ``kt = m g / (N omega_ref(u)^2)`` through the file's command map.
    """
    r = params.rotors  # type: ignore[attr-defined]
    t_hover = params.hover_thrust_per_rotor_n  # type: ignore[attr-defined]
    if not 0.0 < u_hover <= 1.0:
        raise ValueError(f"hover command must be in (0, 1], got {u_hover}")
    if r.thrust_model == "thrust_factor":
        f = r.thr_mdl_fac
        rel = f * u_hover ** 2 + (1.0 - f) * u_hover
        return {"thrust_max_n": float(t_hover / rel)}
    omega = float(r.reference_from_command(np.array(u_hover)))
    return {"kt_n_s2_rad2": float(t_hover / omega ** 2)}
