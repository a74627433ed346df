"""A library's takes (issue 34): each bad take fails with a named code, nothing half-published;
animated GLB takes; skeletons found by role maps; takes on other skeletons retargeted."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dancegraph.errors import DanceGraphError
from dancegraph.motion.bvh import read_bvh, write_bvh
from dancegraph.motion.dataset import import_dataset, load_dataset, parse_manifest
from dancegraph.motion.demo import write_demo_library
from dancegraph.motion.fbx import bvh_to_fbx, fbx_available
from dancegraph.motion.fbx_anim import read_fbx_motion
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.gltf import write_glb
from dancegraph.motion.gltf_anim import read_gltf_motion
from dancegraph.motion.rig import load_rig
from dancegraph.motion.skeleton import Motion, Skeleton
from dancegraph.store import FileStore

needs_blender = pytest.mark.skipif(not fbx_available(), reason="Blender not installed")
GROOVE = {"tempo_bpm": 100.0, "first_downbeat_s": 0.0, "style": "groove"}


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory) -> Path:
    return write_demo_library(tmp_path_factory.mktemp("demo"), seed=0)


def _take(demo_dir: Path, clip: str = "groove_100") -> Motion:
    return read_bvh(demo_dir / f"{clip}.bvh")


def _renamed(motion: Motion, names: list[str]) -> Motion:
    sk = motion.skeleton
    new = Skeleton(names, sk.parents, sk.offsets, sk.channels, sk.end_sites)
    return Motion(new, motion.fps, motion.root_positions, motion.rotations)


def test_every_bad_take_fails_with_its_code_and_the_good_ones_publish(demo_dir, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    good = _take(demo_dir)
    write_bvh(good, src / "a_good.bvh")
    text = (demo_dir / "pop_90.bvh").read_text()
    (src / "b_truncated.bvh").write_text(text[: len(text) // 2])
    (src / "c_junk.glb").write_bytes(b"glTF" + bytes(range(200)))
    glb = tmp_path / "whole.glb"
    write_glb(good, load_rig(demo_dir / "groove_100.bvh"), glb)
    (src / "d_cut.glb").write_bytes(glb.read_bytes()[: glb.stat().st_size // 2])
    (src / "e_take.fbx").write_bytes(b"Kaydara FBX Binary  \x00")
    write_bvh(good.slice(0, 60), src / "f_short.bvh")  # 1 s: under one 2.4-s bar
    write_bvh(Motion(good.skeleton, 30.0, good.root_positions, good.rotations), src / "g_30fps.bvh")
    snake = Skeleton(
        [f"seg{i}" for i in range(6)],
        np.arange(-1, 5),
        np.tile([0.0, 0.0, 0.3], (6, 1)),
        [good.skeleton.channels[0]] + [good.skeleton.channels[1]] * 5,
    )
    n = 600
    rot = np.zeros((n, 6, 4))
    rot[..., 3] = 1.0
    write_bvh(Motion(snake, 60.0, np.zeros((n, 3)), rot), src / "h_snake.bvh")
    write_bvh(good, src / "i_dup.bvh")
    write_glb(good, load_rig(demo_dir / "groove_100.bvh"), src / "i_dup.glb")
    (src / "j_music.bvh").symlink_to(src / "a_good.bvh")
    (src / "j_music.ogg").write_bytes(b"OggS not really")
    (src / "k_nosound.bvh").symlink_to(src / "a_good.bvh")
    manifest = {
        "clips": {
            "a_good": GROOVE,
            "f_short": GROOVE,
            "j_music": {**GROOVE, "audio": "j_music.ogg"},
            "k_nosound": {**GROOVE, "audio": "absent.ogg"},
            "z_absent": {"file": "z_absent.bvh"},
        }
    }
    store = FileStore(tmp_path / "store")
    report = import_dataset(src, "bad", store, manifest)
    failed = {f["file"]: f["code"] for f in report.failed}
    assert failed == {
        "z_absent.bvh": "manifest_file_missing",
        "b_truncated.bvh": "bvh_truncated",
        "c_junk.glb": "gltf_invalid",
        "d_cut.glb": "gltf_invalid",
        "e_take.fbx": "fbx_invalid",
        "f_short.bvh": "take_under_one_bar",
        "g_30fps.bvh": "fps_mixed",
        "h_snake.bvh": "skeleton_unmapped",
        "i_dup.glb": "duplicate_clip_id",
        "j_music.bvh": "audio_undecodable",
        "k_nosound.bvh": "manifest_file_missing",
    }
    assert all(f["error"] for f in report.failed)
    assert sorted(c.id for c in report.clips) == ["a_good", "i_dup"]
    assert sorted(c.id for c in load_dataset(store, "bad").clips) == ["a_good", "i_dup"]

    # strict: one failed take and nothing is published (the earlier version keeps serving)
    with pytest.raises(DanceGraphError) as err:
        import_dataset(src, "bad", store, manifest, strict=True)
    assert err.value.code == "dataset_takes_failed"
    assert {e["field"]: e["code"] for e in err.value.errors or []}["f_short.bvh"] == (
        "take_under_one_bar"
    )
    assert load_dataset(store, "bad").version == report.version
    with pytest.raises(DanceGraphError) as err:
        import_dataset(src, "strict-new", store, manifest, strict=True)
    assert list(store.list("datasets/strict-new")) == []


def test_a_glb_take_reads_as_its_bvh(demo_dir, tmp_path):
    """A take written as GLB on its own rig imports with the BVH's grid and motion."""
    src = tmp_path / "src"
    src.mkdir()
    good = _take(demo_dir)
    rig = load_rig(demo_dir / "groove_100.bvh")
    write_glb(
        Motion(rig.skeleton, good.fps, good.root_positions, good.rotations), rig, src / "g.glb"
    )
    write_bvh(good, src / "b.bvh")
    store = FileStore(tmp_path / "store")
    report = import_dataset(src, "glb", store, {"clips": {"g": GROOVE, "b": GROOVE}})
    assert report.failed == []
    rows = {c.id: c for c in report.clips}
    assert rows["g"].source_format == "glb" and rows["g"].fps == good.fps
    assert rows["g"].n_bars == rows["b"].n_bars == 8
    ds = load_dataset(store, "glb")
    a, _ = forward_kinematics(ds.motion("b"))
    b, _ = forward_kinematics(ds.motion("g"))
    # the same dance: the GLB without a skin binds at its first frame, so it is retargeted
    d = np.linalg.norm(a - b, axis=-1)
    assert np.median(d) < 0.02 and d.max() < 0.08
    # the reader itself is exact: the GLB's joints where the BVH's are
    motion, _ = read_gltf_motion(src / "g.glb")
    assert np.abs(forward_kinematics(motion)[0] - forward_kinematics(good)[0]).max() < 1e-4


@needs_blender
def test_an_fbx_take_reads_as_its_bvh(demo_dir, tmp_path):
    """A take converted to FBX by Blender imports with the BVH's motion and grid."""
    src = tmp_path / "src"
    src.mkdir()
    bvh_to_fbx(demo_dir / "groove_100.bvh", src / "f.fbx")
    (src / "b.bvh").symlink_to(demo_dir / "groove_100.bvh")
    store = FileStore(tmp_path / "store")
    report = import_dataset(src, "fbx", store, {"clips": {"f": GROOVE, "b": GROOVE}})
    assert report.failed == []
    rows = {c.id: c for c in report.clips}
    assert rows["f"].source_format == "fbx" and rows["f"].n_bars == rows["b"].n_bars == 8
    motion, _ = read_fbx_motion(src / "f.fbx")
    good = _take(demo_dir)
    assert motion.n_frames == good.n_frames and motion.fps == good.fps
    assert np.abs(forward_kinematics(motion)[0] - forward_kinematics(good)[0]).max() < 1e-4


def test_role_map_names_a_skeleton_and_other_skeletons_are_retargeted(demo_dir, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    good = _take(demo_dir)
    names = [f"j{i:02d}" for i in range(good.skeleton.n_joints)]
    write_bvh(_renamed(good, names), src / "a_renamed.bvh")
    big = good.skeleton.offsets * 1.2  # a taller dancer: another skeleton
    tall = Skeleton(good.skeleton.names, good.skeleton.parents, big, good.skeleton.channels)
    write_bvh(Motion(tall, good.fps, good.root_positions * 1.2, good.rotations), src / "b_tall.bvh")
    roles = {"hips": "j00", "spine": "j01", "chest": "j02", "head": "j04"}
    manifest = {"roles": roles, "clips": {"a_renamed": GROOVE, "b_tall": GROOVE}}
    store = FileStore(tmp_path / "store")
    report = import_dataset(src, "roles", store, manifest)
    assert report.failed == []
    ds = load_dataset(store, "roles")
    assert ds.skeleton.names == names and ds.skeleton.canonical["hips"] == "j00"
    assert ds.meta["skeleton_source"] == "take:a_renamed.bvh"
    tall_row = {c.id: c for c in report.clips}["b_tall"]
    assert tall_row.retarget["from_joints"] == 21 and tall_row.n_bars == 8
    # on the library's skeleton the taller dancer's hips ride at the library's height
    hips = ds.motion("b_tall").root_positions[:, 1]
    assert abs(np.median(hips) - np.median(ds.motion("a_renamed").root_positions[:, 1])) < 0.05


def test_the_skeleton_source_can_be_a_named_take_or_a_rig_file(demo_dir, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for clip in ("groove_100", "pop_90"):
        (src / f"{clip}.bvh").symlink_to(demo_dir / f"{clip}.bvh")
    clips = {"groove_100": GROOVE, "pop_90": {"tempo_bpm": 90.0, "first_downbeat_s": 0.0}}
    store = FileStore(tmp_path / "store")
    report = import_dataset(src, "named", store, {"skeleton": "pop_90", "clips": clips})
    assert load_dataset(store, "named").meta["skeleton_source"] == "take:pop_90.bvh"
    assert report.failed == []
    with pytest.raises(DanceGraphError) as err:
        import_dataset(src, "named", store, {"skeleton": "nope", "clips": clips})
    assert err.value.code == "manifest_file_missing" and err.value.field == "skeleton"
    (src / "hero.bvh").symlink_to(demo_dir / "step_100.bvh")  # a rig file: not a take
    report = import_dataset(src, "rigged", store, {"skeleton": "hero.bvh", "clips": clips})
    assert load_dataset(store, "rigged").meta["skeleton_source"] == "rig:hero.bvh"
    assert sorted(c.id for c in report.clips) == ["groove_100", "pop_90"]


@pytest.mark.parametrize(
    ("data", "where"),
    [
        ({"roles": {"elbow": "j07"}}, "roles"),  # not a role
        ({"clips": {"a": {"roles": {"hips": ""}}}}, "clips.a.roles"),
        ({"clips": {"a": {"audio_offset_s": "soon"}}}, "clips.a.audio_offset_s"),
        ({"clips": {"a": {"audio_file": "a.ogg"}}}, "clips.a.audio_file"),  # unknown key
        ({"skeleton_file": "hero.fbx"}, "skeleton_file"),
    ],
)
def test_manifest_fields_of_a_library_are_checked(data, where):
    with pytest.raises(DanceGraphError) as err:
        parse_manifest(data)
    assert err.value.code == "manifest_invalid" and err.value.field == where
