"""Vectorised unit-quaternion arithmetic in scipy's (x, y, z, w) order.

scipy's ``Rotation`` is used for Euler conversions; these helpers cover the inner loops (forward
kinematics, slerp, blending) where building ``Rotation`` objects per joint would cost more than
the arithmetic. All functions broadcast over leading axes; quaternions are ``(..., 4)``.
"""

from __future__ import annotations

import numpy as np


def normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)``."""
    return q / np.sqrt(dot(q, q))[..., None]


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products ``(...)`` of quaternions ``(..., 4)``, summed in component order (the sum
    ``np.sum(a * b, axis=-1)`` makes, without its temporary and reduction)."""
    return (
        a[..., 0] * b[..., 0]
        + a[..., 1] * b[..., 1]
        + a[..., 2] * b[..., 2]
        + a[..., 3] * b[..., 3]
    )


def multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``), ``(..., 4)``."""
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        (
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ),
        axis=-1,
    )


def conjugate(q: np.ndarray) -> np.ndarray:
    """Inverse of unit quaternions ``(..., 4)``."""
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``."""
    v = np.asarray(v)
    qx, qy, qz, qw = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
    # t = 2 (q_xyz × v); v + w t + q_xyz × t, written out (np.cross costs more than the sums)
    tx = 2.0 * (qy * vz - qz * vy)
    ty = 2.0 * (qz * vx - qx * vz)
    tz = 2.0 * (qx * vy - qy * vx)
    return np.stack(
        (
            vx + qw * tx + (qy * tz - qz * ty),
            vy + qw * ty + (qz * tx - qx * tz),
            vz + qw * tz + (qx * ty - qy * tx),
        ),
        axis=-1,
    )


def identity(shape: tuple[int, ...] = ()) -> np.ndarray:
    """Identity quaternions of shape ``shape + (4,)``."""
    q = np.zeros(shape + (4,))
    q[..., 3] = 1.0
    return q


def same_hemisphere(q: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``q`` with signs flipped where it lies in the opposite hemisphere from ``ref``."""
    return np.where(dot(q, ref)[..., None] < 0.0, -q, q)


def slerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation from ``a`` to ``b`` at ``t`` (broadcast ``(...)``), shortest arc."""
    t = np.asarray(t, dtype=float)[..., None]
    cos = dot(a, b)[..., None]
    # b's sign flipped into the opposite hemisphere from a goes into its weight (same sums)
    sign = np.ones_like(cos)
    sign[cos < 0.0] = -1.0
    theta = np.arccos(np.clip(sign * cos, -1.0, 1.0))
    sin_theta = np.sin(theta)
    small = sin_theta < 1e-6
    safe = np.where(small, 1.0, sin_theta)
    wa = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    wb = np.where(small, t, np.sin(t * theta) / safe) * sign
    return normalize(wa * a + wb * b)


def to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (axis × angle, radians) ``(..., 3)`` of unit quaternions, angle ≤ π."""
    q = np.where(q[..., 3:4] < 0.0, -q, q)
    s = np.linalg.norm(q[..., :3], axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 3])
    # angle / sin(angle / 2) tends to 2 as the angle tends to 0
    scale = np.where(s > 1e-9, angle / np.where(s > 1e-9, s, 1.0), 2.0)
    return q[..., :3] * scale[..., None]


def from_rotvec(v: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` from rotation vectors ``(..., 3)`` (radians)."""
    angle = np.linalg.norm(v, axis=-1)
    half = 0.5 * angle
    scale = np.where(angle > 1e-9, np.sin(half) / np.where(angle > 1e-9, angle, 1.0), 0.5)
    return np.concatenate((v * scale[..., None], np.cos(half)[..., None]), axis=-1)


def from_y_angle(angle: np.ndarray | float) -> np.ndarray:
    """Rotations about the world Y (up) axis by ``angle`` radians, ``(..., 4)``."""
    angle = np.asarray(angle, dtype=float)
    q = np.zeros(angle.shape + (4,))
    q[..., 1] = np.sin(0.5 * angle)
    q[..., 3] = np.cos(0.5 * angle)
    return q


def heading_angle(q: np.ndarray, forward: np.ndarray | None = None) -> np.ndarray:
    """Yaw (radians, about +Y) of the rotated ``forward`` axis (default +Z) projected on XZ."""
    fwd = np.array([0.0, 0.0, 1.0]) if forward is None else np.asarray(forward, dtype=float)
    f = rotate(q, np.broadcast_to(fwd, q.shape[:-1] + (3,)))
    return np.arctan2(f[..., 0], f[..., 2])


def from_euler(order: str, degrees: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` from intrinsic Euler angles ``(..., 3)`` in degrees.

    ``order`` is upper-case like scipy's intrinsic convention: ``"ZXY"`` is ``Rz · Rx · Ry``
    (the BVH meaning of ``Zrotation Xrotation Yrotation``). Same result as
    ``Rotation.from_euler(order, ..., degrees=True)``, several times faster on large arrays.
    """
    half = np.radians(degrees) * 0.5
    out: np.ndarray | None = None
    for k, axis in enumerate(order):
        q = np.zeros(half.shape[:-1] + (4,))
        q[..., "XYZ".index(axis)] = np.sin(half[..., k])
        q[..., 3] = np.cos(half[..., k])
        out = q if out is None else multiply(out, q)
    assert out is not None, "order names three axes"
    return out
