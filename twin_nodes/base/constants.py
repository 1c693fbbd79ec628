"""Physical constants shared by every layer: one home, so a twin, its identification and its checks agree.

``G_STANDARD_M_S2`` is the standard gravity (CGPM 1901, exact), the value PX4 uses
(``CONSTANTS_ONE_G`` in ``src/lib/geo/geo.h``). A vehicle's own ``gravity_m_s2`` parameter defaults to it;
a simulator with its own constant (RotorPy's 9.81) keeps that one where its flights are generated.

``LEFT_GROUND_M`` is how far above its ground the real vehicle must be to have left it: the twin holds a vehicle
on the ground below it (``twin.ground.HELD_M``) and identification leaves the take-off spot out until it
(``identify.fit_mask.SPOT_M``).
"""
from __future__ import annotations

__all__ = ["G_STANDARD_M_S2", "LEFT_GROUND_M"]

#: standard gravity [m/s^2]
G_STANDARD_M_S2 = 9.80665
#: the real vehicle above its ground plane by more than this has left the ground [m] (an EKF height on the ground
#: wanders by 0.1 m; the fleet's ZweiterFlugtag log_20, held: within 0.1 m for 12 s)
LEFT_GROUND_M = 0.2
