"""Physics outside discovery's vocabulary, for the plant only (``prove --source oov``).

Each is an :class:`~twin_nodes.physics.effects.Effect` with a rotor kernel, deliberately **not**
registered in :data:`~twin_nodes.physics.effects.EFFECTS`: discovery cannot propose it, a params file
cannot carry it, only the flown plant has it (``fly_closed_loop(..., extra_effects=...)`` for our
generator, :class:`RotorPyPlant` for RotorPy).  Their laws are textbook forms, not the features of the
term library (``effects.STATE_TERM_FEATURES``), so the term found has to approximate them:

- :class:`TranslationalLift`: momentum theory (Glauert): at a horizontal airspeed ``mu v_h`` the induced
  velocity of a rotor at hover thrust falls to ``v_i/v_h = sqrt(sqrt(1 + mu^4/4) - mu^2/2)``; the thrust at
  a given rotor speed rises by ``k (1 - v_i/v_h)`` (``k`` the fraction of the blade loading the inflow
  takes);
- :class:`VortexRing`: the vortex-ring state: in a descent at ``d v_h`` the rotor re-ingests its wake and
  loses ``k exp(-((d - d_peak)/width)^2 / 2)`` of its thrust, fading with horizontal airspeed
  (``exp(-(mu/0.5)^2)``: a little forward speed blows the ring away);
- :class:`ThrustFlattening`: the thrust curve flattens near full output (blade stall, ESC current limit):
  above ``u0`` of the top rotor speed the thrust falls short by ``k ((u - u0)/(1 - u0))^2``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from twin_nodes.physics.effects import Effect


@njit(cache=True)
def _k_translational_lift(p, x, ext, omega, T, Q):
    k, v_h = p[0], p[1]
    va0 = x[3] - ext[1]
    va1 = x[4] - ext[2]
    mu = math.sqrt(va0 * va0 + va1 * va1) / v_h
    vi = math.sqrt(max(math.sqrt(1.0 + 0.25 * mu ** 4) - 0.5 * mu * mu, 0.0))
    gain = 1.0 + k * (1.0 - vi)
    for i in range(T.shape[0]):
        T[i] *= gain
        Q[i] *= gain


@njit(cache=True)
def _k_vortex_ring(p, x, ext, omega, T, Q):
    k, v_h, d_peak, width = p[0], p[1], p[2], p[3]
    d = -(x[5] - ext[3]) / v_h
    if d <= 0.0:
        return
    va0 = x[3] - ext[1]
    va1 = x[4] - ext[2]
    mu = math.sqrt(va0 * va0 + va1 * va1) / v_h
    loss = k * math.exp(-0.5 * ((d - d_peak) / width) ** 2) * math.exp(-(mu / 0.5) ** 2)
    for i in range(T.shape[0]):
        T[i] *= 1.0 - loss
        Q[i] *= 1.0 - loss


@njit(cache=True)
def _k_thrust_flattening(p, x, ext, omega, T, Q):
    k, u0, w_max = p[0], p[1], p[2]
    for i in range(T.shape[0]):
        u = omega[i] / w_max
        if u > u0:
            s = (u - u0) / (1.0 - u0)
            T[i] *= 1.0 - k * s * s


class TranslationalLift(Effect):
    name = "translational_lift"
    param_names = ("k", "v_h")
    units = {"k": "-", "v_h": "m/s"}
    ranges = {"k": (0.0, 2.0), "v_h": (0.1, 100.0)}
    description = "thrust gain in forward flight, momentum theory (Glauert)"
    rotor_kernel = staticmethod(_k_translational_lift)


class VortexRing(Effect):
    name = "vortex_ring"
    param_names = ("k", "v_h", "d_peak", "width")
    defaults = {"d_peak": 1.0, "width": 0.35}
    units = {"k": "-", "v_h": "m/s", "d_peak": "descent / v_h", "width": "descent / v_h"}
    ranges = {"k": (0.0, 0.9), "v_h": (0.1, 100.0), "d_peak": (0.1, 3.0), "width": (0.05, 2.0)}
    description = "thrust loss in a descent near the hover induced velocity (vortex-ring state)"
    rotor_kernel = staticmethod(_k_vortex_ring)


class ThrustFlattening(Effect):
    name = "thrust_flattening"
    param_names = ("k", "u0", "omega_max")
    units = {"k": "-", "u0": "omega / omega_max", "omega_max": "rad/s"}
    ranges = {"k": (0.0, 0.9), "u0": (0.0, 0.99), "omega_max": (1.0, 1e5)}
    description = "thrust curve flattening near full rotor speed"
    rotor_kernel = staticmethod(_k_thrust_flattening)


#: the plant-only physics by mechanism name (the manifest's ``mechanism``)
PLANT_EFFECTS = {c.name: c for c in (TranslationalLift, VortexRing, ThrustFlattening)}


def plant_gain(name: str, params: dict, v_air_enu: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """The thrust multiplier (N,) of plant effect ``name`` at one state (numpy, for RotorPy's plant):
    ``v_air_enu`` (3,) air-relative velocity, ``omega`` (N,) rotor speeds."""
    eff = PLANT_EFFECTS[name](**params)
    p = eff.vector()
    x = np.zeros(13)
    x[3:6] = v_air_enu
    x[6] = 1.0
    T = np.ones(len(omega))
    Q = np.ones(len(omega))
    eff.rotor_kernel(p, x, np.zeros(4), np.asarray(omega, float), T, Q)
    return T

