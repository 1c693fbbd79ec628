"""Issue 14.3: ``rotortwin live`` -- the twin shadowing a vehicle's MAVLink telemetry.

A real flight (the CubeOrange ULog) is streamed as the MAVLink PX4 sends (see
``tests/test_live_telemetry_graph.py``) over UDP loopback, at real time, into
:func:`twin_nodes.live.shadow.run_live` (bridge, twin in open loop, metrics, link watchdog as
processes on a private ROS domain):

- the whole-run error metrics equal the offline computation of the stream as the live bridge timed
  it (:func:`twin_nodes.live.offline.compare_telemetry`) within 5 % (XY/Z RMSE and P75; measured
  0.00 %), and that computation matches the offline ``compare_log`` of the same part of the ULog
  within 5 %.  Open-loop errors are timing-sensitive (the twin integrates the 10 Hz motor commands for
  2 s without feedback: 2 ms of receive jitter on the commands moves them by up to 4.5 %), so the live
  graph times every input by the bridge's clock, however late each node runs, and the test compares
  with the stream as the bridge received it (as sent and as scheduled are printed);
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
#: how long the live graph's writers may take to match their readers (0.5-4 s measured at load 10-15)
READY_TIMEOUT_S = 30.0


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
    # scored on the span the stream's metrics cover (its last messages arrive before t1; the offline compare
    # used to lose about as much at the window's end, to a touchdown trim measured from the window's own end)
    t_scored = t0 + st["duration_s"]
    off = flight_metrics(align(run_twin_on_log(log, vp, "open", 2.0, t0=t0, t1=t1), log, t0=t0, t1=t_scored))
    print("stream:", {k: round(st[k], 3) for k in KEYS}, "compare_log:", {k: round(off[k], 3) for k in KEYS})
    assert st["duration_s"] > 10.0
    for k in KEYS:
        assert st[k] == pytest.approx(off[k], rel=0.05), k


def test_live_watermark_holds_a_backlog_taken_round_robin():
    """A twin node that fell 2 s behind takes its queues about one message per topic in turn, so the
    10 Hz motor commands run ahead of the 30 Hz odometry; the watermark follows the slower queue and
    no input is released before an older one has arrived (``late`` stays 0).  With the newest input
    of any topic as the watermark (before), 32 odometry samples were applied late."""
    from twin_nodes.logs import conversions as cv
    from twin_nodes.nodes.engine import NS, TwinEngine
    from twin_nodes.vehicle.params import load_params

    vp = load_params(PARAMS)
    odom = [(int(k * NS / 30), "/real/odom") for k in range(60)]
    mot = [(int(k * NS / 10), "/real/motors") for k in range(20)]
    q = [0.0, 0.0, 0.0, 1.0]

    def run(live: bool) -> int:
        eng = TwinEngine(vp, mode="open")
        for i in range(60):  # round-robin: one of each queue per turn while both have messages
            for queue in (odom, mot):
                if i < len(queue):
                    t, topic = queue[i]
                    msg = (cv.odom_msg(t, [0, 0, 1.0], q, [0, 0, 0], [0, 0, 0]) if topic == "/real/odom"
                           else cv.motors_msg([0.5] * 4))
                    eng.push(t, topic, msg)
                    eng.advance_live(topic, t, now_s=100.0) if live else eng.advance(t)  # taken at once
                    eng.pop()
        eng.pop(flush=True)
        return eng.buf.late

    assert run(live=True) == 0
    assert run(live=False) == 32


# ----------------------------------------------------------------------------- live (ROS)


def _free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class _Live:
    """run_live in a thread; a probe node on its domain (readiness, topic capture)."""

    def __init__(self, tmp_path: Path, topics: tuple[str, ...] = (), **cfg: object):
        self.tmp_path = tmp_path
        self.topics = topics
        self.cfg_extra = cfg  # more LiveConfig fields (e.g. stale_after_s)
        self.discovery_retries: list[dict] = []  # the matched counts of graphs that never came up

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
        # Fast DDS on this shared machine (hundreds of participants' shared-memory files in /dev/shm)
        # once left the bridge's /real/odom writer matched by 2 of its 4 readers for 3 minutes (1 of
        # about 40 runs; 16 other starts matched within 2-6 s): such a graph is stopped and started
        # again on a fresh domain, once, and the test says so
        for attempt in range(2):
            if self._start(attempt):
                return self
            self.discovery_retries.append(dict(self.matched))
            print(f"live graph not matched within {READY_TIMEOUT_S:g} s ({self.matched}): starting it again")
            self.__exit__(None, None, None)
        raise AssertionError(f"the live graph did not come up twice: {self.discovery_retries} {self.logs()}")

    def _start(self, attempt: int) -> bool:
        import rclpy

        from twin_nodes.live.shadow import LiveConfig

        self.port = _free_udp_port()
        self.cfg = LiveConfig(url=f"udpin:127.0.0.1:{self.port}", params_file=str(PARAMS), window_s=3.0,
                              **{**LINK, **self.cfg_extra})
        self.run_dir = self.tmp_path / ("run" if attempt == 0 else f"run{attempt}")
        self.stop = threading.Event()
        self.started = threading.Event()
        self.info: dict = {}
        self.result = None
        self.error: BaseException | None = None
        self.got: dict[str, list[tuple[float, float]]] = {t: [] for t in self.topics}  # (wall time, value)
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
        # the times the bridge gave the inputs: /real/odom's header stamps, /real/motors' DDS source
        # timestamps (what the twin and the metrics time them by) [Unix ns]
        self.bridge_t: dict[str, list[int]] = {"/real/odom": [], "/real/motors": []}
        self.node.create_subscription(msg_class(TOPICS["/real/odom"].type), "/real/odom", lambda m: self.bridge_t[
            "/real/odom"].append(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec), reliable_qos())
        self.node.create_subscription(msg_class(TOPICS["/real/motors"].type), "/real/motors", lambda m, info: self.bridge_t[
            "/real/motors"].append(int(info["source_timestamp"])), reliable_qos())
        # what the bridge and the twin say about who hears them (matched subscriptions, once a second)
        self.matched: dict[str, dict[str, int]] = {}

        def on_diag(m) -> None:
            for st in m.status:
                if st.name in ("px4_bridge/link", "twin/outputs"):
                    self.matched[st.name] = {kv.key: int(kv.value) for kv in st.values
                                             if kv.key.endswith("_subscribers")}
        self.node.create_subscription(msg_class("diagnostic_msgs/msg/DiagnosticArray"), "/diagnostics", on_diag, 10)
        self.ex = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self._spin = True
        self.spinner = threading.Thread(target=self._spin_loop, daemon=True)
        self.spinner.start()
        # ready when the writers have matched their readers (reliable data written from then on is
        # delivered): the bridge's /real/odom by the twin, metrics, watchdog and this probe, its
        # /real/motors by the twin, metrics and probe, the twin's /twin/odom by the metrics and probe.
        # 2-6 s after the start on the loaded machine; a fixed 2 s sleep lost the first messages
        want = {"px4_bridge/link": {"odom_subscribers": 4, "motors_subscribers": 3},
                "twin/outputs": {"odom_subscribers": 2}}
        t_end = time.monotonic() + READY_TIMEOUT_S
        while time.monotonic() < t_end:
            if all(self.matched.get(n, {}).get(k, 0) >= v for n, kv in want.items() for k, v in kv.items()):
                self.t_ready = time.monotonic()
                return True
            time.sleep(0.1)
        return False

    def _spin_loop(self) -> None:
        while self._spin:
            self.ex.spin_once(timeout_sec=0.05)

    def play(self, stream, skip=None) -> float:
        """Send the stream at real time (messages with ``skip(t)`` true are not sent); its start
        [monotonic] (``self.t0_unix``: the same in Unix time, the clock the nodes stamp with).
        ``self.sent``: ``(t_s, data)`` of what was sent, ``t_s`` when it was sent (from the start)."""
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        t_start = time.monotonic()
        self.t0_unix = time.time()
        self.sent = []
        try:
            for t_s, data in stream:
                wait = t_s - (time.monotonic() - t_start)
                if wait > 0:
                    time.sleep(wait)
                if skip is None or not skip(t_s):
                    tx.sendto(data, ("127.0.0.1", self.port))
                    self.sent.append((time.monotonic() - t_start, data))
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


def _decoded(sent):
    from pymavlink.dialects.v20 import common as mavlink2

    parser = mavlink2.MAVLink(None)
    return [(t, parser.decode(bytearray(data))) for t, data in sent]


def _command_times(msgs) -> tuple[np.ndarray, np.ndarray]:
    """When each motor command and odometry sample arrives in a stream ``[(t_s, message)]``."""
    from twin_nodes.mavlink.telemetry import TelemetryAggregator

    agg = TelemetryAggregator(_telemetry_config())
    t_mot, t_odom = [], []
    for t, m in msgs:
        kinds = agg.update(m, now_s=t)
        if "motors" in kinds:
            t_mot.append(t)
        if "odom" in kinds:
            t_odom.append(t)
    return np.array(t_mot), np.array(t_odom)


def _twin_input_delay_s(live: _Live, sent_msgs) -> float:
    """How late the live twin applied the motor commands: the shift of the commands as sent (send
    time + the Unix time of the stream's start) that best matches the twin's own motors (in open
    loop the real ones, held), 0..0.5 s in 1 ms steps."""
    from twin_nodes.mavlink.telemetry import TelemetryAggregator

    agg = TelemetryAggregator(_telemetry_config())
    ts, us = [], []
    for t, m in sent_msgs:
        if "motors" in agg.update(m, now_s=t):
            ts.append(live.t0_unix + t)
            us.append(agg.state.motors.copy())
    ts_a, us_a = np.array(ts), np.array(us)
    n = min(len(live.twin_t), len(live.twin_u))
    tw = np.array(live.twin_t[:n]) / 1e9
    uw = np.array(live.twin_u[:n]).reshape(n, -1)
    best = (math.inf, 0.0)
    for shift in np.arange(0.0, 0.5, 0.001):
        k = np.searchsorted(ts_a, tw - shift, side="right") - 1
        pred = us_a[np.clip(k, 0, None)]
        ok = (k >= 0) & np.isfinite(uw).all(axis=1) & np.isfinite(pred).all(axis=1)
        if ok.sum() > 100:
            best = min(best, (float(np.mean((uw[ok] - pred[ok]) ** 2)), float(shift)))
    return best[1]


def _twin_stop_line(live: _Live) -> str:
    lines = [ln for ln in (live.run_dir / "twin.log").read_text().splitlines() if "stopped:" in ln]
    return lines[-1].split("stopped: ", 1)[1] if lines else "no stop line"


def _bridge_timed(live: _Live, sent_msgs) -> list:
    """The stream as the live bridge timed it: each odometry message at its ``/real/odom`` stamp,
    each motor command at its ``/real/motors`` source timestamp, the rest (heartbeats) at the time
    of the message before it (the bridge takes them in order); ``[(t_s from the stream start, msg)]``."""
    from twin_nodes.mavlink.telemetry import TelemetryAggregator

    agg = TelemetryAggregator(_telemetry_config())
    it = {k: iter(v) for k, v in live.bridge_t.items()}
    out, t_prev = [], 0.0
    for _, m in sent_msgs:
        kinds = agg.update(m, now_s=0.0)
        if "odom" in kinds:
            t_prev = next(it["/real/odom"]) / 1e9 - live.t0_unix
        elif "motors" in kinds:
            t_prev = next(it["/real/motors"]) / 1e9 - live.t0_unix
        out.append((t_prev, m))
    return out


@pytest.mark.ros
@pytest.mark.slow
def test_live_errors_match_the_offline_computation_of_the_stream(tmp_path):
    """The live graph's whole-run errors equal the offline computation of the same stream, timed as the
    live bridge timed it, within 5 % (XY/Z RMSE and P75; measured: 0.00 % in 24 of 24 runs at load
    2-17; the same check runs in the default suite inside the link-loss test): every node times every input by the bridge's clock (header stamps, DDS source
    timestamps for the header-less ones), nothing is lost at the start (the test waits until the
    bridge's and the twin's writers have matched their readers), the twin starts at the first
    odometry, and on stop it applies what its reorder buffer held, as the offline computation does.

    The stream as sent or as scheduled is printed, not asserted: open loop, the twin integrates the
    10 Hz commands for 2 s without feedback, so a command that lands 2 ms later (a loaded machine's
    UDP receive jitter) moves the offline errors of this stream by up to 4.5 % (XY RMSE) and 5 % (Z P75)."""
    _need_log()
    pytest.importorskip("rclpy")
    stream, nominal = _messages(12.0)
    with _Live(tmp_path) as live:
        live.play(stream)
        time.sleep(1.5)
    _check_live_equals_offline(live, nominal)


def _check_live_equals_offline(live: _Live, nominal) -> None:
    """A finished live run's totals against the offline computation of its stream as the bridge
    timed it (asserted), as sent and as scheduled (``nominal``, printed)."""
    from twin_nodes.live.offline import compare_telemetry
    from twin_nodes.vehicle.params import load_params

    res = live.result
    assert live.error is None and res is not None, live.error
    assert all(c == 0 for c in res.exit_codes.values()), (res.exit_codes, live.logs())
    m = res.metrics
    sent = _decoded(live.sent)
    t_mot, t_odom = _command_times(sent)
    # nothing lost: the metrics node (and this probe) got every odometry sample and motor command sent
    got = (m["received"]["/real/odom"], m["received"]["/real/motors"], len(live.bridge_t["/real/odom"]),
           len(live.bridge_t["/real/motors"]))
    assert got == (len(t_odom), len(t_mot)) * 2, (got, len(t_odom), len(t_mot))
    # the twin started at the first odometry sample (its first output one 4 ms control step later)
    start = live.twin_t[0] / 1e9 - live.bridge_t["/real/odom"][0] / 1e9
    assert 0.0 < start < 0.005 + 1e-6, f"the live twin's first output came {start * 1e3:.1f} ms after the first odometry"
    delay = _twin_input_delay_s(live, sent)
    vp = load_params(PARAMS)
    off = compare_telemetry(_bridge_timed(live, sent), vp, config=_telemetry_config(), window_s=3.0)
    as_sent = compare_telemetry(sent, vp, config=_telemetry_config(), window_s=3.0)
    nom = compare_telemetry(nominal, vp, config=_telemetry_config(), window_s=3.0)
    lat = (np.array(live.bridge_t["/real/odom"]) / 1e9 - live.t0_unix - t_odom) * 1e3
    keys = KEYS + ("throttle_rmse",)

    def rel(ref):
        return {k: round(100 * (m[k] / ref[k] - 1), 2) for k in KEYS}
    print(f"live {({k: round(m[k], 4) for k in keys})}; live/offline - 1 [%]: bridge-timed {rel(off)}, as sent "
          f"{rel(as_sent)}, as scheduled {rel(nom)}; bridge stamp - send time: median {np.median(lat):.2f} ms, "
          f"max {lat.max():.1f} ms; motors applied {delay * 1e3:.0f} ms after they were sent; twin: "
          f"{_twin_stop_line(live)}; graphs restarted for discovery: {live.discovery_retries}; "
          f"load {os.getloadavg()[0]:.1f}")
    assert m["duration_s"] == pytest.approx(off["duration_s"], abs=0.05) and m["n_samples"] > 500, m
    assert delay <= 0.01, f"the live twin applied the motor commands {delay * 1e3:.0f} ms after they were sent"
    for k in KEYS:
        assert m[k] == pytest.approx(off[k], rel=0.05), (k, m[k], off[k])
    # open loop: the twin's throttle is the mean of the real commands, its error only their timing
    # (0.4 % of full throttle RMS offline); live within 0.1 % of full throttle of it
    assert m["throttle_rmse"] == pytest.approx(off["throttle_rmse"], abs=0.001), (m["throttle_rmse"],
                                                                                  off["throttle_rmse"])


@pytest.mark.ros
def test_link_loss_is_flagged_and_recovered(tmp_path):
    """20 s of the flight with 5 s of silence in it: the link flag goes up 3 s (``stale_after``) into
    the silence and down with the first message after it, the rolling errors come back, and the
    run's totals still equal the offline computation of the stream as the bridge timed it."""
    _need_log()
    pytest.importorskip("rclpy")
    stream, nominal = _messages(20.0)
    gap = (7.0, 12.0)  # 5 s of silence
    topics = ("/twin_error/link_lost", "/twin_error/xy/rmse_m", "/twin_error/z/rmse_m")
    with _Live(tmp_path, topics) as live:
        t0 = live.play(stream, skip=lambda t: gap[0] <= t < gap[1])
        time.sleep(1.5)
    res = live.result
    _check_live_equals_offline(live, [(t, m) for t, m in nominal if not gap[0] <= t < gap[1]])
    rel = {t: [(w - t0, v) for w, v in live.got[t]] for t in topics}
    flags = rel["/twin_error/link_lost"]
    print("link_lost:", [(round(t, 2), v) for t, v in flags if 5 < t < 16],
          "outages:", res.outages)
    # flagged: up within stale_after (3 s) + 1.5 s of the last message before the gap ...
    up = [t for t, v in flags if v == 1.0 and gap[0] < t < gap[1] + 0.5]
    assert up and gap[0] + 2.9 < up[0] < gap[0] + 3.0 + 1.5, flags
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
