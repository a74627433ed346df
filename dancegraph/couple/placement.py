"""Relative placement of a couple: where the follow stands and faces in the lead's frame.

The lead's frame at a frame is its root's ground position and heading (``quat.heading_angle``,
0 = facing +Z). The follow's placement in it is ``(x, z, yaw)``: the follow's root ground
position minus the lead's, turned by minus the lead's heading (metres), and the follow's heading
minus the lead's (radians, wrapped to (-π, π]). A couple graph stores it at every node's bar
lines (``couple.graph``); the renderer blends it across seams and places the follow from the
lead with it (``couple.render``).
"""

from __future__ import annotations

import numpy as np

from dancegraph.motion import quat

_GROUND = np.array([1.0, 0.0, 1.0])


def wrap(angle: np.ndarray) -> np.ndarray:
    """Angles (radians, any shape) wrapped to (-π, π]."""
    return np.angle(np.exp(1j * np.asarray(angle, dtype=float)))


def relative_placement(
    lead_root: np.ndarray, lead_rot0: np.ndarray, follow_root: np.ndarray, follow_rot0: np.ndarray
) -> np.ndarray:
    """``(..., 3)`` the follow's ``(x, z, yaw)`` in the lead's frame.

    ``lead_root``, ``follow_root (..., 3)`` root positions (m, Y up); ``lead_rot0``,
    ``follow_rot0 (..., 4)`` root rotations (x, y, z, w)."""
    yaw_l = quat.heading_angle(np.asarray(lead_rot0, dtype=float))
    yaw_f = quat.heading_angle(np.asarray(follow_rot0, dtype=float))
    offset = (np.asarray(follow_root, dtype=float) - np.asarray(lead_root, dtype=float)) * _GROUND
    local = quat.rotate(quat.from_y_angle(-yaw_l), offset)
    return np.stack([local[..., 0], local[..., 2], wrap(yaw_f - yaw_l)], axis=-1)


def place_follow(
    lead_root: np.ndarray,
    lead_rot0: np.ndarray,
    follow_root: np.ndarray,
    follow_rot0: np.ndarray,
    placement: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The follow's root positions ``(F, 3)`` and root rotations ``(F, 4)`` moved and turned on
    the ground so that it stands at ``placement (F, 3)`` (x, z, yaw) in the lead's frame of each
    frame (``relative_placement`` inverted); its root height and its rotation apart from the
    heading are kept. Why: the render stitches each partner on its own and then puts the follow
    where the couple's blended relative placement says."""
    yaw_l = quat.heading_angle(np.asarray(lead_rot0, dtype=float))
    yaw_f = quat.heading_angle(np.asarray(follow_rot0, dtype=float))
    p = np.asarray(placement, dtype=float)
    local = np.stack([p[:, 0], np.zeros(len(p)), p[:, 1]], axis=-1)
    ground = np.asarray(lead_root, dtype=float) * _GROUND + quat.rotate(
        quat.from_y_angle(yaw_l), local
    )
    root = ground + np.asarray(follow_root, dtype=float) * (1.0 - _GROUND)
    turn = quat.from_y_angle(wrap(yaw_l + p[:, 2] - yaw_f))
    return root, quat.normalize(quat.multiply(turn, np.asarray(follow_rot0, dtype=float)))
