"""Physics outside the effect list: the structured residual test, sparse term discovery, naming.

After the accepted effects are refitted, what is left in the collective (throttle) channel is tested
for structure: is it explained by the flight's state, on held-out data?  The library is the state
term's features (:data:`twin_nodes.physics.effects.STATE_TERM_FEATURES`), each normalised to the
vehicle (horizontal airspeed and climb/descent rate over the hover induced velocity ``v_h``, height
over the rotor radius, rotor speed over its top speed, tilt), each entering as a thrust multiplier.
Its regressors are the change of the throttle residual that a unit coefficient makes, computed through
the model itself (:func:`term_regressors`), so a fitted coefficient is the coefficient the twin flies.

Method (:func:`find_term`):

1. **Sparse path**: scikit-learn's LARS-lasso path (``lars_path``) over the standardised regressors,
   with the constant thrust scale unpenalised (projected out); its active sets, plus every single
   feature, are the candidate term sets (at most :data:`MAX_TERMS` features).
2. **Cross-validated on held-out blocks**: each candidate set is fitted by least squares with scikit-
   learn's ``GroupKFold`` over contiguous :data:`GROUP_S` groups; every sample is predicted by a fit
   that did not see its group.  The smallest set within one standard error of the best held-out error
   is chosen (the one-standard-error rule).
3. **Structured residual test**: its out-of-fold residual against the constant-only model's over
   independent :data:`TEST_BLOCK_S` blocks (the block test every effect passes, t > 3), and its held-out
   RMS cut >= 10 %; the term must also change the thrust by >= :data:`MIN_GAIN_SPREAD` of itself over
   the flight (the resolution floor of the accelerometer's scale).
4. **Name** (:func:`name_term`): the mechanism whose signature features carry the term, with the sign
   physics gives it, or a drag linear in the vertical speed (a term odd in v_z); otherwise "unnamed term in
   throttle depending on <features>".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from twin_nodes.discovery.blocktest import _block_stats, not_significant
from twin_nodes.discovery.judging import MIN_REL_IMPROVEMENT, T_CRIT
from twin_nodes.discovery.residuals import EquationData, model_rotor_states, modes, residual_channels
from twin_nodes.physics.core import NX_BODY
from twin_nodes.physics.effects import STATE_TERM_FEATURES, STATE_TERM_MEANING, state_term_features
from twin_nodes.physics.model import Multirotor
from twin_nodes.vehicle.params import VehicleParams

#: air density [kg/m^3] for the hover induced velocity (ISA sea level)
RHO = 1.225
#: at most this many features in a term
MAX_TERMS = 3
#: cross-validation groups [s] (contiguous: a group's neighbours are correlated through the 2 Hz low-pass)
GROUP_S = 8.0
N_FOLDS = 5
#: fewer cross-validation groups than this: no held-out test (a flight of under ~24 s airborne)
MIN_GROUPS = 3
#: independent blocks of the structured residual test [s]
TEST_BLOCK_S = 2.0
#: samples kept per second (the residual is low-passed at 2 Hz)
RATE_HZ = 10.0
#: a term must change the thrust by at least this fraction over the flight (5th to 95th percentile):
#: 2 % is the accelerometer scale tolerance and ESC-to-ESC spread the vocabulary's scale floor uses (3 %)
MIN_GAIN_SPREAD = 0.02
#: the unit coefficient of the finite difference (the model is linear in the coefficients; small enough
#: that no multiplier reaches its clip)
_UNIT = 1e-2


def rotor_radius_m(vp: VehicleParams) -> float:
    """A rotor radius where the params do not state one: 0.3 x the spacing of adjacent rotors
    (X500 10" props on 0.354 m: 0.36; Crazyflie 45 mm on 65 mm: 0.35; PX4 SIH 8" on 0.4 m: 0.25)."""
    r = vp.rotors
    arm = float(np.median(np.hypot(r.x_flu_m, r.y_flu_m)))
    return 0.3 * 2.0 * arm * math.sin(math.pi / max(r.count, 2))


def hover_induced_velocity(vp: VehicleParams, radius: float) -> float:
    """Momentum theory's hover induced velocity v_h = sqrt(W / (2 rho n pi R^2)) [m/s]."""
    return math.sqrt(vp.mass_kg * vp.gravity_m_s2 / (2.0 * RHO * vp.rotors.count * math.pi * radius ** 2))


@dataclass
class Normaliser:
    """The vehicle's scales the features are normalised by."""

    v_h: float
    radius: float
    omega_max: float

    @classmethod
    def of(cls, vp: VehicleParams) -> "Normaliser":
        from twin_nodes.physics.effects import effective_params

        eff = effective_params(vp)
        radius = rotor_radius_m(eff)
        return cls(hover_induced_velocity(eff, radius), radius, float(eff.rotors.omega_max_rad_s))

    def fixed(self) -> dict:
        return {"v_h": self.v_h, "radius": self.radius, "omega_max": self.omega_max}


def _throttle(data: EquationData, vp: VehicleParams, nominal: VehicleParams) -> np.ndarray:
    return modes(residual_channels(data, vp, nominal), nominal)[0][:, 0]


def term_regressors(data: EquationData, current: VehicleParams, nominal: VehicleParams, norm: Normaliser
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``(y, X)``: the throttle residual the refitted vehicle ``current`` leaves (T,) and what each
    coefficient (``c_one`` first, then ``STATE_TERM_FEATURES``) takes out of it per unit (T, 1 + K),
    through the model (the state term flown on the logged state)."""
    base = dict(norm.fixed())
    y = _throttle(data, current.with_effect("state_term", **base), nominal)
    names = ["c_one"] + [f"c_{f}" for f in STATE_TERM_FEATURES]
    X = np.empty((len(y), len(names)))
    for k, name in enumerate(names):
        yk = _throttle(data, current.with_effect("state_term", **base, **{name: _UNIT}), nominal)
        X[:, k] = (y - yk) / _UNIT
    return y, X


def features_on_log(data: EquationData, current: VehicleParams, norm: Normaliser) -> np.ndarray:
    """The features (T, K), averaged over the rotors, on the logged state (for naming and reports)."""
    model = Multirotor(current)
    S = model_rotor_states(model, data)
    X = np.zeros((data.n, model.nx))
    X[:, NX_BODY:] = np.nan_to_num(S)
    omega = model.rotor_speeds(X)
    F = state_term_features(np.nan_to_num(data.v), data.height, np.nan_to_num(data.q), omega,
                            norm.v_h, norm.radius, norm.omega_max)
    return F.mean(axis=1)


def _groups(t: np.ndarray, span_s: float) -> np.ndarray:
    return np.floor((t - t[0]) / span_s).astype(int)


def _oof(X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Out-of-fold least-squares residual of y on X (GroupKFold over ``groups``)."""
    from sklearn.linear_model import LinearRegression
    from sklearn.model_selection import GroupKFold

    res = np.empty_like(y)
    n_groups = len(np.unique(groups))
    for train, test in GroupKFold(n_splits=min(N_FOLDS, n_groups)).split(X, y, groups):
        m = LinearRegression(fit_intercept=True).fit(X[train], y[train])
        res[test] = y[test] - m.predict(X[test])
    return res


def _path_supports(X: np.ndarray, y: np.ndarray) -> list[tuple[int, ...]]:
    """The LARS-lasso path's active sets (columns of the feature part of X, constant projected out),
    up to :data:`MAX_TERMS` features, plus every single feature."""
    from sklearn.linear_model import lars_path

    A = np.column_stack([np.ones(len(y)), X[:, 0]])
    P = X[:, 1:] - A @ np.linalg.lstsq(A, X[:, 1:], rcond=None)[0]
    r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
    sd = P.std(axis=0)
    ok = sd > 0
    Z = np.zeros_like(P)
    Z[:, ok] = P[:, ok] / sd[ok]
    _, _, coefs = lars_path(Z, r / max(r.std(), 1e-12), method="lasso", max_iter=4 * P.shape[1])
    supports: list[tuple[int, ...]] = [(k,) for k in range(P.shape[1]) if ok[k]]
    for j in range(coefs.shape[1]):
        s = tuple(int(k) for k in np.flatnonzero(coefs[:, j]))
        if 0 < len(s) <= MAX_TERMS and s not in supports:
            supports.append(s)
    return supports


@dataclass
class TermFit:
    """A term set, fitted and judged (feature indices into STATE_TERM_FEATURES)."""

    support: tuple[int, ...]
    coef: np.ndarray                   # c_one, then the support's coefficients (fitted on the fit part)
    cv_mse: float
    cv_se: float
    t_stat: float = 0.0
    n_blocks: int = 0
    cut: float = 0.0                   # held-out (out-of-fold) RMS cut against the constant-only model
    gain_spread: float = 0.0           # 5th..95th percentile spread of the fitted multiplier
    stats: dict = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        return [STATE_TERM_FEATURES[k] for k in self.support]

    def params(self) -> dict[str, float]:
        out = {"c_one": float(self.coef[0])}
        out.update({f"c_{n}": float(c) for n, c in zip(self.names, self.coef[1:])})
        return out


@dataclass
class TermSearch:
    """What the structured residual test and the sparse fit found (``best`` None: no term)."""

    best: TermFit | None
    tried: list[TermFit]
    null_mse: float
    n_samples: int
    why_none: str = ""


def find_term(y: np.ndarray, X: np.ndarray, t: np.ndarray, fit_rows: np.ndarray, feats: np.ndarray
              ) -> TermSearch:
    """The smallest feature set that explains the structured residual on held-out blocks.

    ``y`` (n,), ``X`` (n, 1 + K) (``c_one`` first), ``t`` (n,) times, ``fit_rows`` (n,) bool: the part the
    final coefficients are fitted on (the flight's fit part), ``feats`` (n, K) the features (for the
    multiplier's spread)."""
    groups = _groups(t, GROUP_S)
    n_groups = len(np.unique(groups))
    if n_groups < MIN_GROUPS:
        return TermSearch(None, [], float(np.mean(y ** 2)) if len(y) else 0.0, len(y),
                          f"too little airborne data for a held-out test: {n_groups} group(s) of {GROUP_S:g} s, "
                          f"{MIN_GROUPS} needed")
    blocks = [np.flatnonzero(b == _groups(t, TEST_BLOCK_S)) for b in np.unique(_groups(t, TEST_BLOCK_S))]
    r0 = _oof(X[:, :1], y, groups)
    null_mse = float(np.mean(r0 ** 2))
    tried: list[TermFit] = []
    for s in _path_supports(X, y):
        cols = [0] + [1 + k for k in s]
        r1 = _oof(X[:, cols], y, groups)
        per_group = np.array([np.mean(r1[groups == g] ** 2) for g in np.unique(groups)])
        tf = TermFit(s, np.zeros(len(cols)), float(np.mean(r1 ** 2)),
                     float(per_group.std(ddof=1) / math.sqrt(len(per_group))) if len(per_group) > 1 else 0.0)
        st = _block_stats(r0[:, None], r1[:, None], blocks)
        tf.t_stat, tf.n_blocks, tf.stats = float(st["t"]), int(st["n"]), st
        tf.cut = 1.0 - math.sqrt(tf.cv_mse / null_mse) if null_mse > 0 else 0.0
        tried.append(tf)
    if not tried:
        return TermSearch(None, [], null_mse, len(y), "no feature varies on this flight")
    best_mse = min(f.cv_mse for f in tried)
    best_se = next(f.cv_se for f in tried if f.cv_mse == best_mse)
    within = [f for f in tried if f.cv_mse <= best_mse + best_se]
    pick = min(within, key=lambda f: (len(f.support), f.cv_mse))
    cols = [0] + [1 + k for k in pick.support]
    A = np.column_stack([np.ones(int(fit_rows.sum())), X[fit_rows][:, cols]])
    sol = np.linalg.lstsq(A, y[fit_rows], rcond=None)[0]
    pick.coef = sol[1:]          # the regression intercept is the residual's offset, not thrust
    gain = feats[:, list(pick.support)] @ pick.coef[1:]
    pick.gain_spread = float(np.percentile(gain, 95) - np.percentile(gain, 5))
    why = []
    if pick.t_stat <= T_CRIT:
        why.append(not_significant(pick.t_stat, pick.n_blocks))
    if pick.cut < MIN_REL_IMPROVEMENT:
        why.append(f"explains only {100 * pick.cut:.0f} % of the held-out residual")
    if pick.gain_spread < MIN_GAIN_SPREAD:
        why.append(f"changes the thrust by only {100 * pick.gain_spread:.1f} % over the flight")
    return TermSearch(pick, tried, null_mse, len(y), "; ".join(why))


# ------------------------------------------------------------------ naming

#: mechanism -> (signature features, the sign physics gives the thrust change, what it is)
MECHANISMS = {
    "translational_lift": (("mu", "mu2"), +1, "translational lift: thrust gained with horizontal airspeed "
                                             "(the rotor's induced velocity falls as it moves into clean air)"),
    "vortex_ring": (("descent", "descent2"), -1, "vortex-ring state: thrust lost in a descent near the hover "
                                                "induced velocity (the rotor in its own wake)"),
    "ground_effect": (("ground",), +1, "ground effect (Cheeseman-Bennett): thrust gained within a few rotor "
                                      "radii of the ground"),
    "thrust_flattening": (("omega2", "omega4", "omega8"), -1, "thrust-curve flattening near full output: less thrust "
                                                   "than the omega^2 curve at high rotor speed"),
}


def _part(fit: TermFit, names: tuple[str, ...], feats: np.ndarray) -> np.ndarray:
    """The fitted multiplier's part carried by features ``names`` (n,)."""
    part = np.zeros(len(feats))
    for k, c in zip(fit.support, fit.coef[1:]):
        if STATE_TERM_FEATURES[k] in names:
            part += c * feats[:, k]
    return part


def _vertical_drag(fit: TermFit, feats: np.ndarray, weight_n: float | None, v_h: float | None) -> dict | None:
    """A term odd in the vertical speed (climb and descent with opposite signs: thrust ~ v_z) is a drag
    linear in the vertical speed, not rotor aerodynamics: a thrust change ``c v_z / v_h`` of the weight is
    a force ``W c / v_h`` per m/s along the vertical velocity (positive: the model's vertical drag is
    that much too strong, e.g. an isotropic linear drag identified on horizontal flight)."""
    c = dict(zip(fit.names, fit.coef[1:]))
    if "climb" not in c or "descent" not in c or c["climb"] * c["descent"] >= 0:
        return None
    pair = _part(fit, ("climb", "descent"), feats)
    rest = [float(np.std(_part(fit, sig, feats))) for m, (sig, _, _) in MECHANISMS.items()
            if m != "vortex_ring"] + [float(np.std(_part(fit, ("descent2",), feats)))]
    if float(np.std(pair)) < max(rest):
        return None
    slope = 0.5 * (c["climb"] - c["descent"])          # thrust fraction per unit of v_z / v_h
    if weight_n and v_h:
        dk = weight_n * slope / v_h
        what = (f"the model's vertical drag is {dk:.3g} N/(m/s) too strong" if dk > 0 else
                f"a vertical drag of {-dk:.3g} N/(m/s) the model lacks")
    else:
        what = "a force along the vertical velocity" if slope > 0 else "a vertical drag the model lacks"
    return {"mechanism": "vertical_drag", "name": "drag linear in vertical speed",
            "meaning": "drag of a given law: linear in the vertical speed (the term is odd in v_z)",
            "evidence": f"thrust {100 * slope:+.1f} % per v_h of climb rate, the same law in descent: {what}"}


def name_term(fit: TermFit, feats: np.ndarray, weight_n: float | None = None, v_h: float | None = None) -> dict:
    """The mechanism a term matches, with the evidence (``mechanism`` None: unnamed).

    The term's parts by mechanism (the features each mechanism's signature owns; ``climb`` and ``tilt``
    belong to none); the largest part (spread over the flight) names it when its sign is the one
    physics gives that mechanism, where the mechanism acts: a thrust gain growing with airspeed, a loss
    at the flown descents of 0.5-1.5 v_h and not at slow ones, a gain near the ground, a loss at the
    highest rotor speeds flown against hover."""
    drag = _vertical_drag(fit, feats, weight_n, v_h)
    if drag is not None:
        return drag
    spreads = {m: float(np.std(_part(fit, sig, feats))) for m, (sig, _, _) in MECHANISMS.items()}
    other = tuple(f for f in fit.names if not any(f in sig for sig, _, _ in MECHANISMS.values()))
    spreads["other"] = float(np.std(_part(fit, other, feats))) if other else 0.0
    top = max(spreads, key=spreads.get)
    features = ", ".join(f"{n} ({STATE_TERM_MEANING[n]})" for n in fit.names)
    unnamed = {"mechanism": None, "name": f"unnamed term in throttle depending on {features}",
               "parts": {k: round(v, 4) for k, v in spreads.items() if v > 0}}
    if top == "other" or spreads[top] <= 0:
        return unnamed
    sig, sign, what = MECHANISMS[top]
    part = _part(fit, sig, feats)
    ok, note = _signature_holds(top, sign, part, feats)
    if not ok:
        unnamed["evidence"] = note
        return unnamed
    return {"mechanism": top, "name": what.split(":")[0], "meaning": what, "evidence": note,
            "parts": unnamed["parts"]}


def _at(feats: np.ndarray, name: str) -> np.ndarray:
    return feats[:, STATE_TERM_FEATURES.index(name)]


def _signature_holds(mech: str, sign: int, part: np.ndarray, feats: np.ndarray) -> tuple[bool, str]:
    """Whether the part has the sign and the place the mechanism gives it; (ok, the evidence in words)."""
    if mech == "translational_lift":
        mu = _at(feats, "mu")
        lo, hi = mu < 0.1, mu > np.percentile(mu, 90)
        if lo.sum() < 10 or hi.sum() < 10:
            return False, "too little forward flight to tell"
        d = float(np.median(part[hi]) - np.median(part[lo]))
        return d * sign > 0, (f"thrust {100 * d:+.1f} % at horizontal airspeed >= {np.percentile(mu, 90):.2f} v_h "
                              "against hover")
    if mech == "vortex_ring":
        dsc = _at(feats, "descent")
        band, slow = (dsc >= 0.5) & (dsc <= 1.5), dsc < 0.2
        if band.sum() < 10:
            return False, (f"thrust {100 * float(np.min(part)):+.1f} % in descent, but the flight never descends at "
                           "0.5-1.5 v_h (not the vortex-ring range)")
        d_band = float(np.median(part[band]) - np.median(part[slow]))
        return d_band * sign > 0, f"thrust {100 * d_band:+.1f} % at descent rates of 0.5-1.5 v_h against hover"
    if mech == "ground_effect":
        g = _at(feats, "ground")
        near, far = g > np.percentile(g, 95), g < np.percentile(g, 50)
        d = float(np.median(part[near]) - np.median(part[far]))
        return d * sign > 0 and near.sum() >= 10, f"thrust {100 * d:+.1f} % nearest the ground against high up"
    u2 = _at(feats, "omega2")
    top, mid = u2 > np.percentile(u2, 97), np.abs(u2 - np.median(u2)) < 0.02
    if top.sum() < 5 or mid.sum() < 10:
        return False, "too little range of rotor speed to tell"
    d = float(np.median(part[top]) - np.median(part[mid]))
    return d * sign > 0, (f"thrust {100 * d:+.1f} % at the top 3 % of rotor speeds (omega/omega_max >= "
                          f"{math.sqrt(np.percentile(u2, 97)):.2f}) against hover")


# ------------------------------------------------------------------ regimes flown too briefly to test

#: mechanism -> (the regime its signature lives in, as a test on the features, in words, the manoeuvre to fly)
REGIMES = {
    "vortex_ring": (lambda F: (_at(F, "descent") >= 0.5) & (_at(F, "descent") <= 1.5),
                    "descent at 0.5-1.5 v_h", "descents at {lo:.1f}-{hi:.1f} m/s (0.5-1.5 v_h), several seconds each"),
    "translational_lift": (lambda F: _at(F, "mu") >= 1.0, "horizontal airspeed >= v_h",
                           "straight legs at >= {v_h:.1f} m/s (v_h)"),
    "thrust_flattening": (lambda F: _at(F, "omega2") >= 0.85 ** 2, "rotor speed >= 0.85 of the top",
                          "hard climbs (rotor speeds >= 0.85 of the top)"),
}
#: a regime flown in fewer independent test blocks than this cannot be cross-validated
MIN_REGIME_BLOCKS = 4


def brief_regimes(y: np.ndarray, X: np.ndarray, t: np.ndarray, feats: np.ndarray, v_h: float) -> list[dict]:
    """Regimes a mechanism lives in that the flight entered, but in too few independent blocks for the
    held-out test: the thrust there against the model (in-sample, the residual over what a unit thrust
    scale takes out: a fraction of the thrust) and the manoeuvre that would make it testable."""
    out = []
    blocks = _groups(t, TEST_BLOCK_S)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.1
    for mech, (test, words, fly) in REGIMES.items():
        k = test(feats)
        n_blocks = len(np.unique(blocks[k]))
        if k.sum() * dt < 0.3 or n_blocks >= MIN_REGIME_BLOCKS:
            continue
        frac = y[k] / np.maximum(X[k, 0], 1e-9)
        rest = y[~k] / np.maximum(X[~k, 0], 1e-9)
        out.append({"mechanism": mech, "regime": words, "seconds": round(float(k.sum() * dt), 2),
                    "blocks": int(n_blocks), "times_s": [round(float(t[k][0]), 2), round(float(t[k][-1]), 2)],
                    "thrust_vs_model": round(float(np.median(frac) - np.median(rest)), 3),
                    "fly": fly.format(lo=0.5 * v_h, hi=1.5 * v_h, v_h=v_h),
                    "note": (f"{words} flown for {k.sum() * dt:.1f} s ({n_blocks} of the {MIN_REGIME_BLOCKS} independent "
                             f"{TEST_BLOCK_S:g}-s blocks a held-out test needs): thrust "
                             f"{100 * (np.median(frac) - np.median(rest)):+.0f} % against the model there (in-sample, "
                             f"not testable); fly {fly.format(lo=0.5 * v_h, hi=1.5 * v_h, v_h=v_h)}")})
    return out
