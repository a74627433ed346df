"""Forward kinematics: local joint rotations → world joint positions and rotations."""

from __future__ import annotations

import numpy as np

from dancegraph.errors import DanceGraphError
from dancegraph.motion import quat
from dancegraph.motion.skeleton import Motion, Skeleton


def forward_kinematics(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """World joint positions ``(F, J, 3)`` metres and world rotations ``(F, J, 4)`` (x, y, z, w).

    Joints are visited in skeleton order (parents come first), each one vectorised over frames.
    """
    return fk_arrays(motion.skeleton, motion.root_positions, motion.rotations)


def fk_arrays(
    skeleton: Skeleton,
    root_positions: np.ndarray,
    rotations: np.ndarray,
    joints: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``forward_kinematics`` on bare arrays: ``root_positions (F, 3)``, ``rotations (F, J, 4)``.

    ``joints``: compute only these joints and their ancestors (the other rows of both outputs
    are left zero), for callers that need a few joints of many frames.
    """
    n_frames, n_joints = rotations.shape[:2]
    positions = np.zeros((n_frames, n_joints, 3))
    world = np.zeros((n_frames, n_joints, 4))
    todo = range(n_joints) if joints is None else with_ancestors(skeleton, joints)
    for j in todo:
        p = skeleton.parents[j]
        if p < 0:
            world[:, j] = rotations[:, j]
            positions[:, j] = root_positions
        else:
            world[:, j] = quat.multiply(world[:, p], rotations[:, j])
            positions[:, j] = positions[:, p] + quat.rotate(world[:, p], skeleton.offsets[j])
    return positions, world


def with_ancestors(skeleton: Skeleton, joints: np.ndarray) -> list[int]:
    """``joints`` and every ancestor of them, in skeleton order (parents first)."""
    need = set()
    for j in np.asarray(joints, dtype=np.int64).reshape(-1).tolist():
        while j >= 0 and j not in need:
            need.add(j)
            j = int(skeleton.parents[j])
    return sorted(need)


def end_site_positions(
    skeleton: Skeleton, positions: np.ndarray, world_rotations: np.ndarray
) -> dict[int, np.ndarray]:
    """World positions ``(F, 3)`` of each End Site, keyed by the joint that carries it."""
    return {
        j: positions[:, j] + quat.rotate(world_rotations[:, j], off)
        for j, off in skeleton.end_sites.items()
    }


def require_canonical(skeleton: Skeleton, keys: tuple[str, ...] | list[str]) -> None:
    """Raise ``DanceGraphError(code="skeleton_unmapped")`` naming canonical joints not mapped."""
    missing = [k for k in keys if k not in skeleton.canonical]
    if missing:
        raise DanceGraphError(
            f"the skeleton (root {skeleton.names[0]!r}) has no joint mapped to "
            f"{', '.join(missing)}",
            code="skeleton_unmapped",
            field=missing[0],
        )


def canonical_positions(
    skeleton: Skeleton,
    positions: np.ndarray,
    world_rotations: np.ndarray,
    keys: tuple[str, ...] | list[str],
) -> np.ndarray:
    """World positions ``(F, K, 3)`` of canonical joints ``keys``.

    A ``*_toe`` key that maps to the ankle joint (skeletons without toe joints, such as the CMU
    salsa one) takes the ankle's End Site, which sits at the toes. A key the skeleton does not
    map raises ``DanceGraphError(code="skeleton_unmapped")``.
    """
    require_canonical(skeleton, keys)
    out = np.empty((positions.shape[0], len(keys), 3))
    for k, key in enumerate(keys):
        j = skeleton.index(skeleton.canonical[key])
        ankle = key.replace("_toe", "_ankle")
        if (
            key.endswith("_toe")
            and skeleton.canonical.get(ankle) == skeleton.canonical[key]
            and j in skeleton.end_sites
        ):
            out[:, k] = positions[:, j] + quat.rotate(world_rotations[:, j], skeleton.end_sites[j])
        else:
            out[:, k] = positions[:, j]
    return out
