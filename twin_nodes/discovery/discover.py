"""Missing-physics discovery: locate the mismatch, name the physics left out, refit, show it on held-out data.

Method (all on equation-error residuals, :mod:`twin_nodes.discovery.residuals`):

1. **Locate.**  Split the residual into collective (throttle), differential per
   motor and horizontal-force channels; flag 2-s windows whose low-passed RMS is
   more than 3x the channel's own noise floor (estimated from its high-frequency
   content), label each by flight regime, merge neighbours.
2. **Name.**  Fit every candidate effect (:mod:`twin_nodes.discovery.candidates`)
   on the first part of the flight; judge it on the held-out rest.  An effect is
   accepted only if (a) its fitted size is above the physical resolution floor,
   (b) it lowers the held-out residual in a block test (t > 3 over >= 4
   independent blocks, so autocorrelation cannot fake significance), and (c) it
   explains at least 10 % of the held-out residual RMS.  Greedy forward
   selection: accept the best, refit the others on top of it.
3. **Refit** all accepted effects jointly with the nominal parameters they
   interact with, and report before/after on the held-out part.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from twin_nodes.discovery.candidates import Candidate, build_candidates
from twin_nodes.discovery.residuals import (LOWPASS_HZ, EquationData, channel_names, modes, prepare,
                                            residual_channels)
from twin_nodes.params import VehicleParams

HELDOUT_FRACTION = 0.35
# Blocks one low-pass period long: the residual's correlation time is set by the common
# LOWPASS_HZ filter, so blocks of 1/LOWPASS_HZ are close to independent.
BLOCK_S = 1.0 / LOWPASS_HZ
T_CRIT = 3.0
# choosing between candidates that are each already significant is model selection, not
# detection: the more complex one must beat the simpler one at one-sided 2 sigma
T_CHOICE = 2.0
MIN_REL_IMPROVEMENT = 0.10
MAX_EFFECTS = 3


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


def _scales(c: Candidate) -> np.ndarray:
    s = np.abs(c.x0).copy()
    span = c.upper - c.lower
    s = np.where(s > 1e-12, s, span / 20.0)
    return np.maximum(s, 1e-9)


def _blocks(t: np.ndarray, mask: np.ndarray, block_s: float) -> list[np.ndarray]:
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return []
    edges = np.arange(t[idx[0]], t[idx[-1]] + block_s, block_s)
    which = np.digitize(t[idx], edges)
    return [idx[which == k] for k in np.unique(which) if (which == k).sum() >= 0.5 * block_s / (t[1] - t[0])]


def _block_test(R0: np.ndarray, R1: np.ndarray, blocks: list[np.ndarray]) -> tuple[float, int]:
    """t statistic of the per-block drop in mean squared residual, over the blocks where the
    candidate changes the prediction at all (>= 25 % of its 90th-percentile block change, so
    one violent manoeuvre cannot silence the rest).

    Effects that act only in some regimes (drag in forward flight, ground effect near the
    ground) leave the other blocks unchanged; counting those would only add variance.  The
    blocks are chosen from the change itself, not from whether it helped, so this does not
    favour the candidate."""
    delta = np.array([np.sqrt(np.mean((R1[b] - R0[b]) ** 2)) for b in blocks])
    if delta.size == 0 or delta.max() <= 0:
        return 0.0, 0
    ref = np.percentile(delta, 90)
    active = [b for b, dl in zip(blocks, delta) if dl >= 0.25 * ref]
    d = np.array([np.mean(R0[b] ** 2) - np.mean(R1[b] ** 2) for b in active])
    if d.size < 4:
        return 0.0, int(d.size)
    sd = d.std(ddof=1)
    t = (math.inf if d.mean() > 0 else 0.0) if sd == 0 else float(d.mean() / (sd / math.sqrt(d.size)))
    # Sign test on the same blocks: the t test loses power when the gains are heavy-tailed
    # (a few manoeuvres carry an inertia or yaw-moment effect).  Under "no effect" a held-out
    # block improves with probability <= 1/2; the binomial tail is mapped to the equivalent
    # one-sided normal quantile so both tests share the threshold T_CRIT.
    # Fisher's sign-flip randomization test keeps the size of the gains without assuming
    # normality: under "no effect" each block's gain is as likely to be a loss of the same
    # size.  20000 fixed-seed flips resolve p down to 5e-5.  The largest of the three
    # statistics is used; at the one-sided 3 sigma level the union's false-alarm rate stays
    # under 0.5 %.
    from scipy.stats import binom, norm
    k = int(np.sum(d > 0))
    p = float(binom.sf(k - 1, d.size, 0.5))
    z = float(norm.isf(max(p, 1e-300)))
    flips = np.random.default_rng(12345).choice((-1.0, 1.0), size=(20000, d.size))
    p_flip = (1.0 + np.sum(flips @ np.abs(d) >= d.sum())) / (1.0 + flips.shape[0])
    zw = float(norm.isf(p_flip))
    return max(t, z, zw), int(d.size)


def fit_candidate(c: Candidate, data: EquationData, nominal: VehicleParams, fit_mask: np.ndarray,
                  max_nfev: int = 60) -> tuple[np.ndarray, VehicleParams, float]:
    """Least-squares fit of one candidate's parameters on the fit samples."""
    s = _scales(c)
    lo, hi = c.lower / s, c.upper / s

    def resid(z):
        theta = np.clip(z * s, c.lower, c.upper)
        R = residual_channels(data, c.build(theta), nominal)
        return R[fit_mask].ravel()

    z0 = np.clip(c.x0 / s, lo, hi)
    if len(z0) == 1:
        # one parameter: a grid then a bounded scalar search (delays give piecewise-flat costs)
        from scipy.optimize import minimize_scalar

        def cost1(z):
            return float(np.sum(resid(np.array([z])) ** 2))
        grid = np.linspace(lo[0], hi[0], 25)
        costs = [cost1(z) for z in grid]
        k = int(np.argmin(costs))
        a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
        sol = minimize_scalar(cost1, bounds=(a, b), method="bounded", options={"xatol": 1e-4 * (hi[0] - lo[0])})
        z = sol.x if sol.fun <= costs[k] else grid[k]
        theta = np.clip(np.array([z]) * s, c.lower, c.upper)
        return theta, c.build(theta), min(float(sol.fun), costs[k])
    best_z, best_cost = z0, float(np.sum(resid(z0) ** 2))
    # Starting points: parameters whose nominal value is zero (drag, offsets, delays) span
    # orders of magnitude, so scan them jointly on a log grid of their range; the others
    # +-20 % around the nominal.  Least squares then starts from the best, inside the bounds.
    starts = []
    zero = c.x0 == 0
    for frac in (0.002, 0.006, 0.02, 0.06, 0.2):
        z = z0.copy()
        z[zero] = lo[zero] + frac * (hi[zero] - lo[zero])
        if np.any(zero):
            starts.append(z)
            if np.any(lo[zero] < 0):  # signed parameters (offsets, wind): both directions
                z2 = z0.copy()
                z2[zero] = hi[zero] - frac * (hi[zero] - lo[zero])
                starts.append(z2)
    for j in np.flatnonzero(~zero):
        for f in (0.8, 1.2):
            z = z0.copy()
            z[j] = z0[j] * f
            starts.append(z)
    for z in starts:
        z = np.clip(z, lo, hi)
        cost = float(np.sum(resid(z) ** 2))
        if cost < best_cost:
            best_z, best_cost = z, cost
    sol = least_squares(resid, best_z, bounds=(lo, hi), x_scale=1.0, diff_step=1e-2, max_nfev=max_nfev,
                        method="trf")
    theta = np.clip(sol.x * s, c.lower, c.upper)
    return theta, c.build(theta), float(2 * sol.cost)


def assess(c: Candidate, data: EquationData, nominal: VehicleParams, R0: np.ndarray,
           folds: list[tuple[np.ndarray, np.ndarray]], blocks: list[np.ndarray], held_mask: np.ndarray) -> Fit:
    """Fit ``c`` on each fold's fit part and judge it on that fold's unseen part (2-fold CV).

    The block test pools the test blocks of both folds, each predicted by the fit that did
    not see it.  The reported parameters and held-out numbers are fold 1's (fit on the
    first part of the flight, judged on the last)."""
    Rcv = np.zeros_like(R0)
    first = None
    for fit_mask, test_mask in folds:
        theta, vp_c, cost = fit_candidate(c, data, nominal, fit_mask)
        R1 = residual_channels(data, vp_c, nominal)
        Rcv[test_mask] = R1[test_mask]
        if first is None:
            first = (theta, vp_c, cost, R1)
    theta, vp_c, cost, R1 = first
    test_all = np.zeros(len(R0), bool)
    for _, test_mask in folds:
        test_all |= test_mask
    h0 = np.sqrt(np.mean(R0[test_all] ** 2))
    hcv = np.sqrt(np.mean(Rcv[test_all] ** 2))
    t_stat, nb = _block_test(R0, Rcv, blocks)
    rel = 1.0 - hcv / h0 if h0 > 0 else 0.0
    # an estimate pinned to the edge of the physical range is not an identification
    span = c.upper - c.lower
    at_bound = bool(np.any((np.abs(theta - c.upper) < 0.01 * span) |
                           ((np.abs(theta - c.lower) < 0.01 * span) & (np.abs(c.x0 - c.lower) > 0.01 * span))))
    fit = Fit(c, theta, vp_c, cost, float(np.sqrt(np.mean(R1[held_mask] ** 2))),
              np.sqrt(np.mean(R1[held_mask] ** 2, axis=0)), t_stat, nb, float(rel), bool(c.floor(theta)))
    fit.at_bound = at_bound
    fit.R = Rcv
    h0_held = np.sqrt(np.mean(R0[held_mask] ** 2))
    fit.heldout_cut = float(1.0 - fit.heldout_rms / h0_held) if h0_held > 0 else 0.0
    # the physical mode (throttle, roll, pitch, yaw, force_x, force_y) where the effect acts
    m0, mnames = modes(R0[held_mask], nominal)
    m1, _ = modes(R1[held_mask], nominal)
    r0 = np.sqrt(np.mean(m0 ** 2, axis=0))
    r1 = np.sqrt(np.mean(m1 ** 2, axis=0))
    k = int(np.argmax(r0 ** 2 - r1 ** 2))
    fit.judged = (mnames[k], float(r0[k]), float(r1[k]))
    return fit


def _parsimonious(winner: Fit, accepted: list[Fit], blocks: list[np.ndarray]) -> Fit:
    """Prefer a simpler accepted candidate unless the winner beats it on held-out blocks."""
    best = winner
    for f in sorted(accepted, key=lambda f: len(f.candidate.param_names)):
        if f is best or len(f.candidate.param_names) >= len(best.candidate.param_names):
            continue
        t, _ = _block_test(f.R, best.R, blocks)
        if t <= T_CHOICE:
            best = f
    return best


def regimes(data: EquationData) -> np.ndarray:
    """Flight regime label per sample."""
    v = data.v
    hs = np.hypot(v[:, 0], v[:, 1])
    yaw_rate = np.abs(data.w[:, 2])
    lab = np.full(data.n, "hover", dtype=object)
    lab[hs > 2.0] = "forward 2-5 m/s"
    lab[hs > 5.0] = "forward >5 m/s"
    lab[v[:, 2] > 0.5] = "climb"
    lab[v[:, 2] < -0.5] = "descent"
    lab[yaw_rate > 0.5] = "yaw turn"
    lab[data.height < 1.5] = "near ground"
    batt = data.battery_v
    if np.isfinite(batt).mean() > 0.8:
        lo, hi = np.nanmin(batt), np.nanmax(batt)
        if hi - lo > 0.02 * hi:
            low = batt < lo + 0.3 * (hi - lo)
            lab[low] = np.array([f"{x}, battery low" for x in lab[low]], dtype=object)
    return lab


def locate(data: EquationData, R: np.ndarray, raw: np.ndarray, names: list[str], window_s: float = 2.0,
           factor: float = 3.0, per_channel: int = 8) -> list[dict]:
    """Time windows, channels and regimes where the residual exceeds its noise floor."""
    n_rot = len(names) - 2
    coll = R[:, :n_rot].mean(1)
    coll_raw = raw[:, :n_rot].mean(1)
    chans = {"throttle": (coll, coll_raw)}
    for i in range(n_rot):
        chans[names[i]] = (R[:, i] - coll, raw[:, i] - coll_raw)
    chans["force_x"] = (R[:, n_rot], raw[:, n_rot])
    chans["force_y"] = (R[:, n_rot + 1], raw[:, n_rot + 1])
    fs = 1.0 / data.dt
    lab = regimes(data)
    per = max(int(round(window_s * fs)), 2)
    out = []
    for ch, (lp, rw) in chans.items():
        hf = np.diff(rw[data.valid])
        sigma_raw = 1.4826 * np.median(np.abs(hf - np.median(hf))) / math.sqrt(2) if hf.size else 0.0
        floor = sigma_raw * math.sqrt(2 * LOWPASS_HZ / fs)
        floor = max(floor, 1e-4)
        flagged = []
        for k0 in range(0, data.n - per + 1, per):
            sl = slice(k0, k0 + per)
            ok = data.valid[sl]
            if ok.sum() < per // 2:
                continue
            rms = float(np.sqrt(np.mean(lp[sl][ok] ** 2)))
            if rms > factor * floor:
                vals, counts = np.unique(lab[sl][ok], return_counts=True)
                flagged.append([data.t[k0], data.t[min(k0 + per, data.n - 1)], str(vals[np.argmax(counts)]),
                                rms / floor, rms])
        merged: list[list] = []
        for f in flagged:
            if merged and abs(f[0] - merged[-1][1]) < 1e-6 and f[2] == merged[-1][2]:
                merged[-1][1] = f[1]
                merged[-1][3] = max(merged[-1][3], f[3])
                merged[-1][4] = max(merged[-1][4], f[4])
            else:
                merged.append(list(f))
        merged.sort(key=lambda f: -f[3])
        for f in merged[:per_channel]:  # per channel, so a loud channel cannot hide the others
            out.append({"channel": ch, "t_start": round(float(f[0]), 2), "t_end": round(float(f[1]), 2),
                        "regime": f[2], "severity": round(float(f[3]), 2),
                        "rms_fraction_of_full_output": round(float(f[4]), 4)})
    out.sort(key=lambda d: -d["severity"])
    return out


def _evidence(f: Fit, names: list[str], before_ch: np.ndarray) -> str:
    drop = before_ch - f.heldout_channels
    ch = names[int(np.argmax(drop))]
    pretty = ", ".join(f"{k}={v:.4g}" for k, v in f.candidate.params_dict(f.theta).items())
    verdict = "accepted" if f.accepted else "rejected"
    why = []
    if not f.above_floor:
        why.append("fitted size below the physical resolution floor")
    if f.at_bound:
        why.append("estimate pinned to the edge of the physical range")
    if f.t_stat <= T_CRIT:
        why.append(f"not significant on held-out blocks (t={f.t_stat:.1f})")
    if f.rel_improvement < MIN_REL_IMPROVEMENT:
        why.append(f"explains only {100 * f.rel_improvement:.0f} % of the held-out residual")
    reason = "; ".join(why) if why else f"t={f.t_stat:.1f} over {f.n_blocks} held-out blocks"
    return (f"{f.candidate.label} ({pretty}) cuts the held-out residual by {100 * f.rel_improvement:.0f} %, "
            f"mostly in {ch}: {verdict} ({reason}).")


def discover(log, vp: VehicleParams, *, heldout_fraction: float = HELDOUT_FRACTION, max_effects: int = MAX_EFFECTS,
             progress: bool = False, closed_loop_metrics: bool = True) -> dict:
    """Run discovery on a FlightLog with nominal params ``vp``; returns the JSON-ready result."""
    t_start = time.time()
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
    blocks = _blocks(data.t, held_mask, BLOCK_S) + _blocks(data.t, held2, BLOCK_S)

    current = vp
    R_base = residual_channels(data, vp, vp)
    raw_base = residual_channels(data, vp, vp, lowpass_hz=None)
    base_held = np.sqrt(np.mean(R_base[held_mask] ** 2, axis=0))
    mismatch = locate(data, R_base, raw_base, names)

    accepted: list[Fit] = []
    ranked: list[Fit] = []
    rounds = 0
    pbar = None
    if progress:
        from tqdm import tqdm
        pbar = tqdm(desc="discover", unit="fit", mininterval=0.5, leave=False)
    while rounds < max_effects:
        rounds += 1
        R0 = residual_channels(data, current, vp)
        cands = build_candidates(current, data)
        fits = []
        for c in cands:
            fits.append(assess(c, data, vp, R0, folds, blocks, held_mask))
            if pbar is not None:
                pbar.update(1)
        # one motor_efficiency entry: the best motor
        best_me = None
        kept = []
        for f in fits:
            if f.candidate.name == "motor_efficiency":
                if best_me is None or f.heldout_rms < best_me.heldout_rms:
                    best_me = f
            else:
                kept.append(f)
        if best_me is not None:
            kept.append(best_me)
        kept.sort(key=lambda f: -f.rel_improvement)
        for f in kept:
            f.accepted = (f.above_floor and not f.at_bound and f.t_stat > T_CRIT
                          and f.rel_improvement >= MIN_REL_IMPROVEMENT)
        winner = next((f for f in kept if f.accepted), None)
        if winner is not None:
            winner = _parsimonious(winner, [f for f in kept if f.accepted], blocks)
        if rounds == 1:
            ranked = kept
        if winner is None:
            for f in kept:
                f.accepted = False
            break
        for f in kept:
            f.accepted = f is winner
        accepted.append(winner)
        if rounds > 1:
            # keep the list of round 1 as the ranking, adding later winners
            ranked = [r for r in ranked if r.candidate.label != winner.candidate.label] + [winner]
        else:
            ranked = kept
        current = winner.vp
    if pbar is not None:
        pbar.close()

    # joint refit of all accepted effects (they may interact)
    if len(accepted) > 1:
        current = _joint_refit(accepted, data, vp, fit_mask)
    R_after = residual_channels(data, current, vp)
    after_held = np.sqrt(np.mean(R_after[held_mask] ** 2, axis=0))

    effects_out = []
    seen = set()
    for f in sorted(ranked, key=lambda f: (not f.accepted, -f.rel_improvement)):
        if f.candidate.label in seen:
            continue
        seen.add(f.candidate.label)
        f.evidence = _evidence(f, names, base_held)
        jname, jb, ja = f.judged
        effects_out.append({
            "name": f.candidate.name,
            "accepted": bool(f.accepted),
            "params": f.candidate.params_dict(f.theta),
            "evidence": f.evidence,
            "heldout_channel": jname,
            "heldout_before": round(jb, 5),
            "heldout_after": round(ja, 5),
            "heldout_units": f"RMS equation error in the {jname} mode on the held-out part, fraction of full "
                             "motor output",
            "heldout_improvement": round(1.0 - ja / jb, 4) if jb > 0 else 0.0,
            "heldout_all_channels_before": round(float(np.sqrt(np.mean(base_held ** 2))), 5),
            "heldout_all_channels_after": round(float(f.heldout_rms), 5),
            "heldout_all_channels_improvement": round(float(f.heldout_cut), 4),
            "heldout_channels_before": {k: round(float(v), 5) for k, v in zip(names, base_held)},
            "heldout_channels_after": {k: round(float(v), 5) for k, v in zip(names, f.heldout_channels)},
            "heldout_t_stat": round(float(f.t_stat), 2) if math.isfinite(f.t_stat) else None,
            "cv_improvement": round(float(f.rel_improvement), 4),
            "above_resolution_floor": bool(f.above_floor),
        })
    result = {
        "log": str(log.path),
        "params": vp.source,
        "method": {
            "residual": "equation error (measured specific force and angular acceleration vs the model fed the "
                        "logged motor commands), per motor and horizontal force, low-passed "
                        f"{LOWPASS_HZ} Hz, in fraction of full motor output",
            "fit_interval_s": [round(float(valid_t[0]), 2), round(float(t_split), 2)],
            "heldout_interval_s": [round(float(t_split), 2), round(float(valid_t[-1]), 2)],
            "acceptance": f"above the physical resolution floor and inside the physical range; 2-fold "
                          f"cross-validated: held-out block test (t or sign test) > {T_CRIT} over up to "
                          f"{len(blocks)} blocks of {BLOCK_S} s, held-out RMS cut >= "
                          f"{int(100 * MIN_REL_IMPROVEMENT)} %",
        },
        "baseline": {"equation_error_heldout": {k: round(float(v), 5) for k, v in zip(names, base_held)}},
        "mismatch": mismatch,
        "effects": effects_out,
        "accepted": [f.candidate.name for f in accepted],
        "after": {"equation_error_heldout": {k: round(float(v), 5) for k, v in zip(names, after_held)}},
        "refit_params": current.to_ros_dict() if accepted else None,
    }
    if closed_loop_metrics:
        _closed_loop(result, log, vp, current, t_split, float(valid_t[-1]))
    result["elapsed_s"] = round(time.time() - t_start, 1)
    result["_series"] = {"t": data.t, "valid": data.valid, "held": held_mask, "R_before": R_base,
                         "R_after": R_after, "names": names}
    return result


def _joint_refit(accepted: list[Fit], data, nominal, fit_mask) -> VehicleParams:
    cands = [f.candidate for f in accepted]
    sizes = [len(c.x0) for c in cands]
    x0 = np.concatenate([f.theta for f in accepted])
    lo = np.concatenate([c.lower for c in cands])
    hi = np.concatenate([c.upper for c in cands])
    s = np.maximum(np.abs(x0), 1e-6)

    def build(theta):
        vpj = nominal
        k = 0
        for c, n in zip(cands, sizes):
            params = dict(c.fixed)
            params.update({p: float(v) for p, v in zip(c.param_names, theta[k:k + n])})
            vpj = vpj.with_effect(c.name, **params)
            k += n
        return vpj

    def resid(z):
        return residual_channels(data, build(np.clip(z * s, lo, hi)), nominal)[fit_mask].ravel()

    sol = least_squares(resid, x0 / s, bounds=(lo / s, hi / s), diff_step=1e-3, max_nfev=80)
    theta = np.clip(sol.x * s, lo, hi)
    k = 0
    for f, n in zip(accepted, sizes):
        f.theta = theta[k:k + n]
        k += n
    return build(theta)


def _closed_loop(result: dict, log, before: VehicleParams, after: VehicleParams, t0: float, t1: float) -> None:
    """Closed-loop twin metrics (Table 2 + throttle + motors) on the held-out part, before and after.

    The twin flies the whole flight (so it reaches the held-out part in a realistic state);
    only the held-out window is scored."""
    from twin_nodes.compare import align
    from twin_nodes.metrics import flight_metrics
    from twin_nodes.twin import run_twin_on_log

    out = {}
    for key, p in (("before", before), ("after", after)):
        run = run_twin_on_log(log, p, mode="closed")
        m = flight_metrics(align(run, log, t0=t0, t1=t1))
        m["interval_s"] = [round(t0, 2), round(t1, 2)]
        out[key] = m
    result["baseline"]["closed_loop_heldout"] = out["before"]
    result["after"]["closed_loop_heldout"] = out["after"]
