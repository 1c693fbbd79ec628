"""The ground effect's size from every low sample of the flight (issue 26, "discovery that generalizes").

A ground effect acts only within a few height scales of the ground, so on most missions it is seen at the
take-off and the landing alone.  The 2-fold cross-validation fits each fold on one of them (fold 1: the first
65 % of the flight, the take-off; fold 2: the last 65 %, the landing) and :func:`judging.assess` reports fold 1's
parameters: on a Crazyflie (height scale 0.15 m) fold 1 may hold 0.3 s within three height scales (r044) and
its coefficient and height scale slide along the ridge c exp(-h/h_s) = const (0.487/0.138 for 0.4/0.15).

So, once the cross-validated test has graded it (``confirmed`` or ``likely``: the acceptance is untouched), the
ground effect's parameters are fitted again on both folds' fit rows, every usable sample of the flight (the
take-off and the landing together), the other accepted effects held at their refitted values.  The entry says
so (``params_fitted_on``) and says what the low flight pins (:func:`pinned`): a flight whose low samples sit at
one height (a low hover) pins the gain at that height, not the coefficient and the height scale apart; the
manoeuvre that would is a hover at two low heights.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from twin_nodes.discovery.judging import Fit, fit_candidate
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.vehicle.params import VehicleParams

NAME = "ground_effect"
#: samples within this many (fitted) height scales of the ground carry the effect (exp(-3) = 5 % of it)
REACH_SCALES = 3.0
#: the low samples' heights (10th to 90th percentile) must span at least this fraction of the height scale for
#: the flight to tell the coefficient from the height scale (a low hover at one height pins only their product)
MIN_SPAN_SCALES = 0.5
TWO_HEIGHTS = "hovering at two low heights (about 1 and 2 height scales up, a few seconds each)"


def gain(coefficient: float, height_scale: float, height) -> np.ndarray:
    """The thrust multiplier of :class:`physics.effects.GroundEffect`: 1 + c exp(-h / h_s), h clipped at 0."""
    h = np.maximum(np.asarray(height, float), 0.0)
    return 1.0 + coefficient * np.exp(-h / height_scale)


def pinned(height: np.ndarray, coefficient: float, height_scale: float, dt: float) -> dict:
    """What the low samples (``height``, m, one per ``dt`` s) pin of a ground effect ``coefficient``,
    ``height_scale``: their time within reach, the span of their heights, and whether the two parameters are
    told apart; where not, the gain c exp(-h_ref/h_s) at their median height is what the flight determines."""
    h = np.asarray(height, float)
    low = h[np.isfinite(h) & (h < REACH_SCALES * height_scale)]
    out = {"low_s": round(float(low.size * dt), 2)}
    if low.size < 2:
        out.update(determined=False, note=f"no usable sample within {REACH_SCALES:g} height scales of the ground; "
                   f"to size it fly {TWO_HEIGHTS}")
        return out
    q10, h_ref, q90 = (float(v) for v in np.percentile(low, [10, 50, 90]))
    span = (q90 - q10) / height_scale
    out.update(h_ref_m=round(h_ref, 3), span_scales=round(span, 2),
               gain_at_h_ref=round(float(gain(coefficient, height_scale, h_ref) - 1.0), 4))
    if span >= MIN_SPAN_SCALES:
        out.update(determined=True, note=f"coefficient and height scale from {out['low_s']:g} s flown between "
                   f"{q10:.2f} and {q90:.2f} m")
    else:
        out.update(determined=False, note=(
            f"the low samples sit near {h_ref:.2f} m (10-90 % within {q90 - q10:.2f} m, {span:.2f} height scales): "
            f"they pin the extra thrust there ({100 * out['gain_at_h_ref']:.1f} %), the coefficient and height "
            f"scale only along c exp(-{h_ref:.2f}/h_s); to tell them apart fly {TWO_HEIGHTS}"))
    return out


def _rows(flight: PreparedFlight) -> np.ndarray:
    """Both folds' fit rows: every usable sample of the flight."""
    rows = np.zeros(flight.data.n, bool)
    for fit_mask, _ in flight.eq.folds:
        rows |= fit_mask
    return rows


def _refit(f: Fit, flight: PreparedFlight, base: VehicleParams | None) -> None:
    """``f``'s parameters fitted on both folds' fit rows on top of ``base`` (None: its own base); its fold
    parameters are kept, the note of what was fitted where is set."""
    c = f.candidate
    if base is not None:
        c = dataclasses.replace(c, build=lambda th, b=base, cc=f.candidate: cc.apply(b, th))
    rows = _rows(flight)
    theta, _, _ = fit_candidate(c, flight.eq, flight.nominal, rows)
    folds = [f.candidate.params_dict(t) for t in f.fold_thetas]
    f.theta = np.asarray(theta, float)
    p = f.candidate.params_dict(f.theta)
    low = flight.data.height[rows]
    f.ground_fit = {"params_fitted_on": ("both folds' fit parts, every usable sample of the flight (the take-off "
                                         "and the landing): each fold alone sees one of them"),
                    "fold_params": folds,
                    **pinned(low, p["coefficient"], p["height_scale"], flight.data.dt)}


def refit_accepted(flight: PreparedFlight, accepted: list[Fit], current: VehicleParams) -> VehicleParams:
    """The accepted equation-error ground effect refitted on the whole flight, every other accepted effect held at
    its value in ``current``'s order (the joint refit's); returns the vehicle with all of them."""
    ground = [f for f in accepted if f.candidate.name == NAME and f.kind == "equation"]
    if not ground:
        return current
    base = flight.nominal
    for f in accepted:
        if f not in ground:
            base = f.candidate.apply(base, f.theta)
    for f in ground:
        _refit(f, flight, base)
    vp = base
    for f in ground:
        vp = f.candidate.apply(vp, f.theta)
        f.vp = vp
    return vp


def annotate(flight: PreparedFlight, ranked: list[Fit], effects: list[dict]) -> None:
    """Each graded ground effect's entry: a ``likely`` one refitted on the whole flight on its own base (an
    accepted one was, :func:`refit_accepted`), its parameters and what the flight pins written in."""
    for f, e in zip(ranked, effects):
        if f.candidate.name != NAME or f.kind != "equation" or e.get("verdict") not in ("confirmed", "likely"):
            continue
        if getattr(f, "ground_fit", None) is None:
            _refit(f, flight, None)
            p = f.candidate.params_dict(f.theta)
            e["evidence"] += (" Refitted on the whole flight: " + ", ".join(f"{k}={v:.4g}" for k, v in p.items())
                              + ".")
        e["params"] = f.candidate.params_dict(f.theta)
        e["ground_fit"] = f.ground_fit
