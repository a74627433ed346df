"""General signal helpers of the beat and bar steps: curves at 50 frames per second, beat grids
in seconds. Why one module: the beat tracker (:mod:`dancegraph.music.beats` and its parts) and
the bar grouping (:mod:`dancegraph.music.bargroup`) read the same curves the same way.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "FPS",
    "HOP",
    "SR",
    "beat_f_measure",
    "beat_phase_profile",
    "beat_spans",
    "harmonic_change",
    "nearest",
    "next_intervals",
    "peak_near",
    "zscore",
]

#: the sample rate (Hz) and hop (samples) of every curve the steps read: BeatNet's frames
#: (:mod:`dancegraph.music.beatnet`, which this module does not import: it loads torch)
SR = 22_050
HOP = 441
FPS = SR / HOP  # 50 frames per second


def zscore(v: np.ndarray) -> np.ndarray:
    """``v`` (K,) standardised: zero mean, unit standard deviation (all zeros if constant)."""
    return (v - v.mean()) / (v.std() + 1e-9)


def peak_near(curve: np.ndarray, frames: np.ndarray, reach: int = 2) -> np.ndarray:
    """(K,) the maximum of ``curve`` (T,) within ``reach`` frames of each of ``frames`` (K,),
    clipped to the curve: a detector's peak lags or leads the beat it belongs to by a frame."""
    fr = np.clip(np.asarray(frames, dtype=np.int64), 0, len(curve) - 1)
    return np.array([curve[max(f - reach, 0) : f + reach + 1].max() for f in fr], dtype=np.float64)


def beat_spans(frames: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) frame indices (K,) of each beat of ``frames`` (K,) in a curve of ``n``
    frames (the last beat lasts the median interval)."""
    starts = np.clip(np.asarray(frames, dtype=np.int64), 0, n - 1)
    last = int(np.median(np.diff(starts))) if len(starts) > 1 else 1
    ends = np.r_[starts[1:], min(n, starts[-1] + max(last, 1))]
    return starts, np.maximum(ends, starts + 1)


def harmonic_change(chroma: np.ndarray, frames: np.ndarray, k: int = 2) -> np.ndarray:
    """(K,) harmonic change into each beat: cosine distance between the mean beat-synchronous
    chroma (12, T) of the ``k`` beats before and the ``k`` beats from it on (chords change on
    bar lines).

    Each beat's chroma is taken over the first half of the beat only, so a chord anticipated by
    an eighth note (arriving on the "and" of the last beat) still counts for the downbeat.
    """
    n = chroma.shape[1]
    starts, ends = beat_spans(frames, n)
    halves = starts + np.maximum((ends - starts) // 2, 1)
    bc = np.stack([chroma[:, a:b].mean(axis=1) for a, b in zip(starts, halves, strict=True)])
    out = np.zeros(len(starts))
    for i in range(1, len(starts)):
        a = bc[max(i - k, 0) : i].mean(axis=0)
        b = bc[i : i + k].mean(axis=0)
        out[i] = 1.0 - float(a @ b) / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-9)
    return out


def next_intervals(times: np.ndarray) -> np.ndarray:
    """(K,) s from each beat of ``times`` (K >= 2) to the next; the last beat repeats the last
    interval. A beat moved a fraction of a beat later moves by that fraction of this."""
    ibi = np.diff(times)
    return np.r_[ibi, ibi[-1]]


def nearest(times: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(K,) index of the beat of ``reference`` (M,) nearest to each of ``times`` (K,)."""
    return np.abs(times[:, None] - reference[None, :]).argmin(axis=1)


def beat_phase_profile(onset_env: np.ndarray, times: np.ndarray, bins: int) -> np.ndarray:
    """(bins,) mean onset strength (T,) at 50 fps over the phase (0..1) of each beat interval of
    ``times`` (K,) s: where in the beat the music's onsets fall."""
    t = np.asarray(times, dtype=np.float64)
    ph = (np.arange(bins) + 0.5) / bins
    fr = (t[:-1, None] + ph[None, :] * np.diff(t)[:, None]) * FPS
    return np.interp(fr, np.arange(len(onset_env)), onset_env).mean(axis=0)


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
