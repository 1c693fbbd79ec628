"""Rotor geometry of a vehicle: how rotor thrusts map to collective thrust and body moments."""

from __future__ import annotations

import numpy as np

from twin_nodes.vehicle.params import VehicleParams


def allocation_matrix(vp: VehicleParams) -> np.ndarray:
    """Pseudo-inverse (N, 4) mapping [collective thrust, Mx, My, Mz] (FLU) to rotor thrusts."""
    r = vp.rotors
    b = np.vstack([np.ones(r.count), np.array(r.y_flu_m), -np.array(r.x_flu_m),
                   -np.array(r.direction, float) * r.km_m])
    return np.linalg.pinv(b)
