"""FBX export through Blender, read back with ufbx and checked against DanceGraph's own FK.

Every written FBX is opened with ufbx (an independent FBX reader) in a child process: the ufbx
Python binding 0.0.5 crashes on some temporary objects, and a crash there must not take the whole
test run with it.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest

from dancegraph.cli import main as cli_main
from dancegraph.errors import MotionFileError
from dancegraph.motion.bvh import read_bvh, write_bvh
from dancegraph.motion.fbx import FbxError, FbxExporter, bvh_to_fbx, fbx_available
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.skeleton import Motion
from tests.motion.ufbx_child import ufbx_json

pytest.importorskip("ufbx")
pytestmark = pytest.mark.skipif(
    not fbx_available(), reason="Blender's Python not installed (scripts/install-blender.sh)"
)

MODERN_SCALE = 0.056444  # CMU ASF units → metres (datasets README)

# Runs in a child Python: prints the FBX's skeleton, timing and world joint positions as JSON.
# Every ufbx object is kept referenced while in use (the binding frees temporaries too early).
_UFBX_READER = r"""
import json, sys, ufbx
path, frames = sys.argv[1], json.loads(sys.argv[2])
scene = ufbx.load_file(path)
settings = scene.settings
fps = settings.frames_per_second
nodes = scene.nodes
keep = [nodes[i] for i in range(len(nodes))]
parents = [n.parent for n in keep]
bone_nodes = [(n, p) for n, p in zip(keep, parents) if n.bone is not None]
stacks = scene.anim_stacks
stack = stacks[0]
curves = scene.anim_curves
curve_list = [curves[i] for i in range(len(curves))]
out = {
    "unit_meters": settings.unit_meters,
    "up": int(settings.axes.up),
    "fps": fps,
    "n_stacks": len(stacks),
    "time_begin": stack.time_begin,
    "time_end": stack.time_end,
    "keys_per_curve": sorted({len(c.keyframes) for c in curve_list}),
    "first_key_time": min(c.keyframes[0].time for c in curve_list),
    "joints": [n.name for n, _ in bone_nodes],
    "parents": [p.name if p is not None and p.bone is not None else None for _, p in bone_nodes],
    "positions": {},
}
anim = scene.anim
for f in frames:
    evaluated = ufbx.evaluate_scene(scene, anim, f / fps)
    enodes = evaluated.nodes
    ekeep = [enodes[i] for i in range(len(enodes))]
    by_name = {n.name: n for n in ekeep}
    pos = []
    for name in out["joints"]:
        t = by_name[name].node_to_world.c3
        pos.append([t.x, t.y, t.z])
    out["positions"][str(f)] = pos
print(json.dumps(out))
"""


def read_fbx(path: Path, frames: list[int]) -> dict:
    """The FBX's bones (names, parent names), timing, and world positions (m) at ``frames``."""
    return ufbx_json(_UFBX_READER, path, frames)


def check_fbx_against_fk(fbx_path: Path, motion: Motion, n_samples: int = 8) -> float:
    """Assert the FBX holds ``motion`` exactly; returns the largest position error in metres."""
    skel = motion.skeleton
    rng = np.random.default_rng(0)
    frames = sorted(
        {0, 1, motion.n_frames // 2, motion.n_frames - 1}
        | set(rng.integers(0, motion.n_frames, n_samples).tolist())
    )
    fbx = read_fbx(fbx_path, frames)

    assert fbx["unit_meters"] == pytest.approx(1.0)
    assert fbx["up"] == 2  # ufbx CoordinateAxis.POSITIVE_Y
    # Same joints, same hierarchy (FBX lists nodes breadth-first, BVH depth-first).
    hierarchy = dict(zip(fbx["joints"], fbx["parents"], strict=True))
    expected = {
        n: (skel.names[p] if p >= 0 else None)
        for n, p in zip(skel.names, skel.parents, strict=True)
    }
    assert len(fbx["joints"]) == skel.n_joints and hierarchy == expected
    order = [fbx["joints"].index(name) for name in skel.names]
    # Rate and length: exactly the BVH's frames, the first at t = 0.
    assert fbx["fps"] == pytest.approx(round(motion.fps), abs=1e-9)
    assert fbx["n_stacks"] == 1
    assert fbx["time_begin"] == pytest.approx(0.0, abs=1e-9)
    assert fbx["first_key_time"] == pytest.approx(0.0, abs=1e-9)
    assert round((fbx["time_end"] - fbx["time_begin"]) * fbx["fps"]) + 1 == motion.n_frames
    assert fbx["keys_per_curve"] == [motion.n_frames]

    positions, _ = forward_kinematics(motion)
    worst = 0.0
    for f in frames:
        got = np.asarray(fbx["positions"][str(f)])[order]
        err = float(np.abs(got - positions[f]).max())
        worst = max(worst, err)
    assert worst < 1e-3, f"world positions off by {worst * 1000:.3f} mm"
    return worst


@pytest.fixture(scope="module")
def exporter():
    with FbxExporter() as ex:
        yield ex


def test_salsa_slice_round_trips_through_fbx(
    salsa_dir: Path, tmp_path: Path, exporter: FbxExporter
):
    motion = read_bvh(salsa_dir / "60_03_scaled.bvh", fps=60.0).slice(900, 1140)  # 4 s at 60 fps
    bvh = tmp_path / "salsa.bvh"
    write_bvh(motion, bvh)
    summary = exporter.convert(bvh, tmp_path / "salsa.fbx")
    assert summary["frames"] == 240 and summary["fps"] == 60.0 and summary["joints"] == 43
    # The root travels in the slice: the check is not satisfied by a static pose.
    assert np.ptp(motion.root_positions[:, [0, 2]], axis=0).max() > 0.05
    check_fbx_against_fk(tmp_path / "salsa.fbx", read_bvh(bvh))


def test_modern_slice_at_30fps_round_trips_through_fbx(
    modern_dir: Path, tmp_path: Path, exporter: FbxExporter
):
    src = read_bvh(modern_dir / "05_06.bvh", scale=MODERN_SCALE)
    assert src.fps == pytest.approx(120.0, rel=1e-3)
    every4 = slice(200, 680, 4)  # 4 s, resampled to 30 fps: a 'Frame Time: 0.033333' file
    motion = Motion(src.skeleton, 30.0, src.root_positions[every4], src.rotations[every4])
    bvh = tmp_path / "modern.bvh"
    write_bvh(motion, bvh)
    fbx = tmp_path / "modern.fbx"
    summary = bvh_to_fbx(bvh, fbx, exporter=exporter)
    assert summary == {**summary, "frames": 120, "fps": 30.0, "joints": 31}
    check_fbx_against_fk(fbx, read_bvh(bvh))


def test_scale_converts_file_units_to_metres(
    modern_dir: Path, tmp_path: Path, exporter: FbxExporter
):
    """A raw CMU file in ASF units, converted with --scale, gives the same FBX as metres."""
    raw = modern_dir / "05_02.bvh"
    text = raw.read_text().splitlines()
    motion_at = text.index("MOTION")
    header = text[: motion_at + 1] + ["Frames: 60", "Frame Time: .0083333"]
    clip = tmp_path / "raw.bvh"
    clip.write_text("\n".join(header + text[motion_at + 3 : motion_at + 63]) + "\n")
    fbx = tmp_path / "raw.fbx"
    assert cli_main(["convert", str(clip), str(fbx), "--scale", str(MODERN_SCALE)]) == 0
    check_fbx_against_fk(fbx, read_bvh(clip, scale=MODERN_SCALE), n_samples=2)


def test_exporter_stays_warm_and_recovers(salsa_dir: Path, tmp_path: Path):
    motion = read_bvh(salsa_dir / "61_03_scaled.bvh", fps=60.0).slice(0, 30)
    bvh = tmp_path / "a.bvh"
    write_bvh(motion, bvh)
    junk = tmp_path / "junk.bvh"
    junk.write_bytes(b"\x00\x01binary junk, not a BVH\xff" * 50)
    with FbxExporter() as ex:
        ex.convert(bvh, tmp_path / "1.fbx")
        pid = ex.pid
        assert ex.convert(bvh, tmp_path / "2.fbx", fps=24.0)["fps"] == 24.0  # rate override
        assert ex.pid == pid and ex.starts == 1  # one warm process for both files
        assert read_fbx(tmp_path / "2.fbx", [0])["fps"] == 24.0

        with pytest.raises(MotionFileError) as err:  # DanceGraph's reader says what is wrong
            ex.convert(junk, tmp_path / "junk.fbx")
        assert err.value.code.startswith("bvh_") and "junk.bvh" in str(err.value.to_dict())
        assert not (tmp_path / "junk.fbx").exists()
        assert ex.pid == pid  # a bad file does not cost the warm process

        os.kill(pid, signal.SIGKILL)  # a crashed worker is replaced on the next request
        ex._proc.wait(timeout=10)
        ex.convert(bvh, tmp_path / "3.fbx")
        assert ex.starts == 2 and ex.pid != pid
    assert not ex.running
    assert (tmp_path / "3.fbx").stat().st_size > 10_000


def test_exporter_is_renewed_after_max_jobs(salsa_dir: Path, tmp_path: Path):
    """A long-lived worker's Blender is replaced after ``max_jobs`` files (its memory grows)."""
    bvh = tmp_path / "a.bvh"
    write_bvh(read_bvh(salsa_dir / "61_03_scaled.bvh", fps=60.0).slice(0, 20), bvh)
    with FbxExporter(max_jobs=2) as ex:
        pids = []
        for k in range(5):
            ex.convert(bvh, tmp_path / f"{k}.fbx")
            pids.append(ex.pid)
        assert ex.starts == 3 and pids[0] == pids[1] != pids[2] == pids[3] != pids[4]
    assert all((tmp_path / f"{k}.fbx").stat().st_size > 5_000 for k in range(5))


def test_timeout_stops_a_stuck_worker(salsa_dir: Path, tmp_path: Path):
    motion = read_bvh(salsa_dir / "60_03_scaled.bvh", fps=60.0).slice(0, 600)
    bvh = tmp_path / "a.bvh"
    write_bvh(motion, bvh)
    with FbxExporter(convert_timeout_s=0.01) as ex:
        ex.start()
        with pytest.raises(FbxError) as err:
            ex.convert(bvh, tmp_path / "a.fbx")
        assert err.value.code == "fbx_export_failed" and "no answer" in err.value.message
        assert not ex.running
        ex.convert_timeout_s = 300.0
        assert ex.convert(bvh, tmp_path / "a.fbx")["frames"] == 600


def test_missing_blender_is_a_clear_error(tmp_path: Path, salsa_dir: Path):
    bvh = tmp_path / "a.bvh"
    write_bvh(read_bvh(salsa_dir / "60_03_scaled.bvh").slice(0, 5), bvh)
    with pytest.raises(FbxError) as err:
        FbxExporter(python=tmp_path / "no-such-python").convert(bvh, tmp_path / "a.fbx")
    assert err.value.code == "fbx_unavailable"


def test_blender_python_comes_from_the_environment(monkeypatch, tmp_path: Path):
    monkeypatch.setenv("DANCEGRAPH_BLENDER_PYTHON", str(tmp_path / "elsewhere" / "python"))
    assert not fbx_available()
    with pytest.raises(FbxError) as err:
        FbxExporter().start()
    assert err.value.code == "fbx_unavailable" and "elsewhere" in err.value.message


def test_convert_cli_reports_bad_input(tmp_path: Path, capsys):
    truncated = tmp_path / "cut.bvh"
    truncated.write_text("HIERARCHY\nROOT hip\n{\n  OFFSET 0 0 0\n  CHANNELS 6 Xposition")
    assert cli_main(["convert", str(truncated), str(tmp_path / "cut.fbx")]) == 2
    err = capsys.readouterr().err
    assert "cut.bvh" in err and "bvh_" in err
    assert cli_main(["convert", str(tmp_path / "absent.bvh"), str(tmp_path / "x.fbx")]) == 2
    assert "absent.bvh" in capsys.readouterr().err
    assert not (tmp_path / "cut.fbx").exists()
