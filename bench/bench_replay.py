"""Replay throughput of the live graph: ULog replay -> twin -> metrics -> recorder, as processes.

    .venv/bin/python bench/bench_replay.py [--minutes 10] [--flight F.ulg] [--rate 0] [--strict]

Without ``--flight`` it simulates a flight of at least ``--minutes`` (the PX4 SIH
quadrotor, params/px4_sih_quadx.yaml, flying the prove-suite mission over and over
with :func:`twin_nodes.twin.sim.fly_closed_loop`) and writes it as a PX4-like ULog with
:mod:`twin_nodes.logs.ulog_write` (cached under ``out/bench/``).  Then it runs the same
graph ``rotortwin compare --mcap`` runs (private ROS_DOMAIN_ID, localhost discovery)
and reports:

- messages/s: every message published in the graph (replay incl. ``/clock``, twin,
  metrics, flow-control acks) per second of replay wall time; the recorder receives
  and writes each of them;
- real-time factor: seconds of log per second of wall time while the replay runs;
- dropped messages: MCAP count vs the replay's plan for every ``/real`` topic, and the
  four ``/twin`` topics against each other (must all be 0);
- the reference measured in the same run: the same twin on the same flight offline, in this
  process (``rotortwin compare --offline``'s :func:`twin_nodes.twin.compare.compare_log`), its
  real-time factor, and the graph's real-time factor as a ratio of it.

``ROTORTWIN_BENCH_SMOKE=1``: a smoke run on one simulated mission (~2 min of log, cached under
``out/bench/smoke/``; the numbers mean nothing).

The issue's target is >= 20x real time on 2 cores; ``--strict`` exits 1 below it or on
any drop.  Timings depend on what else the machine runs: compare numbers only between
runs on the same, otherwise idle, machine.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def make_long_flight(path: Path, minutes: float, seed: int = 3) -> dict:
    """Fly the SIH quad through repeated missions for >= ``minutes`` and write a ULog."""
    from twin_nodes.twin.simflight import EstimateNoise, mission_setpoints, record_to_topics
    from twin_nodes.vehicle.params import shipped
    from twin_nodes.twin.sim import fly_closed_loop
    from twin_nodes.logs.ulog_write import write_px4_ulog

    vp = shipped("px4_sih_quadx")
    rng = np.random.default_rng(seed)
    ts, sps, arm_t, arm_v = [], [], [], []
    t_off = 0.0
    while t_off < minutes * 60.0:
        t, sp, armed = mission_setpoints(rng)
        ts.append(t + t_off)
        sps.append(sp)
        arm_t.append(t + t_off)
        arm_v.append(np.asarray(armed(t), bool))
        t_off = float(ts[-1][-1]) + (t[1] - t[0])
    t_sp, SP = np.concatenate(ts), np.concatenate(sps)
    at, av = np.concatenate(arm_t), np.concatenate(arm_v)

    def armed_fn(tq: np.ndarray) -> np.ndarray:
        return av[np.clip(np.searchsorted(at, tq, side="right") - 1, 0, len(av) - 1)]

    def battery(tq: np.ndarray) -> np.ndarray:
        return 16.6 - 2.0 * np.clip(tq / t_sp[-1], 0, 1)

    rec = fly_closed_loop(vp, t_sp, SP, battery_v=battery, estimate_noise=EstimateNoise(rng, 1 / 250.0),
                          armed=armed_fn, rng=rng, progress=True)
    topics = record_to_topics(rec, vp, battery, (t_sp, SP), np.random.default_rng(seed + 1))
    params = {"SYS_AUTOSTART": 10040, "CA_ROTOR_COUNT": 4, "MPC_THR_HOVER": float(vp.hover_command)}
    write_px4_ulog(str(path), topics, params, {"sys_name": "rotortwin-bench", "ver_hw": "ROTORTWIN_SIM"})
    return {"duration_s": float(rec.t[-1]), "missions": len(ts)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    from _smoke import SMOKE as smoke  # bench/ is on sys.path when a bench runs as a script
    ap.add_argument("--minutes", type=float, default=0.1 if smoke else 10.0,
                    help="length of the simulated flight (default 10; at least one mission, ~2 min)")
    ap.add_argument("--flight", help="replay this ULog instead of a simulated one")
    ap.add_argument("--rate", type=float, default=0.0, help="replay rate (default 0: as fast as the nodes keep up)")
    ap.add_argument("--out", default=str(REPO / "out" / "bench" / ("smoke" if smoke else "")),
                    help="work folder (default out/bench)")
    ap.add_argument("--strict", action="store_true", help="exit 1 below 20x real time or on any dropped message")
    args = ap.parse_args(argv)

    from twin_nodes.graph import run_graph
    from twin_nodes.vehicle.params import params_dir
    from twin_nodes.logs.recording import topic_counts

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.flight:
        flight = Path(args.flight)
    else:
        flight = out / f"sim_sih_{args.minutes:g}min.ulg"
        if not flight.exists():
            t0 = time.monotonic()
            facts = make_long_flight(flight, args.minutes)
            print(f"simulated {facts['duration_s']:.0f} s ({facts['missions']} missions) in "
                  f"{time.monotonic() - t0:.1f} s -> {flight}", flush=True)
    run_dir = out / "run"
    shutil.rmtree(run_dir, ignore_errors=True)
    # the bag beside the run folder: run_graph wants its parent to exist and the bag not to
    bag = out / "bag"
    shutil.rmtree(bag, ignore_errors=True)
    res = run_graph(flight, params_dir() / "px4_sih_quadx.yaml", rate=args.rate, run_dir=run_dir, bag=str(bag),
                    progress=True, timeout_s=3600)
    st = res.replay_stats
    counts = topic_counts(bag)
    drops = {t: n - counts.get(t, 0) for t, n in st["plan_counts"].items() if n != counts.get(t, 0)}
    n_twin = [counts.get(t, 0) for t in ("/twin/odom", "/twin/motors", "/twin/throttle", "/twin/imu")]
    if len(set(n_twin)) != 1:
        drops["/twin/*"] = max(n_twin) - min(n_twin)
    wall = float(st["wall_s"])
    total = sum(counts.values())
    row = {
        "flight": str(flight), "log_s": st["log_s"], "replay_wall_s": wall,
        "real_time_factor": st["real_time_factor"],
        "replay_messages": st["messages"], "replay_msgs_per_s": st["messages_per_s"],
        "graph_messages_recorded": total, "graph_msgs_per_s": total / wall,
        "twin_samples": n_twin[0], "dropped": drops, "end_to_end_wall_s": res.wall_s,
        "cpu_count": os.cpu_count(), "load_avg_1min": os.getloadavg()[0],
        "throttle_rmse": res.metrics.get("throttle_rmse"),
    }
    # the reference, same run: the same twin beside the same flight offline (no ROS, one process)
    from twin_nodes.twin.compare import compare_log, load_flight
    from twin_nodes.vehicle.params import shipped

    log = load_flight(flight)
    t0 = time.perf_counter()
    compare_log(log, shipped("px4_sih_quadx"))
    off_s = time.perf_counter() - t0
    off_rtf = float(st["log_s"]) / off_s
    row.update(offline_wall_s=off_s, offline_real_time_factor=off_rtf)
    (out / "bench_replay.json").write_text(json.dumps(row, indent=1))
    print(f"\nreplay -> twin -> metrics -> recorder, {st['log_s']:.0f} s of log ({flight.name})")
    print(f"  real-time factor      {st['real_time_factor']:8.1f} x   (target >= 20x on 2 cores)")
    print(f"  replay wall time      {wall:8.1f} s   (end to end incl. start-up/shut-down {res.wall_s:.1f} s)")
    print(f"  replayed messages     {st['messages']:8d}     {st['messages_per_s']:8.0f} msg/s")
    print(f"  graph messages        {total:8d}     {total / wall:8.0f} msg/s (all recorded to MCAP)")
    print(f"  dropped messages      {sum(drops.values()) if drops else 0:8d}     {drops or ''}")
    print(f"  offline twin          {off_rtf:8.1f} x   real time ({off_s:.1f} s; compare_log, one process, same flight)")
    print(f"  ratio graph / offline {st['real_time_factor'] / off_rtf:8.2f}     (real-time factors, this run)")
    print(f"  load average (1 min)  {os.getloadavg()[0]:8.2f}     on {os.cpu_count()} cores")
    print(f"  -> {out / 'bench_replay.json'}")
    if args.strict and (drops or st["real_time_factor"] < 20.0):
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
