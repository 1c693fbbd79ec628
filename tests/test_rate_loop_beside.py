"""An axis beside a larger flagged one (``rate_loop.beside_flagged``, rll12): PX4's rate loop reads an axis the
flight left at x1 at 1.011 +- 0.045 (0.91-1.15) on PX4 SIH batches 1-8, the same beside a roll arm as on no-effect
flights, so an axis flagged beside a larger one must move ``MIN_CHANGE_BESIDE`` (0.15); z011 (roll arm x1.18):
roll x1.16, pitch x1.10 flagged (Iyy 14.5 % off) before, unflagged now."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest

from twin_nodes.discovery import rate_loop as rl
from twin_nodes.discovery.stages import lag_inertia as li
from twin_nodes.vehicle.params import shipped

from tests.test_lag_and_inertia_together import PX4_SIH


def _axes(roll: float, pitch: float, se: float = 0.02) -> dict:
    return {a: {"scale": s, "scale_se": se, "flagged": abs(s - 1) > max(rl.MIN_CHANGE, rl.MIN_SE * se)}
            for a, s in (("roll", roll), ("pitch", pitch))}


@pytest.mark.parametrize("roll, pitch, flagged", [
    (1.159, 1.1016, ["roll"]),            # z011: the roll arm x1.18 and pitch read 10 % high
    (1.381, 0.880, ["roll"]),             # low beside high: within 0.15 of x1
    (1.30, 1.28, ["roll", "pitch"]),      # IXX/IYY x1.3 (j018 1.27/1.28)
    (1.30, 1.16, ["roll", "pitch"]),      # beyond 0.15 beside
    (1.11, 1.0, ["roll"]),                # one axis alone: MIN_CHANGE as before
    (1.0, 1.103, ["pitch"]),              # j007 (damping): alone, unchanged by this rule
    (1.02, 0.98, []),
])
def test_an_axis_beside_a_larger_flagged_one_needs_min_change_beside(roll, pitch, flagged):
    axes = _axes(roll, pitch)
    assert rl.MIN_CHANGE_BESIDE == pytest.approx(0.15)
    assert rl.beside_flagged(axes) == flagged
    for a in ("roll", "pitch"):
        assert axes[a]["flagged"] is (a in flagged)
    dropped = [a for a in ("roll", "pitch") if "beside" in axes[a]]
    assert dropped == [a for a in ("roll", "pitch") if abs(axes[a]["scale"] - 1) > rl.MIN_CHANGE
                       and a not in flagged and len(flagged) == 1]


def _flight(roll: float, pitch: float, K: int = 100, n: int = 50, seed: int = 5):
    """Windows flown by PX4's rate loop on roll/pitch inertia x ``roll`` / x ``pitch`` (yaw x1, the model's lag)."""
    rng = np.random.default_rng(seed)
    loop = rl.rate_loop(PX4_SIH, shipped("px4_sih_quadx"))
    dt = 0.02
    w, sp = np.zeros((K, n + 1, 3)), np.zeros((K, n + 1, 3))
    for ax, s in enumerate((roll, pitch, 1.0)):
        x = np.cumsum(rng.normal(size=(K, n + 1)), axis=1) * 0.15
        sp[..., ax] = x - x.mean(1, keepdims=True)
        tr = rl.simulate(loop, ax, sp[..., ax], dt, np.array([s]))[0]
        w[..., ax] = tr[0] + rng.normal(0, 0.2, (K, 1)) * tr[3] + rng.normal(0, 0.01, tr[0].shape)
    data = types.SimpleNamespace(w=w.reshape(-1, 3), w_sp=sp.reshape(-1, 3), dt=dt)
    idx = np.arange(K * (n + 1)).reshape(K, n + 1)
    k = np.arange(K)
    return loop, data, idx, (k >= 0, k < 0.7 * K, k >= 0.7 * K, k >= 0.3 * K, k < 0.3 * K)


@pytest.mark.parametrize("pitch, flagged", [(1.12, False), (1.25, True)])
def test_the_joint_lag_and_inertia_reading_keeps_the_rule(pitch, flagged):
    loop, data, idx, masks = _flight(1.3, pitch)
    r = li.joint_from_errors(li.window_errors(loop, data, idx), masks, loop.tau_s)
    assert r["axes"]["roll"]["scale"] == pytest.approx(1.3, rel=0.03) and r["axes"]["roll"]["flagged"]
    assert r["axes"]["pitch"]["scale"] == pytest.approx(pitch, rel=0.03)
    assert r["axes"]["pitch"]["flagged"] is flagged
    assert ("beside" in r["axes"]["pitch"]) is (not flagged)
