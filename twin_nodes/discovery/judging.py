"""Fitting and judging one candidate on one residual, the toolkit of the discovery stages.

A :class:`Judge` is one residual (the equation error over grid samples, the output error over
windows) with its two cross-validation folds and held-out blocks; :func:`assess` fits a candidate
on each fold's fit part (:func:`fit_candidate`) and judges it on the part it did not see (the
block test of :mod:`~twin_nodes.discovery.blocktest`), as a :class:`Fit`.  The method's thresholds
are here too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import least_squares

from twin_nodes.discovery import evaluate
from twin_nodes.discovery.blocktest import _block_stats
from twin_nodes.discovery.candidates import Candidate
from twin_nodes.discovery.output_error import (AXES, JUDGED, MIN_AXIS_R2, STRIDE_S, Windows, judge_axes, make_windows,
                                               output_error)
from twin_nodes.discovery.residuals import LOWPASS_HZ, EquationData, modes, residual_channels
from twin_nodes.discovery.verdicts import clears_floor, folds_agree, moment_share, resolved_by_folds
from twin_nodes.vehicle.params import VehicleParams

HELDOUT_FRACTION = 0.35
# Blocks one low-pass period long: the residual's correlation time is set by the common
# LOWPASS_HZ filter, so blocks of 1/LOWPASS_HZ are close to independent.
BLOCK_S = 1.0 / LOWPASS_HZ
# output-error blocks: three windows; neighbouring blocks share at most one window overlap
OE_BLOCK_S = 3 * STRIDE_S
T_CRIT = 3.0
# choosing between candidates that are each already significant is model selection, not
# detection: the more complex one must beat the simpler one at one-sided 2 sigma
T_CHOICE = 2.0
MIN_REL_IMPROVEMENT = 0.10
MAX_EFFECTS = 3
#: a significant candidate with at least this fraction of the winner's cut is reported as an
#: alternative the flight cannot tell apart (mass/thrust, delay/lag...)
ALT_FRACTION = 0.8
#: effects that act on every rotational axis through the motors
MOTOR_DYNAMICS = ("motor_time_constant", "actuator_delay")
#: effects that act through the dynamics: judged on the output error as well
OUTPUT_ERROR_EFFECTS = ("yaw_moment", "motor_time_constant", "actuator_delay", "inertia")
#: the output-error axes each parameter needs (AXES order: force_x, force_y, force_z, roll, pitch, yaw)
_PARAM_AXES = {"ixx": (3,), "iyy": (4,), "izz": (5,), "km": (5,)}
#: later rounds refit only candidates that explained at least this much in the first round
PRUNE_GAIN = 0.02
#: an output-error block is active when the candidate changes it by half the axis' typical error
OE_MIN_CHANGE = 0.5
#: the grades in the order results list them
_GRADE_ORDER = {"confirmed": 0, "likely": 1, "rejected": 2}


def insert_likely(effects_out: list[dict], entry: dict) -> None:
    """Put a ``likely`` ``entry`` into the graded list ``effects_out`` in order: after every ``confirmed`` one and
    every ``likely`` one with a larger held-out cut (``cv_improvement``), before the rest."""
    k = next((i for i, e in enumerate(effects_out) if _GRADE_ORDER[e["verdict"]] > 1
              or (e["verdict"] == "likely" and (e.get("cv_improvement") or 0) < entry["cv_improvement"])),
             len(effects_out))
    effects_out.insert(k, entry)
#: joint starts (every parameter with a non-zero nominal scaled together) for multi-parameter
#: fits: the time constants' cost is a curved valley (a slower spin-down helps only once the
#: spin-up is slower too: PX4 SIH with SIH_T_TAU 0.05 -> 0.12 s, logged at 50 Hz, stalled at
#: tau_up 0.08 / tau_down 0.05 from the one-at-a-time starts, and the delay was named instead)
JOINT_STARTS = (0.6, 1.6, 2.5)
JOINT_STARTS_LEAN = (0.7, 1.6, 2.5)
#: fits on the output error use at most this many windows (the judging uses all held-out ones)
OE_FIT_WINDOWS = 300


@dataclass
class Judge:
    """One residual with its cross-validation folds and held-out blocks, over its own rows
    (grid samples for the equation error, windows for the output error)."""

    kind: str                                          # "equation" | "output"
    residual: Callable[..., np.ndarray]                # (vp, rows=None) -> (rows, channels)
    folds: list[tuple[np.ndarray, np.ndarray]]         # (fit, test) boolean masks over rows
    blocks: list[np.ndarray]                           # pooled test blocks of both folds (row indices)
    held_mask: np.ndarray                              # fold 1's test rows
    lean: bool = False                                 # fewer evaluations per fit (costly residual)
    windows: Windows | None = None


@dataclass
class Fit:
    candidate: Candidate
    theta: np.ndarray
    vp: VehicleParams
    fit_cost: float
    heldout_rms: float
    heldout_channels: np.ndarray
    t_stat: float
    n_blocks: int
    rel_improvement: float
    above_floor: bool
    accepted: bool = False
    at_bound: bool = False
    R: np.ndarray | None = None
    heldout_cut: float = 0.0
    judged: tuple = ("", 0.0, 0.0)
    evidence: str = ""
    unphysical: str | None = None
    closed_loop: str | None = None   # why the closed-loop twin rejects it (None: not judged or fine)
    kind: str = "equation"           # the residual it was fitted and judged on
    fold_thetas: list = field(default_factory=list)
    folds_agree: bool = True
    stats: dict = field(default_factory=dict)
    verdict: str = "rejected"
    verdict_note: str = ""
    excitation: dict = field(default_factory=dict)
    other: dict | None = None        # the other residual's numbers at this fit
    base_vp: VehicleParams | None = None   # the vehicle it was fitted on top of
    alternatives: list = field(default_factory=list)   # other effects that pass as well (near-equal cut)
    #: this candidate's fits on each residual this round (kind -> Fit; set by :func:`_pick`)
    by_kind: dict = field(default_factory=dict)
    #: the cross-validated cut over the residual channels the candidate changes at all (None: every channel)
    own_cut: float | None = None
    #: in the model as the provisional base of one more round, not as an accepted effect (stages.provisional)
    provisional: bool = False
    given_others: dict | None = None   # its cut and t given the other accepted effects (inertia_given, stand_in)

    def at_nominal(self, vp: VehicleParams) -> VehicleParams:
        """``vp`` with this fit's effect back at its nominal (the candidate's start, within its bounds)."""
        return self.candidate.apply(vp, np.clip(self.candidate.x0, self.candidate.lower, self.candidate.upper))

    @property
    def explains(self) -> float:
        """The share of the held-out residual it explains, for the ``MIN_REL_IMPROVEMENT`` bar: over the
        channels it can change (a yaw moment cannot move the horizontal-force channels, whose accelerometer
        noise would otherwise dilute it), else over all; the ranking keeps :attr:`rel_improvement`."""
        return self.rel_improvement if self.own_cut is None else self.own_cut

    @property
    def passes(self) -> bool:
        """Its fit passes every acceptance bar of its own: above the resolution floor, not pinned at a bound,
        physical, significant on held-out blocks (``T_CRIT``) and explaining ``MIN_REL_IMPROVEMENT`` of the
        held-out residual (:attr:`explains`)."""
        return bool(self.above_floor and not self.at_bound and self.unphysical is None and self.t_stat > T_CRIT
                    and self.explains >= MIN_REL_IMPROVEMENT)

    @property
    def rank(self) -> float:
        """How strongly the flight asks for this effect: the largest cross-validated cut among its
        accepted fits (each on its own residual), else its own.  :func:`_pick` may report the
        equation error's fit for its less biased parameters; that choice must not also weaken
        the effect against a rival judged on the output error."""
        acc = [g.rel_improvement for g in self.by_kind.values() if g.accepted]
        return max(acc) if self.accepted and acc else self.rel_improvement

    @property
    def mode_cut(self) -> float:
        _, b, a = self.judged
        return 1.0 - a / b if b > 0 else 0.0


def _scales(c: Candidate) -> np.ndarray:
    s = np.abs(c.x0).copy()
    span = c.upper - c.lower
    s = np.where(s > 1e-12, s, span / 20.0)
    return np.maximum(s, 1e-9)


def _blocks(t: np.ndarray, mask: np.ndarray, block_s: float, min_rows: int | None = None) -> list[np.ndarray]:
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return []
    edges = np.arange(t[idx[0]], t[idx[-1]] + block_s, block_s)
    which = np.digitize(t[idx], edges)
    if min_rows is None:
        min_rows = 0.5 * block_s / (t[1] - t[0])
    return [idx[which == k] for k in np.unique(which) if (which == k).sum() >= min_rows]


def fit_candidate(c: Candidate, data: EquationData | Judge, nominal: VehicleParams, fit_mask: np.ndarray,
                  max_nfev: int = 60) -> tuple[np.ndarray, VehicleParams, float]:
    """Least-squares fit of one candidate's parameters on the fit rows of a residual
    (an :class:`EquationData` means the equation error, as before residuals were pluggable)."""
    judge = data if isinstance(data, Judge) else _equation_judge(data, nominal, [], [], fit_mask)
    fitted = c.fit_on(judge, fit_mask) if judge.kind == "equation" and hasattr(c, "fit_on") else None
    if fitted is not None:
        return fitted   # a joint variant on its linearised form (stages.joint)
    s = _scales(c)
    lo, hi = c.lower / s, c.upper / s
    rows = fit_mask
    if judge.lean and fit_mask.sum() > OE_FIT_WINDOWS:
        # every k-th fit window: the fit has a few parameters, hundreds of windows pin them
        idx = np.flatnonzero(fit_mask)
        rows = np.zeros_like(fit_mask)
        rows[idx[np.linspace(0, idx.size - 1, OE_FIT_WINDOWS).round().astype(int)]] = True
    resid = _fit_residual(c, judge, rows, s)
    cost_of = _fit_cost(c, rows, s, resid)

    z0 = np.clip(c.x0 / s, lo, hi)
    if len(z0) == 1:
        # one parameter: a grid then a bounded scalar search (delays give piecewise-flat costs)
        return _fit_scalar(c, judge, cost_of, s, lo, hi)
    best_z, best_cost = z0, cost_of(z0)
    for z in _starts(c, judge, z0, lo, hi):
        z = np.clip(z, lo, hi)
        cost = cost_of(z)
        if cost < best_cost:
            best_z, best_cost = z, cost
    sol = least_squares(resid, best_z, bounds=(lo, hi), x_scale=1.0, diff_step=2e-2 if judge.lean else 1e-2,
                        max_nfev=12 if judge.lean else max_nfev, method="trf")
    theta = np.clip(sol.x * s, c.lower, c.upper)
    return theta, c.build(theta), float(2 * sol.cost)


def _fit_residual(c: Candidate, judge: Judge, rows: np.ndarray, s: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """The residual :func:`fit_candidate` minimises, over scaled parameters ``z`` (theta = z * s)."""
    form = _affine_form(c, judge)
    if form is not None:
        # the residual is exactly linear in this candidate's parameters: fit on that form
        lin = form.on(rows)

        def resid(z):
            return lin(np.clip(z * s, c.lower, c.upper))
    else:
        # residuals by theta: least_squares evaluates its start again, and _fold_fit wants the whole
        # equation error at the fitted theta, which the fit has computed already (every row is)
        seen: dict[bytes, np.ndarray] = {}
        whole = judge.kind == "equation"
        _SEEN[:] = [c, judge, seen]
        costs = _fold_costs(c, judge) if whole else None
        folds = [(fit.tobytes(), fit) for fit, _ in judge.folds] if whole else []

        def resid(z):
            theta = np.clip(z * s, c.lower, c.upper)
            key = theta.tobytes()
            R = seen.get(key)
            if R is None:
                vp_z = c.build(theta)
                R = judge.residual(vp_z) if whole else judge.residual(vp_z, rows)
                if len(seen) >= _SEEN_SIZE:
                    del seen[next(iter(seen))]
                seen[key] = R
                if costs is not None:
                    # every fold's fit cost here: the other fold's fit starts from the same grid / starts
                    costs[key] = {k: float(np.sum(R[fit].ravel() ** 2)) for k, fit in folds}
            return R[rows].ravel() if whole else R.ravel().copy()
        resid.memo = costs is not None
    return resid


def _fold_costs(c: Candidate, judge: Judge) -> dict:
    """The equation error's fit costs per theta and fit rows for ``c`` on ``judge`` (see ``_COSTS``)."""
    if _COSTS[0] is not c or _COSTS[1] is not judge:
        _COSTS[:] = [c, judge, {}]
    return _COSTS[2]


def _fit_cost(c: Candidate, rows: np.ndarray, s: np.ndarray, resid: Callable) -> Callable[[np.ndarray], float]:
    """z -> the fit's cost (sum of squares of ``resid(z)``), from ``_COSTS`` where a fit of the same
    candidate on another fold of the same judge evaluated this theta already (the same number:
    the same expression on the same residual)."""
    costs = _COSTS[2] if _COSTS[0] is c and getattr(resid, "memo", False) else None
    rows_key = rows.tobytes() if costs is not None else b""

    def cost(z):
        if costs is not None:
            hit = costs.get(np.clip(z * s, c.lower, c.upper).tobytes(), {}).get(rows_key)
            if hit is not None:
                return hit
        return float(np.sum(resid(z) ** 2))
    return cost


def _fit_scalar(c: Candidate, judge: Judge, cost_of: Callable, s: np.ndarray, lo: np.ndarray, hi: np.ndarray
                ) -> tuple[np.ndarray, VehicleParams, float]:
    """One parameter: a grid then a bounded scalar search (delays give piecewise-flat costs)."""
    from scipy.optimize import minimize_scalar

    def cost1(z):
        return cost_of(np.array([z]))
    grid = np.linspace(lo[0], hi[0], 9 if judge.lean else 25)
    costs = [cost1(z) for z in grid]
    k = int(np.argmin(costs))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    opts = {"xatol": 1e-4 * (hi[0] - lo[0])}
    if judge.lean:
        opts["maxiter"] = 14
    sol = minimize_scalar(cost1, bounds=(a, b), method="bounded", options=opts)
    z = sol.x if sol.fun <= costs[k] else grid[k]
    theta = np.clip(np.array([z]) * s, c.lower, c.upper)
    return theta, c.build(theta), min(float(sol.fun), costs[k])


def _starts(c: Candidate, judge: Judge, z0: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> list[np.ndarray]:
    """Starting points of a multi-parameter fit (scaled, not yet clipped to the bounds)."""
    # Parameters whose nominal value is zero (drag, offsets, delays) span
    # orders of magnitude, so scan them jointly on a log grid of their range; the others
    # +-20 % around the nominal (the output error: jointly x0.7 and x1.6, fewer evaluations).
    starts = []
    zero = c.x0 == 0
    fracs = (0.02, 0.2) if judge.lean else (0.002, 0.006, 0.02, 0.06, 0.2)
    for frac in fracs:
        z = z0.copy()
        z[zero] = lo[zero] + frac * (hi[zero] - lo[zero])
        if np.any(zero):
            starts.append(z)
            if np.any(lo[zero] < 0):  # signed parameters (offsets, wind): both directions
                z2 = z0.copy()
                z2[zero] = hi[zero] - frac * (hi[zero] - lo[zero])
                starts.append(z2)
    if judge.lean:
        for f in JOINT_STARTS_LEAN:
            z = z0.copy()
            z[~zero] = z0[~zero] * f
            starts.append(z)
        free = np.flatnonzero(~zero)
        if free.size > 1:
            # and each one alone: a change in one axis (Izz x1.5 with Ixx, Iyy as they were) is far
            # from the joint starts, and the short output-error fit stalls on the way (PX4 SIH:
            # izz 0.035 instead of 0.045, its cut halved, and the yaw moment taken for it)
            for j in free:
                for f in (0.7, 1.6):
                    z = z0.copy()
                    z[j] = z0[j] * f
                    starts.append(z)
    else:
        for j in np.flatnonzero(~zero):
            for f in (0.8, 1.2):
                z = z0.copy()
                z[j] = z0[j] * f
                starts.append(z)
        if np.count_nonzero(~zero) > 1:
            for f in JOINT_STARTS:
                z = z0.copy()
                z[~zero] = z0[~zero] * f
                starts.append(z)
    return starts


_AFFINE_FORMS: dict[tuple[int, int], tuple] = {}
#: the residuals the latest non-affine fit of this process evaluated: [candidate, judge, {theta bytes: R}]
_SEEN: list = [None, None, {}]
_SEEN_SIZE = 16
#: the equation error's fit costs of the latest non-affine candidate on its judge, for every fold's
#: fit rows at every theta either fold's fit evaluated: [candidate, judge, {theta bytes: {rows bytes: cost}}]
#: (both folds' fits start from the same grid or starts; kept across the folds, a few floats each)
_COSTS: list = [None, None, {}]


def _affine_form(c: Candidate, judge: Judge) -> evaluate.Affine | None:
    """The equation error's exact linear form in ``c``'s parameters (None: not affine, or the
    output error, or switched off); measured once per candidate and judge (both folds use it)."""
    if not evaluate.AFFINE_FITS or judge.kind != "equation" or judge.lean:
        return None
    key = (id(c), id(judge))
    hit = _AFFINE_FORMS.get(key)
    if hit is None or hit[0] is not c or hit[1] is not judge:
        if len(_AFFINE_FORMS) > 32:
            _AFFINE_FORMS.clear()
        form = evaluate.affine(lambda th: judge.residual(c.build(th)), np.clip(c.x0, c.lower, c.upper),
                               c.lower, c.upper)
        hit = _AFFINE_FORMS[key] = (c, judge, form)
    return hit[2]


def _mode_rms(R: np.ndarray, nominal: VehicleParams) -> tuple[np.ndarray, list[str]]:
    m, names = modes(R, nominal)
    return np.sqrt(np.mean(m ** 2, axis=0)), names


def _fold_fits(c: Candidate, judge: Judge, nominal: VehicleParams, shape: tuple[int, ...]
               ) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """The costly part of :func:`assess`, one process's work: ``c`` fitted on each fold's fit
    rows, as (theta, fit cost, its residual on all rows (the output error: on the fold's test
    rows, zero elsewhere))."""
    return [_fold_fit(c, judge, nominal, shape, k) for k in range(len(judge.folds))]


def _fold_fit(c: Candidate, judge: Judge, nominal: VehicleParams, shape: tuple[int, ...], k: int
              ) -> tuple[np.ndarray, float, np.ndarray]:
    """Fold ``k`` of :func:`_fold_fits`."""
    fit_mask, test_mask = judge.folds[k]
    _SEEN[:] = [None, None, {}]
    theta, vp_c, cost = fit_candidate(c, judge, nominal, fit_mask)
    if judge.lean:
        R1 = np.zeros(shape)
        R1[test_mask] = judge.residual(vp_c, test_mask)
    else:
        owner, owner_judge, seen = _SEEN
        R1 = seen.get(theta.tobytes()) if owner is c and owner_judge is judge and judge.kind == "equation" else None
        if R1 is None:
            R1 = judge.residual(vp_c)
    _SEEN[:] = [None, None, {}]
    if k == len(judge.folds) - 1:
        _COSTS[:] = [None, None, {}]
    return theta, cost, R1


def assess(c: Candidate, data: EquationData | Judge, nominal: VehicleParams, R0: np.ndarray,
           folds: list[tuple[np.ndarray, np.ndarray]] | None = None, blocks: list[np.ndarray] | None = None,
           held_mask: np.ndarray | None = None, fold_fits: list | None = None) -> Fit:
    """Fit ``c`` on each fold's fit part and judge it on that fold's unseen part (2-fold CV).

    The block test pools the test blocks of both folds, each predicted by the fit that did
    not see it.  The reported parameters and held-out numbers are fold 1's (fit on the
    first part of the flight, judged on the last).  ``fold_fits``: :func:`_fold_fits`'s result
    when it was computed elsewhere (another process)."""
    judge = data if isinstance(data, Judge) else _equation_judge(data, nominal, folds, blocks, held_mask)
    Rcv = np.zeros_like(R0)
    first = None
    thetas = []
    done = fold_fits if fold_fits is not None else _fold_fits(c, judge, nominal, R0.shape)
    for (fit_mask, test_mask), (theta, cost, R1) in zip(judge.folds, done):
        vp_c = c.build(theta)
        thetas.append(theta)
        Rcv[test_mask] = R1[test_mask]
        if first is None:
            first = (theta, vp_c, cost, R1)
    theta, vp_c, cost, R1 = first
    held_mask = judge.held_mask
    test_all = np.logical_or.reduce([test_mask for _, test_mask in judge.folds])   # both folds' held-out rows
    h0 = np.sqrt(np.mean(R0[test_all] ** 2))
    hcv = np.sqrt(np.mean(Rcv[test_all] ** 2))
    stats = _block_stats(R0, Rcv, judge.blocks, OE_MIN_CHANGE if judge.lean else 0.0,
                         own_change(c, judge, thetas))
    rel = 1.0 - hcv / h0 if h0 > 0 else 0.0
    own = moment_share(c.name, judge.kind, R0[test_all], Rcv[test_all], nominal,
                       _own_channel_cut(R0[test_all], Rcv[test_all]), rel)
    shared = getattr(c, "shared_mode", None)
    if shared is not None:   # a second effect on a channel: what it explains there (stages.joint.shape_partners)
        own = max(rel if own is None else own, _mode_cut(R0[test_all], Rcv[test_all], nominal, shared))
    # an estimate pinned to the edge of the physical range is not an identification
    span = c.upper - c.lower
    at_bound = bool(np.any((np.abs(theta - c.upper) < 0.01 * span) |
                           ((np.abs(theta - c.lower) < 0.01 * span) & (np.abs(c.x0 - c.lower) > 0.01 * span))))
    fit = Fit(c, theta, vp_c, cost, float(np.sqrt(np.mean(R1[held_mask] ** 2))),
              np.sqrt(np.mean(R1[held_mask] ** 2, axis=0)), stats["t"], stats["n"], float(rel),
              clears_floor(c, theta, thetas))
    fit.kind = judge.kind
    fit.own_cut = own
    fit.stats = stats
    fit.fold_thetas = thetas
    fit.folds_agree = folds_agree(c, thetas, _scales(c)) and (all(bool(c.floor(t)) for t in thetas)
                                                              or resolved_by_folds(c, theta, thetas))
    fit.at_bound = at_bound
    fit.unphysical = c.unphysical(theta)
    fit.R = Rcv
    h0_held = np.sqrt(np.mean(R0[held_mask] ** 2))
    fit.heldout_cut = float(1.0 - fit.heldout_rms / h0_held) if h0_held > 0 else 0.0
    # the physical mode (throttle, roll, pitch, yaw, force_x, force_y) where the effect acts; on
    # the output error over both folds' test parts (its few dynamic manoeuvres may all fall in one)
    if judge.lean:
        r0, mnames = _mode_rms(R0[test_all], nominal)
        r1, _ = _mode_rms(Rcv[test_all], nominal)
    else:
        r0, mnames = _mode_rms(R0[held_mask], nominal)
        r1, _ = _mode_rms(R1[held_mask], nominal)
    k = int(np.argmax(r0 ** 2 - r1 ** 2))
    fit.judged = (mnames[k], float(r0[k]), float(r1[k]))
    return fit


def _mode_cut(R0: np.ndarray, R1: np.ndarray, nominal: VehicleParams, mode: str) -> float:
    """1 - RMS(R1) / RMS(R0) in one physical mode (throttle, yaw...; :func:`_mode_rms`)."""
    r0, names = _mode_rms(R0, nominal)
    r1, _ = _mode_rms(R1, nominal)
    k = names.index(mode)
    return float(1.0 - r1[k] / r0[k]) if r0[k] > 0 else 0.0


def own_change(c: Candidate, judge: Judge, thetas: list) -> np.ndarray | None:
    """A joint variant's own term's change of the equation error on each fold's test rows (its fold fit's own
    parameters against its starting value, the accepted effects as they stand), for the block test's choice of
    the blocks it acts in; None for a plain candidate (its change is ``R1 - R0``).  Refitted beside a confined
    effect, the accepted partners re-balance every block a little (a thrust coefficient's kt shifts by 0.3 %
    once a ground effect takes the take-off's extra thrust): those blocks carry the partners' shift, not the
    effect, and counted as active they drowned a ground effect acting on 2-3 blocks (w032, r065: 26 and 35
    "active" blocks, t 2.5 and 2.8, most of them cruise blocks it does not reach)."""
    base = getattr(c, "base", None)
    if base is None or getattr(c, "lin", None) is None or judge.kind != "equation" or not thetas:
        return None
    n = len(base.param_names)
    ref = judge.residual(base.build(np.clip(base.x0, base.lower, base.upper)))
    out = np.zeros_like(ref)
    for (_, test_mask), theta in zip(judge.folds, thetas):
        out[test_mask] = (judge.residual(base.build(np.asarray(theta, float)[:n])) - ref)[test_mask]
    return out


def _own_channel_cut(R0: np.ndarray, R1: np.ndarray) -> float | None:
    """1 - RMS(R1) / RMS(R0) over the channels (columns) where ``R1`` differs from ``R0`` at all (a channel
    the candidate's model leaves untouched is left out); None when it changes every channel or none."""
    if R0.size == 0:
        return None
    tol = 1e-9 * max(float(np.max(np.abs(R0))), 1e-300)
    moved = np.any(np.abs(R1 - R0) > tol, axis=0)
    if moved.all() or not moved.any():
        return None
    h0 = float(np.sqrt(np.mean(R0[:, moved] ** 2)))
    return float(1.0 - np.sqrt(np.mean(R1[:, moved] ** 2)) / h0) if h0 > 0 else None


def _warm(tasks: list[tuple[Candidate, Judge, np.ndarray]]) -> None:
    """Load each candidate's compiled model here, once, before the worker processes are forked."""
    from twin_nodes.discovery.kernels import warm
    from twin_nodes.physics.model import Multirotor
    seen = set()
    for c, judge, _ in tasks:
        try:
            m = Multirotor(c.build(np.clip(c.x0, c.lower, c.upper)))
        except ValueError:
            continue
        key = (m._mod.__name__, judge.lean)
        if key not in seen:
            seen.add(key)
            warm(m, judge.lean)


def _task_cost(c: Candidate, judge: Judge) -> float:
    """Rough relative cost of fitting ``c`` on ``judge`` (only orders the work across processes)."""
    if judge.lean:
        return 10.0
    return 3.0 if c.name in ("battery_sag", "motor_time_constant", "actuator_delay", "ground_effect", "wind") else 1.0


def _equation_judge(data: EquationData, nominal: VehicleParams, folds, blocks, held_mask) -> Judge:
    def residual(vp, rows=None):
        R = residual_channels(data, vp, nominal)
        return R if rows is None else R[rows]
    return Judge("equation", residual, list(folds or []), list(blocks or []),
                 held_mask if held_mask is not None else np.zeros(data.n, bool))


def _judged_windows(data: EquationData, nominal: VehicleParams) -> Windows | None:
    """The output error's windows with every axis judged (None: too few windows)."""
    win = make_windows(data)
    if win.n < 20:
        return None
    return judge_axes(data, win, nominal)


def _window_folds(win: Windows, t_split: float, t_split2: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The two folds over the windows, (fit, test) each: a window belongs to a part when all of it does."""
    return [(win.t_end < t_split, win.t >= t_split), (win.t >= t_split2, win.t_end < t_split2)]


def _output_judge(data: EquationData, nominal: VehicleParams, t_split: float, t_split2: float,
                  win: Windows | None = None) -> Judge | None:
    """The output-error judge: windows, their folds (a window belongs to a part when all of it
    does) and blocks; None when no axis is predicted credibly or there are too few windows."""
    win = _judged_windows(data, nominal) if win is None else win
    if win is None or not win.usable.any():
        return None
    (fit1, test1), (fit2, test2) = _window_folds(win, t_split, t_split2)

    def residual(vp, rows=None):
        if rows is None:
            return output_error(data, win, vp, nominal)
        rows_idx = np.flatnonzero(rows) if rows.dtype == bool else rows
        return output_error(data, win, vp, nominal, rows=rows_idx)
    blocks = _blocks(win.t, test1, OE_BLOCK_S, min_rows=2) + _blocks(win.t, test2, OE_BLOCK_S, min_rows=2)
    return Judge("output", residual, [(fit1, test1), (fit2, test2)], blocks, test1, lean=True, windows=win)


def _restrict_to_axes(c: Candidate, usable: np.ndarray, r2: np.ndarray | None = None) -> Candidate | None:
    """The candidate with only the parameters the usable output-error axes can see (the others
    fixed at nominal and named in ``held``, with the axis' r^2 when given); None when it sees nothing."""
    keep = [i for i, p in enumerate(c.param_names) if any(usable[a] for a in _PARAM_AXES.get(p, range(6)))]
    if not keep:
        return None
    if len(keep) == len(c.param_names):
        return c
    drop = [i for i in range(len(c.param_names)) if i not in keep]
    fixed = dict(c.fixed)
    fixed.update({c.param_names[i]: float(c.x0[i]) for i in drop})

    def full(theta_k):
        th = c.x0.copy()
        th[keep] = theta_k
        return th
    held = dict(c.held)
    for i in drop:
        axes = _PARAM_AXES.get(c.param_names[i], range(6))
        why = "; ".join(f"{AXES[a]} not judged" if not JUDGED[a] else
                        f"{AXES[a]} r^2 {r2[a]:.2f} < {MIN_AXIS_R2}" if r2 is not None else
                        f"{AXES[a]} (nominal prediction below r^2 {MIN_AXIS_R2})" for a in axes)
        held[c.param_names[i]] = f"held at nominal, not identified on this flight: the output error leaves out {why}"
    return Candidate(c.name, tuple(c.param_names[i] for i in keep), c.x0[keep], c.lower[keep], c.upper[keep],
                     lambda th: c.build(full(th)), fixed, lambda th: c.floor(full(th)), c.label,
                     lambda th: c.unphysical(full(th)), held, dict(c.tied))


def _summary(f: Fit) -> dict:
    jname, jb, ja = f.judged
    return {"residual": f.kind, "heldout_channel": jname, "heldout_before": round(jb, 5),
            "heldout_after": round(ja, 5), "heldout_improvement": round(1.0 - ja / jb, 4) if jb > 0 else 0.0,
            "heldout_all_channels_improvement": round(float(f.heldout_cut), 4),
            "cv_improvement": round(float(f.rel_improvement), 4),
            "heldout_t_stat": round(float(f.t_stat), 2) if math.isfinite(f.t_stat) else None,
            "active_blocks": int(f.n_blocks),
            "params": f.candidate.params_dict(f.theta),
            "fold_params": [f.candidate.params_dict(t) for t in f.fold_thetas]}
