"""Beats, downbeats, meter and tempo of a song: ``track_beats(y, sr) -> BeatTracking``.

An explicit pipeline over one parameters object (:class:`BeatParams`):

1. :func:`beat_evidence`: checks the audio (length, silence), raises quiet input to a mastered
   level, and computes what every step reads (:class:`Evidence`): the activations of BeatNet's
   CRNN models averaged (:mod:`dancegraph.music.beatnet`) and the spectral curves (onset
   strength, chroma above the bass, bass and snare-band onsets).
2. The bar-pointer decoder (:mod:`dancegraph.music.barpointer`) over meters 2, 3 and 4, bar
   restarts allowed between sections; then the no-beat test (:func:`_usable`: the pulse
   strength of the activation; a faint one passes with a ``weak_pulse`` warning unless the
   sound pauses like speech, :func:`speech_evidence`).
3. The steps of :data:`STEPS`, in that order, each a function from the grid and the evidence
   to a new grid and its warnings, each switched by name in ``BeatParams.steps``
   (:data:`DEFAULT_STEPS` by default): ``dotted_pulse`` (decode again at the song's pulse,
   ``beat_level_corrected``), ``one_octave`` (decode again at one tempo octave,
   ``beat_level_unified``), ``halve`` (every other beat of a grid with nothing between its
   beats, ``beats_halved``), ``swing`` (``beat_swing_mended``), ``slips``
   (``beat_slip_mended``), ``off_beat_grid`` (``beat_phase_shifted``), ``within_sound`` (beats
   where the music sounds), ``group`` (meter and bar phase, :mod:`dancegraph.music.bargroup`:
   ``meter_regrouped``, ``downbeat_rephased``) and ``split`` (``beats_split``). What each
   does to real recordings and to generated songs, and why some are off by default:
   docs/music.md.
4. Tempo from the beats with its metrical alternatives (:mod:`dancegraph.music.tempo`) and a
   confidence that the librosa tracker's agreement raises.

Fallback (``method='librosa'``, or BeatNet's weights missing: warning
``beatnet_weights_missing``): ``librosa.beat.beat_track`` on the onset envelope and a global
bar phase and meter (3 or 4) from chroma change, bass onsets and onset strength at the beats.
No usable beat: ``AudioError(code='no_beat')`` — silence, noise, speech, birdsong, a steady
tone. All times in seconds from the start of ``y``; ``y`` at any rate, BeatNet works at
22,050 Hz, 50 frames per second.
"""

from __future__ import annotations

import warnings as _warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from dancegraph import jit
from dancegraph.errors import AudioError, ModelFileError
from dancegraph.music import barpointer
from dancegraph.music.bargroup import (
    bar_clarity,
    beat_features,
    downbeat_evidence,
    fold_contrast,
    group_beats,
    half_bar_contrast,
    harmonic_change,
    lag_distance,
    peak_near,
    zscore,
)
from dancegraph.music.decode import DEFAULT_MAX_SECONDS, resample
from dancegraph.music.tempo import (
    estimate_tempo,
    metrical_relation,
    pulse_salience,
    tempo_from_beats,
)

__all__ = [
    "DOTTED",
    "DOUBLE",
    "LEVEL_BAND",
    "NO_BEAT",
    "OCTAVE",
    "OFF_BEAT",
    "SLIP",
    "SOUND",
    "BeatTracking",
    "beat_f_measure",
    "beat_phase_profile",
    "dotted_pulse",
    "find_slips",
    "half_beat_parity",
    "mend_half_beat_slips",
    "mend_off_beat_grid",
    "mend_swing_off_beats",
    "octave_switch",
    "off_beat_gain",
    "off_beat_score",
    "split_beats",
    "subdivision_strength",
    "within_sound",
    "track_beats",
    "warm_up",
]

SR = 22_050
HOP = 441
DEFAULT_MODELS = (1, 2, 3)
TARGET_LEVEL = 0.1  # loud-part RMS (-20 dBFS) quiet input is raised to: a mastered song's level
MAX_GAIN = 1000.0  # at most +60 dB
FPS = SR / HOP
#: the confidence of a faint pulse (``weak_pulse``) is scaled by this: beats, but not sure ones
WEAK_PULSE_CONFIDENCE = 0.5

# thresholds of the "usable beat" test (:func:`_usable`; values on real music, generated songs
# and the non-music clips: docs/music.md)
NO_BEAT: dict[str, Any] = {
    "min_beats": 8,  # fewer decoded beats than this: no beat
    "min_coverage": 0.5,  # beats must span this share of the non-silent audio
    "min_regularity": 0.6,  # share of inter-beat intervals within 10 % of the local median
    "silence_rms": 1e-4,  # RMS below this (-80 dBFS) is silence
    # on BeatNet's summed beat+downbeat activation: mean peak at the beats, the pulse strength
    # (contrast: peak / mean, times salience: the autocorrelation at the beat period) above
    # which it is a beat (the non-music clips and noise reach 0.22: this is 15 % above), and
    # the contrast and salience under which that pulse is faint (``weak_pulse``)
    "beatnet": {
        "min_peak": 0.3,
        "min_contrast": 0.0,
        "min_salience": 0.0,
        "min_strength": 0.25,
        "clear_contrast": 2.4,
        "clear_salience": 0.2,
    },
    # a faint pulse that sounds like speech is refused (:func:`speech_evidence`): pauses in at
    # least this share of the frames and a harmony (chroma persistence) under this; both needed
    "speech_pauses": 0.14,
    "speech_chroma": 0.7,
    # the same on librosa's onset envelope (fallback only): contrast and salience each, no
    # faint zone (speech reaches a strength of 0.33 here, on a salience under 0.08)
    "librosa": {
        "min_peak": 0.0,
        "min_contrast": 1.5,
        "min_salience": 0.1,
        "min_strength": 0.0,
        "clear_contrast": 1.5,
        "clear_salience": 0.1,
    },
}


# beats on the swung off-beats (see :func:`mend_swing_off_beats`)
SWING: dict[str, Any] = {
    "bins": 50,  # beat-phase resolution of the onset profile
    "window": (0.3, 0.7),  # where the eighth note between two beats is looked for (beats)
    "max_phase": 0.46,  # it comes before this, after the grid's own onset lag: swung off-beats
    "min_swung": 0.54,  # a section moves where the rest of the grid has its eighth after this
    "mirror_tol": 0.08,  # ... and the two phases add up to one beat within this
    "min_rel": 0.2,  # and its onset is at least this share of the profile's peak
}

# a grid at twice the tactus (see :func:`subdivision_strength`)
DOUBLE: dict[str, Any] = {
    "bins": 16,  # beat-phase resolution of the onset profile
    "max_subdivision": 0.14,  # nothing between the beats above this share of the beat's onset
    "min_half_bpm": 60.0,  # and the half tempo is still a beat one counts
}

# a grid on a dotted pulse of the song (see :func:`dotted_pulse`)
DOTTED: dict[str, Any] = {
    "min_ratio": 1.6,  # the 3:2 / 2:3 level's pulse salience over the tracked level's
}

# a grid that changes its tempo octave between sections (see :func:`octave_switch`)
OCTAVE: dict[str, Any] = {
    "min_share": 0.15,  # each of the two levels held for this share of the grid's span
    "max_between": 0.25,  # tempos between the two for at most this share ...
    "min_jump": 1.35,  # ... and somewhere the tempo changes this much within 4 beats: it jumps
}

#: the decoder's tempo range, +-15 %, when it decodes again at one metrical level
LEVEL_BAND = 0.15

# a grid at half the tactus (see :func:`split_beats`)
SPLIT: dict[str, Any] = {
    "max_bpm": 95.0,  # tracked tempo under which 2 beats per bar may be a half-time count
    "max_contrast": 1.2,  # 4-beat bars whose third beat is marked almost as their first
    # 3-beat bars: the split grid repeats after 3 beats at least as closely as after 6 ...
    "max_repeat_gap": 0.0,
    # ... and the harmony changes half-way through the bar almost as at its start
    "max_harmony_contrast": 1.0,
}

# beats before the music starts or after it has stopped (see :func:`within_sound`)
SOUND: dict[str, Any] = {
    "min_onset": 0.1,  # an onset: onset strength at least this share of its median at the beats
    "slack": 0.1,  # beats kept up to this share of a beat interval outside the first/last onset
}

#: noise onsets in this band (Hz) are taken for snares and claps (see :func:`_spectral`)
SNARE_BAND_HZ = (1000.0, 5000.0)

# a whole grid on the straight off-beats (see :func:`mend_off_beat_grid`)
OFF_BEAT: dict[str, Any] = {
    "min_score": 0.83,  # pitched-onset + onset-strength preference for the half-shifted grid
}

# half-beat slips of the beat grid (see :func:`mend_half_beat_slips`)
SLIP: dict[str, Any] = {
    "window": 4,  # beats each side of a slip
    "min": 0.3,  # phase change over 2 * window beats, in beats, that counts as a slip ...
    "max": 0.7,  # ... up to this
    "same_tempo": 0.04,  # relative tempo difference allowed before/after (else a tempo change)
    "context": 33,  # beats of the running interval the phase drift is measured against
    "agree_margin": 0.2,  # F-measure by which the other tracker must prefer the moved beats
    "same_level": (0.8, 1.25),  # its median interval / the section's, to count as a vote ...
    "half_level": (1.6, 2.5),  # ... or at half the tempo (every other beat: F at most 2/3)
    "min_gain": 0.2,  # or the section's mean off-beat gain (a slip bounds it: less than a grid)
    "body_min_gain": 0.6,  # the body of a song gives way to its intro/outro only above this
    "side_margin": 0.2,  # ... where the two sides' mean gains differ by more than this
    "edge_beats": 12,  # one slip: an intro/outro of this many beats or more ...
    "edge_share": 0.25,  # ... and at most this share of the beats moves (the body sets the pulse)
    # a slip is a slide or a jump, not jitter: 4 of its window's intervals hold this share of
    # its phase change, or one interval is this far off the running one (a steady grid's frame
    # jitter spreads its drift evenly over the window; a decoder's slide concentrates it)
    "min_concentration": 0.75,
    "min_jump": 0.11,
}


@dataclass
class BeatTracking:
    """Beat tracking result; times in seconds.

    beats (K,), beat_positions (K,) int (1 = downbeat), downbeats (M,), meter (2|3|4, the meter
    in force for most beats), tempo_bpm, tempo_confidence (0..1), method ('beatnet'|'librosa'),
    warnings (codes with a short text), and ``evidence`` (the numbers behind the no-beat test
    and the confidence).
    """

    beats: np.ndarray
    beat_positions: np.ndarray
    downbeats: np.ndarray
    meter: int
    tempo_bpm: float
    tempo_confidence: float
    method: str
    warnings: list[str] = field(default_factory=list)
    evidence: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("beats", "downbeats"):
            d[k] = [round(float(t), 4) for t in d[k]]
        d["beat_positions"] = [int(p) for p in self.beat_positions]
        return d


def beat_f_measure(ref: np.ndarray, est: np.ndarray, tol: float = 0.07) -> float:
    """F-measure of estimated against reference event times (s): the largest one-to-one matching
    of events within ``tol`` of each other (walking both sorted lists, each event matched to the
    earliest partner still free, is maximal for a common tolerance), F = 2PR / (P + R)."""
    ref = np.sort(np.asarray(ref, dtype=np.float64))
    est = np.sort(np.asarray(est, dtype=np.float64))
    if len(ref) == 0 and len(est) == 0:
        return 1.0
    i = j = hits = 0
    while i < len(est) and j < len(ref):
        if abs(est[i] - ref[j]) <= tol:
            hits, i, j = hits + 1, i + 1, j + 1
        elif est[i] < ref[j]:
            i += 1
        else:
            j += 1
    if hits == 0:
        return 0.0
    p, r = hits / len(est), hits / len(ref)
    return 2 * p * r / (p + r)


def beat_phase_profile(onset_env: np.ndarray, times: np.ndarray, bins: int) -> np.ndarray:
    """(bins,) mean onset strength (T,) at 50 fps over the phase (0..1) of each beat interval of
    ``times`` (K,) s: where in the beat the music's onsets fall."""
    t = np.asarray(times, dtype=np.float64)
    ph = (np.arange(bins) + 0.5) / bins
    fr = (t[:-1, None] + ph[None, :] * np.diff(t)[:, None]) * FPS
    return np.interp(fr, np.arange(len(onset_env)), onset_env).mean(axis=0)


def _eighth_phase(profile: np.ndarray) -> tuple[float, float]:
    """From a beat-phase profile (bins,) (:func:`beat_phase_profile`): the phase (beats) of the
    strongest onset between ``SWING['window']``, measured from the grid's own onset (to cancel
    the onset detector's lag), and its strength relative to the profile's peak."""
    bins = len(profile)
    ph = (np.arange(bins) + 0.5) / bins
    near = (ph < 0.15) | (ph > 0.85)  # the grid's own onset, just after (or before) each beat
    k0 = int(np.argmax(np.where(near, profile, -np.inf)))
    lag = ph[k0] if ph[k0] < 0.5 else ph[k0] - 1.0
    lo, hi = SWING["window"]
    k = int(np.argmax(np.where((ph > lo) & (ph < hi), profile, -np.inf)))
    return float(ph[k] - lag), float(profile[k] / max(profile.max(), 1e-12))


def _on_swung_off_beats(phase: float, rel: float) -> bool:
    return phase < SWING["max_phase"] and rel >= SWING["min_rel"]


def mend_swing_off_beats(times: np.ndarray, onset_env: np.ndarray) -> tuple[np.ndarray, float]:
    """Move onto the beat a grid, or the sections of it, that sit on the swung off-beats.

    Swing delays the off-beat eighth (to 0.58-0.67 of the beat): from a beat, the next onset comes
    *after* the middle of the beat. A tracker can lock onto the swung off-beats (off-beat drums, a
    syncopated bass); from those, the next onset — the real beat — comes *before* the middle (at
    0.33-0.42), a short-long pattern that music does not swing with. So the beat-phase profile of
    the onset strength (:func:`beat_phase_profile`) is read between 0.3 and 0.7 beat: when its peak
    there comes before ``SWING['max_phase']`` (measured from the grid's own onset) and is a real
    onset (``SWING['min_rel']`` of the profile's peak), the beats are moved that far later. Straight
    music (peak at 0.5) and correctly tracked swing (after 0.5) are left alone.

    A grid that slips (:func:`find_slips`) onto the swung off-beats for some sections only is mended
    section by section: one whole-grid profile mixes both and moved the right sections too (slow
    swung songs). A section moves when its own profile says so and the rest of the grid mirrors it —
    its eighth after ``SWING['min_swung']`` and the two phases adding up to a beat within
    ``SWING['mirror_tol']`` — so a section of a straight song on the straight off-beats, whose notes
    happen to come early, stays for :func:`mend_half_beat_slips`. ``times`` (K,) s, ``onset_env``
    (T,) at 50 fps. Returns (beat times (K',), the largest shift in beats, 0.0 when nothing moved).
    """
    t = np.asarray(times, dtype=np.float64)
    if len(t) < 8:
        return t, 0.0
    bins = SWING["bins"]
    _, splits = find_slips(t)
    sections = [s for s in np.split(np.arange(len(t)), splits) if len(s) >= 8]
    if len(sections) > 1:
        # each section's profile, weighted by its beats: the rest's is the sum of the others
        weighted = np.stack([len(s) * beat_phase_profile(onset_env, t[s], bins) for s in sections])
        moved, largest = t.copy(), 0.0
        for i, sec in enumerate(sections):
            phase, rel = _eighth_phase(weighted[i])
            if not _on_swung_off_beats(phase, rel):
                continue
            rest_phase, _ = _eighth_phase(weighted.sum(axis=0) - weighted[i])
            if (
                rest_phase >= SWING["min_swung"]
                and abs(phase + rest_phase - 1.0) <= SWING["mirror_tol"]
            ):
                moved[sec] = t[sec] + phase * _next_intervals(t[sec])
                largest = max(largest, phase)
        if largest:
            return _rejoin(moved, t), largest
    phase, rel = _eighth_phase(beat_phase_profile(onset_env, t, bins))
    if not _on_swung_off_beats(phase, rel):
        return t, 0.0
    return t + phase * _next_intervals(t), phase


def _next_intervals(times: np.ndarray) -> np.ndarray:
    """(K,) s from each beat of ``times`` (K >= 2) to the next; the last beat repeats the last
    interval. A beat moved a fraction of a beat later moves by that fraction of this."""
    ibi = np.diff(times)
    return np.r_[ibi, ibi[-1]]


def subdivision_strength(onset_env: np.ndarray, times: np.ndarray) -> float:
    """How much the music sounds between the beats: the onset-strength profile over the beat
    (:func:`beat_phase_profile`, ``DOUBLE['bins']`` bins, rolled so the grid's own onset peak is at
    0) — its peak between 0.19 and 0.81 beat above the profile's floor, as a share of the beat's own
    onset above the floor. ``onset_env`` (T,) at 50 fps, ``times`` (K,) s.

    The tactus has a level below it: eighths, sixteenths or swung eighths sound between the beats. A
    grid whose beats have nothing between them is the fastest pulse of the music, counted twice per
    beat; the tactus is one level up."""
    t = np.asarray(times, dtype=np.float64)
    if len(t) < 8:
        return 1.0
    bins = DOUBLE["bins"]
    prof = beat_phase_profile(onset_env, t, bins)
    near = np.r_[0, 1, 2, bins - 2, bins - 1]  # the grid's own onset (the detector lags)
    prof = np.roll(prof, -int(near[np.argmax(prof[near])]))
    inner = prof[3 : bins - 2].max()
    return float((inner - prof.min()) / max(prof[0] - prof.min(), 1e-9))


def dotted_pulse(times: np.ndarray, onset_env: np.ndarray) -> float | None:
    """The tempo (BPM) of the song's pulse when the beats ``times`` (K,) s lie at 3:2 or 2:3 of it,
    else None: the onset envelope (T,) at 50 fps repeats far more strongly (by
    ``DOTTED['min_ratio']``) at the x2/3 or x3/2 level than at the tracked beat.

    A syncopated bass on the "and"s or off-beat drums can hold the decoder on a dotted pulse (every
    third eighth), which no bar grouping mends: 3 tracked beats span 2 of the song's, or the
    reverse. Where the tracked level is right, the onsets repeat most strongly at it. Then the
    decoder runs again, its tempo range held to that level (``LEVEL_BAND``)."""
    est = estimate_tempo(times, onset_env, FPS)
    dotted = [
        a
        for a in est.alternatives
        if a["relation"] in ("x2/3", "x3/2") and a["salience"] > DOTTED["min_ratio"] * est.salience
    ]
    return max(dotted, key=lambda a: a["salience"])["bpm"] if dotted else None


def octave_switch(times: np.ndarray) -> float | None:
    """The slower tempo (BPM) when the beat grid ``times`` (K,) s counts stretches of the song at
    twice the tempo of others, each for at least ``OCTAVE['min_share']`` of its span; else None.

    The decoder may change its tempo octave between sections (a slow song's busier sections counted
    in eighths, a fast song's drumless intro in half notes), and bars cut to such a grid halve or
    double their length from one section to the next. Each interval is placed by the running median
    of 9 intervals: at the fastest level (within 15 % of its 5th percentile), at twice it (within 30
    %) or between. A switch jumps, a ritardando glides: the tempos between the two levels last
    ``OCTAVE['max_between']`` of the span at most, and the median of 4 intervals changes by
    ``OCTAVE['min_jump']`` from one beat's 4 to the next 4 somewhere. Then the decoder runs again at
    one level (:func:`_decode_at_level`)."""
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
    least = OCTAVE["min_share"] * span
    if ibi[at_fast].sum() < least or ibi[at_slow].sum() < least:
        return None
    if ibi[~at_fast & ~at_slow].sum() > OCTAVE["max_between"] * span:
        return None  # the tempo glides from one to the other: a ritardando, not a switch
    window = np.median(np.lib.stride_tricks.sliding_window_view(ibi, 4), axis=1)
    change = window[4:] / window[:-4]  # the 4 intervals after a beat against the 4 before it
    if np.maximum(change, 1.0 / change).max() < OCTAVE["min_jump"]:
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
    return out, _split_cycle(positions) % per_bar + 1


def _split_cycle(positions: np.ndarray) -> np.ndarray:
    """(2K - 1,) place of each beat of a split grid in the tracked bar, 0 .. 2 * meter - 1, from
    the tracked ``positions`` (K,) (1-based)."""
    cycle = np.empty(2 * len(positions) - 1, dtype=np.int64)
    cycle[0::2] = 2 * (np.asarray(positions) - 1)
    cycle[1::2] = cycle[0:-1:2] + 1
    return cycle


def within_sound(times: np.ndarray, onset_env: np.ndarray) -> np.ndarray:
    """(K,) bool: the beats of ``times`` (K,) s that lie where the music sounds — from the first
    onset to the last (``onset_env`` (T,) at 50 fps at least ``SOUND['min_onset']`` of its median at
    the beats), with ``SOUND['slack']`` of the median beat interval either side.

    The decoder runs to the end of the audio: after the last note it keeps counting through the
    ring-out and any silence after it, and a dance cut to those beats would go on after the music
    has stopped."""
    t = np.asarray(times, dtype=np.float64)
    if len(t) < 2:
        return np.ones(len(t), dtype=bool)
    level = float(np.median(peak_near(onset_env, np.round(t * FPS))))
    onsets = np.flatnonzero(onset_env >= SOUND["min_onset"] * level)
    if level <= 0 or len(onsets) == 0:
        return np.ones(len(t), dtype=bool)
    slack = SOUND["slack"] * float(np.median(np.diff(t)))
    return (t >= onsets[0] / FPS - slack) & (t <= onsets[-1] / FPS + slack)


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
    shifted = t + 0.5 * _next_intervals(t)
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
    times: np.ndarray, onset_env: np.ndarray, chroma: np.ndarray
) -> tuple[np.ndarray, float]:
    """Move onto the beat a grid that sits on the straight off-beats all song long.

    Off-beat drums and a syncopated bass can hold a tracker on the "and"s from start to end, where
    no slip shows and the other tracker often agrees. The notes do not follow them: an
    :func:`off_beat_score` of the grid above ``OFF_BEAT['min_score']`` moves every beat half an
    interval later (the threshold lies between the scores of grids on the beat and of grids on the
    off-beats). ``times`` (K,) s, ``onset_env`` (T,), ``chroma`` (12, T) at 50 fps. Returns (beat
    times (K,), the score)."""
    t = np.asarray(times, dtype=np.float64)
    score = off_beat_score(t, onset_env, chroma)
    if score <= OFF_BEAT["min_score"]:
        return t, score
    return t + 0.5 * _next_intervals(t), score


def half_beat_parity(
    times: np.ndarray,
    act: np.ndarray,
    onset_env: np.ndarray,
    bass_onset: np.ndarray,
    chroma: np.ndarray,
    snare_onset: np.ndarray,
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
    outvote any one. ``times`` (K,) s; ``act`` (T, 2) and the curves at 50 fps."""
    t = np.asarray(times, dtype=np.float64)
    frames = np.round(t * FPS)
    parity = -off_beat_score(t[0::2], onset_env, chroma)
    for curve in (act[:, 0], snare_onset):
        peaks = zscore(peak_near(curve, frames))
        parity += float(peaks[0::2].mean() - peaks[1::2].mean())
    clarity = [
        bar_clarity(act, frames[k::2].astype(np.int64), onset_env, bass_onset, chroma, snare_onset)
        for k in (0, 1)
    ]
    return parity + clarity[0] - clarity[1]


def mend_half_beat_slips(
    times: np.ndarray, reference: np.ndarray, gain: np.ndarray
) -> tuple[np.ndarray, int]:
    """Put back on the beat the sections a tracker put on the off-beats.

    A tracker can lock onto the off-beats for a section (a syncopated bass without drums) and come
    back later: the grid slips by half a beat and back at a steady tempo, which the music does not
    do (slips: :func:`find_slips`, each taken at the centre of its window). The beats on one side of
    the slips — the side whose notes start more after its beats than the other's (mean ``gain``
    (K,), :func:`off_beat_gain`) — are moved by half an interval, section by section, where an
    independent tracker's beats ``reference`` (s) at the same tempo there or at half of it (median
    interval ratio within ``SLIP['same_level']`` or ``SLIP['half_level']``: at half the tempo its
    beats fall on every other beat of one grid, not the other's, an F-measure of 2/3 against 0)
    agree with the moved beats clearly better (F-measure at 70 ms, by ``SLIP['agree_margin']``) than
    with the tracked ones, or where the section's mean ``gain`` is above ``SLIP['min_gain']`` and
    the two sides' mean gains differ by more than ``SLIP['side_margin']`` (the other tracker often
    follows the same off-beats). A slip bounds the section, so it needs less evidence than a whole
    grid (:func:`mend_off_beat_grid`). With one slip in the song, the shorter side — an intro or
    outro of ``SLIP['edge_beats']`` beats up to ``SLIP['edge_share']`` of the song — moves unless
    the gain says the body is the side off the beat (its notes start after its beats: gain above
    ``SLIP['body_min_gain']``, and clearly more so than the short side's): the body of a song sets
    its pulse, and sparse intros and outros (chord stabs on the off-beats, no drums) are where the
    trackers go astray. Chords comped on the off-beats raise the gain of a body on the beat, so the
    body gives way only to a clear gain. A body whose notes start on its beats does not give way to
    an intro whose notes start there even more clearly. Shorter end parts stay (most single slips
    that near an end are end effects on a correct grid). At the section borders a beat is dropped or
    inserted so that every interval stays within 0.75-1.25 of the local one. ``times`` (K,) s.
    Returns (beat times (K',), number of beats moved)."""
    t = np.asarray(times, dtype=np.float64)
    centres, _ = find_slips(t)
    offset = np.zeros(len(t))  # 0 or 0.5 beat against the first beat's pulse
    for k in centres:
        offset[k:] = (offset[k:] + 0.5) % 1.0
    off = offset > 0.25
    if not off.any():
        return t, 0
    # the side on the off-beats: its notes start half a beat after its beats
    gain_off, gain_on = float(gain[off].mean()), float(gain[~off].mean())
    off_moves = gain_off > gain_on
    clear = abs(gain_off - gain_on) > SLIP["side_margin"]
    # one slip: the two sides are the song's start and end; a short one is an intro or outro
    off_short = off.sum() <= len(off) / 2
    short = off if off_short else ~off
    body_gain = gain_on if off_short else gain_off
    body_off = clear and off_moves != off_short and body_gain > SLIP["body_min_gain"]
    edge = (
        np.count_nonzero(np.diff(off)) == 1
        and SLIP["edge_beats"] <= short.sum() <= SLIP["edge_share"] * len(t)
        and not body_off
    )
    to_move = short if edge else (off if off_moves else ~off)
    nxt = _next_intervals(t)
    idx = np.flatnonzero(to_move)
    moved = t.copy()
    n_moved = 0
    for seg in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
        shifted = t[seg] + 0.5 * nxt[seg]
        lo, hi = t[seg[0]] - 0.05, shifted[-1] + 0.05
        ref = reference[(reference >= lo) & (reference <= hi)]
        level = np.median(np.diff(ref)) / np.median(nxt[seg]) if len(ref) > 2 else 0.0
        agree = (
            any(lo <= level <= hi for lo, hi in (SLIP["same_level"], SLIP["half_level"]))
            and beat_f_measure(ref, shifted) >= beat_f_measure(ref, t[seg]) + SLIP["agree_margin"]
        )
        if edge or agree or (clear and gain[seg].mean() > SLIP["min_gain"]):
            moved[seg] = shifted
            n_moved += len(seg)
    if not n_moved:
        return t, 0
    return _rejoin(moved, t), n_moved


def find_slips(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where a beat grid slips by a fraction of a beat at a steady tempo.

    Slips are found in the grid's phase drift against the running interquartile mean interval
    (``SLIP['context']`` beats): a change of ``SLIP['min']``-``SLIP['max']`` beat over ``2 *
    SLIP['window']`` beats with the same tempo before and after. The decoder's beats lie on 20 ms
    frames, so at 172 BPM (17.4 frames) its intervals alternate 17 and 18 frames: their median (17)
    is 2.5 % short and the drift against it grows by a quarter beat every ten beats: false slips in
    a steady grid. The interquartile mean keeps the fraction and still ignores the slip's own odd
    intervals. ``times`` (K,) s. Returns (centres, splits), int arrays (S,): per slip the beat at
    the centre of the window it was measured over, and the beat after the window's most irregular
    interval (where the grid jumped: the first beat of the new section)."""
    t = np.asarray(times, dtype=np.float64)
    w = SLIP["window"]
    centres: list[int] = []
    splits: list[int] = []
    if len(t) < 4 * w + 2:
        return np.asarray(centres, dtype=np.int64), np.asarray(splits, dtype=np.int64)
    ibi = np.diff(t)
    # the running interquartile mean: the middle half of each sorted window of intervals
    n = SLIP["context"]
    windows = np.lib.stride_tricks.sliding_window_view(np.pad(ibi, n // 2, mode="edge"), n)
    local = np.sort(windows, axis=1)[:, n // 4 : n - n // 4].mean(axis=1)
    drift = np.r_[0.0, np.cumsum(ibi / local - 1.0)]  # (K,) beats the grid has slipped by

    def irregular_at(k: int) -> np.ndarray:
        return np.abs(ibi[k - w : k + w] / local[k - w : k + w] - 1.0)

    def slide(k: int) -> float:  # the largest phase change over 4 intervals of the window
        return float(np.abs(drift[k - w + 4 : k + w + 1] - drift[k - w : k + w - 3]).max())

    k = w
    while k < len(t) - w:
        step = abs(drift[k + w] - drift[k - w])
        before = ibi[max(k - w - 8, 0) : k - w]
        after = ibi[k + w : k + w + 8]
        if (
            SLIP["min"] <= step <= SLIP["max"]
            and len(before)
            and len(after)
            and abs(np.median(after) / np.median(before) - 1.0) <= SLIP["same_tempo"]
            and (
                irregular_at(k).max() >= SLIP["min_jump"]
                or slide(k) >= SLIP["min_concentration"] * step
            )
        ):
            centres.append(k)
            splits.append(k - w + int(np.argmax(irregular_at(k))) + 1)
            k += 2 * w
        else:
            k += 1
    return np.asarray(centres, dtype=np.int64), np.asarray(splits, dtype=np.int64)


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


@dataclass
class _Spectral:
    """Frame-rate (50 fps) curves from one STFT: onset strength (T,), chroma (12, T), bass
    onsets (T,), noise onsets in the snare band (T,) and the frames' RMS level (T,)."""

    onset_env: np.ndarray
    chroma: np.ndarray
    bass_onset: np.ndarray
    snare_onset: np.ndarray
    level: np.ndarray


def _spectral(y22: np.ndarray, n_fft: int = 2048, chunk: int = 2048) -> _Spectral:
    """librosa's onset strength (log-power mel flux), chroma and a bass onset curve, computed
    from one centred STFT taken in chunks of frames, so memory stays ~20 MB for any length
    (librosa's own calls hold several full spectrograms: 1.3 GB for 15 minutes).

    The chroma leaves out the bins below 200 Hz, which the bass curve covers: it is the chords'
    harmony. A syncopated or walking bass moves inside the bar and an anticipated root arrives
    half a beat early, so with the bass in it the chroma changes where the bass moves, not where
    the chords do (docs/music.md).

    The snare curve is the spectral flux of the 1-5 kHz band (``SNARE_BAND_HZ``: snare wires and
    claps; hi-hats and cymbals sit above it) weighted by the band's spectral flatness, so that
    noise bursts count and notes, whose harmonics also fill the band, hardly do."""
    import librosa

    n_frames = 1 + len(y22) // HOP  # librosa's centred framing
    padded = np.zeros(n_frames * HOP + n_fft, dtype=np.float32)
    padded[n_fft // 2 : n_fft // 2 + len(y22)] = y22
    frames = np.lib.stride_tricks.sliding_window_view(padded, n_fft)[::HOP][:n_frames]
    window = librosa.filters.get_window("hann", n_fft, fftbins=True).astype(np.float32)
    mel_fb = librosa.filters.mel(sr=SR, n_fft=n_fft)
    chroma_fb = librosa.filters.chroma(sr=SR, n_fft=n_fft, tuning=0.0)
    n_bass = int(200 * n_fft / SR)  # bins below 200 Hz
    snare_band = slice(*(int(np.ceil(hz * n_fft / SR)) for hz in SNARE_BAND_HZ))  # bins
    mel = np.empty((mel_fb.shape[0], n_frames), dtype=np.float32)
    chroma = np.empty((12, n_frames), dtype=np.float32)
    bass = np.empty(n_frames, dtype=np.float32)
    snare = np.empty(n_frames, dtype=np.float32)
    level = np.empty(n_frames, dtype=np.float32)
    last = None  # the previous chunk's last frame of snare-band log power
    for a in range(0, n_frames, chunk):
        b = min(a + chunk, n_frames)
        mag = np.abs(np.fft.rfft(frames[a:b] * window, axis=1)).astype(np.float32).T
        power = mag**2
        mel[:, a:b] = mel_fb @ power
        chroma[:, a:b] = chroma_fb[:, n_bass:] @ power[n_bass:]
        bass[a:b] = mag[:n_bass].sum(axis=0)
        level[a:b] = np.sqrt(power.mean(axis=0))
        band = np.ascontiguousarray(power.T[:, snare_band])  # (frames, bins): rows contiguous
        log_band = np.log(band + np.float32(1e-10))
        rise = np.diff(log_band, axis=0, prepend=log_band[:1] if last is None else last)
        flatness = np.exp(log_band.mean(axis=1)) / (band.mean(axis=1) + np.float32(1e-10))
        snare[a:b] = np.maximum(rise, 0.0).mean(axis=1) * flatness
        last = log_band[-1:]
    onset_env = librosa.onset.onset_strength(
        S=librosa.power_to_db(mel), sr=SR, hop_length=HOP, n_fft=n_fft
    )
    chroma = librosa.util.normalize(chroma, norm=np.inf, axis=0)  # as chroma_stft does
    bass_onset = np.maximum(np.diff(bass, prepend=bass[:1]), 0)
    return _Spectral(onset_env, chroma, bass_onset, snare, level)


def _librosa_beats(spec: _Spectral) -> tuple[np.ndarray, np.ndarray, int]:
    """librosa beats and a global bar phase: (beat times (K,), positions (K,), meter)."""
    import librosa

    onset_env = spec.onset_env

    _, frames = librosa.beat.beat_track(onset_envelope=onset_env, sr=SR, hop_length=HOP, trim=True)
    frames = np.asarray(frames, dtype=np.int64)
    times = librosa.frames_to_time(frames, sr=SR, hop_length=HOP)
    if len(frames) < 4:
        return times, np.ones(len(frames), np.int64), 4
    # per-beat accent evidence: onset strength, bass onset, harmonic change at the beat
    n = len(onset_env)
    fr = np.clip(frames, 0, n - 1)
    accent = (
        zscore(onset_env[fr])
        + zscore(spec.bass_onset[fr])
        + zscore(harmonic_change(spec.chroma, frames))
    )
    best = (-np.inf, 4, 0)
    for meter in (3, 4):
        for phase in range(meter):
            on = accent[(np.arange(len(frames)) - phase) % meter == 0]
            score = float(on.mean() - accent.mean())
            if meter == 3:
                score -= 0.1  # 4/4 unless 3/4 is clearly better supported
            if score > best[0]:
                best = (score, meter, phase)
    _, meter, phase = best
    positions = (np.arange(len(frames)) - phase) % meter + 1
    return times, positions.astype(np.int64), meter


def _decode_at_level(
    ev: Evidence, params: BeatParams, bpm: float
) -> barpointer.DecodedBeats | None:
    """The bar-pointer decode of ``ev.act`` with its tempo held within ``LEVEL_BAND`` of ``bpm`` or
    of twice it (when that fits under the decoder's ``max_bpm``), whichever path is likelier, or
    None when it fails the no-beat test (:func:`_usable`; ``ev.values`` is not touched): a dotted
    pulse found in the onsets (:func:`dotted_pulse`) may be the beat or every other beat (the
    likelier path tells which), and of the two octaves a grid switched between
    (:func:`octave_switch`) one is kept for the whole song."""
    act = ev.act
    assert act is not None  # the re-decode steps run only on a BeatNet grid
    band = 1.0 + LEVEL_BAND
    dp = params.decoder
    levels = [bpm] + ([2 * bpm] if 2 * bpm <= dp.max_bpm else [])
    decodes = [
        barpointer.decode(act, replace(dp, min_bpm=level / band, max_bpm=level * band))
        for level in levels
    ]
    best = max(decodes, key=lambda d: d.log_prob)
    usable = _usable(best.times, act, ev.spec, dict(ev.values), "beatnet")[0]
    return best if usable else None


def _nearest(times: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(K,) index of the beat of ``reference`` (M,) nearest to each of ``times`` (K,)."""
    return np.abs(times[:, None] - reference[None, :]).argmin(axis=1)


def _frames_tracked(times: np.ndarray, decoded: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K,) frame index of each beat of ``times`` (K,) and (K,) bool: the decoder's own beat
    (``decoded`` (M,) s) is within 2 frames — where a mend moved or inserted a beat, the
    network's downbeat activation is not about it."""
    frames = np.round(times * FPS).astype(np.int64)
    return frames, np.abs(times[:, None] - decoded[None, :]).min(axis=1) <= 2 / FPS


def _loudness(y22: np.ndarray) -> float:
    """95th percentile of the RMS of 0.5 s blocks (the level of the loud parts)."""
    n = int(0.5 * SR)
    k = max(len(y22) // n, 1)
    blocks = np.resize(y22, k * n).reshape(k, n).astype(np.float64)
    return float(np.percentile(np.sqrt((blocks**2).mean(axis=1)), 95))


def _active_span(y22: np.ndarray) -> float:
    """Seconds of audio whose 0.5 s RMS is above -60 dBFS relative to the loudest part."""
    n = int(0.5 * SR)
    k = len(y22) // n
    if k == 0:
        return len(y22) / SR
    rms = np.sqrt((y22[: k * n].reshape(k, n).astype(np.float64) ** 2).mean(axis=1))
    return float((rms > rms.max() * 1e-3).sum() * 0.5)


def _two_bars_per_bar(
    times: np.ndarray,
    positions: np.ndarray,
    per_bar: int,
    halved: bool,
    act: np.ndarray,
    frames: np.ndarray,
    tracked: np.ndarray,
    spec: _Spectral,
) -> str | None:
    """Why the bars of a slow grid (``times`` (K,) s, ``positions`` (K,) in bars of
    ``per_bar``) hold two bars of the music each, or None. 2-beat bars (the bar grouping found
    their two beats alike; not on a halved grid): always. 4-beat bars (not halved): their third
    beat is marked almost as strongly as their first (:func:`~dancegraph.music.bargroup.
    half_bar_contrast` under ``SPLIT['max_contrast']``). 3-beat bars: two 3-beat bars of a fast
    waltz, the second starting half-way through the second tracked beat — on the split grid
    the music repeats after 3 beats as closely as after 6 (``SPLIT['max_repeat_gap']``) and the
    harmony changes in the middle of the tracked bar almost as much as at its start
    (:func:`~dancegraph.music.bargroup.fold_contrast` under ``SPLIT['max_harmony_contrast']``);
    a slow waltz's middle is the off-beat of its second beat. Never when the notes between the
    beats come after their middle (``SWING['min_swung']``): those are the swung eighths of a
    slow song, while a fast song's beats halve the interval (a 70 BPM swung song was split)."""
    between, _ = _eighth_phase(beat_phase_profile(spec.onset_env, times, SWING["bins"]))
    if between >= SWING["min_swung"]:
        return None
    if per_bar == 2:
        return None if halved else "bars of 2 beats"
    if per_bar == 4:
        if halved:
            return None
        contrast = half_bar_contrast(
            downbeat_evidence(act, frames, spec.chroma, tracked), positions
        )
        if contrast < SPLIT["max_contrast"]:
            return (
                f"4-beat bars marked in the middle almost as at the start (contrast {contrast:.2f})"
            )
        return None
    split, _ = split_beats(times, positions, per_bar)
    split_frames = np.round(split * FPS).astype(np.int64)
    x = beat_features(spec.onset_env, spec.bass_onset, spec.chroma, split_frames)
    repeat_gap = lag_distance(x, 3) - lag_distance(x, 6)
    harmony = zscore(harmonic_change(spec.chroma, split_frames))
    contrast = fold_contrast(harmony, _split_cycle(positions), 2 * per_bar)
    if repeat_gap < SPLIT["max_repeat_gap"] and contrast < SPLIT["max_harmony_contrast"]:
        return (
            f"3-beat bars holding two 3-beat bars (repeats after 3 split beats as after 6: "
            f"{repeat_gap:+.2f}; harmony contrast {contrast:.2f})"
        )
    return None


@dataclass
class Evidence:
    """What the steps of one song read: BeatNet's beat/downbeat activations ``act`` (T, 2) at 50
    fps (None where its weights are missing or ``method='librosa'``), the spectral curves
    ``spec`` of the level-raised audio, and ``values``, the numbers behind the no-beat test and
    the confidence. Built once by :func:`beat_evidence`; the steps do not change it."""

    act: np.ndarray | None
    spec: _Spectral
    values: dict
    models: tuple[int, ...] = DEFAULT_MODELS
    notes: list[str] = field(default_factory=list)
    _librosa: tuple[np.ndarray, np.ndarray, int] | None = None

    def librosa_beats(self) -> tuple[np.ndarray, np.ndarray, int]:
        """The librosa tracker's (beat times (K,), positions (K,), meter), computed once."""
        if self._librosa is None:
            self._librosa = _librosa_beats(self.spec)
        return self._librosa


@dataclass(frozen=True)
class Grid:
    """A beat grid between steps: ``times`` (K,) s, ``positions`` (K,) (1 = downbeat) and
    ``meters`` (K,) beats per bar; ``decoded`` (M,) s the decoder's own beats (where the
    network's downbeat activation is about the beat); ``halved``: a step kept every other beat
    of the decoder's (its meter is no prior); ``subdivision``: what sounds between the decoder's
    beats (:func:`subdivision_strength`), once measured."""

    times: np.ndarray
    positions: np.ndarray
    meters: np.ndarray
    decoded: np.ndarray
    halved: bool = False
    subdivision: float | None = None

    @classmethod
    def from_decoded(cls, dec: barpointer.DecodedBeats) -> Grid:
        return cls(dec.times, dec.positions, dec.meters, dec.times)

    def moved(self, times: np.ndarray) -> Grid:
        """The grid with its beats moved to ``times`` (K',) s, each taking the position and
        meter of the nearest beat before the move."""
        near = _nearest(np.asarray(times, dtype=np.float64), self.times)
        return replace(self, times=times, positions=self.positions[near], meters=self.meters[near])

    def frames(self) -> tuple[np.ndarray, np.ndarray]:
        """(K,) frame of each beat and (K,) bool: the decoder's own beat (:func:`_frames_tracked`)."""
        return _frames_tracked(self.times, self.decoded)


#: a step: (grid, evidence, params) -> (new grid, warnings)
StepFn = Callable[[Grid, Evidence, "BeatParams"], tuple[Grid, list[str]]]


def _redecoded(
    grid: Grid, ev: Evidence, params: BeatParams, bpm: float | None, message: str
) -> tuple[Grid, list[str]]:
    """The grid decoded again at ``bpm`` (:func:`_decode_at_level`; unchanged for None or where
    that fails), with ``message`` as its warning, ``{new}`` formatted with the new tempo."""
    again = None if bpm is None else _decode_at_level(ev, params, bpm)
    if again is None:
        return grid, []
    return Grid.from_decoded(again), [message.format(new=tempo_from_beats(again.times)[0])]


def _dotted_pulse_step(grid: Grid, ev: Evidence, params: BeatParams) -> tuple[Grid, list[str]]:
    """Decode again where the decoder held a dotted pulse of the song (:func:`dotted_pulse`)."""
    pulse = dotted_pulse(grid.decoded, ev.spec.onset_env)
    message = (
        f"beat_level_corrected: the tracked beat at {tempo_from_beats(grid.decoded)[0]:.1f} BPM "
        f"was a dotted pulse (3:2) of the song's, whose onsets repeat at {pulse or 0:.1f} BPM; "
        "decoded again at that level or its double: {new:.1f} BPM"
    )
    return _redecoded(grid, ev, params, pulse, message)


def _one_octave_step(grid: Grid, ev: Evidence, params: BeatParams) -> tuple[Grid, list[str]]:
    """Decode again at one level a grid that jumps between two tempo octaves
    (:func:`octave_switch`)."""
    slow = octave_switch(grid.decoded) or 0.0
    message = (
        f"beat_level_unified: the decoder counted some sections at twice the tempo of others "
        f"({slow:.1f} and {2 * slow:.1f} BPM); decoded again at one level: {{new:.1f}} BPM"
    )
    return _redecoded(grid, ev, params, slow or None, message)


def _halve_step(grid: Grid, ev: Evidence, params: BeatParams) -> tuple[Grid, list[str]]:
    """Keep every other beat of a grid with nothing sounding between its beats
    (:func:`subdivision_strength`, :func:`half_beat_parity`)."""
    spec = ev.spec
    sub = subdivision_strength(spec.onset_env, grid.times)
    grid = replace(grid, subdivision=sub)
    half_bpm = tempo_from_beats(grid.times)[0] / 2
    if sub >= DOUBLE["max_subdivision"] or half_bpm < DOUBLE["min_half_bpm"] or ev.act is None:
        return grid, []
    # the beats are the half the notes start on (the other half: the "and"s)
    parity = half_beat_parity(
        grid.times, ev.act, spec.onset_env, spec.bass_onset, spec.chroma, spec.snare_onset
    )
    keep = np.arange(len(grid.times)) % 2 == (0 if parity >= 0 else 1)
    # the kept beats counted in 4 from the first that was a downbeat (the bar grouping, which
    # needs 16 beats, decides again): the decoder's positions of every other eighth (1 3 1 3)
    # form no bar
    downbeats = np.flatnonzero(grid.positions[keep] == 1)
    first = int(downbeats[0]) if len(downbeats) else 0
    counted = (np.arange(int(keep.sum())) - first) % 4 + 1
    halved = replace(
        grid,
        times=grid.times[keep],
        positions=counted.astype(np.int64),
        meters=np.full(len(counted), 4, dtype=np.int64),
        halved=True,
    )
    note = (
        f"beats_halved: nothing sounds between the tracked beats (subdivision {sub:.2f}): they "
        f"were the eighths; every other one kept, {half_bpm:.1f} BPM"
    )
    return halved, [note]


def _swing_step(grid: Grid, ev: Evidence, params: BeatParams) -> tuple[Grid, list[str]]:
    """Move onto the beat a grid or sections on the swung off-beats (:func:`mend_swing_off_beats`)."""
    times, swing = mend_swing_off_beats(grid.times, ev.spec.onset_env)
    if not swing:
        return grid, []
    note = (
        f"beat_swing_mended: beats sat on the swung off-beats (the whole grid, or sections "
        f"between slips); moved up to {swing:.2f} beat later, onto the onsets the swing leads to"
    )
    return grid.moved(times), [note]


def _slip_step(grid: Grid, ev: Evidence, params: BeatParams) -> tuple[Grid, list[str]]:
    """Move back the sections a tracker put on the off-beats (:func:`mend_half_beat_slips`)."""
    gain = off_beat_gain(grid.times, ev.spec.onset_env, ev.spec.chroma)
    times, moved = mend_half_beat_slips(grid.times, ev.librosa_beats()[0], gain)
    if not moved:
        return grid, []
    note = (
        f"beat_slip_mended: {moved} beats a section put on the off-beats moved half a beat, "
        "onto the pulse of the rest of the song"
    )
    return grid.moved(times), [note]


def _off_beat_grid_step(grid: Grid, ev: Evidence, params: BeatParams) -> tuple[Grid, list[str]]:
    """Move a whole grid on the straight off-beats half a beat (:func:`mend_off_beat_grid`)."""
    times, score = mend_off_beat_grid(grid.times, ev.spec.onset_env, ev.spec.chroma)
    if score <= OFF_BEAT["min_score"]:
        return grid, []
    note = (
        f"beat_phase_shifted: the whole grid sat on the off-beats (pitched onsets and onset "
        f"strength prefer the beats half a beat later, score {score:.2f}); all moved half a beat"
    )
    return grid.moved(times), [note]


def _group_step(grid: Grid, ev: Evidence, params: BeatParams) -> tuple[Grid, list[str]]:
    """Meter and bar phase from the music (:func:`~dancegraph.music.bargroup.group_beats`)."""
    if ev.act is None:
        return grid, []
    spec = ev.spec
    frames, tracked = grid.frames()
    positions, meters, notes = group_beats(
        grid.positions, grid.meters, ev.act, frames, spec.onset_env, spec.bass_onset, spec.chroma,
        tracked, meter_prior=not grid.halved, snare_onset=spec.snare_onset,
    )  # fmt: skip
    return replace(grid, positions=positions, meters=meters), notes


def _split_step(grid: Grid, ev: Evidence, params: BeatParams) -> tuple[Grid, list[str]]:
    """Split every beat of a slow grid whose bars hold two bars of the music
    (:func:`_two_bars_per_bar`, :func:`split_beats`) and group the bars again."""
    if ev.act is None:
        return grid, []
    spec = ev.spec
    sub = grid.subdivision
    if sub is None:
        sub = subdivision_strength(spec.onset_env, grid.times)
    bpm = tempo_from_beats(grid.times)[0]
    per_bar = int(grid.meters[0])
    if bpm >= SPLIT["max_bpm"] or not (grid.halved or sub >= DOUBLE["max_subdivision"]):
        return grid, []
    frames, tracked = grid.frames()
    why = _two_bars_per_bar(
        grid.times, grid.positions, per_bar, grid.halved, ev.act, frames, tracked, spec
    )
    if not why:
        return grid, []
    times, positions = split_beats(grid.times, grid.positions, per_bar)
    frames, tracked = _frames_tracked(times, grid.decoded)
    positions, meters, notes = group_beats(
        positions, np.full(len(times), 3 if per_bar == 3 else 4), ev.act, frames, spec.onset_env,
        spec.bass_onset, spec.chroma, tracked, meter_prior=False, snare_onset=spec.snare_onset,
    )  # fmt: skip
    note = (
        f"beats_split: {why} at {bpm:.1f} BPM: the beats were half notes; each split in two, "
        f"{2 * bpm:.1f} BPM, bars regrouped"
    )
    return replace(grid, times=times, positions=positions, meters=meters), [note, *notes]


def _within_sound_step(grid: Grid, ev: Evidence, params: BeatParams) -> tuple[Grid, list[str]]:
    """Drop the beats before the first onset and after the last (:func:`within_sound`)."""
    sounding = within_sound(grid.times, ev.spec.onset_env)
    if sounding.all():
        return grid, []
    ev.values["beats_outside_sound"] = int((~sounding).sum())
    kept = replace(
        grid,
        times=grid.times[sounding],
        positions=grid.positions[sounding],
        meters=grid.meters[sounding],
    )
    return kept, []


#: The steps after the decoder, in the order they run; each can be switched off by name
#: (``BeatParams.steps``). What each does to real and generated music: docs/music.md.
#: ``within_sound`` runs before ``group``: beats the decoder counted in a leading or trailing
#: silence are no evidence of where the bars start (with them in, a second of silence before a
#: recording moved its downbeats: docs/music.md).
STEPS: tuple[tuple[str, StepFn], ...] = (
    ("dotted_pulse", _dotted_pulse_step),
    ("one_octave", _one_octave_step),
    ("halve", _halve_step),
    ("swing", _swing_step),
    ("slips", _slip_step),
    ("off_beat_grid", _off_beat_grid_step),
    ("within_sound", _within_sound_step),
    ("group", _group_step),
    ("split", _split_step),
)


#: The steps that run by default: those that do not cost real recordings with human annotations
#: and keep the generated regression suite on target. Off: ``one_octave`` and ``split`` double
#: grids the networks track steadily and ``halve`` halves them, ``swing`` and ``off_beat_grid``
#: move right grids onto the off-beats. What each does to both: docs/music.md.
DEFAULT_STEPS = frozenset({"dotted_pulse", "slips", "group", "within_sound"})


@dataclass(frozen=True)
class BeatParams:
    """The parameters of :func:`track_beats`: ``models`` the BeatNet models whose activations are
    averaged (an ensemble: fewer of one model's mistakes), ``decoder`` the bar-pointer decoder's
    parameters (``barpointer.MADMOM`` reproduces BeatNet), ``steps`` the names of :data:`STEPS` that
    run (in :data:`STEPS` order, whatever the order here)."""

    models: tuple[int, ...] = DEFAULT_MODELS
    decoder: barpointer.BarPointerParams = barpointer.DEFAULT
    steps: frozenset[str] = DEFAULT_STEPS

    def __post_init__(self) -> None:
        unknown = set(self.steps) - {name for name, _ in STEPS}
        if unknown:
            raise ValueError(f"unknown steps {sorted(unknown)}; known: {[n for n, _ in STEPS]}")

    def without(self, *names: str) -> BeatParams:
        """These parameters with the steps ``names`` switched off."""
        return replace(self, steps=self.steps - set(names))

    def with_steps(self, *names: str) -> BeatParams:
        """These parameters with the steps ``names`` switched on (ValueError for unknown ones)."""
        return replace(self, steps=self.steps | set(names))


#: BeatNet 1.1.3 itself: model 1, its own decoder settings, no step after the decoder
BEATNET_1_1_3 = BeatParams(models=(1,), decoder=barpointer.MADMOM, steps=frozenset())


def run_steps(grid: Grid, ev: Evidence, params: BeatParams) -> tuple[Grid, list[str]]:
    """Run the steps of :data:`STEPS` that ``params.steps`` names, in order, on ``grid``.
    Returns the last grid and the steps' warnings in order."""
    warnings: list[str] = []
    for name, step in STEPS:
        if name in params.steps:
            grid, notes = step(grid, ev, params)
            warnings.extend(notes)
    return grid, warnings


def beat_evidence(
    y: np.ndarray, sr: int, *, method: str = "auto", models: tuple[int, ...] = DEFAULT_MODELS
) -> Evidence:
    """Check the audio and compute what the steps read (:class:`Evidence`).

    ``y`` (N,) float mono at ``sr`` Hz; ``method`` 'auto' (BeatNet, librosa where its weights
    are missing: warning ``beatnet_weights_missing`` in ``Evidence.notes``), 'beatnet' or
    'librosa' (no activations). Raises ``AudioError`` (``audio_too_long`` over 20 minutes,
    ``audio_too_short`` under 3 s, ``no_beat`` for silence), ``ModelFileError``
    (``model_missing`` with ``method='beatnet'`` and no weights), ``ValueError`` for a shape or
    method that is not one of these.
    """
    y = np.asarray(y, dtype=np.float32)
    if y.ndim != 1:
        raise ValueError(f"track_beats needs mono audio (N,), got shape {y.shape}")
    if method not in ("auto", "beatnet", "librosa"):
        raise ValueError(f"method must be auto, beatnet or librosa, got {method!r}")
    if len(y) > DEFAULT_MAX_SECONDS * sr:  # the decoder's memory grows with the length
        raise AudioError(
            f"{len(y) / sr / 60:.1f} min of audio is longer than the limit of "
            f"{DEFAULT_MAX_SECONDS / 60:.0f} min",
            code="audio_too_long",
        )
    if len(y) < 3 * sr:
        raise AudioError(
            f"{len(y) / sr:.2f} s of audio is too short for beat tracking", code="audio_too_short"
        )
    y = np.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0)
    rms = float(np.sqrt(np.mean(y.astype(np.float64) ** 2)))
    if rms < NO_BEAT["silence_rms"]:
        raise AudioError(f"no beat: the audio is silent (RMS {rms:.1e})", code="no_beat")
    y22 = resample(y, sr, SR)
    values: dict = {"rms": rms, "active_s": _active_span(y22)}
    # BeatNet's log-magnitude features are not level-invariant (a song 20 dB down reads as "no
    # beat"): raise quiet input to the level of ordinary mastered music, never lower loud input
    level = _loudness(y22)
    gain = min(TARGET_LEVEL / level, MAX_GAIN) if 0 < level < TARGET_LEVEL else 1.0
    if gain > 1.0:
        y22 = y22 * np.float32(gain)
    values["gain_db"] = float(20 * np.log10(gain))
    act, notes = None, []
    if method != "librosa":
        from dancegraph.music.beatnet import activations

        try:
            act = activations(y22, models)
        except ModelFileError as exc:
            if method == "beatnet":
                raise
            notes.append(f"beatnet_weights_missing: {exc.message}; librosa fallback used")
    return Evidence(act=act, spec=_spectral(y22), values=values, models=models, notes=notes)


def track_beats(
    y: np.ndarray, sr: int, *, method: str = "auto", params: BeatParams | None = None
) -> BeatTracking:
    """Beats, downbeats, meter and tempo of mono audio.

    Args:
        y: (N,) float mono samples.
        sr: their sample rate in Hz.
        method: 'auto' (BeatNet, librosa as fallback), 'beatnet' (no fallback) or 'librosa'.
        params: the models, the decoder and the steps (:class:`BeatParams`; default all).

    Raises:
        AudioError: ``no_beat`` when no usable beat is found; ``audio_too_short`` under 3 s;
            ``audio_too_long`` over 20 minutes (as :func:`~dancegraph.music.decode.load_audio`).
        ModelFileError: ``model_missing`` with ``method='beatnet'`` and no weights installed.
    """
    jit.ensure("music")  # compiles into the shared kernel cache only under its lock
    params = params or BeatParams()
    return track_evidence(beat_evidence(y, sr, method=method, models=params.models), params)


def track_evidence(ev: Evidence, params: BeatParams | None = None) -> BeatTracking:
    """:func:`track_beats` on evidence already computed (:func:`beat_evidence` with the same
    ``params.models``, else ValueError): decode, the no-beat test, the steps, tempo and
    confidence. The evidence is not changed, so one evidence serves many parameters (the
    benchmarks). Raises ``AudioError`` ``no_beat`` as :func:`track_beats`."""
    params = params or BeatParams()
    if ev.act is not None and tuple(ev.models) != tuple(params.models):
        raise ValueError(f"evidence of models {ev.models}, parameters of {params.models}")
    values = dict(ev.values)
    ev = replace(ev, values=values)
    warnings = list(ev.notes)
    onset_env = ev.spec.onset_env
    if ev.act is not None:
        dec = barpointer.decode(ev.act, params.decoder)
        ok, why = _usable(dec.times, ev.act, ev.spec, values, prefix="beatnet")
        if not ok:  # BeatNet's verdict is final: librosa is no better judge of "no beat"
            raise AudioError(f"no beat: {why}", code="no_beat")
        weak = bool(why)
        if weak:
            warnings.append(f"weak_pulse: the beat is faint ({why}); beats and bars less sure")
        grid, notes = run_steps(Grid.from_decoded(dec), ev, params)
        warnings.extend(notes)
        name, times, positions, meters = "beatnet", grid.times, grid.positions, grid.meters
    else:
        lt, lp, lm = ev.librosa_beats()
        ok, why = _usable(lt, None, ev.spec, values, prefix="librosa")
        if not ok:
            raise AudioError(f"no beat: {why}", code="no_beat")
        weak = bool(why)
        if weak:
            warnings.append(f"weak_pulse: the beat is faint ({why}); beats and bars less sure")
        grid = Grid(lt, lp, np.full(len(lt), lm), lt)
        if "within_sound" in params.steps:  # the fallback's grid gets no other step
            grid, _ = _within_sound_step(grid, ev, params)
        name, times, positions, meters = "librosa", grid.times, grid.positions, grid.meters
    values_m, counts = np.unique(meters, return_counts=True)
    meter = int(values_m[np.argmax(counts)])
    if len(values_m) > 1:
        warnings.append(f"meter_change: beats in meters {', '.join(map(str, values_m.tolist()))}")
    tempo = estimate_tempo(times, onset_env, FPS)
    warnings.extend(tempo.warnings)
    confidence = tempo.confidence
    if name == "beatnet":
        lib_times = ev.librosa_beats()[0]
        agree = beat_f_measure(times, lib_times)
        # None where librosa found under 3 beats (no tempo)
        rel = metrical_relation(tempo.bpm, tempo_from_beats(lib_times)[0])
        values["librosa_agreement"] = agree
        values["librosa_relation"] = rel
        # librosa at another metrical level still supports the pulse: half credit
        vote_score = max(agree, 0.5 if rel not in (None, "x1") else 0.0)
        confidence = float(np.clip(0.6 * confidence + 0.4 * vote_score, 0.0, 1.0))
    else:
        confidence *= 0.7  # the fallback's downbeat phase is right about half the time
    if weak:
        confidence *= WEAK_PULSE_CONFIDENCE
    values["tempo"] = {
        "regularity": tempo.regularity,
        "salience": tempo.salience,
        "alternatives": tempo.alternatives,
        "octave": tempo.octave,
    }
    return BeatTracking(
        beats=np.asarray(times, dtype=np.float64),
        beat_positions=np.asarray(positions, dtype=np.int64),
        downbeats=np.asarray(times[positions == 1], dtype=np.float64),
        meter=meter,
        tempo_bpm=float(tempo.bpm),
        tempo_confidence=float(confidence),
        method=name,
        warnings=warnings,
        evidence=values,
    )


#: a frame is a pause where its RMS level is under this share (-14 dB) of the level about it:
#: a gap between words, deeper than the dips of a rhythm part ...
PAUSE_RATIO = 0.2
#: ... averaged over this many seconds (a syllable and its gap)
PAUSE_CONTEXT_S = 1.0
#: the chroma is compared with itself this far ahead: a held chord outlasts it, a syllable not
CHROMA_LAG_S = 0.25


def speech_evidence(spec: _Spectral) -> tuple[float, float]:
    """What tells speech from music with a faint pulse: (pause share, chroma persistence).

    The pause share is the share of frames whose RMS level is under ``PAUSE_RATIO`` of its mean
    over ``PAUSE_CONTEXT_S`` about it (speech stops between words and phrases; music sustains
    and reverberates). The chroma persistence is the level-weighted cosine between each frame's
    chroma and the chroma ``CHROMA_LAG_S`` later (a voice glides from syllable to syllable;
    notes and chords are held). Both in [0, 1]; 0 and 0 for audio too short to compare. Why:
    BeatNet's pulse alone can read a speaker's syllables as a faint beat."""
    from scipy.ndimage import uniform_filter1d

    level = spec.level.astype(np.float64)
    lag = int(round(CHROMA_LAG_S * FPS))
    if len(level) <= lag:
        return 0.0, 0.0
    about = uniform_filter1d(level, max(1, int(round(PAUSE_CONTEXT_S * FPS))), mode="nearest")
    pauses = float(np.mean(level < PAUSE_RATIO * about))
    a = spec.chroma[:, :-lag].astype(np.float64)
    b = spec.chroma[:, lag:].astype(np.float64)
    norms = np.linalg.norm(a, axis=0) * np.linalg.norm(b, axis=0)
    cos = (a * b).sum(axis=0) / np.maximum(norms, 1e-12)
    weight = level[:-lag]
    persistence = float((cos * weight).sum() / max(weight.sum(), 1e-12))
    return pauses, persistence


def _usable(
    times: np.ndarray, act: np.ndarray | None, spec: _Spectral, evidence: dict, prefix: str
) -> tuple[bool, str]:
    """The no-beat test for one tracker; fills ``evidence`` and returns (usable, why not, or
    why the pulse is weak where usable; "" for a clear pulse).

    The decoder always finds *some* regular beat, so regularity alone proves nothing. What
    separates music from speech, noise and steady tones is the pulse: the activation (or onset
    strength) at the beats against its mean (contrast) and its periodicity at the beat period
    (salience; where BeatNet's contrast is clear, at two beats or half a beat if higher there).
    Their product is the pulse strength: soft classical music has little contrast and a solid
    metal wall of drums little contrast too, but each beats speech on the product. A pulse
    with a faint contrast or salience at the beat itself is usable with a ``weak_pulse``
    warning, unless the audio pauses like speech and its harmony does not hold
    (:func:`speech_evidence`): then it is speech, not music.
    """
    onset_env = spec.onset_env
    times = np.asarray(times)
    n = len(times)
    evidence[f"{prefix}_beats"] = n
    if n < NO_BEAT["min_beats"]:
        return False, f"{n} beats found"
    coverage = float(times[-1] - times[0]) / max(evidence["active_s"], 1e-9)
    bpm, regularity = tempo_from_beats(times)
    evidence[f"{prefix}_coverage"] = coverage
    evidence[f"{prefix}_regularity"] = regularity
    curve = act.sum(axis=1) if act is not None else onset_env
    peak = peak_near(curve, np.round(times * FPS))
    contrast = float(peak.mean() / max(curve.mean(), 1e-9))
    salience = pulse_salience(curve, FPS, bpm)
    limits = NO_BEAT["beatnet"] if act is not None else NO_BEAT["librosa"]
    # a network firing clearly at the beats whose activation repeats every two beats or every
    # half beat instead (half-time drums, a syncopated figure) still has a pulse
    pulse = salience
    if act is not None and contrast >= limits["clear_contrast"]:
        pulse = max(salience, *(pulse_salience(curve, FPS, bpm * r) for r in (0.5, 2.0)))
    strength = contrast * pulse
    evidence[f"{prefix}_peak"] = float(peak.mean())
    evidence[f"{prefix}_contrast"] = contrast
    evidence[f"{prefix}_salience"] = salience
    evidence[f"{prefix}_level_salience"] = pulse
    evidence[f"{prefix}_strength"] = strength
    if peak.mean() < limits["min_peak"]:
        return False, f"weak beat evidence (peak {peak.mean():.2f} < {limits['min_peak']})"
    if contrast < limits["min_contrast"]:
        return False, f"no beat contrast ({contrast:.2f} < {limits['min_contrast']})"
    if salience < limits["min_salience"]:
        return False, f"no periodic pulse (salience {salience:.2f} < {limits['min_salience']})"
    if strength < limits["min_strength"]:
        return False, (
            f"no pulse (strength {strength:.2f} < {limits['min_strength']}: contrast "
            f"{contrast:.2f}, salience {salience:.2f})"
        )
    if coverage < NO_BEAT["min_coverage"]:
        return False, f"beats cover only {coverage:.0%} of the sound"
    if regularity < NO_BEAT["min_regularity"]:
        return False, f"irregular beat intervals (regularity {regularity:.2f})"
    if contrast < limits["clear_contrast"] or salience < limits["clear_salience"]:
        pauses, persistence = speech_evidence(spec)
        evidence["pause_share"] = pauses
        evidence["chroma_persistence"] = persistence
        if pauses >= NO_BEAT["speech_pauses"] and persistence < NO_BEAT["speech_chroma"]:
            return False, (
                f"a faint pulse in speech-like sound (pauses in {pauses:.0%} of the frames, "
                f"chroma persistence {persistence:.2f}; strength {strength:.2f})"
            )
        return True, f"contrast {contrast:.2f}, salience {salience:.2f}, strength {strength:.2f}"
    return True, ""


def warm_up() -> None:
    """Compile the decoder, load the models and run librosa's kernels once, so the first song
    does not pay for compilation; never raises. Registered as ``music`` with ``dancegraph.jit``,
    which runs it under the kernel cache's lock."""
    jit.import_cached("librosa.beat")  # its one uncached gufunc, cached (see jit.import_cached)
    barpointer.warm_up()
    try:
        from dancegraph.music.beatnet import load_model

        load_model(1)
    except ModelFileError as exc:
        _warnings.warn(
            f"BeatNet weights missing, librosa fallback will be used: {exc.message}", stacklevel=2
        )
    # 6 s of clicks at 120 BPM through the whole path (librosa's numba kernels included)
    y = np.zeros(6 * SR, dtype=np.float32)
    click = np.exp(-np.arange(400) / 60.0).astype(np.float32) * np.sin(np.arange(400) * 0.6).astype(
        np.float32
    )
    for t in np.arange(0.25, 6.0, 0.5):
        i = int(t * SR)
        y[i : i + 400] += click
    try:
        track_beats(y, SR)
    except AudioError:
        pass


jit.register("music", warm_up)
