"""Issue 26, batch 7's j017 (PX4 SIH SIH_T_TAU 0.05 -> 0.08 with SIH_L_ROLL 0.2 -> 0.17, M1, 50 Hz logs): on the
model's lag PX4's rate loop read roll x1.41 and pitch x1.18 with yaw x1.06 the same way ("the motors, not the
inertia"), the lag was named by ``rate_loop_lag``, and the inertia was never read again.
``stages.instrument._inertia_beside_lag`` reads it on the vehicle with that lag.  The rate loop is replaced by
j017's measured readings (roll x1.186 +- 0.031 on the lag's vehicle, folds x1.213 / x1.169, held-out 0.52 ->
0.017 along the sensitivity), so the rule's checks run on the numbers the flight gave."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from twin_nodes.discovery import rate_loop
from twin_nodes.discovery.stages import instrument
from twin_nodes.physics.effects import effective_params
from twin_nodes.vehicle.params import shipped

LAG = 0.0796     # the rate loop's lag on j017 (fold 1)


def _axis(s, se, s1, s2, b, a):
    return {"index": 3, "gain": 1 / s, "se": se / s ** 2, "scale": s, "scale_se": se,
            "gain_fold1": 1 / s1, "se_fold1": 1.3 * se / s1 ** 2, "gain_fold2": 1 / s2, "se_fold2": 1.3 * se / s2 ** 2,
            "flagged": bool(abs(s - 1) > max(rate_loop.MIN_CHANGE, rate_loop.MIN_SE * se)),
            "heldout_before": b, "heldout_after": a, "heldout_t": 3.6, "heldout_t_after": 0.1}


def _reading(roll, pitch, yaw):
    def inertia(d, p, vp, t1, t2, axes_allowed=("roll", "pitch")):
        ep = effective_params(vp)
        on_lag = ep.rotors.tau_up_s > 0.07
        axes = {"roll": _axis(*roll) if on_lag else _axis(1.41, 0.04, 1.42, 1.40, 0.9, 0.1),
                "pitch": _axis(*pitch) if on_lag else _axis(1.18, 0.02, 1.19, 1.17, 0.5, 0.1)}
        ys, yse = yaw if on_lag else (1.06, 0.019)
        out = {"method": "rate_loop", "loop": "fake", "windows": 300, "window_s": 2.0, "curve": {}, "axes": axes,
               "yaw_scale": ys, "yaw_scale_se": yse, "yaw_gain": 1 / ys, "yaw_se": yse / ys ** 2, "pinned": []}
        out["flagged"] = [a for a, x in axes.items() if x["flagged"]]
        out["motor_signature"] = rate_loop.motor_signature(axes, out["flagged"], ys, yse)
        I0 = np.diag(ep.inertia).astype(float)
        out["params"] = {"ixx": float(I0[0] * (roll[2] if "roll" in out["flagged"] else 1)),
                         "iyy": float(I0[1] * (pitch[2] if "pitch" in out["flagged"] else 1)), "izz": float(I0[2])}
        return out
    return inertia


def _flight(monkeypatch, roll, pitch=(1.014, 0.016, 1.02, 1.01, 0.3, 0.29), yaw=(1.015, 0.020)):
    monkeypatch.setattr(rate_loop, "inertia", _reading(roll, pitch, yaw))
    nominal = shipped("px4_sih_quadx")
    t = np.arange(0.0, 100.0, 2.0)
    S = SimpleNamespace(data=SimpleNamespace(motor_dt_s=0.02), log_params={}, t_split=70.0, t_split2=30.0,
                        nominal=nominal, windows=SimpleNamespace(t=t, t_end=t + 2.0, axis_r2=[0.9, 0.9, 0.9, 0.56, 0.76, 0.9]))
    effects = [{"name": "motor_time_constant", "verdict": "likely", "residual": "rate_loop",
                "params": {"tau_up": LAG, "tau_down": LAG}},
               {"name": "inertia", "verdict": "rejected", "params": {"ixx": 0.0316}}]
    return S, nominal, effects


def test_j017_roll_inertia_named_beside_the_rate_loop_lag(monkeypatch):
    S, nominal, effects = _flight(monkeypatch, roll=(1.186, 0.031, 1.213, 1.169, 0.52, 0.017))
    out = instrument._inertia_beside_lag(S, nominal, [], effects, lambda vp: None)
    assert out["verdict"] == "likely" and out["flagged"] == ["roll"] and out["lag_s"] == pytest.approx(LAG)
    assert not out["motor_signature"]
    assert out["heldout_improvement"] == pytest.approx(1 - 0.017 / 0.52, abs=1e-4)   # 97 %
    e = next(e for e in effects if e["name"] == "inertia")
    assert e["verdict"] == "likely" and e["residual"] == "rate_loop"
    I0 = np.diag(effective_params(nominal).inertia)
    assert e["params"]["ixx"] == pytest.approx(I0[0] * 1.213, rel=1e-3)   # fold 1's roll: x1.213
    assert e["params"]["iyy"] == pytest.approx(I0[1])                     # pitch unflagged: the model's
    assert "motor lag it named (0.080 s)" in e["verdict_note"]
    assert [x["name"] for x in effects].count("inertia") == 1


def test_nothing_added_on_a_lag_alone_or_beside_an_inertia_finding(monkeypatch):
    # a lag alone: on the lag's vehicle roll/pitch read x1.02 +- 0.03 (under the 10 % flag)
    S, nominal, effects = _flight(monkeypatch, roll=(1.02, 0.03, 1.03, 1.01, 0.3, 0.29))
    out = instrument._inertia_beside_lag(S, nominal, [], effects, lambda vp: None)
    assert out["verdict"] == "none" and out["flagged"] == []
    assert next(e for e in effects if e["name"] == "inertia")["verdict"] == "rejected"
    # flagged, but the held-out cut is 10 % (< 30 %)
    S, nominal, effects = _flight(monkeypatch, roll=(1.186, 0.031, 1.213, 1.169, 0.52, 0.468))
    out = instrument._inertia_beside_lag(S, nominal, [], effects, lambda vp: None)
    assert out["verdict"] == "none" and any("held-out cut" in w for w in out["why_not"])
    # an inertia already a finding, or a lag the flight's own residuals named: not read again here
    S, nominal, effects = _flight(monkeypatch, roll=(1.186, 0.031, 1.213, 1.169, 0.52, 0.017))
    effects[1]["verdict"] = "likely"
    assert instrument._inertia_beside_lag(S, nominal, [], effects, lambda vp: None) is None
    effects[1]["verdict"], effects[0]["residual"] = "rejected", "output_error"
    assert instrument._inertia_beside_lag(S, nominal, [], effects, lambda vp: None) is None
