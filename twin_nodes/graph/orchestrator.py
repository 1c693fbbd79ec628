"""The graph's node processes: start, follow the replay, stop, and the run's results.

:func:`run_graph` starts the same four processes as ``launch_scripts/replay_compare.sh``
(ulog_replay, twin, metrics and, with ``bag``, recorder) on a private ``ROS_DOMAIN_ID``
with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, waits for ``/replay/done`` and the
metrics node's whole-flight JSON, stops everything with SIGINT and returns a
:class:`GraphResult`.  Without an explicit params file, :func:`default_params_for`
chooses the shipped one for the log's ``SYS_AUTOSTART`` or builds the nominal from the log itself.
"""

from __future__ import annotations

import json
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

from twin_nodes.base.errors import LogError, TwinError
from twin_nodes.logs.recording import INCOMPLETE_EXIT

#: PX4 SYS_AUTOSTART -> shipped params file stem
NODE_MODULES = {"replay": "ulog_replay", "twin": "twin_node", "metrics": "metrics_node", "recorder": "recorder_node"}


def default_params_for(ulog: str | os.PathLike[str], explicit: str | None = None, log: Any = None) -> Path:
    """The params file to fly: ``explicit``, else the shipped one for the log's airframe, else the
    nominal built from the log itself (:func:`twin_nodes.identify.nominal.params_for_log`); says
    which on stderr in one line when it was not given (``log``: the flight already loaded)."""
    from twin_nodes.identify.nominal import params_for_log

    path, note = params_for_log(ulog, explicit, log=log)
    if note:
        print(f"rotortwin: {note}", file=sys.stderr)
    return path


def ros_env(domain_id: int | None = None) -> dict[str, str]:
    """Environment for graph processes: private domain, localhost-only discovery.

    Without ``domain_id`` a random id of 1..101 with no DDS participant on it (not leased:
    :func:`run_graph` leases its domain with :func:`twin_nodes.graph.domains.lease_domain`)."""
    from twin_nodes.graph.domains import AUTO_DOMAINS, check_domain_id, participant_port_busy

    if domain_id is None:
        ids = list(AUTO_DOMAINS)
        random.shuffle(ids)
        domain_id = next((d for d in ids if not participant_port_busy(d)), ids[0])
    env = dict(os.environ)
    env.pop("ROTORTWIN_PARENT_PID", None)
    env["ROS_DOMAIN_ID"] = str(check_domain_id(domain_id))
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
            val = "[" + ",".join(_yaml_str(x) for x in v) + "]"
        elif isinstance(v, str):
            val = _yaml_str(v)  # a file named `12345` or `true` stays a string
        else:
            val = str(v)
        cmd += ["-p", f"{k}:={val}"]
    return cmd


def _yaml_str(x: Any) -> str:
    """A YAML single-quoted string: ROS parses ``-p name:=value`` values as YAML."""
    return "'" + str(x).replace("'", "''") + "'"


@dataclass
class GraphResult:
    """What a run gave.  ``run_dir`` is removed at the end when it was a temporary folder
    (``run_dir_kept`` False); ``aligned`` holds the metrics node's aligned series then."""

    metrics: dict[str, Any]
    json_path: Path
    aligned_path: Path
    bag_path: Path | None
    replay_stats: dict[str, Any]
    wall_s: float
    run_dir: Path
    domain_id: int
    exit_codes: dict[str, int] = field(default_factory=dict)
    aligned: Any = None
    run_dir_kept: bool = True


class Graph:
    """The four node processes, their pid files and logs under ``run_dir``."""

    def __init__(self, run_dir: Path, env: dict[str, str]):
        self.run_dir = run_dir
        self.env = env
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, params: dict[str, Any], capture_stdout: bool = False) -> subprocess.Popen:
        # the nodes run in their own sessions (a Ctrl-C in the terminal reaches the CLI only, which
        # stops them in order); they die with the CLI: SIGTERM on its death (PR_SET_PDEATHSIG) and a
        # parent-pid watchdog in their spin loop (ROTORTWIN_PARENT_PID)
        env = {**self.env, "ROTORTWIN_PARENT_PID": str(os.getpid())}
        with open(self.run_dir / f"{name}.log", "w", encoding="utf-8") as log:
            p = subprocess.Popen(node_command(name, params), env=env, stdin=subprocess.DEVNULL,
                                 stdout=subprocess.PIPE if capture_stdout else log, stderr=log,
                                 text=True, start_new_session=True, preexec_fn=_die_with_parent())
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

    def why(self, name: str, what: str) -> TwinError:
        """The error for a node that failed: its own one-line error (``rotortwin node: error: ...``)
        when it gave one, else ``what`` and the tail of its log."""
        try:
            text = (self.run_dir / f"{name}.log").read_text(encoding="utf-8", errors="replace")
        except OSError:
            text = ""
        own = [ln for ln in text.splitlines() if ln.startswith("rotortwin node: error: ")]
        if own:
            return TwinError(f"{name} node: {own[-1][len('rotortwin node: error: '):]}")
        return TwinError(f"{what}:\n{self.log_tail(name)}")

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


def _die_with_parent() -> Any:
    """A ``preexec_fn`` that asks Linux to SIGTERM the child when this process dies."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        prctl = libc.prctl
    except (OSError, AttributeError):
        return None
    parent = os.getpid()
    pr_set_pdeathsig = 1

    def setup() -> None:
        prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
        if os.getppid() != parent:  # the parent died before prctl: no signal would come
            os._exit(1)
    return setup


def run_graph(ulog: str | os.PathLike[str], params_file: str | os.PathLike[str], *, mode: str = "closed",
              rate: float = 0.0, run_dir: str | os.PathLike[str] | None = None, bag: str | None = None,
              window_s: float = 5.0, horizon_s: float = 2.0, domain_id: int | None = None,
              progress: bool = True, timeout_s: float = 900.0, n_motors: int | None = None,
              use_sim_time: bool = False, replay_params: dict[str, Any] | None = None) -> GraphResult:
    """Replay ``ulog`` (a ``.ulg``, or a recorded bag: its ``/real`` messages) through the process
    graph and return the metrics node's totals.

    Failures leave nothing behind: a bag of a failed run is removed (one interrupted by Ctrl-C
    or SIGTERM is finalised and kept), and a temporary run folder is removed in every case."""
    from twin_nodes.graph.domains import lease_domain

    ulog = Path(ulog)
    if not (ulog.is_file() or ulog.is_dir()):
        raise LogError(str(ulog), "<file>", "file not found")
    if bag:
        if os.path.lexists(bag):
            raise TwinError(f"{bag}: the recording already exists")
        parent = Path(bag).resolve().parent
        if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            raise TwinError(f"{bag}: expected a bag path in an existing, writable directory ({parent})")
    if n_motors is None:
        from twin_nodes.vehicle.params import load_params
        n_motors = load_params(params_file).rotors.count
    lease = lease_domain(domain_id)
    temp_run = not run_dir
    rd = Path(run_dir) if run_dir else Path(tempfile.mkdtemp(prefix="rotortwin_run_"))
    ok = interrupted = recorder_started = keep_bag = False
    try:
        rd.mkdir(parents=True, exist_ok=True)
        (rd / "domain_id").write_text(f"{lease.domain_id}\n")
        env = ros_env(lease.domain_id)
        g = Graph(rd, env)
        json_path, aligned_path, stats_path = rd / "final_metrics.json", rd / "aligned.npz", rd / "replay_stats.json"
        for p in (json_path, aligned_path, stats_path):
            p.unlink(missing_ok=True)
        common = {"use_sim_time": use_sim_time}
        wait_for = ["twin", "metrics"]
        t_wall = time.monotonic()
        old_term = old_hup = None
        if threading.current_thread() is threading.main_thread():
            # a SIGTERM/SIGHUP to the CLI must still stop the node processes (they run in their own sessions)
            old_term = signal.signal(signal.SIGTERM, _raise_interrupt)
            old_hup = signal.signal(signal.SIGHUP, _raise_interrupt)
        try:
            if bag:
                g.start("recorder", {**common, "out": str(bag)})
                recorder_started = True
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
                    raise g.why(name, f"the {name} node exited ({dead[name]}) before the final metrics")
                if time.monotonic() > deadline:
                    raise TwinError(f"no final metrics from the metrics node after 120 s:\n{g.log_tail('metrics')}")
                time.sleep(0.1)
            time.sleep(0.3)  # let the recorder take the latched final topics
        except KeyboardInterrupt:
            interrupted = True
            raise
        finally:
            # the recorder first, while the other nodes still hold what they published (reliable writers keep
            # unacknowledged messages only while their process lives): it drains until every announced message is in
            codes = g.stop(["recorder"] if recorder_started else [])
            codes.update(g.stop())
            if old_term is not None:
                signal.signal(signal.SIGTERM, old_term)
                signal.signal(signal.SIGHUP, old_hup)
        metrics = json.loads(json_path.read_text())
        stats = json.loads(stats_path.read_text()) if stats_path.exists() else {}
        if "error" in metrics:
            raise TwinError(f"metrics node: {metrics['error']}")
        if bag and codes.get("recorder") == INCOMPLETE_EXIT:
            keep_bag = True  # valid and finalised, but short of announced messages: kept, and said so
            said = [ln for ln in g.log_tail("recorder", 20).splitlines() if "incomplete" in ln]
            raise TwinError(said[-1] if said else f"the recording {bag} is incomplete (kept)")
        if bag and codes.get("recorder") not in (0, None):
            raise TwinError(f"the recorder exited ({codes['recorder']}): the bag is not complete:\n"
                            f"{g.log_tail('recorder')}")
        aligned = load_aligned(aligned_path)
        ok = True
    finally:
        lease.release()
        if not ok and recorder_started and bag and Path(bag).exists() and not keep_bag:
            if interrupted:
                # a rotortwin command staged the bag: its guard removes it with the other unfinished outputs
                print(f"rotortwin: interrupted: the recording so far was finalised ({bag})", file=sys.stderr)
            else:
                if Path(bag).is_dir():
                    shutil.rmtree(bag, ignore_errors=True)  # a failed run's bag is removed
                else:
                    Path(bag).unlink(missing_ok=True)
        if temp_run:
            shutil.rmtree(rd, ignore_errors=True)
    return GraphResult(metrics=metrics, json_path=json_path, aligned_path=aligned_path,
                       bag_path=Path(bag) if bag else None, replay_stats=stats, wall_s=time.monotonic() - t_wall,
                       run_dir=rd, domain_id=lease.domain_id, exit_codes=codes, aligned=aligned,
                       run_dir_kept=not temp_run)


def _raise_interrupt(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)  # as the CLI's guard names it (exit 143/129)


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
            raise g.why(name, f"the {name} node exited ({other[name]}) during the replay")
        if time.monotonic() - t0 > timeout_s:
            raise TwinError(f"replay did not finish in {timeout_s:.0f} s")
        time.sleep(0.1)
    th.join(1.0)
    if bar is not None:
        bar.close()
    if rp.returncode != 0:
        raise g.why("replay", f"the replay node failed ({rp.returncode})")


def run_node(node: str, params: dict[str, Any], extra: list[str] | None = None) -> int:
    """Run one node in the foreground (``node_command`` plus ``extra`` ROS arguments); its exit code."""
    return subprocess.call(node_command(node, params) + list(extra or []))


def bag_dir(arg: str) -> Path:
    """The recording written for ``--mcap ARG``: the path itself.  A path ending in ``.mcap`` is one MCAP
    file (the rosbag2 metadata inside it); any other a rosbag2 folder of that name (``metadata.yaml`` +
    ``ARG/ARG.mcap``).  See :func:`twin_nodes.logs.recording.open_bag_writer`."""
    return Path(arg)


def load_aligned(path: Path) -> Any:
    """The metrics node's ``aligned.npz`` as a :class:`twin_nodes.twin.metrics.Aligned` (None if absent)."""
    import numpy as np

    from twin_nodes.twin.metrics import Aligned

    if not path.exists():
        return None
    d = np.load(path)
    return Aligned(t=d["t"], xy_twin=d["xy_twin"], xy_real=d["xy_real"], z_twin=d["z_twin"], z_real=d["z_real"],
                   throttle_twin=d["throttle_twin"], throttle_real=d["throttle_real"],
                   motors_twin=d["motors_twin"], motors_real=d["motors_real"], mask=d["mask"].astype(bool),
                   mode=str(d["mode"]))
