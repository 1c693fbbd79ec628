"""The twin on the ground: its ground plane, PX4's grounded phases and its take-off ramp.

The physics has its ground at z = 0; the real vehicle's heights are measured from PX4's EKF origin, which
is often not at ground level.  :class:`GroundHandling` (a part of
:class:`~twin_nodes.twin.runner.TwinRunner`) keeps the twin's ground plane at the real take-off height
(``ground_z``, real frame, ENU up), moves it where the real vehicle shows the ground elsewhere, holds the
twin at rest while PX4 commands no thrust, and flies PX4's take-off ramp after such a phase.
"""

from __future__ import annotations

import math

import numpy as np

from twin_nodes.base.constants import G_STANDARD_M_S2, LEFT_GROUND_M
from twin_nodes.physics.core import NX_BODY
from twin_nodes.twin.control import G_ZV_P, G_ZV_UP

__all__ = ["GROUNDED_THRUST", "GROUNDED_ENTER_M", "HELD_M", "TAKEOFF_RAMP_S", "G_ACC", "GroundHandling",
           "log_takeoff_ramp_s"]

#: a logged collective thrust setpoint at or below this (0..1) in PX4's position-controlled modes: PX4
#: commands no thrust, which it does only before its take-off ramp (``TakeoffHandling`` state below
#: ``rampup``) or with ground contact after a touchdown (``mc_pos_control``: ``not_taken_off ||
#: flying_but_ground_contact``: zero thrust, integrators reset); in flight its thrust is at least MPC_THR_MIN
GROUNDED_THRUST = 0.02
#: ... entered only with the real vehicle within this height [m] of the twin's ground plane
GROUNDED_ENTER_M = 0.5
#: the real vehicle above its ground plane by more than this has left the ground [m] (``base.constants``)
HELD_M = LEFT_GROUND_M
#: PX4's take-off ramp (``MPC_TKO_RAMP_T``, 3 s by default since PX4 1.12): from the end of a grounded
#: phase the upward velocity limit goes from -g / MPC_Z_VEL_P_ACC (zero thrust) to MPC_Z_VEL_MAX_UP
TAKEOFF_RAMP_S = 3.0
G_ACC = G_STANDARD_M_S2


def log_takeoff_ramp_s(log) -> float | None:
    """The log's take-off ramp length [s] (its ``MPC_TKO_RAMP_T``), None where it has none usable."""
    ramp_s = (getattr(log, "params", None) or {}).get("MPC_TKO_RAMP_T")
    if ramp_s is not None and math.isfinite(float(ramp_s)) and float(ramp_s) >= 0.0:
        return float(ramp_s)
    return None


class GroundHandling:
    """The ground plane, the grounded phases and the take-off ramp of :class:`~twin_nodes.twin.runner.TwinRunner`.

    Uses the runner's state: ``x`` (the twin's state, its height above the ground plane), ``real_x`` (the
    real state in the ground plane's frame), ``ground_z`` (the plane's real-frame height), ``sp`` and
    ``_sp_ground_z`` (the setpoint and the plane height it was shifted by), ``real_throttle``, ``real_u``,
    ``u``, ``n``, ``flown_as``, ``ctrl``, ``dt_c``, ``ramp``, ``takeoff_ramp_s``, ``params``, ``_initialised``."""

    def _to_ground_frame(self, x: np.ndarray) -> None:
        """The real state ``x`` (13,), shifted in place to the twin's ground plane's frame."""
        if not self._initialised and np.linalg.norm(x[3:6]) < 0.3:
            # at rest when the twin starts (PX4 logs start at boot or at arming, on the ground):
            # that height is the ground (not the arming state: its message may come first or last)
            self.ground_z = float(x[2])
        x[2] -= self.ground_z
        if self._initialised and x[2] < 0.0:
            # the real vehicle below the twin's ground plane (terrain lower than the take-off spot, the
            # baro or EKF height drifting down): the ground is below wherever the vehicle flies, so the
            # plane goes down to it and the twin, flying, keeps its own height
            shift = float(x[2])
            self.ground_z += shift
            x[2] = 0.0
            self.x[2] -= shift  # (the setpoint is taken again in the new frame: _sp_ground_z differs)

    def _ramped_update(self, sp: np.ndarray, q_att) -> tuple[np.ndarray, np.ndarray]:
        """A cascade step during PX4's take-off ramp (``Takeoff::updateRamp``, ``mc_pos_control``): the
        upward velocity limit, the trajectory's own upward velocity included, ramps from -g / Kp_vz (the
        velocity loop asks for zero thrust) to MPC_Z_VEL_MAX_UP over MPC_TKO_RAMP_T; no acceleration
        feed-forward while it ramps."""
        G = self.ctrl.G
        up = float(G[G_ZV_UP])
        self.ramp = min(self.ramp + self.dt_c / max(self.takeoff_ramp_s, self.dt_c), 1.0)
        v0 = -G_ACC / max(float(G[G_ZV_P]), 0.01)
        lim = v0 + self.ramp * (up - v0)
        sp = sp.copy()
        sp[8] = np.nan
        if math.isfinite(sp[5]):
            sp[5] = min(sp[5], lim)
        G[G_ZV_UP] = lim
        try:
            return self.ctrl.update(self.x[:13], sp, self.dt_c, q_att=q_att)
        finally:
            G[G_ZV_UP] = up

    def _px4_grounded(self) -> bool:
        """PX4's position controller commands no thrust (see :data:`GROUNDED_THRUST`): its logged
        collective thrust setpoint, or where none is logged the real motors, at zero."""
        # a grounded phase starts on the ground: a zero thrust setpoint in the air (an idle descent of
        # PX4's old mixer, a logging glitch) is flown, not held; once on the ground it lasts while the
        # thrust stays at zero (the EKF's height may drift, a hand may lift the vehicle)
        if self.flown_as not in ("grounded", "disarmed") and self.real_x is not None:
            h = float(self.real_x[2])
            if math.isfinite(h) and h > GROUNDED_ENTER_M:
                return False
        thr = self.real_throttle
        if math.isfinite(thr):
            return thr <= GROUNDED_THRUST
        u = self.real_u
        return bool(u.shape == (self.n,) and np.isfinite(u).all() and float(np.max(u)) <= GROUNDED_THRUST)

    def _held_with_vehicle(self) -> None:
        """Flying, but the real vehicle has not left the ground since the twin last rested on it (within
        :data:`HELD_M` of the ground plane): the ground holds the twin where it holds the vehicle.  PX4 may
        command full thrust to a vehicle that does not rise (a hand or a tether holding it, a skid caught,
        an overloaded vehicle: ZweiterFlugtag log_20 sits on its take-off spot at a collective of 0.6-1.0 for
        12 s while its land detector says airborne); a free twin would fly away and be compared with a
        vehicle on the ground.  Only while the twin would be higher than the vehicle (a twin that stays down
        by its own thrust is left alone): its position and velocity are the vehicle's; its controller runs on
        (its velocity integrators wind up as PX4's did), and it flies on from there once the vehicle is
        above HELD_M.  Not on a log that starts in the air."""
        h = float(self.real_x[2])
        if self._lifted or not math.isfinite(h):
            return
        if h > HELD_M:
            self._lifted = True
            return
        if self.x[2] <= max(h, 0.0):
            return  # the twin on the ground too (or lower): nothing holds it, its own thrust does
        # its position and velocity (the contact holds them); attitude and rates stay the twin's own (the
        # real ones are noisy, and copying them would start a rate-only mode from a random tilt)
        self.x[0:6] = self.real_x[0:6]
        self.x[2] = max(self.x[2], 0.0)

    def _hold_on_ground(self) -> None:
        """Disarmed, or armed with PX4 commanding no thrust: the vehicle is not flying (it stands on the
        ground, or a hand holds it), so the twin is where the real vehicle is, at rest on a ground plane
        at its height; a later take-off starts the twin from there, as PX4 starts its ramp from the
        ground with reset integrators (a second take-off in one log: a touch-and-go, a payload set down
        at a spot higher or lower than the first, the EKF's height drifted while landed)."""
        shift = float(self.real_x[2])  # the real height above the twin's ground plane
        if shift != 0.0:
            # the ground plane moves to the real height (a touchdown elsewhere, the EKF's height drifting)
            self.ground_z += shift
            self.real_x[2] = 0.0
            if self._sp_ground_z is not None:
                self.sp = self.sp.copy()
                self.sp[2] -= shift
                self._sp_ground_z = self.ground_z
        self.x[:13] = self.real_x
        self.x[2] = max(self.x[2], 0.0)
        self.x[NX_BODY:] = self._rest_reference(self.u)

    def _rest_reference(self, u: np.ndarray) -> np.ndarray:
        """``params.rotors.reference_from_command(np.nan_to_num(u))``, kept per runner by the command's bytes:
        a held twin's command is PX4's zero thrust or the disarmed NaN on every step of a grounded phase, and
        the two numpy calls cost more than the step (the same array values; the caller copies them in)."""
        cache = self.__dict__.setdefault("_rest_refs", {})
        key = u.tobytes()
        ref = cache.get(key)
        if ref is None:
            if len(cache) >= 64:  # a command that varies (not seen in a grounded phase): keep the cache small
                cache.clear()
            ref = cache[key] = self.params.rotors.reference_from_command(np.nan_to_num(u))
        return ref
