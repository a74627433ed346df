"""Accent anchors: a take's beats moved onto its own pauses, and the rendered dance's pauses on
the song's beats.

Takes: demo clips that pause on every beat, time-warped so their pauses sit off a steady grid
(a dancer who is early and late against the music's beat), the steady grid given as their bars.
"""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.graph.artifact import graph_from_arrays
from dancegraph.graph.build import BarSet, BuildParams, build_arrays, take_bars
from dancegraph.metrics.beats import phase_concentration
from dancegraph.motion.demo import DemoClip, make_clip
from dancegraph.motion.features import kinematic_beats
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.retime import Warp, accent_anchors, sample
from dancegraph.motion.skeleton import Motion
from dancegraph.render import STOP_MAX_SPEED, beat_timing, render_path
from dancegraph.rhythm.motion import motion_stops

ON_EVERY_BEAT = "01010101"  # slots 0, 2, 4, 6: a pause on each beat


def _off_grid_take(seed: int, tempo: float, jitter: float):
    """``(motion, bar_beats (n, 5) s, pauses (K,) s)``: a clip pausing on every beat of its
    steady grid, warped so the pause of grid beat k sits ``jitter`` beats early or late
    (random sign per beat); the grid returned is the steady one."""
    rng = np.random.default_rng(seed)
    motion, bars, _ = make_clip(DemoClip(f"t{seed}", "groove", tempo, 6, (ON_EVERY_BEAT,)), rng)
    bars = np.asarray(bars, dtype=float)
    grid = np.unique(bars.reshape(-1))
    beat = 60.0 / tempo
    pauses = grid + jitter * beat * rng.choice([-1.0, 1.0], grid.size)
    pauses[0], pauses[-1] = grid[0], grid[-1]  # the take's ends stay
    t = np.arange(motion.n_frames) / motion.fps
    warped = sample(motion, Warp(pauses, grid)(t) * motion.fps)
    warped.fps = motion.fps
    return warped, bars, pauses[1:-1]


def _pauses(motion) -> np.ndarray:
    return kinematic_beats(forward_kinematics(motion)[0], motion.fps)


def test_anchors_move_the_grid_beats_onto_the_pauses():
    motion, bars, pauses = _off_grid_take(1, 110.0, 0.15)
    found = _pauses(motion)
    grid = np.unique(bars.reshape(-1))[1:-1]
    beat = 60.0 / 110.0
    # the pauses are detected where they were put, 0.15 beat off the grid
    assert np.abs(found[:, None] - pauses[None, :]).min(axis=0).max() < 1.5 / motion.fps
    assert np.abs(np.abs(found[:, None] - grid[None, :]).min(axis=0) - 0.15 * beat).max() < 0.02

    anchored = accent_anchors(bars, found, tolerance=0.25, max_speed=1.5)
    moved = np.unique(anchored.reshape(-1))[1:-1]
    assert np.abs(moved - pauses).max() < 1.5 / motion.fps
    # adjoining bars still share their downbeats, and every bar's beats increase
    assert np.array_equal(anchored[:-1, 4], anchored[1:, 0])
    assert np.all(np.diff(anchored, axis=1) > 0)
    # off by more than the tolerance: the grid stays
    assert np.allclose(accent_anchors(bars, found, tolerance=0.1, max_speed=1.5), bars)


def test_anchors_keep_the_speed_bound():
    grid = np.arange(17) * 0.5  # 120 BPM, 4 bars
    bars = np.stack([grid[4 * b : 4 * b + 5] for b in range(4)])
    pauses = grid + 0.12 * np.where(np.arange(grid.size) % 2, 1.0, -1.0)  # ±0.24 beat, alternating
    for limit in (1.2, 1.5, 2.0):
        anchored = accent_anchors(bars, pauses, tolerance=0.3, max_speed=limit)
        ratio = np.diff(anchored, axis=1) / np.diff(bars, axis=1)
        assert ratio.max() <= limit + 1e-9 and ratio.min() >= 1.0 / limit - 1e-9
        assert np.array_equal(anchored[:-1, 4], anchored[1:, 0])
    # a loose bound keeps every anchor: each beat on its pause
    assert np.allclose(np.unique(accent_anchors(bars, pauses, 0.3, 2.0)), pauses)
    assert np.array_equal(accent_anchors(bars, np.zeros(0)), bars)


@pytest.mark.parametrize("bad", [{"accent_tolerance": 0.5}, {"accent_max_speed": 1.0}])
def test_anchor_params_are_checked(bad):
    with pytest.raises(ValueError):
        BuildParams(**bad)


def _graph(takes, anchors: bool):
    rows = []
    for motion, bars, _ in takes:
        if anchors:  # as bars_from_dataset does
            bars = accent_anchors(bars, motion_stops(motion))
        frames = np.round(bars[:, [0, 4]] * motion.fps).astype(np.int64)
        rows.append((motion, bars, np.arange(len(bars)), [ON_EVERY_BEAT] * len(bars), frames))
    clips = [f"t{k}" for k in range(len(takes))]
    bars = BarSet.from_takes(takes[0][0].skeleton, clips, rows)
    arrays, ids, manifest = build_arrays(bars, BuildParams(blend_ratio=0, shuffle_ratio=0))
    g = graph_from_arrays(arrays, dict(manifest, name="anchors", version="test"))
    g.node_ids[:] = ids
    g._index = {n: i for i, n in enumerate(ids)}
    return g


def test_rendered_pauses_land_on_the_song_beats():
    """Every bar of the takes danced in turn on a song at another tempo with uneven beats: the
    dance's kinematic beats (minima of mean joint speed) gather on the song's beats (R >= 0.8)
    with the build's anchors (on the takes' Shiratori stops) alone, with the renderer's
    stops on the beats (``beat_timing``'s first step, its beat accent off) alone, and with
    both; with neither they do not."""
    takes = [_off_grid_take(seed, tempo, 0.2) for seed, tempo in ((2, 104.0), (3, 118.0))]
    rng = np.random.default_rng(7)
    song_beats = np.cumsum(np.r_[1.0, 0.5 + rng.uniform(-0.03, 0.03, 48)])
    bar_beats = np.stack([song_beats[4 * b : 4 * b + 5] for b in range(12)])
    fps = 60.0
    r = {}
    for anchors in (False, True):
        g = _graph(takes, anchors)
        nodes = [f"t{b // 6 % 2}:{b % 6}" for b in range(12)]
        for land in (False, True):
            dance, _ = render_path(
                g, nodes, bar_beats, fps, foot_cleanup=False, land_stops=land, beat_accent=0.0
            )
            r[anchors, land] = phase_concentration(song_beats[:49], _pauses(dance))[0]
    assert r[True, False] >= 0.8
    assert r[False, True] >= 0.8
    assert r[True, True] >= 0.8
    assert r[False, False] < 0.5


def test_stops_on_beats_moves_stops_and_seams():
    """``render.beat_timing``'s stops on the beats (its accent off) on a dance whose pauses sit 0.1 s (a fifth of a beat) after
    the song's beats: the pauses move onto the beats (within 1.5 frames), the frame count
    stays, and a frame given (a seam) moves with the motion, 0.1 s earlier."""
    motion, bars, _ = _off_grid_take(4, 120.0, 0.0)
    song_bars = bars - 0.1
    before = motion_stops(motion)
    moved, seam, info = beat_timing(
        motion, song_bars, 0, np.array([120]), land_stops=True, accent=0.0
    )
    assert moved.n_frames == motion.n_frames
    beats = np.unique(song_bars)
    inner = (beats > beats[0] + 0.3) & (beats < beats[-1] - 0.3)
    for stops, off in ((before, 0.1), (motion_stops(moved), 0.0)):
        near = np.abs(beats[inner][:, None] + off - stops[None, :]).min(axis=1)
        assert inner.sum() >= 8 and np.all(near <= 1.5 / motion.fps)
    assert abs(int(seam[0]) - (120 - round(0.1 * motion.fps))) <= 1
    assert info["accent_added"] == 0.0 and info["pulse_depth"] is None
    lo, hi = info["speed_factor"]  # the landing moved beats: its rate left 1, within its bound
    assert lo < 1.0 < hi and 1.0 / STOP_MAX_SPEED - 1e-3 <= lo and hi <= STOP_MAX_SPEED + 1e-3


def test_stops_on_beats_leaves_a_dance_without_stops_as_it_is():
    """A pose held still has no stops, and no pace to accent: the dance and the frames come
    back unchanged."""
    motion, bars, _ = _off_grid_take(5, 110.0, 0.0)
    still = Motion(
        motion.skeleton,
        motion.fps,
        np.repeat(motion.root_positions[:1], motion.n_frames, axis=0),
        np.repeat(motion.rotations[:1], motion.n_frames, axis=0),
    )
    out, seams, info = beat_timing(still, bars, 0, np.array([30, 90]), land_stops=True, accent=0.4)
    assert out is still and seams.tolist() == [30, 90]
    assert info["speed_factor"] == [1.0, 1.0]


def test_build_anchors_motion_read_grids_only(tmp_path):
    """``bars_from_dataset``: the demo library's annotated grids stay as annotated (and its
    nodes get no anchoring); gridded from its motion instead (annotations removed), beats move,
    each moved one onto a stop."""
    import json

    from dancegraph.graph.build import bars_from_dataset
    from dancegraph.motion.dataset import import_dataset, load_dataset
    from dancegraph.motion.demo import write_demo_library
    from dancegraph.store import FileStore

    lib = write_demo_library(tmp_path / "lib")
    annotated = json.loads((lib / "manifest.json").read_text())
    from_motion = json.loads(json.dumps(annotated))
    for clip in from_motion["clips"].values():
        del clip["bars"], clip["signatures"]
    store = FileStore(tmp_path / "store")
    for name, manifest in (("annotated", annotated), ("from_motion", from_motion)):
        import_dataset(lib, name, store, manifest)
    on, off = BuildParams(), BuildParams(accent_anchors=False)

    ds = load_dataset(store, "annotated")
    assert {c.beat_source for c in ds.clips} == {"annotation"}
    bars = bars_from_dataset(ds, params=on)
    assert np.array_equal(bars.beats, bars_from_dataset(ds, params=off).beats)
    # the annotated grids' nodes get no anchoring (the search no anchoring term)
    assert not bars.grid_from_motion
    assert "anchoring" not in build_arrays(bars, BuildParams(blend_ratio=0, shuffle_ratio=0))[0]

    ds = load_dataset(store, "from_motion")
    assert "annotation" not in {c.beat_source for c in ds.clips}
    moved, kept = bars_from_dataset(ds, params=on), bars_from_dataset(ds, params=off)
    assert not np.allclose(moved.beats, kept.beats)
    assert moved.grid_from_motion and kept.grid_from_motion
    by_clip = {}
    for b in ds.bars:
        by_clip.setdefault(b.clip_id, []).append(b)
    for c, clip in enumerate(moved.clips):
        grid = np.array([b.beat_times for b in sorted(by_clip[clip], key=lambda b: b.index)])
        motion = ds.motion(clip)
        want, _ = take_bars(motion, accent_anchors(grid, motion_stops(motion)))
        assert np.allclose(moved.beats[moved.clip == c], want)


def test_node_anchoring_counts_stops_on_and_between_the_beats():
    """``anchoring`` = Σ (cos 2πφ − 0.5) / 4 over a bar's stops: bars whose beats sit on the
    take's stops (one per beat) score near 0.5; stops 0.2 beat off their beats (cos 0.31) a
    little below 0; a grid half a beat off the stops (cos −1) near −1.5."""

    def anchoring(motion, bars, anchors: bool) -> np.ndarray:
        g = _graph([(motion, bars, None)], anchors)
        a = np.asarray(g.anchoring)
        assert np.array_equal(a[: len(bars)], a[len(bars) :])  # a mirror copies its bar's
        return a[: len(bars)]

    motion, bars, _ = _off_grid_take(4, 110.0, 0.2)
    assert np.median(anchoring(motion, bars, anchors=True)) >= 0.4
    off = anchoring(motion, bars, anchors=False)
    assert off.max() < 0.0 and off.min() > -0.3

    steady, grid, _ = _off_grid_take(5, 110.0, 0.0)
    assert np.median(anchoring(steady, grid, anchors=False)) >= 0.45
    assert np.median(anchoring(steady, grid[:-1] + 0.5 * 60.0 / 110.0, anchors=False)) <= -1.2


def _grid_bars(start_s: float, bpm: float, end_s: float) -> np.ndarray:
    """``(B, 5)`` s: whole 4-beat bars of a steady grid from ``start_s`` to at most ``end_s``."""
    beats = start_s + 60.0 / bpm * np.arange(int((end_s - start_s) * bpm / 60.0) + 1)
    n = (beats.size - 1) // 4
    return np.stack([beats[4 * b : 4 * b + 5] for b in range(n)])


def test_beat_accent_puts_stops_on_the_beats_of_an_even_dance():
    """A body gliding at an even pace (its stops are rounding noise); ``beat_timing``'s beat
    accent (its stops step off) makes one on every inner beat (within 1.5 frames) and none
    elsewhere, keeps the frame count; a seam frame keeps the glide's own pace within a tenth
    of a beat of it, and the beats more than a beat (``ACCENT_FADE_BEATS``) from it keep their
    stops; accent 0 leaves the dance as it is."""
    motion, _, _ = _off_grid_take(6, 120.0, 0.0)
    n, velocity = 600, np.array([0.8, 0.0, 0.3])
    glide = Motion(
        motion.skeleton,
        motion.fps,
        motion.root_positions[:1] + np.outer(np.arange(n) / motion.fps, velocity),
        np.repeat(motion.rotations[:1], n, axis=0),
    )
    bars = _grid_bars(0.3, 126.0, n / motion.fps - 0.3)
    beats = np.unique(bars)
    beat = beats[1] - beats[0]

    def stops_within_bars(m: Motion) -> np.ndarray:
        stops = motion_stops(m)
        return stops[(stops > beats[0] - 0.1) & (stops < beats[-1] + 0.1)]

    out, _, _ = beat_timing(
        glide, bars, 0, np.zeros(0, dtype=np.int64), land_stops=False, accent=0.4
    )
    assert out.n_frames == n
    stops = stops_within_bars(out)
    assert np.abs(stops[:, None] - beats[None, 1:-1]).min(axis=0).max() <= 1.5 / motion.fps
    assert np.abs(stops[:, None] - beats[None, :]).min(axis=1).max() <= 1.5 / motion.fps

    out, seam, _ = beat_timing(glide, bars, 0, np.array([300]), land_stops=False, accent=0.4)
    at = int(seam[0])
    assert abs(at - 300) <= 1  # the glide's seam frame, where its motion now falls
    speed = np.linalg.norm(np.diff(out.root_positions, axis=0), axis=1) * motion.fps
    near = np.abs(np.arange(n - 1) + 0.5 - at) <= 0.1 * beat * motion.fps
    np.testing.assert_allclose(speed[near], np.linalg.norm(velocity), rtol=0.03)
    far = beats[1:-1][np.abs(beats[1:-1] - at / motion.fps) > beat]
    stops = stops_within_bars(out)
    assert np.abs(stops[:, None] - far[None, :]).min(axis=0).max() <= 1.5 / motion.fps

    same, frames, _ = beat_timing(glide, bars, 0, np.array([300]), land_stops=False, accent=0.0)
    assert same is glide and frames.tolist() == [300]


def test_beat_accent_leaves_a_dance_that_already_slows_on_its_beats():
    """A take that pauses on every beat of its grid already slows on the beat more than the
    accent asks: ``beat_timing`` returns it as it is, and says what it had."""
    motion, bars, _ = _off_grid_take(4, 120.0, 0.0)
    out, _, info = beat_timing(
        motion, bars, 0, np.zeros(0, dtype=np.int64), land_stops=False, accent=0.4
    )
    assert out is motion
    assert info["accent_had"] >= 0.4 and info["accent_added"] == 0.0


@pytest.mark.parametrize("bpm, start_s", [(95.0, 0.3), (120.0, 0.1), (150.0, 0.0), (171.0, 0.2)])
def test_beat_accent_gathers_a_real_takes_stops_on_any_grid(salsa_dir, bpm, start_s):
    """Real salsa (20 s of take 60_07) on a steady grid unrelated to its own beat: its Shiratori
    stops fall at any phase of the grid's beats (R < 0.3); with the beat accent 0.4 alone
    (stops step off) they gather on them (R >= 0.6), and the pulse it adds is reported: the
    mean joint speed's fold on the grid deeper with it than without."""
    from dancegraph.motion.bvh import read_bvh

    take = read_bvh(salsa_dir / "60_07_scaled.bvh", fps=60).slice(600, 1800)
    bars = _grid_bars(start_s, bpm, take.n_frames / take.fps)
    beats = np.unique(bars)
    before = phase_concentration(beats, motion_stops(take))[0]
    out, _, info = beat_timing(
        take, bars, 0, np.zeros(0, dtype=np.int64), land_stops=False, accent=0.4
    )
    after = phase_concentration(beats, motion_stops(out))[0]
    assert before < 0.3
    assert after >= 0.6
    pulse = info["pulse_depth"]
    assert pulse["with"] >= 2.0 * pulse["without"] and pulse["with"] >= 0.3
