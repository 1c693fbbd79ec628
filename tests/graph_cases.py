"""Flight logs for the graph and regression tests, cut from a real PX4 SIH log.

``cut_ulog(src, dst, t1_s=..., drop=(...), gap=(a, b))`` rewrites a ULog with
:func:`twin_nodes.logs.ulog_write.write_px4_ulog`: only the topics the loader reads,
the samples up to ``t1_s`` seconds after the log start, without the topics in
``drop`` and without any sample in ``[a, b)`` seconds (a logger dropout in every
topic).  The parameters and info of the source are kept, so ``SYS_AUTOSTART``
still picks the shipped params.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np

from twin_nodes.logs.ulog_write import write_px4_ulog

#: what read_ulog reads (a smaller file than copying every topic)
FLIGHT_TOPICS = ("vehicle_local_position", "vehicle_attitude", "vehicle_angular_velocity", "actuator_motors",
                 "actuator_outputs", "vehicle_thrust_setpoint", "vehicle_torque_setpoint", "battery_status",
                 "sensor_combined", "trajectory_setpoint", "vehicle_status", "vehicle_land_detected")


def cut_ulog(src: str | Path, dst: str | Path, t1_s: float | None = None, drop: tuple[str, ...] = (),
             gap: tuple[float, float] | None = None) -> Path:
    from pyulog import ULog

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        u = ULog(str(src))
    start = min(int(u.start_timestamp), min(int(d.data["timestamp"][0]) for d in u.data_list
                                            if d.name in FLIGHT_TOPICS and len(d.data["timestamp"])))
    topics: dict[str, dict[str, np.ndarray]] = {}
    for d in u.data_list:
        if d.name not in FLIGHT_TOPICS or d.name in drop:
            continue
        t = np.asarray(d.data["timestamp"], dtype=np.int64)
        rel = (t - start) * 1e-6
        keep = np.ones(len(t), bool)
        if t1_s is not None:
            keep &= rel <= t1_s
        if gap is not None:
            keep &= ~((rel >= gap[0]) & (rel < gap[1]))
        key = d.name if d.multi_id == 0 else f"{d.name}:{d.multi_id}"
        topics[key] = {k: np.asarray(v)[keep] for k, v in d.data.items() if not k.startswith("_padding")}
    info = {k: v for k, v in u.msg_info_dict.items()
            if isinstance(v, str) or (isinstance(v, int) and not isinstance(v, bool) and -2**31 <= v < 2**32)}
    return write_px4_ulog(dst, topics, params=dict(u.initial_parameters), info=info, start_us=start)


SIH_TRIANGLE = "px4sih_default_triangle.ulg"
_CACHE: dict[str, Path] = {}


def short_flight(folder: Path) -> Path:
    """The first 30 s of the PX4 SIH triangle flight (take-off and the start of the first leg:
    21 s airborne), written once per test session."""
    from conftest import shared_log

    if "short" not in _CACHE:
        _CACHE["short"] = cut_ulog(shared_log("sitl", SIH_TRIANGLE), Path(folder) / "sih_short.ulg", t1_s=30.0)
    return _CACHE["short"]


def recorded_baseline(folder: Path) -> Path:
    """A baseline bag of :func:`short_flight` with params/px4_sih_quadx.yaml, recorded once per session by
    ``rotortwin compare --mcap`` (the node graph); callers copy it before changing it."""
    import subprocess
    import sys

    from twin_nodes.vehicle.params import params_dir

    if "baseline" not in _CACHE:
        flight = short_flight(folder)
        bag = Path(folder) / "baseline"
        r = subprocess.run([sys.executable, "-m", "twin_nodes", "compare", str(flight), "--params",
                            str(params_dir() / "px4_sih_quadx.yaml"), "--mcap", str(bag), "--quiet"],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-3000:]
        _CACHE["baseline"] = bag
    return _CACHE["baseline"]


def params_with_mass(folder: Path, mass_kg: float) -> Path:
    """A copy of params/px4_sih_quadx.yaml with ``vehicle.mass_kg`` changed."""
    import re

    from twin_nodes.vehicle.params import params_dir

    text = (params_dir() / "px4_sih_quadx.yaml").read_text(encoding="utf-8")
    new, n = re.subn(r"(?m)^(\s*mass_kg:\s*)[0-9.eE+-]+", rf"\g<1>{mass_kg}", text)
    assert n == 1, "px4_sih_quadx.yaml: expected one vehicle.mass_kg"
    out = Path(folder) / f"px4_sih_quadx_mass{mass_kg:g}.yaml"
    out.write_text(new, encoding="utf-8")
    return out
