"""The form of a drag: linear in the speed (a nominal rotor drag refitted, RotorPy's k_d sum(omega) v) or quadratic
in it (the library's body drag, c |v| v per body axis), told apart on held-out blocks (issue 26, rdrag11).

On a flight at one speed the two laws are one force: c |v| v = (c |v|) v.  They differ only through the speed's
spread (and the small changes of the rotor speeds), so the one-parameter rotor drag refitted won on the RotorPy
circle (RP3) whatever the truth was: n002 (k_d x2) was named right, but q003 and w003 (a body drag) were named as
a rotor drag, k_eq 5.8 / 6.6 % off instead of 1.6 / 1.9 % (``docs/discovery.md``, rdrag10).  So where both forms
pass in a round, the rotor drag refitted is taken over the body drag only where its pooled held-out residual beats
the body drag's at ``T_CHOICE`` sigma (the flight tells the forms apart, :func:`~twin_nodes.discovery.blocktest.
_block_test`); else the body drag is kept (the library's law, as before the refit was offered) and the finding
carries the rotor drag as the form it was not told from (``drag_form``; ``stages.verdicts.not_told_apart`` adds the
manoeuvre that separates them: legs at two speeds)."""

from __future__ import annotations

from twin_nodes.discovery.blocktest import _block_test
from twin_nodes.discovery.judging import OE_MIN_CHANGE, T_CHOICE, Fit

#: the linear form: a nominal rotor drag with its k_d refitted (``selection.nominal_refits``)
LINEAR = "rotor_drag (nominal refitted)"
#: the quadratic form: the library's body drag
QUADRATIC = "body_drag"


def form_test(linear: Fit, quadratic: Fit, blocks: dict) -> dict | None:
    """The held-out block tests (one-sided, each way) of ``linear`` against ``quadratic`` on a residual both were
    fitted on (the linear form's own first); ``told_apart``: one of them, and only one, beats the other at
    ``T_CHOICE`` sigma (the sign and sign-flip tests can pass both ways on a few large blocks).  None: no shared
    residual."""
    for kind in dict.fromkeys((linear.kind, quadratic.kind)):
        a = (linear.by_kind or {linear.kind: linear}).get(kind)
        b = (quadratic.by_kind or {quadratic.kind: quadratic}).get(kind)
        if a is None or b is None or a.R is None or b.R is None:
            continue
        floor = OE_MIN_CHANGE if kind == "output" else 0.0
        t, n = _block_test(b.R, a.R, blocks[kind], floor)
        t_back, _ = _block_test(a.R, b.R, blocks[kind], floor)
        return {"linear": LINEAR, "quadratic": QUADRATIC, "residual": kind, "blocks": int(n),
                "t_linear_over_quadratic": round(float(t), 2), "t_quadratic_over_linear": round(float(t_back), 2),
                "told_apart": bool((t > T_CHOICE) != (t_back > T_CHOICE))}
    return None


def choose(winner: Fit, accepted: list[Fit], blocks: dict) -> Fit:
    """``winner`` or, where it is one drag form and the other form also passes this round, the form the held-out
    blocks choose: the linear one only where it beats the quadratic one at ``T_CHOICE`` sigma.  The chosen fit
    carries the test (``drag_form``)."""
    labels = {LINEAR: QUADRATIC, QUADRATIC: LINEAR}
    other_label = labels.get(winner.candidate.label)
    other = next((f for f in accepted if f.candidate.label == other_label and f is not winner), None)
    if other is None:
        return winner
    linear, quadratic = (winner, other) if winner.candidate.label == LINEAR else (other, winner)
    test = form_test(linear, quadratic, blocks)
    if test is None:
        return winner
    pick = linear if test["told_apart"] and test["t_linear_over_quadratic"] > T_CHOICE else quadratic
    pick.drag_form = test
    return pick


def offered_on_top(label: str, accepted: list[Fit]) -> bool:
    """The linear form is not offered on top of an accepted quadratic one: where both passed, the form test chose
    the quadratic one for that force, and the linear one fitted on top would split it between two laws."""
    return label != LINEAR or not any(f.candidate.label == QUADRATIC for f in accepted)
