"""Foot contacts (height + speed) and foot-skate cleanup by two-bone IK on planted feet."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_closing, binary_opening, gaussian_filter1d

from dancegraph.motion import quat
from dancegraph.motion.fk import (
    canonical_positions,
    fk_arrays,
    require_canonical,
)
from dancegraph.motion.skeleton import Motion, Skeleton

#: A foot point is planted when it is this close (m) above its own floor level ...
CONTACT_HEIGHT_M = 0.05
#: ... and moves slower than this (m/s, smoothed over ~30 ms).
CONTACT_SPEED_M_S = 0.35
#: Contacts and gaps shorter than this are dropped (s).
MIN_CONTACT_S = 0.05

_FOOT_KEYS = (("left_ankle", "left_toe"), ("right_ankle", "right_toe"))


def foot_points(
    positions: np.ndarray, skeleton: Skeleton, world_rotations: np.ndarray | None = None
) -> np.ndarray:
    """``(F, 2, 2, 3)`` world positions of (left, right) × (ankle, toe), metres.

    Without ``world_rotations`` a skeleton without toe joints uses the ankle for both points;
    with them, the ankle's End Site stands in for the toe.
    """
    keys = [k for pair in _FOOT_KEYS for k in pair]
    if world_rotations is None:
        # without rotations there are no End Sites: a toe-less skeleton's ankle stands in
        require_canonical(skeleton, keys)
        pts = np.stack([positions[:, skeleton.index(skeleton.canonical[k])] for k in keys], axis=1)
    else:
        pts = canonical_positions(skeleton, positions, world_rotations, keys)
    return pts.reshape(positions.shape[0], 2, 2, 3)


def foot_contacts(
    positions: np.ndarray,
    fps: float,
    skeleton: Skeleton,
    world_rotations: np.ndarray | None = None,
    *,
    height_m: float = CONTACT_HEIGHT_M,
    speed_m_s: float = CONTACT_SPEED_M_S,
) -> np.ndarray:
    """``(F, 2)`` bool: (left, right) foot planted per frame.

    ``positions``: ``(F, J, 3)`` world joint positions (m), Y up. A foot is planted where its
    ankle or toe is within ``height_m`` of that point's floor level (the 5th height percentile
    over the clip, so a clip whose floor is not at y = 0 still works) and slower than
    ``speed_m_s``. Blips and gaps shorter than ``MIN_CONTACT_S`` are removed.
    """
    pts = foot_points(positions, skeleton, world_rotations)  # (F, 2, 2, 3)
    return point_contacts(pts, fps, height_m=height_m, speed_m_s=speed_m_s)


def point_contacts(
    points: np.ndarray,
    fps: float,
    *,
    height_m: float = CONTACT_HEIGHT_M,
    speed_m_s: float = CONTACT_SPEED_M_S,
) -> np.ndarray:
    """``(F, 2)`` bool: (left, right) foot planted per frame, from ``foot_points`` output.

    ``points``: ``(F, 2, 2, 3)`` world positions (m, Y up) of (left, right) × (ankle, toe).
    The rule of ``foot_contacts``: a point within ``height_m`` of its own floor level (5th
    height percentile) and slower than ``speed_m_s`` plants its foot; blips and gaps shorter
    than ``MIN_CONTACT_S`` are removed.
    """
    pts = np.asarray(points, dtype=float)
    n_frames = pts.shape[0]
    height = pts[..., 1]
    floor = np.percentile(height, 5, axis=0)
    sigma = max(0.5, 0.015 * fps)
    smooth = gaussian_filter1d(pts, sigma, axis=0, mode="nearest") if n_frames > 1 else pts
    if n_frames > 1:
        speed = np.linalg.norm(np.gradient(smooth, axis=0), axis=-1) * fps
    else:
        speed = np.zeros(height.shape)
    planted = ((height - floor) < height_m) & (speed < speed_m_s)
    contacts = planted.any(axis=2)
    width = max(1, int(round(MIN_CONTACT_S * fps)))
    if width > 1 and n_frames > 2 * width:
        structure = np.ones(width, dtype=bool)
        for side in range(2):
            c = binary_closing(contacts[:, side], structure, border_value=0) | contacts[:, side]
            contacts[:, side] = binary_opening(c, structure)
    return contacts


def step_onsets(contacts: np.ndarray, fps: float) -> np.ndarray:
    """``(N,)`` times (s), increasing, at which a foot is planted: the first frame of every
    contact of either foot after the take's first frame (``contacts``: ``(F, 2)`` bool)."""
    c = np.asarray(contacts, dtype=bool)
    starts = c[1:] & ~c[:-1]  # (F - 1, 2)
    return np.sort(np.nonzero(starts)[0] + 1) / fps


def _leg_joints(skeleton: Skeleton) -> np.ndarray:
    """The joints of the feet (``foot_points``) and every joint above them."""
    keys = [k for pair in _FOOT_KEYS for k in pair]
    require_canonical(skeleton, keys)
    return np.array([skeleton.index(skeleton.canonical[k]) for k in keys])


def _segments(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` runs of True in a 1-D bool array."""
    padded = np.concatenate([[False], mask, [False]])
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def _rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Shortest-arc unit quaternions ``(..., 4)`` turning directions ``u`` into ``v``."""
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    w = 1.0 + np.sum(u * v, axis=-1, keepdims=True)
    q = np.concatenate([np.cross(u, v), w], axis=-1)
    # antiparallel: any axis perpendicular to u
    anti = w[..., 0] < 1e-9
    if np.any(anti):
        perp = np.cross(u[anti], [1.0, 0.0, 0.0])
        weak = np.linalg.norm(perp, axis=-1) < 1e-6
        perp[weak] = np.cross(u[anti][weak], [0.0, 0.0, 1.0])
        q[anti] = np.concatenate([perp, np.zeros((perp.shape[0], 1))], axis=-1)
    return quat.normalize(q)


def two_bone_ik(
    hip: np.ndarray,
    knee: np.ndarray,
    ankle: np.ndarray,
    target: np.ndarray,
    hip_world: np.ndarray,
    knee_world: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Analytic two-bone IK: new world rotations of the hip and knee joints ``(N, 4)`` each.

    ``hip, knee, ankle, target``: ``(N, 3)`` world positions; ``hip_world, knee_world``: ``(N, 4)``.
    The knee stays in the plane of the target and its current bend direction; bone lengths are
    kept; an unreachable target is approached along the hip→target line (leg straight).
    """
    l1 = np.linalg.norm(knee - hip, axis=-1)
    l2 = np.linalg.norm(ankle - knee, axis=-1)
    to_t = target - hip
    dist = np.linalg.norm(to_t, axis=-1)
    direction = to_t / np.maximum(dist, 1e-9)[:, None]
    reach = np.clip(dist, np.abs(l1 - l2) + 1e-6, l1 + l2 - 1e-6)
    along = (l1**2 - l2**2 + reach**2) / (2.0 * reach)
    height = np.sqrt(np.maximum(l1**2 - along**2, 0.0))
    bend = knee - hip
    pole = bend - np.sum(bend * direction, axis=-1, keepdims=True) * direction
    pole_len = np.linalg.norm(pole, axis=-1)
    # a straight leg has no bend direction: fall back to the knee's forward (+Z) axis
    fallback = quat.rotate(knee_world, np.broadcast_to([0.0, 0.0, 1.0], knee.shape))
    fallback -= np.sum(fallback * direction, axis=-1, keepdims=True) * direction
    pole = np.where((pole_len > 1e-6)[:, None], pole, fallback)
    pole /= np.maximum(np.linalg.norm(pole, axis=-1, keepdims=True), 1e-9)
    new_knee = hip + along[:, None] * direction + height[:, None] * pole
    new_ankle = hip + reach[:, None] * direction
    r_hip = _rotation_between(knee - hip, new_knee - hip)
    shin_after = quat.rotate(r_hip, ankle - knee)
    r_knee = quat.multiply(_rotation_between(shin_after, new_ankle - new_knee), r_hip)
    return quat.multiply(r_hip, hip_world), quat.multiply(r_knee, knee_world)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _fade_between_runs(corr: np.ndarray, runs: list[tuple[int, int]], blend: int) -> None:
    """Fill ``corr (F, 3)`` outside the contact ``runs`` in place, continuously: a gap shorter
    than two blends glides from one run's correction to the next; a longer one fades each run's
    correction out (in) over ``blend`` frames after (before) it; before the first and after the
    last run the correction fades likewise."""
    n = len(corr)
    edges: list[tuple[int | None, int | None]] = [(None, runs[0][0])] if runs else []
    edges += [(a[1] - 1, b[0]) for a, b in zip(runs[:-1], runs[1:], strict=True)]
    edges += [(runs[-1][1] - 1, None)] if runs else []
    for last, first in edges:  # last frame of the run before, first frame of the run after
        lo = 0 if last is None else last + 1
        hi = n if first is None else first
        if hi <= lo:
            continue
        f = np.arange(lo, hi)
        if last is not None and first is not None and hi - lo <= 2 * blend:
            u = _smoothstep((f - last) / (first - last))[:, None]
            corr[lo:hi] = (1.0 - u) * corr[last] + u * corr[first]
            continue
        if last is not None:
            w = _smoothstep(1.0 - (f - last) / (blend + 1))[:, None]
            corr[lo:hi] += w * corr[last]
        if first is not None:
            w = _smoothstep(1.0 - (first - f) / (blend + 1))[:, None]
            corr[lo:hi] += w * corr[first]


def _sliding(points: np.ndarray, mask: np.ndarray, fps: float) -> tuple[float, float]:
    """Mean horizontal speed (m/s) and total distance (m) of ``points (F, 3)`` over ``mask``."""
    step = np.linalg.norm(np.diff(points[:, [0, 2]], axis=0), axis=-1)
    both = mask[1:] & mask[:-1]
    if not both.any():
        return 0.0, 0.0
    return float(step[both].mean() * fps), float(step[both].sum())


def clean_foot_skate(
    motion: Motion,
    contacts: np.ndarray | None = None,
    *,
    blend_s: float = 0.1,
) -> tuple[Motion, dict]:
    """Lock planted feet in place with two-bone leg IK; returns the motion and a report.

    In each contact run the foot's lower point (ankle or toe) is pinned to its mean ground-plane
    position (its height is left as it was); the correction fades in and out over ``blend_s``
    around the run so nothing pops. Hip and knee rotations change; the foot keeps its world
    orientation. ``contacts``: ``(F, 2)`` (left, right) from ``foot_contacts`` by default.

    Report: ``contact_frames`` per foot, ``sliding_before_m_s`` / ``sliding_after_m_s`` (mean
    horizontal speed of the pinned points over contact frames), ``sliding_before_m`` /
    ``sliding_after_m`` (total distance), ``max_correction_m``.
    """
    sk = motion.skeleton
    fps = motion.fps
    legs = _leg_joints(sk)  # forward kinematics of the legs is all this needs
    pos, world = fk_arrays(sk, motion.root_positions, motion.rotations, legs)
    if contacts is None:
        contacts = foot_contacts(pos, fps, sk, world)
    contacts = np.asarray(contacts, dtype=bool)
    pts = foot_points(pos, sk, world)  # (F, 2, 2, 3): side, (ankle, toe)
    n_frames = motion.n_frames
    rotations = motion.rotations.copy()
    blend = max(1, int(round(blend_s * fps)))
    anchors = np.zeros((n_frames, 2), dtype=np.int64)  # which point carries the contact
    max_corr = 0.0
    for side, prefix in enumerate(("left", "right")):
        if any(f"{prefix}_{part}" not in sk.canonical for part in ("hip", "knee", "ankle")):
            continue  # no mapped leg: nothing to lock
        hip_j = sk.index(sk.canonical[f"{prefix}_hip"])
        knee_j = sk.index(sk.canonical[f"{prefix}_knee"])
        ankle_j = sk.index(sk.canonical[f"{prefix}_ankle"])
        if sk.parents[knee_j] != hip_j or sk.parents[ankle_j] != knee_j:
            continue  # not a plain two-bone leg: leave it
        runs = _segments(contacts[:, side])
        corr = np.zeros((n_frames, 3))
        for start, stop in runs:
            anchor = int(pts[start:stop, side, 1, 1].mean() < pts[start:stop, side, 0, 1].mean())
            anchors[start:stop, side] = anchor
            p = pts[start:stop, side, anchor]
            corr[start:stop, [0, 2]] = p.mean(axis=0)[[0, 2]] - p[:, [0, 2]]
        _fade_between_runs(corr, runs, blend)
        active = np.linalg.norm(corr, axis=-1) > 0
        if not active.any():
            continue
        max_corr = max(max_corr, float(np.linalg.norm(corr[active], axis=-1).max()))
        target = pts[active, side, 0] + corr[active]
        new_hip_w, new_knee_w = two_bone_ik(
            pos[active, hip_j],
            pos[active, knee_j],
            pos[active, ankle_j],
            target,
            world[active, hip_j],
            world[active, knee_j],
        )
        parent_w = world[active, sk.parents[hip_j]]
        rotations[active, hip_j] = quat.multiply(quat.conjugate(parent_w), new_hip_w)
        rotations[active, knee_j] = quat.multiply(quat.conjugate(new_hip_w), new_knee_w)
        rotations[active, ankle_j] = quat.multiply(
            quat.conjugate(new_knee_w), world[active, ankle_j]
        )
    cleaned = Motion(sk, fps, motion.root_positions.copy(), rotations)
    pos2, world2 = fk_arrays(sk, cleaned.root_positions, rotations, legs)
    pts2 = foot_points(pos2, sk, world2)
    before_speed, before_dist, after_speed, after_dist = [], [], [], []
    for side in range(2):
        for anchor in range(2):
            mask = contacts[:, side] & (anchors[:, side] == anchor)
            s, d = _sliding(pts[:, side, anchor], mask, fps)
            before_speed.append((s, mask.sum()))
            before_dist.append(d)
            s, d = _sliding(pts2[:, side, anchor], mask, fps)
            after_speed.append((s, mask.sum()))
            after_dist.append(d)

    def mean_speed(rows: list[tuple[float, int]]) -> float:
        n = sum(c for _, c in rows)
        return float(sum(s * c for s, c in rows) / n) if n else 0.0

    report = {
        "contact_frames": [int(contacts[:, 0].sum()), int(contacts[:, 1].sum())],
        "sliding_before_m_s": mean_speed(before_speed),
        "sliding_after_m_s": mean_speed(after_speed),
        "sliding_before_m": float(sum(before_dist)),
        "sliding_after_m": float(sum(after_dist)),
        "max_correction_m": max_corr,
    }
    return cleaned, report
