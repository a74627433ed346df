"""Time warping: a clip onto a new frame count and frame rate (linear root, slerp rotations)."""

from __future__ import annotations

import numpy as np

from dancegraph.motion import quat
from dancegraph.motion.skeleton import Motion


def sample(motion: Motion, frames: np.ndarray) -> Motion:
    """Motion sampled at fractional source frame indices ``frames (N,)`` (clamped to the clip).

    Root positions are interpolated linearly, rotations by slerp along the shorter arc. The
    result keeps ``motion.fps``; callers set the rate they mean.
    """
    f = np.clip(np.asarray(frames, dtype=float), 0.0, motion.n_frames - 1)
    lo = np.floor(f).astype(np.int64)
    hi = np.minimum(lo + 1, motion.n_frames - 1)
    t = f - lo
    root = motion.root_positions[lo] + t[:, None] * (
        motion.root_positions[hi] - motion.root_positions[lo]
    )
    rot = quat.slerp(motion.rotations[lo], motion.rotations[hi], t[:, None])
    return Motion(motion.skeleton, motion.fps, root, rot)


def retime(motion: Motion, n_frames: int, fps: float, *, endpoint: bool = False) -> Motion:
    """Warp a clip uniformly onto ``n_frames`` frames at ``fps``.

    Default (half-open, for bars laid end to end): the clip's span ``[0, F)`` frames maps onto
    ``[0, n_frames)``, so output frame k shows source frame ``k · F / n_frames`` and the next
    clip's first frame takes the place of the (absent) frame ``n_frames``. With ``endpoint``
    the first and last frames map onto each other (``k · (F-1) / (n_frames-1)``), for a clip
    that includes its closing downbeat. Rotations are slerped, the root interpolated linearly.
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be at least 1, got {n_frames}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    k = np.arange(n_frames, dtype=float)
    if endpoint:
        src = k * (motion.n_frames - 1) / max(n_frames - 1, 1)
    else:
        src = k * motion.n_frames / n_frames
    out = sample(motion, src)
    out.fps = float(fps)
    return out


def resample(motion: Motion, fps: float) -> Motion:
    """The same motion at another frame rate (same duration ``F / fps_src`` seconds)."""
    n = max(1, int(round(motion.n_frames * fps / motion.fps)))
    return retime(motion, n, fps)
