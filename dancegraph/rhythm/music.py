"""Rhythm signatures of music bars: onset evidence at the 8 half-beat slots (ChoreoMaster §3.2).

Slot ``i`` of a 4-beat bar sits at beat ``i / 2``; its time comes from the bar's own beat times
(linear between beats, so tempo drift follows the tracked beats), the half-beat slots delayed by
the song's swing (estimated: the delay that collects the most onset strength). A slot's evidence is
the strongest onset within a small window around it, less the bar's median onset strength (the
floor of sustained sound), scaled by the bar's strongest slot (but by at least a fraction of the
song's level) and clipped to [0, 1]. The onset curve given should leave the hi-hats out
(``FrameFeatures.accent``, bands below 4 kHz): hats on every half beat say nothing of the bar. ``dancegraph.rhythm.signatures.scores_from_slot_evidence`` turns that into a score for
each of the 13 common signatures.
"""

from __future__ import annotations

import numpy as np

from dancegraph.rhythm.signatures import COMMON_BITS, N_SLOTS, scores_from_slot_evidence, top_k

#: Half-width of the window searched for an onset around a slot: this many seconds, at most a
#: quarter of a half beat (so neighbouring slots never share an onset).
SLOT_WINDOW_S = 0.05
#: A bar's evidence is scaled by its strongest slot, or by this fraction of the song's 95th
#: percentile of slot evidence where that is larger.
QUIET_FRACTION = 0.3
#: Evidence (relative to the bar's strongest slot) above which a slot counts as accented: a
#: note or drum hit a third as strong as the bar's main accent is still part of the rhythm
#: (0.3 found best on generated songs: top-3 0.79 vs 0.70 at 0.5).
ACCENT_THRESHOLD = 0.3
#: Swing delays tried for the half-beat slots, in beats (1/6 is triplet swing).
SWING_GRID = np.linspace(0.0, 1 / 6, 6)


def slot_times(bar_beats: np.ndarray, swing: float = 0.0) -> np.ndarray:
    """``(B, 5)`` beat times (4 beats + next downbeat) → ``(B, 8)`` slot times in seconds.

    ``swing``: the half-beat slots are delayed by this fraction of a beat (1/6: triplet swing).
    """
    bar_beats = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    pos = np.arange(N_SLOTS) / 2.0 + np.where(np.arange(N_SLOTS) % 2 == 1, swing, 0.0)
    lo = np.floor(pos).astype(int)
    frac = pos - lo
    return bar_beats[:, lo] * (1 - frac) + bar_beats[:, lo + 1] * frac


def rhythm_points(bar_beats: np.ndarray, signatures: np.ndarray) -> np.ndarray:
    """``(P,)`` seconds, sorted: the music's rhythm points, the active slots of each bar's rhythm
    signature (ChoreoMaster's beat-accuracy denominator). ``bar_beats (B, 5)`` s;
    ``signatures (B,)`` indices into ``COMMON_SIGNATURES`` (e.g. ``signature_topk[:, 0]``)."""
    bar_beats = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    bits = COMMON_BITS[np.asarray(signatures, dtype=int).reshape(-1)]
    if len(bits) != len(bar_beats):
        raise ValueError(f"{len(bits)} signatures for {len(bar_beats)} bars")
    return np.sort(slot_times(bar_beats)[bits.astype(bool)])


def _slot_peaks(
    onset: np.ndarray, frame_rate: float, bar_beats: np.ndarray, swing: float
) -> np.ndarray:
    """``(B, 8)`` strongest onset within the window around each slot."""
    st = slot_times(bar_beats, swing)
    half_beat = np.diff(bar_beats, axis=1).mean(axis=1) / 2  # (B,)
    width = np.minimum(SLOT_WINDOW_S, half_beat / 4)[:, None]
    offsets = np.linspace(-1.0, 1.0, 9)
    t = st[:, :, None] + width[:, :, None] * offsets[None, None, :]
    frames = np.clip(np.round(t * frame_rate).astype(int), 0, onset.size - 1)
    return onset[frames].max(axis=2)


def estimate_swing(onset: np.ndarray, frame_rate: float, bar_beats: np.ndarray) -> float:
    """The half-beat delay (fraction of a beat, 0 … 1/6) at which the half-beat slots collect
    the most onset strength over the song; 0 for straight eighths."""
    bar_beats = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    if len(bar_beats) == 0 or np.asarray(onset).size == 0:
        return 0.0
    onset = np.asarray(onset, dtype=float)
    best, best_s = -1.0, 0.0
    for s in SWING_GRID:
        v = float(_slot_peaks(onset, frame_rate, bar_beats, s)[:, 1::2].sum())
        if v > best * 1.02:  # prefer straight time unless swing is clearly better
            best, best_s = v, float(s)
    return best_s


def slot_evidence(
    onset: np.ndarray, frame_rate: float, bar_beats: np.ndarray, swing: float | None = None
) -> np.ndarray:
    """Accent evidence in [0, 1] per half-beat slot → ``(B, 8)`` (slot 0 = downbeat).

    ``onset`` (T,) onset strength sampled at ``frame_rate`` Hz (frame k at ``k / frame_rate`` s);
    ``bar_beats`` (B, 5) seconds; ``swing`` the half-beat delay in beats (None: estimated).
    """
    onset = np.asarray(onset, dtype=float)
    bar_beats = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    if len(bar_beats) == 0 or onset.size == 0:
        return np.zeros((len(bar_beats), N_SLOTS))
    if swing is None:
        swing = estimate_swing(onset, frame_rate, bar_beats)
    peak = _slot_peaks(onset, frame_rate, bar_beats, swing)
    # The bar's onset floor: median of the curve over the bar.
    f0 = np.clip((bar_beats[:, 0] * frame_rate).astype(int), 0, onset.size - 1)
    f1 = np.clip((bar_beats[:, 4] * frame_rate).astype(int), 1, onset.size)
    floor = np.array([np.median(onset[a : max(b, a + 1)]) for a, b in zip(f0, f1, strict=True)])
    ev = np.maximum(peak - floor[:, None], 0.0)
    ref = float(np.percentile(ev, 95))
    if ref <= 1e-9:
        return np.zeros_like(ev)
    # Scale by the bar's own strongest slot, but never by less than a fraction of the song's
    # level: a quiet section keeps its accents, a near-silent bar does not invent any.
    scale = np.maximum(ev.max(axis=1, keepdims=True), QUIET_FRACTION * ref)
    return np.clip(ev / scale, 0.0, 1.0)


def song_signatures(
    ff, bar_beats: np.ndarray, k: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``music_signatures`` of a song's frame features ``ff`` (``music.features.FrameFeatures``)
    on its bars ``bar_beats (B, 5)`` s: from the accent curve (bands below 4 kHz, no hats)."""
    return music_signatures(ff.accent, ff.frame_rate, bar_beats, k)


def music_signatures(
    onset: np.ndarray, frame_rate: float, bar_beats: np.ndarray, k: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per bar: ``(B, 13)`` scores for the common signatures, ``(B, k)`` top-k indices (best
    first) into ``COMMON_SIGNATURES``, and the ``(B, 8)`` slot evidence they came from."""
    ev = slot_evidence(onset, frame_rate, bar_beats)
    if len(ev) == 0:
        return np.zeros((0, 13)), np.zeros((0, k), dtype=int), ev
    scores = scores_from_slot_evidence(ev, threshold=ACCENT_THRESHOLD)
    return scores, top_k(scores, k), ev
