"""The held-out corpus list (docs/corpus_flights.csv, docs/corpus.md) and its cache.

The list checks run always.  The cache check needs the flights fetched by ``tools/corpus_fetch.py``
(outside the repo) and skips with one line when they are absent.
"""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import corpus_fetch as cf  # noqa: E402

ROWS = cf.read_list()
REAL = [r for r in ROWS if r["kind"] == "real"]
HEX40 = re.compile(r"^[0-9a-f]{40}$")


def test_list_is_well_formed():
    ids = [r["id"] for r in ROWS]
    blobs = [r["blob"] for r in ROWS]
    assert len(set(ids)) == len(ids), "duplicate ids"
    assert len(set(blobs)) == len(blobs), "duplicate blobs"
    for r in ROWS:
        assert HEX40.match(r["blob"]) and HEX40.match(r["commit"]), r["id"]
        assert re.match(r"^[\w.-]+/[\w.-]+$", r["repository"]), r["id"]
        assert r["kind"] in ("real", "sitl") and r["airborne"] in ("yes", "no"), r["id"]
        assert r["half"] in cf.HALVES and r["vehicle"] and r["path"].endswith((".ulg", ".ulog")), r["id"]
        assert r["batch"].isdigit(), r["id"]


def test_halves_follow_the_seeded_rule_and_are_non_empty():
    want = cf.split(ROWS)
    assert {r["id"]: r["half"] for r in ROWS} == want
    for half in cf.HALVES:
        assert any(r["half"] == half for r in REAL), f"no real flight in the {half} half"
    # the kept-aside vehicles of issue 24 are never tuned on
    assert all(r["half"] == "judging" for r in ROWS if r["holdout_suspect"] == "1")


def test_split_rule_deals_each_vehicle_into_both_halves():
    rows = [{"id": f"f{i}", "vehicle": f"v{i % 3}", "holdout_suspect": "0"} for i in range(12)]
    rows.append({"id": "h", "vehicle": "vh", "holdout_suspect": "1"})
    half = cf.split(rows)
    assert half["h"] == "judging"
    for v in ("v0", "v1", "v2"):
        assert {half[r["id"]] for r in rows if r["vehicle"] == v} == set(cf.HALVES)
    assert sum(h == "tuning" for h in half.values()) == 6


def test_a_later_batch_moves_no_earlier_flight():
    first = [{"id": f"a{i}", "vehicle": f"v{i % 3}", "holdout_suspect": "0", "batch": "1"} for i in range(7)]
    second = [{"id": f"b{i}", "vehicle": f"v{i % 2}", "holdout_suspect": "0", "batch": "2"} for i in range(5)]
    alone = cf.split(first)
    both = cf.split(first + second)
    assert {k: both[k] for k in alone} == alone
    # the second batch is dealt by the same rule as if it were the only one
    assert {k: both[k] for k in both if k.startswith("b")} == cf.split([{**r, "batch": "1"} for r in second])
    # a row without a batch is batch 1
    assert cf.split([{k: v for k, v in r.items() if k != "batch"} for r in first]) == alone


def test_corpus_meets_the_size_of_issue_24():
    # issue 24 item 6: at least 40 real flights of at least 8 vehicles, and each half holds several vehicles;
    # bench, stand and arm/disarm runs are rows of the list but not flights
    assert len(REAL) >= 40
    assert sum(r["airborne"] == "yes" for r in REAL) >= 40
    assert len({r["vehicle"] for r in REAL}) >= 8
    for half in cf.HALVES:
        assert len({r["vehicle"] for r in REAL if r["half"] == half}) >= 4, half


def test_git_blob_sha_is_gits():
    # `printf 'hello\n' | git hash-object --stdin`
    assert cf.git_blob_sha(b"hello\n") == "ce013625030ba8dba906f756967f9e9ca394464a"


def test_cached_files_match_their_blob():
    cached = [(r, cf.cache_path(r)) for r in ROWS if cf.cache_path(r).is_file()]
    if not cached:
        pytest.skip(f"corpus cache absent ({cf.cache_root()}): run tools/corpus_fetch.py")
    for r, p in cached:
        assert cf.git_blob_sha(p.read_bytes()) == r["blob"], f"{p}: sha differs from {r['blob']}"


def test_fetch_extracts_by_blob_and_names_a_missing_mirror(tmp_path, monkeypatch):
    data = b"ULog\x01\x12\x35 not a real flight, just bytes"
    git = tmp_path / "mirrors" / "owner+name" / "repo" / ".git"
    subprocess.run(["git", "init", "-q", str(git.parent)], check=True)
    blob = subprocess.run(["git", f"--git-dir={git}", "hash-object", "-w", "--stdin"], input=data,
                          capture_output=True, check=True).stdout.decode().strip()
    assert blob == cf.git_blob_sha(data)
    monkeypatch.setenv("ROTORTWIN_MIRRORS", str(tmp_path / "mirrors"))
    monkeypatch.setenv("ROTORTWIN_CORPUS", str(tmp_path / "cache"))
    row = {"id": "x1", "repository": "owner/name", "blob": blob, "half": "tuning"}
    assert cf._extract(row).startswith("ok x1")
    assert (tmp_path / "cache" / "tuning" / "x1.ulg").read_bytes() == data
    assert cf._extract(row).startswith("ok (cached) x1")
    missing = cf._extract({**row, "id": "x3", "repository": "nobody/there"})
    assert "fetch github:nobody/there" in missing and "\n" not in missing
    bad = cf._extract({**row, "id": "x2", "blob": "0" * 40})
    assert bad.startswith("MISSING blob")


def test_throttle_floor_is_the_rms_above_half_a_hertz():
    import corpus_measures as cm
    t = np.arange(0.0, 60.0, 0.02)                      # 50 Hz, 60 s
    fast = 0.04 * np.sin(2 * np.pi * 3.0 * t)            # 3 Hz: all of it above 0.5 Hz
    slow = 0.2 * np.sin(2 * np.pi * 0.05 * t)            # 0.05 Hz: none of it
    assert cm.high_freq_rms(t, 0.5 + slow + fast) == pytest.approx(0.04 / np.sqrt(2), rel=0.03)
    assert cm.high_freq_rms(t, 0.5 + slow) < 0.002
    assert np.isnan(cm.high_freq_rms(t[:10], fast[:10]))


def test_controlled_axes_follow_nav_state():
    import corpus_measures as cm
    t_nav = np.array([0.0, 10.0, 20.0])
    nav = np.array([15.0, 1.0, 2.0])                     # STAB, then ALTCTL, then POSCTL
    assert cm.held_fraction(t_nav, nav, 0.0, 30.0, cm.XY_HELD) == pytest.approx(1 / 3, abs=0.01)
    assert cm.held_fraction(t_nav, nav, 0.0, 30.0, cm.Z_HELD) == pytest.approx(2 / 3, abs=0.01)
    m = {"throttle_rmse": 0.05, "motor_p75_mean": 0.04, "xy_rmse_m": 12.0, "z_rmse_m": 0.3}
    # XY not held: 12 m is not scored; throttle 5 % is within 1.25 x a 4.4 % floor
    assert cm.verdict({"floor": 0.044, "xy_held": 0.0, "z_held": 1.0}, m) == (True, [])
    ok, fails = cm.verdict({"floor": 0.01, "xy_held": 1.0, "z_held": 1.0}, m)
    assert not ok and len(fails) == 2


def test_a_vehicle_held_still_is_not_airborne_whatever_the_land_detector_says():
    import corpus_describe as cd
    from types import SimpleNamespace as NS
    t = np.arange(0, 20_000_000, 20_000)                          # 20 s at 50 Hz, us
    half_tilt = np.radians(2.0 * np.sin(2 * np.pi * t / 4e6)) / 2  # roll swings +-2 deg, 5 periods

    def ulog(q1, z):
        att = {"timestamp": t, "q[0]": np.cos(q1), "q[1]": np.sin(q1), "q[2]": 0 * t, "q[3]": 0 * t}
        land = {"timestamp": t, "landed": 0 * t}                  # the land detector says airborne throughout
        lp = {"timestamp": t, "z": z}
        return NS(data_list=[NS(name=n, multi_id=0, data=d) for n, d in
                             (("vehicle_attitude", att), ("vehicle_land_detected", land), ("vehicle_local_position", lp))])
    held = ulog(0 * t + 1e-4, -0.1 * (t / t[-1]))                 # level, height moves 0.1 m
    flown = ulog(half_tilt, -0.1 * (t / t[-1]))                   # the same, tilting +-2 deg: a low hop
    climbed = ulog(0 * t, -3.0 * (t / t[-1]))                     # perfectly level but rises 3 m
    assert cd._tilt_sd_deg(held, 0, t[-1]) < 0.01
    # tilt = |2 deg sin|: its standard deviation is 2 sqrt(1/2 - 4/pi^2) = 0.616 deg
    assert cd._tilt_sd_deg(flown, 0, t[-1]) == pytest.approx(2.0 * np.sqrt(0.5 - 4 / np.pi**2), rel=0.02)
    assert cd._height_range_m(climbed, 0, t[-1]) == pytest.approx(3.0)
    assert cd._airborne(held, 0, t[-1]) is False
    assert cd._airborne(flown, 0, t[-1]) is True
    assert cd._airborne(climbed, 0, t[-1]) is True


def test_batch5_caps_six_flights_per_vehicle_and_repeats_no_blob_or_vehicle():
    # batch 5 (docs/corpus.md): at most 6 rows per vehicle, chosen before any survey; no blob or vehicle of
    # an earlier batch comes back, and the HIL board is labelled sitl
    b5 = [r for r in ROWS if cf.batch_of(r) == "5"]
    earlier = [r for r in ROWS if int(cf.batch_of(r)) < 5]
    per_vehicle = {}
    for r in b5:
        per_vehicle[r["vehicle"]] = per_vehicle.get(r["vehicle"], 0) + 1
    assert max(per_vehicle.values()) <= 6
    assert sum(r["kind"] == "real" for r in b5) == 13 and len({r["vehicle"] for r in b5 if r["kind"] == "real"}) == 3
    assert not {r["blob"] for r in b5} & {r["blob"] for r in earlier}
    assert not {r["vehicle"] for r in b5} & {r["vehicle"] for r in earlier}
    assert all(r["kind"] == "sitl" for r in b5 if r["vehicle"].endswith("20002d"))
