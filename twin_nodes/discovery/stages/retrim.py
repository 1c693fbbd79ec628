"""The static trims remade for a refit vehicle (used by stage 5, :mod:`.closed_loop`).

The nominal's static trims (``com_offset``, ``rotor_tilt``; :mod:`twin_nodes.identify.static_trims`) are made so
that the twin's steady moment balance is the vehicle's: they balance, on the steady samples, the moment every
*other* term of the model gives (the rotors' H-forces at hubs above the centre of mass, the rotor torque ``km T``,
a coaxial loss...).  A refit that changes one of those terms leaves trims made for the old values, and the twin
then holds another motor split than the vehicle.  On fr_v6c_battery_brownout (tuning half) discovery refitted
the rotor drag (``k_d`` 1.98e-4 -> 5.5e-5) and the yaw moment (``km`` 0.02 -> 0.0046 m): the held-out throttle
RMSE went 2.15 -> 1.27 % but the per-motor P75 5.11 -> 6.03 %; the yaw moment alone, on the nominal's trims,
gave 16.9 %.  With the trims remade for the refit model: 4.97 % (rotor drag alone 7.07 -> 4.66 %).

The trims are remade as a *change*: the trims the refit model needs less those the nominal model needs, both
read by :func:`~twin_nodes.identify.static_trims.model_trims` on the same steady samples, sample by sample (the
median of each sample's change, :func:`paired_change`), added to the trims the vehicle carries.  A refit that
changes nothing the steady balance reads leaves them exactly as they are.  Pure numpy on
:class:`~twin_nodes.vehicle.params.VehicleParams`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from twin_nodes.identify.nominal import STEADY_MIN_S, STEADY_SPEED_M_S, _balanced
from twin_nodes.identify.static_trims import COM_EDGE_ARM, TRIM_EFFECTS, Trims, model_trims, polygon_margin
from twin_nodes.physics.core import NX_BODY
from twin_nodes.physics.model import Multirotor
from twin_nodes.vehicle.params import VehicleParams

__all__ = ["paired_change", "retrimmed", "retrim_for_flight", "steady_samples"]


def _trims_of(vp: VehicleParams) -> tuple[float, float, float]:
    e = vp.effect_dict
    c, r = e.get("com_offset", {}), e.get("rotor_tilt", {})
    return float(c.get("dx", 0.0)), float(c.get("dy", 0.0)), float(r.get("lever_m", 0.0))


def retrimmed(vp: VehicleParams, nominal: VehicleParams, states_of: Callable[[VehicleParams], np.ndarray],
              alpha: np.ndarray | None = None, battery_v: np.ndarray | None = None) -> VehicleParams:
    """``vp`` with its static trims moved by what its model's steady balance needs beyond ``nominal``'s.

    ``states_of(v)`` gives the model state (S, nx) of vehicle ``v`` on the steady samples (the logged body
    state and the rotor states the logged commands give through ``v``'s command path); ``alpha`` (S, 3) the
    measured angular acceleration there [rad/s^2, FLU]; ``battery_v`` (S,) [V].  ``vp`` unchanged where the
    nominal carries no trim, where the change is zero, or where the moved centre of mass would leave the
    rotor polygon (``COM_EDGE_ARM`` of the arm from its edge)."""
    nom_eff = nominal.effect_dict
    if not any(k in nom_eff for k in TRIM_EFFECTS):
        return vp
    need_new = model_trims(vp, states_of(vp), alpha, battery_v)
    need_old = model_trims(nominal, states_of(nominal), alpha, battery_v)
    d = paired_change(need_new, need_old)
    if not all(np.isfinite(d)) or not any(d):
        return vp
    dx, dy, lever = (a + b for a, b in zip(_trims_of(vp), d))
    r = vp.rotors
    x, y = np.asarray(r.x_flu_m, float), np.asarray(r.y_flu_m, float)
    arm = float(np.median(np.hypot(x, y)))
    if polygon_margin(x, y, dx, dy) < COM_EDGE_ARM * arm:
        return vp
    return vp.with_effect("com_offset", dx=dx, dy=dy).with_effect("rotor_tilt", lever_m=lever)


def paired_change(new: Trims, old: Trims) -> tuple[float, float, float]:
    """The change of the trims (dx, dy, lever) from ``old`` to ``new``, both read on the same steady samples: the
    median over the samples of what each asks for more (paired), not the change of the two medians.  A refit
    changes the moment per sample (``km`` times the sample's own split, ``I alpha`` where the inertia moved);
    the median of a sum of terms it moves by different amounts is not the sum of their medians.  On
    auterion_v3_esc_status a yaw moment ``km`` 0.02 -> 0.0083 m moved the lever +0.86 mm by the medians: the twin's
    yaw split went 0.75 % of full output further off the vehicle's before the held-out part (yaw-mode mean error
    -0.10 -> -0.85 %), held-out per-motor P75 7.03 -> 7.46 %.  The paired change, +1.03 mm, keeps it (-0.10 %;
    6.98 %).  On fr_v6c_battery_brownout (rotor drag and yaw moment) 4.54 -> 4.62 %, within the run's scatter
    (+0.08 +- 0.06, 1-s block bootstrap).  The change of the medians where a read lacks its samples."""
    a, b = new.per_sample, old.per_sample
    if a is not None and b is not None and a.shape == b.shape:
        diff = a - b
        ok = np.isfinite(diff).all(axis=1)
        if ok.any():
            return tuple(float(v) for v in np.median(diff[ok], axis=0))
    return new.dx - old.dx, new.dy - old.dy, new.lever - old.lever


def steady_samples(data) -> np.ndarray | None:
    """The steady samples of a discovery flight (:class:`~twin_nodes.discovery.residuals.EquationData`) by the
    rule the nominal reads its trims with (:mod:`twin_nodes.identify.nominal`): attitude channels usable, ground
    speed below ``STEADY_SPEED_M_S`` (every usable sample where that leaves under ``STEADY_MIN_S``), every motor
    inside its range (``_balanced``); None: too few."""
    ok = np.asarray(data.valid_attitude, bool)
    rate = 1.0 / data.dt
    slow = ok & (np.linalg.norm(np.nan_to_num(data.v, nan=np.inf), axis=1) < STEADY_SPEED_M_S)
    steady = slow if slow.sum() >= STEADY_MIN_S * rate else ok
    u = np.asarray(data.u_fine, float)[::data.up][:data.n]
    if u.shape[0] < data.n:
        return None
    return _balanced(steady, np.where(np.isfinite(u), u, -1.0), rate)


def retrim_for_flight(vp: VehicleParams, nominal: VehicleParams, data) -> VehicleParams:
    """:func:`retrimmed` on a discovery flight's steady samples (``vp`` as it is where there are too few)."""
    from twin_nodes.discovery.residuals import _body_states, model_rotor_states

    sel = steady_samples(data)
    if sel is None:
        return vp

    def states_of(v: VehicleParams) -> np.ndarray:
        model = Multirotor(v)
        X = np.empty((data.n, model.nx))
        X[:, :NX_BODY] = _body_states(data)
        X[:, NX_BODY:] = np.nan_to_num(model_rotor_states(model, data))
        return X[sel]

    bv = np.asarray(data.battery_v, float)[sel]
    try:
        return retrimmed(vp, nominal, states_of, np.asarray(data.alpha, float)[sel],
                         bv if np.isfinite(bv).all() else None)
    except ValueError:  # model_trims: no steady sample with thrust
        return vp
