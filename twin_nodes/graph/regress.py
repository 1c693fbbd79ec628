"""``rotortwin regress``: fly a baseline recording again with today's twin and compare.

A *baseline* is a bag recorded by ``rotortwin compare --mcap`` (or re-recorded by
``regress --update``).  It holds the flight as the replay published it (``/real/...``),
the twin that flew it (``/twin/config``: the params file's path, text and sha256, the
mode and rates) and what the metrics node computed (``/twin_error/...`` and the
whole-flight ``/twin_error/final_json``).

:func:`regress_baseline` replays the baseline's ``/real`` messages through **today's**
twin and metrics code — with the baseline's own params unless others are given — and
compares every whole-flight metric (``xy``, ``z``, ``throttle`` and each motor; RMSE,
P75, median, max) with the baseline's:

- the graph path runs the node processes (:func:`~twin_nodes.graph.orchestrator.run_graph`
  with the bag as the replay's source: the recorded messages are republished byte for
  byte at their recorded times);
- the offline path (``offline=True``) runs the same cores in one process
  (:class:`~twin_nodes.nodes.engine.TwinEngine` → :class:`~twin_nodes.nodes.engine.MetricsEngine`,
  i.e. :class:`~twin_nodes.twin.runner.TwinRunner` and
  :func:`~twin_nodes.twin.compare.metrics_from_streams`, the twin applied to the same
  events in the same order), so an unchanged twin reproduces a graph-recorded baseline.

A metric *regresses* when it got worse (larger) by more than
``max(abs_tol, rel_tol · |baseline|)``, or when it was computed before and no longer is;
fewer compared samples than the baseline (beyond ``rel_tol``) counts as worse too (an
error can shrink by covering less of the flight).  Better-than-baseline is reported,
not failed.  ``update=True`` accepts the result: the baseline is re-recorded (into a
temporary folder beside it, then swapped in).

:func:`regress_bag` (``regress --self-check``) is the older consistency check of one
recording: the whole-flight metrics recomputed from its own ``/real`` and ``/twin``
topics must equal the stored ones.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from twin_nodes.base.errors import LogError, TwinError

__all__ = ["regress_bag", "regress_baseline", "check_tolerance", "metric_values", "compare_with_baseline",
           "MetricChange", "RegressResult", "Baseline", "load_baseline", "fly_offline", "format_changes"]

_FAIL = ("WORSE", "LOST")


def check_tolerance(value: Any, option: str) -> float:
    """``value`` as a finite float > 0, else a one-line :class:`TwinError`."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise TwinError(f"{option}: expected a finite number > 0, got {value!r}")
    return v


# =========================================================================== metrics and changes


def metric_values(m: dict[str, Any]) -> dict[str, float]:
    """Every whole-flight metric by its ``/twin_error`` name (``xy/rmse_m``, ``motor3/p75``…), plus
    ``samples`` (the number of compared samples); NaN where not computed."""
    from twin_nodes.twin.metrics import CHANNELS, STATS, UNITS

    def num(v: Any) -> float:
        try:
            return float(v)
        except (TypeError, ValueError):
            return math.nan

    out: dict[str, float] = {}
    for ch in CHANNELS:
        for st in STATS:
            out[f"{ch}/{st}{UNITS[ch]}"] = num(m.get(f"{ch}_{st}{UNITS[ch]}"))
    n = len(m.get("motor_rmse") or [])
    for i in range(n):
        for st in STATS:
            vals = m.get(f"motor_{st}") or []
            out[f"motor{i + 1}/{st}"] = num(vals[i]) if i < len(vals) else math.nan
    out["samples"] = num(m.get("n_samples"))
    return out


@dataclass
class MetricChange:
    """One metric, baseline against now: ``verdict`` is ``ok``, ``better``, ``WORSE``, ``LOST``
    (computed in the baseline, not now), ``new`` or ``n/a``."""

    name: str
    baseline: float
    now: float
    tolerance: float
    verdict: str

    @property
    def change(self) -> float:
        return self.now - self.baseline

    @property
    def failed(self) -> bool:
        return self.verdict in _FAIL


def compare_with_baseline(baseline: dict[str, Any], now: dict[str, Any], rel_tol: float = 0.05,
                          abs_tol: float = 1e-3) -> list[MetricChange]:
    """Every metric of ``baseline`` and ``now`` (whole-flight metric dicts), one-sided: larger
    errors beyond ``max(abs_tol, rel_tol·|baseline|)`` are ``WORSE``; fewer samples beyond
    ``rel_tol`` too."""
    rel_tol = check_tolerance(rel_tol, "--tolerance")
    abs_tol = check_tolerance(abs_tol, "--abs-tolerance")
    b, n = metric_values(baseline), metric_values(now)
    out = []
    for name in list(b) + [k for k in n if k not in b]:
        a, c = b.get(name, math.nan), n.get(name, math.nan)
        fa, fc = math.isfinite(a), math.isfinite(c)
        if name == "samples":
            tol = rel_tol * abs(a) if fa else math.nan
            verdict = ("ok" if c >= a - tol else "WORSE") if fa and fc else ("n/a" if not fa else "LOST")
        elif not fa and not fc:
            tol, verdict = math.nan, "n/a"
        elif not fc:
            tol, verdict = math.nan, "LOST"
        elif not fa:
            tol, verdict = math.nan, "new"
        else:
            tol = max(abs_tol, rel_tol * abs(a))
            verdict = "WORSE" if c - a > tol else ("better" if a - c > tol else "ok")
        out.append(MetricChange(name, a, c, tol, verdict))
    return out


def format_changes(changes: list[MetricChange], only_moved: bool = False) -> str:
    """The comparison as a text table (throttle and motor values in %, positions in m)."""
    def scale(name: str) -> tuple[float, str]:
        if name == "samples":
            return 1.0, ""
        return (1.0, "m") if name.endswith("_m") else (100.0, "%")

    def f(v: float, k: float) -> str:
        return "n/a" if not math.isfinite(v) else f"{v * k:.3f}" if k != 1.0 or abs(v) < 1e4 else f"{v:.0f}"

    rows = [c for c in changes if not only_moved or c.verdict not in ("ok", "n/a")]
    head = f"{'metric':<16} {'unit':<4} {'baseline':>10} {'now':>10} {'change':>10} {'rel':>8} {'tolerance':>10}  verdict"
    lines = [head, "-" * len(head)]
    for c in rows:
        k, unit = scale(c.name)
        rel = (f"{100 * c.change / abs(c.baseline):+.1f} %" if math.isfinite(c.change) and c.baseline
               else "")
        chg = f"{c.change * k:+.3f}" if math.isfinite(c.change) else ""
        lines.append(f"{c.name:<16} {unit:<4} {f(c.baseline, k):>10} {f(c.now, k):>10} {chg:>10} {rel:>8} "
                     f"{f(c.tolerance, k):>10}  {c.verdict}")
    if not rows:
        lines.append("(no metric moved beyond tolerance)")
    return "\n".join(lines)


# =========================================================================== the baseline


@dataclass
class Baseline:
    path: Path
    metrics: dict[str, Any]
    config: dict[str, Any] | None
    plan: dict[str, Any]
    topics: dict[str, Any]  # topic -> twin_nodes.logs.recording.BagTopic

    @property
    def bag_dir(self) -> Path:
        """The recording: a rosbag2 folder (also when given its ``.mcap``), or a single ``.mcap`` file."""
        if self.path.is_dir() or not (self.path.parent / "metadata.yaml").is_file():
            return self.path
        return self.path.parent


def _last_json(topics: dict[str, Any], topic: str) -> dict[str, Any] | None:
    bt = topics.get(topic)
    if bt is None or not len(bt):
        return None
    return json.loads(bt.decode()[-1].data)


def load_baseline(bag: str | os.PathLike[str]) -> Baseline:
    """A recording with ``/real`` streams and stored final metrics (one-line error otherwise)."""
    from twin_nodes.logs.recording import read_bag_raw

    p = Path(bag)
    topics = read_bag_raw(p)
    try:
        metrics = _last_json(topics, "/twin_error/final_json")
        config = _last_json(topics, "/twin/config")
        plan = _last_json(topics, "/replay/plan") or {}
    except (ValueError, AttributeError) as exc:
        raise LogError(str(p), "/twin_error/final_json", f"expected JSON: {exc}") from None
    if not metrics or "error" in metrics:
        raise LogError(str(p), "/twin_error/final_json", "expected the whole-flight metrics of a finished run "
                                                         "(recorded by 'rotortwin compare --mcap')")
    if not len(topics.get("/real/odom") or []):
        raise LogError(str(p), "/real/odom", "expected the recorded flight (no /real/odom message)")
    return Baseline(p, metrics, config, plan, topics)


def _params_of(base: Baseline, params: str | os.PathLike[str] | None, tmp: Path) -> tuple[Path, str]:
    """The params file to fly and how it was chosen."""
    if params:
        return Path(params), f"{params} (--params)"
    cfg = base.config or {}
    text = cfg.get("params_yaml")
    if not text:
        raise LogError(str(base.path), "/twin/config", "expected the params the baseline was recorded with "
                                                       "(recorded before /twin/config existed?); pass --params")
    name = Path(str(cfg.get("params_file") or "baseline_params.yaml")).name
    path = tmp / name
    path.write_text(text, encoding="utf-8")
    return path, f"recorded with the baseline ({cfg.get('params_file', '?')}, sha256 " \
                 f"{str(cfg.get('params_sha256', ''))[:12]})"


# =========================================================================== the offline path


@dataclass
class OfflineRun:
    metrics: dict[str, Any]
    twin: list[tuple[int, Any]]          # (t_ns, TwinSample) as the twin node publishes them
    rolling: list[tuple[int, dict[str, dict[str, float]]]]  # what the metrics node publishes
    t0_ns: int
    t1_ns: int


def _real_events(base: Baseline, topics: tuple[str, ...]) -> list[tuple[int, int, str, Any]]:
    """The recorded ``/real`` messages as ``(t_ns, order, topic, msg)`` in the replay's order:
    time, then the replay's topic order (its event order)."""
    import numpy as np

    from msgs_py.topics import TOPICS
    from twin_nodes.logs import conversions as cv

    plan_order = list(base.plan.get("counts", {}))
    names = [t for t in plan_order if t in topics] + sorted(t for t in topics if t not in plan_order)
    events: list[tuple[int, int, str, Any]] = []
    for rank, topic in enumerate(names):
        bt = base.topics.get(topic)
        if bt is None or not len(bt):
            continue
        msgs = bt.decode()
        if TOPICS[topic].stamped:
            t = np.array([cv.stamp_to_ns(m.header.stamp) for m in msgs], dtype=np.int64)
        else:
            t = np.asarray(bt.log_ns, dtype=np.int64)
        for i in np.argsort(t, kind="stable"):
            events.append((int(t[i]), rank, topic, msgs[i]))
    events.sort(key=lambda e: (e[0], e[1]))
    return events


def fly_offline(base: Baseline, vp: Any, mode: str = "closed", horizon_s: float = 2.0,
                publish_rate_hz: float = 50.0, window_s: float = 5.0, rate_hz: float = 50.0) -> OfflineRun:
    """What the twin and metrics nodes compute from the baseline's ``/real`` messages, in one process."""
    import numpy as np

    from twin_nodes.nodes.engine import NS, TWIN_INPUTS, MetricsEngine, TwinEngine, as_float32

    events = _real_events(base, tuple(dict.fromkeys(TWIN_INPUTS + MetricsEngine.REAL)))
    if not events:
        raise LogError(str(base.path), "/real", "expected recorded /real messages")
    twin = TwinEngine(vp, mode=mode, horizon_s=horizon_s, publish_rate_hz=publish_rate_hz)
    n_motors = int(vp.rotors.count)
    met = MetricsEngine(n_motors, window_s=window_s, publish_period_ns=NS // 2)
    for t, _, topic, msg in events:
        if topic in TWIN_INPUTS:
            twin.push(t, topic, msg)
        if topic in MetricsEngine.REAL:
            met.add_real(topic, t, msg)
    out = twin.pop(flush=True)
    for t_ns, s in out:
        # what the metrics node reads back from /twin/odom (float64), /twin/throttle and /twin/motors (float32)
        met.add_twin(t_ns, np.asarray(s.x[0:3], float), float(as_float32(s.throttle)), as_float32(s.motors))
    rolling = met.evaluate(final=True)
    start = int(base.plan.get("start_ns", events[0][0]))
    try:
        res = met.totals(start, mode, rate_hz, source=str(base.plan.get("ulog") or base.path))
    except ValueError as exc:  # e.g. a params file with another motor count than the flight
        raise TwinError(f"{base.path}: whole-flight metrics: {exc}") from None
    m = res.metrics
    m["log"] = str(base.plan.get("ulog", ""))
    m["source"] = "rotortwin regress --offline (TwinEngine -> MetricsEngine in one process)"
    m["received"] = {"/twin/*": len(out)}
    t1 = int(base.plan.get("t1_ns", events[-1][0]))
    return OfflineRun(metrics=m, twin=out, rolling=rolling, t0_ns=int(base.plan.get("t0_ns", events[0][0])),
                      t1_ns=t1)


def _write_offline_bag(base: Baseline, run: OfflineRun, config: dict[str, Any], out: Path) -> None:
    """A baseline bag from an offline run: the recorded flight and replay topics, the new twin's
    ``/twin/...``, ``/twin_error/...`` and ``/twin/config``, every message at its own time."""
    try:
        from rclpy.serialization import serialize_message
    except ImportError:
        raise TwinError("regress --update --offline: writing a bag needs the ROS 2 message packages "
                        "(pip install -e '.[ros]'); or drop --offline") from None
    from msgs_py.topics import METRIC_STATS, TOPICS, metric_topic, msg_class
    from twin_nodes.logs import conversions as cv
    from twin_nodes.logs.recording import McapRecorder, cdr_header_stamp
    from twin_nodes.nodes.engine import CONFIG_TOPIC
    from twin_nodes.twin.metrics import table2, to_jsonable

    rows: list[tuple[int, str, bytes]] = []
    types: dict[str, tuple[str, str]] = {}
    latched = ("/replay/plan", "/replay/timeline", "/replay/done", CONFIG_TOPIC, "/twin/done",
               "/twin_error/final_json", "/twin_error/final_table")

    def add(topic: str, msgtype: str, t: int, data: bytes) -> None:
        types.setdefault(topic, (msgtype, "transient_local" if topic in latched else "reliable"))
        rows.append((int(t), topic, data))

    for topic, bt in base.topics.items():
        if topic.startswith(("/twin/", "/twin_error/")) or not len(bt):
            continue
        stamped = topic == "/clock" or (topic in TOPICS and TOPICS[topic].stamped)
        for t, raw in zip(bt.log_ns, bt.raw):
            if stamped:
                t = cdr_header_stamp(raw)
            elif topic in ("/replay/plan", "/replay/timeline"):
                t = run.t0_ns
            add(topic, bt.msgtype, t, raw)
    ser = serialize_message
    add(CONFIG_TOPIC, "std_msgs/msg/String", run.t0_ns, ser(cv.string_msg(json.dumps(config))))
    for t_ns, s in run.twin:
        x = s.x
        q = x[6:10]
        add("/twin/odom", "nav_msgs/msg/Odometry", t_ns,
            ser(cv.odom_msg(t_ns, x[0:3], q, cv.body_velocity(q, x[3:6]), x[10:13])))
        add("/twin/motors", "std_msgs/msg/Float32MultiArray", t_ns, ser(cv.motors_msg(s.motors)))
        add("/twin/throttle", "std_msgs/msg/Float32", t_ns, ser(cv.float32_msg(s.throttle)))
        add("/twin/imu", "sensor_msgs/msg/Imu", t_ns, ser(cv.imu_msg(t_ns, s.specific_force, x[10:13], q)))
    f64 = msg_class("std_msgs/msg/Float64")
    for t, stats in run.rolling:
        for ch, by_stat in stats.items():
            for st in METRIC_STATS:
                add(metric_topic(ch, st), "std_msgs/msg/Float64", t, ser(f64(data=float(by_stat[st]))))
        add("/twin_error/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", t, ser(cv.diagnostics_msg(t, stats)))
    m = run.metrics
    add("/twin/done", "std_msgs/msg/UInt64", run.t1_ns, ser(cv.uint64_msg(len(run.twin))))
    add("/twin_error/final_json", "std_msgs/msg/String", run.t1_ns, ser(cv.string_msg(json.dumps(to_jsonable(m)))))
    add("/twin_error/final_table", "std_msgs/msg/String", run.t1_ns,
        ser(cv.string_msg(table2(m, title=f"Twin vs real (Table 2 layout): {m.get('log', '')}"))))
    rows.sort(key=lambda r: r[0])
    with McapRecorder(out) as rec:
        for topic, (msgtype, qos) in types.items():
            rec.add_topic(topic, msgtype, qos)
        for t, topic, data in rows:
            rec.write_raw(topic, data, max(t, 0))


# =========================================================================== regress


@dataclass
class RegressResult:
    bag: Path
    params: str                       # which params flew, and why
    path: str                         # 'graph' or 'offline'
    changes: list[MetricChange]
    metrics: dict[str, Any]           # today's
    baseline: dict[str, Any]          # the baseline's
    updated: bool = False
    notes: list[str] = field(default_factory=list)

    @property
    def failed(self) -> bool:
        return any(c.failed for c in self.changes)

    @property
    def worse(self) -> list[MetricChange]:
        return [c for c in self.changes if c.failed]


def regress_baseline(bag: str | os.PathLike[str], params: str | os.PathLike[str] | None = None, *,
                     offline: bool = False, rel_tol: float = 0.05, abs_tol: float = 1e-3, update: bool = False,
                     domain_id: int | None = None, progress: bool = False, timeout_s: float = 900.0
                     ) -> RegressResult:
    """Replay the baseline ``bag`` through today's twin and compare (see the module docstring)."""
    rel_tol = check_tolerance(rel_tol, "--tolerance")
    abs_tol = check_tolerance(abs_tol, "--abs-tolerance")
    base = load_baseline(bag)
    bag_dir = base.bag_dir
    if update and bag_dir.is_dir() and not (bag_dir / "metadata.yaml").is_file():
        raise LogError(str(bag_dir), "metadata.yaml", "expected a bag directory to update")
    cfg = base.config or {}
    mode = str(cfg.get("mode") or base.metrics.get("mode") or "closed")
    horizon = float(cfg.get("horizon_s") or 2.0)
    rate = float(cfg.get("publish_rate_hz") or 50.0)
    work = Path(tempfile.mkdtemp(prefix="rotortwin_regress_"))
    staging = bag_dir.parent / f".{bag_dir.name}.update-{os.getpid()}" if update else None
    try:
        pfile, how = _params_of(base, params, work)
        from twin_nodes.nodes.engine import twin_config
        from twin_nodes.vehicle.params import load_params

        vp = load_params(pfile)
        new_bag = None
        if staging is not None:
            staging.mkdir()
            new_bag = staging / bag_dir.name
        if offline:
            run = fly_offline(base, vp, mode=mode, horizon_s=horizon, publish_rate_hz=rate)
            metrics = run.metrics
            if new_bag is not None:
                config = twin_config(str(pfile), vp, mode, horizon, rate, float(cfg.get("reorder_lag_s") or 0.5))
                if params is None:
                    config["params_file"] = cfg.get("params_file", config["params_file"])
                _write_offline_bag(base, run, config, new_bag)
        else:
            from twin_nodes.graph.orchestrator import run_graph

            res = run_graph(bag_dir, pfile, mode=mode, horizon_s=horizon, bag=str(new_bag) if new_bag else None,
                            domain_id=domain_id, progress=progress, timeout_s=timeout_s,
                            n_motors=int(vp.rotors.count))
            metrics = res.metrics
        changes = compare_with_baseline(base.metrics, metrics, rel_tol, abs_tol)
        if new_bag is not None:
            old = staging / (bag_dir.name + ".old")
            os.replace(bag_dir, old)
            os.replace(new_bag, bag_dir)
        return RegressResult(bag=bag_dir, params=how, path="offline" if offline else "graph", changes=changes,
                             metrics=metrics, baseline=base.metrics, updated=new_bag is not None)
    finally:
        shutil.rmtree(work, ignore_errors=True)
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)


# =========================================================================== self-check


def regress_bag(bag: str | os.PathLike[str], rel_tol: float = 0.05, abs_tol: float = 1e-3
                ) -> tuple[dict[str, Any], dict[str, Any], list[str]]:
    """Recompute the whole-flight metrics from a recording's ``/real`` and ``/twin`` topics.

    Returns ``(stored, fresh, problems)``: the metrics stored at record time
    (``/twin_error/final_json``), the recomputed ones, and one line per metric that
    moved by more than ``max(abs_tol, rel_tol * |stored|)``."""
    import numpy as np

    from twin_nodes.logs.recording import read_bag
    from twin_nodes.twin.compare import metrics_from_streams

    rel_tol = check_tolerance(rel_tol, "--tolerance")
    abs_tol = check_tolerance(abs_tol, "--abs-tolerance")
    msgs = read_bag(bag)
    final = msgs.get("/twin_error/final_json") or []
    if not final:
        raise LogError(str(bag), "/twin_error/final_json", "expected the metrics stored at record time; "
                                                            "was the metrics node part of the recording?")
    stored = json.loads(final[-1][1].data)
    plan = json.loads(msgs["/replay/plan"][-1][1].data) if msgs.get("/replay/plan") else {}
    start = int(plan.get("start_ns", 0))
    n_motors = int(stored.get("n_motors", plan.get("n_motors", 4)))

    def stamp(m: Any) -> int:
        return int(m.header.stamp.sec) * 1_000_000_000 + int(m.header.stamp.nanosec)

    def s(t_ns: list[int]) -> np.ndarray:
        return (np.asarray(t_ns, dtype=np.int64) - start) / 1e9

    real: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    od = msgs.get("/real/odom") or []
    if od:
        real["position_enu"] = (s([stamp(m) for _, m in od]),
                                np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z]
                                          for _, m in od]))
    for topic, key in (("/real/throttle", "throttle"), ("/real/motors", "motors"), ("/real/status", "status")):
        rows = msgs.get(topic) or []
        if rows:
            vals = [np.asarray(m.data, float).ravel() for _, m in rows]
            v = np.array(vals)
            if key == "status":
                v = v.astype(float)
                v[v == 255] = np.nan
            real[key] = (s([t for t, _ in rows]), v[:, 0] if key == "throttle" and v.ndim == 2 else v)
    to, tt, tm = (msgs.get(t) or [] for t in ("/twin/odom", "/twin/throttle", "/twin/motors"))
    n = min(len(to), len(tt), len(tm))
    twin = {"t": s([stamp(m) for _, m in to[:n]]),
            "p": np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z]
                           for _, m in to[:n]]).reshape(n, 3),
            "throttle": np.array([float(m.data) for _, m in tt[:n]]),
            "motors": np.array([np.asarray(m.data, float) for _, m in tm[:n]]).reshape(n, n_motors)}
    res = metrics_from_streams(real, twin, str(stored.get("mode", "closed")), n_motors,
                               float(stored.get("rate_hz", 50.0) or 50.0), True, source=str(bag))
    fresh = res.metrics
    from twin_nodes.twin.metrics import compare_metrics, to_jsonable
    problems = compare_metrics(stored, to_jsonable(fresh), rel_tol=rel_tol, abs_tol=abs_tol)
    return stored, fresh, problems
