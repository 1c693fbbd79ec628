"""Discovery's refit vehicle gets the static trims its own model needs (twin_nodes/discovery/stages/retrim.py).

Known truth: steady states balanced by a true vehicle (rotor drag in wind, a centre-of-mass offset, a rotor
tilt); a nominal with a wrong rotor drag / yaw moment and the trims made for that wrong model; the refit with the
true values must get the true trims back, and a refit that changes nothing keeps its trims exactly.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from test_static_trims import _balanced_state, _quat, _truth
from twin_nodes.discovery.stages.retrim import retrimmed, steady_samples
from twin_nodes.identify.static_trims import model_trims, without_trims
from twin_nodes.physics.model import Multirotor
from twin_nodes.vehicle.params import shipped


def _steady(truth) -> np.ndarray:
    model = Multirotor(truth)
    rng = np.random.default_rng(3)
    return np.array([_balanced_state(model, _quat(*rng.normal(0, 0.05, 2), yaw), rng.normal(0, 0.3, 3))
                     for yaw in np.linspace(-3.0, 3.0, 9)])


def _trimmed_for(vp, X):
    """``vp`` with the trims model_trims makes for its own model on ``X`` (as the nominal makes them)."""
    tr = model_trims(vp, X, np.zeros((len(X), 3)))
    return vp.with_effect("com_offset", dx=tr.dx, dy=tr.dy).with_effect("rotor_tilt", lever_m=tr.lever)


def _trims(vp):
    e = vp.effect_dict
    return e["com_offset"]["dx"], e["com_offset"]["dy"], e["rotor_tilt"]["lever_m"]


@pytest.mark.parametrize("wrong", [{"rotor_drag": {"k_d": 5.0e-4}}, {"yaw_moment": {"km": 0.03}}])
def test_a_refit_gets_the_trims_its_own_model_needs(wrong):
    truth = _truth(shipped("px4_sih_quadx"))
    X = _steady(truth)
    nominal = without_trims(truth)
    for name, p in wrong.items():
        nominal = nominal.with_effect(name, **p)
    nominal = _trimmed_for(nominal, X)
    assert max(abs(a - b) for a, b in zip(_trims(nominal), (0.012, -0.008, 0.0021))) > 1e-4  # the wrong trims
    # the refit puts the true value back but keeps the nominal's trims; the retrim moves them to the truth's
    refit = nominal.with_effect("rotor_drag", k_d=2.0e-4)
    if "yaw_moment" in wrong:
        refit = refit.with_effect("yaw_moment", km=truth.rotors.km_m)
    out = retrimmed(refit, nominal, lambda v: X, np.zeros((len(X), 3)))
    assert _trims(out) == pytest.approx((0.012, -0.008, 0.0021), abs=1e-9)


def test_a_refit_that_changes_no_steady_moment_keeps_its_trims_exactly():
    truth = _truth(shipped("px4_sih_quadx"))
    X = _steady(truth)
    nominal = _trimmed_for(without_trims(truth), X)
    inertia = nominal.inertia * 1.3       # alpha 0 and steady rates: the balance does not read it
    refit = nominal.replace(inertia_kg_m2=tuple(map(tuple, inertia)))
    out = retrimmed(refit, nominal, lambda v: X, np.zeros((len(X), 3)))
    assert _trims(out) == _trims(nominal)


def test_no_trims_in_the_nominal_none_are_added():
    truth = _truth(shipped("px4_sih_quadx"))
    X = _steady(truth)
    nominal = without_trims(truth).with_effect("rotor_drag", k_d=5.0e-4)
    refit = nominal.with_effect("rotor_drag", k_d=2.0e-4)
    out = retrimmed(refit, nominal, lambda v: X, np.zeros((len(X), 3)))
    assert "com_offset" not in out.effect_dict and "rotor_tilt" not in out.effect_dict


def test_a_centre_of_mass_moved_out_of_the_rotor_polygon_is_refused():
    truth = _truth(shipped("px4_sih_quadx"))
    X = _steady(truth)
    nominal = _trimmed_for(without_trims(truth), X)
    arm = float(np.median(np.hypot(nominal.rotors.x_flu_m, nominal.rotors.y_flu_m)))
    # the vehicle already carries an offset at the polygon's edge: any further move is refused
    refit = nominal.with_effect("com_offset", dx=0.7 * arm, dy=0.0).with_effect("rotor_drag", k_d=4.0e-4)
    out = retrimmed(refit, nominal, lambda v: X, np.zeros((len(X), 3)))
    assert out is refit


def test_steady_samples_are_slow_usable_and_inside_the_motor_range():
    n, up, rate = 2000, 10, 50.0
    v = np.zeros((n, 3))
    v[:300, 0] = 5.0                                  # a fast leg: not steady
    u = np.full((n * up, 4), 0.5)
    u[(500 * up):(600 * up), 2] = 0.995               # a motor at its top: PX4 gave yaw up there
    valid = np.ones(n, bool)
    valid[-100:] = False                              # on the ground
    data = SimpleNamespace(valid_attitude=valid, dt=1.0 / rate, v=v, u_fine=u, up=up, n=n)
    sel = steady_samples(data)
    assert int(sel.sum()) == n - 300 - 100 - 100
    assert not sel[:300].any() and not sel[500:600].any() and not sel[-100:].any()
    # under 10 s of slow samples: every usable sample (with its motors inside the range)
    data.v = np.full((n, 3), 5.0)
    assert int(steady_samples(data).sum()) == n - 100 - 100
    # under 6 s balanced (the nominal's BALANCED_MIN_S): none
    data.valid_attitude = np.zeros(n, bool)
    data.valid_attitude[:200] = True
    assert steady_samples(data) is None


def _split_and_noise(truth):
    """Steady states whose yaw split varies sample by sample (a yaw torque the model lacks holds it: the rotors
    of one spin direction 0-12 % up, skewed), beside a measured yaw acceleration that is noise of its own
    (skewed too, independent of the split): what a real flight's steady samples hold."""
    X = _steady(truth)
    d = np.asarray(truth.rotors.direction, float)
    eps = np.array([0.0, 0.01, 0.02, 0.02, 0.03, 0.05, 0.08, 0.10, 0.12])
    X[:, -4:] *= 1.0 + eps[:, None] * (d[None, :] > 0)
    alpha = np.zeros((len(X), 3))
    alpha[:, 2] = [4.2, -1.2, -3.3, 6.6, 1.8, -2.7, 0.3, -0.6, 0.9]   # rad/s^2
    return X, alpha


def test_the_trims_move_by_the_median_of_each_samples_change():
    """A yaw moment refit (km 0.03 -> 0.015 m) on samples where the split and the measured acceleration vary
    independently: the lever moves by the median over the samples of the change each sample's own balance
    asks for, not by the change of the two medians (the median of a difference of two varying terms is not
    the difference of their medians).  auterion_v3_esc_status (km 0.02 -> 0.0083 m): the change of the medians
    moved the twin's yaw split 0.75 % of full output off the vehicle's before the held-out part, held-out
    per-motor P75 7.03 -> 7.46 %; the paired change keeps it, 6.98 %."""
    truth = _truth(shipped("px4_sih_quadx"))
    X, alpha = _split_and_noise(truth)
    nominal = without_trims(truth).with_effect("yaw_moment", km=0.03)
    tr = model_trims(nominal, X, alpha)
    nominal = nominal.with_effect("com_offset", dx=tr.dx, dy=tr.dy).with_effect("rotor_tilt", lever_m=tr.lever)
    refit = nominal.with_effect("yaw_moment", km=0.015)
    out = retrimmed(refit, nominal, lambda v: X, alpha)
    # each sample's own change: the rotors' yaw moment the refit takes away, per newton of its thrust
    t = np.arange(len(X), dtype=float)
    m_yaw, thrust = [], []
    for v in (nominal, refit):
        model = Multirotor(without_trims(v).with_effect("com_offset", dx=tr.dx, dy=tr.dy))
        terms = model.wrench_terms(X, model.exogenous(t, np.random.default_rng(0)))
        m_yaw.append(sum(w[1] for w in terms.values())[:, 2])
        thrust.append(terms["rotors"][0][:, 2])
    per_sample = -(m_yaw[1] - m_yaw[0]) / thrust[0]
    moved = _trims(out)[2] - tr.lever
    assert moved == pytest.approx(float(np.median(per_sample)), rel=1e-6)
    assert moved == pytest.approx(-1.7028e-3, abs=1e-6)
    # the change of the medians would have moved it more than twice as far
    by_medians = model_trims(refit, X, alpha).lever - tr.lever
    assert by_medians == pytest.approx(-3.8270e-3, abs=1e-6)
    # roll and pitch: the yaw moment moves neither
    assert _trims(out)[:2] == pytest.approx((tr.dx, tr.dy), abs=1e-12)


def test_the_paired_change_falls_back_to_the_medians_without_samples():
    """Three samples whose lever terms cross: the paired change and the change of the medians differ; a read
    without its samples (``per_sample`` None) gives the change of the medians."""
    from twin_nodes.discovery.stages.retrim import paired_change
    from twin_nodes.identify.static_trims import Trims

    a, b = np.array([0.0, 1.0, 5.0]), np.array([3.0, 0.0, 1.0])
    old = Trims(0.0, 0.0, float(np.median(a - 0.03 * b)), (0.0, 0.0, 0.0), 3,
                np.column_stack([np.zeros(3), np.zeros(3), a - 0.03 * b]))
    new = Trims(0.0, 0.0, float(np.median(a - 0.015 * b)), (0.0, 0.0, 0.0), 3,
                np.column_stack([np.zeros(3), np.zeros(3), a - 0.015 * b]))
    # paired: the median of 0.015 b = 0.015; the change of the medians: 1 - 1 = 0 (the same sample is the median)
    assert paired_change(new, old) == pytest.approx((0.0, 0.0, 0.015), abs=1e-12)
    bare = Trims(new.dx, new.dy, new.lever, new.moment_other_nm, 3)
    assert paired_change(bare, old) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
