"""One FBX holding both dancers: a real partner pair (60_03 lead, 61_03 follow, captured
together) written as ``couple.glb``, converted by Blender (``FbxExporter.glb_to_fbx``) and read
back with ufbx (an independent reader, in a child Python): two armatures, ``lead`` and
``follow``, each with the library's 43 joints (named ``<partner>:<joint>``), every joint within 1 mm of its BVH's FK."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dancegraph.couple.glb import write_couple_glb
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fbx import FbxExporter, fbx_available
from dancegraph.motion.fk import forward_kinematics
from tests.couple.test_couple import couple  # noqa: F401  (the module fixture: a couple graph)
from tests.demo import demo_song
from tests.motion.ufbx_child import ufbx_json

pytest.importorskip("ufbx")
pytestmark = pytest.mark.skipif(
    not fbx_available(), reason="Blender's Python not installed (scripts/install-blender.sh)"
)

# Child Python: per armature (the nearest non-bone ancestor of each bone) its bones' names and
# world positions (m) at the given frames, and the file's rate. ufbx objects kept referenced.
_READER = r"""
import json, sys, ufbx
path, frames = sys.argv[1], json.loads(sys.argv[2])
scene = ufbx.load_file(path)
fps = scene.settings.frames_per_second
nodes = [scene.nodes[i] for i in range(len(scene.nodes))]
index = {id(n): i for i, n in enumerate(nodes)}
def owner(n):
    p = n.parent
    while p is not None and p.bone is not None:
        p = p.parent
    return p.name if p is not None else None
bones = [(i, owner(n), n.name) for i, n in enumerate(nodes) if n.bone is not None]
out = {"fps": fps, "unit_meters": scene.settings.unit_meters, "armatures": {}}
for _, arm, name in bones:
    out["armatures"].setdefault(arm, {"joints": [], "positions": {}})["joints"].append(name)
anim = scene.anim
for f in frames:
    ev = ufbx.evaluate_scene(scene, anim, f / fps)
    enodes = [ev.nodes[i] for i in range(len(ev.nodes))]
    for i, arm, _ in bones:
        t = enodes[i].node_to_world.c3
        out["armatures"][arm]["positions"].setdefault(str(f), []).append([t.x, t.y, t.z])
print(json.dumps(out))
"""


def test_couple_glb_to_one_fbx_holds_both_dancers(salsa_dir: Path, tmp_path: Path):
    dancers = {
        "lead": read_bvh(salsa_dir / "60_03_scaled.bvh", fps=60.0).slice(600, 900),
        "follow": read_bvh(salsa_dir / "61_03_scaled.bvh", fps=60.0).slice(600, 900),
    }
    glb, fbx = tmp_path / "couple.glb", tmp_path / "couple.fbx"
    write_couple_glb(dancers, glb)
    with FbxExporter() as exporter:
        summary = exporter.glb_to_fbx(glb, fbx, fps=60.0, frames=300)
    assert summary["armatures"] == {"lead": 43, "follow": 43} and summary["frames"] == 300
    check_couple_fbx(fbx, dancers, [0, 1, 150, 299])


def check_couple_fbx(fbx: Path, dancers: dict, frames: list[int]) -> None:
    """Assert ``fbx`` holds one armature per dancer (``{name: Motion}``, one rate), named as
    the dancer, joints ``<name>:<joint>`` within 1 mm of the Motion's FK at ``frames``, the
    hips 0.2-1.9 m apart at the middle one."""
    got = ufbx_json(_READER, fbx, frames)
    fps = next(iter(dancers.values())).fps
    assert got["fps"] == pytest.approx(fps) and got["unit_meters"] == pytest.approx(1.0)
    assert sorted(got["armatures"]) == sorted(dancers)
    drawn = {}
    for name, motion in dancers.items():
        arm = got["armatures"][name]
        skel = motion.skeleton
        names = [f"{name}:{j}" for j in skel.names]  # the GLB's joint names, unique per dancer
        assert sorted(arm["joints"]) == sorted(names)
        order = [arm["joints"].index(j) for j in names]
        positions, _ = forward_kinematics(motion)
        for f in frames:
            drawn[name, f] = np.asarray(arm["positions"][str(f)])[order]
            err = np.abs(drawn[name, f] - positions[f]).max()
            assert err < 1e-3, f"{name} frame {f}: {1000 * err:.3f} mm"
    # the two dancers stand apart as captured (hips 0.2-1.9 m: the library's p1-p99 band)
    mid = frames[len(frames) // 2]
    assert 0.2 < np.linalg.norm(drawn["lead", mid][0] - drawn["follow", mid][0]) < 1.9


def test_synthesize_couple_writes_couple_fbx(couple, tmp_path: Path):  # noqa: F811
    """``dancegraph synthesize --couple`` with ``fbx`` in the formats: ``couple.fbx`` holds the
    alternative's ``lead.bvh`` and ``follow.bvh`` (one alternative of the generated song)."""
    from dancegraph.cli import main

    wav, _ = demo_song(tmp_path)
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"output": {"formats": ["bvh", "fbx"]}, "alternatives": 1}))
    argv = ["synthesize", str(wav), "--dataset", "salsa6", "--couple", "--out", str(tmp_path)]
    assert main([*argv, "--spec", str(spec), "--store", str(couple[1].root)]) == 0
    files = json.loads((tmp_path / "timeline.json").read_text())["alternatives"][0]["files"]
    assert files["fbx"] == "alternatives/0/couple.fbx"
    dancers = {p: read_bvh(tmp_path / f"alternatives/0/{p}.bvh") for p in ("lead", "follow")}
    n = dancers["lead"].n_frames
    check_couple_fbx(tmp_path / files["fbx"], dancers, [0, n // 2, n - 1])


def test_glb_to_fbx_refuses_a_missing_file(tmp_path: Path):
    from dancegraph.errors import MotionFileError

    with FbxExporter() as exporter, pytest.raises(MotionFileError) as err:
        exporter.glb_to_fbx(tmp_path / "none.glb", tmp_path / "x.fbx", fps=30.0, frames=10)
    assert err.value.code == "motion_file_not_found" and not (tmp_path / "x.fbx").exists()
