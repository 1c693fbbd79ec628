"""The ground effect's size from every low sample of the flight (issue 26, "discovery that generalizes").

A ground effect acts only within a few height scales of the ground, so on most missions it is seen at the
take-off and the landing alone.  The 2-fold cross-validation fits each fold on one of them (fold 1: the first
65 % of the flight, the take-off; fold 2: the last 65 %, the landing) and :func:`judging.assess` reports fold 1's
parameters: on a Crazyflie (height scale 0.15 m) fold 1 may hold 0.3 s within three height scales (r044) and
its coefficient and height scale slide along the ridge c exp(-h/h_s) = const (0.487/0.138 for 0.4/0.15).

So, once the cross-validated test has graded it (``confirmed`` or ``likely``: the acceptance is untouched), the
ground effect's parameters are fitted again on both folds' fit rows, every usable sample of the flight (the
take-off and the landing together): an accepted one jointly with the other accepted equation-error effects (at
cruise height a ground effect of a few arm lengths' scale is a near-constant thrust scale, which trades with a
sag or a thrust coefficient), a ``likely`` one on the vehicle it was judged on.  The entry says so
(``ground_fit``: what it was fitted on, the folds' own values) and what the flight pins (:func:`pinned`): a flight
whose low samples sit at one height (a low hover) pins the extra thrust at that height, not the coefficient and
the height scale apart; the manoeuvre that would is a hover at two low heights.

Before that refit, a mass or a thrust coefficient accepted beside the ground effect (chosen in a round without it)
is chosen again with it in (:func:`rechoose_scale`, tenth session: k014).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from twin_nodes.discovery.candidates import build_candidates
from twin_nodes.discovery.judging import Fit, assess, fit_candidate
from twin_nodes.discovery.residuals import residual_channels
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.discovery.stages.refit import _joint_refit
from twin_nodes.vehicle.params import VehicleParams

NAME = "ground_effect"
#: samples within this many (fitted) height scales of the ground carry the effect (exp(-3) = 5 % of it)
REACH_SCALES = 3.0
#: the flight tells the coefficient from the height scale where its heights, weighted by the effect's squared
#: sensitivity there (exp(-2h/h_s)), spread by at least this fraction of the height scale (a climb through the
#: whole reach: 0.5; a low hover at one height pins only c exp(-h/h_s) there: under 0.1)
MIN_SPREAD_SCALES = 0.25
#: the two scale effects that both move the thrust needed (mass: the collective only; thrust coefficient: every
#: rotor's thrust, so also the roll/pitch moments per command); beside a ground effect the one chosen before the
#: ground effect was in is chosen again with it (:func:`rechoose_scale`)
SCALE_PAIR = ("mass", "thrust_coefficient")
#: the other member replaces the chosen one where, refitted jointly with the ground effect on every usable sample,
#: it leaves at most this fraction of the chosen one's squared residual (k014: 0.11; k016, a true thrust
#: coefficient: the mass would leave 2.75 times the thrust coefficient's)
RECHOOSE_COST_RATIO = 0.8
#: and where they hold at least this long within reach: 0.42 s of one Crazyflie take-off and landing (k016,
#: heights spread 0.66 h_s) left c and h_s correlated -0.89 along the ridge, 0.448 / 0.143 for 0.4 / 0.1505;
#: 1.10 s (ra016, fast descents, spread 0.57) read 0.460 / 0.138, 15 / 8 % off (the extra thrust at h_ref 3.8 %);
#: the seen take-offs and landings of 1.54-1.66 s (x011, a011, ra030, i021, i034) read both within 7.7 %
MIN_LOW_S = 1.3
#: two folds give one degree of freedom: a range of one standard error's coverage (68.3 %) from them is the folds'
#: half-width times Student's t for 1 degree of freedom at that coverage, tan(pi/2 erf(1/sqrt 2)) = 1.837.  The
#: bare half-width (factor 1) left the truth outside on 6 of the 29 seen readings of batches 7-14 (ged17: at 1.22-1.77
#: times it; ra016 re-flown here: 1.69 / 1.68 in c / h_s), inside it at this factor on all of them
RIDGE_T = math.tan(0.5 * math.pi * math.erf(1.0 / math.sqrt(2.0)))
TWO_HEIGHTS = "hovers at two low heights (about 1 and 2 height scales up, a few seconds each)"


def gain(coefficient: float, height_scale: float, height) -> np.ndarray:
    """The thrust multiplier of :class:`physics.effects.GroundEffect`: 1 + c exp(-h / h_s), h clipped at 0."""
    h = np.maximum(np.asarray(height, float), 0.0)
    return 1.0 + coefficient * np.exp(-h / height_scale)


def pinned(height: np.ndarray, coefficient: float, height_scale: float, dt: float) -> dict:
    """What the flight's samples (``height``, m, one per ``dt`` s) pin of a ground effect ``coefficient``,
    ``height_scale``: their time within reach, their heights weighted by the effect's squared sensitivity
    (exp(-2h/h_s), :data:`MIN_SPREAD_SCALES`; and at least :data:`MIN_LOW_S` within reach), and whether the two
    parameters are told apart; where not, the
    extra thrust c exp(-h_ref/h_s) at the weighted mean height h_ref is what the flight determines."""
    h = np.asarray(height, float)
    h = np.maximum(h[np.isfinite(h)], 0.0)
    near = h < REACH_SCALES * height_scale
    out = {"low_s": round(float(near.sum() * dt), 2)}
    if near.sum() < 2:
        out.update(determined=False, note=f"no usable sample within {REACH_SCALES:g} height scales of the ground; "
                   f"to size it fly {TWO_HEIGHTS}")
        return out
    w = np.exp(-2.0 * h / height_scale)
    h_ref = float(np.sum(w * h) / np.sum(w))
    spread = float(np.sqrt(np.sum(w * (h - h_ref) ** 2) / np.sum(w))) / height_scale
    out.update(h_ref_m=round(h_ref, 3), spread_scales=round(spread, 3),
               gain_at_h_ref=round(float(gain(coefficient, height_scale, h_ref) - 1.0), 4))
    if spread >= MIN_SPREAD_SCALES and out["low_s"] < MIN_LOW_S:
        out.update(determined=False, note=(
            f"only {out['low_s']:g} s within {REACH_SCALES:g} height scales of the ground (under {MIN_LOW_S:g} s): "
            f"it pins the extra thrust near {h_ref:.2f} m ({100 * out['gain_at_h_ref']:.1f} %), the coefficient "
            f"and height scale only along c exp(-{h_ref:.2f}/h_s); to tell them apart fly {TWO_HEIGHTS}"))
    elif spread >= MIN_SPREAD_SCALES:
        out.update(determined=True, note=(f"coefficient and height scale told apart: {out['low_s']:g} s within "
                                          f"{REACH_SCALES:g} height scales, heights spread {spread:.2f} of it"))
    else:
        out.update(determined=False, note=(
            f"the low samples sit near {h_ref:.2f} m (spread {spread:.2f} height scales): they pin the extra "
            f"thrust there ({100 * out['gain_at_h_ref']:.1f} %), the coefficient and height scale only along "
            f"c exp(-{h_ref:.2f}/h_s); to tell them apart fly {TWO_HEIGHTS}"))
    return out


def along_ridge(pin: dict, params: dict, folds: list[dict]) -> dict | None:
    """Where the low flight pins only the extra thrust near ``h_ref`` (:func:`pinned`'s ``determined`` False), how
    far along the ridge c exp(-h_ref/h_s) = g the coefficient and height scale are read (i014: 0.357 / 0.170 for
    0.4 / 0.1505), as a relative half-width about the whole flight's reading, the larger of two:

    - the folds' own readings' distance from it (q030: folds 0.417 / 0.143 and 0.352 / 0.169, their extra thrust
      at h_ref 0.4 % apart: they slid along the ridge, not across it);
    - the slope of ln g(h) = ln c - h/h_s known to its level's error over the heights' spread sigma_h
      (least squares: sd(slope) = sd(level) / sigma_h): the height scale to ``gain_rel`` / ``spread_scales``,
      the coefficient (c = g exp(h_ref/h_s)) to the root sum of squares of ``gain_rel`` and h_ref/h_s times that;
      ``gain_rel``: the folds' extra thrust at h_ref, their difference over their mean (the whole difference: the
      folds share 30 % of the flight).

    Two folds give one degree of freedom, so the larger half-width is widened by :data:`RIDGE_T` (Student's t for
    one degree of freedom at one standard error's coverage): still a rough range from two readings, but one that
    does not claim the precision of a known spread (ra016: +- 8.5 % in c from the bare folds, the truth 14 % away).
    None: no folds or no low samples."""
    if len(folds) < 2 or "h_ref_m" not in pin or pin.get("spread_scales", 0.0) <= 0.0:
        return None
    h_ref, hs, c = pin["h_ref_m"], params["height_scale"], params["coefficient"]
    g = [float(gain(f["coefficient"], f["height_scale"], h_ref) - 1.0) for f in folds[:2]]
    if min(g) <= 0.0:
        return None
    gain_rel = abs(g[0] - g[1]) / (0.5 * (g[0] + g[1]))
    hs_rel = RIDGE_T * max(gain_rel / pin["spread_scales"], *(abs(f["height_scale"] / hs - 1.0) for f in folds[:2]))
    c_rel = RIDGE_T * max(float(np.hypot(gain_rel, h_ref / hs * gain_rel / pin["spread_scales"])),
                          *(abs(f["coefficient"] / c - 1.0) for f in folds[:2]))
    return {"gain_rel": round(gain_rel, 4), "height_scale_rel": round(hs_rel, 3), "coefficient_rel": round(c_rel, 3),
            "coefficient_range": [round(c * max(1 - c_rel, 0.0), 4), round(c * (1 + c_rel), 4)],
            "height_scale_range_m": [round(hs * max(1 - hs_rel, 0.0), 4), round(hs * (1 + hs_rel), 4)]}


def _rows(flight: PreparedFlight) -> np.ndarray:
    """Both folds' fit rows: every usable sample of the flight."""
    rows = np.zeros(flight.data.n, bool)
    for fit_mask, _ in flight.eq.folds:
        rows |= fit_mask
    return rows


def _refit(f: Fit, flight: PreparedFlight) -> None:
    """A graded ground effect that was not accepted (``likely``): its parameters fitted on both folds' fit rows
    on its own base (the vehicle it was judged on top of)."""
    folds = [f.candidate.params_dict(t) for t in f.fold_thetas]
    theta, _, _ = fit_candidate(f.candidate, flight.eq, flight.nominal, _rows(flight))
    f.theta = np.asarray(theta, float)
    _note(f, flight, folds, [])


def _note(f: Fit, flight: PreparedFlight, folds: list[dict], jointly: list[str]) -> None:
    """What ``f``'s parameters were fitted on and what the flight pins of them (``f.ground_fit``)."""
    p = f.candidate.params_dict(f.theta)
    on = ("both folds' fit parts, every usable sample of the flight (the take-off and the landing; each fold "
          "alone sees one of them)")
    pin = pinned(flight.data.height[_rows(flight)], p["coefficient"], p["height_scale"], flight.data.dt)
    ridge = along_ridge(pin, p, folds) if pin["determined"] is False else None
    if ridge is not None:
        pin.update(ridge=ridge, note=pin["note"] + (
            f"; read along it: coefficient {p['coefficient']:.3g} +- {100 * ridge['coefficient_rel']:.0f} %, height "
            f"scale {p['height_scale']:.3g} m +- {100 * ridge['height_scale_rel']:.0f} % (two folds' range, widened "
            f"x{RIDGE_T:.2f} for their one degree of freedom; their extra thrust there differs "
            f"{100 * ridge['gain_rel']:.1f} %)"))
    f.ground_fit = {"params_fitted_on": on + (f", jointly with {', '.join(jointly)}" if jointly else ""),
                    "fold_params": folds, **pin}


def _refit_cost(fits: list[Fit], flight: PreparedFlight, rows: np.ndarray) -> tuple[float, list[Fit]]:
    """``fits`` (copies) refitted jointly on ``rows``; their squared equation error there and the copies."""
    trial = [dataclasses.replace(f, theta=np.array(f.theta, float)) for f in fits]
    vp = _joint_refit(trial, flight.data, flight.nominal, rows)
    return float(np.sum(residual_channels(flight.data, vp, flight.nominal)[rows] ** 2)), trial


def rechoose_scale(flight: PreparedFlight, accepted: list[Fit], last: dict[str, Fit]) -> dict | None:
    """Beside an accepted ground effect, the member of :data:`SCALE_PAIR` chosen before it was in, chosen again
    with it.  A mass and a thrust coefficient both move the thrust needed, and on the collective alone they are
    one number (thrust per unit mass); the thrust coefficient also scales every rotor's share of the roll/pitch
    moments, the mass does not.  Chosen on a round without the ground effect, the two are "not told apart" (k014,
    a mass x1.15 beside a ground effect 0.4 / 0.84 m on a 1.45 m circle: cuts 36 and 39 %) and the ground effect is
    then fitted beside the wrong one, which its height scale bends to absorb (0.39 / 0.50, squared error 0.213;
    beside the mass 0.40 / 0.82, 0.023).  So both members are refitted jointly with the accepted equation-error
    effects on every usable sample; where the other leaves at most :data:`RECHOOSE_COST_RATIO` of the chosen
    one's squared error, it is judged on top of the others (its own cross-validated numbers) and, if it passes,
    replaces the chosen one in ``accepted`` and ``last`` (the chosen one is then graded against it).  Returns what
    was compared (None: no ground effect or no single member accepted)."""
    eq = [f for f in accepted if f.kind == "equation"]
    chosen = [f for f in eq if f.candidate.name in SCALE_PAIR]
    if len(chosen) != 1 or not any(f.candidate.name == NAME for f in eq):
        return None
    old, rows, m0 = chosen[0], _rows(flight), flight.nominal.mass_kg
    other = SCALE_PAIR[1 - SCALE_PAIR.index(old.candidate.name)]
    partner = next(c for c in build_candidates(flight.nominal, flight.data) if c.name == other)
    # the same thrust per unit mass: mass = m0 / kt_scale, kt_scale = m0 / mass
    x0 = np.clip([m0 / float(old.theta[0])], partner.lower, partner.upper)
    cost_old, _ = _refit_cost(accepted, flight, rows)
    cost_new, trial = _refit_cost([dataclasses.replace(old, candidate=partner, theta=x0) if f is old else f
                                   for f in accepted], flight, rows)
    out = {"chosen": old.candidate.name, "other": other, "squared_error": {old.candidate.name: round(cost_old, 6),
                                                                          other: round(cost_new, 6)}}
    if not cost_new <= RECHOOSE_COST_RATIO * cost_old:
        return {**out, "kept": old.candidate.name}
    base = flight.nominal
    for f, g in zip(accepted, trial):
        if f is not old:
            base = g.candidate.apply(base, g.theta)
    c = next(c for c in build_candidates(base, flight.data) if c.name == other)
    new = assess(c, flight.eq, flight.nominal, flight.eq.residual(base))
    if not new.passes:
        return {**out, "kept": old.candidate.name, "why": f"{other} on top of the others does not pass on its own"}
    new.base_vp, new.accepted = base, True
    new.theta = np.array(trial[accepted.index(old)].theta, float)
    old.accepted = False
    accepted[accepted.index(old)] = new
    last[other] = new
    return {**out, "kept": other}


def refit_accepted(flight: PreparedFlight, accepted: list[Fit], current: VehicleParams,
                   last: dict[str, Fit] | None = None) -> VehicleParams:
    """Where a ground effect is accepted on the equation error (and kept by the closed-loop check, which refits
    what it keeps on fold 1; its twin metrics are of those values): every accepted equation-error effect refitted
    jointly on both folds' fit rows (the joint refit of :mod:`.refit` on the whole flight), from their values in
    ``current``.  Jointly, because at cruise height a ground effect of a few arm lengths' scale is a near-constant
    thrust scale that trades with a sag's or a thrust coefficient's (w035: coefficient 0.355 with the sag held at
    its fold-1 value, 0.385 with the true sag, truth 0.4).  Returns the vehicle with all of them."""
    ground = [f for f in accepted if f.candidate.name == NAME and f.kind == "equation"]
    if not ground:
        return current
    folds = {id(f): [f.candidate.params_dict(t) for t in f.fold_thetas] for f in ground}
    scale = rechoose_scale(flight, accepted, last) if last is not None else None
    vp = _joint_refit(accepted, flight.data, flight.nominal, _rows(flight))
    for f in ground:
        f.vp = vp
        _note(f, flight, folds[id(f)], [g.candidate.name for g in accepted if g is not f and g.kind == "equation"])
        if scale is not None:
            f.ground_fit["scale_rechosen"] = scale
    return vp


def annotate(flight: PreparedFlight, ranked: list[Fit], effects: list[dict]) -> None:
    """Each graded ground effect's entry: a ``likely`` one refitted on the whole flight on its own base (an
    accepted one was, :func:`refit_accepted`), its parameters and what the flight pins written in."""
    for f, e in zip(ranked, effects):
        if f.candidate.name != NAME or f.kind != "equation" or e.get("verdict") not in ("confirmed", "likely"):
            continue
        if getattr(f, "ground_fit", None) is None:
            _refit(f, flight)
            p = f.candidate.params_dict(f.theta)
            e["evidence"] += (" Refitted on the whole flight: " + ", ".join(f"{k}={v:.4g}" for k, v in p.items())
                              + ".")
        e["params"] = f.candidate.params_dict(f.theta)
        e["ground_fit"] = f.ground_fit
