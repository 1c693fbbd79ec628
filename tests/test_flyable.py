"""A log that loads but is no usable flight is refused in one line saying which (issue 28).

``twin_nodes.logs.flyable.check_flyable`` is the one place: too short, never airborne (bench and
arm/disarm tests), without GPS / horizontal velocity.  Every command that loads a flight goes through
it (``compare`` offline and graph, ``discover``, ``params from-ulog``, ``identify``); the real fleet's
21 Jun log_59 and log_65 (no GPS) used to end ``params from-ulog`` with ``ValueError: need more samples
than coefficients``.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_log

import ulog_cases as C
from twin_nodes.base.errors import LogError
from twin_nodes.cli import main
from twin_nodes.logs.flyable import check_flyable, read_flight
from twin_nodes.logs.ulog_io import read_ulog

ROOT = Path(__file__).resolve().parents[1]
PARAMS = str(ROOT / "params" / "px4_sih_quadx.yaml")
NO_GPS = ("DritterFlugtag/log_59_2023-6-21-08-28-14.ulg", "DritterFlugtag/log_65_2023-6-21-08-36-08.ulg")


def run(argv: list[str]) -> tuple[object, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc: object = main(argv)
        except SystemExit as exc:
            rc = exc.code
    return rc, out.getvalue(), err.getvalue()


def test_each_kind_is_named(tmp_path):
    good = C.small_flight(tmp_path / "good.ulg")
    assert read_flight(good).path == str(good)
    cases = {
        "never_airborne": (C.never_airborne, r"vehicle_land_detected\.landed: never airborne: expected a flight, "
                                             r"the land detector says landed throughout"),
        "no_gps": (C.no_horizontal_velocity, r"vehicle_local_position\.xy_valid,v_xy_valid: without GPS \(no "
                                             r"horizontal position or velocity\): expected both in flight, valid "
                                             r"in 0 % / 0 % of the 1\d\.\d s airborne"),
        "one": (C.one_sample, r"vehicle_local_position: too short: expected at least 5 s of flight, the log has 1 "
                              r"position sample\(s\) over 0\.00 s"),
    }
    for name, (edit, msg) in cases.items():
        p = C.edited_flight(tmp_path / f"{name}.ulg", edit)
        with pytest.raises(LogError, match=rf"^{p}: {msg}"):
            read_flight(p)

    def no_hvel(topics):
        topics["vehicle_local_position"]["v_xy_valid"][:] = False

    p = C.edited_flight(tmp_path / "no_hvel.ulg", no_hvel)
    with pytest.raises(LogError, match=r"vx,vy \(v_xy_valid\): without horizontal velocity: expected it in flight"):
        read_flight(p)
    short = C.small_flight(tmp_path / "short.ulg", dur_s=2.0)
    with pytest.raises(LogError, match=r"too short: .* 100 position sample\(s\) over 1\.98 s"):
        read_flight(short)
    # ground-only methods ask for less: a bench log is their input, a 2 s log still is not
    assert check_flyable(read_ulog(tmp_path / "never_airborne.ulg"), airborne=False, horizontal=False)
    with pytest.raises(LogError, match="too short"):
        check_flyable(read_ulog(short), airborne=False, horizontal=False)


@pytest.mark.parametrize("name", NO_GPS, ids=["log_59", "log_65"])
def test_fleet_logs_without_gps_are_one_line_where_horizontal_is_needed(tmp_path, monkeypatch, name):
    """discover and identify fit horizontal forces: refused in one line.  params from-ulog and compare
    fly the flight on what it has (issue 24.5): see test_fleet_logs_without_gps_are_flown."""
    f = str(shared_log("fleet_quadx_v6c", name))
    monkeypatch.chdir(tmp_path)
    for argv in (["discover", f, "--params", PARAMS, "--json", "r.json", "--no-closed-loop"],
                 ["identify", "regress", f, "--out", "r.yaml"],
                 ["identify", "hover", f, "--out", "h.yaml"]):
        rc, _, err = run(argv)
        lines = [ln for ln in err.splitlines() if not ln.startswith("rotortwin: warning: ")]
        assert rc == 2 and len(lines) == 1, (argv, err)
        assert lines[0].startswith(f"rotortwin: error: {f}: vehicle_local_position.xy_valid,v_xy_valid: without "
                                   "GPS (no horizontal position or velocity)"), (argv, lines)
        assert list(tmp_path.iterdir()) == [], argv


@pytest.mark.parametrize("name", NO_GPS, ids=["log_59", "log_65"])
def test_fleet_logs_without_gps_are_flown(tmp_path, monkeypatch, name):
    """Without GPS the nominal is built without horizontal drag and the twin flies and is scored on Z,
    throttle and motors (XY has no real value: n/a).  log_59 is MANUAL throughout (its Z is no PX4
    axis either), log_65 ALTCTL: PX4 held the height, which the twin's altitude loop holds too."""
    import json

    f = str(shared_log("fleet_quadx_v6c", name))
    monkeypatch.chdir(tmp_path)
    rc, _, err = run(["params", "from-ulog", f, "--out", "p.yaml"])
    assert rc == 0, err
    assert "no horizontal velocity" in (tmp_path / "p.yaml").read_text()
    rc, out, err = run(["compare", "--offline", f, "--params", "p.yaml", "--quiet", "--json", "m.json"])
    assert rc == 0, err
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["xy_rmse_m"] is None and m["controlled_s"]["xy"] == 0.0
    assert m["divergence"] is None
    assert m["throttle_rmse"] < 0.05 and m["motor_p75_mean"] < 0.06
    if name.startswith("DritterFlugtag/log_65"):
        assert m["controlled_s"]["z"] > 40 and m["z_rmse_m"] < 0.5
    else:
        assert m["controlled_s"]["z"] == 0.0 and m["z_rmse_m"] is None


def test_never_left_the_ground_is_named(tmp_path):
    """The fleet's 7 Jun log_13: the land detector says airborne for 12 s, the vehicle rose 0.25 m at
    full throttle (a held or overweight vehicle): refused as never having left the ground."""
    f = shared_log("fleet_quadx_v6c", "ZweiterFlugtag/log_13_2023-6-7-10-44-58.ulg")
    with pytest.raises(LogError, match=r"vehicle_local_position\.z: never left the ground: expected it to rise at "
                                       r"least 0\.5 m above where it took off \(or landed, for a log started in the air\), it rose 0\.\d\d m"):
        read_flight(f)


def test_held_still_is_named_even_when_the_baro_drifts():
    """A vehicle on a stand (the fleet's 21 Jun log_62: tilt s.d. 0.02 deg while the land detector calls it
    airborne) whose height estimate drifts over the 0.5 m rise: refused as held still, not flown.  Corpus
    batch 4's held motor run jmh_v3_d04 rose 0.50 m on its baro alone and failed with 'rotors cannot lift'."""
    log = read_ulog(shared_log("fleet_quadx_v6c", "DritterFlugtag/log_62_2023-6-21-08-32-30.ulg"))
    iv = log.airborne_intervals()
    from twin_nodes.logs.flyable import tilt_sd_deg
    assert tilt_sd_deg(log, iv) == pytest.approx(0.02, abs=0.015)
    pos = log.get("position_enu")
    a, b = iv[0]
    inside = (pos.t_s >= a) & (pos.t_s <= b)
    pos.values[inside, 2] += np.linspace(0.0, 1.0, int(inside.sum()))   # a 1.0 m drift: past the rise check
    with pytest.raises(LogError, match=r"vehicle_attitude\.q: never left the ground: held still, .* its tilt varied "
                                       r"by 0\.0\d deg .* it rose 1\.\d\d m"):
        check_flyable(log, horizontal=False)


def test_tilt_sd_closed_form():
    """Tilt of a w-x-y-z quaternion: alternating 0 and 2 deg roll -> s.d. 1 deg."""
    from types import SimpleNamespace

    from twin_nodes.logs.flyable import tilt_sd_deg
    ang = np.radians(np.tile([0.0, 2.0], 50))
    q = np.stack([np.cos(ang / 2), np.sin(ang / 2), 0 * ang, 0 * ang], axis=1)
    log = SimpleNamespace(get=lambda name: _Series(np.arange(100) * 0.1, q) if name == "attitude_q" else None)
    assert tilt_sd_deg(log, [(0.0, 10.0)]) == pytest.approx(1.0, rel=1e-9)


class _Series:
    def __init__(self, t, v):
        self.t_s, self.values = t, v

    def __len__(self):
        return len(self.t_s)
