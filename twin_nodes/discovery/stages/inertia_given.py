"""An ``inertia`` accepted on the output error, judged again given the effects accepted beside it.

Effects found on the output error keep the values they were fitted with (:mod:`.refit` refits the
equation-error ones only), and the selection judged each on top of what was accepted *before* it.  An
inertia accepted first is then never judged given an effect accepted after it that scales the rotors'
moments the same way: a battery sag (every rotor's thrust falls with the pack voltage, so the roll
authority per command falls, the footprint of a larger Ixx in the rate response).  Here each such
inertia's own parameters are put back at their nominal values in the final vehicle (the others as
refitted) and the output error of the two compared on the held-out blocks of both folds; below the
acceptance bar (``T_CRIT``, ``MIN_REL_IMPROVEMENT``) it is not kept: the graders then call it explained by
the others (:mod:`.verdicts`).  RotorPy a026 (battery sag + ground effect, fast descents): Ixx x1.21
accepted first on the roll output error (70 % cut, t 3.9) beside the sag confirmed after it."""

from __future__ import annotations

import numpy as np

from twin_nodes.discovery.blocktest import MIN_TEST_BLOCKS, _block_stats
from twin_nodes.discovery.candidates import Candidate
from twin_nodes.discovery.judging import MIN_REL_IMPROVEMENT, T_CRIT, Fit, Judge, fit_candidate
from twin_nodes.physics.effects import EFFECTS
from twin_nodes.vehicle.params import VehicleParams


def contribution(oe: Judge, vp: VehicleParams, f: Fit) -> dict:
    """``f``'s held-out output-error cut and block t in ``vp`` against ``vp`` with ``f``'s own parameters
    at the candidate's nominal values (both folds' test rows), and the active blocks the t is over.  Where the
    block test cannot run (under ``MIN_TEST_BLOCKS`` active blocks, or a t that is not finite) ``t`` is None and
    ``not_judged`` says why: x015 (Crazyflie, Ixx x1.6 beside a thrust coefficient) has the nominal inertia's
    open-loop roll diverge in three windows (block change 200-600, elsewhere 0.1-60), so the confined-change
    selection keeps 3 blocks and the t read 0.0, which dropped an inertia with a 99.6 % cut."""
    test = np.logical_or.reduce([t for _, t in oe.folds])   # both folds' held-out rows
    full, without = oe.residual(vp), oe.residual(f.at_nominal(vp))
    ok = np.isfinite(full).all(axis=1) & np.isfinite(without).all(axis=1)
    r0 = float(np.sqrt(np.mean(without[test & ok] ** 2)))
    r1 = float(np.sqrt(np.mean(full[test & ok] ** 2)))
    st = _block_stats(without, full, oe.blocks, 0.0)
    g = {"cut": round(1.0 - r1 / r0, 4) if r0 > 0 else 0.0, "t": None, "blocks": int(st["n"])}
    if not st["tested"]:
        g["not_judged"] = f"{st['n']} active held-out blocks (< {MIN_TEST_BLOCKS}): the block test did not run"
    elif not np.isfinite(st["t"]):
        g["not_judged"] = f"block t not finite over {st['n']} active blocks"
    else:
        g["t"] = round(float(st["t"]), 2)
    return g


def dropped(g: dict) -> bool:
    """Under the acceptance bar given the others: a cut under ``MIN_REL_IMPROVEMENT``, or a block t under
    ``T_CRIT`` where the block test ran.  Where it did not (``t`` None) the effect keeps the acceptance it had
    (its own block test passed) unless the cut alone fails: an untestable comparison is no evidence against it."""
    return g["cut"] < MIN_REL_IMPROVEMENT or (g["t"] is not None and g["t"] < T_CRIT)


#: effects that move the yaw axis only through the same ratio as the inertia's izz (yaw acceleration per command:
#: km T / izz): accepted after an inertia, they were fitted against its izz as it stood then
YAW_RATIO = ("yaw_moment",)


def _own(f: Fit, base: VehicleParams) -> tuple[Candidate, np.ndarray, list[int]]:
    """``f``'s own effect parameters as a plain candidate on ``base`` (from the values ``base`` carries), its
    start and their indices in ``f.theta`` (a joint variant also carries the effects it refitted)."""
    c = f.candidate
    own = [i for i, k in enumerate(c.param_names) if k in EFFECTS[c.name].param_names]
    names = tuple(c.param_names[i] for i in own)
    cur = dict(base.effect_dict.get(c.name) or {})
    x0 = np.array([cur.get(k, f.theta[i]) for k, i in zip(names, own)], float)
    fixed = {k: v for k, v in c.params_dict(f.theta).items() if k not in names}

    def build(th, base=base, name=c.name, names=names, fixed=fixed):
        return base.with_effect(name, **{**fixed, **{k: float(v) for k, v in zip(names, th)}})
    plain = Candidate(c.name, names, x0, c.lower[own], c.upper[own], build, fixed, lambda th: True, c.label)
    return plain, x0, own


def refit_given(judge: Judge, vp: VehicleParams, f: Fit) -> VehicleParams:
    """``vp`` with ``f``'s own parameters refitted on ``judge``'s fold-1 fit rows given the others as they are
    in ``vp`` (those it held stay held); where the refit does not lower the fit rows' residual, ``vp``."""
    plain, x0, own = _own(f, vp)
    rows = judge.folds[0][0]
    theta, vp_new, _ = fit_candidate(plain, judge, vp, rows)
    before, after = judge.residual(plain.build(x0), rows=rows), judge.residual(vp_new, rows=rows)
    ok = np.isfinite(before).all(axis=1) & np.isfinite(after).all(axis=1)
    if not ok.any() or np.sum(after[ok] ** 2) >= np.sum(before[ok] ** 2):
        return vp
    f.refit_given_others = {k: [round(float(a), 6), round(float(b), 6)]
                            for k, a, b in zip(plain.param_names, x0, theta)}
    f.theta = np.array(f.theta, float)
    f.theta[own] = theta
    f.vp = vp_new
    return vp_new


def run(oe: Judge | None, accepted: list[Fit], vp: VehicleParams,
        eq: Judge | None = None) -> tuple[list[Fit], VehicleParams]:
    """Each output-error inertia refitted given the other accepted effects, then dropped where it does not pass
    given them; a yaw moment accepted after it (:data:`YAW_RATIO`, with ``eq``) is refitted after it on the
    equation error and dropped likewise.  Returns the kept effects and their vehicle (a dropped effect back at
    nominal)."""
    if oe is None or len(accepted) < 2:
        return accepted, vp
    kept = list(accepted)
    for f in accepted:
        if f.candidate.name != "inertia" or f.kind != "output":
            continue
        later = [a for a in accepted[accepted.index(f) + 1:] if a.candidate.name in YAW_RATIO
                 and a.kind == "equation" and "izz" in f.candidate.param_names and eq is not None]
        trial = vp
        for a in later:      # fitted against the inertia's izz as it stood: at nominal while the inertia is refitted
            trial = a.at_nominal(trial)
        refit = refit_given(oe, trial, f) if later else trial
        if refit is trial:   # no later yaw moment, or the inertia does not take the yaw back: refitted beside it
            vp = refit_given(oe, vp, f)
        else:
            vp = refit
            for a in later:
                vp = refit_given(eq, vp, a)
                a.given_others = {**contribution(eq, vp, a), "residual": "equation"}
                if dropped(a.given_others):
                    vp = a.at_nominal(vp)
                    a.accepted = False
                    kept.remove(a)
        g = contribution(oe, vp, f)
        f.given_others = g
        if dropped(g):
            vp = f.at_nominal(vp)
            f.accepted = False
            kept.remove(f)
    return kept, vp


def annotate(ranked: list[Fit], effects: list[dict]) -> None:
    """Each re-judged inertia's numbers given the others in its entry (``given_the_others``, output error)."""
    for f, e in zip(ranked, effects):
        g = f.given_others
        if g is not None:
            e["given_the_others"] = {"residual": "output", **g, "kept": not dropped(g)}
