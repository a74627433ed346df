"""Kinematic features on real salsa and on motions with known answers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dancegraph.motion import quat
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.features import (
    MAIN_JOINTS,
    bar_rhythm_features,
    joint_weights,
    kinematic_beats,
    kinematic_curve,
    phrase_positions,
    rhythm_curves,
    trajectory_curvature,
)
from dancegraph.motion.fk import canonical_positions, forward_kinematics


@pytest.fixture(scope="module")
def salsa(salsa_dir: Path):
    return read_bvh(salsa_dir / "60_05_scaled.bvh", fps=60).slice(0, 900)


def test_main_joints_are_canonical(salsa):
    assert len(MAIN_JOINTS) == 18 and len(set(MAIN_JOINTS)) == 18
    assert all(k in salsa.skeleton.canonical for k in MAIN_JOINTS)


def test_kinematic_curve_matches_independent_computation(salsa):
    curve = kinematic_curve(salsa, smooth_s=0.0)
    step = (
        np.stack(
            [
                (
                    Rotation.from_quat(salsa.rotations[t + 1])
                    * Rotation.from_quat(salsa.rotations[t]).inv()
                ).magnitude()
                for t in range(salsa.n_frames - 1)
            ]
        )
        * salsa.fps
    )
    w = joint_weights(salsa.skeleton)
    # the curve's frame t (0 < t < F-1) averages the steps either side of it
    expected = 0.5 * (step[1:] + step[:-1]) @ w
    np.testing.assert_allclose(curve[1:-1], expected, rtol=1e-6, atol=1e-6)
    assert np.isclose(w.sum(), 1.0) and w[0] == w.max()  # the root moves the most
    # a whole-body turn and shift does not change it
    turned = salsa.copy()
    turn = quat.from_y_angle(np.full(salsa.n_frames, 1.1))
    turned.rotations[:, 0] = quat.multiply(turn, salsa.rotations[:, 0])
    turned.root_positions = quat.rotate(turn, salsa.root_positions) + [3.0, 0.0, -2.0]
    np.testing.assert_allclose(kinematic_curve(turned), kinematic_curve(salsa), atol=1e-6)


def _paused_trajectory(fps: float, pauses_s: np.ndarray, duration_s: float) -> np.ndarray:
    """A (F, 2, 3) two-point trajectory that eases in and out between keyframes at ``pauses_s``."""
    t = np.arange(int(duration_s * fps)) / fps
    keys = np.concatenate([[0.0], pauses_s, [duration_s]])
    seg = np.clip(np.searchsorted(keys, t, side="right") - 1, 0, len(keys) - 2)
    u = (t - keys[seg]) / (keys[seg + 1] - keys[seg])
    ease = u * u * (3 - 2 * u)
    rng = np.random.default_rng(1)
    poses = rng.normal(scale=0.3, size=(len(keys), 2, 3))
    return poses[seg] + ease[:, None, None] * (poses[seg + 1] - poses[seg])


@pytest.mark.parametrize("fps", [30.0, 60.0, 120.0])
def test_kinematic_beats_find_known_pauses(fps):
    pauses = np.cumsum(np.full(12, 0.42)) + 0.1
    pos = _paused_trajectory(fps, pauses, pauses[-1] + 0.5)
    beats = kinematic_beats(pos, fps)
    assert len(beats) == len(pauses)
    # smoothing the speed shifts a minimum by at most ~20 ms where neighbouring moves differ
    np.testing.assert_allclose(beats, pauses, atol=0.025)


def test_kinematic_beats_on_salsa(salsa):
    pos, _ = forward_kinematics(salsa)
    beats = kinematic_beats(pos, salsa.fps)
    # salsa at ~168 BPM read at 60 fps: dancers pause on most beats, 60-200 minima a minute
    rate = len(beats) / salsa.duration_s * 60
    assert 60 < rate < 200
    assert np.all(np.diff(beats) >= 0.15 - 1e-9)


def test_trajectory_curvature_of_circles():
    fps = 60.0
    t = np.arange(240) / fps
    for radius in (0.05, 0.2, 0.8):
        w = 0.5 / radius  # 0.5 m/s along the circle: well above the still-point floor
        pts = np.stack(
            [radius * np.cos(w * t), np.full_like(t, 1.0), radius * np.sin(w * t)], axis=1
        )
        c = trajectory_curvature(pts, fps)[20:-20]
        expected = (1 / radius) / (1 / radius + 10.0)
        np.testing.assert_allclose(c, expected, rtol=0.05)
    line = np.stack([t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    assert trajectory_curvature(line, fps).max() < 1e-6


def test_bar_rhythm_features(salsa):
    curves = rhythm_curves(salsa)
    assert curves.shape == (5, salsa.n_frames)
    bar = bar_rhythm_features(salsa, 4.0, 5.43, curves)
    assert bar.shape == (5, 60) and bar.dtype == np.float32
    assert bar.min() >= 0.0 and bar.max() <= 1.0 and np.isclose(bar[0].max(), 1.0, atol=1e-3)
    # sample k of the bar is the curve at 4.0 + k * 1.43 / 60 s
    k = 30
    frame = (4.0 + k * 1.43 / 60) * salsa.fps
    lo = int(np.floor(frame))
    expect = curves[1, lo] + (frame - lo) * (curves[1, lo + 1] - curves[1, lo])
    assert np.isclose(bar[1, k], expect, atol=1e-5)
    # salsa feet are planted a fair share of a bar, but not all of it for both feet
    assert 0.0 < bar[3:].mean() < 1.0
    # without precomputed curves: the same numbers except where the contact floor differs
    alone = bar_rhythm_features(salsa, 4.0, 5.43)
    np.testing.assert_allclose(alone[:3], bar[:3], atol=1e-4)
    with pytest.raises(ValueError):
        bar_rhythm_features(salsa, 5.0, 5.0)


def test_phrase_positions(salsa):
    ph = phrase_positions(salsa, 2.0)
    assert ph.shape == (3, 18, 240) and ph.dtype == np.float32
    # sample k at 30 fps is source frame 120 + 2k at 60 fps (before canonicalisation)
    pos, rot = forward_kinematics(salsa)
    pts = canonical_positions(salsa.skeleton, pos, rot, MAIN_JOINTS)[120::2][:240]
    rel = pts - pts[0, 0] * [1, 0, 1]
    dist = np.linalg.norm(rel[:, :, None] - rel[:, None], axis=-1)
    got = ph.transpose(2, 1, 0)
    np.testing.assert_allclose(
        np.linalg.norm(got[:, :, None] - got[:, None], axis=-1), dist, atol=1e-4
    )
    np.testing.assert_allclose(got[..., 1], rel[..., 1], atol=1e-4)  # heights kept
    assert np.allclose(got[0, 0, [0, 2]], 0.0, atol=1e-5)
    # invariant to where on the floor and which way the phrase was danced
    moved = salsa.copy()
    turn = quat.from_y_angle(np.full(salsa.n_frames, -2.0))
    moved.rotations[:, 0] = quat.multiply(turn, salsa.rotations[:, 0])
    moved.root_positions = quat.rotate(turn, salsa.root_positions) + [1.5, 0.0, 4.0]
    np.testing.assert_allclose(phrase_positions(moved, 2.0), ph, atol=1e-4)
    # past the clip's end the last frame is held
    tail = phrase_positions(salsa, salsa.duration_s - 1.0)
    assert np.allclose(tail[:, :, -1], tail[:, :, -100])
