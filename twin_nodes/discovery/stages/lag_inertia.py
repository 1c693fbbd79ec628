"""Stage 7, end: the motors' lag and the roll/pitch inertia read together by PX4's rate loop flown on the model
(attitude loop closed, :func:`~twin_nodes.discovery.rate_loop.with_attitude_loop`), one common lag for the three
axes and one inertia scale each for roll and pitch, Izz held (:func:`joint_reading`), and used where a lag or an
inertia is a finding (:func:`read_together`).

Why together: on PX4 SIH a slower motor and a larger roll/pitch inertia both slow roll and pitch, so either read
alone absorbs the other (SIH_T_TAU 0.08 with IXX/IYY x1.3, M1: on the model's lag the rate loop reads roll x1.49,
pitch x1.46; on that inertia it reads the lag 0.070 s).  Yaw is moved by the lag alone, and roll/pitch's
response shape differs between the two, so the joint minimum separates them (the same flights: 0.080 s, roll
x1.28, pitch x1.31); a lag alone read as an inertia on the model's lag (SIH_T_TAU 0.08, M5: roll x1.25, pitch x1.22)
reads roll/pitch x1.03 / x0.99 beside its lag."""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

from twin_nodes.discovery import rate_loop
from twin_nodes.discovery.rate_loop import parabola_min
from twin_nodes.discovery.judging import insert_likely
from twin_nodes.discovery.output_error import IV_AXIS_PARAM
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.discovery.verdicts import LIKELY_MIN_CUT
from twin_nodes.physics.effects import effective_params
from twin_nodes.vehicle.params import VehicleParams

#: the motors' time constants the joint reading simulates [s] (log-spaced, ~12 % apart; refined by a parabola)
JOINT_TAUS = np.exp(np.linspace(math.log(0.025), math.log(0.3), 23))
RP = ("roll", "pitch")


def _row(Q: np.ndarray, lt: np.ndarray, x: float) -> np.ndarray:
    """``Q`` (T, S) at log lag ``x``, linear between the grid's rows."""
    j = int(np.clip(np.searchsorted(lt, x), 1, len(lt) - 1))
    w = float(np.clip((x - lt[j - 1]) / (lt[j] - lt[j - 1]), 0.0, 1.0))
    return (1 - w) * Q[j - 1] + w * Q[j]


def _at(Q: np.ndarray, lt: np.ndarray, ls: np.ndarray, x: float, s: float) -> float:
    """``Q`` (T, S) at log lag ``x`` and log scale ``s`` (bilinear)."""
    r = _row(Q, lt, x)
    return float(np.interp(s, ls, r)) if len(r) > 1 else float(r[0])


def _fit(E: dict, rows: np.ndarray, lt: np.ndarray, ls: np.ndarray) -> dict:
    """The joint minimum over ``rows``: the common log lag (each axis's sum of squares over its own minimum,
    added), each roll/pitch axis's log scale there (yaw held), each axis's own best log lag (the roll/pitch
    profiles over their scale), and the best log lag with roll/pitch at the model's inertia (log scale 0)."""
    Q = {a: E[a][:, :, rows].sum(-1) for a in E}
    prof = {a: (np.array([parabola_min(q, ls)[1] for q in Q[a]]) if Q[a].shape[1] > 1 else Q[a][:, 0]) for a in Q}
    tot = sum(p / max(float(p.min()), 1e-300) for p in prof.values())
    x, _, inside = parabola_min(tot, lt)
    s = {a: parabola_min(_row(Q[a], lt, x), ls)[0] for a in RP if a in Q}
    at1 = sum((np.array([np.interp(0.0, ls, q) for q in Q[a]]) if Q[a].shape[1] > 1 else Q[a][:, 0])
              / max(float(prof[a].min()), 1e-300) for a in Q)
    return {"x": x, "s": s, "inside": inside, "axis_x": {a: parabola_min(prof[a], lt)[0] for a in prof},
            "x_lag_alone": parabola_min(at1, lt)[0]}


def window_errors(loop: rate_loop.RateLoop, data, idx: np.ndarray, taus: np.ndarray = JOINT_TAUS,
                  scales: np.ndarray = rate_loop.SCALES) -> dict[str, np.ndarray]:
    """Per axis the sum of squares of each window's body-rate residual (:func:`rate_loop.residuals`), (T, S, K)
    over the lags ``taus`` and inertia ``scales`` (yaw: S = 1, Izz as the model has it)."""
    out = {}
    for ax, name in enumerate(rate_loop.AXES):
        w, sp = data.w[idx, ax], data.w_sp[idx, ax]
        if name == "yaw":
            R = rate_loop.residuals(loop, ax, w, sp, data.dt, taus=taus)
            out[name] = np.einsum("tkn,tkn->tk", R, R)[:, None, :]
            continue
        per = []
        for t in taus:
            R = rate_loop.residuals(dataclasses.replace(loop, tau_s=float(t)), ax, w, sp, data.dt, scales)
            per.append(np.einsum("skn,skn->sk", R, R))
        out[name] = np.stack(per)
    return out


def joint_from_errors(E: dict, masks: tuple, tau0: float, taus: np.ndarray = JOINT_TAUS,
                      scales: np.ndarray = rate_loop.SCALES) -> dict:
    """The joint reading from the per-window sums of squares ``E`` (:func:`window_errors`) and the window masks
    (all, fold 1 fit, fold 1 held out, fold 2 fit, fold 2 held out): the lag ``tau`` and the roll/pitch ``scale``
    on all windows, each fold's, each axis's own lag, and both folds' held-out sums of squares (each axis over
    the model's, averaged) of the model, the inertia alone (at the model's lag), the lag alone (at the model's
    inertia) and both together, each at its own fold's fit.  ``lag_flagged``: the lag moves ``MIN_TAU_CHANGE``,
    both folds half of that the same way, yaw (which no roll/pitch inertia moves) ``AXIS_AGREE`` of it, and it
    beats the inertia alone on the held-out windows; an axis is flagged when its scale moves ``MIN_CHANGE``, both
    folds half of that the same way, and the two together beat the lag alone on the held-out windows (beside a
    larger flagged axis, ``MIN_CHANGE_BESIDE``: :func:`~twin_nodes.discovery.rate_loop.beside_flagged`)."""
    lt, ls = np.log(taus), np.log(scales)
    every, fit1, test1, fit2, test2 = masks
    f = [_fit(E, m, lt, ls) for m in (every, fit1, fit2)]
    x0 = math.log(tau0)
    held = {k: 0.0 for k in ("model", "inertia", "lag", "both")}
    for a in E:
        Ea = E[a]
        h = {k: 0.0 for k in held}
        for fk, test in ((f[1], test1), (f[2], test2)):
            Q = Ea[:, :, test].sum(-1)
            Qf = Ea[:, :, fit1 if test is test1 else fit2].sum(-1)
            s_in = parabola_min(_row(Qf, lt, x0), ls)[0] if a in RP else 0.0
            h["model"] += _at(Q, lt, ls, x0, 0.0)
            h["inertia"] += _at(Q, lt, ls, x0, s_in)
            h["lag"] += _at(Q, lt, ls, fk["x_lag_alone"], 0.0)
            h["both"] += _at(Q, lt, ls, fk["x"], fk["s"].get(a, 0.0))
        for k in held:
            held[k] += h[k] / max(h["model"], 1e-300) / len(E)
    tau, taus_f = math.exp(f[0]["x"]), [math.exp(g["x"]) for g in f[1:]]
    change = tau - tau0
    yaw = math.exp(f[0]["axis_x"].get("yaw", f[0]["x"]))
    lag_flagged = bool(f[0]["inside"] and abs(change) > rate_loop.MIN_TAU_CHANGE * tau0
                       and all((t - tau0) * np.sign(change) > 0.5 * rate_loop.MIN_TAU_CHANGE * tau0 for t in taus_f)
                       and (yaw - tau0) * np.sign(change) >= rate_loop.AXIS_AGREE * abs(change)
                       and held["both"] < held["inertia"])
    axes = {}
    for a in RP:
        s, s1, s2 = (math.exp(g["s"][a]) for g in f)
        axes[a] = {"scale": s, "scale_fold1": s1, "scale_fold2": s2,
                   "flagged": bool(abs(s - 1) > rate_loop.MIN_CHANGE and held["both"] < held["lag"]
                                   and all((v - 1) * np.sign(s - 1) > 0.5 * rate_loop.MIN_CHANGE for v in (s1, s2)))}
    rate_loop.beside_flagged(axes)
    return {"tau": tau, "tau_fold1": taus_f[0], "tau_fold2": taus_f[1], "model_tau": tau0,
            "axis_tau": {a: math.exp(v) for a, v in f[0]["axis_x"].items()}, "axes": axes,
            "heldout_relative_sse": {k: round(v, 5) for k, v in held.items()}, "lag_flagged": lag_flagged}


def _lag_cut(loop: rate_loop.RateLoop, data, idx: np.ndarray, masks: tuple, r: dict) -> dict:
    """Both folds' held-out body-rate error along the lag's sensitivity (:func:`rate_loop.projected_folds`, the
    three axes each in units of its own RMS at the model) at the model's lag and at each fold's, on the joint
    reading's roll/pitch inertia: the cut, and each axis's."""
    sc = np.array([r["axes"]["roll"]["scale"], r["axes"]["pitch"]["scale"], 1.0])
    on = dataclasses.replace(loop, authority=loop.authority / sc, damping=loop.damping / sc)
    _, _, test1, _, test2 = masks
    per = {}
    stack = []
    for ax, name in enumerate(rate_loop.AXES):
        R = rate_loop.residuals(on, ax, data.w[idx, ax], data.w_sp[idx, ax], data.dt, taus=JOINT_TAUS)
        j0 = int(np.argmin(np.abs(JOINT_TAUS - loop.tau_s)))
        R = R / (float(np.sqrt(np.mean(R[j0] ** 2))) or 1.0)
        stack.append(R)
    model = [(loop.tau_s, test1), (loop.tau_s, test2)]
    fits = [(r["tau_fold1"], test1), (r["tau_fold2"], test2)]
    for name, R in list(zip(rate_loop.AXES, stack)) + [("joint", np.concatenate(stack, axis=-1))]:
        b, tb = rate_loop.projected_folds(R, JOINT_TAUS, model)
        a, _ = rate_loop.projected_folds(R, JOINT_TAUS, fits)
        per[name] = {"before": b, "after": a, "t": abs(tb) if np.isfinite(tb) else math.nan,
                     "cut": 1.0 - a / b if np.isfinite(a) and np.isfinite(b) and b > 0 else math.nan}
    return per


def joint_reading(data, params, vp: VehicleParams, t_split: float, t_split2: float) -> dict | None:
    """:func:`joint_from_errors` on PX4's rate loop flown on ``vp`` (attitude loop closed), with the lag's held-out
    cut on the joint inertia (``heldout``, :func:`_lag_cut`); None where the log has no rate loop or too few windows."""
    setup = rate_loop._flight(data, params, vp, t_split, t_split2)
    if setup is None:
        return None
    loop, idx, masks = setup
    loop = rate_loop.with_attitude_loop(loop, params)
    r = joint_from_errors(window_errors(loop, data, idx), masks, loop.tau_s)
    r["windows"] = int(idx.shape[0])
    if r["lag_flagged"]:
        r["heldout"] = _lag_cut(loop, data, idx, masks, r)
    return r


def _finding(effects_out: list[dict], name: str) -> dict | None:
    return next((e for e in effects_out if e["name"] == name and e["verdict"] in ("confirmed", "likely")), None)


def read_together(S: PreparedFlight, current: VehicleParams, effects_out: list[dict],
                  guard: Callable[[VehicleParams], str | None]) -> tuple[VehicleParams | None, dict | None]:
    """The lag and the roll/pitch inertia read together (:func:`joint_reading`) where an inertia is a finding and
    no delay is (a lag alone is left to its own readings: SIH_T_TAU 0.13, M1, confirmed at 0.131 s, reads 0.139
    here), on the vehicle without the lag and with the nominal's roll/pitch (Izz the finding's).  Where the joint
    lag is flagged: the lag entry takes it (or a ``likely`` entry from the rate loop is named in place of a
    rejected one), an inertia finding takes the joint scale on each roll/pitch axis it flags and the model's on the
    others, and a ``likely`` inertia the joint reading flags on no axis is rejected (the motors' lag read as
    inertia); a ``confirmed`` inertia it flags on no axis leaves everything as it is.  The refit vehicle takes
    what it carries, the closed-loop check permitting.  Returns (new refit vehicle or None, the numbers or None)."""
    lag_e, in_e = _finding(effects_out, "motor_time_constant"), _finding(effects_out, "inertia")
    eff = dict(current.effect_dict)
    if in_e is None or S.nominal is None or "actuator_delay" in eff \
            or _finding(effects_out, "actuator_delay") is not None:
        return None, None
    I_nom = np.diag(effective_params(S.nominal).inertia).astype(float)
    r0 = effective_params(S.nominal).rotors
    base = current.with_effect("motor_time_constant", tau_up=r0.tau_up_s, tau_down=r0.tau_down_s)
    # Izz as the finding reads it (a `likely` one is not in the refit vehicle): yaw then reads the lag alone (PX4 SIH
    # SIH_IZZ x1.6, M5: on the model's Izz yaw reads a lag of 0.24 s, the joint lag 0.062 s)
    izz = float(in_e["params"].get("izz", eff.get("inertia", {}).get("izz", I_nom[2])))
    base = base.with_effect("inertia", ixx=float(I_nom[0]), iyy=float(I_nom[1]), izz=izz)
    r = joint_reading(S.data, S.log_params, base, S.t_split, S.t_split2)
    if r is None:
        return None, None
    out = {k: (round(v, 5) if isinstance(v, float) else v) for k, v in r.items()}
    out["verdict"] = "none"
    if not r["lag_flagged"]:
        return None, out
    cut = r["heldout"]["joint"]["cut"]
    flagged = [a for a in RP if r["axes"][a]["flagged"]]
    if not (cut >= LIKELY_MIN_CUT):
        out["why_not"] = f"the lag's held-out cut {100 * cut:.0f} % < {100 * LIKELY_MIN_CUT:.0f} %"
        return None, out
    if not flagged and in_e["verdict"] == "confirmed":
        out["why_not"] = "the joint reading flags no roll/pitch inertia beside the lag, the confirmed finding does"
        return None, out
    tau = float(r["tau"])
    I_new = dict(in_e["params"])
    for a in RP:
        k, j = IV_AXIS_PARAM[a]
        I_new[k] = float(I_nom[j] * r["axes"][a]["scale"]) if a in flagged else float(I_nom[j])
    new = current
    if "motor_time_constant" in eff:
        new = new.with_effect("motor_time_constant", tau_up=tau, tau_down=tau)
    if "inertia" in eff and flagged:
        new = new.with_effect("inertia", **{k: float(I_new.get(k, v)) for k, v in eff["inertia"].items()})
    against = guard(new) if new is not current else None
    if against:
        out["why_not"] = against
        return None, out
    _name_lag(r, tau, cut, lag_e, effects_out)
    _inertia_read_together(r, in_e, I_new, flagged, tau)
    out["verdict"] = "lag and inertia" if flagged else "lag, the inertia rejected"
    return (new if new is not current else None), out


def _axes_text(r: dict) -> str:
    return ", ".join(f"{a} x{r['axes'][a]['scale']:.2f}" for a in RP)


def _name_lag(r: dict, tau: float, cut: float, lag_e: dict | None, effects_out: list[dict]) -> None:
    """The lag entry takes the joint reading's lag (its own value kept in ``own_params``), or a ``likely`` entry
    from the joint reading is named in place of a rejected one."""
    h = r["heldout"]
    main = max(rate_loop.AXES, key=lambda a: h[a]["cut"] if np.isfinite(h[a]["cut"]) else -1.0)
    residual = {"residual": "rate_loop_joint", "heldout_channel": main, "heldout_before": round(float(h[main]["before"]), 5),
                "heldout_after": round(float(h[main]["after"]), 5), "heldout_improvement": round(float(h[main]["cut"]), 4),
                "heldout_joint": {k: round(float(v), 4) for k, v in h["joint"].items()},
                "heldout_t_stat": round(float(h["joint"]["t"]), 2),
                "params": {"tau_up": tau, "tau_down": tau},
                "fold_params": [round(float(r["tau_fold1"]), 5), round(float(r["tau_fold2"]), 5)]}
    note = (f"PX4's rate loop flown on the model (attitude loop closed) reads the motors' lag and the roll/pitch "
            f"inertia together: lag {tau:.3f} s (folds {r['tau_fold1']:.3f} / {r['tau_fold2']:.3f}, model "
            f"{r['model_tau']:.3f}; yaw alone {r['axis_tau']['yaw']:.3f}) beside {_axes_text(r)}; held-out body-rate "
            f"error along the lag's sensitivity cut {100 * cut:.0f} %")
    if lag_e is not None:
        lag_e.setdefault("own_params", dict(lag_e["params"]))
        lag_e["params"] = {"tau_up": tau, "tau_down": tau}
        lag_e.setdefault("residuals", {})["rate_loop_joint"] = residual
        lag_e["verdict_note"] = lag_e.get("verdict_note", "") + "; read again together with the inertia: " + note
        return
    prev = next((e for e in effects_out if e["name"] == "motor_time_constant"), None)
    new = {"name": "motor_time_constant", "accepted": False, "verdict": "likely", "verdict_note": "likely (rate loop): " + note,
           "params": {"tau_up": tau, "tau_down": tau}, "residual": "rate_loop_joint",
           "evidence": f"motor_time_constant (tau {tau:.4g} s) read together with the roll/pitch inertia by PX4's rate "
                       f"loop: held-out cut {100 * cut:.0f} %: likely (rate loop)",
           **{k: residual[k] for k in ("heldout_channel", "heldout_before", "heldout_after", "heldout_improvement",
                                       "heldout_t_stat")},
           "heldout_units": (f"{main} body-rate error (in units of its own RMS) along its sensitivity to the lag, "
                             "held-out windows of PX4's rate loop flown on the model"),
           "cv_improvement": residual["heldout_improvement"], "above_resolution_floor": True,
           "excitation": {**((prev or {}).get("excitation") or {}), "channel": main, "residual": "rate_loop_joint",
                          "windows": r["windows"], "plans": ["rate_doublets"]},
           "residuals": {**((prev or {}).get("residuals") or {}), "rate_loop_joint": residual}, "alternatives": []}
    if prev is not None:
        effects_out.remove(prev)
    insert_likely(effects_out, new)


def _inertia_read_together(r: dict, in_e: dict, I_new: dict, flagged: list[str], tau: float) -> None:
    """The inertia finding takes the joint reading's roll/pitch (the model's on an axis it does not flag), or, a
    ``likely`` one it flags on no axis, is rejected: the motors' lag read as inertia."""
    note = f"read again together with the motors' lag ({tau:.3f} s) by PX4's rate loop: {_axes_text(r)}"
    if not flagged:
        in_e["verdict"], in_e["accepted"] = "rejected", False
        in_e["verdict_note"] = in_e.get("verdict_note", "") + "; " + note + ": no roll/pitch inertia beside the lag"
        return
    own = dict(in_e["params"])
    if any(abs(float(I_new[k]) - float(own.get(k, I_new[k]))) > 0 for k in I_new):
        in_e.setdefault("own_params", own)
    in_e["params"] = {**own, **I_new}
    in_e["verdict_note"] = in_e.get("verdict_note", "") + "; " + note
