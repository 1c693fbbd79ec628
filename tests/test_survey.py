"""The survey says why a flight is not scored rather than printing blanks (issue 24, item 5)."""

from __future__ import annotations

import pytest


def test_a_held_out_window_with_nothing_scored_is_a_hop_left_out():
    """Corpus batch 4's jmh_v3_maymun_20_2: a 28 s hand-flown hop whose last 35 % (22.5-25.4 s) is all
    touchdown; its row was blanks counted as a miss.  Now a one-line 'too short' that the survey leaves out."""
    from twin_nodes.base.errors import LogError
    from twin_nodes.discovery import survey

    with pytest.raises(LogError, match=r"f\.ulg: held-out window: too short: .* \(22\.5-25\.4 s\), every one is "
                                       r"take-off or touchdown"):
        survey._check_scored("f.ulg", {"throttle_rmse": None, "interval_s": [22.5, 25.4]})
    survey._check_scored("f.ulg", {"throttle_rmse": 0.01, "interval_s": [22.5, 25.4]})   # scored: no error
    assert any(k in "too short: expected airborne samples" for k in survey.LEFT_OUT_KINDS)


def test_a_log_whose_outputs_never_move_is_left_out_as_carrying_no_motor_outputs():
    """Corpus RflyBUAA logs (PX4 1.11, SYS_AUTOSTART 4050): actuator_outputs[0] holds 1932/1500/1500/1500 us
    while armed, no channel moves; the motors are driven by something the log does not record.  The one-line
    error says so and the survey leaves the log out; a log whose outputs move but were not recognised as motors
    stays a failure (a reader to fix, not a log to hide)."""
    from twin_nodes.base.errors import LogError
    from twin_nodes.discovery import survey
    from twin_nodes.logs.ulog_io import FlightLog

    def log(moving):
        return FlightLog(path="r.ulg", start_us=0, duration_s=60.0, params={}, info={}, series={}, warnings=[],
                         n_motors=4, moving_outputs=moving)

    with pytest.raises(LogError) as e:
        log((0, "actuator_outputs[0].output")).require("motors")
    msg = str(e.value)
    assert msg.startswith("r.ulg: motors: expected series 'motors'") and msg.endswith(
        "no channel of actuator_outputs[0].output moves while armed, this log carries no motor outputs")
    assert any(k in msg for k in survey.LEFT_OUT_KINDS)
    with pytest.raises(LogError) as e:
        log((4, "actuator_outputs[0].output")).require("motors")
    assert not any(k in str(e.value) for k in survey.LEFT_OUT_KINDS)
    with pytest.raises(LogError) as e:
        log(None).require("motors")
    assert not any(k in str(e.value) for k in survey.LEFT_OUT_KINDS)
