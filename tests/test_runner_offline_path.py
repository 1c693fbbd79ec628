"""The offline runner's fast loop (run_twin_on_log) is the streaming engine, bit for bit.

``run_twin_on_log`` feeds a whole log through :class:`TwinRunner` without the per-sample work
of the public inputs (the real state rows and their finiteness made once, repeated setpoint
samples skipped, no TwinSample objects).  The live twin node drives the same runner through
``real_state``/``setpoint``/``advance_to``.  Both must give the same twin to the last bit, in
both modes, on a simulated flight and on a real one with a MANUAL segment and a ground offset.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.conftest import shared_log
from twin_nodes.identify.nominal import params_for_log
from twin_nodes.logs.ulog_io import read_ulog
from twin_nodes.twin.inputs import armed_rows, log_inputs, setpoint_rows
from twin_nodes.twin.runner import TwinRunner, run_twin_on_log
from twin_nodes.vehicle.params import load_params

ROOT = Path(__file__).resolve().parents[1]


def _streamed(log, vp, mode: str, t0: float, t1: float) -> dict[str, np.ndarray]:
    """The twin driven through the runner's public inputs, one log sample at a time."""
    runner = TwinRunner(vp, mode)
    data = log_inputs(log, runner.rate_hz, t0, t1)
    t = data["t"]
    n = len(t)
    sp = setpoint_rows(data, n)
    armed = armed_rows(data, n)
    batt = np.asarray(data["battery_v"]).reshape(n) if "battery_v" in data else np.full(n, np.nan)
    nav = np.asarray(data["nav_state"]).reshape(n) if "nav_state" in data else np.full(n, np.nan)
    thr = np.asarray(data["throttle"]).reshape(n) if "throttle" in data else np.full(n, np.nan)
    def col(name: str, k: int) -> np.ndarray:
        return np.asarray(data[name], float).reshape(n, k) if name in data else np.full((n, k), np.nan)
    att_q, att_thr, att_yr = col("attitude_setpoint_q", 4), col("attitude_setpoint_thrust", 1), col(
        "attitude_setpoint_yawrate", 1)
    rates, offb = col("setpoint_rates_flu", 3), col("offboard_mode", 6)
    out = []
    for k in range(n):
        runner.real_state(t[k], data["position_enu"][k], data["velocity_enu"][k], data["attitude_q"][k],
                          data["body_rates_flu"][k])
        runner.real_motors(data["motors"][k])
        runner.setpoint(sp[k])
        runner.armed(float(armed[k]))
        runner.px4_mode(nav[k], thr[k])
        runner.attitude_setpoint(att_q[k], att_thr[k, 0], att_yr[k, 0])
        runner.rate_setpoint(rates[k])
        runner.offboard_mode(offb[k])
        if np.isfinite(batt[k]):
            runner.battery(batt[k])
        if k + 1 < n:
            out += runner.advance_to(t[k + 1])
    return {"t": np.array([s.t for s in out]), "x": np.array([s.x for s in out]),
            "motors": np.array([s.motors for s in out]), "throttle": np.array([s.throttle for s in out]),
            "specific_force": np.array([s.specific_force for s in out])}


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return a.shape == b.shape and bool(np.all(a.view(np.uint64) == b.view(np.uint64)))


@pytest.mark.parametrize("mode", ["closed", "open"])
@pytest.mark.parametrize("flight, params, t0, t1", [
    (ROOT / "bags" / "sim_quadx_weak_motor3.ulg", ROOT / "params" / "px4_sih_quadx.yaml", None, 40.0),
    # a MANUAL segment (41.9-42.5 s) and a take-off height 3.8 m off the EKF origin
    ("real/real_quadx_v6c_climb35m.ulg", None, 30.0, 55.0),
], ids=["demo", "climb35m"])
def test_offline_loop_equals_streaming_inputs(flight, params, t0, t1, mode):
    if isinstance(flight, str):
        flight = shared_log(*flight.split("/"))
    pf, _ = params_for_log(str(flight), None if params is None else str(params))
    vp = load_params(pf)
    log = read_ulog(flight)
    fast = run_twin_on_log(log, vp, mode=mode, t0=t0, t1=t1)
    ref = _streamed(log, vp, mode, t0, t1)
    assert len(ref["t"]) > 1000
    for key in ("t", "x", "motors", "throttle", "specific_force"):
        assert _same_bits(getattr(fast, key), ref[key]), key


def test_open_loop_rejects_a_motor_vector_of_the_wrong_size_closed_loop_ignores_it():
    """Open loop flies the real motor commands (the model's unchecked step needs N of them); the
    closed loop flies its own and never reads them (a 16-channel output vector is harmless)."""
    vp = load_params(ROOT / "params" / "px4_sih_quadx.yaml")
    for mode in ("open", "closed"):
        runner = TwinRunner(vp, mode)
        runner.real_state(0.0, [0, 0, 0], [0, 0, 0], [1, 0, 0, 0], [0, 0, 0])
        runner.real_motors([0.5, 0.5, 0.5])
        runner.armed(True)
        if mode == "open":
            with pytest.raises(ValueError, match="expected 4 motor commands"):
                runner.advance_to(0.1)
        else:
            assert len(runner.advance_to(0.1)) == 25
