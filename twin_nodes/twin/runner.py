"""The twin beside a real vehicle: one streaming engine for the ROS node and offline runs.

Two ways to shadow the real vehicle:

``closed``  the PX4-like controller flies the real flight's setpoints (PX4
            ``trajectory_setpoint``; where a log has none, the real position as a
            position setpoint), armed when the real vehicle is armed.  The twin's
            own throttle and motor commands are then compared with the real ones
            (the Búho Negro paper's method, with our controller in PX4's place).
``open``    the real motor commands drive the model and the state is re-synced to
            the real state every ``horizon_s`` (the second reference's method);
            the prediction error over each horizon is the comparison.

:class:`TwinRunner` consumes time-ordered inputs (``real_state``, ``setpoint``,
``real_motors``, ``armed``, ``battery``) and ``advance_to(t)`` returns the twin's
outputs at its control rate.  :func:`run_twin_on_log` feeds a whole
:class:`~twin_nodes.logs.ulog_io.FlightLog` through the same engine.

The runner's parts live beside it: which PX4 mode is flown how, and where PX4 held the position
(:mod:`twin_nodes.twin.flight_mode`); the ground plane, PX4's grounded phases and its take-off ramp
(:mod:`twin_nodes.twin.ground`); a whole log's inputs on the control grid (:mod:`twin_nodes.twin.inputs`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from twin_nodes.twin.control import SP_SIZE
from twin_nodes.twin.controllers import make_controller
from twin_nodes.vehicle.params import VehicleParams
from twin_nodes.physics.core import NX_BODY
from twin_nodes.physics.model import Multirotor
from twin_nodes.twin.sim import DelayLine
from twin_nodes.twin.pilot import PilotStandIn
from twin_nodes.twin.flight_mode import ALTCTL_NAV_STATE, fly_mode, fly_modes
from twin_nodes.twin.ground import TAKEOFF_RAMP_S, GroundHandling, log_takeoff_ramp_s
from twin_nodes.twin.inputs import log_feed
from twin_nodes.twin.estimate_check import height_reset_shift
from twin_nodes.logs.ulog_io import MANUAL_NAV_STATES

MODES = ("closed", "open")
__all__ = ["MODES", "TwinSample", "TwinRunner", "TwinRun", "run_twin_on_log"]


@dataclass
class TwinSample:
    t: float
    x: np.ndarray          # (nx,) twin state, ENU/FLU
    motors: np.ndarray     # (N,) motor commands the twin used (0..1, NaN stopped)
    throttle: float        # collective throttle (PX4 thrust-setpoint convention)
    specific_force: np.ndarray  # (3,) FLU
    resynced: bool = False


#: the real state's horizontal position and velocity columns (may be unknown: no GPS) and the rest
_HORIZONTAL = (0, 1, 3, 4)
_NON_HORIZONTAL = np.array([2, 5, 6, 7, 8, 9, 10, 11, 12])


class TwinRunner(GroundHandling):
    """Streaming twin.  Feed inputs in time order, call ``advance_to(t)``.  Its ground handling (the ground
    plane, grounded phases, take-off ramp) is :class:`~twin_nodes.twin.ground.GroundHandling`."""

    def __init__(self, vp: VehicleParams, mode: str = "closed", horizon_s: float = 2.0,
                 rate_hz: float | None = None, pilot: bool = True):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        self.params = vp
        self.mode = mode
        self.horizon_s = float(horizon_s)
        self.model = Multirotor(vp)
        # the controller knows the twin as it is (parameter-type effects applied), as PX4 knows
        # the real vehicle through its hover-thrust estimate
        # (the SE(3) law believes the params as given: its mass and inertia, not the fitted physics)
        self.ctrl = make_controller(self.model.params, believed=vp)
        self.rate_hz = float(rate_hz or self.ctrl.gains.rate_hz)
        self.dt_c = 1.0 / self.rate_hz
        self.nsub = max(int(round(self.dt_c / vp.dt_s)), 1)
        self.dt = self.dt_c / self.nsub
        n = self.model.n_rotors
        self.n = n
        self.t: float | None = None
        self.x = self.model.initial_state()
        # steady exogenous inputs from the params' effects (a steady wind); the battery voltage is fed in
        self.ext = self.model.exogenous(np.zeros(1))[0]
        self.sp = np.full(SP_SIZE, np.nan)
        self._sp_raw = np.full(SP_SIZE, np.nan)  # the last setpoint sample as given (before the ground shift)
        self.real_x: np.ndarray | None = None
        self.real_u = np.full(n, np.nan)
        self.is_armed: bool | None = None  # None: no armed state received yet
        self.u = np.full(n, np.nan)
        self.throttle = float("nan")
        self.last_resync = -np.inf
        self._delay = DelayLine(self.model.command_delay_s, self.dt_c, np.full(n, np.nan))
        self._initialised = False
        #: real-frame height of the twin's ground plane [m, ENU up]: the physics has its ground at
        #: z = 0, PX4's EKF origin is often not at ground level (a log may start at z = -3.8 m NED)
        self.ground_z = 0.0
        #: when the current translational (sp[0:9]) and yaw (sp[9:11]) samples arrived: they are
        #: carried on from there separately (a log may carry the yaw at 20 Hz, the position at 5 Hz)
        self.sp_t: float | None = None
        self.yaw_t: float | None = None
        #: the current setpoint sample's (moving, velocity, half the acceleration, has a position or
        #: velocity target), made when first carried
        self._sp_rates: tuple | None = None
        self._sp_ground_z: float | None = None  # the ground height self.sp was shifted by
        #: PX4 nav_state of the real vehicle (NaN unknown) and its logged collective thrust setpoint
        self.nav_state = float("nan")
        self.real_throttle = float("nan")
        #: PX4's own attitude setpoint (``vehicle_attitude_setpoint``: q_d FLU->ENU, collective thrust,
        #: yaw-rate feed-forward), its rate setpoint (FLU) and the offboard flags (NaN: not logged)
        self.att_q = np.full(4, np.nan)
        self.att_thrust = float("nan")
        self.att_yawrate = float("nan")
        self.rates_sp = np.full(3, np.nan)
        self.offboard_flags = np.full(6, np.nan)
        #: PX4's take-off ramp (``Takeoff::updateRamp``): its length [s] (the log's MPC_TKO_RAMP_T) and
        #: progress 0..1 (1: flying; set to 0 by a grounded phase, so a log started in the air has none)
        self.takeoff_ramp_s = TAKEOFF_RAMP_S
        self.ramp = 1.0
        #: the real vehicle has left the ground since the twin last rested on it (see _held_with_vehicle)
        self._lifted = True
        #: how the last control step was flown (:data:`~twin_nodes.twin.flight_mode.FLOWN_AS`)
        self.flown_as = ""
        #: the pilot stand-in for the vertical axis in PX4's manual modes (None: the logged thrust alone)
        self.pilot = PilotStandIn(self.model.params.hover_command, vp.gravity_m_s2) if pilot else None
        #: the real height the pilot stand-in follows, less the real state's [m]: the resets of the vehicle's
        #: height estimate taken out (minus :func:`~twin_nodes.twin.estimate_check.height_reset_shift`)
        self.pilot_shift_m = 0.0
        #: the offline run's per-row decision (:func:`~twin_nodes.twin.flight_mode.fly_modes`): what PX4 flies
        #: and whether its attitude setpoint is all finite, for the inputs now held (None: decided per step)
        self._row_mode: tuple[str, bool] | None = None
        #: ... and its setpoint sample's carried terms (as ``_sp_rates``; None: made from ``sp`` when first carried)
        self._row_rates: tuple | None = None

    # ---------------------------------------------------------------- inputs
    def real_state(self, t: float, p_enu, v_enu, q_wxyz, w_flu) -> None:
        x = np.concatenate([np.asarray(p_enu, float), np.asarray(v_enu, float),
                            np.asarray(q_wxyz, float), np.asarray(w_flu, float)])
        self._take_real_state(t, x, bool(np.all(np.isfinite(x))))

    def _take_real_state(self, t: float, x: np.ndarray, finite: bool) -> None:
        """The real state ``x`` (13,) [p, v, q, w], a float array of the caller's that this keeps and
        shifts; ``finite``: all of it is finite (a sample with a NaN is ignored)."""
        if not finite:
            if not np.isfinite(x[_NON_HORIZONTAL]).all():
                return
            # no horizontal position/velocity (no GPS, or the EKF's horizontal estimate invalid): the
            # last known ones (at the start 0), so that the twin flies on what the flight has; XY is not
            # scored where the real one is unknown
            prev = self.real_x if self.real_x is not None else np.zeros(13)
            for k in _HORIZONTAL:
                if not math.isfinite(x[k]):
                    x[k] = prev[k]
        self._to_ground_frame(x)
        self.real_x = x
        if not self._initialised:
            self._start(t)

    def setpoint(self, sp: np.ndarray) -> None:
        sp = np.asarray(sp, float)
        if sp.shape != (SP_SIZE,):
            raise ValueError(f"setpoint must have {SP_SIZE} entries")
        self._take_setpoint(sp, False)

    def _take_setpoint(self, sp: np.ndarray, repeated: bool, same: tuple[bool, bool] | None = None) -> None:
        """The setpoint sample ``sp`` (SP_SIZE,), not modified; ``repeated``: bit for bit the sample of
        the previous call (then nothing changes while the ground height has not); ``same``: whether its
        trajectory (sp[0:9]) and its yaw (sp[9:11]) equal the previous call's (NaN = NaN) where the caller
        knows (the offline run compares all rows at once, :func:`_same_as_previous`)."""
        if repeated and self._sp_ground_z == self.ground_z:
            return
        # a new sample is one whose logged values differ (the same sample taken again in a moved ground
        # plane's frame keeps its time: its trajectory is carried on from where it was logged)
        if same is None:
            new, old = sp.tolist(), self._sp_raw.tolist()
            same = _same(new[0:9], old[0:9]), _same(new[9:11], old[9:11])
        if not same[0]:
            self.sp_t = self.t  # a new setpoint sample: the trajectory is carried on from here
            self._sp_rates = None  # its velocity and acceleration terms, made when first carried
        if not same[1]:
            self.yaw_t = self.t  # a new yaw sample: carried by its feed-forward from here
            self._sp_rates = None
        self._sp_raw = sp.copy()
        sp = sp.copy()
        sp[2] -= self.ground_z
        self.sp = sp
        self._sp_ground_z = self.ground_z

    def real_motors(self, u) -> None:
        self.real_u = np.asarray(u, float)

    def armed(self, armed: bool | float | None) -> None:
        """The real vehicle's armed state; None or NaN: not known (no armed message yet: a log or a link
        that starts in the air), flown as armed (PX4's zero thrust on the ground still holds the twin)."""
        if armed is None or (isinstance(armed, float) and armed != armed):
            self.is_armed = None
        else:
            self.is_armed = bool(armed)

    def px4_mode(self, nav_state: float, throttle: float = float("nan")) -> None:
        """The real vehicle's PX4 ``nav_state`` and collective thrust setpoint (0..1).  In PX4's manual
        modes (:data:`MANUAL_NAV_STATES`) the position controller does not run: the twin then flies
        the pilot's thrust and the real attitude (see :attr:`manual`)."""
        self.nav_state = float(nav_state)
        self.real_throttle = float(throttle)

    def attitude_setpoint(self, q_wxyz, thrust: float = float("nan"), yawrate: float = float("nan")) -> None:
        """PX4's attitude setpoint (``vehicle_attitude_setpoint``; q FLU->ENU): the pilot's attitude in
        MANUAL/STABILIZED, the stick's tilt and the yaw in ALTCTL, an offboard attitude."""
        self.att_q = np.asarray(q_wxyz, float).reshape(4)
        self.att_thrust = float(thrust)
        self.att_yawrate = float(yawrate)

    def rate_setpoint(self, w_flu) -> None:
        """PX4's body-rate setpoint (``vehicle_rates_setpoint``, FLU rad/s): flown in ACRO."""
        self.rates_sp = np.asarray(w_flu, float).reshape(3)

    def offboard_mode(self, flags) -> None:
        """``offboard_control_mode`` flags (position, velocity, acceleration, attitude, body_rate, thrust)."""
        self.offboard_flags = np.asarray(flags, float).reshape(6)

    def _fly_mode(self) -> str:
        """What PX4 flies now, by ``nav_state`` and what the log carries
        (:func:`~twin_nodes.twin.flight_mode.fly_mode`; the offline run decides it once per row)."""
        if self._row_mode is not None:
            return self._row_mode[0]
        return fly_mode(self.nav_state, self.real_throttle, self.att_q, self.att_thrust, self.rates_sp,
                        self.offboard_flags, self.sp, self.real_x is not None)

    @property
    def manual(self) -> bool:
        return (self.nav_state in MANUAL_NAV_STATES and math.isfinite(self.real_throttle)
                and self.real_x is not None)

    def battery(self, volts: float) -> None:
        self.ext[0] = volts

    def restart(self) -> None:
        """The real vehicle restarted (new EKF origin, reboot): no twin output until the next real
        state, which starts the twin afresh from it (the old state is never carried across)."""
        self._initialised = False

    # ---------------------------------------------------------------- stepping
    def _start(self, t: float) -> None:
        rx = self.real_x
        self.x = self.model.initial_state(position_enu=rx[0:3], velocity_enu=rx[3:6], q_wxyz=rx[6:10],
                                          rates_flu=rx[10:13])
        self.t = float(t)
        self.last_resync = float(t)
        self._initialised = True

    def _resync(self) -> None:
        rx = self.real_x
        self.x[:13] = rx
        # rotor speeds are not logged: take the steady state of the last real command
        self.x[NX_BODY:] = self.params.rotors.reference_from_command(self.real_u)
        self.last_resync = self.t

    def advance_to(self, t: float) -> list[TwinSample]:
        """Step the twin up to time ``t`` at its control rate; one sample per control step."""
        out: list[TwinSample] = []
        if not self._initialised or self.t is None:
            return out
        while self.t + self.dt_c <= t + 1e-9:
            resynced, applied = self._step()
            x_real_frame = self.x.copy()
            x_real_frame[2] += self.ground_z
            out.append(TwinSample(self.t, x_real_frame, self.u.copy(), self.throttle,
                                  self.model.specific_force_unchecked(self.x, applied, self.ext), resynced))
        return out

    def _step(self) -> tuple[bool, np.ndarray]:
        """One control step: the command (``self.u``, ``self.throttle``), then the physics
        (``self.x``, ``self.t``); returns (re-synced, the command the rotors got after the delay)."""
        resynced = False
        if self.mode == "open":
            if self.real_u.shape != (self.n,):  # the model's unchecked step below needs the vehicle's motor count
                raise ValueError(f"expected {self.n} motor commands, got shape {self.real_u.shape}")
            if self.real_x is not None and self.t - self.last_resync >= self.horizon_s - 1e-9:
                self._resync()
                resynced = True
            u = self.real_u.copy()
            mean_u = np.nanmean(u) if np.any(np.isfinite(u)) else np.nan
            self.throttle = float(mean_u)
        else:
            how = self._fly_mode() if self.is_armed is not False else "disarmed"
            if how == "cascade" and self._px4_grounded():
                how = "grounded"
            thr = self.real_throttle if math.isfinite(self.real_throttle) else self.att_thrust
            thr = self._piloted(how, thr)
            if how == "attitude":
                # PX4 MANUAL/STAB (or offboard attitude): no position controller; PX4's attitude
                # setpoint (the pilot's sticks) and collective thrust through the attitude and rate loops
                u, info = self.ctrl.update_manual(self.x[:13], self.att_q, thr, self.dt_c, yawspeed=self.att_yawrate)
            elif how == "rates":
                # ACRO (or offboard rates): the logged rate setpoint straight to the rate loop
                u, info = self.ctrl.update_manual(self.x[:13], None, thr, self.dt_c, rates=self.rates_sp)
            elif how == "real_attitude":
                # a manual mode in a log without an attitude setpoint: the real attitude stands for it
                u, info = self.ctrl.update_manual(self.x[:13], self.real_x[6:10], thr, self.dt_c)
            elif how == "cascade":
                q_ok = self._row_mode[1] if self._row_mode is not None else bool(np.isfinite(self.att_q).all())
                q_att = self.att_q if q_ok else None
                sp = self._effective_setpoint()
                if sp[9] != sp[9] and sp[10] != sp[10] and math.isfinite(self.att_yawrate):
                    # no yaw setpoint (the pilot yawing in POSCTL/ALTCTL): PX4 holds its current heading and
                    # feeds the stick's yaw rate forward, logged as the attitude setpoint's yaw_sp_move_rate
                    sp = sp.copy()
                    sp[10] = self.att_yawrate
                if self.ramp < 1.0 and self.ctrl.law == "px4":  # PX4's take-off ramp; other laws have none
                    u, info = self._ramped_update(sp, q_att)
                elif self.ctrl.law == "px4":
                    # the runner's own float64 arrays: the controller's unchecked entry point
                    u, info = self.ctrl.update_unchecked(self.x[:13], sp, self.dt_c, q_att)
                else:
                    u, info = self.ctrl.update(self.x[:13], sp, self.dt_c, q_att=q_att)
            elif how == "grounded":
                # PX4 before its take-off ramp or with ground contact: zero thrust, integrators reset
                self.ctrl.reset()
                self.ramp = 0.0
                u, info = np.zeros(self.n), np.zeros(1)
            else:
                self.ctrl.reset()
                u, info = np.full(self.n, np.nan), np.full(1, np.nan)
            self.flown_as = how
            self.throttle = float(info[0])
        self.u = u
        applied = self._delay.push(u)
        # the runner's own arrays (float64, checked shapes): the model's unchecked entry point
        self.x = self.model.step_unchecked(self.x, applied, self.dt, self.ext, self.nsub)
        self.t += self.dt_c
        if self.mode != "open" and self.flown_as in ("grounded", "disarmed") and self.real_x is not None:
            self._hold_on_ground()
            self._lifted = False
        elif self.mode != "open" and self.real_x is not None:
            self._held_with_vehicle()
        return resynced, applied

    def _piloted(self, how: str, thr: float) -> float:
        """The collective thrust a pilot would give the twin: in PX4's manual modes the logged thrust plus the
        stand-in's slow correction holding the real vehicle's height (:mod:`twin_nodes.twin.pilot`)."""
        p = self.pilot
        if p is None:
            return thr
        if how not in ("attitude", "rates", "real_attitude") or self.nav_state not in MANUAL_NAV_STATES \
                or not math.isfinite(thr):
            p.reset()
            return thr
        return thr + p.update(self.x[2], self.x[5], self.real_x[2] + self.pilot_shift_m, self.real_x[5], self.dt_c)

    def _carried_setpoint(self) -> np.ndarray:
        """The position setpoint carried along by the velocity and acceleration setpoints since the
        last setpoint sample: PX4's trajectory is smooth at the controller rate, its log (and the
        /real topic) a 5-25 Hz subsample of it; a held staircase makes the twin chase 1 m steps at
        5 m/s.  The yaw likewise by its yaw-rate feed-forward (``sp[10]``), from its own sample time (the
        reader takes it from the 20 Hz attitude setpoint where PX4 logs one).  Never carried more than
        1 s (a logging gap)."""
        sp = self.sp
        if (self.sp_t is None and self.yaw_t is None) or self.t is None:
            return sp
        if self._sp_rates is None and self._row_rates is not None:
            self._sp_rates = self._row_rates  # the offline run's, made for all rows at once (the same values)
        elif self._sp_rates is None:
            # once per setpoint sample, not per control step (the sample is held for 10-50 steps)
            finite = np.isfinite(sp[0:9])
            turning = bool(math.isfinite(sp[9]) and math.isfinite(sp[10]) and sp[10] != 0.0)
            # np.nan_to_num only where a value is not finite (per step: its call costs more than the step)
            # as plain floats (the per-step arithmetic below on 3-vectors costs more in numpy calls than in
            # float operations; each operation is the same IEEE one, so the same numbers)
            vel = (sp[3:6] if finite[3:6].all() else np.nan_to_num(sp[3:6])).tolist()
            acc = (sp[6:9] if finite[6:9].all() else np.nan_to_num(sp[6:9])).tolist()
            half_acc = [0.5 * a for a in acc]
            self._sp_rates = (bool(finite[3:6].any()), vel, half_acc, bool(finite[0:6].any()), turning)
        moving, vel, half_acc, _, turning = self._sp_rates
        if not (moving or turning):
            return sp
        out = sp.copy()
        if moving and self.sp_t is not None:
            dt = min(max(self.t - self.sp_t, 0.0), 1.0)
            p0, p1, p2 = sp[0:3].tolist()
            # sp[0:3] + vel * dt + half_acc * dt * dt, element by element (the same operations in the same order)
            out[0] = p0 + vel[0] * dt + half_acc[0] * dt * dt
            out[1] = p1 + vel[1] * dt + half_acc[1] * dt * dt
            out[2] = p2 + vel[2] * dt + half_acc[2] * dt * dt
        if turning and self.yaw_t is not None:
            # the yaw setpoint carried by its yaw-rate feed-forward, as PX4's flight task integrates it
            # at the controller rate (held, it would lag the feed-forward and pull the yaw back)
            dt = min(max(self.t - self.yaw_t, 0.0), 1.0)
            out[9] = (sp[9] + sp[10] * dt + np.pi) % (2.0 * np.pi) - np.pi
        return out

    def _effective_setpoint(self) -> np.ndarray:
        sp = self._carried_setpoint()
        # a position or velocity target (the carried position is finite where the sample's is)
        target = self._sp_rates[3] if self._sp_rates is not None else (
            bool(np.any(np.isfinite(sp[0:3])) or np.any(np.isfinite(sp[3:6]))))
        if not target:
            # no position or velocity setpoint (manual modes, old logs): fly the real position; in ALTCTL
            # with PX4's attitude setpoint logged, its real height only (the tilt is the pilot's)
            sp = sp.copy()
            if self.real_x is not None:
                altctl = self.nav_state == ALTCTL_NAV_STATE and bool(np.isfinite(self.att_q).all())
                if altctl:
                    sp[2] = self.real_x[2]
                else:
                    sp[0:3] = self.real_x[0:3]
                if not np.isfinite(sp[9]):
                    q = self.real_x[6:10]
                    sp[9] = np.arctan2(2 * (q[0] * q[3] + q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2))
        return sp


def _same(a: list, b: list) -> bool:
    """``np.array_equal(a, b, equal_nan=True)`` for two equally long lists of floats (the setpoint's
    entries, compared every control step: a numpy call costs more than the comparison)."""
    for x, y in zip(a, b):
        if x != y and (x == x or y == y):  # differ, and not both NaN
            return False
    return True


#: rows of a log whose per-row decisions and scalars are made at once (as Python objects, ~0.3 kB a row: made
#: for every row of a 1-hour log at once they took ~0.5 GB; ``make bench``'s memory budget found it)
ROW_CHUNK = 4096


def _row_decisions(feed, chunk: int = ROW_CHUNK):
    """What the closed-loop runner decides from each row of a log's feed (:class:`~twin_nodes.twin.inputs.LogFeed`)
    alone, made ``chunk`` rows at a time and yielded row by row: (what PX4 flies,
    :func:`~twin_nodes.twin.flight_mode.fly_modes`; its attitude setpoint all finite; (the trajectory sp[0:9] the
    same as the row before, the yaw sp[9:11] the same), as :meth:`TwinRunner._take_setpoint` compares them; the
    row's carried terms as :meth:`TwinRunner._carried_setpoint` makes them: (moving, velocity, half the
    acceleration, a position or velocity target, turning), none changed by the ground plane's shift of sp[2]).
    The same values the runner makes per control step (``tests/test_fleet_speed.py``), without a numpy call per
    step."""
    sp = feed.sp
    same_traj, same_yaw = _same_as_previous(sp[:, 0:9]), _same_as_previous(sp[:, 9:11])
    fin = np.isfinite(sp)
    moving, target = fin[:, 3:6].any(axis=1), fin[:, 0:6].any(axis=1)
    turning = fin[:, 9] & fin[:, 10] & (sp[:, 10] != 0.0)
    for c0 in range(0, len(sp), chunk):
        s = slice(c0, c0 + chunk)
        modes, q_ok = fly_modes(feed.nav_state[s], feed.throttle[s], feed.att_q[s], feed.att_thrust[s],
                                feed.rates_sp[s], feed.offboard[s], sp[s])
        same = zip(same_traj[s].tolist(), same_yaw[s].tolist())
        rates = zip(moving[s].tolist(), np.nan_to_num(sp[s, 3:6]).tolist(),
                    (0.5 * np.nan_to_num(sp[s, 6:9])).tolist(), target[s].tolist(), turning[s].tolist())
        yield from zip(modes, q_ok, same, rates)


def _row_scalars(columns: list, chunk: int = ROW_CHUNK):
    """Each row of the equal-length 1-d ``columns`` as a tuple of Python scalars (the same values), made
    ``chunk`` rows at a time, plus the first column's next value (None after the last row)."""
    n = len(columns[0])
    for c0 in range(0, n, chunk):
        c1 = min(c0 + chunk, n)
        cols = [np.asarray(c[c0:c1]).tolist() for c in columns]
        nxt = np.asarray(columns[0][c0 + 1:c1 + 1]).tolist()
        nxt += [None] * (c1 - c0 - len(nxt))  # the last row has no next
        yield from zip(*cols, nxt)


def _same_as_previous(rows: np.ndarray) -> np.ndarray:
    """For each row of ``rows`` (n, k): :func:`_same` with the row before it (the first against a row of NaN,
    the runner's setpoint before any sample)."""
    if not len(rows):
        return np.zeros(0, bool)
    prev = np.vstack([np.full((1, rows.shape[1]), np.nan), rows[:-1]])
    return ((rows == prev) | (np.isnan(rows) & np.isnan(prev))).all(axis=1)


@dataclass
class TwinRun:
    """Twin outputs on its own control-rate grid, ready for alignment with the real log."""

    t: np.ndarray
    x: np.ndarray
    motors: np.ndarray
    throttle: np.ndarray
    specific_force: np.ndarray
    mode: str
    info: dict = field(default_factory=dict)


def run_twin_on_log(log, vp: VehicleParams, mode: str = "closed", horizon_s: float = 2.0,
                    t0: float | None = None, t1: float | None = None, progress: bool = False,
                    pilot: bool = True, setpoint_between_samples: bool = True) -> TwinRun:
    """Run the twin beside a whole log (offline), returning its outputs on the control grid (``pilot``: the
    vertical pilot stand-in in manual modes, :mod:`twin_nodes.twin.pilot`; ``setpoint_between_samples``: the
    logged setpoint trajectory read between its samples, :func:`~twin_nodes.twin.inputs.log_inputs`; False:
    each sample held and carried, as the live twin in the graph gets them)."""
    runner = TwinRunner(vp, mode, horizon_s, pilot=pilot)
    ramp_s = log_takeoff_ramp_s(log)
    if ramp_s is not None:
        runner.takeoff_ramp_s = ramp_s
    feed = log_feed(log, runner.rate_hz, t0, t1, between_samples=setpoint_between_samples)
    t, X, finite, U, sp, repeated = feed.t, feed.x, feed.finite, feed.motors, feed.sp, feed.repeated
    armed, batt, nav, thr = feed.armed, feed.battery_v, feed.nav_state, feed.throttle
    att_q, att_thr, att_yr = feed.att_q, feed.att_thrust, feed.att_yawrate
    rates_sp, offb = feed.rates_sp, feed.offboard
    n = len(t)
    model = runner.model
    # the height the pilot stand-in follows: the estimate without its resets
    dz_ref = -height_reset_shift(log, np.asarray(t, float))
    # the outputs go into arrays made for the whole run (one row per control step) rather than lists of
    # per-step arrays (~0.5 kB a step in objects, then copied once more: 0.9 GB on a 1-hour flight)
    out = _Rows(n_steps=int((t[-1] - t[0]) * runner.rate_hz) + 2 if n else 0, nx=model.nx, n=runner.n)
    flown: dict[str, int] = {}
    it = range(n)
    if progress:
        from tqdm import tqdm
        it = tqdm(it, desc=f"twin ({mode} loop)", unit="step", mininterval=0.5, leave=False)
    # each row's decisions and scalars as Python objects, made a chunk of rows at a time (None: decided per
    # control step, as the live twin decides them)
    rows = _row_decisions(feed) if mode == "closed" and n else None
    U = np.asarray(U, float)
    scalars = _row_scalars([t, finite, repeated, armed, np.asarray(nav, float), np.asarray(thr, float),
                            dz_ref, np.asarray(batt, float)])
    for k, (t_k, finite_k, repeated_k, armed_k, nav_k, thr_k, dz_k, b, t_after) in zip(it, scalars):
        runner._take_real_state(t_k, X[k].copy(), finite_k)
        runner.real_u = U[k]
        if rows is not None:
            how, q_ok, same, runner._row_rates = next(rows)
            runner._row_mode = (how, q_ok)
            runner._take_setpoint(sp[k], repeated_k, same)
        else:
            runner._take_setpoint(sp[k], repeated_k)
        runner.armed(armed_k)
        runner.nav_state, runner.real_throttle = nav_k, thr_k
        runner.att_q, runner.att_thrust, runner.att_yawrate = att_q[k], att_thr[k], att_yr[k]
        runner.rates_sp, runner.offboard_flags = rates_sp[k], offb[k]
        runner.pilot_shift_m = dz_k
        if b == b and b not in (math.inf, -math.inf):
            runner.battery(b)
        if t_after is not None and runner._initialised and runner.t is not None:
            # advance_to(t[k + 1]) without its per-sample objects (the same steps, the same numbers)
            t_next = t_after + 1e-9
            while runner.t + runner.dt_c <= t_next:
                _, applied = runner._step()
                flown[runner.flown_as] = flown.get(runner.flown_as, 0) + 1
                out.add(runner.t, runner.x, runner.u, runner.throttle,
                        model.specific_force_unchecked(runner.x, applied, runner.ext), runner.ground_z)
    out_t, out_x, out_u, out_thr, out_sf, out_ground = out.arrays()
    if len(out_x):
        # the twin's ground at each step, in the real frame (the take-off height; it moves only while the
        # vehicle is held on the ground, see TwinRunner._hold_on_ground)
        out_x[:, 2] += out_ground
    return TwinRun(t=out_t, x=out_x, motors=out_u, throttle=out_thr, specific_force=out_sf, mode=mode,
                   info={"rate_hz": runner.rate_hz, "horizon_s": horizon_s, "params": vp.name,
                         "ground_z": float(out_ground[0]) if len(out_ground) else runner.ground_z,
                         "ground_z_t": out_ground,
                         "flown_as_s": {k: v / runner.rate_hz for k, v in flown.items() if k},
                         "pilot": runner.pilot.summary() if runner.pilot is not None else None})


class _Rows:
    """The offline run's per-step outputs, written into preallocated float64 arrays (grown by half
    if the estimate was short); :meth:`arrays` gives the rows of the steps taken (views, no copy)."""

    def __init__(self, n_steps: int, nx: int, n: int):
        self.k = 0
        self.cols = (None, nx, n, None, 3, None)
        self.a = [np.empty((max(n_steps, 1),) + ((c,) if c else ())) for c in self.cols]

    def add(self, t: float, x: np.ndarray, u: np.ndarray, throttle: float, sf: np.ndarray, ground: float) -> None:
        k = self.k
        if k == len(self.a[0]):
            grow = len(self.a[0]) // 2 + 1
            self.a = [np.concatenate([a, np.empty((grow,) + a.shape[1:])]) for a in self.a]
        a_t, a_x, a_u, a_thr, a_sf, a_ground = self.a  # one row written column by column (the same values)
        a_t[k], a_x[k], a_u[k], a_thr[k], a_sf[k], a_ground[k] = t, x, u, throttle, sf, ground
        self.k = k + 1

    def arrays(self) -> list[np.ndarray]:
        return [a[:self.k] for a in self.a]
