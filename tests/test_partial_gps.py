"""Flights whose GPS velocity is valid in part of the flight only, and logs that take off at their start and end
in the air (jangminhyuk's Pixhawk 3, hand-flown in STABILIZED, logs cut for their audio; docs/corpus.md,
"Eleventh session").

- The closed-loop twin's held-out window is the last 35 % of the span where its throttle and motors can be
  scored, not of the span where the horizontal velocity is valid (the fits need it, the twin's scores do
  not): ``stages.prepare.scored_window``.
- A flight with 5 s to score but under 5 s of usable data with horizontal velocity is refused with
  ``residuals.NO_HORIZONTAL_FIELD``, and the survey flies and scores its nominal as on a flight without GPS.
- A log that takes off within ``LOG_START_S`` of its start and ends in the air is measured from the lower of
  its first and last height (``flyable._max_rise``).

The synthetic tests run everywhere; the corpus ones need the tuning half (tools/corpus_fetch.py) and skip
with one line when it is absent.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from testlogs import corpus_tuning_dir


def _corpus(name: str):
    p = corpus_tuning_dir() / f"{name}.ulg"
    if not p.is_file():
        pytest.skip(f"corpus flight {name} absent ({corpus_tuning_dir()}): run tools/corpus_fetch.py")
    return p


def test_the_scored_window_does_not_need_the_horizontal_velocity():
    """Scorable 2-28 s, velocity valid from 20 s: the window is 18.9-28 s (the last 35 % of 2-28 s), not
    25.1-28 s (of 20-28 s); where the velocity is valid all flight it is the fits' own split."""
    from twin_nodes.discovery.stages.prepare import scored_window

    t = np.arange(0.0, 30.0, 0.02)
    scored = (t >= 2.0) & (t <= 28.0)
    late = SimpleNamespace(t=t, valid=scored & (t >= 20.0), attitude_valid=scored & (t >= 20.0),
                           attitude_scored=scored)
    a, b = scored_window(late, 0.35)
    assert a == pytest.approx(2.0 + 0.65 * 26.0, abs=0.02) and b == pytest.approx(28.0, abs=0.02)
    full = SimpleNamespace(t=t, valid=scored, attitude_valid=scored, attitude_scored=scored)
    va = t[full.attitude_valid]
    assert scored_window(full, 0.35) == (pytest.approx(va[0] + 0.65 * (va[-1] - va[0])), pytest.approx(va[-1]))
    # data prepared before the field existed: the fits' span
    old = SimpleNamespace(t=t, valid=late.valid, attitude_valid=late.attitude_valid, attitude_scored=None)
    assert scored_window(old, 0.35)[0] == pytest.approx(20.0 + 0.65 * 8.0, abs=0.02)


def test_a_take_off_at_the_log_start_with_the_log_ending_in_the_air_is_a_flight():
    """Airborne from 0.5 s of a log that starts at 0 s (within LOG_START_S), rising 1.4 m from -6.7 m and cut
    at -5.45 m in flight: the rise is 1.4 m above the take-off (it was 0.16 m above the last height)."""
    from twin_nodes.logs.flyable import _max_rise
    from twin_nodes.logs.ulog_io import Series

    t = np.linspace(0.0, 20.0, 201)
    z = -6.7 + np.clip((t - 5.0) / 3.0, 0.0, 1.0) * 1.4 - np.clip((t - 15.0) / 5.0, 0.0, 1.0) * 0.15
    pos = Series(t, np.column_stack([0 * t, 0 * t, z]), "m", "ENU", "test", "linear")
    assert _max_rise(pos, [(0.5, 20.0)]) == pytest.approx(1.4, abs=0.01)


def test_the_late_gps_flights_are_scored_on_their_last_35_percent():
    """jmh_v3_kus_11_1 (airborne 2.2-27.3 s, GPS velocity from 20.5 s): the twin is scored on 17.99-25.77 s;
    the fits' own held-out part is 23.93-25.77 s, where the survey scored it before (measured 2026-11-28)."""
    from twin_nodes.discovery.residuals import prepare
    from twin_nodes.discovery.stages.prepare import scored_window
    from twin_nodes.identify.nominal import params_for_log
    from twin_nodes.logs.flyable import read_flight
    from twin_nodes.vehicle.params import load_params

    path = _corpus("jmh_v3_kus_11_1")
    log = read_flight(path, horizontal=False)
    data = prepare(log, load_params(params_for_log(path, None, log=log)[0]))
    va = data.t[data.attitude_valid]
    assert va[0] + 0.65 * (va[-1] - va[0]) == pytest.approx(23.93, abs=0.02)
    a, b = scored_window(data)
    assert a == pytest.approx(17.99, abs=0.02) and b == pytest.approx(25.77, abs=0.02)


def test_a_flight_with_too_little_velocity_to_fit_is_scored_on_its_nominal():
    """jmh_v3_esek_14_2: 2.1 s of usable data with horizontal velocity, so discovery refuses it, with the field
    the survey reads; the survey flies its nominal on 17.02-25.29 s: per-motor P75 5.39 % beside its motors'
    own 5.09 % above 0.5 Hz, throttle 1.20 % (measured 2026-11-28)."""
    from twin_nodes.base.errors import LogError
    from twin_nodes.discovery.residuals import NO_HORIZONTAL_FIELD, prepare
    from twin_nodes.discovery.survey import survey_row
    from twin_nodes.identify.nominal import params_for_log
    from twin_nodes.logs.flyable import read_flight
    from twin_nodes.vehicle.params import load_params

    path = _corpus("jmh_v3_esek_14_2")
    log = read_flight(path, horizontal=False)
    with pytest.raises(LogError) as e:
        prepare(log, load_params(params_for_log(path, None, log=log)[0]))
    assert e.value.field == NO_HORIZONTAL_FIELD and "2.1 s with horizontal velocity" in str(e.value)
    row = survey_row(path)
    assert row["status"] == "ok" and row["rejected_top"][0].startswith("discovery not run: expected at least 5 s")
    b = row["before"]
    assert b["interval_s"] == pytest.approx([17.02, 25.29], abs=0.02)
    assert b["motor_p75_mean"] == pytest.approx(0.0539, abs=0.001)
    assert b["motor_real_hf_p75_mean"] == pytest.approx(0.0509, abs=0.001)
    assert b["throttle_rmse"] == pytest.approx(0.0120, abs=0.0005)


@pytest.mark.parametrize("name, rise_m", [("jmh_v3_p232_003_1", 1.43), ("jmh_v3_p232_003_3", 1.50)])
def test_the_audio_logs_that_end_in_the_air_are_flights(name, rise_m):
    """Both take off within a second of the log start and end in the air; read as flights (they were 'never
    left the ground', 0.16 m and 0.08 m above their last height)."""
    from twin_nodes.logs.flyable import _max_rise, read_flight

    log = read_flight(_corpus(name), horizontal=False)
    assert _max_rise(log.require("position_enu"), log.airborne_intervals()) == pytest.approx(rise_m, abs=0.01)
