"""Mission plan files and their upload/start with MAVSDK 4.x (the in-process ctypes API).

A plan file is YAML::

    mission:
      name: triangle
      speed_m_s: 6.0              # cruise speed of every leg
      acceptance_radius_m: 2.0
      fly_through: true           # don't stop at the waypoints
      rtl_after: true             # return to launch after the last item
      home: [47.397743, 8.545594] # optional [lat_deg, lon_deg]; default: the vehicle's home
      waypoints:                  # [north_m, east_m, alt_m above home], relative to home
        - [20.0, 0.0, 15.0]
        - {north_m: 80.0, east_m: 0.0, alt_m: 15.0, speed_m_s: 4.0}   # per-item overrides
        - {north_m: 80.0, east_m: 0.0, alt_m: 15.0, yaw_deg: 90.0, fly_through: false}  # heading

Waypoints are relative to home (the take-off point), as in
``../shared/flightlogs/sitl/MANIFEST.md``; they become MAVSDK ``MissionItem``\\ s
with absolute latitude/longitude through PX4's own map projection
(:func:`twin_nodes.mavlink.sensors.reproject_ne_to_latlon`) and
``relative_altitude_m`` = ``alt_m``.  Yaw is left to PX4 (NaN: ``MPC_YAW_MODE``) unless
an item gives ``yaw_deg`` (its commanded heading, degrees clockwise from north, -360..360;
MAVLink ``param4`` of the NAV_WAYPOINT; PX4 accepts the item once the heading error is below
``MIS_YAW_ERR``); a second item at the same position with another ``yaw_deg`` turns in place.
PX4 inserts the take-off to the first item's altitude itself.

Without ``home`` in the file the vehicle's home position is read over the link
at upload; with it, the upload refuses a plan whose home is more than
``max_home_offset_m`` (1 km) from the vehicle's, so a plan written for the SIH
origin is never flown somewhere else by accident.

Bad files raise :class:`~twin_nodes.base.errors.ParamsError` with a one-line
``<file>: <field>: <what was expected>`` message.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping


from twin_nodes.base.errors import ParamsError, TwinError
from twin_nodes.mavlink.sensors import project_latlon_to_ne, reproject_ne_to_latlon

__all__ = [
    "Waypoint", "MissionPlanFile", "load_plan", "plan_from_mapping", "plan_to_mission_items",
    "normalise_mavsdk_url", "upload_plan", "start_mission", "wait_flight_done", "DEFAULT_URL",
]

DEFAULT_URL = "udpin://0.0.0.0:14540"  # PX4 SITL sends to offboard APIs on UDP 14540

_PLAN_KEYS = {"name", "speed_m_s", "acceptance_radius_m", "fly_through", "rtl_after", "home", "waypoints",
              "notes"}
_WP_KEYS = {"north_m", "east_m", "alt_m", "speed_m_s", "acceptance_radius_m", "fly_through", "yaw_deg"}


@dataclass(frozen=True)
class Waypoint:
    north_m: float
    east_m: float
    alt_m: float                # above home
    speed_m_s: float
    acceptance_radius_m: float
    fly_through: bool
    yaw_deg: float | None = None  # commanded heading [deg from north, clockwise]; None: left to PX4


@dataclass(frozen=True)
class MissionPlanFile:
    name: str
    waypoints: tuple[Waypoint, ...]
    rtl_after: bool
    home_lat_deg: float | None = None
    home_lon_deg: float | None = None
    source: str = "<memory>"

    @property
    def has_home(self) -> bool:
        return self.home_lat_deg is not None

    def length_m(self) -> float:
        """Path length from the first to the last waypoint (3D) [m]."""
        total = 0.0
        for a, b in zip(self.waypoints[:-1], self.waypoints[1:]):
            total += math.dist((a.north_m, a.east_m, a.alt_m), (b.north_m, b.east_m, b.alt_m))
        return total


# --------------------------------------------------------------------------- parsing


def _num(path: str, key: str, v: Any, *, gt: float | None = None, ge: float | None = None,
         le: float | None = None) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise ParamsError(path, key, f"expected a finite number, got {v!r}")
    v = float(v)
    if gt is not None and not v > gt:
        raise ParamsError(path, key, f"expected > {gt:g}, got {v:g}")
    if ge is not None and not v >= ge:
        raise ParamsError(path, key, f"expected >= {ge:g}, got {v:g}")
    if le is not None and not v <= le:
        raise ParamsError(path, key, f"expected <= {le:g}, got {v:g}")
    return v


def _bool(path: str, key: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise ParamsError(path, key, f"expected true or false, got {v!r}")
    return v


def plan_from_mapping(doc: Any, path: str = "<memory>") -> MissionPlanFile:
    """Validate a parsed plan document (``{mission: {...}}``)."""
    if not isinstance(doc, Mapping) or "mission" not in doc:
        raise ParamsError(path, "mission", "missing: expected a top-level 'mission:' mapping")
    extra = set(doc) - {"mission"}
    if extra:
        raise ParamsError(path, sorted(extra)[0], "unknown top-level key (only 'mission' is allowed)")
    m = doc["mission"]
    if not isinstance(m, Mapping):
        raise ParamsError(path, "mission", f"expected a mapping, got {type(m).__name__}")
    for k in m:
        if k not in _PLAN_KEYS:
            raise ParamsError(path, f"mission.{k}", f"unknown key (allowed: {', '.join(sorted(_PLAN_KEYS))})")
    name = m.get("name", Path(path).stem.split(".")[0])
    if not isinstance(name, str) or not name:
        raise ParamsError(path, "mission.name", f"expected a non-empty string, got {name!r}")
    for k in ("speed_m_s", "acceptance_radius_m"):
        if k not in m:
            raise ParamsError(path, f"mission.{k}", "missing (a number)")
    speed = _num(path, "mission.speed_m_s", m["speed_m_s"], gt=0.0, le=30.0)
    radius = _num(path, "mission.acceptance_radius_m", m["acceptance_radius_m"], gt=0.0, le=100.0)
    fly_through = _bool(path, "mission.fly_through", m.get("fly_through", True))
    rtl_after = _bool(path, "mission.rtl_after", m.get("rtl_after", True))
    home_lat = home_lon = None
    if m.get("home") is not None:
        h = m["home"]
        if not isinstance(h, (list, tuple)) or len(h) != 2:
            raise ParamsError(path, "mission.home", f"expected [lat_deg, lon_deg], got {h!r}")
        home_lat = _num(path, "mission.home[0]", h[0], gt=-90.0)
        if home_lat >= 90.0:
            raise ParamsError(path, "mission.home[0]", f"expected a latitude < 90, got {home_lat:g}")
        home_lon = _num(path, "mission.home[1]", h[1], ge=-180.0, le=180.0)
    wps = m.get("waypoints")
    if not isinstance(wps, (list, tuple)) or not wps:
        raise ParamsError(path, "mission.waypoints",
                          f"expected a non-empty list of [north_m, east_m, alt_m], got {wps!r}")
    out = []
    for i, wp in enumerate(wps):
        key = f"mission.waypoints[{i}]"
        if isinstance(wp, Mapping):
            for k in wp:
                if k not in _WP_KEYS:
                    raise ParamsError(path, f"{key}.{k}", f"unknown key (allowed: {', '.join(sorted(_WP_KEYS))})")
            for k in ("north_m", "east_m", "alt_m"):
                if k not in wp:
                    raise ParamsError(path, f"{key}.{k}", "missing (a number)")
            n = _num(path, f"{key}.north_m", wp["north_m"])
            e = _num(path, f"{key}.east_m", wp["east_m"])
            a = _num(path, f"{key}.alt_m", wp["alt_m"], gt=0.0, le=1000.0)
            sp = _num(path, f"{key}.speed_m_s", wp.get("speed_m_s", speed), gt=0.0, le=30.0)
            rad = _num(path, f"{key}.acceptance_radius_m", wp.get("acceptance_radius_m", radius), gt=0.0, le=100.0)
            ft = _bool(path, f"{key}.fly_through", wp.get("fly_through", fly_through))
            yaw = None if wp.get("yaw_deg") is None else _num(path, f"{key}.yaw_deg", wp["yaw_deg"],
                                                              ge=-360.0, le=360.0)
        elif isinstance(wp, (list, tuple)):
            if len(wp) != 3:
                raise ParamsError(path, key, f"expected [north_m, east_m, alt_m] (3 numbers), got {list(wp)!r}")
            n = _num(path, f"{key}[0]", wp[0])
            e = _num(path, f"{key}[1]", wp[1])
            a = _num(path, f"{key}[2]", wp[2], gt=0.0, le=1000.0)
            sp, rad, ft, yaw = speed, radius, fly_through, None
        else:
            raise ParamsError(path, key, f"expected [north_m, east_m, alt_m] or a mapping, got {wp!r}")
        if math.hypot(n, e) > 50_000.0:
            raise ParamsError(path, key, f"expected within 50 km of home, got {math.hypot(n, e):.0f} m")
        out.append(Waypoint(n, e, a, sp, rad, ft, yaw))
    return MissionPlanFile(name=name, waypoints=tuple(out), rtl_after=rtl_after,
                           home_lat_deg=home_lat, home_lon_deg=home_lon, source=path)


def load_plan(path: str | Path) -> MissionPlanFile:
    """Read and validate a plan file."""
    from twin_nodes.base.yamlio import read_yaml_file  # regular UTF-8 file, size-limited, one-line errors

    p = str(path)
    doc = read_yaml_file(p, "mission plan YAML file")
    return plan_from_mapping(doc, p)


def plan_to_mission_items(plan: MissionPlanFile, home_lat_deg: float, home_lon_deg: float) -> list:
    """MAVSDK ``MissionItem`` objects for the plan flown from home (lat, lon) [deg]."""
    from mavsdk.plugins.mission import MissionItem

    items = []
    for wp in plan.waypoints:
        lat, lon = reproject_ne_to_latlon(wp.north_m, wp.east_m, home_lat_deg, home_lon_deg)
        items.append(MissionItem(
            latitude_deg=float(lat), longitude_deg=float(lon), relative_altitude_m=float(wp.alt_m),
            speed_m_s=float(wp.speed_m_s), is_fly_through=bool(wp.fly_through),
            acceptance_radius_m=float(wp.acceptance_radius_m),
            yaw_deg=float("nan") if wp.yaw_deg is None else float(wp.yaw_deg),
            gimbal_pitch_deg=float("nan"), gimbal_yaw_deg=float("nan"), loiter_time_s=float("nan"),
            camera_action=MissionItem.CameraAction.NONE, vehicle_action=MissionItem.VehicleAction.NONE))
    return items


# --------------------------------------------------------------------------- MAVSDK


def normalise_mavsdk_url(url: str) -> str:
    """MAVSDK 1.x spellings -> MAVSDK 2+/4.x ones.

    ``udp://:14540`` / ``udp://0.0.0.0:14540`` -> ``udpin://0.0.0.0:14540``;
    ``tcp://host:port`` -> ``tcpout://host:port``; ``serial://`` and the new
    ``udpin://``, ``udpout://``, ``tcpin://``, ``tcpout://`` pass unchanged."""
    u = url.strip()
    if "://" not in u:
        raise TwinError(f"{url}: not a MAVSDK connection URL (expected e.g. udpin://0.0.0.0:14540)")
    scheme, rest = u.split("://", 1)
    if scheme == "udp":
        scheme = "udpin"
    elif scheme == "tcp":
        scheme = "tcpout"
    if scheme in ("udpin", "tcpin") and rest.startswith(":"):
        rest = "0.0.0.0" + rest
    return f"{scheme}://{rest}"


class _Link:
    """A MAVSDK instance connected to the first autopilot on ``url``."""

    def __init__(self, url: str, timeout_s: float):
        from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk

        self.url = normalise_mavsdk_url(url)
        self.mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        res = self.mavsdk.add_any_connection(self.url)
        if res != ConnectionResult.SUCCESS:
            self.close()
            raise TwinError(f"{self.url}: cannot open the connection ({res.name})")
        self.system = self.mavsdk.first_autopilot(timeout_s)
        if self.system is None:
            self.close()
            raise TwinError(f"{self.url}: no autopilot heartbeat within {timeout_s:g} s")

    def close(self) -> None:
        self.mavsdk.destroy()


def _vehicle_home(system: Any, timeout_s: float) -> tuple[float, float] | None:
    from mavsdk.plugins.telemetry import Telemetry

    tel = Telemetry(system)
    deadline = time.monotonic() + timeout_s
    while True:
        home = tel.home()
        if math.isfinite(home.latitude_deg) and math.isfinite(home.longitude_deg) and (
                home.latitude_deg != 0.0 or home.longitude_deg != 0.0):
            return float(home.latitude_deg), float(home.longitude_deg)
        if time.monotonic() > deadline:
            return None
        time.sleep(0.2)


def _wait_current_item(mission: Any, index: int, timeout_s: float) -> bool:
    """True once the vehicle reports ``index`` as its current mission item (MISSION_CURRENT)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if int(mission.mission_progress().current) == index:
                return True
        except Exception:  # no progress known yet
            pass
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)


def upload_plan(plan: MissionPlanFile, url: str = DEFAULT_URL, *, connect_timeout_s: float = 10.0,
                home_timeout_s: float = 10.0, max_home_offset_m: float = 1000.0,
                current_timeout_s: float = 2.0) -> dict[str, Any]:
    """Connect, resolve home, upload the plan and the RTL-after flag and set the current item to 0
    (so the mission starts from its beginning even if an identical one was flown before); returns
    a summary (``current_item_confirmed``: the vehicle reported item 0 as current within
    ``current_timeout_s``)."""
    from mavsdk.plugins.mission import Mission, MissionError, MissionPlan

    link = _Link(url, connect_timeout_s)
    try:
        vehicle_home = _vehicle_home(link.system, home_timeout_s)
        if plan.has_home:
            home = (plan.home_lat_deg, plan.home_lon_deg)
            if vehicle_home is not None:
                n, e = project_latlon_to_ne(home[0], home[1], *vehicle_home)
                off = math.hypot(float(n), float(e))
                if off > max_home_offset_m:
                    raise TwinError(f"{plan.source}: mission.home: is {off:.0f} m from the vehicle's home "
                                    f"{vehicle_home[0]:.6f}, {vehicle_home[1]:.6f} (limit {max_home_offset_m:g} m)")
        elif vehicle_home is not None:
            home = vehicle_home
        else:
            raise TwinError(f"{link.url}: the vehicle reported no home position within {home_timeout_s:g} s "
                            f"and {plan.source} has no mission.home")
        items = plan_to_mission_items(plan, *home)
        mission = Mission(link.system)
        try:
            mission.set_return_to_launch_after_mission(plan.rtl_after)
            mission.upload_mission(MissionPlan(items))
            # PX4 keeps the mission's current index in dataman (across reboots) and keeps it for an
            # identical upload: a mission flown to its end would "finish" at once when started
            # again.  Restart it from item 0 -- in this MAVSDK instance, which knows the uploaded
            # items (a fresh instance, e.g. in start_mission, answers ERROR).
            mission.set_current_mission_item(0)
        except MissionError as exc:
            raise TwinError(f"{link.url}: mission upload failed: {exc}") from None
        confirmed = _wait_current_item(mission, 0, current_timeout_s)
        return {"url": link.url, "name": plan.name, "items": len(items), "home": home,
                "rtl_after": plan.rtl_after, "length_m": plan.length_m(), "current_item": 0,
                "current_item_confirmed": confirmed}
    finally:
        link.close()


def start_mission(url: str = DEFAULT_URL, *, arm: bool = True, connect_timeout_s: float = 10.0) -> dict[str, Any]:
    """Connect, arm (unless ``arm=False``) and start the uploaded mission."""
    from mavsdk.plugins.action import Action, ActionError
    from mavsdk.plugins.mission import Mission, MissionError

    link = _Link(url, connect_timeout_s)
    try:
        if arm:
            try:
                Action(link.system).arm()
            except ActionError as exc:
                raise TwinError(f"{link.url}: arming refused: {exc}") from None
        try:
            Mission(link.system).start_mission()
        except MissionError as exc:
            raise TwinError(f"{link.url}: mission start failed: {exc}") from None
        return {"url": link.url, "armed": arm}
    finally:
        link.close()


def wait_flight_done(url: str = DEFAULT_URL, *, connect_timeout_s: float = 10.0, arm_timeout_s: float = 60.0,
                     timeout_s: float = 900.0) -> dict[str, Any]:
    """Connect, wait until the vehicle is armed (``arm_timeout_s``), then until it is disarmed again
    (``timeout_s``): a mission with RTL flown and landed (PX4 disarms after landing).  Returns the
    flight time; TwinError if either does not happen in time."""
    from mavsdk.plugins.telemetry import Telemetry

    link = _Link(url, connect_timeout_s)
    try:
        tel = Telemetry(link.system)
        t0 = time.monotonic()
        while not tel.armed():
            if time.monotonic() - t0 > arm_timeout_s:
                raise TwinError(f"{link.url}: the vehicle did not arm within {arm_timeout_s:g} s")
            time.sleep(0.2)
        t_armed = time.monotonic()
        while tel.armed():
            if time.monotonic() - t_armed > timeout_s:
                raise TwinError(f"{link.url}: still armed after {timeout_s:g} s")
            time.sleep(0.5)
        return {"url": link.url, "flight_s": time.monotonic() - t_armed}
    finally:
        link.close()
