"""The ground-contact pad per channel (``residuals.contact_pads``): after a lift-off the vertical force is read
again 0.1 s after the last contact sample, the attitude channels (moments, horizontal force) 0.5 s after it;
before a contact sample (a touchdown) both keep 0.5 s."""

import numpy as np

from twin_nodes.discovery.locate import modes
from twin_nodes.discovery.residuals import (CLIMB_OUT_M_S, CONTACT_PAD_AFTER_S, CONTACT_PAD_BEFORE_S,
                                            THROTTLE_PAD_AFTER_S, EquationData, contact_pads, residual_channels)
from twin_nodes.vehicle.params import shipped

RATE = 50.0


def _lift_off_and_land(n=700, lift=100, touch=600):
    """2 s on the ground (samples 0-99), flown 100-599, on the ground again from 600."""
    c = np.zeros(n, bool)
    c[:lift] = True
    c[touch:] = True
    return c


def test_pads_on_a_synthetic_lift_off_and_landing_keep_these_samples():
    assert (CONTACT_PAD_BEFORE_S, CONTACT_PAD_AFTER_S, THROTTLE_PAD_AFTER_S, CLIMB_OUT_M_S) == (0.5, 0.5, 0.1, 0.3)
    throttle, attitude = contact_pads(_lift_off_and_land(), RATE)
    # the vertical force: 5 samples (0.1 s) after the last contact sample 99, 25 (0.5 s) before touchdown at 600
    assert np.flatnonzero(~throttle).tolist() == list(range(105, 575))
    # the attitude channels: 25 samples either side
    assert np.flatnonzero(~attitude).tolist() == list(range(125, 575))
    # 20 more samples (0.4 s) of the climb out for the vertical force, none for the attitude
    assert int((~throttle).sum() - (~attitude).sum()) == 20
    assert not (~attitude & throttle).any()


def test_the_shorter_pad_holds_only_where_the_vehicle_climbs_away():
    """A vehicle that leaves the contact test while still spinning up on the ground (no climb for the
    first 0.3 s after it) gets the vertical force back only from its climb-out on (sample 115)."""
    climbing = np.zeros(700, bool)
    climbing[115:300] = True
    throttle, attitude = contact_pads(_lift_off_and_land(), RATE, climbing)
    assert np.flatnonzero(~throttle).tolist() == list(range(115, 575))
    assert np.flatnonzero(~attitude).tolist() == list(range(125, 575))
    # never climbing: the long pad, as for the attitude
    throttle, _ = contact_pads(_lift_off_and_land(), RATE, np.zeros(700, bool))
    assert np.flatnonzero(~throttle).tolist() == list(range(125, 575))


def test_pads_of_a_flight_with_no_contact_and_a_bounce():
    throttle, attitude = contact_pads(np.zeros(300, bool), RATE)
    assert not throttle.any() and not attitude.any()
    c = np.zeros(300, bool)
    c[150] = True  # one contact sample mid-flight (a bounce)
    throttle, attitude = contact_pads(c, RATE)
    assert np.flatnonzero(throttle).tolist() == list(range(125, 156))
    assert np.flatnonzero(attitude).tolist() == list(range(125, 176))


def _flat_data(attitude_valid):
    """A vehicle level and still whose angular acceleration spikes while on the ground (RotorPy's
    flattening of the attitude at rest), 0.3 s before its lift-off at sample 100."""
    n, up = 400, 2
    t = np.arange(n) / RATE
    z = np.zeros((n, 3))
    alpha = np.zeros((n, 3))
    alpha[80:86, 0] = 40.0  # rad/s^2 roll, on the ground
    f = np.zeros((n, 3))
    f[:, 2] = 9.81
    u = np.full((n * up, 4), 0.5)
    contact = np.zeros(n, bool)
    contact[:100] = True
    throttle, attitude = contact_pads(contact, RATE)
    data = EquationData("x", t, ~throttle, z, z, np.tile([1.0, 0, 0, 0], (n, 1)), z, alpha, f, u, up,
                        np.full(n, np.nan), np.full(n, 0.3), 0.02)
    if attitude_valid:
        data.attitude_valid = ~attitude
    return data


def test_the_attitude_channels_carry_nothing_of_the_ground_into_the_climb_out():
    vp = shipped("px4_sih_quadx")
    M_old, _ = modes(residual_channels(_flat_data(False), vp), vp)
    M_new, _ = modes(residual_channels(_flat_data(True), vp), vp)
    kept = slice(105, 125)  # read for the vertical force only (0.1-0.5 s after the lift-off)
    # before: the ground's roll spike reaches the climb out through the 2 Hz low-pass
    assert np.abs(M_old[kept, 1]).max() > 1e-3
    # after: zeroed on the ground and up to 0.5 s after the lift-off, so nothing of it is anywhere
    assert np.abs(M_new[:, 1]).max() < 1e-12
    # the throttle (vertical force) is the same either way, and not zero
    np.testing.assert_allclose(M_new[:, 0], M_old[:, 0], atol=1e-12)
    assert np.abs(M_new[kept, 0]).min() > 1e-3
