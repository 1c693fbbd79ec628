"""Stage 3, the greedy forward selection: each round lists the candidates on top of what is
accepted (:mod:`.candidates`), fits and judges them on both residuals (:mod:`.judge`), keeps one fit
per candidate and accepts the best (the simpler of two unless the other beats it at 2 sigma); the
next round refits the others on top (``SelectionInput`` -> ``Selection``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from twin_nodes.discovery.blocktest import _block_test
from twin_nodes.discovery.candidates import SYMMETRIC_LAG
from twin_nodes.discovery.judging import (ALT_FRACTION, MAX_EFFECTS, MIN_REL_IMPROVEMENT, OE_MIN_CHANGE, T_CHOICE,
                                          T_CRIT, Fit, _summary)
from twin_nodes.discovery.stages import candidates, judge
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.discovery.verdicts import corroboration, likely_failures
from twin_nodes.vehicle.params import VehicleParams


@dataclass
class SelectionInput:
    """The prepared flight and how many effects to accept at most."""

    flight: PreparedFlight
    max_effects: int = MAX_EFFECTS
    progress: bool = False
    #: called with the first accepted effect's vehicle (the closed-loop check's first trial, started ahead)
    on_first: Callable[[VehicleParams], None] | None = None


@dataclass
class Selection:
    """What the rounds accepted, and the latest fit of every candidate."""

    accepted: list[Fit]
    current: VehicleParams                                   # the vehicle with the last accepted effect
    last: dict[str, Fit] = field(default_factory=dict)       # report entry -> its latest assessment
    first_rank: list[str] = field(default_factory=list)      # labels in round 1's order


def run(inp: SelectionInput) -> Selection:
    """Accept the best candidate per round until none passes or ``max_effects`` are accepted."""
    S = inp.flight
    eq, oe, data = S.eq, S.oe, S.data
    blocks = {"equation": eq.blocks, "output": oe.blocks if oe else []}
    current = S.nominal
    accepted: list[Fit] = []
    last: dict[str, Fit] = {}        # the latest assessment of each candidate (label)
    first_rank: list[str] = []
    oe_gain: dict[str, float] = {}   # round-1 output-error gain, to skip hopeless refits later
    r1_gain: dict[str, float] = {}   # round-1 best gain per candidate
    rounds = 0
    pbar = None
    if inp.progress:
        from tqdm import tqdm
        pbar = tqdm(desc="discover", unit="fit", mininterval=0.5, leave=False)
    while rounds < inp.max_effects:
        rounds += 1
        R0 = eq.residual(current)
        R0_oe = oe.residual(current) if oe else None
        done = {f.candidate.label for f in accepted}
        cs = candidates.run(candidates.CandidateQuery(current, data, rounds, done, r1_gain))

        def fit_all(batch, all_oe=False, R0=R0, R0_oe=R0_oe, current=current, rounds=rounds):
            j = judge.run(judge.JudgeQuery(S, current, batch, R0, R0_oe, rounds, oe_gain, all_oe, pbar))
            oe_gain.update(j.oe_gain)
            return j.per_label
        per_label = fit_all(cs.first)
        if cs.richer and any(f.accepted for f in per_label.get(SYMMETRIC_LAG, [])):
            per_label.update(fit_all(cs.richer, all_oe=True))
        kept = _one_per_entry(per_label, blocks)
        if rounds == 1:
            first_rank = [f.candidate.label for f in kept]
            r1_gain = {lab: max(f.rel_improvement for f in fl) for lab, fl in per_label.items()}
        for f in kept:
            if f.candidate.label not in done:
                last[_entry_key(f)] = f
        winner = _winner(kept, blocks)
        if winner is None:
            break
        accepted.append(winner)
        current = winner.vp
        if inp.on_first is not None and len(accepted) == 1:
            inp.on_first(winner.vp)
    if pbar is not None:
        pbar.close()
    return Selection(accepted, current, last, first_rank)


def _one_per_entry(per_label: dict[str, list[Fit]], blocks: dict[str, list[np.ndarray]]) -> list[Fit]:
    """One entry per candidate, one motor_efficiency entry (the best motor) and one motor lag
    (symmetric or up/down: :func:`_one_variant`), strongest first."""
    kept = []
    best_me = None
    variants: dict[str, list[Fit]] = {}
    for lab, fl in per_label.items():
        f = _pick(fl)
        f.other = None
        for g in fl:
            if g is not f:
                f.other = _summary(g)
        if f.candidate.name == "motor_efficiency":
            if best_me is None or f.heldout_rms < best_me.heldout_rms:
                best_me = f
        else:
            variants.setdefault(f.candidate.name, []).append(f)
    kept = [_one_variant(v, blocks) for v in variants.values()]
    if best_me is not None:
        kept.append(best_me)
    kept.sort(key=lambda f: -f.rank)
    return kept


def _winner(kept: list[Fit], blocks: dict[str, list[np.ndarray]]) -> Fit | None:
    """The round's accepted effect (None: nothing passes); every other fit of the round is marked not accepted."""
    winner = next((f for f in kept if f.accepted), None)
    if winner is not None:
        winner = _tie_break(winner, [f for f in kept if f.accepted])
        winner = _parsimonious(winner, [f for f in kept if f.accepted], blocks)
        # what the flight cannot tell apart from the winner: also passing, nearly as large a cut
        winner.alternatives = [
            {"name": f.candidate.name, "params": f.candidate.params_dict(f.theta), "residual": f.kind,
             "cv_improvement": round(float(f.rel_improvement), 4)}
            for f in kept if f is not winner and f.t_stat > T_CRIT and f.above_floor and not f.at_bound
            and f.unphysical is None and f.rel_improvement >= ALT_FRACTION * winner.rel_improvement]
    for f in kept:
        f.accepted = f is winner
    return winner


def _parsimonious(winner: Fit, accepted: list[Fit], blocks: dict[str, list[np.ndarray]] | list[np.ndarray]) -> Fit:
    """Prefer a simpler accepted candidate (judged on the same residual) unless the winner beats
    it on held-out blocks."""
    best = winner
    for f in sorted(accepted, key=lambda f: len(f.candidate.param_names)):
        if f is best or len(f.candidate.param_names) >= len(best.candidate.param_names):
            continue
        # compared on one residual: the pair's own if they share it, else one both pass on
        pairs = [(f, best)] if f.kind == best.kind else [
            (f.by_kind[k], best.by_kind[k]) for k in ("equation", "output")
            if k in f.by_kind and k in best.by_kind and f.by_kind[k].accepted and best.by_kind[k].accepted]
        if not pairs:
            continue
        a, b = pairs[0]
        bl = blocks[a.kind] if isinstance(blocks, dict) else blocks
        t, _ = _block_test(a.R, b.R, bl, OE_MIN_CHANGE if a.kind == "output" else 0.0)
        if t <= T_CHOICE:
            best = f
    return best


def _both_residuals(f: Fit) -> float:
    """The cross-validated cut of ``f``'s effect summed over both residuals (each its own fit)."""
    return float(sum(g.rel_improvement for g in (f.by_kind or {f.kind: f}).values()))


def _tie_break(winner: Fit, accepted: list[Fit]) -> Fit:
    """Among accepted rivals the winner's residual does not tell apart (a cut within
    ``ALT_FRACTION`` of the winner's, as many parameters, judged on the same residual), the one
    the *two* residuals together favour: the larger summed cross-validated cut.  On a 50 Hz PX4
    log a motor lag and a pure delay fit the output error's yaw alike (PX4 SIH T_TAU 0.12 s: cuts
    0.198 and 0.197); the equation error's collective sees the lag's smaller amplitude."""
    n = len(winner.candidate.param_names)
    tied = [f for f in accepted if f is winner or (
        len(f.candidate.param_names) == n and f.kind == winner.kind
        and f.rank >= ALT_FRACTION * winner.rank)]
    return max(tied, key=_both_residuals)


def _one_variant(fits: list[Fit], blocks: dict[str, list[np.ndarray]]) -> Fit:
    """One fit among an effect's variants (the motor lag: one time constant, or separate up and
    down ones): the accepted one with the fewest parameters unless a richer accepted one beats it
    on held-out blocks (:func:`_parsimonious`); with none accepted, the larger cross-validated cut."""
    if len(fits) == 1:
        return fits[0]
    acc = [f for f in fits if f.accepted]
    if not acc:
        return max(fits, key=lambda f: f.rel_improvement)
    return _parsimonious(max(acc, key=lambda f: f.rank), acc, blocks)


def _entry_key(f: Fit) -> str:
    """The report's entry for a fit: one per effect (its variants share it), one per motor."""
    return f.candidate.label if f.candidate.name == "motor_efficiency" else f.candidate.name


def _pick(fits: list[Fit]) -> Fit:
    """One fit per candidate: accepted first, then one that is ``likely`` on its residual (or that the
    two residuals corroborate, :func:`~twin_nodes.discovery.verdicts.corroboration`), and among
    equals the equation error's (the output error judges what the equation error cannot see; where
    both see an effect, the equation error, which does not integrate the aliased 50 Hz commands, is
    the less biased: on our inertia x1.6 flight ixx 0.0412 against 0.0465, truth 0.040); else the
    larger cross-validated cut."""
    kinds = {f.kind: f for f in fits}
    corr = corroboration(kinds.get("output"), kinds.get("equation"), T_CRIT) is not None

    def key(f):
        acc = f.accepted
        lik = corr or not likely_failures(f, T_CRIT, MIN_REL_IMPROVEMENT)
        return (acc, lik, (acc or lik) and f.kind == "equation", f.rel_improvement)
    best = max(fits, key=key)
    best.by_kind = {f.kind: f for f in fits}
    return best
