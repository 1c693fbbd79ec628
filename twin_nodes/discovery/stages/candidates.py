"""Stage 3a, the candidates of one selection round: every effect of the ``physics`` catalogue as a fit
on top of what is accepted so far (``CandidateQuery`` -> ``CandidateSet``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twin_nodes.discovery.candidates import SYMMETRIC_LAG, Candidate, build_candidates
from twin_nodes.discovery.judging import PRUNE_GAIN, _restrict_to_axes
from twin_nodes.discovery.locate import supply_for
from twin_nodes.discovery.residuals import EquationData
from twin_nodes.vehicle.params import VehicleParams


@dataclass
class CandidateQuery:
    """One round of the forward selection."""

    current: VehicleParams                # the vehicle with the effects accepted so far
    data: EquationData
    round: int                            # 1, 2, ...
    done: set[str] = field(default_factory=set)               # accepted labels
    first_gain: dict[str, float] = field(default_factory=dict)  # round 1's cut per label, rescaled
    excitation: dict = field(default_factory=dict)              # per channel (locate.excitation)


@dataclass
class CandidateSet:
    """The round's candidates: fitted first, and the richer variants fitted only where the simpler
    one is accepted."""

    first: list[Candidate]
    richer: list[Candidate]


def run(q: CandidateQuery) -> CandidateSet:
    """The candidates of round ``q.round``."""
    # round 2 refits every candidate: round 1 fitted them beside the first effect's residual, which a
    # one-sided effect (a ground effect under a thrust deficit) or one that tried to take it up (a drag's
    # vertical term) could not explain; from round 3 a candidate that explained nothing in round 1 (< 2 %
    # cross-validated, rescaled to the residual left: stages.selection) is not refitted
    cands = [hold_unexcited(c, q.excitation) for c in build_candidates(q.current, q.data) if c.label not in q.done
             and (q.round <= 2 or q.first_gain.get(c.label, 1.0) >= PRUNE_GAIN)]
    cands = [c for c in cands if c is not None]
    # the up/down motor lag is fitted only where the one-constant lag is found (it can only
    # refine it; on the other flights it would cost the most expensive fit of the round)
    richer = [c for c in cands if c.name == "motor_time_constant" and c.label != SYMMETRIC_LAG
              and any(d.label == SYMMETRIC_LAG for d in cands)]
    return CandidateSet([c for c in cands if c not in richer], richer)


#: an inertia axis is fitted only where the flight excites it: at least this many blocks of the whole flight carry
#: a moment command on that axis above its noise (``locate.excitation``).  With none, the fit of that axis moves on
#: whatever else the channel holds (RotorPy fast descents, pitch never commanded: Iyy to a quarter or a third of the
#: nominal beside a battery sag or a thrust deficit, q034 and r070) and is never the inertia's
MIN_AXIS_BLOCKS = 1
_INERTIA_AXES = {"ixx": "roll", "iyy": "pitch", "izz": "yaw"}


def hold_unexcited(c: Candidate, excitation: dict) -> Candidate | None:
    """``c`` with the inertia axes the flight does not excite held at the model's value (named in ``held``
    with the manoeuvre that would excite them); None where no axis is left.  Other candidates unchanged."""
    if c.name != "inertia" or not excitation:
        return c
    still = [p for p in c.param_names if p in _INERTIA_AXES
             and excitation.get(_INERTIA_AXES[p], {}).get("blocks_flight", MIN_AXIS_BLOCKS) < MIN_AXIS_BLOCKS]
    if not still:
        return c
    usable = np.ones(6, bool)
    for p in still:
        usable[3 + ("ixx", "iyy", "izz").index(p)] = False
    out = _restrict_to_axes(c, usable)
    if out is None:
        return None
    for p in still:
        ax = _INERTIA_AXES[p]
        out.held[p] = (f"held at nominal, not identified on this flight: no block of it carries a {ax} moment "
                       f"above its noise; to identify it fly {supply_for(ax)}")
    return out


def not_excited(data, excitation: dict) -> list[dict]:
    """The effect classes this flight cannot show, each with why and the manoeuvre that would (issue 26, item 3:
    a hover neither drags nor turns its roll/pitch inertia; discovery says so instead of finding nothing silently).
    The same thresholds as the candidates (``build_candidates``, :func:`hold_unexcited`)."""
    out = []
    speed = np.linalg.norm(data.v[data.valid], axis=1)
    v_typ = float(np.percentile(speed, 90)) if speed.size else 0.0
    if v_typ <= 0.5:
        # the rotor drag's yaw damping (its hubs' airspeed in yaw turns) is still fitted (candidates.build_candidates)
        out.append({"effects": ["rotor_drag (force)", "body_drag (horizontal)"], "why": f"90th-percentile speed "
                    f"{v_typ:.2f} m/s <= 0.5: no horizontal airspeed for a drag to act on (a rotor drag's yaw damping "
                    "in yaw turns and a nominal body drag's vertical term in fast climbs are fitted)",
                    "fly": supply_for("force_x")})
    for p, ax in _INERTIA_AXES.items():
        n = (excitation.get(ax) or {}).get("blocks_flight")
        if n is not None and n < MIN_AXIS_BLOCKS:
            out.append({"effects": [f"inertia ({p})"], "why": f"no block carries a {ax} moment above its noise",
                        "fly": supply_for(ax)})
    low = data.valid & (data.height < 3.0)
    if low.sum() <= 1.0 / data.dt:
        out.append({"effects": ["ground_effect"], "why": "under 1 s flown below 3 m",
                    "fly": "a low hover (hovering low and high: a ground effect fades with height)"})
    return out
