"""stages.stand_in: an equation-error effect accepted before others, judged again given all of them."""

import numpy as np

from test_modes import PARAMS
from twin_nodes.discovery.candidates import Candidate
from twin_nodes.discovery.judging import Fit
from twin_nodes.discovery.stages import stand_in
from twin_nodes.vehicle.params import load_params


def _fit(vp, name: str, param: str, x0: float, value: float, kind: str = "equation") -> Fit:
    c = Candidate(name, (param,), np.array([x0]), np.array([0.5 * x0]), np.array([2.0 * x0]), build=None,
                  fixed={}, floor=lambda th: True)
    return Fit(c, np.array([value]), c.apply(vp, [value]), 0.0, 0.0, np.zeros(2), 5.0, 10, 0.7, True,
               accepted=True, kind=kind)


def _given(rows_by_name):
    """A stand-in for joint.contributions: each kept fit's row by its effect name."""
    calls = []

    def contributions(eq, vp, kept):
        calls.append([f.candidate.name for f in kept])
        return {i: dict(rows_by_name[f.candidate.name]) for i, f in enumerate(kept)
                if f.candidate.name in rows_by_name}
    return contributions, calls


def test_the_seen_stand_ins_and_their_neighbours():
    # given the others (block t, cut): the four seen stand-ins of RotorPy batches 7-13 ...
    for g in ({"t": -1.34, "cut": -0.0017}, {"t": -0.16, "cut": -0.0004}, {"t": 0.66, "cut": 0.0006},
              {"t": 1.59, "cut": 0.03}):
        assert stand_in.stands_in(g)
    # ... and the nearest kept effects: true ones under the t bar with a large cut (w033's sag, g021's body drag),
    # a022's lag (t 3.10, cut 86 %), o034's yaw moment and the true yaw moments of g019 and c019 (small cuts with a
    # large t), a block test that did not run
    for g in ({"t": 2.93, "cut": 0.9508}, {"t": 2.89, "cut": 0.544}, {"t": 3.10, "cut": 0.8631},
              {"t": 4.48, "cut": 0.0157}, {"t": 5.43, "cut": 0.0181}, {"t": 5.29, "cut": 0.0646},
              # PX4 SIH d019, f011: a true angular damping accepted first, small cut, large t
              {"t": 6.52, "cut": 0.0313}, {"t": 9.47, "cut": 0.0444},
              {"t": None, "cut": 0.0}, {"t": 1.0, "cut": None}, None):
        assert not stand_in.stands_in(g)
    # both bars: a weak t with a real cut, or a small cut with t just over the bar, is kept
    assert not stand_in.stands_in({"t": 2.9, "cut": 0.10})
    assert not stand_in.stands_in({"t": 3.01, "cut": 0.05})
    assert stand_in.stands_in({"t": 3.0, "cut": 0.0999})


def test_the_first_effect_that_adds_nothing_given_the_later_ones_is_dropped_at_nominal(monkeypatch):
    vp = load_params(PARAMS)
    com = _fit(vp, "thrust_coefficient", "kt_scale", 1.0, 0.9988)     # c033: accepted first, refitted to ~1
    ground, drag = _fit(vp, "mass", "mass", 1.0, 1.2), _fit(vp, "yaw_moment", "km", 0.02, 0.03)
    vp_final = drag.candidate.apply(ground.candidate.apply(com.vp, [1.2]), [0.03])
    fake, calls = _given({"thrust_coefficient": {"t": 1.59, "cut": 0.03, "residual": "equation"},
                          "mass": {"t": 3.9, "cut": 0.73, "residual": "equation"}})
    monkeypatch.setattr(stand_in, "contributions", fake)
    kept, vp_out = stand_in.run(object(), [com, ground, drag], vp_final)
    assert [f.candidate.name for f in kept] == ["mass", "yaw_moment"] and not com.accepted
    assert com.given_others == {"t": 1.59, "cut": 0.03, "residual": "equation"}
    assert dict(dict(vp_out.effects)["thrust_coefficient"])["kt_scale"] == 1.0       # back at nominal
    assert dict(dict(vp_out.effects)["mass"])["mass"] == 1.2                          # the others as refitted
    # judged again after the drop, on what is kept
    assert calls == [["thrust_coefficient", "mass", "yaw_moment"], ["mass", "yaw_moment"]]


def test_the_last_accepted_a_lone_effect_and_an_output_error_fit_are_left_alone(monkeypatch):
    vp = load_params(PARAMS)
    a, b = _fit(vp, "mass", "mass", 1.0, 1.2), _fit(vp, "yaw_moment", "km", 0.02, 0.0201)
    weak = {"t": 0.1, "cut": 0.0, "residual": "equation"}
    fake, _ = _given({"yaw_moment": weak})
    monkeypatch.setattr(stand_in, "contributions", fake)
    # the last one accepted was judged on top of all the others already
    kept, _ = stand_in.run(object(), [a, b], b.vp)
    assert kept == [a, b] and b.accepted
    kept, _ = stand_in.run(object(), [b], b.vp)
    assert kept == [b]
    # an output-error fit is inertia_given's to judge
    oe = _fit(vp, "yaw_moment", "km", 0.02, 0.0201, kind="output")
    kept, _ = stand_in.run(object(), [oe, a], a.vp)
    assert kept == [oe, a] and oe.accepted


def test_two_stand_ins_for_each_other_lose_only_the_weaker(monkeypatch):
    vp = load_params(PARAMS)
    a, b, c = (_fit(vp, "thrust_coefficient", "kt_scale", 1.0, 0.95), _fit(vp, "mass", "mass", 1.0, 1.05),
               _fit(vp, "yaw_moment", "km", 0.02, 0.03))
    rows = {"thrust_coefficient": {"t": 0.5, "cut": 0.01}, "mass": {"t": 1.0, "cut": 0.02}}

    def fake(eq, vp, kept):
        names = [f.candidate.name for f in kept]
        out = {i: dict(rows[n]) for i, n in enumerate(names) if n in rows}
        if "thrust_coefficient" not in names:       # without its twin the mass carries the collective again
            out[names.index("mass")] = {"t": 6.0, "cut": 0.5}
        return out
    monkeypatch.setattr(stand_in, "contributions", fake)
    kept, _ = stand_in.run(object(), [a, b, c], c.vp)
    assert [f.candidate.name for f in kept] == ["mass", "yaw_moment"]


def test_a_dropped_stand_in_carries_its_numbers_given_the_others_into_the_result():
    from twin_nodes.discovery.stages.verdicts import _effect_json
    vp = load_params(PARAMS)
    f = _fit(vp, "thrust_coefficient", "kt_scale", 1.0, 0.9988)
    f.judged, f.accepted = ("throttle", 0.02, 0.0199), False
    f.given_others = {"t": 1.59, "cut": 0.03, "residual": "equation", "blocks": 12}
    out = _effect_json(f, ["throttle", "roll", "pitch", "yaw"], np.full(4, 0.01))
    assert out["given_others"] == {"t": 1.59, "cut": 0.03, "residual": "equation", "blocks": 12}
    assert not out["accepted"]
    f.given_others = None
    assert "given_others" not in _effect_json(f, ["throttle", "roll", "pitch", "yaw"], np.full(4, 0.01))
    # back at nominal: the candidate's start value, whatever it was fitted to
    assert dict(dict(f.at_nominal(f.vp).effects)["thrust_coefficient"])["kt_scale"] == 1.0
