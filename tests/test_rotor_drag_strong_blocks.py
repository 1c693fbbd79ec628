"""A rotor drag on a fast-descent mission (rdr16): its held-out blocks read over the blocks that carry its change
strongly (``blocktest.STRONG_SHARE``, ``verdicts.strong_blocks_favour``), and its share read over the
horizontal-force channels (``verdicts.force_share``)."""

import numpy as np
import pytest

from twin_nodes.discovery.blocktest import STRONG_SHARE, _block_stats
from twin_nodes.discovery.judging import Fit
from twin_nodes.discovery.verdicts import FORCE_SHARE_MIN, force_share, likely_failures, moment_share, strong_blocks_favour


DESCENT = (3, 11, 12, 30)


def _descents(n_blocks=40, rows=25, seed=0, loss=6e-4, gains=(0.0105, 0.00495, 0.0159, 0.0013)):
    """A force_y residual shaped as i002's held-out part: the nominal misses the drag on 4 descent blocks (each
    taken out by the refit, to a noise of 5e-4); on every other block the refit adds ``loss`` (the logged
    velocity's error times the extra k_d)."""
    rng = np.random.default_rng(seed)
    blocks = [np.arange(k * rows, (k + 1) * rows) for k in range(n_blocks)]
    R0 = 5e-4 * rng.standard_normal((n_blocks * rows, 1))
    R1 = R0.copy()
    for k, g in zip(DESCENT, gains):
        R0[blocks[k]] += g
    for k in range(n_blocks):
        if k not in DESCENT:
            R1[blocks[k]] += loss * np.sign(R0[blocks[k]].mean() + 1e-12)
    return R0, R1, blocks


def test_strong_blocks_are_the_descents_and_every_one_improves():
    R0, R1, blocks = _descents()
    st = _block_stats(R0, R1, blocks)
    # every block is active (the loss is 3.8 % of the largest change, over NEGLIGIBLE and 25 % of the 90th
    # percentile, which the 36 losing blocks set), 4 of 40 improved: no test passes, most blocks do not favour it
    assert st["n"] == 40 and st["n_pos"] == 4 and st["t"] < 1.5
    assert st["n_strong"] == 3 and st["pos_strong"] == 3 and st["mean"] > 0
    assert STRONG_SHARE == 0.25
    assert strong_blocks_favour(st)
    # one strong block only, or a strong block that loses, or the active blocks losing on the whole: not favoured
    assert not strong_blocks_favour({"n_strong": 1, "pos_strong": 1, "mean": 1e-5})
    assert not strong_blocks_favour({"n_strong": 3, "pos_strong": 2, "mean": 1e-5})
    assert not strong_blocks_favour({"n_strong": 3, "pos_strong": 3, "mean": -1e-7})
    # losses as large as the gains' blocks: those blocks are strong too, and lose
    st = _block_stats(*_descents(loss=6e-3))
    assert st["n_strong"] > 3 and st["pos_strong"] < st["n_strong"] and not strong_blocks_favour(st)


class _Drag:
    param_names = ("k_d",)
    fixed: dict = {}
    x0 = np.array([1.025e-6])
    lower = np.array([0.205e-6])
    upper = np.array([5.125e-6])

    def __init__(self, name):
        self.name = self.label = name

    def floor(self, th):
        return abs(th[0] - 1.025e-6) / 1.025e-6 > 0.10


def _fit(name, kind="equation"):
    R0, R1, blocks = _descents()
    c = _Drag(name)
    th = np.array([1.627e-6])
    f = Fit(c, th, None, 0.0, 0.0, np.zeros(6), 1.4, 40, 0.755, True)
    f.kind = kind
    f.judged = ("force_y", 0.00925, 0.00115)   # i002's held-out force_y, 88 % cut
    f.stats = _block_stats(R0, R1, blocks)
    f.fold_thetas = [th, np.array([1.633e-6])]
    return f


def test_only_a_rotor_drag_on_the_equation_error_is_read_over_its_strong_blocks():
    assert "held-out blocks do not favour it" not in likely_failures(_fit("rotor_drag"), 3.0, 0.1)
    assert likely_failures(_fit("rotor_drag"), 3.0, 0.1) == []
    for f in (_fit("body_drag"), _fit("rotor_drag", kind="output")):
        assert "held-out blocks do not favour it" in likely_failures(f, 3.0, 0.1)


class _Rotors:
    count = 4


class _Nominal:
    rotors = _Rotors()


def test_rotor_drag_share_over_the_horizontal_force_channels():
    # i034's held-out RMS per channel: the four motor channels carry the ground effect's 0.0239, the refit cuts
    # force_y 0.00901 -> 0.00129 and costs force_x 0.00107 -> 0.00147
    n = 100
    R0 = np.tile([0.02394, 0.02394, 0.02394, 0.02394, 0.00107, 0.00901], (n, 1))
    R1 = np.tile([0.02394, 0.02394, 0.02394, 0.02394, 0.00147, 0.00129], (n, 1))
    share = force_share("rotor_drag", "equation", R0, R1, _Nominal())
    assert share == pytest.approx(1 - np.hypot(0.00147, 0.00129) / np.hypot(0.00107, 0.00901), abs=1e-9)
    assert share == pytest.approx(0.7844, abs=1e-4)
    rel = 1 - np.sqrt(np.mean(R1 ** 2)) / np.sqrt(np.mean(R0 ** 2))
    assert rel == pytest.approx(0.0167, abs=1e-4)              # the share over all six channels
    assert moment_share("rotor_drag", "equation", R0, R1, _Nominal(), None, rel) == pytest.approx(share)
    # a cut under FORCE_SHARE_MIN (30 %) is not read as the share: i012's k_d refit to 0.2 x nominal cut force_x
    # 0.00107 -> 0.00092 (the logged velocity's error, not a drag)
    R2 = np.tile([0.02394, 0.02394, 0.02394, 0.02394, 0.00092, 0.00088], (n, 1))
    R3 = np.tile([0.02394, 0.02394, 0.02394, 0.02394, 0.00107, 0.00088], (n, 1))
    assert force_share("rotor_drag", "equation", R3, R2, _Nominal()) is None
    assert FORCE_SHARE_MIN == 0.30
    for name, kind in (("body_drag", "equation"), ("rotor_drag", "output")):
        assert force_share(name, kind, R0, R1, _Nominal()) is None
        assert moment_share(name, kind, R0, R1, _Nominal(), None, rel) is None
