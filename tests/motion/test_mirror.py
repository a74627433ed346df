"""Mirroring on real data: an involution, and FK positions reflect."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.mirror import mirror, mirrored_skeleton
from dancegraph.motion.skeleton import find_mirror_pairs

REFLECT = np.array([-1.0, 1.0, 1.0])


@pytest.fixture(scope="module", params=["salsa", "modern"])
def motion(request, salsa_dir: Path, modern_dir: Path):
    if request.param == "salsa":
        return read_bvh(salsa_dir / "60_10_scaled.bvh", fps=60).slice(0, 400)
    return read_bvh(modern_dir / "05_08.bvh", scale=0.056444).slice(0, 400)


def test_pairs_from_names():
    names = [
        "Hips",
        "LeftArm",
        "RightArm",
        "lShldr",
        "rShldr",
        "LHipJoint",
        "RHipJoint",
        "leftEye",
        "rightEye",
        "hand_l",
        "hand_r",
        "Spine",
        "Lonely",
        "rCollar",
    ]
    got = {(names[a], names[b]) for a, b in find_mirror_pairs(names)}
    assert got == {
        ("LeftArm", "RightArm"),
        ("lShldr", "rShldr"),
        ("LHipJoint", "RHipJoint"),
        ("leftEye", "rightEye"),
        ("hand_l", "hand_r"),
    }


def test_involution(motion):
    twice = mirror(mirror(motion))
    np.testing.assert_allclose(twice.rotations, motion.rotations, atol=1e-15)
    np.testing.assert_allclose(twice.root_positions, motion.root_positions, atol=1e-15)
    exact = mirror(mirror(motion, mirror_skeleton=True), mirror_skeleton=True)
    assert exact.skeleton == motion.skeleton
    np.testing.assert_allclose(exact.rotations, motion.rotations, atol=1e-15)


def test_fk_positions_reflect(motion):
    sk = motion.skeleton
    perm = np.arange(sk.n_joints)
    for a, b in sk.mirror_pairs():
        perm[a], perm[b] = b, a
    p, _ = forward_kinematics(motion)
    reflected = p[:, perm] * REFLECT
    # exact with the reflected bone offsets
    pm, _ = forward_kinematics(mirror(motion, mirror_skeleton=True))
    np.testing.assert_allclose(pm, reflected, atol=1e-9)
    # on the dataset's own skeleton, off only by its few-mm asymmetry
    asym = np.abs(mirrored_skeleton(sk).offsets - sk.offsets).max()
    assert asym < 0.013
    p_same, _ = forward_kinematics(mirror(motion))
    err = np.linalg.norm(p_same - reflected, axis=-1)
    assert err.max() < 8 * asym + 1e-9
    # the left hand now does what the right hand did
    lw, rw = sk.index("left_wrist"), sk.index("right_wrist")
    np.testing.assert_allclose(pm[:, lw], p[:, rw] * REFLECT, atol=1e-9)


def test_pairs_override(motion):
    sk = motion.skeleton
    explicit = mirror(motion, pairs=sk.mirror_pairs())
    np.testing.assert_array_equal(explicit.rotations, mirror(motion).rotations)
    # without pairs no side swaps: the root path still reflects, the arms do not change sides
    none = mirror(motion, pairs=[])
    p, _ = forward_kinematics(motion)
    pn, _ = forward_kinematics(none)
    np.testing.assert_allclose(pn[:, 0], p[:, 0] * REFLECT, atol=1e-12)
    lw = sk.index("left_wrist")
    pm, _ = forward_kinematics(mirror(motion, mirror_skeleton=True))
    assert np.abs(pn[:, lw] - pm[:, lw]).max() > 0.05
