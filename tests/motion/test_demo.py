"""The generated demo library: exact bars, tempos and signatures that the motion really has."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.dataset import parse_manifest
from dancegraph.motion.demo import DEMO_CLIPS, demo_skeleton, write_demo_library
from dancegraph.motion.features import kinematic_beats
from dancegraph.motion.fk import canonical_positions, forward_kinematics
from dancegraph.motion.skeleton import CANONICAL_JOINTS
from dancegraph.rhythm.signatures import COMMON_SIGNATURES, to_bits


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_demo_library(tmp_path_factory.mktemp("demo"), seed=0)


@pytest.fixture(scope="module")
def manifest(library: Path) -> dict:
    return json.loads((library / "manifest.json").read_text())


def test_skeleton_is_standard():
    sk = demo_skeleton()
    assert set(sk.canonical) == set(CANONICAL_JOINTS)
    assert (
        sk.canonical["left_toe"] == "LeftToeBase" and sk.canonical["right_shoulder"] == "RightArm"
    )
    names = {(sk.names[a], sk.names[b]) for a, b in sk.mirror_pairs()}
    assert ("LeftArm", "RightArm") in names and ("LeftToeBase", "RightToeBase") in names
    assert len(sk.mirror_pairs()) == 8
    # left is +X, mirrored offsets match
    for a, b in sk.mirror_pairs():
        np.testing.assert_allclose(sk.offsets[a] * [-1, 1, 1], sk.offsets[b])


def test_manifest_is_importable_and_exact(library: Path, manifest: dict):
    parsed = parse_manifest(manifest)  # the dataset importer's own validation
    assert set(parsed.clips) == {c.id for c in DEMO_CLIPS}
    for recipe in DEMO_CLIPS:
        clip = manifest["clips"][recipe.id]
        assert (library / clip["file"]).is_file()
        assert clip["style"] == recipe.style
        bars = np.array(clip["bars"])
        assert bars.shape == (recipe.n_bars, 5)
        beat = 60.0 / recipe.tempo_bpm
        np.testing.assert_allclose(np.diff(bars, axis=1), beat, atol=1e-5)
        np.testing.assert_allclose(bars[1:, 0], bars[:-1, 4], atol=1e-9)  # bars tile the clip
        assert bars[0, 0] == 0.0
        assert len(clip["signatures"]) == recipe.n_bars
        assert all(s in COMMON_SIGNATURES for s in clip["signatures"])


def test_motion_pauses_on_the_accented_slots(library: Path, manifest: dict):
    """Kinematic beats fall on exactly the half-beat slots the signatures mark (± 25 ms)."""
    for recipe in DEMO_CLIPS:
        clip = manifest["clips"][recipe.id]
        motion = read_bvh(library / clip["file"])
        assert motion.fps == 60.0
        bars = np.array(clip["bars"])
        assert motion.duration_s >= bars[-1, 4]
        pos, _ = forward_kinematics(motion)
        found = kinematic_beats(pos, motion.fps)
        accents = np.array(
            [
                bar[0] + slot * (bar[4] - bar[0]) / 8
                for bar, s in zip(bars, clip["signatures"], strict=True)
                for slot in np.flatnonzero(to_bits(s))
            ]
        )
        accents = accents[accents > 0.0]  # the first frame cannot be a local minimum
        assert len(found) == len(accents), recipe.id
        np.testing.assert_allclose(found, accents, atol=0.025, err_msg=recipe.id)


def test_feet_on_the_floor(library: Path, manifest: dict):
    clip = manifest["clips"]["step_120"]
    motion = read_bvh(library / clip["file"])
    pos, rot = forward_kinematics(motion)
    toes = canonical_positions(motion.skeleton, pos, rot, ["left_toe", "right_toe"])[..., 1]
    lowest = toes.min(axis=1)
    assert np.all(lowest > -0.01) and np.all(lowest < 0.02)


def test_seeded_and_deterministic(library: Path, tmp_path: Path):
    again = write_demo_library(tmp_path / "again", seed=0)
    other = write_demo_library(tmp_path / "other", seed=1)
    name = DEMO_CLIPS[0].id + ".bvh"
    assert (again / name).read_bytes() == (library / name).read_bytes()
    assert (other / name).read_bytes() != (library / name).read_bytes()


def test_cli_demo_and_info(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    from dancegraph.cli import main

    assert main(["motion", "demo", str(tmp_path / "lib"), "--seed", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert "manifest.json" in out["files"] and f"{DEMO_CLIPS[0].id}.bvh" in out["files"]
    assert main(["motion", "info", str(tmp_path / "lib" / f"{DEMO_CLIPS[0].id}.bvh")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["joints"] == 21 and info["fps"] == 60.0 and info["canonical"]["hips"] == "Hips"
    (tmp_path / "junk.bvh").write_bytes(b"\x00\x01\x02junk")
    assert main(["motion", "info", str(tmp_path / "junk.bvh")]) == 2
    assert "bvh_not_text" in capsys.readouterr().err
