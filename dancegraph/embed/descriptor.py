"""Descriptor style embedding ('descriptor-v1'): the documented fallback for the learned one.

Music bars and dance bars are described by the same eight interpretable quantities, each computed
in its own modality, standardised, and mapped into one 32-d space by a fixed matrix with
orthonormal columns (so distances in the 32-d space equal distances between the standardised
descriptors):

=============  ==============================================  ===============================================
descriptor     music bar (tempo, ``bar_onset_rms``)             dance bar (main-joint positions)
=============  ==============================================  ===============================================
tempo          log2(bar BPM / 120)                              log2(bar BPM / 120) from the bar's beats
energy         log mean RMS                                     log mean joint speed (m/s)
dynamics       coefficient of variation of RMS                  coefficient of variation of mean speed
articulation   log(mean onset strength / mean RMS)              log(mean acceleration · beat length / speed)
density        onset peaks per beat                             speed minima (kinematic beats) per beat
syncopation    onset share on half-beat slots vs beat slots      speed share on half-beat slots vs beat slots
accent         onset at the downbeat / mean onset               speed at the downbeat / mean speed
slope          (RMS 2nd half − 1st half) / mean RMS             (speed 2nd half − 1st half) / mean speed
=============  ==============================================  ===============================================

Standardisation: tempo with fixed constants on both sides (absolute, comparable units); the other
descriptors are z-scored per modality — the music over the bars of the song (loudness has no
absolute scale across recordings), the dance over the original bars of the dataset (the mean and
standard deviation are stored in the graph manifest so queries reuse them).
"""

from __future__ import annotations

import numpy as np

VERSION = "descriptor-v1"
DIM = 32
NAMES = ("tempo", "energy", "dynamics", "articulation", "density", "syncopation", "accent", "slope")
#: relative weight of each descriptor in the embedding (tempo counts double: it is absolute)
WEIGHTS = np.array([2.0, 1.0, 0.7, 0.7, 0.7, 0.7, 0.5, 0.5])
_TEMPO_SCALE = 0.35  # log2 units: 120 BPM vs 154 BPM is one standard unit
_EPS = 1e-6


def _projection() -> np.ndarray:
    """``(32, 8)`` fixed matrix with orthonormal columns (seeded QR; part of the version)."""
    rng = np.random.default_rng(20240601)
    q, _ = np.linalg.qr(rng.standard_normal((DIM, len(NAMES))))
    return q


PROJECTION = _projection()


def _slot_share(curve: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``curve (N, S)`` near beat slots and near half-beat slots (S covers 4 beats)."""
    n = curve.shape[1]
    pos = (np.arange(n) + 0.5) / n * 8.0  # position in half-beat slots
    frac = pos - np.floor(pos)
    near = np.minimum(frac, 1.0 - frac) < 0.25
    slot = np.floor(pos + 0.5).astype(int) % 8
    on = near & (slot % 2 == 0)
    off = near & (slot % 2 == 1)
    return curve[:, on].mean(axis=1), curve[:, off].mean(axis=1)


def _count_minima(curve: np.ndarray) -> np.ndarray:
    """Strict local minima per row of a smoothed ``(N, S)`` curve."""
    kernel = np.array([1.0, 2.0, 3.0, 2.0, 1.0]) / 9.0
    sm = np.apply_along_axis(lambda r: np.convolve(r, kernel, mode="same"), 1, curve)
    inner = sm[:, 1:-1]
    mins = (inner < sm[:, :-2]) & (inner < sm[:, 2:])
    # ignore shallow wiggles: a minimum must lie below the row mean
    mins &= inner < sm.mean(axis=1, keepdims=True)
    return mins.sum(axis=1).astype(float)


def _count_peaks(curve: np.ndarray) -> np.ndarray:
    inner = curve[:, 1:-1]
    peaks = (inner > curve[:, :-2]) & (inner >= curve[:, 2:])
    peaks &= inner > curve.mean(axis=1, keepdims=True) + 0.5 * curve.std(axis=1, keepdims=True)
    return peaks.sum(axis=1).astype(float)


def music_descriptors(bar_durations: np.ndarray, bar_onset_rms: np.ndarray) -> np.ndarray:
    """Raw music descriptors ``(B, 8)`` (order ``NAMES``).

    ``bar_durations (B,)`` seconds per 4-beat bar; ``bar_onset_rms (B, 2, S)``: onset strength
    (channel 0) and RMS (channel 1) sampled evenly over each bar.
    """
    dur = np.maximum(np.asarray(bar_durations, dtype=float), _EPS)
    x = np.asarray(bar_onset_rms, dtype=float)
    if x.ndim != 3 or x.shape[1] != 2 or x.shape[0] != dur.shape[0]:
        raise ValueError(f"bar_onset_rms must be (B, 2, S) with B = {dur.shape[0]}, got {x.shape}")
    onset, rms = np.maximum(x[:, 0], 0.0), np.maximum(x[:, 1], 0.0)
    rms_mean = rms.mean(axis=1) + _EPS
    onset_mean = onset.mean(axis=1) + _EPS
    on, off = _slot_share(onset)
    half = rms.shape[1] // 2
    head = onset[:, : max(1, onset.shape[1] // 16)].max(axis=1)
    return np.stack(
        [
            np.log2(240.0 / dur / 120.0),
            np.log(rms_mean),
            rms.std(axis=1) / rms_mean,
            np.log(onset_mean / rms_mean),
            _count_peaks(onset) / 4.0,
            off / (on + off + _EPS),
            head / onset_mean,
            (rms[:, half:].mean(axis=1) - rms[:, :half].mean(axis=1)) / rms_mean,
        ],
        axis=1,
    )


def dance_descriptors(positions: np.ndarray, durations: np.ndarray) -> np.ndarray:
    """Raw dance descriptors ``(N, 8)`` (order ``NAMES``).

    ``positions (N, F, K, 3)``: world positions (m) of the main joints over each bar, sampled
    beat-aligned (beat k at frame k·F/4); ``durations (N,)`` bar lengths in seconds.
    """
    pos = np.asarray(positions, dtype=float)
    dur = np.maximum(np.asarray(durations, dtype=float), _EPS)
    n, f = pos.shape[:2]
    dt = (dur / f)[:, None]
    vel = np.diff(pos, axis=1) / dt[:, :, None, None]
    speed = np.linalg.norm(vel, axis=-1).mean(axis=2)  # (N, F-1) mean over joints
    acc = np.linalg.norm(np.diff(vel, axis=1), axis=-1).mean(axis=2) / dt  # (N, F-2)
    sp_mean = speed.mean(axis=1) + _EPS
    on, off = _slot_share(speed)
    half = speed.shape[1] // 2
    beat_len = dur / 4.0
    head = speed[:, : max(1, speed.shape[1] // 16)].mean(axis=1)
    return np.stack(
        [
            np.log2(240.0 / dur / 120.0),
            np.log(sp_mean),
            speed.std(axis=1) / sp_mean,
            np.log(acc.mean(axis=1) * beat_len / sp_mean + _EPS),
            _count_minima(speed) / 4.0,
            off / (on + off + _EPS),
            head / sp_mean,
            (speed[:, half:].mean(axis=1) - speed[:, :half].mean(axis=1)) / sp_mean,
        ],
        axis=1,
    )


def fit_stats(raw: np.ndarray) -> dict:
    """Mean and standard deviation per descriptor of ``raw (N, 8)`` (JSON-able)."""
    raw = np.asarray(raw, dtype=float)
    std = raw.std(axis=0)
    return {"mean": raw.mean(axis=0).tolist(), "std": np.where(std > 1e-3, std, 1.0).tolist()}


def embed(raw: np.ndarray, stats: dict | None = None) -> np.ndarray:
    """Standardise raw descriptors ``(N, 8)`` and project to ``(N, 32) float32``.

    Tempo uses fixed constants; the others use ``stats`` (``fit_stats`` of the reference set), or
    the rows' own statistics when ``stats`` is None.
    """
    raw = np.asarray(raw, dtype=float)
    stats = stats if stats is not None else fit_stats(raw)
    z = (raw - np.asarray(stats["mean"])) / np.asarray(stats["std"])
    z[:, 0] = raw[:, 0] / _TEMPO_SCALE
    z = np.clip(z, -4.0, 4.0) * WEIGHTS
    return (z @ PROJECTION.T).astype(np.float32)


def embed_music(bar_durations: np.ndarray, bar_onset_rms: np.ndarray) -> np.ndarray:
    """32-d style of each music bar ``(B, 32)``, standardised over the song's own bars."""
    return embed(music_descriptors(bar_durations, bar_onset_rms))


def embed_dance(
    positions: np.ndarray, durations: np.ndarray, stats: dict | None = None
) -> np.ndarray:
    """32-d style of each dance bar ``(N, 32)``; ``stats`` from the dataset (``fit_stats``)."""
    return embed(dance_descriptors(positions, durations), stats)
