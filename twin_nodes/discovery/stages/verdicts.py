"""Stage 6, the verdicts: every candidate's latest fit graded ``confirmed`` / ``likely`` / ``rejected``
(physical range and resolution floor, held-out significance, what a ``likely`` one lacks), with the
other residual's view of it, ranked and written as the result's effect entries
(``GradeInput`` -> ``Verdicts``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from twin_nodes.discovery.blocktest import not_significant
from twin_nodes.discovery.judging import (MIN_REL_IMPROVEMENT, MOTOR_DYNAMICS, T_CRIT, _GRADE_ORDER, Fit, Judge,
                                          _mode_rms, _summary, _window_folds)
from twin_nodes.discovery.output_error import projected_view
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.discovery.stages.provisional import is_provisional
from twin_nodes.discovery.stages.joint import COLLECTIVE_SHAPES, contributions
from twin_nodes.discovery.verdicts import LIKELY_MIN_T, grade
from twin_nodes.physics.effects import EFFECTS
from twin_nodes.base.errors import ParamsError
from twin_nodes.vehicle.params import VehicleParams


@dataclass
class GradeInput:
    """The selection's fits after the closed-loop check."""

    flight: PreparedFlight
    accepted: list[Fit]               # what is kept (the closed-loop check may have dropped some)
    last: dict[str, Fit]              # report entry -> the latest fit of each candidate
    first_rank: list[str]             # round 1's order (the rejected are listed in it)
    base_held: np.ndarray             # the nominal's held-out equation error per channel


@dataclass
class Verdicts:
    """The graded fits, ranked, and their entries of the result (same order)."""

    ranked: list[Fit]
    effects: list[dict]
    accepted_labels: list[str]


def run(inp: GradeInput) -> Verdicts:
    """Grade, rank and describe every candidate's latest fit."""
    S, accepted, last = inp.flight, inp.accepted, inp.last
    eq, oe, vp, names, base_held = S.eq, S.oe, S.nominal, S.names, inp.base_held
    # grades: confirmed (accepted and kept), likely, rejected (with why); a provisional base (stages.provisional)
    # is in the model but graded on its own fit, never confirmed for what was found on top of it
    found = [f for f in accepted if not is_provisional(f)]
    acc_labels = [f.candidate.label for f in found]
    side_base: dict[tuple[int, str], np.ndarray] = {}   # (base vehicle, residual) -> that residual of it
    for f in last.values():
        if f in found:
            f.accepted = True
        elif f.accepted:
            f.accepted = False
        expl = None
        if not f.accepted and f.passes and acc_labels and f.closed_loop is None:
            expl = ", ".join(acc_labels)
        grade(f, T_CRIT, MIN_REL_IMPROVEMENT, S.excitation, expl)
        g = f.given_others
        if expl and g and g.get("t") is not None and g.get("cut") is not None:   # dropped given the others
            f.verdict_note += f" (given them: block t {g['t']:.2f}, held-out cut {100 * g['cut']:.1f} %)"
        if f.other is None:
            # the other residual's view of this fit, for the report
            judge = oe if f.kind == "equation" else eq
            if judge is not None:
                b = f.base_vp or vp
                key = (id(b), judge.kind)
                if key not in side_base:
                    side_base[key] = (judge.residual(b) if judge is eq else
                                      _scatter(judge.residual(b, judge.held_mask), judge.held_mask))
                f.other = _side(judge, f.vp, side_base[key], vp)
        f.evidence = _evidence(f, names, base_held)
    rank = {lab: i for i, lab in enumerate(inp.first_rank)}
    ranked = sorted(last.values(), key=lambda f: (_GRADE_ORDER[f.verdict],
                                                  acc_labels.index(f.candidate.label) if f.accepted else 0,
                                                  -f.rel_improvement if f.verdict != "rejected"
                                                  else rank.get(f.candidate.label, 99)))
    effects_out = [_effect_json(f, names, base_held) for f in ranked]
    for f, e in zip(ranked, effects_out):
        if f in accepted and len(accepted) > 1:
            # each effect's own held-out contribution: its cross-validated cut on top of those accepted before
            # it (the residual it was judged against already had them in)
            i = accepted.index(f)
            e["heldout_contribution"] = {"cut": round(float(f.rel_improvement), 4), "residual": f.kind,
                                         "on_top_of": [g.candidate.name for g in accepted[:i]]}
        if f in accepted and is_provisional(f):
            e["provisional"] = ("kept in the model as the base the effects after it were judged on; graded on its "
                                "own fit")
    _instrumented_views(S, ranked, effects_out)
    told_apart(effects_out)
    return Verdicts(ranked, effects_out, acc_labels)


def told_apart(effects_out: list[dict]) -> None:
    """A finding's ``not_told_apart`` rival that is itself confirmed (accepted beside it, fitted on top of it or
    jointly) was told apart by the flight: the pair is dropped (kept as ``told_apart_from``, the rival's
    single-fit values no finding claims).  q017 (a motor lag with an inertia, both confirmed): the lag's pair
    carried the inertia as it was fitted alone in the lag's place (Ixx +11 %), beside the inertia's own finding.
    Not between two effects on the collective force per unit mass (:data:`_COLLECTIVE`): the IMU does not tell
    those apart, so both accepted is a combination, not a separation (PX4 SIH t006: a battery sag ~ thrust
    coefficient 0.842 (truth 0.84), then a mass and a thrust coefficient 1.10 accepted on top of the sag), unless
    their regressors differ in shape (a battery sag follows the voltage, its level held at the full pack, while a
    thrust coefficient is constant: RotorPy w033, both confirmed and refitted jointly, kt 0.862 for 0.87)."""
    kinds = {_kind(e["name"]) for e in effects_out if e.get("verdict") == "confirmed"}
    for e in effects_out:
        pair = e.get("not_told_apart")
        if pair and {e["name"], pair["with"]["name"]} <= _COLLECTIVE and \
                COLLECTIVE_SHAPES[e["name"]] == COLLECTIVE_SHAPES[pair["with"]["name"]]:
            continue
        if pair and _kind(pair["with"]["name"]) in kinds - {_kind(e["name"])}:
            e["told_apart_from"] = {"name": pair["with"]["name"],
                                    "why": "confirmed as a finding of its own beside this one"}
            del e["not_told_apart"]


def given_the_others(v: Verdicts, eq: Judge, vp: VehicleParams, accepted: list[Fit]) -> None:
    """Each accepted equation-error effect's held-out contribution given all the others as well
    (:func:`~twin_nodes.discovery.stages.joint.contributions`), in its ``heldout_contribution``."""
    by_index = contributions(eq, vp, accepted)
    for f, e in zip(v.ranked, v.effects):
        if f in accepted and accepted.index(f) in by_index and "heldout_contribution" in e:
            e["heldout_contribution"]["given_the_others"] = by_index[accepted.index(f)]


def lag_delay_pair(v: Verdicts, eq: Judge, accepted: list[Fit]) -> list[dict]:
    """A motor lag and a delay both ``likely`` on the equation error, each fitted without the other (neither's
    base carries the other): one reading of the same residual twice, unless the weaker adds something given the
    stronger.  The weaker's held-out contribution given the stronger and the accepted effects
    (:func:`~twin_nodes.discovery.stages.joint.contributions` on the stronger's vehicle with the weaker added at
    its fit) keeps it when it still clears the ``likely`` bars (cut >= ``MIN_REL_IMPROVEMENT``, t >
    ``LIKELY_MIN_T``); otherwise it is reported as the stronger's ``not_told_apart`` partner, with the manoeuvre
    that separates them, and rejected as a finding of its own.  RotorPy o032 (sag + a 24 ms delay): the delay's
    joint variant cut 91 %, a lag's (tau 0.074 s) 46 %, both ``likely``, the lag adding nothing given the delay.
    Returns what was judged (one row per pair)."""
    by = {f.candidate.name: (f, e) for f, e in zip(v.ranked, v.effects)
          if f.candidate.name in MOTOR_DYNAMICS and e["verdict"] == "likely" and not f.accepted and f.kind == "equation"}
    in_a_base = {n for f, _ in by.values() if f.base_vp is not None for n, _ in f.base_vp.effects}
    if len(by) < 2 or in_a_base & set(MOTOR_DYNAMICS):
        return []
    (strong, es), (weak, ew) = sorted(by.values(), key=lambda fe: -fe[0].rel_improvement)
    own = {k: x for k, x in weak.candidate.params_dict(weak.theta).items()
           if k in EFFECTS[weak.candidate.name].param_names}
    base = [f for f in accepted if f.kind == "equation" and not is_provisional(f)]
    try:
        given = contributions(eq, strong.vp.with_effect(weak.candidate.name, **own), base + [strong, weak])
    except ParamsError:
        return []
    g = given.get(len(base) + 1) or {}
    row = {"kept": strong.candidate.name, "other": weak.candidate.name, "given_the_other": g}
    if g.get("cut") is not None and g.get("t") is not None and g["cut"] >= MIN_REL_IMPROVEMENT \
            and g["t"] > LIKELY_MIN_T:
        ew["given_the_other"] = row
        return [row]
    alt = {"name": weak.candidate.name, "params": own, "residual": weak.kind,
           "cv_improvement": round(float(weak.rel_improvement), 4), "given_the_other": g}
    es["alternatives"] = [alt] + [a for a in es.get("alternatives") or [] if a.get("name") != alt["name"]]
    strong.alternatives = es["alternatives"]
    pair = not_told_apart(es)
    if pair is not None:
        es["not_told_apart"] = pair
    weak.verdict = ew["verdict"] = "rejected"
    ew["verdict_note"] = (f"not told apart from {strong.candidate.name}: given it, held-out cut "
                          f"{100 * (g.get('cut') or 0.0):.0f} %, t {g.get('t')} (reported as its pair)")
    order = sorted(range(len(v.ranked)), key=lambda i: _GRADE_ORDER[v.ranked[i].verdict])
    v.ranked[:], v.effects[:] = [v.ranked[i] for i in order], [v.effects[i] for i in order]
    return [row]


def _instrumented_views(S: PreparedFlight, ranked: list[Fit], effects_out: list[dict]) -> None:
    """A motor lag or delay acts on every rotational axis: its held-out cut there in the
    instrument-projected error too, which the 50 Hz aliasing does not bound (reported only)."""
    if S.windows is not None:
        held_w = _window_folds(S.windows, S.t_split, S.t_split2)[0][1]
        for f, e in zip(ranked, effects_out):
            if e["verdict"] in ("confirmed", "likely") and f.candidate.name in MOTOR_DYNAMICS:
                view = projected_view(S.data, S.windows, f.base_vp or S.nominal, f.vp, held_w)
                if view is not None:
                    e.setdefault("residuals", {})["instrumented"] = view


def _side(judge: Judge, vp_c: VehicleParams, R0: np.ndarray, nominal: VehicleParams, rows=None) -> dict:
    """The other residual's held-out numbers (fold 1) at a fit: the mode it moves most."""
    rows = judge.held_mask if rows is None else rows
    R1 = judge.residual(vp_c, rows)
    r0, names = _mode_rms(R0[rows], nominal)
    r1, _ = _mode_rms(R1, nominal)
    k = int(np.argmax(r0 ** 2 - r1 ** 2))
    tot0 = float(np.sqrt(np.mean(R0[rows] ** 2)))
    tot1 = float(np.sqrt(np.mean(R1 ** 2)))
    return {"residual": judge.kind, "heldout_channel": names[k], "heldout_before": round(float(r0[k]), 5),
            "heldout_after": round(float(r1[k]), 5),
            "heldout_improvement": round(1.0 - float(r1[k]) / float(r0[k]), 4) if r0[k] > 0 else 0.0,
            "heldout_all_channels_improvement": round(1.0 - tot1 / tot0, 4) if tot0 > 0 else 0.0}


def _scatter(R_rows: np.ndarray, rows: np.ndarray) -> np.ndarray:
    out = np.zeros((rows.size, R_rows.shape[1]))
    out[rows] = R_rows
    return out


def _evidence(f: Fit, names: list[str], before_ch: np.ndarray) -> str:
    pretty = ", ".join(f"{k}={v:.4g}" for k, v in f.candidate.params_dict(f.theta).items())
    if f.kind == "equation":
        drop = before_ch - f.heldout_channels
        ch = names[int(np.argmax(drop))]
    else:
        ch = f"{f.judged[0]} (output error)"
    why = []
    if not f.above_floor:
        why.append("fitted size below the physical resolution floor")
    if f.at_bound:
        why.append("estimate pinned to the edge of the physical range")
    if f.unphysical:
        why.append(f"unphysical: {f.unphysical}")
    if f.closed_loop:
        why.append(f.closed_loop)
    if f.t_stat <= T_CRIT:
        why.append(not_significant(f.t_stat, f.n_blocks))
    if f.explains < MIN_REL_IMPROVEMENT:
        why.append(f"explains only {100 * f.explains:.0f} % of the held-out residual")
    reason = "; ".join(why) if why else f"t={f.t_stat:.1f} over {f.n_blocks} held-out blocks"
    verdict = f.verdict if f.verdict else ("accepted" if f.accepted else "rejected")
    if verdict == "confirmed":
        verdict = "accepted, confirmed"
    note = f"; {f.verdict_note}" if f.verdict in ("likely",) or (f.verdict == "rejected" and
                                                                  f.verdict_note.startswith("explained")) else ""
    alt = ""
    if f.alternatives:
        alt = " Not told apart from: " + ", ".join(
            f"{a['name']} ({', '.join(f'{k}={v:.4g}' for k, v in a['params'].items())}, {100 * a['cv_improvement']:.0f} %)"
            for a in f.alternatives) + "."
    return (f"{f.candidate.label} ({pretty}) cuts the held-out residual by {100 * f.rel_improvement:.0f} %, "
            f"mostly in {ch}: {verdict} ({reason}{note}).{alt}")


def _effect_json(f: Fit, names: list[str], base_held: np.ndarray) -> dict:
    jname, jb, ja = f.judged
    out = {
        "name": f.candidate.name,
        "accepted": bool(f.accepted),
        "verdict": f.verdict,
        "verdict_note": f.verdict_note,
        "params": f.candidate.params_dict(f.theta),
        "evidence": f.evidence,
        "residual": f.kind,
        "heldout_channel": jname,
        "heldout_before": round(jb, 5),
        "heldout_after": round(ja, 5),
        "heldout_units": (f"RMS {'equation' if f.kind == 'equation' else 'output'} error in the {jname} mode on "
                          "the held-out part, fraction of full motor output"),
        "heldout_improvement": round(1.0 - ja / jb, 4) if jb > 0 else 0.0,
        "heldout_t_stat": round(float(f.t_stat), 2) if math.isfinite(f.t_stat) else None,
        "cv_improvement": round(float(f.rel_improvement), 4),
        **({"cv_improvement_own_channels": round(float(f.own_cut), 4)} if f.own_cut is not None else {}),
        "above_resolution_floor": bool(f.above_floor),
        "excitation": f.excitation,
        "residuals": {f.kind: _summary(f)},
        "alternatives": f.alternatives,
    }
    if f.candidate.held:
        out["held_at_nominal"] = dict(f.candidate.held)
    if f.given_others:   # judged again given the other accepted effects (stages.inertia_given, .stand_in)
        out["given_others"] = {k: (round(float(v), 4) if isinstance(v, (int, float)) and not isinstance(v, bool)
                                   else v) for k, v in f.given_others.items()}
    if f.closed_loop:
        out["closed_loop"] = f.closed_loop
    if getattr(f, "closed_loop_note", None):
        out["closed_loop_note"] = f.closed_loop_note
    for key in ("joint_refit_of", "refitted_jointly_with", "rival_path", "drag_form", "pair_with"):   # stages.selection
        if getattr(f, key, None):
            out[key] = getattr(f, key)
    if f.verdict in ("confirmed", "likely"):
        pair = not_told_apart(out)
        if pair is not None:
            out["not_told_apart"] = pair
    if f.other is not None:
        out["residuals"][f.other["residual"]] = f.other
    if f.kind == "equation":
        out.update({
            "heldout_all_channels_before": round(float(np.sqrt(np.mean(base_held ** 2))), 5),
            "heldout_all_channels_after": round(float(f.heldout_rms), 5),
            "heldout_all_channels_improvement": round(float(f.heldout_cut), 4),
            "heldout_channels_before": {k: round(float(v), 5) for k, v in zip(names, base_held)},
            "heldout_channels_after": {k: round(float(v), 5) for k, v in zip(names, f.heldout_channels)},
        })
    else:
        out["heldout_all_channels_improvement"] = round(float(f.heldout_cut), 4)
    return out


# ---------------------------------------------------------------- pairs the flight does not tell apart
#
# Issue 26: where two candidates explain the same residual (a steady wind and a drag in steady flight, a motor
# lag and a pure delay), the finding names both and the manoeuvre that separates them, with its plan
# (discovery.plans), instead of silently picking one.

#: one class of drag (scoring calls them one class): an alternative within it is not a different effect
_DRAG = {"linear_drag", "rotor_drag", "body_drag"}
#: the manoeuvre that separates two effects (by the set of their names; drags as "drag")
SEPARATING = {
    frozenset({"wind", "drag"}): ("fast_legs", "legs in four directions at two speeds: a wind adds a force fixed "
                                               "in the world, a drag opposes each leg's own airspeed"),
    frozenset({"motor_time_constant", "actuator_delay"}): (
        "rate_doublets", "hard stops and sharp corners: a delay shifts the response, a lag rounds it"),
    frozenset({"battery_sag", "mass"}): ("vertical_steps", "collective steps: the sag follows the load's voltage "
                                                           "drop, a mass does not"),
    frozenset({"battery_sag", "thrust_coefficient"}): ("vertical_steps", "collective steps: the sag follows the "
                                                                         "voltage, a thrust coefficient does not"),
    frozenset({"ground_effect", "mass"}): ("low_hover", "hovering low and high: a ground effect fades with height"),
    frozenset({"ground_effect", "thrust_coefficient"}): ("low_hover", "hovering low and high: a ground effect "
                                                                      "fades with height"),
    frozenset({"yaw_moment", "inertia"}): ("yaw_sweeps", "yaw turns in place at several rates"),
    frozenset({"rotor_drag", "body_drag"}): ("fast_legs", "legs at two speeds: a rotor drag grows with the speed, "
                                                         "a body drag with its square"),
}


#: effects that act on the collective force per unit mass alone, which the IMU cannot tell apart on their own
_COLLECTIVE = {"mass", "thrust_coefficient", "battery_sag"}


def _kind(name: str) -> str:
    return "drag" if name in _DRAG else name


def not_told_apart(effect: dict, separating: tuple[str, str] | None = None) -> dict | None:
    """The first alternative of another kind than ``effect`` (``effect["alternatives"]``), as a pair with the
    manoeuvre that separates the two and that manoeuvre's plan; ``plan_flyable``: the plan passes the
    mission schema's checks (:func:`twin_nodes.mavlink.mission.plan_from_mapping`).  None: no such rival.
    ``separating``: (manoeuvre, why) where the pair's context, not its two names, says what separates them
    (stage 10's yaw pair beside a damping: roll/pitch rates, not yaw sweeps)."""
    from twin_nodes.discovery.plans import manoeuvre

    form = effect.get("drag_form") or {}   # stages.drag_form: the linear and the quadratic drag, not told apart
    for alt in effect.get("alternatives") or []:
        a, b = _kind(effect["name"]), _kind(alt.get("name", ""))
        forms = form and not form["told_apart"] and {effect["name"], alt.get("name")} == {"rotor_drag", "body_drag"}
        if (a == b and not forms) or {a, b} == {"mass", "thrust_coefficient"}:
            continue
        a, b = (effect["name"], alt["name"]) if forms else (a, b)
        kind, why = separating or SEPARATING.get(frozenset({a, b}), ("rate_doublets", "hard stops and sharp corners"))
        reps = {"fast_legs": 2, "rate_doublets": 6, "vertical_steps": 4, "low_hover": 4, "yaw_sweeps": 12}[kind]
        plan = {"mission": {"name": f"separate_{a}_{b}", "speed_m_s": 3.0, "acceptance_radius_m": 1.0,
                            "fly_through": False, "rtl_after": True, "waypoints": manoeuvre(kind, reps)}}
        return {"with": {"name": alt["name"], "params": alt.get("params") or {}},
                "manoeuvre": kind, "why": why, "plan": plan, "plan_flyable": _flyable(plan)}
    return None


def _flyable(plan: dict) -> bool:
    """The plan's waypoints are within what a multirotor mission flies: finite, 0.5-120 m above home, within
    500 m of it, 0 < speed <= 30 m/s, at most 500 items (the limits of the mission schema,
    ``twin_nodes.mavlink.mission``, which discovery does not import; tests check the two agree)."""
    import math

    wps = plan.get("mission", {}).get("waypoints") or []
    if not 0 < len(wps) <= 500:
        return False
    for w in wps:
        vals = [w.get("north_m"), w.get("east_m"), w.get("alt_m"), w.get("speed_m_s")]
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
            return False
        if not (0.5 <= w["alt_m"] <= 120.0 and math.hypot(w["north_m"], w["east_m"]) <= 500.0
                and 0.0 < w["speed_m_s"] <= 30.0):
            return False
    return True
