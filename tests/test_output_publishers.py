"""Motor outputs of a second ``actuator_outputs`` publisher (issue 24, docs/corpus.md "Eighteenth session,
rest18"): a module that advertises ``actuator_outputs`` itself shares instance 0 with PX4's output driver
and the log interleaves both; the motors are the publisher whose channels move, whatever the other one holds.
Synthetic logs for the detection; the real tuning flight ``rfly_3539_07_03_18`` skips when the corpus cache
is absent."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from twin_nodes.logs import legacy_topics as L
from twin_nodes.logs import ulog_io as U


def _topics(second_publisher: bool, t_armed=(10.0, 90.0), seed: int = 0):
    """100 s at 200 Hz.  PX4's driver publishes noutputs 4 at 1500 us on every channel (armed or not, as the
    RflyBUAA lab build's driver does); with ``second_publisher`` a module publishes noutputs 0 at 1000..2000 us
    on the same instance while armed, interleaved with the driver's samples, its four motors following a
    noisy thrust."""
    rng = np.random.default_rng(seed)
    t_drv = np.arange(0.0, 100.0, 1 / 160)
    rows = [(t_drv, np.full((t_drv.size, 16), 0.0), np.full(t_drv.size, 4))]
    rows[0][1][:, :4] = 1500.0
    if second_publisher:
        t_mod = np.arange(t_armed[0], t_armed[1], 1 / 200) + 0.0013
        o = np.zeros((t_mod.size, 16))
        o[:, :4] = 1380.0 + 60.0 * np.sin(0.4 * t_mod)[:, None] + rng.normal(0.0, 25.0, (t_mod.size, 4))
        rows.append((t_mod, o, np.zeros(t_mod.size)))
    t = np.concatenate([r[0] for r in rows])
    order = np.argsort(t, kind="stable")
    out = np.concatenate([r[1] for r in rows])[order]
    nout = np.concatenate([r[2] for r in rows])[order]
    data = {f"output[{i}]": out[:, i] for i in range(16)}
    data["noutputs"] = nout
    ao = U._Topic("actuator_outputs", 0, (t[order] * 1e6).astype(np.int64), data)
    st = np.array([0.0, t_armed[0], t_armed[1]])
    vs = U._Topic("vehicle_status", 0, (st * 1e6).astype(np.int64),
                  {"arming_state": np.array([1, 2, 1]), "nav_state": np.array([2, 2, 2])})
    return {("actuator_outputs", 0): ao, ("vehicle_status", 0): vs}


def test_interleaved_publishers_are_split_and_the_moving_one_is_the_motors():
    topics = _topics(second_publisher=True)
    ao = topics[("actuator_outputs", 0)]
    pubs = U._output_publishers(ao)
    assert [lab for lab, _ in pubs] == [" (noutputs 0)", " (noutputs 4)"]
    assert [p.t_us.size for _, p in pubs] == [16000, 16000]
    inst, lab, tp, chans = U._guess_motor_stream({0: ao}, 4, topics)
    assert (inst, lab, chans) == (0, " (noutputs 0)", [0, 1, 2, 3])
    assert np.all(tp.col("noutputs") == 0)
    assert U.moving_motor_outputs(topics) == (4, "actuator_outputs[0].output (noutputs 0)")


def test_the_merged_stream_would_have_rested_above_its_armed_range():
    """Why the reader missed them before: merged, the channels rest at 1500 us disarmed, above their armed
    5th percentile (about 1290 us), so the rest-low test refused them."""
    topics = _topics(second_publisher=True)
    ao = topics[("actuator_outputs", 0)]
    arm = U._armed_at(topics, ao.t_s)
    o = ao.arr("output", 4)
    assert np.all(o[~arm] == 1500.0)
    assert np.all(np.percentile(o[arm & (ao.col("noutputs") == 0)], 5, axis=0) < 1400.0)


def test_a_driver_alone_at_a_constant_value_gives_no_motors():
    """The 12 other RflyBUAA logs: only the driver's constant 1500 us; nothing moves, nothing invented."""
    topics = _topics(second_publisher=False)
    ao = topics[("actuator_outputs", 0)]
    assert [lab for lab, _ in U._output_publishers(ao)] == [""]
    assert U.moving_motor_outputs(topics) == (0, "actuator_outputs[0].output")
    assert U._guess_motor_stream({0: ao}, 4, topics)[0] is None


def test_noutputs_that_changes_once_is_one_publisher():
    """A driver whose noutputs goes 0 -> 8 once (mixer loaded) is not split."""
    topics = _topics(second_publisher=False)
    ao = topics[("actuator_outputs", 0)]
    n = ao.col("noutputs").copy()
    n[: n.size // 3] = 0
    ao.data["noutputs"] = n
    assert [lab for lab, _ in U._output_publishers(ao)] == [""]


def test_outputs_above_the_pwm_maximum_are_read_on_the_default_scale():
    lo, hi = np.full(2, 1075.0), np.full(2, 1950.0)
    a = np.column_stack([np.linspace(1000.0, 1960.0, 1000), np.linspace(1100.0, 1900.0, 1000)])
    why = L.not_driver_scaled(a, lo, hi)
    assert why is not None and "1000-2000" in why and "1.0 %" in why
    assert L.not_driver_scaled(np.clip(a, 1075.0, 1950.0), lo, hi) is None  # the driver's clamp: kept
    assert L.not_driver_scaled(a + 100.0, lo, hi) is None  # beyond 2000 us: not the default scale either


sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import corpus_fetch as cf  # noqa: E402


def _tuning_row(fid: str) -> dict:
    return next(r for r in cf.read_list() if r["id"] == fid and r["half"] == "tuning")


def test_rfly_3539_real_motors_from_the_second_publisher():
    p = cf.cache_path(_tuning_row("rfly_3539_07_03_18"))
    if not p.is_file():
        pytest.skip(f"corpus cache absent ({p}): run tools/corpus_fetch.py")
    fl = U.read_ulog(p)
    assert fl.moving_outputs == (4, "actuator_outputs[0].output (noutputs 0)")
    m = fl.require("motors")
    assert m.source.startswith("actuator_outputs[0] (noutputs 0).output[0,1,2,3]")
    assert "1000-2000 us" in m.source
    assert fl.require("throttle").source.startswith("vehicle_rates_setpoint.thrust")
    t, v = m.t_s, m.values
    hover = (t > 10.0) & (t < 16.0)
    assert np.allclose(np.nanmedian(v[hover], axis=0), [0.30, 0.30, 0.29, 0.32], atol=0.03)
    # the experiment's fault: motor 1 (channel 0) commanded to 1000 us from 16.2 s until the stream ends
    cut = (t > 16.5) & (t < 21.3)
    assert np.mean(v[cut, 0] == 0.0) > 0.9
    assert np.mean(v[cut, 1:] == 0.0) < 0.3


def _disarm_mid_topics():
    """One publisher, 100 s at 50 Hz, armed 10-90 s: four motors 1100..1900 us while armed resting at
    1500 us disarmed (a reversible ESC or a PWM_DISARMED set mid-range); channel 4 a servo that moves while
    armed and rests at 2000 us."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 100.0, 0.02)
    armed = (t >= 10.0) & (t < 90.0)
    o = np.zeros((t.size, 16))
    o[:, :4] = np.where(armed[:, None], 1400.0 + 100.0 * np.sin(0.3 * t)[:, None]
                        + rng.normal(0.0, 30.0, (t.size, 4)), 1500.0)
    o[:, 4] = np.where(armed, 1500.0 + 300.0 * np.sin(0.2 * t), 2000.0)
    ao = U._Topic("actuator_outputs", 0, (t * 1e6).astype(np.int64), {f"output[{i}]": o[:, i] for i in range(16)})
    st = np.array([0.0, 10.0, 90.0])
    vs = U._Topic("vehicle_status", 0, (st * 1e6).astype(np.int64),
                  {"arming_state": np.array([1, 2, 1]), "nav_state": np.array([2, 2, 2])})
    return {("actuator_outputs", 0): ao, ("vehicle_status", 0): vs}


def test_motors_resting_at_the_logs_own_disarmed_value_are_motors_whatever_it_is():
    topics = _disarm_mid_topics()
    aos = {0: topics[("actuator_outputs", 0)]}
    # without parameters the rest-low rule alone: 1500 us is above their armed 5th percentile, refused
    assert U._guess_motor_stream(aos, 4, topics)[0] is None
    # PWM_DISARMED 1500 (PX4 1.8-1.11 MAIN): the driver writes 1500 disarmed, so resting there is no evidence
    inst, _, _, chans = U._guess_motor_stream(aos, 4, topics, 800.0, {"PWM_DISARMED": 1500.0})
    assert (inst, chans) == (0, [0, 1, 2, 3])
    # the same through a per-channel PWM_MAIN_DISn, and the 1.12 name; the servo parked at 2000 stays out
    p = {"PWM_DISARMED": 900.0, **{f"PWM_MAIN_DIS{i}": 1500.0 for i in range(1, 5)}, "PWM_MAIN_DIS5": -1.0}
    assert U._guess_motor_stream(aos, 4, topics, 800.0, p)[3] == [0, 1, 2, 3]
    assert U._guess_motor_stream(aos, 5, topics, 800.0, p)[0] is None
    assert U._guess_motor_stream(aos, 4, topics, 800.0, {"PWM_MAIN_DISARM": 1500.0})[3] == [0, 1, 2, 3]
    # a disarmed value the outputs do not rest at says nothing
    assert U._guess_motor_stream(aos, 4, topics, 800.0, {"PWM_DISARMED": 900.0})[0] is None
    dis, how = L.disarmed_pwm(p, "MAIN", 6)
    assert dis.tolist() == [1500.0, 1500.0, 1500.0, 1500.0, 900.0, 900.0]  # DIS5 -1 and DIS6 unset: PWM_DISARMED
    assert np.isnan(L.disarmed_pwm({}, "AUX", 2)[0]).all()
    assert how == "PWM_DISARMED/PWM_MAIN_DISn"
