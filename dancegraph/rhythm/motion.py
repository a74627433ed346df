"""The rhythm of dance: Shiratori-style motion beats (the moments the dancer stops), the motion
side of rhythm signatures (ChoreoMaster §3.2) and of the seeds' beat accuracy.

After Shiratori & Ikeuchi (2008), a dance's rhythm is read from the speeds of the hands (relative
to the body), the feet and the centre of mass: a motion beat is a moment where they come to a
stop between two moves. Inputs are SMPL-like joint positions ``(F, 24, 3)`` in metres
(``metrics.kinetic.smpl_positions``, ``SMPL_JOINTS`` order) at ``fps``; times in seconds.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import argrelextrema

from dancegraph.metrics.kinetic import smpl_positions
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.skeleton import Motion

#: Shiratori-style motion beats (values chosen on the generated demo library, whose key poses
#: are exact, see docs/evaluation.md): the speed curve's Gaussian smoothing (s) ...
STOP_SMOOTH_S = 0.03
#: ... the window (s) of the running mean the stop and move thresholds are relative to ...
STOP_WINDOW_S = 1.0
#: ... a stop is a local minimum below this fraction of the running mean ...
STOP_RATIO = 1.0
#: ... and two stops count separately only when the body moves in between: the curve rises
#: above this fraction of the running mean (otherwise the lower of the two is kept).
MOVE_RATIO = 0.6
#: m/s: a body part of the stop curve moving slower than this on average is held still.
STILL_SPEED = 1e-4

# SMPL_JOINTS indices (metrics.kinetic) of the body parts Shiratori's motion rhythm watches
_PELVIS = 0
_WRISTS = (20, 21)
_ANKLES = (7, 8)


def _running_mean(x: np.ndarray, width: int) -> np.ndarray:
    """Mean of ``x`` over a centred window of ``width`` samples (shrunk at the ends)."""
    c = np.concatenate([[0.0], np.cumsum(x)])
    i = np.arange(x.size)
    lo = np.clip(i - width // 2, 0, x.size)
    hi = np.clip(i + width // 2 + 1, 0, x.size)
    return (c[hi] - c[lo]) / (hi - lo)


def stop_curve(smpl: np.ndarray, fps: float) -> np.ndarray:
    """``(F,)`` Shiratori's motion rhythm curve: the speeds (m/s) of the hands relative to the
    pelvis (Shiratori measures them in the body's frame), of the feet and of the centre of mass
    (mean of the 24 joints), each divided by its own mean over the dance so the three weigh
    alike (a part whose mean speed is under ``STILL_SPEED`` is left out: it does not move, and
    its rounding noise must not weigh as a move), summed, Gaussian-smoothed over
    ``STOP_SMOOTH_S``; all zeros for a motion that does not move. ``smpl (F, 24, 3)`` at ``fps``."""
    smpl = np.asarray(smpl, dtype=float)
    if smpl.shape[0] < 2:
        return np.zeros(smpl.shape[0])
    pelvis = smpl[:, _PELVIS : _PELVIS + 1]
    parts = [
        np.gradient(smpl[:, list(_WRISTS)] - pelvis, axis=0),
        np.gradient(smpl[:, list(_ANKLES)], axis=0),
        np.gradient(smpl.mean(axis=1, keepdims=True), axis=0),
    ]
    curve = np.zeros(smpl.shape[0])
    for v in parts:
        speed = np.linalg.norm(v, axis=-1).sum(axis=1) * fps
        if speed.mean() > STILL_SPEED:
            curve += speed / speed.mean()
    return gaussian_filter1d(curve, STOP_SMOOTH_S * fps, mode="nearest")


def shiratori_beats(smpl: np.ndarray, fps: float) -> np.ndarray:
    """``(K,)`` motion beat times (s) after Shiratori & Ikeuchi (2008): the moments the dancer
    stops, local minima of ``stop_curve`` that lie below ``STOP_RATIO`` × its running mean
    (``STOP_WINDOW_S``); of two stops with no move between them (the curve stays below
    ``MOVE_RATIO`` × the running mean) the lower is kept. Minima are refined to sub-frame time
    by a parabola through the three samples. ``smpl (F, 24, 3)`` metres at ``fps``."""
    curve = stop_curve(smpl, fps)
    if curve.size < 3:
        return np.zeros(0)
    level = _running_mean(curve, max(3, int(round(STOP_WINDOW_S * fps))))
    idx = argrelextrema(curve, np.less)[0]
    idx = idx[curve[idx] < STOP_RATIO * level[idx]]
    kept: list[int] = []
    for i in idx.tolist():
        if kept and curve[kept[-1] : i + 1].max() < MOVE_RATIO * level[kept[-1] : i + 1].max():
            if curve[i] < curve[kept[-1]]:
                kept[-1] = i
            continue
        kept.append(i)
    k = np.asarray(kept, dtype=int)
    k = k[(k > 0) & (k < curve.size - 1)]
    y0, y1, y2 = curve[k - 1], curve[k], curve[k + 1]
    denom = y0 - 2.0 * y1 + y2
    shift = np.where(denom > 1e-12, 0.5 * (y0 - y2) / np.where(denom > 1e-12, denom, 1.0), 0.0)
    return (k + np.clip(shift, -0.5, 0.5)) / fps


def motion_stops(motion: Motion) -> np.ndarray:
    """``(K,)`` s: the ``shiratori_beats`` of a motion, read on its SMPL-like joints
    (``metrics.kinetic.smpl_positions``) at its own frame rate; raises ``skeleton_unmapped``
    where a canonical joint is missing."""
    return motion_rhythm(motion)[1]


def motion_rhythm(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """A motion's ``stop_curve`` ``(F,)`` and its stops ``(K,)`` s (``shiratori_beats``), from one
    forward kinematics at its own frame rate; raises ``skeleton_unmapped`` where a canonical
    joint is missing."""
    positions, world = forward_kinematics(motion)
    smpl = smpl_positions(motion.skeleton, positions, world)
    return stop_curve(smpl, motion.fps), shiratori_beats(smpl, motion.fps)
