"""USD out: a dance as UsdSkel, read back with Pixar's own ``pxr`` and checked by its validators."""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.cli import main as cli_main
from dancegraph.errors import DanceGraphError
from dancegraph.motion.fbx import fbx_available
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.retarget import retarget, write_on_rig
from dancegraph.motion.rig import load_rig
from dancegraph.motion.usd import write_usd

pxr = pytest.importorskip("pxr")
from pxr import Usd, UsdGeom, UsdSkel, UsdValidation  # noqa: E402

needs_blender = pytest.mark.skipif(not fbx_available(), reason="Blender not installed")


def _read(path, frames: list[int]) -> tuple[Usd.Stage, np.ndarray]:
    """The stage and its joints' world positions ``(len(frames), J, 3)`` (metres) by UsdSkel."""
    stage = Usd.Stage.Open(str(path))
    skel = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    query = UsdSkel.Cache().GetSkelQuery(skel)
    scale = UsdGeom.GetStageMetersPerUnit(stage)
    out = []
    for f in frames:
        xf = UsdGeom.XformCache(Usd.TimeCode(f))
        out.append(np.array(query.ComputeJointWorldTransforms(xf))[:, 3, :3] * scale)
    return stage, np.stack(out)


def _validation_errors(stage: Usd.Stage) -> list[str]:
    """Every error of every registered validator (the checks ``usdchecker`` runs)."""
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errors]


@pytest.mark.parametrize(
    ("name", "suffix"),
    [
        pytest.param("skinned.glb", ".usdc", marks=needs_blender),
        pytest.param("parented.glb", ".usda", marks=needs_blender),
        pytest.param("prerot.fbx", ".usd", marks=needs_blender),
        ("cmu_cm.bvh", ".usda"),
    ],
)
def test_usd_on_rig_reads_back(rig_dir, salsa_clip, tmp_path, name, suffix):
    rig = load_rig(rig_dir / name)
    motion, _ = retarget(salsa_clip.slice(0, 240), rig)
    out = tmp_path / f"dance{suffix}"
    summary = write_on_rig(motion, rig, rig_dir / name, out)
    assert summary["frames"] == 240 and summary["placement"]["upright"]
    frames = [0, 97, 239]
    stage, got = _read(out, frames)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == pytest.approx(motion.fps)
    assert stage.GetEndTimeCode() == 239
    pos, _ = forward_kinematics(motion)
    assert np.abs(got - pos[frames]).max() < 1e-3  # joints within 1 mm of DanceGraph's FK
    assert _validation_errors(stage) == []
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    if rig.mesh is None:
        assert not meshes
        return
    (body,) = meshes
    assert len(body.GetPointsAttr().Get()) == rig.mesh.n_vertices
    # the skin deforms with the dance: UsdSkel's own skinning moves the vertices
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(next(p for p in stage.Traverse() if p.IsA(UsdSkel.Root)))
    cache.Populate(root, Usd.TraverseInstanceProxies())
    (binding,) = cache.ComputeSkelBindings(root, Usd.TraverseInstanceProxies())
    query = cache.GetSkelQuery(binding.GetSkeleton())
    skinning = binding.GetSkinningTargets()[0]
    moved = []
    for f in (0, 97):
        xforms = query.ComputeSkinningTransforms(Usd.TimeCode(f))
        points = body.GetPointsAttr().Get(Usd.TimeCode(f))
        assert skinning.ComputeSkinnedPoints(xforms, points, Usd.TimeCode(f))
        moved.append(np.array(points))
    assert np.median(np.linalg.norm(moved[1] - moved[0], axis=1)) > 0.05


def test_usd_of_the_library_skeleton(salsa_clip, tmp_path):
    """``output.formats: ["usd"]`` writes each alternative on the library's skeleton as USD."""
    motion = salsa_clip.slice(0, 120)
    summary = write_usd(motion, tmp_path / "0.usd")
    assert summary == {**summary, "frames": 120, "joints": motion.skeleton.n_joints}
    stage, got = _read(tmp_path / "0.usd", [0, 60, 119])
    pos, _ = forward_kinematics(motion)
    assert np.abs(got - pos[[0, 60, 119]]).max() < 1e-3
    assert _validation_errors(stage) == []
    with pytest.raises(DanceGraphError) as err:
        write_usd(motion, tmp_path / "0.obj")
    assert err.value.code == "usd_output_format"


def test_cli_retarget_to_usd(rig_dir, salsa_dir, tmp_path, capsys):
    from dancegraph.motion.bvh import read_bvh, write_bvh

    src = tmp_path / "dance.bvh"
    write_bvh(read_bvh(salsa_dir / "60_02_scaled.bvh", fps=60).slice(0, 120), src)
    out = tmp_path / "on_rig.usda"
    args = ["retarget", str(src), "--rig", str(rig_dir / "cmu_cm.bvh"), "--out", str(out)]
    assert cli_main(args) == 0, capsys.readouterr().err
    assert out.read_text().startswith("#usda 1.0")
    assert not list(tmp_path.glob(".tmp-*"))  # written atomically, nothing left beside it
