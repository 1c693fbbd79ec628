"""Issue 26 item 2, two effects on one channel: a battery sag's level is held at the full pack (a free v_ref is a
constant thrust scale), and after an acceptance on a channel the effects of another shape there are refitted
jointly with it and judged in that channel's mode (``discovery.stages.joint.shape_partners``).  Synthetic closed
forms, and, where the grid's cache holds them, seen flights."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from twin_nodes.discovery import evaluate
from twin_nodes.discovery.candidates import build_candidates, full_pack_voltage
from twin_nodes.discovery.judging import BLOCK_S, Judge, _blocks, _mode_cut
from twin_nodes.discovery.residuals import mode_basis, modes
from twin_nodes.discovery.stages import joint, selection, verdicts
from twin_nodes.vehicle.params import shipped

V_FULL, KT, EXPO = 16.8, 0.87, 1.0


def test_full_pack_voltage_reads_the_cells_from_the_highest_reading():
    # the fewest cells that can read it at 4.35 V a cell: a 4S pack under load (15.9 V), low (13.6 V) or LiHV full
    # (17.4 V); a 3S full (12.6 V) or low (10.0 V); a 6S; one cell
    for v, full in ((15.9, 16.8), (13.6, 16.8), (17.4, 16.8), (12.6, 12.6), (10.0, 12.6), (22.0, 25.2), (3.7, 4.2)):
        assert full_pack_voltage(np.array([v - 0.5, v, np.nan])) == pytest.approx(full)


def _collective_flight(kt: float = KT, expo: float = EXPO, seed: int = 0):
    """A synthetic equation error with the collective only: the measured thrust per motor is the command times
    ``kt * (V / 16.8) ** expo``; the pack voltage falls 1.4 V over the flight and sags 0.9 V per unit of load (the
    RotorPy grid's pack); the model's thrust follows its own thrust coefficient, mass and battery sag."""
    rng = np.random.default_rng(seed)
    dt, T = 0.02, 120.0
    t = np.arange(0.0, T, dt)
    load = 1.0 + 0.25 * np.sin(2 * np.pi * t / 9.0) + 0.1 * np.sin(2 * np.pi * t / 2.3 + 1.0)
    volts = V_FULL - 1.4 * t / T - 0.9 * load
    u = 0.5 * load
    meas = u * kt * (volts / V_FULL) ** expo + 0.002 * rng.normal(size=t.size)
    vp = shipped("px4_sih_quadx")
    m0 = vp.mass_kg

    def residual(v, rows=None):
        eff = {k: dict(p) for k, p in v.effects}
        scale = eff.get("thrust_coefficient", {}).get("kt_scale", 1.0) * m0 / eff.get("mass", {}).get("mass", m0)
        sag = eff.get("battery_sag")
        if sag:
            scale = scale * (volts / sag["v_ref"]) ** sag["exponent"]
        R = np.zeros((t.size, 6))
        R[:, :4] = (meas - u * scale)[:, None]
        return R if rows is None else R[rows]
    folds = [(t < 0.65 * T, t >= 0.65 * T), (t >= 0.35 * T, t < 0.35 * T)]
    eq = Judge("equation", residual, folds, _blocks(t, folds[0][1], BLOCK_S) + _blocks(t, folds[1][1], BLOCK_S),
               folds[0][1])
    n = t.size
    data = SimpleNamespace(v=np.zeros((n, 3)), valid=np.ones(n, bool), motor_dt_s=0.004, dt=dt,
                           height=np.full(n, 10.0), battery_v=volts)
    return SimpleNamespace(eq=eq, oe=None, data=data, nominal=vp)


def _found(sel) -> dict:
    return {f.candidate.name: f.candidate.params_dict(f.theta) for f in sel.accepted}


def test_the_battery_sag_is_offered_as_its_shape_with_the_level_at_the_full_pack():
    S = _collective_flight()
    c = next(c for c in build_candidates(S.nominal, S.data) if c.name == "battery_sag")
    assert c.param_names == ("exponent",) and c.fixed == {"v_ref": V_FULL}
    assert c.params_dict(np.array([1.3])) == {"v_ref": V_FULL, "exponent": 1.3}


def test_a_thrust_deficit_beside_a_battery_sag_is_found_with_it(monkeypatch):
    # RotorPy w033's kind (sag exponent 1.0 with a thrust coefficient 0.87): before, the sag's free v_ref took the
    # deficit (v_ref 18.18 for 16.8) and the thrust coefficient fitted on top of it was left at 1.000
    monkeypatch.setattr(evaluate, "WORKERS", 1)
    sel = selection.run(selection.SelectionInput(_collective_flight()))
    found = _found(sel)
    # the deficit as a thrust coefficient or a mass (one force per unit mass: one scoring class)
    assert set(found) in ({"battery_sag", "thrust_coefficient"}, {"battery_sag", "mass"}), found
    # the joint variant is fitted on the sag's regressor linearised where the sag alone stood (exponent ~2.4, the
    # deficit in it): one step to 1.10 here; discover's final joint refit, on true evaluations, finishes it (w033:
    # 0.94 for 1.0)
    assert found["battery_sag"]["exponent"] == pytest.approx(EXPO, rel=0.12)
    m0 = shipped("px4_sih_quadx").mass_kg     # thrust per unit mass: a mass found for the deficit is one too
    level = found.get("thrust_coefficient", {}).get("kt_scale", 1.0) * m0 / found.get("mass", {}).get("mass", m0)
    assert level == pytest.approx(KT, rel=0.02)


@pytest.mark.parametrize("kt,expo,want", [(1.0, EXPO, {"battery_sag"}), (KT, 0.0, {"thrust_coefficient"})])
def test_one_collective_effect_stays_one(monkeypatch, kt, expo, want):
    # a sag alone (the level right): no thrust coefficient beside it; a deficit alone: no sag beside it
    monkeypatch.setattr(evaluate, "WORKERS", 1)
    found = _found(selection.run(selection.SelectionInput(_collective_flight(kt, expo, seed=1))))
    assert set(found) == want or (want == {"thrust_coefficient"} and set(found) == {"mass"}), found


def _acc(name: str):
    return SimpleNamespace(candidate=SimpleNamespace(name=name), kind="equation")


def test_shape_partners_are_the_other_shapes_of_the_accepted_effects_channel():
    cands = [SimpleNamespace(name=n, label=n) for n in
             ("mass", "thrust_coefficient", "battery_sag", "ground_effect", "yaw_moment", "inertia", "angular_damping",
              "motor_time_constant")]
    cands.append(SimpleNamespace(name="mass", label="mass (+thrust_coefficient refitted)"))
    per = {c.label: [object()] for c in cands}
    # a constant scale accepted: the voltage and the height are offered on the collective, not another scale
    assert joint.shape_partners([_acc("thrust_coefficient")], cands, per) == {"battery_sag": "throttle",
                                                                             "ground_effect": "throttle"}
    # a sag accepted: the constant scales and the ground effect
    assert joint.shape_partners([_acc("battery_sag")], cands, per) == {
        "mass": "throttle", "thrust_coefficient": "throttle", "ground_effect": "throttle"}
    # yaw: a damping accepted offers a yaw moment or a yaw inertia (one scale there); a scale offers the damping
    assert joint.shape_partners([_acc("angular_damping")], cands, per) == {"yaw_moment": "yaw", "inertia": "yaw"}
    assert joint.shape_partners([_acc("yaw_moment")], cands, per) == {"angular_damping": "yaw"}
    # both shapes of yaw taken: no third; an effect of no listed channel offers nothing; no plain fit, no offer
    assert joint.shape_partners([_acc("yaw_moment"), _acc("angular_damping")], cands, per) == {}
    assert joint.shape_partners([_acc("motor_time_constant")], cands, per) == {}
    assert joint.shape_partners([_acc("battery_sag")], cands, {"mass": [object()]}) == {"mass": "throttle"}


def test_the_mode_cut_is_read_in_one_mode():
    vp = shipped("px4_sih_quadx")
    rng = np.random.default_rng(2)
    m0 = rng.normal(size=(400, 6))
    # a residual built in mode space: halve the yaw mode only
    _, names = modes(m0, vp)
    b = mode_basis(vp.rotors)
    R0 = np.column_stack([m0[:, :4] @ np.linalg.inv(b.T), m0[:, 4:]])
    m1 = m0.copy()
    m1[:, names.index("yaw")] *= 0.5
    R1 = np.column_stack([m1[:, :4] @ np.linalg.inv(b.T), m1[:, 4:]])
    assert _mode_cut(R0, R1, vp, "yaw") == pytest.approx(0.5, abs=1e-9)
    assert _mode_cut(R0, R1, vp, "throttle") == pytest.approx(0.0, abs=1e-9)


def test_a_sag_and_a_thrust_coefficient_both_confirmed_are_told_apart():
    # their shapes differ (the voltage, a constant): both confirmed is a separation; a mass with a thrust
    # coefficient (one shape: force per unit mass) stays a pair
    def eff(name, pair=None):
        e = {"name": name, "verdict": "confirmed", "params": {}}
        if pair:
            e["not_told_apart"] = {"with": {"name": pair, "params": {}}, "plan_flyable": True}
        return e
    out = [eff("battery_sag", "thrust_coefficient"), eff("thrust_coefficient")]
    verdicts.told_apart(out)
    assert "not_told_apart" not in out[0] and out[0]["told_apart_from"]["name"] == "thrust_coefficient"
    out = [eff("mass", "thrust_coefficient"), eff("thrust_coefficient")]
    verdicts.told_apart(out)
    assert out[0]["not_told_apart"]["with"]["name"] == "thrust_coefficient"


# ------------------------------------------------------------------ seen flights of the declared grids (cache only)

CACHE = Path.home() / ".cache" / "rotortwin" / "grids"


def _seen(source: str, half: str, fid: str):
    from twin_nodes.prove import grid_prove

    jobs, _ = (grid_prove.rotorpy_jobs(half, CACHE / "rotorpy") if source == "rotorpy"
               else grid_prove.sih_jobs(half, CACHE / "sih"))
    job = next((j for j in jobs if (j[1].id if source == "rotorpy" else j[1][0]) == fid), None)
    if job is None:
        pytest.skip(f"{source} flight {fid} not in the grid cache {CACHE} (tools/fly_grids.sh flies it)")
    return grid_prove.run_one(job)


@pytest.mark.slow
@pytest.mark.parametrize("source,half,fid,truth", [
    ("rotorpy", "judge3", "w023", {"battery_sag", "mass"}),
    ("rotorpy", "judge3", "w033", {"battery_sag", "thrust_coefficient"})])
def test_a_seen_two_effect_flight_on_the_collective(source, half, fid, truth, monkeypatch):
    # before (sixth session): w023 named the sag alone (v_ref 18.0 for 16.8: the mass in it); w033 the sag 8 % and
    # the thrust coefficient 15 % off (through the pair, v_ref 18.2)
    monkeypatch.setenv("ROTORTWIN_DISCOVER_WORKERS", "1")
    row, _ = _seen(source, half, fid)
    assert set(row["named"]) == truth, row["findings"]
    assert all(e is not None and e <= 0.10 for e in row["param_errors"].values()), row["param_text"]
    assert row["passed"]


def test_a_what_if_vehicle_out_of_range_is_said_not_a_failed_flight(monkeypatch, tmp_path):
    """The real fleet's overloaded Quad X (23_juni log_20, motors at their bound for 31 of 34 s): battery sag,
    mass and thrust coefficient accepted together; mass's contribution given the others asks for the others
    refitted with mass at its nominal, a vehicle whose rotors cannot lift it (4 x 2.98 N < 14.7 N).  That
    what-if is said in its row and the flight is surveyed; it used to fail the whole flight with a ParamsError."""
    from conftest import shared_log

    from twin_nodes.discovery.survey import survey_flight

    monkeypatch.setenv("ROTORTWIN_CACHE", str(tmp_path))
    monkeypatch.setenv("ROTORTWIN_DISCOVER_WORKERS", "1")
    row = survey_flight(shared_log("fleet_quadx_v6c/23_juni", "log_20_2023-6-23-11-05-22.ulg"), None)
    assert row["status"] == "ok"
    given = {e["name"]: e["heldout_contribution"]["given_the_others"] for e in row["accepted"]
             if "given_the_others" in e.get("heldout_contribution", {})}
    assert given["mass"]["cut"] is None and "cannot lift the vehicle" in given["mass"]["not_computed"]
    assert given["thrust_coefficient"]["cut"] > 0.3 and given["battery_sag"]["cut"] > 0.1
