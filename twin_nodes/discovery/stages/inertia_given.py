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

from twin_nodes.discovery.blocktest import _block_stats
from twin_nodes.discovery.judging import MIN_REL_IMPROVEMENT, T_CRIT, Fit, Judge
from twin_nodes.vehicle.params import VehicleParams


def contribution(oe: Judge, vp: VehicleParams, f: Fit) -> dict:
    """``f``'s held-out output-error cut and block t in ``vp`` against ``vp`` with ``f``'s own parameters
    at the candidate's nominal values (both folds' test rows)."""
    c = f.candidate
    without_vp = c.apply(vp, np.clip(c.x0, c.lower, c.upper))
    test = np.zeros(oe.held_mask.shape, bool)
    for _, t in oe.folds:
        test |= t
    full, without = oe.residual(vp), oe.residual(without_vp)
    ok = np.isfinite(full).all(axis=1) & np.isfinite(without).all(axis=1)
    r0 = float(np.sqrt(np.mean(without[test & ok] ** 2)))
    r1 = float(np.sqrt(np.mean(full[test & ok] ** 2)))
    t = _block_stats(without, full, oe.blocks, 0.0)["t"]
    return {"cut": round(1.0 - r1 / r0, 4) if r0 > 0 else 0.0, "t": round(float(t), 2) if np.isfinite(t) else 0.0}


def run(oe: Judge | None, accepted: list[Fit], vp: VehicleParams) -> tuple[list[Fit], VehicleParams]:
    """Drop each output-error inertia that does not pass given the other accepted effects; returns the kept
    effects and their vehicle (the dropped inertia back at nominal)."""
    if oe is None or len(accepted) < 2:
        return accepted, vp
    kept = list(accepted)
    for f in accepted:
        if f.candidate.name != "inertia" or f.kind != "output":
            continue
        g = contribution(oe, vp, f)
        f.given_others = g
        if g["t"] < T_CRIT or g["cut"] < MIN_REL_IMPROVEMENT:
            vp = f.candidate.apply(vp, np.clip(f.candidate.x0, f.candidate.lower, f.candidate.upper))
            f.accepted = False
            kept.remove(f)
    return kept, vp


def annotate(ranked: list[Fit], effects: list[dict]) -> None:
    """Each re-judged inertia's numbers given the others in its entry (``given_the_others``, output error)."""
    for f, e in zip(ranked, effects):
        g = f.given_others
        if g is not None:
            e["given_the_others"] = {**g, "residual": "output",
                                     "kept": g["t"] >= T_CRIT and g["cut"] >= MIN_REL_IMPROVEMENT}
