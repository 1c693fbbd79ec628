"""Frame conversions PX4 (NED / FRD) <-> ROS (ENU / FLU) and quaternion maths.

This module is the **only** place in rotortwin that converts between the PX4
and the ROS conventions (conventions.md §1), and the one home of generic
quaternion helpers.  Everything is vectorised: a vector argument has shape
``(3,)`` or ``(n, 3)``, a quaternion ``(4,)`` or ``(n, 4)``; the result has the
same leading shape.

Conventions
-----------
- World frames: PX4 **NED** (x North, y East, z Down), ROS **ENU** (x East,
  y North, z Up; REP-103).
- Body frames: PX4 **FRD** (x Forward, y Right, z Down), ROS **FLU** (x Forward,
  y Left, z Up).
- Quaternions are ``[w, x, y, z]`` (Hamilton, scalar first) everywhere in this
  project, including ROS-side arrays; only ``geometry_msgs/Quaternion`` itself
  orders fields x, y, z, w.
- A quaternion ``q_a_b`` *rotates vectors from frame b into frame a*:
  ``v_a = q_a_b ⊗ v_b ⊗ q_a_b*``.  PX4 ``vehicle_attitude.q`` is ``q_ned_frd``;
  the ROS orientation is ``q_enu_flu``.
- ``q`` and ``-q`` are the same rotation.  Single-sample conversions return the
  representative with ``w >= 0``; :func:`quat_make_continuous` picks signs for a
  time series so that neighbouring samples stay close (no jumps for plotting or
  interpolation).

The vector maps and ``NED_ENU_Q``/``AIRCRAFT_BASELINK_Q`` follow px4_ros_com
``frame_transforms`` exactly:

- NED -> ENU: ``(x, y, z) -> (y, x, -z)`` (self-inverse);
- FRD -> FLU: ``(x, y, z) -> (x, -y, -z)`` (self-inverse);
- ``q_enu_flu = NED_ENU_Q ⊗ q_ned_frd ⊗ AIRCRAFT_BASELINK_Q`` with
  ``NED_ENU_Q = quaternion_from_euler(pi, 0, pi/2) = (0, √½, √½, 0)`` and
  ``AIRCRAFT_BASELINK_Q = (0, 1, 0, 0)`` (w, x, y, z).

Euler angles are the aerospace ZYX sequence: ``R = Rz(yaw) Ry(pitch) Rx(roll)``,
in radians.  In ROS ENU/FLU yaw is measured from East, counter-clockwise
(``yaw_enu = pi/2 - yaw_ned``).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "NED_ENU_Q",
    "AIRCRAFT_BASELINK_Q",
    "ned_to_enu",
    "enu_to_ned",
    "frd_to_flu",
    "flu_to_frd",
    "q_ned_frd_to_enu_flu",
    "q_enu_flu_to_ned_frd",
    "yaw_ned_to_enu",
    "yaw_enu_to_ned",
    "wrap_pi",
    "quat_multiply",
    "quat_conjugate",
    "quat_normalize",
    "quat_canonical",
    "quat_make_continuous",
    "quat_rotate",
    "quat_to_rotmat",
    "quat_from_rotmat",
    "quat_from_euler",
    "euler_from_quat",
    "quat_angle_between",
]

_S = np.sqrt(0.5)
#: px4_ros_com ``NED_ENU_Q`` = quaternion_from_euler(pi, 0, pi/2), [w, x, y, z].
NED_ENU_Q = np.array([0.0, _S, _S, 0.0])
#: px4_ros_com ``AIRCRAFT_BASELINK_Q`` = quaternion_from_euler(pi, 0, 0), [w, x, y, z].
AIRCRAFT_BASELINK_Q = np.array([0.0, 1.0, 0.0, 0.0])


def _as_vec(v: np.ndarray, name: str = "v") -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape[-1:] != (3,):
        raise ValueError(f"{name}: expected shape (3,) or (n, 3), got {a.shape}")
    return a


def _as_quat(q: np.ndarray, name: str = "q") -> np.ndarray:
    a = np.asarray(q, dtype=float)
    if a.shape[-1:] != (4,):
        raise ValueError(f"{name}: expected [w, x, y, z] with shape (4,) or (n, 4), got {a.shape}")
    return a


# --------------------------------------------------------------------------- vectors


def ned_to_enu(v: np.ndarray) -> np.ndarray:
    """World vector NED -> ENU: ``(x, y, z) -> (y, x, -z)``. Shape (3,) or (n, 3)."""
    a = _as_vec(v)
    return np.stack([a[..., 1], a[..., 0], -a[..., 2]], axis=-1)


def enu_to_ned(v: np.ndarray) -> np.ndarray:
    """World vector ENU -> NED (the same swap, it is self-inverse)."""
    return ned_to_enu(v)


def frd_to_flu(v: np.ndarray) -> np.ndarray:
    """Body vector FRD -> FLU: ``(x, y, z) -> (x, -y, -z)``. Also for rates, moments."""
    a = _as_vec(v)
    return np.stack([a[..., 0], -a[..., 1], -a[..., 2]], axis=-1)


def flu_to_frd(v: np.ndarray) -> np.ndarray:
    """Body vector FLU -> FRD (self-inverse)."""
    return frd_to_flu(v)


# --------------------------------------------------------------------------- quaternion maths


def quat_multiply(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Hamilton product ``q1 ⊗ q2`` ([w, x, y, z]); broadcasts over leading axes."""
    a = _as_quat(q1, "q1")
    b = _as_quat(q2, "q2")
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate ``[w, -x, -y, -z]`` (the inverse for a unit quaternion)."""
    a = _as_quat(q)
    return a * np.array([1.0, -1.0, -1.0, -1.0])


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion(s). A zero or non-finite quaternion becomes all-NaN."""
    a = _as_quat(q)
    n = np.linalg.norm(a, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = a / n
    bad = ~(np.isfinite(n) & (n > 1e-12))
    return np.where(bad, np.nan, out)


def quat_canonical(q: np.ndarray) -> np.ndarray:
    """The representative of ``±q`` with ``w >= 0`` (ties broken on x, y, z)."""
    a = _as_quat(q)
    # first non-zero component decides the sign, so w == 0 cases are canonical too
    key = a[..., 0].copy()
    for i in (1, 2, 3):
        key = np.where(np.abs(key) < 1e-15, a[..., i], key)
    sign = np.where(key < 0, -1.0, 1.0)
    return a * sign[..., None]


def quat_make_continuous(q: np.ndarray) -> np.ndarray:
    """Flip signs along a time series (n, 4) so that consecutive quaternions have
    a non-negative dot product.  The first finite sample is made ``w >= 0``.
    NaN rows are kept and skipped (the next finite row is compared with the last
    finite one)."""
    a = np.array(_as_quat(q), dtype=float, copy=True)
    if a.ndim == 1:
        return quat_canonical(a)
    finite = np.all(np.isfinite(a), axis=-1)
    idx = np.flatnonzero(finite)
    if idx.size == 0:
        return a
    f = a[idx]
    f[0] = quat_canonical(f[0])
    d = np.einsum("ij,ij->i", f[1:], f[:-1])
    # sign of sample k relative to sample k-1; cumulative product gives absolute flips
    flips = np.concatenate([[1.0], np.where(d < 0, -1.0, 1.0)])
    f = f * np.cumprod(flips)[:, None]
    a[idx] = f
    return a


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vector(s) ``v`` by unit quaternion(s) ``q``: ``q ⊗ v ⊗ q*``."""
    a = _as_quat(q)
    b = _as_vec(v)
    w = a[..., :1]
    u = a[..., 1:]
    t = 2.0 * np.cross(u, b)
    return b + w * t + np.cross(u, t)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (…, 3, 3) of unit quaternion(s); ``R @ v_b = v_a`` for ``q_a_b``."""
    a = quat_normalize(q)
    w, x, y, z = np.moveaxis(a, -1, 0)
    r = np.empty(a.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - w * z)
    r[..., 0, 2] = 2 * (x * z + w * y)
    r[..., 1, 0] = 2 * (x * y + w * z)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - w * x)
    r[..., 2, 0] = 2 * (x * z - w * y)
    r[..., 2, 1] = 2 * (y * z + w * x)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def quat_from_rotmat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) ``w >= 0`` from rotation matrices (…, 3, 3) (Shepperd's method)."""
    m = np.asarray(r, dtype=float)
    if m.shape[-2:] != (3, 3):
        raise ValueError(f"r: expected shape (3, 3) or (n, 3, 3), got {m.shape}")
    flat = m.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    tr = np.trace(flat, axis1=1, axis2=2)
    diag = np.stack([flat[:, 0, 0], flat[:, 1, 1], flat[:, 2, 2]], axis=1)
    choice = np.argmax(np.column_stack([tr, diag]), axis=1)
    for k in range(4):
        sel = choice == k
        if not np.any(sel):
            continue
        f = flat[sel]
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + tr[sel])
            q = [0.25 * s, (f[:, 2, 1] - f[:, 1, 2]) / s, (f[:, 0, 2] - f[:, 2, 0]) / s,
                 (f[:, 1, 0] - f[:, 0, 1]) / s]
        elif k == 1:
            s = 2.0 * np.sqrt(1.0 + f[:, 0, 0] - f[:, 1, 1] - f[:, 2, 2])
            q = [(f[:, 2, 1] - f[:, 1, 2]) / s, 0.25 * s, (f[:, 0, 1] + f[:, 1, 0]) / s,
                 (f[:, 0, 2] + f[:, 2, 0]) / s]
        elif k == 2:
            s = 2.0 * np.sqrt(1.0 + f[:, 1, 1] - f[:, 0, 0] - f[:, 2, 2])
            q = [(f[:, 0, 2] - f[:, 2, 0]) / s, (f[:, 0, 1] + f[:, 1, 0]) / s, 0.25 * s,
                 (f[:, 1, 2] + f[:, 2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + f[:, 2, 2] - f[:, 0, 0] - f[:, 1, 1])
            q = [(f[:, 1, 0] - f[:, 0, 1]) / s, (f[:, 0, 2] + f[:, 2, 0]) / s,
                 (f[:, 1, 2] + f[:, 2, 1]) / s, 0.25 * s]
        out[sel] = np.column_stack(q)
    out = quat_canonical(quat_normalize(out))
    return out.reshape(m.shape[:-2] + (4,))


def quat_from_euler(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Quaternion (…, 4) of ZYX Euler angles [rad]: ``q = qz(yaw) ⊗ qy(pitch) ⊗ qx(roll)``."""
    r = np.asarray(roll, dtype=float) * 0.5
    p = np.asarray(pitch, dtype=float) * 0.5
    y = np.asarray(yaw, dtype=float) * 0.5
    cr, sr = np.cos(r), np.sin(r)
    cp, sp = np.cos(p), np.sin(p)
    cy, sy = np.cos(y), np.sin(y)
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def euler_from_quat(q: np.ndarray) -> np.ndarray:
    """ZYX Euler angles ``[roll, pitch, yaw]`` [rad], shape (…, 3), of unit quaternion(s).

    Pitch is clipped to ±pi/2 at the gimbal-lock singularity."""
    a = quat_normalize(q)
    w, x, y, z = np.moveaxis(a, -1, 0)
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def quat_angle_between(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Rotation angle [rad, 0..pi] between two attitudes; insensitive to ``q ≡ -q``."""
    # atan2 of the relative rotation keeps full precision near 0 (arccos does not)
    rel = quat_multiply(quat_conjugate(quat_normalize(q1)), quat_normalize(q2))
    return 2.0 * np.arctan2(np.linalg.norm(rel[..., 1:], axis=-1), np.abs(rel[..., 0]))


def wrap_pi(angle: np.ndarray) -> np.ndarray:
    """Wrap angle(s) to [-pi, pi)."""
    a = np.asarray(angle, dtype=float)
    return (a + np.pi) % (2.0 * np.pi) - np.pi


# --------------------------------------------------------------------------- PX4 <-> ROS attitude


def q_ned_frd_to_enu_flu(q_wxyz: np.ndarray) -> np.ndarray:
    """PX4 attitude ``q_ned_frd`` -> ROS orientation ``q_enu_flu`` ([w, x, y, z]).

    px4_ros_com ``px4_to_ros_orientation``: ``NED_ENU_Q ⊗ q ⊗ AIRCRAFT_BASELINK_Q``.
    Returns the ``w >= 0`` representative of each quaternion (renormalised);
    apply :func:`quat_make_continuous` afterwards for a time series."""
    q = _as_quat(q_wxyz, "q_wxyz")
    out = quat_multiply(quat_multiply(NED_ENU_Q, q), AIRCRAFT_BASELINK_Q)
    return quat_canonical(quat_normalize(out))


def q_enu_flu_to_ned_frd(q_wxyz: np.ndarray) -> np.ndarray:
    """ROS orientation ``q_enu_flu`` -> PX4 attitude ``q_ned_frd`` (inverse of
    :func:`q_ned_frd_to_enu_flu`): ``NED_ENU_Q* ⊗ q ⊗ AIRCRAFT_BASELINK_Q*``, ``w >= 0``."""
    q = _as_quat(q_wxyz, "q_wxyz")
    out = quat_multiply(quat_multiply(quat_conjugate(NED_ENU_Q), q),
                        quat_conjugate(AIRCRAFT_BASELINK_Q))
    return quat_canonical(quat_normalize(out))


def yaw_ned_to_enu(yaw: np.ndarray) -> np.ndarray:
    """Heading from North clockwise (PX4) -> yaw from East counter-clockwise (ROS),
    ``pi/2 - yaw``, wrapped to [-pi, pi).  NaN stays NaN (= yaw not controlled)."""
    return wrap_pi(np.pi / 2 - np.asarray(yaw, dtype=float))


def yawspeed_ned_to_enu(rate: np.ndarray) -> np.ndarray:
    """Heading rate (PX4, about down, clockwise seen from above) -> yaw rate about up (ROS,
    counter-clockwise), ``-rate``; self-inverse.  NaN stays NaN (= no feed-forward)."""
    return -np.asarray(rate, dtype=float)


def yaw_enu_to_ned(yaw: np.ndarray) -> np.ndarray:
    """ROS yaw -> PX4 heading (the same map, it is self-inverse), wrapped to [-pi, pi)."""
    return wrap_pi(np.pi / 2 - np.asarray(yaw, dtype=float))
