"""Time warping: clips onto new frame counts and rates, and the beat-anchored warp of the renderer.

``Warp`` is the one time-warp of the project: a monotone, smooth (C1) map through anchor pairs,
the monotone cubic of Fritsch and Carlson (PCHIP) between the anchors and straight lines
with the end slopes beyond them. A rendered bar maps song time to the source frames of its node
through two of them (``song_phase`` and ``node_warp``), so every beat of the node lands on the
song's beat of the same number, the dance speeds up and slows down with uneven beats (turning
from one beat's rate to the next on the beat, ``TURN_BEATS``), and the warp stays defined past
the bar's ends, where the seam's cut may fall (docs/rendering.md). The stitched dance is
re-timed by the same construction (``beat_map``: the song's beats onto its stops near them,
``accent_anchors``), as the build moves a take's grid beats onto its stops, and made to slow into
every beat (``accent_map``, ``accent_phase``, ``accent_depth``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from dancegraph.motion import quat
from dancegraph.motion.skeleton import Motion

#: A node stores where its bar's beats -2 .. 6 fall in its frames: the bar's 4 beats and closing
#: downbeat (0 .. 4) and two beats either side, so the warp's slopes on the beat either side of
#: the bar (where a cut may fall) are those of the take's own beats; phase p of the bar is beat p.
NODE_BEATS = np.arange(-2, 7)
#: Column of the downbeat (beat 0) in a node's beats: beat j is column ``BEAT0 + j``.
BEAT0 = 2
#: Half-width (beats) of the turn around each beat in ``song_phase`` and ``node_warp``: the rate
#: of a beat interval holds from this far after its first beat to this far before its last, so
#: a change of rate between two beats happens on the beat, where an accent-anchored take stops
#: (docs/rendering.md, "Accent anchors"), and not mid-beat, where it would make a new stop.
TURN_BEATS = 0.2
#: How much a rendered dance slows into every beat by default (``accent_phase``'s depth that the
#: renderer reaches, counting what the dance already has: ``accent_depth``): none. The accent is
#: a stylization a user asks for (0.4 slows a dance of even pace to 0.6 of it on the beat and
#: speeds it to 1.4 half-way); by default the dance keeps the pulse its takes have
#: (docs/rendering.md, "Beat accent", and docs/evaluation.md, "Naturalness").
BEAT_ACCENT = 0.0
#: Whether the renderer lands the stitched dance's stops on the song's beats by default: no. The
#: step moves beat intervals by up to 1.5x and deepened the dance's pulse to 1.2-2.9x the
#: anchored dance's on the CC and generated songs (docs/evaluation.md, "Naturalness").
STOPS_ON_BEATS = False
#: Beats either side of a moment that keeps the dance's own pace (a seam: a hand-over already
#: carries the stitch's offsets, and the accent's speed-up would add to them) over which the
#: accent fades out; one beat keeps ``accent_phase`` monotone up to depth 0.8.
ACCENT_FADE_BEATS = 1.0


class Warp:
    """A monotone, C1 map through anchors ``x (K,)`` → ``y (K,)`` (both increasing, K >= 2).

    Between the anchors: the monotone piecewise cubic Hermite interpolant of Fritsch and Carlson
    (the slopes of scipy's ``PchipInterpolator``), which neither overshoots nor reverses where
    the anchors are uneven; outside them: straight lines continuing the end slopes, so the map
    is defined, monotone and C1 everywhere. Anchors that are not strictly increasing are nudged
    apart by 1e-9 of their span.
    """

    def __init__(self, x: np.ndarray, y: np.ndarray) -> None:
        x = _strictly_increasing(np.asarray(x, dtype=float).reshape(-1))
        y = _strictly_increasing(np.asarray(y, dtype=float).reshape(-1))
        if x.size < 2 or x.size != y.size:
            raise ValueError(f"a warp needs at least 2 anchor pairs, got {x.size} and {y.size}")
        self.x, self.y = x, y
        self.slopes = _pchip_slopes(x, y)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        x, y, d = self.x, self.y, self.slopes
        i = np.clip(np.searchsorted(x, t, side="right") - 1, 0, x.size - 2)
        h = x[i + 1] - x[i]
        s = (t - x[i]) / h
        s2, s3 = s * s, s * s * s
        inner = (
            (2 * s3 - 3 * s2 + 1) * y[i]
            + (s3 - 2 * s2 + s) * h * d[i]
            + (-2 * s3 + 3 * s2) * y[i + 1]
            + (s3 - s2) * h * d[i + 1]
        )
        below = y[0] + d[0] * (t - x[0])
        above = y[-1] + d[-1] * (t - x[-1])
        return np.where(t < x[0], below, np.where(t > x[-1], above, inner))


def _pchip_slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fritsch-Carlson slopes at the anchors (weighted harmonic mean of the neighbouring secants,
    zero where they change sign; shape-preserving three-point slopes at the ends)."""
    h = np.diff(x)
    m = np.diff(y) / h
    if x.size == 2:
        return np.array([m[0], m[0]])
    d = np.zeros_like(x)
    w1 = 2 * h[1:] + h[:-1]
    w2 = h[1:] + 2 * h[:-1]
    same = m[:-1] * m[1:] > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        harmonic = (w1 + w2) / (w1 / m[:-1] + w2 / m[1:])
    d[1:-1] = np.where(same, harmonic, 0.0)
    for end, (h0, h1, m0, m1) in (
        (0, (h[0], h[1], m[0], m[1])),
        (-1, (h[-1], h[-2], m[-1], m[-2])),
    ):
        e = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
        if np.sign(e) != np.sign(m0):
            e = 0.0
        elif np.sign(m0) != np.sign(m1) and abs(e) > 3 * abs(m0):
            e = 3 * m0
        d[end] = e
    return d


def _strictly_increasing(v: np.ndarray) -> np.ndarray:
    if v.size < 2 or np.all(np.diff(v) > 0):
        return v
    eps = 1e-9 * max(float(v.max() - v.min()), 1.0)
    return np.maximum.accumulate(v) + eps * np.arange(v.size)


def song_phase(bar_beats: np.ndarray) -> Warp:
    """Song time (s) → beat phase: beat j of bar b (``bar_beats (B, 5)`` s) at phase ``4b + j``.

    The anchors are every bar's beats 0-3 and the last bar's closing downbeat (with their turns,
    ``_turns``), so a gap between two bars (a downbeat correction) is danced by the earlier bar,
    as ``render.bar_frames`` gives its frames to it.
    """
    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    if len(bb) == 0:
        raise ValueError("song_phase needs at least one bar")
    times = _phase_beats(bb)
    phase, times = _turns(np.arange(times.size, dtype=float), times)
    return Warp(times, phase)


def _phase_beats(bar_beats: np.ndarray) -> np.ndarray:
    """The beats at phases 0, 1, 2, ... of ``bar_beats (B, 5)``: every bar's beats 0-3 and the
    last bar's closing downbeat, ``(4B + 1,)``."""
    return np.concatenate([bar_beats[:, :4].reshape(-1), bar_beats[-1:, 4]])


def node_warp(beats: np.ndarray) -> Warp:
    """Bar phase (beats, 0 = downbeat) → frame of a node's stored motion; ``beats (9,)``: the
    frames (fractional) of its beats -2 .. 6 (``NODE_BEATS``), with their turns (``_turns``)."""
    return Warp(*_turns(NODE_BEATS.astype(float), np.asarray(beats, dtype=float)))


def _turns(phase: np.ndarray, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Anchors ``phase (K,)`` (beats, one apart) → ``value (K,)`` with two more about each inner
    beat, ``TURN_BEATS`` before and after it on the straight lines of its two intervals (one
    after the first beat and one before the last), so the PCHIP through them is straight within
    each interval and turns from one interval's rate to the next within ``TURN_BEATS`` of the
    beat: ``(phase (3K-4,), value (3K-4,))``, K >= 2."""
    w = TURN_BEATS
    rate = np.diff(value) / np.diff(phase)
    before = (phase[1:] - w, value[1:] - w * rate)  # each interval's end, approached
    after = (phase[:-1] + w, value[:-1] + w * rate)  # each interval's start, left
    p = np.concatenate([phase, before[0], after[0]])
    v = np.concatenate([value, before[1], after[1]])
    order = np.argsort(p, kind="stable")
    return p[order], v[order]


def _nearest(sorted_values: np.ndarray, x: np.ndarray) -> np.ndarray:
    """For each of ``x (N,)`` the nearest of ``sorted_values (K,)`` (ascending, K >= 1), the
    earlier one on a tie: ``(N,)``."""
    j = np.searchsorted(sorted_values, x)
    left = sorted_values[np.maximum(j - 1, 0)]
    right = sorted_values[np.minimum(j, sorted_values.size - 1)]
    return np.where(x - left <= right - x, left, right)


def accent_anchors(
    bar_beats: np.ndarray, accents: np.ndarray, tolerance: float = 0.45, max_speed: float = 1.5
) -> np.ndarray:
    """Bar beats moved onto motion accents: ``(n, 5)`` s, like ``bar_beats``.

    ``bar_beats (n, 5)``: bars' beat times (s: a take's beat grid, or a song's); ``accents
    (K,)``: the motion's beats on the same clock (s; ``rhythm.motion.motion_stops``). Each
    distinct grid beat (a beat shared by two adjoining bars counts once, so both keep sharing it)
    with an accent within ``tolerance`` of its bar's beat length moves onto that accent; the
    beats between moved ones shift by the linear interpolation of their shifts (constant beyond
    the first and last). Where a beat interval of a bar would be stretched or squeezed by more
    than ``max_speed`` (ratio to the grid's interval), the end of it that moved further moves
    back until the interval is at the bound (where an end is not anchored, the anchor that moved
    further is dropped), until no interval is. Why: mapping the moved beats back onto the grid's
    (``node_warp`` at build, ``beat_map`` at render) lands the accents on the beats; a steady
    grid leaves them at any phase of the beat.
    """
    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    acc = np.sort(np.asarray(accents, dtype=float).reshape(-1))
    if bb.size == 0 or acc.size == 0:
        return bb.copy()
    flat = bb.reshape(-1)
    order = np.argsort(flat, kind="stable")
    new = np.concatenate([[True], np.diff(flat[order]) > 1e-6])
    group = np.empty(flat.size, dtype=np.int64)
    group[order] = np.cumsum(new) - 1
    times = flat[order][new]
    beat_len = np.repeat((bb[:, 4] - bb[:, 0]) / 4.0, 5)
    period = np.full(times.size, np.inf)
    np.minimum.at(period, group, beat_len)
    shift = _nearest(acc, times) - times
    anchored = np.abs(shift) <= tolerance * period
    grp = group.reshape(-1, 5)
    lo, hi = grp[:, :4].reshape(-1), grp[:, 1:].reshape(-1)  # every bar's beat intervals
    grid = times[hi] - times[lo]
    clips = 0
    while anchored.any():
        d = np.interp(times, times[anchored], shift[anchored])
        ratio = (times[hi] + d[hi] - times[lo] - d[lo]) / grid
        bad = np.where(ratio > 0, np.maximum(ratio / max_speed, 1.0 / (ratio * max_speed)), np.inf)
        worst = int(np.argmax(bad))
        if bad[worst] <= 1.0 + 1e-9:
            return (times + d)[group].reshape(-1, 5)
        a, b = lo[worst], hi[worst]
        if anchored[a] and anchored[b] and clips < 20 * times.size:
            # the end that moved further goes back until the interval is at the bound
            k, other = (a, b) if abs(shift[a]) > abs(shift[b]) else (b, a)
            target = grid[worst] * (max_speed if ratio[worst] > 1 else 1.0 / max_speed)
            shift[k] = d[other] + (target - grid[worst]) * (1.0 if k == b else -1.0)
            clips += 1
        else:  # an end follows its neighbours: drop the anchor that moved furthest near it
            ends = [k for k in (a, b) if anchored[k]] or list(np.flatnonzero(anchored))
            anchored[max(ends, key=lambda k: abs(shift[k]))] = False
    return bb.copy()


def beat_map(bar_beats: np.ndarray, source_beats: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Source times (s) of song times ``t (N,)`` s: each beat of ``bar_beats (B, 5)`` maps onto
    the same beat of ``source_beats (B, 5)`` (the same bars' beats in the motion being warped,
    e.g. ``accent_anchors`` of them), monotone and C1, the rate turning within ``TURN_BEATS`` of
    each beat (``_turns``), so a stop that sits on a source beat stays a stop, on the song's
    beat. Anchors as in ``song_phase``: every bar's beats 0-3 and the last closing downbeat.
    Raises ``ValueError`` where the two sides' shapes differ."""
    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    src = np.asarray(source_beats, dtype=float).reshape(-1, 5)
    if src.shape != bb.shape:
        raise ValueError(f"beat_map needs the same bars on both sides: {bb.shape}, {src.shape}")
    values = _phase_beats(src)
    to_source = Warp(*_turns(np.arange(values.size, dtype=float), values))
    return to_source(song_phase(bb)(np.asarray(t, dtype=float)))


def accent_phase(phase: np.ndarray, depth: float | np.ndarray) -> np.ndarray:
    """Beat phase ``phase (N,)`` (beats) → the phase of the un-accented dance danced there:
    ``φ − depth·sin(2πφ)/(2π)``. The dance then runs at ``1 − depth·cos(2πφ)`` times its pace:
    slowest (``1 − depth``) on every beat, fastest (``1 + depth``) half-way between, every beat
    (integer phase) where it was, so a stop on a beat stays there and bar lines do not move.
    ``depth``: a number in [0, 1) (monotone, C∞), or one per phase ``(N,)`` varying slowly (a
    fade over ``ACCENT_FADE_BEATS`` keeps the map monotone up to depth 0.8); raises
    ``ValueError`` outside [0, 1). Why: a dancer marks the beat by slowing into it; the stops
    the dance has near its beats become stops on them, which the eye and every motion-beat
    detector read."""
    d = np.asarray(depth, dtype=float)
    if d.size and (d.min() < 0.0 or d.max() >= 1.0):
        raise ValueError(f"accent depth must be in [0, 1), got {d.min()} .. {d.max()}")
    p = np.asarray(phase, dtype=float)
    return p - d / (2.0 * np.pi) * np.sin(2.0 * np.pi * p)


def accent_depth(speed: np.ndarray, phase: np.ndarray) -> float:
    """How much a dance already slows on its beats: ``−2 Σ s·cos(2πφ) / Σ s`` of its speed curve
    ``speed (N,)`` (any positive speed, e.g. ``rhythm.motion.stop_curve``) at beat phases ``phase
    (N,)``, sampled evenly in time: 0 for no relation to the beat, ``a`` for a speed proportional
    to ``1 − a·cos(2πφ)`` (what ``accent_phase`` with depth ``a`` makes of an even pace),
    negative where the dance is slowest between the beats; 0 for an empty or still curve."""
    s = np.asarray(speed, dtype=float).reshape(-1)
    p = np.asarray(phase, dtype=float).reshape(-1)
    total = float(s.sum())
    if s.size == 0 or total <= 0.0:
        return 0.0
    return float(-2.0 * np.sum(s * np.cos(2.0 * np.pi * p)) / total)


def accent_map(
    bar_beats: np.ndarray, t: np.ndarray, depth: float, fade_at: np.ndarray | None = None
) -> np.ndarray:
    """Song times ``t (N,)`` s → the times of the un-accented dance danced there (``accent_phase``
    on the song's beat phase, ``song_phase`` of ``bar_beats (B, 5)`` s, and back): the song's
    beats map onto themselves, and between them the dance runs at ``1 − depth·cos(2πφ)`` times
    its pace. ``depth`` in [0, 0.8]. ``fade_at (K,)`` s: moments that keep the dance's own pace
    (e.g. its seams): the depth fades to 0 at each of them over ``ACCENT_FADE_BEATS`` either
    side (a raised cosine in beats)."""
    phase = song_phase(bar_beats)
    p = phase(np.asarray(t, dtype=float))
    local: float | np.ndarray = depth
    fade = np.zeros(0) if fade_at is None else phase(np.asarray(fade_at, dtype=float).ravel())
    if fade.size and depth > 0.0:
        nearest = np.abs(p - _nearest(np.sort(fade), p))
        near = nearest < ACCENT_FADE_BEATS
        calm = np.where(near, 0.5 * (1.0 + np.cos(np.pi * nearest / ACCENT_FADE_BEATS)), 0.0)
        local = depth * (1.0 - calm)
    return Warp(phase.y, phase.x)(accent_phase(p, local))


def sample(motion: Motion, frames: np.ndarray) -> Motion:
    """Motion sampled at fractional source frame indices ``frames (N,)`` (clamped to the clip).

    Root positions are interpolated linearly, rotations by slerp along the shorter arc. The
    result keeps ``motion.fps``; callers set the rate they mean.
    """
    lo, hi, t = _bracket(motion, frames)
    root, rot = _interpolate(
        motion.root_positions[lo],
        motion.root_positions[hi],
        motion.rotations[lo],
        motion.rotations[hi],
        t,
    )
    return Motion(motion.skeleton, motion.fps, root, rot)


def sample_runs(
    motions: Sequence[Motion], frames: Sequence[np.ndarray], joints: Sequence[int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``sample`` of each motion at its frames, one after the other: root positions ``(N, 3)``
    and rotations ``(N, J, 4)`` (N the total of the frames; the motions share a skeleton;
    ``joints``: only these joints' rotations, ``(N, len(joints), 4)``). One slerp for all of
    them, for callers that sample many short runs (a dance's bars, a seam's candidates)."""
    parts = [(m, *_bracket(m, f)) for m, f in zip(motions, frames, strict=True)]

    def rot(m: Motion, rows: np.ndarray) -> np.ndarray:
        out = np.take(m.rotations, rows, axis=0)
        return out if joints is None else np.take(out, joints, axis=1)

    return _interpolate(
        np.concatenate([np.take(m.root_positions, lo, axis=0) for m, lo, _, _ in parts]),
        np.concatenate([np.take(m.root_positions, hi, axis=0) for m, _, hi, _ in parts]),
        np.concatenate([rot(m, lo) for m, lo, _, _ in parts]),
        np.concatenate([rot(m, hi) for m, _, hi, _ in parts]),
        np.concatenate([t for _, _, _, t in parts]),
    )


def _bracket(motion: Motion, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stored frames either side of each fractional frame (clamped to the clip) and the
    fraction of the way from the one to the other."""
    f = np.clip(np.asarray(frames, dtype=float), 0.0, motion.n_frames - 1)
    lo = np.floor(f).astype(np.int64)
    hi = np.minimum(lo + 1, motion.n_frames - 1)
    return lo, hi, f - lo


def _interpolate(
    root_lo: np.ndarray, root_hi: np.ndarray, rot_lo: np.ndarray, rot_hi: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    root = root_lo + t[:, None] * (root_hi - root_lo)
    return root, quat.slerp(rot_lo, rot_hi, t[:, None])


def retime(motion: Motion, n_frames: int, fps: float, *, endpoint: bool = False) -> Motion:
    """Warp a clip uniformly onto ``n_frames`` frames at ``fps``.

    Default (half-open): the clip's span ``[0, F)`` frames maps onto ``[0, n_frames)``, so
    output frame k shows source frame ``k · F / n_frames``. With ``endpoint`` the first and last
    frames map onto each other (``k · (F-1) / (n_frames-1)``). Rotations are slerped, the root
    interpolated linearly.
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be at least 1, got {n_frames}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    k = np.arange(n_frames, dtype=float)
    if endpoint:
        src = k * (motion.n_frames - 1) / max(n_frames - 1, 1)
    else:
        src = k * motion.n_frames / n_frames
    out = sample(motion, src)
    out.fps = float(fps)
    return out


def resample(motion: Motion, fps: float) -> Motion:
    """The same motion at another frame rate (same duration ``F / fps_src`` seconds)."""
    n = max(1, int(round(motion.n_frames * fps / motion.fps)))
    return retime(motion, n, fps)
