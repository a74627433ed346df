"""The metrical level of a beat grid: is it the beat, or a faster or slower pulse of the song?

- :func:`dotted_pulse` (step ``dotted_pulse``): a grid at 3:2 or 2:3 of the song's pulse.
- :func:`octave_switch` (step ``one_octave``): a grid that counts sections at two tempo octaves.
- :func:`subdivision_strength` (step ``halve``): nothing sounds between the beats, so they
  are eighths.
- :func:`two_bars_per_bar` and :func:`split_beats` (step ``split``; also the style tempo range
  of :func:`dancegraph.music.analysis.fit_tempo_range`): a slow grid whose bars hold two bars.
- :func:`within_sound` (step ``within_sound``): the beats where the music sounds.

Curves at 50 frames per second, beat times in seconds; the thresholds are the parameters given
(:mod:`dancegraph.music.params`; what they were measured on: docs/music.md).
"""

from __future__ import annotations

import numpy as np

from dancegraph.music.bargroup import (
    beat_features,
    downbeat_evidence,
    fold_contrast,
    half_bar_contrast,
    lag_distance,
)
from dancegraph.music.evidence import Spectral
from dancegraph.music.mends import eighth_phase
from dancegraph.music.params import (
    AnalysisParams,
    DottedParams,
    DoubleParams,
    OctaveParams,
    SoundParams,
    TempoParams,
)
from dancegraph.music.signal import FPS, beat_phase_profile, harmonic_change, peak_near, zscore
from dancegraph.music.tempo import estimate_tempo

__all__ = [
    "dotted_pulse",
    "octave_switch",
    "split_beats",
    "split_cycle",
    "subdivision_strength",
    "two_bars_per_bar",
    "within_sound",
]


def subdivision_strength(
    onset_env: np.ndarray, times: np.ndarray, p: DoubleParams = DoubleParams()
) -> float:
    """How much the music sounds between the beats: the onset-strength profile over the beat
    (:func:`beat_phase_profile`, ``p.bins`` bins, rolled so the grid's own onset peak is at
    0) — its peak between 0.19 and 0.81 beat above the profile's floor, as a share of the beat's own
    onset above the floor. ``onset_env`` (T,) at 50 fps, ``times`` (K,) s.

    The tactus has a level below it: eighths, sixteenths or swung eighths sound between the beats. A
    grid whose beats have nothing between them is the fastest pulse of the music, counted twice per
    beat; the tactus is one level up."""
    t = np.asarray(times, dtype=np.float64)
    if len(t) < 8:
        return 1.0
    bins = p.bins
    prof = beat_phase_profile(onset_env, t, bins)
    near = np.r_[0, 1, 2, bins - 2, bins - 1]  # the grid's own onset (the detector lags)
    prof = np.roll(prof, -int(near[np.argmax(prof[near])]))
    inner = prof[3 : bins - 2].max()
    return float((inner - prof.min()) / max(prof[0] - prof.min(), 1e-9))


def dotted_pulse(
    times: np.ndarray,
    onset_env: np.ndarray,
    p: DottedParams = DottedParams(),
    tempo: TempoParams = TempoParams(),
) -> float | None:
    """The tempo (BPM) of the song's pulse when the beats ``times`` (K,) s lie at 3:2 or 2:3 of it,
    else None: the onset envelope (T,) at 50 fps repeats far more strongly (by
    ``p.min_ratio``) at the x2/3 or x3/2 level than at the tracked beat.

    A syncopated bass on the "and"s or off-beat drums can hold the decoder on a dotted pulse (every
    third eighth), which no bar grouping mends: 3 tracked beats span 2 of the song's, or the
    reverse. Where the tracked level is right, the onsets repeat most strongly at it. Then the
    decoder runs again, its tempo range held to that level (``AnalysisParams.level_band``);
    ``tempo`` the tempo estimate's parameters."""
    est = estimate_tempo(times, onset_env, FPS, tempo)
    dotted = [
        a
        for a in est.alternatives
        if a["relation"] in ("x2/3", "x3/2") and a["salience"] > p.min_ratio * est.salience
    ]
    return max(dotted, key=lambda a: a["salience"])["bpm"] if dotted else None


def octave_switch(times: np.ndarray, p: OctaveParams = OctaveParams()) -> float | None:
    """The slower tempo (BPM) when the beat grid ``times`` (K,) s counts stretches of the song at
    twice the tempo of others, each for at least ``p.min_share`` of its span; else None.

    The decoder may change its tempo octave between sections (a slow song's busier sections counted
    in eighths, a fast song's drumless intro in half notes), and bars cut to such a grid halve or
    double their length from one section to the next. Each interval is placed by the running median
    of 9 intervals: at the fastest level (within 15 % of its 5th percentile), at twice it (within 30
    %) or between. A switch jumps, a ritardando glides: the tempos between the two levels last
    ``p.max_between`` of the span at most, and the median of 4 intervals changes by
    ``p.min_jump`` from one beat's 4 to the next 4 somewhere. Then the decoder runs again at
    one level (:func:`dancegraph.music.steps.decode_at_level`)."""
    from scipy.ndimage import median_filter

    t = np.asarray(times, dtype=np.float64)
    if len(t) < 24:
        return None
    ibi = np.diff(t)
    local = median_filter(ibi, 9, mode="nearest")
    fastest = float(np.percentile(local, 5))
    at_fast = np.abs(local / fastest - 1.0) < 0.15
    at_slow = np.abs(local / fastest - 2.0) < 0.3
    span = t[-1] - t[0]
    least = p.min_share * span
    if ibi[at_fast].sum() < least or ibi[at_slow].sum() < least:
        return None
    if ibi[~at_fast & ~at_slow].sum() > p.max_between * span:
        return None  # the tempo glides from one to the other: a ritardando, not a switch
    window = np.median(np.lib.stride_tricks.sliding_window_view(ibi, 4), axis=1)
    change = window[4:] / window[:-4]  # the 4 intervals after a beat against the 4 before it
    if np.maximum(change, 1.0 / change).max() < p.min_jump:
        return None
    return 60.0 / float(np.median(ibi[at_slow]))


def split_beats(
    times: np.ndarray, positions: np.ndarray, meter: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """Every beat interval of ``times`` (K,) split in two at its middle: (2K - 1,) times and
    their positions in bars of the split grid. ``meter`` is the tracked grid's bar length:
    4 (or 2), a beat at ``positions`` (K,) 1 or 3 (of 4; 1 or 2 of 2) starts a 4-beat bar of the
    split grid (the inserted beats are its 2nd and 4th); 3, a tracked bar holds two 3-beat bars,
    the second starting half-way through its second beat."""
    times = np.asarray(times, dtype=np.float64)
    out = np.empty(2 * len(times) - 1)
    out[0::2], out[1::2] = times, (times[:-1] + times[1:]) / 2
    per_bar = 3 if meter == 3 else 4
    return out, split_cycle(positions) % per_bar + 1


def split_cycle(positions: np.ndarray) -> np.ndarray:
    """(2K - 1,) place of each beat of a split grid in the tracked bar, 0 .. 2 * meter - 1, from
    the tracked ``positions`` (K,) (1-based)."""
    cycle = np.empty(2 * len(positions) - 1, dtype=np.int64)
    cycle[0::2] = 2 * (np.asarray(positions) - 1)
    cycle[1::2] = cycle[0:-1:2] + 1
    return cycle


def within_sound(
    times: np.ndarray, onset_env: np.ndarray, p: SoundParams = SoundParams()
) -> np.ndarray:
    """(K,) bool: the beats of ``times`` (K,) s that lie where the music sounds — from the first
    onset to the last (``onset_env`` (T,) at 50 fps at least ``p.min_onset`` of its median at
    the beats), with ``p.slack`` of the median beat interval either side.

    The decoder runs to the end of the audio: after the last note it keeps counting through the
    ring-out and any silence after it, and a dance cut to those beats would go on after the music
    has stopped."""
    t = np.asarray(times, dtype=np.float64)
    if len(t) < 2:
        return np.ones(len(t), dtype=bool)
    level = float(np.median(peak_near(onset_env, np.round(t * FPS))))
    onsets = np.flatnonzero(onset_env >= p.min_onset * level)
    if level <= 0 or len(onsets) == 0:
        return np.ones(len(t), dtype=bool)
    slack = p.slack * float(np.median(np.diff(t)))
    return (t >= onsets[0] / FPS - slack) & (t <= onsets[-1] / FPS + slack)


def two_bars_per_bar(
    times: np.ndarray,
    positions: np.ndarray,
    per_bar: int,
    halved: bool,
    act: np.ndarray,
    frames: np.ndarray,
    tracked: np.ndarray,
    spec: Spectral,
    params: AnalysisParams = AnalysisParams(),
) -> str | None:
    """Why the bars of a slow grid (``times`` (K,) s, ``positions`` (K,) in bars of
    ``per_bar``) hold two bars of the music each, or None. 2-beat bars (the bar grouping found
    their two beats alike; not on a halved grid): always. 4-beat bars (not halved): their third
    beat is marked almost as strongly as their first (:func:`~dancegraph.music.bargroup.
    half_bar_contrast` under ``params.split.max_contrast``). 3-beat bars: two 3-beat bars of a fast
    waltz, the second starting half-way through the second tracked beat — on the split grid
    the music repeats after 3 beats as closely as after 6 (``params.split.max_repeat_gap``) and the
    harmony changes in the middle of the tracked bar almost as much as at its start
    (:func:`~dancegraph.music.bargroup.fold_contrast` under ``params.split.max_harmony_contrast``);
    a slow waltz's middle is the off-beat of its second beat. Never when the notes between the
    beats come after their middle (``params.swing.min_swung``): those are the swung eighths of a
    slow song, while a fast song's beats halve the interval (a 70 BPM swung song was split)."""
    profile = beat_phase_profile(spec.onset_env, times, params.swing.bins)
    between, _ = eighth_phase(profile, params.swing)
    if between >= params.swing.min_swung:
        return None
    if per_bar == 2:
        return None if halved else "bars of 2 beats"
    if per_bar == 4:
        if halved:
            return None
        contrast = half_bar_contrast(
            downbeat_evidence(act, frames, spec.chroma, tracked, p=params.group), positions
        )
        if contrast < params.split.max_contrast:
            return (
                f"4-beat bars marked in the middle almost as at the start (contrast {contrast:.2f})"
            )
        return None
    split, _ = split_beats(times, positions, per_bar)
    split_frames = np.round(split * FPS).astype(np.int64)
    x = beat_features(spec.onset_env, spec.bass_onset, spec.chroma, split_frames)
    repeat_gap = lag_distance(x, 3) - lag_distance(x, 6)
    harmony = zscore(harmonic_change(spec.chroma, split_frames))
    contrast = fold_contrast(harmony, split_cycle(positions), 2 * per_bar)
    if repeat_gap < params.split.max_repeat_gap and contrast < params.split.max_harmony_contrast:
        return (
            f"3-beat bars holding two 3-beat bars (repeats after 3 split beats as after 6: "
            f"{repeat_gap:+.2f}; harmony contrast {contrast:.2f})"
        )
    return None
