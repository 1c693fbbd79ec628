"""The linear (rotor) against the quadratic (body) drag: the form test of ``stages.drag_form`` (rdrag11)."""

import numpy as np
import pytest

from twin_nodes.discovery.candidates import Candidate
from twin_nodes.discovery.judging import Fit
from twin_nodes.discovery.stages import drag_form, selection, verdicts
from twin_nodes.prove.rotorpy_flights import nominal_params, rotorpy_params

BLOCKS = [np.arange(25 * i, 25 * (i + 1)) for i in range(40)]


def _fit(cand, R, kind="equation"):
    f = Fit(cand, cand.x0 * 2, None, 0.0, 0.0, np.zeros(3), 5.0, 40, 0.8, True, accepted=True)
    f.kind, f.R = kind, R
    f.by_kind = {kind: f}
    return f


def _pair(scale_linear: float, seed: int = 7):
    """The rotor drag refitted and a body drag whose held-out residuals share one part; the linear one's own
    noise ``scale_linear`` against the quadratic one's 0.2."""
    vp = nominal_params(rotorpy_params("crazyflie"), "rotorpy_crazyflie")
    (rotor,) = [c for c in selection.nominal_refits(vp, vp) if c.name == "rotor_drag"]
    body = Candidate("body_drag", ("c_dx", "c_dy", "c_dz"), np.full(3, 1e-3), np.zeros(3), np.full(3, 1.0),
                     lambda th: vp, {}, lambda th: True, "body_drag")
    rng = np.random.default_rng(seed)
    common = 0.3 * rng.standard_normal((1000, 3))
    lin = _fit(rotor, common + scale_linear * rng.standard_normal((1000, 3)))
    quad = _fit(body, common + 0.2 * rng.standard_normal((1000, 3)))
    return lin, quad


def test_linear_drag_taken_only_where_the_blocks_tell_it_from_the_quadratic():
    # the linear form leaves half the quadratic one's own noise: told apart, the rotor drag refitted is taken
    lin, quad = _pair(0.1)
    pick = drag_form.choose(lin, [lin, quad], {"equation": BLOCKS})
    assert pick is lin and pick.drag_form["told_apart"]
    assert pick.drag_form["t_linear_over_quadratic"] == pytest.approx(8.14, abs=0.01)
    assert pick.drag_form["t_quadratic_over_linear"] < 0 and pick.drag_form["blocks"] == 40
    # the same size of noise: not told apart, the body drag is kept even where the rotor drag won the round
    lin, quad = _pair(0.2)
    pick = drag_form.choose(lin, [lin, quad], {"equation": BLOCKS})
    assert pick is quad and not pick.drag_form["told_apart"]
    assert pick.drag_form["t_linear_over_quadratic"] == pytest.approx(-1.11, abs=0.01)
    assert pick.drag_form["t_quadratic_over_linear"] == pytest.approx(1.20, abs=0.01)
    # the quadratic one clearly better: told apart the other way
    lin, quad = _pair(0.4)
    pick = drag_form.choose(quad, [lin, quad], {"equation": BLOCKS})
    assert pick is quad and pick.drag_form["told_apart"] and pick.drag_form["t_quadratic_over_linear"] == pytest.approx(9.94, abs=0.01)
    # only the other form passing changes a winner; no rival: as it was
    assert drag_form.choose(lin, [lin], {"equation": BLOCKS}) is lin


def test_linear_drag_not_offered_on_top_of_the_quadratic():
    lin, quad = _pair(0.2)
    assert not drag_form.offered_on_top(drag_form.LINEAR, [quad])
    assert drag_form.offered_on_top(drag_form.LINEAR, [lin])
    assert drag_form.offered_on_top("body_drag", [lin]) and drag_form.offered_on_top("mass", [quad])


def test_forms_not_told_apart_reported_with_legs_at_two_speeds():
    e = {"name": "body_drag", "alternatives": [{"name": "rotor_drag", "params": {"k_d": 2.0e-6}}],
         "drag_form": {"told_apart": False}}
    pair = verdicts.not_told_apart(e)
    assert pair["with"]["name"] == "rotor_drag" and pair["manoeuvre"] == "fast_legs" and pair["plan_flyable"]
    assert "square" in pair["why"]
    assert verdicts.not_told_apart(dict(e, drag_form={"told_apart": True})) is None
    assert verdicts.not_told_apart({k: v for k, v in e.items() if k != "drag_form"}) is None


def test_forms_that_each_pass_one_way_are_not_told_apart(monkeypatch):
    # the sign and sign-flip tests can pass both ways on a few large blocks: neither form is chosen by the blocks
    lin, quad = _pair(0.2)
    monkeypatch.setattr(drag_form, "_block_test", lambda R0, R1, blocks, floor: (2.5, 12))
    pick = drag_form.choose(lin, [lin, quad], {"equation": BLOCKS})
    assert pick is quad and not pick.drag_form["told_apart"] and pick.drag_form["blocks"] == 12
