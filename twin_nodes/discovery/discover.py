"""Missing-physics discovery: locate the mismatch, name the physics left out, grade it, refit, show it on held-out data.

Two residuals judge the candidates:

- the **equation error** (:mod:`twin_nodes.discovery.residuals`): measured specific force and
  angular acceleration minus what the model predicts from the logged motor commands, per motor and
  horizontal force, low-passed at 2 Hz.  Forces that act at every sample (mass, thrust, drag,
  wind, ground effect, a weak motor...) show here.
- the **output error** (:mod:`twin_nodes.discovery.output_error`): the model flown open loop for
  0.4 s from the logged state at the start of each window, driven by the logged motor commands,
  compared on body rates and velocity.  What acts through the dynamics (rotor lag, delay, inertia,
  the reaction torque of a yaw manoeuvre) shows here; the equation error's 2 Hz low-pass hides it.

Method:

1. **Locate** (:mod:`twin_nodes.discovery.locate`): every channel (collective, roll, pitch and yaw
   moments, each motor, horizontal force): 2-s windows whose equation error is above 3x the
   channel's noise floor, by flight regime; and per channel its *excitation*, the number of
   held-out blocks that carry signal and the manoeuvres they come from.
2. **Name.**  Every candidate effect (:mod:`twin_nodes.discovery.candidates`) is fitted on 65 % of
   the flight and judged on the rest, both ways round (2-fold cross-validation), on the equation
   error; the dynamic ones (``OUTPUT_ERROR_EFFECTS``) also on the output error, on the axes the
   nominal model predicts credibly there.  Accepted (``confirmed``) only if its size is above the
   physical resolution floor, it is inside the physical range, it lowers the held-out residual in
   a block test (t, sign or sign-flip test > 3 over independent blocks) and explains >= 10 % of
   the held-out residual.  Greedy forward selection: accept the best, refit the others on top.
3. **Grade** (:mod:`twin_nodes.discovery.verdicts`): ``confirmed``, ``likely`` (a large held-out cut
   and a clear parameter, but too few excited blocks for the test: how many are missing and which
   manoeuvre supplies them) or ``rejected``.
4. **Refit** all accepted effects jointly; report before/after on the held-out part.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import least_squares

from twin_nodes.discovery import evaluate, rate_loop
from twin_nodes.discovery.candidates import SYMMETRIC_LAG, Candidate, build_candidates
from twin_nodes.discovery.locate import events, excitation, locate, locate_output, regimes  # noqa: F401  (regimes: re-exported)
from twin_nodes.discovery.output_error import (AXES, HORIZON_S, IV_AXIS_PARAM, IV_GAIN_RANGE, JUDGED, MIN_AXIS_R2, STRIDE_S, Windows,
                                               authority_mismatch, instrumented_inertia, judge_axes, make_windows,
                                               output_error, projected_view)
from twin_nodes.discovery.residuals import (LOWPASS_HZ, EquationData, channel_names, modes, prepare,
                                            residual_channels)
from twin_nodes.discovery.plans import RATE_LOOP_LOG_S
from twin_nodes.discovery.verdicts import LIKELY_MIN_CUT, corroboration, folds_agree, grade, likely_failures
from twin_nodes.physics.effects import EFFECTS, effective_params
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


def _block_stats(R0: np.ndarray, R1: np.ndarray, blocks: list[np.ndarray], min_change: float = 0.0) -> dict:
    """Per-block drop in mean squared residual over the blocks where the candidate changes the
    prediction at all (>= 25 % of its 90th-percentile block change, so one violent manoeuvre
    cannot silence the rest), and the three tests on it.

    Effects that act only in some regimes (drag in forward flight, ground effect near the
    ground) leave the other blocks unchanged; counting those would only add variance.  The
    blocks are chosen from the change itself, not from whether it helped, so this does not
    favour the candidate.  ``min_change``: a block must also change by at least this much (the
    output error is in units of its typical error, so half of that separates a manoeuvre the
    candidate acts in from noise when under a tenth of the blocks carry it)."""
    delta = np.array([np.sqrt(np.mean((R1[b] - R0[b]) ** 2)) for b in blocks])
    if delta.size == 0 or delta.max() <= 0:
        return {"t": 0.0, "n": 0, "mean": 0.0, "sd": 0.0, "n_pos": 0}
    ref = np.percentile(delta, 90)
    active = [b for b, dl in zip(blocks, delta) if dl >= max(0.25 * ref, min_change)]
    d = np.array([np.mean(R0[b] ** 2) - np.mean(R1[b] ** 2) for b in active])
    st = {"n": int(d.size), "mean": float(d.mean()) if d.size else 0.0,
          "sd": float(d.std(ddof=1)) if d.size > 1 else 0.0, "n_pos": int(np.sum(d > 0))}
    if d.size < 4:
        st["t"] = 0.0
        return st
    from scipy.stats import binom, norm
    from scipy.stats import t as student_t
    sd = st["sd"]
    t = (math.inf if d.mean() > 0 else 0.0) if sd == 0 else float(d.mean() / (sd / math.sqrt(d.size)))
    if math.isfinite(t):
        # Student's t with n - 1 degrees of freedom, as the equivalent normal quantile (with 4
        # blocks t = 3 is only p = 0.03)
        t = float(norm.isf(min(max(float(student_t.sf(t, d.size - 1)), 1e-300), 1.0 - 1e-15)))
    # Sign test on the same blocks: the t test loses power when the gains are heavy-tailed
    # (a few manoeuvres carry an inertia or yaw-moment effect).  Under "no effect" a held-out
    # block improves with probability <= 1/2; the binomial tail is mapped to the equivalent
    # one-sided normal quantile so both tests share the threshold T_CRIT.
    # Fisher's sign-flip randomization test keeps the size of the gains without assuming
    # normality: under "no effect" each block's gain is as likely to be a loss of the same
    # size.  20000 fixed-seed flips resolve p down to 5e-5.  The largest of the three
    # statistics is used; at the one-sided 3 sigma level the union's false-alarm rate stays
    # under 0.5 %.
    k = int(np.sum(d > 0))
    p = float(binom.sf(k - 1, d.size, 0.5))
    z = float(norm.isf(max(p, 1e-300)))
    p_flip = (1.0 + np.sum(_flip_sums(d.size, np.abs(d)) >= d.sum())) / (1.0 + N_FLIPS)
    zw = float(norm.isf(p_flip))
    st["t"] = max(t, z, zw)
    return st


_FLIPS: dict[int, np.ndarray] = {}
#: the sign-flip test's flips, and the rows made and multiplied at a time: the flip matrix is
#: 20000 x (active blocks) and the blocks are 0.5 s, so as float64 it grew with the flight (a
#: 1-hour flight: ~800 MB per block count, up to 17 counts cached); kept as bits (1/64), made
#: FLIP_ROWS rows at a time with the same random stream (an even number of draws per chunk: the
#: generator's 32-bit buffer ends with each chunk) and multiplied a few rows at a time with the
#: same BLAS product per row (bit for bit what the whole matrix gave, tests/test_bench_smoke.py)
N_FLIPS = 20000
FLIP_ROWS = 2000


def _sign_flips(n: int) -> np.ndarray:
    """The sign-flip test's 20000 fixed-seed flips of n blocks, packed as bits (True: +1), made once
    per n (:func:`_flip_sums` expands them)."""
    if n not in _FLIPS:
        if len(_FLIPS) > 16:
            _FLIPS.clear()
        rng = np.random.default_rng(12345)
        _FLIPS[n] = np.concatenate([
            np.packbits(rng.choice((-1.0, 1.0), size=(min(FLIP_ROWS, N_FLIPS - r0), n)) > 0, axis=1)
            for r0 in range(0, N_FLIPS, FLIP_ROWS)])
        _FLIPS[n].flags.writeable = False
    return _FLIPS[n]


def _sum_rows(n: int) -> int:
    """Rows of +-1.0 expanded and multiplied at a time: ~2 MB of float64 (stays in the CPU's cache;
    3x faster than 2000 rows on a 1-hour flight), from 64 to FLIP_ROWS, a multiple of 16: BLAS's
    matrix-vector kernel takes rows in groups, and a remainder group sums in another order (rows
    = 2 mod 4 gave other last bits); 20000 is a multiple of 16, so every chunk is whole groups."""
    return int(min(max(2 ** 18 // max(n, 1), 64), FLIP_ROWS)) & ~15


def _flip_sums(n: int, a: np.ndarray) -> np.ndarray:
    """``flips @ a`` for the n-block flip matrix, a few rows at a time (:func:`_sum_rows`; equal bit
    for bit to the product with the whole float64 matrix)."""
    bits = _sign_flips(n)
    out = np.empty(N_FLIPS)
    rows = _sum_rows(n)
    for r0 in range(0, N_FLIPS, rows):
        f = np.multiply(np.unpackbits(bits[r0:r0 + rows], axis=1, count=n), 2.0)
        f -= 1.0
        out[r0:r0 + rows] = f @ a
    return out


def _block_test(R0: np.ndarray, R1: np.ndarray, blocks: list[np.ndarray], min_change: float = 0.0
                ) -> tuple[float, int]:
    """(statistic, active blocks) of :func:`_block_stats`: t, sign and sign-flip tests, the largest."""
    st = _block_stats(R0, R1, blocks, min_change)
    return st["t"], st["n"]


def fit_candidate(c: Candidate, data: EquationData | Judge, nominal: VehicleParams, fit_mask: np.ndarray,
                  max_nfev: int = 60) -> tuple[np.ndarray, VehicleParams, float]:
    """Least-squares fit of one candidate's parameters on the fit rows of a residual
    (an :class:`EquationData` means the equation error, as before residuals were pluggable)."""
    judge = data if isinstance(data, Judge) else _equation_judge(data, nominal, [], [], fit_mask)
    s = _scales(c)
    lo, hi = c.lower / s, c.upper / s
    rows = fit_mask
    if judge.lean and fit_mask.sum() > OE_FIT_WINDOWS:
        # every k-th fit window: the fit has a few parameters, hundreds of windows pin them
        idx = np.flatnonzero(fit_mask)
        rows = np.zeros_like(fit_mask)
        rows[idx[np.linspace(0, idx.size - 1, OE_FIT_WINDOWS).round().astype(int)]] = True

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
            return R[rows].ravel() if whole else R.ravel().copy()

    z0 = np.clip(c.x0 / s, lo, hi)
    if len(z0) == 1:
        # one parameter: a grid then a bounded scalar search (delays give piecewise-flat costs)
        from scipy.optimize import minimize_scalar

        def cost1(z):
            return float(np.sum(resid(np.array([z])) ** 2))
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
    best_z, best_cost = z0, float(np.sum(resid(z0) ** 2))
    # Starting points: parameters whose nominal value is zero (drag, offsets, delays) span
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
    for z in starts:
        z = np.clip(z, lo, hi)
        cost = float(np.sum(resid(z) ** 2))
        if cost < best_cost:
            best_z, best_cost = z, cost
    sol = least_squares(resid, best_z, bounds=(lo, hi), x_scale=1.0, diff_step=2e-2 if judge.lean else 1e-2,
                        max_nfev=12 if judge.lean else max_nfev, method="trf")
    theta = np.clip(sol.x * s, c.lower, c.upper)
    return theta, c.build(theta), float(2 * sol.cost)


_AFFINE_FORMS: dict[tuple[int, int], tuple] = {}
#: the residuals the latest non-affine fit of this process evaluated: [candidate, judge, {theta bytes: R}]
_SEEN: list = [None, None, {}]
_SEEN_SIZE = 16


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
    test_all = np.zeros(len(R0), bool)
    for _, test_mask in judge.folds:
        test_all |= test_mask
    h0 = np.sqrt(np.mean(R0[test_all] ** 2))
    hcv = np.sqrt(np.mean(Rcv[test_all] ** 2))
    stats = _block_stats(R0, Rcv, judge.blocks, OE_MIN_CHANGE if judge.lean else 0.0)
    rel = 1.0 - hcv / h0 if h0 > 0 else 0.0
    # an estimate pinned to the edge of the physical range is not an identification
    span = c.upper - c.lower
    at_bound = bool(np.any((np.abs(theta - c.upper) < 0.01 * span) |
                           ((np.abs(theta - c.lower) < 0.01 * span) & (np.abs(c.x0 - c.lower) > 0.01 * span))))
    fit = Fit(c, theta, vp_c, cost, float(np.sqrt(np.mean(R1[held_mask] ** 2))),
              np.sqrt(np.mean(R1[held_mask] ** 2, axis=0)), stats["t"], stats["n"], float(rel),
              bool(c.floor(theta)))
    fit.kind = judge.kind
    fit.stats = stats
    fit.fold_thetas = thetas
    fit.folds_agree = folds_agree(c, thetas, _scales(c)) and all(bool(c.floor(t)) for t in thetas)
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
        why.append(f"not significant on held-out blocks (t={f.t_stat:.1f})")
    if f.rel_improvement < MIN_REL_IMPROVEMENT:
        why.append(f"explains only {100 * f.rel_improvement:.0f} % of the held-out residual")
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


@dataclass
class Setup:
    """What discovery needs about one flight: data, splits, both judges, excitation."""

    data: EquationData
    names: list[str]
    fit_mask: np.ndarray
    held_mask: np.ndarray
    t_split: float
    t_end: float
    eq: Judge
    oe: Judge | None
    excitation: dict
    #: the output error's judged windows, also where no axis is usable (the instrumented gains)
    windows: Windows | None = None
    #: the second fold's split: fit on the part after it, judge on the part before
    t_split2: float = math.nan
    #: the log's own parameters (PX4's rate-loop gains and filters for :mod:`rate_loop`)
    log_params: dict = field(default_factory=dict)


def prepare_flight(log, vp: VehicleParams, heldout_fraction: float = HELDOUT_FRACTION, output_error: bool = True) -> Setup:
    """Prepare a flight: equation-error data, the 2-fold splits, both judges, per-channel excitation."""
    data = prepare(log, vp)
    names = channel_names(vp.rotors.count)
    valid_t = data.t[data.valid]
    t_split = valid_t[0] + (1.0 - heldout_fraction) * (valid_t[-1] - valid_t[0])
    fit_mask = data.valid & (data.t < t_split)
    held_mask = data.valid & (data.t >= t_split)
    # second fold: fit on the last part, judge on the first (disjoint from fold 1's test part)
    t_split2 = valid_t[0] + heldout_fraction * (valid_t[-1] - valid_t[0])
    held2 = data.valid & (data.t < t_split2)
    folds = [(fit_mask, held_mask), (data.valid & (data.t >= t_split2), held2)]
    held_blocks = _blocks(data.t, held_mask, BLOCK_S) + _blocks(data.t, held2, BLOCK_S)
    eq = _equation_judge(data, vp, folds, held_blocks, held_mask)
    win = _judged_windows(data, vp) if output_error else None
    oe = _output_judge(data, vp, t_split, t_split2, win) if win is not None else None
    ex = excitation(data, vp, names, _blocks(data.t, data.valid, BLOCK_S), held_blocks)
    return Setup(data, names, fit_mask, held_mask, float(t_split), float(valid_t[-1]), eq, oe, ex, win,
                 float(t_split2), dict(getattr(log, "params", None) or {}))


def discover(log, vp: VehicleParams, *, heldout_fraction: float = HELDOUT_FRACTION, max_effects: int = MAX_EFFECTS,
             progress: bool = False, closed_loop_metrics: bool = True, output_error: bool = True) -> dict:
    """Run discovery on a FlightLog with nominal params ``vp``; returns the JSON-ready result."""
    t_start = time.time()
    S = prepare_flight(log, vp, heldout_fraction, output_error)
    data, names, fit_mask, held_mask, t_split = S.data, S.names, S.fit_mask, S.held_mask, S.t_split
    _closed_loop_reset()
    if closed_loop_metrics:
        # the nominal twin's closed-loop run, in another process while the candidates are fitted
        _prefetch_closed_loop(log, vp, t_split, S.t_end)
    eq, oe = S.eq, S.oe
    blocks = {"equation": eq.blocks, "output": oe.blocks if oe else []}

    current = vp
    R_base = residual_channels(data, vp, vp)
    raw_base = residual_channels(data, vp, vp, lowpass_hz=None)
    base_held = np.sqrt(np.mean(R_base[held_mask] ** 2, axis=0))
    mismatch = locate(data, R_base, raw_base, names, vp)
    oe_base = oe.residual(vp) if oe else None
    if oe is not None:
        mismatch = sorted(mismatch + locate_output(data, oe.windows, oe_base, vp), key=lambda d: -d["severity"])

    accepted: list[Fit] = []
    last: dict[str, Fit] = {}        # the latest assessment of each candidate (label)
    first_rank: list[str] = []
    oe_gain: dict[str, float] = {}   # round-1 output-error gain, to skip hopeless refits later
    r1_gain: dict[str, float] = {}   # round-1 best gain per candidate
    rounds = 0
    pbar = None
    if progress:
        from tqdm import tqdm
        pbar = tqdm(desc="discover", unit="fit", mininterval=0.5, leave=False)
    while rounds < max_effects:
        rounds += 1
        R0 = eq.residual(current)
        R0_oe = oe.residual(current) if oe else None
        done = {f.candidate.label for f in accepted}
        # after the first round, a candidate that explained nothing then (< 2 % cross-validated, on
        # either residual) is not refitted: adding an effect does not make it explain the rest
        cands = [c for c in build_candidates(current, data) if c.label not in done
                 and (rounds == 1 or r1_gain.get(c.label, 1.0) >= PRUNE_GAIN)]
        def fit_all(batch: list[Candidate], all_oe: bool = False) -> dict[str, list[Fit]]:
            """Each candidate of ``batch`` fitted and assessed on its residuals (both folds each)."""
            tasks: list[tuple[Candidate, Judge, np.ndarray]] = []
            for c in batch:
                tasks.append((c, eq, R0))
                if oe is not None and c.name in OUTPUT_ERROR_EFFECTS and (
                        all_oe or rounds == 1 or oe_gain.get(c.label, 0) > 0.02):
                    co = _restrict_to_axes(c, oe.windows.usable, oe.windows.axis_r2)
                    if co is not None:
                        tasks.append((co, oe, R0_oe))
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
            for i, (c, judge, R0j) in enumerate(tasks):
                fold_fits = [res for (ti, _), res in zip(jobs, done) if ti == i]
                f = assess(c, judge, vp, R0j, fold_fits=fold_fits)
                f.base_vp = current
                f.accepted = (f.above_floor and not f.at_bound and f.unphysical is None and f.t_stat > T_CRIT
                              and f.rel_improvement >= MIN_REL_IMPROVEMENT)
                out.setdefault(c.label, []).append(f)
                if judge is oe and rounds == 1:
                    oe_gain[c.label] = f.rel_improvement
            return out

        # the up/down motor lag is fitted only where the one-constant lag is found (it can only
        # refine it; on the other flights it would cost the most expensive fit of the round)
        richer = [c for c in cands if c.name == "motor_time_constant" and c.label != SYMMETRIC_LAG
                  and any(d.label == SYMMETRIC_LAG for d in cands)]
        per_label = fit_all([c for c in cands if c not in richer])
        if richer and any(f.accepted for f in per_label.get(SYMMETRIC_LAG, [])):
            per_label.update(fit_all(richer, all_oe=True))
        # one entry per candidate, one motor_efficiency entry (the best motor) and one motor lag
        # (symmetric or up/down: _one_variant)
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
        if rounds == 1:
            first_rank = [f.candidate.label for f in kept]
            r1_gain = {lab: max(f.rel_improvement for f in fl) for lab, fl in per_label.items()}
        for f in kept:
            if f.candidate.label not in done:
                last[_entry_key(f)] = f
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
        if winner is None:
            break
        accepted.append(winner)
        current = winner.vp
        if closed_loop_metrics and len(accepted) == 1:
            _prefetch_closed_loop(log, winner.vp, t_split, S.t_end)   # the closed-loop guard's first trial
    if pbar is not None:
        pbar.close()

    # joint refit of all accepted effects (they may interact)
    if len(accepted) > 1:
        current = _joint_refit(accepted, data, vp, fit_mask)
    closed = None
    if closed_loop_metrics and accepted:
        # an effect must also make the closed-loop twin better on the held-out part, never worse
        accepted, current, closed = _closed_loop_guard(accepted, log, vp, data, fit_mask, t_split, S.t_end)

    # grades: confirmed (accepted and kept), likely, rejected (with why)
    acc_labels = [f.candidate.label for f in accepted]
    side_base: dict[int, np.ndarray] = {}
    for f in last.values():
        if f in accepted:
            f.accepted = True
        elif f.accepted:
            f.accepted = False
        expl = None
        if (not f.accepted and f.t_stat > T_CRIT and f.rel_improvement >= MIN_REL_IMPROVEMENT and acc_labels
                and f.above_floor and not f.at_bound and f.unphysical is None and f.closed_loop is None):
            expl = ", ".join(acc_labels)
        grade(f, T_CRIT, MIN_REL_IMPROVEMENT, S.excitation, expl)
        if f.other is None:
            # the other residual's view of this fit, for the report
            judge = oe if f.kind == "equation" else eq
            if judge is not None:
                b = f.base_vp or vp
                if id(b) not in side_base:
                    side_base[id(b)] = (judge.residual(b) if judge is eq else
                                        _scatter(judge.residual(b, judge.held_mask), judge.held_mask))
                f.other = _side(judge, f.vp, side_base[id(b)], vp)
        f.evidence = _evidence(f, names, base_held)
    rank = {lab: i for i, lab in enumerate(first_rank)}
    ranked = sorted(last.values(), key=lambda f: (_GRADE_ORDER[f.verdict],
                                                  acc_labels.index(f.candidate.label) if f.accepted else 0,
                                                  -f.rel_improvement if f.verdict != "rejected"
                                                  else rank.get(f.candidate.label, 99)))
    effects_out = [_effect_json(f, names, base_held) for f in ranked]
    if S.windows is not None:
        # a motor lag or delay acts on every rotational axis: its held-out cut there in the
        # instrument-projected error too, which the 50 Hz aliasing does not bound (reported only)
        held_w = _window_folds(S.windows, S.t_split, S.t_split2)[0][1]
        for f, e in zip(ranked, effects_out):
            if e["verdict"] in ("confirmed", "likely") and f.candidate.name in MOTOR_DYNAMICS:
                view = projected_view(data, S.windows, f.base_vp or vp, f.vp, held_w)
                if view is not None:
                    e.setdefault("residuals", {})["instrumented"] = view
    def guard(vp_new: VehicleParams) -> str | None:
        """The closed-loop twin's held-out throttle RMSE must not get worse (as ``_closed_loop_guard``)."""
        if not (closed_loop_metrics and closed):
            return None
        m = _closed_loop_metrics(log, vp_new, t_split, S.t_end)
        if not _worse(m["throttle_rmse"], closed["after"]["throttle_rmse"], closed["before"]["throttle_rmse"]):
            closed["after"] = m
            return None
        return (f"makes the closed-loop twin worse on the held-out part (throttle RMSE "
                f"{closed['after']['throttle_rmse']:.6f} -> {m['throttle_rmse']:.6f})")
    # an inertia finding's roll/pitch axes, each on its own evidence, then the instrument on what is
    # still held: either may change the refit vehicle
    current = _equation_axes(S, ranked, effects_out, current, acc_labels, guard) or current
    instrumented, refit = _instrumented(S, current, acc_labels, effects_out, guard, vp)
    current = refit or current
    # where the rate loop says the motors are slow, not an inertia: how slow
    lag = (_rate_loop_lag(S, current, effects_out)
           if instrumented is not None and instrumented.get("method") == "rate_loop" and instrumented["motor_signature"]
           else None)
    R_after = residual_channels(data, current, vp)
    after_held = np.sqrt(np.mean(R_after[held_mask] ** 2, axis=0))
    # what even the refitted model leaves: short events no steady effect is made for
    transients = events(data, R_after, vp, names)
    likely = [e["name"] for e in effects_out if e["verdict"] == "likely"]
    result = {
        "log": str(log.path),
        "params": vp.source,
        "method": {
            "residual": "equation error (measured specific force and angular acceleration vs the model fed the "
                        "logged motor commands), per motor and horizontal force, low-passed "
                        f"{LOWPASS_HZ} Hz, in fraction of full motor output",
            "output_error": (f"the model flown open loop for {HORIZON_S} s from the logged state (windows every "
                             f"{STRIDE_S} s), driven by the logged motor commands; per window the mean "
                             "acceleration error of body rates and velocity over the horizon as force/moment, "
                             "same channels and units; axes where the nominal prediction's r^2 < "
                             f"{MIN_AXIS_R2} are left out"),
            "fit_interval_s": [round(float(data.t[data.valid][0]), 2), round(float(t_split), 2)],
            "heldout_interval_s": [round(float(t_split), 2), round(S.t_end, 2)],
            "motor_log_interval_s": round(float(data.motor_dt_s), 5),
            "timing": data.info.get("timing", ""),
            "acceptance": f"above the physical resolution floor and inside the physical range; 2-fold "
                          f"cross-validated: held-out block test (t or sign test) > {T_CRIT} over up to "
                          f"{len(eq.blocks)} blocks of {BLOCK_S} s (output error: {len(blocks['output'])} "
                          f"blocks of {OE_BLOCK_S:.1f} s), held-out RMS cut >= {int(100 * MIN_REL_IMPROVEMENT)} %",
            "likely": "not significant yet, but held-out cut >= 30 % in its channel, parameter well away from "
                      "nominal and physical, both folds agree, most active blocks improved",
            **({"rate_loop": f"PX4's rate loop (the log's MC_*RATE_* gains, gyro/D-term/yaw-torque filters, rate-loop "
                             f"hold) flown on the model from the logged rate setpoint in {rate_loop.WINDOW_S:g} s "
                             "windows (integrator, motor and rate state free per window), compared on body rates: "
                             "roll/pitch inertia, and the motors' lag where every axis reads slow"}
               if instrumented is not None and instrumented.get("method") == "rate_loop" else {}),
        },
        "baseline": {"equation_error_heldout": {k: round(float(v), 5) for k, v in zip(names, base_held)}},
        "mismatch": mismatch,
        "events": transients,
        "excitation": S.excitation,
        "effects": effects_out,
        "accepted": [f.candidate.name for f in accepted],
        "likely": likely,
        "after": {"equation_error_heldout": {k: round(float(v), 5) for k, v in zip(names, after_held)}},
        "refit_params": current.to_ros_dict() if accepted else None,
    }
    if oe is not None:
        r0, mn = _mode_rms(oe_base[oe.held_mask], vp)
        result["baseline"]["output_error_heldout"] = {k: round(float(v), 5) for k, v in zip(mn, r0)}
        result["output_error_axes"] = {**oe.windows.describe(), "horizon_s": HORIZON_S}
        result["authority"] = authority_mismatch(oe.windows)
        if accepted:
            r1, _ = _mode_rms(oe.residual(current, oe.held_mask), vp)
            result["after"]["output_error_heldout"] = {k: round(float(v), 5) for k, v in zip(mn, r1)}
    else:
        # no axis usable: the output error is not used, its axes and instrumented gains still shown
        result["output_error_axes"] = ({**S.windows.describe(), "horizon_s": HORIZON_S}
                                       if S.windows is not None else None)
        result["authority"] = authority_mismatch(S.windows) if S.windows is not None else []
    if instrumented is not None:
        result["instrumented"] = instrumented
    if lag is not None:
        result["rate_loop_lag"] = lag
    if closed_loop_metrics:
        _closed_loop(result, log, vp, current, t_split, S.t_end, closed)
    _closed_loop_reset()
    result["elapsed_s"] = round(time.time() - t_start, 1)
    result["_series"] = {"t": data.t, "valid": data.valid, "held": held_mask, "R_before": R_base,
                         "R_after": R_after, "names": names}
    return result


def attach_instrumented(entry: dict, iv: dict, residual: dict, nominal_inertia: np.ndarray,
                        replace: bool = False) -> str:
    """Attach the instrumented inertia (``iv``: :func:`instrumented_inertia`'s or
    :func:`~twin_nodes.discovery.rate_loop.inertia`'s result with its ``params``; ``residual``: its
    held-out numbers) to an ``inertia`` finding already made on the flight's own residuals, as a
    third residual for the axes it flags.  It is attached where the finding moves those axes the
    same way within x1.5, or held them at the model's value (then the instrument supplies them;
    ``held_at_nominal`` loses them); else the disagreement is returned and nothing changes.  With
    ``replace`` (PX4's rate loop on a log whose motor commands are aliased, where the finding's own
    roll/pitch fit is biased) the same direction is agreement enough, and the rate loop's value
    replaces the finding's (kept in ``own_params``).  Returns what happened, for the result's
    ``instrumented.verdict``."""
    params, ax = iv["params"], iv["axes"]
    agree = []
    for a in iv["flagged"]:
        k, j = IV_AXIS_PARAM[a]
        d_iv = params[k] / nominal_inertia[j] - 1.0
        d_f = entry["params"][k] / nominal_inertia[j] - 1.0
        held = k in (entry.get("held_at_nominal") or {})
        ok = held or (d_iv * d_f > 0 and (replace or max(abs(d_iv), abs(d_f)) <= 1.5 * min(abs(d_iv), abs(d_f))))
        agree.append((a, k, held, ok))
    if not all(ok for *_, ok in agree):
        return "disagrees with the " + entry["verdict"] + " finding"
    for a, k, held, _ in agree:
        if held or replace:
            if not held:
                entry.setdefault("own_params", {})[k] = entry["params"][k]
            entry["params"][k] = params[k]
            entry.get("held_at_nominal", {}).pop(k, None)
            entry.setdefault("instrumented_params", {})[k] = params[k]
    if "held_at_nominal" in entry and not entry["held_at_nominal"]:
        entry.pop("held_at_nominal")
    kind = residual.get("residual", "instrumented")
    entry.setdefault("residuals", {})[kind] = residual
    if kind == "rate_loop":
        says = "PX4's rate loop flown on the model agrees ("
        part = [f"{a} inertia x{ax[a]['scale']:.2f} +- {ax[a]['scale_se']:.2f}" for a, *_ in agree]
        held_out = f"held-out {residual['heldout_channel']} body-rate error along the inertia's sensitivity cut "
    else:
        says = "the rate setpoint as instrument agrees ("
        part = [f"{a} gain {ax[a]['gain']:.2f} +- {ax[a]['se']:.2f}" for a, *_ in agree]
        held_out = f"held-out instrument-projected {residual['heldout_channel']} error cut "
    def how(k, held):
        if held:
            return " supplied by it"
        if replace:
            return (f" in place of the finding's {entry['own_params'][k]:.4g} (fitted to motor commands logged "
                    "slower than the rate loop runs)")
        return ""
    entry["verdict_note"] = (entry.get("verdict_note", "") + "; " + says
                             + ", ".join(f"{p_}, {k} {params[k]:.4g}" + how(k, held)
                                         for p_, (a, k, held, _) in zip(part, agree))
                             + f"; {held_out}{100 * residual['heldout_improvement']:.0f} %)")
    return "corroborates the " + entry["verdict"] + " finding"


#: the output-error blocks an instrumented effect's plan asks for: the axis had none a fit could use,
#: so no block statistic says how many; PX4 SIH SIH_L_ROLL 0.16 (g26, g34): 50-65 active roll blocks
#: gave t 3.9-4.9 in one follow-up and 58 gave t 2.4 in another, so twice g34's missing 15
INSTRUMENTED_BLOCKS_MISSING = 30


#: the inertia candidate's roll and pitch parameters
_RP_AXES = tuple(k for k, _ in IV_AXIS_PARAM.values())


def _axis_tests(S: Setup, g: Fit) -> dict[str, tuple[float, int]]:
    """Per roll/pitch axis of an equation-error inertia fit ``g``: the held-out block test of the fit
    with that axis free against the same fit (each fold's) with the axis at its nominal value:
    (statistic, active blocks).  Whether the equation error identifies that axis, not just the set."""
    c = g.candidate
    out = {}
    if g.R is None or len(g.fold_thetas) != len(S.eq.folds):
        return out
    for k, name in enumerate(c.param_names):
        if name not in _RP_AXES:
            continue
        Rr = np.zeros_like(g.R)
        for (_, test), th in zip(S.eq.folds, g.fold_thetas):
            th0 = np.array(th, float)
            th0[k] = c.x0[k]
            Rr[test] = S.eq.residual(c.build(th0))[test]
        out[name] = _block_test(Rr, g.R, S.eq.blocks)
    return out


def _equation_axes(S: Setup, ranked: list[Fit], effects_out: list[dict], current: VehicleParams,
                   accepted: list[str], guard: Callable[[VehicleParams], str | None]) -> VehicleParams | None:
    """An inertia finding's roll/pitch axes, each on its own evidence.  The output error leaves an axis
    out on 50 Hz logs (aliased commands) and holds it at the model's value; the equation error fits
    every axis but, on PX4 SIH's noisy roll gyro, moves an axis it cannot resolve (SIH_IZZ x1.5 on
    M3: Ixx +17 %, Iyy +10 % for an unchanged truth).  So an axis the output error left out takes the
    equation error's value when freeing that axis alone beats the nominal on held-out blocks
    (:func:`_axis_tests`, > ``T_CRIT``), and is held at the model's value otherwise, whichever
    residual the finding was reported from.  A confirmed finding's refit vehicle follows (unless
    ``guard``, the closed-loop twin, objects).  Updates ``effects_out`` in place; returns the new
    refit vehicle (None: unchanged)."""
    refit = None
    for f, e in zip(ranked, effects_out):
        if f.candidate.name != "inertia" or e["verdict"] not in ("confirmed", "likely"):
            continue
        g, o = f.by_kind.get("equation"), f.by_kind.get("output")
        if g is None:
            continue
        left_out = set(o.candidate.held) if o is not None else set(_RP_AXES)
        axes = [a for a in _RP_AXES if a in left_out and a in g.candidate.param_names]
        if not axes:
            continue
        tests = _axis_tests(S, g)
        eqp = g.candidate.params_dict(g.theta)
        nominal = dict(zip(g.candidate.param_names, g.candidate.x0))
        params = dict(e["params"])
        held = dict(e.get("held_at_nominal") or {})
        why_held = o.candidate.held if o is not None else {}
        note = {}
        for a in axes:
            t, n = tests.get(a, (0.0, 0))
            note[a] = {"t": round(float(t), 2), "blocks": int(n), "equation_value": round(float(eqp[a]), 6)}
            if t > T_CRIT:
                params[a] = float(eqp[a])
                held.pop(a, None)
                note[a]["used"] = True
            else:
                params[a] = float(nominal[a])
                held[a] = (f"{why_held.get(a, 'held at nominal: the output error leaves the axis out')}; the "
                           f"equation error's {a} {eqp[a]:.4g} does not beat the nominal on held-out blocks "
                           f"alone (t={t:.1f} over {n})")
                note[a]["used"] = False
        if params == e["params"]:
            e["equation_axes"] = note
            continue
        if e["verdict"] == "confirmed" and f.candidate.label in accepted:
            trial = (refit or current).with_effect("inertia", **params)
            against = guard(trial)
            if against:
                e["equation_axes"] = {**note, "not_applied": against}
                continue
            refit = trial
        e["params"] = params
        e["equation_axes"] = note
        if held:
            e["held_at_nominal"] = held
        else:
            e.pop("held_at_nominal", None)
        used = [a for a in axes if note[a]["used"]]
        kept = [a for a in axes if not note[a]["used"]]
        if used:
            ts = ", ".join("t={:.1f}".format(note[a]["t"]) for a in used)
            e["verdict_note"] += (f"; {', '.join(used)} from the equation error (freeing it alone beats the "
                                  f"nominal on held-out blocks: {ts})")
        if kept:
            e["verdict_note"] += f"; {', '.join(kept)} held at the model's value (not resolved on its own)"
    return refit


def _left_out_text(win: Windows, axes: list[str], motor_dt_s: float) -> str:
    """Why the output error could not fit these axes, and what follow-up flight would."""
    r2 = ", ".join(f"{a} r^2 {win.axis_r2[AXES.index(a)]:.3f}" for a in axes)
    if motor_dt_s > RATE_LOOP_LOG_S:
        return (f"the output error leaves the axis out ({r2} < {MIN_AXIS_R2}: motors logged every "
                f"{1000 * motor_dt_s:.0f} ms, aliased): confirm on a flight with the motors logged every 4 ms "
                "(rate doublets)")
    return (f"the output error leaves the axis out ({r2} < {MIN_AXIS_R2}, too little of it excited): confirm "
            "on a flight with more rate doublets")


def _instrumented(S: Setup, current: VehicleParams, accepted: list[str], effects_out: list[dict],
                  guard: Callable[[VehicleParams], str | None] = lambda vp: None,
                  nominal: VehicleParams | None = None) -> tuple[dict | None, VehicleParams | None]:
    """Roll/pitch inertia on the axes the output error leaves out, with the rate setpoint as
    instrument (:func:`~twin_nodes.discovery.output_error.instrumented_inertia`), on top of what
    was accepted.  On its own it can only be ``likely``: a single moment on an axis no fit can
    resolve, for a follow-up flight with the motors logged at the rate loop's rate (where the axis
    is usable) to confirm; beside an ``inertia`` finding it is a third residual
    (:func:`attach_instrumented`).  A *confirmed* inertia that held an axis at the model's value
    gets that axis from the instrument when it passes the same checks and ``guard`` (the closed-loop
    twin on the held-out part) has nothing against it (the refit vehicle with it is returned).  Updates the ``inertia`` entry of ``effects_out`` in place (re-sorted by grade);
    returns the numbers for the result (None: nothing to instrument) and the new refit vehicle
    (None: unchanged)."""
    win = S.windows
    if win is None:
        return None, None
    entry = next((e for e in effects_out if e["name"] == "inertia"), None)
    d = S.data
    finding = "inertia" in accepted or (entry is not None and entry["verdict"] == "likely")
    if (finding and entry is None) or (not finding and any(name == "inertia" for name, _ in current.effects)):
        return None, None
    I_cur = np.diag(effective_params(current).inertia)
    # a confirmed finding leaves the instrument the axes it held at the model's value
    held = (entry or {}).get("held_at_nominal") or {}
    allowed = (tuple(a for a, (k, _) in IV_AXIS_PARAM.items() if k in held) if "inertia" in accepted
               else ("roll", "pitch"))
    fold1, fold2 = _window_folds(win, S.t_split, S.t_split2)

    def build(ixx, iyy):
        return current.with_effect("inertia", ixx=ixx, iyy=iyy, izz=float(I_cur[2]))

    def flown(vp_on, axes):
        """PX4's rate loop on ``vp_on`` (a PX4 log: no aliased motor commands in it), None where the
        log has none or it reads an axis at the edge of its range (then the reason)."""
        r = rate_loop.inertia(d, S.log_params, vp_on, S.t_split, S.t_split2, axes)
        if r is not None and r.get("pinned"):
            return None, (f"PX4's rate loop on the model reads {', '.join(r['pinned'])} at the edge of x0.5-x2 of "
                          "the model's inertia: not this vehicle's rate loop, the rate setpoint as instrument instead")
        return r, None
    iv, not_used, reference, replace = None, None, I_cur, False
    if finding and d.motor_dt_s > RATE_LOOP_LOG_S and nominal is not None:
        # the finding's roll/pitch were fitted to aliased motor commands (the output error's least
        # squares is attenuated, the equation error's roll noisy): PX4's rate loop, which uses none,
        # reads both axes against the model's own inertia and supplies what it flags
        I_nom = np.diag(effective_params(nominal).inertia)
        iv, not_used = flown(current.with_effect("inertia", ixx=float(I_nom[0]), iyy=float(I_nom[1]),
                                                 izz=float(I_cur[2])), ("roll", "pitch"))
        replace = iv is not None
        reference = I_nom if replace else I_cur
    if not replace:
        if not allowed:
            return None, None
        if not_used is None:
            iv, not_used = flown(current, allowed)
        if iv is None:
            iv = instrumented_inertia(d, win, current, fold1, fold2, build, allowed)
    if iv is None:
        return None, None
    if replace and iv.get("params"):
        # an axis the rate loop does not flag keeps the finding's value
        for a, (k, j) in IV_AXIS_PARAM.items():
            if a not in iv["flagged"]:
                iv["params"][k] = float(I_cur[j])
    method = iv.get("method", "instrument")
    out = {"method": method,
           "axes": {a: {k: (round(float(v), 4) if isinstance(v, float) else v) for k, v in ax.items() if k != "index"}
                    for a, ax in iv["axes"].items()},
           "yaw_gain": round(float(iv["yaw_gain"]), 4), "flagged": iv["flagged"], "verdict": "none",
           "motor_signature": bool(iv.get("motor_signature"))}
    if method == "rate_loop":
        out.update(loop=iv["loop"], windows=iv["windows"], window_s=iv["window_s"],
                   yaw_scale=round(float(iv["yaw_scale"]), 4), curve=iv["curve"])
    if not_used:
        out["rate_loop_not_used"] = not_used
    if not iv["flagged"]:
        return out, None
    why = []
    if iv.get("motor_signature"):
        why.append(f"yaw is off the same way (gain {iv['yaw_gain']:.3f} +- {iv['yaw_se']:.3f}): the motors (lag, "
                   "delay, thrust or moment per command), not the inertia")
    ax = iv["axes"]
    main = max(iv["flagged"], key=lambda a: ax[a].get("heldout_before", 0.0) or 0.0)
    for a in iv["flagged"]:
        x = ax[a]
        lo, hi = IV_GAIN_RANGE
        if not lo <= x["gain"] <= hi:
            why.append(f"{a} gain {x['gain']:.2f} outside the physical range")
        sides = [(x[f"gain_fold{k}"] - 1.0) / x[f"se_fold{k}"] for k in (1, 2)
                 if np.isfinite(x[f"gain_fold{k}"]) and np.isfinite(x[f"se_fold{k}"]) and x[f"se_fold{k}"] > 0]
        if len(sides) < 2 or not all(abs(t) > 2.0 and np.sign(t) == np.sign(x["gain"] - 1.0) for t in sides):
            why.append(f"the two folds do not both move {a} the same way at 2 standard errors")
    m = ax[main]
    b0, b1 = m.get("heldout_before", math.nan), m.get("heldout_after", math.nan)
    cut = 1.0 - b1 / b0 if np.isfinite(b0) and np.isfinite(b1) and b0 > 0 else math.nan
    rl = method == "rate_loop"
    kind = "rate_loop" if rl else "instrumented"
    what = (f"{main} body-rate error along its sensitivity to the inertia (PX4's rate loop flown on the model)" if rl
            else f"instrument-projected {main} error")
    if not (cut >= LIKELY_MIN_CUT):
        why.append(f"held-out cut of the {what} {100 * cut:.0f} % < {100 * LIKELY_MIN_CUT:.0f} %")
    params = iv.get("params")
    out.update(params=params, heldout_channel=main, heldout_improvement=round(float(cut), 4) if np.isfinite(cut) else None)
    if why or params is None:
        out["verdict"] = "none"
        out["why_not"] = why
        return out, None
    out["verdict"] = "likely"
    if rl:
        note = ("likely (rate loop): PX4's rate loop (the log's gains and filters) flown on the model from the logged "
                "rate setpoint reads " + ", ".join(f"{a} inertia x{ax[a]['scale']:.2f} +- {ax[a]['scale_se']:.2f}"
                                                   for a in iv["flagged"])
                + f" (yaw x{iv['yaw_scale']:.2f}: not the motors); held-out {what} cut {100 * cut:.0f} %; "
                + _left_out_text(win, iv["flagged"], d.motor_dt_s))
    else:
        note = ("likely (instrumented): the rate setpoint as instrument gives "
                + ", ".join(f"{a} gain {ax[a]['gain']:.2f} +- {ax[a]['se']:.2f}" for a in iv["flagged"])
                + f" (yaw {iv['yaw_gain']:.2f}: not the motors); held-out {what} cut "
                  f"{100 * cut:.0f} %; " + _left_out_text(win, iv["flagged"], d.motor_dt_s))
    if entry is not None and entry.get("closed_loop"):
        # the inertia the flight's own residuals fitted was dropped by the closed-loop twin: the
        # instrument does not bring the effect back on its own
        out["verdict"] = "none"
        out["why_not"] = [f"the inertia fitted on this flight {entry['closed_loop']}"]
        return out, None
    prev = dict(entry) if entry is not None else {}
    residual = {"residual": kind, "heldout_channel": main, "heldout_before": round(float(b0), 5),
                "heldout_after": round(float(b1), 5), "heldout_improvement": round(float(cut), 4),
                "heldout_t_stat": round(float(m.get("heldout_t", math.nan)), 2), "params": params,
                "fold_gains": [round(float(ax[main]["gain_fold1"]), 4), round(float(ax[main]["gain_fold2"]), 4)]}
    if entry is not None and entry["verdict"] != "rejected":
        # already a finding on its own residuals: the instrument is a third residual for its axes
        refit = None
        if entry["verdict"] == "confirmed":
            # the refit vehicle takes the axes the confirmed fit held and the instrument supplies,
            # unless the closed-loop twin says otherwise
            refit = build(float(params["ixx"]), float(params["iyy"]))
            against = guard(refit)
            if against:
                out["verdict"] = f"not supplied to the confirmed finding: {against}"
                return out, None
        out["verdict"] = attach_instrumented(entry, iv, residual, reference, replace)
        return out, refit if out["verdict"].startswith("corroborates") else None
    # standard errors of the instrumented axes (from the fit part's gain: I/g, se_I = I se_g / g)
    params_se = {}
    for a in iv["flagged"]:
        k = IV_AXIS_PARAM[a][0]
        g1, s1 = ax[a]["gain_fold1"], ax[a]["se_fold1"]
        if np.isfinite(g1) and np.isfinite(s1) and g1 > 0:
            params_se[k] = float(params[k] * s1 / g1)
    new = {"name": "inertia", "accepted": False, "verdict": "likely", "verdict_note": note, "params": params,
           "params_se": params_se,
           "evidence": (f"inertia ({', '.join(f'{k}={v:.4g}' for k, v in params.items())}) cuts the held-out "
                        f"{what} by {100 * cut:.0f} %: likely ({'rate loop' if rl else 'instrumented'})"),
           "residual": kind, "heldout_channel": main, "heldout_before": residual["heldout_before"],
           "heldout_after": residual["heldout_after"],
           "heldout_units": ((f"{main} body-rate error along its sensitivity to the inertia, |sum <J, e>| / |J| "
                              "(rad/s), held-out windows of PX4's rate loop flown on the model") if rl else
                             (f"RMS of the output error in {main} projected on the rate setpoint's change (rad/s^2) "
                              "on the held-out part")),
           "heldout_improvement": residual["heldout_improvement"], "heldout_t_stat": residual["heldout_t_stat"],
           "cv_improvement": residual["heldout_improvement"], "above_resolution_floor": True,
           "excitation": {**(prev.get("excitation") or {}), "channel": main, "residual": kind,
                          **({"windows": iv["windows"]} if rl else {"instrument_r": round(float(m["instrument_r"]), 3)}),
                          "plans": ["rate_doublets"], "blocks_missing": INSTRUMENTED_BLOCKS_MISSING,
                          "supplied_by": "roll and pitch rate doublets" + (
                              " with the motors logged every 4 ms (PX4: SDLOG_PROFILE's high-rate bit), where the "
                              "output error can fit the axis" if d.motor_dt_s > RATE_LOOP_LOG_S else "")},
           "residuals": {**(prev.get("residuals") or {}), kind: residual},
           "alternatives": []}
    if entry is not None:
        effects_out.remove(entry)
    k = next((i for i, e in enumerate(effects_out) if _GRADE_ORDER[e["verdict"]] > 1
              or (e["verdict"] == "likely" and (e.get("cv_improvement") or 0) < new["cv_improvement"])), len(effects_out))
    effects_out.insert(k, new)
    return out, None


def _rate_loop_lag(S: Setup, current: VehicleParams, effects_out: list[dict]) -> dict | None:
    """The motors' time constant read by PX4's rate loop flown on the model
    (:func:`~twin_nodes.discovery.rate_loop.motor_lag`), where the rate loop said the motors, not an
    inertia, are slow (every axis off the same way) and the model's lag and delay are its own.

    It is ``likely`` when the lag is far from the model's on every axis alike, both folds move it the
    same way by 2 standard errors, fold 1's lag cuts the held-out rate error along its sensitivity by
    ``LIKELY_MIN_CUT``, lies inside the effect's physical range, and beats an extra delay on the
    held-out windows; never ``confirmed`` (no residual of the flight's own shows it: PX4 SIH
    SIH_T_TAU 0.09 s on a 50 Hz log, where lag and delay cut the output error 9-10 %).  The entry
    replaces the flight's own ``motor_time_constant`` (kept as its residuals), re-sorted by grade.
    Returns the numbers for the result (None: not looked at)."""
    if any(name in MOTOR_DYNAMICS for name, _ in current.effects):
        return None
    r = rate_loop.motor_lag(S.data, S.log_params, current, S.t_split, S.t_split2)
    if r is None:
        return None
    out = {k: (round(float(v), 5) if isinstance(v, float) else v) for k, v in r.items() if k not in ("loop", "heldout_sse")}
    out["heldout_sse"] = {k: round(float(v), 2) for k, v in r["heldout_sse"].items()}
    out["verdict"] = "none"
    tau0, tau1 = r["model_tau"], r["tau_fold1"]
    if not r["flagged"]:
        out["why_not"] = [f"the lag {r['tau']:.3f} +- {r['se']:.3f} s is not far from the model's {tau0:.3f} s on "
                          f"every axis alike (roll, pitch, yaw {', '.join(f'{v:.3f}' for v in r['axis_tau'].values())})"]
        return out
    why = []
    sides = [(r[f"tau_fold{k}"] - tau0) / r[f"se_fold{k}"] for k in (1, 2)
             if np.isfinite(r[f"tau_fold{k}"]) and np.isfinite(r[f"se_fold{k}"]) and r[f"se_fold{k}"] > 0]
    if len(sides) < 2 or not all(abs(t) > 2.0 and np.sign(t) == np.sign(r["tau"] - tau0) for t in sides):
        why.append("the two folds do not both move the lag the same way at 2 standard errors")
    b0, b1 = r["heldout_before"], r["heldout_after"]
    cut = 1.0 - b1 / b0 if np.isfinite(b0) and np.isfinite(b1) and b0 > 0 else math.nan
    if not (cut >= LIKELY_MIN_CUT):
        why.append(f"held-out cut of the body-rate error along the lag's sensitivity {100 * cut:.0f} % < "
                   f"{100 * LIKELY_MIN_CUT:.0f} %")
    lo, hi = EFFECTS["motor_time_constant"].ranges["tau_up"]
    if not lo <= tau1 <= hi:
        why.append(f"lag {tau1:.3f} s outside the physical range {lo:g}-{hi:g} s")
    held = r["heldout_sse"]
    if not held["lag"] < held["delay"]:
        why.append(f"an extra {1e3 * r['delay_fold1']:.0f} ms delay fits the held-out windows as well "
                   f"(sum of squares {held['delay']:.0f} vs the lag's {held['lag']:.0f})")
    out["heldout_improvement"] = round(float(cut), 4) if np.isfinite(cut) else None
    if why:
        out["why_not"] = why
        return out
    out["verdict"] = "likely"
    params = {"tau_up": float(tau1), "tau_down": float(tau1)}
    # reported in the axis the lag moves most (as projected_view), the joint numbers beside it
    per = r["heldout_axes"]
    main = max(per, key=lambda a: per[a]["before"] if np.isfinite(per[a]["before"]) else -1.0)
    residual = {"residual": "rate_loop", "heldout_channel": main, "heldout_before": round(float(per[main]["before"]), 5),
                "heldout_after": round(float(per[main]["after"]), 5),
                "heldout_improvement": round(float(per[main]["cut"]), 4),
                "heldout_axes": {a: {k: round(float(v), 4) for k, v in x.items()} for a, x in per.items()},
                "heldout_joint": {"before": round(float(b0), 5), "after": round(float(b1), 5),
                                  "cut": round(float(cut), 4), "t": round(float(r["heldout_t"]), 2)},
                "heldout_t_stat": round(float(r["heldout_t"]), 2), "params": params,
                "fold_params": [round(float(r["tau_fold1"]), 5), round(float(r["tau_fold2"]), 5)]}
    prev = next((e for e in effects_out if e["name"] == "motor_time_constant"), None)
    if prev is not None and prev["verdict"] in ("confirmed", "likely"):
        return out
    axis_tau = ", ".join(f"{a} {v:.3f}" for a, v in r["axis_tau"].items())
    note = (f"likely (rate loop): PX4's rate loop (the log's gains and filters) flown on the model from the logged "
            f"rate setpoint reads the motors' lag {r['tau']:.3f} +- {r['se']:.3f} s for the model's {tau0:.3f} "
            f"(each axis: {axis_tau} s); held-out body-rate error along the lag's sensitivity cut {100 * cut:.0f} % "
            f"(roll, pitch, yaw together; {main} {100 * per[main]['cut']:.0f} %); "
            f"an extra {1e3 * r['delay_fold1']:.0f} ms delay instead fits the held-out windows worse (sum of squares "
            f"{held['delay']:.0f} vs {held['lag']:.0f}); confirm on a flight with the motors logged every 4 ms "
            "(rate doublets), where the output error resolves it")
    new = {"name": "motor_time_constant", "accepted": False, "verdict": "likely", "verdict_note": note,
           "params": params, "params_se": {"tau_up": float(r["se_fold1"]), "tau_down": float(r["se_fold1"])},
           "evidence": (f"motor_time_constant (tau {tau1:.4g} s) cuts the held-out body-rate error of PX4's rate loop "
                        f"along its sensitivity by {100 * cut:.0f} %: likely (rate loop)"),
           "residual": "rate_loop", "heldout_channel": main, "heldout_before": residual["heldout_before"],
           "heldout_after": residual["heldout_after"],
           "heldout_units": (f"{main} body-rate error (in units of its own RMS) along its sensitivity to the lag, "
                             "|sum <J, e>| / |J|, held-out windows of PX4's rate loop flown on the model"),
           "heldout_improvement": residual["heldout_improvement"], "heldout_t_stat": residual["heldout_t_stat"],
           "cv_improvement": residual["heldout_improvement"], "above_resolution_floor": True,
           "excitation": {**((prev or {}).get("excitation") or {}), "channel": main,
                          "residual": "rate_loop", "windows": r["windows"], "plans": ["rate_doublets"],
                          "blocks_missing": INSTRUMENTED_BLOCKS_MISSING,
                          "supplied_by": "roll and pitch rate doublets with the motors logged every 4 ms (PX4: "
                                         "SDLOG_PROFILE's high-rate bit), where the output error can fit the lag"},
           "residuals": {**((prev or {}).get("residuals") or {}), "rate_loop": residual},
           "alternatives": [{"name": "actuator_delay", "params": {"delay": float(r["delay_fold1"])},
                             "heldout_sse": held["delay"], "note": "the rate loop's best extra delay"}]}
    if prev is not None:
        effects_out.remove(prev)
    k = next((i for i, e in enumerate(effects_out) if _GRADE_ORDER[e["verdict"]] > 1
              or (e["verdict"] == "likely" and (e.get("cv_improvement") or 0) < new["cv_improvement"])), len(effects_out))
    effects_out.insert(k, new)
    return out


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
        "above_resolution_floor": bool(f.above_floor),
        "excitation": f.excitation,
        "residuals": {f.kind: _summary(f)},
        "alternatives": f.alternatives,
    }
    if f.candidate.held:
        out["held_at_nominal"] = dict(f.candidate.held)
    if f.closed_loop:
        out["closed_loop"] = f.closed_loop
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


def _joint_refit(accepted: list[Fit], data, nominal, fit_mask) -> VehicleParams:
    """Refit the equation-error effects among ``accepted`` jointly (they may interact); effects
    found on the output error keep their values (the equation error cannot see them well)."""
    base = nominal
    for f in accepted:
        if f.kind != "equation":
            base = base.with_effect(f.candidate.name, **f.candidate.params_dict(f.theta))
    eq_fits = [f for f in accepted if f.kind == "equation"]
    if not eq_fits:
        return base
    cands = [f.candidate for f in eq_fits]
    sizes = [len(c.x0) for c in cands]
    x0 = np.concatenate([f.theta for f in eq_fits])
    lo = np.concatenate([c.lower for c in cands])
    hi = np.concatenate([c.upper for c in cands])
    s = np.maximum(np.abs(x0), 1e-6)

    def build(theta):
        vpj = base
        k = 0
        for c, n in zip(cands, sizes):
            vpj = vpj.with_effect(c.name, **c.params_dict(theta[k:k + n]))
            k += n
        return vpj

    def resid(z):
        return residual_channels(data, build(np.clip(z * s, lo, hi)), nominal)[fit_mask].ravel()

    sol = least_squares(resid, x0 / s, bounds=(lo / s, hi / s), diff_step=1e-3, max_nfev=80)
    theta = np.clip(sol.x * s, lo, hi)
    k = 0
    for f, n in zip(eq_fits, sizes):
        f.theta = theta[k:k + n]
        k += n
    return build(theta)


#: closed-loop twin runs of this discover call: (log, vp, t0, t1) ids -> (log, vp, evaluate.Pending)
_CLOSED_LOOP: dict[tuple, tuple] = {}


def _closed_loop_reset() -> None:
    for _, _, run in _CLOSED_LOOP.values():
        run.cancel()
    _CLOSED_LOOP.clear()


def _closed_loop_run(log, vp: VehicleParams, t0: float, t1: float, background: bool):
    key = (id(log), id(vp), float(t0), float(t1))
    hit = _CLOSED_LOOP.get(key)
    if hit is None or hit[0] is not log or hit[1] is not vp:
        def fn():
            return _closed_loop_twin(log, vp, t0, t1)
        run = evaluate.start(fn) if background else evaluate.Pending(fn, background=False)
        hit = _CLOSED_LOOP[key] = (log, vp, run)
    return hit[2]


def _prefetch_closed_loop(log, vp: VehicleParams, t0: float, t1: float) -> None:
    """Start the closed-loop run that :func:`_closed_loop_metrics` will ask for (another process)."""
    _closed_loop_run(log, vp, t0, t1, background=True)


def _closed_loop_metrics(log, vp: VehicleParams, t0: float, t1: float) -> dict:
    """Closed-loop twin metrics (Table 2 + throttle + motors) on [t0, t1], each vehicle flown once
    per discover call (or ahead, in another process: :func:`_prefetch_closed_loop`)."""
    return copy.deepcopy(_closed_loop_run(log, vp, t0, t1, background=False).result())


def _closed_loop_twin(log, vp: VehicleParams, t0: float, t1: float) -> dict:
    """Closed-loop twin metrics (Table 2 + throttle + motors) on [t0, t1].

    The twin flies the whole flight (so it reaches the window in a realistic state);
    only the window is scored."""
    from twin_nodes.twin.compare import align
    from twin_nodes.twin.metrics import flight_metrics
    from twin_nodes.twin.runner import run_twin_on_log

    m = flight_metrics(align(run_twin_on_log(log, vp, mode="closed"), log, t0=t0, t1=t1))
    m["interval_s"] = [round(t0, 2), round(t1, 2)]
    return m


#: the closed-loop twin is "worse" when its held-out throttle RMSE rises by more than this fraction:
#: below it the change is the closed-loop run's numerical resolution, not the effect.  Effects that do
#: not act on the collective (inertia, yaw moment) move it by 1e-6..4e-6 of full throttle (0.01-0.04 %);
#: a strict comparison dropped the true inertia on 4 of 5 PX4 SIH flights and the true yaw moment on
#: one (e.g. e11: 0.011723 -> 0.011724)
CLOSED_LOOP_TOL_REL = 0.005


def _worse(rmse: float, best: float, baseline: float) -> bool:
    """Worse than the best so far (or than the nominal twin) beyond ``CLOSED_LOOP_TOL_REL``."""
    return rmse > (1.0 + CLOSED_LOOP_TOL_REL) * min(best, baseline)


def _closed_loop_guard(accepted: list[Fit], log, nominal: VehicleParams, data, fit_mask, t0: float, t1: float
                       ) -> tuple[list[Fit], VehicleParams, dict]:
    """Add the accepted effects one at a time (in acceptance order); drop each one that makes the
    closed-loop twin's held-out throttle RMSE worse.  Returns the kept effects, their (re)fitted
    vehicle and the metrics cache ``{"before": ..., "after": ...}``."""
    before = _closed_loop_metrics(log, nominal, t0, t1)
    best = before["throttle_rmse"]
    kept: list[Fit] = []
    current = nominal
    for f in accepted:
        trial = kept + [f]
        vp_t = _joint_refit(trial, data, nominal, fit_mask) if len(trial) > 1 else f.vp
        m = _closed_loop_metrics(log, vp_t, t0, t1)
        if not _worse(m["throttle_rmse"], best, before["throttle_rmse"]):
            kept, current, best, after = trial, vp_t, m["throttle_rmse"], m
        else:
            f.accepted = False
            f.closed_loop = (f"makes the closed-loop twin worse on the held-out part (throttle RMSE "
                             f"{best:.6f} -> {m['throttle_rmse']:.6f})")
    return kept, current, {"before": before, "after": after if kept else before}


def _closed_loop(result: dict, log, before: VehicleParams, after: VehicleParams, t0: float, t1: float,
                 cached: dict | None = None) -> None:
    """Closed-loop twin metrics on the held-out part, before and after (reusing the guard's runs)."""
    out = dict(cached or {})
    for key, p in (("before", before), ("after", after)):
        if key not in out:
            out[key] = _closed_loop_metrics(log, p, t0, t1)
    result["baseline"]["closed_loop_heldout"] = out["before"]
    result["after"]["closed_loop_heldout"] = out["after"]
