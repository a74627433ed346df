"""FID-style kinetic distance (FID_k): AIST++ kinetic features on 24 SMPL-like joints at 60 fps.

- ``smpl_positions`` maps any skeleton with the canonical joints onto the 24 SMPL joints (in
  SMPL order). Joints our skeletons lack are made from neighbours: spine2 halfway between spine
  and chest; a collar is the shoulder's parent joint when that is a clavicle, else halfway
  between neck and shoulder; a hand is the wrist's first child (or End Site), else the forearm
  extended by 40 %.
- ``kinetic_features``: per joint the mean squared horizontal speed, the mean squared vertical
  speed and the mean acceleration magnitude, speeds and accelerations averaged over a sliding
  window of ±2 frames (AIST++'s ``KineticFeatures``, frame time 1/60 s, Y up): ``(72,)``.
- ``frechet_distance``: ‖μ_a − μ_b‖² + Tr(Σ_a + Σ_b − 2 (Σ_a Σ_b)^½) of two feature sets.

Feature sets are normalised by the *reference* set's mean and standard deviation (the library's
real dances) so that the rows of one evaluation share one scale (Bailando normalises each pair of
sets jointly, which moves the scale from row to row).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter1d

from dancegraph.motion.fk import canonical_positions, end_site_positions
from dancegraph.motion.skeleton import Skeleton

SMPL_JOINTS: tuple[str, ...] = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
)
#: SMPL joints that are one canonical joint of ours.
_DIRECT = {
    "pelvis": "hips",
    "spine1": "spine",
    "spine3": "chest",
    "left_foot": "left_toe",
    "right_foot": "right_toe",
}
KINETIC_FPS = 60.0
KINETIC_WINDOW = 2  # frames either side (AIST++'s sliding_window)
HAND_EXTENSION = 0.4  # forearm fraction that stands in for a missing hand joint


def smpl_positions(
    skeleton: Skeleton, positions: np.ndarray, world_rotations: np.ndarray
) -> np.ndarray:
    """``(F, 24, 3)`` SMPL-like joint positions (m) from world positions ``(F, J, 3)`` and world
    rotations ``(F, J, 4)``; raises ``skeleton_unmapped`` when a canonical joint is missing."""
    from dancegraph.motion.skeleton import CANONICAL_JOINTS

    canon = canonical_positions(skeleton, positions, world_rotations, CANONICAL_JOINTS)
    c = {name: canon[:, k] for k, name in enumerate(CANONICAL_JOINTS)}
    ends = None
    out = []
    for joint in SMPL_JOINTS:
        side = joint.split("_")[0]
        if joint in _DIRECT:
            out.append(c[_DIRECT[joint]])
        elif joint == "spine2":
            out.append(0.5 * (c["spine"] + c["chest"]))
        elif joint.endswith("_collar"):
            shoulder = skeleton.index(skeleton.canonical[f"{side}_shoulder"])
            parent = int(skeleton.parents[shoulder])
            trunk = {skeleton.canonical.get(k) for k in ("chest", "neck", "spine", "hips")}
            if parent >= 0 and skeleton.names[parent] not in trunk:
                out.append(positions[:, parent])
            else:
                out.append(0.5 * (c["neck"] + c[f"{side}_shoulder"]))
        elif joint.endswith("_hand"):
            wrist = skeleton.index(skeleton.canonical[f"{side}_wrist"])
            kids = skeleton.children(wrist)
            if kids:
                out.append(positions[:, kids[0]])
            elif wrist in skeleton.end_sites:
                if ends is None:
                    ends = end_site_positions(skeleton, positions, world_rotations)
                out.append(ends[wrist])
            else:
                w, e = c[f"{side}_wrist"], c[f"{side}_elbow"]
                out.append(w + HAND_EXTENSION * (w - e))
        else:
            out.append(c[joint])
    return np.stack(out, axis=1)


def _windowed(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Mean of ``values (N, J)`` over the valid entries within ±``KINETIC_WINDOW`` samples."""
    size = 2 * KINETIC_WINDOW + 1
    v = np.where(valid[:, None], values, 0.0)
    total = uniform_filter1d(v, size, axis=0, mode="constant") * size
    count = uniform_filter1d(valid.astype(float), size, mode="constant") * size
    return total / np.maximum(count, 1e-9)[:, None]


def kinetic_features(positions: np.ndarray, fps: float = KINETIC_FPS) -> np.ndarray:
    """``(3·J,)`` kinetic features of ``positions (F, J, 3)`` (m, Y up) at ``fps``: per joint
    [mean squared horizontal speed (m²/s²), mean squared vertical speed (m²/s²), mean
    acceleration magnitude (m/s²)], joint-major. Needs at least 3 frames."""
    pos = np.asarray(positions, dtype=float)
    n = pos.shape[0]
    if n < 3:
        raise ValueError(f"kinetic features need at least 3 frames, got {n}")
    d = np.diff(pos, axis=0) * fps  # (F-1, J, 3): velocity between frames i and i+1
    vh = np.linalg.norm(d[..., [0, 2]], axis=-1)
    vv = np.abs(d[..., 1])
    acc = np.linalg.norm(np.diff(d, axis=0), axis=-1) * fps  # (F-2, J), centred on frame i+1
    # AIST++ evaluates frames 1 .. F-2, each from the window of samples around it
    valid_v = np.ones(n - 1, dtype=bool)
    valid_a = np.ones(n - 2, dtype=bool)
    vh_w = _windowed(vh, valid_v)[:-1]  # sample i-1 (frames i-1 → i) for frame i = 1 .. F-2
    vv_w = _windowed(vv, valid_v)[:-1]
    acc_w = _windowed(acc, valid_a)
    feats = np.stack([(vh_w**2).mean(0), (vv_w**2).mean(0), acc_w.mean(0)], axis=1)
    return feats.reshape(-1)


def window_features(positions: np.ndarray, fps: float, window_s: float) -> np.ndarray:
    """``(W, 3·J)`` kinetic features of consecutive non-overlapping ``window_s`` windows of
    ``positions (F, J, 3)``; a trailing part shorter than half a window is dropped."""
    n = positions.shape[0]
    w = max(3, int(round(window_s * fps)))
    starts = list(range(0, max(n - w // 2, 1), w))
    rows = [kinetic_features(positions[s : s + w], fps) for s in starts if n - s >= max(3, w // 2)]
    return np.stack(rows) if rows else np.zeros((0, 3 * positions.shape[1]))


def normaliser(reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation ``(D,)`` of reference features ``(N, D)`` (std floored)."""
    ref = np.asarray(reference, dtype=float)
    return ref.mean(axis=0), np.maximum(ref.std(axis=0), 1e-8)


def frechet_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance between Gaussians fitted to feature sets ``a (N, D)`` and ``b (M, D)``
    (each needs two rows or more)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if len(a) < 2 or len(b) < 2:
        raise ValueError("the Fréchet distance needs at least two samples per set")
    mu_a, mu_b = a.mean(0), b.mean(0)
    cov_a, cov_b = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    # Tr (Σa Σb)^½ = Σ √λ of the symmetric PSD matrix Σa^½ Σb Σa^½ (stable when rank-deficient)
    w, v = np.linalg.eigh(np.atleast_2d(cov_a))
    half = (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T
    lam = np.linalg.eigvalsh(half @ np.atleast_2d(cov_b) @ half)
    cross = float(np.sqrt(np.clip(lam, 0.0, None)).sum())
    value = float(((mu_a - mu_b) ** 2).sum() + np.trace(cov_a) + np.trace(cov_b) - 2.0 * cross)
    return max(value, 0.0)
