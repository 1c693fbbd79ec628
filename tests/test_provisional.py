"""Issue 26, two effects at once (docs/discovery.md, "A likely effect as a provisional base"): the forward
selection with scripted fits, so that each rule is asserted on its own.

- class B: a ``likely`` first effect (good fit, large cut, folds agree, t under the bar) seeds one provisional round
  on top of it; a second effect that passes only there is accepted, and the first stays ``likely`` (never confirmed
  because something was found on top of it).  Where nothing passes on top of it, the result is as before.
- class E: a one-sided candidate (nominal at an edge of its range) whose fit stayed at that edge is not pruned
  after round 2; a two-sided one that stayed at nominal is."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from twin_nodes.discovery.candidates import Candidate
from twin_nodes.discovery.judging import MIN_REL_IMPROVEMENT, PRUNE_GAIN, T_CRIT, Fit
from twin_nodes.discovery.stages import candidates, judge, selection
from twin_nodes.discovery.stages import verdicts as stage_verdicts
from twin_nodes.discovery.stages.provisional import PROVISIONAL_MIN_CUT, held_at_one_side, is_provisional
from twin_nodes.discovery.verdicts import grade, likely_failures
from twin_nodes.vehicle.params import shipped

NOMINAL = shipped("px4_sih_quadx")


def _cand(name: str, x0: float, lo: float, hi: float, floor: float) -> Candidate:
    """A one-parameter candidate on the vehicle it is applied to (the effects' own parameters do not matter here:
    the scripted judge reads which effects the base vehicle carries)."""
    key = {"ground_effect": "coefficient", "body_drag": "c_dx", "mass": "mass"}[name]

    def build(theta, name=name):
        return SimpleNamespace(effects=[], tag=name)
    return Candidate(name, (key,), np.array([x0]), np.array([lo]), np.array([hi]), build, {},
                     lambda th, x0=x0, f=floor: abs(th[0] - x0) > f, name)


GROUND = _cand("ground_effect", 0.0, 0.0, 2.0, 0.02)
DRAG = _cand("body_drag", 0.0, 0.0, 0.05, 1e-4)


def _fit(c: Candidate, theta: float, cut: float, t: float, n: int, base) -> Fit:
    """A judged fit: ``cut`` cross-validated and in its channel, ``t`` over ``n`` active held-out blocks, all
    improved where ``t`` > 0; both folds at ``theta``."""
    th = np.array([theta])
    f = Fit(c, th, SimpleNamespace(tag=c.name, base=base), 0.0, 1.0 - cut, np.full(6, 1.0 - cut), t, n, cut,
            bool(c.floor(th)))
    f.judged = ("throttle", 1.0, 1.0 - cut)
    f.stats = {"n": n, "n_pos": n if t > 0 else 0, "t": t, "mean": 0.01, "sd": 0.01}
    f.fold_thetas = [th, th]
    f.accepted = f.passes
    return f


def _tags(vp) -> list[str]:
    """The scripted effects a vehicle carries (each fit's vehicle names its base)."""
    out = []
    while getattr(vp, "tag", None) is not None:
        out.append(vp.tag)
        vp = vp.base
    return out


def _flight():
    eq = SimpleNamespace(residual=lambda vp, rows=None: np.ones((40, 6)), blocks=[np.arange(10)], kind="equation")
    data = SimpleNamespace(v=np.zeros((40, 3)), valid=np.ones(40, bool))
    return SimpleNamespace(eq=eq, oe=None, data=data, nominal=NOMINAL, excitation={})


@pytest.fixture
def scripted(monkeypatch):
    """The rounds' candidates and fits by script: the ground effect is ``likely`` (cut 49 %, t 1.5 over 4 active
    blocks: g023's numbers) on any base; the drag fails beside the unmodelled ground effect (cut 1 %, folds apart)
    and, when ``drag_on_ground`` is set, passes on top of it (cut 35 %, t 4.9)."""
    script = {"drag_on_ground": True, "rounds": []}

    def cands(q):
        return candidates.CandidateSet([c for c in (GROUND, DRAG) if c.label not in q.done], [])

    def judged(q):
        on = _tags(q.current)
        script["rounds"].append(on)
        out = {}
        for c in q.batch:
            if c is GROUND:
                f = _fit(c, 0.43, 0.49, 1.54, 4, q.current)
            elif "ground_effect" in on and script["drag_on_ground"]:
                f = _fit(c, 0.0011, 0.35, 4.9, 30, q.current)
            else:
                f = _fit(c, 0.0009, 0.012, 0.4, 30, q.current)
                f.folds_agree = False
            f.base_vp = q.current
            out[c.label] = [f]
        return judge.JudgedFits(out)

    monkeypatch.setattr(candidates, "run", cands)
    monkeypatch.setattr(judge, "run", judged)
    monkeypatch.setattr(selection, "wind_with_drag", lambda vp, data: [])
    monkeypatch.setattr(selection, "nominal_refits", lambda nominal, current, data=None: [])
    monkeypatch.setattr(selection, "offer", lambda *a: [])
    return script


def test_the_scripted_ground_effect_is_likely_and_solid():
    f = _fit(GROUND, 0.43, 0.49, 1.54, 4, NOMINAL)
    assert not f.passes and f.t_stat <= T_CRIT
    assert likely_failures(f, T_CRIT, MIN_REL_IMPROVEMENT) == []
    assert f.explains >= PROVISIONAL_MIN_CUT


def test_a_likely_first_effect_seeds_a_round_where_the_second_is_found(scripted):
    sel = selection.run(selection.SelectionInput(_flight(), max_effects=3))
    ground, drag = sel.accepted
    # the drag was judged on top of the ground effect, and accepted there; the ground effect is the base
    assert ground.candidate is GROUND and is_provisional(ground) and not ground.accepted
    assert drag.candidate is DRAG and drag.accepted and not is_provisional(drag)
    assert scripted["rounds"][:2] == [[], ["ground_effect"]]
    assert _tags(sel.current) == ["body_drag", "ground_effect"]
    # the provisional round does not count as an effect: max_effects rounds are still left for the others
    assert len(scripted["rounds"]) == 3
    # graded: the drag confirmed, the ground effect stays likely on its own fit (t 1.54)
    grade(drag, T_CRIT, MIN_REL_IMPROVEMENT, {}, None)
    ground.accepted = False
    grade(ground, T_CRIT, MIN_REL_IMPROVEMENT, {}, None)
    assert (drag.verdict, ground.verdict) == ("confirmed", "likely")


def test_nothing_on_top_of_a_likely_effect_leaves_the_result_as_before(scripted):
    scripted["drag_on_ground"] = False
    sel = selection.run(selection.SelectionInput(_flight(), max_effects=3))
    assert sel.accepted == [] and sel.current is NOMINAL
    # the entries are round 1's (judged on the nominal), not the provisional round's
    assert sel.last["ground_effect"].base_vp is NOMINAL and sel.last["body_drag"].base_vp is NOMINAL
    assert not is_provisional(sel.last["ground_effect"])
    assert scripted["rounds"] == [[], ["ground_effect"]]     # one provisional round, no more


def test_a_weak_likely_effect_seeds_nothing(scripted):
    # likely (cut 28 % in its channel is under LIKELY_MIN_CUT: not even likely) -> no provisional round
    weak = _fit(GROUND, 0.43, 0.28, 1.54, 4, NOMINAL)
    assert likely_failures(weak, T_CRIT, MIN_REL_IMPROVEMENT)
    from twin_nodes.discovery.stages.provisional import provisional_seed
    assert provisional_seed([weak], [], NOMINAL, {}) is None
    # a significant fit is not a seed either (it passes or fails on its own)
    strong = _fit(GROUND, 0.43, 0.49, 3.5, 12, NOMINAL)
    assert provisional_seed([strong], [], NOMINAL, {}) is None
    # folds that disagree: no seed
    split = _fit(GROUND, 0.43, 0.49, 1.54, 4, NOMINAL)
    split.fold_thetas = [np.array([0.43]), np.array([0.1])]
    split.folds_agree = False
    assert provisional_seed([split], [], NOMINAL, {}) is None


def test_the_verdict_stage_grades_the_provisional_base_on_its_own_fit():
    ground = _fit(GROUND, 0.43, 0.49, 1.54, 4, NOMINAL)
    drag = _fit(DRAG, 0.0011, 0.35, 4.9, 30, ground.vp)
    ground.provisional = True
    names = ["motor1", "motor2", "motor3", "motor4", "force_x", "force_y"]
    flight = SimpleNamespace(eq=SimpleNamespace(kind="equation"), oe=None, nominal=NOMINAL, names=names,
                             excitation={}, windows=None)
    for f in (ground, drag):
        f.other = {"residual": "output"}       # the other residual's view is not under test
    v = stage_verdicts.run(stage_verdicts.GradeInput(flight, [ground, drag], {"ground_effect": ground,
                                                                              "body_drag": drag},
                                                     ["ground_effect", "body_drag"], np.ones(6)))
    by = {e["name"]: e for e in v.effects}
    assert by["body_drag"]["verdict"] == "confirmed" and by["body_drag"]["accepted"]
    assert by["ground_effect"]["verdict"] == "likely" and not by["ground_effect"]["accepted"]
    assert "provisional" in by["ground_effect"] and "provisional" not in by["body_drag"]
    assert by["body_drag"]["heldout_contribution"]["on_top_of"] == ["ground_effect"]
    assert v.accepted_labels == ["body_drag"]


def test_a_one_sided_candidate_held_at_its_edge_is_not_pruned():
    # g030: beside the sag's thrust deficit the ground effect can only fit 0 (its nominal, its lower edge)
    held = SimpleNamespace(candidate=GROUND, theta=np.array([0.0]), rel_improvement=0.0, above_floor=False,
                           at_bound=False)
    assert held_at_one_side(held)
    assert selection._first_gain([held]) == PRUNE_GAIN
    # moved off its edge and explaining nothing: its own cut, pruned
    moved = SimpleNamespace(candidate=GROUND, theta=np.array([0.3]), rel_improvement=0.001, above_floor=True,
                            at_bound=False)
    assert not held_at_one_side(moved) and selection._first_gain([moved]) == 0.001
    # a two-sided candidate (a mass: nominal inside its range) that stayed at nominal explained nothing: pruned
    mass = _cand("mass", 1.0, 0.5, 2.0, 0.03)
    still = SimpleNamespace(candidate=mass, theta=np.array([1.0]), rel_improvement=0.0, above_floor=False,
                            at_bound=False)
    assert not held_at_one_side(still) and selection._first_gain([still]) == 0.0
    # and the round-3 candidate list keeps the held one, drops the two-sided one
    gains = selection._rescaled_gain({"ground_effect": PRUNE_GAIN, "mass": 0.0}, (1.0, 0.0), (0.5, 0.0))
    assert gains["ground_effect"] >= PRUNE_GAIN and gains["mass"] < PRUNE_GAIN
