"""Discovery's closed-loop guard also watches the twin's motors (discovery/stages/closed_loop._veto).

A change the equations accept whose closed-loop twin then follows the vehicle's motors worse on the held-out part
(per-motor P75 more than CLOSED_LOOP_MOTOR_TOL_REL above the best so far or the nominal twin, and by at least
CLOSED_LOOP_MOTOR_MIN_RISE of full output) is vetoed, whatever
its throttle; within the tolerance, or where the nominal twin does not stand (``veto_standing``), the throttle
rule decides as before."""

from __future__ import annotations

import numpy as np

from twin_nodes.discovery.stages import closed_loop


def _run(throttle_scale: float, p75: float | None) -> dict:
    t = np.arange(0.0, 12.0, 0.02)
    e = 0.02 * throttle_scale * np.sin(2 * np.pi * t / 3.0)
    m = {"throttle_rmse": float(np.sqrt(np.mean(e ** 2))), "_throttle_err": (t, e), "divergence": None}
    if p75 is not None:
        m["motor_p75_mean"] = p75
    return m


def test_the_tolerance():
    assert closed_loop.CLOSED_LOOP_MOTOR_TOL_REL == 0.10
    assert closed_loop.CLOSED_LOOP_MOTOR_MIN_RISE == 0.005


def test_a_better_throttle_with_motors_worse_beyond_the_tolerance_is_vetoed():
    before = _run(1.0, 0.0702)
    # auterion_v3_esc_status's tilt state term: throttle 2.03 -> 1.73 %, per-motor P75 7.46 -> 10.95 %
    after = _run(0.85, 0.1095)
    best = _run(1.0, 0.0746)
    vetoed, why = closed_loop._veto(after, best, before, (True, "the twin's controller flew this flight"))
    assert vetoed
    assert why.startswith("closed-loop held-out per-motor P75 0.0702 -> 0.1095, more than 10 % worse")


def test_within_the_tolerance_or_without_standing_the_throttle_decides():
    before = _run(1.0, 0.0300)
    # s500 mission2's yaw moment: per-motor P75 3.00 -> 3.20 % (+6.7 %), throttle unchanged: kept
    assert closed_loop._veto(_run(1.0, 0.0320), before, before, (True, "")) == (False, None)
    # from 6 %: 10.1 % worse (0.61 % of full output) vetoed; 9.9 % kept
    six = _run(1.0, 0.0600)
    assert closed_loop._veto(_run(1.0, 0.06606), six, six, (True, ""))[0] is True
    assert closed_loop._veto(_run(1.0, 0.06594), six, six, (True, "")) == (False, None)
    # a twin already within 1 % of its motors: 0.39 -> 0.43 % is 10 % worse but under half a percent of full output
    tight = _run(1.0, 0.0039)
    assert closed_loop._veto(_run(1.0, 0.0043), tight, tight, (True, "")) == (False, None)
    # the nominal twin does not follow the flight: no veto from the motors (as from the throttle)
    assert closed_loop._veto(_run(1.0, 0.0600), before, before, (False, "does not follow")) == (False, None)
    # runs without per-motor numbers: the throttle alone, as before
    assert closed_loop._veto(_run(1.0, None), _run(1.0, None), _run(1.0, None), (True, "")) == (False, None)
