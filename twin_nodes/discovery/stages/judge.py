"""Stage 3b, the judged fits per residual: each candidate fitted per fold on the equation error and,
for the dynamic effects, on the output error, and judged on the held-out blocks; the fits (each
candidate, each fold) spread over processes (``JudgeQuery`` -> ``JudgedFits``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twin_nodes.discovery import evaluate
from twin_nodes.discovery.candidates import Candidate
from twin_nodes.discovery.judging import (OUTPUT_ERROR_EFFECTS, T_CRIT, Fit, Judge, _fold_fit, _restrict_to_axes,
                                          _task_cost, _warm, assess)
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.discovery.verdicts import corroborated_share
from twin_nodes.vehicle.params import VehicleParams


@dataclass
class JudgeQuery:
    """A batch of candidates to fit on top of ``current``."""

    flight: PreparedFlight
    current: VehicleParams
    batch: list[Candidate]
    R0: np.ndarray                    # the equation error of ``current``
    R0_oe: np.ndarray | None          # the output error of ``current`` (None: no output error)
    round: int
    #: round 1's output-error cut per label (later rounds refit on the output error only above 2 %)
    oe_gain: dict[str, float] = field(default_factory=dict)
    all_oe: bool = False              # every dynamic candidate on the output error as well
    oe_only: bool = False             # on the output error only (the joint dynamic refits of selection)
    pbar: object = None               # a tqdm bar to advance per fitted candidate


@dataclass
class JudgedFits:
    """Per candidate label its fits, one per residual it was judged on."""

    per_label: dict[str, list[Fit]]
    #: round 1: the output-error cut per label
    oe_gain: dict[str, float] = field(default_factory=dict)


def run(q: JudgeQuery) -> JudgedFits:
    """Each candidate of ``q.batch`` fitted and assessed on its residuals (both folds each)."""
    eq, oe, vp, rounds, pbar = q.flight.eq, q.flight.oe, q.flight.nominal, q.round, q.pbar
    tasks: list[tuple[Candidate, Judge, np.ndarray]] = []
    for c in q.batch:
        if not q.oe_only:
            tasks.append((c, eq, q.R0))
        if oe is not None and c.name in OUTPUT_ERROR_EFFECTS and (
                q.all_oe or rounds == 1 or q.oe_gain.get(c.label, 0) > 0.02):
            co = _restrict_to_axes(c, oe.windows.usable, oe.windows.axis_r2)
            if co is not None:
                tasks.append((co, oe, q.R0_oe))
    if evaluate.workers() > 1:
        _warm(tasks)
    # the fits (each candidate, each fold) are independent: spread over processes, results in
    # task order (evaluate.py)
    jobs = [(i, k) for i, (_, judge, _) in enumerate(tasks) for k in range(len(judge.folds))]
    done = evaluate.run_tasks(
        lambda j, tasks=tasks, jobs=jobs: _fold_fit(tasks[jobs[j][0]][0], tasks[jobs[j][0]][1], vp,
                                                    tasks[jobs[j][0]][2].shape, jobs[j][1]),
        len(jobs), cost=[_task_cost(tasks[i][0], tasks[i][1]) for i, _ in jobs],
        done=(lambda j, jobs=jobs: pbar.update(1) if jobs[j][1] == 0 else None) if pbar is not None else None)
    out: dict[str, list[Fit]] = {}
    oe_gain: dict[str, float] = {}
    for i, (c, judge, R0j) in enumerate(tasks):
        fold_fits = [res for (ti, _), res in zip(jobs, done) if ti == i]
        f = assess(c, judge, vp, R0j, fold_fits=fold_fits)
        f.base_vp = q.current
        f.accepted = f.passes
        out.setdefault(c.label, []).append(f)
        if judge is oe and rounds == 1:
            oe_gain[c.label] = f.rel_improvement
    if not q.oe_only:
        _corroborated(out, q.R0, eq, vp)
    return JudgedFits(out, oe_gain)


def _corroborated(out: dict[str, list[Fit]], R0: np.ndarray, eq: Judge, vp: VehicleParams) -> None:
    """A yaw moment's share read over the yaw mode where its output-error fit corroborates its equation-error fit
    (``verdicts.CORROBORATED_SHARE``): its acceptance judged again on that share."""
    rows = np.logical_or.reduce([test_mask for _, test_mask in eq.folds])   # both folds' held-out rows
    for fits in out.values():
        f = next((g for g in fits if g.kind == "equation"), None)
        share = corroborated_share(f, next((g for g in fits if g.kind == "output"), None), R0, rows, vp, T_CRIT)
        if share is not None:
            f.own_cut = share
            f.accepted = f.passes
