"""Two rules of the forward selection (:mod:`.selection`) for flights with two effects at once (issue 26, classes
B and E of docs/discovery.md, "Batch 5 RotorPy misses, diagnosed"): a ``likely`` effect as the provisional base
of one more round (:func:`provisional_seed`), and a one-sided candidate held at its edge kept for the later
rounds (:func:`held_at_one_side`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin_nodes.discovery.judging import MIN_REL_IMPROVEMENT, T_CRIT, Fit
from twin_nodes.discovery.verdicts import likely_failures
from twin_nodes.vehicle.params import VehicleParams

# Issue 26, class B (docs/discovery.md, "Batch 5 RotorPy misses, diagnosed"): a round where nothing passes but one
# effect is ``likely`` (a good fit, a large cross-validated cut, both folds agreeing, t under the bar only for want
# of active held-out blocks) ended the search, so every other effect was judged only beside that unmodelled one.
# RotorPy g023 (ground effect 0.4 + body drag): the ground effect fitted 0.43 (cut 49 %, own 71 %, t 1.5 over 4
# active blocks); the drag, judged beside it, took part of it up with its vertical term in one fold and failed (cv
# 1.2 %).  So such an effect seeds one provisional round on top of it: the round's candidates are judged with it in
# the model.  Where one passes there, the search goes on with both; the provisional effect stays in the model (what
# came after was judged on it) but keeps its own grade (``likely``, from its own fit: never confirmed because
# something was found on top of it; ``stages.verdicts``).  Where nothing passes, the result is as without it.

#: the cross-validated cut (over the channels it changes) a likely effect needs to seed a provisional round
PROVISIONAL_MIN_CUT = 0.30


@dataclass
class Provisional:
    """The seed and the selection's state before it (restored where nothing is found on top of it)."""

    fit: Fit
    before: tuple[list[Fit], VehicleParams, dict[str, Fit]]

    def withdraw(self) -> tuple[list[Fit], VehicleParams, dict[str, Fit]]:
        self.fit.provisional = False
        return self.before


def is_provisional(f: Fit) -> bool:
    """``f`` is in the model as a provisional base, not as an accepted effect."""
    return f.provisional


def provisional_seed(kept: list[Fit], accepted: list[Fit], current: VehicleParams,
                     last: dict[str, Fit]) -> Provisional | None:
    """The strongest fit of a round where nothing passed that is ``likely`` on its own residual with a solid fit:
    physical, off its bounds, both folds agreeing and a cross-validated cut of ``PROVISIONAL_MIN_CUT`` (the
    module comment above); None where there is none."""
    for f in kept:
        if (f.t_stat <= T_CRIT and f.folds_agree and not f.at_bound and f.unphysical is None
                and f.explains >= PROVISIONAL_MIN_CUT and not likely_failures(f, T_CRIT, MIN_REL_IMPROVEMENT)):
            f.provisional = True
            return Provisional(f, (list(accepted), current, dict(last)))
    return None


def held_at_one_side(f: Fit) -> bool:
    """A one-sided candidate (every parameter whose nominal is an edge of its range, and there is one: a ground
    effect or a drag only adds, a delay only delays) whose fit stayed at that edge: the residual pushed it the
    other way, which says nothing of whether it is there.  Issue 26, class E (RotorPy g030, battery sag + ground
    effect): beside the sag's thrust deficit the ground effect can only fit 0 (rounds 1-2, t -4.85) and was pruned
    from round 3 on, the round after the sag was accepted; refitted there it is accepted (0.432 for 0.4).  Such a
    candidate is re-offered in every round after an accepted effect, as a two-sided one that stayed at nominal is
    not (it explained nothing either way)."""
    c = getattr(f, "candidate", None)
    if c is None or getattr(f, "theta", None) is None:
        return False
    x0, lo, hi, th = (np.asarray(a, float) for a in (c.x0, c.lower, c.upper, f.theta))
    tol = 0.01 * (hi - lo)
    edge = (np.abs(x0 - lo) < tol) | (np.abs(x0 - hi) < tol)
    return bool(edge.any() and np.all(np.abs(th - x0)[edge] < tol[edge]))
