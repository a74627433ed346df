"""Frame- and bar-level music features.

One short-time spectrum at 22.05 kHz (2048-sample window, 256-sample hop, about 11.6 ms) feeds
everything the analysis needs per frame — onset strength, RMS, chroma, MFCC, a coarse log-mel —
so the song is transformed once. From these:

- ``bar_onset_rms``: per bar, onset strength and RMS resampled to 200 points, ``(B, 2, 200)``,
  each curve scaled by its song-wide 99th percentile (values about 0..1).
- ``music_logmel`` / ``logmel_window``: the style encoder's input, a log-mel spectrogram at
  16 kHz, 96 bands, hop 160 (10 ms), cut into 8-s windows ``(1, 96, 800)`` at a phrase position;
  computed on demand, not during ``analyze``.
"""

from __future__ import annotations

from dataclasses import dataclass

import librosa
import numpy as np

FEATURE_SR = 22050
N_FFT = 2048
HOP = 256
BAR_POINTS = 200
ACCENT_MAX_HZ = 4000.0
CHUNK_FRAMES = 4096  # spectrum block: about 48 s of audio

LOGMEL_SR = 16000
LOGMEL_BANDS = 96
LOGMEL_HOP = 160
LOGMEL_WINDOW_S = 8.0
LOGMEL_FRAMES = 800


@dataclass
class FrameFeatures:
    """Per-frame features of one song at ``sr`` with ``hop`` samples per frame.

    ``times`` (T,) s (frame centres); ``onset`` (T,) onset strength (spectral flux of the log-mel,
    ≥ 0); ``accent`` (T,) the same flux over the bands below 4 kHz only (kick, snare body, bass,
    chords — not the hi-hats, which would mark every half beat alike); ``rms`` (T,) linear RMS; ``chroma`` (12, T) per-frame max-normalised; ``mfcc`` (20, T);
    ``mel_db`` (40, T) log-mel in dB (coarse; for comparing bars).
    """

    sr: int
    hop: int
    times: np.ndarray
    onset: np.ndarray
    accent: np.ndarray
    rms: np.ndarray
    chroma: np.ndarray
    mfcc: np.ndarray
    mel_db: np.ndarray

    @property
    def frame_rate(self) -> float:
        return self.sr / self.hop


def frame_features(y: np.ndarray, sr: int) -> FrameFeatures:
    """Compute ``FrameFeatures`` of mono audio ``y`` (N,) at ``sr`` Hz (resampled to 22.05 kHz).

    The spectrum is taken in blocks of ``CHUNK_FRAMES`` frames, so memory stays near 100 MB
    even for a 20-minute song (frames are centred, as ``librosa.stft(center=True)``).
    """
    y = np.asarray(y, dtype=np.float32)
    if sr != FEATURE_SR:
        y = librosa.resample(y, orig_sr=sr, target_sr=FEATURE_SR)
        sr = FEATURE_SR
    n_frames = 1 + len(y) // HOP
    yp = np.pad(y, (N_FFT // 2, N_FFT // 2))
    mel_fb = librosa.filters.mel(sr=sr, n_fft=N_FFT, n_mels=128, fmax=11025)
    coarse_fb = librosa.filters.mel(sr=sr, n_fft=N_FFT, n_mels=40, fmax=11025)
    # tuning=0: no per-song tuning estimate (slow, and bar similarity does not need it)
    chroma_fb = librosa.filters.chroma(sr=sr, n_fft=N_FFT, tuning=0.0)
    mel = np.empty((128, n_frames), dtype=np.float32)
    coarse = np.empty((40, n_frames), dtype=np.float32)
    chroma = np.empty((12, n_frames), dtype=np.float32)
    rms = np.empty(n_frames, dtype=np.float32)
    for f0 in range(0, n_frames, CHUNK_FRAMES):
        f1 = min(n_frames, f0 + CHUNK_FRAMES)
        seg = yp[f0 * HOP : (f1 - 1) * HOP + N_FFT]
        spec = np.abs(librosa.stft(seg, n_fft=N_FFT, hop_length=HOP, center=False)) ** 2
        mel[:, f0:f1] = mel_fb @ spec
        coarse[:, f0:f1] = coarse_fb @ spec
        chroma[:, f0:f1] = chroma_fb @ spec
        # RMS from the spectrum, as librosa.feature.rms(S=...) computes it.
        power = 2 * spec.sum(axis=0) - spec[0] - spec[-1]
        rms[f0:f1] = np.sqrt(np.maximum(power, 0) / N_FFT**2)
    ref = float(mel.max()) + 1e-12
    mel_db = librosa.power_to_db(mel, ref=ref, top_db=80.0)
    onset = librosa.onset.onset_strength(S=mel_db, sr=sr, hop_length=HOP, lag=1, max_size=1)
    low = librosa.mel_frequencies(n_mels=128, fmax=11025) < ACCENT_MAX_HZ
    accent = librosa.onset.onset_strength(S=mel_db[low], sr=sr, hop_length=HOP, lag=1, max_size=1)
    chroma = librosa.util.normalize(chroma, norm=np.inf, axis=0)
    mfcc = librosa.feature.mfcc(S=mel_db, n_mfcc=20)
    coarse = librosa.power_to_db(coarse, ref=ref, top_db=80.0)
    times = librosa.frames_to_time(np.arange(n_frames), sr=sr, hop_length=HOP)
    return FrameFeatures(
        sr,
        HOP,
        times,
        onset.astype(np.float32),
        accent.astype(np.float32),
        rms.astype(np.float32),
        chroma,
        mfcc,
        coarse,
    )


def _scale(x: np.ndarray) -> np.ndarray:
    ref = float(np.percentile(x, 99)) if x.size else 0.0
    return x / ref if ref > 1e-9 else np.zeros_like(x)


def resample_per_bar(
    curve: np.ndarray, times: np.ndarray, bars: np.ndarray, n: int = BAR_POINTS
) -> np.ndarray:
    """Sample a frame curve ``(T,)`` at ``n`` evenly spaced points in each bar → ``(B, n)``.

    ``bars`` (B, 2) start/end seconds; point k of a bar sits at ``start + k/n * (end - start)``.
    """
    bars = np.asarray(bars, dtype=float).reshape(-1, 2)
    frac = np.arange(n) / n
    t = bars[:, :1] + frac[None, :] * (bars[:, 1:] - bars[:, :1])
    return np.interp(t, times, curve, left=0.0, right=0.0)


def bar_onset_rms(ff: FrameFeatures, bars: np.ndarray) -> np.ndarray:
    """``(B, 2, 200)`` float32: per bar the onset strength (row 0) and RMS (row 1), resampled.

    Both curves are divided by their song-wide 99th percentile so songs at different levels
    compare; values are about 0..1 (peaks may exceed 1).
    """
    onset = resample_per_bar(_scale(ff.onset), ff.times, bars)
    rms = resample_per_bar(_scale(ff.rms), ff.times, bars)
    return np.stack([onset, rms], axis=1).astype(np.float32)


def bar_synchronous(
    feat: np.ndarray, times: np.ndarray, bars: np.ndarray, n_sub: int = 4
) -> np.ndarray:
    """Average a feature ``(D, T)`` over ``n_sub`` equal parts of each bar → ``(B, n_sub * D)``.

    A part with no frame centre inside it takes the nearest frame.
    """
    bars = np.asarray(bars, dtype=float).reshape(-1, 2)
    edges = bars[:, :1] + np.linspace(0, 1, n_sub + 1)[None, :] * (bars[:, 1:] - bars[:, :1])
    idx = np.searchsorted(times, edges)  # (B, n_sub + 1)
    csum = np.concatenate([np.zeros((feat.shape[0], 1)), np.cumsum(feat, axis=1)], axis=1)
    lo, hi = idx[:, :-1], np.maximum(idx[:, 1:], idx[:, :-1] + 1)
    hi = np.minimum(hi, feat.shape[1])
    lo = np.minimum(lo, hi - 1)
    means = (csum[:, hi] - csum[:, lo]) / (hi - lo)[None]  # (D, B, n_sub)
    return np.transpose(means, (1, 2, 0)).reshape(len(bars), -1)


def music_logmel(y: np.ndarray, sr: int) -> np.ndarray:
    """Log-mel spectrogram of mono ``y`` at 16 kHz: ``(96, T)`` float32 in dB (ref 1.0, floor -100),
    hop 160 samples (10 ms), 400-sample (25 ms) window."""
    y = np.asarray(y, dtype=np.float32)
    if sr != LOGMEL_SR:
        y = librosa.resample(y, orig_sr=sr, target_sr=LOGMEL_SR)
    mel = librosa.feature.melspectrogram(
        y=y,
        sr=LOGMEL_SR,
        n_fft=512,
        win_length=400,
        hop_length=LOGMEL_HOP,
        n_mels=LOGMEL_BANDS,
        fmax=8000,
    )
    return np.maximum(10.0 * np.log10(mel + 1e-10), -100.0).astype(np.float32)


def logmel_window(mel: np.ndarray, start_s: float) -> np.ndarray:
    """The 8-s window of a ``music_logmel`` output that starts at ``start_s`` → ``(1, 96, 800)``.

    Frames past the end of the song (or before its start) are filled with the floor (-100 dB).
    """
    start = int(round(start_s * LOGMEL_SR / LOGMEL_HOP))
    out = np.full((1, mel.shape[0], LOGMEL_FRAMES), -100.0, dtype=np.float32)
    lo, hi = max(start, 0), min(start + LOGMEL_FRAMES, mel.shape[1])
    if hi > lo:
        out[0, :, lo - start : hi - start] = mel[:, lo:hi]
    return out


def phrase_logmel_windows(y: np.ndarray, sr: int, starts_s: np.ndarray) -> np.ndarray:
    """8-s log-mel windows starting at each of ``starts_s`` (P,) seconds → ``(P, 1, 96, 800)``."""
    mel = music_logmel(y, sr)
    starts = np.asarray(starts_s, dtype=float).reshape(-1)
    if len(starts) == 0:
        return np.zeros((0, 1, LOGMEL_BANDS, LOGMEL_FRAMES), dtype=np.float32)
    return np.stack([logmel_window(mel, s) for s in starts])
