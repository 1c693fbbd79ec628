"""Stage 5, the closed-loop check: the closed-loop twin flown on the held-out part before and after;
an accepted effect that makes its throttle RMSE (or, beyond ``CLOSED_LOOP_MOTOR_TOL_REL``, its per-motor P75) worse
is dropped (``CheckInput`` -> ``Checked``).
The twin runs are made once per vehicle per discover call, the first ones ahead in another process
(:func:`prefetch`); :func:`guard` judges later changes of the refit vehicle the same way."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Callable

import numpy as np

from twin_nodes.discovery import evaluate
from twin_nodes.discovery.judging import Fit
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.discovery.stages.refit import _joint_refit
from twin_nodes.discovery.stages.retrim import retrim_for_flight
from twin_nodes.vehicle.params import VehicleParams


@dataclass
class CheckInput:
    log: object                       # the FlightLog the twin flies
    flight: PreparedFlight
    accepted: list[Fit]
    current: VehicleParams            # the refitted vehicle
    enabled: bool = True              # False: no closed-loop twin (``--no-closed-loop``)


@dataclass
class Checked:
    accepted: list[Fit]               # the effects kept
    current: VehicleParams            # their vehicle
    closed: dict | None               # the twin's metrics {"before": ..., "after": ...} (None: not flown)


def run(inp: CheckInput) -> Checked:
    """An effect must also make the closed-loop twin better on the held-out part, never worse."""
    if not (inp.enabled and inp.accepted):
        return Checked(inp.accepted, inp.current, None)
    S = inp.flight
    accepted, current, closed = _closed_loop_guard(inp.accepted, inp.log, S.nominal, S.data, S.fit_mask,
                                                   *S.scored)
    return Checked(accepted, current, closed)


# ---------------------------------------------------------------- the guard's own noise and standing
#
# Issue 26: a true motor lag (fit right, held-out cut 46-85 %, t = 8.7) was dropped because the closed-loop
# twin's held-out throttle RMSE went from 0.856 % to 0.872 %: inside the run's own scatter, from a twin that
# flies our PX4-like controller on a RotorPy flight flown by RotorPy's SE(3) controller.  The guard now vetoes
# only (1) where its twin stands for the flight's controller: our own simulator's flights (the same
# controller), or PX4 logs on which the nominal twin is shown to follow the flight (``FIDELITY``); and (2)
# where the rise is beyond its own uncertainty: a block bootstrap of the per-sample change of the squared
# throttle error over the held-out part (``VETO_Z`` standard errors), as well as beyond ``CLOSED_LOOP_TOL_REL``.
# Elsewhere the open-loop residuals decide; a veto that overrides a significant open-loop finding says so,
# with both numbers.

#: the nominal twin follows a PX4 flight when its held-out throttle and horizontal errors are below these
FIDELITY = {"throttle_rmse": 0.05, "xy_rmse_m": 2.0}
#: a rise counts when it exceeds this many bootstrap standard errors
VETO_Z = 2.0
BOOT_BLOCK_S = 1.0
BOOT_N = 400


def controller_of(log) -> str:
    """Who flew the log: ``twin`` (our simulator's PX4-like controller, the twin's own), ``px4`` (PX4
    firmware, which the twin's controller models), ``rotorpy`` (RotorPy's SE(3) controller), or ``other``."""
    info = getattr(log, "info", None) or {}
    hw = str(info.get("ver_hw", "")).upper()
    if hw == "ROTORTWIN_SIM":
        return "twin"
    if hw == "ROTORPY_SIM":
        return "rotorpy"
    if hw.endswith("_SIM") and hw != "PX4_SITL":
        return "other"
    if info.get("ver_sw") or "PX4" in str(info.get("sys_name", "")).upper() or hw.startswith("PX4"):
        return "px4"
    return "other"


#: who flew a flight (``controller_of``) -> the twin's control law (``controller.law``) that stands for it
LAW_OF = {"twin": "px4", "px4": "px4", "rotorpy": "se3"}


def veto_standing(log, before: dict, vp: VehicleParams | None = None) -> tuple[bool, str]:
    """Whether the closed-loop twin of ``vp`` may veto on this flight, and why (or why not): it flies the law
    the flight was flown by, and (unless it is our own simulator's flight) follows the flight (``FIDELITY``)."""
    from twin_nodes.twin.controllers import controller_law

    who = controller_of(log)
    law = controller_law(vp) if vp is not None else "px4"
    if LAW_OF.get(who) != law:
        return False, "the flight was flown by another controller than the twin's"
    if who == "twin":
        return True, "the twin's controller flew this flight"
    ok = all(float(before.get(k, float("inf"))) <= v for k, v in FIDELITY.items())
    return ok, (f"the nominal twin follows this {who} flight" if ok else
                f"the nominal twin does not follow this {who} flight closely enough "
                f"(throttle RMSE {before.get('throttle_rmse', float('nan')):.4f}, xy {before.get('xy_rmse_m', float('nan')):.2f} m)")


def rise_significance(after: dict, best: dict) -> tuple[float, float]:
    """The rise of the held-out mean squared throttle error from ``best`` to ``after`` and its block-bootstrap
    standard error (1-s blocks, paired sample by sample); (nan, nan) when the runs carry no error series."""
    a, b = after.get("_throttle_err"), best.get("_throttle_err")
    if a is None or b is None:
        return float("nan"), float("nan")
    ta, ea = (np.asarray(x, float) for x in a)
    tb, eb = (np.asarray(x, float) for x in b)
    if ta.shape != tb.shape or not np.allclose(ta, tb):
        eb = np.interp(ta, tb, eb)
    d = ea ** 2 - eb ** 2
    ok = np.isfinite(d)
    d, t = d[ok], ta[ok]
    if d.size < 10:
        return float("nan"), float("nan")
    blk = np.floor((t - t[0]) / BOOT_BLOCK_S).astype(int)
    sums = np.bincount(blk, weights=d)
    counts = np.bincount(blk).astype(float)
    keep = counts > 0
    sums, counts = sums[keep], counts[keep]
    rng = np.random.default_rng(26)
    idx = rng.integers(0, sums.size, size=(BOOT_N, sums.size))
    boot = sums[idx].sum(1) / counts[idx].sum(1)
    return float(d.mean()), float(boot.std(ddof=1)) if sums.size > 1 else float("nan")


def _veto(m: dict, best: dict, before: dict, standing: tuple[bool, str]) -> tuple[bool, str | None]:
    """(vetoed, what to say): a twin that leaves the flight with the change where it did not without it
    (``divergence`` of the metrics: a divergence the vehicle did not have, whatever the throttle says; on the
    fleet's ZweiterFlugtag log_39 a yaw-moment refit was accepted whose twin lost its heading at 6.5 s, per-motor
    P75 22.4 -> 44.8 %); then, where the nominal twin stands, held-out motors worse beyond CLOSED_LOOP_MOTOR_TOL_REL
    (:func:`_motors_worse`); else the throttle's rise beyond the tolerance, beyond its own noise, and the twin's
    standing."""
    new_div, old_div = m.get("divergence"), best.get("divergence") or before.get("divergence")
    if new_div and not old_div:
        return True, (f"the twin leaves the flight with it ({new_div['cause']} at {new_div['t_s']:.1f} s), "
                      "not without")
    motors = _motors_worse(m, best, before)
    if motors and standing[0]:
        return True, motors
    if not _worse(m["throttle_rmse"], best["throttle_rmse"], before["throttle_rmse"]):
        return False, None
    rise, se = rise_significance(m, best)
    numbers = (f"closed-loop held-out throttle RMSE {best['throttle_rmse']:.6f} -> {m['throttle_rmse']:.6f}"
               + (f", rise of the mean square {rise:.3g} +- {se:.2g} (block bootstrap)" if np.isfinite(se) else ""))
    if np.isfinite(se) and rise <= VETO_Z * se:
        return False, f"not vetoed: {numbers}, within the run's own scatter"
    if not standing[0]:
        return False, f"not vetoed: {numbers}; {standing[1]}"
    return True, numbers


def guard(checked: Checked, log, flight: PreparedFlight, enabled: bool) -> Callable[[VehicleParams], str | None]:
    """The check for a later change of the refit vehicle: why it makes the closed-loop twin worse (None: fine)."""
    closed = checked.closed

    def check(vp_new: VehicleParams) -> str | None:
        """The closed-loop twin's held-out throttle RMSE must not get worse (as ``_closed_loop_guard``)."""
        if not (enabled and closed):
            return None
        m = _closed_loop_metrics(log, vp_new, *flight.scored)
        vetoed, why = _veto(m, closed["after"], closed["before"], veto_standing(log, closed["before"], flight.nominal))
        if not vetoed:
            closed["after"] = m
            return None
        return f"makes the closed-loop twin worse on the held-out part ({why})"
    return check


def reset() -> None:
    """Cancel and forget this discover call's closed-loop runs."""
    _closed_loop_reset()


def prefetch(log, vp: VehicleParams, flight: PreparedFlight) -> None:
    """Start the closed-loop twin of ``vp`` on the held-out part in another process."""
    _prefetch_closed_loop(log, vp, *flight.scored)


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

    from twin_nodes.twin.metrics import channel_errors

    al = align(run_twin_on_log(log, vp, mode="closed"), log, t0=t0, t1=t1)
    m = flight_metrics(al)
    m["interval_s"] = [round(t0, 2), round(t1, 2)]
    # private (not reported): the per-sample throttle error, the guard's noise estimate (rise_significance)
    m["_throttle_err"] = (np.asarray(al.t, float), channel_errors(al)["throttle"])
    return m


#: the closed-loop twin is "worse" when its held-out throttle RMSE rises by more than this fraction:
#: below it the change is the closed-loop run's numerical resolution, not the effect.  Effects that do
#: not act on the collective (inertia, yaw moment) move it by 1e-6..4e-6 of full throttle (0.01-0.04 %);
#: a strict comparison dropped the true inertia on 4 of 5 PX4 SIH flights and the true yaw moment on
#: one (e.g. e11: 0.011723 -> 0.011724)
CLOSED_LOOP_TOL_REL = 0.005


#: the closed-loop twin's motors are "worse" when their held-out per-motor P75 (mean over the motors) rises by
#: more than this fraction: on the tuning half and the shared real logs an accepted effect moved it by -29 % to
#: +7 % (s500 mission2's yaw moment, 3.0 -> 3.2 %), but by +47 % on auterion_v3_esc_status once its thrust was
#: identified on an unaliased specific force (a tilt state term whose trims made the held-out descent's motors
#: 7.5 -> 10.9 % off while its throttle improved); a change the equations accept that the twin's own motors
#: follow worse is no better twin (issue 24 scores the per-motor P75)
CLOSED_LOOP_MOTOR_TOL_REL = 0.10
#: ... and by at least this much of full output: a rise below it is under the precision the survey reports the
#: per-motor P75 at (0.1 %) five times over, where a 10 % rise of a twin already within 1 % of its motors is noise
#: (RotorPy's oov vortex-ring flight 2732: 0.39 -> 0.43 %)
CLOSED_LOOP_MOTOR_MIN_RISE = 0.005


def _motors_worse(m: dict, best: dict, before: dict) -> str | None:
    """What to say when the held-out per-motor P75 rises beyond ``CLOSED_LOOP_MOTOR_TOL_REL`` and by at least
    ``CLOSED_LOOP_MOTOR_MIN_RISE`` over the best so far (or the nominal twin); None otherwise or where a run has
    none."""
    new = m.get("motor_p75_mean")
    old = min((x for x in (best.get("motor_p75_mean"), before.get("motor_p75_mean"))
               if x is not None and np.isfinite(x)), default=None)
    if (new is None or old is None or not np.isfinite(new) or new <= (1.0 + CLOSED_LOOP_MOTOR_TOL_REL) * old
            or new - old < CLOSED_LOOP_MOTOR_MIN_RISE):
        return None
    return (f"closed-loop held-out per-motor P75 {old:.4f} -> {new:.4f}, more than "
            f"{100 * CLOSED_LOOP_MOTOR_TOL_REL:.0f} % worse (throttle RMSE {best['throttle_rmse']:.6f} -> "
            f"{m['throttle_rmse']:.6f})")


def _worse(rmse: float, best: float, baseline: float) -> bool:
    """Worse than the best so far (or than the nominal twin) beyond ``CLOSED_LOOP_TOL_REL``."""
    return rmse > (1.0 + CLOSED_LOOP_TOL_REL) * min(best, baseline)


def _closed_loop_guard(accepted: list[Fit], log, nominal: VehicleParams, data, fit_mask, t0: float, t1: float
                       ) -> tuple[list[Fit], VehicleParams, dict]:
    """Add the accepted effects one at a time (in acceptance order), each trial's static trims remade for its
    refit model (:func:`.retrim.retrim_for_flight`); drop each one that makes the
    closed-loop twin's held-out throttle RMSE worse.  Returns the kept effects, their (re)fitted
    vehicle and the metrics cache ``{"before": ..., "after": ...}``."""
    before = _closed_loop_metrics(log, nominal, t0, t1)
    standing = veto_standing(log, before, nominal)
    best = before
    kept: list[Fit] = []
    current = nominal
    for f in accepted:
        trial = kept + [f]
        vp_t = _joint_refit(trial, data, nominal, fit_mask) if len(trial) > 1 else f.vp
        # the static trims remade for what the refit changed in the steady balance (stages.retrim)
        vp_t = retrim_for_flight(vp_t, nominal, data)
        m = _closed_loop_metrics(log, vp_t, t0, t1)
        vetoed, why = _veto(m, best, before, standing)
        f.closed_loop_note = why
        if not vetoed:
            kept, current, best = trial, vp_t, m
        else:
            f.accepted = False
            f.closed_loop = f"makes the closed-loop twin worse on the held-out part ({why})"
            if f.t_stat > 3.0:
                f.closed_loop += (f"; this veto overrides a significant open-loop finding (held-out t = "
                                  f"{f.t_stat:.1f}, cut {100 * f.rel_improvement:.0f} %)")
    return kept, current, {"before": before, "after": best, "standing": standing[1]}


def _closed_loop(result: dict, log, before: VehicleParams, after: VehicleParams, t0: float, t1: float,
                 cached: dict | None = None) -> None:
    """Closed-loop twin metrics on the held-out part, before and after (reusing the guard's runs)."""
    out = dict(cached or {})
    for key, p in (("before", before), ("after", after)):
        if key not in out:
            out[key] = _closed_loop_metrics(log, p, t0, t1)
    result["baseline"]["closed_loop_heldout"] = _public(out["before"])
    result["after"]["closed_loop_heldout"] = _public(out["after"])
    if out.get("standing"):
        result["after"]["closed_loop_veto_standing"] = out["standing"]


def _public(m: dict) -> dict:
    return {k: v for k, v in m.items() if not k.startswith("_")}
