"""Forward kinematics on the real skeletons, checked against an independent matrix computation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fk import canonical_positions, end_site_positions, forward_kinematics
from dancegraph.motion.skeleton import CANONICAL_JOINTS


@pytest.fixture(scope="module", params=["salsa", "modern"])
def motion(request, salsa_dir: Path, modern_dir: Path):
    if request.param == "salsa":
        return read_bvh(salsa_dir / "61_02_scaled.bvh", fps=60).slice(500, 800)
    return read_bvh(modern_dir / "05_06.bvh", scale=0.056444).slice(0, 300)


def test_matches_matrix_chain(motion):
    """Each joint's world transform equals the product of 4x4 matrices down its chain."""
    pos, rot = forward_kinematics(motion)
    sk = motion.skeleton
    for frame in (0, 137, 299):
        mats = []
        for j in range(sk.n_joints):
            m = np.eye(4)
            m[:3, :3] = Rotation.from_quat(motion.rotations[frame, j]).as_matrix()
            m[:3, 3] = motion.root_positions[frame] if sk.parents[j] < 0 else sk.offsets[j]
            mats.append(m if sk.parents[j] < 0 else mats[sk.parents[j]] @ m)
        world = np.stack(mats)
        np.testing.assert_allclose(pos[frame], world[:, :3, 3], atol=1e-9)
        np.testing.assert_allclose(
            Rotation.from_quat(rot[frame]).as_matrix(), world[:, :3, :3], atol=1e-9
        )


def test_bone_lengths_constant_and_feet_on_floor(motion):
    pos, rot = forward_kinematics(motion)
    sk = motion.skeleton
    child = np.arange(1, sk.n_joints)
    lengths = np.linalg.norm(pos[:, child] - pos[:, sk.parents[child]], axis=-1)
    np.testing.assert_allclose(
        lengths,
        np.broadcast_to(np.linalg.norm(sk.offsets[child], axis=-1), lengths.shape),
        atol=1e-9,
    )
    # Y is up and the dancer stands on a floor near y = 0 (modern dance also jumps)
    feet = canonical_positions(sk, pos, rot, ["left_toe", "right_toe", "left_ankle", "right_ankle"])
    lowest = feet[..., 1].min(axis=1)
    assert np.all(lowest > -0.12) and abs(np.median(lowest)) < 0.08
    # head above hips in most frames (modern dance bends over now and then)
    assert np.mean(pos[:, sk.index("head"), 1] > pos[:, sk.index("hips"), 1]) > 0.6


def test_canonical_joints_and_end_sites(motion):
    sk = motion.skeleton
    assert set(sk.canonical) == set(CANONICAL_JOINTS)
    pos, rot = forward_kinematics(motion)
    ends = end_site_positions(sk, pos, rot)
    assert set(ends) == set(sk.end_sites)
    for j, p in ends.items():
        np.testing.assert_allclose(
            np.linalg.norm(p - pos[:, j], axis=-1), np.linalg.norm(sk.end_sites[j]), atol=1e-9
        )
    toes = canonical_positions(sk, pos, rot, ["left_toe", "left_ankle"])
    # toes sit in front of and below the ankle, 5-25 cm away
    gap = np.linalg.norm(toes[:, 0] - toes[:, 1], axis=-1)
    assert np.all((gap > 0.05) & (gap < 0.25))


def test_skeleton_dict_round_trip_and_motion_basics(motion):
    import json

    from dancegraph.motion.skeleton import Motion, Skeleton

    sk = motion.skeleton
    back = Skeleton.from_dict(json.loads(json.dumps(sk.to_dict())))
    assert back == sk and back.canonical == sk.canonical
    assert back.index("left_wrist") == sk.index(sk.canonical["left_wrist"])
    with pytest.raises(KeyError):
        sk.index("no_such_joint")
    part = motion.slice(10, 40)
    assert part.n_frames == 30 and np.isclose(part.duration_s, 30 / motion.fps)
    np.testing.assert_array_equal(part.rotations, motion.rotations[10:40])
    with pytest.raises(ValueError):
        Motion(sk, 30.0, np.zeros((5, 3)), np.zeros((5, sk.n_joints - 1, 4)))
