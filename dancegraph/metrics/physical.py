"""Physical plausibility of a dance: foot skating at contacts and the root inside the stage.

Positions are world joint positions ``(F, J, 3)`` in metres (Y up) at ``fps``; ``stage`` is the
spec's rectangle on the ground plane (x, z), metres.
"""

from __future__ import annotations

import numpy as np

from dancegraph.motion.contacts import foot_contacts, foot_points
from dancegraph.motion.skeleton import Skeleton
from dancegraph.render import stage_violation

#: A planted foot moving faster than this (m/s, horizontally) counts as skating.
SKATE_SPEED_M_S = 0.1


def foot_skating(
    positions: np.ndarray,
    world_rotations: np.ndarray,
    skeleton: Skeleton,
    fps: float,
    frames: np.ndarray | None = None,
) -> dict:
    """Horizontal sliding of planted feet.

    Contacts come from ``foot_contacts`` (height and speed thresholds, on the whole dance); on
    each contact frame the lower of the foot's two points (ankle, toe) carries the contact.
    ``frames``: ``(F,)`` bool, count only steps between two of these frames (e.g. near seams).
    Returns ``contact_share`` (contact frames / frames, both feet), ``mean_speed_m_s`` (mean
    horizontal speed of the planted point over the counted contact steps), ``skating_share``
    (share of them faster than ``SKATE_SPEED_M_S``) and ``steps`` (how many were counted).
    """
    contacts = foot_contacts(positions, fps, skeleton, world_rotations)  # (F, 2)
    pts = foot_points(positions, skeleton, world_rotations)  # (F, 2, 2, 3)
    n = pts.shape[0]
    if n < 2:
        return {"contact_share": 0.0, "mean_speed_m_s": 0.0, "skating_share": 0.0, "steps": 0}
    counted = np.ones(n, dtype=bool) if frames is None else np.asarray(frames, dtype=bool)
    lower = np.argmin(pts[..., 1], axis=2)  # (F, 2): 0 ankle, 1 toe
    speeds = []
    for side in range(2):
        p = pts[np.arange(n), side, lower[:, side]]  # (F, 3)
        step = np.linalg.norm(np.diff(p[:, [0, 2]], axis=0), axis=-1) * fps
        both = contacts[1:, side] & contacts[:-1, side] & counted[1:] & counted[:-1]
        # the anchor point may switch between frames: measure each point against itself
        same = lower[1:, side] == lower[:-1, side]
        speeds.append(step[both & same])
    s = np.concatenate(speeds)
    return {
        "contact_share": float(contacts.mean()),
        "mean_speed_m_s": float(s.mean()) if s.size else 0.0,
        "skating_share": float((s > SKATE_SPEED_M_S).mean()) if s.size else 0.0,
        "steps": int(s.size),
    }


def stage_report(root_xz: np.ndarray, stage) -> dict | None:
    """``inside_share`` of frames whose root ``(F, 2)`` (x, z) lies in ``stage`` and
    ``max_outside_m``; None without a stage."""
    if stage is None:
        return None
    xz = np.asarray(root_xz, dtype=float).reshape(-1, 2)
    inside = (
        (xz[:, 0] >= stage.x[0])
        & (xz[:, 0] <= stage.x[1])
        & (xz[:, 1] >= stage.z[0])
        & (xz[:, 1] <= stage.z[1])
    )
    return {
        "inside_share": float(inside.mean()) if inside.size else 1.0,
        "max_outside_m": stage_violation(xz, stage),
    }
