"""The no-beat decision: is there a beat to dance to in this sound?

The decoder always finds *some* regular beat, so regularity alone proves nothing. What separates
music from speech, noise and steady tones is the pulse: the tracker's curve (BeatNet's summed
activation, or librosa's onset strength in the fallback) at the beats against its mean
(contrast) and its periodicity at the beat period (salience). Their product is the pulse
strength: soft classical music has little contrast and a solid metal wall of drums little
contrast too, but each beats speech on the product. A pulse with a faint contrast or salience
is usable with a ``weak_pulse`` warning, unless the sound pauses like speech and its harmony
does not hold (:func:`speech_evidence`). The limits: :class:`~dancegraph.music.params.
NoBeatParams`; what they are on real music and on the non-music clips: docs/music.md.
"""

from __future__ import annotations

import numpy as np

from dancegraph.music.evidence import Spectral
from dancegraph.music.params import NoBeatParams, PulseLimits, SpeechParams
from dancegraph.music.signal import FPS, peak_near
from dancegraph.music.tempo import pulse_salience, tempo_from_beats

__all__ = ["speech_evidence", "usable"]


def speech_evidence(spec: Spectral, p: SpeechParams = SpeechParams()) -> tuple[float, float]:
    """What tells speech from music with a faint pulse: (pause share, chroma persistence).

    The pause share is the share of frames whose RMS level is under ``p.pause_ratio`` of its
    mean over ``p.pause_context_s`` about it (speech stops between words and phrases; music
    sustains and reverberates). The chroma persistence is the level-weighted cosine between each
    frame's chroma and the chroma ``p.chroma_lag_s`` later (a voice glides from syllable to
    syllable; notes and chords are held). Both in [0, 1]; 0 and 0 for audio too short to
    compare. Why: BeatNet's pulse alone can read a speaker's syllables as a faint beat."""
    from scipy.ndimage import uniform_filter1d

    level = spec.level.astype(np.float64)
    lag = int(round(p.chroma_lag_s * FPS))
    if len(level) <= lag:
        return 0.0, 0.0
    about = uniform_filter1d(level, max(1, int(round(p.pause_context_s * FPS))), mode="nearest")
    pauses = float(np.mean(level < p.pause_ratio * about))
    a = spec.chroma[:, :-lag].astype(np.float64)
    b = spec.chroma[:, lag:].astype(np.float64)
    norms = np.linalg.norm(a, axis=0) * np.linalg.norm(b, axis=0)
    cos = (a * b).sum(axis=0) / np.maximum(norms, 1e-12)
    weight = level[:-lag]
    persistence = float((cos * weight).sum() / max(weight.sum(), 1e-12))
    return pauses, persistence


def _pulse(
    times: np.ndarray, act: np.ndarray | None, onset_env: np.ndarray, limits: PulseLimits
) -> tuple[float, float, float, float]:
    """(mean curve peak at the beats, contrast, salience at the beat, level salience) of the
    tracker's curve; where BeatNet's contrast is clear, the level salience is the best of the
    beat, two beats and half a beat (half-time drums, a syncopated figure still pulse)."""
    bpm, _ = tempo_from_beats(times)
    curve = act.sum(axis=1) if act is not None else onset_env
    peak = peak_near(curve, np.round(times * FPS))
    contrast = float(peak.mean() / max(curve.mean(), 1e-9))
    salience = pulse_salience(curve, FPS, bpm)
    pulse = salience
    if act is not None and contrast >= limits.clear_contrast:
        pulse = max(salience, *(pulse_salience(curve, FPS, bpm * r) for r in (0.5, 2.0)))
    return float(peak.mean()), contrast, salience, pulse


def _refusal(
    peak: float, contrast: float, salience: float, strength: float, lim: PulseLimits
) -> str:
    """Why the pulse is no beat by the ``lim`` limits, or ""."""
    if peak < lim.min_peak:
        return f"weak beat evidence (peak {peak:.2f} < {lim.min_peak})"
    if contrast < lim.min_contrast:
        return f"no beat contrast ({contrast:.2f} < {lim.min_contrast})"
    if salience < lim.min_salience:
        return f"no periodic pulse (salience {salience:.2f} < {lim.min_salience})"
    if strength < lim.min_strength:
        return (
            f"no pulse (strength {strength:.2f} < {lim.min_strength}: contrast "
            f"{contrast:.2f}, salience {salience:.2f})"
        )
    return ""


def usable(
    times: np.ndarray,
    act: np.ndarray | None,
    spec: Spectral,
    evidence: dict,
    prefix: str,
    p: NoBeatParams = NoBeatParams(),
) -> tuple[bool, str]:
    """The no-beat test of one tracker's beats ``times`` (K,) s (``act`` (T, 2) BeatNet's
    activations, or None for librosa's onset strength in ``spec``); fills ``evidence`` (keys
    ``{prefix}_...``; it needs ``active_s``) and returns (usable, why not, or why the pulse is
    weak where usable; "" for a clear pulse). See the module docstring."""
    times = np.asarray(times)
    n = len(times)
    evidence[f"{prefix}_beats"] = n
    if n < p.min_beats:
        return False, f"{n} beats found"
    coverage = float(times[-1] - times[0]) / max(evidence["active_s"], 1e-9)
    _, regularity = tempo_from_beats(times)
    evidence[f"{prefix}_coverage"] = coverage
    evidence[f"{prefix}_regularity"] = regularity
    limits = p.beatnet if act is not None else p.librosa
    peak, contrast, salience, pulse = _pulse(times, act, spec.onset_env, limits)
    strength = contrast * pulse
    evidence[f"{prefix}_peak"] = peak
    evidence[f"{prefix}_contrast"] = contrast
    evidence[f"{prefix}_salience"] = salience
    evidence[f"{prefix}_level_salience"] = pulse
    evidence[f"{prefix}_strength"] = strength
    refused = _refusal(peak, contrast, salience, strength, limits)
    if refused:
        return False, refused
    if coverage < p.min_coverage:
        return False, f"beats cover only {coverage:.0%} of the sound"
    if regularity < p.min_regularity:
        return False, f"irregular beat intervals (regularity {regularity:.2f})"
    if contrast < limits.clear_contrast or salience < limits.clear_salience:
        pauses, persistence = speech_evidence(spec, p.speech)
        evidence["pause_share"] = pauses
        evidence["chroma_persistence"] = persistence
        if pauses >= p.speech.min_pauses and persistence < p.speech.max_chroma:
            return False, (
                f"a faint pulse in speech-like sound (pauses in {pauses:.0%} of the frames, "
                f"chroma persistence {persistence:.2f}; strength {strength:.2f})"
            )
        return True, f"contrast {contrast:.2f}, salience {salience:.2f}, strength {strength:.2f}"
    return True, ""
