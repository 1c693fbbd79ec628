"""How well a flight shows an effect class, measured on the flight itself (issue 26: discovery that says what a
flight cannot show instead of finding nothing silently).

For an inertia axis the measure is its *visibility*: how far a reference change (that axis' inertia x1.3) moves
the axis' moment channel of the equation error (:func:`~twin_nodes.discovery.residuals.residual_channels`,
rotated into modes, 2 Hz low-pass) over the airborne samples, against the channel's noise in the same band,
as a matched filter's signal-to-noise ratio over the whole flight: RMS change / band noise x sqrt(2 f_c T).
The band noise is read from the flight: the channel's content above the low-pass corner (rotor and sensor
noise, broadband) scaled to the low-pass band's width (``sqrt(f_c / (f_N - f_c))`` for white noise).  Both
the change and the noise are properties of the flight and the nominal model, not of the hidden truth.

Under :data:`MIN_SNR` an axis is *barely excited*: the held-out third of the flight (35 %) would see a 30 %
change at under 6 x sqrt(0.35) = 3.5, at the held-out test's bar (t >= 3) before any model mismatch.  On the
seen grid batches (1-3, ``docs/discovery.md``): PX4 SIH take-off and land (M5) reads roll 4.2-5.7, pitch
3.3-8.6, yaw 2.5-5.2, and none of its eight inertia changes was found; every other SIH mission reads pitch
>= 11 and yaw >= 14 (roll 5.6-20: the yaw square M3 5.6-7.1, where a x1.6 roll change was found at 7.0);
RotorPy's hover with yaw reads yaw 4-489 (median over 30), roll and pitch 1.2 where no block is excited.
"""

from __future__ import annotations

import numpy as np

from twin_nodes.discovery.residuals import LOWPASS_HZ, EquationData, modes, residual_channels
from twin_nodes.vehicle.params import VehicleParams

#: the reference change of an inertia axis (the grids' inertia changes are x1.17 to x1.6)
INERTIA_STEP = 1.3
#: under this signal-to-noise ratio of a 30 % change over the flight an inertia axis is barely excited
#: (the module doc: the held-out part would see it at the held-out test's bar)
MIN_SNR = 6.0
_AXES = (("ixx", "roll", 1), ("iyy", "pitch", 2), ("izz", "yaw", 3))


def _band_noise(data: EquationData, vp: VehicleParams, M_lp: np.ndarray) -> np.ndarray:
    """Per mode, the RMS white noise that passes the residuals' low-pass (from the content above it)."""
    M_raw, _ = modes(residual_channels(data, vp, lowpass_hz=None), vp)
    hp = (M_raw - M_lp)[data.valid]
    f_n = 0.5 / data.dt
    if hp.size == 0 or f_n <= LOWPASS_HZ:
        return np.full(M_lp.shape[1], np.nan)
    return np.sqrt(np.mean(hp ** 2, axis=0)) * np.sqrt(LOWPASS_HZ / (f_n - LOWPASS_HZ))


def inertia_visibility(data: EquationData, vp: VehicleParams) -> dict[str, float]:
    """Per inertia axis (``ixx``, ``iyy``, ``izz``): the signal-to-noise ratio over the flight of the change a
    x1.3 inertia makes in that axis' moment channel (the module doc).  NaN where it cannot be read."""
    ok = data.valid
    if ok.sum() < 10:
        return {p: float("nan") for p, _, _ in _AXES}
    M0, _ = modes(residual_channels(data, vp), vp)
    noise = _band_noise(data, vp, M0)
    inertia = vp.inertia
    base = {"ixx": inertia[0, 0], "iyy": inertia[1, 1], "izz": inertia[2, 2]}
    out = {}
    for p, _, j in _AXES:
        changed = dict(base)
        changed[p] = INERTIA_STEP * base[p]
        M1, _ = modes(residual_channels(data, vp.with_effect("inertia", **changed), norm_params=vp), vp)
        move = float(np.sqrt(np.mean((M1[ok, j] - M0[ok, j]) ** 2)))
        out[p] = move / float(noise[j]) if noise[j] > 0 else float("nan")
    # a change of known shape stands out of band-limited noise over the flight by its RMS ratio times the
    # square root of the independent samples in the band (2 f_c T): the matched filter's signal-to-noise
    n_ind = 2.0 * LOWPASS_HZ * float(ok.sum()) * data.dt
    return {p: v * float(np.sqrt(n_ind)) for p, v in out.items()}


def barely_excited(data: EquationData, vp: VehicleParams, skip: set[str] = frozenset()) -> list[dict]:
    """``not_excited`` entries for the inertia axes whose visibility is under :data:`MIN_SNR` (``skip``: axes
    not to report, e.g. already reported as not excited at all or identified by a finding)."""
    from twin_nodes.discovery.locate import supply_for

    vis = inertia_visibility(data, vp)
    out = []
    for p, ax, _ in _AXES:
        v = vis[p]
        if p in skip or not np.isfinite(v) or v >= MIN_SNR:
            continue
        out.append({"effects": [f"inertia ({p})"], "visibility": round(v, 2),
                    "why": (f"barely excited: a {100 * (INERTIA_STEP - 1):.0f} % change of {p} stands out of the {ax} "
                            f"channel's noise by {v:.1f} over the flight (< {MIN_SNR:g})"),
                    "fly": supply_for(ax)})
    return out


__all__ = ["INERTIA_STEP", "MIN_SNR", "barely_excited", "inertia_visibility"]
