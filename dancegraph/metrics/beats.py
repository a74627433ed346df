"""Beat alignment of a dance to its music: ChoreoMaster's beat accuracy and the Beat Align Score.

All motion inputs are world joint positions ``(F, J, 3)`` in metres at ``fps`` (the published
scores are defined at 60 fps: resample first). Beat times are seconds.

- ``beat_accuracy``: ChoreoMaster's measure, the share of music beats that have a kinematic beat
  (``dancegraph.motion.features.kinematic_beats``) within ``ACCURACY_TOLERANCE_S``.
- Beat Align Score, σ = 3 frames at 60 fps, in its two published variants (they differ, so every
  number carries its label):

  * ``bailando``: Li et al., "Bailando" (CVPR 2022). Music beats from librosa's beat tracker on
    the percussive part (``librosa_beats``); motion beats are the local minima of the mean joint
    speed smoothed by a Gaussian of σ = 5 frames; the score is averaged over *music* beats:
    mean_m exp(−min_k (m − k)² / 2σ²).
  * ``fact``: Li et al., "AI Choreographer" (FACT / AIST++, ICCV 2021). Motion beats are the
    local minima of the *sum* of joint speeds that are the lowest within 10 frames either side;
    the score is averaged over *motion* beats: mean_k exp(−min_m (k − m)² / 2σ²).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import argrelextrema

#: Frame rate at which the published scores are defined.
BAS_FPS = 60.0
#: σ of the Beat Align Score: 3 frames at 60 fps.
BAS_SIGMA_S = 3.0 / BAS_FPS
#: Bailando's smoothing of the mean joint speed (frames at 60 fps).
BAILANDO_SMOOTH_FRAMES = 5.0
#: FACT's motion beats are minima over ±10 frames (at 60 fps).
FACT_ORDER_FRAMES = 10
#: A music beat is "hit" when a kinematic beat lies within this many seconds (ChoreoMaster
#: reports beat hits at a tolerance of a few frames; 0.1 s is 3 frames at 30 fps, 6 at 60).
ACCURACY_TOLERANCE_S = 0.1

Variant = Literal["bailando", "fact"]


def librosa_beats(y: np.ndarray, sr: int) -> np.ndarray:
    """``(N,)`` beat times (s) of mono audio ``y (S,)`` at ``sr`` Hz: librosa's beat tracker run on
    the percussive part (HPSS), as Bailando's evaluation does."""
    import librosa

    y = np.asarray(y, dtype=np.float32)
    if y.size < sr // 4:
        return np.zeros(0)
    percussive = librosa.effects.percussive(y)
    _, frames = librosa.beat.beat_track(y=percussive, sr=sr, units="frames")
    return np.asarray(librosa.frames_to_time(frames, sr=sr), dtype=float)


def _frame_speeds(positions: np.ndarray) -> np.ndarray:
    """``(F-1, J)`` joint displacement per frame (m/frame) of ``positions (F, J, 3)``."""
    return np.linalg.norm(np.diff(np.asarray(positions, dtype=float), axis=0), axis=-1)


def motion_beats(positions: np.ndarray, fps: float, variant: Variant) -> np.ndarray:
    """``(K,)`` motion beat times (s) of ``positions (F, J, 3)`` at ``fps`` by ``variant``'s rule.

    ``bailando``: strict local minima of the mean joint speed smoothed with σ = 5 frames·fps/60.
    ``fact``: minima of the summed joint speed that are the lowest within 10·fps/60 frames either
    side. Speed sample i sits between frames i and i+1; beats are reported at frame i + 1 as
    the published code does (its velocity array starts with a zero row).
    """
    speeds = _frame_speeds(positions)
    if speeds.shape[0] < 3:
        return np.zeros(0)
    scale = fps / BAS_FPS
    if variant == "bailando":
        envelope = gaussian_filter1d(speeds.mean(axis=1), BAILANDO_SMOOTH_FRAMES * scale)
        idx = argrelextrema(envelope, np.less)[0]
    elif variant == "fact":
        envelope = speeds.sum(axis=1)
        order = max(1, int(round(FACT_ORDER_FRAMES * scale)))
        idx = argrelextrema(envelope, np.less, order=order)[0]
    else:
        raise ValueError(f"unknown Beat Align Score variant {variant!r}")
    return (idx + 1) / fps


def beat_align_score(
    music_beats: np.ndarray,
    dance_beats: np.ndarray,
    variant: Variant,
    sigma_s: float = BAS_SIGMA_S,
) -> float:
    """Beat Align Score in [0, 1] (1 = every beat of the averaged side has a partner exactly).

    ``bailando`` averages over ``music_beats``, ``fact`` over ``dance_beats`` (both ``(N,)`` s);
    each beat scores exp(−d² / 2σ²) with d the distance to the nearest beat of the other side.
    An empty side to average over, or nothing to match against, scores 0.
    """
    music = np.asarray(music_beats, dtype=float).reshape(-1)
    dance = np.asarray(dance_beats, dtype=float).reshape(-1)
    if variant == "bailando":
        over, against = music, dance
    elif variant == "fact":
        over, against = dance, music
    else:
        raise ValueError(f"unknown Beat Align Score variant {variant!r}")
    if over.size == 0 or against.size == 0:
        return 0.0
    d = np.abs(over[:, None] - against[None, :]).min(axis=1)
    return float(np.mean(np.exp(-(d**2) / (2.0 * sigma_s**2))))


def beat_accuracy(
    music_beats: np.ndarray, kinematic_beats: np.ndarray, tolerance_s: float = ACCURACY_TOLERANCE_S
) -> float:
    """Share in [0, 1] of ``music_beats (N,)`` with a kinematic beat ``(K,)`` within
    ``tolerance_s`` seconds (ChoreoMaster's beat accuracy); 0 when there are no music beats."""
    music = np.asarray(music_beats, dtype=float).reshape(-1)
    kin = np.asarray(kinematic_beats, dtype=float).reshape(-1)
    if music.size == 0 or kin.size == 0:
        return 0.0
    d = np.abs(music[:, None] - kin[None, :]).min(axis=1)
    return float(np.mean(d <= tolerance_s + 1e-9))


def within(beats: np.ndarray, start_s: float, end_s: float) -> np.ndarray:
    """The beats ``(N,)`` inside ``[start_s, end_s]`` (the span a dance actually moves in)."""
    b = np.asarray(beats, dtype=float).reshape(-1)
    return b[(b >= start_s) & (b <= end_s)]
