"""Retiming real salsa bars to 30 and 60 fps output."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.retime import resample, retime, sample, sample_runs


@pytest.fixture(scope="module")
def salsa(salsa_dir: Path):
    return read_bvh(salsa_dir / "60_07_scaled.bvh", fps=60).slice(600, 1200)


def test_identity_retime(salsa):
    same = retime(salsa, salsa.n_frames, salsa.fps)
    np.testing.assert_allclose(same.root_positions, salsa.root_positions, atol=1e-12)
    np.testing.assert_allclose(
        np.abs(np.sum(same.rotations * salsa.rotations, -1)), 1.0, atol=1e-12
    )


@pytest.mark.parametrize("fps", [30.0, 60.0])
def test_bar_to_music_bar(salsa, fps):
    """An 86-frame salsa bar (1.43 s at 60 fps) warped onto a 1.6 s music bar."""
    bar = salsa.slice(100, 186)
    n = int(round(1.6 * fps))
    out = retime(bar, n, fps)
    assert out.n_frames == n and out.fps == fps and np.isclose(out.duration_s, 1.6)
    # frame k shows source frame k * 86 / n: compare with scipy's Slerp on every joint
    src = np.arange(n) * 86 / n
    for j in (0, 5, 20, 40):
        ref = Slerp(np.arange(86), Rotation.from_quat(bar.rotations[:, j]))(np.clip(src, 0, 85))
        dots = np.abs(np.sum(ref.as_quat() * out.rotations[:, j], axis=-1))
        assert dots.min() > 1 - 1e-10
    np.testing.assert_allclose(
        out.root_positions[:, 1], np.interp(src, np.arange(86), bar.root_positions[:, 1])
    )
    # the warp is uniform: the world path is the source path, just slower
    p_src, _ = forward_kinematics(bar)
    p_out, _ = forward_kinematics(out)
    np.testing.assert_allclose(p_out[0], p_src[0], atol=1e-12)
    k = n // 2
    f = k * 86 / n
    lo = int(f)
    np.testing.assert_allclose(
        p_out[k], p_src[lo] + (f - lo) * (p_src[lo + 1] - p_src[lo]), atol=5e-3
    )


def test_endpoint_mode_hits_both_ends(salsa):
    bar = salsa.slice(0, 87)  # a bar and its closing downbeat frame
    out = retime(bar, 49, 30.0, endpoint=True)
    np.testing.assert_allclose(out.root_positions[[0, -1]], bar.root_positions[[0, -1]], atol=1e-12)


def test_slerp_takes_the_short_arc(salsa):
    m = salsa.slice(0, 2)
    m.rotations[1] = -m.rotations[1]  # same rotations, opposite sign
    mid = sample(m, np.array([0.5]))
    np.testing.assert_allclose(
        np.abs(np.sum(mid.rotations[0] * m.rotations[0], -1)), 1.0, atol=1e-3
    )


def test_resample_keeps_duration(salsa):
    for fps in (30.0, 60.0, 24.0):
        out = resample(salsa, fps)
        assert abs(out.duration_s - salsa.duration_s) <= 0.5 / fps
    with pytest.raises(ValueError):
        retime(salsa, 0, 30.0)


def test_warp_is_monotone_smooth_and_passes_its_anchors():
    """Uneven anchors: through every anchor, never reversing, slopes continuous (C1), the same
    curve as scipy's PCHIP between the anchors and straight lines beyond them."""
    from scipy.interpolate import PchipInterpolator

    from dancegraph.motion.retime import Warp

    rng = np.random.default_rng(0)
    x = np.cumsum(rng.uniform(0.2, 1.0, 9))
    y = np.cumsum(rng.uniform(5.0, 40.0, 9))
    w = Warp(x, y)
    np.testing.assert_allclose(w(x), y, atol=1e-12)
    t = np.linspace(x[0] - 2.0, x[-1] + 2.0, 4001)
    v = w(t)
    assert (np.diff(v) > 0).all()
    inside = (t >= x[0]) & (t <= x[-1])
    np.testing.assert_allclose(v[inside], PchipInterpolator(x, y)(t[inside]), atol=1e-9)
    slope = np.diff(v) / np.diff(t)
    assert np.abs(np.diff(slope)).max() < 0.05 * np.abs(slope).max()  # no kink anywhere
    below = t < x[0]
    np.testing.assert_allclose(np.diff(v[below]) / np.diff(t[below]), slope[0], rtol=1e-6)
    with pytest.raises(ValueError):
        Warp(np.array([1.0]), np.array([2.0]))


def test_song_phase_counts_beats_across_bars():
    from dancegraph.motion.retime import song_phase

    bars = np.array([[0.5, 1.0, 1.6, 2.0, 2.5], [2.5, 3.0, 3.4, 4.0, 4.5], [4.6, 5.0, 5.5, 6, 6.5]])
    phase = song_phase(bars)
    np.testing.assert_allclose(phase(bars[:, :4].ravel()), np.arange(12), atol=1e-12)
    # a gap between bars 1 and 2 belongs to bar 1: its closing downbeat is bar 2's first beat
    assert phase(np.array([4.5]))[0] < 8.0 and phase(np.array([6.5]))[0] == pytest.approx(12.0)


def test_beat_map_lands_each_beat_on_its_source_beat():
    """``beat_map``: song beat k maps onto source beat k exactly, monotone everywhere, the
    identity where both sides are the same beats (within 1 ms: the two maps' turns are not
    exact inverses), straight (one rate) on the middle of each beat interval (the turns sit
    within ``TURN_BEATS`` of the beats), and a shape mismatch is an error."""
    from dancegraph.motion.retime import TURN_BEATS, beat_map

    song = np.array([[0.5, 1.0, 1.6, 2.0, 2.5], [2.5, 3.0, 3.4, 4.0, 4.5]])
    moved = song + np.array([[0.1, -0.05, 0.12, 0.0, 0.08], [0.08, 0.1, -0.1, 0.02, 0.0]])
    beats = np.r_[song[:, :4].ravel(), song[-1, 4]]
    want = np.r_[moved[:, :4].ravel(), moved[-1, 4]]
    np.testing.assert_allclose(beat_map(song, moved, beats), want, atol=1e-9)
    t = np.linspace(0.0, 5.0, 5001)
    assert (np.diff(beat_map(song, moved, t)) > 0).all()
    np.testing.assert_allclose(beat_map(song, song, t), t, atol=1e-3)
    a, b = beats[1], beats[2]  # the interval 1.0-1.6 s, its middle away from the turns
    mid = np.linspace(a + (TURN_BEATS + 0.05) * (b - a), b - (TURN_BEATS + 0.05) * (b - a), 50)
    rate = np.diff(beat_map(song, moved, mid)) / np.diff(mid)
    np.testing.assert_allclose(rate, (want[2] - want[1]) / (b - a), rtol=1e-6)
    with pytest.raises(ValueError):
        beat_map(song, moved[:1], t)


def test_accent_phase_slows_into_every_beat_and_keeps_it():
    """``accent_phase``: every integer phase (beat) maps onto itself, the map increases, its
    rate is ``1 - depth`` on the beats and ``1 + depth`` half-way, depth 0 is the identity, and
    a depth of 1 or more (a dance standing still or running back) is refused."""
    from dancegraph.motion.retime import accent_phase

    beats = np.arange(-2.0, 9.0)
    np.testing.assert_allclose(accent_phase(beats, 0.4), beats, atol=1e-12)
    p = np.linspace(-2.0, 8.0, 10001)
    assert (np.diff(accent_phase(p, 0.8)) > 0).all()
    np.testing.assert_allclose(accent_phase(p, 0.0), p)
    h = 1e-6
    for at, rate in ((3.0, 0.6), (3.5, 1.4)):
        got = (
            (accent_phase(np.array([at + h]), 0.4) - accent_phase(np.array([at - h]), 0.4)) / 2 / h
        )
        np.testing.assert_allclose(got, rate, rtol=1e-6)
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError):
            accent_phase(p, bad)


def test_accent_depth_reads_how_much_a_speed_slows_on_the_beat():
    """``accent_depth``: a speed ``1 - a cos(2πφ)`` reads ``a``; an even speed 0; a speed slowest
    between the beats reads negative; an empty or still curve 0."""
    from dancegraph.motion.retime import accent_depth

    phase = np.linspace(0.0, 16.0, 1600, endpoint=False)
    for a in (0.0, 0.25, 0.6):
        assert accent_depth(1.0 - a * np.cos(2 * np.pi * phase), phase) == pytest.approx(
            a, abs=1e-9
        )
    assert accent_depth(1.0 + 0.3 * np.cos(2 * np.pi * phase), phase) == pytest.approx(-0.3)
    assert accent_depth(np.zeros(0), np.zeros(0)) == 0.0
    assert accent_depth(np.zeros(10), np.arange(10.0)) == 0.0


def test_accent_map_keeps_the_song_beats_and_makes_the_dance_slow_on_them():
    """``accent_map`` on uneven song beats: each beat maps onto itself (within 1 ms: the song
    phase and its inverse are PCHIPs through the same anchors), the map increases, and an even
    pace read through it is slowest on the beats (``1 - depth``) and fastest half-way."""
    from dancegraph.motion.retime import accent_map

    song = np.array([[0.5, 1.0, 1.6, 2.0, 2.5], [2.5, 3.0, 3.4, 4.0, 4.5]])
    beats = np.r_[song[:, :4].ravel(), song[-1, 4]]
    np.testing.assert_allclose(accent_map(song, beats, 0.4), beats, atol=1e-3)
    t = np.linspace(0.0, 5.0, 50001)
    mapped = accent_map(song, t, 0.4)
    rate = np.gradient(mapped, t)
    assert (np.diff(mapped) > 0).all()
    on_beat = np.abs(t[:, None] - beats[1:-1][None, :]).min(axis=1) < 0.005
    half_way = np.abs(t[:, None] - ((beats[1:] + beats[:-1]) / 2)[None, :]).min(axis=1) < 0.005
    np.testing.assert_allclose(rate[on_beat], 0.6, atol=0.02)
    np.testing.assert_allclose(rate[half_way], 1.4, atol=0.02)


def test_accent_map_fades_out_at_the_moments_that_keep_their_pace():
    """``accent_map`` with ``fade_at``: the pace there is the dance's own (rate 1), the beats
    more than ``ACCENT_FADE_BEATS`` away keep the full accent (rate ``1 - depth``), every beat
    still maps onto itself, and the map increases at the largest depth (0.8) wherever the
    fades fall."""
    from dancegraph.motion.retime import ACCENT_FADE_BEATS, accent_map

    beats = 0.5 * np.arange(33)  # 120 BPM, 8 bars
    song = np.stack([beats[4 * b : 4 * b + 5] for b in range(8)])
    t = np.linspace(0.0, 16.0, 64001)
    seam = 5.37
    mapped = accent_map(song, t, 0.4, fade_at=np.array([seam]))
    rate = np.gradient(mapped, t)
    np.testing.assert_allclose(rate[np.abs(t - seam) < 1e-3], 1.0, atol=0.01)
    far = beats[np.abs(beats - seam) > ACCENT_FADE_BEATS * 0.5 + 0.01][1:-1]
    on_far = np.abs(t[:, None] - far[None, :]).min(axis=1) < 1e-3
    np.testing.assert_allclose(rate[on_far], 0.6, atol=0.01)
    np.testing.assert_allclose(
        accent_map(song, beats, 0.4, fade_at=np.array([seam])), beats, atol=1e-9
    )
    rng = np.random.default_rng(3)
    for _ in range(20):
        fades = rng.uniform(0.0, 16.0, rng.integers(1, 6))
        assert (np.diff(accent_map(song, t, 0.8, fade_at=fades)) > 0).all()


def test_sample_runs_is_each_run_sampled_alone(salsa):
    """``sample_runs`` (one slerp for many runs) returns each run's ``sample``, one after the
    other, and with ``joints`` those joints' columns of it; frames outside a clip clamp."""
    runs = [salsa.slice(0, 200), salsa.slice(150, 420), salsa.slice(300, 310)]
    rng = np.random.default_rng(2)
    frames = [
        rng.uniform(-3.0, m.n_frames + 3.0, n) for m, n in zip(runs, (50, 7, 30), strict=True)
    ]
    root, rot = sample_runs(runs, frames)
    alone = [sample(m, f) for m, f in zip(runs, frames, strict=True)]
    np.testing.assert_array_equal(root, np.concatenate([a.root_positions for a in alone]))
    np.testing.assert_array_equal(rot, np.concatenate([a.rotations for a in alone]))
    joints = [0, 3, 4, 17]
    some_root, some = sample_runs(runs, frames, joints)
    np.testing.assert_array_equal(some_root, root)
    np.testing.assert_array_equal(some, rot[:, joints])
