"""Stitching real salsa bars: root alignment and seams as smooth as the data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dancegraph.motion import quat
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.retime import retime
from dancegraph.motion.stitch import frame_jumps, seam_jumps, stitch

BAR = 86  # one salsa bar at ~168 BPM read at 60 fps


@pytest.fixture(scope="module")
def takes(salsa_dir: Path):
    return [
        read_bvh(salsa_dir / f, fps=60).slice(0, 1800)
        for f in ("60_02_scaled.bvh", "61_04_scaled.bvh")
    ]


@pytest.fixture(scope="module")
def pool(takes):
    return [t.slice(s, s + BAR) for t in takes for s in range(0, t.n_frames - BAR, 43)]


def _pose(m, k):
    p, r = forward_kinematics(m.slice(k, k + 1))
    p = p[0] - p[0, 0] * [1.0, 0.0, 1.0]
    turn = quat.from_y_angle(-quat.heading_angle(r[0, 0]))
    return quat.rotate(np.broadcast_to(turn, p.shape[:-1] + (4,)), p)


def _graph_chain(pool, n, seed):
    """Bars chained as a motion graph links them: each next bar among the 5 whose first pose is
    nearest the current bar's last pose (heading and ground position factored out)."""
    starts = np.stack([_pose(b, 0) for b in pool])
    ends = np.stack([_pose(b, b.n_frames - 1) for b in pool])
    rng = np.random.default_rng(seed)
    idx = [int(rng.integers(len(pool)))]
    for _ in range(n - 1):
        d = np.linalg.norm(starts - ends[idx[-1]], axis=-1).mean(axis=1)
        d[idx[-1]] = np.inf
        idx.append(int(rng.choice(np.argsort(d)[:5])))
    return [pool[i] for i in idx]


def _seam_window_ratio(bars, method):
    source_p99 = np.percentile(
        np.concatenate([frame_jumps(forward_kinematics(b)[0]).ravel() for b in bars]), 99
    )
    motion, seams = stitch(bars, method=method)
    assert motion.n_frames == sum(b.n_frames for b in bars)
    np.testing.assert_array_equal(seams, np.cumsum([b.n_frames for b in bars])[:-1])
    pos, _ = forward_kinematics(motion)
    jumps = frame_jumps(pos)
    w = int(round(0.3 * bars[0].fps))  # the blend on either side of a seam
    # the blend window: both sides of a split seam, the frames after an inertialized one
    before = w if method == "split" else 0
    around = np.concatenate([jumps[s - 1 - before : s + w] for s in seams])
    at_seam = seam_jumps(pos, seams)
    return np.percentile(around, 99) / source_p99, np.percentile(at_seam, 99) / source_p99


@pytest.mark.parametrize("fps", [30.0, 60.0])
@pytest.mark.parametrize("method", ["split", "inertialize"])
def test_seams_as_smooth_as_the_data(pool, fps, method):
    """p99 per-frame joint jump around seams <= 1.2 x the source clips' own p99."""
    bars = _graph_chain(pool, 30, seed=1)
    if fps != 60.0:
        bars = [retime(b, int(round(BAR * fps / 60)), fps) for b in bars]
    around, at_seam = _seam_window_ratio(bars, method)
    assert around <= 1.2 and at_seam <= 1.2
    # without blending the seams pop
    raw, seams = stitch(bars, blend_frames=0)
    raw_pos, _ = forward_kinematics(raw)
    ref = np.percentile(
        np.concatenate([frame_jumps(forward_kinematics(b)[0]).ravel() for b in bars]), 99
    )
    assert np.percentile(seam_jumps(raw_pos, seams), 99) > 2.0 * ref


def test_root_alignment_carries_position_and_heading(pool):
    a, b = pool[3], pool[20]
    motion, seams = stitch([a, b], blend_frames=0)
    s = int(seams[0])
    root = motion.root_positions
    # ground position continues at the previous velocity; height stays the clip's own
    np.testing.assert_allclose(root[s, [0, 2]], (2 * root[s - 1] - root[s - 2])[[0, 2]], atol=1e-9)
    np.testing.assert_allclose(root[s:, 1], b.root_positions[:, 1], atol=1e-12)
    h = quat.heading_angle(motion.rotations[:, 0])
    turn = np.angle(np.exp(1j * (h[s - 1] - h[s - 2])))
    assert abs(np.angle(np.exp(1j * (h[s] - (h[s - 1] + turn))))) < 1e-9
    # the clip's own path is kept: same shape, turned and moved
    d_src = np.linalg.norm(np.diff(b.root_positions[:, [0, 2]], axis=0), axis=-1)
    d_out = np.linalg.norm(np.diff(root[s:, [0, 2]], axis=0), axis=-1)
    np.testing.assert_allclose(d_out, d_src, atol=1e-9)


def test_continuous_halves_restitch_to_the_original(takes):
    take = takes[0].slice(200, 500)
    motion, _ = stitch([take.slice(0, 150), take.slice(150, 300)])
    p0, _ = forward_kinematics(take)
    p1, _ = forward_kinematics(motion)
    assert np.abs(p1 - p0).max() < 0.02  # only the one-frame extrapolation error is blended away
    np.testing.assert_allclose(p1[:100], p0[:100], atol=1e-12)  # far from the seam: untouched


def test_blend_leaves_the_clip_after_the_window(pool):
    motion, seams = stitch([pool[0], pool[9]], blend_frames=10)
    tail = motion.rotations[seams[0] + BAR - 1, 1:]
    np.testing.assert_allclose(
        np.abs(np.sum(tail * pool[9].rotations[-1, 1:], axis=-1)), 1.0, atol=1e-12
    )


def test_rejects_mixed_clips(pool, modern_dir: Path):
    other = read_bvh(modern_dir / "05_02.bvh", scale=0.056444).slice(0, 50)
    with pytest.raises(ValueError):
        stitch([pool[0], other])
    with pytest.raises(ValueError):
        stitch([pool[0], retime(pool[1], 43, 30.0)])
    with pytest.raises(ValueError):
        stitch([])
