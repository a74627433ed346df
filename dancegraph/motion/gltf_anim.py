"""Animated GLB/glTF takes: a glTF animation's joint channels → a :class:`Motion` on the file's rig.

The rig (joints, bind pose, roles) is :func:`dancegraph.motion.rig.load_rig`'s; the motion is
in the library's BVH convention on ``rig.skeleton``: each joint's world rotation from its bind
rotation, as local rotations relative to the parent, and the root joint's world position per
frame (metres, the file's axes; glTF is Y up). The first animation of the file is read; its
``rotation``, ``translation`` and ``scale`` channels of every node above and at the joints are
sampled at ``fps`` (``LINEAR``: slerp / lerp, ``STEP``: the previous key, ``CUBICSPLINE``: the
key values, linearly) from the earliest key to the latest. glTF stores no frame rate: without
``fps`` it is read from the median key interval (snapped to a common rate within 1 %).
Translations of joints below the root are not kept (the bind offsets stand), as for BVH.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from dancegraph.errors import MotionFileError
from dancegraph.motion import quat
from dancegraph.motion.skeleton import Motion

if TYPE_CHECKING:
    from dancegraph.motion.gltf import _Buffers

#: Frame rates a key interval snaps to.
COMMON_FPS = (24.0, 25.0, 30.0, 48.0, 50.0, 60.0, 100.0, 120.0, 240.0)


def _channel(
    doc: dict, buffers: _Buffers, sampler: dict, path: Path
) -> tuple[np.ndarray, np.ndarray]:
    """``(K,)`` key times and ``(K, w)`` key values of one sampler (spline tangents dropped)."""
    from dancegraph.motion.gltf import _accessor

    times = _accessor(doc, buffers, sampler["input"], path).astype(float).ravel()
    values = _accessor(doc, buffers, sampler["output"], path).astype(float)
    if sampler.get("interpolation") == "CUBICSPLINE":
        values = values[1::3]
    if len(values) != len(times) or len(times) == 0 or np.any(np.diff(times) < 0):
        raise ValueError(f"a sampler has {len(times)} key times and {len(values)} values")
    return times, values


def _sample(times: np.ndarray, values: np.ndarray, t: np.ndarray, kind: str, step: bool):
    """``values`` keyed at ``times`` at the times ``t``: slerp for rotations, else lerp."""
    if len(times) == 1:
        return np.repeat(values[:1], len(t), axis=0)
    i = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    u = np.clip((t - times[i]) / np.maximum(times[i + 1] - times[i], 1e-12), 0.0, 1.0)
    if step:
        u = (u >= 1.0).astype(float)
    if kind == "rotation":
        return quat.slerp(quat.normalize(values[i]), quat.normalize(values[i + 1]), u)
    return values[i] + u[:, None] * (values[i + 1] - values[i])


def _take_fps(all_times: list[np.ndarray], path: Path) -> float:
    """The frame rate of the keys: 1 / median key interval, snapped to a common rate."""
    diffs = [np.diff(np.unique(t)) for t in all_times if len(t) > 1]
    steps = np.concatenate(diffs) if diffs else np.zeros(0)
    steps = steps[steps > 1e-6]
    if steps.size == 0:
        raise MotionFileError(
            "the animation has a single key: no motion", path=path.name, code="take_no_animation"
        )
    fps = 1.0 / float(np.median(steps))
    near = min(COMMON_FPS, key=lambda f: abs(f - fps))
    return near if abs(near - fps) <= 0.01 * near else fps


def _node_tracks(doc: dict, buffers: _Buffers, path: Path, fps: float | None):
    """``(t (F,), fps, tracks)``: ``tracks[node][path]`` sampled at ``t``."""
    anims = doc.get("animations") or []
    if not anims or not anims[0].get("channels"):
        raise MotionFileError(
            "the file holds no animation", path=path.name, code="take_no_animation"
        )
    anim = anims[0]
    keyed = []
    for ch in anim["channels"]:
        target = ch.get("target", {})
        if "node" not in target or target.get("path") not in ("rotation", "translation", "scale"):
            continue
        sampler = anim["samplers"][ch["sampler"]]
        keyed.append(
            (target["node"], target["path"], sampler, *_channel(doc, buffers, sampler, path))
        )
    if not keyed:
        raise MotionFileError(
            "the animation moves no joint", path=path.name, code="take_no_animation"
        )
    rate = fps or _take_fps([k[3] for k in keyed], path)
    t0 = min(float(k[3][0]) for k in keyed)
    t1 = max(float(k[3][-1]) for k in keyed)
    t = t0 + np.arange(int(np.floor((t1 - t0) * rate + 1e-6)) + 1) / rate
    tracks: dict[int, dict[str, np.ndarray]] = {}
    for node, kind, sampler, times, values in keyed:
        step = sampler.get("interpolation") == "STEP"
        tracks.setdefault(node, {})[kind] = _sample(times, values, t, kind, step)
    return t, rate, tracks


def _world_matrices(doc: dict, tracks: dict, n: int, needed: list[int]) -> dict[int, np.ndarray]:
    """``(F, 4, 4)`` world matrix per node of ``needed`` (and their ancestors), per frame."""
    from dancegraph.motion.gltf import _local_matrix

    nodes = doc["nodes"]
    parent_of = {c: i for i, nd in enumerate(nodes) for c in nd.get("children", [])}
    world: dict[int, np.ndarray] = {}

    def world_of(i: int) -> np.ndarray:
        if i in world:
            return world[i]
        node = nodes[i]
        tr = tracks.get(i, {})
        if "matrix" in node or not tr:
            local = np.broadcast_to(_local_matrix(node), (n, 4, 4))
        else:
            local = np.tile(np.eye(4), (n, 1, 1))
            r = tr.get("rotation", np.broadcast_to(node.get("rotation", [0, 0, 0, 1]), (n, 4)))
            s = tr.get("scale", np.broadcast_to(node.get("scale", [1, 1, 1]), (n, 3)))
            local[:, :3, :3] = Rotation.from_quat(quat.normalize(r)).as_matrix() * s[:, None, :]
            local[:, :3, 3] = tr.get(
                "translation", np.broadcast_to(node.get("translation", [0, 0, 0]), (n, 3))
            )
        p = parent_of.get(i)
        world[i] = local if p is None else world_of(p) @ local
        return world[i]

    return {i: world_of(i) for i in needed}


def read_gltf_motion(
    path: str | Path, *, fps: float | None = None, mapping: dict[str, str] | None = None
):
    """``(Motion, Rig)`` of an animated GLB/glTF take (see the module docstring).

    ``fps``: the sampling rate (default: the keys' own rate); ``mapping``: role → joint name
    for a skeleton whose roles the names do not tell. Raises ``MotionFileError``
    (``take_no_animation``, ``gltf_invalid`` for a malformed or truncated file) and the
    ``RigError`` codes of ``load_rig`` (``rig_missing_roles`` for a non-humanoid skeleton).
    """
    from dancegraph.motion.gltf import _load
    from dancegraph.motion.rig import RigError

    path = Path(path)
    rig = take_rig(path, mapping, "gltf_invalid")
    try:
        doc, buffers = _load(path)
        t, rate, tracks = _node_tracks(doc, buffers, path, fps)
        by_name: dict[str, int] = {}
        for i, nd in enumerate(doc["nodes"]):
            by_name.setdefault(nd.get("name") or f"joint_{i}", i)
        sk = rig.skeleton
        node_of = [by_name[nm] for nm in sk.names]
        world = _world_matrices(doc, tracks, len(t), node_of)
    except (KeyError, IndexError, TypeError, ValueError, RigError) as exc:
        raise MotionFileError(
            f"malformed glTF animation ({type(exc).__name__}: {exc})",
            path=path.name,
            code="gltf_invalid",
        ) from None
    mats = np.stack([world[i] for i in node_of], axis=1)  # (F, J, 4, 4)
    return motion_from_world(rig, mats, rate, path.name, "gltf_invalid"), rig


def take_rig(path: Path, mapping: dict[str, str] | None, code: str):
    """The rig of an animated take file (``load_rig``); an unreadable file is the take's
    ``MotionFileError`` ``code``, the other ``RigError`` codes pass."""
    from dancegraph.motion.rig import RigError, load_rig

    try:
        return load_rig(path, mapping=mapping)
    except RigError as exc:
        if exc.code == "rig_unreadable":
            raise MotionFileError(exc.message, path=path.name, code=code) from None
        raise


def motion_from_world(rig, world: np.ndarray, fps: float, name: str, code: str) -> Motion:
    """The BVH-convention motion on ``rig.skeleton`` of its joints' world matrices
    ``(F, J, 4, 4)`` (rig order, metres): each joint's world rotation from its bind rotation
    (``rig.rest_rotations``) as local rotations, the root joint's world position.
    ``MotionFileError`` ``code`` for non-finite values."""
    sk = rig.skeleton
    rot = world[..., :3, :3] / np.linalg.norm(world[..., :3, :3], axis=-2, keepdims=True)
    r = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat().reshape(len(world), sk.n_joints, 4)
    g = quat.multiply(r, quat.conjugate(quat.normalize(rig.rest_rotations))[None])
    local = g.copy()
    nonroot = sk.parents >= 0
    local[:, nonroot] = quat.multiply(quat.conjugate(g[:, sk.parents[nonroot]]), g[:, nonroot])
    motion = Motion(sk, fps, world[:, 0, :3, 3], quat.normalize(local))
    if not (np.isfinite(motion.rotations).all() and np.isfinite(motion.root_positions).all()):
        raise MotionFileError("the animation holds NaN or infinite values", path=name, code=code)
    return motion
