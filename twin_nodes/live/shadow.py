"""``rotortwin live --url URL``: the twin shadowing a live vehicle (or PX4 SITL) in one command.

The graph's own processes on a private ROS domain (localhost discovery), started, watched and
stopped with :class:`twin_nodes.graph.Graph`:

=============  ==============================================================================
process        what it does
=============  ==============================================================================
``bridge``     ``px4_bridge telemetry``: the vehicle's MAVLink stream as ``/real/...`` (wall time)
``twin``       ``twin_node`` in **open loop**: the real motor commands drive the model, re-synced
               to the real state every ``horizon_s`` (the graph's open-loop mode)
``metrics``    ``metrics_node``: rolling ``/twin_error/...``; the totals of what was seen on stop
``link``       :mod:`twin_nodes.live.link_node`: ``/twin_error/link_lost``
``recorder``   (with ``bag``) every topic into a rosbag2 MCAP
``foxglove``   (with ``foxglove_port``) :mod:`twin_nodes.live.foxglove_node`
=============  ==============================================================================

Times: the bridge stamps what it publishes with its clock when the MAVLink message arrives; the
twin and the metrics time the header-less ``/real/...`` messages (motors, throttle, setpoint,
status) by their DDS source timestamp, i.e. the bridge's clock when it published them, so every
node puts every input at the same time however late its own callback runs (the processes run
rclpy's classic executor for this: see :func:`twin_nodes.nodes.common.source_stamps`).  On stop the
twin applies the inputs its reorder buffer still holds and the metrics read every twin sample
already delivered, so the totals cover the data up to the last input, whenever the stop comes.

Reconnects: the bridge keeps its link (a UDP listener waits, TCP/serial are reopened) and the
processes keep running through an outage; the link flag goes up after ``stale_after_s`` of
silence and down with the first message after it.  Measured recovery of the error topics after a
5 s outage: see ``tests/test_live_shadow.py`` and docs/px4_sitl.md.

Stopping (``stop`` event, ``duration_s``, Ctrl-C or SIGTERM): the bridge and the link watchdog
first (no more inputs; the bridge announces its clean stop, so neither the watchdog nor the totals
count the end as a link loss -- issue 28), then the twin, then the metrics (which publish and
write the totals of the data seen), then the recorder (which takes the final topics) and the
Foxglove server.

Vehicle restarts (issue 28): the bridge publishes ``/real/reset``; the twin starts afresh from the
next real state and the metrics restart their rolling window (``/twin_error/reset`` notes when and
why).  The totals (:attr:`LiveResult.metrics`, ``live.json``) say what was watched: the URL, the
vehicle's system id, start and end, the resets and the link losses (:func:`watched_header`).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from twin_nodes.base.errors import TwinError
from twin_nodes.graph.orchestrator import Graph, _die_with_parent, node_command, ros_env

__all__ = ["LiveConfig", "LiveResult", "run_live", "module_command", "watched_header"]


@dataclass
class LiveConfig:
    """What ``rotortwin live`` runs (see :func:`run_live`)."""

    url: str
    params_file: str
    bag: str | None = None
    foxglove_port: int | None = None
    foxglove_host: str = "127.0.0.1"
    window_s: float = 5.0
    horizon_s: float = 2.0
    stale_after_s: float = 3.0
    airborne_only: bool = True
    pwm_min_us: float = 1000.0
    pwm_max_us: float = 2000.0
    motor_channels: str = ""
    request_streams: bool = True
    system_id: int | None = None   # the vehicle's MAVLink system id (None: the first autopilot heartbeat's)


@dataclass
class LiveResult:
    metrics: dict[str, Any] | None      # whole-run totals (metrics node), None if it saw no twin sample
    outages: list[dict[str, Any]]       # link outages (wall-clock start, length [s])
    run_dir: Path
    domain_id: int
    bag_path: Path | None
    foxglove_url: str | None
    exit_codes: dict[str, int] = field(default_factory=dict)
    wall_s: float = 0.0
    watched: dict[str, Any] = field(default_factory=dict)  # what was watched (also in metrics when scored)


def watched_header(url: str, bridge: dict[str, Any], link: dict[str, Any]) -> dict[str, Any]:
    """What a live run watched, for its totals (``live.json``): the URL, the vehicle's system id, the
    first and last message's time (Unix s), what was ignored, the vehicle restarts and the link
    losses (the watchdog's outages; a clean end is listed under ``ends``, not as a loss)."""
    return {"log": url, "source": "rotortwin live (vehicle telemetry -> twin -> metrics nodes)",
            "system_id": bridge.get("system_id"), "component_id": bridge.get("component_id"),
            "start_s": bridge.get("start_s"), "end_s": bridge.get("end_s"), "messages": bridge.get("messages"),
            "ignored": bridge.get("ignored", {}), "resets": bridge.get("resets", []),
            "link_losses": link.get("outages", []), "ends": link.get("ends", []),
            "vehicle_closed": bridge.get("vehicle_closed", False)}


def module_command(module: str, args: list[str], params: dict[str, Any]) -> list[str]:
    """``python -m <module> <args> --ros-args -p k:=v ...`` (values as :func:`node_command` quotes them)."""
    base = node_command("twin", {})          # [python, -m, module, --ros-args]
    ros = node_command("twin", params)[len(base):]  # the quoted -p k:=v pairs
    return [sys.executable, "-m", module, *args, "--ros-args", *ros]


class _LiveGraph(Graph):
    """:class:`Graph` that also starts processes which are not replay-graph nodes."""

    def start_cmd(self, name: str, cmd: list[str], capture_stdout: bool = False) -> subprocess.Popen:
        env = {**self.env, "ROTORTWIN_PARENT_PID": str(os.getpid())}
        with open(self.run_dir / f"{name}.log", "w", encoding="utf-8") as log:
            p = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL,
                                 stdout=subprocess.PIPE if capture_stdout else log, stderr=log, text=True,
                                 start_new_session=True, preexec_fn=_die_with_parent())
        self.procs[name] = p
        (self.run_dir / f"{name}.pid").write_text(f"{p.pid}\n")
        return p


def _read_url(p: subprocess.Popen, timeout_s: float) -> str | None:
    """The ``FOXGLOVE ws://...`` line of a Foxglove node (None if it did not come)."""
    out: list[str] = []

    def reader() -> None:
        assert p.stdout is not None
        for line in p.stdout:
            if line.startswith("FOXGLOVE "):
                out.append(line.split()[1])
                return

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    th.join(timeout_s)
    return out[0] if out else None


def run_live(cfg: LiveConfig, *, domain_id: int | None = None, run_dir: str | os.PathLike[str] | None = None,
             duration_s: float | None = None, stop: threading.Event | None = None,
             on_start: Callable[[dict[str, Any]], None] | None = None) -> LiveResult:
    """Run the live shadow until ``stop`` is set, ``duration_s`` passed, or Ctrl-C / SIGTERM.

    ``on_start(info)`` is called once everything runs (``info``: domain id, run folder, Foxglove URL)."""
    from twin_nodes.graph.domains import lease_domain
    from twin_nodes.vehicle.params import load_params

    n_motors = load_params(cfg.params_file).rotors.count
    if cfg.bag and Path(cfg.bag).exists():
        raise TwinError(f"{cfg.bag}: the recording already exists")
    lease = lease_domain(domain_id)
    temp_run = run_dir is None
    rd = Path(run_dir) if run_dir else Path(tempfile.mkdtemp(prefix="rotortwin_live_"))
    rd.mkdir(parents=True, exist_ok=True)
    (rd / "domain_id").write_text(f"{lease.domain_id}\n")
    # the classic executor: header-less inputs timed by their DDS source timestamp (common.source_stamps)
    g = _LiveGraph(rd, {**ros_env(lease.domain_id), "ROTORTWIN_EXECUTOR": "single"})
    json_path, link_path, aligned_path = rd / "final_metrics.json", rd / "link.json", rd / "aligned.npz"
    bridge_path = rd / "bridge.json"
    stop = stop or threading.Event()
    old = {}
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGTERM, signal.SIGHUP):
            old[s] = signal.signal(s, lambda *_: stop.set())
    t_wall = time.monotonic()
    url = None
    codes: dict[str, int] = {}
    try:
        if cfg.bag:
            g.start("recorder", {"out": str(cfg.bag)})
        if cfg.foxglove_port is not None:
            fp = g.start_cmd("foxglove", module_command("twin_nodes.live.foxglove_node", [],
                                                        {"port": int(cfg.foxglove_port), "host": cfg.foxglove_host,
                                                         "params_file": str(cfg.params_file)}), capture_stdout=True)
            url = _read_url(fp, 60.0)
            if url is None:
                raise TwinError(f"the Foxglove server did not start:\n{g.log_tail('foxglove')}")
        g.start_cmd("link", module_command("twin_nodes.live.link_node", [],
                                           {"stale_after_s": cfg.stale_after_s, "summary_out": str(link_path)}))
        g.start("metrics", {"window_s": cfg.window_s, "n_motors": n_motors, "mode": "open",
                            "airborne_only": cfg.airborne_only, "json_out": str(json_path),
                            "aligned_out": str(aligned_path), "source": cfg.url})
        g.start("twin", {"params_file": str(cfg.params_file), "mode": "open", "horizon_s": cfg.horizon_s,
                         "diagnostics_period_s": 1.0})
        g.start_cmd("bridge", module_command("twin_nodes.nodes.px4_bridge", ["telemetry"], {
            "url": cfg.url, "pwm_min_us": float(cfg.pwm_min_us), "pwm_max_us": float(cfg.pwm_max_us),
            "n_motors": n_motors, "motor_channels": cfg.motor_channels, "stale_after_s": float(cfg.stale_after_s),
            "request_streams": bool(cfg.request_streams), "system_id": int(cfg.system_id or 0),
            "summary_out": str(bridge_path)}))
        if on_start is not None:
            on_start({"domain_id": lease.domain_id, "run_dir": str(rd), "foxglove_url": url})
        t_end = time.monotonic() + duration_s if duration_s else float("inf")
        try:
            while not stop.is_set() and time.monotonic() < t_end:
                dead = g.dead()
                if dead:
                    name = next(iter(dead))
                    raise TwinError(f"the {name} node exited ({dead[name]}):\n{g.log_tail(name)}")
                stop.wait(0.2)
        except KeyboardInterrupt:
            pass
    finally:
        # inputs first, then the consumers in the order that keeps the totals and the bag complete
        # the watchdog with the bridge: a normal stop is not a link loss (issue 28)
        for group in (["bridge", "link"], ["twin"], ["metrics"], ["recorder", "foxglove"]):
            names = [n for n in group if n in g.procs]
            if names:
                codes.update(g.stop(names, timeout_s=30.0))
        for s, h in old.items():
            signal.signal(s, h)
        lease.release()
    metrics = json.loads(json_path.read_text()) if json_path.exists() else None
    link = json.loads(link_path.read_text()) if link_path.exists() else {"outages": []}
    bridge = json.loads(bridge_path.read_text()) if bridge_path.exists() else {}
    header = watched_header(cfg.url, bridge, link)
    if metrics is not None:
        metrics.update(header)
    res = LiveResult(metrics=metrics, outages=link.get("outages", []), run_dir=rd, domain_id=lease.domain_id,
                     bag_path=Path(cfg.bag) if cfg.bag else None, foxglove_url=url, exit_codes=codes,
                     wall_s=time.monotonic() - t_wall, watched=header)
    if temp_run:
        shutil.rmtree(rd, ignore_errors=True)
    return res
