"""Graded verdicts, both residuals, excitation, confirmation plans and the confirmation round trip.

PX4 SIH flights (real PX4 firmware, ../shared/flightlogs/sitl_effects, truth in truth.json):
no `likely`/`confirmed` finding on the no-effect flights; e03 (SIH_Q_MAX x1.4) found with its parameter
near the truth; e04 (SIH_T_TAU 0.05 -> 0.09 s): its own output error cuts 9-10 %, PX4's rate loop reads 0.090 s,\n`likely`; e05 (SIH_IXX/IYY x1.3):
on 50 Hz motor logs the roll/pitch output error is attenuated by the aliased commands (the nominal
model explains <= 60 % of the roll/pitch rate changes), so those axes are left out of it; PX4's rate
loop flown on the model from the logged rate setpoint reads both inertias, `likely` (docs/discovery.md).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import missing_shared

from twin_nodes.discovery.discover import Fit, discover
from twin_nodes.discovery.plans import manoeuvre, plan_for, plan_yaml, write_plans
from twin_nodes.discovery.residuals import mode_basis
from twin_nodes.discovery.verdicts import grade
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.mavlink.mission import load_plan
from twin_nodes.vehicle.params import shipped

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "flightlogs"
EFFECTS = SHARED / "sitl_effects"
FINDINGS = ("likely", "confirmed")


def _sih(name: str):
    p = EFFECTS / name / "flight.ulg" if name.startswith("e") else SHARED / "sitl" / name
    if not p.exists():
        missing_shared(str(p.relative_to(SHARED.parent)))
    return read_ulog(p)


@pytest.fixture(scope="module")
def sih_results():
    cache: dict[str, dict] = {}

    def get(name):
        if name not in cache:
            cache[name] = discover(_sih(name), shipped("px4_sih_quadx"), closed_loop_metrics=False)
        return cache[name]
    return get


def _findings(res):
    return [e for e in res["effects"] if e["verdict"] in FINDINGS]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["e07", "e08", "px4sih_default_triangle.ulg", "px4sih_default_grid.ulg"])
def test_no_finding_on_px4_sih_no_effect_flights(sih_results, name):
    res = sih_results(name)
    assert _findings(res) == [], [(e["name"], e["verdict"], e["verdict_note"]) for e in _findings(res)]
    assert res["likely"] == [] and res["accepted"] == []
    # both residuals are reported for every candidate that the output error judges
    km = next(e for e in res["effects"] if e["name"] == "yaw_moment")
    assert set(km["residuals"]) == {"equation", "output"}
    assert res["output_error_axes"]["axes"]["yaw"]["used"]
    # the rate setpoint as instrument flags no roll/pitch axis on them (logged on every one)
    iv = res.get("instrumented") or {}
    assert iv.get("flagged", []) == [] and iv.get("verdict", "none") == "none", iv
    # PX4's sensor timing is the log's, not the motors': with the gyro low-pass' 5.6 ms and the
    # command hold re-timed (px4_params.sensor_timing), the output error fits no delay (< 2 ms; it
    # read 5.6-8.6 ms taken at the stamps) and SIH's own 0.05 s lag within 10 % (it read 0.052-0.064)
    fits = {e["name"]: e["residuals"]["output"]["params"] for e in res["effects"]
            if e["name"] in ("actuator_delay", "motor_time_constant")}
    assert fits["actuator_delay"]["delay"] < 0.002, fits
    assert fits["motor_time_constant"]["tau_up"] == pytest.approx(0.05, rel=0.10), fits
    assert "IMU_GYRO_CUTOFF 40 Hz" in res["method"]["timing"]


@pytest.mark.slow
def test_e03_yaw_moment_found_with_km_near_truth(sih_results):
    truth = json.loads((EFFECTS / "e03" / "truth.json").read_text())["effects"][0]["params"]["km"]
    res = sih_results("e03")
    top = _findings(res)[0]
    assert top["name"] == "yaw_moment" and top["verdict"] in FINDINGS, top
    assert top["params"]["km"] == pytest.approx(truth, rel=0.10)
    # the output error corroborates the equation error's yaw moment, whose share is then read over the yaw mode
    # (verdicts.CORROBORATED_SHARE): both pass, and the equation error's fit is reported (km 0.02819 for 0.028)
    assert top["residual"] == "equation" and top["heldout_channel"] == "yaw"
    assert top["residuals"]["output"]["params"]["km"] == pytest.approx(truth, rel=0.10)
    assert top["excitation"]["channel"] == "yaw"
    assert any(m.startswith("yaw turn") for m in res["excitation"]["yaw"]["manoeuvres"])
    # the located mismatches now include the yaw channel
    assert any(m["channel"] == "yaw" for m in res["mismatch"])


@pytest.mark.slow
def test_e04_motor_lag_is_likely_from_the_px4_rate_loop(sih_results):
    """SIH_T_TAU 0.05 -> 0.09 s on a 50 Hz log.  On the flight's own residuals the extra lag and a pure
    delay of the same size fit the output error's yaw alike, each cutting it 9-10 %, under the 10 % bar.
    PX4's rate loop flown on the model from the logged rate setpoint reads roll, pitch and yaw slow alike
    (the motors' signature, not an inertia), and the lag that explains it is 0.090 s on every axis; it
    cuts the held-out rate error along its sensitivity by > 80 % and beats an extra delay there: the
    top finding, `likely` (one residual of PX4's, none of the flight's own)."""
    res = sih_results("e04")
    found = _findings(res)
    assert [e["name"] for e in found] == ["motor_time_constant"], [e["name"] for e in found]
    top = found[0]
    assert top["verdict"] == "likely" and top["residual"] == "rate_loop" and res["effects"][0] is top
    assert top["params"]["tau_up"] == pytest.approx(0.09, rel=0.05) and top["params"]["tau_down"] == top["params"]["tau_up"]
    assert top["heldout_improvement"] > 0.8
    rl = res["rate_loop_lag"]
    assert all(t == pytest.approx(0.09, rel=0.10) for t in rl["axis_tau"].values()), rl["axis_tau"]
    assert rl["heldout_sse"]["lag"] < rl["heldout_sse"]["delay"] < rl["heldout_sse"]["model"]
    assert res["instrumented"]["motor_signature"] and res["instrumented"]["verdict"] == "none"
    # the flight's own output error, kept beside it: right size, under the bar; the delay likewise, rejected
    out = top["residuals"]["output"]
    assert out["heldout_channel"] == "yaw" and 0.05 < out["cv_improvement"] < 0.10, out
    assert out["params"]["tau_up"] - 0.05 == pytest.approx(0.09 - 0.05, rel=0.25)
    delay = next(e for e in res["effects"] if e["name"] == "actuator_delay")
    assert delay["verdict"] == "rejected" and delay["params"]["delay"] == pytest.approx(0.04, rel=0.25)


@pytest.mark.slow
def test_the_report_shows_the_rate_loops_curves(sih_results, tmp_path):
    """The report plots what the rate loop read: each axis's fit against its inertia scale and, on e04,
    against the motors' time constant, every axis's lowest point at the lag found."""
    from twin_nodes.discovery.report import write_report
    res = sih_results("e04")
    lag = res["rate_loop_lag"]["curve"]
    for a in ("roll", "pitch", "yaw"):
        best = lag["taus"][int(np.argmin(lag[a]))]
        assert best == pytest.approx(0.09, rel=0.10), (a, best)
        assert min(res["instrumented"]["curve"][a]) == 1.0 and max(res["instrumented"]["curve"][a]) > 1.1
    write_report(tmp_path, res, res["_series"])
    assert (tmp_path / "rate_loop.png").stat().st_size > 10_000
    assert "<h2>PX4's rate loop flown on the model</h2>" in (tmp_path / "index.html").read_text()


@pytest.mark.slow
def test_e05_roll_pitch_inertia_is_likely_from_the_px4_rate_loop(sih_results):
    """What the 50 Hz motor log hides, PX4's own rate loop shows: roll and pitch are left out of the
    output error (the aliased commands), and the instrument of the commands flags pitch only, its
    held-out cut 6 %.  Flown as PX4 flies it (the log's rate gains and filters on the model, driven by
    the logged rate setpoint), roll reads x1.20 and pitch x1.31 of the model's inertia (truth x1.3), yaw
    x1.02: an inertia, not the motors.  It is the top finding, `likely` (one moment per axis, no
    residual of the flight's own to confirm it), both axes within 10 % of 0.0325."""
    res = sih_results("e05")
    axes = res["output_error_axes"]["axes"]
    assert not axes["roll"]["used"] and axes["roll"]["r2"] < 0.8
    rl = res["instrumented"]
    assert rl["method"] == "rate_loop" and sorted(rl["flagged"]) == ["pitch", "roll"] and rl["verdict"] == "likely"
    top = _findings(res)[0]
    assert top["name"] == "inertia" and top["verdict"] == "likely" and top["residual"] == "rate_loop"
    assert top["params"]["ixx"] == pytest.approx(0.0325, rel=0.10)
    assert top["params"]["iyy"] == pytest.approx(0.0325, rel=0.10)
    assert top["heldout_improvement"] >= 0.5 and "rate loop" in top["verdict_note"]
    # the vocabulary names the inertia alone; stage 9 (physics outside the list, fitted on what the
    # vocabulary leaves) finds a vertical-speed law here (out-of-fold t 3.43, cut 16 %) that the SIH truth
    # does not change; flown, it makes the held-out part's throttle residual 106 % worse, so the held-out
    # rule (stages.terms._verdict) rejects it (it was kept, a known false term, before the eighth session)
    assert [e["name"] for e in _findings(res)] == ["inertia"]
    for term in res["terms"]["found"]:
        assert term["verdict"] == "rejected" and term["heldout_improvement"] < 0.10, term


# ----------------------------------------------------------------------------- grading (unit)


class _Cand:
    name = "yaw_moment"
    param_names = ("km",)
    fixed: dict = {}
    label = "yaw_moment"
    x0 = np.array([0.02])
    lower = np.array([0.004])
    upper = np.array([0.1])

    def floor(self, th):
        return abs(th[0] - 0.02) / 0.02 > 0.03

    def params_dict(self, th):
        return {"km": float(th[0])}


def _fit(theta, cut, t, n, pos, folds=None, accepted=False):
    c = _Cand()
    f = Fit(c, np.array([theta]), None, 0.0, 0.0, np.zeros(6), t, n, cut, bool(c.floor(np.array([theta]))))
    f.judged = ("yaw", 1.0, 1.0 - cut)
    f.kind = "output"
    f.stats = {"n": n, "n_pos": pos, "mean": 0.1, "sd": 0.1, "t": t}
    f.fold_thetas = [np.array([x]) for x in (folds or [theta, theta])]
    f.folds_agree = True
    f.accepted = accepted
    return f


def test_grade_likely_only_when_all_but_significance_holds():
    ex = {"yaw": {"blocks_heldout": 3, "blocks_heldout_total": 80, "manoeuvres": {"yaw turn": 3}}}
    f = _fit(0.028, 0.7, 2.0, 5, 5)
    grade(f, 3.0, 0.1, ex)
    assert f.verdict == "likely"
    assert f.excitation["blocks_missing"] >= 1 and "yaw_sweeps" in f.excitation["plans"]
    assert "yaw sweeps" in f.verdict_note
    # fewer than 4 active blocks (no test possible): likely only when every one improves
    f = _fit(0.028, 0.7, 0.0, 3, 3)
    grade(f, 3.0, 0.1, ex)
    assert f.verdict == "likely"
    f = _fit(0.028, 0.7, 0.0, 3, 2)
    grade(f, 3.0, 0.1, ex)
    assert f.verdict == "rejected"
    # small cut, or a parameter next to nominal, or significant-but-not-accepted: never likely
    for f in (_fit(0.028, 0.2, 2.0, 5, 5), _fit(0.0205, 0.7, 2.0, 5, 5), _fit(0.028, 0.7, 3.5, 12, 12)):
        grade(f, 3.0, 0.1, ex)
        assert f.verdict == "rejected", f.verdict_note
    f = _fit(0.028, 0.7, 6.0, 20, 20, accepted=True)
    grade(f, 3.0, 0.1, ex)
    assert f.verdict == "confirmed"


def test_locate_output_flags_mode_windows_above_3x_typical_error_merged_by_overlap():
    """Output-error windows (0.4 s every 0.2 s) whose yaw error is above 3x the typical error merge
    into one span per run of overlapping (or touching) windows, per channel worst first, labelled
    with the regime they fly."""
    from types import SimpleNamespace

    from twin_nodes.discovery.locate import locate_output
    from twin_nodes.discovery.residuals import EquationData

    vp = shipped("px4_sih_quadx")
    n = 1000  # 20 s at 50 Hz
    t = np.arange(n) * 0.02
    w = np.zeros((n, 3))
    w[(t >= 4.0) & (t < 6.0), 2] = 1.0  # a yaw turn
    z = np.zeros((n, 3))
    data = EquationData("x", t, np.ones(n, bool), z, z, np.tile([1.0, 0, 0, 0], (n, 1)), w, z, z,
                        np.zeros((n, 4)), 1, np.full(n, np.nan), np.full(n, 10.0), 0.02)
    k = 95
    win = SimpleNamespace(t=np.arange(k) * 0.2, t_end=np.arange(k) * 0.2 + 0.4)
    err = np.zeros((k, 6))  # per window, axes in mode units: throttle, roll, pitch, yaw
    err[20:26, 3] = [3.5, 5.0, 4.0, 2.0, 2.0, 3.2]   # 20-22 overlap (4.0-4.8 s), 25 alone (5.0-5.4 s)
    err[60, 1] = 4.0                             # a roll window at 12 s (hover)
    b = mode_basis(vp.rotors)
    R = np.column_stack([err[:, :4] @ np.linalg.pinv(b).T, np.zeros((k, 2))])  # as output_error lays them
    out = locate_output(data, win, R, vp)
    assert [(m["channel"], m["t_start"], m["t_end"], m["severity"]) for m in out] == [
        ("roll", 12.0, 12.4, 4.0), ("yaw", 4.0, 4.8, 5.0), ("yaw", 5.0, 5.4, 3.2)]
    assert all(m["residual"] == "output" for m in out)
    assert [m["regime"] for m in out] == ["hover", "yaw turn", "yaw turn"]


# ----------------------------------------------------------------------------- plans


def _likely_effect(name="yaw_moment", plans=("yaw_sweeps",), missing=6):
    return {"name": name, "verdict": "likely", "params": {"km": 0.028}, "verdict_note": "needs yaw blocks",
            "excitation": {"channel": "yaw", "plans": list(plans), "blocks_missing": missing}}


@pytest.mark.parametrize("kind", ["yaw_sweeps", "rate_doublets", "vertical_steps", "low_hover", "fast_legs"])
def test_every_manoeuvre_is_a_valid_plan(tmp_path, kind):
    e = _likely_effect(plans=(kind,))
    p = tmp_path / f"{kind}.plan.yaml"
    p.write_text(plan_yaml(plan_for(e, "x.ulg")))
    plan = load_plan(p)
    assert len(plan.waypoints) >= 5 and plan.rtl_after
    alts = [w.alt_m for w in plan.waypoints]
    if kind == "vertical_steps":
        assert max(alts) - min(alts) >= 9.0
    if kind == "low_hover":
        assert min(alts) <= 1.0


def test_yaw_sweeps_turn_at_every_stop():
    wps = manoeuvre("yaw_sweeps", 12)
    headings = []
    for a, b in zip(wps[:-1], wps[1:]):
        headings.append(np.degrees(np.arctan2(b["east_m"] - a["east_m"], b["north_m"] - a["north_m"])))
    turns = np.abs((np.diff(headings) + 180) % 360 - 180)
    assert np.sum(turns >= 80) >= 10
    assert all(not w["fly_through"] for w in wps)


def test_write_plans_one_file_per_likely_effect_and_mission_check_accepts_it(tmp_path):
    res = {"log": "f.ulg", "effects": [_likely_effect(), {"name": "mass", "verdict": "rejected", "params": {}},
                                       _likely_effect("inertia", ("rate_doublets", "yaw_sweeps"))]}
    paths = write_plans(res, tmp_path / "plans", "f.ulg")
    assert [p.name for p in paths] == ["confirm_yaw_moment.plan.yaml", "confirm_inertia.plan.yaml"]
    for p in paths:
        r = subprocess.run([sys.executable, "-m", "twin_nodes", "mission", "check", str(p)], capture_output=True,
                           text=True)
        assert r.returncode == 0, r.stderr
        assert "waypoints" in r.stdout and "RTL after: yes" in r.stdout


def test_plans_ask_for_rate_loop_logging_only_where_it_decides(tmp_path):
    """A likely inertia/lag/delay from a 50 Hz motor log gets a plan that says to log at the rate loop
    (measured on PX4 SIH: 4 ms logs separate lag from delay and resolve roll/pitch inertia); a yaw
    moment, or a flight already logged at the rate loop, does not."""
    res = {"log": "f.ulg", "effects": [_likely_effect(), _likely_effect("inertia", ("rate_doublets",))],
           "method": {"motor_log_interval_s": 0.02}}
    slow = write_plans(res, tmp_path / "slow", "f.ulg")
    texts = {p.name: p.read_text() for p in slow}
    assert "SDLOG_PROFILE" in texts["confirm_inertia.plan.yaml"] and "every 20 ms" in texts["confirm_inertia.plan.yaml"]
    assert "SDLOG_PROFILE" not in texts["confirm_yaw_moment.plan.yaml"]
    fast = write_plans({**res, "method": {"motor_log_interval_s": 0.004}}, tmp_path / "fast", "f.ulg")
    assert all("SDLOG_PROFILE" not in p.read_text() for p in fast)
    for p in slow:  # still a valid plan: the advice is a comment
        assert load_plan(p).rtl_after


def test_plan_setpoints_follow_the_plan():
    from twin_nodes.discovery.plan_flight import plan_setpoints

    wps = [(5.0, 0.0, 10.0, 2.0, False), (9.0, 0.0, 10.0, 2.0, False), (5.0, 0.0, 12.0, 2.0, False)]
    t, SP, armed = plan_setpoints(wps, rtl_after=True)
    ok = np.isfinite(SP[:, 0])
    # ENU: north is +y; the vehicle reaches (north 9, alt 10) and (north 5, alt 12)
    assert np.min(np.hypot(SP[ok, 1] - 9.0, SP[ok, 2] - 10.0)) < 0.05
    assert np.min(np.hypot(SP[ok, 1] - 5.0, SP[ok, 2] - 12.0)) < 0.05
    # yaw follows the path: north (pi/2) on the way out, south (-pi/2) on the way back
    yaw = SP[ok, 9]
    assert np.any(np.abs(yaw - np.pi / 2) < 0.01) and np.any(np.abs(np.abs(yaw) - np.pi / 2) < 0.01)
    assert armed(np.array([0.0]))[0] == False and armed(np.array([10.0]))[0] == True  # noqa: E712
    assert SP[-1, 2] < 0.0  # landed (the setpoint goes below ground, as PX4's land does)


# ----------------------------------------------------------------------------- round trip


HIDDEN_RT = "yaw_moment:km=0.023"
# a hop with two small heading changes (20 deg early, 70 deg mid-flight) and no return: the yaw
# moment is seen in the middle (both folds fit it) but the held-out parts hold too few yaw blocks.
# km 0.023 (nominal 0.020) leaves 3 active held-out blocks (too few for any test: likely); at 0.024
# and above, since the twin's vertical anti-windup (2026-11-23) changed this flight, 4 blocks with
# near-identical gains pass the t test and the effect is confirmed outright
HOP_PLAN = """mission:
  name: hop
  speed_m_s: 3.0
  acceptance_radius_m: 2.0
  fly_through: false
  rtl_after: false
  waypoints:
    - [2.2, 6.0, 10.0]
    - [2.2, 6.0, 16.0]
    - [2.2, 6.0, 10.0]
    - [8.2, 6.0, 10.0]
    - [8.2, 6.0, 16.0]
    - [8.2, 6.0, 4.0]
"""


def _cli(*args):
    r = subprocess.run([sys.executable, "-m", "twin_nodes", *args], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


@pytest.mark.slow
def test_confirmation_round_trip_on_our_simulator(tmp_path):
    """A short hop with a hidden effect: the effect comes out `likely` (too few excited blocks); the
    generated confirmation plan, flown with the same hidden effect, confirms it."""
    vp_file = str(ROOT / "params" / "px4_sih_quadx.yaml")
    hop = tmp_path / "hop.plan.yaml"
    hop.write_text(HOP_PLAN)
    first = tmp_path / "hop.ulg"
    _cli("simulate", "--params", vp_file, "--plan", str(hop), "--effect", HIDDEN_RT, "--seed", "5", "--out", str(first))
    plans = tmp_path / "plans"
    _cli("discover", str(first), "--params", vp_file, "--no-closed-loop", "--json", str(tmp_path / "d1.json"),
         "--plan-dir", str(plans))
    d1 = json.loads((tmp_path / "d1.json").read_text())
    name = HIDDEN_RT.split(":")[0]
    eff = next(e for e in d1["effects"] if e["name"] == name)
    assert eff["verdict"] == "likely", eff["evidence"]
    assert d1["likely"][0] == name and not d1["accepted"]
    plan = plans / f"confirm_{name}.plan.yaml"
    assert plan.exists()
    _cli("mission", "check", str(plan))
    followup = tmp_path / "followup.ulg"
    _cli("simulate", "--params", vp_file, "--plan", str(plan), "--effect", HIDDEN_RT, "--seed", "6", "--out",
         str(followup))
    _cli("discover", str(first), "--params", vp_file, "--no-closed-loop", "--confirm", str(followup), "--json",
         str(tmp_path / "d2.json"))
    d2 = json.loads((tmp_path / "d2.json").read_text())
    row = next(r for r in d2["confirmation"]["effects"] if r["name"] == name)
    assert row["verdict"] == "confirmed", row["note"]
    assert next(e for e in d2["effects"] if e["name"] == name)["verdict"] == "confirmed"
    true = dict(kv.split("=") for kv in HIDDEN_RT.split(":")[1].split(","))
    for k, v in true.items():
        assert row["refit_on_followup"]["params"][k] == pytest.approx(float(v), rel=0.10)
        assert eff["params"][k] == pytest.approx(float(v), rel=0.10)
    # the same plan flown by a vehicle without the effect: the likely effect is dropped
    clean = tmp_path / "followup_clean.ulg"
    _cli("simulate", "--params", vp_file, "--plan", str(plan), "--seed", "6", "--out", str(clean))
    _cli("discover", str(first), "--params", vp_file, "--no-closed-loop", "--confirm", str(clean), "--json",
         str(tmp_path / "d3.json"))
    d3 = json.loads((tmp_path / "d3.json").read_text())
    row = next(r for r in d3["confirmation"]["effects"] if r["name"] == name)
    assert row["verdict"] == "rejected" and row["note"].startswith("dropped"), row


def test_parameters_the_output_error_cannot_see_are_reported_as_held_at_nominal():
    """An inertia fit on the output error with the roll axis left out keeps ixx at nominal, and says
    so (JSON ``held_at_nominal``, the summary line) instead of reporting it as an identified value."""
    from twin_nodes.discovery.candidates import build_candidates
    from twin_nodes.discovery.discover import _restrict_to_axes
    from twin_nodes.discovery.residuals import prepare
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.vehicle.params import shipped
    vp = shipped("px4_sih_quadx")
    data = prepare(read_ulog(Path(__file__).resolve().parents[1] / "bags" / "sim_quadx_weak_motor3.ulg"), vp)
    c = next(c for c in build_candidates(vp, data) if c.name == "inertia")
    usable = np.array([False, False, True, False, True, True])
    r2 = np.array([0.1, 0.2, 0.95, 0.66, 0.9, 0.85])
    co = _restrict_to_axes(c, usable, r2)
    assert co.param_names == ("iyy", "izz")
    assert set(co.held) == {"ixx"} and "roll r^2 0.66 < 0.8" in co.held["ixx"]
    assert co.params_dict(np.array([0.04, 0.03]))["ixx"] == c.params_dict(c.x0)["ixx"]
    assert _restrict_to_axes(c, np.ones(6, bool), r2).held == {}
    from twin_nodes.discovery.report import _param_text
    e = {"held_at_nominal": dict(co.held)}
    assert _param_text(e, "ixx", 0.025).startswith("ixx=0.025 (held at nominal")
    assert _param_text(e, "iyy", 0.0381) == "iyy=0.0381"


def test_rank_and_parsimony_compare_effects_on_one_residual():
    """An effect reported with its equation-error fit (less biased parameters) ranks by its strongest
    accepted residual, and the simpler rival is judged against it on a residual both pass on (PX4 SIH
    e14, Izz x1.5: inertia's output-error cut 47 %, its equation-error cut 11 %, the yaw moment's
    output-error cut 27 %: the yaw moment used to win on 27 > 11)."""
    from twin_nodes.discovery.discover import _parsimonious, _pick

    class _Inertia(_Cand):
        name = label = "inertia"
        param_names = ("ixx", "iyy", "izz")

    rng = np.random.default_rng(0)
    n_blocks, per = 20, 10
    blocks = [np.arange(k * per, (k + 1) * per) for k in range(n_blocks)]
    R0 = 5.0 + 0.25 * rng.normal(size=(n_blocks * per, 6))   # output-error units: changes above OE_MIN_CHANGE

    def fit(cand, kind, rel, resid_scale, accepted=True):
        f = Fit(cand, np.array([0.03]), None, 0.0, 0.0, np.zeros(6), 6.0, n_blocks, rel, True)
        f.kind, f.accepted, f.R = kind, accepted, R0 * resid_scale
        return f

    in_eq, in_out = fit(_Inertia(), "equation", 0.11, 0.89), fit(_Inertia(), "output", 0.47, 0.53)
    ym_eq, ym_out = fit(_Cand(), "equation", 0.07, 0.93, accepted=False), fit(_Cand(), "output", 0.27, 0.73)
    inertia, yaw = _pick([in_eq, in_out]), _pick([ym_eq, ym_out])
    assert inertia is in_eq and inertia.rank == pytest.approx(0.47)   # parameters: equation; rank: output
    assert yaw is ym_out and yaw.rank == pytest.approx(0.27)
    kept = sorted([yaw, inertia], key=lambda f: -f.rank)
    assert kept[0] is inertia
    # parsimony: the yaw moment (1 parameter) against inertia (3), on the output error both pass on;
    # inertia's output residual is lower in every block, so it stays
    blocks_by_kind = {"equation": blocks, "output": blocks}
    assert _parsimonious(inertia, [inertia, yaw], blocks_by_kind) is inertia
    # equally good on that residual: the simpler one is kept
    in_out.R = ym_out.R.copy()
    assert _parsimonious(inertia, [inertia, yaw], blocks_by_kind) is yaw
    # no residual both pass on: nothing to compare, the winner stays
    in_out.accepted = False
    assert _parsimonious(inertia, [inertia, yaw], blocks_by_kind) is inertia


class _Inertia3:
    name = label = "inertia"
    param_names = ("ixx", "iyy", "izz")
    fixed: dict = {}
    x0 = np.array([0.025, 0.025, 0.030])
    lower = 0.2 * x0
    upper = 5.0 * x0

    def floor(self, th):
        return bool(np.max(np.abs(np.asarray(th) - self.x0) / self.x0) > 0.03)

    def params_dict(self, th):
        return dict(zip(self.param_names, map(float, th)))


def _fit3(kind, theta, cut, t, n, rel, channel="roll"):
    c = _Inertia3()
    th = np.array(theta, float)
    f = Fit(c, th, None, 0.0, 0.0, np.zeros(6), t, n, rel, c.floor(th))
    f.kind, f.judged = kind, (channel, 1.0, 1.0 - cut)
    f.stats = {"n": n, "n_pos": n - 1, "mean": 0.1, "sd": 0.2, "t": t}
    f.fold_thetas = [th, th]
    return f


def test_two_residuals_corroborate_a_roll_inertia_change():
    """PX4 SIH g34 (SIH_L_ROLL 0.2 -> 0.16 m: the roll moment x0.8, i.e. Ixx 0.025 -> 0.03125): the
    output error cuts the held-out roll error by 22 % over only 5 excited blocks (t 1.3), the
    equation error is significant (t 4.9 over 153 blocks) but its roll channel is the differentiated
    gyro (a 7 % cut); both fit Ixx 0.0304.  Together: ``likely``, reported with the equation error's
    parameters (it saw the roll axis); any one piece missing: rejected."""
    from twin_nodes.discovery.discover import _pick
    from twin_nodes.discovery.verdicts import corroboration

    ex = {"roll": {"blocks_heldout": 15, "blocks_heldout_total": 168, "manoeuvres": {"hover": 9}}}

    def pair(out_theta=(0.0304, 0.0257, 0.030), eq_theta=(0.0304, 0.0269, 0.0298), out_cut=0.22, eq_t=4.9,
             eq_fold=None):
        o = _fit3("output", out_theta, out_cut, 1.3, 5, 0.042)
        e = _fit3("equation", eq_theta, 0.065, eq_t, 153, 0.001)
        if eq_fold is not None:
            e.fold_thetas = [e.theta, np.array(eq_fold)]
            e.folds_agree = False
        return o, e

    o, e = pair()
    assert "t=4.9" in corroboration(o, e, 3.0)
    f = _pick([o, e])
    assert f is e                                   # the equation error's parameters are reported
    grade(f, 3.0, 0.1, ex)
    assert f.verdict == "likely", f.verdict_note
    assert "corroborate" in f.verdict_note and "roll" in f.verdict_note
    assert f.excitation["blocks_missing"] >= 1 and "rate_doublets" in f.excitation["plans"]
    # each piece on its own is not enough
    for kw in ({"eq_t": 2.5},                                  # equation error not significant
               {"out_cut": 0.10},                              # output error's cut too small
               {"eq_theta": (0.021, 0.025, 0.030)},            # the fits disagree in direction
               {"eq_theta": (0.0265, 0.025, 0.030)},           # ... or in size (x4 apart)
               {"out_theta": (0.0255, 0.025, 0.030)},          # next to nominal
               {"eq_fold": (0.020, 0.025, 0.030)}):            # the equation error's folds disagree
        o, e = pair(**kw)
        assert corroboration(o, e, 3.0) is None, kw
        f = _pick([o, e])
        grade(f, 3.0, 0.1, ex)
        assert f.verdict == "rejected", (kw, f.verdict_note)


def test_closed_loop_worse_means_beyond_the_runs_resolution():
    """An effect that does not act on the collective (an inertia, a yaw moment) moves the closed-loop
    held-out throttle RMSE by 1e-6 of full throttle: that is not 'worse' (PX4 SIH e11: 0.011723 -> 0.011724
    dropped the true inertia).  Above 0.5 % of the nominal's (or the best so far) it is."""
    from twin_nodes.discovery.discover import CLOSED_LOOP_TOL_REL, _worse
    assert CLOSED_LOOP_TOL_REL == 0.005
    assert not _worse(0.011724, 0.011723, 0.011723)
    assert _worse(0.0118, 0.011723, 0.011723)                  # +0.66 %
    assert not _worse(0.0270, 0.0274, 0.0274)                  # better
    # the limit never creeps: after an accepted effect that was a hair worse, the nominal's value still caps it
    assert _worse(0.01185, 0.01179, 0.01172)
    assert not _worse(0.01177, 0.01179, 0.01172)


@pytest.mark.slow
@pytest.mark.parametrize("change, resolved", [({"izz": 1.5}, set()), ({"ixx": 1.6}, {"ixx"})])
def test_each_roll_pitch_inertia_axis_stands_on_its_own_evidence(tmp_path, change, resolved):
    """The equation error fits every inertia axis at once; an axis is taken from it (where the output
    error leaves the axis out) only when freeing that axis alone beats the nominal on held-out blocks
    (discover._axis_tests, t > 3).  On our generator: Izz x1.5 moves no roll/pitch axis beyond that
    test; Ixx x1.6 passes it on roll and not on pitch.  (PX4 SIH, 50 Hz: Izz x1.5 on M3 read Ixx +17 %,
    Iyy +10 %, t 1.05 and 0.80, now held; IXX/IYY x1.5 on M4 gives Ixx t 3.89, supplied 0.0376 for 0.0375.)"""
    from twin_nodes.discovery.candidates import build_candidates
    from twin_nodes.discovery.discover import T_CRIT, _axis_tests, assess, prepare_flight
    from twin_nodes.twin.simflight import Hidden, write_flight
    vp = shipped("px4_sih_quadx")
    inertia = np.diag(vp.inertia)
    params = {k: float(inertia[i] * change.get(k, 1.0)) for i, k in enumerate(("ixx", "iyy", "izz"))}
    path = tmp_path / "flight.ulg"
    write_flight(path, vp, Hidden("inertia", params), 2024)
    S = prepare_flight(read_ulog(path), vp)
    c = next(c for c in build_candidates(vp, S.data) if c.name == "inertia")
    g = assess(c, S.eq, vp, S.eq.residual(vp))
    tests = _axis_tests(S, g)
    assert set(tests) == {"ixx", "iyy"}
    assert {a for a, (t, _) in tests.items() if t > T_CRIT} == resolved, tests


def test_the_explained_share_is_read_over_the_channels_the_candidate_changes():
    from twin_nodes.discovery.judging import _own_channel_cut
    rng = np.random.default_rng(3)
    # four motor channels with a yaw error the candidate removes, two force channels of accelerometer noise
    # it cannot touch: over all six channels the cut is diluted, over its own four it is 1 - 0.5 = 50 %
    R0 = np.column_stack([np.full(400, 0.02), np.full(400, -0.02), np.full(400, 0.02), np.full(400, -0.02),
                          rng.normal(0, 0.05, (400, 2))])
    R1 = R0.copy()
    R1[:, :4] *= 0.5
    assert _own_channel_cut(R0, R1) == pytest.approx(0.5, abs=1e-12)
    whole = 1 - np.sqrt(np.mean(R1 ** 2)) / np.sqrt(np.mean(R0 ** 2))
    assert whole < 0.25
    # a candidate that moves every channel, or none: no own-channel number (the whole residual decides)
    assert _own_channel_cut(R0, 0.9 * R0) is None and _own_channel_cut(R0, R0.copy()) is None
    f = Fit(None, np.zeros(1), None, 0.0, 0.0, np.zeros(6), 4.0, 100, float(whole), True)
    assert f.explains == pytest.approx(whole)
    f.own_cut = 0.5
    assert f.explains == 0.5 and f.rel_improvement == pytest.approx(whole)



def test_a_torque_s_share_is_read_over_the_modes_it_moves_not_the_collective():
    """A damping or yaw moment cannot move the collective: its share is read over the moment modes it moves
    (u017's shape: a yaw error a damping halves beside a collective error four times as large)."""
    from twin_nodes.discovery.judging import _own_channel_cut
    from twin_nodes.discovery.residuals import modes
    from twin_nodes.discovery.verdicts import moment_share
    from twin_nodes.vehicle.params import shipped

    nominal = shipped("px4_sih_quadx")
    rng = np.random.default_rng(7)
    n = 600
    b = mode_basis(nominal.rotors)
    collective, yaw = rng.normal(0, 0.04, n), rng.normal(0, 0.01, n)
    forces = rng.normal(0, 0.02, (n, 2))
    R0 = np.column_stack([np.outer(collective, b[0]) + np.outer(yaw, b[3]), forces])
    R1 = np.column_stack([np.outer(collective, b[0]) + np.outer(0.5 * yaw, b[3]), forces])
    m0, m1 = modes(R0, nominal)[0], modes(R1, nominal)[0]
    assert np.allclose(m1[:, 0], m0[:, 0]) and np.allclose(m1[:, 3], 0.5 * m0[:, 3])
    own = _own_channel_cut(R0, R1)              # the four motor channels: the collective dilutes it
    assert own == pytest.approx(1 - np.sqrt((0.04 ** 2 + 0.25 * 0.01 ** 2) / (0.04 ** 2 + 0.01 ** 2)), abs=0.01)
    assert own < 0.05
    rel = 1 - np.sqrt(np.mean(R1 ** 2)) / np.sqrt(np.mean(R0 ** 2))
    # over the yaw mode it moves: 1 - 0.5 = 50 %
    assert moment_share("angular_damping", "equation", R0, R1, nominal, own, rel) == pytest.approx(0.5, abs=1e-9)
    # not the inertia or the yaw moment (s500_rcac_mission1: verdicts.MOMENT_SHARE), not the output error, not
    # where the collective moves too
    assert moment_share("yaw_moment", "equation", R0, R1, nominal, own, rel) == own
    assert moment_share("inertia", "equation", R0, R1, nominal, own, rel) == own
    assert moment_share("angular_damping", "output", R0, R1, nominal, own, rel) == own
    R2 = R1.copy()
    R2[:, :4] += 0.001
    assert moment_share("angular_damping", "equation", R0, R2, nominal, own, rel) == own
    assert moment_share("angular_damping", "equation", R0, R1, nominal, None, rel) == pytest.approx(0.5, abs=1e-9)


def test_block_test_counts_only_the_blocks_a_regime_effect_reaches():
    """A ground effect changes the take-off's and the landing's blocks and leaves the other 48 a millionth as
    much: those 48 are not active (before, the 90th percentile of the changes fell among them and all 50 counted,
    their coin-flip gains drowning the two that carry the effect); a broad effect keeps every block."""
    from twin_nodes.discovery.blocktest import NEGLIGIBLE, _block_stats
    rng = np.random.default_rng(7)
    blocks = [np.arange(k * 10, (k + 1) * 10) for k in range(50)]
    R0 = rng.normal(0, 1e-3, (500, 4))
    R0[:10] += 0.05
    R0[-10:] += 0.03
    R1 = R0 + rng.normal(0, 1e-9, R0.shape)      # a change a millionth of the residual: noise
    R1[:10] -= 0.05
    R1[-10:] -= 0.03
    st = _block_stats(R0, R1, blocks)
    assert st["n"] == 2 and st["n_pos"] == 2 and st["t"] == 0.0   # too few for a test: 'likely' at most
    assert 1e-9 / 0.03 < NEGLIGIBLE
    # a broad effect (a tenth of the residual removed in every block): every block counts, as before
    wide = R0 - 0.1 * R0
    st = _block_stats(R0, wide, blocks)
    assert st["n"] == 50 and st["n_pos"] == 50 and st["t"] > 3


class _Lag(_Cand):
    """RotorPy's Crazyflie lag (0.072 s) on a 20 ms motor log: the floor is one logging interval."""

    name = "motor_time_constant"
    param_names = ["tau_up"]
    label = "motor_time_constant(tau_up = tau_down)"
    x0 = np.array([0.072])
    lower = np.array([0.01])
    upper = np.array([0.36])

    def floor(self, th):
        return abs(th[0] - 0.072) > 0.02

    def params_dict(self, th):
        return {"tau_up": float(th[0]), "tau_down": float(th[0])}


def _lag_fit(theta, folds, cand=_Lag):
    f = _fit(theta, 0.36, 2.87, 12, 11, folds=folds)
    f.candidate = cand()
    f.above_floor = bool(f.candidate.floor(np.array([theta])))
    f.judged = ("throttle", 1.0, 0.64)
    f.kind = "equation"
    return f


def test_lag_just_over_the_sampling_floor_resolved_by_its_folds():
    """x001 (judge8): a 1.3 x lag (0.0936 s) fitted 0.0945 s, folds 0.0945 / 0.0904 s, cut 36 %, t 2.9: half the
    0.022 s change is under the 20 ms floor and fold 2's 0.018 s change is too, yet the folds are 4 ms apart."""
    from twin_nodes.discovery.verdicts import FOLD_RESOLUTION, far_from_nominal, resolved_by_folds
    c = _Lag()
    th, folds = np.array([0.0945]), [np.array([0.0945]), np.array([0.0904])]
    assert not far_from_nominal(c, th)                       # the half-change bar alone
    assert resolved_by_folds(c, th, folds)                   # 0.0041 <= 0.25 * 0.0225 = 0.0056
    assert far_from_nominal(c, th, folds)
    assert FOLD_RESOLUTION == 0.25
    f = _lag_fit(0.0945, [0.0945, 0.0904])
    grade(f, 3.0, 0.1, {"throttle": {"blocks_heldout": 21}})
    assert f.verdict == "likely", f.verdict_note
    # folds 10 ms apart (0.0945 / 0.0845: 0.010 > 0.0056), opposite ways, or the change under the floor: rejected
    assert not resolved_by_folds(c, th, [np.array([0.0945]), np.array([0.0845])])
    assert not resolved_by_folds(c, th, [np.array([0.0945]), np.array([0.065])])
    assert not resolved_by_folds(c, np.array([0.080]), [np.array([0.080]), np.array([0.0795])])  # 8 ms < 10 ms
    for f in (_lag_fit(0.0945, [0.0945, 0.0845]), _lag_fit(0.080, [0.080, 0.0795])):
        grade(f, 3.0, 0.1, {"throttle": {"blocks_heldout": 21}})
        assert f.verdict == "rejected" and "not well away from nominal" in f.verdict_note
    # a floor that is a physical size (the yaw moment's 3 %) keeps the half-change bar
    y = _Cand()
    assert not resolved_by_folds(y, np.array([0.0212]), [np.array([0.0212]), np.array([0.0211])])
    assert not far_from_nominal(y, np.array([0.0212]), [np.array([0.0212]), np.array([0.0211])])


class _Delay(_Cand):
    """An actuator delay on a 20 ms motor log: nominal 0, the sampling floor one logging interval."""

    name = "actuator_delay"
    param_names = ["delay"]
    label = "actuator_delay"
    x0 = np.array([0.0])
    lower = np.array([0.0])
    upper = np.array([0.3])

    def floor(self, th):
        return th[0] > 0.02

    def params_dict(self, th):
        return {"delay": float(th[0])}


def _delay_fit(theta, folds, cut, t):
    f = _fit(theta, cut, t, 23, 22, folds=folds)
    from twin_nodes.discovery.verdicts import clears_floor
    f.candidate = _Delay()
    f.above_floor = clears_floor(f.candidate, np.array([theta]), f.fold_thetas)   # as judging sets it
    f.judged = ("throttle", 1.0, 1.0 - cut)
    f.kind = "equation"
    return f


def test_a_sub_sample_delay_resolved_by_its_folds_and_the_timing_background_not():
    """a007 (judge9, 1 kg quad, RP1 waypoints, truth 0.012 s on a 20 ms motor log): fitted 0.0118 s, folds
    0.0118 / 0.0120 s, held-out cut 63 %, t 9.7.  The change is over half the interval (``SUBSAMPLE_SHARE``)
    and the folds 0.24 ms apart (<= 0.25 x 11.8 ms): resolved.  The nominal's own timing background on the
    no-effect flights (a037/a039/a041, x039: 0.0018 s, folds identical, cut 42-46 %, t 3.5-3.9) and a
    motor lag read as a delay (a024: 0.0057 / 0.0059 s, t 6.6) are under half the interval: not resolved."""
    from twin_nodes.discovery.verdicts import SUBSAMPLE_SHARE, far_from_nominal, resolved_by_folds
    c = _Delay()
    assert SUBSAMPLE_SHARE == 0.5
    th, folds = np.array([0.0118]), [np.array([0.0118]), np.array([0.0120])]
    assert not c.floor(th) and not far_from_nominal(c, th)          # the interval alone rejects it
    assert resolved_by_folds(c, th, folds) and far_from_nominal(c, th, folds)
    f = _delay_fit(0.0118, [0.0118, 0.0120], 0.63, 2.9)               # under the 3-sigma test: likely
    grade(f, 3.0, 0.1, {"throttle": {"blocks_heldout": 23}})
    assert f.verdict == "likely", f.verdict_note
    for theta, fold in ((0.0018, [0.0018, 0.0018]), (0.0029, [0.0029, 0.0028]), (0.0057, [0.0057, 0.0059]),
                        (0.0099, [0.0099, 0.0099])):                   # all under 10 ms
        assert not resolved_by_folds(c, np.array([theta]), [np.array([x]) for x in fold])
        g = _delay_fit(theta, fold, 0.45, 2.9)
        grade(g, 3.0, 0.1, {"throttle": {"blocks_heldout": 23}})
        assert g.verdict == "rejected" and "not well away from nominal" in g.verdict_note
    # over half the interval, folds apart by more than a quarter of the change (SIH z006: 0.0114 / 0.0221 s)
    assert not resolved_by_folds(c, np.array([0.0114]), [np.array([0.0114]), np.array([0.0221])])
    assert not resolved_by_folds(c, np.array([0.0155]), [np.array([0.0155]), np.array([0.0083])])


def test_a_delay_fitted_with_the_accepted_sag_refitted_is_resolved_by_its_own_folds():
    """RotorPy o032 (judge13, 1 kg quad, RP2 figure-eight, battery sag + 24 ms delay on a 20 ms motor log): the sag
    is confirmed in round 1; round 2 keeps the delay's joint variant (:mod:`~twin_nodes.discovery.stages.joint`:
    delay, v_ref, exponent free together), fitted 0.02407 s, folds 0.02407 / 0.02432 s, held-out cut 98 % in yaw,
    t 2.75 over 8 blocks.  Half the change (12 ms) is under the interval; the folds are 0.25 ms apart (<= 0.25 x
    24 ms), as for a plain delay, so it is ``likely``.  Before, the variant's three parameters kept it from the
    fold reading and it was rejected as "not well away from nominal"."""
    from twin_nodes.discovery.candidates import Candidate
    from twin_nodes.discovery.stages.joint import Linearized, variant
    from twin_nodes.discovery.verdicts import clears_floor, far_from_nominal, resolved_by_folds
    plain = Candidate("actuator_delay", ("delay",), np.array([0.0]), np.array([0.0]), np.array([0.3]),
                      lambda th: None, {}, lambda th: th[0] > 0.02, "actuator_delay")
    sag = Linearized(["battery_sag"], [("v_ref", "exponent")], np.array([16.8, 0.99]), np.array([10.0, 0.0]),
                     np.array([30.0, 3.0]), np.empty(0), [])
    c = variant(plain, sag, [])
    assert c.param_names == ("delay", "v_ref", "exponent") and c.label == "actuator_delay (+battery_sag refitted)"
    th = np.array([0.024065, 16.8, 0.9918])
    folds = [th, np.array([0.024317, 16.8, 0.9775])]
    assert c.floor(th) and not c.floor(c.x0 + 0.5 * (th - c.x0))     # 24 ms > 20 ms, 12 ms is not
    assert resolved_by_folds(c, th, folds) and far_from_nominal(c, th, folds) and clears_floor(c, th, folds)
    assert resolved_by_folds(plain, th[:1], [f[:1] for f in folds])  # the same reading as the plain delay
    # folds 7 ms apart (> 0.25 x 24 ms = 6 ms) or the change under half the interval: not resolved, as for a plain one
    assert not resolved_by_folds(c, th, [th, np.array([0.0311, 16.8, 0.99])])
    assert not resolved_by_folds(c, np.array([0.0095, 16.8, 0.99]), [np.array([0.0095, 16.8, 0.99])] * 2)
    f = Fit(c, th, None, 0.0, 0.0, np.zeros(6), 2.75, 8, 0.9123, clears_floor(c, th, folds))
    f.judged, f.kind = ("yaw", 1.0, 1.0 - 0.9841), "equation"
    f.stats = {"n": 8, "n_pos": 8, "mean": 0.1, "sd": 0.1, "t": 2.75}
    f.fold_thetas, f.folds_agree, f.accepted = folds, True, False
    grade(f, 3.0, 0.1, {"yaw": {"blocks_heldout": 6}})
    assert f.verdict == "likely", f.verdict_note


def _held(t_log: np.ndarray, u_log: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The logged command held between samples (what the motors see), read at times ``t``."""
    k = np.clip(np.searchsorted(t_log, t, side="right") - 1, 0, len(t_log) - 1)
    return u_log[k]


def test_a_delay_of_a_fraction_of_a_sample_moves_the_residual_and_both_folds_find_it():
    """Synthetic known truth: a command logged every 20 ms acts through a first-order motor (0.05 s) 12 ms
    late; the response is logged every 20 ms with noise.  Fitting the delay on each half of the flight
    (the model's own motor fed the logged command, delay on a 1 ms grid) finds 0.012 s on both, within
    1 ms: a delay of 0.6 samples is not below what the log resolves; its folds agree within
    ``FOLD_RESOLUTION`` of the change and it clears ``SUBSAMPLE_SHARE`` of the interval."""
    from twin_nodes.discovery.verdicts import FOLD_RESOLUTION, resolved_by_folds
    rng = np.random.default_rng(12)
    dt_log, dt, tau, true_delay = 0.02, 0.001, 0.05, 0.012
    t_log = np.arange(0.0, 60.0, dt_log)
    steps = np.repeat(rng.uniform(0.3, 0.7, len(t_log) // 25 + 1), 25)[: len(t_log)]   # a step every 0.5 s
    u_log = steps + 0.02 * rng.standard_normal(len(t_log))                             # the controller's jitter
    t = np.arange(0.0, 60.0, dt)

    def motor(delay):
        u = _held(t_log, u_log, t - delay)
        y = np.empty_like(u)
        y[0] = u[0]
        a = dt / tau
        for i in range(1, len(u)):
            y[i] = y[i - 1] + a * (u[i] - y[i - 1])
        return y[::int(round(dt_log / dt))]

    y_log = motor(true_delay) + 0.003 * rng.standard_normal(len(t_log))
    grid = np.arange(0.0, 0.031, 0.001)
    models = [motor(d) for d in grid]
    halves = (t_log < 30.0, t_log >= 30.0)
    fits = [float(grid[int(np.argmin([np.mean((y_log[h] - m[h]) ** 2) for m in models]))]) for h in halves]
    assert all(abs(f - true_delay) <= 0.001 for f in fits), fits
    # the residual the delay leaves when it is not modelled is several times the noise
    rms_nominal = float(np.sqrt(np.mean((y_log - models[0]) ** 2)))
    rms_true = float(np.sqrt(np.mean((y_log - models[12]) ** 2)))
    assert rms_nominal > 3 * rms_true, (rms_nominal, rms_true)
    assert abs(fits[0] - fits[1]) <= FOLD_RESOLUTION * true_delay
    assert resolved_by_folds(_Delay(), np.array([fits[0]]), [np.array([f]) for f in fits])


class _YawMoment:
    name = label = "yaw_moment"
    param_names = ("km",)
    fixed: dict = {}
    x0 = np.array([0.03391])            # RotorPy's Crazyflie, c029's nominal
    lower = 0.2 * x0
    upper = 5.0 * x0

    def floor(self, th):
        return bool(abs(float(th[0]) - self.x0[0]) / self.x0[0] > 0.03)

    def params_dict(self, th):
        return {"km": float(th[0])}


def test_a_yaw_moment_s_share_over_the_yaw_mode_counts_where_the_output_error_corroborates_it():
    """RotorPy c029 (mass x1.15 with wind): on top of a thrust coefficient 0.87 the yaw moment that reading needs
    (km 0.0339 -> 0.0391, the yaw torque it scales) explains 0.6 % of the four motor channels but 86 % of the yaw
    mode, and the output error corroborates it (87 % held-out cut in yaw, km 0.0390); its share is read over the
    yaw mode, so it passes.  The shared real log s500_rcac_mission1 has no output-error yaw reading: its yaw
    moment keeps the per-channel share (7.5 %) and is not accepted (``verdicts.CORROBORATED_SHARE``)."""
    from types import SimpleNamespace

    from twin_nodes.discovery.judging import _own_channel_cut
    from twin_nodes.discovery.stages.judge import _corroborated
    from twin_nodes.discovery.verdicts import corroborated_share, mode_share, moment_share

    nominal = shipped("px4_sih_quadx")
    rng = np.random.default_rng(11)
    n = 800
    b = mode_basis(nominal.rotors)
    collective, yaw = rng.normal(0, 0.04, n), rng.normal(0, 0.01, n)
    R0 = np.column_stack([np.outer(collective, b[0]) + np.outer(yaw, b[3]), rng.normal(0, 0.02, (n, 2))])
    test = np.zeros(n, bool)
    test[200:400] = test[600:] = True                  # both folds' held-out rows
    Rcv = np.zeros_like(R0)
    Rcv[test] = R0[test]
    Rcv[test, :4] -= np.outer(0.86 * yaw[test], b[3])  # the yaw mode cut 86 %
    own = _own_channel_cut(R0[test], Rcv[test])
    assert own < 0.05
    assert mode_share("yaw_moment", "equation", R0[test], Rcv[test], nominal) == pytest.approx(0.86, abs=1e-9)
    # the damping keeps its share over the modes whatever the output error; the yaw moment not on its own
    assert moment_share("yaw_moment", "equation", R0[test], Rcv[test], nominal, own, 0.005) == own
    assert mode_share("inertia", "equation", R0[test], Rcv[test], nominal) is None

    def fits(out_cut=0.87, out_km=0.0390, eq_t=3.89):
        c = _YawMoment()
        e = Fit(c, np.array([0.03905]), None, 0.0, 0.0, np.zeros(6), eq_t, 18, 0.006, c.floor([0.03905]))
        e.kind, e.judged, e.own_cut, e.R = "equation", ("yaw", 1.0, 0.14), own, Rcv
        e.fold_thetas = [e.theta, np.array([0.0399])]
        e.accepted = e.passes
        o = Fit(c, np.array([out_km]), None, 0.0, 0.0, np.zeros(6), 3.86, 12, 0.013, c.floor([out_km]))
        o.kind, o.judged = "output", ("yaw", 1.0, 1.0 - out_cut)
        o.fold_thetas = [o.theta, o.theta]
        return e, o

    e, o = fits()
    assert not e.accepted                               # 0.6 % of the motor channels: under the 10 % bar
    assert corroborated_share(e, o, R0, test, nominal, 3.0) == pytest.approx(0.86, abs=1e-9)
    _corroborated({"yaw_moment": [e, o]}, R0, SimpleNamespace(folds=[(~test, test)]), nominal)
    assert e.accepted and e.own_cut == pytest.approx(0.86, abs=1e-9)
    # s500_rcac_mission1: no output-error fit; an output error that cuts the yaw mode under 15 %; fits moving km
    # different ways; an equation error under the 3-sigma bar: the share stays the motor channels'
    for kw in ({"out_cut": 0.10}, {"out_km": 0.0300}, {"eq_t": 2.9}):
        e, o = fits(**kw)
        assert corroborated_share(e, o, R0, test, nominal, 3.0) is None, kw
        _corroborated({"yaw_moment": [e, o]}, R0, SimpleNamespace(folds=[(~test, test)]), nominal)
        assert not e.accepted and e.own_cut == own, kw
    e, _ = fits()
    assert corroborated_share(e, None, R0, test, nominal, 3.0) is None
    _corroborated({"yaw_moment": [e]}, R0, SimpleNamespace(folds=[(~test, test)]), nominal)
    assert not e.accepted and e.own_cut == own


def _md_fit(name, theta, cut, vp, base_vp):
    """A ``likely`` equation-error motor-dynamics fit (plain candidate) and its effect entry."""
    from twin_nodes.discovery.candidates import Candidate
    names = ("delay",) if name == "actuator_delay" else ("tau_up",)
    tied = {} if name == "actuator_delay" else {"tau_down": "tau_up"}
    c = Candidate(name, names, np.array([0.0]), np.array([0.0]), np.array([0.3]), lambda th: None, {},
                  lambda th: True, name, tied=tied)
    f = Fit(c, np.array([theta]), vp, 0.0, 0.0, np.zeros(6), 2.8, 8, cut, True)
    f.kind, f.verdict, f.base_vp = "equation", "likely", base_vp
    e = {"name": name, "verdict": "likely", "verdict_note": "", "params": c.params_dict(f.theta), "alternatives": []}
    return f, e


@pytest.mark.parametrize("given, paired", [({"cut": -1.4094, "t": -2.8}, True),   # RotorPy o032's lag on the delay
                                           ({"cut": 0.35, "t": 2.4}, False),       # a lag that adds to the delay
                                           ({"cut": 0.35, "t": 1.2}, True),        # a cut, not borne out by blocks
                                           ({"cut": 0.05, "t": 4.0}, True)])       # significant, but too small
def test_a_likely_lag_beside_a_likely_delay_is_its_pair_unless_it_adds_given_it(monkeypatch, given, paired):
    """RotorPy o032 (judge13, sag + a 24 ms delay): round 2 offered the delay and a motor lag each on top of the
    sag, neither refitted given the other: the delay cut 91 % (fitted 0.02407 s), the lag 46 % (tau 0.0736 s, no
    lag flown), both ``likely``.  Given the delay and the sag (:func:`stages.joint.contributions` on the delay's
    vehicle with the lag added), the lag's held-out cut is -141 % at t -2.8: it is the delay's not-told-apart
    pair (with rate doublets to separate them), not a finding.  A lag still cutting >= 10 % at t > 1.5 given the
    delay is kept beside it; a lag fitted on top of the delay (its base carries it) is not looked at."""
    from twin_nodes.discovery.stages import verdicts as V
    vp0 = shipped("px4_sih_quadx")
    with_delay = vp0.with_effect("actuator_delay", delay=0.02407)
    seen = []

    def fake(eq, vp, fits):
        seen.append(({n: dict(p) for n, p in vp.effects}, [f.candidate.name for f in fits]))
        return {len(fits) - 1: {**given, "residual": "equation"}}

    monkeypatch.setattr(V, "contributions", fake)
    d = _md_fit("actuator_delay", 0.02407, 0.9123, with_delay, vp0)
    lag = _md_fit("motor_time_constant", 0.0736, 0.4623, vp0.with_effect("motor_time_constant", tau_up=0.0736,
                                                                            tau_down=0.0736), vp0)
    v = V.Verdicts([lag[0], d[0]], [lag[1], d[1]], [])
    rows = V.lag_delay_pair(v, None, [])
    assert rows and rows[0]["kept"] == "actuator_delay" and rows[0]["other"] == "motor_time_constant"
    eff, names = seen[0]
    assert names == ["actuator_delay", "motor_time_constant"]
    assert eff["actuator_delay"]["delay"] == pytest.approx(0.02407)
    assert eff["motor_time_constant"]["tau_up"] == pytest.approx(0.0736)
    if paired:
        assert [e["verdict"] for e in v.effects] == ["likely", "rejected"] and v.ranked[0] is d[0]
        pair = d[1]["not_told_apart"]
        assert pair["with"]["name"] == "motor_time_constant" and pair["manoeuvre"] == "rate_doublets"
        assert pair["with"]["params"]["tau_up"] == pytest.approx(0.0736) and pair["plan_flyable"]
        assert lag[1]["verdict_note"].startswith("not told apart from actuator_delay")
    else:
        assert [e["verdict"] for e in v.effects] == ["likely", "likely"] and "not_told_apart" not in d[1]
        assert lag[1]["given_the_other"]["given_the_other"]["t"] == pytest.approx(given["t"])
    # the lag fitted on top of the delay: already judged given it, not looked at again
    lag2 = _md_fit("motor_time_constant", 0.0736, 0.4623, with_delay, with_delay)
    d2 = _md_fit("actuator_delay", 0.02407, 0.9123, with_delay, vp0)
    assert V.lag_delay_pair(V.Verdicts([d2[0], lag2[0]], [d2[1], lag2[1]], []), None, []) == []
