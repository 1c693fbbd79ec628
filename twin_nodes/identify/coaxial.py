"""The coaxial efficiency: how much thrust the lower rotor of a coaxial pair gives, at the same command,
relative to the upper one (it works in the upper rotor's slipstream).

Identified from the body-z specific force with the upper and the lower rotors in separate columns,

    f_z = a sum_upper T~ + b sum_lower T~ - (k_z/m) v_z,      efficiency = b / a,

where ``T~`` are the lagged commands' thrust units (as the nominal's thrust fit).  The two columns
differ only where PX4 drives the levels apart: on a layout whose upper rotors all spin one way (Y6,
PX4's hexa_cox) yaw is made that way and the yaw trim holds them apart; on one with both spins on each
level (PX4's octo_cox X8) the levels' sums are equal at every sample and only the pairs' total thrust
is identified (said so; the value is then ASSUMED).  The value is kept when its standard
error (delta method) is at most :data:`SE_MAX`, it lies in :data:`RANGE` and the flight's two halves
agree within :data:`HALVES_MAX`; otherwise :data:`ASSUMED` is used and marked so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from twin_nodes.identify.regression import fit_linear

#: lower/upper thrust ratio used where the flight does not determine it
ASSUMED = 0.8
ASSUMED_WHY = ("the ~20 % thrust loss of a lower propeller in the upper one's slipstream reported for small "
               "coaxial multirotor propulsion (Bondyra et al. 2016, 'Performance of coaxial propulsion in design "
               "of multi-rotor UAVs', AISC 440); momentum theory puts the pair's induced power 28 % above two "
               "isolated rotors (Leishman & Syal 2008, JAHS 53(3))")
SE_MAX = 0.05
#: both sides are low-passed this far before the fit [Hz]: the levels are driven apart in yaw manoeuvres
#: faster than the motor lag is known (a lag 0.02 s off biased the ratio 3 % on a simulated Y6 at the
#: nominal's 2.5 Hz; at 0.5 Hz it is within 0.2 % for lags 0.03-0.08 s against 0.05)
LOWPASS_HZ = 0.5
RANGE = (0.4, 1.1)
HALVES_MAX = 0.1


@dataclass(frozen=True)
class CoaxialFit:
    efficiency: float
    identified: bool
    source: str


def _ratio(up: np.ndarray, low: np.ndarray, f_z: np.ndarray, v_z: np.ndarray) -> tuple[float, float]:
    fit = fit_linear(np.column_stack([up, low, -v_z]), f_z, ["a", "b", "kz/m"])
    a, b = fit["a"], fit["b"]
    if not (a > 0 and np.all(np.isfinite(fit.stderr[:2]))) or fit.cov is None or fit.cov.shape[0] < 2:
        return math.nan, math.inf
    ratio = b / a
    grad = np.array([-b / a ** 2, 1.0 / a])
    var = float(grad @ fit.cov[:2, :2] @ grad)
    return ratio, math.sqrt(max(var, 0.0))


def coaxial_efficiency(tt: np.ndarray, f_z: np.ndarray, v_z: np.ndarray, lower: tuple[int, ...]) -> CoaxialFit:
    """The lower rotors' thrust ratio from thrust units ``tt`` (n, N), body-z specific force ``f_z`` and
    body-z velocity ``v_z`` (n,), with ``lower`` the 0-based lower rotors (see the module)."""
    low = np.zeros(tt.shape[1], bool)
    low[list(lower)] = True
    up_sum, low_sum = tt[:, ~low].sum(axis=1), tt[:, low].sum(axis=1)
    if float(np.std(up_sum - low_sum)) <= 1e-6 * max(float(np.mean(np.abs(up_sum))), 1e-12):
        return CoaxialFit(ASSUMED, False,
                          f"ASSUMED {ASSUMED}: not identifiable on any flight of this layout: its upper and lower "
                          f"rotors' commands sum alike throughout (each level has both spins, so PX4's allocation "
                          f"makes yaw across the pairs, never within them), and only the pairs' total thrust shows; "
                          f"{ASSUMED_WHY}")
    eta, se = _ratio(up_sum, low_sum, f_z, v_z)
    h = f_z.size // 2
    halves = [_ratio(up_sum[s], low_sum[s], f_z[s], v_z[s])[0] for s in (slice(0, h), slice(h, None))]
    spread = abs(halves[0] - halves[1]) if all(np.isfinite(halves)) else math.inf
    ok = math.isfinite(eta) and se <= SE_MAX and RANGE[0] <= eta <= RANGE[1] and spread <= HALVES_MAX
    fit = f"{eta:.3f} ± {se:.3f}, halves {halves[0]:.2f}/{halves[1]:.2f}" if math.isfinite(eta) else "no fit"
    if ok:
        return CoaxialFit(eta, True, f"identified: lower rotors give {eta:.3f} ± {se:.3f} of the upper's thrust at "
                                     f"equal command (body-z specific force, upper and lower rotors in separate "
                                     f"columns; halves {halves[0]:.2f}/{halves[1]:.2f})")
    return CoaxialFit(ASSUMED, False,
                      f"ASSUMED {ASSUMED}: the flight does not determine it (fit {fit}; needs se <= {SE_MAX}, "
                      f"{RANGE[0]}-{RANGE[1]} and halves within {HALVES_MAX}): {ASSUMED_WHY}")
