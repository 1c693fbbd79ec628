"""A real PX4 >= 1.11 flight rewritten in PX4 1.8's topic layout, for the old-layout tests.

No public PX4 1.8-1.9 multirotor flight log was found (docs/real_logs.md, "Older PX4 topic sets"),
so the loader's 1.8 route is checked on a real flight re-expressed as PX4 1.8 logged it: the same
samples, only the layout changed, as PX4 1.8's ``logger.cpp`` and ``msg/*.msg`` define it:

- ``vehicle_angular_velocity`` removed; ``vehicle_attitude`` gains ``rollspeed/pitchspeed/yawspeed``
  (the angular velocity at the attitude's stamps);
- ``trajectory_setpoint`` and the newer ``vehicle_local_position_setpoint`` removed; PX4 1.8's
  ``vehicle_local_position_setpoint`` written from them the way 1.8's ``mc_pos_control`` filled it:
  ``x,y,z`` the position setpoint, ``vx,vy,vz`` the velocity loop's input
  ``(x,y,z - position) * MPC_XY_P/MPC_Z_P + feed-forward``, ``acc_x..`` thrust x g;
- ``vehicle_thrust_setpoint``/``vehicle_torque_setpoint`` removed (``actuator_controls_0`` stays);
- ``vehicle_attitude_setpoint``/``vehicle_rates_setpoint``: ``thrust_body[3]`` -> scalar ``thrust``;
- parameters ``PWM_MAIN_MIN/MAX`` -> ``PWM_MIN/MAX``, per-channel ``PWM_MAIN_MINn/MAXn`` removed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pyulog import ULog

from twin_nodes.logs import time_sync
from twin_nodes.logs.ulog_io import TOPICS
from twin_nodes.logs.ulog_write import write_px4_ulog

_DROP = ("vehicle_angular_velocity", "trajectory_setpoint", "vehicle_local_position_setpoint",
         "vehicle_thrust_setpoint", "vehicle_torque_setpoint")


def _fields(d) -> dict[str, np.ndarray]:
    return {k: np.asarray(v) for k, v in d.data.items()}


def to_px4_18_layout(src: Path, dst: Path) -> Path:
    """Write ``src`` (a PX4 >= 1.11 log with vehicle_angular_velocity and trajectory_setpoint) to
    ``dst`` in PX4 1.8's layout (module docstring)."""
    u = ULog(str(src), message_name_filter_list=list(TOPICS))
    data = {(d.name, d.multi_id): d for d in u.data_list}
    p = {k: v for k, v in u.initial_parameters.items()}
    av = data[("vehicle_angular_velocity", 0)].data
    ts = data[("trajectory_setpoint", 0)].data
    lp = data[("vehicle_local_position", 0)].data
    topics: dict[str, dict[str, np.ndarray]] = {}
    for (name, mid), d in data.items():
        if name in _DROP:
            continue
        f = _fields(d)
        if name == "vehicle_attitude":
            w = time_sync.interp_to(av["timestamp"] * 1e-6, np.column_stack(
                [av[f"xyz[{i}]"] for i in range(3)]), f["timestamp"] * 1e-6, kind="linear")
            for i, k in enumerate(("rollspeed", "pitchspeed", "yawspeed")):
                f[k] = w[:, i].astype(np.float32)
        if name in ("vehicle_attitude_setpoint", "vehicle_rates_setpoint") and "thrust_body[2]" in f:
            f["thrust"] = (-f.pop("thrust_body[2]")).astype(np.float32)
            f.pop("thrust_body[0]"), f.pop("thrust_body[1]")
        topics[f"{name}:{mid}" if mid else name] = f
    t = ts["timestamp"]
    sp = np.column_stack([ts[f"position[{i}]"] for i in range(3)]) if "position[0]" in ts else \
        np.column_stack([ts[k] for k in ("x", "y", "z")])
    ff = np.column_stack([ts[f"velocity[{i}]"] for i in range(3)]) if "velocity[0]" in ts else \
        np.column_stack([ts[k] for k in ("vx", "vy", "vz")])
    pos = time_sync.interp_to(lp["timestamp"] * 1e-6, np.column_stack([lp["x"], lp["y"], lp["z"]]),
                              t * 1e-6, kind="linear")
    gains = np.array([p["MPC_XY_P"], p["MPC_XY_P"], p["MPC_Z_P"]])
    vel_sp = (sp - pos) * gains + np.nan_to_num(ff)
    lpsp = {"timestamp": t, "x": sp[:, 0], "y": sp[:, 1], "z": sp[:, 2],
            "yaw": ts["yaw"], "yawspeed": ts["yawspeed"],
            "vx": vel_sp[:, 0], "vy": vel_sp[:, 1], "vz": vel_sp[:, 2],
            "acc_x": np.zeros(t.size), "acc_y": np.zeros(t.size), "acc_z": np.full(t.size, -6.0)}
    topics["vehicle_local_position_setpoint"] = {k: np.asarray(v, dtype=np.float32) if k != "timestamp"
                                                 else np.asarray(v) for k, v in lpsp.items()}
    for k in ("MIN", "MAX"):
        p[f"PWM_{k}"] = p.pop(f"PWM_MAIN_{k}")
        for c in range(1, 17):
            p.pop(f"PWM_MAIN_{k}{c}", None)
    p.pop("SYS_CTRL_ALLOC", None)
    info = {k: v for k, v in u.msg_info_dict.items() if isinstance(v, (str, int))}
    start = int(u.start_timestamp)
    for name, f in topics.items():  # as the reader does: a state before the start is the state at it
        ts0 = np.asarray(f["timestamp"]).astype(np.int64)
        if name in ("vehicle_status", "vehicle_land_detected"):
            f["timestamp"] = np.maximum(ts0, start).astype(np.uint64)
        elif (ts0 < start).any():
            topics[name] = {k: np.asarray(v)[ts0 >= start] for k, v in f.items()}
    return write_px4_ulog(dst, topics, p, info, start_us=start)
