"""metrics.py: statistics against direct numpy, rolling window against brute force, Table 2."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from twin_nodes.twin.metrics import (Aligned, RollingStats, compare_metrics, error_stats, flight_metrics,
                                percentile_sorted, table2, to_jsonable)


def test_error_stats_matches_numpy():
    rng = np.random.default_rng(1)
    e = rng.normal(0.1, 0.5, 1001)
    e[::97] = np.nan
    s = error_stats(e)
    f = e[np.isfinite(e)]
    assert s["n"] == f.size
    assert s["rmse"] == pytest.approx(np.sqrt(np.mean(f ** 2)), rel=1e-12)
    assert s["p75"] == pytest.approx(np.percentile(np.abs(f), 75), rel=1e-12)
    assert s["median"] == pytest.approx(np.median(np.abs(f)), rel=1e-12)
    assert s["max"] == pytest.approx(np.max(np.abs(f)), rel=1e-12)


def test_error_stats_empty_and_known_values():
    s = error_stats([np.nan, np.nan])
    assert s["n"] == 0 and all(math.isnan(s[k]) for k in ("rmse", "p75", "median", "max"))
    s = error_stats([3.0, -4.0])
    assert s["rmse"] == pytest.approx(math.sqrt(12.5))
    assert s["median"] == pytest.approx(3.5)
    assert s["p75"] == pytest.approx(3.75)  # linear interpolation between 3 and 4
    assert s["max"] == 4.0


@pytest.mark.parametrize("q", [0, 25, 50, 75, 90, 100])
def test_percentile_sorted_is_numpy_linear(q):
    rng = np.random.default_rng(q)
    for n in (1, 2, 3, 10, 101):
        a = np.sort(rng.random(n))
        assert percentile_sorted(list(a), q) == pytest.approx(np.percentile(a, q), rel=1e-12)


def _brute(ts, es, t, w):
    sel = (ts > t - w) & (ts <= t) & np.isfinite(es)
    return error_stats(es[sel])


def test_rolling_matches_brute_force():
    rng = np.random.default_rng(7)
    n = 3000
    ts = np.cumsum(rng.exponential(0.01, n))
    ts[100:110] = ts[100]  # repeated times are allowed
    es = rng.normal(0, 1, n) * (1 + 5 * (rng.random(n) < 0.02))
    es[rng.random(n) < 0.05] = np.nan
    w = 0.5
    r = RollingStats(w)
    for i in range(n):
        r.add(ts[i], es[i])
        if i % 37 == 0 or i == n - 1:
            got, ref = r.stats(), _brute(ts[: i + 1], es[: i + 1], ts[i], w)
            assert got["n"] == ref["n"]
            for k in ("rmse", "p75", "median", "max"):
                assert got[k] == pytest.approx(ref[k], rel=1e-9, abs=1e-12), (i, k)


def test_rolling_advance_expires_and_rejects_going_back():
    r = RollingStats(1.0)
    r.add(0.0, 2.0)
    r.add(0.5, -1.0)
    assert r.stats()["n"] == 2
    r.advance(1.2)
    assert r.stats()["n"] == 1 and r.stats()["max"] == 1.0
    r.advance(3.0)
    assert r.stats()["n"] == 0 and math.isnan(r.stats()["rmse"])
    with pytest.raises(ValueError, match="non-decreasing"):
        r.add(2.0, 1.0)
    with pytest.raises(ValueError, match="window_s"):
        RollingStats(0.0)


def _aligned(n=500, n_motors=4, seed=3):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.02
    xy_r = np.cumsum(rng.normal(0, 0.1, (n, 2)), axis=0)
    xy_t = xy_r + rng.normal(0, 0.3, (n, 2))
    z_r = 5 + np.sin(t)
    z_t = z_r + rng.normal(0, 0.2, n)
    th_r = 0.5 + 0.05 * np.sin(3 * t)
    th_t = th_r + rng.normal(0, 0.02, n)
    m_r = np.clip(th_r[:, None] + rng.normal(0, 0.03, (n, n_motors)), 0, 1)
    m_t = m_r + rng.normal(0, 0.01, (n, n_motors))
    m_t[:20] = np.nan  # stopped at the start
    mask = np.ones(n, bool)
    mask[:10] = False
    mask[-30:] = False
    return Aligned(t=t, xy_twin=xy_t, xy_real=xy_r, z_twin=z_t, z_real=z_r, throttle_twin=th_t,
                   throttle_real=th_r, motors_twin=m_t, motors_real=m_r, mask=mask)


def test_flight_metrics_vs_direct_numpy():
    al = _aligned()
    m = flight_metrics(al)
    k = al.mask
    exy = np.linalg.norm(al.xy_twin[k] - al.xy_real[k], axis=1)
    assert m["xy_rmse_m"] == pytest.approx(np.sqrt(np.mean(exy ** 2)))
    assert m["xy_p75_m"] == pytest.approx(np.percentile(exy, 75))
    assert m["xy_median_m"] == pytest.approx(np.median(exy))
    assert m["xy_max_m"] == pytest.approx(exy.max())
    ez = al.z_twin[k] - al.z_real[k]
    assert m["z_rmse_m"] == pytest.approx(np.sqrt(np.mean(ez ** 2)))
    assert m["z_p75_m"] == pytest.approx(np.percentile(np.abs(ez), 75))
    et = al.throttle_twin[k] - al.throttle_real[k]
    assert m["throttle_rmse"] == pytest.approx(np.sqrt(np.mean(et ** 2)))
    assert m["throttle_median"] == pytest.approx(np.median(np.abs(et)))
    assert m["throttle_max"] == pytest.approx(np.abs(et).max())
    for i in range(4):
        em = al.motors_twin[k, i] - al.motors_real[k, i]
        em = em[np.isfinite(em)]
        assert m["motor_rmse"][i] == pytest.approx(np.sqrt(np.mean(em ** 2)))
        assert m["motor_p75"][i] == pytest.approx(np.percentile(np.abs(em), 75))
        assert m["motor_median"][i] == pytest.approx(np.median(np.abs(em)))
        assert m["motor_max"][i] == pytest.approx(np.abs(em).max())
    assert m["n_samples"] == int(k.sum())
    assert m["duration_s"] == pytest.approx(al.t[k][-1] - al.t[k][0])
    assert m["rate_hz"] == pytest.approx(50.0)
    json.dumps(to_jsonable(m), allow_nan=False)


def test_aligned_rejects_bad_shapes():
    al = _aligned()
    with pytest.raises(ValueError, match="xy_twin"):
        Aligned(t=al.t, xy_twin=al.xy_twin[:-1], xy_real=al.xy_real, z_twin=al.z_twin, z_real=al.z_real,
                throttle_twin=al.throttle_twin, throttle_real=al.throttle_real, motors_twin=al.motors_twin,
                motors_real=al.motors_real, mask=al.mask)


def test_table2_layout_and_regression_check():
    m = flight_metrics(_aligned())
    txt = table2(m)
    for row in ("XY trajectory RMSE [m]", "XY trajectory P75 [m]", "Altitude RMSE [m]", "Altitude P75 [m]",
                "Per-motor output P75 [%]", "Throttle RMSE [%]", "Throttle median [%]"):
        assert row in txt
    assert f"{m['throttle_rmse'] * 100:.1f}" in txt
    stored = to_jsonable(m)
    assert compare_metrics(stored, m) == []
    worse = dict(m, xy_rmse_m=m["xy_rmse_m"] * 1.5)
    bad = compare_metrics(stored, worse, rel_tol=0.05)
    assert len(bad) == 1 and bad[0].startswith("xy_rmse_m")
