"""The motors' lag and the roll/pitch inertia read together by PX4's rate loop (``stages/lag_inertia``): each
read alone absorbs the other (PX4 SIH SIH_T_TAU 0.08 with IXX/IYY x1.3), the joint minimum separates them."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest

from twin_nodes.discovery import rate_loop as rl
from twin_nodes.discovery.stages import lag_inertia as li
from twin_nodes.vehicle.params import shipped

PX4_SIH = {"MC_ROLLRATE_P": 0.15, "MC_ROLLRATE_I": 0.2, "MC_ROLLRATE_D": 0.003, "MC_ROLLRATE_K": 1.0,
           "MC_PITCHRATE_P": 0.15, "MC_PITCHRATE_I": 0.2, "MC_PITCHRATE_D": 0.003, "MC_PITCHRATE_K": 1.0,
           "MC_YAWRATE_P": 0.2, "MC_YAWRATE_I": 0.1, "MC_YAWRATE_K": 1.0, "MC_YAW_TQ_CUTOFF": 2.0,
           "IMU_GYRO_CUTOFF": 40.0, "IMU_DGYRO_CUTOFF": 20.0, "IMU_GYRO_RATEMAX": 800.0, "IMU_INTEG_RATE": 250.0,
           "CA_ROTOR0_KM": 0.05}


def _flight(tau: float, scale: float, K: int = 100, n: int = 50, seed: int = 3):
    """Windows flown by the rate loop with the motors' lag ``tau`` and roll/pitch inertia x ``scale`` (yaw x1),
    with per-window integrator offsets, initial rates and gyro noise, side by side as one log."""
    rng = np.random.default_rng(seed)
    loop = rl.rate_loop(PX4_SIH, shipped("px4_sih_quadx"))
    true = dataclasses.replace(loop, tau_s=tau)
    dt = 0.02
    w, sp = np.zeros((K, n + 1, 3)), np.zeros((K, n + 1, 3))
    for ax in range(3):
        x = np.cumsum(rng.normal(size=(K, n + 1)), axis=1) * 0.15
        sp[..., ax] = x - x.mean(1, keepdims=True)
        tr = rl.simulate(true, ax, sp[..., ax], dt, np.array([scale if ax < 2 else 1.0]))[0]
        w[..., ax] = (tr[0] + rng.normal(0, 0.05, (K, 1)) * tr[1] + rng.normal(0, 0.2, (K, 1)) * tr[3]
                      + rng.normal(0, 0.01, tr[0].shape))
    data = types.SimpleNamespace(w=w.reshape(-1, 3), w_sp=sp.reshape(-1, 3), dt=dt)
    idx = np.arange(K * (n + 1)).reshape(K, n + 1)
    k = np.arange(K)
    masks = (k >= 0, k < 0.7 * K, k >= 0.7 * K, k >= 0.3 * K, k < 0.3 * K)
    return loop, data, idx, masks


@pytest.mark.parametrize("tau, scale, lag, axes", [(0.08, 1.3, True, True), (0.08, 1.0, True, False),
                                                    (0.05, 1.3, False, True)])
def test_the_lag_and_the_inertia_are_read_apart(tau, scale, lag, axes):
    loop, data, idx, masks = _flight(tau, scale)
    assert loop.tau_s == pytest.approx(0.05)
    E = li.window_errors(loop, data, idx)
    r = li.joint_from_errors(E, masks, loop.tau_s)
    assert r["tau"] == pytest.approx(tau, rel=0.04)
    for a in li.RP:
        assert r["axes"][a]["scale"] == pytest.approx(scale, rel=0.03)
        assert r["axes"][a]["flagged"] is axes
    assert r["lag_flagged"] is lag
    held = r["heldout_relative_sse"]
    assert held["both"] <= min(held["inertia"], held["lag"]) + 1e-3
    if lag and axes:
        # read alone at the model's lag, the inertia absorbs the lag (x1.3 reads > x1.38): the joint minimum does not
        Q = E["roll"].sum(-1)
        s_alone = np.exp(rl.parabola_min(li._row(Q, np.log(li.JOINT_TAUS), np.log(0.05)), np.log(rl.SCALES))[0])
        assert s_alone > 1.38
        assert held["both"] < held["inertia"] - 0.02 and held["both"] < held["lag"] - 0.02


def _reading(tau: float, roll: float, pitch: float, flagged=(True, True), lag=True) -> dict:
    return {"tau": tau, "tau_fold1": tau, "tau_fold2": tau, "model_tau": 0.05, "windows": 100,
            "axis_tau": {"roll": tau, "pitch": tau, "yaw": tau}, "lag_flagged": lag,
            "axes": {"roll": {"scale": roll, "flagged": flagged[0]}, "pitch": {"scale": pitch, "flagged": flagged[1]}},
            "heldout_relative_sse": {}, "heldout": {a: {"before": 1.0, "after": 0.1, "cut": 0.9, "t": 5.0}
                                                    for a in ("roll", "pitch", "yaw", "joint")}}


def _stage(monkeypatch, reading: dict, effects: list[dict], current, guard=lambda vp: None):
    monkeypatch.setattr(li, "joint_reading", lambda *a: reading)
    S = types.SimpleNamespace(nominal=shipped("px4_sih_quadx"), data=None, log_params=PX4_SIH, t_split=0.0,
                              t_split2=0.0)
    return li.read_together(S, current, effects, guard)


def test_an_inertia_that_absorbed_the_lag_is_read_again_beside_it(monkeypatch):
    """h019's class: the inertia confirmed at x1.47/x1.42, the lag rejected: both named at the joint reading."""
    vp = shipped("px4_sih_quadx")
    current = vp.with_effect("inertia", ixx=0.03674, iyy=0.03557, izz=0.03096)
    inertia = {"name": "inertia", "verdict": "confirmed", "params": {"ixx": 0.03674, "iyy": 0.03557, "izz": 0.03096}}
    lag = {"name": "motor_time_constant", "verdict": "rejected", "params": {"tau_up": 0.0776, "tau_down": 0.0776},
           "residuals": {"output": {"heldout_improvement": 0.1}}}
    effects = [inertia, lag]
    new, out = _stage(monkeypatch, _reading(0.0817, 1.269, 1.295), effects, current)
    assert out["verdict"] == "lag and inertia"
    named = next(e for e in effects if e["name"] == "motor_time_constant")
    assert named["verdict"] == "likely" and named["params"]["tau_up"] == pytest.approx(0.0817)
    assert set(named["residuals"]) == {"output", "rate_loop_joint"} and effects[1] is named
    assert inertia["params"]["ixx"] == pytest.approx(0.025 * 1.269) and inertia["params"]["iyy"] == pytest.approx(0.025 * 1.295)
    assert inertia["params"]["izz"] == 0.03096 and inertia["own_params"]["ixx"] == 0.03674
    assert dict(new.effect_dict)["inertia"]["ixx"] == pytest.approx(0.025 * 1.269)
    # the closed-loop check objecting: nothing changes
    inertia2 = dict(inertia, params={"ixx": 0.03674, "iyy": 0.03557, "izz": 0.03096})
    inertia2.pop("own_params")
    effects2 = [inertia2, dict(lag)]
    new2, out2 = _stage(monkeypatch, _reading(0.0817, 1.269, 1.295), effects2, current, guard=lambda vp: "diverges")
    assert new2 is None and out2["why_not"] == "diverges" and inertia2["params"]["ixx"] == 0.03674
    assert effects2[1]["verdict"] == "rejected"


def test_a_lag_read_as_a_likely_inertia_is_named_as_the_lag(monkeypatch):
    """s013's class: SIH_T_TAU 0.08 alone read as roll/pitch x1.25/x1.22 on the model's lag."""
    inertia = {"name": "inertia", "verdict": "likely", "params": {"ixx": 0.025, "iyy": 0.0314, "izz": 0.03}}
    effects = [inertia]
    new, out = _stage(monkeypatch, _reading(0.0794, 1.033, 0.995, flagged=(False, False)), effects,
                      shipped("px4_sih_quadx"))
    assert new is None and out["verdict"] == "lag, the inertia rejected"
    assert inertia["verdict"] == "rejected"
    assert [e["name"] for e in effects if e["verdict"] == "likely"] == ["motor_time_constant"]
    # a confirmed inertia the joint reading does not bear out, or a lag it does not flag: left as they are
    confirmed = {"name": "inertia", "verdict": "confirmed", "params": {"ixx": 0.03, "iyy": 0.025, "izz": 0.03}}
    _, out = _stage(monkeypatch, _reading(0.0794, 1.0, 1.0, flagged=(False, False)), [confirmed], shipped("px4_sih_quadx"))
    assert confirmed["verdict"] == "confirmed" and "why_not" in out
    _, out = _stage(monkeypatch, _reading(0.055, 1.3, 1.3, lag=False), [confirmed], shipped("px4_sih_quadx"))
    assert out["verdict"] == "none" and confirmed["params"]["ixx"] == 0.03
    # no inertia finding: not read (a lag alone is its own readings')
    assert _stage(monkeypatch, _reading(0.0794, 1.0, 1.0), [], shipped("px4_sih_quadx")) == (None, None)
