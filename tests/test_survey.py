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
