"""Issue 26, "an effect absorbed by the first one found": every later candidate also competes with the accepted
effects refitted jointly (``discovery.stages.joint``), on a linearised form that is judged on true evaluations."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from twin_nodes.discovery import evaluate
from twin_nodes.discovery.candidates import build_candidates
from twin_nodes.discovery.judging import BLOCK_S, Judge, _blocks
from twin_nodes.discovery.stages import joint, selection
from twin_nodes.vehicle.params import shipped

MASS, DRAG = 1.2, 1.5     # the truth: the model's 1 kg and linear drag 1.0 N/(m/s)


def _flight(seed: int = 0, rho: float = 0.95, drag: float = DRAG):
    """A synthetic equation-error problem with two effects at once: a mass (regressor X1) and the nominal linear
    drag's size (X2), their regressors correlated ``rho`` over the flight (what a thrust per unit mass and a drag
    both move in tilted flight), white noise; residual = y - m X1 - k X2 in the equation error's six channels."""
    rng = np.random.default_rng(seed)
    dt, T = 0.02, 120.0
    t = np.arange(0.0, T, dt)

    def smooth(k):
        x = sum(a * np.sin(2 * np.pi * f * t + ph)
                for f, a, ph in zip(rng.uniform(0.05, 0.6, k), rng.normal(size=k), rng.uniform(0, 6.3, k)))
        return x / x.std()
    base, other = smooth(8), smooth(8)
    w = np.array([1.0, 0.9, 1.1, 1.0, 0.5, 0.4])
    X1 = 0.05 * base[:, None] * w
    X2 = 0.01 * (rho * base + np.sqrt(1 - rho ** 2) * other)[:, None] * w
    y = MASS * X1 + drag * X2 + 0.002 * rng.normal(size=X1.shape)
    vp = shipped("px4_sih_quadx")
    calls = []

    def residual(v, rows=None):
        calls.append(1)
        eff = {k: dict(p) for k, p in v.effects}
        R = y - eff.get("mass", {}).get("mass", v.mass_kg) * X1 - eff["linear_drag"]["k_n_s_m"] * X2
        return R if rows is None else R[rows]
    folds = [(t < 0.65 * T, t >= 0.65 * T), (t >= 0.35 * T, t < 0.35 * T)]
    eq = Judge("equation", residual, folds, _blocks(t, folds[0][1], BLOCK_S) + _blocks(t, folds[1][1], BLOCK_S),
               folds[0][1])
    n = t.size
    data = SimpleNamespace(v=np.tile([[5.0, 0.0, 0.0]], (n, 1)), valid=np.ones(n, bool), motor_dt_s=0.004, dt=dt,
                           height=np.full(n, 10.0), battery_v=np.full(n, np.nan))
    return SimpleNamespace(eq=eq, oe=None, data=data, nominal=vp), calls


def _found(sel) -> dict:
    return {f.candidate.name: f.candidate.params_dict(f.theta) for f in sel.accepted}


def test_only_the_joint_refit_recovers_both_effects(monkeypatch):
    monkeypatch.setattr(evaluate, "WORKERS", 1)
    S, _ = _flight()
    sel = selection.run(selection.SelectionInput(S))
    found = _found(sel)
    assert set(found) == {"mass", "linear_drag"}
    assert found["mass"]["mass"] == pytest.approx(MASS, rel=0.02)
    assert found["linear_drag"]["k_n_s_m"] == pytest.approx(DRAG, rel=0.03)
    drag = sel.accepted[1]
    assert drag.candidate.label == "linear_drag (nominal refitted) (+mass refitted)"
    assert drag.joint_refit_of == "mass" and sel.accepted[0].refitted_jointly_with == "linear_drag"
    # the mass took the joint value (the vehicle the next round and the refit start from)
    assert dict(dict(sel.current.effects)["mass"])["mass"] == pytest.approx(MASS, rel=0.02)

    # each one's held-out contribution given the other (both linear: the drag's is the cut it was accepted with)
    given = joint.contributions(S.eq, sel.current, sel.accepted)
    assert given[1]["cut"] == pytest.approx(drag.rel_improvement, abs=1e-3) and given[1]["t"] > 3
    assert given[0]["cut"] > 0.1 and given[0]["t"] > 3

    # without the joint variants: the mass fitted first takes up the drag's share, and the drag left is too small
    monkeypatch.setattr(selection, "offer", lambda *a: [])
    S, _ = _flight()
    sel = selection.run(selection.SelectionInput(S))
    found = _found(sel)
    assert set(found) == {"mass"}
    assert abs(found["mass"]["mass"] / MASS - 1) > 0.05
    assert not sel.last["linear_drag"].accepted and sel.last["linear_drag"].rel_improvement < 0.10


def test_no_second_effect_where_there_is_one(monkeypatch):
    # the same kind of flight with the drag at the model's size: the joint variants find nothing beside the mass
    monkeypatch.setattr(evaluate, "WORKERS", 1)
    for seed in (3, 4):
        S, _ = _flight(seed=seed, drag=1.0)
        sel = selection.run(selection.SelectionInput(S))
        found = _found(sel)
        assert set(found) == {"mass"} and found["mass"]["mass"] == pytest.approx(MASS, rel=0.02)


def test_linearised_fit_is_the_true_joint_fit_and_cheap(monkeypatch):
    # both effects enter linearly: the linearised joint fit equals the fit on true evaluations, and it evaluates
    # the flight a fixed handful of times instead of once per search step
    monkeypatch.setattr(evaluate, "WORKERS", 1)
    S, calls = _flight(seed=1)
    mass = next(c for c in build_candidates(S.nominal, S.data) if c.name == "mass")
    a = SimpleNamespace(candidate=mass, theta=np.array([1.29]), kind="equation")
    current = mass.build(a.theta)
    drag = next(c for c in selection.nominal_refits(S.nominal, current) if c.name == "linear_drag")
    plain = [SimpleNamespace(kind="equation", fold_thetas=[np.array([1.05]), np.array([1.05])])]
    lin = joint.linearize(S.eq, current, [a])
    assert lin.names == ["mass"] and lin.D.shape[0] == 1
    v = joint.variant(drag, lin, plain)
    assert v.param_names == ("k_n_s_m", "mass") and v.label == "linear_drag (nominal refitted) (+mass refitted)"
    fit_mask = S.eq.folds[0][0]
    calls.clear()
    theta, vp_j, _ = joint.fit(v, S.eq, fit_mask)
    n_fast = len(calls)
    assert n_fast <= 8                                         # the candidate's affine form: 1 + 1 + 3 checks
    eff = {k: dict(p) for k, p in vp_j.effects}
    assert eff["linear_drag"]["k_n_s_m"] == pytest.approx(theta[0]) and eff["mass"]["mass"] == pytest.approx(theta[1])
    monkeypatch.setattr(joint, "LINEARISED", False)
    from twin_nodes.discovery.judging import fit_candidate
    calls.clear()
    theta_slow, _, _ = fit_candidate(v, S.eq, S.nominal, fit_mask)
    assert theta == pytest.approx(theta_slow, rel=1e-4)
    assert theta == pytest.approx([DRAG, MASS], rel=0.03)


def test_an_accepted_effect_of_the_candidates_kind_is_not_freed():
    # a mass beside an accepted thrust coefficient (one force per unit mass) or two drag laws: never both free
    vp = shipped("px4_sih_quadx")
    data = SimpleNamespace(v=np.tile([[5.0, 0.0, 0.0]], (100, 1)), valid=np.ones(100, bool), motor_dt_s=0.004,
                           dt=0.004, height=np.full(100, 10.0), battery_v=np.full(100, np.nan))
    cands = {c.label: c for c in build_candidates(vp, data)}
    lin = joint.Linearized(["thrust_coefficient", "body_drag"], [("kt_scale",), ("c_dx", "c_dy", "c_dz")],
                           np.array([0.87, 0.1, 0.1, 0.1]), np.zeros(4), np.ones(4), np.zeros((4, 1, 1)), ["kt", "cd"])
    assert joint.partners(cands["mass"], lin) == (1,)
    assert joint.partners(cands["rotor_drag"], lin) == (0,)
    assert joint.partners(cands["yaw_moment"], lin) == (0, 1)
    sub = joint.subset(lin, (1,))
    assert sub.names == ["body_drag"] and list(sub.theta0) == [0.1, 0.1, 0.1] and sub.D.shape[0] == 3
    assert sub.fits == ["cd"]


def test_an_accepted_wind_with_its_drag_is_refitted_as_the_wind():
    # wind(+linear_drag) (a vehicle without a drag law) reports its drag beside the wind's parameters: refitted
    # jointly, the wind's own parameters move and the drag stays where the vehicle has it
    vp = shipped("px4_sih_quadx").replace(effects=())
    data = SimpleNamespace(v=np.tile([[5.0, 0.0, 0.0]], (100, 1)), valid=np.ones(100, bool))
    w = selection.wind_with_drag(vp, data)[0]
    a = SimpleNamespace(candidate=w, theta=np.array([2.0, -1.0, 0.5]), kind="equation")

    def residual(v):
        eff = {n: dict(p) for n, p in v.effects}
        return np.array([[eff["wind"]["vx"], eff["wind"]["vy"], eff["linear_drag"]["k_n_s_m"]]])
    lin = joint.linearize(SimpleNamespace(residual=residual), w.build(a.theta), [a])
    assert lin.params == [("vx", "vy")] and list(lin.theta0) == [2.0, -1.0]
    assert lin.D[:, 0] == pytest.approx(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))


def test_the_wind_offered_with_its_drag_refits_jointly_with_another_effect(monkeypatch):
    """The wind offered with the drag it needs (a vehicle without a drag law) accepted beside another
    equation-error effect: the joint refit builds the vehicle with the drag and the wind (before, it passed the
    drag's size to the wind effect, which has no such parameter: a parameter error in the refit stage)."""
    from types import SimpleNamespace

    from twin_nodes.discovery.stages import refit
    from twin_nodes.discovery.stages.selection import wind_with_drag
    from twin_nodes.discovery.candidates import Candidate
    from twin_nodes.vehicle.params import shipped

    vp = shipped("px4_sih_quadx")
    vp = vp.replace(effects=tuple((n, p) for n, p in vp.effects if n not in ("linear_drag", "rotor_drag", "body_drag")))
    data = SimpleNamespace(v=np.tile([3.0, 0.0, 0.0], (50, 1)), valid=np.ones(50, bool))
    wind = wind_with_drag(vp, data)[0]
    theta_w = np.array([2.0, -1.0, 0.5])
    built = wind.apply(vp, theta_w)
    eff = {n: dict(p) for n, p in built.effects}
    assert eff["linear_drag"]["k_n_s_m"] == pytest.approx(0.5)
    assert (eff["wind"]["vx"], eff["wind"]["vy"]) == (pytest.approx(2.0), pytest.approx(-1.0))
    mass = Candidate("mass", ("mass",), np.array([1.0]), np.array([0.5]), np.array([2.0]),
                     lambda th: vp.with_effect("mass", mass=float(th[0])), {}, lambda th: True)
    fits = [SimpleNamespace(kind="equation", candidate=wind, theta=theta_w.copy()),
            SimpleNamespace(kind="equation", candidate=mass, theta=np.array([1.1]))]
    monkeypatch.setattr(refit, "residual_channels", lambda d, v, nominal: np.zeros((20, 3)))
    out = refit._joint_refit(fits, data, vp, np.ones(20, bool))
    eff = {n: dict(p) for n, p in out.effects}
    assert eff["linear_drag"]["k_n_s_m"] == pytest.approx(0.5) and eff["wind"]["vx"] == pytest.approx(2.0)
    assert eff["mass"]["mass"] == pytest.approx(1.1)
