"""frames.py: PX4 NED/FRD <-> ROS ENU/FLU, hand-worked cases and properties."""

from __future__ import annotations

import numpy as np
import pytest

from twin_nodes.base import frames as F

DEG = np.pi / 180


def same_rotation(q1, q2, atol=1e-9):
    """q and -q are the same rotation."""
    return np.all(F.quat_angle_between(q1, q2) < atol) or np.allclose(
        np.abs(np.sum(F.quat_normalize(q1) * F.quat_normalize(q2), axis=-1)), 1.0, atol=atol)


def random_quats(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# --------------------------------------------------------------------------- vectors


@pytest.mark.parametrize("ned, enu", [
    ((1, 0, 0), (0, 1, 0)),    # North -> ENU y
    ((0, 1, 0), (1, 0, 0)),    # East -> ENU x
    ((0, 0, 1), (0, 0, -1)),   # Down -> -Up
    ((3, -2, -5), (-2, 3, 5)),  # 5 m above the origin
])
def test_ned_enu_hand_cases(ned, enu):
    assert np.allclose(F.ned_to_enu(np.array(ned, float)), enu)
    assert np.allclose(F.enu_to_ned(np.array(enu, float)), ned)


@pytest.mark.parametrize("frd, flu", [
    ((1, 0, 0), (1, 0, 0)),    # forward stays
    ((0, 1, 0), (0, -1, 0)),   # right -> -left
    ((0, 0, 1), (0, 0, -1)),   # down -> -up
])
def test_frd_flu_hand_cases(frd, flu):
    assert np.allclose(F.frd_to_flu(np.array(frd, float)), flu)
    assert np.allclose(F.flu_to_frd(np.array(flu, float)), frd)


def test_vector_maps_vectorised_and_self_inverse():
    v = np.random.default_rng(1).normal(size=(50, 3))
    assert F.ned_to_enu(v).shape == (50, 3)
    assert np.array_equal(F.enu_to_ned(F.ned_to_enu(v)), v)
    assert np.array_equal(F.flu_to_frd(F.frd_to_flu(v)), v)
    # at rest the accelerometer reads z = -9.81 in FRD, +9.81 in FLU
    assert np.allclose(F.frd_to_flu([0.0, 0.0, -9.81]), [0, 0, 9.81])


def test_vector_bad_shape():
    with pytest.raises(ValueError, match=r"v: expected shape \(3,\) or \(n, 3\), got \(4,\)"):
        F.ned_to_enu(np.zeros(4))


# --------------------------------------------------------------------------- constants


def test_px4_ros_com_constants():
    # NED_ENU_Q = quaternion_from_euler(pi, 0, pi/2); AIRCRAFT_BASELINK_Q = (pi, 0, 0)
    assert same_rotation(F.NED_ENU_Q, F.quat_from_euler(np.pi, 0.0, np.pi / 2))
    assert same_rotation(F.AIRCRAFT_BASELINK_Q, F.quat_from_euler(np.pi, 0.0, 0.0))
    assert np.allclose(F.NED_ENU_Q, [0, np.sqrt(0.5), np.sqrt(0.5), 0])
    # NED_ENU_Q rotates NED vectors into ENU, matching the vector map
    v = np.random.default_rng(2).normal(size=(10, 3))
    assert np.allclose(F.quat_rotate(F.NED_ENU_Q, v), F.ned_to_enu(v))
    assert np.allclose(F.quat_rotate(F.AIRCRAFT_BASELINK_Q, v), F.frd_to_flu(v))


# --------------------------------------------------------------------------- attitude


@pytest.mark.parametrize("px4_rpy_deg, ros_rpy_deg", [
    ((0, 0, 0), (0, 0, 90)),      # level, nose North -> ROS yaw +90
    ((0, 0, 90), (0, 0, 0)),      # nose East -> ROS yaw 0
    ((0, 0, -90), (0, 0, 180)),   # nose West
    ((0, 0, 180), (0, 0, -90)),   # nose South
    ((30, 0, 0), (30, 0, 90)),    # right wing down: roll keeps its sign
    ((0, 10, 0), (0, -10, 90)),   # nose up: FRD pitch +10 = FLU pitch -10
])
def test_attitude_hand_cases(px4_rpy_deg, ros_rpy_deg):
    q_px4 = F.quat_from_euler(*(np.array(px4_rpy_deg) * DEG))
    q_ros = F.q_ned_frd_to_enu_flu(q_px4)
    expect = F.quat_from_euler(*(np.array(ros_rpy_deg) * DEG))
    assert same_rotation(q_ros, expect)
    assert same_rotation(F.q_enu_flu_to_ned_frd(expect), q_px4)


def test_level_nose_north_exact():
    q = F.q_ned_frd_to_enu_flu(np.array([1.0, 0, 0, 0]))
    assert np.allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)])  # w >= 0 representative
    assert np.isclose(F.euler_from_quat(q)[2], np.pi / 2)


def test_random_round_trips():
    q = random_quats(1000, seed=3)
    back = F.q_enu_flu_to_ned_frd(F.q_ned_frd_to_enu_flu(q))
    assert F.quat_angle_between(back, q).max() < 1e-9
    back2 = F.q_ned_frd_to_enu_flu(F.q_enu_flu_to_ned_frd(q))
    assert F.quat_angle_between(back2, q).max() < 1e-9


def test_rotation_consistency_frd_ned_enu_vs_flu():
    """Rotate an FRD vector by the PX4 q then go NED->ENU, or go FRD->FLU then rotate
    by the converted q: the same ENU vector (conventions.md §1, 1000 attitudes)."""
    rng = np.random.default_rng(4)
    q_px4 = random_quats(1000, seed=5)
    v_frd = rng.normal(size=(1000, 3))
    a = F.ned_to_enu(F.quat_rotate(q_px4, v_frd))
    b = F.quat_rotate(F.q_ned_frd_to_enu_flu(q_px4), F.frd_to_flu(v_frd))
    assert np.allclose(a, b, atol=1e-12)
    # and with rotation matrices
    r_ros = F.quat_to_rotmat(F.q_ned_frd_to_enu_flu(q_px4))
    assert np.allclose(np.einsum("nij,nj->ni", r_ros, F.frd_to_flu(v_frd)), a, atol=1e-12)


def test_q_and_minus_q():
    q = random_quats(200, seed=6)
    assert np.allclose(F.q_ned_frd_to_enu_flu(q), F.q_ned_frd_to_enu_flu(-q))
    assert np.allclose(F.q_enu_flu_to_ned_frd(q), F.q_enu_flu_to_ned_frd(-q))
    assert np.all(F.q_ned_frd_to_enu_flu(q)[:, 0] >= 0)
    assert np.allclose(F.quat_angle_between(q, -q), 0.0, atol=1e-7)


def test_euler_relations_px4_vs_ros():
    """roll_ros = roll_px4, pitch_ros = -pitch_px4, yaw_ros = pi/2 - yaw_px4."""
    rng = np.random.default_rng(7)
    rpy = np.column_stack([rng.uniform(-3, 3, 500), rng.uniform(-1.3, 1.3, 500),
                           rng.uniform(-3.1, 3.1, 500)])
    q_px4 = F.quat_from_euler(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    ros = F.euler_from_quat(F.q_ned_frd_to_enu_flu(q_px4))
    assert np.allclose(F.wrap_pi(ros[:, 0] - rpy[:, 0]), 0, atol=1e-9)
    assert np.allclose(ros[:, 1], -rpy[:, 1], atol=1e-9)
    assert np.allclose(F.wrap_pi(ros[:, 2] - F.yaw_ned_to_enu(rpy[:, 2])), 0, atol=1e-9)


def test_yaw_maps():
    assert np.isclose(F.yaw_ned_to_enu(0.0), np.pi / 2)
    assert np.isclose(F.yaw_ned_to_enu(np.pi / 2), 0.0)
    assert np.isclose(F.yaw_ned_to_enu(np.pi), -np.pi / 2)
    y = np.random.default_rng(8).uniform(-np.pi, np.pi, 100)
    assert np.allclose(F.wrap_pi(F.yaw_enu_to_ned(F.yaw_ned_to_enu(y)) - y), 0, atol=1e-12)
    # NaN = yaw not controlled: stays NaN
    out = F.yaw_ned_to_enu(np.array([np.nan, 0.0]))
    assert np.isnan(out[0]) and np.isclose(out[1], np.pi / 2)


# --------------------------------------------------------------------------- quaternion helpers


def test_quat_helpers_consistent():
    q1, q2 = random_quats(100, 9), random_quats(100, 10)
    r12 = F.quat_to_rotmat(F.quat_multiply(q1, q2))
    assert np.allclose(r12, F.quat_to_rotmat(q1) @ F.quat_to_rotmat(q2), atol=1e-12)
    assert F.quat_angle_between(F.quat_from_rotmat(F.quat_to_rotmat(q1)), q1).max() < 1e-7
    rpy = F.euler_from_quat(q1)
    assert F.quat_angle_between(F.quat_from_euler(rpy[:, 0], rpy[:, 1], rpy[:, 2]), q1).max() < 1e-7
    ident = F.quat_multiply(q1, F.quat_conjugate(q1))
    assert np.allclose(ident, [1, 0, 0, 0], atol=1e-12)
    v = np.random.default_rng(11).normal(size=(100, 3))
    assert np.allclose(F.quat_rotate(q1, v), np.einsum("nij,nj->ni", F.quat_to_rotmat(q1), v))


def test_quat_from_euler_yaw_only():
    q = F.quat_from_euler(0.0, 0.0, np.pi / 2)
    assert np.allclose(F.quat_rotate(q, [1.0, 0, 0]), [0, 1, 0])


def test_make_continuous_and_normalize():
    q = random_quats(1, 12)[0]
    series = np.array([q, -q, q, -q, [np.nan] * 4, -q])
    c = F.quat_make_continuous(series)
    finite = c[np.all(np.isfinite(c), axis=1)]
    assert np.all(np.einsum("ij,ij->i", finite[1:], finite[:-1]) > 0)
    assert finite[0][0] >= 0
    assert np.all(np.isnan(c[4]))
    assert np.all(np.isnan(F.quat_normalize(np.zeros(4))))


def test_quat_bad_shape():
    with pytest.raises(ValueError, match=r"q_wxyz: expected \[w, x, y, z\]"):
        F.q_ned_frd_to_enu_flu(np.zeros(3))
