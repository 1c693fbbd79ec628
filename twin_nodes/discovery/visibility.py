"""How well a flight shows an effect class, measured on the flight itself (issue 26: discovery that says what a
flight cannot show instead of finding nothing silently).

For an inertia axis (and the yaw moment coefficient km) the measure is its *visibility*: how far a reference
change (that parameter x1.3) moves the axis' moment channel of the equation error (:func:`~twin_nodes.discovery.residuals.residual_channels`,
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
The yaw moment (km x1.3 on the yaw channel): M5 2.0-5.2 (its one yaw moment change, u019, not found), every
other SIH mission >= 15, RotorPy >= 64 where a yaw moment change was found (3.3-4.3 on three Crazyflie flights
whose yaw channel is that noisy).
"""

from __future__ import annotations

import numpy as np

from twin_nodes.discovery.residuals import LOWPASS_HZ, EquationData, modes, residual_channels
from twin_nodes.vehicle.params import VehicleParams

#: the reference change of a parameter (the grids' inertia and yaw moment changes are x1.17 to x1.6)
STEP = 1.3
#: under this signal-to-noise ratio of a 30 % change over the flight a parameter is barely excited
#: (the module doc: the held-out part would see it at the held-out test's bar)
MIN_SNR = 6.0
_AXES = (("ixx", "roll", 1), ("iyy", "pitch", 2), ("izz", "yaw", 3))


def band_noise(raw: np.ndarray, low: np.ndarray, dt: float) -> np.ndarray:
    """Per column, the RMS of white noise that passes the ``LOWPASS_HZ`` low-pass, from the content above it:
    ``raw`` the signal, ``low`` its low-passed copy (``residuals._lowpass``), ``dt`` the sample interval."""
    f_n = 0.5 / dt
    if raw.size == 0 or f_n <= LOWPASS_HZ:
        return np.full(low.shape[1], np.nan)
    return np.sqrt(np.mean((raw - low) ** 2, axis=0)) * np.sqrt(LOWPASS_HZ / (f_n - LOWPASS_HZ))


def _band_noise(data: EquationData, vp: VehicleParams, M_lp: np.ndarray) -> np.ndarray:
    M_raw, _ = modes(residual_channels(data, vp, lowpass_hz=None), vp)
    ok = data.valid_attitude
    return band_noise(M_raw[ok], M_lp[ok], data.dt)


def _changed(vp: VehicleParams) -> dict[str, tuple[VehicleParams, int, str]]:
    """Per parameter, the nominal with it x1.3 (``STEP``), the mode index (``modes``) it acts on and its axis."""
    inertia = vp.inertia
    base = {"ixx": inertia[0, 0], "iyy": inertia[1, 1], "izz": inertia[2, 2]}
    out = {}
    for p, ax, j in _AXES:
        changed = dict(base)
        changed[p] = STEP * base[p]
        out[p] = (vp.with_effect("inertia", **changed), j, ax)
    out["km"] = (vp.with_effect("yaw_moment", km=STEP * vp.rotors.km_m), 3, "yaw")
    return out


def visibility(data: EquationData, vp: VehicleParams) -> dict[str, float]:
    """Per parameter (the inertia axes ``ixx``, ``iyy``, ``izz`` and the yaw moment coefficient ``km``): the
    signal-to-noise ratio over the flight of the change a x1.3 of it makes in its moment channel (the module
    doc).  NaN where it cannot be read."""
    ok = data.valid_attitude  # moment channels
    changed = _changed(vp)
    if ok.sum() < 10:
        return {p: float("nan") for p in changed}
    M0, _ = modes(residual_channels(data, vp), vp)
    noise = _band_noise(data, vp, M0)
    # a change of known shape stands out of band-limited noise over the flight by its RMS ratio times the
    # square root of the independent samples in the band (2 f_c T): the matched filter's signal-to-noise
    root_n = float(np.sqrt(2.0 * LOWPASS_HZ * float(ok.sum()) * data.dt))
    out = {}
    for p, (vp_p, j, _) in changed.items():
        M1, _ = modes(residual_channels(data, vp_p, norm_params=vp), vp)
        move = float(np.sqrt(np.mean((M1[ok, j] - M0[ok, j]) ** 2)))
        out[p] = move / float(noise[j]) * root_n if noise[j] > 0 else float("nan")
    return out


def barely_excited(data: EquationData, vp: VehicleParams, skip: set[str] = frozenset()) -> list[dict]:
    """``not_excited`` entries for the parameters whose visibility is under :data:`MIN_SNR` (``skip``: parameters
    not to report, e.g. an axis already reported as not excited at all or one identified by a finding)."""
    from twin_nodes.discovery.locate import supply_for

    vis = visibility(data, vp)
    axis = {p: ax for p, (_, _, ax) in _changed(vp).items()}
    out = []
    for p, v in vis.items():
        if p in skip or not np.isfinite(v) or v >= MIN_SNR:
            continue
        out.append({"effects": ["yaw_moment" if p == "km" else f"inertia ({p})"], "visibility": round(v, 2),
                    "why": (f"barely excited: a {100 * (STEP - 1):.0f} % change of {p} stands out of the "
                            f"{axis[p]} channel's noise by {v:.1f} over the flight (< {MIN_SNR:g})"),
                    "fly": supply_for(axis[p])})
    return out


def _both_beyond(ratios: list[float], step: float) -> float | None:
    """The side (+1 up, -1 down) when every fold's ratio to the nominal is beyond ``step`` on that side, else None."""
    if len(ratios) < 2 or not all(np.isfinite(ratios)) or min(ratios) <= 0:
        return None
    if min(ratios) >= step:
        return 1.0
    if max(ratios) <= 1.0 / step:
        return -1.0
    return None


def yaw_moment_lean(effects: list[dict], km_nominal: float, yaw_gain: float | None = None) -> dict | None:
    """What a barely excited yaw moment's own equation-error fit still says (issue 26, ``m516``: PX4 SIH's take-off
    and land, ``docs/discovery.md``): a hint, never a finding.  The flight *leans* to a km change where the yaw
    moment candidate, judged in the yaw mode, moves km past the reference change (x``STEP`` or /``STEP``) the same
    way in both folds, with a positive held-out yaw cut and a held-out block statistic above the `likely` grade's
    (``verdicts.LIKELY_MIN_T``), and PX4's rate loop, where it read the flight, sees the yaw authority moved the
    same way (``yaw_gain`` > 1 for a larger km).  Measured on the seen M5 flights: the three with SIH_Q_MAX
    changed (b007, l017, l019, u019) fit km x1.44-x1.86 by fold for x1.3-x1.7 (t 2.1-5.1, rate-loop yaw x1.61-x1.85);
    the 22 without, x0.83-x1.31 (no flight with both folds past x1.3 or under /1.3).  None when it does not lean."""
    from twin_nodes.discovery.verdicts import LIKELY_MIN_T

    e = next((x for x in effects if x.get("name") == "yaw_moment"), None)
    eq = ((e or {}).get("residuals") or {}).get("equation") or {}
    if eq.get("heldout_channel") != "yaw" or not km_nominal > 0:
        return None
    ratios = [float(f.get("km", np.nan)) / km_nominal for f in eq.get("fold_params") or []]
    side = _both_beyond(ratios, STEP)
    t, cut = eq.get("heldout_t_stat"), eq.get("heldout_improvement") or 0.0
    if side is None or t is None or t <= LIKELY_MIN_T or cut <= 0:
        return None
    if yaw_gain is not None and np.isfinite(yaw_gain) and (yaw_gain - 1.0) * side <= 0:
        return None
    out = {"km_fold_ratios": [round(r, 3) for r in ratios], "heldout_t": t, "heldout_yaw_cut": cut}
    if yaw_gain is not None and np.isfinite(yaw_gain):
        out["rate_loop_yaw_gain"] = round(float(yaw_gain), 3)
    return out


def with_lean(entries: list[dict], effects: list[dict], km_nominal: float, yaw_gain: float | None = None) -> list[dict]:
    """``entries`` (``not_excited``) with the barely excited yaw moment's lean (:func:`yaw_moment_lean`) said in
    its ``why``: the flight carries a hint of the change it cannot size."""
    lean = yaw_moment_lean(effects, km_nominal, yaw_gain)
    if lean is None:
        return entries
    r = lean["km_fold_ratios"]
    rl = (f"; PX4's rate loop reads the yaw authority x{lean['rate_loop_yaw_gain']:.2f}"
          if "rate_loop_yaw_gain" in lean else "")
    say = (f"; the flight leans to km x{r[0]:.2f} / x{r[1]:.2f} by fold (held-out t {lean['heldout_t']:.1f}, "
           f"{100 * lean['heldout_yaw_cut']:.0f} % of the yaw mode{rl}): a hint it cannot size or test, not a finding")
    return [({**n, "why": n["why"] + say, "leans": lean} if n.get("effects") == ["yaw_moment"] else n)
            for n in entries]


__all__ = ["MIN_SNR", "STEP", "band_noise", "barely_excited", "visibility", "with_lean", "yaw_moment_lean"]
