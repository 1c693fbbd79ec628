"""Every later candidate also with the accepted effects refitted jointly (issue 26, "an effect absorbed by the
first one found"), made affordable by linearising the accepted effects.

Forward selection fits each later candidate on top of what is accepted, with the accepted parameters fixed.
Where the first effect took up part of the second while it was fitted alone (a mass taking up a drag in tilted
flight, a thrust coefficient taking up a ground effect or a battery sag), the second is left with too little to
pass.  So in a later round the round's strongest candidates (:data:`TOP_K` entries by their plain fit's
cross-validated cut) also compete as a *joint variant*: the candidate's parameters and those of every effect
accepted on the equation error free together, on the equation error (effects found on the output error keep
their values, as in the final refit).

What makes it affordable: the accepted effects enter through their regressors, ``D_a = dR/dtheta_a`` over the
whole flight, measured once per round at their accepted values (one residual evaluation per parameter, shared by
every joint variant).  For the effects that enter the equation error linearly (mass, thrust and yaw-moment
scales, inertia, drags, CoM offset: ``evaluate.affine``) this is exact.  A joint variant is then fitted on
``R_c(theta_c) + D_a (theta_a - theta_a0)``: where the candidate is affine too (``judging._affine_form``) the
whole problem is linear and costs microseconds; otherwise each search step evaluates the flight only when the
candidate's own parameters move (the accepted ones are a matrix product), started from the plain candidate's
fold fit.  The fitted variant is then judged like any fit, on true evaluations of the joint vehicle
(``judging._fold_fit``), so the linearisation can only cost a variant its acceptance, never grant it one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, lsq_linear

from twin_nodes.discovery.blocktest import MIN_TEST_BLOCKS, _block_stats
from twin_nodes.discovery.candidates import Candidate
from twin_nodes.discovery.judging import Fit, Judge, _affine_form, _scales
from twin_nodes.physics.effects import EFFECTS
from twin_nodes.base.errors import ParamsError
from twin_nodes.vehicle.params import VehicleParams

#: the round's entries (by their plain fit's best cross-validated cut) offered with the accepted refitted
TOP_K = 4
#: a candidate whose plain fit explains less than this on every residual gets no joint variant
MIN_PLAIN_CUT = 0.0
#: the search's evaluations of a joint variant whose candidate is not affine
MAX_NFEV = 40
#: fit joint variants on the linearised form (False: on true evaluations of every step, the slow way, kept to
#: measure what the linearisation saves)
LINEARISED = True


@dataclass
class Linearized:
    """The accepted equation-error effects' parameters and regressors on one residual at ``current``."""

    names: list[str]                  # accepted effect per block of parameters
    params: list[tuple[str, ...]]     # their own fitted parameter names
    theta0: np.ndarray                # (p,) accepted values
    lower: np.ndarray
    upper: np.ndarray
    D: np.ndarray                     # (p, rows, channels): dR/dtheta
    fits: list[Fit]                   # the accepted fits


def own_params(a: Fit) -> list[int]:
    """The indices of an accepted fit's own effect parameters (a joint variant accepted before also carries the
    parameters of the effects it refitted)."""
    return [i for i, k in enumerate(a.candidate.param_names) if k in EFFECTS[a.candidate.name].param_names]


def merged(params: dict, names: tuple, values: np.ndarray, tied: dict) -> dict:
    """An effect's parameters with ``names`` set to ``values`` (and those tied to them following)."""
    out = {**params, **{k: float(v) for k, v in zip(names, values)}}
    out.update({k: out[v] for k, v in tied.items() if v in out})
    return out


def in_place(vp: VehicleParams, name: str, params: dict) -> VehicleParams:
    """``vp`` with effect ``name``'s parameters replaced where it stands in the effect order (its parameters not in
    ``params`` kept: a horizontal-only linear drag refitted stays horizontal only)."""
    new = vp.with_effect(name, **{**vp.effect_dict.get(name, {}), **params})
    eff = dict(new.effects)
    return new.replace(effects=tuple((n, eff[n]) for n, _ in vp.effects))


def _apply(vp: VehicleParams, lin: Linearized, theta_a: np.ndarray) -> VehicleParams:
    """``vp`` with the accepted effects of ``lin`` at ``theta_a`` (in place)."""
    k = 0
    for a, names in zip(lin.fits, lin.params):
        name = a.candidate.name
        pa = merged(a.candidate.params_dict(a.theta), names, theta_a[k:k + len(names)], a.candidate.tied)
        # the effect's own parameters (the wind offered with a drag reports the drag's beside them)
        vp = in_place(vp, name, {p: v for p, v in pa.items() if p in EFFECTS[name].param_names})
        k += len(names)
    return vp


def linearize(judge: Judge, current: VehicleParams, accepted: list[Fit]) -> Linearized | None:
    """The regressors of every parameter of the effects accepted on the equation error, at ``current`` (one
    residual evaluation per parameter: a step of 2 % of its range into the range; exact for affine effects)."""
    fits = [a for a in accepted if a.kind == "equation" and own_params(a)]
    if not fits:
        return None
    params, th, lo, hi = [], [], [], []
    eff = {n: dict(p) for n, p in current.effects}
    for a in fits:
        own = own_params(a)
        params.append(tuple(a.candidate.param_names[i] for i in own))
        # the values the vehicle carries (the refit may have moved them since the fit)
        th.append(np.array([eff.get(a.candidate.name, {}).get(params[-1][k], a.theta[i]) for k, i in enumerate(own)]))
        lo.append(a.candidate.lower[own])
        hi.append(a.candidate.upper[own])
    lin = Linearized([a.candidate.name for a in fits], params, np.concatenate(th), np.concatenate(lo),
                     np.concatenate(hi), np.empty(0), fits)
    R0 = judge.residual(current)
    D = np.empty((len(lin.theta0),) + R0.shape)
    for j in range(len(lin.theta0)):
        span = lin.upper[j] - lin.lower[j]
        h = 0.02 * span if lin.upper[j] - lin.theta0[j] >= 0.02 * span else -0.02 * span
        th = lin.theta0.copy()
        th[j] += h
        D[j] = (judge.residual(_apply(current, lin, th)) - R0) / h
    lin.D = D
    return lin


@dataclass
class _Joint(Candidate):
    """A candidate with the accepted effects of ``lin`` free beside it (their parameters after its own)."""

    base: Candidate | None = None
    lin: Linearized | None = None
    #: per fold (fit mask identity -> the plain candidate's fold fit): the start of the search
    starts: tuple = ()
    #: offered as a second effect on this mode (:func:`shape_partners`): the share it explains is read there
    shared_mode: str | None = None

    def params_dict(self, theta):
        return self.base.params_dict(theta[:len(self.base.param_names)])

    @property
    def refits(self) -> list[str]:
        return list(self.lin.names)

    def fit_on(self, judge: Judge, fit_mask: np.ndarray) -> tuple[np.ndarray, VehicleParams, float]:
        """Fitted on the equation error's fit rows (:func:`fit`; ``judging.fit_candidate`` comes here; None: fit it
        the slow way, on true evaluations)."""
        return fit(self, judge, fit_mask) if LINEARISED else None


#: effects of one kind: a joint variant never frees an accepted effect of its candidate's kind (the IMU fixes
#: only force per unit mass: a mass with a thrust coefficient both free trade along that ridge and take up in
#: the horizontal channels what a missing drag leaves, PX4 SIH grid s044; two drag laws are one law's freedom)
KINDS = ({"mass", "thrust_coefficient"}, {"linear_drag", "rotor_drag", "body_drag"})


def _same_kind(a: str, b: str) -> bool:
    return a == b or any(a in k and b in k for k in KINDS)


def partners(c: Candidate, lin: Linearized) -> tuple[int, ...]:
    """The blocks of ``lin`` (accepted effects) refitted beside ``c``: not of its kind, no shared parameter name."""
    return tuple(i for i, (name, names) in enumerate(zip(lin.names, lin.params))
                 if not _same_kind(c.name, name) and not set(c.param_names) & set(names))


def subset(lin: Linearized, blocks: tuple[int, ...]) -> Linearized:
    """``lin`` restricted to the accepted effects ``blocks``."""
    starts = np.cumsum([0] + [len(p) for p in lin.params])
    idx = np.concatenate([np.arange(starts[i], starts[i + 1]) for i in blocks]).astype(int)
    return Linearized([lin.names[i] for i in blocks], [lin.params[i] for i in blocks], lin.theta0[idx],
                      lin.lower[idx], lin.upper[idx], lin.D[idx], [lin.fits[i] for i in blocks])


def variant(c: Candidate, lin: Linearized, plain: list[Fit], shared_mode: str | None = None,
            cls: type[_Joint] | None = None) -> _Joint:
    """``c`` with the accepted effects of ``lin`` refitted jointly (``shared_mode``: :attr:`_Joint.shared_mode`), as
    a :class:`_Joint` or the subclass ``cls`` (one that fits otherwise, e.g. :class:`.throttle_pair._Pair`)."""
    n = len(c.param_names)
    eq = next((f for f in plain if f.kind == "equation"), None)

    def build(theta, c=c, lin=lin, n=n):
        return _apply(c.build(theta[:n]), lin, theta[n:])

    def unphysical(theta, c=c, lin=lin, n=n):
        why = c.unphysical(theta[:n])
        k = n
        for a, names in zip(lin.fits, lin.params):
            full = merged(a.candidate.params_dict(a.theta), names, theta[k:k + len(names)], a.candidate.tied)
            why = why or a.candidate.unphysical(np.array([full.get(p, 0.0) for p in a.candidate.param_names]))
            k += len(names)
        return why
    names = tuple(c.param_names) + tuple(k for p in lin.params for k in p)
    j = (cls or _Joint)(c.name, names, np.concatenate([c.x0, lin.theta0]), np.concatenate([c.lower, lin.lower]),
                        np.concatenate([c.upper, lin.upper]), build, dict(c.fixed),
                        lambda th, c=c, n=n: c.floor(th[:n]), f"{c.label} (+{', '.join(lin.names)} refitted)",
                        unphysical, dict(c.held), dict(c.tied))
    j.base, j.lin = c, lin
    j.starts = tuple(eq.fold_thetas) if eq is not None else ()
    j.shared_mode = shared_mode
    return j


def offer(accepted: list[Fit], cands: list[Candidate], per_label: dict[str, list[Fit]], judge: Judge,
          current: VehicleParams) -> list[tuple[list[Candidate], np.ndarray]]:
    """The joint variants of the round's :data:`TOP_K` strongest entries (their plain fits in ``per_label``), in
    groups that free the same accepted effects, each group with the residual it is judged against
    (:func:`baseline`)."""
    if not accepted:
        return []
    best: dict[str, tuple[float, Candidate]] = {}
    for c in cands:
        fl = per_label.get(c.label)
        if not fl or " (+" in c.label:
            continue
        cut = max(f.rel_improvement for f in fl)
        key = c.name if c.name == "motor_efficiency" else c.label
        if cut > MIN_PLAIN_CUT and (key not in best or cut > best[key][0]):
            best[key] = (cut, c)
    top = [c for _, c in sorted(best.values(), key=lambda x: -x[0])[:TOP_K]]
    shared = shape_partners(accepted, cands, per_label)
    top += [c for c in cands if c.label in shared and c not in top]
    lin = linearize(judge, current, accepted) if top else None
    if lin is None:
        return []
    groups: dict[tuple[int, ...], list[Candidate]] = {}
    for c in top:
        blocks = partners(c, lin)
        if blocks:
            groups.setdefault(blocks, []).append(c)
    out = []
    for blocks, cs in groups.items():
        sub = subset(lin, blocks)
        out.append(([variant(c, sub, per_label[c.label], shared.get(c.label)) for c in cs],
                    baseline(judge, current, sub)))
    return out


#: what an effect's regressor looks like over a flight, per channel it shares with others (issue 26, "two effects
#: on one channel"): on the collective a constant scale, the pack voltage, the height, the airspeed; on yaw a
#: scale or the body rate.  Yaw in command units is Izz r' + k_d r = k_m du: homogeneous, so a yaw moment and a yaw
#: inertia are one scale there (only k_m / Izz and k_d / Izz are read: PX4 SIH u017, damping, Izz and k_m all
#: accepted came out 0.56x of the truth together).  Two effects of different shapes can both act; the first
#: accepted takes up what it can of the other (a battery sag's level is a thrust deficit's), which then has little
#: plain cut left and was not refitted jointly with it
CHANNEL_SHAPES = {
    "throttle": {"mass": "constant", "thrust_coefficient": "constant", "battery_sag": "voltage",
                 "ground_effect": "height", "body_drag": "airspeed", "linear_drag": "airspeed",
                 "rotor_drag": "airspeed"},
    "yaw": {"yaw_moment": "scale", "inertia": "scale", "angular_damping": "rate"},
}
COLLECTIVE_SHAPES = CHANNEL_SHAPES["throttle"]


def shape_partners(accepted: list[Fit], cands: list[Candidate], per_label: dict[str, list[Fit]]
                   ) -> dict[str, str]:
    """The candidates (label -> the mode they share) acting on a mode beside an accepted equation-error effect
    there of another shape (:data:`CHANNEL_SHAPES`), offered jointly whatever their plain cut (it is what the
    accepted one left), the share they explain read in that mode (the first one, of the same size, was judged
    on every channel: a second one is a part of a part)."""
    out: dict[str, str] = {}
    for mode, shapes in CHANNEL_SHAPES.items():
        taken = {shapes.get(a.candidate.name) for a in accepted if a.kind == "equation"} - {None}
        if taken:
            out.update({c.label: mode for c in cands if per_label.get(c.label) and " (+" not in c.label
                        and c.label not in out and shapes.get(c.name) not in taken | {None}})
    return out


def baseline(judge: Judge, current: VehicleParams, lin: Linearized) -> np.ndarray:
    """What the joint variants are judged against: the accepted effects alone refitted on each fold's fit rows
    (a bounded linear solve on their regressors, then a true evaluation), that fold's test rows from that fit.
    The accepted values were fitted on fold 1's fit rows; against ``current`` itself, fold 2's test rows would
    hold them in-sample, and any refit would look worse there than it is."""
    R0 = judge.residual(current)
    out = np.zeros_like(R0)
    p = len(lin.theta0)
    for fit_mask, test_mask in judge.folds:
        A = lin.D[:, fit_mask].reshape(p, -1).T
        sol = lsq_linear(A, -R0[fit_mask].ravel(), bounds=(lin.lower - lin.theta0, lin.upper - lin.theta0))
        out[test_mask] = judge.residual(_apply(current, lin, lin.theta0 + sol.x))[test_mask]
    return out


def fit(c: _Joint, judge: Judge, fit_mask: np.ndarray) -> tuple[np.ndarray, VehicleParams, float]:
    """A joint variant fitted on the fit rows of the equation error: ``R_c(theta_c) + D_a (theta_a - theta_a0)``
    (see the module doc); returns (theta, the joint vehicle, the cost on that linearised form)."""
    base, lin = c.base, c.lin
    n = len(base.param_names)
    s = _scales(c)
    lo, hi = c.lower / s, c.upper / s
    d = lin.D[:, fit_mask].reshape(len(lin.theta0), -1)
    form = _affine_form(base, judge)
    if form is not None:
        rc = form.on(fit_mask)
    else:
        seen: dict[bytes, np.ndarray] = {}

        def rc(th_c):
            key = th_c.tobytes()
            r = seen.get(key)
            if r is None:
                if len(seen) > 64:
                    seen.clear()
                r = seen[key] = judge.residual(base.build(th_c))[fit_mask].ravel()
            return r

    def resid(z):
        th = np.clip(z * s, c.lower, c.upper)
        return rc(th[:n]) + (th[n:] - lin.theta0) @ d

    k = next((i for i, (fm, _) in enumerate(judge.folds) if fm is fit_mask), None)
    starts = [np.concatenate([np.clip(base.x0, base.lower, base.upper), lin.theta0])]
    if k is not None and k < len(c.starts):
        starts.insert(0, np.concatenate([c.starts[k], lin.theta0]))
    best_z, best_cost = None, np.inf
    for z in starts:
        z = np.clip(z / s, lo, hi)
        cost = float(np.sum(resid(z) ** 2))
        if cost < best_cost:
            best_z, best_cost = z, cost
    sol = least_squares(resid, best_z, bounds=(lo, hi), x_scale=1.0, diff_step=1e-2,
                        max_nfev=200 if form is not None else MAX_NFEV, method="trf")
    theta = np.clip(sol.x * s, c.lower, c.upper)
    return theta, c.build(theta), float(2 * sol.cost)


# ---------------------------------------------------------------- each accepted effect's contribution given the others


def contributions(judge: Judge, vp: VehicleParams, accepted: list[Fit]) -> dict[int, dict]:
    """For a result with several accepted effects: each equation-error effect's held-out contribution *given the
    others* (index in ``accepted`` -> ``{"cut", "t", "residual"}``): the cross-validated cut of the final vehicle
    ``vp`` against the same vehicle with that effect at its nominal value, the others refitted on each fold
    (:func:`baseline`, both on true evaluations).  Unlike the cut it was accepted with (on top of the effects
    accepted before it), this does not credit the first effect with what it had taken up of a later one."""
    lin = linearize(judge, vp, accepted) if len(accepted) > 1 else None
    if lin is None:
        return {}
    test = np.zeros(judge.held_mask.shape, bool)
    for _, t in judge.folds:
        test |= t
    full = baseline(judge, vp, lin)
    starts = np.cumsum([0] + [len(p) for p in lin.params])
    out = {}
    for i, a in enumerate(lin.fits):
        th = lin.theta0.copy()
        own = own_params(a)
        th[starts[i]:starts[i + 1]] = np.clip(a.candidate.x0[own], a.candidate.lower[own], a.candidate.upper[own])
        others = tuple(k for k in range(len(lin.names)) if k != i)
        try:
            vp_i = _apply(vp, lin, th)
            without = baseline(judge, vp_i, subset(lin, others)) if others else judge.residual(vp_i)
        except ParamsError as exc:
            # a what-if vehicle that cannot exist (the others refitted without it cannot lift the vehicle:
            # an overloaded Quad X of the real fleet, 23_juni log_20): said, not computed, and the flight goes on
            out[accepted.index(a)] = {"cut": None, "t": None, "residual": judge.kind,
                                      "not_computed": f"without it the others refit to a vehicle out of range: "
                                                      f"{str(exc).split(': ', 1)[-1]}"}
            continue
        r0, r1 = float(np.sqrt(np.mean(without[test] ** 2))), float(np.sqrt(np.mean(full[test] ** 2)))
        st = _block_stats(without, full, judge.blocks, 0.0)
        row = {"cut": round(1.0 - r1 / r0, 4) if r0 > 0 else 0.0,
               "t": round(float(st["t"]), 2) if st["tested"] and np.isfinite(st["t"]) else None, "residual": judge.kind}
        if not st["tested"]:
            row["not_judged"] = f"{st['n']} active held-out blocks (< {MIN_TEST_BLOCKS}): the block test did not run"
        out[accepted.index(a)] = row
    return out
