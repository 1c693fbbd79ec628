"""``rotortwin discover FLIGHT --confirm FOLLOWUP.ulg``: re-judge each ``likely`` effect on a follow-up flight.

Design: the effect's parameters stay those fitted on FLIGHT, and the follow-up flight (flown
with a confirmation plan, :mod:`twin_nodes.discovery.plans`) is a pure held-out test of them: it
was not seen by the fit, so every one of its blocks is a held-out block.  On the residual the
effect was graded on (equation or output error; the output error for an effect the two residuals
corroborated, whose missing output-error blocks the plan supplies, and for an instrumented inertia,
found on an axis the flight's output error could not fit), with the nominal vehicle plus
FLIGHT's confirmed effects as the baseline:

- *confirmed* when the block test over all the follow-up's blocks passes the discovery bar
  (statistic > ``T_CRIT``, >= ``MIN_REL_IMPROVEMENT`` of the follow-up residual explained in the
  effect's own channel, no channel made worse overall) and a refit on the follow-up alone (2-fold,
  as discovery fits) lands on the same side of nominal within a factor of 1.5 of FLIGHT's change.
  (or within ``SE_AGREE`` standard errors of it, where the flight's estimate has one: the
  instrumented inertia).  The cut is asked in the effect's channel, not of all channels together: the plan excites the
  effect's channel, and an effect acting in one of four axes (a roll inertia) cannot explain a
  tenth of all four (PX4 SIH g34's follow-up: 30 % in roll, t 6, 6 % of all);
- otherwise *dropped* (``rejected``), with the follow-up's numbers.

Judging the fixed FLIGHT fit, rather than refitting on FLIGHT + FOLLOWUP, keeps the test free of
any fit to the data it judges; the refit on the follow-up is reported beside it (it is the
better-excited estimate of the parameter) and must agree.
"""

from __future__ import annotations

import math

import numpy as np

from twin_nodes.discovery.candidates import build_candidates
from twin_nodes.discovery.blocktest import MIN_TEST_BLOCKS, _block_stats
from twin_nodes.discovery.judging import (BLOCK_S, MIN_REL_IMPROVEMENT, OE_BLOCK_S, OE_MIN_CHANGE, T_CRIT, _blocks,
                                          _mode_rms, _restrict_to_axes, _scales, assess)
from twin_nodes.discovery.stages.prepare import prepare_flight
from twin_nodes.vehicle.params import VehicleParams

AGREE_FACTOR = 1.5
#: or within this many of the flight estimate's standard errors, where it has one
SE_AGREE = 2.0


def _apply(vp: VehicleParams, name: str, params: dict) -> VehicleParams:
    return vp.with_effect(name, **{k: float(v) for k, v in params.items()})


def _refit_on_followup(e: dict, cands: dict, judge, vp: VehicleParams, R0: np.ndarray) -> tuple[dict | None, bool]:
    """The effect ``e`` refitted on the follow-up alone (its own 2-fold test), the better-excited
    estimate, and whether it agrees with the flight's fit."""
    refit = None
    agree = False
    label = e["name"] if e["name"] != "motor_efficiency" else f"motor_efficiency(motor {int(e['params']['motor'])})"
    c = cands.get(label)
    if c is not None and judge.kind == "output":
        c = _restrict_to_axes(c, judge.windows.usable)
    if c is not None:
        f = assess(c, judge, vp, R0)
        refit = {"params": c.params_dict(f.theta), "heldout_t_stat": round(float(f.t_stat), 2),
                 "cv_improvement": round(float(f.rel_improvement), 4)}
        theta_flight = np.array([float(e["params"][p]) for p in c.param_names])
        s = _scales(c)
        d0 = (theta_flight - c.x0) / s
        d1 = (f.theta - c.x0) / s
        j = int(np.argmax(np.abs(d0)))
        agree = bool(d0[j] * d1[j] > 0 and max(abs(d0[j]), abs(d1[j])) <= AGREE_FACTOR * min(abs(d0[j]), abs(d1[j])))
        # where the flight's estimate has a standard error (the instrumented inertia), agreeing
        # within two of them is agreeing too: a +25 % change estimated 7 % high in the inertia
        # itself is 1.5 x the change (PX4 SIH g26: Ixx 0.0334 +- 0.0018 against the follow-up's 0.0305)
        se = (e.get("params_se") or {}).get(c.param_names[j])
        if se and d0[j] * d1[j] > 0 and abs(f.theta[j] - theta_flight[j]) <= SE_AGREE * se:
            agree = True
    return refit, agree


def confirm(result: dict, followup_log, vp: VehicleParams) -> dict:
    """Re-judge the ``likely`` effects of ``result`` (a discover result of FLIGHT with nominal ``vp``)
    on ``followup_log``; returns ``{"followup": path, "effects": [...]}`` and updates the verdicts in
    ``result["effects"]`` in place."""
    likely = [e for e in result.get("effects", []) if e.get("verdict") == "likely"]
    base = vp
    for e in result.get("effects", []):
        if e.get("verdict") == "confirmed":
            base = _apply(base, e["name"], e["params"])
    out = {"followup": str(getattr(followup_log, "path", "")), "baseline_effects": result.get("accepted", []),
           "effects": []}
    if not likely:
        return out
    S = prepare_flight(followup_log, vp)
    cands = {c.label: c for c in build_candidates(base, S.data)}
    for e in likely:
        # a corroborated effect (verdicts.corroboration) lacked output-error blocks, which the plan
        # supplies: the follow-up judges it there
        # likewise an instrumented one (an axis the flight's output error could not fit): a follow-up
        # with the motors logged at the rate loop's rate makes the axis usable there
        kind = ("output" if (e.get("excitation") or {}).get("corroborated") or e.get("residual") in ("instrumented", "rate_loop")
                else e.get("residual", "equation"))
        judge = S.oe if kind == "output" and S.oe is not None else S.eq
        if judge.kind == "equation":
            rows = S.data.valid
            blocks = _blocks(S.data.t, rows, BLOCK_S)
        else:
            rows = np.ones(judge.windows.n, bool)
            blocks = _blocks(judge.windows.t, rows, OE_BLOCK_S, min_rows=2)
        vp1 = _apply(base, e["name"], e["params"])
        R0 = judge.residual(base)
        R1 = judge.residual(vp1)
        st = _block_stats(R0, R1, blocks, OE_MIN_CHANGE if judge.kind == "output" else 0.0)
        tot0 = float(np.sqrt(np.mean(R0[rows] ** 2)))
        tot1 = float(np.sqrt(np.mean(R1[rows] ** 2)))
        rel = 1.0 - tot1 / tot0 if tot0 > 0 else 0.0
        m0, mnames = _mode_rms(R0[rows], vp)
        m1, _ = _mode_rms(R1[rows], vp)
        ch = e.get("heldout_channel") if e.get("heldout_channel") in mnames else mnames[int(np.argmax(m0 ** 2 - m1 ** 2))]
        k = mnames.index(ch)
        mode_cut = 1.0 - m1[k] / m0[k] if m0[k] > 0 else 0.0
        # the refit on the follow-up alone (its own 2-fold test), the better-excited estimate
        refit, agree = _refit_on_followup(e, cands, judge, vp, R0)
        passed = st["t"] > T_CRIT and rel >= 0.0 and mode_cut >= MIN_REL_IMPROVEMENT and agree
        why = []
        if st["t"] <= T_CRIT:
            why.append(f"not significant on the follow-up (t={st['t']:.1f} over {st['n']} active blocks)" if st["tested"]
                       else f"the follow-up's block test did not run ({st['n']} active blocks, {MIN_TEST_BLOCKS} needed)")
        if rel < 0.0:
            why.append(f"makes the follow-up residual worse overall ({100 * rel:.0f} %)")
        if mode_cut < MIN_REL_IMPROVEMENT:
            why.append(f"explains only {100 * mode_cut:.0f} % of the follow-up residual in {ch}")
        if not agree:
            why.append("the refit on the follow-up disagrees with the flight's fit")
        row = {"name": e["name"], "params_flight": e["params"], "residual": judge.kind, "channel": ch,
               "followup_before": round(float(m0[k]), 5), "followup_after": round(float(m1[k]), 5),
               "followup_improvement": round(float(mode_cut), 4), "followup_all_channels_improvement": round(rel, 4),
               "followup_t_stat": round(float(st["t"]), 2) if math.isfinite(st["t"]) else None,
               "followup_active_blocks": int(st["n"]), "refit_on_followup": refit,
               "verdict": "confirmed" if passed else "rejected",
               "note": (f"confirmed on the follow-up: t={st['t']:.1f} over {st['n']} blocks, {100 * mode_cut:.0f} % "
                        f"cut in {ch}" if passed else "dropped: " + "; ".join(why))}
        out["effects"].append(row)
        e["verdict"] = row["verdict"]
        e["accepted"] = bool(passed)
        e["verdict_note"] = row["note"]
        e["confirmation"] = row
    result["likely"] = [e["name"] for e in result.get("effects", []) if e.get("verdict") == "likely"]
    result["confirmed_on_followup"] = [r["name"] for r in out["effects"] if r["verdict"] == "confirmed"]
    return out


__all__ = ["confirm"]
