"""Two throttle-level effects offered as a pair in the round where neither passes alone (thr12, issue 26 item 2).

Forward selection offers a second effect jointly with the first only beside an *accepted* one (:mod:`.joint`).
Where two effects act on the collective together, one constant (a thrust coefficient, a mass) and one of another
shape (a ground effect with height, a battery sag with the pack voltage), each fitted alone takes up what it can
of the other and the two folds disagree: RotorPy a020 (1 kg quad, thrust coefficient 0.87 with a ground effect
0.4 / 0.84 m, hover with yaw at two heights) fitted kt 0.935 alone (held-out cut -21 %, the folds disagree), the
ground effect alone 1e-11, and nothing was accepted in the throttle; batch 3's w014 (mass with a ground effect)
the same.  So in a round with no throttle effect accepted before and no constant member passing alone, where the
constant member's plain fit moved above its floor, each shaped member is also offered with the constant one free
beside it: the joint variant of :mod:`.joint` (the constant member linearised at its nominal value), then polished
on true evaluations (:class:`_Pair`: the product of the two is not linear), and judged **as a pair** against the
vehicle without either (the round's residual, not the constant member alone).  It competes as a variant of the
shaped effect (``selection._one_variant``: where the shaped one passes alone too, the pair is taken only where it
beats it on held-out blocks).  Where the pair wins, both are accepted, the constant member carrying the pair's
value and the pair's held-out numbers (:func:`members`)"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares

from twin_nodes.discovery.candidates import Candidate
from twin_nodes.discovery.judging import Fit, Judge, _scales
from twin_nodes.discovery.stages.joint import COLLECTIVE_SHAPES, _Joint, fit, linearize, variant
from twin_nodes.vehicle.params import VehicleParams

#: true evaluations of the flight that polish a pair's linearised fit
POLISH_NFEV = 30


class _Pair(_Joint):
    """A pair variant: fitted on :mod:`.joint`'s linearised form, then polished on true evaluations (the constant
    member is linearised at its nominal value, and its product with the shaped one is not linear)."""

    def fit_on(self, judge: Judge, fit_mask: np.ndarray) -> tuple[np.ndarray, VehicleParams, float]:
        theta, _, _ = fit(self, judge, fit_mask)
        s = _scales(self)

        def resid(z):
            return judge.residual(self.build(np.clip(z * s, self.lower, self.upper)))[fit_mask].ravel()
        sol = least_squares(resid, theta / s, bounds=(self.lower / s, self.upper / s), diff_step=1e-3,
                            max_nfev=POLISH_NFEV)
        theta = np.clip(sol.x * s, self.lower, self.upper)
        return theta, self.build(theta), float(2 * sol.cost)


#: the constant members and the shaped members a pair is made of
CONSTANT = ("thrust_coefficient", "mass")
SHAPED = ("ground_effect", "battery_sag")


def _plain(per_label: dict[str, list[Fit]], name: str) -> tuple[Candidate, Fit] | None:
    """The plain (not joint) candidate of ``name`` and its equation-error fit of this round."""
    for lab, fl in per_label.items():
        eq = next((f for f in fl if f.kind == "equation"), None)
        if eq is not None and eq.candidate.name == name and " (+" not in lab:
            return eq.candidate, eq
    return None


def offer(accepted: list[Fit], per_label: dict[str, list[Fit]], judge: Judge, current: VehicleParams
          ) -> list[Candidate]:
    """The pair variants of this round (module doc): none where a throttle effect is accepted or passed alone."""
    if any(a.candidate.name in COLLECTIVE_SHAPES for a in accepted):
        return []
    if any(f.accepted for fl in per_label.values() for f in fl if f.candidate.name in CONSTANT):
        return []
    out = []
    for const in CONSTANT:
        pc = _plain(per_label, const)
        if pc is None or not pc[1].above_floor:
            continue
        c_const, f_const = pc
        seed = copy.copy(f_const)
        seed.theta = np.clip(c_const.x0, c_const.lower, c_const.upper).astype(float)
        with_const = c_const.build(seed.theta)   # the constant member in the model, at its nominal value
        lin = linearize(judge, with_const, [seed])
        if lin is None:
            continue
        for shaped in SHAPED:
            ps = _plain(per_label, shaped)
            if ps is None:
                continue
            on_top = replace(ps[0], build=lambda th, c=ps[0], vp=with_const: c.apply(vp, th))
            j = variant(on_top, lin, per_label[ps[0].label], cls=_Pair)   # polished on true evaluations
            j.label = f"{ps[0].label} (+{const} as a pair)"
            j.pair_member = c_const
            out.append(j)
    return out


def members(winner: Fit) -> list[Fit]:
    """The accepted fits a round's winner stands for: a pair winner (:func:`offer`) is its constant member (the
    pair's value, the pair's held-out numbers) and itself; any other winner is itself."""
    c = getattr(winner.candidate, "pair_member", None)
    if c is None:
        return [winner]
    n = len(winner.candidate.base.param_names)
    member = copy.copy(winner)
    member.candidate = c
    member.theta = np.asarray(winner.theta[n:n + len(c.param_names)], float)
    member.alternatives, member.by_kind = [], {winner.kind: member}
    member.pair_with = winner.candidate.name
    winner.pair_with = c.name
    return [member, winner]
