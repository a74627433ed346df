"""What the beat steps of one song read: BeatNet's activations and the spectral curves.

:func:`beat_evidence` checks the audio (length, silence), raises quiet input to a mastered
level and computes :class:`Evidence`: the activations of BeatNet's CRNN models averaged
(:mod:`dancegraph.music.beatnet`) and, from one STFT, the onset strength, the chroma above the
bass, the bass and snare-band onsets and the frames' level (:func:`spectral`), all at 50 frames
per second. Why apart from the steps: the evidence is the expensive part, computed once per song
and shared by every parameter set (the benchmarks run many on one evidence).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dancegraph.errors import AudioError, ModelFileError
from dancegraph.music.decode import DEFAULT_MAX_SECONDS, resample
from dancegraph.music.params import AnalysisParams, EvidenceParams
from dancegraph.music.signal import FPS, HOP, SR

__all__ = [
    "Evidence",
    "Spectral",
    "beat_evidence",
    "librosa_times",
    "librosa_times_between",
    "spectral",
]


@dataclass
class Spectral:
    """Frame-rate (50 fps) curves from one STFT: onset strength (T,), chroma (12, T), bass
    onsets (T,), noise onsets in the snare band (T,) and the frames' RMS level (T,)."""

    onset_env: np.ndarray
    chroma: np.ndarray
    bass_onset: np.ndarray
    snare_onset: np.ndarray
    level: np.ndarray


def _stft_frames(y22: np.ndarray, n_fft: int) -> np.ndarray:
    """(T, n_fft) views of librosa's centred framing of ``y22`` at :data:`HOP` (no copy)."""
    n_frames = 1 + len(y22) // HOP
    padded = np.zeros(n_frames * HOP + n_fft, dtype=np.float32)
    padded[n_fft // 2 : n_fft // 2 + len(y22)] = y22
    return np.lib.stride_tricks.sliding_window_view(padded, n_fft)[::HOP][:n_frames]


def spectral(
    y22: np.ndarray,
    n_fft: int = 2048,
    chunk: int = 2048,
    snare_band_hz: tuple[float, float] = EvidenceParams.snare_band_hz,
) -> Spectral:
    """librosa's onset strength (log-power mel flux), chroma and a bass onset curve of ``y22``
    (N,) at 22,050 Hz, computed from one centred STFT taken in chunks of frames, so memory stays
    ~20 MB for any length (librosa's own calls hold several full spectrograms: 1.3 GB for 15
    minutes).

    The chroma leaves out the bins below 200 Hz, which the bass curve covers: it is the chords'
    harmony. A syncopated or walking bass moves inside the bar and an anticipated root arrives
    half a beat early, so with the bass in it the chroma changes where the bass moves, not where
    the chords do (docs/music.md).

    The snare curve is the spectral flux of the ``snare_band_hz`` band (snare wires and claps;
    hi-hats and cymbals sit above it) weighted by the band's spectral flatness, so that noise
    bursts count and notes, whose harmonics also fill the band, hardly do."""
    import librosa

    frames = _stft_frames(y22, n_fft)
    n_frames = len(frames)
    window = librosa.filters.get_window("hann", n_fft, fftbins=True).astype(np.float32)
    mel_fb = librosa.filters.mel(sr=SR, n_fft=n_fft)
    chroma_fb = librosa.filters.chroma(sr=SR, n_fft=n_fft, tuning=0.0)
    n_bass = int(200 * n_fft / SR)  # bins below 200 Hz
    snare_band = slice(*(int(np.ceil(hz * n_fft / SR)) for hz in snare_band_hz))  # bins
    mel = np.empty((mel_fb.shape[0], n_frames), dtype=np.float32)
    chroma = np.empty((12, n_frames), dtype=np.float32)
    bass, snare, level = (np.empty(n_frames, dtype=np.float32) for _ in range(3))
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
    return Spectral(onset_env, chroma, bass_onset, snare, level)


def librosa_times(spec: Spectral) -> np.ndarray:
    """(K,) s: the beats of librosa's tracker (``librosa.beat.beat_track``) on the onset
    strength of ``spec``: an independent tracker, the fallback and the steps' second opinion."""
    import librosa

    _, frames = librosa.beat.beat_track(
        onset_envelope=spec.onset_env, sr=SR, hop_length=HOP, trim=True
    )
    return librosa.frames_to_time(np.asarray(frames, dtype=np.int64), sr=SR, hop_length=HOP)


def librosa_times_between(spec: Spectral, start_s: float, end_s: float, bpm: float) -> np.ndarray:
    """(K,) s: librosa's tracker on the onset strength of ``spec`` between ``start_s`` and
    ``end_s`` (s) alone, its tempo held at ``bpm``: where that stretch's own onsets put the
    beats' phase, whatever else was analysed (the whole song's tracker picks one tempo for all,
    and its path through a section depends on the rest). Empty under 1 s."""
    import librosa

    lo = max(int(np.floor(start_s * FPS)), 0)
    env = spec.onset_env[lo : int(np.ceil(end_s * FPS)) + 1]
    if len(env) < FPS:
        return np.zeros(0)
    _, frames = librosa.beat.beat_track(
        onset_envelope=env, sr=SR, hop_length=HOP, bpm=bpm, trim=True
    )
    return (np.asarray(frames, dtype=np.float64) + lo) / FPS


@dataclass
class Evidence:
    """What the steps of one song read: BeatNet's beat/downbeat activations ``act`` (T, 2) at 50
    fps (None where its weights are missing or ``method='librosa'``), the spectral curves
    ``spec`` of the level-raised audio, and ``values``, the numbers behind the no-beat test and
    the confidence. Built once by :func:`beat_evidence` for ``models`` and ``params``; the steps
    do not change it."""

    act: np.ndarray | None
    spec: Spectral
    values: dict
    models: tuple[int, ...] = AnalysisParams.models
    params: EvidenceParams = EvidenceParams()
    notes: list[str] = field(default_factory=list)
    _librosa: np.ndarray | None = None

    def librosa_times(self) -> np.ndarray:
        """The librosa tracker's beat times (K,) s (:func:`librosa_times`), computed once."""
        if self._librosa is None:
            self._librosa = librosa_times(self.spec)
        return self._librosa


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


def _checked(y: np.ndarray, sr: int, method: str, silence_rms: float) -> tuple[np.ndarray, float]:
    """(``y`` as float32 without NaN or infinities, its RMS); raises as :func:`beat_evidence`."""
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
    if rms < silence_rms:
        raise AudioError(f"no beat: the audio is silent (RMS {rms:.1e})", code="no_beat")
    return y, rms


def beat_evidence(
    y: np.ndarray, sr: int, *, method: str = "auto", params: AnalysisParams = AnalysisParams()
) -> Evidence:
    """Check the audio and compute what the steps read (:class:`Evidence`) for ``params``
    (its ``models``, ``evidence`` and ``no_beat.silence_rms``).

    ``y`` (N,) float mono at ``sr`` Hz; ``method`` 'auto' (BeatNet, librosa where its weights
    are missing: warning ``beatnet_weights_missing`` in ``Evidence.notes``), 'beatnet' or
    'librosa' (no activations). Raises ``AudioError`` (``audio_too_long`` over 20 minutes,
    ``audio_too_short`` under 3 s, ``no_beat`` for silence), ``ModelFileError``
    (``model_missing`` with ``method='beatnet'`` and no weights), ``ValueError`` for a shape or
    method that is not one of these.
    """
    p = params.evidence
    y, rms = _checked(y, sr, method, params.no_beat.silence_rms)
    y22 = resample(y, sr, SR)
    values: dict = {"rms": rms, "active_s": _active_span(y22)}
    # BeatNet's log-magnitude features are not level-invariant (a song 20 dB down reads as "no
    # beat"): raise quiet input to the level of ordinary mastered music, never lower loud input
    level = _loudness(y22)
    gain = min(p.target_rms / level, p.max_gain) if 0 < level < p.target_rms else 1.0
    if gain > 1.0:
        y22 = y22 * np.float32(gain)
    values["gain_db"] = float(20 * np.log10(gain))
    act, notes = None, []
    if method != "librosa":
        from dancegraph.music.beatnet import activations  # loads torch: only when used

        try:
            act = activations(y22, params.models)
        except ModelFileError as exc:
            if method == "beatnet":
                raise
            notes.append(f"beatnet_weights_missing: {exc.message}; librosa fallback used")
    spec = spectral(y22, snare_band_hz=p.snare_band_hz)
    return Evidence(act, spec, values, models=params.models, params=p, notes=notes)
