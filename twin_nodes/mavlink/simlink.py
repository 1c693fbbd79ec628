"""The PX4 simulator link: the twin as a lockstep MAVLink HIL simulator (no ROS).

PX4 SITL's ``simulator_mavlink`` module is a TCP **client**; the simulator is
the **server** on port 4560 + instance (PX4 ``px4-rc.simulator``:
``simulator_mavlink start -c $((4560+px4_instance))``).  The protocol, as
PX4's ``SimulatorMavlink.cpp`` and Gazebo-classic's ``gazebo_mavlink_interface``
implement it (conventions.md §3):

1. PX4 connects, sends HEARTBEAT and a COMMAND_LONG ``SET_MESSAGE_INTERVAL``
   asking for HIL_STATE_QUATERNION (ground truth) every 5 ms.
2. The simulator sends HIL_SENSOR (``id`` 0); its ``time_usec`` sets PX4's
   clock.  Until the first HIL_ACTUATOR_CONTROLS arrives the simulator
   *freewheels*: it steps with the motors stopped and sends HIL_SENSOR at the
   step rate on the wall clock.
3. PX4 runs one iteration and answers with HIL_ACTUATOR_CONTROLS
   (``controls[16]``, ``mode`` with SAFETY_ARMED = 128 when armed, ``flags``
   bit 0 = lockstep).
4. In lockstep the simulator steps the physics by exactly one step per
   HIL_ACTUATOR_CONTROLS and answers with the next HIL_SENSOR, so simulated time
   advances only with PX4.  HIL_GPS goes out at ``gps_rate_hz`` and
   HIL_STATE_QUATERNION at the interval PX4 asked for, both in simulated time.
   If no reply comes for ``lockstep_timeout_s`` of wall time the simulator steps
   once with the last command and sends again (Gazebo's 1 s poll timeout).

Pacing: lockstep lets PX4 run as fast as both sides can, but the *simulator*
sets the pace — Gazebo runs at ``real_time_update_rate`` (250 Hz) x
``PX4_SIM_SPEED_FACTOR``, jMAVSim at ``-r 250`` — because ground stations,
MAVSDK and PX4's link-loss timeouts live on the wall clock (PX4's ``rcS``
scales ``COM_DL_LOSS_T`` & co. by the speed factor).  So a step owed to PX4 is
run no earlier than its wall time at ``speed_factor`` x real time (default 1);
``speed_factor <= 0`` runs as fast as PX4 answers (tests, benchmarks).  A side
that falls behind is not made to catch up in a burst.

Commands: non-reversible motor outputs are 0..1 (PX4 ``PWMSim``); disarmed
(``mode`` without SAFETY_ARMED) means stopped = NaN, the project's convention.
A client that disconnects sends the link back to waiting; the next client
starts freewheeling again (the twin's state is kept, as in Gazebo).  One client
flies at a time: a second connection is refused (closed at once, counted in
``LinkStats.refused``) while the current client has sent anything in the last
``takeover_after_s`` (5 s); a client silent for longer is taken to be dead (a
restarted PX4 may connect before the old socket is seen dead) and replaced.

The server listens on the loopback interface (``127.0.0.1``) unless ``host`` says
otherwise (``0.0.0.0`` for PX4 in another container or machine): the link has no
authentication, and whoever connects flies the twin.

Frames: the twin is ENU/FLU; everything on the wire is NED/FRD, converted by
:mod:`twin_nodes.base.frames` only.
"""

from __future__ import annotations

import logging
import select
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from twin_nodes.base import frames
from twin_nodes.base.errors import ParamsError, TwinError
from twin_nodes.mavlink.sensors import SensorConfig, SensorModel, reproject_ne_to_latlon
from twin_nodes.vehicle.params import VehicleParams
from twin_nodes.twin.sim import Simulator

__all__ = [
    "SimLinkServer", "StepInfo", "LinkStats", "motor_commands_from_controls",
    "FIELDS_ACCEL", "FIELDS_GYRO", "FIELDS_MAG", "FIELDS_BARO", "SAFETY_ARMED", "LOCKSTEP_FLAG",
    "DEFAULT_PORT", "DEFAULT_HOST", "DEFAULT_STEP_S", "ScriptedPX4", "PeerStats",
]

log = logging.getLogger("rotortwin.simlink")

DEFAULT_PORT = 4560
DEFAULT_HOST = "127.0.0.1"  # loopback unless told otherwise: the link has no authentication
DEFAULT_STEP_S = 0.004  # PX4/Gazebo lockstep assume 4 ms (250 Hz)

# HIL_SENSOR.fields_updated bits, as PX4 SimulatorMavlink masks them
FIELDS_ACCEL = 0x7
FIELDS_GYRO = 0x38
FIELDS_MAG = 0x1C0
FIELDS_BARO = 0x1A00  # abs_pressure (9) | pressure_alt (11) | temperature (12)

SAFETY_ARMED = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED  # 128
LOCKSTEP_FLAG = 1  # HIL_ACTUATOR_CONTROLS.flags bit 0

# Gazebo-classic sends as system 1, component 200
_SRC_SYSTEM = 1
_SRC_COMPONENT = 200

_INT16 = (-32768, 32767)


def motor_commands_from_controls(controls, mode: int, n_motors: int) -> np.ndarray:
    """HIL_ACTUATOR_CONTROLS -> motor commands (n_motors,), PX4 order.

    Armed: ``controls[:n]`` clipped to [0, 1] (non-finite -> NaN).  Disarmed
    (no SAFETY_ARMED bit in ``mode``): all NaN = stopped."""
    if not (int(mode) & SAFETY_ARMED):
        return np.full(n_motors, np.nan)
    u = np.asarray(list(controls)[:n_motors], dtype=float)
    if u.size < n_motors:
        u = np.concatenate([u, np.full(n_motors - u.size, np.nan)])
    return np.where(np.isfinite(u), np.clip(u, 0.0, 1.0), np.nan)


@dataclass
class StepInfo:
    """What one simulator step exchanged (ENU/FLU unless the name says FRD)."""

    time_usec: int            # simulated time sent to PX4 [µs]
    state: np.ndarray         # twin state after the step (copy), see docs/ARCHITECTURE.md
    u: np.ndarray             # motor commands applied during the step (NaN = stopped)
    armed: bool
    lockstep: bool            # False while freewheeling
    specific_force_flu: np.ndarray  # true accelerometer value [m/s²]
    accel_frd: np.ndarray     # measured (bias + noise) as sent in HIL_SENSOR
    gyro_frd: np.ndarray
    mag_frd: np.ndarray | None   # None when not sent this step
    baro: tuple[float, float, float] | None  # (hPa, pressure alt m, °C) when sent
    gps_sent: bool
    state_sent: bool

    @property
    def t_s(self) -> float:
        return self.time_usec * 1e-6

    @property
    def position_enu(self) -> np.ndarray:
        return self.state[0:3]

    @property
    def velocity_enu(self) -> np.ndarray:
        return self.state[3:6]

    @property
    def q_enu_flu(self) -> np.ndarray:
        return self.state[6:10]

    @property
    def rates_flu(self) -> np.ndarray:
        return self.state[10:13]

    @property
    def velocity_body_flu(self) -> np.ndarray:
        """Velocity in the body frame (the twist frame of nav_msgs/Odometry)."""
        return frames.quat_rotate(frames.quat_conjugate(self.q_enu_flu), self.velocity_enu)

    @property
    def accel_flu(self) -> np.ndarray:
        return frames.frd_to_flu(self.accel_frd)

    @property
    def gyro_flu(self) -> np.ndarray:
        return frames.frd_to_flu(self.gyro_frd)


@dataclass
class LinkStats:
    """Message and step counters (the tests compare them with the peer's)."""

    connections: int = 0
    disconnects: int = 0
    heartbeats_rx: int = 0
    controls_rx: int = 0
    commands_rx: int = 0
    bad_rx: int = 0
    sensors_tx: int = 0
    gps_tx: int = 0
    state_tx: int = 0
    acks_tx: int = 0
    freewheel_steps: int = 0
    lockstep_steps: int = 0
    lockstep_timeouts: int = 0
    refused: int = 0  # connections refused while another client was flying
    time_usec: int = 0

    @property
    def steps(self) -> int:
        return self.freewheel_steps + self.lockstep_steps


class _Outbox:
    """File-like sink for pymavlink's ``MAVLink.send``; flushed once per step."""

    def __init__(self) -> None:
        self.buf = bytearray()

    def write(self, data: bytes) -> None:
        self.buf += data

    def take(self) -> bytes:
        out = bytes(self.buf)
        self.buf.clear()
        return out


@dataclass
class _Schedule:
    """Fires at an interval in simulated time; keeps the average rate."""

    interval_us: int  # <= 0: never
    next_due_us: int = 0

    def due(self, t_us: int) -> bool:
        if self.interval_us <= 0 or t_us < self.next_due_us:
            return False
        self.next_due_us += self.interval_us
        if self.next_due_us <= t_us:
            self.next_due_us = t_us + self.interval_us
        return True


class SimLinkServer:
    """Lockstep MAVLink simulator server around a :class:`~twin_nodes.twin.sim.Simulator`.

    >>> srv = SimLinkServer(shipped('px4_sih_quadx'), port=4560, step_s=0.004, on_step=print)
    >>> srv.serve_forever()          # or srv.start_thread(); ...; srv.close()

    ``on_step(info: StepInfo)`` runs in the server thread after every step; an
    exception in it is logged and does not stop the link.  ``port=0`` binds a
    free port (read ``srv.port`` after :meth:`bind`).  ``speed_factor``: the
    pace in multiples of real time (<= 0: unpaced, see the module docstring).
    """

    def __init__(self, vp: VehicleParams, port: int = DEFAULT_PORT, step_s: float = DEFAULT_STEP_S,
                 on_step: Callable[[StepInfo], None] | None = None, *, host: str = DEFAULT_HOST,
                 sensors: SensorConfig | None = None, lockstep_timeout_s: float = 1.0,
                 freewheel: bool = True, max_steps: int | None = None, speed_factor: float = 1.0,
                 rng: np.random.Generator | None = None, takeover_after_s: float = 5.0):
        if not step_s > 0:
            raise ParamsError(vp.source, "step_s", f"expected a link step > 0 s, got {step_s!r}")
        if isinstance(port, bool) or not isinstance(port, (int, np.integer)) or not 0 <= int(port) <= 65535:
            raise TwinError(f"port: expected a TCP port 0..65535 (0 = any free one), got {port!r}")
        ratio = step_s / vp.dt_s
        if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
            raise ParamsError(vp.source, "simulation.dt_s",
                              f"the link step {step_s:g} s must be a whole multiple of dt_s {vp.dt_s:g} s")
        self.vp = vp
        self.host = host
        self.port = int(port)
        self.step_s = float(step_s)
        self.step_us = int(round(step_s * 1e6))
        self.on_step = on_step
        self.lockstep_timeout_s = float(lockstep_timeout_s)
        self.takeover_after_s = float(takeover_after_s)
        self.freewheel = bool(freewheel)
        self.max_steps = max_steps
        self.speed_factor = float(speed_factor)
        self.sensor_config = sensors if sensors is not None else SensorConfig.from_params(vp)
        self.sensors = SensorModel(self.sensor_config, vp.gravity_m_s2, rng)
        self.sim = Simulator(vp, dt_s=vp.dt_s)
        self.n_motors = self.sim.model.n_rotors
        # compile (or load) the numba kernels now, not while PX4 waits for the first step
        stopped = np.full(self.n_motors, np.nan)
        self.sim.model.step(self.sim.state, stopped, vp.dt_s, self.sim.ext, 1)
        self.sim.model.specific_force_flu(self.sim.state, stopped, self.sim.ext)
        self.stats = LinkStats()
        c = self.sensor_config
        self._gps_sched = _Schedule(int(round(1e6 / c.gps_rate_hz)))
        self._mag_sched = _Schedule(int(round(1e6 / c.mag_rate_hz)))
        self._baro_sched = _Schedule(int(round(1e6 / c.baro_rate_hz)))
        self._state_sched = _Schedule(0)  # until PX4 asks for HIL_STATE_QUATERNION
        self._outbox = _Outbox()
        self._mav = mavlink2.MAVLink(self._outbox, srcSystem=_SRC_SYSTEM, srcComponent=_SRC_COMPONENT)
        self._rx = self._new_parser()
        self._lsock: socket.socket | None = None
        self._conn: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lockstep = False
        self._peer_lockstep = True
        self._u = np.full(self.n_motors, np.nan)
        self._pending: deque[np.ndarray] = deque()
        self._pace_wall0 = 0.0
        self._pace_step0 = 0
        self._armed = False
        self._step_count = 0
        self._last_tx_wall = 0.0
        self._last_rx_wall = 0.0
        self._next_wall = 0.0
        self._last_mag = np.zeros(3)
        self._last_baro = (0.0, 0.0, 0.0)

    # ----------------------------------------------------------------- life cycle
    def bind(self) -> int:
        """Create the listening socket; returns the bound port."""
        if self._lsock is None:
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((self.host, self.port))
                s.listen(1)
            except (OSError, OverflowError) as exc:
                s.close()
                why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
                raise TwinError(f"TCP {self.host}:{self.port}: cannot listen: {why}") from None
            self.port = s.getsockname()[1]
            self._lsock = s
            log.info("simulator link listening on TCP %s:%d (step %.1f ms)", self.host, self.port,
                     self.step_s * 1e3)
        return self.port

    def start_thread(self) -> threading.Thread:
        """Bind and serve in a daemon thread."""
        self.bind()
        self._thread = threading.Thread(target=self.serve_forever, name="simlink", daemon=True)
        self._thread.start()
        return self._thread

    def stop(self) -> None:
        """Ask the loop to end (returns at once; the loop notices within 0.1 s)."""
        self._stop.set()

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop, join the thread started by :meth:`start_thread` and close the sockets."""
        self.stop()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
        self._close_sockets()

    @property
    def connected(self) -> bool:
        return self._conn is not None

    @property
    def lockstep(self) -> bool:
        return self._lockstep

    # ----------------------------------------------------------------- main loop
    def serve_forever(self) -> None:
        """Run until :meth:`stop` (or ``max_steps`` steps)."""
        self.bind()
        try:
            while not self._stop.is_set():
                if self.max_steps is not None and self.stats.steps >= self.max_steps:
                    break
                if self._conn is None:
                    ready, _, _ = select.select([self._lsock], [], [], 0.1)
                    if ready:
                        self._accept()
                    continue
                timeout = min(max(self._time_to_next_event(time.monotonic()), 0.0), 0.1)
                ready, _, _ = select.select([self._conn, self._lsock], [], [], timeout)
                if self._lsock in ready:
                    self._accept()
                    continue
                if self._conn in ready:
                    self._read()
                if self._conn is not None:
                    self._advance(time.monotonic())
        finally:
            self._close_sockets()

    @property
    def _paced(self) -> bool:
        return self.speed_factor > 0

    @property
    def _wall_step_s(self) -> float:
        return self.step_s / self.speed_factor if self._paced else self.step_s

    def _stepping_on_clock(self) -> bool:
        return (not self._lockstep and self.freewheel) or (self._lockstep and not self._peer_lockstep)

    def _due_wall(self) -> float:
        """Wall time at which the next lockstep step may run (real time x speed_factor)."""
        return self._pace_wall0 + (self._step_count + 1 - self._pace_step0) * self._wall_step_s

    def _time_to_next_event(self, now: float) -> float:
        if self._stepping_on_clock():
            return self._next_wall - now
        if self._lockstep:
            if self._pending:
                return self._due_wall() - now if self._paced else 0.0
            return self._last_tx_wall + self.lockstep_timeout_s - now
        return 0.1

    def _advance(self, now: float) -> None:
        """Run the steps that are due: owed lockstep steps, clock steps, or a timeout step."""
        if self._stepping_on_clock():
            if now >= self._next_wall:
                self._step(self._u if self._lockstep else np.full(self.n_motors, np.nan))
                self._next_wall += self._wall_step_s
                if now - self._next_wall > 0.25:  # fell behind: don't burst to catch up
                    self._next_wall = now + self._wall_step_s
            return
        if not self._lockstep:
            return
        while self._pending and self._conn is not None:
            if self._paced:
                due = self._due_wall()
                if now < due:
                    return
                if now - due > 0.5:  # PX4 (or we) fell behind real time: don't burst to catch up
                    self._pace_wall0, self._pace_step0 = now, self._step_count
            self._step(self._pending.popleft())
            now = time.monotonic()
        if self._conn is not None and now - self._last_tx_wall >= self.lockstep_timeout_s:
            self.stats.lockstep_timeouts += 1
            log.warning("no HIL_ACTUATOR_CONTROLS for %.1f s: stepping with the last command",
                        self.lockstep_timeout_s)
            self._step(self._u)

    # ----------------------------------------------------------------- sockets
    def _new_parser(self) -> mavlink2.MAVLink:
        mav = mavlink2.MAVLink(None, srcSystem=_SRC_SYSTEM, srcComponent=_SRC_COMPONENT)
        mav.robust_parsing = True
        return mav

    def _accept(self) -> None:
        try:
            conn, addr = self._lsock.accept()
        except OSError:
            return
        if self._conn is not None and not self._peer_closed():
            if time.monotonic() - self._last_rx_wall < self.takeover_after_s:
                # one client flies the twin at a time: whoever else connects is turned away
                self.stats.refused += 1
                log.warning("refused a second client (%s:%d) while one is flying", *addr[:2])
                try:
                    conn.close()
                except OSError:
                    pass
                return
            log.warning("a new client connected (%s:%d); the current one was silent for %.0f s: replacing it",
                        addr[0], addr[1], time.monotonic() - self._last_rx_wall)
            self._disconnect()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._conn = conn
        self._rx = self._new_parser()
        self._lockstep = False
        self._peer_lockstep = True
        self._u = np.full(self.n_motors, np.nan)
        self._pending.clear()
        self._armed = False
        self._state_sched = _Schedule(0)
        self._next_wall = time.monotonic()
        self._last_tx_wall = time.monotonic()
        self._last_rx_wall = time.monotonic()
        self.stats.connections += 1
        log.info("PX4 connected from %s:%d: freewheeling until the first HIL_ACTUATOR_CONTROLS", *addr)

    def _peer_closed(self) -> bool:
        """Take in what the current client has sent; True once it turns out to have closed the
        connection (a PX4 that quits and restarts reconnects at once)."""
        while self._conn is not None:
            try:
                ready, _, _ = select.select([self._conn], [], [], 0)
            except (OSError, ValueError):
                self._disconnect()
                break
            if not ready:
                return False
            self._read()
        return True

    def _disconnect(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError:
                pass
            self._conn = None
            self.stats.disconnects += 1
            log.info("PX4 disconnected at t = %.3f s; waiting for a new connection", self._step_count * self.step_s)
        self._lockstep = False
        self._u = np.full(self.n_motors, np.nan)
        self._pending.clear()
        self._armed = False

    def _close_sockets(self) -> None:
        self._disconnect()
        if self._lsock is not None:
            try:
                self._lsock.close()
            except OSError:
                pass
            self._lsock = None

    def _read(self) -> None:
        try:
            data = self._conn.recv(65536)
        except (ConnectionError, OSError):
            data = b""
        if not data:
            self._disconnect()
            return
        self._last_rx_wall = time.monotonic()
        for msg in self._rx.parse_buffer(data) or ():
            self._handle(msg)
            if self._conn is None:
                return

    def _send(self) -> None:
        data = self._outbox.take()
        if not data or self._conn is None:
            return
        try:
            self._conn.sendall(data)
        except (ConnectionError, OSError):
            self._disconnect()
            return
        self._last_tx_wall = time.monotonic()

    # ----------------------------------------------------------------- messages
    def _handle(self, msg) -> None:
        mtype = msg.get_type()
        if mtype == "HIL_ACTUATOR_CONTROLS":
            self.stats.controls_rx += 1
            self._armed = bool(msg.mode & SAFETY_ARMED)
            self._u = motor_commands_from_controls(msg.controls, msg.mode, self.n_motors)
            peer_lockstep = bool(msg.flags & LOCKSTEP_FLAG)
            if not self._lockstep:
                self._lockstep = True
                self._peer_lockstep = peer_lockstep
                now = time.monotonic()
                self._next_wall = now + self._wall_step_s
                self._pace_wall0, self._pace_step0 = now - self._wall_step_s, self._step_count
                log.info("first HIL_ACTUATOR_CONTROLS at t = %.3f s: %s", self._step_count * self.step_s,
                         "lockstep" if peer_lockstep else "PX4 without lockstep, stepping on the wall clock")
            if self._peer_lockstep:
                self._pending.append(self._u)  # one step owed per command, run by _advance
        elif mtype == "HEARTBEAT":
            self.stats.heartbeats_rx += 1
        elif mtype == "COMMAND_LONG":
            self.stats.commands_rx += 1
            self._handle_command(msg)
        elif mtype == "BAD_DATA":
            self.stats.bad_rx += 1

    def _handle_command(self, msg) -> None:
        if msg.command != mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        if int(msg.param1) == mavlink2.MAVLINK_MSG_ID_HIL_STATE_QUATERNION:
            interval = float(msg.param2)
            if interval < 0:
                self._state_sched = _Schedule(0)
            else:  # 0 = "default rate": every step
                iv = self.step_us if interval == 0 else int(round(interval))
                self._state_sched = _Schedule(iv, self._step_count * self.step_us)
            result = mavlink2.MAV_RESULT_ACCEPTED
        else:
            result = mavlink2.MAV_RESULT_UNSUPPORTED
        self._mav.send(self._mav.command_ack_encode(msg.command, result, 0, 0,
                                                    msg.get_srcSystem(), msg.get_srcComponent()))
        self.stats.acks_tx += 1
        self._send()

    # ----------------------------------------------------------------- stepping
    def _step(self, u: np.ndarray) -> None:
        sim = self.sim
        sim.advance(u, self.step_s)
        self._step_count += 1
        t_us = self._step_count * self.step_us
        x = sim.state
        f_flu = sim.specific_force_flu()
        r_enu_flu = frames.quat_to_rotmat(x[6:10])
        acc, gyro = self.sensors.imu(f_flu, x[10:13])
        fields_updated = FIELDS_ACCEL | FIELDS_GYRO
        mag = baro = None
        if self._mag_sched.due(t_us):
            mag = self._last_mag = self.sensors.mag_from_rotmat(r_enu_flu)
            fields_updated |= FIELDS_MAG
        if self._baro_sched.due(t_us):
            baro = self._last_baro = self.sensors.baro(x[2])
            fields_updated |= FIELDS_BARO
        m = self._mav
        mg, (p_hpa, p_alt, temp_c) = self._last_mag, self._last_baro
        m.send(m.hil_sensor_encode(t_us, acc[0], acc[1], acc[2], gyro[0], gyro[1], gyro[2],
                                   mg[0], mg[1], mg[2], p_hpa, 0.0, p_alt, temp_c, fields_updated, 0))
        self.stats.sensors_tx += 1
        gps_sent = self._gps_sched.due(t_us)
        if gps_sent:
            self._send_gps(t_us, x)
        state_sent = self._state_sched.due(t_us)
        if state_sent:
            self._send_state(t_us, x, f_flu, r_enu_flu)
        self._send()
        if self._lockstep:
            self.stats.lockstep_steps += 1
        else:
            self.stats.freewheel_steps += 1
        self.stats.time_usec = t_us
        if self.on_step is not None:
            info = StepInfo(time_usec=t_us, state=x.copy(), u=np.array(u, float), armed=self._armed,
                            lockstep=self._lockstep, specific_force_flu=f_flu, accel_frd=acc,
                            gyro_frd=gyro, mag_frd=mag, baro=baro, gps_sent=gps_sent,
                            state_sent=state_sent)
            try:
                self.on_step(info)
            except Exception:  # the link must survive a broken consumer
                log.exception("on_step callback failed")

    def _send_gps(self, t_us: int, x: np.ndarray) -> None:
        fix = self.sensors.gps(x[0:3], x[3:6])
        v = fix.vel_ned_m_s
        speed = fix.ground_speed_m_s
        cog = int(round(np.degrees(fix.course_rad) * 100.0)) % 36000 if speed > 0.05 else 65535
        self._mav.send(self._mav.hil_gps_encode(
            t_us, 3, int(round(fix.lat_deg * 1e7)), int(round(fix.lon_deg * 1e7)),
            int(round(fix.alt_m * 1e3)), int(round(fix.eph_m * 100)), int(round(fix.epv_m * 100)),
            min(int(round(speed * 100)), 65534), _i16(v[0] * 100), _i16(v[1] * 100), _i16(v[2] * 100),
            cog, 10, 0, 0))
        self.stats.gps_tx += 1

    def _send_state(self, t_us: int, x: np.ndarray, f_flu: np.ndarray, r_enu_flu: np.ndarray) -> None:
        """HIL_STATE_QUATERNION: the true state (PX4 publishes it as *_groundtruth)."""
        c = self.sensor_config
        q_ned_frd = frames.q_enu_flu_to_ned_frd(x[6:10])
        w_frd = frames.flu_to_frd(x[10:13])
        p_ned = frames.enu_to_ned(x[0:3])
        v_ned = frames.enu_to_ned(x[3:6])
        lat, lon = reproject_ne_to_latlon(p_ned[0], p_ned[1], c.home_lat_deg, c.home_lon_deg)
        # kinematic acceleration in the body frame, in mG (MAVLink units)
        g = self.vp.gravity_m_s2
        a_flu = f_flu - r_enu_flu[2] * g          # R^T [0, 0, g] = g * (third row of R)
        a_frd = frames.flu_to_frd(a_flu)
        v_body = r_enu_flu.T @ x[3:6]
        self._mav.send(self._mav.hil_state_quaternion_encode(
            t_us, [float(v) for v in q_ned_frd], float(w_frd[0]), float(w_frd[1]), float(w_frd[2]),
            int(round(float(lat) * 1e7)), int(round(float(lon) * 1e7)),
            int(round((c.home_alt_m - p_ned[2]) * 1e3)),
            _i16(v_ned[0] * 100), _i16(v_ned[1] * 100), _i16(v_ned[2] * 100),
            min(max(int(round(v_body[0] * 100)), 0), 65535),
            min(int(round(float(np.linalg.norm(x[3:6])) * 100)), 65535),
            _i16(a_frd[0] / g * 1000), _i16(a_frd[1] / g * 1000), _i16(a_frd[2] / g * 1000)))
        self.stats.state_tx += 1


def _i16(v: float) -> int:
    return int(min(max(round(float(v)), _INT16[0]), _INT16[1]))


# --------------------------------------------------------------------------- scripted PX4 stand-in


@dataclass
class PeerStats:
    """What :class:`ScriptedPX4` saw and sent."""

    sensors_rx: int = 0
    gps_rx: int = 0
    state_rx: int = 0
    acks_rx: int = 0
    other_rx: int = 0
    bad_rx: int = 0
    controls_tx: int = 0
    heartbeats_tx: int = 0
    commands_tx: int = 0
    freewheel_sensors_rx: int = 0       # HIL_SENSORs before the first reply
    sensor_time_usec: list[int] = field(default_factory=list)
    sensor_fields: list[int] = field(default_factory=list)
    wall_s: float = 0.0            # whole run, drain included
    lockstep_wall_s: float = 0.0   # from the first reply to the last HIL_SENSOR asked for


class ScriptedPX4:
    """A scripted stand-in for PX4 SITL's ``simulator_mavlink``, for tests and benchmarks.

    It behaves as PX4 does on the simulator interface: connects as a TCP
    client (retrying until the server accepts), sends HEARTBEAT (autopilot 12,
    then once per simulated second) and COMMAND_LONG SET_MESSAGE_INTERVAL for
    HIL_STATE_QUATERNION, stays silent for the first ``freewheel_sensors``
    HIL_SENSORs (PX4 booting), then answers every HIL_SENSOR with one
    HIL_ACTUATOR_CONTROLS (``flags`` = lockstep) whose controls come from
    ``command(t_s) -> (controls, armed)``.  When disarmed the controls are 0,
    as PX4 sends them.
    """

    def __init__(self, port: int, host: str = "127.0.0.1", *,
                 command: Callable[[float], tuple[list[float], bool]] | None = None,
                 freewheel_sensors: int = 5, request_state_interval_us: int = 5000,
                 on_message: Callable[[object], None] | None = None, keep_times: bool = True):
        self.host = host
        self.port = int(port)
        self.command = command or (lambda t: ([0.0] * 4, False))
        self.freewheel_sensors = int(freewheel_sensors)
        self.request_state_interval_us = int(request_state_interval_us)
        self.on_message = on_message
        self.keep_times = keep_times
        self.stats = PeerStats()
        self._sock: socket.socket | None = None
        self._out = _Outbox()
        self._mav = mavlink2.MAVLink(self._out, srcSystem=1, srcComponent=1)
        self._rx = mavlink2.MAVLink(None)
        self._rx.robust_parsing = True
        self._last_hb_us = -(10 ** 12)

    def connect(self, timeout_s: float = 5.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                s = socket.create_connection((self.host, self.port), timeout=1.0)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.01)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.settimeout(2.0)
        self._sock = s

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def _flush(self) -> None:
        data = self._out.take()
        if data:
            self._sock.sendall(data)

    def _heartbeat(self, armed: bool) -> None:
        self._mav.send(self._mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4,
                                                  SAFETY_ARMED if armed else 0, 0, 0))
        self.stats.heartbeats_tx += 1

    def run(self, until_time_s: float, drain_s: float = 0.2) -> PeerStats:
        """Exchange until a HIL_SENSOR stamped >= ``until_time_s`` arrives (not answered),
        then keep reading (without answering) for ``drain_s`` of wall time and return the counts."""
        if self._sock is None:
            self.connect()
        t_wall = time.monotonic()
        st = self.stats
        self._heartbeat(False)
        if self.request_state_interval_us:
            self._mav.send(self._mav.command_long_encode(
                0, 0, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                mavlink2.MAVLINK_MSG_ID_HIL_STATE_QUATERNION, self.request_state_interval_us, 0, 0, 0, 0, 0))
            st.commands_tx += 1
        self._flush()
        until_us = int(round(until_time_s * 1e6))
        done = False
        t_first_reply = time.monotonic()
        while not done:
            data = self._sock.recv(65536)
            if not data:
                raise ConnectionError("simulator closed the connection")
            for msg in self._rx.parse_buffer(data) or ():
                if self._count(msg) and not done:
                    t_us = msg.time_usec
                    if t_us >= until_us:
                        done = True
                    elif st.sensors_rx > self.freewheel_sensors:
                        t_s = t_us * 1e-6
                        controls, armed = self.command(t_s)
                        c16 = [float(v) for v in controls][:16] if armed else []
                        c16 += [0.0] * (16 - len(c16))
                        if t_us - self._last_hb_us >= 1_000_000:
                            self._heartbeat(armed)
                            self._last_hb_us = t_us
                        self._mav.send(self._mav.hil_actuator_controls_encode(
                            t_us, c16, 1 | (SAFETY_ARMED if armed else 0), LOCKSTEP_FLAG))
                        st.controls_tx += 1
                        if st.controls_tx == 1:
                            t_first_reply = time.monotonic()
                        self._flush()
                    else:
                        st.freewheel_sensors_rx += 1
        if st.controls_tx:
            st.lockstep_wall_s = time.monotonic() - t_first_reply
        deadline = time.monotonic() + drain_s
        try:
            while (left := deadline - time.monotonic()) > 0:
                self._sock.settimeout(left)
                data = self._sock.recv(65536)
                if not data:
                    break
                for msg in self._rx.parse_buffer(data) or ():
                    self._count(msg)
        except (socket.timeout, TimeoutError):
            pass
        self._sock.settimeout(2.0)
        st.wall_s = time.monotonic() - t_wall
        return st

    def _count(self, msg) -> bool:
        """Count a received message; True for a HIL_SENSOR."""
        st = self.stats
        mtype = msg.get_type()
        if self.on_message is not None:
            self.on_message(msg)
        if mtype == "HIL_SENSOR":
            st.sensors_rx += 1
            if self.keep_times:
                st.sensor_time_usec.append(msg.time_usec)
                st.sensor_fields.append(msg.fields_updated)
            return True
        if mtype == "HIL_GPS":
            st.gps_rx += 1
        elif mtype == "HIL_STATE_QUATERNION":
            st.state_rx += 1
        elif mtype == "COMMAND_ACK":
            st.acks_rx += 1
        elif mtype == "BAD_DATA":
            st.bad_rx += 1
        else:
            st.other_rx += 1
        return False
