"""The fallback tracker (``method='librosa'``, or BeatNet's weights missing): librosa's beats and
one bar phase and meter (3 or 4) for the whole song from the accents at the beats (onset
strength, bass onsets and chroma change). Why kept: a deployment without the network's weights
still dances, with a bar phase right about half the time (its confidence says so).
"""

from __future__ import annotations

import numpy as np

from dancegraph.music.evidence import Spectral
from dancegraph.music.params import FallbackParams
from dancegraph.music.signal import FPS, harmonic_change, zscore

__all__ = ["librosa_bars"]


def librosa_bars(
    times: np.ndarray, spec: Spectral, p: FallbackParams = FallbackParams()
) -> tuple[np.ndarray, int]:
    """One bar phase and meter for librosa's beats ``times`` (K,) s: (positions (K,), meter).

    Per beat the accent is z(onset strength) + z(bass onset) + z(harmonic change into it); the
    meter (3 or 4, 3 giving up ``p.triple_penalty``) and phase whose downbeats' mean accent most
    exceeds the mean win. Under 4 beats: all downbeats, meter 4."""
    frames = np.round(np.asarray(times, dtype=np.float64) * FPS).astype(np.int64)
    if len(frames) < 4:
        return np.ones(len(frames), np.int64), 4
    onset_env = spec.onset_env
    fr = np.clip(frames, 0, len(onset_env) - 1)
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
                score -= p.triple_penalty  # 4/4 unless 3/4 is clearly better supported
            if score > best[0]:
                best = (score, meter, phase)
    _, meter, phase = best
    positions = (np.arange(len(frames)) - phase) % meter + 1
    return positions.astype(np.int64), meter
