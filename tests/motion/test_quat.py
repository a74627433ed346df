"""Quaternion helpers against the straightforward formulas they restructure (the renderer's
output must not move when a helper is rewritten for speed)."""

from __future__ import annotations

import numpy as np

from dancegraph.motion import quat


def _unit(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    q = rng.normal(size=shape + (4,))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def test_rotate_dot_normalize_are_the_plain_formulas():
    """``rotate`` is v + 2w(u × v) + 2u × (u × v) as np.cross writes it, ``dot`` and
    ``normalize`` the sums np.sum and np.linalg.norm make, broadcasting as they do."""
    rng = np.random.default_rng(0)
    q, v = _unit(rng, (200, 7)), rng.normal(size=(200, 7, 3))

    def plain_rotate(q, v):
        t = 2.0 * np.cross(q[..., :3], v)
        return v + q[..., 3:4] * t + np.cross(q[..., :3], t)

    np.testing.assert_allclose(quat.rotate(q, v), plain_rotate(q, v), rtol=0, atol=1e-12)
    one = np.array([0.3, -1.2, 0.5])  # one vector for many rotations (as forward kinematics)
    np.testing.assert_allclose(quat.rotate(q, one), plain_rotate(q, one), rtol=0, atol=1e-12)
    b = rng.normal(size=(200, 7, 4))
    np.testing.assert_allclose(quat.dot(q, b), np.sum(q * b, axis=-1), rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        quat.normalize(b), b / np.linalg.norm(b, axis=-1, keepdims=True), rtol=0, atol=1e-12
    )
    flipped = quat.same_hemisphere(b, q)
    assert (np.sum(flipped * q, axis=-1) >= 0).all()
    np.testing.assert_array_equal(np.abs(flipped), np.abs(b))


def test_slerp_is_the_textbook_slerp():
    """``slerp`` folds the hemisphere flip into a weight: it is the textbook slerp along the
    shorter arc (b flipped first), at the ends, between equal, opposite and nearly equal
    quaternions, in float64 and from float32 inputs."""
    rng = np.random.default_rng(1)
    a, b = _unit(rng, (500, 5)), _unit(rng, (500, 5))
    b[:20] = a[:20]  # equal
    b[20:40] = -a[20:40]  # the same rotation, other sign
    b[40:60] = quat.normalize(a[40:60] + 1e-8 * rng.normal(size=(20, 5, 4)))  # nearly equal
    t = rng.uniform(size=(500, 1))
    t[60:70], t[70:80] = 0.0, 1.0

    def textbook(a, b, t):
        t = np.asarray(t, dtype=float)[..., None]
        b = np.where(np.sum(a * b, axis=-1, keepdims=True) < 0.0, -b, b)
        theta = np.arccos(np.clip(np.sum(a * b, axis=-1, keepdims=True), -1.0, 1.0))
        s = np.sin(theta)
        small = s < 1e-6
        safe = np.where(small, 1.0, s)
        wa = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
        wb = np.where(small, t, np.sin(t * theta) / safe)
        out = wa * a + wb * b
        return out / np.linalg.norm(out, axis=-1, keepdims=True)

    for x, y in ((a, b), (a.astype(np.float32), b.astype(np.float32))):
        got = quat.slerp(x, y, t)
        np.testing.assert_allclose(got, textbook(x, y, t), rtol=0, atol=1e-12)
    got = quat.slerp(a, b, t)
    np.testing.assert_allclose(got[60:70], a[60:70], atol=1e-12)
    ends = np.where(np.sum(a * b, axis=-1, keepdims=True) < 0, -b, b)
    np.testing.assert_allclose(got[70:80], ends[70:80], atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(got[:40] * a[:40], axis=-1)), 1.0, atol=1e-12)
