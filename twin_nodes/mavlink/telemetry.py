"""Live telemetry from a real vehicle over MAVLink, parsed into ROS-frame numbers (no ROS).

The parsing is a set of pure functions (one MAVLink message -> numbers in ENU /
FLU, SI units) plus :class:`TelemetryAggregator`, which keeps the latest value
of everything and says what changed.  :class:`TelemetryClient` owns the link:
it opens a pymavlink ``mavutil`` connection (``udpin:``, ``udpout:``, ``tcp:``,
``tcpin:``, a serial device), sends a GCS heartbeat every second, asks the
autopilot for the streams it needs (``SET_MESSAGE_INTERVAL``), marks the link
stale when nothing arrives for ``stale_after_s`` and reopens non-UDP links that
stay silent for ``reopen_after_s``.

Messages used (conventions.md §3) and what they become:

=========================  ===============================================================
LOCAL_POSITION_NED (#32)   position/velocity NED -> ENU
ATTITUDE_QUATERNION (#31)  ``q1..q4`` = w,x,y,z FRD->NED -> q FLU->ENU; rates FRD -> FLU
HIGHRES_IMU (#105)         accel (specific force) / gyro FRD -> FLU
ACTUATOR_OUTPUT_STATUS     PWM µs (PX4 copies ``actuator_outputs``) -> motor commands 0..1
SERVO_OUTPUT_RAW (#36)     PWM µs (used when ACTUATOR_OUTPUT_STATUS is absent)
BATTERY_STATUS (#147)      mV / cA / % -> V, A, 0..1 (SYS_STATUS as a fallback)
ATTITUDE_TARGET (#83)      ``thrust`` 0..1 -> throttle (else the mean motor command)
POSITION_TARGET_LOCAL_NED  the 11-entry setpoint of ``msgs_py.topics`` (ENU; masked = NaN)
HEARTBEAT (#0)             armed flag, PX4 ``nav_state`` (from ``custom_mode``) and mode name
EXTENDED_SYS_STATE (#245)  ``landed_state`` -> landed 0/1
=========================  ===============================================================

Motor commands follow the project convention (docs/ARCHITECTURE.md): 0..1 per
motor in PX4 order, NaN = stopped.  ``u = (pwm - pwm_min) / (pwm_max - pwm_min)``
clipped to [0, 1]; a PWM below ``pwm_min`` by more than 2 % of the range (PX4's
900 µs disarmed value, 0 = unused) or a disarmed vehicle gives NaN.

What counts (issue 28): only MAVLink that parsed with a good checksum (no ``BAD_DATA``, no
message of an id the dialect does not know: pymavlink cannot check those) from *our* vehicle --
``config.system_id`` when given, else the system and component of the first autopilot heartbeat
-- refreshes the link.  Garbage (``bad_data``), other systems or components (``foreign``) and
messages before the vehicle is known (``unbound``) are counted in :class:`TelemetryState` and
never used.  Physically absurd values (non-finite, a quaternion that is not unit, a position
beyond :data:`MAX_POSITION_M`, a speed above :data:`MAX_SPEED_M_S`, ...) are dropped at the edge
(``rejected``, one warning per message type), never published.

Vehicle restarts (kind ``reset``; :attr:`TelemetryState.resets`): the vehicle's boot time going
backwards (a reboot), a new ``GPS_GLOBAL_ORIGIN`` (EKF origin reset), or a position jump that
its velocity cannot explain (a local-position reset).  A heartbeat with ``system_status``
``MAV_STATE_POWEROFF`` is the vehicle's own clean shutdown (:attr:`TelemetryState.vehicle_closed`).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from pymavlink.dialects.v20 import common as mavlink2

from twin_nodes.base import frames

__all__ = [
    "TelemetryConfig", "TelemetryState", "TelemetryAggregator", "TelemetryClient", "Battery",
    "parse_local_position_ned", "parse_attitude_quaternion", "motors_from_pwm",
    "motors_from_actuator_output_status", "motors_from_servo_output_raw", "parse_battery_status",
    "parse_sys_status_battery", "parse_position_target_local_ned", "parse_highres_imu",
    "landed_from_extended_sys_state", "px4_nav_state", "px4_mode_name", "normalise_url", "STREAM_RATES_HZ",
    "watched",
]

log = logging.getLogger("rotortwin.telemetry")

MAV_AUTOPILOT_PX4 = mavlink2.MAV_AUTOPILOT_PX4  # 12
MAV_AUTOPILOT_INVALID = mavlink2.MAV_AUTOPILOT_INVALID  # 8
SAFETY_ARMED = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED  # 128
UINT16_MAX = 65535
MAV_STATE_POWEROFF = mavlink2.MAV_STATE_POWEROFF  # 7

#: what is physically plausible for a multirotor's telemetry; beyond it a message is dropped
MAX_POSITION_M = 1e6          # local position, any axis [m]
MAX_SPEED_M_S = 100.0         # velocity, any axis [m/s]
MAX_RATE_RAD_S = 50.0         # body rates [rad/s] (PX4's gyros saturate at 2000 deg/s = 35 rad/s)
MAX_ACCEL_M_S2 = 1000.0       # specific force [m/s^2]
QUAT_NORM_TOL = 0.01          # |‖q‖ - 1|
#: restart detection: boot time going back by more than this is a reboot [s]
REBOOT_BACKWARDS_S = 1.0
#: a local-position step larger than this plus twice what the velocity explains is a reset [m]
POSITION_JUMP_M = 5.0
#: ... between consecutive samples at most this far apart (after a longer gap, e.g. a link outage,
#: the vehicle may simply have moved; a reboot still shows by its boot time) [s]
JUMP_CHECK_MAX_DT_S = 1.0

#: streams requested from the autopilot with SET_MESSAGE_INTERVAL (message id -> Hz)
STREAM_RATES_HZ: dict[int, float] = {
    mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 50.0,
    mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    mavlink2.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS: 20.0,
    mavlink2.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: 10.0,
    mavlink2.MAVLINK_MSG_ID_ATTITUDE_TARGET: 20.0,
    mavlink2.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: 10.0,
    mavlink2.MAVLINK_MSG_ID_BATTERY_STATUS: 2.0,
    mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU: 25.0,
    mavlink2.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 2.0,
}

# PX4 custom_mode: main mode in bits 16-23, sub mode in bits 24-31 (px4_custom_mode.h)
_PX4_MAIN = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD",
             7: "STABILIZED", 8: "RATTITUDE", 9: "SIMPLE", 10: "TERMINATION"}
_PX4_AUTO = {1: "READY", 2: "TAKEOFF", 3: "LOITER", 4: "MISSION", 5: "RTL", 6: "LAND",
             8: "FOLLOW_TARGET", 9: "PRECLAND", 10: "VTOL_TAKEOFF"}
_PX4_POSCTL = {0: "POSCTL", 1: "ORBIT", 2: "SLOW"}
# (main, sub) -> vehicle_status.nav_state, the inverse of PX4's get_px4_custom_mode()
# (src/modules/commander/px4_custom_mode.h); DESCEND and TERMINATION share LAND and MANUAL there
_PX4_NAV_STATE = {(1, 0): 0, (2, 0): 1, (3, 0): 2, (3, 1): 21, (3, 2): 6, (4, 2): 17, (4, 3): 4, (4, 4): 3,
                  (4, 5): 5, (4, 6): 18, (4, 8): 19, (4, 9): 20, (4, 10): 22, (5, 0): 10, (6, 0): 14, (7, 0): 15}


@dataclass(frozen=True)
class TelemetryConfig:
    """How to read motors and judge the link.

    ``motor_channels``: 0-based output channels of Motor1..N (default 0..n-1).
    Channels 0-15 are MAIN (SERVO_OUTPUT_RAW port 0), 16-31 AUX (port 1).
    """

    pwm_min_us: float = 1000.0
    pwm_max_us: float = 2000.0
    n_motors: int = 4
    motor_channels: tuple[int, ...] | None = None
    stale_after_s: float = 3.0
    reopen_after_s: float = 5.0
    request_streams: bool = True
    system_id: int | None = None
    throttle_timeout_s: float = 1.0

    def __post_init__(self) -> None:
        if not self.pwm_max_us > self.pwm_min_us:
            raise ValueError(f"pwm_max_us ({self.pwm_max_us:g}) must be > pwm_min_us ({self.pwm_min_us:g})")
        if self.n_motors < 1:
            raise ValueError(f"n_motors must be >= 1, got {self.n_motors}")
        if self.motor_channels is not None and (
                len(self.motor_channels) != self.n_motors or not all(0 <= c < 32 for c in self.motor_channels)):
            raise ValueError(f"motor_channels must list {self.n_motors} channels in 0..31, "
                             f"got {self.motor_channels}")
        if not self.stale_after_s > 0:
            raise ValueError(f"stale_after_s must be > 0, got {self.stale_after_s:g}")

    @property
    def channels(self) -> tuple[int, ...]:
        return self.motor_channels if self.motor_channels is not None else tuple(range(self.n_motors))


@dataclass
class Battery:
    voltage_v: float
    current_a: float          # positive = discharging (MAVLink sign); NaN unknown
    remaining: float          # 0..1, NaN unknown
    cell_voltages_v: tuple[float, ...] = ()
    temperature_c: float = float("nan")


# --------------------------------------------------------------------------- pure parsers


def parse_local_position_ned(msg: Any) -> tuple[float, np.ndarray, np.ndarray]:
    """LOCAL_POSITION_NED -> ``(t_boot_s, position_enu (3,), velocity_enu (3,))``."""
    p = frames.ned_to_enu(np.array([msg.x, msg.y, msg.z], dtype=float))
    v = frames.ned_to_enu(np.array([msg.vx, msg.vy, msg.vz], dtype=float))
    return msg.time_boot_ms * 1e-3, p, v


def parse_attitude_quaternion(msg: Any) -> tuple[float, np.ndarray, np.ndarray]:
    """ATTITUDE_QUATERNION -> ``(t_boot_s, q_enu_flu [w,x,y,z], rates_flu (3,))``."""
    q = frames.q_ned_frd_to_enu_flu(np.array([msg.q1, msg.q2, msg.q3, msg.q4], dtype=float))
    w = frames.frd_to_flu(np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float))
    return msg.time_boot_ms * 1e-3, q, w


def motors_from_pwm(pwm_us: Sequence[float], pwm_min_us: float = 1000.0, pwm_max_us: float = 2000.0,
                    armed: bool = True) -> np.ndarray:
    """PWM [µs] -> commands 0..1; below ``pwm_min`` by > 2 % of the range, or disarmed -> NaN."""
    pwm = np.asarray(pwm_us, dtype=float)
    span = pwm_max_us - pwm_min_us
    u = (pwm - pwm_min_us) / span
    stopped = ~np.isfinite(u) | (u < -0.02) | (not armed)
    return np.where(stopped, np.nan, np.clip(u, 0.0, 1.0))


def motors_from_actuator_output_status(msg: Any, cfg: TelemetryConfig, armed: bool = True) -> np.ndarray:
    """ACTUATOR_OUTPUT_STATUS (PX4: ``actuator_outputs`` values, PWM µs) -> commands.

    ``active`` is ignored: the MAVLink spec calls it a bitmask but PX4 fills it
    with the output count (``streams/ACTUATOR_OUTPUT_STATUS.hpp``); unused
    channels are 0 µs and come out NaN."""
    pwm = [float(msg.actuator[c]) for c in cfg.channels]
    return motors_from_pwm(pwm, cfg.pwm_min_us, cfg.pwm_max_us, armed)


def motors_from_servo_output_raw(msg: Any, cfg: TelemetryConfig, ports: dict[int, Any],
                                 armed: bool = True) -> np.ndarray | None:
    """SERVO_OUTPUT_RAW -> commands once every port the motors use has been seen.

    ``ports`` maps port -> the latest SERVO_OUTPUT_RAW of that port (updated here)."""
    ports[int(msg.port)] = msg
    pwm = []
    for c in cfg.channels:
        m = ports.get(c // 16)
        if m is None:
            return None
        raw = getattr(m, f"servo{c % 16 + 1}_raw", 0)
        pwm.append(float(raw) if raw not in (0, UINT16_MAX) else np.nan)
    return motors_from_pwm(pwm, cfg.pwm_min_us, cfg.pwm_max_us, armed)


def parse_battery_status(msg: Any) -> Battery:
    """BATTERY_STATUS -> :class:`Battery`.

    The voltage is the sum of the used ``voltages``/``voltages_ext`` entries:
    PX4 (``streams/BATTERY_STATUS.hpp``) sends either the cell voltages or,
    when it doesn't know them, the total in ``voltages[0]`` (split into 65534 mV
    chunks above 65.5 V).  Cell voltages are reported only when there are
    several entries that all look like cells (< 5 V)."""
    cells = [v for v in list(msg.voltages) + list(getattr(msg, "voltages_ext", []) or [])
             if v not in (UINT16_MAX, 0)]
    volts = tuple(v * 1e-3 for v in cells)
    is_cells = len(volts) > 1 and all(v < 5.0 for v in volts)
    current = msg.current_battery * 1e-2 if msg.current_battery != -1 else float("nan")
    remaining = msg.battery_remaining * 1e-2 if msg.battery_remaining != -1 else float("nan")
    temp = msg.temperature * 1e-2 if msg.temperature != 32767 else float("nan")
    return Battery(voltage_v=float(sum(volts)) if volts else float("nan"), current_a=float(current),
                   remaining=float(remaining), cell_voltages_v=volts if is_cells else (),
                   temperature_c=float(temp))


def parse_sys_status_battery(msg: Any) -> Battery:
    """SYS_STATUS battery fields -> :class:`Battery`."""
    v = msg.voltage_battery * 1e-3 if msg.voltage_battery not in (UINT16_MAX, 0) else float("nan")
    a = msg.current_battery * 1e-2 if msg.current_battery != -1 else float("nan")
    r = msg.battery_remaining * 1e-2 if msg.battery_remaining != -1 else float("nan")
    return Battery(voltage_v=float(v), current_a=float(a), remaining=float(r))


def parse_position_target_local_ned(msg: Any) -> tuple[float, np.ndarray] | None:
    """POSITION_TARGET_LOCAL_NED -> ``(t_boot_s, sp)`` with ``sp`` the 11-entry setpoint of
    ``msgs_py.topics.SETPOINT_LABELS``: position, velocity, acceleration (ENU), yaw (from East,
    CCW), yaw rate (about Up); entries masked by ``type_mask`` are NaN (not controlled).
    None when everything is masked."""
    mask = int(msg.type_mask)
    sp = np.full(11, np.nan)
    for bit, sl, names in ((0, slice(0, 3), ("x", "y", "z")), (3, slice(3, 6), ("vx", "vy", "vz")),
                           (6, slice(6, 9), ("afx", "afy", "afz"))):
        if not (mask >> bit) & 0b111 and not (bit == 6 and mask & (1 << 9)):  # bit 9: afx..afz are forces
            sp[sl] = frames.ned_to_enu(np.array([float(getattr(msg, n)) for n in names]))
    if not mask & (1 << 10) and np.isfinite(msg.yaw):
        sp[9] = float(frames.yaw_ned_to_enu(float(msg.yaw)))
    if not mask & (1 << 11) and np.isfinite(msg.yaw_rate):
        sp[10] = float(frames.ned_to_enu(np.array([0.0, 0.0, float(msg.yaw_rate)]))[2])
    if not np.any(np.isfinite(sp)):
        return None
    return msg.time_boot_ms * 1e-3, sp


def parse_highres_imu(msg: Any) -> tuple[float, np.ndarray, np.ndarray]:
    """HIGHRES_IMU -> ``(t_s, specific_force_flu, gyro_flu)`` (PX4 sends body FRD)."""
    sf = frames.frd_to_flu(np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float))
    w = frames.frd_to_flu(np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=float))
    return msg.time_usec * 1e-6, sf, w


def landed_from_extended_sys_state(msg: Any) -> float:
    """EXTENDED_SYS_STATE.landed_state -> 1.0 on the ground, 0.0 in the air / taking off /
    landing, NaN undefined."""
    state = int(msg.landed_state)
    if state == mavlink2.MAV_LANDED_STATE_ON_GROUND:
        return 1.0
    if state in (mavlink2.MAV_LANDED_STATE_IN_AIR, mavlink2.MAV_LANDED_STATE_TAKEOFF,
                 mavlink2.MAV_LANDED_STATE_LANDING):
        return 0.0
    return float("nan")


def px4_nav_state(custom_mode: int, base_mode: int = 1, autopilot: int = MAV_AUTOPILOT_PX4) -> float:
    """PX4 ``custom_mode`` -> ``vehicle_status.nav_state`` (PX4 numbering), NaN if unknown."""
    if autopilot != MAV_AUTOPILOT_PX4 or not (base_mode & mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED):
        return float("nan")
    key = ((int(custom_mode) >> 16) & 0xFF, (int(custom_mode) >> 24) & 0xFF)
    return float(_PX4_NAV_STATE.get(key, float("nan")))


def px4_mode_name(custom_mode: int, base_mode: int = 1, autopilot: int = MAV_AUTOPILOT_PX4) -> str:
    """PX4 ``custom_mode`` -> e.g. ``"AUTO.MISSION"``, ``"POSCTL"``."""
    if autopilot != MAV_AUTOPILOT_PX4 or not (base_mode & mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED):
        return f"custom:{int(custom_mode)}"
    main = (int(custom_mode) >> 16) & 0xFF
    sub = (int(custom_mode) >> 24) & 0xFF
    name = _PX4_MAIN.get(main, f"MAIN{main}")
    if main == 4:
        return f"AUTO.{_PX4_AUTO.get(sub, f'SUB{sub}')}"
    if main == 3 and sub:
        return f"POSCTL.{_PX4_POSCTL.get(sub, f'SUB{sub}')}"
    return name


def normalise_url(url: str) -> tuple[str, dict[str, Any]]:
    """A connection URL -> ``(mavutil device, kwargs)``.

    Accepts mavutil URLs (``udpin:0.0.0.0:14550``, ``udpout:host:port``,
    ``tcp:host:port``, ``tcpin:…``, ``/dev/ttyACM0``), MAVSDK-style ``scheme://``
    spellings (``udpin://0.0.0.0:14540``, ``udp://:14540`` = listen,
    ``tcp://host:port``) and ``serial:/dev/ttyUSB0:57600`` / ``serial:///dev/ttyUSB0:57600``."""
    u = url.strip()
    kwargs: dict[str, Any] = {}
    if u.startswith("serial:"):
        rest = u[len("serial:"):].lstrip("/")
        if rest.startswith("dev/"):  # serial:/dev/ttyUSB0 and serial:///dev/ttyUSB0
            rest = "/" + rest
        if ":" in rest:
            dev, baud = rest.rsplit(":", 1)
            kwargs["baud"] = int(baud)
        else:
            dev = rest
        return dev, kwargs
    if "://" in u:
        scheme, rest = u.split("://", 1)
        scheme = {"udp": "udpin"}.get(scheme, scheme)
        if scheme in ("udpin", "tcpin") and rest.startswith(":"):
            rest = "0.0.0.0" + rest
        return f"{scheme}:{rest}", kwargs
    if u.startswith("udp:"):
        rest = u[4:]
        return f"udpin:{'0.0.0.0' + rest if rest.startswith(':') else rest}", kwargs
    return u, kwargs


# --------------------------------------------------------------------------- aggregation


@dataclass
class TelemetryState:
    """Latest values, ROS frames (NaN = not received yet / unknown)."""

    system_id: int | None = None
    component_id: int | None = None
    autopilot: int | None = None
    armed: bool = False
    mode: str = "unknown"
    t_position_s: float = float("nan")       # vehicle boot time of the values [s]
    position_enu: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    velocity_enu: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    t_attitude_s: float = float("nan")
    q_enu_flu: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    rates_flu: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    motors: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    throttle: float = float("nan")
    throttle_source: str = ""
    battery: Battery | None = None
    t_setpoint_s: float = float("nan")
    setpoint: np.ndarray = field(default_factory=lambda: np.full(11, np.nan))  # msgs_py SETPOINT_LABELS
    t_imu_s: float = float("nan")
    imu_specific_force_flu: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    imu_gyro_flu: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    nav_state: float = float("nan")          # PX4 vehicle_status.nav_state, NaN unknown
    landed: float = float("nan")             # 1 on the ground, 0 in the air, NaN unknown
    last_rx_wall_s: float = float("nan")    # time.monotonic() of the last message from the vehicle
    messages_rx: int = 0
    stale: bool = True
    link_open: bool = False
    # what was not used (issue 28): garbage, other systems/components, before the vehicle was
    # known, physically absurd values (per message type)
    bad_data: int = 0
    foreign: int = 0
    unbound: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    # vehicle restarts: {"rx_s": receive time, "reason": ..., "t_boot_s": ...}; the last one's reason
    resets: list[dict[str, Any]] = field(default_factory=list)
    reset_reason: str = ""
    vehicle_closed: bool = False             # the vehicle announced its shutdown (MAV_STATE_POWEROFF)

    @property
    def n_rejected(self) -> int:
        return int(sum(self.rejected.values()))

    @property
    def setpoint_has_position(self) -> bool:
        return bool(np.all(np.isfinite(self.setpoint[0:3])))

    @property
    def status(self) -> tuple[float, float, float]:
        """``(armed, nav_state, landed)`` as ``/real/status`` carries them (NaN unknown)."""
        return (1.0 if self.armed else 0.0) if self.system_id is not None else float("nan"), \
            self.nav_state, self.landed

    @property
    def has_odometry(self) -> bool:
        return bool(np.all(np.isfinite(self.position_enu)) and np.all(np.isfinite(self.q_enu_flu)))

    def velocity_body_flu(self) -> np.ndarray:
        """Velocity in the body frame (nav_msgs/Odometry puts the twist in the child frame)."""
        return frames.quat_rotate(frames.quat_conjugate(self.q_enu_flu), self.velocity_enu)


class TelemetryAggregator:
    """Feeds messages into a :class:`TelemetryState`; :meth:`update` returns what changed.

    Kinds: ``odom`` (position or attitude, once both are known), ``imu``, ``motors``,
    ``throttle``, ``battery``, ``setpoint``, ``status`` (armed, nav_state or landed
    changed), ``link`` (the link came up or went stale), ``heartbeat`` (an autopilot
    heartbeat arrived)."""

    def __init__(self, config: TelemetryConfig | None = None):
        self.config = config or TelemetryConfig()
        self.state = TelemetryState(system_id=self.config.system_id,
                                    motors=np.full(self.config.n_motors, np.nan))
        self._servo_ports: dict[int, Any] = {}
        self._aos_wall_s = -np.inf
        self._thrust_wall_s = -np.inf
        self._battery_status_seen = False
        self._warned: set[str] = set()
        self._t_boot_s = -np.inf          # the newest vehicle boot time seen [s]
        self._origin: tuple | None = None  # the last GPS_GLOBAL_ORIGIN
        self._last_pos: tuple[float, np.ndarray, np.ndarray] | None = None  # (t_boot_s, p, v) ENU

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning(text)

    def _accept(self, msg: Any, mtype: str) -> bool:
        """Is this a good message from our vehicle?  Counts what is not (bad_data, foreign, unbound)
        and binds the vehicle with its first autopilot heartbeat."""
        st = self.state
        if mtype == "BAD_DATA" or mtype.startswith("UNKNOWN"):
            # garbage, a bad checksum, or an id the dialect does not know (its checksum cannot be
            # checked): never a sign of life
            st.bad_data += 1
            self._warn_once("bad_data", "telemetry: ignoring data that is not valid MAVLink (bad checksum or "
                                        "unknown message); counted in bad_data")
            return False
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        if mtype == "HEARTBEAT" and st.component_id is None and msg.autopilot != MAV_AUTOPILOT_INVALID \
                and (st.system_id is None or src == st.system_id):
            st.system_id = src  # our vehicle: the first autopilot heartbeat (or the configured system's)
            st.component_id = comp
            log.info("telemetry: vehicle is system %d component %d", src, comp)
        if st.system_id is None:
            st.unbound += 1  # no autopilot heartbeat yet: whose data this is is unknown
            return False
        if src != st.system_id or (st.component_id is not None and comp != st.component_id):
            st.foreign += 1
            self._warn_once(f"foreign{src}.{comp}", f"telemetry: ignoring system {src} component {comp} (the "
                                                   f"vehicle is system {st.system_id} component {st.component_id})")
            return False
        return True

    def _reject(self, mtype: str, why: str) -> list[str]:
        st = self.state
        st.rejected[mtype] = st.rejected.get(mtype, 0) + 1
        self._warn_once(f"reject{mtype}", f"telemetry: dropping {mtype} with {why} (counted in rejected; "
                                          f"further ones are dropped quietly)")
        return []

    def _restart(self, kinds: list[str], now: float, reason: str, t_boot_s: float) -> None:
        st = self.state
        st.resets.append({"rx_s": float(now), "reason": reason, "t_boot_s": float(t_boot_s)})
        st.reset_reason = reason
        log.warning("telemetry: vehicle restart (%s): the twin re-syncs", reason)
        self._last_pos = None
        self._servo_ports.clear()
        if "reset" not in kinds:
            kinds.append("reset")

    def _boot_time(self, t_boot_s: float, kinds: list[str], now: float) -> None:
        """A reboot shows as the vehicle's boot time going backwards."""
        if t_boot_s < self._t_boot_s - REBOOT_BACKWARDS_S:
            self._t_boot_s = t_boot_s
            self._restart(kinds, now, f"reboot (boot time went back to {t_boot_s:.1f} s)", t_boot_s)
        else:
            self._t_boot_s = max(self._t_boot_s, t_boot_s)

    def update(self, msg: Any, now_s: float | None = None) -> list[str]:
        now = time.monotonic() if now_s is None else float(now_s)
        st = self.state
        mtype = msg.get_type()
        if mtype == "HEARTBEAT" and msg.autopilot == MAV_AUTOPILOT_INVALID \
                and msg.get_srcSystem() != st.system_id:
            st.foreign += 1  # a GCS or companion computer: another system, never a sign of our vehicle
            return []
        if not self._accept(msg, mtype):
            return []
        if mtype == "HEARTBEAT" and msg.autopilot == MAV_AUTOPILOT_INVALID:
            return []  # a companion computer of our own system
        bad = _implausible(msg, mtype)
        if bad:
            return self._reject(mtype, bad)
        if mtype == "HEARTBEAT":
            st.autopilot = msg.autopilot
        st.messages_rx += 1
        st.last_rx_wall_s = now
        kinds: list[str] = []
        if st.stale:
            st.stale = False
            kinds.append("link")
        cfg = self.config
        if mtype == "HEARTBEAT":
            armed = bool(msg.base_mode & SAFETY_ARMED)
            mode = px4_mode_name(msg.custom_mode, msg.base_mode, msg.autopilot)
            nav = px4_nav_state(msg.custom_mode, msg.base_mode, msg.autopilot)
            first = st.messages_rx == 1 or "link" in kinds
            if first or armed != st.armed or mode != st.mode or not _same(nav, st.nav_state):
                st.armed, st.mode, st.nav_state = armed, mode, nav
                kinds.append("status")
            closed = int(msg.system_status) == MAV_STATE_POWEROFF
            if closed and not st.vehicle_closed:
                log.info("telemetry: the vehicle announced its shutdown (MAV_STATE_POWEROFF)")
            st.vehicle_closed = closed
            kinds.append("heartbeat")
        elif mtype == "EXTENDED_SYS_STATE":
            landed = landed_from_extended_sys_state(msg)
            if not _same(landed, st.landed):
                st.landed = landed
                kinds.append("status")
        elif mtype == "HIGHRES_IMU":
            st.t_imu_s, st.imu_specific_force_flu, st.imu_gyro_flu = parse_highres_imu(msg)
            kinds.append("imu")
        elif mtype == "LOCAL_POSITION_NED":
            t_b, p, v = parse_local_position_ned(msg)
            self._boot_time(t_b, kinds, now)
            prev = self._last_pos
            dt = t_b - prev[0] if prev is not None else np.inf
            if prev is not None and "reset" not in kinds and 0.0 <= dt <= JUMP_CHECK_MAX_DT_S:  # not across a gap
                explained = 2.0 * max(float(np.max(np.abs(prev[2]))), float(np.max(np.abs(v)))) * dt
                jump = float(np.linalg.norm(p - prev[1]))
                if jump > POSITION_JUMP_M + explained:
                    self._restart(kinds, now, f"position jump of {jump:.1f} m in {dt:.2f} s (local position reset)",
                                  t_b)
            self._last_pos = (t_b, p, v)
            st.t_position_s, st.position_enu, st.velocity_enu = t_b, p, v
            if st.has_odometry:
                kinds.append("odom")
        elif mtype == "GPS_GLOBAL_ORIGIN":
            origin = (int(msg.latitude), int(msg.longitude), int(msg.altitude))
            if self._origin is not None and origin != self._origin:
                self._restart(kinds, now, "new EKF origin (GPS_GLOBAL_ORIGIN)", st.t_position_s)
            self._origin = origin
        elif mtype == "SYSTEM_TIME":
            self._boot_time(msg.time_boot_ms * 1e-3, kinds, now)
        elif mtype == "ATTITUDE_QUATERNION":
            t_b, q, w = parse_attitude_quaternion(msg)
            self._boot_time(t_b, kinds, now)
            st.t_attitude_s, st.q_enu_flu, st.rates_flu = t_b, q, w
            if st.has_odometry:
                kinds.append("odom")
        elif mtype == "ACTUATOR_OUTPUT_STATUS":
            self._aos_wall_s = now
            st.motors = motors_from_actuator_output_status(msg, cfg, st.armed)
            kinds += self._motors_changed(now)
        elif mtype == "SERVO_OUTPUT_RAW":
            u = motors_from_servo_output_raw(msg, cfg, self._servo_ports, st.armed)
            if u is not None and now - self._aos_wall_s > 2.0:
                st.motors = u
                kinds += self._motors_changed(now)
        elif mtype == "ATTITUDE_TARGET":
            if np.isfinite(msg.thrust):
                self._thrust_wall_s = now
                st.throttle, st.throttle_source = float(msg.thrust), "attitude_target"
                kinds.append("throttle")
        elif mtype == "BATTERY_STATUS":
            if msg.id == 0:
                self._battery_status_seen = True
                st.battery = parse_battery_status(msg)
                kinds.append("battery")
        elif mtype == "SYS_STATUS":
            if not self._battery_status_seen:
                st.battery = parse_sys_status_battery(msg)
                kinds.append("battery")
        elif mtype == "POSITION_TARGET_LOCAL_NED":
            sp = parse_position_target_local_ned(msg)
            if sp is not None:
                st.t_setpoint_s, st.setpoint = sp
                kinds.append("setpoint")
        return kinds

    def _motors_changed(self, now: float) -> list[str]:
        st = self.state
        out = ["motors"]
        if now - self._thrust_wall_s > self.config.throttle_timeout_s:
            finite = st.motors[np.isfinite(st.motors)]
            st.throttle = float(finite.mean()) if finite.size else float("nan")
            st.throttle_source = "mean_motor"
            out.append("throttle")
        return out

    def check_stale(self, now_s: float | None = None) -> bool:
        """Mark the link stale after ``stale_after_s`` of silence; True when this call changed it."""
        now = time.monotonic() if now_s is None else float(now_s)
        st = self.state
        silent = not np.isfinite(st.last_rx_wall_s) or now - st.last_rx_wall_s > self.config.stale_after_s
        if silent and not st.stale:
            st.stale = True
            return True
        return False


def _same(a: float, b: float) -> bool:
    return (np.isnan(a) and np.isnan(b)) or a == b


def _bounded(values: Sequence[float], limit: float) -> bool:
    a = np.asarray(values, dtype=float)
    return bool(np.all(np.isfinite(a)) and np.all(np.abs(a) <= limit))


def _implausible(msg: Any, mtype: str) -> str:
    """Why a message of our vehicle cannot be true ("" when it can): non-finite numbers, a
    quaternion that is not unit, a position, speed, rate or acceleration no multirotor has."""
    if mtype == "LOCAL_POSITION_NED":
        if not _bounded([msg.x, msg.y, msg.z], MAX_POSITION_M):
            return f"a non-finite or absurd position ({msg.x:g}, {msg.y:g}, {msg.z:g}) m"
        if not _bounded([msg.vx, msg.vy, msg.vz], MAX_SPEED_M_S):
            return f"a non-finite or absurd velocity ({msg.vx:g}, {msg.vy:g}, {msg.vz:g}) m/s"
    elif mtype == "ATTITUDE_QUATERNION":
        q = np.array([msg.q1, msg.q2, msg.q3, msg.q4], dtype=float)
        if not np.all(np.isfinite(q)) or abs(float(np.linalg.norm(q)) - 1.0) > QUAT_NORM_TOL:
            return f"a quaternion that is not unit (norm {float(np.linalg.norm(q)):g})"
        if not _bounded([msg.rollspeed, msg.pitchspeed, msg.yawspeed], MAX_RATE_RAD_S):
            return "non-finite or absurd body rates"
    elif mtype == "HIGHRES_IMU":
        if not _bounded([msg.xacc, msg.yacc, msg.zacc], MAX_ACCEL_M_S2) or \
                not _bounded([msg.xgyro, msg.ygyro, msg.zgyro], MAX_RATE_RAD_S):
            return "non-finite or absurd accelerations or rates"
    elif mtype == "POSITION_TARGET_LOCAL_NED":
        for names, limit in ((("x", "y", "z"), MAX_POSITION_M), (("vx", "vy", "vz"), MAX_SPEED_M_S),
                             (("afx", "afy", "afz"), MAX_ACCEL_M_S2)):
            a = np.array([float(getattr(msg, n)) for n in names])
            if np.any(np.isinf(a)) or np.any(np.abs(a[np.isfinite(a)]) > limit):  # NaN = not controlled
                return f"an absurd setpoint ({', '.join(f'{x:g}' for x in a)})"
    elif mtype == "ATTITUDE_TARGET":
        if np.isinf(msg.thrust) or (np.isfinite(msg.thrust) and abs(msg.thrust) > 1.5):
            return f"an absurd thrust {msg.thrust:g}"
    return ""


# --------------------------------------------------------------------------- the link


class TelemetryClient:
    """Reads a vehicle's MAVLink stream in a loop; ``on_update(kinds, state)`` on every change.

    >>> c = TelemetryClient("udpin:0.0.0.0:14550", on_update=lambda k, s: print(k, s.position_enu))
    >>> c.start_thread(); ...; c.close()
    """

    def __init__(self, url: str, config: TelemetryConfig | None = None,
                 on_update: Callable[[list[str], TelemetryState], None] | None = None):
        self.url = url
        self.device, self._kwargs = normalise_url(url)
        self.config = config or TelemetryConfig()
        self.aggregator = TelemetryAggregator(self.config)
        self.on_update = on_update
        self._conn: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_hb_tx = -np.inf
        self._streams_requested = False
        self._opened_wall_s = 0.0
        self.reopens = 0

    @property
    def state(self) -> TelemetryState:
        return self.aggregator.state

    @property
    def _is_udp_listen(self) -> bool:
        return self.device.startswith(("udpin:", "udp:"))

    def start_thread(self) -> threading.Thread:
        self._thread = threading.Thread(target=self.run, name="telemetry", daemon=True)
        self._thread.start()
        return self._thread

    def stop(self) -> None:
        self._stop.set()

    def close(self, timeout_s: float = 2.0) -> None:
        self.stop()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
        self._close_conn()

    def _open(self) -> None:
        from pymavlink import mavutil

        kwargs = dict(self._kwargs)
        if self.device.startswith("tcp:"):
            kwargs.update(autoreconnect=True, retries=1)
        self._conn = mavutil.mavlink_connection(self.device, source_system=255, source_component=190,
                                                dialect="common", **kwargs)
        self._opened_wall_s = time.monotonic()
        self._streams_requested = False
        if self.device.startswith(("udpin:", "udpout:", "udp:", "udpbcast:")):
            self._frame_datagrams()
        self.state.link_open = True
        log.info("telemetry link open: %s", self.device)

    def _frame_datagrams(self) -> None:
        """UDP: a MAVLink packet never spans two datagrams, so whatever the parser still holds when a
        new datagram arrives is the truncated tail of garbage (counted in ``bad_data``).  Without
        this a garbage header claiming 280 bytes swallowed the vehicle's next valid packets."""
        conn = self._conn
        mav = conn.mav
        raw_recv = conn.recv

        def recv(n: int | None = None) -> Any:
            data = raw_recv() if n is None else raw_recv(n)
            if data and mav.buf_len() > 0:
                mav.buf = bytearray()
                mav.buf_index = 0
                mav.expected_length = mavlink2.HEADER_LEN_V1 + 2
                self.state.bad_data += 1
            return data

        conn.recv = recv

    def _close_conn(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:  # closing a broken serial/tcp link may raise anything
                pass
            self._conn = None
        self.state.link_open = False

    def _emit(self, kinds: list[str]) -> None:
        if kinds and self.on_update is not None:
            try:
                self.on_update(kinds, self.state)
            except Exception:
                log.exception("on_update callback failed")

    def run(self) -> None:
        """The loop (blocking) until :meth:`stop`."""
        while not self._stop.is_set():
            if self._conn is None:
                try:
                    self._open()
                except Exception as exc:  # serial.SerialException, OSError, ...
                    log.warning("cannot open %s (%s); retrying in 1 s", self.device, exc)
                    self._stop.wait(1.0)
                    continue
            try:
                msg = self._conn.recv_match(blocking=True, timeout=0.1)
            except Exception as exc:
                log.warning("telemetry link error (%s): reopening", exc)
                self._close_conn()
                self.reopens += 1
                if self.aggregator.check_stale(np.inf):
                    self._emit(["link"])
                continue
            now = time.monotonic()
            if msg is not None:
                kinds = self.aggregator.update(msg, now)
                if "heartbeat" in kinds and self.config.request_streams and not self._streams_requested:
                    self._request_streams()
                self._emit([k for k in kinds if k != "heartbeat"])
            self._tick(now)

    def _tick(self, now: float) -> None:
        if now - self._last_hb_tx >= 1.0:
            self._last_hb_tx = now
            try:
                self._conn.mav.heartbeat_send(mavlink2.MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0,
                                              mavlink2.MAV_STATE_ACTIVE)
            except Exception:  # udpin before the vehicle's first packet has nowhere to send
                pass
        if self.aggregator.check_stale(now):
            log.warning("telemetry stale: nothing for %.1f s", self.config.stale_after_s)
            self._streams_requested = False
            self._emit(["link"])
        st = self.state
        silent_for = now - (st.last_rx_wall_s if np.isfinite(st.last_rx_wall_s) else self._opened_wall_s)
        if (not self._is_udp_listen and silent_for > self.config.reopen_after_s
                and now - self._opened_wall_s > self.config.reopen_after_s):
            log.warning("no data on %s for %.1f s: reopening", self.device, silent_for)
            self._close_conn()
            self.reopens += 1

    def _request_streams(self) -> None:
        st = self.state
        try:
            for msg_id, hz in STREAM_RATES_HZ.items():
                self._conn.mav.command_long_send(st.system_id or 1, st.component_id or 1,
                                                 mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                 msg_id, 1e6 / hz, 0, 0, 0, 0, 0)
            self._streams_requested = True
        except Exception as exc:
            log.warning("could not request streams: %s", exc)


def watched(what: str, st: Any, t_start: float | None, t_end: float | None, losses: list) -> dict[str, Any]:
    """What a live run or a telemetry log watched (``live.json``'s header, issue 28)."""
    return {"log": what, "system_id": st.system_id, "component_id": st.component_id,
            "start_s": t_start, "end_s": t_end, "messages": st.messages_rx,
            "ignored": {"bad_data": st.bad_data, "foreign": st.foreign, "before_heartbeat": st.unbound,
                        "rejected": dict(st.rejected)},
            "resets": [{"t_s": r.get("t_s", r["rx_s"]), "reason": r["reason"]} for r in st.resets],
            "link_losses": losses}
