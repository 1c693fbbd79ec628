"""Issue 26, a motor lag beside a roll/pitch inertia on PX4 SIH: the flight's own residuals fit the lag before the
inertia is in the model, so a slower roll/pitch is partly read as slower motors (h019: SIH_T_TAU 0.08 s read
0.098 s) and the inertia, read on that lag, comes out short.  ``stages.motor_lag.beside_inertia`` reads the two again
on PX4's rate loop, alternately, each on the vehicle carrying the other.  Here the rate loop is replaced by a linear
coupling with a known fixed point (h019's measured slopes), so the alternation's closed form is known."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from twin_nodes.discovery import rate_loop
from twin_nodes.discovery.stages import motor_lag
from twin_nodes.physics.effects import effective_params
from twin_nodes.vehicle.params import shipped

TAU, IXX = 0.08, 0.0325          # the truth
A = 0.5                          # lag read on the vehicle: TAU + A (TAU / IXX) (IXX - ixx) ... s per unit inertia share
B = 0.5                          # inertia read on the lag: ixx scale 1 + B (tau - TAU) / TAU ... around the truth


def _lag_read(vp):
    ixx = float(effective_params(vp).inertia[0, 0])
    tau = TAU + A * TAU * (IXX - ixx) / IXX
    return {"model_tau": 0.5 * (effective_params(vp).rotors.tau_up_s + effective_params(vp).rotors.tau_down_s),
            "tau": tau, "se": 0.001, "tau_fold1": tau, "se_fold1": 0.001, "tau_fold2": tau, "se_fold2": 0.001,
            "heldout_before": 1.0, "heldout_after": 0.2, "heldout_sse": {"lag": 1.0, "delay": 2.0},
            "delay_fold1": 0.0, "axis_tau": {"roll": tau, "pitch": tau, "yaw": tau}, "flagged": False}


def _inertia_read(vp):
    ep = effective_params(vp)
    tau = 0.5 * (ep.rotors.tau_up_s + ep.rotors.tau_down_s)
    out = {}
    for a, j in (("roll", 0), ("pitch", 1)):
        want = IXX * (1.0 + B * (tau - TAU) / TAU)       # what a loop with this lag asks for
        out[a] = {"gain_fold1": float(ep.inertia[j, j]) / want}
    return {"axes": out, "pinned": []}


def _flight(monkeypatch):
    monkeypatch.setattr(rate_loop, "motor_lag", lambda d, p, vp, t1, t2: _lag_read(vp))
    monkeypatch.setattr(rate_loop, "inertia", lambda d, p, vp, t1, t2, axes_allowed=("roll", "pitch"): _inertia_read(vp))
    nominal = shipped("px4_sih_quadx")
    S = SimpleNamespace(data=None, log_params={}, t_split=1.0, t_split2=0.5, nominal=nominal)
    current = (nominal.with_effect("motor_time_constant", tau_up=0.098, tau_down=0.098)
               .with_effect("inertia", ixx=0.0313, iyy=0.0313, izz=0.03))
    effects = [{"name": "motor_time_constant", "verdict": "confirmed", "params": {"tau_up": 0.098, "tau_down": 0.098}},
               {"name": "inertia", "verdict": "confirmed", "params": {"ixx": 0.0313, "iyy": 0.0313, "izz": 0.03}}]
    return S, current, effects


def test_lag_and_inertia_read_again_alternately_converge_on_the_closed_form(monkeypatch):
    S, current, effects = _flight(monkeypatch)
    new = motor_lag.beside_inertia(S, current, effects, lambda vp: None)
    assert new is not None
    # the alternation's error shrinks by A B per round: lag, inertia, lag, inertia, lag (two rounds)
    e_i = (0.0313 - IXX) / IXX
    tau1 = TAU - A * TAU * e_i                         # first lag read, on the finding's inertia
    i1 = IXX * (1 + B * (tau1 - TAU) / TAU)
    tau2 = TAU + A * TAU * (IXX - i1) / IXX
    i2 = IXX * (1 + B * (tau2 - TAU) / TAU)
    ep = effective_params(new)
    assert ep.rotors.tau_up_s == pytest.approx(tau2, rel=1e-9)
    assert ep.inertia[0, 0] == pytest.approx(i2, rel=1e-9) and ep.inertia[1, 1] == pytest.approx(i2, rel=1e-9)
    assert abs(tau2 - TAU) == pytest.approx((A * B) * abs(tau1 - TAU), rel=1e-9)
    assert ep.inertia[2, 2] == pytest.approx(0.03)  # yaw is not read again
    lag_e, in_e = effects
    assert lag_e["params"]["tau_up"] == pytest.approx(tau2) and lag_e["own_params"]["tau_up"] == 0.098
    assert in_e["params"]["ixx"] == pytest.approx(i2) and in_e["own_params"]["ixx"] == 0.0313
    assert abs(tau2 - TAU) < 0.03 * TAU and abs(i2 - IXX) < 0.01 * IXX


def test_nothing_changes_when_the_closed_loop_check_objects_or_there_is_no_inertia(monkeypatch):
    S, current, effects = _flight(monkeypatch)
    assert motor_lag.beside_inertia(S, current, effects, lambda vp: "the twin diverges") is None
    assert effects[0]["params"]["tau_up"] == 0.098 and "own_params" not in effects[1]
    assert effects[0]["rate_loop_beside_inertia"]["not_used"] == ["the twin diverges"]
    S, current, effects = _flight(monkeypatch)
    assert motor_lag.beside_inertia(S, current, effects[:1], lambda vp: None) is None


def test_a_lag_the_rate_loop_reads_as_the_findings_is_left_alone(monkeypatch):
    S, current, effects = _flight(monkeypatch)
    at_truth = current.with_effect("inertia", ixx=IXX, iyy=IXX, izz=0.03)
    effects[0]["params"] = {"tau_up": TAU, "tau_down": TAU}
    at_truth = at_truth.with_effect("motor_time_constant", tau_up=TAU, tau_down=TAU)
    assert motor_lag.beside_inertia(S, at_truth, effects, lambda vp: None) is None
    assert any("within" in w for w in effects[0]["rate_loop_beside_inertia"]["not_used"])
    assert math.isfinite(effects[0]["rate_loop_beside_inertia"]["tau"])


def test_the_rate_loops_lag_is_read_on_the_vehicle_carrying_a_likely_roll_pitch_inertia():
    """A ``likely`` inertia is not in the refit vehicle; the lag is read with its roll/pitch (m017), yaw as it was."""
    vp = shipped("px4_sih_quadx")
    effects = [{"name": "inertia", "verdict": "likely", "params": {"ixx": 0.025, "iyy": 0.0309, "izz": 0.0303}}]
    on = motor_lag._with_inertia_finding(vp, effects)
    assert [float(effective_params(on).inertia[j, j]) for j in range(3)] == pytest.approx([0.025, 0.0309, 0.03])
    # a rejected finding, or a vehicle already carrying an inertia: unchanged
    assert motor_lag._with_inertia_finding(vp, [dict(effects[0], verdict="rejected")]) is vp
    carried = vp.with_effect("inertia", ixx=0.03, iyy=0.03, izz=0.03)
    assert motor_lag._with_inertia_finding(carried, effects) is carried
