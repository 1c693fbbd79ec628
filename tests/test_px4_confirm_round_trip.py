"""Issue 11: the confirmation round trip on real PX4 firmware (PX4 SIH), end to end.

A flight with roll/pitch inertia x1.5 (manifest flight e12: SIH_IXX/IYY 0.025 -> 0.0375, mission M3,
PX4's default 50 Hz log) gives ``inertia`` only ``likely``; ``discover --plan-dir`` writes a
confirmation plan that asks for rate-loop (4 ms) logging; that plan flown in PX4 SIH with the same
SIH change and the ``highrate`` logging profile confirms it (the refit on the follow-up lands on the
truth), and the same plan flown with no SIH change (the control) drops it.

``test_round_trip_flown_in_px4_sih`` flies the follow-up and the control itself (about 2.5 min), after
e12 from out/sih_flights/e12 when that exists, else flown here too (then it skips when that e12 confirms
inertia outright: on M3 it sits at the 3-sigma edge, t 2.4-3.1 over three flights).
``test_round_trip_replayed_from_out`` replays the flights recorded in ``docs/discovery.md``
(out/sih_flights/e12, out/confirm_e12/{c1,n1}); ``test_roll_arm_round_trip_replayed_from_out`` the
SIH_L_ROLL round trip (out/sih_grid/g34, out/confirm_g34/{c1,n1}).  Both run only with ``PX4_DIR`` set to a
PX4-Autopilot tree built with ``make px4_sitl_default`` (the replay also needs its logs under out/).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import px4_sitl_binary

REPO = Path(__file__).resolve().parents[1]
PX4_DIR = os.environ.get("PX4_DIR", "")
PARAMS = REPO / "params" / "px4_sih_quadx.yaml"
SIH = ["SIH_IXX=0.0375", "SIH_IYY=0.0375"]
TRUTH, NOMINAL = 0.0375, 0.025

pytestmark = pytest.mark.slow



def _run(args: list[str], timeout: float = 600) -> str:
    env = dict(os.environ, ROTORTWIN_PYTHON=sys.executable)
    p = subprocess.run(args, check=False, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, f"{' '.join(args)}\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}"
    return p.stdout


def _rotortwin(*args: str) -> str:
    return _run([sys.executable, "-m", "twin_nodes", *map(str, args)])


def _fly(out: Path, *args: str) -> None:
    _run(["bash", str(REPO / "launch_scripts" / "fly_sih.sh"), "--px4", PX4_DIR, "--out", str(out), *args])


def _discover(flight: Path, plan_dir: Path, json_out: Path) -> dict:
    _rotortwin("discover", flight, "--params", PARAMS, "--plan-dir", plan_dir, "--json", json_out,
               "--no-closed-loop")
    res = json.loads(json_out.read_text())
    eff = next(e for e in res["effects"] if e["name"] == "inertia")
    # found on the pitch output error, on the right side of nominal, whatever its verdict; reported with
    # the equation error's fit when the two residuals corroborate it (verdicts.corroboration)
    oe = eff["residuals"]["output"]
    assert oe["heldout_channel"] == "pitch" and oe["heldout_improvement"] > 0.2, eff["verdict_note"]
    assert eff["residual"] == "output" or eff["excitation"].get("corroborated"), eff["verdict_note"]
    assert eff["params"]["iyy"] > 1.2 * NOMINAL, eff["params"]
    return res


def _likely_plan(res: dict, plan_dir: Path) -> Path:
    """inertia is `likely` (block t < 3) and nothing else is found: its confirmation plan, checked."""
    eff = next(e for e in res["effects"] if e["name"] == "inertia")
    assert res["likely"] == ["inertia"] and res["accepted"] == [], (res["likely"], res["accepted"])
    assert eff["residuals"]["output"]["heldout_t_stat"] < 3.0, eff["verdict_note"]  # too few blocks there
    plan = plan_dir / "confirm_inertia.plan.yaml"
    assert plan.is_file(), sorted(plan_dir.iterdir())
    checked = _rotortwin("mission", "check", plan)  # exits 2 on an invalid plan
    assert "'confirm_inertia'" in checked and "RTL after: yes" in checked, checked[:400]
    text = plan.read_text()
    assert "every 4 ms" in text and "rate_doublets" in text, text[:600]  # the plan's logging advice
    return plan


def _confirmation(flight: Path, followup: Path, json_out: Path, name: str = "inertia") -> dict:
    _rotortwin("discover", flight, "--params", PARAMS, "--confirm", followup, "--json", json_out, "--no-closed-loop")
    (c,) = [c for c in json.loads(json_out.read_text())["confirmation"]["effects"] if c["name"] == name]
    return c


def _check_round_trip(flight: Path, followup: Path, control: Path, work: Path) -> tuple[dict, dict]:
    c = _confirmation(flight, followup, work / "confirm.json")
    refit = c["refit_on_followup"]["params"]
    # measured 2026-11-23: t 9.6-11.0 over 163-164 blocks, 56 % cut; refit iyy 0.0376/0.0381, ixx 0.0367/0.0378
    assert c["verdict"] == "confirmed", c["note"]
    assert c["followup_t_stat"] > 5.0 and c["followup_improvement"] > 0.3, c["note"]
    assert abs(refit["iyy"] / TRUTH - 1) < 0.10, refit
    assert abs(refit["ixx"] / TRUTH - 1) < 0.15, refit  # the 4 ms log resolves roll too (50 Hz left it nominal)
    n = _confirmation(flight, control, work / "control.json")
    nrefit = n["refit_on_followup"]["params"]
    # measured: t -7.9 (the flight's fit makes the control worse), refit iyy 0.0254/0.0259 ~ nominal
    assert n["verdict"] == "rejected" and n["note"].startswith("dropped"), n["note"]
    assert n["followup_t_stat"] < 3.0, n["note"]
    assert abs(nrefit["iyy"] / NOMINAL - 1) < 0.10, nrefit
    print(f"follow-up: {c['note']}; refit {refit}\ncontrol: {n['note']}; refit {nrefit}")
    return c, n


def test_round_trip_flown_in_px4_sih(tmp_path):
    """Flies the follow-up and the control; e12 is the recorded flight when out/ has it, else flown here."""
    px4_sitl_binary()
    flight = REPO / "out" / "sih_flights" / "e12" / "flight.ulg"
    if not flight.is_file():
        _fly(tmp_path, "--flight", "e12")  # the manifest flight: M3, 50 Hz motors, inertia x1.5
        flight = tmp_path / "e12" / "flight.ulg"
    res = _discover(flight, tmp_path / "plans", tmp_path / "e12.json")
    if res["accepted"] == ["inertia"] and not res["likely"]:
        # e12 on M3 sat at the 3-sigma edge (re-flown: t 2.4, likely, once; 3.1, confirmed, once); since
        # PX4's rate loop is flown on the model (2026-11-26) the recorded e12 is confirmed outright
        # (Ixx 0.0351, Iyy 0.0380 for 0.0375): then that is checked, and there is nothing to follow up
        (inertia,) = [e for e in res["effects"] if e["name"] == "inertia"]
        assert abs(inertia["params"]["iyy"] / TRUTH - 1) < 0.10, inertia["params"]
        assert abs(inertia["params"]["ixx"] / TRUTH - 1) < 0.15, inertia["params"]
        pytest.skip("e12 confirmed inertia outright (checked against the truth): no `likely` effect to follow up")
    plan = _likely_plan(res, tmp_path / "plans")
    _fly(tmp_path, "--id", "f1", "--mission", str(plan), "--sih", *SIH, "--logging", "highrate")
    _fly(tmp_path, "--id", "n1", "--mission", str(plan), "--logging", "highrate")
    for fid, truth in (("f1", "inertia"), ("n1", "none")):
        assert json.loads((tmp_path / fid / "truth.json").read_text())["effects"][0]["name"] == truth
    _check_round_trip(flight, tmp_path / "f1" / "flight.ulg", tmp_path / "n1" / "flight.ulg", tmp_path)


def test_round_trip_replayed_from_out(tmp_path):
    px4_sitl_binary()
    flight = REPO / "out" / "sih_flights" / "e12" / "flight.ulg"
    followup = REPO / "out" / "confirm_e12" / "c1" / "flight.ulg"
    control = REPO / "out" / "confirm_e12" / "n1" / "flight.ulg"
    missing = [str(p.relative_to(REPO)) for p in (flight, followup, control) if not p.is_file()]
    if missing:
        pytest.skip(f"round-trip flights not flown here: {', '.join(missing)} (docs/discovery.md)")
    _likely_plan(_discover(flight, tmp_path / "plans", tmp_path / "e12.json"), tmp_path / "plans")
    c, n = _check_round_trip(flight, followup, control, tmp_path)
    # the recorded flights' own numbers (docs/discovery.md; 2026-11-24: e12's fit is now the equation
    # error's, ixx 0.0323 / iyy 0.0374, closer to the truth than the output error's, so t 11.0 -> 14.8)
    assert abs(c["followup_active_blocks"] - 163) <= 5 and abs(c["followup_t_stat"] - 14.79) < 1.0, c["note"]
    assert abs(c["refit_on_followup"]["params"]["iyy"] - 0.0379) < 0.001, c["refit_on_followup"]
    assert abs(n["followup_t_stat"] + 7.94) < 1.0, n["note"]


def _replayed(tmp_path, flight_rel: str, followups: tuple[str, ...], name: str) -> tuple[dict, Path, list[Path]]:
    """Discover FLIGHT (out/...) with plans into tmp_path, after skipping (one line) when the flight or
    its follow-ups were not flown here; returns the result, the flight and the follow-up paths."""
    px4_sitl_binary()
    flight = REPO / "out" / flight_rel
    paths = [REPO / "out" / f for f in followups]
    missing = [str(p.relative_to(REPO)) for p in (flight, *paths) if not p.is_file()]
    if missing:
        pytest.skip(f"round-trip flights not flown here: {', '.join(missing)} (docs/discovery.md)")
    _rotortwin("discover", flight, "--params", PARAMS, "--plan-dir", tmp_path / "plans", "--json",
               tmp_path / f"{name}.json", "--no-closed-loop")
    return json.loads((tmp_path / f"{name}.json").read_text()), flight, paths


def _roll_arm_confirmed_and_control_dropped(flight: Path, followup: Path, control: Path, tmp_path) -> None:
    """The roll-arm plan flown with the change confirms the effect on the roll output error, its refit
    within 5 % of Ixx 0.03125; flown with no change it is dropped (the flight's fit makes it worse)."""
    c = _confirmation(flight, followup, tmp_path / "confirm.json")
    assert c["verdict"] == "confirmed" and c["residual"] == "output" and c["channel"] == "roll", c["note"]
    assert c["followup_t_stat"] > 3.0 and c["followup_improvement"] > 0.2, c["note"]
    assert abs(c["refit_on_followup"]["params"]["ixx"] / 0.03125 - 1) < 0.05, c["refit_on_followup"]
    n = _confirmation(flight, control, tmp_path / "control.json")
    assert n["verdict"] == "rejected" and n["followup_t_stat"] < 0.0, n["note"]


def test_roll_arm_round_trip_replayed_from_out(tmp_path):
    """SIH_L_ROLL 0.2 -> 0.16 m (the roll moment x0.8, as Ixx 0.025 -> 0.03125) on grid flight g34: the
    two residuals corroborate ``inertia`` (``likely``); its plan flown with the same change and the 4 ms
    log (out/confirm_g34/c1) confirms it on the roll output error and the refit lands on the truth; flown
    with no change (n1) it is dropped.  Recorded 2026-11-24 (docs/discovery.md)."""
    res, flight, (followup, control) = _replayed(tmp_path, "sih_grid/g34/flight.ulg",
                                                 ("confirm_g34/c1/flight.ulg", "confirm_g34/n1/flight.ulg"), "g34")
    eff = next(e for e in res["effects"] if e["name"] == "inertia")
    assert res["likely"] == ["inertia"] and res["accepted"] == [], (res["likely"], res["accepted"])
    assert eff["excitation"].get("corroborated") and "roll" in eff["verdict_note"], eff["verdict_note"]
    assert abs(eff["params"]["ixx"] / 0.03125 - 1) < 0.10, eff["params"]
    assert (tmp_path / "plans" / "confirm_inertia.plan.yaml").is_file()
    # measured: t 3.9 over 65 blocks, 30 % cut in roll (6 % of all four axes), refit ixx 0.0313; the
    # control t -7.2 (the flight's fit makes it worse), refit ixx 0.0261
    _roll_arm_confirmed_and_control_dropped(flight, followup, control, tmp_path)


def test_instrumented_roll_arm_round_trip_replayed_from_out(tmp_path):
    """SIH_L_ROLL 0.2 -> 0.16 m on grid flight g26 (yaw-square mission, 4 ms logs): roll's output error
    is left out (r^2 0.797 < 0.8), PX4's rate loop flown on the model reads roll x1.16 +- 0.03 of the
    model's inertia and yaw x1.01, and ``inertia`` is ``likely`` on that residual (Ixx 0.0286 +- 0.0011
    vs 0.03125; the rate setpoint as instrument of the commands, used before 2026-11-26, read 0.0334 +-
    0.0018).  Its plan
    (15 rate doublets) flown with the same change (out/confirm_g26/c2) confirms it on the roll output
    error, the refit within 5 % of the truth; flown with no change (n2) it is dropped.  The first plan
    (6 doublets, c1) was too short: t 2.4 over 58 blocks, dropped.  Recorded 2026-11-25 (docs/discovery.md)."""
    res, flight, (followup, control) = _replayed(tmp_path, "sih_grid/g26/flight.ulg",
                                                 ("confirm_g26/c2/flight.ulg", "confirm_g26/n2/flight.ulg"), "g26")
    eff = next(e for e in res["effects"] if e["name"] == "inertia")
    assert res["likely"] == ["inertia"] and res["accepted"] == [], (res["likely"], res["accepted"])
    assert eff["residual"] == "rate_loop" and eff["heldout_channel"] == "roll", eff
    assert abs(eff["params"]["ixx"] / 0.03125 - 1) < 0.10 and eff["params"]["iyy"] == 0.025, eff["params"]
    assert eff["heldout_improvement"] > 0.5 and 0 < eff["params_se"]["ixx"] < 0.003
    assert res["instrumented"]["axes"]["roll"]["flagged"] and abs(res["instrumented"]["yaw_gain"] - 1) < 0.02
    plan = (tmp_path / "plans" / "confirm_inertia.plan.yaml").read_text()
    assert plan.count("north_m") >= 45, "15 rate doublets"
    # measured: t 5.1 over 113 blocks, 32 % cut in roll, refit ixx 0.0305; the control t -7.9 (the
    # flight's fit makes it 22 % worse in roll)
    _roll_arm_confirmed_and_control_dropped(flight, followup, control, tmp_path)


def test_rate_loop_motor_lag_round_trip_on_the_shared_e04(tmp_path):
    """SIH_T_TAU 0.05 -> 0.09 s on the shared 50 Hz flight e04 (not ours): the flight's own residuals cut
    9-10 %, PX4's rate loop flown on the model reads 0.090 s on every axis, ``motor_time_constant`` is
    ``likely``.  Its plan (rate doublets, 4 ms logging advised) flown with the same change
    (c1) confirms it on the roll output error, the refit within 5 % of the truth; flown with no change
    (n1) it is dropped, the refit back at the model's 0.05 s.  The follow-ups recorded 2026-11-26 in
    out/confirm_e04 are replayed when there; else they are flown here from the plan this run writes
    (docs/discovery.md)."""
    from conftest import shared_log
    px4_sitl_binary()
    flight = shared_log("sitl_effects", "e04/flight.ulg")
    _rotortwin("discover", flight, "--params", PARAMS, "--plan-dir", tmp_path / "plans", "--json",
               tmp_path / "e04.json", "--no-closed-loop")
    res = json.loads((tmp_path / "e04.json").read_text())
    assert res["likely"] == ["motor_time_constant"] and res["accepted"] == [], (res["likely"], res["accepted"])
    eff = res["effects"][0]
    assert eff["name"] == "motor_time_constant" and eff["residual"] == "rate_loop", eff
    assert abs(eff["params"]["tau_up"] / 0.09 - 1) < 0.05, eff["params"]
    plan = tmp_path / "plans" / "confirm_motor_time_constant.plan.yaml"
    assert plan.is_file() and "rate_doublets" in plan.read_text()
    recorded = REPO / "out" / "confirm_e04"
    followup, control = recorded / "c1" / "flight.ulg", recorded / "n1" / "flight.ulg"
    if not (followup.is_file() and control.is_file()):
        _fly(tmp_path, "--id", "c1", "--mission", str(plan), "--sih", "SIH_T_TAU=0.09", "--logging", "highrate")
        _fly(tmp_path, "--id", "n1", "--mission", str(plan), "--logging", "highrate")
        followup, control = tmp_path / "c1" / "flight.ulg", tmp_path / "n1" / "flight.ulg"
    # measured: t 21.0 over 332 blocks, 42 % cut in roll, refit tau 0.0865 / 0.0877; the control t -7.9,
    # refit 0.053 / 0.048
    c = _confirmation(flight, followup, tmp_path / "confirm.json", "motor_time_constant")
    assert c["verdict"] == "confirmed" and c["residual"] == "output", c["note"]
    assert c["followup_t_stat"] > 5.0 and c["followup_improvement"] > 0.2, c["note"]
    assert all(abs(v / 0.09 - 1) < 0.05 for v in c["refit_on_followup"]["params"].values()), c["refit_on_followup"]
    n = _confirmation(flight, control, tmp_path / "control.json", "motor_time_constant")
    assert n["verdict"] == "rejected" and n["followup_t_stat"] < 0.0, n["note"]
    assert all(abs(v / 0.05 - 1) < 0.10 for v in n["refit_on_followup"]["params"].values()), n["refit_on_followup"]
