"""Stage 12, an angular damping confirmed alone, read against what else damps the yaw (``apply`` on the result).

An angular damping (a moment ``-k w`` on every body rate) found on a flight whose damping evidence is the yaw axis
has two stand-ins there that act on nothing else the flight shows:

- **A rotor drag's hub damping.**  Each hub moves through the air when the vehicle yaws (``w x r_i``), so a
  rotor drag damps the yaw by ``k_d sum|omega_i| (x_i^2 + y_i^2)`` (``effects._k_rotor_drag``; RotorPy's rotor
  drag acts on the same hub airspeed).  Where the flight has no horizontal airspeed for the drag's force to act on
  (``not_excited`` names ``rotor_drag (force)``: 90th-percentile speed <= 0.5 m/s), the drag's force columns carry
  the velocity estimate's noise only, and what is left of a rotor drag is that yaw damping: on a hover with yaw
  it and the angular damping fit the yaw mode alike (RotorPy e002, Crazyflie, k_d x2: damping 1.3605e-5 N m s/rad
  = 1.028e-6 x 7156 rad/s x 1.849e-3 m^2, the drag's k_d change to 0.1 %; the nominal rotor drag refitted on every
  channel read k_d x1.45 at a held-out t of -1.0, pulled down by force channels whose horizontal "speed" is the
  estimate's noise, p50 0.03 m/s).  The rotor drag's k_d is refitted on the yaw mode alone with the damping back
  at the model's.
- **A yaw moment and a yaw inertia changed together** (PX4 SIH f017, b017: SIH_Q_MAX and SIH_IZZ both x1.3).  On
  the yaw row ``Izz alpha = km D - k w``, the triple is fixed up to one scale: ``(km s, Izz s, k)`` is
  ``(km, Izz, k / s)``.  Where the model has a damping ``k0`` and the damping found is ``k``, the other reading is
  ``km x s`` and ``Izz x s`` with ``s = k0 / k`` and the damping at ``k0``: exactly the same yaw residual (times s).
  A damping moved alone was confirmed at ``k0 / 1.29`` there (0.0194 for 0.025), and neither flown effect was named.

Roll and pitch choose (the damping acts there at its own value; the hub damping, a yaw moment and a yaw inertia do
not).  On a PX4 log they choose by their own damping reading (``yaw_pair.calibrated_choice``): the other reading is
taken, or the damping kept, only where the two readings' roll/pitch dampings differ by more than twice that
reading's measured between-flight scatter (``yaw_pair.RP_DAMPING_READING``: 37 % of the model's damping at 20 ms,
10.6 % at 4 ms; the reading divided by its measured bias, x0.80 at 20 ms) and the reading and both folds fall nearer
that side; a block t over the flight's blocks is not a calibrated test there (the reading of one truth scatters 35 %
between flights, a bias the blocks share: PX4 SIH sb016 and l016, one truth, read t -3.3 and +4.1).  On other logs
the block test decides: the other reading is taken where it lowers the roll + pitch equation error beyond ``T_CRIT``
over the flight's blocks and on the held-out part, the damping is kept (told apart) where the other reading is worse
beyond ``T_CRIT``.  Otherwise the damping is reported with the other reading as the pair the flight does not tell
apart (``not_told_apart``; the yaw pair's second member under ``also``), with the manoeuvre that separates them:
fast legs for the rotor drag (its force grows with the airspeed, a damping has none), roll/pitch rate doublets for
the yaw pair.  The result's ``damping_pair`` holds the numbers either way.  A damping beside a confirmed yaw moment
or yaw inertia is stage 10's (``stages.yaw_pair``); one that already names a rival is left as it is, unless that
rival is a yaw moment or a yaw inertia alone (:data:`PART_OF_YAW_READING`: one member of the yaw pair's reading,
which is read whole in its place)."""

from __future__ import annotations

import numpy as np

from twin_nodes.discovery.residuals import modes, residual_channels
from twin_nodes.discovery.stages.yaw_pair import SEPARATING as ROLL_PITCH_RATES
from twin_nodes.discovery.stages.yaw_pair import choice_evidence, effect_value, roll_pitch_choice, roll_pitch_test
from twin_nodes.vehicle.params import VehicleParams, from_ros_dict

#: the yaw mode of :func:`~twin_nodes.discovery.residuals.modes`
YAW = 3
#: ``not_excited``'s entry for a flight without horizontal airspeed (``stages.candidates.not_excited``)
NO_DRAG_FORCE = "rotor_drag (force)"
#: what separates a damping from a rotor drag's hub damping
FAST_LEGS = ("fast_legs", "legs at speed: a rotor drag's H-force opposes the airspeed at each hub, an angular "
                          "damping acts on the body rates alone")
#: the yaw pair's other reading moves both by more than this (else no yaw-scale change is left to read)
MIN_SCALE_CHANGE = 0.03
#: a rival already named beside the damping that is one member of the yaw pair's other reading: round 1's
#: alternatives can list a yaw moment (or inertia) fitted alone on the same yaw residual (PX4 SIH p019, SIH_Q_MAX and
#: SIH_IZZ both x1.3, M4: the damping 0.01936 beside a yaw moment km 0.0220 alone, a reading 15 % off the truth that
#: leaves the inertia out); the whole reading (km and Izz both x k0/k) is read in its place, the old rival kept
#: where roll/pitch tell the damping apart
PART_OF_YAW_READING = ("yaw_moment", "inertia")


def _damping(vp: VehicleParams) -> float:
    return effect_value(vp, "angular_damping", "k_nm_s_rad")


def _at_model_damping(vp: VehicleParams, nominal: VehicleParams) -> VehicleParams:
    """``vp`` with its angular damping put back at the model's (removed where the model has none)."""
    k0 = _damping(nominal)
    if k0 > 0:
        return vp.with_effect("angular_damping", k_nm_s_rad=k0)
    return vp.replace(effects=tuple(e for e in vp.effects if e[0] != "angular_damping"))


def hub_reading(data, nominal: VehicleParams, fit_mask: np.ndarray, current: VehicleParams) -> VehicleParams:
    """``current`` with the damping at the model's and the rotor drag's k_d refitted on the yaw mode alone (least
    squares over the fit part; the yaw mode is affine in k_d)."""
    base = _at_model_damping(current, nominal)
    kd_now = float((base.effect_dict.get("rotor_drag") or {}).get("k_d", 0.0))
    step = max(kd_now, 1e-9)
    rows = fit_mask & data.valid
    y0 = modes(residual_channels(data, base.with_effect("rotor_drag", k_d=kd_now), nominal), nominal)[0][rows, YAW]
    y1 = modes(residual_channels(data, base.with_effect("rotor_drag", k_d=kd_now + step), nominal),
               nominal)[0][rows, YAW]
    col = (y1 - y0) / step
    dk = -float(col @ y0) / float(col @ col) if float(col @ col) > 0 else 0.0
    return base.with_effect("rotor_drag", k_d=max(kd_now + dk, 0.0))


def yaw_scale_reading(current: VehicleParams, nominal: VehicleParams) -> tuple[VehicleParams, float] | None:
    """(``current`` with the damping at the model's k0 and the yaw moment and Izz both x s, s = k0 / k) where the
    model has a damping and ``current`` has neither a yaw moment nor an inertia of its own; None otherwise."""
    k0, k = _damping(nominal), _damping(current)
    eff = current.effect_dict
    if k0 <= 0 or k <= 0 or "yaw_moment" in eff or "inertia" in eff:
        return None
    s = k0 / k
    if abs(s - 1.0) <= MIN_SCALE_CHANGE:
        return None
    i0 = np.diag(nominal.inertia).astype(float)
    alt = current.with_effect("angular_damping", k_nm_s_rad=k0)
    alt = alt.with_effect("yaw_moment", km=float(nominal.rotors.km_m) * s)
    return alt.with_effect("inertia", ixx=float(i0[0]), iyy=float(i0[1]), izz=float(i0[2]) * s), s


def _entry(result: dict) -> dict | None:
    """The damping's confirmed or likely entry, where it stands alone on the yaw axis and names no rival but a
    yaw-scale one (:data:`PART_OF_YAW_READING`)."""
    names = set(result.get("accepted") or []) | set(result.get("likely") or [])
    if "angular_damping" not in names or names & {"yaw_moment", "inertia"} or result.get("yaw_pair"):
        return None
    e = next((e for e in result.get("effects") or [] if e["name"] == "angular_damping"
              and e.get("verdict") in ("confirmed", "likely")), None)
    if e is None or _rival(e) not in (None, *PART_OF_YAW_READING) or e.get("heldout_channel") != "yaw":
        return None
    return e


def _rival(entry: dict) -> str | None:
    """The name of the rival the entry already names (``not_told_apart``), None where it names none."""
    return ((entry.get("not_told_apart") or {}).get("with") or {}).get("name")


def _readings(result: dict, flight, current: VehicleParams) -> list[tuple[str, VehicleParams, tuple[str, str]]]:
    """The other readings this flight allows: (kind, vehicle, separating manoeuvre)."""
    out = []
    if any(NO_DRAG_FORCE in (x.get("effects") or []) for x in result.get("not_excited") or []) \
            and flight.nominal.rotors.count > 0:
        out.append(("rotor_drag", hub_reading(flight.data, flight.nominal, flight.fit_mask, current), FAST_LEGS))
    ys = yaw_scale_reading(current, flight.nominal)
    if ys is not None:
        out.append(("yaw_moment+inertia", ys[0], ROLL_PITCH_RATES))
    return out


def _members(kind: str, alt: VehicleParams) -> list[dict]:
    new = alt.effect_dict
    return [{"name": n, "params": dict(new[n])} for n in kind.split("+")]


def _pair(entry: dict, kind: str, alt: VehicleParams, separating: tuple[str, str], test: dict) -> bool:
    from twin_nodes.discovery.stages.verdicts import not_told_apart

    members = _members(kind, alt)
    pair = not_told_apart({"name": "angular_damping", "alternatives": members[:1]}, separating=separating)
    if pair is None:
        return False
    if len(members) > 1:
        pair["also"] = members[1:]
    pair["roll_pitch"] = test
    if entry.get("not_told_apart"):       # one member of this reading, fitted alone (PART_OF_YAW_READING)
        pair["replaces"] = entry["not_told_apart"]["with"]
    entry["not_told_apart"] = pair
    return True


def _switch(result: dict, entry: dict, kind: str, alt: VehicleParams, test: dict) -> None:
    """The damping's entry takes the other reading (the first member; a second one is added beside it)."""
    members = _members(kind, alt)
    why = choice_evidence(test, test.get("roll_pitch_damping"))
    note = (f"read on roll/pitch (the yaw axis alone does not tell it from {kind.replace('+', ' + ')}): "
            f"{kind.replace('+', ' + ')} with the damping at the model's fits the roll+pitch equation error "
            f"better ({why})")
    entry["read_as"] = {"was": "angular_damping", "params": entry.get("params")}
    entry.pop("not_told_apart", None)     # a yaw-scale rival fitted alone: the reading taken holds it whole
    entry["name"], entry["params"] = members[0]["name"], members[0]["params"]
    entry["verdict_note"] = f"{entry.get('verdict_note', '')}; {note}"
    for m in members[1:]:
        result["effects"].append({**{k: v for k, v in entry.items() if k not in ("name", "params", "read_as")},
                                  **m, "verdict_note": f"beside {members[0]['name']}: {note}"})
    for key in ("accepted", "likely"):
        if "angular_damping" in (result.get(key) or []):
            rest = [n for n in result[key] if n != "angular_damping"]
            result[key] = rest + [m["name"] for m in members if m["name"] not in rest]
    result["refit_params"] = alt.to_ros_dict()


def apply(result: dict, flight) -> VehicleParams | None:
    """Read a damping confirmed (or likely) alone on the yaw axis against its other readings (module doc); where
    roll/pitch take one, the result's entries, ``accepted`` and ``refit_params`` take it (returned; None:
    unchanged)."""
    entry = _entry(result)
    if entry is None or not result.get("refit_params") or flight.nominal is None:
        return None
    current = from_ros_dict(result["refit_params"])
    notes = []
    for kind, alt, separating in _readings(result, flight, current):
        test = roll_pitch_test(flight.data, flight.nominal, flight.held_mask, current, alt)
        choice, cal = roll_pitch_choice(flight, current, alt, test)
        notes.append({"other": kind, "params": {m["name"]: m["params"] for m in _members(kind, alt)},
                      "roll_pitch": test, "choice": choice, **({"roll_pitch_damping": cal} if cal else {})})
        if choice == "switch":
            result["damping_pair"] = notes
            _switch(result, entry, kind, alt, {**test, **({"roll_pitch_damping": cal} if cal else {})})
            return alt
        if choice == "pair" and _pair(entry, kind, alt, separating,
                                      {**test, **({"roll_pitch_damping": cal} if cal else {})}):
            break
    if notes:
        result["damping_pair"] = notes
    return None


__all__ = ["FAST_LEGS", "MIN_SCALE_CHANGE", "NO_DRAG_FORCE", "PART_OF_YAW_READING", "apply", "hub_reading",
           "yaw_scale_reading"]
