"""Stage 3a, the candidates of one selection round: every effect of the ``physics`` catalogue as a fit
on top of what is accepted so far (``CandidateQuery`` -> ``CandidateSet``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from twin_nodes.discovery.candidates import SYMMETRIC_LAG, Candidate, build_candidates
from twin_nodes.discovery.judging import PRUNE_GAIN
from twin_nodes.discovery.residuals import EquationData
from twin_nodes.vehicle.params import VehicleParams


@dataclass
class CandidateQuery:
    """One round of the forward selection."""

    current: VehicleParams                # the vehicle with the effects accepted so far
    data: EquationData
    round: int                            # 1, 2, ...
    done: set[str] = field(default_factory=set)               # accepted labels
    first_gain: dict[str, float] = field(default_factory=dict)  # round 1's cut per label, rescaled


@dataclass
class CandidateSet:
    """The round's candidates: fitted first, and the richer variants fitted only where the simpler
    one is accepted."""

    first: list[Candidate]
    richer: list[Candidate]


def run(q: CandidateQuery) -> CandidateSet:
    """The candidates of round ``q.round``."""
    # round 2 refits every candidate: round 1 fitted them beside the first effect's residual, which a
    # one-sided effect (a ground effect under a thrust deficit) or one that tried to take it up (a drag's
    # vertical term) could not explain; from round 3 a candidate that explained nothing in round 1 (< 2 %
    # cross-validated, rescaled to the residual left: stages.selection) is not refitted
    cands = [c for c in build_candidates(q.current, q.data) if c.label not in q.done
             and (q.round <= 2 or q.first_gain.get(c.label, 1.0) >= PRUNE_GAIN)]
    # the up/down motor lag is fitted only where the one-constant lag is found (it can only
    # refine it; on the other flights it would cost the most expensive fit of the round)
    richer = [c for c in cands if c.name == "motor_time_constant" and c.label != SYMMETRIC_LAG
              and any(d.label == SYMMETRIC_LAG for d in cands)]
    return CandidateSet([c for c in cands if c not in richer], richer)
