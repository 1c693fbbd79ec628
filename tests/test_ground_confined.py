"""A confined effect judged beside refitted partners (gnd10): the block test counts the blocks its own term acts in
(``judging.own_change``, ``blocktest._block_stats(change=)``), and a ground effect read from under a second near the
ground is reported as a product, not as two determined parameters (``stages.ground.pinned``, ``MIN_LOW_S``)."""

import numpy as np
import pytest

from twin_nodes.discovery.blocktest import _block_stats
from twin_nodes.discovery.stages import ground


def _flight(n_blocks=40, rows=25, seed=0):
    """A residual of ``n_blocks`` blocks; an effect acting in the first and the last two blocks (a take-off and a
    landing) and a partner's re-balance (a thrust coefficient's small shift) on every block, of random help."""
    rng = np.random.default_rng(seed)
    blocks = [np.arange(k * rows, (k + 1) * rows) for k in range(n_blocks)]
    R0 = 0.01 * rng.standard_normal((n_blocks * rows, 1))
    own = np.zeros_like(R0)
    for k in (0, n_blocks - 2, n_blocks - 1):
        own[blocks[k]] = 0.05                 # the effect: the nominal's miss near the ground, taken out
        R0[blocks[k]] += 0.05
    shift = 0.004 * rng.standard_normal((n_blocks, 1)).repeat(rows, axis=0)   # the partner's re-balance
    R1 = R0 - own + shift
    return R0, R1, -own, blocks


def test_partners_rebalance_does_not_count_as_the_effects_blocks():
    R0, R1, change, blocks = _flight()
    plain = _block_stats(R0, R1, blocks)
    # judged on R1 - R0, the blocks the partner moved count: 25 of 40 active, about half of them worse
    assert plain["n"] >= 20 and plain["n_pos"] < 0.75 * plain["n"]
    own = _block_stats(R0, R1, blocks, change=change)
    # judged where its own term acts: the three near-ground blocks, each improved (too few for the 3-sigma test)
    assert own["n"] == 3 and own["n_pos"] == 3 and own["t"] == 0.0
    assert own["mean"] == pytest.approx(np.mean([np.mean(R0[b] ** 2) - np.mean(R1[b] ** 2)
                                                 for b in (blocks[0], blocks[-2], blocks[-1])]))


def test_a_block_carrying_more_partner_than_effect_is_not_the_effects():
    R0, R1, change, blocks = _flight()
    change = change.copy()
    change[blocks[5]] = 1e-3                  # the effect barely reaches block 5 (2 % of its largest change) ...
    R1[blocks[5]] += 1e-3
    R1[blocks[5]] += 0.01                     # ... where the partner moves the prediction ten times as much
    st = _block_stats(R0, R1, blocks, change=change)
    assert st["n"] == 3
    change[blocks[5]] = 0.02                  # where its own term dominates, the block is the effect's
    assert _block_stats(R0, R1, blocks, change=change)["n"] == 4


def test_no_change_argument_is_the_old_test():
    R0, R1, _, blocks = _flight(seed=4)
    assert _block_stats(R0, R1, blocks) == _block_stats(R0, R1, blocks, change=R1 - R0)


def test_under_a_second_near_the_ground_pins_a_product_only():
    # k016's shape: one Crazyflie take-off and landing through the reach, 0.42 s within 3 height scales
    up = np.linspace(0.0, 1.4, 70)            # 1.4 s climb at 50 Hz: 0.45 m reached in 0.46 s
    h = np.concatenate([up, np.full(2500, 1.4), up[::-1]])
    out = ground.pinned(h, 0.448, 0.143, 0.02)
    assert out["low_s"] == pytest.approx(0.02 * (h < 3 * 0.143).sum()) and out["low_s"] < ground.MIN_LOW_S
    assert out["spread_scales"] >= ground.MIN_SPREAD_SCALES      # spread enough, too short
    assert out["determined"] is False and "only" in out["note"] and "two low heights" in out["note"]
    assert out["gain_at_h_ref"] == pytest.approx(0.448 * np.exp(-out["h_ref_m"] / 0.143), abs=1e-3)
    slow = np.concatenate([np.linspace(0.0, 1.4, 700), np.full(2500, 1.4)])   # a 14 s climb: 4.6 s in reach
    assert ground.pinned(slow, 0.448, 0.143, 0.02)["determined"] is True
