"""The live node graph from the command line.

::

    rotortwin compare FLIGHT.ulg [--params P.yaml] [--mode closed|open] [--rate R] [--json OUT.json]
                                 [--mcap OUT_BAG] [--report DIR] [--window S] [--offline]
    rotortwin monitor [--once] [--duration S] [--domain-id N]
    rotortwin topics list | echo TOPIC [--count N]
    rotortwin regress BAG [--tolerance REL] [--abs-tolerance ABS]
    rotortwin replay FLIGHT.ulg [--rate R] [--wait-for NODE ...]       (one node, in the foreground)
    rotortwin twin --params P.yaml [--mode closed|open]
    rotortwin metrics [--window S] [--json OUT.json]
    rotortwin record OUT_BAG | rotortwin record recover BAG [--out DIR]

``compare`` starts the same four processes as ``launch_scripts/replay_compare.sh``
(ulog_replay, twin, metrics and, with ``--mcap``, recorder) on a private
``ROS_DOMAIN_ID`` with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, waits for
``/replay/done`` and the metrics node's whole-flight JSON, stops everything
with SIGINT and prints the Table-2 summary.  ``--offline`` computes the same
metrics without ROS (``twin_nodes.compare.compare_log``).

Without ``--params`` the vehicle file is chosen from the log's ``SYS_AUTOSTART``
(:data:`AUTOSTART_PARAMS`); an airframe without a shipped file is an error that
says so.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from twin_nodes.errors import LogError, TwinError

#: PX4 SYS_AUTOSTART -> shipped params file stem
AUTOSTART_PARAMS = {10040: "px4_sih_quadx", 1100: "px4_sih_quadx"}
NODE_MODULES = {"replay": "ulog_replay", "twin": "twin_node", "metrics": "metrics_node", "recorder": "recorder_node"}


# =========================================================================== helpers

def default_params_for(ulog: str | os.PathLike[str], explicit: str | None = None) -> Path:
    """The params file to fly: ``explicit`` if given, else by the log's SYS_AUTOSTART."""
    from twin_nodes.params import params_dir

    if explicit:
        p = Path(explicit)
        if not p.is_file():
            raise TwinError(f"{p}: params file not found")
        return p
    autostart = _sys_autostart(ulog)
    stem = AUTOSTART_PARAMS.get(int(autostart)) if autostart is not None else None
    if stem is None:
        shipped = ", ".join(sorted(p.stem for p in params_dir().glob("*.yaml") if not p.stem.startswith("derive")))
        raise TwinError(f"{ulog}: SYS_AUTOSTART {autostart if autostart is not None else '(not logged)'} has no "
                        f"shipped params file (known: {AUTOSTART_PARAMS}); pass --params, e.g. one of: {shipped}")
    return params_dir() / f"{stem}.yaml"


def _sys_autostart(ulog: str | os.PathLike[str]) -> int | None:
    import contextlib
    import io

    from pyulog import ULog

    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            u = ULog(str(ulog), parse_header_only=True)
    except FileNotFoundError:
        raise LogError(str(ulog), "<file>", "file not found") from None
    except Exception as exc:
        raise LogError(str(ulog), "<header>", f"expected a PX4 ULog file ({type(exc).__name__}: {exc})") from None
    v = u.initial_parameters.get("SYS_AUTOSTART")
    return int(v) if v is not None else None


def ros_env(domain_id: int | None = None) -> dict[str, str]:
    """Environment for graph processes: private domain, localhost-only discovery."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id if domain_id is not None else random.randint(1, 200))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("MPLBACKEND", "Agg")
    return env


def node_command(node: str, params: dict[str, Any]) -> list[str]:
    """``python -m twin_nodes.nodes.<module> --ros-args -r __node:=<node> -p k:=v ...``."""
    cmd = [sys.executable, "-m", f"twin_nodes.nodes.{NODE_MODULES[node]}", "--ros-args"]
    for k, v in params.items():
        if isinstance(v, bool):
            val = "true" if v else "false"
        elif isinstance(v, (list, tuple)):
            val = "[" + ",".join(f"'{x}'" for x in v) + "]"
        else:
            val = str(v)
        cmd += ["-p", f"{k}:={val}"]
    return cmd


@dataclass
class GraphResult:
    metrics: dict[str, Any]
    json_path: Path
    aligned_path: Path
    bag_path: Path | None
    replay_stats: dict[str, Any]
    wall_s: float
    run_dir: Path
    domain_id: int
    exit_codes: dict[str, int] = field(default_factory=dict)


class Graph:
    """The four node processes, their pid files and logs under ``run_dir``."""

    def __init__(self, run_dir: Path, env: dict[str, str]):
        self.run_dir = run_dir
        self.env = env
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, params: dict[str, Any], capture_stdout: bool = False) -> subprocess.Popen:
        log = open(self.run_dir / f"{name}.log", "w", encoding="utf-8")
        p = subprocess.Popen(node_command(name, params), env=self.env, stdin=subprocess.DEVNULL,
                             stdout=subprocess.PIPE if capture_stdout else log, stderr=log,
                             text=True, start_new_session=True)
        self.procs[name] = p
        (self.run_dir / f"{name}.pid").write_text(f"{p.pid}\n")
        return p

    def dead(self) -> dict[str, int]:
        return {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}

    def log_tail(self, name: str, n: int = 6) -> str:
        try:
            lines = (self.run_dir / f"{name}.log").read_text(encoding="utf-8", errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-n:])

    def stop(self, names: list[str] | None = None, timeout_s: float = 15.0) -> dict[str, int]:
        """SIGINT, then SIGTERM, then SIGKILL (each process only, by pid)."""
        names = names or list(self.procs)
        for n in names:
            p = self.procs[n]
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout_s
        for n in names:
            p = self.procs[n]
            try:
                p.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                p.terminate()
                try:
                    p.wait(3)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        codes = {}
        for n in names:
            codes[n] = self.procs[n].returncode
            (self.run_dir / f"{n}.pid").unlink(missing_ok=True)
        return codes


def run_graph(ulog: str | os.PathLike[str], params_file: str | os.PathLike[str], *, mode: str = "closed",
              rate: float = 0.0, run_dir: str | os.PathLike[str] | None = None, bag: str | None = None,
              window_s: float = 5.0, horizon_s: float = 2.0, domain_id: int | None = None,
              progress: bool = True, timeout_s: float = 900.0, n_motors: int | None = None,
              use_sim_time: bool = False, replay_params: dict[str, Any] | None = None) -> GraphResult:
    """Replay ``ulog`` through the process graph and return the metrics node's totals."""
    ulog = Path(ulog)
    if not ulog.is_file():
        raise LogError(str(ulog), "<file>", "file not found")
    rd = Path(run_dir) if run_dir else Path(tempfile.mkdtemp(prefix="rotortwin_run_"))
    rd.mkdir(parents=True, exist_ok=True)
    env = ros_env(domain_id)
    g = Graph(rd, env)
    json_path, aligned_path, stats_path = rd / "final_metrics.json", rd / "aligned.npz", rd / "replay_stats.json"
    for p in (json_path, aligned_path, stats_path):
        p.unlink(missing_ok=True)
    if n_motors is None:
        from twin_nodes.params import load_params
        n_motors = load_params(params_file).rotors.count
    common = {"use_sim_time": use_sim_time}
    wait_for = ["twin", "metrics"]
    t_wall = time.monotonic()
    old_term = None
    if threading.current_thread() is threading.main_thread():
        # a SIGTERM to the CLI must still stop the node processes (they run in their own sessions)
        old_term = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        if bag:
            if Path(bag).exists():
                raise TwinError(f"{bag}: the bag directory already exists")
            g.start("recorder", {**common, "out": str(bag)})
            wait_for.append("recorder")
        g.start("metrics", {**common, "window_s": window_s, "n_motors": n_motors, "mode": mode,
                            "json_out": str(json_path), "aligned_out": str(aligned_path)})
        g.start("twin", {**common, "params_file": str(params_file), "mode": mode, "horizon_s": horizon_s})
        rp = g.start("replay", {"ulog": str(ulog), "rate": float(rate), "wait_for": wait_for,
                                "stats_file": str(stats_path), "progress": True, **(replay_params or {})},
                     capture_stdout=True)
        _follow_replay(g, rp, progress, timeout_s, ulog)
        deadline = time.monotonic() + 120.0
        while not json_path.exists():
            dead = {n: c for n, c in g.dead().items() if n in ("metrics", "twin")}
            if dead:
                name = next(iter(dead))
                raise TwinError(f"the {name} node exited ({dead[name]}) before the final metrics:\n"
                                f"{g.log_tail(name)}")
            if time.monotonic() > deadline:
                raise TwinError(f"no final metrics from the metrics node after 120 s (see {rd}/metrics.log)")
            time.sleep(0.1)
        time.sleep(0.3)  # let the recorder take the latched final topics
    finally:
        codes = g.stop()
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)
    metrics = json.loads(json_path.read_text())
    stats = json.loads(stats_path.read_text()) if stats_path.exists() else {}
    if "error" in metrics:
        raise TwinError(f"metrics node: {metrics['error']}")
    return GraphResult(metrics=metrics, json_path=json_path, aligned_path=aligned_path,
                       bag_path=Path(bag) if bag else None, replay_stats=stats, wall_s=time.monotonic() - t_wall,
                       run_dir=rd, domain_id=int(env["ROS_DOMAIN_ID"]), exit_codes=codes)


def _raise_interrupt(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def _follow_replay(g: Graph, rp: subprocess.Popen, progress: bool, timeout_s: float, ulog: Path) -> None:
    """Read the replay's PROGRESS lines into a progress bar until it exits."""
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=1.0, desc=f"replay {ulog.name}", unit="s log", leave=False,
                   bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s of log [{elapsed}<{remaining}]")
    lines: list[str] = []

    def reader() -> None:
        assert rp.stdout is not None
        for line in rp.stdout:
            lines.append(line)

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    t0 = time.monotonic()
    seen = 0
    while rp.poll() is None:
        while seen < len(lines):
            parts = lines[seen].split()
            seen += 1
            if bar is not None and len(parts) == 3 and parts[0] == "PROGRESS":
                bar.total = float(parts[2])
                bar.n = float(parts[1])
                bar.refresh()
        other = {n: c for n, c in g.dead().items() if n != "replay"}
        if other:
            name = next(iter(other))
            rp.send_signal(signal.SIGINT)
            raise TwinError(f"the {name} node exited ({other[name]}) during the replay:\n{g.log_tail(name)}")
        if time.monotonic() - t0 > timeout_s:
            raise TwinError(f"replay did not finish in {timeout_s:.0f} s")
        time.sleep(0.1)
    th.join(1.0)
    if bar is not None:
        bar.close()
    if rp.returncode != 0:
        raise TwinError(f"the replay node failed ({rp.returncode}):\n{g.log_tail('replay')}")


# =========================================================================== compare

def _cmd_compare(args: argparse.Namespace) -> int:
    from twin_nodes.metrics import table2, to_jsonable

    params_file = default_params_for(args.flight, args.params)
    report_dir = Path(args.report) if args.report else None
    if args.offline:
        from twin_nodes.compare import compare_log
        from twin_nodes.params import load_params
        from twin_nodes.ulog_io import read_ulog

        if args.mcap:
            raise TwinError("--mcap needs the ROS graph; drop --offline")
        res = compare_log(read_ulog(args.flight), load_params(params_file), mode=args.mode, horizon_s=args.horizon,
                          progress=True)
        metrics, aligned = res.metrics, res.aligned
        metrics["source"] = "offline (twin_nodes.compare.compare_log)"
    else:
        bag = _bag_dir(args.mcap) if args.mcap else None
        run_dir = Path(args.run_dir) if args.run_dir else (report_dir / "run" if report_dir else None)
        res_g = run_graph(args.flight, params_file, mode=args.mode, rate=args.rate, run_dir=run_dir,
                          bag=str(bag) if bag else None, window_s=args.window, horizon_s=args.horizon,
                          domain_id=args.domain_id, progress=not args.quiet)
        metrics = res_g.metrics
        aligned = _load_aligned(res_g.aligned_path)
        st = res_g.replay_stats
        if st:
            print(f"graph: ROS_DOMAIN_ID {res_g.domain_id}, {st.get('messages', 0)} messages replayed in "
                  f"{st.get('wall_s', 0):.1f} s ({st.get('real_time_factor', 0):.1f}x real time); "
                  f"run dir {res_g.run_dir}", file=sys.stderr)
        if bag:
            print(f"recording: {bag} (MCAP {bag / (bag.name + '.mcap')})", file=sys.stderr)
    metrics["params_file"] = str(params_file)
    print(table2(metrics, title=f"Twin vs real (Table 2 layout): {Path(args.flight).name}, "
                                f"params {Path(params_file).name}"))
    if args.json:
        Path(args.json).write_text(json.dumps(to_jsonable(metrics), indent=1))
    if report_dir:
        from twin_nodes.report import write_report
        idx = write_report(report_dir, aligned, metrics, title=Path(args.flight).name)
        print(f"report: {idx}", file=sys.stderr)
    return 0


def _bag_dir(arg: str) -> Path:
    p = Path(arg)
    return p.with_suffix("") if p.suffix == ".mcap" else p


def _load_aligned(path: Path) -> Any:
    import numpy as np

    from twin_nodes.metrics import Aligned

    if not path.exists():
        return None
    d = np.load(path)
    return Aligned(t=d["t"], xy_twin=d["xy_twin"], xy_real=d["xy_real"], z_twin=d["z_twin"], z_real=d["z_real"],
                   throttle_twin=d["throttle_twin"], throttle_real=d["throttle_real"],
                   motors_twin=d["motors_twin"], motors_real=d["motors_real"], mask=d["mask"].astype(bool),
                   mode=str(d["mode"]))


# =========================================================================== regress

def regress_bag(bag: str | os.PathLike[str], rel_tol: float = 0.05, abs_tol: float = 1e-3
                ) -> tuple[dict[str, Any], dict[str, Any], list[str]]:
    """Recompute the whole-flight metrics from a recording's ``/real`` and ``/twin`` topics.

    Returns ``(stored, fresh, problems)``: the metrics stored at record time
    (``/twin_error/final_json``), the recomputed ones, and one line per metric that
    moved by more than ``max(abs_tol, rel_tol * |stored|)``."""
    import numpy as np

    from twin_nodes.compare import metrics_from_streams
    from twin_nodes.recording import read_bag

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
    from twin_nodes.metrics import compare_metrics, to_jsonable
    problems = compare_metrics(stored, to_jsonable(fresh), rel_tol=rel_tol, abs_tol=abs_tol)
    return stored, fresh, problems


def _cmd_regress(args: argparse.Namespace) -> int:
    from twin_nodes.metrics import table2

    stored, fresh, problems = regress_bag(args.bag, args.tolerance, args.abs_tolerance)
    print(table2(fresh, title=f"Recomputed from {args.bag}"))
    if problems:
        print(f"REGRESSION: {len(problems)} metric(s) differ from the stored ones:", file=sys.stderr)
        for line in problems:
            print(f"  {line}", file=sys.stderr)
        return 1
    print(f"OK: every stored metric reproduced within rel {args.tolerance:g} / abs {args.abs_tolerance:g}",
          file=sys.stderr)
    return 0


# =========================================================================== monitor / topics

def _spin_node(name: str, setup: Any, duration: float | None, until: Any = None) -> None:
    import rclpy
    from rclpy.node import Node

    from twin_nodes.nodes.common import make_executor

    rclpy.init(args=[sys.argv[0]])
    node = Node(name)
    try:
        tick = setup(node)
        ex = make_executor()
        ex.add_node(node)
        t_end = time.monotonic() + duration if duration else math.inf
        while rclpy.ok() and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
            if tick is not None:
                tick()
            if until is not None and until():
                break
    except KeyboardInterrupt:
        pass
    except Exception as exc:  # Ctrl-C: rclpy's handler shuts the context down under the spin
        if type(exc).__name__ != "ExternalShutdownException":
            raise
    finally:
        node.destroy_node()
        try:
            rclpy.shutdown()
        except Exception:
            pass


def format_monitor(values: dict[str, float], t_s: float | None) -> str:
    """The monitor's table: one row per channel, one column per statistic."""
    from msgs_py.topics import METRIC_STATS

    chans: list[str] = []
    for topic in values:
        ch = topic.split("/")[2]
        if ch not in chans:
            chans.append(ch)
    order = {c: i for i, c in enumerate(["xy", "z", "throttle"])}
    chans.sort(key=lambda c: (order.get(c, 3), len(c), c))
    head = f"{'channel':<13}" + "".join(f"{s:>12}" for s in METRIC_STATS)
    lines = [f"twin error, rolling window  (log time {t_s:.1f} s)" if t_s is not None else "twin error, rolling window",
             head, "-" * len(head)]
    for ch in chans:
        unit = "m" if ch in ("xy", "z") else "%"
        row = f"{ch + ' [' + unit + ']':<13}"
        for st in METRIC_STATS:
            topic = f"/twin_error/{ch}/{st}" + ("_m" if unit == "m" else "")
            v = values.get(topic, math.nan)
            v = v * 100 if unit == "%" else v
            row += f"{v:>12.3f}" if math.isfinite(v) else f"{'-':>12}"
        lines.append(row)
    return "\n".join(lines)


def _cmd_monitor(args: argparse.Namespace) -> int:
    from msgs_py.topics import msg_class

    if args.domain_id is not None:
        os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)
    values: dict[str, float] = {}
    subs: dict[str, Any] = {}
    state = {"last_draw": 0.0, "t": None, "lines": 0, "final": None}

    def setup(node: Any) -> Any:
        f64 = msg_class("std_msgs/msg/Float64")
        from twin_nodes.nodes.common import reliable_qos
        node.create_subscription(msg_class("rosgraph_msgs/msg/Clock"), "/clock",
                                 lambda m: state.__setitem__("t", m.clock.sec + m.clock.nanosec * 1e-9), 10)
        node.create_subscription(msg_class("std_msgs/msg/String"), "/twin_error/final_table",
                                 lambda m: state.__setitem__("final", m.data), reliable_qos(1, latched=True))

        def tick() -> None:
            for topic, types in node.get_topic_names_and_types():
                if topic.startswith("/twin_error/") and types == ["std_msgs/msg/Float64"] and topic not in subs:
                    subs[topic] = node.create_subscription(
                        f64, topic, lambda m, tp=topic: values.__setitem__(tp, float(m.data)), 10)
            now = time.monotonic()
            if now - state["last_draw"] >= 0.5:
                state["last_draw"] = now
                text = format_monitor(values, state["t"]) if values else "waiting for /twin_error/... topics"
                if args.once:
                    return
                if sys.stdout.isatty():
                    sys.stdout.write("\x1b[H\x1b[2J" + text + "\n")
                else:
                    sys.stdout.write(text + "\n\n")
                sys.stdout.flush()
        return tick

    until = (lambda: bool(values) and len(values) >= len(subs) and len(subs) >= 12) if args.once else None
    _spin_node("rotortwin_monitor", setup, args.duration if args.duration else (30.0 if args.once else None), until)
    if args.once:
        print(format_monitor(values, state["t"]) if values else "no /twin_error topics seen")
    if state["final"]:
        print(state["final"])
    return 0 if (values or not args.once) else 1


def _cmd_topics(args: argparse.Namespace) -> int:
    from msgs_py.topics import TOPICS, msg_class

    if args.domain_id is not None:
        os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)
    if args.topics_command in (None, "list"):
        found: dict[str, list[str]] = {}

        def setup(node: Any) -> Any:
            def tick() -> None:
                for t, ty in node.get_topic_names_and_types():
                    found[t] = ty
            return tick

        _spin_node("rotortwin_topics", setup, args.wait)
        if not found:
            for spec in TOPICS.values():
                print(f"{spec.name:<28} {spec.type:<38} (documented; not seen on the network)")
            return 0
        for t in sorted(found):
            note = TOPICS[t].content[:60] if t in TOPICS else ""
            print(f"{t:<34} {', '.join(found[t]):<38} {note}")
        return 0
    topic = args.topic
    got = {"n": 0}

    def setup_echo(node: Any) -> None:
        from rclpy.qos import QoSProfile

        ty = None
        t_end = time.monotonic() + args.wait
        while ty is None and time.monotonic() < t_end:
            for t, tys in node.get_topic_names_and_types():
                if t == topic:
                    ty = tys[0]
            if ty is None:
                time.sleep(0.1)
        if ty is None:
            raise TwinError(f"{topic}: no such topic after {args.wait:g} s")
        pubs = node.get_publishers_info_by_topic(topic)
        qos = QoSProfile(depth=100)
        if pubs:
            qos.reliability = pubs[0].qos_profile.reliability
            qos.durability = pubs[0].qos_profile.durability

        def cb(m: Any) -> None:
            got["n"] += 1
            print(f"--- {topic} #{got['n']}\n{m}", flush=True)
        node.create_subscription(msg_class(ty), topic, cb, qos)

    _spin_node("rotortwin_echo", setup_echo, args.duration, until=lambda: args.count and got["n"] >= args.count)
    return 0 if got["n"] else 1


# =========================================================================== single nodes

def _run_module(module: str, params: dict[str, Any], extra: list[str]) -> int:
    cmd = node_command(module, params) + list(extra or [])
    return subprocess.call(cmd)


def _cmd_replay(args: argparse.Namespace) -> int:
    return _run_module("replay", {"ulog": args.flight, "rate": float(args.rate), "use_sim_time": False,
                                  **({"wait_for": args.wait_for} if args.wait_for else {})}, args.ros_args)


def _cmd_twin(args: argparse.Namespace) -> int:
    return _run_module("twin", {"params_file": args.params, "mode": args.mode, "use_sim_time": not args.wall_time},
                       args.ros_args)


def _cmd_metrics(args: argparse.Namespace) -> int:
    p: dict[str, Any] = {"window_s": args.window, "use_sim_time": not args.wall_time, "n_motors": args.motors}
    if args.json:
        p["json_out"] = args.json
    return _run_module("metrics", p, args.ros_args)


def _cmd_record(args: argparse.Namespace) -> int:
    if args.out == "recover":
        if not args.bag:
            raise TwinError("record recover: expected the bag directory or .mcap to recover")
        from twin_nodes.recording import recover
        rep = recover(args.bag, args.recover_out)
        print(f"recovered {rep.n_messages} messages into {rep.out_dir}"
              + ("" if rep.complete else f" (the source was cut short: {rep.error or 'no footer'})"))
        for t, c in sorted(rep.counts.items()):
            print(f"  {t:<34} {c}")
        return 0
    return _run_module("recorder", {"out": args.out, "use_sim_time": not args.wall_time}, args.ros_args)


# =========================================================================== registration

def register(subparsers: argparse._SubParsersAction) -> None:
    raw = argparse.RawDescriptionHelpFormatter
    c = subparsers.add_parser("compare", help="replay a ULog through the node graph and print Table-2 metrics",
                              description=__doc__, formatter_class=raw)
    c.add_argument("flight", help="PX4 ULog (.ulg)")
    c.add_argument("--params", help="vehicle params YAML (default: from the log's SYS_AUTOSTART)")
    c.add_argument("--mode", choices=("closed", "open"), default="closed",
                   help="closed: our controller flies the setpoints; open: real motor commands, re-synced")
    c.add_argument("--rate", type=float, default=0.0,
                   help="replay speed: 0 = as fast as the nodes keep up (default), 1 = real time, 20 = 20x")
    c.add_argument("--horizon", type=float, default=2.0, help="open loop: re-sync period [s] (default 2)")
    c.add_argument("--window", type=float, default=5.0, help="rolling metrics window [s] (default 5)")
    c.add_argument("--json", help="write the whole-flight metrics here")
    c.add_argument("--mcap", help="record every topic into this bag directory (rosbag2 layout; a trailing "
                                  ".mcap is dropped: OUT.mcap -> OUT/OUT.mcap)")
    c.add_argument("--report", help="write PNG plots and index.html here")
    c.add_argument("--run-dir", help="node logs and pid files (default: REPORT/run or a temp dir)")
    c.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: random 1..200)")
    c.add_argument("--offline", action="store_true", help="no ROS: the same metrics via compare_log")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=_cmd_compare)

    m = subparsers.add_parser("monitor", help="live /twin_error/... metrics as a terminal table")
    m.add_argument("--once", action="store_true", help="print one table once the topics are seen, then exit")
    m.add_argument("--duration", type=float, help="stop after S seconds")
    m.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID of the graph (default: the environment's)")
    m.set_defaults(func=_cmd_monitor)

    t = subparsers.add_parser("topics", help="list the graph's topics or echo one")
    t.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID of the graph")
    t.add_argument("--wait", type=float, default=1.5, help="discovery time [s] (default 1.5)")
    ts = t.add_subparsers(dest="topics_command", metavar="list|echo")
    ts.add_parser("list", help="topics and types on the network (or the documented ones)")
    e = ts.add_parser("echo", help="print the messages of one topic")
    e.add_argument("topic")
    e.add_argument("--count", type=int, default=0, help="stop after N messages")
    e.add_argument("--duration", type=float, help="stop after S seconds")
    t.set_defaults(func=_cmd_topics)

    r = subparsers.add_parser("regress", help="recompute a recording's metrics and compare with the stored ones")
    r.add_argument("bag", help="bag directory (or .mcap) recorded by 'rotortwin compare --mcap'")
    r.add_argument("--tolerance", type=float, default=0.05, help="relative tolerance (default 0.05)")
    r.add_argument("--abs-tolerance", type=float, default=1e-3, help="absolute tolerance (default 1e-3)")
    r.set_defaults(func=_cmd_regress)

    def ros_extra(p: argparse.ArgumentParser) -> None:
        p.add_argument("--wall-time", action="store_true", help="use wall time instead of /clock")
        p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[],
                       help="further ROS arguments, passed after the node's own")

    rp = subparsers.add_parser("replay", help="run the ULog replay node in the foreground")
    rp.add_argument("flight")
    rp.add_argument("--rate", type=float, default=1.0, help="1 real time (default), 20 = 20x, 0 = flow-controlled")
    rp.add_argument("--wait-for", nargs="*", default=[], help="consumer node names to wait for")
    rp.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[])
    rp.set_defaults(func=_cmd_replay)

    tw = subparsers.add_parser("twin", help="run the twin node in the foreground")
    tw.add_argument("--params", required=True, help="vehicle params YAML")
    tw.add_argument("--mode", choices=("closed", "open"), default="closed")
    ros_extra(tw)
    tw.set_defaults(func=_cmd_twin)

    me = subparsers.add_parser("metrics", help="run the metrics node in the foreground")
    me.add_argument("--window", type=float, default=5.0, help="rolling window [s]")
    me.add_argument("--motors", type=int, default=4, help="number of motors")
    me.add_argument("--json", help="write the whole-flight metrics here at the end")
    ros_extra(me)
    me.set_defaults(func=_cmd_metrics)

    rc = subparsers.add_parser("record", help="record every graph topic to MCAP, or 'record recover BAG'",
                               description="rotortwin record OUT_BAG   |   rotortwin record recover BAG [--out DIR]")
    rc.add_argument("out", help="bag directory to create, or 'recover'")
    rc.add_argument("bag", nargs="?", help="with 'recover': the cut-short bag directory or .mcap")
    rc.add_argument("--out", dest="recover_out", help="with 'recover': output directory (default BAG_recovered)")
    ros_extra(rc)
    rc.set_defaults(func=_cmd_record)
