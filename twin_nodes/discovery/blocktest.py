"""The held-out block test: per-block drop in mean squared residual, judged by a t, a sign and a
sign-flip test (the largest of the three)."""

from __future__ import annotations

import math

import numpy as np


#: a block whose change is under this fraction of the candidate's largest block change carries nothing of it
NEGLIGIBLE = 0.01
#: an effect whose own term reaches (NEGLIGIBLE of its largest block change) under this share of the blocks is
#: confined (a Crazyflie's ground effect: the take-off and the landing); beside refitted partners its blocks are
#: chosen from its own term (:func:`_block_stats` ``change``).  One reaching more (a 1 kg quad's ground effect, 0.84 m
#: height scale, at a 1.45 m cruise: every block) is judged on its net change with them, as before
CONFINED_SHARE = 0.5
#: fewer active held-out blocks than this and :func:`_block_stats` runs none of its tests: its ``t`` reads 0.0 (no
#: evidence for the candidate) and ``tested`` is False, so a caller using the t as evidence *against* it (a drop, a
#: veto) can tell an untestable comparison from a failed one
MIN_TEST_BLOCKS = 4
#: a block whose change is at least this share of the candidate's largest block change carries it strongly: a drag
#: on a fast-descent mission acts in the 2-4 held-out blocks of its diagonal descents, while the logged velocity's
#: error moves every other block a little (:func:`verdicts.strong_blocks_favour`; rdr16)
STRONG_SHARE = 0.25


def _confined(per_block: np.ndarray) -> bool:
    """A change (per block, >= 0, not all zero) reaches ``NEGLIGIBLE`` of its largest block change in under
    ``CONFINED_SHARE`` of the blocks."""
    return bool(np.mean(per_block >= NEGLIGIBLE * per_block.max()) < CONFINED_SHARE)


#: the percentile's method over a confined change's reached blocks: an observed block's change, never an interpolation
#: toward the largest (see :func:`_reference`)
CONFINED_METHOD = "lower"


def _reference(delta: np.ndarray) -> float:
    """The typical block change (>= 0, not all zero) that :func:`_block_stats`'s active blocks are measured against:
    its 90th percentile, over the blocks a confined change reaches (``NEGLIGIBLE`` of its largest).

    The 90th percentile is there so that one violent manoeuvre cannot silence the rest.  Over every block (a hundred
    and more) the linear percentile keeps that; over a confined change's reached blocks (about ten on a Crazyflie's
    ground effect) it does not: with n <= 10 values the linear 90th percentile lies between the second largest and
    the largest and gives the largest the weight 1.1 - 0.1 n (n = 10: 0.1, n = 5: 0.6), so one dominant block (a
    take-off 34 times the rest) sets the reference, and one tail block more or less moves the active set between 1
    and 11 blocks (rb035 against k016, yp18).  ``method="lower"`` takes the order statistic at or below the 90th
    percentile: an observed block's change, never the largest for n >= 2; from n = 11 on it is the lower of the two
    blocks the linear method interpolates between (at n = 11 the same block).  An effect reaching most blocks keeps
    the linear percentile over every block, as before."""
    if _confined(delta):
        return float(np.percentile(delta[delta >= NEGLIGIBLE * delta.max()], 90, method=CONFINED_METHOD))
    return float(np.percentile(delta, 90))


def _block_stats(R0: np.ndarray, R1: np.ndarray, blocks: list[np.ndarray], min_change: float = 0.0,
                 change: np.ndarray | None = None) -> dict:
    """Per-block drop in mean squared residual over the blocks where the candidate changes the
    prediction at all (>= 25 % of its 90th-percentile block change, so one violent manoeuvre
    cannot silence the rest), and the three tests on it.

    Effects that act only in some regimes (drag in forward flight, ground effect near the
    ground) leave the other blocks unchanged; counting those would only add variance.  The
    blocks are chosen from the change itself, not from whether it helped, so this does not
    favour the candidate.  ``min_change``: a block must also change by at least this much (the
    output error is in units of its typical error, so half of that separates a manoeuvre the
    candidate acts in from noise when under a tenth of the blocks carry it).  ``change``: where the candidate's
    own term changes the prediction, when that is not ``R1 - R0`` (a joint variant, whose refitted partners
    re-balance every block a little: :func:`judging.own_change`).  A confined change (it reaches ``NEGLIGIBLE`` of
    its largest block change in under ``CONFINED_SHARE`` of the blocks) takes its 90th percentile over the blocks
    it reaches, not over every block, as an observed block's change (:func:`_reference`): otherwise the zeros pull
    the threshold down to blocks it moves at the noise's size, whose gains are coin flips (x033's ground effect: 9
    active blocks, 6 improved)."""
    delta = np.array([np.sqrt(np.mean((R1[b] - R0[b]) ** 2)) for b in blocks])
    if change is not None:
        own = np.array([np.sqrt(np.mean(change[b] ** 2)) for b in blocks])
        if own.max() > 0 and _confined(own):
            # a confined effect beside refitted partners: its blocks are where its own term acts, and more than
            # the partners' re-balance there (what is left of the change once its own term is taken out)
            rest = np.array([np.sqrt(np.mean((R1[b] - R0[b] - change[b]) ** 2)) for b in blocks])
            delta = np.where(own >= rest, own, 0.0)
    if delta.size == 0 or delta.max() <= 0:
        return {"t": 0.0, "n": 0, "mean": 0.0, "sd": 0.0, "n_pos": 0, "tested": False}
    # a confined change (a Crazyflie's ground effect at take-off and landing): its typical block change is taken
    # over the blocks it reaches, so the many blocks it leaves at noise do not pull the threshold down to them
    ref = _reference(delta)
    on = delta >= max(0.25 * ref, min_change, NEGLIGIBLE * delta.max())
    active = [b for b, o in zip(blocks, on) if o]
    d = np.array([np.mean(R0[b] ** 2) - np.mean(R1[b] ** 2) for b in active])
    st = {"n": int(d.size), "mean": float(d.mean()) if d.size else 0.0,
          "sd": float(d.std(ddof=1)) if d.size > 1 else 0.0, "n_pos": int(np.sum(d > 0)),
          "tested": bool(d.size >= MIN_TEST_BLOCKS)}
    ds = d[delta[on] >= STRONG_SHARE * delta.max()]   # the active blocks that carry the change strongly
    st["n_strong"], st["pos_strong"] = int(ds.size), int(np.sum(ds > 0))
    if not st["tested"]:
        st["t"] = 0.0
        return st
    from scipy.stats import binom, norm
    from scipy.stats import t as student_t
    sd = st["sd"]
    t = (math.inf if d.mean() > 0 else 0.0) if sd == 0 else float(d.mean() / (sd / math.sqrt(d.size)))
    if math.isfinite(t):
        # Student's t with n - 1 degrees of freedom, as the equivalent normal quantile (with 4
        # blocks t = 3 is only p = 0.03)
        t = float(norm.isf(min(max(float(student_t.sf(t, d.size - 1)), 1e-300), 1.0 - 1e-15)))
    # Sign test on the same blocks: the t test loses power when the gains are heavy-tailed
    # (a few manoeuvres carry an inertia or yaw-moment effect).  Under "no effect" a held-out
    # block improves with probability <= 1/2; the binomial tail is mapped to the equivalent
    # one-sided normal quantile so both tests share the threshold T_CRIT.
    # Fisher's sign-flip randomization test keeps the size of the gains without assuming
    # normality: under "no effect" each block's gain is as likely to be a loss of the same
    # size.  20000 fixed-seed flips resolve p down to 5e-5.  The largest of the three
    # statistics is used; at the one-sided 3 sigma level the union's false-alarm rate stays
    # under 0.5 %.
    k = int(np.sum(d > 0))
    p = float(binom.sf(k - 1, d.size, 0.5))
    z = float(norm.isf(max(p, 1e-300)))
    p_flip = (1.0 + np.sum(_flip_sums(d.size, np.abs(d)) >= d.sum())) / (1.0 + N_FLIPS)
    zw = float(norm.isf(p_flip))
    st["t"] = max(t, z, zw)
    return st


_FLIPS: dict[int, np.ndarray] = {}
#: the sign-flip test's flips, and the rows made and multiplied at a time: the flip matrix is
#: 20000 x (active blocks) and the blocks are 0.5 s, so as float64 it grew with the flight (a
#: 1-hour flight: ~800 MB per block count, up to 17 counts cached); kept as bits (1/64), made
#: FLIP_ROWS rows at a time with the same random stream (an even number of draws per chunk: the
#: generator's 32-bit buffer ends with each chunk) and multiplied a few rows at a time with the
#: same BLAS product per row (bit for bit what the whole matrix gave, tests/test_bench_smoke.py)
N_FLIPS = 20000
FLIP_ROWS = 2000


def _sign_flips(n: int) -> np.ndarray:
    """The sign-flip test's 20000 fixed-seed flips of n blocks, packed as bits (True: +1), made once
    per n (:func:`_flip_sums` expands them)."""
    if n not in _FLIPS:
        if len(_FLIPS) > 16:
            _FLIPS.clear()
        rng = np.random.default_rng(12345)
        _FLIPS[n] = np.concatenate([
            np.packbits(rng.choice((-1.0, 1.0), size=(min(FLIP_ROWS, N_FLIPS - r0), n)) > 0, axis=1)
            for r0 in range(0, N_FLIPS, FLIP_ROWS)])
        _FLIPS[n].flags.writeable = False
    return _FLIPS[n]


def _sum_rows(n: int) -> int:
    """Rows of +-1.0 expanded and multiplied at a time: ~2 MB of float64 (stays in the CPU's cache;
    3x faster than 2000 rows on a 1-hour flight), from 64 to FLIP_ROWS, a multiple of 16: BLAS's
    matrix-vector kernel takes rows in groups, and a remainder group sums in another order (rows
    = 2 mod 4 gave other last bits); 20000 is a multiple of 16, so every chunk is whole groups."""
    return int(min(max(2 ** 18 // max(n, 1), 64), FLIP_ROWS)) & ~15


def _flip_sums(n: int, a: np.ndarray) -> np.ndarray:
    """``flips @ a`` for the n-block flip matrix, a few rows at a time (:func:`_sum_rows`; equal bit
    for bit to the product with the whole float64 matrix)."""
    bits = _sign_flips(n)
    out = np.empty(N_FLIPS)
    rows = _sum_rows(n)
    for r0 in range(0, N_FLIPS, rows):
        f = np.multiply(np.unpackbits(bits[r0:r0 + rows], axis=1, count=n), 2.0)
        f -= 1.0
        out[r0:r0 + rows] = f @ a
    return out


def not_significant(t: float, n: int) -> str:
    """Why a candidate's held-out block test did not carry it, in one phrase: its t over ``n`` active blocks, or
    that the test did not run (under ``MIN_TEST_BLOCKS`` active blocks: its t of 0.0 is no measured value)."""
    if n < MIN_TEST_BLOCKS:
        return f"held-out block test not run ({n} active block{'s' if n != 1 else ''}, {MIN_TEST_BLOCKS} needed)"
    return f"not significant on held-out blocks (t={t:.1f} over {n})"


def _block_test(R0: np.ndarray, R1: np.ndarray, blocks: list[np.ndarray], min_change: float = 0.0
                ) -> tuple[float, int]:
    """(statistic, active blocks) of :func:`_block_stats`: t, sign and sign-flip tests, the largest."""
    st = _block_stats(R0, R1, blocks, min_change)
    return st["t"], st["n"]
