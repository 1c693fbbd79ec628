"""Pure helpers of the Foxglove view (no rclpy; foxglove is imported only where messages are built).

- :class:`VehicleOutline`: the arms and rotor discs of a vehicle, from its params (body FLU).
- :class:`Trail`: a decimated, bounded path of positions.
- :func:`errors_record`, :func:`motors_record`, :func:`status_record`: the JSON records of the
  ``/viz/errors``, ``/viz/motors`` and ``/viz/status`` channels, and their JSON schemas.
- :func:`scene_update`, :func:`frame_transforms`: the ``foxglove.SceneUpdate`` /
  ``foxglove.FrameTransforms`` messages of ``/viz/scene`` and ``/viz/transforms``.

Frames: ``odom`` is the world (ENU) frame of every ``/real`` and ``/twin`` pose; the two vehicles
are ``real/base_link`` and ``twin/base_link`` (both odometries say ``base_link``; the viewer needs
two names).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["VehicleOutline", "Trail", "REAL_FRAME", "TWIN_FRAME", "WORLD_FRAME", "COLORS",
           "errors_record", "motors_record", "status_record", "ERRORS_SCHEMA", "MOTORS_SCHEMA", "STATUS_SCHEMA",
           "scene_update", "frame_transforms", "vehicle_from_config"]

WORLD_FRAME = "odom"
REAL_FRAME = "real/base_link"
TWIN_FRAME = "twin/base_link"
#: RGBA of the two vehicles (real: blue, twin: orange) and the setpoint
COLORS = {"real": (0.16, 0.47, 0.96, 1.0), "twin": (1.0, 0.55, 0.1, 1.0), "setpoint": (0.2, 0.8, 0.3, 0.8)}


@dataclass(frozen=True)
class VehicleOutline:
    """Rotor positions (N, 3) [m, body FLU] and a rotor disc radius [m]."""

    rotors_flu_m: np.ndarray
    disc_radius_m: float

    @classmethod
    def from_params(cls, vp: Any) -> "VehicleOutline":
        pos = np.asarray(vp.rotors.positions_flu_m, dtype=float).reshape(-1, 3)
        return cls(pos, _disc_radius(pos))

    @classmethod
    def default(cls, n: int = 4, arm_m: float = 0.25) -> "VehicleOutline":
        """A quad X (PX4 order) with ``arm_m`` arms, when no params are known."""
        ang = np.radians([-45.0, 135.0, 45.0, -135.0])[:n] if n == 4 else np.linspace(0, 2 * np.pi, n, endpoint=False)
        pos = np.column_stack([arm_m * np.cos(ang), arm_m * np.sin(ang), np.zeros(len(ang))])
        return cls(pos, _disc_radius(pos))


def _disc_radius(pos: np.ndarray) -> float:
    """About half the distance to the nearest neighbouring rotor (discs just short of touching)."""
    if len(pos) < 2:
        return 0.12
    d = np.linalg.norm(pos[:, None, :2] - pos[None, :, :2], axis=-1)
    d[d == 0] = np.inf
    return float(np.clip(0.45 * d.min(), 0.03, 1.0))


def vehicle_from_config(config: Mapping[str, Any]) -> VehicleOutline | None:
    """The outline of the twin described by a ``/twin/config`` record (its params YAML), or None."""
    text = config.get("params_yaml")
    if not isinstance(text, str):
        return None
    try:
        from twin_nodes.base.yamlio import safe_load
        from twin_nodes.vehicle.params import from_ros_dict

        return VehicleOutline.from_params(from_ros_dict(safe_load(text), str(config.get("params_file", ""))))
    except Exception:  # a config we cannot read gives the default outline
        return None


@dataclass
class Trail:
    """Positions (ENU) kept when they moved ``spacing_m`` from the last kept one; at most ``max_points``
    (the oldest half is thinned by 2 when full, so a long flight keeps its whole shape)."""

    spacing_m: float = 0.1
    max_points: int = 4000
    points: list[tuple[float, float, float]] = field(default_factory=list)

    def add(self, p: Sequence[float]) -> bool:
        x, y, z = (float(v) for v in p[:3])
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            return False
        if self.points:
            lx, ly, lz = self.points[-1]
            if (x - lx) ** 2 + (y - ly) ** 2 + (z - lz) ** 2 < self.spacing_m ** 2:
                return False
        self.points.append((x, y, z))
        if len(self.points) > self.max_points:
            half = len(self.points) // 2
            self.points = self.points[:half:2] + self.points[half:]
        return True


# ----------------------------------------------------------------------------- JSON records

def _num(v: Any) -> float | None:
    """JSON has no NaN: unknown values are null."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


_NUM = {"type": ["number", "null"]}
_NUMS = {"type": "array", "items": _NUM}

ERRORS_SCHEMA: dict[str, Any] = {
    "title": "rotortwin.TwinErrors",
    "description": "rolling-window twin-minus-real errors of every channel (xy, z in m; throttle, motors in "
                   "fractions), from /twin_error/diagnostics; null = not known",
    "type": "object",
    "properties": {"t_s": _NUM, "link_lost": {"type": ["boolean", "null"]},
                   "channels": {"type": "object", "additionalProperties": {
                       "type": "object", "additionalProperties": _NUM}}},
}
MOTORS_SCHEMA: dict[str, Any] = {
    "title": "rotortwin.MotorCommands",
    "description": "motor commands 0..1 in PX4 order: the real vehicle's (latest), the twin's, and twin - real",
    "type": "object",
    "properties": {"t_s": _NUM, "real": _NUMS, "twin": _NUMS, "error": _NUMS},
}
STATUS_SCHEMA: dict[str, Any] = {
    "title": "rotortwin.Status",
    "description": "what the graph is doing: source, time, vehicle state, link, twin, final metrics",
    "type": "object",
    "properties": {"source": {"type": "string"}, "t_s": _NUM, "armed": {"type": ["boolean", "null"]},
                   "nav_state": _NUM, "landed": {"type": ["boolean", "null"]}, "link": {"type": "string"},
                   "link_lost": {"type": ["boolean", "null"]}, "twin": {"type": "object"},
                   "messages": {"type": "object"}, "final": {"type": ["object", "null"]}},
}


def errors_record(t_ns: int, values: Mapping[str, Mapping[str, float]], link_lost: bool | None) -> dict[str, Any]:
    """``/viz/errors``: ``{t_s, link_lost, channels: {channel: {stat: value}}}`` (stat keys as in
    ``/twin_error/diagnostics``: ``rmse_m``, ``p75`` ...)."""
    return {"t_s": t_ns / 1e9, "link_lost": link_lost,
            "channels": {ch: {k: _num(v) for k, v in stats.items()} for ch, stats in values.items()}}


def motors_record(t_ns: int, real: Sequence[float] | None, twin: Sequence[float]) -> dict[str, Any]:
    """``/viz/motors``: the latest real commands beside the twin's, and their difference."""
    tw = [float(v) for v in twin]
    re = [float(v) for v in real] if real is not None else [math.nan] * len(tw)
    n = max(len(tw), len(re))
    tw += [math.nan] * (n - len(tw))
    re += [math.nan] * (n - len(re))
    return {"t_s": t_ns / 1e9, "real": [_num(v) for v in re], "twin": [_num(v) for v in tw],
            "error": [_num(a - b) for a, b in zip(tw, re)]}


def status_record(*, source: str, t_ns: int | None, status: Sequence[float] | None, link: str,
                  link_lost: bool | None, twin: Mapping[str, Any], messages: Mapping[str, int],
                  final: Mapping[str, Any] | None) -> dict[str, Any]:
    """``/viz/status``: one record saying what is going on (2 Hz)."""
    armed = nav = landed = None
    if status is not None and len(status) >= 3:
        a, n, l_ = (float(v) for v in status[:3])
        armed = None if not math.isfinite(a) or a == 255 else a > 0.5
        nav = None if not math.isfinite(n) or n == 255 else n
        landed = None if not math.isfinite(l_) or l_ == 255 else l_ > 0.5
    return {"source": source, "t_s": None if t_ns is None else t_ns / 1e9, "armed": armed, "nav_state": nav,
            "landed": landed, "link": link, "link_lost": link_lost, "twin": dict(twin),
            "messages": dict(messages), "final": dict(final) if final is not None else None}


# ----------------------------------------------------------------------------- foxglove messages

def _ts(t_ns: int) -> Any:
    from foxglove.messages import Timestamp

    t_ns = max(int(t_ns), 0)
    return Timestamp(t_ns // 1_000_000_000, t_ns % 1_000_000_000)


def _color(rgba: Sequence[float]) -> Any:
    from foxglove.messages import Color

    return Color(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]), a=float(rgba[3]))


def _pose(p: Sequence[float] = (0.0, 0.0, 0.0), q_wxyz: Sequence[float] = (1.0, 0.0, 0.0, 0.0)) -> Any:
    from foxglove.messages import Pose, Quaternion, Vector3

    return Pose(position=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=Quaternion(w=float(q_wxyz[0]), x=float(q_wxyz[1]), y=float(q_wxyz[2]), z=float(q_wxyz[3])))


def frame_transforms(poses: Mapping[str, tuple[int, Sequence[float], Sequence[float]]]) -> Any:
    """``foxglove.FrameTransforms``: ``odom`` -> ``<name>/base_link`` for each ``name: (t_ns, p_enu,
    q_wxyz)`` (FLU -> ENU)."""
    from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Vector3

    out = []
    for name, (t_ns, p, q) in poses.items():
        out.append(FrameTransform(timestamp=_ts(t_ns), parent_frame_id=WORLD_FRAME, child_frame_id=f"{name}/base_link",
                                  translation=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                                  rotation=Quaternion(w=float(q[0]), x=float(q[1]), y=float(q[2]), z=float(q[3]))))
    return FrameTransforms(transforms=out)


def _vehicle_entity(name: str, frame: str, outline: VehicleOutline, t_ns: int) -> Any:
    from foxglove.messages import (
        CubePrimitive,
        CylinderPrimitive,
        LinePrimitive,
        LinePrimitiveLineType,
        Point3,
        SceneEntity,
        TextPrimitive,
        Vector3,
    )

    col = COLORS[name]
    disc = (col[0], col[1], col[2], 0.45)
    arms = []
    for r in outline.rotors_flu_m:
        arms += [Point3(x=0.0, y=0.0, z=0.0), Point3(x=float(r[0]), y=float(r[1]), z=float(r[2]))]
    d = 2.0 * outline.disc_radius_m
    reach = float(np.max(np.linalg.norm(outline.rotors_flu_m, axis=1))) if len(outline.rotors_flu_m) else 0.3
    return SceneEntity(
        timestamp=_ts(t_ns), frame_id=frame, id=f"{name}_vehicle", frame_locked=True,
        lines=[LinePrimitive(type=LinePrimitiveLineType.LineList, pose=_pose(), thickness=4.0, scale_invariant=True,
                             points=arms, color=_color(col))],
        cylinders=[CylinderPrimitive(pose=_pose(r), size=Vector3(x=d, y=d, z=0.01), bottom_scale=1.0, top_scale=1.0,
                                     color=_color(disc)) for r in outline.rotors_flu_m],
        cubes=[CubePrimitive(pose=_pose((0.3 * reach, 0.0, 0.0)), size=Vector3(x=0.3 * reach, y=0.05, z=0.05),
                             color=_color(col))],  # the nose
        texts=[TextPrimitive(pose=_pose((0.0, 0.0, 0.3 + 0.2 * reach)), billboard=True, font_size=14.0,
                             scale_invariant=True, color=_color(col), text=name)])


def _path_entity(name: str, trail: Trail, t_ns: int) -> Any:
    from foxglove.messages import LinePrimitive, LinePrimitiveLineType, Point3, SceneEntity

    pts = [Point3(x=p[0], y=p[1], z=p[2]) for p in trail.points]
    return SceneEntity(timestamp=_ts(t_ns), frame_id=WORLD_FRAME, id=f"{name}_path",
                       lines=[LinePrimitive(type=LinePrimitiveLineType.LineStrip, pose=_pose(), thickness=2.0,
                                            scale_invariant=True, points=pts, color=_color(COLORS[name]))])


def scene_update(t_ns: int, outlines: Mapping[str, VehicleOutline], trails: Mapping[str, Trail],
                 setpoint_enu: Sequence[float] | None = None) -> Any:
    """``foxglove.SceneUpdate``: each vehicle's outline (locked to its frame), each path (in ``odom``)
    and the position setpoint as a small sphere."""
    from foxglove.messages import SceneEntity, SceneUpdate, SpherePrimitive, Vector3

    frames = {"real": REAL_FRAME, "twin": TWIN_FRAME}
    ents = [_vehicle_entity(n, frames[n], o, t_ns) for n, o in outlines.items()]
    ents += [_path_entity(n, tr, t_ns) for n, tr in trails.items() if len(tr.points) >= 2]
    if setpoint_enu is not None and all(math.isfinite(float(v)) for v in setpoint_enu[:3]):
        ents.append(SceneEntity(timestamp=_ts(t_ns), frame_id=WORLD_FRAME, id="setpoint",
                                spheres=[SpherePrimitive(pose=_pose(setpoint_enu), size=Vector3(x=0.4, y=0.4, z=0.4),
                                                         color=_color(COLORS["setpoint"]))]))
    return SceneUpdate(entities=ents)
