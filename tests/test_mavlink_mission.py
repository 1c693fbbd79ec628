"""Mission plans: parsing, validation messages, MAVSDK MissionItems, and upload/start against a
pymavlink fake autopilot over UDP loopback (MAVSDK 4.x, in process)."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from twin_nodes.base.errors import ParamsError, TwinError
from twin_nodes.mavlink.mission import (
    load_plan,
    normalise_mavsdk_url,
    plan_from_mapping,
    plan_to_mission_items,
    start_mission,
    upload_plan,
)
from twin_nodes.mavlink.sensors import project_latlon_to_ne

REPO = Path(__file__).resolve().parents[1]
HOME = (47.397743, 8.545594)
# ../shared/flightlogs/sitl/MANIFEST.md, "Missions"
M1 = [[20, 0, 15], [80, 0, 15], [50, 51.96, 15], [20, 0, 15]]
M2 = [[10, 0, 10], [60, 0, 10], [60, 15, 25], [10, 15, 25], [10, 30, 10], [60, 30, 10], [60, 45, 25],
      [10, 45, 25]]


def test_shipped_plans_are_the_manifest_missions():
    tri = load_plan(REPO / "missions" / "triangle.plan.yaml")
    grid = load_plan(REPO / "missions" / "grid.plan.yaml")
    assert [[w.north_m, w.east_m, w.alt_m] for w in tri.waypoints] == M1
    assert [[w.north_m, w.east_m, w.alt_m] for w in grid.waypoints] == M2
    assert {w.speed_m_s for w in tri.waypoints} == {6.0} and {w.speed_m_s for w in grid.waypoints} == {7.0}
    for plan in (tri, grid):
        assert plan.rtl_after and not plan.has_home
        assert all(w.fly_through and w.acceptance_radius_m == 2.0 for w in plan.waypoints)
    # triangle: 60 m sides (3 legs, the last closes it)
    assert tri.length_m() == pytest.approx(180.0, abs=0.01)
    assert {w.alt_m for w in tri.waypoints} == {15.0} and {w.alt_m for w in grid.waypoints} == {10.0, 25.0}


def test_mission_items_from_plan():
    plan = plan_from_mapping({"mission": {"speed_m_s": 5.0, "acceptance_radius_m": 1.5, "waypoints": [
        [100.0, -30.0, 12.0], {"north_m": 0.0, "east_m": 50.0, "alt_m": 20.0, "speed_m_s": 3.0,
                               "fly_through": False}]}})
    items = plan_to_mission_items(plan, *HOME)
    assert len(items) == 2
    n, e = project_latlon_to_ne([it.latitude_deg for it in items], [it.longitude_deg for it in items], *HOME)
    np.testing.assert_allclose(n, [100.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(e, [-30.0, 50.0], atol=1e-6)
    assert [it.relative_altitude_m for it in items] == [12.0, 20.0]
    assert [it.speed_m_s for it in items] == [5.0, 3.0]
    assert [it.is_fly_through for it in items] == [True, False]
    assert [it.acceptance_radius_m for it in items] == [1.5, 1.5]
    assert all(np.isnan(it.yaw_deg) for it in items)  # yaw left to PX4


@pytest.mark.parametrize("doc, match", [
    ({}, r"plan\.yaml: mission: missing: expected a top-level 'mission:' mapping"),
    ({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "waypoints": []}},
     r"plan\.yaml: mission\.waypoints: expected a non-empty list of \[north_m, east_m, alt_m\]"),
    ({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "waypoints": [[1, 2]]}},
     r"plan\.yaml: mission\.waypoints\[0\]: expected \[north_m, east_m, alt_m\] \(3 numbers\), got \[1, 2\]"),
    ({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "waypoints": [[1, 2, 3], [1, 2, -4]]}},
     r"plan\.yaml: mission\.waypoints\[1\]\[2\]: expected > 0, got -4"),
    ({"mission": {"speed_m_s": 0, "acceptance_radius_m": 2, "waypoints": [[1, 2, 3]]}},
     r"plan\.yaml: mission\.speed_m_s: expected > 0, got 0"),
    ({"mission": {"acceptance_radius_m": 2, "waypoints": [[1, 2, 3]]}},
     r"plan\.yaml: mission\.speed_m_s: missing \(a number\)"),
    ({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "fly_through": "yes", "waypoints": [[1, 2, 3]]}},
     r"plan\.yaml: mission\.fly_through: expected true or false, got 'yes'"),
    ({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "waypoint": [[1, 2, 3]]}},
     r"plan\.yaml: mission\.waypoint: unknown key"),
    ({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "waypoints": [{"north_m": 1, "east_m": 2}]}},
     r"plan\.yaml: mission\.waypoints\[0\]\.alt_m: missing \(a number\)"),
    ({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "home": [47.4], "waypoints": [[1, 2, 3]]}},
     r"plan\.yaml: mission\.home: expected \[lat_deg, lon_deg\], got \[47\.4\]"),
])
def test_plan_errors_name_file_field_and_expectation(doc, match):
    with pytest.raises(ParamsError, match=match):
        plan_from_mapping(doc, "plan.yaml")


def test_load_plan_file_errors(tmp_path):
    with pytest.raises(ParamsError, match=r"nope\.yaml: <file>: file not found"):
        load_plan(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("mission: [unclosed\n")
    with pytest.raises(ParamsError, match=r"bad\.yaml: line \d+: not valid YAML"):
        load_plan(bad)


def test_mavsdk_url_spellings():
    assert normalise_mavsdk_url("udp://:14540") == "udpin://0.0.0.0:14540"
    assert normalise_mavsdk_url("udpin://0.0.0.0:14540") == "udpin://0.0.0.0:14540"
    assert normalise_mavsdk_url("tcp://10.0.0.2:5760") == "tcpout://10.0.0.2:5760"
    assert normalise_mavsdk_url("serial:///dev/ttyACM0:57600") == "serial:///dev/ttyACM0:57600"
    with pytest.raises(TwinError, match="not a MAVSDK connection URL"):
        normalise_mavsdk_url("udpin:0.0.0.0:14540")


# --------------------------------------------------------------------------- fake autopilot


class FakeAutopilot:
    """PX4-like enough for MAVSDK's mission upload: heartbeat + HOME_POSITION + MISSION_CURRENT at
    10 Hz, the MISSION_COUNT / MISSION_REQUEST_INT / MISSION_ITEM_INT / MISSION_ACK exchange,
    MISSION_SET_CURRENT, and COMMAND_ACK ACCEPTED for every command (recording arming).

    ``dataman`` models PX4's persistent mission storage (pass the same dict to a new instance to
    "reboot"): the mission items and the **current index**, which PX4 keeps across reboots and
    keeps when an identical mission is uploaded again.  Starting the mission (DO_SET_MODE
    AUTO.MISSION) records the index it starts from in ``starts``; ``fly_to_end()`` is the vehicle
    flying it (the current index goes past the last item), after which a start with the index left
    there "finishes at once", as PX4 does."""

    def __init__(self, gcs_port: int, home=(HOME[0], HOME[1], 489.4), dataman: dict | None = None):
        self.dataman = dataman if dataman is not None else {}
        self.dataman.setdefault("items", [])
        self.dataman.setdefault("current", 0)
        self.starts: list[int] = []
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.02)
        dst = ("127.0.0.1", gcs_port)
        sock = self.sock

        class _Out:
            def write(self, b):
                sock.sendto(b, dst)

        self.mav = mavlink2.MAVLink(_Out(), srcSystem=1, srcComponent=1)
        self.rx = mavlink2.MAVLink(None)
        self.rx.robust_parsing = True
        self.home = home
        self.items: dict[int, object] = {}
        self.count = None
        self.acked = threading.Event()
        self.commands: list[tuple[int, float]] = []
        self.armed = False
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def start(self):
        self.thread.start()
        return self

    def close(self):
        self._stop.set()
        self.thread.join(2.0)
        self.sock.close()

    def _run(self):
        last = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now - last > 0.1:
                last = now
                self.mav.send(self.mav.heartbeat_encode(2, 12, 1 | (128 if self.armed else 0), 0, 3))
                self.mav.send(self.mav.home_position_encode(int(self.home[0] * 1e7), int(self.home[1] * 1e7),
                                                            int(self.home[2] * 1000), 0, 0, 0, [1, 0, 0, 0],
                                                            0, 0, 0))
                self.mav.send(self.mav.mission_current_encode(self.dataman["current"]))
            try:
                data, _ = self.sock.recvfrom(65536)
            except (socket.timeout, OSError):
                continue
            for msg in self.rx.parse_buffer(data) or ():
                self._handle(msg)

    def _handle(self, msg):
        t = msg.get_type()
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if t == "MISSION_COUNT":
            self.count, self.items = msg.count, {}
            self.mav.send(self.mav.mission_request_int_encode(*src, 0, msg.mission_type))
        elif t == "MISSION_ITEM_INT":
            self.items[msg.seq] = msg
            if msg.seq + 1 < self.count:
                self.mav.send(self.mav.mission_request_int_encode(*src, msg.seq + 1, msg.mission_type))
            else:
                new = [_item_key(self.items[k]) for k in sorted(self.items)]
                if new != self.dataman["items"]:  # PX4 keeps the current index for an identical mission
                    self.dataman["current"] = 0
                self.dataman["items"] = new
                self.mav.send(self.mav.mission_ack_encode(*src, mavlink2.MAV_MISSION_ACCEPTED, msg.mission_type))
                self.acked.set()
        elif t == "MISSION_SET_CURRENT":
            if msg.seq < len(self.dataman["items"]):
                self.dataman["current"] = msg.seq
            self.mav.send(self.mav.mission_current_encode(self.dataman["current"]))
        elif t in ("COMMAND_LONG", "COMMAND_INT"):
            self.commands.append((msg.command, msg.param1))
            if msg.command == mavlink2.MAV_CMD_COMPONENT_ARM_DISARM:
                self.armed = msg.param1 == 1
            if msg.command == mavlink2.MAV_CMD_DO_SET_MODE and int(msg.param2) == 4 and int(msg.param3) == 4:
                self.starts.append(self.dataman["current"])  # AUTO.MISSION from the stored index
            self.mav.send(self.mav.command_ack_encode(msg.command, mavlink2.MAV_RESULT_ACCEPTED, 0, 0, *src))

    def fly_to_end(self):
        """The vehicle flew the mission: the current index is past the last item (PX4 keeps it)."""
        self.dataman["current"] = len(self.dataman["items"])

    @property
    def finished_at_once(self) -> bool:
        """The last start began past the last item: PX4 reports the mission finished immediately."""
        return bool(self.starts) and self.starts[-1] >= len(self.dataman["items"])


def _item_key(it):
    # repr: NaN parameters (yaw left to PX4) compare equal
    return repr((it.seq, it.frame, it.command, it.param1, it.param2, it.param3, it.param4, it.x, it.y, it.z))


@pytest.fixture()
def fake_ap():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    ap = FakeAutopilot(port).start()
    yield ap, f"udpin://127.0.0.1:{port}"
    ap.close()


def test_upload_triangle_to_fake_autopilot(fake_ap):
    ap, url = fake_ap
    plan = load_plan(REPO / "missions" / "triangle.plan.yaml")
    out = upload_plan(plan, url, connect_timeout_s=5.0, home_timeout_s=5.0)
    assert ap.acked.is_set()
    assert out["home"] == pytest.approx(HOME, abs=1e-7) and out["items"] == 4
    items = [ap.items[k] for k in sorted(ap.items)]
    wps = [it for it in items if it.command == mavlink2.MAV_CMD_NAV_WAYPOINT]
    assert len(wps) == 4
    n, e = project_latlon_to_ne(np.array([w.x for w in wps]) * 1e-7, np.array([w.y for w in wps]) * 1e-7, *HOME)
    np.testing.assert_allclose(np.column_stack([n, e, [w.z for w in wps]]), np.array(M1, dtype=float), atol=0.02)
    assert all(w.frame == mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT for w in wps)  # alt above home
    assert all(w.param1 == 0.0 and w.param2 == 2.0 for w in wps)      # fly-through (no hold), 2 m radius
    speeds = {it.param2 for it in items if it.command == mavlink2.MAV_CMD_DO_CHANGE_SPEED}
    assert speeds == {6.0}
    assert items[-1].command == mavlink2.MAV_CMD_NAV_RETURN_TO_LAUNCH   # RTL after the mission


def test_upload_refuses_a_home_far_from_the_vehicle(fake_ap):
    ap, url = fake_ap
    plan = plan_from_mapping({"mission": {"speed_m_s": 5, "acceptance_radius_m": 2, "home": [47.5, 8.5],
                                          "waypoints": [[10, 0, 10]]}}, "far.yaml")
    with pytest.raises(TwinError, match=r"far\.yaml: mission\.home: is \d+ m from the vehicle's home"):
        upload_plan(plan, url, connect_timeout_s=5.0, home_timeout_s=5.0)
    assert not ap.acked.is_set()


def test_start_arms_and_starts(fake_ap):
    ap, url = fake_ap
    out = start_mission(url, connect_timeout_s=5.0)
    assert out["armed"] and ap.armed
    cmds = [c for c, _ in ap.commands]
    assert mavlink2.MAV_CMD_COMPONENT_ARM_DISARM in cmds
    assert mavlink2.MAV_CMD_DO_SET_MODE in cmds                         # MAVSDK: mission mode = start


def _free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def _fly_twice(dataman: dict) -> list[FakeAutopilot]:
    """Upload + start the triangle, fly it, reboot the autopilot (same dataman), upload + start again."""
    plan = load_plan(REPO / "missions" / "triangle.plan.yaml")
    aps = []
    for _ in range(2):
        port = _free_udp_port()
        ap = FakeAutopilot(port, dataman=dataman).start()
        try:
            url = f"udpin://127.0.0.1:{port}"
            out = upload_plan(plan, url, connect_timeout_s=5.0, home_timeout_s=5.0)
            start_mission(url, connect_timeout_s=5.0)
            deadline = time.monotonic() + 3.0
            while not ap.starts and time.monotonic() < deadline:
                time.sleep(0.02)
            ap.fly_to_end()
            ap.upload_summary = out
        finally:
            ap.close()
        aps.append(ap)
    return aps


def test_identical_mission_flown_twice_restarts_from_item_0():
    """Issue 14.1: PX4 keeps the current index across a reboot and an identical upload; the upload
    sets it back to 0 so the second flight flies the whole mission again."""
    first, second = _fly_twice({})
    assert first.starts == [0] and second.starts == [0]
    assert not second.finished_at_once
    assert second.upload_summary["current_item"] == 0 and second.upload_summary["current_item_confirmed"]


def test_fake_autopilot_reproduces_the_finished_at_once_bug(monkeypatch):
    """Without set_current_mission_item(0) the second identical mission starts past its end."""
    from mavsdk.plugins.mission import Mission, MissionResult

    monkeypatch.setattr(Mission, "set_current_mission_item", lambda self, index: MissionResult.SUCCESS)
    first, second = _fly_twice({})
    assert first.starts == [0]
    assert second.finished_at_once and second.starts[-1] == len(second.dataman["items"])


def test_no_autopilot_is_a_one_line_error():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    with pytest.raises(TwinError, match=r"udpin://127\.0\.0\.1:\d+: no autopilot heartbeat within 0\.5 s"):
        start_mission(f"udpin://127.0.0.1:{port}", connect_timeout_s=0.5)


def test_wait_flight_done_returns_after_arm_and_disarm(fake_ap):
    from twin_nodes.mavlink.mission import wait_flight_done

    ap, url = fake_ap

    def fly():
        time.sleep(1.0)
        ap.armed = True
        time.sleep(1.5)
        ap.armed = False
    threading.Thread(target=fly, daemon=True).start()
    out = wait_flight_done(url, connect_timeout_s=5.0, arm_timeout_s=10.0, timeout_s=10.0)
    assert 1.0 < out["flight_s"] < 5.0
    with pytest.raises(TwinError, match="did not arm within 0.5 s"):
        wait_flight_done(url, connect_timeout_s=5.0, arm_timeout_s=0.5)
