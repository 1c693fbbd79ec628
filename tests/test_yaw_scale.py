"""Stage 11 (``discovery/stages/yaw_scale.py``): a yaw moment or a yaw inertia read without the equation error's
unit bias.  On the yaw row km x s and Izz / s give residuals exactly s apart where no other yaw torque acts; each
reading's yaw error over sqrt(Izz/Izz_n km/km_n) makes them tie there, and a torque that neither scales (a hub
damping, a CoM offset's H-force moment) then tells them apart."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from twin_nodes.discovery.stages import yaw_scale as Y
from twin_nodes.vehicle.params import shipped


@pytest.fixture(scope="module")
def nominal():
    return shipped("px4_sih_quadx")        # km 0.02, Ixx = Iyy 0.025, Izz 0.03


def test_the_other_reading_closed_form(nominal):
    # RotorPy k015's shape: Izz x0.667 alone -> a yaw moment x1.5, Izz back at the model's, no inertia left
    cur = nominal.with_effect("inertia", ixx=0.025, iyy=0.025, izz=0.02)
    alt, was, becomes, s = Y.other_reading(cur, nominal)
    assert (was, becomes) == ("inertia", "yaw_moment") and s == pytest.approx(1.5)
    assert "inertia" not in alt.effect_dict and alt.effect_dict["yaw_moment"]["km"] == pytest.approx(0.03)
    assert Y.scales(cur, nominal) == pytest.approx((2 / 3, 1.0)) and Y.scales(alt, nominal) == pytest.approx((1, 1.5))
    # g019's shape: roll/pitch moved too; they stay an inertia, Izz goes back to the model's
    cur = nominal.with_effect("inertia", ixx=0.04, iyy=0.038, izz=0.0225)
    alt, was, becomes, s = Y.other_reading(cur, nominal)
    assert alt.effect_dict["inertia"] == pytest.approx({"ixx": 0.04, "iyy": 0.038, "izz": 0.03})
    assert alt.effect_dict["yaw_moment"]["km"] == pytest.approx(0.02 * 0.03 / 0.0225)
    # a yaw moment -> an inertia of Izz / s
    alt, was, becomes, s = Y.other_reading(nominal.with_effect("yaw_moment", km=0.03), nominal)
    assert (was, becomes, s) == ("yaw_moment", "inertia", pytest.approx(1.5))
    assert alt.effect_dict["inertia"] == pytest.approx({"ixx": 0.025, "iyy": 0.025, "izz": 0.02})
    # no reading: Izz within 3 %, both yaw effects, none
    assert Y.other_reading(nominal.with_effect("inertia", ixx=0.04, iyy=0.025, izz=0.0295), nominal) is None
    assert Y.other_reading(nominal.with_effect("yaw_moment", km=0.03).with_effect(
        "inertia", ixx=0.025, iyy=0.025, izz=0.035), nominal) is None
    assert Y.other_reading(nominal, nominal) is None


def _yaw_flight(c_damp: float, seed: int = 3):
    """A synthetic yaw row, truth Izz 1, km 1.5: D = (alpha + c r) / 1.5 + noise; 60 s at 50 Hz."""
    rng = np.random.default_rng(seed)
    n = 3000
    t = np.arange(n) / 50.0
    r = np.convolve(rng.normal(size=n), np.ones(50) / 50, mode="same") * 8
    alpha = np.gradient(r, t)
    D = (alpha + c_damp * r) / 1.5 + 0.02 * rng.normal(size=n)
    return SimpleNamespace(t=t, valid=np.ones(n, bool), r=r, alpha=alpha, D=D, c=c_damp)


def _patch(monkeypatch, data, nominal):
    """The yaw mode of a vehicle as the row Izz alpha - km D + c r (every other mode nil)."""
    izz0, km0 = float(nominal.inertia[2, 2]), float(nominal.rotors.km_m)

    def residual_channels(d, vp, nom):
        p, q = Y.scales(vp, nominal)
        out = np.zeros((d.t.size, 6))
        out[:, Y.YAW] = p * d.alpha - q * d.D + d.c * d.r
        return out

    monkeypatch.setattr(Y, "residual_channels", residual_channels)
    monkeypatch.setattr(Y, "modes", lambda R, vp: (R, None))
    return izz0, km0


def test_the_two_readings_tie_without_another_yaw_torque(monkeypatch, nominal):
    data = _yaw_flight(0.0)
    izz0, km0 = _patch(monkeypatch, data, nominal)
    as_km = nominal.with_effect("yaw_moment", km=1.5 * km0)
    as_izz = nominal.with_effect("inertia", ixx=0.025, iyy=0.025, izz=izz0 / 1.5)
    raw_km = Y.residual_channels(data, as_km, nominal)[:, Y.YAW]
    raw_izz = Y.residual_channels(data, as_izz, nominal)[:, Y.YAW]
    # in torque units the smaller scale always wins, by exactly s
    assert np.allclose(raw_km, 1.5 * raw_izz)
    # scaled, they are one residual: no test prefers either, the pair is reported
    assert np.allclose(Y.scaled_modes(data, as_km, nominal), Y.scaled_modes(data, as_izz, nominal))
    test = Y.compare(data, nominal, data.t > 39, as_izz, as_km)
    assert test["t_alt"] == 0.0 and test["t_current"] == 0.0 and test["heldout_cut"] == pytest.approx(0.0, abs=1e-12)
    assert Y.choose(test) == "pair"


def test_a_damping_torque_tells_them_apart(monkeypatch, nominal):
    data = _yaw_flight(0.6)
    izz0, km0 = _patch(monkeypatch, data, nominal)
    as_km = nominal.with_effect("yaw_moment", km=1.5 * km0)
    as_izz = nominal.with_effect("inertia", ixx=0.025, iyy=0.025, izz=izz0 / 1.5)
    test = Y.compare(data, nominal, data.t > 39, as_izz, as_km)
    # the truth's reading (km x1.5) leaves the noise alone; Izz / 1.5 leaves c r (1 - 1/1.5) in yaw
    assert test["t_alt"] == pytest.approx(12.13, abs=0.05) and test["heldout_cut"] == pytest.approx(0.910, abs=0.002)
    assert Y.choose(test) == "switch"
    back = Y.compare(data, nominal, data.t > 39, as_km, as_izz)
    assert back["t_current"] == pytest.approx(12.13, abs=0.05) and Y.choose(back) == "kept"


def test_choose_on_the_block_test_and_the_held_out_part():
    """Measured on the grid flights (tenth session, ``docs/discovery.md``): RotorPy k015 (rotor drag + km x1.5,
    reported Izz x0.667 `likely`) t 5.04, held-out 27.5 % -> km; g019 (Ixx/Iyy x1.6 + km x1.5, reported Izz
    x0.75) t 6.55, 0.4 % -> km; g033 (1 kg quad hover, no yaw torque but the two) t 0.09 / 1.06 -> the pair;
    g012 (km x2, the truth reported) the inertia reading worse at t 8.93 -> kept; the shared real log
    s500_rcac_mission2 (km 0.0144 confirmed) t 1.32 / -0.28 -> the pair."""
    assert Y.choose({"t_alt": 5.04, "t_current": -3.52, "heldout_cut": 0.2752}) == "switch"
    assert Y.choose({"t_alt": 6.55, "t_current": -6.14, "heldout_cut": 0.0041}) == "switch"
    assert Y.choose({"t_alt": 0.09, "t_current": 1.06, "heldout_cut": 0.0}) == "pair"
    assert Y.choose({"t_alt": -4.56, "t_current": 8.93, "heldout_cut": -0.1366}) == "kept"
    assert Y.choose({"t_alt": 1.32, "t_current": -0.28, "heldout_cut": -0.0163}) == "pair"
    assert Y.choose({"t_alt": 3.5, "t_current": 0.0, "heldout_cut": 0.01}) == "switch"
    assert Y.choose({"t_alt": 3.5, "t_current": 0.0, "heldout_cut": -0.01}) == "pair"
    assert Y.choose({"t_alt": 0.0, "t_current": 3.2, "heldout_cut": -0.2}) == "kept"
    assert Y.choose({"t_alt": 2.9, "t_current": 2.9, "heldout_cut": 0.0}) == "pair"


def test_a_reading_refitted_to_the_models_value_is_no_effect(nominal):
    # RotorPy g030 (battery sag + ground effect, no yaw change): a false inertia Ixx/Iyy/Izz x1.23/1.13/1.23 read
    # as a yaw moment refits to km 0.019982 (x0.999): no yaw moment, the inertia keeps its roll/pitch axes
    alt = nominal.with_effect("inertia", ixx=0.0306, iyy=0.0282, izz=0.03).with_effect("yaw_moment", km=0.019982)
    back, gone = Y.at_model(alt, "yaw_moment", nominal)
    assert gone and "yaw_moment" not in back.effect_dict and back.effect_dict["inertia"]["ixx"] == 0.0306
    assert Y._rename(["inertia", "battery_sag", "ground_effect"], "inertia", "yaw_moment", back.effect_dict) == [
        "battery_sag", "ground_effect", "inertia"]
    kept, gone = Y.at_model(nominal.with_effect("yaw_moment", km=0.03), "yaw_moment", nominal)
    assert not gone and kept.effect_dict["yaw_moment"]["km"] == 0.03
    # an Izz reading within 3 % of the model's: Izz back at the model's, or no inertia where roll/pitch are too
    back, gone = Y.at_model(nominal.with_effect("inertia", ixx=0.04, iyy=0.04, izz=0.0295), "inertia", nominal)
    assert gone and back.effect_dict["inertia"] == pytest.approx({"ixx": 0.04, "iyy": 0.04, "izz": 0.03})
    back, gone = Y.at_model(nominal.with_effect("inertia", ixx=0.025, iyy=0.025, izz=0.0295), "inertia", nominal)
    assert gone and "inertia" not in back.effect_dict


def test_the_refit_never_varies_a_whole_number_parameter(nominal):
    """RotorPy c028 (judge10: a weak motor 1 beside a mass, hover with yaw): the yaw reading's refit freed the weak
    motor's index with its efficiency, and the first finite-difference step (motor 1.001) was refused by the params
    check, so discover stopped.  Whole-number parameters (``Effect.discrete``) are held like a sag's v_ref."""
    from twin_nodes.discovery.candidates import NOT_FITTED

    assert {("motor_efficiency", "motor"), ("coaxial", "lower_mask"), ("battery_sag", "v_ref")} <= NOT_FITTED
    vp = (nominal.with_effect("motor_efficiency", motor=1.0, efficiency=0.8)
          .with_effect("mass", mass=1.15 * nominal.mass_kg)
          .with_effect("inertia", ixx=nominal.inertia[0, 0], iyy=nominal.inertia[1, 1], izz=1.2 * nominal.inertia[2, 2]))
    free = Y._free(vp, "inertia", ["motor_efficiency", "mass"])
    assert ("motor_efficiency", "efficiency") in free and ("mass", "mass") in free and ("inertia", "izz") in free
    assert ("motor_efficiency", "motor") not in free
