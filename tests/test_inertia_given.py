"""stages.inertia_given: an output-error inertia judged again given the effects accepted beside it."""

import numpy as np

from test_modes import PARAMS
from twin_nodes.discovery.candidates import Candidate
from twin_nodes.discovery.judging import Fit, Judge
from twin_nodes.discovery.stages import inertia_given
from twin_nodes.vehicle.params import load_params

N, BLOCK = 400, 20


def _ixx(vp):
    return dict(dict(vp.effects).get("inertia", ())).get("ixx", vp.inertia[0, 0])


def _judge(true_ixx: float, noise: np.ndarray) -> Judge:
    """A fake output error: the roll error grows with the model's Ixx off ``true_ixx`` (a rate-response scale)."""
    drive = np.sin(np.linspace(0.0, 40.0, N))

    def residual(vp, rows=None):
        r = np.stack([(_ixx(vp) / true_ixx - 1.0) * drive + noise, noise[::-1]], axis=1)
        return r if rows is None else r[rows]

    half = np.arange(N) < N // 2
    blocks = [np.arange(i, i + BLOCK) for i in range(0, N, BLOCK)]
    return Judge("output", residual, [(half, ~half), (~half, half)], blocks, ~half)


def _fit(vp, ixx: float, kind: str = "output") -> Fit:
    x0 = np.array([vp.inertia[0, 0]])
    c = Candidate("inertia", ("ixx",), x0, 0.5 * x0, 2.0 * x0, build=None,
                  fixed={"iyy": float(vp.inertia[1, 1]), "izz": float(vp.inertia[2, 2])}, floor=lambda th: True)
    return Fit(c, np.array([ixx]), c.apply(vp, [ixx]), 0.0, 0.0, np.zeros(2), 5.0, 10, 0.7, True, accepted=True,
               kind=kind)


def _other():
    return Fit(Candidate("battery_sag", ("exponent",), np.zeros(1), np.zeros(1), np.ones(1), build=None, fixed={},
                         floor=lambda th: True), np.ones(1), None, 0.0, 0.0, np.zeros(2), 5.0, 10, 0.6, True,
               accepted=True)


def test_inertia_not_borne_out_given_the_others_is_dropped():
    vp = load_params(PARAMS)
    ixx0 = float(vp.inertia[0, 0])
    noise = 0.01 * np.random.default_rng(3).standard_normal(N)
    inertia, sag = _fit(vp, 1.21 * ixx0), _other()
    # the others already explain the rate response: the true Ixx is the nominal's, the fitted x1.21 makes it worse
    kept, vp_out = inertia_given.run(_judge(ixx0, noise), [inertia, sag], inertia.vp)
    assert [id(f) for f in kept] == [id(sag)] and not inertia.accepted
    assert abs(_ixx(vp_out) - ixx0) < 1e-12
    assert inertia.given_others["cut"] == -9.5359 and inertia.given_others["t"] < 0.0


def test_inertia_borne_out_given_the_others_is_kept():
    vp = load_params(PARAMS)
    ixx0 = float(vp.inertia[0, 0])
    noise = 0.01 * np.random.default_rng(3).standard_normal(N)
    inertia, sag = _fit(vp, 1.6 * ixx0), _other()
    kept, vp_out = inertia_given.run(_judge(1.6 * ixx0, noise), [inertia, sag], inertia.vp)
    assert [id(f) for f in kept] == [id(inertia), id(sag)] and inertia.accepted
    assert abs(_ixx(vp_out) - 1.6 * ixx0) < 1e-12
    g = inertia.given_others
    assert g["cut"] > 0.9 and g["t"] > 3.0
    entries = [{"name": "inertia"}]
    inertia_given.annotate([inertia], entries)
    assert entries[0]["given_the_others"]["kept"] is True


def test_equation_error_inertia_and_a_lone_inertia_are_left_alone():
    vp = load_params(PARAMS)
    ixx0 = float(vp.inertia[0, 0])
    judge = _judge(ixx0, np.zeros(N))
    eq_inertia, sag = _fit(vp, 1.21 * ixx0, kind="equation"), _other()
    kept = inertia_given.run(judge, [eq_inertia, sag], eq_inertia.vp)[0]
    assert [id(f) for f in kept] == [id(eq_inertia), id(sag)]
    lone = _fit(vp, 1.21 * ixx0)
    assert [id(f) for f in inertia_given.run(judge, [lone], lone.vp)[0]] == [id(lone)]
    assert [id(f) for f in inertia_given.run(None, [lone, sag], lone.vp)[0]] == [id(lone), id(sag)]
