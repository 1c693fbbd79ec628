"""Issue 14.3: ``rotortwin live`` -- the twin shadowing a vehicle's MAVLink telemetry.

A real flight (the CubeOrange ULog) is streamed as the MAVLink PX4 sends (see
``tests/test_live_telemetry_graph.py``) over UDP loopback, at real time, into
:func:`twin_nodes.live.shadow.run_live` (bridge, twin in open loop, metrics, link watchdog as
processes on a private ROS domain):

- the whole-run error metrics match the offline computation of the same stream
  (:func:`twin_nodes.live.offline.compare_telemetry`): the RMSEs within 5 % (the P75s within 8 %)
  of the range it spans when the motor commands arrive 0-20 ms late (open-loop errors are that
  timing-sensitive: see DELAYS_S),
  and that computation matches the offline ``compare_log`` of the same part of the ULog within 5 %;
- a 5 s silence is flagged on ``/twin_error/link_lost`` and the error topics come back after it.
"""

from __future__ import annotations

import math
import os
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import missing_shared

REPO = Path(__file__).resolve().parents[1]
LOG = REPO.parent / "shared" / "flightlogs" / "real" / "real_cubeorange_takeoff_land.ulg"
PARAMS = REPO / "params" / "quad_c_3dr.yaml"
# the vehicle's motors are on AUX 1-4 (SERVO_OUTPUT_RAW port 1), PWM_AUX_MIN/MAX 1100/1900
LINK = dict(motor_channels="16,17,18,19", request_streams=False, pwm_min_us=1100.0, pwm_max_us=1900.0)
KEYS = ("xy_rmse_m", "xy_p75_m", "z_rmse_m", "z_p75_m")
#: Open-loop errors are timing-sensitive: the twin integrates the 10 Hz motor commands over 2 s
#: without feedback, so the offline computation of this stream itself moves by up to 4 % (XY RMSE)
#: when the commands are applied 5-20 ms later -- and a live twin stamps them when their callback
#: runs (a few ms after the odometry, more on a loaded machine).  The live errors are compared with
#: the range the offline computation spans over these input delays (and the delay the live twin
#: showed), within 5 %.
DELAYS_S = (0.0, 0.005, 0.01, 0.02)


def _need_log() -> None:
    if not LOG.exists():
        missing_shared(LOG.name)


def _messages(seconds: float):
    from pymavlink.dialects.v20 import common as mavlink2
    from test_live_telemetry_graph import _stream

    stream = _stream(seconds)
    parser = mavlink2.MAVLink(None)
    return stream, [(t, parser.decode(bytearray(data))) for t, data in stream]


def _telemetry_config():
    from twin_nodes.mavlink.telemetry import TelemetryConfig

    return TelemetryConfig(pwm_min_us=LINK["pwm_min_us"], pwm_max_us=LINK["pwm_max_us"], n_motors=4,
                           motor_channels=(16, 17, 18, 19), request_streams=False)


def test_offline_stream_compare_matches_compare_log():
    """The live computation done offline on the stream agrees with the ULog's offline compare (the
    rest: the live twin holds each 10 Hz motor command, the offline one interpolates the log)."""
    _need_log()
    from twin_nodes.live.offline import compare_telemetry
    from twin_nodes.logs.ulog_io import read_ulog
    from twin_nodes.twin.compare import align
    from twin_nodes.twin.metrics import flight_metrics
    from twin_nodes.twin.runner import run_twin_on_log
    from twin_nodes.vehicle.params import load_params

    vp = load_params(PARAMS)
    _, msgs = _messages(12.0)
    st = compare_telemetry(msgs, vp, config=_telemetry_config(), window_s=3.0)
    log = read_ulog(LOG)
    t0, t1 = 8.0, 20.0  # the streamed part (log time)
    off = flight_metrics(align(run_twin_on_log(log, vp, "open", 2.0, t0=t0, t1=t1), log, t0=t0, t1=t1))
    print("stream:", {k: round(st[k], 3) for k in KEYS}, "compare_log:", {k: round(off[k], 3) for k in KEYS})
    assert st["duration_s"] > 10.0
    for k in KEYS:
        assert st[k] == pytest.approx(off[k], rel=0.05), k


# ----------------------------------------------------------------------------- live (ROS)


def _free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class _Live:
    """run_live in a thread; a probe node on its domain (readiness, topic capture)."""

    def __init__(self, tmp_path: Path, topics: tuple[str, ...] = ()):
        from twin_nodes.live.shadow import LiveConfig

        self.port = _free_udp_port()
        self.cfg = LiveConfig(url=f"udpin:127.0.0.1:{self.port}", params_file=str(PARAMS), window_s=3.0, **LINK)
        self.run_dir = tmp_path / "run"
        self.stop = threading.Event()
        self.started = threading.Event()
        self.info: dict = {}
        self.result = None
        self.error: BaseException | None = None
        self.topics = topics
        self.got: dict[str, list[tuple[float, float]]] = {t: [] for t in topics}  # (wall time, value)

    def _run(self) -> None:
        from twin_nodes.live.shadow import run_live

        def on_start(info):
            self.info = info
            self.started.set()
        try:
            self.result = run_live(self.cfg, run_dir=self.run_dir, stop=self.stop, on_start=on_start)
        except BaseException as exc:  # reported by the test
            self.error = exc
            self.started.set()

    def __enter__(self) -> "_Live":
        import rclpy

        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        assert self.started.wait(180) and self.error is None, self.error
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=self.info["domain_id"])
        self.node = rclpy.create_node("live_probe", context=self.ctx)
        from std_msgs.msg import Bool, Float64

        from twin_nodes.nodes.common import reliable_qos

        for t in self.topics:
            cls, qos = (Bool, reliable_qos(1, latched=True)) if t.endswith("link_lost") else (Float64, 50)
            self.node.create_subscription(cls, t, lambda m, t=t: self.got[t].append((time.monotonic(),
                                                                                    float(m.data))), qos)
        # the twin's motor commands and their times (message k of /twin/motors has /twin/odom k's stamp)
        from msgs_py.topics import TOPICS, msg_class

        self.twin_t: list[int] = []
        self.twin_u: list[np.ndarray] = []
        self.node.create_subscription(msg_class(TOPICS["/twin/odom"].type), "/twin/odom", lambda m: self.twin_t.append(
            m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec), reliable_qos())
        self.node.create_subscription(msg_class(TOPICS["/twin/motors"].type), "/twin/motors",
                                      lambda m: self.twin_u.append(np.asarray(m.data, float)), reliable_qos())
        self.ex = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self._spin = True
        self.spinner = threading.Thread(target=self._spin_loop, daemon=True)
        self.spinner.start()
        # ready: the bridge publishes /real/odom and the twin, metrics and watchdog subscribe to it
        t_end = time.monotonic() + 180
        while time.monotonic() < t_end:
            subs = {i.node_name for i in self.node.get_subscriptions_info_by_topic("/real/odom")}
            pubs = self.node.get_publishers_info_by_topic("/real/odom")
            if {"twin", "metrics", "link_watch"} <= subs and pubs:
                break
            time.sleep(0.2)
        else:
            raise AssertionError(f"the live graph did not come up: {self.logs()}")
        time.sleep(2.0)  # let the endpoints match
        return self

    def _spin_loop(self) -> None:
        while self._spin:
            self.ex.spin_once(timeout_sec=0.05)

    def play(self, stream, skip=None) -> float:
        """Send the stream at real time (messages with ``skip(t)`` true are not sent); its start
        [monotonic] (``self.t0_unix``: the same in Unix time, the clock the nodes stamp with)."""
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        t_start = time.monotonic()
        self.t0_unix = time.time()
        try:
            for t_s, data in stream:
                wait = t_s - (time.monotonic() - t_start)
                if wait > 0:
                    time.sleep(wait)
                if skip is None or not skip(t_s):
                    tx.sendto(data, ("127.0.0.1", self.port))
        finally:
            tx.close()
        return t_start

    def logs(self) -> str:
        return "\n".join(f"{p.name}: {p.read_text()[-800:]}" for p in sorted(self.run_dir.glob("*.log")))

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(240)
        self._spin = False
        self.spinner.join(5)
        self.ex.shutdown()
        self.node.destroy_node()
        import rclpy
        rclpy.try_shutdown(context=self.ctx)


def _twin_input_delay_s(live: _Live, msgs) -> float:
    """How late the live twin applied the motor commands: the shift of the commands as sent (stream
    time + the Unix time of the stream's start) that best matches the twin's own motors (in open
    loop the real ones, held), 0..0.5 s in 5 ms steps."""
    from twin_nodes.mavlink.telemetry import TelemetryAggregator

    agg = TelemetryAggregator(_telemetry_config())
    ts, us = [], []
    for t, m in msgs:
        if "motors" in agg.update(m, now_s=t):
            ts.append(live.t0_unix + t)
            us.append(agg.state.motors.copy())
    ts_a, us_a = np.array(ts), np.array(us)
    n = min(len(live.twin_t), len(live.twin_u))
    tw = np.array(live.twin_t[:n]) / 1e9
    uw = np.array(live.twin_u[:n]).reshape(n, -1)
    best = (math.inf, 0.0)
    for shift in np.arange(0.0, 0.5, 0.005):
        k = np.searchsorted(ts_a, tw - shift, side="right") - 1
        pred = us_a[np.clip(k, 0, None)]
        ok = (k >= 0) & np.isfinite(uw).all(axis=1) & np.isfinite(pred).all(axis=1)
        if ok.sum() > 100:
            best = min(best, (float(np.mean((uw[ok] - pred[ok]) ** 2)), float(shift)))
    return best[1]


@pytest.mark.ros
@pytest.mark.slow
def test_live_errors_match_the_offline_computation_of_the_stream(tmp_path):
    _need_log()
    pytest.importorskip("rclpy")
    from twin_nodes.live.offline import compare_telemetry
    from twin_nodes.vehicle.params import load_params

    stream, msgs = _messages(12.0)
    with _Live(tmp_path) as live:
        live.play(stream)
        time.sleep(1.5)
    res = live.result
    assert live.error is None and res is not None, live.error
    assert all(c == 0 for c in res.exit_codes.values()), (res.exit_codes, live.logs())
    m = res.metrics
    assert m["duration_s"] > 10.0 and m["n_samples"] > 500, m
    vp = load_params(PARAMS)
    delay = _twin_input_delay_s(live, msgs)
    assert delay < 0.4, f"the live twin applied the motor commands {delay:.2f} s late"
    offs = [compare_telemetry(msgs, vp, config=_telemetry_config(), window_s=3.0, twin_input_delay_s=d)
            for d in sorted(set(DELAYS_S) | {round(delay, 3)})]
    lo = {k: min(o[k] for o in offs) for k in KEYS}
    hi = {k: max(o[k] for o in offs) for k in KEYS}
    print(f"live {({k: round(m[k], 3) for k in KEYS})}; offline, input delays 0-{max(DELAYS_S + (delay,)) * 1e3:.0f} ms: "
          f"{({k: (round(lo[k], 3), round(hi[k], 3)) for k in KEYS})}; undelayed/live - 1: "
          f"{({k: round(100 * (m[k] / offs[0][k] - 1), 1) for k in KEYS})} %; the live twin's input delay "
          f"{delay * 1e3:.0f} ms; load {os.getloadavg()[0]:.1f}")
    # RMSE within 5 %; a 75th percentile moves more with the live stamps' millisecond jitter (Z P75 came
    # out 0-6 % above the range in 5 runs while the RMSEs stayed within 2 %)
    for k in KEYS:
        tol = 0.05 if k.endswith("rmse_m") else 0.08
        assert lo[k] * (1 - tol) <= m[k] <= hi[k] * (1 + tol), (k, m[k], lo[k], hi[k])


@pytest.mark.ros
@pytest.mark.slow
def test_link_loss_is_flagged_and_recovered(tmp_path):
    _need_log()
    pytest.importorskip("rclpy")
    stream, _ = _messages(20.0)
    gap = (7.0, 12.0)  # 5 s of silence
    topics = ("/twin_error/link_lost", "/twin_error/xy/rmse_m", "/twin_error/z/rmse_m")
    with _Live(tmp_path, topics) as live:
        t0 = live.play(stream, skip=lambda t: gap[0] <= t < gap[1])
        time.sleep(1.5)
    res = live.result
    assert live.error is None and res is not None, live.error
    assert all(c == 0 for c in res.exit_codes.values()), (res.exit_codes, live.logs())
    rel = {t: [(w - t0, v) for w, v in live.got[t]] for t in topics}
    flags = rel["/twin_error/link_lost"]
    print("link_lost:", [(round(t, 2), v) for t, v in flags if 5 < t < 16],
          "outages:", res.outages)
    # flagged: up within stale_after (3 s) + 1.5 s of the last message before the gap ...
    up = [t for t, v in flags if v == 1.0 and gap[0] < t < gap[1] + 0.5]
    assert up and up[0] < gap[0] + 3.0 + 1.5, flags
    # ... and down within 2 s of the first message after it
    down = [t for t, v in flags if v == 0.0 and t > up[0]]
    assert down and down[0] < gap[1] + 2.0, flags
    closed = [o for o in res.outages if not o.get("open")]
    assert len(closed) == 1 and 4.5 < closed[0]["length_s"] < 7.5, res.outages
    # recovered: rolling errors flow again after the gap and settle back to the level before it
    for t in ("/twin_error/xy/rmse_m", "/twin_error/z/rmse_m"):
        before = [v for w, v in rel[t] if w < gap[0] + 1.0 and math.isfinite(v)]
        after = [v for w, v in rel[t] if w > gap[1] + 3.0 + 2.0 + 1.0 and math.isfinite(v)]  # window + horizon
        print(t, "before", np.round(before[-3:], 2), "after", np.round(after[-3:], 2))
        assert len(before) >= 3 and len(after) >= 3, rel[t]
        assert after[-1] < 2.0 * max(before[-3:]) + 0.5, (before[-3:], after[-3:])
