"""An equation-error effect accepted before others, judged again given all of them.

The selection judges each effect on top of what was accepted *before* it, so the first one accepted takes up
what a later one explains better, and the joint refit then reads it back at about its nominal value, but it
stays accepted, first in the findings.  On the seen RotorPy batches 7-13 the four such findings are all a third
effect on top of two true ones, both named: o027 (a weak motor 4 x0.85 + ground effect) a CoM offset refitted
to (0.03, 0.04) mm; i029 (thrust coefficient + CoM offset) a motor efficiency refitted to 0.99985; c033 (body
drag + ground effect) a thrust coefficient refitted to 0.99883; o035 (rotor drag + yaw moment) an inertia
refitted to x1.00/1.00/1.01.

Here every accepted equation-error effect that has another accepted after it is judged given all the others
(:func:`.joint.contributions`: the final vehicle against the same vehicle with it at nominal, the others refitted
on each fold, over both folds' held-out blocks).  One that is neither significant (block t <= ``T_CRIT``) nor
cuts ``MIN_REL_IMPROVEMENT`` of the held-out residual given them is a stand-in: it is put back at nominal in the
vehicle and not kept, and the graders call it explained by the others (:mod:`.verdicts`).  One at a time, the
weakest first, judged again after each drop (two stand-ins for each other are not both dropped on one reading).

Both bars, not either (seen numbers given the others, RotorPy batches 2-13, 245 readings): the t bar alone would
drop w033's true battery sag, accepted first (t 2.93, cut 95 %); true effects accepted last read small cuts with a
large t (yaw moments g019, c019, e016, x016: cut 1.8-8.9 %, t 5.3-6.1), so a small cut alone is no evidence
against an effect; on PX4 SIH true effects accepted first do too (d019, f011 angular damping beside an inertia,
cut 3.1 / 4.4 %, t 6.5 / 9.5).  Where the block test did not run (``t`` None) the effect is kept.  The four
stand-ins read t -1.34, -0.16, 0.66, 1.59 and cut -0.2, -0.0, 0.1, 3.0 %; every other early reading t >= 3.10 or
cut >= 10 %."""

from __future__ import annotations

from twin_nodes.discovery.judging import MIN_REL_IMPROVEMENT, T_CRIT, Fit, Judge
from twin_nodes.discovery.stages.joint import contributions
from twin_nodes.discovery.stages.provisional import is_provisional
from twin_nodes.vehicle.params import VehicleParams


def stands_in(g: dict | None) -> bool:
    """Given the others, neither significant nor a cut of ``MIN_REL_IMPROVEMENT`` (and the block test ran)."""
    if not g or g.get("t") is None or g.get("cut") is None:
        return False
    return g["t"] <= T_CRIT and g["cut"] < MIN_REL_IMPROVEMENT


def run(eq: Judge | None, accepted: list[Fit], vp: VehicleParams) -> tuple[list[Fit], VehicleParams]:
    """The accepted effects less the stand-ins, and their vehicle (a stand-in back at nominal); each dropped
    fit carries its numbers given the others in ``given_others``."""
    kept = list(accepted)
    while eq is not None and len(kept) > 1:
        by_index = contributions(eq, vp, kept)
        rows = [(by_index.get(i), f) for i, f in enumerate(kept[:-1])
                if f.kind == "equation" and not is_provisional(f)]
        rows = [(g, f) for g, f in rows if stands_in(g)]
        if not rows:
            break
        g, f = min(rows, key=lambda gf: gf[0]["t"])
        vp = f.at_nominal(vp)
        f.accepted = False
        f.given_others = dict(g)
        kept.remove(f)
    return kept, vp
