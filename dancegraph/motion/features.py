"""Kinematic features of dance motion: rhythm curves per bar, phrase positions, kinematic beats.

- ``kinematic_curve``: the motion kinematic curve of Shiratori et al. (2004), a weighted sum of
  joint angular speeds; its local minima are the moments where the dance "stops" on a beat.
- ``bar_rhythm_features``: ChoreoMaster's per-bar rhythm input, ``(5, 60)``: the kinematic curve,
  left/right wrist trajectory curvature and left/right foot contact, resampled onto 60 samples
  across the bar (a 4-beat bar at 120 BPM is 2 s = 60 frames at 30 fps).
- ``phrase_positions``: the 18 main joints' global positions over 8 s at 30 fps, ``(3, 18, 240)``.
- ``kinematic_beats``: local minima of smoothed joint speed, in seconds.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import find_peaks

from dancegraph.motion import quat
from dancegraph.motion.contacts import foot_contacts
from dancegraph.motion.fk import canonical_positions, forward_kinematics
from dancegraph.motion.skeleton import CANONICAL_JOINTS, Motion, Skeleton

#: The 18 main joints (canonical names) of the phrase input and of transition costs.
MAIN_JOINTS: tuple[str, ...] = tuple(j for j in CANONICAL_JOINTS if j != "spine")

BAR_SAMPLES = 60
PHRASE_FPS = 30.0
PHRASE_FRAMES = 240
#: Curvature (1/m) at which the bounded wrist-curvature feature reaches 0.5 (a 10 cm radius).
CURVATURE_HALF_1_M = 10.0
#: Below this speed (m/s) the wrist is "still" and its path curvature is damped toward 0.
CURVATURE_SPEED_FLOOR_M_S = 0.1


def joint_weights(skeleton: Skeleton) -> np.ndarray:
    """``(J,)`` weights summing to 1: the bone length each joint's rotation moves (below it).

    A hip turn moves the whole body, a finger joint almost nothing; this stands in for the
    mass-based weights of Shiratori et al.
    """
    lengths = np.linalg.norm(skeleton.offsets, axis=1)
    lengths[skeleton.parents < 0] = 0.0
    subtree = lengths.copy()
    for end, off in skeleton.end_sites.items():
        subtree[end] += np.linalg.norm(off)
    for j in range(skeleton.n_joints - 1, 0, -1):  # children come after parents
        subtree[skeleton.parents[j]] += subtree[j]
    moved = subtree - lengths  # a joint turns the bones below it, not the one leading to it
    return moved / moved.sum()


def kinematic_curve(motion: Motion, smooth_s: float = 0.03) -> np.ndarray:
    """``(F,)`` weighted joint angular speed, rad/s (Shiratori et al.'s motion kinematic curve).

    Local rotations' angular speed per joint (central differences), weighted by
    ``joint_weights``, smoothed with a Gaussian of ``smooth_s`` seconds.
    """
    rot = motion.rotations
    n_frames = rot.shape[0]
    if n_frames < 2:
        return np.zeros(n_frames)
    # angle between consecutive frames per joint: 2 acos |<q_t, q_t+1>|
    dots = np.abs(np.sum(rot[1:] * rot[:-1], axis=-1)).clip(0.0, 1.0)
    step = 2.0 * np.arccos(dots) * motion.fps  # (F-1, J) rad/s
    speed = np.empty((n_frames, rot.shape[1]))
    speed[0], speed[-1] = step[0], step[-1]
    speed[1:-1] = 0.5 * (step[1:] + step[:-1])
    curve = speed @ joint_weights(motion.skeleton)
    sigma = smooth_s * motion.fps
    return gaussian_filter1d(curve, sigma, mode="nearest") if sigma > 0.3 else curve


def joint_speed(positions: np.ndarray, fps: float, smooth_s: float = 0.05) -> np.ndarray:
    """``(F,)`` mean joint speed (m/s) of world positions ``(F, J, 3)``, Gaussian-smoothed."""
    if positions.shape[0] < 2:
        return np.zeros(positions.shape[0])
    vel = np.gradient(positions, axis=0) * fps
    speed = np.linalg.norm(vel, axis=-1).mean(axis=1)
    sigma = smooth_s * fps
    return gaussian_filter1d(speed, sigma, mode="nearest") if sigma > 0.3 else speed


def kinematic_beats(
    positions: np.ndarray,
    fps: float,
    *,
    smooth_s: float = 0.03,
    min_interval_s: float = 0.15,
    prominence: float = 0.02,
) -> np.ndarray:
    """``(K,)`` seconds: local minima of smoothed mean joint speed (pauses and sharp turns).

    ``positions``: ``(F, J, 3)`` world joint positions (m) at ``fps``. A minimum counts when it
    is at least ``min_interval_s`` from the next one and dips by ``prominence`` × the clip's
    median speed below its surroundings. Each minimum is then moved to the lowest unsmoothed
    speed nearby and refined to sub-frame precision by a parabola through it and its neighbours.
    """
    smooth = joint_speed(positions, fps, smooth_s)
    if smooth.size < 3:
        return np.zeros(0)
    scale = float(np.median(smooth)) + 1e-9
    distance = max(1, int(round(min_interval_s * fps)))
    idx, _ = find_peaks(-smooth, distance=distance, prominence=prominence * scale)
    # Smoothing pulls a pause toward the slower of its neighbouring moves: refine each minimum
    # on the unsmoothed speed within two smoothing widths.
    speed = joint_speed(positions, fps, 0.0)
    reach = int(np.ceil(2.0 * smooth_s * fps))
    if reach > 0 and idx.size:
        offsets = np.arange(-reach, reach + 1)
        window = np.clip(idx[:, None] + offsets[None, :], 0, speed.size - 1)
        idx = window[np.arange(idx.size), np.argmin(speed[window], axis=1)]
        idx = np.unique(idx)
    idx = idx[(idx > 0) & (idx < speed.size - 1)]
    y0, y1, y2 = speed[idx - 1], speed[idx], speed[idx + 1]
    denom = y0 - 2.0 * y1 + y2
    shift = np.where(denom > 1e-12, 0.5 * (y0 - y2) / np.where(denom > 1e-12, denom, 1.0), 0.0)
    return (idx + np.clip(shift, -0.5, 0.5)) / fps


def trajectory_curvature(points: np.ndarray, fps: float) -> np.ndarray:
    """``(F,)`` bounded path curvature in [0, 1) of a point trajectory ``(F, 3)``.

    κ = |v × a| / (|v|³ + v₀³) in 1/m (v₀ damps curvature of a near-still point), mapped to
    κ / (κ + ``CURVATURE_HALF_1_M``).
    """
    if points.shape[0] < 3:
        return np.zeros(points.shape[0])
    smooth = gaussian_filter1d(points, max(0.5, 0.02 * fps), axis=0, mode="nearest")
    vel = np.gradient(smooth, axis=0) * fps
    acc = np.gradient(vel, axis=0) * fps
    speed = np.linalg.norm(vel, axis=-1)
    kappa = np.linalg.norm(np.cross(vel, acc), axis=-1) / (speed**3 + CURVATURE_SPEED_FLOOR_M_S**3)
    return kappa / (kappa + CURVATURE_HALF_1_M)


def rhythm_curves(motion: Motion) -> np.ndarray:
    """``(5, F)`` per-frame rhythm curves of a clip.

    Rows: kinematic curve (rad/s), left and right wrist curvature (0..1), left and right foot
    contact (0/1). Compute once per clip and pass to ``bar_rhythm_features(curves=...)``.
    """
    sk = motion.skeleton
    pos, rot = forward_kinematics(motion)
    wrists = canonical_positions(sk, pos, rot, ["left_wrist", "right_wrist"])
    contacts = foot_contacts(pos, motion.fps, sk, rot)
    return np.stack(
        [
            kinematic_curve(motion),
            trajectory_curvature(wrists[:, 0], motion.fps),
            trajectory_curvature(wrists[:, 1], motion.fps),
            contacts[:, 0].astype(float),
            contacts[:, 1].astype(float),
        ]
    )


def _sample(curves: np.ndarray, fps: float, times: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``(C, F)`` curves at ``times`` (s), held at the ends."""
    frames = np.arange(curves.shape[1]) / fps
    return np.stack([np.interp(times, frames, c) for c in curves])


def bar_rhythm_features(
    motion: Motion, start_s: float, end_s: float, curves: np.ndarray | None = None
) -> np.ndarray:
    """``(5, 60)`` float32 rhythm input of the bar ``[start_s, end_s)`` of ``motion``.

    The five ``rhythm_curves`` are sampled at 60 evenly spaced times across the bar (30 fps for
    a 2 s bar, time-normalised otherwise). The kinematic curve is divided by its maximum within
    the bar, so all rows lie in [0, 1]: the network sees the bar's rhythm, not its energy.
    ``curves``: the clip's ``rhythm_curves`` (faster across many bars, and the contact floor is
    the clip's); without it they are computed on the bar plus 1 s either side.
    """
    if not end_s > start_s:
        raise ValueError(f"bar end {end_s} must follow its start {start_s}")
    offset_s = 0.0
    if curves is None:
        first = max(0, int(np.floor((start_s - 1.0) * motion.fps)))
        stop = min(motion.n_frames, int(np.ceil((end_s + 1.0) * motion.fps)) + 1)
        curves = rhythm_curves(motion.slice(first, stop))
        offset_s = first / motion.fps
    times = start_s + (end_s - start_s) * np.arange(BAR_SAMPLES) / BAR_SAMPLES - offset_s
    out = _sample(curves, motion.fps, times)
    out[0] = out[0] / (out[0].max() + 1e-6)
    return out.astype(np.float32)


def phrase_positions(motion: Motion, start_s: float) -> np.ndarray:
    """``(3, 18, 240)`` float32 world positions (m) of ``MAIN_JOINTS`` over 8 s at 30 fps.

    Sampled at ``start_s + k / 30`` (linear interpolation, the last frame held past the clip's
    end), then expressed relative to the hips at ``start_s``: ground-plane position moved to the
    origin and heading turned to face +Z, so a phrase's shape does not depend on where on the
    stage or which way it was danced. Channel axis first (x, y, z).
    """
    fps = motion.fps
    times = start_s + np.arange(PHRASE_FRAMES) / PHRASE_FPS
    first = max(0, min(motion.n_frames - 1, int(np.floor(start_s * fps))))
    stop = min(motion.n_frames, int(np.ceil(times[-1] * fps)) + 2)
    clip = motion.slice(first, max(stop, first + 1))
    pos, rot = forward_kinematics(clip)
    pts = canonical_positions(clip.skeleton, pos, rot, MAIN_JOINTS)  # (f, 18, 3)
    frame_t = (first + np.arange(pts.shape[0])) / fps
    flat = pts.reshape(pts.shape[0], -1)
    sampled = np.stack([np.interp(times, frame_t, c) for c in flat.T], axis=1)
    sampled = sampled.reshape(PHRASE_FRAMES, len(MAIN_JOINTS), 3)
    # canonicalise on the hips at the first sample
    root_t = np.array([np.interp(times[0], frame_t, pos[:, 0, a]) for a in range(3)])
    k0 = int(np.clip(round((times[0] - frame_t[0]) * fps), 0, pos.shape[0] - 1))
    heading = quat.heading_angle(rot[k0, 0])
    turn = quat.from_y_angle(-heading)
    sampled = sampled - np.array([root_t[0], 0.0, root_t[2]])
    sampled = quat.rotate(np.broadcast_to(turn, sampled.shape[:-1] + (4,)), sampled)
    return np.ascontiguousarray(sampled.transpose(2, 1, 0)).astype(np.float32)
