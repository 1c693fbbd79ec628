"""The rate integrators as PX4's RateControl::updateIntegral: each axis's own limit (MC_RR/PR/YR_INT_LIM,
converted from PX4's normalised torque per axis) and the I-gain reduction with the rate error.

mantis_follow_00018 (issue 24): the twin's one shared 10 rad/s^2 limit held 0.055 N m about its
0.0055 kg m^2 pitch axis, where PX4's MC_PR_INT_LIM 0.3 holds ~1.4 N m; the identified drag moment
(H-force 201 mm above the centre of mass) outgrew it, and the twin's pitch rate stayed within
+-13 deg/s against a 60-190 deg/s demand until the position loop ran away."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from twin_nodes.twin.control import C_RI, I_FACTOR_RATE, Controller, ControllerGains
from twin_nodes.vehicle.params import shipped
from twin_nodes.vehicle.px4_params import RateGainsPx4, rate_gains_physical


def test_integrator_limits_convert_per_axis_from_px4s_normalised_torque():
    """Quad X, arm 0.25 m, thrust slope 6 N per unit command: PX4's normalised mix moves each motor by
    sqrt(2)/2 per unit roll/pitch torque, a moment of 2 * 0.25 * 6 = 3.0 N m; per unit yaw torque by 1,
    4 km s = 0.48 N m with the vehicle's km 0.02.  The limit is that moment times INT_LIM over each
    axis's own inertia (not the mean the shared P/I/D gains take)."""
    a = 0.25 / math.sqrt(2.0)
    x, y = np.array([a, -a, a, -a]), np.array([a, -a, -a, a])
    d = np.array([-1, -1, 1, 1])
    px4 = RateGainsPx4.from_params({"MC_RR_INT_LIM": 0.3, "MC_PR_INT_LIM": 0.2})  # MC_YR_INT_LIM: default 0.3
    assert px4.int_lim == (0.3, 0.2, 0.3)
    g = rate_gains_physical(px4, x, y, d, 0.05, 6.0, (0.02, 0.005, 0.03), km_physical_m=0.02)
    assert g["rate_i_max_rad_s2"] == pytest.approx(0.3 * 3.0 / 0.02, rel=1e-9)       # 45
    assert g["pitchrate_i_max_rad_s2"] == pytest.approx(0.2 * 3.0 / 0.005, rel=1e-9)  # 120
    assert g["yawrate_i_max_rad_s2"] == pytest.approx(0.3 * 0.48 / 0.03, rel=1e-9)    # 4.8


def _controller(**gains) -> Controller:
    vp = shipped("px4_sih_quadx")
    vp = dataclasses.replace(vp, controller={**dict(vp.controller or {}), **gains})
    return Controller(vp)


def test_one_given_limit_stands_for_every_axis():
    """A params file that gives only rate_i_max_rad_s2 (as before the per-axis limits) limits all three."""
    g = ControllerGains.from_params(dataclasses.replace(shipped("px4_sih_quadx"), controller={"rate_i_max_rad_s2": 7.0}))
    assert (g.rate_i_max_rad_s2, g.pitchrate_i_max_rad_s2, g.yawrate_i_max_rad_s2) == (7.0, 7.0, 7.0)


def test_each_axis_is_clamped_at_its_own_limit():
    ctrl = _controller(rate_i_max_rad_s2=5.0, pitchrate_i_max_rad_s2=50.0, yawrate_i_max_rad_s2=7.0)
    x = np.zeros(13)
    x[6] = 1.0  # level, at rest
    ctrl.C[C_RI:C_RI + 3] = (4.999, -49.999, 6.999)
    ctrl.update_manual(x, None, 0.5, 0.004, rates=np.array([1.0, -1.0, 1.0]))
    assert ctrl.C[C_RI:C_RI + 3] == pytest.approx([5.0, -50.0, 7.0], abs=1e-12)


def test_integration_follows_pxs_i_factor():
    """PX4 scales the I gain by 1 - (e / 400 deg/s)^2: 0.75 at a 200 deg/s rate error, 1 - 1/64 at 50."""
    ctrl = _controller(rate_i_max_rad_s2=1e4, pitchrate_i_max_rad_s2=1e4, yawrate_i_max_rad_s2=1e4)
    x = np.zeros(13)
    x[6] = 1.0
    e = np.radians([200.0, 50.0, 0.0])
    dt = 0.004
    ctrl.update_manual(x, None, 0.5, dt, rates=e)
    ki = ctrl.gains.rate_i_1_s2
    assert I_FACTOR_RATE == pytest.approx(np.radians(400.0))
    assert ctrl.C[C_RI] == pytest.approx(0.75 * ki * e[0] * dt, rel=1e-12)
    assert ctrl.C[C_RI + 1] == pytest.approx((1.0 - 1.0 / 64.0) * ki * e[1] * dt, rel=1e-12)
    assert ctrl.C[C_RI + 2] == 0.0
