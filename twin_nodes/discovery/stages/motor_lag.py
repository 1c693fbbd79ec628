"""Stage 7, the motors' lag read by PX4's rate loop flown on the model (:func:`~twin_nodes.discovery.rate_loop.
motor_lag`, which uses no motor command): a lag found on the flight's own residuals from aliased 50 Hz commands
read again (:func:`read_finding`), a lag where the rate loop says the motors are slow and nothing else named them
(:func:`rate_loop_lag`), or beside a delay the flight's own residuals named (:func:`_beside_the_delay`)."""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from twin_nodes.discovery import rate_loop
from twin_nodes.discovery.judging import MOTOR_DYNAMICS, insert_likely
from twin_nodes.discovery.output_error import IV_AXIS_PARAM
from twin_nodes.discovery.plans import RATE_LOOP_LOG_S
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.discovery.verdicts import LIKELY_MIN_CUT
from twin_nodes.physics.effects import EFFECTS, effective_params
from twin_nodes.vehicle.params import VehicleParams

#: the output-error blocks an instrumented effect's plan asks for: the axis had none a fit could use,
#: so no block statistic says how many; PX4 SIH SIH_L_ROLL 0.16 (g26, g34): 50-65 active roll blocks
#: gave t 3.9-4.9 in one follow-up and 58 gave t 2.4 in another, so twice g34's missing 15
INSTRUMENTED_BLOCKS_MISSING = 30


def _lag_checks(r: dict) -> tuple[list[str], float]:
    """Why the rate loop's lag reading ``r`` (:func:`~twin_nodes.discovery.rate_loop.motor_lag`, flagged) is not
    a finding (empty: it is), and the held-out cut: both folds move it the model's lag the same way at 2
    standard errors, each fold's lag cuts the held-out rate error along its sensitivity (both folds' held-out
    windows pooled, :func:`~twin_nodes.discovery.rate_loop.projected_folds`) by ``LIKELY_MIN_CUT``, fold 1's lies
    in the effect's physical range and beats an extra delay on the held-out windows."""
    tau0, tau1 = r["model_tau"], r["tau_fold1"]
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
    return why, cut


def read_finding(S: PreparedFlight, current: VehicleParams, effects_out: list[dict],
                 guard: Callable[[VehicleParams], str | None]) -> VehicleParams | None:
    """A motor lag found on the flight's own residuals from motor commands logged slower than PX4's rate loop
    runs (aliased: on PX4 SIH's 50 Hz logs SIH_T_TAU 0.13 s was fitted 0.147/0.151 by the equation error), read
    again by PX4's rate loop flown on the model with the nominal lag (it uses no motor command; the same log
    reads 0.129 +- 0.001).  Where that reading passes :func:`_lag_checks` and moves the lag the finding's way,
    its value replaces the finding's (kept in ``own_params``) and the refit vehicle's, the closed-loop check
    permitting.  Returns the new refit vehicle (None: unchanged)."""
    d = S.data
    entry = next((e for e in effects_out if e["name"] == "motor_time_constant"
                  and e["verdict"] in ("confirmed", "likely") and e.get("residual") != "rate_loop"), None)
    lag = dict(current.effect_dict).get("motor_time_constant")
    if entry is None or lag is None or S.nominal is None or d.motor_dt_s <= RATE_LOOP_LOG_S:
        return None
    r0 = effective_params(S.nominal).rotors
    base = current.with_effect("motor_time_constant", tau_up=r0.tau_up_s, tau_down=r0.tau_down_s)
    r = rate_loop.motor_lag(d, S.log_params, base, S.t_split, S.t_split2)
    if r is None or not r["flagged"]:
        return None
    why, cut = _lag_checks(r)
    tau1 = float(r["tau_fold1"])
    own = 0.5 * (lag["tau_up"] + lag["tau_down"])
    if (own - r["model_tau"]) * (tau1 - r["model_tau"]) <= 0:
        why.append(f"it moves the lag the other way from the finding's {own:.3f} s")
    new = current.with_effect("motor_time_constant", tau_up=tau1, tau_down=tau1)
    against = None if why else guard(new)
    if why or against:
        entry["rate_loop_reading"] = {"tau": round(float(r["tau"]), 5), "se": round(float(r["se"]), 5),
                                      "not_used": why or [against]}
        return None
    entry["own_params"] = dict(entry["params"])
    entry["params"] = {"tau_up": tau1, "tau_down": tau1}
    entry.setdefault("residuals", {})["rate_loop"] = {
        "residual": "rate_loop", "heldout_improvement": round(float(cut), 4), "params": dict(entry["params"]),
        "fold_params": [round(float(r["tau_fold1"]), 5), round(float(r["tau_fold2"]), 5)]}
    axis_tau = ", ".join(f"{a} {v:.3f}" for a, v in r["axis_tau"].items())
    entry["verdict_note"] = (entry.get("verdict_note", "") + f"; PX4's rate loop (no motor command in it) reads the "
                             f"lag {r['tau']:.3f} +- {r['se']:.3f} s (each axis: {axis_tau} s; held-out cut "
                             f"{100 * cut:.0f} %), in place of the finding's "
                             + "/".join(f"{v:.3g}" for v in entry["own_params"].values())
                             + f" s (fitted to motor commands logged every {1e3 * d.motor_dt_s:.0f} ms, aliased)")
    return new


def rate_loop_lag(S: PreparedFlight, current: VehicleParams, effects_out: list[dict]) -> dict | None:
    """The motors' time constant read by PX4's rate loop flown on the model
    (:func:`~twin_nodes.discovery.rate_loop.motor_lag`), where the rate loop said the motors, not an
    inertia, are slow (every axis off the same way) and the model's lag and delay are its own.

    It is ``likely`` when the lag is far from the model's on every axis alike, both folds move it the
    same way by 2 standard errors, each fold's lag cuts both folds' held-out rate error along its sensitivity by
    ``LIKELY_MIN_CUT``, lies inside the effect's physical range, and beats an extra delay on the
    held-out windows; never ``confirmed`` (no residual of the flight's own shows it: PX4 SIH
    SIH_T_TAU 0.09 s on a 50 Hz log, where lag and delay cut the output error 9-10 %).  The entry
    replaces the flight's own ``motor_time_constant`` (kept as its residuals), re-sorted by grade.
    Returns the numbers for the result (None: not looked at)."""
    delay = None
    if any(name in MOTOR_DYNAMICS for name, _ in current.effects):
        # a delay found on the flight's own residuals (on a 50 Hz log they cannot tell it from a lag): the
        # rate loop reads the lag on the vehicle without it, and a lag it prefers is named beside the delay
        delay = next((e for e in effects_out if e["name"] == "actuator_delay" and e["verdict"] != "rejected"), None)
        if delay is None or {n for n, _ in current.effects if n in MOTOR_DYNAMICS} != {"actuator_delay"}:
            return None
        current = current.replace(effects=tuple(e for e in current.effects if e[0] != "actuator_delay"))
    current = _with_inertia_finding(current, effects_out)
    r = rate_loop.motor_lag(S.data, S.log_params, current, S.t_split, S.t_split2)
    if r is None:
        return None
    out = {k: (round(float(v), 5) if isinstance(v, float) else v) for k, v in r.items() if k not in ("loop", "heldout_sse")}
    out["heldout_sse"] = {k: round(float(v), 2) for k, v in r["heldout_sse"].items()}
    out["verdict"] = "none"
    tau0 = r["model_tau"]
    if not r["flagged"]:
        out["why_not"] = [f"the lag {r['tau']:.3f} +- {r['se']:.3f} s is not far from the model's {tau0:.3f} s on "
                          f"every axis alike (roll, pitch, yaw {', '.join(f'{v:.3f}' for v in r['axis_tau'].values())})"]
        return out
    why, cut = _lag_checks(r)
    out["heldout_improvement"] = round(float(cut), 4) if np.isfinite(cut) else None
    if why:
        out["why_not"] = why
        return out
    out["verdict"] = "likely"
    if delay is not None:
        return _beside_the_delay(r, out, delay)
    return _rate_loop_lag_entry(r, out, cut, effects_out)


def _with_inertia_finding(current: VehicleParams, effects_out: list[dict]) -> VehicleParams:
    """``current`` carrying a ``likely`` inertia finding's roll/pitch (a ``likely`` finding is not in the refit
    vehicle), so that the rate loop reads the motors' lag on the vehicle with it, not on one whose roll/pitch
    is the nominal's and whose slowness it would read as the motors' (PX4 SIH SIH_T_TAU 0.08 with SIH_L_PITCH
    0.17, m017: 0.088 s on the nominal inertia); unchanged when the vehicle already carries an inertia."""
    e = next((e for e in effects_out if e["name"] == "inertia" and e["verdict"] == "likely"), None)
    if e is None or "inertia" in dict(current.effect_dict):
        return current
    I0 = np.diag(effective_params(current).inertia).astype(float)
    return current.with_effect("inertia", ixx=float(e["params"].get("ixx", I0[0])),
                               iyy=float(e["params"].get("iyy", I0[1])), izz=float(I0[2]))


def _beside_the_delay(r: dict, out: dict, delay: dict) -> dict:
    """The rate loop's lag (``r``, which beat an extra delay on its held-out windows) as the ``actuator_delay``
    finding's not-told-apart partner, with the manoeuvre that separates them; the finding and the refit
    vehicle are unchanged (the flight's own residuals chose the delay)."""
    from twin_nodes.discovery.stages.verdicts import not_told_apart

    tau = float(r["tau_fold1"])
    alt = {"name": "motor_time_constant", "params": {"tau_up": tau, "tau_down": tau},
           "note": (f"PX4's rate loop flown on the model without the delay reads the motors' lag {r['tau']:.3f} +- "
                    f"{r['se']:.3f} s (model {r['model_tau']:.3f} s), and it fits the held-out windows better than "
                    f"an extra delay (sum of squares {r['heldout_sse']['lag']:.0f} vs {r['heldout_sse']['delay']:.0f})")}
    delay["alternatives"] = [alt] + [a for a in delay.get("alternatives") or [] if a.get("name") != alt["name"]]
    pair = not_told_apart(delay)
    if pair is not None:
        delay["not_told_apart"] = pair
    delay["verdict_note"] = delay.get("verdict_note", "") + "; not told apart from a motor lag: " + alt["note"]
    out["verdict"] = "named beside the delay found on the flight's own residuals"
    return out


def _rate_loop_lag_entry(r: dict, out: dict, cut: float, effects_out: list[dict]) -> dict:
    """A ``likely`` motor lag from PX4's rate loop (``r``: :func:`~twin_nodes.discovery.rate_loop.motor_lag`'s
    result): its residual, and its entry in ``effects_out`` in place of the flight's own
    ``motor_time_constant`` unless that is already a finding; returns ``out``."""
    tau0, tau1 = r["model_tau"], r["tau_fold1"]
    b0, b1 = r["heldout_before"], r["heldout_after"]
    held = r["heldout_sse"]
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
    insert_likely(effects_out, new)
    return out


def beside_inertia(S: PreparedFlight, current: VehicleParams, effects_out: list[dict],
                   guard: Callable[[VehicleParams], str | None]) -> VehicleParams | None:
    """A motor lag found beside an inertia, both read again together by PX4's rate loop flown on the model.

    The flight's own residuals fit the lag before the inertia is in the model, so a slower roll/pitch (a larger
    inertia, a shorter arm) is partly read as slower motors (PX4 SIH SIH_T_TAU 0.08 s with IXX/IYY x1.3, h019:
    the output error's lag 0.098 s), and the inertia, read on that vehicle, comes out short (x1.21).  Here the
    lag is read by the rate loop on the refit vehicle, which carries the inertia (h019: 0.083 s), the roll/pitch
    inertia the finding moved is read again on that lag, and the lag once more on that inertia (alternating
    the two one-parameter reads).  The new lag is used where it passes :func:`_lag_checks` and lies more than
    ``rate_loop.MIN_SE`` standard errors from the finding's; the closed-loop check permitting.  Returns the new
    refit vehicle (None: unchanged)."""
    lag_e, in_e = (next((e for e in effects_out if e["name"] == n and e["verdict"] in ("confirmed", "likely")), None)
                   for n in ("motor_time_constant", "inertia"))
    eff = dict(current.effect_dict)
    if lag_e is None or in_e is None or "motor_time_constant" not in eff or "inertia" not in eff or S.nominal is None:
        return None
    I_nom = np.diag(effective_params(S.nominal).inertia).astype(float)
    moved = [a for a, (k, j) in IV_AXIS_PARAM.items()
             if abs(float(in_e["params"].get(k, I_nom[j])) - I_nom[j]) > 1e-9 * I_nom[j]]
    own = 0.5 * (eff["motor_time_constant"]["tau_up"] + eff["motor_time_constant"]["tau_down"])
    d, p = S.data, S.log_params
    r = rate_loop.motor_lag(d, p, current, S.t_split, S.t_split2)
    if r is None:
        return None
    why, cut = _lag_checks(r)
    if not abs(r["tau"] - own) > rate_loop.MIN_SE * r["se"]:
        why.append(f"the lag {r['tau']:.3f} +- {r['se']:.3f} s is within {rate_loop.MIN_SE:g} standard errors of "
                   f"the finding's {own:.3f} s")
    if why:
        lag_e["rate_loop_beside_inertia"] = {"tau": round(float(r["tau"]), 5), "se": round(float(r["se"]), 5),
                                             "not_used": why}
        return None
    new, inertia = current, dict(eff["inertia"])
    for _ in range(2):
        tau = float(r["tau_fold1"])
        new = new.with_effect("motor_time_constant", tau_up=tau, tau_down=tau)
        iv = rate_loop.inertia(d, p, new, S.t_split, S.t_split2, axes_allowed=tuple(moved)) if moved else None
        for a in moved if iv is not None and not iv.get("pinned") else ():
            k, j = IV_AXIS_PARAM[a]
            g = iv["axes"][a]["gain_fold1"]
            inertia[k] = float(inertia[k] / g) if np.isfinite(g) and g > 0 else inertia[k]
        new = new.with_effect("inertia", **inertia)
        r2 = rate_loop.motor_lag(d, p, new, S.t_split, S.t_split2)
        if r2 is None or not np.isfinite(r2["tau_fold1"]):
            break
        r = r2
    against = guard(new)
    if against:
        lag_e["rate_loop_beside_inertia"] = {"tau": round(float(r["tau"]), 5), "se": round(float(r["se"]), 5),
                                             "not_used": [against]}
        return None
    tau = float(dict(new.effect_dict)["motor_time_constant"]["tau_up"])
    lag_e.setdefault("own_params", dict(lag_e["params"]))
    lag_e["params"] = {"tau_up": tau, "tau_down": tau}
    lag_e["verdict_note"] = (lag_e.get("verdict_note", "") + f"; read again beside the inertia by PX4's rate loop "
                             f"flown on the vehicle carrying it: lag {tau:.3f} s (the finding's {own:.3f} s; held-out cut "
                             f"{100 * cut:.0f} %)")
    for a in moved:
        k = IV_AXIS_PARAM[a][0]
        in_e.setdefault("own_params", {}).setdefault(k, in_e["params"][k])
        in_e["params"][k] = inertia[k]
    if moved:
        in_e["verdict_note"] = (in_e.get("verdict_note", "") + "; roll/pitch read again by PX4's rate loop on the "
                                f"motor lag read beside it ({tau:.3f} s): " +
                                ", ".join(f"{IV_AXIS_PARAM[a][0]} {inertia[IV_AXIS_PARAM[a][0]]:.4g}" for a in moved))
    return new
