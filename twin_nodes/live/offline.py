"""The live shadow offline: a recorded MAVLink telemetry stream (e.g. a QGroundControl ``.tlog``)
through the same cores as ``rotortwin live``, in one process, with the stream's own times.

What ``rotortwin live`` does with processes and wall time -- the PX4 bridge turning MAVLink into
``/real/...`` messages (:class:`~twin_nodes.mavlink.telemetry.TelemetryAggregator` +
:mod:`twin_nodes.logs.conversions`), the twin node's :class:`~twin_nodes.nodes.engine.TwinEngine`
in open loop with the newest input time as its watermark, and the metrics node's
:class:`~twin_nodes.nodes.engine.MetricsEngine` totals -- is done here message by message, so the
live run of a stream can be checked against the offline computation of the same stream
(``tests/test_live_shadow.py``: within 5 %).  Messages are stamped with their stream time, where
the live graph stamps them with the bridge's clock at reception (the twin and the metrics read the
header-less ones' DDS source timestamps, see :mod:`twin_nodes.live.shadow`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable

import numpy as np

from twin_nodes.mavlink.telemetry import watched

__all__ = ["compare_telemetry", "read_tlog", "watched"]

NS = 1_000_000_000


def read_tlog(path: str | Path) -> list[tuple[float, Any]]:
    """``[(t_s, message), ...]`` of a MAVLink telemetry log (``.tlog``: each packet after its 8-byte
    µs Unix time), in file order."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(path), dialect="common")
    out = []
    try:
        while True:
            m = conn.recv_match(blocking=False)
            if m is None:
                break
            if m.get_type() != "BAD_DATA":
                out.append((float(getattr(m, "_timestamp", 0.0)), m))
    finally:
        conn.close()
    return out


def compare_telemetry(messages: Iterable[tuple[float, Any]], vp: Any, *, config: Any = None, mode: str = "open",
                      horizon_s: float = 2.0, window_s: float = 5.0, airborne_only: bool = True,
                      publish_rate_hz: float = 50.0, reorder_lag_s: float = 0.5, rate_hz: float = 50.0,
                      flush: bool = True, source: str = "", rolling: list | None = None) -> dict[str, Any]:
    """Whole-run metrics of the twin beside a telemetry stream ``[(t_s, mavlink message), ...]``,
    computed as the live graph computes them (``flush``: also apply the last ``reorder_lag_s`` of
    inputs at the end, as the live twin node does when it is stopped).

    A vehicle restart in the stream (:class:`~twin_nodes.mavlink.telemetry.TelemetryAggregator`'s
    ``reset``) starts the twin afresh and restarts the rolling window, as live.  The result also says
    what was watched: ``source`` (e.g. the tlog's path) in ``log``, the vehicle's system id, the
    stream's start/end time, the resets and the link losses (silences longer than the config's
    ``stale_after_s``).  ``rolling``: a list that gets ``(t_ns, {channel: {stat: value}})`` of the
    rolling window as the metrics node publishes it."""
    from twin_nodes.logs import conversions as cv
    from twin_nodes.mavlink.telemetry import TelemetryAggregator, TelemetryConfig
    from twin_nodes.nodes.engine import RESET_TOPIC, MetricsEngine, TwinEngine, as_float32, reset_msg

    cfg = config or TelemetryConfig(n_motors=vp.rotors.count)
    agg = TelemetryAggregator(cfg)
    twin = TwinEngine(vp, mode=mode, horizon_s=horizon_s, publish_rate_hz=publish_rate_hz,
                      reorder_lag_s=reorder_lag_s)
    met = MetricsEngine(vp.rotors.count, window_s, NS // 2, airborne_only)

    def twin_in(t: int, topic: str, msg: Any) -> None:
        twin.push(t, topic, msg)
        twin.advance_live(topic, t, t / NS)  # live: the inputs' own times are the twin's watermark

    def drain(flush_: bool = False) -> None:
        for t, s in twin.pop(flush=flush_):
            # what the metrics node reads back: odom in float64, throttle and motors through Float32
            met.add_twin(t, s.x[0:3].copy(), float(np.float32(s.throttle)), as_float32(s.motors))
        out = met.evaluate()
        if rolling is not None:
            rolling.extend(out)

    t_first = t_last = None
    losses: list[dict[str, float]] = []
    for t_s, msg in messages:
        t_first = t_s if t_first is None else t_first
        if agg.check_stale(t_s) and agg.state.system_id is not None:  # the silence before this message
            last = agg.state.last_rx_wall_s
            losses.append({"start_s": float(last), "length_s": float(t_s - last)})
        kinds = agg.update(msg, now_s=t_s)
        t_last = t_s
        if not kinds:
            continue
        st = agg.state
        t = int(round(t_s * NS))
        if "reset" in kinds:  # just before the message that showed it (the bridge does the same)
            twin_in(t - 1, RESET_TOPIC, reset_msg(t - 1, st.reset_reason, len(st.resets)))
            met.reset(t - 1, st.reset_reason)
        if "odom" in kinds:
            m = cv.odom_msg(t, st.position_enu, st.q_enu_flu, st.velocity_body_flu(), st.rates_flu)
            twin_in(t, "/real/odom", m)
            met.add_real("/real/odom", t, m)
        if "motors" in kinds:
            m = cv.motors_msg(st.motors)
            twin_in(t, "/real/motors", m)
            met.add_real("/real/motors", t, m)
        if "throttle" in kinds:
            met.add_real("/real/throttle", t, cv.float32_msg(st.throttle))
        if "battery" in kinds and st.battery is not None:
            twin_in(t, "/real/battery", cv.battery_msg(t, st.battery.voltage_v, st.battery.current_a))
        if "setpoint" in kinds:
            twin_in(t, "/real/setpoint", cv.setpoint_msg(st.setpoint))
        if "status" in kinds:
            m = cv.status_msg(*st.status)
            twin_in(t, "/real/status", m)
            met.add_real("/real/status", t, m)
        drain()
    drain(flush)
    out = met.evaluate(final=True)
    if rolling is not None:
        rolling.extend(out)
    m = met.totals(0, mode, rate_hz, source="telemetry").metrics
    st = agg.state
    m.update(watched(source or "telemetry stream", st, t_first, t_last, losses))
    m["source"] = "rotortwin live tlog (telemetry log -> twin -> metrics, offline)"
    return m


