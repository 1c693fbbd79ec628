"""A simulated fleet for demos and tests: several vehicles, each flight a PX4-like ULog with a
vehicle identity (``sys_uuid``, ``sys_name``) and a date (``time_ref_utc``) in its header.

Flown with the prove suite's generator (the built-in mission, the PX4-like controller,
the logging of :func:`twin_nodes.twin.simflight.record_to_topics`).  :func:`plan` lays out the
standard fleet: one vehicle whose motor weakens flight by flight, one that carries a payload on
some days, the rest healthy.
"""

from __future__ import annotations

import datetime as _dt
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: 2026-06-01 00:00 UTC: the fleet's first day
START_UTC = int(_dt.datetime(2026, 6, 1, 9, 0, tzinfo=_dt.timezone.utc).timestamp())


@dataclass(frozen=True)
class Flight:
    vehicle: str  # sys_name
    uuid: str
    day: int
    effect: str  # "none" or an effect name
    params: tuple  # ((key, value), ...)
    seed: int

    @property
    def name(self) -> str:
        return f"{self.vehicle}_d{self.day:02d}.ulg"

    @property
    def time_ref_utc(self) -> int:
        return START_UTC + self.day * 86400


def plan(n_vehicles: int = 5, flights_per_vehicle: int = 10, *, weak_motor: int = 3, eff_end: float = 0.8,
         payload_factor: float = 1.25, payload_every: int = 3, nominal_mass_kg: float = 1.0,
         seed0: int = 100) -> list[Flight]:
    """Vehicle 0 (``quad-00``): motor ``weak_motor`` efficiency 1.0 -> ``eff_end`` evenly over its
    flights; vehicle 1: mass x ``payload_factor`` on every ``payload_every``-th flight (from its
    2nd); the rest healthy.  One flight per vehicle per day."""
    out = []
    for v in range(n_vehicles):
        name, uuid = f"quad-{v:02d}", f"{0xA17E0000 + v:016x}"
        for k in range(flights_per_vehicle):
            seed = seed0 + 97 * v + k
            eff, prm = "none", ()
            if v == 0:
                e = 1.0 + (eff_end - 1.0) * k / max(flights_per_vehicle - 1, 1)
                if e < 0.999:
                    eff, prm = "motor_efficiency", (("motor", weak_motor), ("efficiency", round(e, 4)))
            elif v == 1 and k % payload_every == 1:
                eff, prm = "mass", (("mass", round(nominal_mass_kg * payload_factor, 4)),)
            out.append(Flight(name, uuid, k, eff, prm, seed))
    return out


def write_fleet_flight(folder: str | os.PathLike[str], f: Flight, params_file: str | os.PathLike[str]) -> Path:
    """Simulate one flight of the plan and write it (atomically) as ``folder/<vehicle>_dNN.ulg``."""
    from twin_nodes.twin.simflight import Hidden, record_to_topics, simulate_flight
    from twin_nodes.logs.ulog_write import write_px4_ulog
    from twin_nodes.vehicle.export_px4 import simulated_log_params
    from twin_nodes.vehicle.params import load_params

    vp = load_params(params_file)
    rec, battery, sp_hist = simulate_flight(vp, Hidden(f.effect, dict(f.params)), f.seed)
    topics = record_to_topics(rec, vp, battery, sp_hist, np.random.default_rng(f.seed + 7))
    params = simulated_log_params(vp)  # the rotor layout and hover command as PX4 logs them
    info = {"sys_name": f.vehicle, "sys_uuid": f.uuid, "ver_hw": "ROTORTWIN_SIM", "sim_vehicle": vp.name,
            "time_ref_utc": int(f.time_ref_utc)}
    out = Path(folder) / f.name
    out.parent.mkdir(parents=True, exist_ok=True)
    write_px4_ulog(str(out), topics, params, info)
    return out


def _write_task(args) -> str:
    folder, f, params_file = args
    if (Path(folder) / f.name).is_file():
        return str(Path(folder) / f.name)
    return str(write_fleet_flight(folder, f, params_file))


def write_fleet(folder: str | os.PathLike[str], flights: list[Flight], params_file: str | os.PathLike[str],
                workers: int = 2) -> list[Path]:
    """Write every flight of ``flights`` not already in ``folder`` (processes in parallel)."""
    from concurrent.futures import ProcessPoolExecutor

    from twin_nodes.fleet.run import check_workers

    check_workers(workers)
    jobs = [(str(folder), f, str(params_file)) for f in flights]
    if workers <= 1:
        return [Path(_write_task(j)) for j in jobs]
    with ProcessPoolExecutor(workers) as ex:
        return [Path(p) for p in ex.map(_write_task, jobs)]
