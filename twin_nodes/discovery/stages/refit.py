"""Stage 4, the refit: the accepted effects refitted jointly on the equation error
(they may interact); effects found on the output error keep their values (``RefitInput`` -> ``Refit``).
The closed-loop check (:mod:`.closed_loop`) refits each subset it tries the same way."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from twin_nodes.discovery.judging import Fit
from twin_nodes.discovery.residuals import residual_channels
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.vehicle.params import VehicleParams


@dataclass
class RefitInput:
    flight: PreparedFlight
    accepted: list[Fit]
    current: VehicleParams            # the selection's vehicle (the last accepted effect on top)


@dataclass
class Refit:
    vp: VehicleParams                 # the refitted vehicle


def run(inp: RefitInput) -> Refit:
    """The joint refit when more than one effect is accepted (it updates their ``theta``)."""
    if len(inp.accepted) > 1:
        return Refit(_joint_refit(inp.accepted, inp.flight.data, inp.flight.nominal, inp.flight.fit_mask))
    return Refit(inp.current)


def _joint_refit(accepted: list[Fit], data, nominal, fit_mask) -> VehicleParams:
    """Refit the equation-error effects among ``accepted`` jointly (they may interact); effects
    found on the output error keep their values (the equation error cannot see them well)."""
    base = nominal
    for f in accepted:
        if f.kind != "equation":
            base = f.candidate.apply(base, f.theta)
    eq_fits = [f for f in accepted if f.kind == "equation"]
    if not eq_fits:
        return base
    cands = [f.candidate for f in eq_fits]
    sizes = [len(c.x0) for c in cands]
    x0 = np.concatenate([f.theta for f in eq_fits])
    lo = np.concatenate([c.lower for c in cands])
    hi = np.concatenate([c.upper for c in cands])
    s = np.maximum(np.abs(x0), 1e-6)

    def build(theta):
        vpj = base
        k = 0
        for c, n in zip(cands, sizes):
            vpj = c.apply(vpj, theta[k:k + n])
            k += n
        return vpj

    def resid(z):
        return residual_channels(data, build(np.clip(z * s, lo, hi)), nominal)[fit_mask].ravel()

    sol = least_squares(resid, x0 / s, bounds=(lo / s, hi / s), diff_step=1e-3, max_nfev=80)
    theta = np.clip(sol.x * s, lo, hi)
    k = 0
    for f, n in zip(eq_fits, sizes):
        f.theta = theta[k:k + n]
        k += n
    return build(theta)
