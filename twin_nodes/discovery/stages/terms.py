"""Stage 9, physics outside the effect list (``TermsInput`` -> ``Terms``): after the accepted effects are
refitted, the structured residual test and sparse term discovery (:mod:`twin_nodes.discovery.terms`) on
what the final vehicle leaves in the throttle channel; a term found is named, flown as the ``state_term``
effect (refitted with the accepted effects), and graded like any other finding: the closed-loop twin
flown on the held-out part with and without it, the equation error's held-out cut.

It runs on the report's result and adds ``terms`` to it; a term that is kept (``confirmed`` or
``likely``) also joins ``effects``, ``accepted`` / ``likely`` and ``refit_params``; a confirmed one's joint
refit is what the accepted effects then report (:func:`carry_to_findings`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin_nodes.discovery import terms as T
from twin_nodes.discovery.blocktest import not_significant
from twin_nodes.discovery.judging import MIN_REL_IMPROVEMENT, T_CHOICE, T_CRIT, Fit
from twin_nodes.discovery.residuals import modes, residual_channels
from twin_nodes.discovery.stages import closed_loop
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.discovery.stages.refit import _joint_refit
from twin_nodes.physics.effects import STATE_TERM_FEATURES, STATE_TERM_MEANING
from twin_nodes.vehicle.params import VehicleParams

#: a term not significant yet (t in T_CHOICE..T_CRIT) but cutting this much of the held-out residual is ``likely``
LIKELY_CUT = 0.30


@dataclass
class TermsInput:
    log: object                       # the FlightLog
    flight: PreparedFlight
    accepted: list[Fit]               # the vocabulary's kept effects
    current: VehicleParams            # the final refitted vehicle
    result: dict                      # the report's result (changed in place)
    closed_loop: bool = True


@dataclass
class Terms:
    result: dict


def run(inp: TermsInput) -> Terms:
    """Test what the refitted vehicle leaves for structure; find, name, fly and grade a term."""
    S, nominal, current = inp.flight, inp.flight.nominal, inp.current
    data = S.data
    norm = T.Normaliser.of(current)
    y_all, X_all = T.term_regressors(data, current, nominal, norm)
    feats_all = T.features_on_log(data, current, norm)
    step = max(int(round(1.0 / (data.dt * T.RATE_HZ))), 1)
    rows = np.flatnonzero(data.valid)[::step]
    fit_rows = S.fit_mask[rows]
    search = T.find_term(y_all[rows], X_all[rows], data.t[rows], fit_rows, feats_all[rows])
    out = {"method": _method(norm), "normalisation": {k: round(v, 4) for k, v in norm.fixed().items()},
           "test": _test_json(search), "found": []}
    out["brief_regimes"] = T.brief_regimes(y_all[rows], X_all[rows], data.t[rows], feats_all[rows], norm.v_h)
    inp.result["terms"] = out
    fit = search.best
    if fit is None or (search.why_none and not _likely(fit)):
        out["verdict"] = "none"
        out["why"] = search.why_none or "no feature set beats the constant on held-out blocks"
        return Terms(inp.result)
    named = T.name_term(fit, feats_all[rows], current.mass_kg * current.gravity_m_s2, norm.v_h)
    vp_term, theta = _fly(inp, fit, norm)
    entry = _grade(inp, fit, named, vp_term, theta, norm)
    out["found"].append(entry)
    out["verdict"] = entry["verdict"]
    if entry["verdict"] in ("confirmed", "likely"):
        _join(inp.result, entry, vp_term)
    return Terms(inp.result)


def _likely(fit: T.TermFit) -> bool:
    return T_CHOICE < fit.t_stat <= T_CRIT and fit.cut >= LIKELY_CUT and fit.gain_spread >= T.MIN_GAIN_SPREAD


def _fly(inp: TermsInput, fit: T.TermFit, norm: T.Normaliser) -> tuple[VehicleParams, dict]:
    """The vehicle with the term, its coefficients refitted with the accepted equation-error effects on
    the fit part (the twin flies exactly this)."""
    from twin_nodes.discovery.candidates import Candidate

    S = inp.flight
    names = ("c_one",) + tuple(f"c_{n}" for n in fit.names)
    theta0 = np.asarray(fit.coef, float)
    lo = np.array([-0.5] + [-10.0] * (len(names) - 1))
    hi = np.array([1.0] + [10.0] * (len(names) - 1))
    theta0 = np.clip(theta0, lo + 1e-9, hi - 1e-9)
    cand = Candidate("state_term", names, theta0, lo, hi, lambda th: inp.current, norm.fixed(),
                     lambda th: True, label="state_term")
    tf = Fit(cand, theta0.copy(), inp.current, 0.0, 0.0, np.zeros(0), fit.t_stat, fit.n_blocks, fit.cut, True)
    vp = _joint_refit(list(inp.accepted) + [tf], S.data, S.nominal, S.fit_mask)
    have = dict(vp.effects)
    for name, params in inp.current.effects:   # what the instrument stages set stays as they set it
        if name not in have:
            vp = vp.with_effect(name, **dict(params))
    return vp, dict(dict(vp.effects)["state_term"])


def _grade(inp: TermsInput, fit: T.TermFit, named: dict, vp_term: VehicleParams, theta: dict,
           norm: T.Normaliser) -> dict:
    """The term's entry: name, evidence, held-out numbers before/after, the closed-loop twin, verdict."""
    S, nominal = inp.flight, inp.flight.nominal
    before = modes(residual_channels(S.data, inp.current, nominal), nominal)[0][S.held_mask, 0]
    after = modes(residual_channels(S.data, vp_term, nominal), nominal)[0][S.held_mask, 0]
    rb, ra = float(np.sqrt(np.mean(before ** 2))), float(np.sqrt(np.mean(after ** 2)))
    entry = {"name": "state_term", "mechanism": named["mechanism"], "label": named["name"],
             "channel": "throttle", "features": fit.names,
             "feature_meaning": {n: STATE_TERM_MEANING[n] for n in fit.names},
             "params": {k: round(float(v), 6) for k, v in theta.items()},
             "named_evidence": named.get("evidence", ""), "parts": named.get("parts", {}),
             "heldout_t_stat": round(fit.t_stat, 2), "heldout_blocks": fit.n_blocks,
             "cv_improvement": round(fit.cut, 4), "gain_spread": round(fit.gain_spread, 4),
             "heldout_channel": "throttle", "heldout_before": round(rb, 5), "heldout_after": round(ra, 5),
             "heldout_improvement": round(1.0 - ra / rb, 4) if rb > 0 else 0.0, "residual": "equation"}
    why = []
    if inp.closed_loop:
        # (flown once per discover call: the refitted vehicle's run is cached, with its per-sample errors)
        m0 = closed_loop._closed_loop_metrics(inp.log, inp.current, *S.scored)
        m1 = closed_loop._closed_loop_metrics(inp.log, vp_term, *S.scored)
        closed_loop.reset()
        entry["closed_loop_heldout"] = {"before": m0, "after": m1}
        b, a = m0["throttle_rmse"], m1["throttle_rmse"]
        entry["closed_loop_throttle_cut"] = round(1.0 - a / b, 4) if b > 0 else 0.0
        diverged = _diverged(m0, m1)
        if diverged:
            entry["closed_loop_diverged"] = diverged
        # the guard's one rule (closed_loop._veto): a rise vetoes only beyond its own scatter, and only where the
        # twin flies the flight's controller and follows the flight
        vetoed, said = closed_loop._veto(m1, m0, m0, closed_loop.veto_standing(inp.log, m0, S.nominal))
        if vetoed:
            why.append(f"makes the closed-loop twin worse on the held-out part ({said})")
        elif said:
            entry["closed_loop_note"] = said
    verdict, why = _verdict(fit, entry["heldout_improvement"], why)
    entry["verdict"] = verdict
    entry["accepted"] = verdict == "confirmed"
    entry["verdict_note"] = "; ".join(why)
    feats = ", ".join(f"{n} ({STATE_TERM_MEANING[n]})" for n in fit.names)
    entry["evidence"] = (f"{named['name']}: a thrust multiplier in {feats}; held-out cut {100 * fit.cut:.0f} % "
                         f"(out-of-fold), t={fit.t_stat:.1f} over {fit.n_blocks} blocks; {named.get('evidence', '')}"
                         + (f"; {entry['verdict_note']}" if why else ""))
    return entry


def _verdict(fit: T.TermFit, heldout_cut: float, why: list[str]) -> tuple[str, list[str]]:
    """The term's verdict from the search's out-of-fold test (``fit``), the held-out cut of the term as flown
    (its coefficients fitted on the fit part, jointly with the accepted effects: ``heldout_cut`` on the flight's
    last part, the same held-out cut every vocabulary effect must pass) and the closed-loop veto (``why``).

    The search picks the best of up to 8 term sets on out-of-fold errors over the whole flight, so its t
    is the best of several tries; the flown term's cut on the held-out part is a second test it was not chosen
    on. A term whose flown version does not cut the held-out part by ``MIN_REL_IMPROVEMENT`` is rejected
    (measured: PX4 SIH no-effect y023, mu2+climb at t 3.72 but -16 % on the held-out part; every real term
    of the oov flights, RotorPy and the real take-off-and-land log cuts it by 57-96 %)."""
    why = list(why)
    if fit.t_stat <= T_CRIT:
        why.append(not_significant(fit.t_stat, fit.n_blocks))
    if fit.cut < MIN_REL_IMPROVEMENT:
        why.append(f"explains only {100 * fit.cut:.0f} % of the held-out residual")
    flown_short = not heldout_cut >= MIN_REL_IMPROVEMENT  # NaN (no held-out residual): not shown, so short
    if flown_short:
        why.append(f"the term as flown (fitted on the fit part) cuts the held-out part's throttle residual by "
                   f"{100 * heldout_cut:.0f} % < {int(100 * MIN_REL_IMPROVEMENT)} %")
    if not why:
        return "confirmed", why
    keep_likely = not flown_short and not any("worse" in w for w in why) and _likely(fit)
    return ("likely" if keep_likely else "rejected"), why


def _diverged(before: dict, after: dict) -> str:
    """Where the closed-loop twin left the flight (``divergence`` of its metrics) before or after the term: said,
    since its held-out numbers then compare runs that no longer follow the flight (e.g. a saturated vehicle's
    heading); empty when neither diverged."""
    said = [f"{k}: {d['cause']} at {d['t_s']:.1f} s" for k, d in (("before", before.get("divergence")),
                                                                   ("after", after.get("divergence"))) if d]
    return "; ".join(said)


def _join(result: dict, entry: dict, vp_term: VehicleParams) -> None:
    """A kept term is a finding like the others: listed with the effects, accepted or likely, flown."""
    result["effects"].append(entry)
    key = "accepted" if entry["verdict"] == "confirmed" else "likely"
    result.setdefault(key, []).append(f"state_term ({entry['label']})")
    if entry["verdict"] == "confirmed":
        result["refit_params"] = vp_term.to_ros_dict()
        carry_to_findings(result, vp_term)
        if "closed_loop_heldout" in entry:
            result.setdefault("after", {})["closed_loop_heldout"] = entry["closed_loop_heldout"]["after"]


def carry_to_findings(result: dict, vp_term: VehicleParams) -> None:
    """The accepted effects refitted jointly with a confirmed term report what the twin flies (``vp_term``), the
    values before the term kept as ``params_before_term``: the term takes up a throttle error the effects had
    absorbed alone (RotorPy o016: a vertical body drag only ``likely``, so the ground effect was fitted with the
    nominal c_dz and read height scale 0.941 for 0.841; refitted beside the term's climb multiplier 0.876).
    An effect accepted twice (two motors' efficiencies) keeps its own values."""
    flown = vp_term.effect_dict
    acc = [e for e in result.get("effects", []) if e.get("accepted") and e["name"] != "state_term"]
    names = [e["name"] for e in acc]
    for e in acc:
        new = flown.get(e["name"])
        if new is None or names.count(e["name"]) > 1:
            continue
        moved = {k: float(new[k]) for k, v in e["params"].items() if k in new and float(new[k]) != float(v)}
        if not moved:
            continue
        e["params_before_term"] = dict(e["params"])
        e["params"] = {**e["params"], **moved}
        prev = e.get("refitted_jointly_with")
        e["refitted_jointly_with"] = f"{prev}, state_term" if prev else "state_term"


def _test_json(search: T.TermSearch) -> dict:
    best = search.best
    return {"samples": search.n_samples, "null_mse": search.null_mse,
            "term_sets_tried": [{"features": f.names, "cv_improvement": round(f.cut, 4), "t": round(f.t_stat, 2),
                                 "blocks": f.n_blocks} for f in sorted(search.tried, key=lambda f: f.cv_mse)[:8]],
            "chosen": best.names if best else [], "structured": bool(best) and not search.why_none,
            "why_not": search.why_none}


def _method(norm: T.Normaliser) -> str:
    return (f"structured residual test and sparse term discovery on the throttle channel the refitted model "
            f"leaves: library {', '.join(STATE_TERM_FEATURES)} (thrust multipliers; v_h {norm.v_h:.2f} m/s from a "
            f"rotor radius of {norm.radius:.3f} m estimated from the rotor spacing), scikit-learn's LARS-lasso "
            f"path, least squares cross-validated over {T.GROUP_S:g} s groups ({T.N_FOLDS} folds), the smallest "
            f"set within one standard error; accepted at t > {T_CRIT:g} over {T.TEST_BLOCK_S:g} s blocks, a "
            f"held-out cut >= {int(100 * MIN_REL_IMPROVEMENT)} % and a thrust change >= "
            f"{100 * T.MIN_GAIN_SPREAD:g} % over the flight")


def summary_lines(res: dict) -> list[str]:
    """The terminal summary's lines for ``res['terms']``."""
    tr = res.get("terms")
    if not tr:
        return []
    brief = [f"    not testable: {b['note']}" for b in tr.get("brief_regimes") or []]
    if not tr.get("found"):
        return [f"  physics outside the effect list: none ({tr.get('why', '')})"] + brief
    lines = ["  physics outside the effect list (structured residual, sparse term):"] + brief
    for e in tr["found"]:
        lines.append(f"    {e['verdict'].upper():<9} {e['label']}  EE {100 * e['heldout_improvement']:.1f} % throttle  "
                     + ", ".join(f"{k}={v:.4g}" for k, v in e["params"].items() if k.startswith("c_")))
        lines.append(f"              {e['evidence']}")
        cl = e.get("closed_loop_heldout")
        if cl:
            lines.append(f"              closed-loop twin, held-out throttle RMSE {cl['before']['throttle_rmse']:.4f} -> "
                         f"{cl['after']['throttle_rmse']:.4f} ({100 * e['closed_loop_throttle_cut']:.0f} % lower)"
                         + (f"; the twin diverged ({e['closed_loop_diverged']}): these compare runs that left the "
                            "flight" if e.get("closed_loop_diverged") else ""))
    return lines


__all__ = ["TermsInput", "Terms", "carry_to_findings", "run", "summary_lines"]
