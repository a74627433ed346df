"""Foot contacts and foot-skate cleanup on real salsa and modern dance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dancegraph.motion import quat
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.contacts import clean_foot_skate, foot_contacts, foot_points, two_bone_ik
from dancegraph.motion.fk import forward_kinematics


@pytest.fixture(scope="module")
def salsa(salsa_dir: Path):
    return read_bvh(salsa_dir / "61_09_scaled.bvh", fps=60).slice(300, 1200)


@pytest.fixture(scope="module")
def modern(modern_dir: Path):
    return read_bvh(modern_dir / "05_03.bvh", scale=0.056444)


def test_contacts_on_salsa(salsa):
    pos, rot = forward_kinematics(salsa)
    c = foot_contacts(pos, salsa.fps, salsa.skeleton, rot)
    assert c.shape == (salsa.n_frames, 2) and c.dtype == bool
    # a salsa dancer has a foot on the floor most of the time, but steps with each foot
    assert 0.1 < c[:, 0].mean() < 0.95 and 0.1 < c[:, 1].mean() < 0.95
    assert (c[:, 0] | c[:, 1]).mean() > 0.7
    pts = foot_points(pos, salsa.skeleton, rot)
    speed = np.linalg.norm(np.gradient(pts, axis=0), axis=-1) * salsa.fps  # (F, 2, 2)
    slow = speed.min(axis=2)
    for side in range(2):
        assert np.median(slow[c[:, side], side]) < np.median(slow[~c[:, side], side])


def test_lifted_body_has_no_contacts(salsa):
    lifted = salsa.copy()
    lifted.root_positions[200:400, 1] += 0.4  # both feet 40 cm off the floor
    pos, rot = forward_kinematics(lifted)
    c = foot_contacts(pos, lifted.fps, lifted.skeleton, rot)
    assert not c[205:395].any()
    assert c[:195].any() and c[405:].any()


def test_two_bone_ik_reaches_targets(salsa):
    pos, rot = forward_kinematics(salsa.slice(0, 200))
    sk = salsa.skeleton
    h, k, a = (sk.index(sk.canonical[n]) for n in ("left_hip", "left_knee", "left_ankle"))
    rng = np.random.default_rng(0)
    target = pos[:, a] + rng.normal(scale=0.05, size=(200, 3))
    hip_w, knee_w = two_bone_ik(pos[:, h], pos[:, k], pos[:, a], target, rot[:, h], rot[:, k])
    new_knee = pos[:, h] + quat.rotate(hip_w, sk.offsets[k])
    new_ankle = new_knee + quat.rotate(knee_w, sk.offsets[a])
    reach = np.linalg.norm(target - pos[:, h], axis=-1)
    ok = reach < np.linalg.norm(sk.offsets[k]) + np.linalg.norm(sk.offsets[a]) - 1e-3
    assert ok.mean() > 0.8
    np.testing.assert_allclose(new_ankle[ok], target[ok], atol=1e-6)
    # the knee keeps bending the same way (forward of the hip→ankle line)
    before = np.cross(pos[:, a] - pos[:, h], pos[:, k] - pos[:, h])
    after = np.cross(new_ankle - pos[:, h], new_knee - pos[:, h])
    assert np.mean(np.sum(before * after, axis=-1) > 0) > 0.95


@pytest.mark.parametrize("which", ["salsa", "modern"])
def test_cleanup_removes_sliding(which, salsa, modern):
    motion = salsa if which == "salsa" else modern
    cleaned, report = clean_foot_skate(motion)
    assert report["contact_frames"][0] > 0 and report["contact_frames"][1] > 0
    assert report["sliding_before_m_s"] > 0.02  # real mocap slides a little
    assert report["sliding_after_m_s"] < 0.05 * report["sliding_before_m_s"]
    assert report["sliding_after_m"] < 0.05 * report["sliding_before_m"]
    assert 0.0 < report["max_correction_m"] < 0.15
    p0, _ = forward_kinematics(motion)
    p1, _ = forward_kinematics(cleaned)
    sk = motion.skeleton
    legs = set()
    for side in ("left", "right"):
        for part in ("knee", "ankle", "toe"):
            j = sk.index(sk.canonical[f"{side}_{part}"])
            legs.add(j)
            legs.update(i for i in range(sk.n_joints) if j in _ancestors(sk.parents, i))
    others = [j for j in range(sk.n_joints) if j not in legs]
    np.testing.assert_allclose(p1[:, others], p0[:, others], atol=1e-9)  # upper body untouched
    np.testing.assert_array_equal(cleaned.root_positions, motion.root_positions)
    # no pops: per-frame joint jumps stay as smooth as the source
    jump0 = np.linalg.norm(np.diff(p0, axis=0), axis=-1)
    jump1 = np.linalg.norm(np.diff(p1, axis=0), axis=-1)
    assert np.percentile(jump1, 99) <= 1.1 * np.percentile(jump0, 99)


def _ancestors(parents: np.ndarray, j: int) -> set[int]:
    out = set()
    while parents[j] >= 0:
        j = int(parents[j])
        out.add(j)
    return out


def test_unmapped_skeleton_is_a_clear_error(salsa):
    from dancegraph.errors import DanceGraphError
    from dancegraph.motion.skeleton import Motion, Skeleton

    sk = salsa.skeleton
    bare = Skeleton(
        sk.names, sk.parents, sk.offsets, sk.channels, sk.end_sites, canonical={"hips": "hip"}
    )
    motion = Motion(bare, salsa.fps, salsa.root_positions[:50], salsa.rotations[:50])
    pos, rot = forward_kinematics(motion)
    with pytest.raises(DanceGraphError) as info:
        foot_contacts(pos, motion.fps, bare, rot)
    assert info.value.code == "skeleton_unmapped" and "left_ankle" in info.value.message
    with pytest.raises(DanceGraphError):
        foot_contacts(pos, motion.fps, bare)


def test_correction_glides_between_close_contact_runs(salsa):
    """Two contact runs two frames apart, the foot sliding through both: each run is pinned to
    its own spot, so the correction changes by ~0.3 m between them; it glides over the gap
    instead of switching in one frame (which moved the foot by the whole change at once)."""
    motion = salsa.slice(0, 120).copy()
    motion.root_positions[:, 0] += 0.5 * np.arange(motion.n_frames) / motion.fps  # 0.5 m/s
    contacts = np.zeros((motion.n_frames, 2), dtype=bool)
    contacts[20:50, 0] = True
    contacts[52:90, 0] = True
    cleaned, report = clean_foot_skate(motion, contacts)
    sk = motion.skeleton
    p, r = forward_kinematics(cleaned)
    after = foot_points(p, sk, r)[:, 0, 0, [0, 2]]
    p, r = forward_kinematics(motion)
    before = foot_points(p, sk, r)[:, 0, 0, [0, 2]]
    corr = after - before
    change = np.linalg.norm(corr[52] - corr[49])
    assert change > 0.2
    steps = np.linalg.norm(np.diff(corr[49:53], axis=0), axis=-1)
    assert steps.max() < 0.5 * change
