"""The pure cores of the graph's nodes (no rclpy): what the twin and metrics nodes compute.

The nodes are thin shells around these classes, and ``rotortwin regress --offline``
runs the same classes in one process on a recording's messages, so the graph and
the offline regression compute the same numbers the same way.

- :class:`Timeline`: times of the messages of header-less replayed topics.
- :class:`ReorderBuffer`: releases inputs in time order behind a watermark.
- :class:`TwinEngine`: the twin node's core.  Inputs (``/real/...`` messages or
  anything with the same attributes, e.g. rosbags messages) are applied in time
  order to a :class:`twin_nodes.twin.runner.TwinRunner`; outputs come at
  ``publish_rate_hz`` of log time.
- :class:`Track` and :func:`final_streams`: the metrics node's real signals and the
  arrays its whole-flight totals are computed from
  (:func:`twin_nodes.twin.compare.metrics_from_streams`).
"""

from __future__ import annotations

import bisect
import heapq
import itertools
import math
from typing import Any, Iterable

import numpy as np

from twin_nodes.logs import conversions as cv

__all__ = ["NS", "Timeline", "ReorderBuffer", "TwinEngine", "Track", "final_streams", "TWIN_INPUTS",
           "as_float32", "CONFIG_TOPIC", "twin_config", "RESET_TOPIC", "METRICS_RESET_TOPIC", "reset_msg",
           "reset_fields", "MetricsEngine"]

NS = 1_000_000_000
#: the twin's inputs
TWIN_INPUTS = ("/real/odom", "/real/setpoint", "/real/motors", "/real/status", "/real/battery", "/real/throttle")
#: the twin's outputs, one message each per twin sample (``/twin/done`` carries how many samples)
TWIN_OUTPUTS = ("/twin/odom", "/twin/motors", "/twin/throttle", "/twin/imu")
#: live, the inputs whose times move the twin's watermark (TwinEngine.advance_live), and how long
#: one may be silent [s of the receiving clock] before it no longer holds the others back
LIVE_PACED = ("/real/odom", "/real/motors")
LIVE_STALE_S = 1.0
#: latched JSON published by the twin node: the params file (path, text, sha256) and its settings
CONFIG_TOPIC = "/twin/config"
#: a vehicle restart (issue 28), published by the PX4 bridge: std_msgs/String, JSON
#: ``{"t_ns": the bridge's time of the restart, "reason": ..., "count": n}``.  The twin starts afresh
#: from the next real state; the metrics restart their rolling window and never compare across it
RESET_TOPIC = "/real/reset"
#: the metrics' note of each restart of their rolling window: std_msgs/String, JSON
#: ``{"t_s": time, "reason": ..., "count": n}`` (latched, the last one)
METRICS_RESET_TOPIC = "/twin_error/reset"


def reset_msg(t_ns: int, reason: str, count: int) -> Any:
    """The ``/real/reset`` message."""
    import json

    return cv.string_msg(json.dumps({"t_ns": int(t_ns), "reason": str(reason), "count": int(count)}))


def reset_fields(msg: Any) -> tuple[int, str]:
    """``(t_ns, reason)`` of a ``/real/reset`` message."""
    import json

    d = json.loads(msg.data)
    return int(d["t_ns"]), str(d.get("reason", ""))


class Timeline:
    """Times of the messages of header-less topics (from the replay's ``/replay/timeline``).

    ``take(topic)`` returns the time [ns] of the next message of that topic, or None
    when the topic has no timeline (live data: the caller uses its clock)."""

    def __init__(self) -> None:
        self._t: dict[str, np.ndarray] = {}
        self._i: dict[str, int] = {}

    def set(self, topic: str, t_ns: Iterable[int]) -> None:
        self._t[topic] = np.asarray(list(t_ns) if not isinstance(t_ns, np.ndarray) else t_ns, dtype=np.int64)
        self._i.setdefault(topic, 0)

    def has(self, topic: str) -> bool:
        return topic in self._t

    def take(self, topic: str) -> int | None:
        t = self._t.get(topic)
        if t is None:
            return None
        i = self._i[topic]
        self._i[topic] = i + 1
        if i >= len(t):
            raise IndexError(f"{topic}: message {i + 1} beyond the {len(t)} announced by /replay/timeline")
        return int(t[i])


class ReorderBuffer:
    """Releases ``(t, item)`` in time order once the watermark has passed ``t + lag``.

    Inputs may arrive out of order by up to ``lag_ns``; equal times keep arrival order."""

    def __init__(self, lag_ns: int):
        self.lag_ns = int(lag_ns)
        self._heap: list[tuple[int, int, Any]] = []
        self._seq = itertools.count()
        self.watermark = -(2 ** 62)
        self.released_until = -(2 ** 62)
        self.late = 0  # items that arrived after their time had been released (processed late)
        self.max_late_ns = 0  # by how much the latest of them missed its turn

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, t_ns: int, item: Any) -> None:
        if t_ns < self.released_until:
            self.late += 1
            self.max_late_ns = max(self.max_late_ns, self.released_until - int(t_ns))
        heapq.heappush(self._heap, (int(t_ns), next(self._seq), item))

    def advance(self, watermark_ns: int) -> None:
        self.watermark = max(self.watermark, int(watermark_ns))

    def pop_ready(self, flush: bool = False) -> list[tuple[int, Any]]:
        lim = 2 ** 62 if flush else self.watermark - self.lag_ns
        out = []
        h = self._heap
        while h and h[0][0] <= lim:
            t, _, item = heapq.heappop(h)
            out.append((t, item))
        if out:
            self.released_until = max(self.released_until, out[-1][0])
        return out


class FollowerWatermark:
    """The watermark a recorder may release up to: the replay's clock, but never past the latest stamp of a
    stream computed from the replay (the twin's and the metrics' outputs, ``follower``) that is still
    publishing, since such a stream runs behind the clock (by more than the reorder lag when its node is
    starved of CPU: its messages then missed their place and two MCAP chunks overlapped in time).  A follower
    silent for ``stale_s`` of wall time (finished, or gone) no longer holds the watermark back."""

    def __init__(self, stale_s: float = 1.0):
        self.stale_s = float(stale_s)
        self._latest: dict[str, int] = {}
        self._wall: dict[str, float] = {}

    def seen(self, topic: str, t_ns: int, wall_s: float) -> None:
        """A follower's message at stamp ``t_ns``, received at wall time ``wall_s``."""
        self._latest[topic] = max(self._latest.get(topic, -(2 ** 62)), int(t_ns))
        self._wall[topic] = float(wall_s)

    def limit(self, clock_ns: int, wall_s: float) -> int:
        """``clock_ns`` held back to the slowest live follower's latest stamp."""
        live = [t for k, t in self._latest.items() if wall_s - self._wall[k] < self.stale_s]
        return min([int(clock_ns)] + live)


def as_float32(x: Any) -> Any:
    """What a value looks like after a ``std_msgs/Float32[MultiArray]`` round trip."""
    return np.asarray(x, dtype=np.float32).astype(float)


class TwinEngine:
    """The twin node's core: time-ordered inputs in, twin samples out.

    ``push(t_ns, topic, msg)`` queues an input; ``advance(t_ns)`` moves the watermark
    (the replay's ``/clock``); ``pop(flush)`` applies every released input in time order
    and returns ``[(t_ns, TwinSample), ...]`` decimated to ``publish_rate_hz`` — exactly
    what the twin node publishes."""

    def __init__(self, vp: Any, mode: str = "closed", horizon_s: float = 2.0, publish_rate_hz: float = 50.0,
                 reorder_lag_s: float = 0.5):
        from twin_nodes.twin.runner import TwinRunner

        if not publish_rate_hz > 0:
            raise ValueError(f"publish_rate_hz: expected > 0, got {publish_rate_hz}")
        self.runner = TwinRunner(vp, mode=mode, horizon_s=horizon_s)
        self.mode = mode
        self.buf = ReorderBuffer(int(reorder_lag_s * NS))
        self.pub_period_ns = int(NS / float(publish_rate_hz))
        self.t0_ns: int | None = None
        self.next_pub_ns: int | None = None
        self.n_out = 0
        self.resets = 0  # vehicle restarts applied (RESET_TOPIC)
        self.newest: dict[str, tuple[int, float]] = {}  # advance_live: topic -> (newest time, received at)

    def push(self, t_ns: int, topic: str, msg: Any) -> None:
        self.buf.push(t_ns, (topic, msg))

    def advance(self, t_ns: int) -> None:
        self.buf.advance(t_ns)

    def advance_live(self, topic: str, t_ns: int, now_s: float) -> None:
        """Live (no replay clock): move the watermark with the inputs themselves, to the oldest of
        the newest times of the paced inputs (``LIVE_PACED``: odometry and motor commands) that
        are flowing (one arrived within ``LIVE_STALE_S`` of ``now_s``, the receiving clock).  A
        backlog is taken about round-robin per topic, so a 10 Hz topic's queue runs ahead of a
        30 Hz one's; the newest input of any topic as the watermark released inputs still queued."""
        self.newest[topic] = (max(self.newest[topic][0], t_ns) if topic in self.newest else t_ns, now_s)
        paced = [self.newest[k] for k in LIVE_PACED if k in self.newest]
        flowing = [t for t, rx in paced if now_s - rx <= LIVE_STALE_S]
        self.buf.advance(min(flowing) if flowing else t_ns)

    def pop(self, flush: bool = False) -> list[tuple[int, Any]]:
        out: list[tuple[int, Any]] = []
        for t_ns, (topic, msg) in self.buf.pop_ready(flush=flush):
            out += self._apply(t_ns, topic, msg)
        return out

    def _apply(self, t_ns: int, topic: str, msg: Any) -> list[tuple[int, Any]]:
        r = self.runner
        if self.t0_ns is None:
            self.t0_ns = t_ns
        t = (t_ns - self.t0_ns) / NS
        out = self._decimate(r.advance_to(t))
        if topic == "/real/odom":
            _, p, q, v_flu, w = cv.odom_arrays(msg)
            r.real_state(t, p, cv.world_velocity(q, v_flu), q, w)
        elif topic == "/real/setpoint":
            r.setpoint(cv.setpoint_array(msg))
        elif topic == "/real/motors":
            r.real_motors(cv.motors_array(msg))
        elif topic == "/real/status":
            st = cv.status_array(msg)
            armed, nav_state = (float(st[0]) if st.size > 0 else np.nan), (float(st[1]) if st.size > 1 else np.nan)
            if np.isfinite(armed):
                r.armed(armed > 0.5)
            r.px4_mode(nav_state, r.real_throttle)  # PX4's manual modes: the twin flies the pilot's thrust
        elif topic == "/real/throttle":
            r.px4_mode(r.nav_state, cv.float_value(msg))
        elif topic == "/real/battery":
            v = cv.battery_arrays(msg)[1]
            if np.isfinite(v):
                r.battery(v)
        elif topic == RESET_TOPIC:
            r.restart()  # the samples up to here are out; the next real state starts the twin afresh
            self.resets += 1
        return out

    def _decimate(self, samples: list) -> list[tuple[int, Any]]:
        out = []
        for s in samples:
            t_ns = self.t0_ns + int(round(s.t * NS))
            if self.next_pub_ns is not None and t_ns < self.next_pub_ns:
                continue
            self.next_pub_ns = t_ns + self.pub_period_ns - NS // 10000  # tolerate float rounding
            out.append((t_ns, s))
            self.n_out += 1
        return out


def twin_config(params_file: str, vp: Any, mode: str, horizon_s: float, publish_rate_hz: float,
                reorder_lag_s: float) -> dict[str, Any]:
    """The ``/twin/config`` record: the params file (path, text, sha256) and the twin's settings."""
    import hashlib
    from pathlib import Path

    text = Path(params_file).read_text(encoding="utf-8")
    return {"params_file": str(Path(params_file).resolve()), "params_yaml": text,
            "params_sha256": hashlib.sha256(text.encode("utf-8")).hexdigest(), "vehicle": str(vp.name),
            "mode": mode, "horizon_s": float(horizon_s), "publish_rate_hz": float(publish_rate_hz),
            "reorder_lag_s": float(reorder_lag_s)}


class Track:
    """A growing real signal: times [ns] and values, linear interpolation by bisect.

    A sample at or before the last time is a duplicate (the replay keeps per-topic
    order): an equal time replaces the value, an earlier one is dropped."""

    def __init__(self) -> None:
        self.t: list[int] = []
        self.v: list[Any] = []
        self.breaks: list[int] = []  # vehicle restarts: never interpolated across

    def add_break(self, t: int) -> None:
        bisect.insort(self.breaks, int(t))

    def add(self, t: int, v: Any) -> None:
        if self.t and t <= self.t[-1]:
            if t == self.t[-1]:
                self.v[-1] = v
            return
        self.t.append(t)
        self.v.append(v)

    @property
    def last(self) -> int:
        return self.t[-1] if self.t else -(2 ** 62)

    def at(self, t: int) -> Any:
        i = bisect.bisect_right(self.t, t)
        if i == 0:
            return None
        if i == len(self.t):
            return self.v[-1] if self.t[-1] == t else None
        t0, t1 = self.t[i - 1], self.t[i]
        if self.breaks:
            j = bisect.bisect_right(self.breaks, t0)
            if j < len(self.breaks) and self.breaks[j] <= t1:
                return None  # a vehicle restart between the two samples
        w = (t - t0) / (t1 - t0)
        return self.v[i - 1] + (self.v[i] - self.v[i - 1]) * w

    def hold(self, t: int) -> Any:
        i = bisect.bisect_right(self.t, t)
        return self.v[i - 1] if i else None


class MetricsEngine:
    """The metrics node's core: real and twin samples in, rolling error statistics and the
    whole-flight totals out.

    ``add_real(topic, t_ns, msg)`` for ``/real/odom|throttle|motors|status`` (per-topic time
    order), ``add_twin(t_ns, p, throttle, motors)`` for each twin sample; ``evaluate(final)``
    scores the twin samples the real data has caught up with (all with ``final``) and returns
    ``[(t_ns, {channel: {stat: value}}), ...]`` every ``publish_period_ns`` of log time — what
    the node publishes on ``/twin_error/...``; ``totals(...)`` is the whole-flight
    :class:`~twin_nodes.twin.compare.CompareResult`."""

    REAL = ("/real/odom", "/real/throttle", "/real/motors", "/real/status")

    def __init__(self, n_motors: int, window_s: float = 5.0, publish_period_ns: int = NS // 2,
                 airborne_only: bool = True):
        from msgs_py.topics import metric_channels
        from twin_nodes.twin.metrics import RollingStats

        self.n_motors = int(n_motors)
        self.channels = metric_channels(self.n_motors)
        self.rolling = {ch: RollingStats(window_s) for ch in self.channels}
        self.pub_period_ns = int(publish_period_ns)
        self.airborne_only = bool(airborne_only)
        self.real = {k: Track() for k in ("p", "throttle", "motors", "status")}
        self.twin: list[tuple[int, Any, float, Any]] = []
        self.k_eval = 0
        self.next_pub_ns: int | None = None
        self.window_s = float(window_s)
        self.pending_resets: list[tuple[int, str]] = []  # vehicle restarts not yet reached by evaluate
        self.resets: list[dict[str, Any]] = []           # applied: {"t_ns", "t_s", "reason", "count"}

    def reset(self, t_ns: int, reason: str) -> None:
        """The vehicle restarted at ``t_ns``: the real signals are never interpolated across it, twin
        samples up to it are compared with the real data before it only, and the rolling window
        restarts (empty) with the first twin sample after it (:attr:`resets` notes when and why)."""
        for k in ("p", "throttle", "motors"):
            self.real[k].add_break(t_ns)
        if self.k_eval and self.twin[self.k_eval - 1][0] > t_ns:
            self._restart_window(int(t_ns), str(reason))  # heard late: restart the window now
        else:
            bisect.insort(self.pending_resets, (int(t_ns), str(reason)))

    def add_real(self, topic: str, t: int, msg: Any) -> None:
        if topic == "/real/odom":
            self.real["p"].add(t, cv.odom_arrays(msg)[1])
        elif topic == "/real/throttle":
            self.real["throttle"].add(t, cv.float_value(msg))
        elif topic == "/real/motors":
            self.real["motors"].add(t, cv.motors_array(msg))
        elif topic == "/real/status":
            self.real["status"].add(t, cv.status_array(msg))

    def add_twin(self, t_ns: int, p: Any, throttle: float, motors: Any) -> None:
        self.twin.append((int(t_ns), p, float(throttle), motors))

    def airborne(self, t: int) -> bool:
        st = self.real["status"].hold(t)
        if st is None:
            return not self.airborne_only
        armed, _, landed = st
        if math.isfinite(landed):
            return landed < 0.5
        if math.isfinite(armed):
            return armed > 0.5
        return True

    def evaluate(self, final: bool = False) -> list[tuple[int, dict[str, dict[str, float]]]]:
        real = self.real
        real_until = min(real["p"].last, real["throttle"].last if real["throttle"].t else 2 ** 62,
                         real["motors"].last if real["motors"].t else 2 ** 62)
        out = []
        while self.k_eval < len(self.twin):
            t, p, thr, mot = self.twin[self.k_eval]
            if t > real_until and not final:
                break
            self.k_eval += 1
            while self.pending_resets and t > self.pending_resets[0][0]:
                self._restart_window(*self.pending_resets.pop(0))
            ok = (not self.airborne_only) or self.airborne(t)
            rp = real["p"].at(t)
            errs = {ch: math.nan for ch in self.channels}
            if ok and rp is not None:
                errs["xy"] = float(math.hypot(p[0] - rp[0], p[1] - rp[1]))
                errs["z"] = float(p[2] - rp[2])
                rt = real["throttle"].at(t)
                if rt is not None:
                    errs["throttle"] = float(thr - rt)
                rm = real["motors"].at(t)
                if rm is not None:
                    for i in range(min(self.n_motors, len(rm), len(mot))):
                        errs[f"motor{i + 1}"] = float(mot[i] - rm[i])
            ts = t / NS
            for ch, e in errs.items():
                self.rolling[ch].add(ts, e)
            if self.next_pub_ns is None or t >= self.next_pub_ns:
                self.next_pub_ns = t + self.pub_period_ns
                out.append((t, {ch: r.stats() for ch, r in self.rolling.items()}))
        return out

    def _restart_window(self, t_ns: int, reason: str) -> None:
        from twin_nodes.twin.metrics import RollingStats

        self.rolling = {ch: RollingStats(self.window_s) for ch in self.channels}
        self.next_pub_ns = None  # publish the fresh window with its first sample
        self.resets.append({"t_ns": int(t_ns), "t_s": t_ns / NS, "reason": reason, "count": len(self.resets) + 1})

    def totals(self, start_ns: int, mode: str, rate_hz: float = 50.0, source: str = "topics") -> Any:
        from twin_nodes.twin.compare import metrics_from_streams

        real, twin = final_streams(self.real, self.twin, start_ns, self.n_motors)
        return metrics_from_streams(real, twin, mode, self.n_motors, rate_hz, self.airborne_only, source=source)


def final_streams(real: dict[str, Track], twin: list[tuple[int, Any, float, Any]], start_ns: int,
                  n_motors: int) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, np.ndarray]]:
    """The ``(real, twin)`` arrays of :func:`twin_nodes.twin.compare.metrics_from_streams` from the
    metrics node's tracks (``p``, ``throttle``, ``motors``, ``status``) and twin samples
    ``(t_ns, p (3,), throttle, motors (N,))``; times in s from ``start_ns``."""

    def arr(track: Track, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        tt, vv = list(track.t), list(track.v)
        for b in track.breaks:  # a vehicle restart: a NaN sample, so nothing is interpolated across it
            i = bisect.bisect_left(tt, b)
            if 0 < i < len(tt):
                tt.insert(i, b)
                vv.insert(i, np.full(np.shape(vv[0]), np.nan) if k is not None else float("nan"))
        t = (np.asarray(tt, dtype=np.int64) - start_ns) / NS
        v = np.asarray(vv, float)
        return t, (v if k is None else v.reshape(len(t), k))

    r: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for key, name, k in (("p", "position_enu", 3), ("throttle", "throttle", None), ("motors", "motors", n_motors),
                         ("status", "status", 3)):
        if real[key].t:
            r[name] = arr(real[key], k)
    breaks = real["p"].breaks if "p" in real else []
    if breaks and twin:  # nor the twin across a restart (the twin starts afresh after it)
        tts = [s[0] for s in twin]
        twin = list(twin)
        for b in reversed(breaks):
            i = bisect.bisect_right(tts, b)
            if 0 < i < len(tts):
                n = len(twin[0][3])
                twin.insert(i, (b + 1, np.full(3, np.nan), float("nan"), np.full(n, np.nan)))
                tts.insert(i, b + 1)
    tw = {"t": (np.array([s[0] for s in twin], dtype=np.int64) - start_ns) / NS,
          "p": np.array([s[1] for s in twin]).reshape(-1, 3), "throttle": np.array([s[2] for s in twin]),
          "motors": np.array([s[3] for s in twin]).reshape(-1, n_motors)}
    return r, tw
