"""``rotortwin prove --source px4sih``: PX4 SIH flights (real PX4 firmware) with one SIH parameter changed.

The flights are not ours and are not in the repository (no licence to redistribute the logs): they live in
``../shared/flightlogs/sitl_effects/eNN/`` (``flight.ulg`` with every SIH_* parameter scrubbed, the truth in
``truth.json``), plus the two no-effect baselines ``../shared/flightlogs/sitl/*.ulg``.  How to fly them again
(PX4 commit, SIH parameter changes, missions, launch commands) is in ``missions/sih_effects/manifest.yaml``.
Flights of our own making (``launch_scripts/fly_sih.sh``, same ``eNN/{flight.ulg,truth.json}`` layout) are read
from any further folder given as ``sih_dirs`` (``rotortwin prove --source px4sih --sih-dir DIR``).

The truth is mapped from the SIH parameter that changed (``truth.json``'s ``sih_changes``) onto our effect
vocabulary (:data:`twin_nodes.physics.effects.EFFECTS`) with ``params/px4_sih_quadx.yaml`` as the nominal:

==============  =====================================================================================
SIH_MASS        ``mass``: mass = SIH_MASS
SIH_T_MAX       ``thrust_coefficient``: kt_scale = T_MAX / 5.0 (SIH keeps Q_MAX, so km = Q_MAX/T_MAX moves too)
SIH_Q_MAX       ``yaw_moment``: km = Q_MAX / T_MAX
SIH_T_TAU       ``motor_time_constant``: tau_up = tau_down = T_TAU
SIH_IXX/IYY/IZZ ``inertia``: ixx, iyy, izz (an unchanged axis keeps the nominal value and is scored too)
SIH_KDV         ``linear_drag``: k_n_s_m = KDV (world-frame isotropic drag; truth.json calls it body_drag, linear)
SIH_KDW         ``angular_damping``: k_nm_s_rad = KDW
SIH_L_ROLL/PITCH ``inertia`` equivalent: roll (pitch) moment per command scales with L, so ixx_eq = ixx L0/L
                (with SIH_IXX/IYY changed too: one inertia, per axis IXX L0/L_ROLL, IYY L0/L_PITCH)
==============  =====================================================================================
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

from twin_nodes.base.errors import TwinError
from twin_nodes.prove.scoring import DragContext, Truth, effect_class, map_jobs, score, score_flight, write_result
from twin_nodes.twin.simflight import Hidden
from twin_nodes.vehicle.params import VehicleParams, load_params

REPO = Path(__file__).resolve().parents[2]
NOMINAL = REPO / "params" / "px4_sih_quadx.yaml"
MANIFEST = REPO / "missions" / "sih_effects" / "manifest.yaml"
#: the flights a CI-size run takes: one per class that differs most, plus a no-effect flight
CI_FLIGHTS = ("e01", "e06", "e07")


def shared_dir(given: str | Path | None = None) -> Path:
    """``../shared`` beside the repository (or ``given``, or ``$ROTORTWIN_SHARED``)."""
    p = Path(given or os.environ.get("ROTORTWIN_SHARED") or REPO.parent / "shared")
    return p


#: the SIH parameters that change the body-rate dynamics per axis: one ``inertia`` truth together
ARM_PARAMS = frozenset({"SIH_L_ROLL", "SIH_L_PITCH"})
INERTIA_GROUP = frozenset({"SIH_IXX", "SIH_IYY", "SIH_IZZ"}) | ARM_PARAMS


def inertia_equivalent(changes: dict[str, float], nominal: VehicleParams) -> dict[str, float]:
    """The per-axis inertia our model (arms fixed at the nominal's) needs to turn as SIH turns with
    ``changes`` (SIH_IXX/IYY/IZZ and SIH_L_ROLL/L_PITCH, the values flown).

    SIH (``simulator_sih/sih.cpp``): ``M = (L_ROLL T_MAX (-u0+u1+u2-u3), L_PITCH T_MAX (u0-u1+u2-u3),
    Q_MAX (u0+u1-u2-u3))`` and ``w_dot = I^-1 (M - KDW w - w x I w)``; PX4's mixer allocates with the
    airframe's own rotor positions, which do not move.  An arm length scales that axis's moment per
    command alone, so ``w_dot_x = (L_ROLL / L0) M0_x / IXX``: the axis turns as with an inertia
    ``IXX L0 / L_ROLL`` (pitch likewise with IYY and L_PITCH; yaw untouched).  An inertia and an arm
    change on the same axis combine in one: ``I_axis L0 / L_axis``.  Exact for the commanded
    moment; the damping and gyroscopic terms are then read at ``L0 / L`` of their size (KDW 0.025:
    < 0.5 % of the moment in these flights)."""
    inertia = nominal.inertia
    r = nominal.rotors
    arm_roll, arm_pitch = abs(float(r.y_flu_m[0])), abs(float(r.x_flu_m[0]))
    return {"ixx": float(changes.get("SIH_IXX", inertia[0, 0])) * arm_roll / float(changes.get("SIH_L_ROLL", arm_roll)),
            "iyy": float(changes.get("SIH_IYY", inertia[1, 1])) * arm_pitch / float(changes.get("SIH_L_PITCH", arm_pitch)),
            "izz": float(changes.get("SIH_IZZ", inertia[2, 2]))}


def map_truth(truth: dict, nominal: VehicleParams) -> Truth:
    """``truth.json`` of one SIH flight -> the truth in our effect vocabulary."""
    changes = {k: float(v[1]) for k, v in (truth.get("sih_changes") or {}).items()}
    text = ", ".join(f"{k} {float(v[0]):g}->{float(v[1]):g}" for k, v in (truth.get("sih_changes") or {}).items())
    if not changes:
        return Truth(Hidden("none", {}), "no SIH change")
    t_max0 = nominal.rotors.thrust_max_n
    names = set(changes)
    if names == {"SIH_MASS"}:
        return Truth(Hidden("mass", {"mass": changes["SIH_MASS"]}), text)
    if names == {"SIH_T_MAX"}:
        return Truth(Hidden("thrust_coefficient", {"kt_scale": changes["SIH_T_MAX"] / t_max0}), text)
    if names == {"SIH_Q_MAX"}:
        return Truth(Hidden("yaw_moment", {"km": changes["SIH_Q_MAX"] / t_max0}), text)
    if names == {"SIH_T_TAU"}:
        tau = changes["SIH_T_TAU"]
        return Truth(Hidden("motor_time_constant", {"tau_up": tau, "tau_down": tau}), text)
    if names and names <= INERTIA_GROUP:
        eq = inertia_equivalent(changes, nominal)
        return Truth(Hidden("inertia", eq), text + (" (inertia equivalent)" if names & ARM_PARAMS else ""))
    if names == {"SIH_KDV"}:
        return Truth(Hidden("linear_drag", {"k_n_s_m": changes["SIH_KDV"]}), text)
    if names == {"SIH_KDW"}:
        return Truth(Hidden("angular_damping", {"k_nm_s_rad": changes["SIH_KDW"]}), text)
    # the patched SIH (missions/sih_effects/px4_sih_weak_motor_com.patch): one motor, PX4 order; a CoM in FRD
    if names == {"SIH_MOT_WEAK", "SIH_MOT_EFF"}:
        return Truth(Hidden("motor_efficiency", {"motor": float(changes["SIH_MOT_WEAK"]),
                                                 "efficiency": changes["SIH_MOT_EFF"]}), text)
    if names and names <= {"SIH_CG_X", "SIH_CG_Y"}:
        return Truth(Hidden("com_offset", {"dx": changes.get("SIH_CG_X", 0.0), "dy": -changes.get("SIH_CG_Y", 0.0)}),
                     text)
    raise TwinError(f"truth.json: sih_changes: expected one SIH parameter group we map, got {sorted(names)}")


def flight_dirs(folder: str | Path) -> list[dict]:
    """The flights ``folder/<name>/{flight.ulg, truth.json}`` (the ``sitl_effects`` layout; ``<name>`` any
    folder holding both files), sorted by name."""
    out = []
    for d in sorted(p for p in Path(folder).iterdir() if p.is_dir()) if Path(folder).is_dir() else ():
        f, tj = d / "flight.ulg", d / "truth.json"
        if f.is_file() and tj.is_file():
            try:
                truth = json.loads(tj.read_text())
            except ValueError as exc:
                raise TwinError(f"{tj}: not valid JSON ({exc})") from None
            if not isinstance(truth, dict) or not isinstance(truth.get("sih_changes", {}), dict):
                raise TwinError(f"{tj}: sih_changes: expected a mapping {{PARAM: [default, used]}}")
            out.append({"flight": d.name, "path": str(f), "truth_json": truth, "mission": truth.get("mission", "")})
    return out


def flights(shared: str | Path | None = None, size: str = "full",
            sih_dirs: list[str | Path] | tuple = ()) -> list[dict]:
    """The SIH flights available under ``shared`` and in each of ``sih_dirs``:
    ``{"flight", "path", "truth_json", "mission"}``.

    The changed-parameter flights ``sitl_effects/eNN`` and the no-effect baselines ``sitl/*.ulg``; an empty
    list when the shared folder is absent (PX4 is not available to CI, so nothing is generated here).  A flight
    of a ``sih_dirs`` folder whose name is taken already is named ``<folder>/<name>``."""
    root = shared_dir(shared) / "flightlogs"
    out = [f for f in flight_dirs(root / "sitl_effects") if re.fullmatch(r"e\d\d", f["flight"])]
    for f in sorted((root / "sitl").glob("px4sih_*.ulg")):
        mission = {"triangle": "M1", "grid": "M2"}.get(f.stem.rsplit("_", 1)[-1], "")
        out.append({"flight": f.stem, "path": str(f), "mission": mission,
                    "truth_json": {"effects": [{"name": "none", "params": {}}], "sih_changes": {}}})
    if size == "ci":
        out = [f for f in out if f["flight"] in CI_FLIGHTS]
    for d in sih_dirs:
        if not Path(d).is_dir():
            raise TwinError(f"--sih-dir {d}: not a folder (expected <name>/flight.ulg + truth.json inside)")
        own = flight_dirs(d)
        if not own:
            raise TwinError(f"--sih-dir {d}: no <name>/flight.ulg + truth.json inside")
        taken = {f["flight"] for f in out}
        for f in own:
            if f["flight"] in taken:
                f["flight"] = f"{Path(d).name}/{f['flight']}"
        out += own
    return out


def run_one(args) -> dict:
    """Discover blind on one SIH flight with the nominal SIH params and score it."""
    flight, out_dir = args
    from twin_nodes.discovery.discover import discover
    from twin_nodes.logs.ulog_io import read_ulog

    vp = load_params(NOMINAL)
    truth = map_truth(flight["truth_json"], vp)
    log = read_ulog(flight["path"])
    res = discover(log, vp, closed_loop_metrics=False)
    res.pop("_series", None)
    drag = DragContext.from_log(log, vp) if effect_class(truth.hidden.name) == "drag" else None
    name = f"{flight['flight']} ({flight['mission']})" if flight["mission"] else flight["flight"]
    write_result(Path(out_dir) / f"{flight['flight'].replace('/', '_')}.json", res)
    row = score_flight(name, truth, res, vp, drag, source="px4sih", log=flight["path"])
    tj = flight["truth_json"]
    # the groups a breakdown reports (scoring.breakdown): how the flight was logged, what was changed
    row["logging"] = str((tj.get("logging") or {}).get("profile") or "default")
    row["sih_change"] = "+".join(sorted(tj.get("sih_changes") or {})) or "none"
    return row


def run_suite(out_dir: str | Path, size: str = "full", workers: int = 2, shared: str | Path | None = None,
              progress: bool = True, sih_dirs: list[str | Path] | tuple = ()) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fl = flights(shared, size, sih_dirs)
    if not fl:
        raise TwinError(f"--source px4sih: {shared_dir(shared) / 'flightlogs'}: expected the PX4 SIH flights "
                        "(sitl_effects/eNN/flight.ulg + truth.json, sitl/px4sih_*.ulg); none found "
                        f"(how to fly them: {MANIFEST.relative_to(REPO)})")
    return score(map_jobs(run_one, [(f, str(out)) for f in fl], workers, "prove px4sih", progress),
                 source="px4sih")
