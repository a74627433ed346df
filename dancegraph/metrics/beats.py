"""Beat alignment of a dance to its music, as the seeds measure it, and its chance rows.

Motion inputs are SMPL-like joint positions ``(F, 24, 3)`` in metres (``metrics.kinetic``'s
``smpl_positions``, in ``SMPL_JOINTS`` order) at ``fps``; the published scores are defined at
60 fps. Times are seconds. Each metric names the motion beats and the music points it compares:

- ``cm_accuracy`` (ChoreoMaster's beat accuracy): the share of the music's *rhythm points* (the
  active slots of each bar's rhythm signature, ``rhythm.music.rhythm_points``) that have a
  Shiratori-style motion beat (``rhythm.motion.shiratori_beats``) within
  ``ACCURACY_TOLERANCE_S``.
- ``beat_accuracy`` (all beats): the same share over *every* tracked beat, with the kinematic
  beats of ``motion.features``: a different metric, labelled so.
- Beat Align Score, σ = 3 frames at 60 fps, in its two published variants (they differ, so every
  number carries its label); music beats from librosa's tracker on the percussive part:

  * ``bailando`` (Li et al., CVPR 2022): motion beats are the strict local minima of the mean
    joint displacement per frame smoothed by a Gaussian of σ = 5 frames, at the frame where the
    displacement starts; averaged over *music* beats: mean_m exp(−min_k (m − k)² / 2σ²).
  * ``fact`` (AI Choreographer, ICCV 2021): motion beats are the minima of the *summed* joint
    displacement (a zero first frame) that are the lowest within 10 frames either side, at the
    frame the displacement ends; averaged over *motion* beats.
- ``phase_concentration``: R = |mean e^{2πiφ}| of the motion beats' phases φ on the song's beat
  grid (0: no relation, 1: every motion beat at one phase), and that mean phase (in beats).

Chance rows (``SyncGrid``): the same dance against the music shifted by half a beat
(``SyncGrid.half_beat``) and against another song's grid. R does not change under a constant
phase shift, so its only chance row is another song's grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import argrelextrema

from dancegraph.rhythm.motion import shiratori_beats

#: Frame rate at which the published scores are defined.
BAS_FPS = 60.0
#: σ of the Beat Align Score: 3 frames at 60 fps.
BAS_SIGMA_S = 3.0 / BAS_FPS
#: Bailando's smoothing of the mean joint speed (frames at 60 fps).
BAILANDO_SMOOTH_FRAMES = 5.0
#: FACT's motion beats are minima over ±10 frames (at 60 fps).
FACT_ORDER_FRAMES = 10
#: A music point is "hit" when a motion beat lies within this many seconds (ChoreoMaster).
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


def _displacements(positions: np.ndarray) -> np.ndarray:
    """``(F-1, J)`` joint displacement per frame (m/frame) of ``positions (F, J, 3)``."""
    return np.linalg.norm(np.diff(np.asarray(positions, dtype=float), axis=0), axis=-1)


def motion_beats(positions: np.ndarray, fps: float, variant: Variant) -> np.ndarray:
    """``(K,)`` motion beat times (s) of ``positions (F, J, 3)`` at ``fps`` by ``variant``'s rule.

    ``bailando``: strict local minima of the mean joint displacement, smoothed with σ =
    5 frames·fps/60; displacement i (frames i → i+1) is reported at frame i, as the published
    code indexes it. ``fact``: the summed joint displacement with a zero first row (displacement
    i − 1 → i at frame i), minima lowest within 10·fps/60 frames either side (scipy's
    ``argrelextrema``, clipped at the ends). Raises ``ValueError`` for another variant.
    """
    disp = _displacements(positions)
    if variant not in ("bailando", "fact"):
        raise ValueError(f"unknown Beat Align Score variant {variant!r}")
    if disp.shape[0] < 3:
        return np.zeros(0)
    scale = fps / BAS_FPS
    if variant == "bailando":
        envelope = gaussian_filter1d(disp.mean(axis=1), BAILANDO_SMOOTH_FRAMES * scale)
        return argrelextrema(envelope, np.less)[0] / fps
    envelope = np.concatenate([[0.0], disp.sum(axis=1)])
    order = max(1, int(round(FACT_ORDER_FRAMES * scale)))
    return argrelextrema(envelope, np.less, order=order)[0] / fps


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
    points: np.ndarray, motion_beats: np.ndarray, tolerance_s: float = ACCURACY_TOLERANCE_S
) -> float:
    """Share in [0, 1] of the music ``points (N,)`` (rhythm points, or beats) with a motion beat
    ``(K,)`` within ``tolerance_s`` seconds; 0 when there are no points."""
    music = np.asarray(points, dtype=float).reshape(-1)
    kin = np.asarray(motion_beats, dtype=float).reshape(-1)
    if music.size == 0 or kin.size == 0:
        return 0.0
    d = np.abs(music[:, None] - kin[None, :]).min(axis=1)
    return float(np.mean(d <= tolerance_s + 1e-9))


def phase_concentration(beats: np.ndarray, events: np.ndarray) -> tuple[float, float]:
    """``(R, phase)`` of ``events (K,)`` on the beat grid ``beats (N,)`` (s): each event inside
    the grid gets the phase φ ∈ [0, 1) of its place between the two beats around it;
    R = |mean e^{2πiφ}| and ``phase`` (beats, in [0, 1)) is the mean direction. ``(0, 0)`` with
    fewer than two beats or no event inside them."""
    b = np.asarray(beats, dtype=float).reshape(-1)
    e = np.asarray(events, dtype=float).reshape(-1)
    if b.size < 2:
        return 0.0, 0.0
    e = e[(e >= b[0]) & (e < b[-1])]
    if e.size == 0:
        return 0.0, 0.0
    phi = np.interp(e, b, np.arange(b.size)) % 1.0
    z = np.exp(2j * np.pi * phi).mean()
    return float(abs(z)), float((np.angle(z) / (2 * np.pi)) % 1.0)


def half_beat_shift(times: np.ndarray, beats: np.ndarray) -> np.ndarray:
    """``times (N,)`` each moved later by half the beat period around it (the interval of
    ``beats (M,)`` it falls in; the nearest interval outside the grid)."""
    t = np.asarray(times, dtype=float).reshape(-1)
    b = np.asarray(beats, dtype=float).reshape(-1)
    if b.size < 2 or t.size == 0:
        return t.copy()
    k = np.clip(np.searchsorted(b, t, side="right") - 1, 0, b.size - 2)
    return t + 0.5 * (b[k + 1] - b[k])


def within(times: np.ndarray, start_s: float, end_s: float) -> np.ndarray:
    """The times ``(N,)`` inside ``[start_s, end_s]`` (the span a dance actually moves in)."""
    b = np.asarray(times, dtype=float).reshape(-1)
    return b[(b >= start_s) & (b <= end_s)]


@dataclass(frozen=True)
class SyncGrid:
    """The music side of the sync metrics, seconds: ``beats (N,)`` the tracker's beats,
    ``percussive_beats (M,)`` librosa's on the percussive part (the BAS's), ``rhythm_points
    (P,)`` the active slots of each bar's rhythm signature, ``span`` the music's bars (start of
    the first, end of the last)."""

    beats: np.ndarray
    percussive_beats: np.ndarray
    rhythm_points: np.ndarray
    span: tuple[float, float]

    def half_beat(self) -> SyncGrid:
        """The same grid with every point half a beat later (a chance row)."""
        return SyncGrid(
            beats=half_beat_shift(self.beats, self.beats),
            percussive_beats=half_beat_shift(self.percussive_beats, self.beats),
            rhythm_points=half_beat_shift(self.rhythm_points, self.beats),
            span=self.span,
        )


@dataclass(frozen=True)
class DanceBeats:
    """The motion side, seconds: ``shiratori``, ``bailando``, ``fact`` (``motion_beats``) and
    ``kinematic`` (``motion.features.kinematic_beats``, the all-beats accuracy's)."""

    shiratori: np.ndarray
    bailando: np.ndarray
    fact: np.ndarray
    kinematic: np.ndarray

    @classmethod
    def of(cls, smpl: np.ndarray, fps: float, kinematic: np.ndarray) -> DanceBeats:
        """Every detector on ``smpl (F, 24, 3)`` at ``fps``; ``kinematic (K,)`` given."""
        return cls(
            shiratori=shiratori_beats(smpl, fps),
            bailando=motion_beats(smpl, fps, "bailando"),
            fact=motion_beats(smpl, fps, "fact"),
            kinematic=np.asarray(kinematic, dtype=float),
        )


#: The sync metrics of ``sync_scores``, in table order.
SYNC_METRICS: tuple[str, ...] = (
    "cm_accuracy",
    "beat_accuracy",
    "bas_bailando",
    "bas_fact",
    "bas_beats",
    "phase_r",
)


def sync_scores(dance: DanceBeats, grid: SyncGrid, span: tuple[float, float]) -> dict:
    """Every sync metric of ``dance`` against ``grid``, counting only the points and motion beats
    inside ``span`` (where the dance moves) and the grid's own span: ``{cm_accuracy,
    beat_accuracy, bas_bailando, bas_fact, bas_beats, phase_r, phase}`` (``bas_beats``: Bailando's
    rule against the tracker's beats instead of librosa's; ``phase``: the motion beats' mean
    phase on the beat grid, in beats; ``cm_accuracy`` None where the grid has no rhythm
    points there)."""
    a, b = max(span[0], grid.span[0]), min(span[1], grid.span[1])
    r, phase = phase_concentration(within(grid.beats, a, b), within(dance.shiratori, a, b))
    points = within(grid.rhythm_points, a, b)
    return {
        "cm_accuracy": beat_accuracy(points, within(dance.shiratori, a, b))
        if points.size
        else None,
        "beat_accuracy": beat_accuracy(within(grid.beats, a, b), within(dance.kinematic, a, b)),
        "bas_bailando": beat_align_score(
            within(grid.percussive_beats, a, b), within(dance.bailando, a, b), "bailando"
        ),
        "bas_fact": beat_align_score(
            within(grid.percussive_beats, a, b), within(dance.fact, a, b), "fact"
        ),
        "bas_beats": beat_align_score(
            within(grid.beats, a, b), within(dance.bailando, a, b), "bailando"
        ),
        "phase_r": r,
        "phase": phase,
    }
