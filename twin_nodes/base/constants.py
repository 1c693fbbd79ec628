"""Physical constants shared by every layer: one home, so a twin, its identification and its checks agree.

``G_STANDARD_M_S2`` is the standard gravity (CGPM 1901, exact), the value PX4 uses
(``CONSTANTS_ONE_G`` in ``src/lib/geo/geo.h``). A vehicle's own ``gravity_m_s2`` parameter defaults to it;
a simulator with its own constant (RotorPy's 9.81) keeps that one where its flights are generated.
"""
from __future__ import annotations

__all__ = ["G_STANDARD_M_S2"]

#: standard gravity [m/s^2]
G_STANDARD_M_S2 = 9.80665
