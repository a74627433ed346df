"""USD out: a dance as a UsdSkel skeleton and animation (with the rig's skinned mesh), via ``usd-core``.

:func:`write_usd` writes one stage (``.usda`` text, ``.usdc`` binary, ``.usd`` binary):

- stage metadata: ``metersPerUnit`` 1, ``upAxis`` Y, ``timeCodesPerSecond`` and
  ``framesPerSecond`` the dance's rate, time codes 0 … F-1 (one per frame);
- the rig's ancestor nodes (its file's nodes above the skeleton: an armature, a unit or axis
  change) as ``Xform`` prims holding their matrices, so the skeleton under them stands where it
  stood in the user's file, in metres, Y up;
- under them a ``SkelRoot`` ``Character`` with a ``Skeleton`` (joint paths, bind and rest
  transforms in skeleton space), a ``SkelAnimation`` (each joint's local translation, rotation and
  scale at every frame) and, when the rig has one, the skinned ``Mesh`` ``Body`` (four joint
  influences per vertex).

A dance on the motion library's own skeleton (no rig) is written the same way, with each
joint's frame aligned to the world at rest. ``usd-core`` is Pixar's Python build of USD.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dancegraph.errors import DanceGraphError
from dancegraph.motion.gltf import joint_locals

#: Suffixes :func:`write_usd` writes (``.usd`` is written in the binary crate format).
USD_SUFFIXES = (".usd", ".usda", ".usdc")


def _identifiers(names: list[str]) -> list[str]:
    """Valid, distinct USD prim names for ``names`` (``mixamorig:Hips`` → ``mixamorig_Hips``)."""
    from pxr import Tf

    out: list[str] = []
    seen: set[str] = set()
    for name in names:
        base = Tf.MakeValidIdentifier(name or "joint")
        ident, k = base, 1
        while ident in seen:
            ident, k = f"{base}_{k}", k + 1
        seen.add(ident)
        out.append(ident)
    return out


def _joint_paths(names: list[str], parents: np.ndarray) -> list[str]:
    """UsdSkel joint paths (``Hips/Spine/Chest``), parents first."""
    idents = _identifiers(names)
    paths: list[str] = []
    for j, p in enumerate(parents):
        paths.append(idents[j] if p < 0 else f"{paths[int(p)]}/{idents[j]}")
    return paths


def _matrices(rot: np.ndarray, trans: np.ndarray, scale: float = 1.0):
    """``Vt.Matrix4dArray`` of row-vector USD matrices from rotations ``(N, 4)`` xyzw and
    translations ``(N, 3)``."""
    from pxr import Vt
    from scipy.spatial.transform import Rotation

    m = np.tile(np.eye(4), (len(rot), 1, 1))
    m[:, :3, :3] = Rotation.from_quat(rot).as_matrix() * scale
    m[:, :3, 3] = trans
    return Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(m.transpose(0, 2, 1)))


class _Bare:
    """The parts of a rig :func:`write_usd` reads, for a dance on the library skeleton."""

    def __init__(self, skeleton) -> None:
        self.skeleton = skeleton
        self.rest_rotations = np.tile([0.0, 0.0, 0.0, 1.0], (skeleton.n_joints, 1))
        self.ancestors: list = []
        self.mesh = None

    def ancestors_world(self) -> np.ndarray:
        return np.eye(4)


def write_usd(motion, path: str | Path, rig=None) -> dict:
    """Write ``motion`` as a UsdSkel stage at ``path`` (see the module docstring).

    ``motion``: on ``rig.skeleton`` (BVH convention, metres, the rig's world), or on any
    skeleton when ``rig`` is None. Written atomically (temporary file, rename). Returns
    ``{frames, joints, vertices, bytes}``; raises ``DanceGraphError`` (``usd_output_format``)
    for another suffix.
    """
    from pxr import Sdf, Usd, UsdGeom, UsdSkel

    path = Path(path)
    if path.suffix.lower() not in USD_SUFFIXES:
        raise DanceGraphError(
            f"{path.name}: USD is written as {', '.join(USD_SUFFIXES)}",
            code="usd_output_format",
            field=path.name,
        )
    rig = rig if rig is not None else _Bare(motion.skeleton)
    local, moves, sigma = joint_locals(motion, rig)
    kind = ".usdc" if path.suffix.lower() == ".usd" else path.suffix.lower()
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.stem}{kind}")
    try:
        layer = Sdf.Layer.CreateNew(str(tmp))
        stage = Usd.Stage.Open(layer)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        stage.SetTimeCodesPerSecond(motion.fps)
        stage.SetFramesPerSecond(motion.fps)
        stage.SetStartTimeCode(0)
        stage.SetEndTimeCode(motion.n_frames - 1)
        where = Sdf.Path.absoluteRootPath
        names = _identifiers([n for n, _ in rig.ancestors])
        for name, (_, matrix) in zip(names, rig.ancestors, strict=True):
            where = where.AppendChild(name)
            xform = UsdGeom.Xform.Define(stage, where)
            xform.AddTransformOp().Set(_gf_matrix(np.asarray(matrix, dtype=float)))
        root = UsdSkel.Root.Define(stage, where.AppendChild("Character"))
        stage.SetDefaultPrim(stage.GetPrimAtPath(root.GetPath().GetPrefixes()[0]))
        skel = _write_skeleton(stage, root, rig, local, moves, sigma)
        n_vertices = _write_mesh(stage, root, skel, rig)
        layer.Save()
        del stage, layer
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)  # nothing half-written is left beside the file
    return {
        "frames": motion.n_frames,
        "joints": rig.skeleton.n_joints,
        "vertices": n_vertices,
        "bytes": path.stat().st_size,
    }


def _write_skeleton(stage, root, rig, local: np.ndarray, moves: np.ndarray, sigma: float):
    """The ``Skeleton`` and its ``SkelAnimation`` (one sample per frame) under ``root``."""
    from pxr import Sdf, UsdSkel, Vt

    sk = rig.skeleton
    skel = UsdSkel.Skeleton.Define(stage, root.GetPath().AppendChild("Skeleton"))
    joints = Vt.TokenArray(_joint_paths(sk.names, sk.parents))
    skel.CreateJointsAttr(joints)
    skel.CreateBindTransformsAttr(_skeleton_space_bind(rig, sigma))
    skel.CreateRestTransformsAttr(_matrices(local[0], moves[0]))
    anim = UsdSkel.Animation.Define(stage, root.GetPath().AppendChild("Animation"))
    anim.CreateJointsAttr(joints)
    t_attr, r_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr()
    anim.CreateScalesAttr().Set(Vt.Vec3hArray.FromNumpy(np.ones((sk.n_joints, 3), np.float16)))
    rot_xyzw = local.astype(np.float32)  # GfQuatf's memory order: imaginary part, then real
    trans = moves.astype(np.float32)
    with Sdf.ChangeBlock():  # one change notice for all samples, not one per Set
        for f in range(len(local)):
            t_attr.Set(Vt.Vec3fArray.FromNumpy(trans[f]), f)
            r_attr.Set(Vt.QuatfArray.FromNumpy(rot_xyzw[f]), f)
    binding = UsdSkel.BindingAPI.Apply(skel.GetPrim())
    binding.CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    return skel


def _gf_matrix(m: np.ndarray):
    """A ``Gf.Matrix4d`` (row vectors, translation in the last row) from a column-vector matrix."""
    from pxr import Gf

    return Gf.Matrix4d(*m.T.ravel().tolist())


def _skeleton_space_bind(rig, sigma: float):
    """Bind matrices in skeleton space (the ancestors' units and axes), as ``Vt.Matrix4dArray``."""
    from pxr import Vt
    from scipy.spatial.transform import Rotation

    from dancegraph.motion.rig import bind_positions

    world = np.tile(np.eye(4), (rig.skeleton.n_joints, 1, 1))
    world[:, :3, :3] = Rotation.from_quat(rig.rest_rotations).as_matrix() * sigma
    world[:, :3, 3] = bind_positions(rig)
    skel = np.linalg.inv(rig.ancestors_world())[None] @ world
    return Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(skel.transpose(0, 2, 1)))


def _write_mesh(stage, root, skel, rig) -> int:
    """The rig's skinned mesh as ``Body`` (skeleton space); returns its vertex count (0: none)."""
    from pxr import UsdGeom, UsdSkel, Vt

    mesh = getattr(rig, "mesh", None)
    if mesh is None or not mesh.n_vertices:
        return 0
    to_skel = np.linalg.inv(rig.ancestors_world())
    points = mesh.positions @ to_skel[:3, :3].T + to_skel[:3, 3]
    body = UsdGeom.Mesh.Define(stage, root.GetPath().AppendChild("Body"))
    body.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    body.CreateFaceVertexCountsAttr(
        Vt.IntArray.FromNumpy(np.full(len(mesh.triangles), 3, np.int32))
    )
    body.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(mesh.triangles.astype(np.int32).ravel()))
    body.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    lo, hi = points.min(axis=0), points.max(axis=0)
    body.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([lo, hi]).astype(np.float32)))
    binding = UsdSkel.BindingAPI.Apply(body.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 4).Set(
        Vt.IntArray.FromNumpy(mesh.joints.astype(np.int32).ravel())
    )
    binding.CreateJointWeightsPrimvar(False, 4).Set(
        Vt.FloatArray.FromNumpy(mesh.weights.astype(np.float32).ravel())
    )
    binding.CreateGeomBindTransformAttr(_gf_matrix(np.eye(4)))
    return mesh.n_vertices


def joint_world_positions(path: str | Path, frames: list[int]) -> tuple[list[str], np.ndarray]:
    """Read a stage written by :func:`write_usd` back with UsdSkel: joint names (the paths' last
    parts) and world positions ``(len(frames), J, 3)`` in metres (``metersPerUnit`` applied)."""
    from pxr import Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(path))
    scale = UsdGeom.GetStageMetersPerUnit(stage)
    cache = UsdSkel.Cache()
    skel = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    query = cache.GetSkelQuery(skel)
    xf_cache = UsdGeom.XformCache()
    out = []
    for f in frames:
        xf_cache.SetTime(Usd.TimeCode(f))
        world = np.array(query.ComputeJointWorldTransforms(xf_cache))
        out.append(world[:, 3, :3] * scale)  # row vectors: the translation is the last row
    names = [str(t).rsplit("/", 1)[-1] for t in query.GetJointOrder()]
    return names, np.stack(out)
