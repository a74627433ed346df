"""Mends of a beat grid's phase: sections or whole grids a tracker put on the off-beats.

- :func:`mend_swing_off_beats` (step ``swing``): a grid, or its sections, on the swung
  off-beats, moved onto the onsets the swing leads to.
- :func:`mend_half_beat_slips` (step ``slips``): sections between half-beat slips
  (:func:`find_slips`) moved back onto the pulse of the rest of the song.
- :func:`mend_off_beat_grid` (step ``off_beat_grid``): a whole grid on the straight off-beats.
- :func:`half_beat_parity`: which half of a grid at twice the tactus holds the beats (step
  ``halve``).

Curves at 50 frames per second, beat times in seconds; the thresholds are the
:class:`~dancegraph.music.params.SwingParams`, :class:`~dancegraph.music.params.SlipParams` and
:class:`~dancegraph.music.params.OffBeatParams` given (what they were measured on:
docs/music.md).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from dancegraph.music.bargroup import bar_clarity
from dancegraph.music.params import GroupParams, OffBeatParams, SlipParams, SwingParams
from dancegraph.music.signal import (
    FPS,
    beat_f_measure,
    beat_phase_profile,
    next_intervals,
    peak_near,
    zscore,
)

#: An independent tracker's beats (s) between two times (s) at a tempo (BPM): the second
#: opinion on a section (:func:`~dancegraph.music.evidence.librosa_times_between`).
Reference = Callable[[float, float, float], np.ndarray]

__all__ = [
    "eighth_phase",
    "find_slips",
    "half_beat_parity",
    "mend_half_beat_slips",
    "mend_off_beat_grid",
    "mend_swing_off_beats",
    "off_beat_gain",
    "off_beat_score",
]


def eighth_phase(profile: np.ndarray, p: SwingParams = SwingParams()) -> tuple[float, float]:
    """From a beat-phase profile (bins,) (:func:`beat_phase_profile`): the phase (beats) of the
    strongest onset between ``p.window``, measured from the grid's own onset (to cancel
    the onset detector's lag), and its strength relative to the profile's peak."""
    bins = len(profile)
    ph = (np.arange(bins) + 0.5) / bins
    near = (ph < 0.15) | (ph > 0.85)  # the grid's own onset, just after (or before) each beat
    k0 = int(np.argmax(np.where(near, profile, -np.inf)))
    lag = ph[k0] if ph[k0] < 0.5 else ph[k0] - 1.0
    lo, hi = p.window
    k = int(np.argmax(np.where((ph > lo) & (ph < hi), profile, -np.inf)))
    return float(ph[k] - lag), float(profile[k] / max(profile.max(), 1e-12))


def _on_swung_off_beats(phase: float, rel: float, p: SwingParams) -> bool:
    return phase < p.max_phase and rel >= p.min_rel


def mend_swing_off_beats(
    times: np.ndarray,
    onset_env: np.ndarray,
    p: SwingParams = SwingParams(),
    slip: SlipParams = SlipParams(),
) -> tuple[np.ndarray, float]:
    """Move onto the beat a grid, or the sections of it, that sit on the swung off-beats.

    Swing delays the off-beat eighth (to 0.58-0.67 of the beat): from a beat, the next onset comes
    *after* the middle of the beat. A tracker can lock onto the swung off-beats (off-beat drums, a
    syncopated bass); from those, the next onset — the real beat — comes *before* the middle (at
    0.33-0.42), a short-long pattern that music does not swing with. So the beat-phase profile of
    the onset strength (:func:`beat_phase_profile`) is read between 0.3 and 0.7 beat: when its peak
    there comes before ``p.max_phase`` (measured from the grid's own onset) and is a real
    onset (``p.min_rel`` of the profile's peak), the beats are moved that far later. Straight
    music (peak at 0.5) and correctly tracked swing (after 0.5) are left alone.

    A grid that slips (:func:`find_slips`) onto the swung off-beats for some sections only is mended
    section by section: one whole-grid profile mixes both and moved the right sections too (slow
    swung songs). A section moves when its own profile says so and the rest of the grid mirrors it —
    its eighth after ``p.min_swung`` and the two phases adding up to a beat within
    ``p.mirror_tol`` — so a section of a straight song on the straight off-beats, whose notes
    happen to come early, stays for :func:`mend_half_beat_slips`. ``times`` (K,) s, ``onset_env``
    (T,) at 50 fps. Returns (beat times (K',), the largest shift in beats, 0.0 when nothing moved).
    """
    t = np.asarray(times, dtype=np.float64)
    if len(t) < 8:
        return t, 0.0
    bins = p.bins
    _, splits = find_slips(t, slip)
    sections = [s for s in np.split(np.arange(len(t)), splits) if len(s) >= 8]
    if len(sections) > 1:
        # each section's profile, weighted by its beats: the rest's is the sum of the others
        weighted = np.stack([len(s) * beat_phase_profile(onset_env, t[s], bins) for s in sections])
        moved, largest = t.copy(), 0.0
        for i, sec in enumerate(sections):
            phase, rel = eighth_phase(weighted[i], p)
            if not _on_swung_off_beats(phase, rel, p):
                continue
            rest_phase, _ = eighth_phase(weighted.sum(axis=0) - weighted[i], p)
            if rest_phase >= p.min_swung and abs(phase + rest_phase - 1.0) <= p.mirror_tol:
                moved[sec] = t[sec] + phase * next_intervals(t[sec])
                largest = max(largest, phase)
        if largest:
            return _rejoin(moved, t), largest
    phase, rel = eighth_phase(beat_phase_profile(onset_env, t, bins), p)
    if not _on_swung_off_beats(phase, rel, p):
        return t, 0.0
    return t + phase * next_intervals(t), phase


def off_beat_gain(times: np.ndarray, onset_env: np.ndarray, chroma: np.ndarray) -> np.ndarray:
    """(K,) how much more the notes start half a beat after each beat than on it.

    Two curves at 50 fps: the pitched onsets (the chroma's (12, T) summed rise: new pitch
    classes sounding; the chroma leaves the bass out) and the onset strength (T,); per beat of
    ``times`` (K,) s, (curve half an interval later - curve at the beat) / the curve's standard
    deviation, summed over the two. Chords are struck and melody notes start on the beats, so a
    grid on the beat has a negative mean gain, one on the off-beats a positive one.
    """
    t = np.asarray(times, dtype=np.float64)
    if len(t) < 2:
        return np.zeros(len(t))
    shifted = t + 0.5 * next_intervals(t)
    pitched = np.r_[0.0, np.maximum(np.diff(chroma, axis=1), 0.0).sum(axis=0)]
    gain = np.zeros(len(t))
    for curve in (pitched, onset_env):
        frames = np.arange(len(curve))
        diff = np.interp(shifted * FPS, frames, curve) - np.interp(t * FPS, frames, curve)
        gain += diff / (curve.std() + 1e-9)
    return gain


def off_beat_score(times: np.ndarray, onset_env: np.ndarray, chroma: np.ndarray) -> float:
    """The grid's mean :func:`off_beat_gain` (0.0 under 8 beats: too few to say): above 0 the
    notes start rather half a beat after its beats, below 0 on them."""
    t = np.asarray(times, dtype=np.float64)
    return float(off_beat_gain(t, onset_env, chroma).mean()) if len(t) >= 8 else 0.0


def mend_off_beat_grid(
    times: np.ndarray, onset_env: np.ndarray, chroma: np.ndarray, p: OffBeatParams = OffBeatParams()
) -> tuple[np.ndarray, float]:
    """Move onto the beat a grid that sits on the straight off-beats all song long.

    Off-beat drums and a syncopated bass can hold a tracker on the "and"s from start to end, where
    no slip shows and the other tracker often agrees. The notes do not follow them: an
    :func:`off_beat_score` of the grid above ``p.min_score`` moves every beat half an
    interval later (the threshold lies between the scores of grids on the beat and of grids on the
    off-beats). ``times`` (K,) s, ``onset_env`` (T,), ``chroma`` (12, T) at 50 fps. Returns (beat
    times (K,), the score)."""
    t = np.asarray(times, dtype=np.float64)
    score = off_beat_score(t, onset_env, chroma)
    if score <= p.min_score:
        return t, score
    return t + 0.5 * next_intervals(t), score


def half_beat_parity(
    times: np.ndarray,
    act: np.ndarray,
    onset_env: np.ndarray,
    bass_onset: np.ndarray,
    chroma: np.ndarray,
    snare_onset: np.ndarray,
    p: GroupParams = GroupParams(),
) -> float:
    """Which half of a grid at twice the tactus holds the beats: > 0 the even beats (0, 2, ...), < 0
    the odd ones.

    Four cues, each the even beats against the odd ones, summed with equal weight: where the notes
    start (minus the even beats' :func:`off_beat_score`: pitched onsets and onset strength),
    BeatNet's own beat activation (``act[:, 0]``; it fires harder on the beats than on the eighths
    between them, even where its decoder counted both) and the noise onsets in the snare band
    (backbeat snares and claps fall on beats; see :func:`_spectral`), these two in z-units, and how
    clearly each half forms bars (:func:`~dancegraph.music.bargroup.bar_clarity`: downbeat
    activation, harmony and backbeat mark the bars of the beats, not of the eighths between them).
    Any one of them can mislead: a syncopated part puts the notes on the eighths between the beats,
    off-beat hi-hats pull the network there, a song without drums has no snare: together they
    outvote any one. ``times`` (K,) s; ``act`` (T, 2) and the curves at 50 fps; ``p`` the bar
    grouping's parameters."""
    t = np.asarray(times, dtype=np.float64)
    frames = np.round(t * FPS)
    parity = -off_beat_score(t[0::2], onset_env, chroma)
    for curve in (act[:, 0], snare_onset):
        peaks = zscore(peak_near(curve, frames))
        parity += float(peaks[0::2].mean() - peaks[1::2].mean())
    clarity = [
        bar_clarity(
            act, frames[k::2].astype(np.int64), onset_env, bass_onset, chroma, snare_onset, p
        )
        for k in (0, 1)
    ]
    return parity + clarity[0] - clarity[1]


def _edge_to_move(sections: list[np.ndarray], means: list[float], p: SlipParams) -> int | None:
    """With one slip, the index (0 or 1) of an intro or outro that moves as a whole: ``p.
    edge_beats`` to ``p.edge_max_beats`` beats against a body of ``p.body_beats`` or more,
    unless the body is clearly the side off the beat (its mean gain above ``p.body_min_gain``
    and more than ``p.side_margin`` above the edge's). ``sections`` the two sections' beat
    indices, ``means`` their mean :func:`off_beat_gain`. None where no edge moves."""
    if len(sections) != 2:
        return None
    short = int(len(sections[1]) < len(sections[0]))
    body = 1 - short
    body_off = means[body] > p.body_min_gain and means[body] - means[short] > p.side_margin
    fits = p.edge_beats <= len(sections[short]) <= p.edge_max_beats
    return short if fits and len(sections[body]) >= p.body_beats and not body_off else None


def _section_moves(
    t: np.ndarray, nxt: np.ndarray, sections: list[np.ndarray], means: list[float], i: int,
    reference: Reference, gain: np.ndarray, p: SlipParams,
) -> bool:  # fmt: skip
    """Whether section ``i`` of ``sections`` (beat indices into ``t`` (K,) s, split at the
    slips; ``nxt`` (K,) s :func:`next_intervals` of ``t``) is on the off-beats by its own evidence: its notes start later after its beats than
    in the sections next to it (mean :func:`off_beat_gain` ``gain`` (K,) against theirs), and
    either by more than ``p.side_margin`` with its mean gain above ``p.min_gain``, or, over
    ``p.edge_beats`` beats or more, the reference tracker on this section alone (``reference``)
    agrees; a body
    (``p.body_beats`` or more and ``p.body_ratio`` times the beats next to it) only on a gain
    above ``p.body_min_gain`` (see :func:`mend_half_beat_slips`)."""
    sec = sections[i]
    near = np.concatenate([sections[j] for j in (i - 1, i + 1) if 0 <= j < len(sections)])
    later = means[i] - float(gain[near].mean())
    if later <= 0.0:
        return False
    # a body: long, and longer than the sections next to it by far (they slipped from it)
    if len(sec) >= max(p.body_beats, p.body_ratio * len(near)):
        return means[i] > p.body_min_gain and later > p.side_margin
    if means[i] > p.min_gain and later > p.side_margin:
        return True
    if len(sec) < p.edge_beats:
        return False
    step = nxt[sec]
    shifted = t[sec] + 0.5 * step
    lo, hi = t[sec[0]] - 0.05, shifted[-1] + 0.05
    ref = np.asarray(reference(lo, hi, 60.0 / float(np.median(step))))
    ref = ref[(ref >= lo) & (ref <= hi)]
    level = np.median(np.diff(ref)) / np.median(step) if len(ref) > 2 else 0.0
    return any(a <= level <= b for a, b in (p.same_level, p.half_level)) and (
        beat_f_measure(ref, shifted) >= beat_f_measure(ref, t[sec]) + p.agree_margin
    )


def mend_half_beat_slips(
    times: np.ndarray, reference: Reference, gain: np.ndarray, p: SlipParams = SlipParams()
) -> tuple[np.ndarray, int]:
    """Put back on the beat the sections a tracker put on the off-beats.

    A tracker can lock onto the off-beats for a section (a syncopated bass without drums) and come
    back later: the grid slips by half a beat and back at a steady tempo, which the music does not
    do (slips: :func:`find_slips`, each taken at the centre of its window). Each section between
    slips is judged by its own evidence against its neighbours', so that the decision does not
    depend on where the analysis started: it moves by half an interval when its notes start
    clearly more after its beats than in the sections next to it (mean ``gain`` (K,),
    :func:`off_beat_gain`, more than ``p.side_margin`` higher) and either its own mean gain is
    above ``p.min_gain`` (``p.body_min_gain`` for a body of ``p.body_beats`` or more: chords comped
    on the off-beats raise the gain of a body on the beat) or an independent tracker run on the
    section alone at its tempo (``reference(start s, end s, bpm)`` -> beat times s; at half the
    tempo, median interval ratio within ``p.half_level``, its beats fall on every other beat of one
    grid, not the other's, an F-measure of 2/3 against 0) agrees with the moved beats clearly
    better (F-measure at 70 ms, by ``p.agree_margin``) than with the tracked ones. With one slip,
    an intro or outro of ``p.edge_beats``-``p.edge_max_beats`` beats against a body of
    ``p.body_beats`` or more moves instead, on no cue, unless the body is clearly the side off the
    beat (:func:`_edge_to_move`): the body of a song sets its pulse, and sparse intros and outros
    (chord stabs on the off-beats, no drums) are where the trackers go astray. Shorter end parts
    stay (most single slips that near an end are end effects on a correct grid). At the section
    borders a beat is dropped or inserted so that every interval stays within 0.75-1.25 of the
    local one. ``times`` (K,) s. Returns (beat times (K',), number of beats moved)."""
    t = np.asarray(times, dtype=np.float64)
    centres, _ = find_slips(t, p)
    if not len(centres):
        return t, 0
    sections = np.split(np.arange(len(t)), centres)
    means = [float(gain[sec].mean()) for sec in sections]
    edge = _edge_to_move(sections, means, p)
    nxt = next_intervals(t)
    moved, n_moved = t.copy(), 0
    for i, sec in enumerate(sections):
        if edge is None:
            go = _section_moves(t, nxt, sections, means, i, reference, gain, p)
        else:
            go = i == edge
        if go:
            moved[sec] = t[sec] + 0.5 * nxt[sec]
            n_moved += len(sec)
    if not n_moved:
        return t, 0
    return _rejoin(moved, t), n_moved


def find_slips(times: np.ndarray, p: SlipParams = SlipParams()) -> tuple[np.ndarray, np.ndarray]:
    """Where a beat grid slips by a fraction of a beat at a steady tempo.

    Slips are found in the grid's phase drift against the running interquartile mean interval
    (``p.context`` beats): a change of ``p.min``-``p.max`` beat over ``2 *
    p.window`` beats with the same tempo before and after. The decoder's beats lie on 20 ms
    frames, so at 172 BPM (17.4 frames) its intervals alternate 17 and 18 frames: their median (17)
    is 2.5 % short and the drift against it grows by a quarter beat every ten beats: false slips in
    a steady grid. The interquartile mean keeps the fraction and still ignores the slip's own odd
    intervals. Where no slip is found that way, a slower slide is looked for the same way over
    ``2 * p.slow_window`` beats: a decoder can also slide onto the off-beats over ten beats or so
    (each interval a few per cent short), too spread for the short window, which then found the
    slip or not depending on where the analysis started. ``times`` (K,) s. Returns (centres,
    splits), int arrays (S,), in order: per slip the beat at the centre of the window it was
    measured over, and the beat after the window's most irregular interval (where the grid
    jumped: the first beat of the new section)."""
    t = np.asarray(times, dtype=np.float64)
    found: list[tuple[int, int]] = []
    if len(t) >= 4 * p.window + 2:
        ibi = np.diff(t)
        # the running interquartile mean: the middle half of each sorted window of intervals
        n = p.context
        windows = np.lib.stride_tricks.sliding_window_view(np.pad(ibi, n // 2, mode="edge"), n)
        local = np.sort(windows, axis=1)[:, n // 4 : n - n // 4].mean(axis=1)
        for w, steady in ((p.window, np.inf), (p.slow_window, p.slow_steady)):
            found += _scan_slips(ibi, local, w, steady, [c for c, _ in found], p)
    found.sort()
    return (
        np.asarray([c for c, _ in found], dtype=np.int64),
        np.asarray([k for _, k in found], dtype=np.int64),
    )


def _scan_slips(
    ibi: np.ndarray, local: np.ndarray, w: int, steady: float, taken: list[int], p: SlipParams
) -> list[tuple[int, int]]:
    """The slips (centre, split) of :func:`find_slips` over windows of ``2 * w`` beats of the
    intervals ``ibi`` (K-1,) s against the running ``local`` (K-1,) s, away from the windows of
    the slips already found (centres ``taken``, found with windows of up to ``w`` beats), where
    the phase drift over the ``w`` beats before and after the window stays within ``steady``
    beats (a slide between two steady phases, not a tempo that keeps changing)."""
    drift = np.r_[0.0, np.cumsum(ibi / local - 1.0)]  # (K,) beats the grid has slipped by

    def irregular_at(k: int) -> np.ndarray:
        return np.abs(ibi[k - w : k + w] / local[k - w : k + w] - 1.0)

    def slide(k: int) -> float:  # the largest phase change over w intervals of the window
        return float(np.abs(drift[k : k + w + 1] - drift[k - w : k + 1]).max())

    def drifting(k: int) -> bool:  # the phase moves before or after the window
        ends = (drift[max(k - 2 * w, 0) : k - w + 1], drift[k + w : k + 2 * w + 1])
        return any(np.ptp(d) > steady for d in ends)

    found: list[tuple[int, int]] = []
    k = w
    while k < len(drift) - w:
        step = abs(drift[k + w] - drift[k - w])
        before = ibi[max(k - w - 8, 0) : k - w]
        after = ibi[k + w : k + w + 8]
        if (
            all(abs(k - c) >= 2 * w for c in taken)
            and p.min <= step <= p.max
            and not drifting(k)
            and len(before)
            and len(after)
            and abs(np.median(after) / np.median(before) - 1.0) <= p.same_tempo
            and (irregular_at(k).max() >= p.min_jump or slide(k) >= p.min_concentration * step)
        ):
            found.append((k, k - w + int(np.argmax(irregular_at(k))) + 1))
            k += 2 * w
        else:
            k += 1
    return found


def _rejoin(moved: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Beat times ``moved`` (K,) (some sections of the grid ``times`` (K,) moved) in order, with
    a beat dropped or inserted where a moved section meets the rest, so that every interval
    stays within 0.75-1.25 of the grid's local one."""
    ibi = np.diff(times)
    moved = np.sort(moved)
    out = [moved[0]]
    for x in moved[1:]:
        gap, period = x - out[-1], float(np.interp(x, times[1:], ibi))
        if gap < 0.75 * period:
            continue  # a beat too many where a moved section meets the rest
        if gap > 1.25 * period:
            out.append(out[-1] + gap / 2)  # one missing
        out.append(x)
    return np.asarray(out)
