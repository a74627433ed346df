"""Left/right mirroring of motion about the body's sagittal plane (world X = 0, Y up).

The reflection S = diag(-1, 1, 1) maps a rotation R to S·R·S, which for a quaternion
(x, y, z, w) is (x, -y, -z, w). Each joint takes its mirror partner's reflected local rotation
and the root's path is reflected in X. On a left/right symmetric skeleton the mirrored world
positions are exactly the reflected originals; real skeletons are a few millimetres off
symmetric, so ``mirror_skeleton=True`` also reflects the bone offsets (exact mirroring, at the
price of a second skeleton).
"""

from __future__ import annotations

import numpy as np

from dancegraph.motion.skeleton import Motion, Skeleton

_REFLECT_QUAT = np.array([1.0, -1.0, -1.0, 1.0])
_REFLECT_VEC = np.array([-1.0, 1.0, 1.0])


def mirror_permutation(n_joints: int, pairs: list[tuple[int, int]]) -> np.ndarray:
    """``(J,)`` index map: joint j takes its data from ``perm[j]`` (its partner, or itself)."""
    perm = np.arange(n_joints)
    for a, b in pairs:
        perm[a], perm[b] = b, a
    return perm


def mirrored_skeleton(skeleton: Skeleton, pairs: list[tuple[int, int]] | None = None) -> Skeleton:
    """The skeleton with every offset and End Site taken from its partner and reflected in X."""
    perm = mirror_permutation(
        skeleton.n_joints, skeleton.mirror_pairs() if pairs is None else pairs
    )
    end_sites = {}
    for j in range(skeleton.n_joints):
        if perm[j] in skeleton.end_sites:
            end_sites[j] = skeleton.end_sites[int(perm[j])] * _REFLECT_VEC
    return Skeleton(
        names=list(skeleton.names),
        parents=skeleton.parents.copy(),
        offsets=skeleton.offsets[perm] * _REFLECT_VEC,
        channels=list(skeleton.channels),
        end_sites=end_sites,
        canonical=dict(skeleton.canonical),
    )


def mirror(
    motion: Motion,
    pairs: list[tuple[int, int]] | None = None,
    *,
    mirror_skeleton: bool = False,
) -> Motion:
    """Mirror ``motion`` left/right.

    ``pairs``: ``(left, right)`` joint index pairs; default ``skeleton.mirror_pairs()`` (found
    from names). ``mirror(mirror(m)) == m``. With ``mirror_skeleton`` the result carries
    reflected bone offsets too, so its FK positions equal the reflected originals exactly.
    """
    sk = motion.skeleton
    pairs = sk.mirror_pairs() if pairs is None else [(int(a), int(b)) for a, b in pairs]
    perm = mirror_permutation(sk.n_joints, pairs)
    rotations = motion.rotations[:, perm] * _REFLECT_QUAT
    root = motion.root_positions * _REFLECT_VEC
    skeleton = mirrored_skeleton(sk, pairs) if mirror_skeleton else sk
    return Motion(skeleton, motion.fps, root, rotations)
