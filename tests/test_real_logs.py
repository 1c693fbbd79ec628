"""Real PX4 flights out of the box (slow): every shared real log runs ``compare`` and ``discover``
with no ``--params`` (the nominal is built from the log), and what discovery accepts on a real log
improves both the equation error and the closed-loop held-out throttle RMSE.  The measured table is
docs/real_logs.md (``rotortwin survey ../shared/flightlogs/real --md docs/real_logs_table.md``)."""

from __future__ import annotations

import json
import math

import pytest

from conftest import need_log, shared_log, ulog_params
from twin_nodes.cli import main
from twin_nodes.discovery.survey import survey_flight

pytestmark = pytest.mark.slow


#: docs/real_logs.md's table, after discovery's refit (throttle RMSE, per-motor P75 mean, XY RMSE m,
#: Z RMSE m on the held-out part); re-measured here within 3 % (or 0.002 / 0.01 m).  Values re-measured 2026-11-27
#: (seventh session, main b6556cf, `survey ../shared/flightlogs/real --json`; the table was stale since the fifth
#: session's changes, slow tests are not in `make test`).  Earlier: branch permotor
#: (static trims made from the whole model, identify/static_trims.py, with main's take-off/touchdown phases read from
#: the whole flight): per-motor P75 against main 06961cf cubeorange 2.48 -> 2.58, climb35m 7.64 -> 8.13, 2hops
#: 3.92 -> 3.97, noload 3.49 -> 3.40, S500 mission1 4.95 -> 4.82, mission2 3.05 -> 3.00, X500 4.17 -> 4.06
#: (climb35m's split moves across its vortex-ring event: its held-out part holds another roll trim than its median,
#: docs/real_logs.md "Per-motor error: the class")
TABLE = {
    "real_cubeorange_takeoff_land": (0.0041, 0.0258, 0.035, 0.020),  # 2026-11-27: linear_drag refitted (the nominal's isotropic drag too strong vertically)
    "real_quadx_v6c_climb35m": (0.0303, 0.0748, 0.242, 2.082),  # 2026-11-27: 5.5 s saturated left out; its 0.5 s of MANUAL flown with the pilot stand-in
    "real_quadx_v6c_mission_2hops": (0.0182, 0.0381, 0.347, 0.040),  # 2026-11-27: the second take-off from the ground the vehicle stood on
    # 2026-11-28 (branch quadx14): the take-off spot left out of the identification (identify/fit_mask.on_spot);
    # before it noload (0.0128, 0.0318, 0.254, 0.052), S500 mission1 (0.0263, 0.0489, 0.247, 0.459), mission2
    # (0.0192, 0.0317, 0.385, 0.118)
    "real_quadx_v6c_mission_noload": (0.0128, 0.0321, 0.301, 0.054),
    "real_s500_rcac_mission1": (0.0255, 0.0412, 0.342, 0.461),
    "real_s500_rcac_mission2": (0.0149, 0.0287, 0.372, 0.114),
    "real_x500v2_mission_rtl": (0.0208, 0.0388, 0.238, 0.132),
    "sitl_iris_takeoff_land": (0.0046, 0.0053, 0.026, 0.018),  # 2026-11-27: PX4's take-off ramp
}
#: the one flight above a target (docs/real_logs.md, "What is not met"): its real throttle's own content
#: above 0.5 Hz is 3.3 % RMS on the held-out part, over the 3 % target; Z is made by a vortex-ring descent
NOT_MET = {"real_quadx_v6c_climb35m": {"motor_p75_mean", "z_rmse_m"}}  # throttle 3.0 % <= 1.25 x its 3.3 % > 0.5 Hz


@pytest.mark.parametrize("log", ulog_params("real"))
def test_real_log_compare_and_discover_without_params(log, tmp_path, capsys):
    path = need_log(log)
    out = tmp_path / "c.json"
    assert main(["compare", "--offline", str(path), "--json", str(out)]) == 0
    m = json.loads(out.read_text())
    assert math.isfinite(m["throttle_rmse"]) and m["n_samples"] > 100
    err = capsys.readouterr().err
    assert "params:" in err  # one line saying which params flew

    row = survey_flight(path)
    b, a = row["before"], row["after"]
    for eff in row["accepted"]:
        assert eff["params"], eff
    if row["accepted"]:
        # a vocabulary effect lowers the equation error; a stage-9 term (physics outside the list) is
        # judged on the closed-loop twin's held-out throttle, which it must lower
        vocab = [e for e in row["accepted"] if e.get("name", e.get("effect")) != "state_term"]
        if vocab:
            assert row["equation_error_after"] < row["equation_error_before"]
        else:
            assert row["equation_error_after"] <= row["equation_error_before"]
            assert a["throttle_rmse"] < b["throttle_rmse"]
        assert a["throttle_rmse"] <= b["throttle_rmse"]
    else:
        assert a == {k: b[k] for k in a}
    # the twin built from the log is a working twin, not a placeholder: beside the paper's 5.2 %
    assert b["throttle_rmse"] < 0.08 and b["xy_rmse_m"] < 1.0
    # the documented table, and which targets it meets
    from twin_nodes.discovery.survey import meets_targets

    keys = ("throttle_rmse", "motor_p75_mean", "xy_rmse_m", "z_rmse_m")
    for k, want, floor in zip(keys, TABLE[row["flight"]], (0.002, 0.002, 0.01, 0.01)):
        assert a[k] == pytest.approx(want, rel=0.03, abs=floor), (k, a[k], want)
    failed = {k for k, ok in meets_targets(a).items() if not ok}
    assert failed == NOT_MET.get(row["flight"], set()), failed


def test_twin_flies_px4_manual_modes_and_the_identified_wind():
    """climb35m: 0.5 s in PX4 MANUAL at 8 % thrust (nav_state 0) before the POSCTL descent flown on velocity
    setpoints only (PX4 PositionControl: a NaN position adds nothing, nothing corrects a height offset); the
    twin flies the logged thrust there, which lowers its held-out Z error (2.64 m before; 1.78 m when this was written,
    2.08 m since the twin reads the logged setpoint trajectory between its samples, docs/corpus.md).  X500: the steady
    wind and the drag's line of action found from the log itself bring the per-motor P75 under 5 % (6.0 before)."""
    from twin_nodes.discovery.discover import _closed_loop_metrics
    from twin_nodes.identify.nominal import nominal_from_log
    from twin_nodes.logs.ulog_io import read_ulog

    log = read_ulog(shared_log("real", "real_quadx_v6c_climb35m.ulg"))
    nom = nominal_from_log(log)
    m = _closed_loop_metrics(log, nom.params, 47.9, 65.6)
    assert m["z_rmse_m"] < 2.2 and m["xy_rmse_m"] < 0.5

    log = read_ulog(shared_log("real", "real_x500v2_mission_rtl.ulg"))
    nom = nominal_from_log(log)
    wind = dict(dict(nom.params.effects)["wind"])
    assert abs(wind["vx"]) < 0.5 and -2.5 < wind["vy"] < -1.5          # ~2 m/s from the north
    assert 0.1 < nom.params.rotors.z_flu_m[0] < 0.25                   # the drag acts well above the CoM
    m = _closed_loop_metrics(log, nom.params, 50.6, 75.8)
    assert m["motor_p75_mean"] < 0.05 and m["throttle_rmse"] < 0.03


def test_s500_twin_flies_the_yaw_law_its_firmware_applied():
    """S500 mission1 (RCAC fork, RCAC off): its rate setpoints show a yaw gain of MC_YAW_P x MC_YAW_WEIGHT
    (1.2, not 2.8).  The nominal flies it, and the closed-loop per-motor P75 on the held-out part falls
    (measured 5.9 -> 5.5 %) with XY and throttle unchanged; discovery's rotor drag then brings it to 4.95 %."""
    from twin_nodes.discovery.discover import _closed_loop_metrics
    from twin_nodes.identify.nominal import nominal_from_log
    from twin_nodes.logs.ulog_io import read_ulog

    log = read_ulog(shared_log("real", "real_s500_rcac_mission1.ulg"))
    vp = nominal_from_log(log).params
    assert 1.1 < vp.controller["yaw_p_1_s"] < 1.3
    stock = vp.replace(controller={**vp.controller, "yaw_p_1_s": log.params["MC_YAW_P"]})
    a = _closed_loop_metrics(log, stock, 36.0, 52.3)
    b = _closed_loop_metrics(log, vp, 36.0, 52.3)
    assert b["motor_p75_mean"] < a["motor_p75_mean"] - 0.002
    assert b["xy_rmse_m"] < a["xy_rmse_m"] + 0.02 and b["throttle_rmse"] < a["throttle_rmse"] + 0.001
