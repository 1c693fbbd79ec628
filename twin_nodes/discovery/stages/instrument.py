"""Stage 7, the refit continued on PX4 logs: an inertia finding's roll/pitch axes each on its
own evidence (:func:`_equation_axes`), the roll/pitch inertia read by PX4's rate loop flown on the
model or by the rate setpoint as instrument (:func:`_instrumented`), and where the rate loop says the
motors are slow, how slow (:mod:`.motor_lag`); each may update the verdicts' entries and the
refit vehicle, the closed-loop check permitting (``InstrumentInput`` -> ``Instrumented``)."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from twin_nodes.discovery import rate_loop
from twin_nodes.discovery.blocktest import _block_test
from twin_nodes.discovery.judging import T_CRIT, Fit, _window_folds, insert_likely
from twin_nodes.discovery.output_error import (AXES, IV_AXIS_PARAM, IV_GAIN_RANGE, MIN_AXIS_R2, Windows,
                                               instrumented_inertia)
from twin_nodes.discovery.plans import RATE_LOOP_LOG_S
from twin_nodes.discovery.stages import lag_inertia, motor_lag
from twin_nodes.discovery.stages.inertia_holds import hold_axes_not_borne_out, hold_yaw_not_borne_out, read_weak_axes
from twin_nodes.discovery.stages.motor_lag import INSTRUMENTED_BLOCKS_MISSING
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.discovery.stages.verdicts import Verdicts
from twin_nodes.discovery.verdicts import LIKELY_MIN_CUT
from twin_nodes.physics.effects import effective_params
from twin_nodes.vehicle.params import VehicleParams


@dataclass
class InstrumentInput:
    flight: PreparedFlight
    verdicts: Verdicts                # updated in place
    current: VehicleParams            # the refit vehicle after the closed-loop check
    #: the closed-loop check of a changed refit vehicle (:func:`.closed_loop.guard`): why not, or None
    guard: Callable[[VehicleParams], str | None]


@dataclass
class Instrumented:
    current: VehicleParams            # the refit vehicle
    instrumented: dict | None         # the result's ``instrumented`` (None: nothing to instrument)
    lag: dict | None                  # the result's ``rate_loop_lag`` (None: not looked at)
    joint: dict | None = None         # the result's ``lag_and_inertia`` (None: not looked at)


def run(inp: InstrumentInput) -> Instrumented:
    """The roll/pitch axes, then the instrument on what is still held, then the rate loop's motor lag."""
    S, v, current, guard = inp.flight, inp.verdicts, inp.current, inp.guard
    # a motor lag found on aliased 50 Hz commands: PX4's rate loop, which uses none, reads its time constant
    # (before the inertia, which it reads on the refit vehicle's motors)
    current = motor_lag.read_finding(S, current, v.effects, guard) or current
    # an inertia finding's roll/pitch axes, each on its own evidence, then the instrument on what is
    # still held: either may change the refit vehicle
    current = _equation_axes(S, v.ranked, v.effects, current, v.accepted_labels, guard) or current
    instrumented, refit = _instrumented(S, current, v.accepted_labels, v.effects, guard, S.nominal)
    current = refit or current
    # a motor lag beside an inertia: the two read again together on the rate loop (the lag was fitted without it)
    current = motor_lag.beside_inertia(S, current, v.effects, guard) or current
    # where the rate loop says the motors are slow, not an inertia: how slow (on the vehicle its yaw was read on)
    on = (_thrust_yaw_share_removed(current) or current) if (instrumented or {}).get("yaw_read_on") else current
    lag = (motor_lag.rate_loop_lag(S, on, v.effects)
           if instrumented is not None and instrumented.get("method") == "rate_loop" and instrumented["motor_signature"]
           else None)
    if lag is not None and lag.get("verdict") == "likely":
        beside = _inertia_beside_lag(S, on, v.accepted_labels, v.effects, guard)
        if beside is not None:
            instrumented["beside_rate_loop_lag"] = beside
    # the lag and the roll/pitch inertia read together where either is a finding (each read alone absorbs the other)
    refit, joint = lag_inertia.read_together(S, current, v.effects, guard)
    # last, each inertia axis with its readings: a weakly excited one at their midpoint, or not read where they
    # disagree (not where the joint reading replaced them: the others were read on the model's lag)
    current = refit or current
    if (joint or {}).get("verdict") != "lag and inertia":
        current = read_weak_axes(S.data, S.nominal, v.effects, current, instrumented, guard) or current
    return Instrumented(current, instrumented, lag, joint)


def _inertia_beside_lag(S: PreparedFlight, on: VehicleParams, accepted: list[str], effects_out: list[dict],
                        guard: Callable[[VehicleParams], str | None]) -> dict | None:
    """The roll/pitch inertia read again by PX4's rate loop on the vehicle carrying the motor lag it has just
    named (:func:`.motor_lag.rate_loop_lag`), where no inertia is a finding: the first reading, on the model's
    lag, saw a slower roll/pitch and yaw off the same way and put it all on the motors (PX4 SIH SIH_T_TAU 0.08
    with SIH_L_ROLL 0.17, j017: roll x1.41, pitch x1.18, yaw x1.06; on the lag's vehicle roll x1.19 +- 0.03,
    pitch and yaw x1.01).  The same checks as any rate-loop inertia reading (:func:`_instrument_verdict`: 10 %
    and 4 standard errors, both folds, the held-out cut, no motor signature) name it ``likely`` beside the lag;
    the refit vehicle is unchanged.  Returns the second reading's numbers (None: not read)."""
    lag_e = next((e for e in effects_out if e["name"] == "motor_time_constant" and e["verdict"] == "likely"
                  and e.get("residual") == "rate_loop"), None)
    if lag_e is None or any(e["name"] == "inertia" and e["verdict"] in ("confirmed", "likely") for e in effects_out) \
            or "inertia" in dict(on.effect_dict) or any(n in ("motor_time_constant", "actuator_delay") for n, _ in on.effects):
        return None
    tau = float(lag_e["params"]["tau_up"])
    out, _ = _instrumented(S, on.with_effect("motor_time_constant", tau_up=tau, tau_down=tau),
                           [a for a in accepted if a != "inertia"], effects_out, guard, S.nominal)
    if out is None:
        return None
    out["lag_s"] = round(tau, 5)
    entry = next((e for e in effects_out if e["name"] == "inertia" and e["verdict"] == "likely"), None)
    if entry is not None and out.get("verdict") == "likely":
        entry["verdict_note"] += f"; read by PX4's rate loop on the vehicle with the motor lag it named ({tau:.3f} s)"
    return out


#: two readings of an inertia change agree, whatever their ratio, when their values are this close (a fraction
#: of the model's value: the bar a named parameter is held to). A small change read by two instruments whose
#: biases of a few percent go opposite ways breaks a ratio bar on the changes (PX4 SIH SIH_L_ROLL 0.17, M6, 4 ms:
#: the rate loop +24 %, the finding +14.5 %, truth +17.6 %; SIH_L_PITCH + KDV, M2: +16.6 % against +11.4 %)
AGREE_WITHIN = 0.10


def attach_instrumented(entry: dict, iv: dict, residual: dict, nominal_inertia: np.ndarray,
                        replace: bool = False) -> str:
    """Attach the instrumented inertia (``iv``: :func:`instrumented_inertia`'s or
    :func:`~twin_nodes.discovery.rate_loop.inertia`'s result with its ``params``; ``residual``: its
    held-out numbers) to an ``inertia`` finding already made on the flight's own residuals, as a
    third residual for the axes it flags.  It is attached where the finding moves those axes the
    same way within x1.5 or to within :data:`AGREE_WITHIN` of the rate loop's value, or held them at the model's value (then the instrument supplies them;
    ``held_at_nominal`` loses them); else the disagreement is returned and nothing changes.  With
    ``replace`` (PX4's rate loop on a log whose motor commands are aliased, where the finding's own
    roll/pitch fit is biased) the same direction is agreement enough, and the rate loop's value
    replaces the finding's (kept in ``own_params``).  PX4's rate loop (``iv["method"] == "rate_loop"``,
    either logging) also decides which axes moved: one it reads and does not flag is held at the model's
    value (the finding's own kept in ``own_params``; PX4 SIH SIH_L_PITCH 0.15 on M3 at 4 ms: the output
    error's Ixx +14 %, the rate loop's roll x0.90 +- 0.03).  Returns what happened, for the result's
    ``instrumented.verdict``."""
    params, ax = iv["params"], iv["axes"]
    agree = []
    for a in iv["flagged"]:
        k, j = IV_AXIS_PARAM[a]
        d_iv = params[k] / nominal_inertia[j] - 1.0
        d_f = entry["params"][k] / nominal_inertia[j] - 1.0
        held = k in (entry.get("held_at_nominal") or {})
        ok = held or (d_iv * d_f > 0 and (replace or max(abs(d_iv), abs(d_f)) <= 1.5 * min(abs(d_iv), abs(d_f))
                                          or abs(d_iv - d_f) <= AGREE_WITHIN))
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
    # PX4's rate loop (either logging; replacing, always) decides which of roll and pitch moved: an axis it
    # reads and does not flag is held at the model's value, whatever the finding's own fit moved it to
    unmoved = []
    for a in ax if (replace or iv.get("method") == "rate_loop") else ():
        k, j = IV_AXIS_PARAM[a]
        if a in iv["flagged"] or not np.isfinite(ax[a].get("scale", math.nan)) or \
                abs(entry["params"][k] - nominal_inertia[j]) <= 1e-9 * nominal_inertia[j]:
            continue
        entry.setdefault("own_params", {})[k] = entry["params"][k]
        entry["params"][k] = float(nominal_inertia[j])
        entry.setdefault("held_at_nominal", {})[k] = (
            f"PX4's rate loop reads {a} inertia x{ax[a]['scale']:.2f} +- {ax[a]['scale_se']:.2f} (not flagged): the "
            f"finding's {k} {entry['own_params'][k]:.4g} " + ("was fitted to motor commands logged slower than the rate "
                                                               "loop runs" if replace else "is not borne out by it"))
        unmoved.append((a, k))
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
                             + f"; {held_out}{100 * residual['heldout_improvement']:.0f} %)"
                             + "".join(f"; {k} held at the model's {nominal_inertia[IV_AXIS_PARAM[a][1]]:.4g} (the rate "
                                       f"loop reads {a} x{ax[a]['scale']:.2f} +- {ax[a]['scale_se']:.2f}; the finding's "
                                       f"{entry['own_params'][k]:.4g} " + ("fitted to aliased commands)" if replace else
                                                                            "not borne out)") for a, k in unmoved))
    return "corroborates the " + entry["verdict"] + " finding"


#: the inertia candidate's roll and pitch parameters
_RP_AXES = tuple(k for k, _ in IV_AXIS_PARAM.values())


def _axis_tests(S: PreparedFlight, g: Fit) -> dict[str, tuple[float, int]]:
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


def _equation_axes(S: PreparedFlight, ranked: list[Fit], effects_out: list[dict], current: VehicleParams,
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


def _instrumented(S: PreparedFlight, current: VehicleParams, accepted: list[str], effects_out: list[dict],
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

    def build(ixx, iyy, izz=float(I_cur[2])):
        return current.with_effect("inertia", ixx=ixx, iyy=iyy, izz=izz)
    reading = _instrument_reading(S, current, nominal, finding, allowed, I_cur, build, (fold1, fold2))
    if reading is None:
        return None, None
    iv, not_used, reference, replace = reading
    yaw_note = _yaw_without_thrust_share(S, current, iv)
    out = _instrument_numbers(iv, not_used)
    if yaw_note:
        out["yaw_read_on"] = yaw_note
    if not iv["flagged"]:
        return out, _hold_unflagged(iv, out, entry, build, guard, reference, float(I_cur[2]))
    v = _instrument_verdict(iv, out, win, d, entry)
    if v is None:
        return out, None
    return _instrument_entry(v, iv, out, entry, effects_out, build, guard, reference, replace, d)


def _hold_unflagged(iv: dict, out: dict, entry: dict | None, build: Callable, guard: Callable[[VehicleParams], str | None],
                    reference: np.ndarray, izz: float) -> VehicleParams | None:
    """Where PX4's rate loop flags nothing, the finding's axes it reads precisely and disagrees with held at the
    value read on (:func:`hold_axes_not_borne_out`, :func:`hold_yaw_not_borne_out`); a confirmed finding's
    refit vehicle takes them unless ``guard`` objects (then the finding stays).  Returns the new refit vehicle."""
    if entry is None or entry["verdict"] == "rejected" or iv.get("method") != "rate_loop":
        return None
    before = copy.deepcopy(entry)
    held = hold_axes_not_borne_out(entry, iv, reference) + (["izz"] if hold_yaw_not_borne_out(entry, iv, izz) else [])
    if not held:
        return None
    out["verdict"] = f"held the finding's {', '.join(held)} at the model's value (the rate loop does not bear them out)"
    if entry["verdict"] != "confirmed":
        return None
    refit = build(*(float(entry["params"].get(k, reference[j])) for k, j in (("ixx", 0), ("iyy", 1))),
                  float(entry["params"].get("izz", izz)))
    against = guard(refit)
    if against:
        entry.clear()
        entry.update(before)
        out["verdict"] = f"the finding's {', '.join(held)} not held: {against}"
        return None
    return refit


def _thrust_yaw_share_removed(vp: VehicleParams) -> VehicleParams | None:
    """``vp`` with the yaw torque its thrust coefficient scaled (``Q = km T``) put back to the model's, where it
    has a thrust coefficient and no yaw moment of its own (None: not so).  The thrust coefficient is read on the
    collective; its share of yaw is assumed, and a vehicle whose yaw torque is set apart from its thrust (PX4 SIH:
    SIH_Q_MAX beside SIH_T_MAX) keeps its yaw authority."""
    eff = dict(vp.effect_dict)
    if "thrust_coefficient" not in eff or "yaw_moment" in eff or not eff["thrust_coefficient"]["kt_scale"] > 0:
        return None
    km = float(effective_params(vp).rotors.km_m)
    return vp.with_effect("yaw_moment", km=km / float(eff["thrust_coefficient"]["kt_scale"]))


def _yaw_without_thrust_share(S: PreparedFlight, current: VehicleParams, iv: dict) -> str | None:
    """Where PX4's rate loop flags roll/pitch slow or fast but yaw does not read off the same way, yaw read again
    with the yaw torque an accepted thrust coefficient scaled put back (:func:`_thrust_yaw_share_removed`): if
    yaw then reads the motor signature, ``iv``'s yaw numbers and ``motor_signature`` are that reading's and a
    note says so (returned; None: unchanged).  PX4 SIH y018/t013 (SIH_T_MAX x0.92 and SIH_T_TAU 0.05 -> 0.08):
    yaw read 1.03/1.01 on the thrust coefficient's vehicle, whose yaw torque it cut 8 %, and the lag was lost."""
    if iv.get("method") != "rate_loop" or not iv.get("flagged") or iv.get("motor_signature"):
        return None
    alt = _thrust_yaw_share_removed(current)
    if alt is None:
        return None
    sy, sey = rate_loop.yaw_scale(S.data, S.log_params, alt, S.t_split, S.t_split2)
    if not rate_loop.motor_signature(iv["axes"], iv["flagged"], sy, sey):
        return None
    g, sg = (1.0 / sy, sey / (sy * sy)) if sy > 0 else (math.nan, math.nan)
    note = (f"yaw read with the yaw torque the thrust coefficient scaled put back: x{sy:.3f} +- {sey:.3f} "
            f"(on the thrust coefficient's vehicle x{iv['yaw_scale']:.3f})")
    iv.update(motor_signature=True, yaw_scale=sy, yaw_scale_se=sey, yaw_gain=g, yaw_se=sg)
    return note


def _instrument_reading(S: PreparedFlight, current: VehicleParams, nominal: VehicleParams | None, finding: bool,
                        allowed: tuple, I_cur: np.ndarray, build: Callable, folds: tuple) -> tuple | None:
    """The instrument's reading of the roll/pitch inertia: PX4's rate loop flown on the model where the log
    has it, else the rate setpoint as instrument; (reading, why the rate loop is not used, the inertia
    it is read against, whether it replaces the finding's values), None: nothing to read."""
    win, d = S.windows, S.data
    fold1, fold2 = folds

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
    elif finding and not allowed and nominal is not None:
        # a confirmed finding fitted roll and pitch itself (motors logged at the rate loop's rate): PX4's
        # rate loop reads both against the model's own inertia, a check of which axes moved
        I_nom = np.diag(effective_params(nominal).inertia)
        iv, not_used = flown(current.with_effect("inertia", ixx=float(I_nom[0]), iyy=float(I_nom[1]),
                                                 izz=float(I_cur[2])), ("roll", "pitch"))
        if iv is None:
            return None
        reference = I_nom
        iv.setdefault("params", {"ixx": float(I_nom[0]), "iyy": float(I_nom[1]), "izz": float(I_cur[2])})
        for a, (k, j) in IV_AXIS_PARAM.items():
            if a not in iv["flagged"]:
                iv["params"][k] = float(I_nom[j])
        return iv, not_used, reference, False
    if not replace:
        if not allowed:
            return None
        if not_used is None:
            iv, not_used = flown(current, allowed)
        if iv is None:
            iv = instrumented_inertia(d, win, current, fold1, fold2, build, allowed)
    if iv is None:
        return None
    if replace and iv.get("params"):
        # an axis the rate loop reads and does not flag is the model's: the finding's value for it was
        # fitted to the aliased commands (SIH_L_PITCH 0.15 on a 50 Hz log: the equation error's Ixx +14 %
        # at t=3.0, the rate loop's roll x1.02 +- 0.03)
        for a, (k, j) in IV_AXIS_PARAM.items():
            if a not in iv["flagged"]:
                iv["params"][k] = float(reference[j] if a in iv["axes"] else I_cur[j])
    return iv, not_used, reference, replace


def _instrument_numbers(iv: dict, not_used: str | None) -> dict:
    """The instrument's numbers for the result's ``instrumented`` entry (its verdict still "none")."""
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
    return out


def _instrument_verdict(iv: dict, out: dict, win: Windows, d, entry: dict | None) -> dict | None:
    """Whether the flagged axes make a ``likely`` inertia (updates ``out``); None: they do not (``out`` says
    why), else the numbers :func:`_instrument_entry` reports."""
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
    rl = iv.get("method", "instrument") == "rate_loop"
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
        return None
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
        return None
    return {"note": note, "main": main, "m": m, "b0": b0, "b1": b1, "cut": cut, "rl": rl, "kind": kind,
            "what": what, "params": params}


def _instrument_entry(v: dict, iv: dict, out: dict, entry: dict | None, effects_out: list[dict], build: Callable,
                      guard: Callable[[VehicleParams], str | None], reference: np.ndarray, replace: bool, d
                      ) -> tuple[dict, VehicleParams | None]:
    """The instrument's ``likely`` inertia as a third residual of the flight's own finding, or as a new
    ``inertia`` entry of ``effects_out`` (re-sorted by grade); returns the result's numbers and the new
    refit vehicle (None: unchanged)."""
    note, main, m, b0, b1, cut = v["note"], v["main"], v["m"], v["b0"], v["b1"], v["cut"]
    rl, kind, what, params = v["rl"], v["kind"], v["what"], v["params"]
    ax = iv["axes"]
    prev = dict(entry) if entry is not None else {}
    residual = {"residual": kind, "heldout_channel": main, "heldout_before": round(float(b0), 5),
                "heldout_after": round(float(b1), 5), "heldout_improvement": round(float(cut), 4),
                "heldout_t_stat": round(float(m.get("heldout_t", math.nan)), 2), "params": params,
                "fold_gains": [round(float(ax[main]["gain_fold1"]), 4), round(float(ax[main]["gain_fold2"]), 4)]}
    if entry is not None and entry["verdict"] != "rejected":
        # already a finding on its own residuals: the instrument is a third residual for its axes
        before = copy.deepcopy(entry)
        out["verdict"] = attach_instrumented(entry, iv, residual, reference, replace)
        if not out["verdict"].startswith("corroborates"):
            return out, None
        hold_yaw_not_borne_out(entry, iv)
        if entry["verdict"] != "confirmed" or entry["params"] == before["params"]:
            return out, None
        # the refit vehicle takes the roll/pitch the instrument supplied or held, unless the closed-loop
        # twin says otherwise (then the finding stays as it was)
        refit = build(float(entry["params"]["ixx"]), float(entry["params"]["iyy"]),
                      float(entry["params"].get("izz", iv["params"]["izz"])))
        against = guard(refit)
        if against:
            entry.clear()
            entry.update(before)
            out["verdict"] = f"not supplied to the confirmed finding: {against}"
            return out, None
        return out, refit
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
    insert_likely(effects_out, new)
    return out, None
