"""Static trims (centre-of-mass offset, tangential rotor tilt) made so the twin holds the real motor split.

PX4's rate integrators hold whatever steady moment the vehicle needs; in steady flight that shows
as a static split of the motor outputs.  The twin holds the same split only if its own model needs
the same moment there.  Other terms of the model carry steady moments as well: the rotors' H-force
(``rotor_drag``) at hubs above the centre of mass gives roll and pitch moments in wind, and, where
the rotors turn at different speeds (the pitch/roll trim itself), a *yaw* moment too; a coaxial
lower rotor, a weaker motor, a battery scale all change what the same commands give.  A trim made
from the motor outputs alone (moment of the median thrusts) leaves those out, and the twin then
holds another split than the vehicle: on a V6C quad in 6 m/s of wind, the rotor drag's yaw moment
was 80 % of the trim's, and the twin's yaw split was 1.1 % of full output where PX4's was 4.1 %.

:func:`model_trims` measures instead, on the steady samples, the moment the model (every term but
the trims) gives with the logged commands and state, less the moment the measured motion needs
(``I alpha + w x I w``), and makes ``com_offset`` (roll/pitch, ``-d x F`` of the total thrust) and
``rotor_tilt`` (yaw, lever x total thrust) of what is left: by construction the twin's steady moment
balance is the vehicle's.  The offset moves every rotor (its rotor drag too: a yaw moment ``-d x H`` in
wind), so the lever is read with the offset in the model.

A centre of mass far off (a payload hanging off-centre, 0.10-0.12 m on a 0.23 m arm on the 23 Jun 2023
V6C flights) is a trim only where the flight shows it: within 30 % of the arm as before; beyond, where
the steady flight's two halves give the same trim (held the whole flight, not a transient) and it lies
inside the rotor polygon (:func:`com_verdict`).  Pure numpy on :class:`~twin_nodes.physics.model.Multirotor`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from twin_nodes.physics.core import NX_BODY
from twin_nodes.physics.model import Multirotor
from twin_nodes.vehicle.params import VehicleParams

__all__ = ["TRIM_EFFECTS", "ComSupport", "Trims", "com_verdict", "model_trims", "polygon_margin", "without_trims"]

#: the effects the trims are made of (replaced, not added to)
TRIM_EFFECTS = ("com_offset", "rotor_tilt")


#: fixed-point steps for the centre-of-mass trim (see model_trims) and the change [m] at which they stop
_TRIM_STEPS = 8
_TRIM_TOL_M = 1e-12


@dataclass(frozen=True)
class Trims:
    """``com_offset`` (dx, dy) [m, body FLU] and ``rotor_tilt`` lever [m] (yaw moment per newton of
    total thrust, + CCW seen from above), and the steady moments they balance [N m] (FLU); ``per_sample``
    (S, 3): the (dx, dy, lever) each steady sample alone asks for (NaN where it has no thrust), whose
    medians the trims are (:func:`model_trims`; the paired change of :mod:`twin_nodes.discovery.stages.retrim`)."""
    dx: float
    dy: float
    lever: float
    moment_other_nm: tuple[float, float, float]
    n_samples: int
    per_sample: np.ndarray | None = field(default=None, repr=False, compare=False)


def without_trims(vp: VehicleParams) -> VehicleParams:
    """``vp`` with its static-trim effects removed (every other effect kept)."""
    eff = {k: v for k, v in vp.effect_dict.items() if k not in TRIM_EFFECTS}
    return vp.replace(effects=tuple((k, tuple(v.items())) for k, v in eff.items()))


def model_trims(vp: VehicleParams, states: np.ndarray, alpha: np.ndarray | None = None,
                battery_v: np.ndarray | None = None) -> Trims:
    """The trims that balance the model's steady moments (see the module docstring).

    ``states`` (T, nx): the model's state on steady samples (ENU position/velocity, attitude, FLU rates
    and the rotor states the logged commands give through the motor lag); ``alpha`` (T, 3): the
    measured angular acceleration there (FLU; None: 0); ``battery_v`` (T,): the pack voltage for a
    ``battery_sag`` effect.  Medians over the samples: a steady flight's outliers (a gust, a turn)
    move them little."""
    base = without_trims(vp)
    X = np.ascontiguousarray(np.atleast_2d(states), dtype=float)
    t = np.arange(X.shape[0], dtype=float)
    J = vp.inertia
    w = X[:, 10:13]
    need = np.cross(w, w @ J.T)
    if alpha is not None:
        need = need + np.asarray(alpha, float) @ J.T
    # The offset moves every rotor (physics/core.pack): besides -d x F of the thrust it turns the rotor drag's
    # H-forces about the moved centre of mass (a yaw moment -d x H) and changes the hubs' airspeed w x (r - d).
    # So (dx, dy) is found by fixed-point steps on the roll/pitch moment per newton (exact for the thrust part,
    # which dominates: one or two steps), and the lever from the yaw moment left with that offset in the model.
    dx = dy = 0.0
    for step in range(_TRIM_STEPS):
        trial = base if step == 0 else base.with_effect("com_offset", dx=dx, dy=dy)
        model = Multirotor(trial)
        if X.shape[1] != model.nx:
            raise ValueError(f"model_trims: states need {model.nx} columns, got {X.shape[1]}")
        ext = model.exogenous(t, np.random.default_rng(0), battery_v)
        terms = model.wrench_terms(X, ext)
        m_model = sum(v[1] for v in terms.values())
        thrust_z = terms["rotors"][0][:, 2]
        trim_m = need - m_model                     # what the trims must still give, per sample
        ok = np.isfinite(trim_m).all(axis=1) & (thrust_z > 1e-6)
        if not ok.any():
            raise ValueError("model_trims: no steady sample with thrust")
        if step == 0:  # the rest of the model, without any trim
            other = tuple(float(v) for v in np.median(m_model[ok] - need[ok], axis=0))
        per_n = trim_m[ok] / thrust_z[ok, None]     # per newton of total thrust
        # a further offset (ex, ey) gives (-ey Tz, ex Tz, 0) of the thrust; rotor_tilt gives (0, 0, lever Tz)
        ex, ey = float(np.median(per_n[:, 1])), -float(np.median(per_n[:, 0]))
        if not math.hypot(ex, ey) > _TRIM_TOL_M or step == _TRIM_STEPS - 1:  # converged (or NaN, or the last step)
            break
        dx, dy = dx + ex, dy + ey
    lever = float(np.median(per_n[:, 2]))
    # what each sample asks for: the offset plus its own further step, and its lever (medians: the trims)
    each = np.full((X.shape[0], 3), np.nan)
    each[ok] = np.column_stack([dx + per_n[:, 1], dy - per_n[:, 0], per_n[:, 2]])
    return Trims(dx, dy, lever, other, int(ok.sum()), each)


#: a centre-of-mass trim beyond this fraction of the arm is accepted only where the flight shows it held
#: (:func:`com_verdict`): enough seconds of steady flight, and its two halves' trims within
#: ``COM_HALVES_REL`` of the trim (a payload hanging off-centre for the whole flight, not a transient)
COM_FREE_ARM = 0.3
COM_HALVES_REL = 0.25
#: and in every case inside the rotor polygon at least this fraction of the arm from its edge: beyond the
#: polygon no set of rotor thrusts >= 0 holds the vehicle level
COM_EDGE_ARM = 0.1


@dataclass(frozen=True)
class ComSupport:
    """What the flight says about a centre-of-mass trim: the rotor positions (FLU x, y), the seconds of
    steady flight it was made of and the trims (dx, dy, lever) made of the first and second half of them."""

    x_flu_m: tuple[float, ...]
    y_flu_m: tuple[float, ...]
    seconds: float
    halves: tuple[tuple[float, float, float], ...]


def polygon_margin(x: np.ndarray, y: np.ndarray, px: float, py: float) -> float:
    """Signed distance [m] of the point (px, py) inside the convex hull of the rotors (x, y) (negative:
    outside); -inf for fewer than 3 rotors off one line."""
    pts = np.column_stack([x, y]).astype(float)
    c = pts.mean(axis=0)
    ang = np.arctan2(pts[:, 1] - c[1], pts[:, 0] - c[0])
    ring = pts[np.argsort(ang)]
    best = math.inf
    for a, b in zip(ring, np.roll(ring, -1, axis=0)):
        e = b - a
        ln = float(np.hypot(*e))
        if ln < 1e-9:
            continue
        # inward normal of a counter-clockwise ring: (-e_y, e_x)
        best = min(best, float((-e[1] * (px - a[0]) + e[0] * (py - a[1])) / ln))
    return best if len(ring) >= 3 and math.isfinite(best) else -math.inf


def com_verdict(dx: float, dy: float, arm: float, support: ComSupport | None, min_seconds: float
                ) -> tuple[bool, str]:
    """Whether a centre-of-mass trim (dx, dy) [m] goes into the twin, and why (the reason, or for a large
    accepted one the evidence, to append to its source): see the constants above."""
    d = math.hypot(dx, dy)
    edge = -math.inf if support is None else polygon_margin(np.array(support.x_flu_m), np.array(support.y_flu_m),
                                                            dx, dy)
    if math.isfinite(edge) and edge < COM_EDGE_ARM * arm:
        return False, (f"{edge * 1000:.0f} mm inside the rotor polygon (needs >= {COM_EDGE_ARM:.0%} of the arm, "
                       f"{COM_EDGE_ARM * arm * 1000:.0f} mm)")
    if max(abs(dx), abs(dy)) <= COM_FREE_ARM * arm:
        return True, ""
    if not math.isfinite(edge):
        return False, f"beyond {COM_FREE_ARM:.0%} of the arm"
    spread = max((math.hypot(h[0] - dx, h[1] - dy) for h in support.halves), default=math.inf)
    held = support.seconds >= min_seconds and len(support.halves) == 2 and spread <= COM_HALVES_REL * d
    how = (f"{d * 1000:.0f} mm ({d / arm:.0%} of the arm), beyond {COM_FREE_ARM:.0%}: the flight's halves give "
           + ", ".join(f"({1000 * h[0]:.0f}, {1000 * h[1]:.0f})" for h in support.halves)
           + f" mm over {support.seconds:.1f} s of steady flight")
    if held:
        return True, f"; {how}: held the whole flight (halves within {COM_HALVES_REL:.0%}), inside the rotor polygon"
    return False, (f"{how}, not shown held (needs >= {min_seconds:g} s and halves within "
                   f"{COM_HALVES_REL:.0%} of it)")
