"""Seams on real salsa bars and on generated motion: where the cut falls, what the blend keeps,
and that every beat of a node lands on the song's beat of the same number."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dancegraph.metrics.smoothness import Reference, seam_report
from dancegraph.motion import quat
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.retime import NODE_BEATS, TURN_BEATS, node_warp, sample, song_phase
from dancegraph.motion.skeleton import Motion
from dancegraph.motion.stitch import (
    BLEND_MAX_S,
    BLEND_MIN_S,
    MAX_OFFSET_ACC,
    hand_over,
    limb_reach,
    seam_distance,
    seam_features,
    stitch,
)
from dancegraph.render import bar_frames

BEAT = 21.5  # frames per beat of a salsa bar at ~168 BPM read at 60 fps
FPS = 60.0


@pytest.fixture(scope="module")
def takes(salsa_dir: Path):
    return [
        read_bvh(salsa_dir / f, fps=60).slice(0, 1800)
        for f in ("60_02_scaled.bvh", "61_04_scaled.bvh")
    ]


def _piece(take: Motion, start: float, beat: float = BEAT) -> tuple[Motion, np.ndarray]:
    """The frames of ``take`` around the bar whose downbeat is frame ``start`` (beats ``beat``
    frames apart), and where its beats -2 .. 6 fall in them."""
    lo = int(np.floor(start - beat)) - 2
    hi = int(np.ceil(start + 5 * beat)) + 3
    return take.slice(lo, hi), start + NODE_BEATS * beat - lo


def _song(n_bars: int, bar_s: float = 1.6, wobble: float = 0.0, seed: int = 0) -> np.ndarray:
    """``(n_bars, 5)`` beat times of a song; ``wobble``: beats moved by up to this share of a
    beat (uneven beats within each bar)."""
    rng = np.random.default_rng(seed)
    beats = np.arange(4 * n_bars + 1) * bar_s / 4 + 0.5
    beats[1:-1] += rng.uniform(-wobble, wobble, beats.size - 2) * bar_s / 4
    return np.stack([beats[4 * b : 4 * b + 5] for b in range(n_bars)])


def _pose(m: Motion, k: int) -> np.ndarray:
    p, r = forward_kinematics(m.slice(k, k + 1))
    p = p[0] - p[0, 0] * [1.0, 0.0, 1.0]
    turn = quat.from_y_angle(-quat.heading_angle(r[0, 0]))
    return quat.rotate(np.broadcast_to(turn, p.shape[:-1] + (4,)), p)


@pytest.fixture(scope="module")
def pool(takes):
    """Bars every half bar of both takes (the previous beat and the next available)."""
    return [
        _piece(t, s) for t in takes for s in np.arange(2 * BEAT, t.n_frames - 6 * BEAT, 2 * BEAT)
    ]


def _graph_chain(pool, n: int, seed: int) -> list:
    """Bars chained as a motion graph links them: each next bar among the 5 whose downbeat pose
    is nearest the current bar's closing downbeat pose (heading and ground position out)."""
    starts = np.stack([_pose(m, int(round(b[2]))) for m, b in pool])
    ends = np.stack([_pose(m, int(round(b[6]))) for m, b in pool])
    rng = np.random.default_rng(seed)
    idx = [int(rng.integers(len(pool)))]
    for _ in range(n - 1):
        d = np.linalg.norm(starts - ends[idx[-1]], axis=-1).mean(axis=1)
        d[idx[-1]] = np.inf
        idx.append(int(rng.choice(np.argsort(d)[:5])))
    return [pool[i] for i in idx]


def test_seams_score_like_the_library_frames(takes, pool):
    """30 hand-overs between real salsa bars at 60 fps: no seam above the takes' own p99 of joint
    speed and acceleration, median seam percentile below 85; without the blend they pop."""
    ref = Reference.from_takes([forward_kinematics(t)[0] for t in takes], FPS)
    chain = _graph_chain(pool, 31, seed=1)
    bar_beats = _song(len(chain))
    frames = bar_frames(bar_beats[:, [0, 4]], FPS)
    dance, rep = stitch(chain, bar_beats, frames, FPS)
    assert dance.n_frames == frames[-1, 1] - frames[0, 0] and dance.fps == FPS
    seams = rep["cuts"][~rep["continuous"]] - frames[0, 0]
    assert len(seams) >= 20  # (the pool overlaps: a bar may be followed by its take's next)
    assert (np.abs(rep["cut_beats"]) <= 1.0 + 1e-9).all()
    assert np.abs(rep["cut_beats"]).max() > 0.2  # some cuts move off the bar line
    pos, _ = forward_kinematics(dance)
    good = seam_report(pos, FPS, seams, ref)
    assert good["flagged"] == 0 and good["median_percentile"] < 85.0
    raw, _ = stitch(chain, bar_beats, frames, FPS, blend=False)
    bad = seam_report(forward_kinematics(raw)[0], FPS, seams, ref)
    assert bad["flagged_share"] > 0.3 and bad["median_percentile"] > 95.0


def test_cut_falls_where_the_nodes_match(takes):
    """q's frames from half a beat after its downbeat are p's own frames half a beat after p's
    closing downbeat: the cut moves there (about +0.5 beat), where the two match exactly."""
    p_motion, p_beats = _piece(takes[0], 300.0)
    q_motion, q_beats = _piece(takes[1], 500.0)
    q_motion = q_motion.copy()
    splice = int(round(q_beats[2] + 0.5 * BEAT))  # q's frame at its beat 0.5
    src = int(round(p_beats[6] + 0.5 * BEAT))  # p's frame at its beat 4.5
    n = min(q_motion.n_frames - splice, p_motion.n_frames - src)
    q_motion.root_positions[splice : splice + n] = p_motion.root_positions[src : src + n]
    q_motion.rotations[splice : splice + n] = p_motion.rotations[src : src + n]
    song = 1.0 + np.arange(9) * BEAT / FPS  # the source's own tempo
    bar_beats = np.stack([song[:5], song[4:]])
    frames = bar_frames(bar_beats[:, [0, 4]], FPS)
    dance, rep = stitch([(p_motion, p_beats), (q_motion, q_beats)], bar_beats, frames, FPS)
    assert not rep["continuous"][0]
    assert 0.45 <= rep["cut_beats"][0] <= 0.75
    assert rep["distance"][0] < 1e-3


def test_hand_over_continues_pose_and_velocity(pool):
    """At the cut the dance shows p's pose (every joint within 1 mm) moving at about p's velocity
    (the jump is a fifth of the unblended one), and q's own motion after the blend."""
    (pm, pb), (qm, qb) = pool[3], pool[40]
    c = int(round(pb[6]))  # p's closing downbeat
    k = int(round(qb[2]))  # q's downbeat
    before = pm.slice(c - 1, c + 2)
    after = qm.slice(k - 1, k + 2)
    segment = qm.slice(k, qm.n_frames)
    joined, (turn, pivot, target), n = hand_over(before, after, segment)
    assert 1 <= n < segment.n_frames
    p_pos, _ = forward_kinematics(pm.slice(c - 1, c + 2))
    j_pos, _ = forward_kinematics(joined.slice(0, 2))
    np.testing.assert_allclose(j_pos[0], p_pos[1], atol=1e-3)
    v_p = (p_pos[2] - p_pos[0]) / 2 * FPS
    jump = np.linalg.norm((j_pos[1] - p_pos[0]) / 2 * FPS - v_p, axis=-1).max()
    # after the blend: q's own pose (turned and moved on the ground only)
    tail = joined.rotations[n:, 1:]
    np.testing.assert_allclose(np.abs(np.sum(tail * segment.rotations[n:, 1:], -1)), 1.0, atol=1e-9)
    # the same hand-over without the blend only aligns the root: the pose jumps
    raw, _, none = hand_over(before, after, segment, blend=False)
    assert none == 0
    r_pos, _ = forward_kinematics(raw.slice(0, 2))
    assert np.abs(r_pos[0] - p_pos[1]).max() > 0.02
    raw_jump = np.linalg.norm((r_pos[1] - p_pos[0]) / 2 * FPS - v_p, axis=-1).max()
    assert jump < 0.2 * raw_jump


def _turned(motion: Motion, turn: float, pivot: np.ndarray, target: np.ndarray) -> Motion:
    q = quat.from_y_angle(np.float64(turn))
    rel = motion.root_positions - pivot * [1.0, 0.0, 1.0]
    root = quat.rotate(np.broadcast_to(q, rel.shape[:-1] + (4,)), rel) + target * [1.0, 0.0, 1.0]
    rot = motion.rotations.copy()
    rot[:, 0] = quat.multiply(np.broadcast_to(q, rot[:, 0].shape), rot[:, 0])
    return Motion(motion.skeleton, motion.fps, root, rot)


def _hand_over_written_out(before, after, segment, blend, reach):
    """The hand-over of one seam written out step by step (module docstring of stitch): turn
    and move q onto p's ground at the cut, then decay the offsets of the root and of every
    joint along Bollo's quintic, each over the shortest length its acceleration bound allows."""
    fps = segment.fps
    turn = float(
        quat.heading_angle(before.rotations[1, 0]) - quat.heading_angle(after.rotations[1, 0])
    )
    pivot, target = after.root_positions[1].copy(), before.root_positions[1].copy()
    segment = _turned(segment, turn, pivot, target)
    if not blend or segment.n_frames < 2:
        return segment, (turn, pivot, target), 0
    q3 = _turned(after, turn, pivot, target)
    p_root, q_root = before.root_positions, q3.root_positions
    x0 = p_root[1] - q_root[1]
    v0 = 0.5 * ((p_root[2] - p_root[0]) - (q_root[2] - q_root[0]))
    p_rot = before.rotations
    q_rot = quat.same_hemisphere(q3.rotations, p_rot)

    def rotvec(a, b):  # the rotation taking b to a
        return quat.to_rotvec(quat.multiply(a, quat.conjugate(b)))

    x0r = rotvec(p_rot[1], q_rot[1])
    v0r = 0.5 * (rotvec(p_rot[2], p_rot[0]) - rotvec(q_rot[2], q_rot[0]))
    least = max(1, int(round(BLEND_MIN_S * fps)))
    top = max(least, min(segment.n_frames, int(round(BLEND_MAX_S * fps))))

    def length(size, speed):
        t = 8.0 * speed + np.sqrt(64.0 * speed**2 + 80.0 * MAX_OFFSET_ACC * size)
        return np.clip(np.ceil(t / (2.0 * MAX_OFFSET_ACC) * fps), least, top)

    def decay(x0, v0, T, n):
        T = np.broadcast_to(T, x0.shape)
        t = np.arange(n, dtype=float).reshape((-1,) + (1,) * x0.ndim)
        a0 = (-8.0 * v0 * T - 20.0 * x0) / T**2
        A = -(a0 * T**2 + 6.0 * v0 * T + 12.0 * x0) / (2.0 * T**5)
        B = (3.0 * a0 * T**2 + 16.0 * v0 * T + 30.0 * x0) / (2.0 * T**4)
        C = -(3.0 * a0 * T**2 + 12.0 * v0 * T + 20.0 * x0) / (2.0 * T**3)
        x = A * t**5 + B * t**4 + C * t**3 + 0.5 * a0 * t**2 + v0 * t + x0
        return np.where(t < T, x, 0.0)

    reach = np.maximum(reach, 0.1)[:, None]
    n_pos = length(np.linalg.norm(x0), np.linalg.norm(v0) * fps)
    n_rot = length(
        np.linalg.norm(x0r, axis=-1, keepdims=True) * reach,
        np.linalg.norm(v0r, axis=-1, keepdims=True) * reach * fps,
    )
    n = int(min(segment.n_frames, max(float(n_pos), float(n_rot.max()))))
    root = segment.root_positions.copy()
    root[:n] += decay(x0, v0, n_pos, n)
    rot = segment.rotations.copy()
    offsets = quat.from_rotvec(decay(x0r, v0r, n_rot, n))
    rot[:n] = quat.normalize(quat.multiply(offsets, quat.same_hemisphere(rot[:n], offsets)))
    return Motion(segment.skeleton, fps, root, rot), (turn, pivot, target), n


def _stitch_bar_by_bar(pieces, bar_beats, frames, cuts, flow):
    """The dance ``stitch`` makes on the cuts it chose, one bar and one hand-over at a time:
    each bar's segment sampled alone, then handed over (``_hand_over_written_out``) from the
    previous bar's node, on the ground the previous hand-over put that one."""
    phase = song_phase(bar_beats)

    def source(b, k):
        return node_warp(pieces[b][1])(phase(np.asarray(k) / FPS) - 4.0 * b)

    bounds = np.concatenate([[frames[0, 0]], cuts, [frames[-1, 1]]])
    reach = limb_reach(pieces[0][0].skeleton)
    roots, rots, blends, transform = [], [], [], None
    for b, (motion, _) in enumerate(pieces):
        seg = sample(motion, source(b, np.arange(bounds[b], bounds[b + 1])))
        if b > 0:
            c = int(bounds[b])
            prev = sample(pieces[b - 1][0], source(b - 1, np.arange(c - 1, c + 2)))
            if transform is not None:
                prev = _turned(prev, *transform)
            now = sample(motion, source(b, np.arange(c - 1, c + 2)))
            prev.fps = now.fps = seg.fps = FPS
            seg, transform, n = _hand_over_written_out(prev, now, seg, not flow[b - 1], reach)
            blends.append(n)
        roots.append(seg.root_positions)
        rots.append(seg.rotations)
    return np.concatenate(roots), np.concatenate(rots), np.asarray(blends)


def test_stitch_is_the_bar_by_bar_dance(pool, takes):
    """``stitch`` samples every bar in one go and hands over at all seams at once: the dance is
    the one made bar by bar and seam by seam, written out (within 1e-9: positions in m,
    quaternion components), on graph-like chains of real bars with uneven song beats and on a
    take that continues (no seam); ``hand_over`` alone is the written-out hand-over too."""
    take = takes[0]
    starts = 200.0 + 4 * BEAT * np.arange(4)
    cases = [
        (_graph_chain(pool, 25, seed=2), _song(25, wobble=0.1, seed=5)),
        (_graph_chain(pool, 12, seed=3), _song(12, bar_s=1.4)),
        (
            [_piece(take, s) for s in starts] + _graph_chain(pool, 3, seed=4),
            _song(7, bar_s=4 * BEAT / FPS),
        ),
    ]
    for pieces, bar_beats in cases:
        frames = bar_frames(bar_beats[:, [0, 4]], FPS)
        dance, rep = stitch(pieces, bar_beats, frames, FPS)
        assert rep["continuous"].any() and (~rep["continuous"]).sum() >= 3
        root, rot, blends = _stitch_bar_by_bar(
            pieces, bar_beats, frames, rep["cuts"], rep["continuous"]
        )
        np.testing.assert_allclose(dance.root_positions, root, rtol=0, atol=1e-9)
        np.testing.assert_allclose(dance.rotations, rot, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(rep["blend_frames"], blends)
        # the cut search's distance (main joints alone) is the whole skeleton's at the cut
        phase = song_phase(bar_beats)
        for b in range(1, len(pieces)):
            k = np.arange(rep["cuts"][b - 1] - 1, rep["cuts"][b - 1] + 2)
            feats = []
            for i in (b - 1, b):
                m, beats = pieces[i]
                x = sample(m, node_warp(beats)(phase(k / FPS) - 4.0 * i))
                feats.append(
                    seam_features(m.skeleton, x.root_positions[None], x.rotations[None], 1 / FPS)
                )
            whole = seam_distance(feats[0][0], feats[1][0], feats[0][1])[0, 0]
            assert rep["distance"][b - 1] == pytest.approx(whole, abs=1e-9)
    (pm, pb), (qm, qb) = pool[5], pool[31]
    c, k = int(round(pb[6])), int(round(qb[2]))
    before, after, segment = pm.slice(c - 1, c + 2), qm.slice(k - 1, k + 2), qm.slice(k, k + 40)
    for blend in (True, False):
        got, transform, n = hand_over(before, after, segment, blend=blend)
        want, transform_w, n_w = _hand_over_written_out(
            before, after, segment, blend, limb_reach(segment.skeleton)
        )
        assert n == n_w and (n > 0) == blend and transform[0] == transform_w[0]
        np.testing.assert_allclose(got.root_positions, want.root_positions, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.rotations, want.rotations, rtol=0, atol=1e-9)


def test_a_take_continuing_is_no_seam(takes):
    """Consecutive bars of one take: no cut moves, nothing is blended, the dance is the take."""
    take = takes[0]
    starts = 200.0 + 4 * BEAT * np.arange(6)
    pieces = [_piece(take, s) for s in starts]
    bar_beats = (200.0 + BEAT * np.arange(25)) / FPS
    bar_beats = np.stack([bar_beats[4 * b : 4 * b + 5] for b in range(6)])
    frames = bar_frames(bar_beats[:, [0, 4]], FPS)
    dance, rep = stitch(pieces, bar_beats, frames, FPS)
    assert rep["continuous"].all() and (rep["cut_beats"] == 0).all()
    assert (rep["blend_frames"] == 0).all()
    np.testing.assert_allclose(
        dance.root_positions, take.root_positions[frames[0, 0] : frames[-1, 1]], atol=1e-6
    )


def _clock(n_frames: int, fps: float) -> Motion:
    """Generated motion whose frame index can be read back: joint 1 turns about X by 0.001 rad
    per frame (frame f shows angle f / 1000)."""
    from dancegraph.motion.demo import demo_skeleton

    sk = demo_skeleton()
    rot = quat.identity((n_frames, sk.n_joints))
    rot[:, 1] = quat.from_rotvec(np.arange(n_frames)[:, None] * [0.001, 0.0, 0.0])
    return Motion(sk, fps, np.zeros((n_frames, 3)), rot)


def _shown(motion: Motion) -> np.ndarray:
    return quat.to_rotvec(motion.rotations[:, 1])[:, 0] * 1000.0


@pytest.mark.parametrize("wobble", [0.0, 0.15])
def test_beats_land_on_the_song_beats(wobble):
    """Every source beat lands on the song's beat of the same number (uneven song beats and
    uneven source beats), and the warp's speed has no jump at the bar lines."""
    rng = np.random.default_rng(3)
    n_bars = 6
    src_fps = 120.0
    beats_src = np.cumsum(rng.uniform(40.0, 52.0, 4 * n_bars + 5))  # uneven, sub-frame
    clock = _clock(int(beats_src[-1]) + 20, src_fps)
    pieces = []
    for b in range(n_bars):
        own = beats_src[4 * b : 4 * b + 9]  # beats -2 .. 6 of bar b
        lo = int(np.floor(own[1])) - 2
        hi = int(np.ceil(own[7])) + 3
        pieces.append((clock.slice(lo, hi), own - lo))
    song = _song(n_bars, bar_s=1.9, wobble=wobble, seed=4)
    frames = bar_frames(song[:, [0, 4]], FPS)
    dance, rep = stitch(pieces, song, frames, FPS)
    assert rep["continuous"].all()  # one take, bar after bar
    shown = _shown(dance)  # the source frame each output frame shows
    t = (np.arange(frames[0, 0], frames[-1, 1])) / FPS
    for b in range(n_bars):
        for j in range(4):
            got = np.interp(song[b, j], t, shown)
            assert got == pytest.approx(beats_src[4 * b + j + 2], abs=0.05)
    rate = np.diff(shown)  # source frames per output frame: smooth, no jump at the bar lines
    assert (rate > 0).all()
    # the rate turns from one beat interval's to the next within TURN_BEATS of the beat (a
    # cubic, steepest on the beat: here up to a quarter of the rate a frame with beats 15 % off;
    # the salsa takes' own speed changes by more than 0.3 of its median in 2 % of their frames,
    # docs/rendering.md)
    assert np.abs(np.diff(rate)).max() < (0.1 if wobble == 0 else 0.3) * np.median(rate)
    # and holds between the turns: straight from TURN_BEATS after a beat to TURN_BEATS before
    # the next (well inside: 0.1 beat more either side)
    phase = song_phase(song)(t[:-1])
    mid = np.abs((phase % 1.0) - 0.5) < 0.5 - TURN_BEATS - 0.1
    change = np.abs(np.diff(rate))[mid[:-1] & mid[1:]]
    assert change.max() < 1e-6 * np.median(rate)


def test_seam_distance_is_zero_for_the_same_frames_and_grows_with_the_offset(takes):
    take = takes[0]
    run = take.slice(100, 110)
    root, rot = run.root_positions[None], run.rotations[None]
    a, blocks = seam_features(take.skeleton, root, rot, 1.0 / FPS)
    assert a.shape == (1, 8, sum(blocks)) and len(blocks) == 3
    # turned and moved on the ground: the same features (each in its own heading frame)
    turned = run.copy()
    q = quat.from_y_angle(np.float64(1.0))
    turned.root_positions = quat.rotate(np.broadcast_to(q, (10, 4)), run.root_positions) + [
        2.0,
        0,
        1.0,
    ]
    turned.rotations[:, 0] = quat.multiply(np.broadcast_to(q, (10, 4)), run.rotations[:, 0])
    b, _ = seam_features(
        take.skeleton, turned.root_positions[None], turned.rotations[None], 1 / FPS
    )
    assert seam_distance(a, b, blocks).max() < 1e-4
    later = take.slice(104, 114)
    c, _ = seam_features(take.skeleton, later.root_positions[None], later.rotations[None], 1 / FPS)
    d = seam_distance(a, c, blocks)[0]
    assert d.min() > 0.05


def test_bad_input_is_rejected(takes, modern_dir: Path):
    piece = _piece(takes[0], 300.0)
    song = _song(2)
    frames = bar_frames(song[:, [0, 4]], FPS)
    with pytest.raises(ValueError):
        stitch([], song, frames, FPS)
    with pytest.raises(ValueError):
        stitch([piece], song, frames, FPS)
    other = read_bvh(modern_dir / "05_02.bvh", scale=0.056444)
    with pytest.raises(ValueError):
        stitch([piece, (other, piece[1])], song, frames, FPS)
