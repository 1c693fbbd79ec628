"""A pilot stand-in for the vertical axis in PX4's manual modes (MANUAL 0, STABILIZED 15, ACRO 10, RATTITUDE 16).

In those modes no position controller runs on the real vehicle: the pilot closes the height loop by eye, and
the logged collective thrust is what that pilot commanded for the REAL vehicle.  A twin flying that thrust open
loop integrates any thrust-model error into a height drift (and crashes or climbs away).  The stand-in does what
the pilot did: it adds a slow correction to the logged thrust so that the twin's height and vertical speed follow
the real vehicle's.  The correction is then the collective the model lacks, so the twin's throttle (logged +
correction) against the real logged throttle measures the model's error instead of 0 by construction.

Design (linear, level flight, thrust ~ throttle near hover): a throttle change ``c`` gives a vertical
acceleration ``g c / hover``.  The stand-in asks for ``a = KV e_v + KP e_z + KI int(e_z)`` (``e``: real minus
twin, height [m] and vertical speed [m/s], ENU up), ``c = hover a / g``, limited to +-30 % of the hover throttle
(integration stops while limited).  The gains put the closed loop's three poles at ``-OMEGA`` (``(s + w)^3``):
KV = 3 w [1/s], KP = 3 w^2 [1/s^2], KI = w^3 [1/s^3]; with w = 0.5 rad/s (an attitude loop is ~10x faster):
KV = 1.5 1/s, KP = 0.75 1/s^2, KI = 0.125 1/s^3.  A constant model error (an acceleration bias d) leaves no steady
height error; its peak is d (2/w)^2 e^-2 / 2 = 1.08 m per g/10 of bias.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from twin_nodes.base.constants import G_STANDARD_M_S2

#: the closed loop's (triple) pole [rad/s]
OMEGA_RAD_S = 0.5
#: the correction's limit, as a fraction of the twin's hover throttle
LIMIT_OF_HOVER = 0.30


@dataclass
class PilotStandIn:
    """PI(D) on real-vs-twin height; ``hover``: the twin's hover throttle (0..1), ``g`` [m/s^2]."""
    hover: float
    g: float = G_STANDARD_M_S2
    omega: float = OMEGA_RAD_S
    limit: float = LIMIT_OF_HOVER
    integral_m_s: float = 0.0      # int(e_z) dt [m s]
    correction: float = 0.0        # the last correction (throttle, 0..1 units)
    active_s: float = 0.0          # how long it flew [s]
    sum_rel: float = 0.0           # sum of correction / hover over its steps (for the mean)
    steps: int = 0

    def reset(self) -> None:
        """Out of a manual mode (or disarmed): the pilot's integrator starts afresh."""
        self.integral_m_s = 0.0
        self.correction = 0.0

    def update(self, z_twin: float, vz_twin: float, z_real: float, vz_real: float, dt: float) -> float:
        """The throttle correction for this step (add it to the logged collective thrust)."""
        if not (math.isfinite(z_real) and math.isfinite(vz_real)):
            return self.correction  # the real height unknown for a sample: hold the stick
        w = self.omega
        ez, ev = z_real - z_twin, vz_real - vz_twin
        integ = self.integral_m_s + ez * dt
        a = 3.0 * w * ev + 3.0 * w * w * ez + w ** 3 * integ
        c = self.hover * a / self.g
        lim = self.limit * self.hover
        if abs(c) <= lim:
            self.integral_m_s = integ   # conditional integration: no wind-up at the limit
        self.correction = float(min(max(c, -lim), lim))
        self.active_s += dt
        self.sum_rel += self.correction / self.hover
        self.steps += 1
        return self.correction

    def summary(self) -> dict:
        """``{"s": seconds flown, "mean_correction_of_hover": mean correction / hover}`` (NaN if never)."""
        return {"s": self.active_s, "mean_correction_of_hover": self.sum_rel / self.steps if self.steps else float("nan")}
