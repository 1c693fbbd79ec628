"""The dispatch stepper (one numba module for every effect combination) flies what the per-combination
stepper flew.

``bench/model_before.py`` keeps the generator of main eda17af (one module per ordered set of effect
kinds, hooks calling the kernels directly) with its stepper template; each vehicle below is flown
through both, on the same commands, battery and wind: every output must agree to 1e-12 relative
(they are bit for bit equal today: the same kernels on the same parameter slices, in the same order).
The effect sets include duplicates of a kind, several orders, and the prove suite's plant-only
effects (twin_nodes/prove/oov_physics.py, kernels outside physics/effects.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from twin_nodes.physics import model
from twin_nodes.physics.effects import EFFECTS, make_effect
from twin_nodes.physics.model import Multirotor, MultirotorBatch
from twin_nodes.prove.oov_physics import ThrustFlattening, TranslationalLift, VortexRing
from twin_nodes.vehicle.params import shipped

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from model_before import OldModel  # noqa: E402

V_REF = {"buho_negro": 16.8, "px4_sih_quadx": 12.6, "quad_c_3dr": 12.6, "rotorpy_crazyflie": 4.2}


def _all_kinds(vp):
    return (vp.with_effect("battery_sag", v_ref=12.6, exponent=0.8)
            .with_effect("motor_efficiency", motor=3, efficiency=0.85)
            .with_effect("ground_effect", coefficient=0.3, height_scale=0.4)
            .with_effect("linear_drag", k_n_s_m=0.25)
            .with_effect("angular_damping", k_nm_s_rad=0.002)
            .with_effect("rotor_drag", k_d=1e-4)
            .with_effect("body_drag", c_dx=0.02, c_dy=0.03, c_dz=0.05, norm=1.0)
            .with_effect("com_offset", dx=0.01, dy=-0.015)
            .with_effect("rotor_tilt", lever_m=0.003)
            .with_effect("coaxial", efficiency=0.9, lower_mask=5)
            .with_effect("state_term", v_h=5.0, radius=0.12, omega_max=1000.0, c_one=0.02, c_mu=0.05,
                         c_descent2=-0.03, c_omega4=0.04, c_tilt=0.1)
            .with_effect("wind", vx=2.0, vy=-1.0))


# (vehicle, params, extra plant-only effects)
CASES = {
    "no_kernel_effects": ("buho_negro", lambda vp: vp, ()),
    "shipped_sih_drags": ("px4_sih_quadx", lambda vp: vp, ()),
    "every_kind": ("px4_sih_quadx", _all_kinds, ()),
    "wrench_reversed": ("quad_c_3dr", lambda vp: (vp.with_effect("com_offset", dx=-0.02, dy=0.01)
                                                  .with_effect("body_drag", c_dx=0.05, c_dy=0.02, c_dz=0.1)
                                                  .with_effect("rotor_drag", k_d=2e-4)
                                                  .with_effect("linear_drag", k_n_s_m=0.1)), ()),
    "two_weak_motors": ("buho_negro", lambda vp: (vp.with_effect("motor_efficiency", motor=1, efficiency=0.9)
                                                  .with_effect("battery_sag", v_ref=16.8, exponent=1.2)),
                        (make_effect("motor_efficiency", motor=4, efficiency=0.7),)),  # a kind twice
    "plant_only": ("px4_sih_quadx", lambda vp: vp.with_effect("battery_sag", v_ref=12.6, exponent=0.9),
                   (TranslationalLift(k=0.15, v_h=4.0), VortexRing(k=0.3, v_h=4.0),
                    ThrustFlattening(k=0.2, u0=0.7, omega_max=1000.0))),
    "plant_only_crazyflie": ("rotorpy_crazyflie", lambda vp: vp.with_effect("ground_effect", coefficient=0.2,
                                                                            height_scale=0.1),
                             (VortexRing(k=0.4, v_h=2.0, d_peak=0.8), TranslationalLift(k=0.1, v_h=2.0))),
}

DT, NSUB, NT = 0.002, 2, 500


def _scenario(params, name, n_rotors, seed=0):
    t = np.arange(NT) * DT * NSUB
    ph = np.arange(n_rotors)
    U = params.hover_command * (1.1 + 0.12 * np.sin(2 * np.pi * (0.6 + 0.35 * ph)[None, :] * t[:, None]
                                                     + ph[None, :] + seed))
    U[NT - 50:, 1] = np.nan  # motor 2 stops
    EXT = np.empty((NT, 4))
    EXT[:, 0] = V_REF[name] * (1.02 - 0.06 * t / t[-1])
    EXT[:, 1] = 2.0 + 0.5 * np.sin(1.3 * t)
    EXT[:, 2] = -1.0 + 0.3 * np.cos(0.9 * t)
    EXT[:, 3] = 0.1 * np.sin(2.1 * t) - 1.5 * (t > t[-1] / 2)  # a descent through the air: vortex ring
    return U, EXT


def _close(a, b):
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("case", sorted(CASES))
def test_dispatch_stepper_flies_what_the_per_combination_stepper_flew(case):
    name, build, extra = CASES[case]
    vp = build(shipped(name))
    new, old = Multirotor(vp, extra), OldModel(vp, extra)
    assert new.term_names == old.term_names
    U, EXT = _scenario(new.params, name, new.n_rotors)
    x0 = new.initial_state(position_enu=(0.0, 0.0, 0.3), velocity_enu=(3.0, -1.0, 0.0), yaw_enu_rad=0.4,
                           rotor_state="hover")
    X = new.simulate(x0, U, DT, EXT, NSUB)
    Xo = old.mod.simulate(old.P, x0, U, EXT, DT, NSUB)
    assert np.isfinite(X).all() and np.ptp(X[:, 2]) > 0.1  # it flew
    _close(X, Xo)
    for k in (0, 200, NT - 1):
        _close(new.specific_force_flu(X[k], U[k], EXT[k]), old.mod.specific_force(old.P, X[k], U[k], EXT[k]))
    terms = new.wrench_terms(X[1:], EXT)
    F = np.zeros((NT, len(old.term_names), 3))
    M = np.zeros_like(F)
    old.mod.wrench_terms(old.P, np.ascontiguousarray(X[1:]), EXT, F, M)
    for j, term in enumerate(old.term_names):
        _close(terms[term][0], F[:, j])
        _close(terms[term][1], M[:, j])
    S = new._mod.rotor_states(new.P, U, EXT, DT * NSUB, 3, np.zeros(new.n_rotors))
    _close(S, old.mod.rotor_states(old.P, U, EXT, DT * NSUB, 3, np.zeros(new.n_rotors)))
    # a batch of two vehicles with other values of the same kinds, stepped one command at a time
    vp2 = vp.replace(mass_kg=vp.mass_kg * 1.2)
    models, olds = [new, Multirotor(vp2, extra)], [old, OldModel(vp2, extra)]
    batch = MultirotorBatch(models)
    XB = np.stack([x0, x0])
    XO = XB.copy()
    PO = np.stack([o.P for o in olds])
    for k in range(60):
        UB = np.stack([U[k], U[k] * 0.98])
        EB = np.stack([EXT[k], EXT[k]])
        XB = batch.step(XB, UB, DT, EB, NSUB)
        old.mod.step_batch(PO, XO, UB, EB, DT, NSUB)
    _close(XB, XO)


def test_every_combination_shares_one_compiled_module():
    mods = {id(Multirotor(CASES[c][1](shipped(CASES[c][0])))._mod) for c in CASES}
    assert len(mods) == 1
    with_plant = {id(Multirotor(CASES[c][1](shipped(CASES[c][0])), CASES[c][2])._mod) for c in CASES}
    assert len(with_plant) <= 2  # at most the registry before and after the plant-only kinds joined it


def test_codes_of_the_built_in_kinds_do_not_depend_on_what_was_used():
    builtin = [cls for cls in EFFECTS.values() if model._has_kernel(cls)]
    reg = model._registry([VortexRing])
    assert list(reg[:len(builtin)]) == builtin
    # a plant-only kind brings every kernel effect of its module, in a fixed order
    assert set(reg[len(builtin):]) >= {TranslationalLift, VortexRing, ThrustFlattening}
    assert list(reg[len(builtin):]) == sorted(reg[len(builtin):], key=lambda k: (k.__module__, k.__qualname__))


def test_effect_table_layout():
    vp = (shipped("buho_negro").with_effect("battery_sag").with_effect("linear_drag", k_n_s_m=0.1)
          .with_effect("motor_efficiency", motor=2, efficiency=0.8))
    m = Multirotor(vp)
    n0 = len(Multirotor(shipped("buho_negro")).P)  # the vehicle and an empty table [0, 0, 0]
    b = n0 - 3
    code = {cls: i for i, cls in enumerate(model._registry())}
    assert list(m.P[b:b + 3]) == [1, 1, 1]
    start = b + 3 + 6
    assert list(m.P[b + 3:start]) == [code[EFFECTS["battery_sag"]], start,
                                      code[EFFECTS["motor_efficiency"]], start + 4,
                                      code[EFFECTS["linear_drag"]], start + 2]
    # linear_drag's k and its ``vertical`` (1: SIH's isotropic drag, the default)
    assert list(m.P[start:]) == [12.6, 1.0, 0.1, 1.0, 2.0, 0.8]
