"""Stage 11, a yaw moment or a yaw inertia read without the equation error's unit bias (``apply`` on the result).

The yaw row of the equation error is ``r = Izz alpha - km D - o`` (D: the motors' thrust differential, o: the yaw
torques no yaw-scale parameter scales, such as the rotor drag's hub damping or a CoM offset's H-force moment).
A yaw moment ``km x s`` and an inertia ``Izz / s`` give the same ratio km / Izz, and where o is nil their residuals
are exactly ``r_km = s r_Izz``: in torque units the reading with the smaller scale always wins, whatever the
flight (a 1.5x yaw moment loses to Izz x0.667 on every flight: RotorPy k015, g019, g029, g033).  Read per unit
Izz (``r / Izz``) the bias only changes side (a larger Izz shrinks the model's moment; branch ``yaw9``: it
confirmed Izz x2.3 on shared real logs).  Each reading's yaw row is therefore divided by the geometric mean of its
two scales, ``sqrt(Izz / Izz_n * km / km_n)``: the two readings then tie exactly where o is nil (the flight cannot
tell them apart), and differ by ``o (1/sqrt(s) - sqrt(s))`` where it is not, which is what the flight shows of the
truth; a common scale of both (an errors-in-variables line through the origin) does not move the comparison.

Where a confirmed or `likely` effect is one reading (an inertia whose Izz moved with no yaw moment beside it, or a yaw moment
with Izz at the model's), the other is built, its yaw-scale parameter and the other positive parameters of the
refitted vehicle refitted jointly on fold 1's fit part, and the two compared by the block test over the flight's
blocks (every mode, the yaw mode so scaled):

- the other reading better beyond ``T_CRIT`` and on the held-out part: it is taken (entries, ``accepted``,
  ``refit_params``; the entry keeps what it was under ``read_as``);
- the reported one better beyond ``T_CRIT``: kept, told apart;
- neither: the finding is reported with the other reading as the pair not told apart (``not_told_apart``, yaw
  sweeps: turns in place at several rates, where the damping's share of the yaw torque changes with the rate).

An accepted angular damping beside them is stage 10's (``stages.yaw_pair``): not read here."""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from twin_nodes.discovery.blocktest import _block_stats
from twin_nodes.discovery.judging import BLOCK_S, T_CRIT, _blocks
from twin_nodes.discovery.candidates import NOT_FITTED
from twin_nodes.discovery.residuals import modes, residual_channels
from twin_nodes.vehicle.params import VehicleParams, from_ros_dict

#: the yaw mode of :func:`~twin_nodes.discovery.residuals.modes`
YAW = 3
#: an inertia's Izz off the model's by more than this is a yaw-scale reading (the inertia candidate's floor)
MOVED = 0.03
#: effects whose positive parameters are refitted with the other reading (they share the yaw row or are fitted
#: beside it); an output-error effect keeps its value as in the joint refit
_HELD = {"actuator_delay", "motor_time_constant", "com_offset", "wind"}


def scales(vp: VehicleParams, nominal: VehicleParams) -> tuple[float, float]:
    """(Izz / Izz_n, km / km_n) of ``vp``."""
    eff = vp.effect_dict
    izz = float(eff["inertia"]["izz"]) if "inertia" in eff else float(nominal.inertia[2, 2])
    km = float(eff["yaw_moment"]["km"]) if "yaw_moment" in eff else float(nominal.rotors.km_m)
    return izz / float(nominal.inertia[2, 2]), km / float(nominal.rotors.km_m)


def other_reading(current: VehicleParams, nominal: VehicleParams) -> tuple[VehicleParams, str, str, float] | None:
    """(the vehicle with the other reading, the yaw-scale effect it had, the one it gets, s = km x / Izz /) where
    ``current`` carries exactly one yaw-scale reading; None otherwise."""
    eff = current.effect_dict
    i0 = np.diag(nominal.inertia).astype(float)
    km0 = float(nominal.rotors.km_m)
    p, q = scales(current, nominal)
    rest = current.replace(effects=tuple(e for e in current.effects if e[0] not in ("inertia", "yaw_moment")))
    ixx, iyy = (float(eff["inertia"][k]) for k in ("ixx", "iyy")) if "inertia" in eff else (i0[0], i0[1])
    # roll/pitch within the inertia candidate's floor of the model's: no inertia finding of their own is left
    roll_pitch_moved = abs(ixx / i0[0] - 1.0) > MOVED or abs(iyy / i0[1] - 1.0) > MOVED
    if "inertia" in eff and "yaw_moment" not in eff and abs(p - 1.0) > MOVED:
        s = 1.0 / p
        alt = rest.with_effect("inertia", ixx=ixx, iyy=iyy, izz=i0[2]) if roll_pitch_moved else rest
        return alt.with_effect("yaw_moment", km=km0 * s), "inertia", "yaw_moment", s
    if "yaw_moment" in eff and abs(p - 1.0) <= 1e-6:
        s = q
        return rest.with_effect("inertia", ixx=ixx, iyy=iyy, izz=i0[2] / s), "yaw_moment", "inertia", s
    return None


def _free(vp: VehicleParams, becomes: str, found: list[str]) -> list[tuple[str, str]]:
    """The (effect, parameter) pairs refitted with a reading: its own yaw-scale parameter and the positive
    parameters of the effects found beside it (``found``; the nominal's own laws, the inertia's roll/pitch axes,
    a drag law's form and what the library never fits, ``candidates.NOT_FITTED``, held: RotorPy a016, a sag's
    v_ref freed here beside a thrust coefficient read 18.7 V for 16.8 with kt 1.08 for 0.87)."""
    out = []
    for name, params in vp.effects:
        if name in _HELD or name != becomes and name not in found:
            continue
        for k, v in params:
            if name == "inertia" and k != "izz" or name == "inertia" and becomes != "inertia":
                continue
            if name == "yaw_moment" and becomes != "yaw_moment":
                continue
            if v > 0 and k != "norm" and (name, k) not in NOT_FITTED:
                out.append((name, k))
    return out


def refit(vp: VehicleParams, becomes: str, found: list[str], data, nominal: VehicleParams,
          fit_mask: np.ndarray) -> VehicleParams:
    """``vp`` with :func:`_free`'s parameters refitted jointly on the equation error's fit part (0.2x-5x)."""
    free = _free(vp, becomes, found)
    if not free:
        return vp
    eff = vp.effect_dict
    x0 = np.array([eff[n][k] for n, k in free])

    def build(z):
        out = vp
        for (n, k), v in zip(free, z * x0):
            out = out.with_effect(n, **{**out.effect_dict[n], k: float(v)})
        return out

    def resid(z):
        return residual_channels(data, build(z), nominal)[fit_mask].ravel()

    sol = least_squares(resid, np.ones(len(free)), bounds=(0.2, 5.0), diff_step=1e-3, max_nfev=60)
    return build(sol.x)


def at_model(alt: VehicleParams, becomes: str, nominal: VehicleParams) -> tuple[VehicleParams, bool]:
    """``alt`` with its refitted yaw-scale parameter put back at the model's where it is within ``MOVED`` of it (the
    other reading asks for no yaw-scale change at all: RotorPy g030's false Izz x1.23 refits to km x0.999); True
    where it was."""
    eff = alt.effect_dict
    p, q = scales(alt, nominal)
    if abs((q if becomes == "yaw_moment" else p) - 1.0) > MOVED:
        return alt, False
    if becomes == "yaw_moment":
        return alt.replace(effects=tuple(e for e in alt.effects if e[0] != "yaw_moment")), True
    i0 = np.diag(nominal.inertia).astype(float)
    if abs(eff["inertia"]["ixx"] / i0[0] - 1.0) > MOVED or abs(eff["inertia"]["iyy"] / i0[1] - 1.0) > MOVED:
        return alt.with_effect("inertia", **{**eff["inertia"], "izz": float(i0[2])}), True
    return alt.replace(effects=tuple(e for e in alt.effects if e[0] != "inertia")), True


def scaled_modes(data, vp: VehicleParams, nominal: VehicleParams) -> np.ndarray:
    """The equation error's modes of ``vp`` with the yaw mode divided by sqrt(Izz/Izz_n km/km_n)."""
    m = modes(residual_channels(data, vp, nominal), nominal)[0]
    p, q = scales(vp, nominal)
    m[:, YAW] /= math.sqrt(p * q)
    return m


def compare(data, nominal: VehicleParams, held_mask: np.ndarray, current: VehicleParams, alt: VehicleParams) -> dict:
    """The block test of ``alt`` against ``current`` over the flight's blocks on :func:`scaled_modes` (``t_alt``:
    alt better; ``t_current``: current better) and the held-out part's RMS cut (alt over current)."""
    m0, m1 = scaled_modes(data, current, nominal), scaled_modes(data, alt, nominal)
    blocks = _blocks(data.t, data.valid, BLOCK_S)
    r0 = float(np.sqrt(np.mean(m0[held_mask] ** 2)))
    r1 = float(np.sqrt(np.mean(m1[held_mask] ** 2)))
    y0 = float(np.sqrt(np.mean(m0[data.valid, YAW] ** 2)))
    y1 = float(np.sqrt(np.mean(m1[data.valid, YAW] ** 2)))
    # one residual to rounding (no other yaw torque, nothing else moved): no block test on rounding noise
    same = float(np.max(np.abs(m1[data.valid] - m0[data.valid]))) <= 1e-9 * max(y0, y1, 1e-300)
    return {"t_alt": 0.0 if same else round(float(_block_stats(m0, m1, blocks)["t"]), 2),
            "t_current": 0.0 if same else round(float(_block_stats(m1, m0, blocks)["t"]), 2),
            "heldout_cut": round(1.0 - r1 / r0, 4) if r0 > 0 else 0.0,
            "yaw_rms_scaled": [round(y0, 7), round(y1, 7)]}


def choose(test: dict) -> str:
    """``switch`` (the other reading), ``kept`` (told apart) or ``pair`` (not told apart)."""
    if test["t_alt"] > T_CRIT and test["heldout_cut"] > 0.0:
        return "switch"
    if test["t_current"] > T_CRIT:
        return "kept"
    return "pair"


def _pair(entry: dict, becomes: str, params: dict, test: dict) -> None:
    """The finding reported with the other reading as the pair the flight does not tell apart."""
    from twin_nodes.discovery.stages.verdicts import not_told_apart

    pair = not_told_apart({"name": entry["name"], "alternatives": [{"name": becomes, "params": params}]})
    if pair is not None:
        pair["yaw_scale"] = test
        entry["not_told_apart"] = pair


def _switch(result: dict, entry: dict, was: str, becomes: str, new: dict, note: str) -> None:
    """The entry takes the other reading; where that reading is the model's own value (``becomes`` not in
    ``new``), an inertia keeps its roll/pitch axes and anything else is rejected."""
    entry["read_as"] = {"was": was, "params": entry.get("params"),
                        **{k: entry.pop(k) for k in ("held_at_nominal", "equation_axes") if k in entry}}
    entry["verdict_note"] = f"{entry.get('verdict_note', '')}; {note}"
    if becomes not in new:
        if was == "inertia" and "inertia" in new:
            entry["params"] = dict(new["inertia"])
        else:
            entry["verdict"] = "rejected"
        return
    entry["name"], entry["params"] = becomes, dict(new[becomes])
    if was == "inertia" and "inertia" in new:        # the roll/pitch axes stay an inertia finding of their own
        result["effects"].append({**{k: v for k, v in entry["read_as"].items() if k != "was"}, "name": "inertia",
                                  "params": dict(new["inertia"]), "verdict": entry["verdict"],
                                  "verdict_note": "its roll/pitch axes; Izz read as a yaw moment (stage 11)"})


def _rename(names: list, was: str, becomes: str, new: dict) -> list:
    """``names`` with ``was`` replaced by what the other reading keeps of it (``becomes``, the inertia's roll/pitch
    axes, or nothing)."""
    keep = [n for n in (becomes, "inertia" if was == "inertia" else None) if n and n in new]
    out = [n for n in names if n != was]
    return out + [n for n in keep if n not in out] if was in names else out


def apply(result: dict, flight) -> VehicleParams | None:
    """Read a confirmed or ``likely`` yaw-scale finding against its other reading (module doc); where the other is
    taken, the result's entries, ``accepted``, ``likely`` and ``refit_params`` take it (returned; None: unchanged)."""
    accepted, likely = list(result.get("accepted") or []), list(result.get("likely") or [])
    if not result.get("refit_params") or flight.nominal is None or "angular_damping" in accepted:
        return None
    current = from_ros_dict(result["refit_params"])
    other = other_reading(current, flight.nominal)
    if other is None or other[1] not in accepted + likely:
        return None
    alt, was, becomes, s = other
    entry = next((e for e in result["effects"] if e["name"] == was and e.get("verdict") in ("confirmed", "likely")),
                 None)
    if entry is None:
        return None
    alt, gone = at_model(refit(alt, becomes, accepted + likely, flight.data, flight.nominal, flight.fit_mask), becomes,
                         flight.nominal)
    test = compare(flight.data, flight.nominal, flight.held_mask, current, alt)
    choice = choose(test)
    new = alt.effect_dict
    result["yaw_scale"] = {"reported": was, "other": becomes, "yaw_scale": round(s, 4), "test": test,
                           "choice": choice, "other_params": {k: dict(v) for k, v in new.items()},
                           "other_at_model": gone}
    if choice == "pair" and not gone:
        _pair(entry, becomes, dict(new[becomes]), test)
    if choice != "switch":
        return None
    what = f"{becomes} at the model's value" if gone else becomes
    note = (f"read per yaw scale (the yaw axis gives km/Izz only; each reading's yaw error over sqrt(Izz km) of "
            f"the model's): {what} lowers the equation error (t={test['t_alt']:.1f}, held-out "
            f"{100 * test['heldout_cut']:.1f} %) against {was}")
    _switch(result, entry, was, becomes, new, note)
    for e in result["effects"]:
        if e is not entry and e.get("verdict") in ("confirmed", "likely") and e["name"] in new \
                and e["name"] not in ("inertia", becomes):
            e.setdefault("read_as", {"params": e.get("params")})
            e["params"] = dict(new[e["name"]])
    result["accepted"] = _rename(accepted, was, becomes, new)
    if "likely" in result:
        result["likely"] = _rename(likely, was, becomes, new)
    result["refit_params"] = alt.to_ros_dict()
    return alt


__all__ = ["MOVED", "YAW", "apply", "at_model", "choose", "compare", "other_reading", "refit", "scaled_modes", "scales"]
