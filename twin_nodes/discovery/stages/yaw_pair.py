"""Stage 10, the yaw pair beside an angular damping, read on roll and pitch (``apply`` on the result).

On the yaw axis a yaw moment and a yaw inertia are one ratio, km / Izz, and an angular damping enters as
k_d / Izz: with both a damping and one yaw-scale effect (``yaw_moment``, or ``inertia`` with Ixx and Iyy at the
model's) accepted, the joint refit gives one of two readings that fit yaw equally,

    (km x s, k_d)  or  (Izz / s, k_d / s),

and the damping it reports is the truth's only if it picked the vehicle's reading (PX4 SIH u017, SIH_Q_MAX x1.3 +
SIH_KDW x2: Izz x0.746 with k_d 0.0385 for km x1.34 with 0.0517; the truth 0.026 and 0.05).  Roll and pitch carry
k_d alone (their inertia and arms are the model's), so they choose.  On a PX4 log by their own damping reading
(:func:`calibrated_choice`: least squares on the roll + pitch modes, the whole flight and both folds): a reading is
taken only where the two readings' dampings differ by more than twice the reading's measured between-flight
scatter (:data:`RP_DAMPING_READING`, by the motor log interval; the reading divided by its measured bias) and the
reading and both folds fall nearer it.
Elsewhere the other reading is taken when it lowers the
roll + pitch equation error over the flight's blocks beyond ``T_CRIT`` (the choice fits nothing on roll/pitch) and
also on the held-out part.  Where roll and pitch choose neither (the other reading not better beyond ``T_CRIT``
and the reported one not either: PX4 SIH y012 at 50 Hz, t -1.6), the confirmed yaw-scale finding is reported
with the other reading as the pair not told apart (``not_told_apart``, with the damping that reading asks for and
roll/pitch rate doublets to separate them), as stage 11 does for a yaw-scale finding alone.  Where the damping
itself is paired with a rotor drag (its hub damping, fitted beside the reported reading), that drag is given at the
other reading too (``damping_partner_with_it``; on a switch the damping's partner moves with it): RotorPy i032,
Izz 0.0200 with k_d 0.005646 and drag 3.5005e-5, reads km x1.5 with 0.008470 and drag 5.251e-5 (truth 5.25e-5),
one whole reading for the scorer to take (``prove.grid_prove``).  The result's
``yaw_pair`` holds the numbers either way (``pair``: whether the pair was reported)."""

from __future__ import annotations

import math

import numpy as np

from twin_nodes.discovery.blocktest import _block_stats
from twin_nodes.discovery.judging import BLOCK_S, T_CRIT, _blocks
from twin_nodes.discovery.residuals import modes, residual_channels
from twin_nodes.vehicle.params import VehicleParams, from_ros_dict

#: the roll and pitch modes of :func:`~twin_nodes.discovery.residuals.modes`
ROLL_PITCH = [1, 2]


def _without(vp: VehicleParams, name: str) -> VehicleParams:
    return vp.replace(effects=tuple(e for e in vp.effects if e[0] != name))


def effect_value(vp: VehicleParams, effect: str, key: str) -> float:
    """``vp``'s value of ``effect``'s parameter ``key``, 0.0 where it has no such effect (a model without an angular
    damping or a rotor drag): the one reading of the model's damping and drag for both yaw stages."""
    return float((vp.effect_dict.get(effect) or {}).get(key, 0.0))


def other_reading(current: VehicleParams, nominal: VehicleParams) -> tuple[VehicleParams, str, str, float] | None:
    """(the vehicle with the yaw pair's other reading, the yaw effect it had, the one it gets, s) where
    ``current`` has an angular damping and exactly one yaw-scale effect; None otherwise."""
    eff = current.effect_dict
    if "angular_damping" not in eff:
        return None
    km0 = float(nominal.rotors.km_m)
    i0 = np.diag(nominal.inertia).astype(float)
    k = float(eff["angular_damping"]["k_nm_s_rad"])
    if "yaw_moment" in eff and "inertia" not in eff:
        s = float(eff["yaw_moment"]["km"]) / km0
        alt = _without(current, "yaw_moment").with_effect("inertia", ixx=i0[0], iyy=i0[1], izz=i0[2] / s)
        return alt.with_effect("angular_damping", k_nm_s_rad=k / s), "yaw_moment", "inertia", s
    if "inertia" in eff and "yaw_moment" not in eff:
        p = eff["inertia"]
        if not (math.isclose(p["ixx"], i0[0], rel_tol=1e-6) and math.isclose(p["iyy"], i0[1], rel_tol=1e-6)):
            return None
        s = float(i0[2] / p["izz"])
        alt = _without(current, "inertia").with_effect("yaw_moment", km=km0 * s)
        return alt.with_effect("angular_damping", k_nm_s_rad=k * s), "inertia", "yaw_moment", s
    return None


def roll_pitch_test(data, nominal: VehicleParams, held_mask: np.ndarray, current: VehicleParams,
                    alt: VehicleParams) -> dict:
    """The roll + pitch equation error of ``alt`` against ``current``: the block test over the flight's
    blocks (t, blocks) and the held-out part's RMS cut."""
    m0 = modes(residual_channels(data, current, nominal), nominal)[0][:, ROLL_PITCH]
    m1 = modes(residual_channels(data, alt, nominal), nominal)[0][:, ROLL_PITCH]
    st = _block_stats(m0, m1, _blocks(data.t, data.valid, BLOCK_S))
    r0 = float(np.sqrt(np.mean(m0[held_mask] ** 2)))
    r1 = float(np.sqrt(np.mean(m1[held_mask] ** 2)))
    return {"t": round(float(st["t"]), 2), "blocks": int(st["n"]),
            "heldout_before": round(r0, 6), "heldout_after": round(r1, 6),
            "heldout_cut": round(1.0 - r1 / r0, 4) if r0 > 0 else 0.0}


#: the roll + pitch damping reading (:func:`roll_pitch_damping`) on PX4 logs, by the motor log interval [s] up to
#: which a row holds: ``(interval, bias, scatter)``, the reading's mean over the truth (``k / k0``) and the RMS of
#: ``k / (bias k0) - 1`` between flights, over the seen PX4 SIH flights whose roll/pitch damping is SIH's
#: (``SIH_KDW`` at 0.025; their other SIH changes in the model, arm-length flights left out), every mission pooled
#: (docs/discovery.md, "Nineteenth session (st19)").  At 4 ms (rate-loop logging) 12 flights on M1-M6 read
#: 0.0172-0.0270 (mean 0.0247); at 20 ms (PX4's default) 19 flights on M1-M4 and M6 read 0.0050-0.0334 (mean
#: 0.0201, 20 % low; true dampings x2 and x4 read 0.70-1.04 of theirs): a flight-level bias the folds share, not
#: noise.  A discovery run does not know the mission; the log interval is what sets the scatter (every 20 ms
#: mission 0.0028-0.0127 RMS about 0.025, every 4 ms one 0.0002-0.0014 but the take-off-and-land M5's 0.0059).
RP_DAMPING_READING = ((0.01, 0.989, 0.106), (math.inf, 0.802, 0.369))
#: the two readings are told apart on roll/pitch only where their roll/pitch dampings differ by more than this many
#: scatters (about 95 % of the readings of one truth fall within)
SCATTER_TIMES = 2.0


def is_px4_log(log_params: dict | None) -> bool:
    """Whether the log carries PX4's rate-loop parameters (``MC_ROLLRATE_P``): the logs the scatter was measured on;
    our own and RotorPy logs keep the block test."""
    return "MC_ROLLRATE_P" in (log_params or {})


def rp_damping_law(motor_dt_s: float) -> tuple[float, float]:
    """(bias, scatter) of the roll + pitch damping reading at this motor log interval (:data:`RP_DAMPING_READING`)."""
    return next((b, f) for dt, b, f in RP_DAMPING_READING if motor_dt_s <= dt + 1e-9)


def roll_pitch_damping(data, nominal: VehicleParams, current: VehicleParams, fit_mask: np.ndarray,
                       t_split2: float) -> list[float]:
    """The angular damping k that roll and pitch alone ask for, ``current`` otherwise as it is: least squares over
    the roll + pitch modes (affine in k, two evaluations), on the whole flight and on both folds' fit parts
    (``[whole, fold 1, fold 2]``; fold 2 fits after ``t_split2``)."""
    k = effect_value(current, "angular_damping", "k_nm_s_rad")
    k0 = effect_value(nominal, "angular_damping", "k_nm_s_rad")
    step = -0.5 * max(k, k0, 1e-9)
    m0 = modes(residual_channels(data, current.with_effect("angular_damping", k_nm_s_rad=k), nominal),
               nominal)[0][:, ROLL_PITCH]
    m1 = modes(residual_channels(data, current.with_effect("angular_damping", k_nm_s_rad=k + step), nominal),
               nominal)[0][:, ROLL_PITCH]
    col = (m1 - m0) / step
    out = []
    for mask in (data.valid, fit_mask & data.valid, data.valid & (data.t >= t_split2)):
        y, c = m0[mask].ravel(), col[mask].ravel()
        cc = float(c @ c)
        out.append(round(k - float(c @ y) / cc, 6) if cc > 0 else math.nan)
    return out


def damping_choice(k_reported: float, k_other: float, reading: list[float], scatter: float, k0: float,
                   bias: float = 1.0) -> dict:
    """Which reading roll and pitch choose, from their own damping ``reading`` ([whole, fold 1, fold 2], divided by
    its measured ``bias``): ``kept`` (the reported reading's damping ``k_reported``) or ``switch`` (``k_other``) only
    where the two differ by more than :data:`SCATTER_TIMES` x ``scatter`` x k0 and the reading and both folds fall
    nearer that side; else ``pair``."""
    need = SCATTER_TIMES * scatter * k0
    gap = abs(k_reported - k_other)
    read = [round(r / bias, 6) for r in reading]
    near = {"kept" if abs(r - k_reported) < abs(r - k_other) else "switch" for r in read if math.isfinite(r)}
    resolved = gap > need and len(near) == 1 and all(math.isfinite(r) for r in read)
    return {"k_reported": round(k_reported, 6), "k_other": round(k_other, 6), "reading": reading, "bias": bias,
            "corrected": read, "gap": round(gap, 6), "needed": round(need, 6), "scatter": scatter,
            "choice": next(iter(near)) if resolved else "pair"}


def calibrated_choice(flight, current: VehicleParams, alt: VehicleParams) -> dict | None:
    """:func:`damping_choice` for a flight on a PX4 log (:func:`is_px4_log`); None elsewhere (the block test
    decides there, as before)."""
    if not is_px4_log(getattr(flight, "log_params", None)):
        return None
    k0 = effect_value(flight.nominal, "angular_damping", "k_nm_s_rad")
    if k0 <= 0:
        return None
    reading = roll_pitch_damping(flight.data, flight.nominal, current, flight.fit_mask, flight.t_split2)
    bias, scatter = rp_damping_law(float(flight.data.motor_dt_s))
    return damping_choice(effect_value(current, "angular_damping", "k_nm_s_rad"),
                          effect_value(alt, "angular_damping", "k_nm_s_rad"), reading, scatter, k0, bias)


def roll_pitch_choice(flight, current: VehicleParams, alt: VehicleParams, test: dict) -> tuple[str, dict | None]:
    """``switch``, ``kept`` or ``pair`` for ``alt`` against ``current``, with the calibrated reading it came from: on a
    PX4 log :func:`calibrated_choice`, elsewhere the block ``test`` (:func:`roll_pitch_test`)."""
    cal = calibrated_choice(flight, current, alt)
    if cal:
        return cal["choice"], cal
    return ("switch" if takes_other(test) else "kept" if keeps_reported(test) else "pair"), None


def choice_evidence(test: dict, cal: dict | None) -> str:
    """The numbers a switch stood on, for the finding's note: the calibrated reading or the block test."""
    if cal:
        return (f"roll/pitch read the damping {cal['corrected'][0]:.4g} (folds {cal['corrected'][1]:.4g} / "
                f"{cal['corrected'][2]:.4g}, bias {cal['bias']} taken out), nearer {cal['k_other']:.4g} than "
                f"{cal['k_reported']:.4g}, a gap beyond {cal['needed']:.4g}")
    return f"t={test['t']:.1f} over {test['blocks']} blocks, held-out {100 * test['heldout_cut']:.1f} %"


def takes_other(test: dict) -> bool:
    """Whether roll/pitch choose the other reading: beyond ``T_CRIT`` over the flight, and lower on the held-out part."""
    return test["t"] > T_CRIT and test["heldout_cut"] > 0.0


def keeps_reported(test: dict) -> bool:
    """Whether roll/pitch choose the reported reading: the other one worse beyond ``T_CRIT`` over the flight."""
    return test["t"] < -T_CRIT


#: what separates the two readings: roll and pitch rates, where the damping acts at its own value and km, Izz
#: do not (on yaw the two readings are one for every input, so yaw sweeps cannot)
SEPARATING = ("rate_doublets", "roll and pitch rates: the damping acts there at its own value, the yaw moment and "
                               "the yaw inertia do not")


def report_pair(result: dict, was: str, becomes: str, alt: VehicleParams,
                nominal: VehicleParams | None = None) -> bool:
    """The confirmed ``was`` entry reported with the other reading as the pair the flight does not tell apart
    (``not_told_apart``: ``becomes`` at its value, ``damping_with_it`` the damping that reading asks for, roll/pitch
    rate doublets as the separating manoeuvre; ``damping_partner_with_it`` the damping's own rotor-drag partner at
    that reading, so the reading is one whole); False where there is no such entry."""
    from twin_nodes.discovery.stages.verdicts import not_told_apart

    entry = next((e for e in result["effects"] if e["name"] == was and e.get("verdict") == "confirmed"), None)
    if entry is None:
        return False
    new = alt.effect_dict
    pair = not_told_apart({"name": was, "alternatives": [{"name": becomes, "params": dict(new[becomes])}]},
                          separating=SEPARATING)
    if pair is None:
        return False
    pair["damping_with_it"] = dict(new["angular_damping"])
    partner = damping_partner_in_reading(result, float(new["angular_damping"]["k_nm_s_rad"]), nominal)
    if partner is not None:
        pair["damping_partner_with_it"] = partner
    pair["yaw_pair"] = dict(result["yaw_pair"]["roll_pitch"])
    entry["not_told_apart"] = pair
    return True


def drag_in_reading(kd: float, kd0: float, k: float, k_new: float, k0: float) -> float:
    """The rotor drag k_d standing in for a damping ``k`` (fitted with the damping at the model's ``k0``) at the
    reading whose damping is ``k_new``: its hub damping ``(k_d - kd0) c`` takes the damping's change ``k - k0``,
    so it scales by ``(k_new - k0) / (k - k0)`` (i032: 3.5005e-5 beside k 0.005646 -> 5.251e-5 beside 0.008470)."""
    return kd0 + (kd - kd0) * (k_new - k0) / (k - k0)


def damping_partner_in_reading(result: dict, k_new: float, nominal: VehicleParams | None) -> dict | None:
    """The confirmed damping's rotor-drag pair partner (``not_told_apart``: its hub damping stands in for the
    damping on yaw) given at the yaw pair's other reading, where that reading asks for the damping ``k_new``:
    ``{"name": "rotor_drag", "params": {"k_d": ...}}``; None where the damping has no such partner."""
    e = next((e for e in result.get("effects") or [] if e["name"] == "angular_damping"
              and e.get("verdict") == "confirmed"), None)
    w = ((e or {}).get("not_told_apart") or {}).get("with") or {}
    if nominal is None or w.get("name") != "rotor_drag" or "k_d" not in (w.get("params") or {}):
        return None
    k = float((e.get("params") or {}).get("k_nm_s_rad", 0.0))
    k0, kd0 = effect_value(nominal, "angular_damping", "k_nm_s_rad"), effect_value(nominal, "rotor_drag", "k_d")
    if abs(k - k0) <= 1e-12 * max(abs(k), 1e-12):
        return None
    return {"name": "rotor_drag", "params": {**w["params"],
                                             "k_d": drag_in_reading(float(w["params"]["k_d"]), kd0, k, k_new, k0)}}


def apply(result: dict, flight) -> VehicleParams | None:
    """Read the yaw pair on roll/pitch where a damping and one yaw-scale effect are confirmed; where roll/pitch
    choose the other reading, the result's entries, ``accepted`` and ``refit_params`` take it (returned; None:
    unchanged)."""
    accepted = list(result.get("accepted") or [])
    if "angular_damping" not in accepted or not result.get("refit_params") or flight.nominal is None:
        return None
    current = from_ros_dict(result["refit_params"])
    other = other_reading(current, flight.nominal)
    if other is None or other[1] not in accepted:
        return None
    alt, was, becomes, s = other
    test = roll_pitch_test(flight.data, flight.nominal, flight.held_mask, current, alt)
    choice, cal = roll_pitch_choice(flight, current, alt, test)
    switched = choice == "switch"
    result["yaw_pair"] = {"reported": was, "other": becomes, "yaw_scale": round(s, 4), "roll_pitch": test,
                          "switched": switched}
    if cal:
        result["yaw_pair"]["roll_pitch_damping"] = cal
    if not switched:
        # neither reading chosen: the flight does not tell them apart, and the finding says so (as stage 11 does)
        result["yaw_pair"]["pair"] = choice == "pair" and report_pair(result, was, becomes, alt, flight.nominal)
        return None
    why = choice_evidence(test, cal)
    note = (f"read on roll/pitch (the yaw axis gives km/Izz and k_d/Izz only): {becomes} with the damping x"
            f"{s if becomes == 'yaw_moment' else 1 / s:.3f} fits the roll+pitch equation error better ({why}) "
            f"against {was}")
    new = alt.effect_dict
    partner = damping_partner_in_reading(result, float(new["angular_damping"]["k_nm_s_rad"]), flight.nominal)
    for e in result["effects"]:
        if e.get("verdict") != "confirmed":
            continue
        if e["name"] == was:
            e["read_as"] = {"was": was, "params": e.get("params"), **{k: e.pop(k) for k in
                                                                    ("held_at_nominal", "equation_axes") if k in e}}
            e["name"], e["params"] = becomes, dict(new[becomes])
            e["verdict_note"] = f"{e.get('verdict_note', '')}; {note}"
        elif e["name"] == "angular_damping":
            e["read_as"] = {"params": e.get("params")}
            e["params"] = dict(new["angular_damping"])
            if partner is not None:     # its rotor-drag partner at the reading taken too
                e["not_told_apart"]["with"] = partner
            e["verdict_note"] = f"{e.get('verdict_note', '')}; {note}"
    result["accepted"] = [becomes if n == was else n for n in accepted]
    alt = damping_at_model(result, alt, flight.nominal)
    result["refit_params"] = alt.to_ros_dict()
    return alt


def damping_at_model(result: dict, alt: VehicleParams, nominal: VehicleParams) -> VehicleParams:
    """``alt`` with its damping put back at the model's where the other reading leaves it within the nominal
    refit's floor (``selection.REFIT_FLOOR``) of it: the damping was accepted for the yaw-scale change's share of
    the yaw damping (Izz x1.3 reads as k_d/Izz x0.77), and with the right reading no damping change is left (PX4
    SIH b018: SIH_IZZ x1.3 beside SIH_KDV, k_d 0.0255 for the model's 0.025).  Its entry is then rejected and it
    leaves ``accepted``; else ``alt`` as it is."""
    from twin_nodes.discovery.stages.selection import REFIT_FLOOR

    k0 = effect_value(nominal, "angular_damping", "k_nm_s_rad")
    k = alt.effect_dict["angular_damping"]["k_nm_s_rad"]
    if not k0 or abs(k / k0 - 1.0) > REFIT_FLOOR:
        return alt
    for e in result["effects"]:
        if e["name"] == "angular_damping" and e.get("verdict") == "confirmed":
            e["verdict"] = "rejected"
            e["verdict_note"] = (f"{e.get('verdict_note', '')}; with the other reading the damping is x{k / k0:.3f} "
                                 f"of the model's, within its {100 * REFIT_FLOOR:.0f} % floor: no damping change")
    result["accepted"] = [n for n in result["accepted"] if n != "angular_damping"]
    return alt.with_effect("angular_damping", k_nm_s_rad=float(k0))


__all__ = ["ROLL_PITCH", "RP_DAMPING_READING", "SCATTER_TIMES", "SEPARATING", "apply", "calibrated_choice",
           "choice_evidence", "damping_at_model", "damping_choice", "damping_partner_in_reading", "drag_in_reading",
           "is_px4_log", "keeps_reported", "other_reading", "report_pair", "roll_pitch_choice", "roll_pitch_damping",
           "roll_pitch_test", "rp_damping_law", "takes_other"]
