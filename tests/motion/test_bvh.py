"""BVH read/write on both shared skeletons, and every kind of bad file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dancegraph.errors import MotionFileError
from dancegraph.motion.bvh import read_bvh, write_bvh
from dancegraph.motion.fk import forward_kinematics

CMU_SCALE = 0.056444


@pytest.fixture(scope="module")
def salsa(salsa_dir: Path):
    return read_bvh(salsa_dir / "60_03_scaled.bvh", fps=60)


@pytest.fixture(scope="module")
def modern(modern_dir: Path):
    return read_bvh(modern_dir / "05_04.bvh", scale=CMU_SCALE)


def test_read_salsa_skeleton(salsa):
    sk = salsa.skeleton
    assert sk.n_joints == 43
    assert sk.names[0] == "hip" and sk.parents[0] == -1
    assert sk.channels[0] == (
        "Xposition",
        "Yposition",
        "Zposition",
        "Zrotation",
        "Yrotation",
        "Xrotation",
    )
    assert all(c == ("Zrotation", "Xrotation", "Yrotation") for c in sk.channels[1:])
    assert salsa.fps == 60.0
    assert salsa.n_frames > 1000
    # End Sites: eyes, finger tips and the two feet
    assert len(sk.end_sites) == 2 + 10 + 2
    assert sk.canonical["left_ankle"] == "lFoot" and sk.canonical["right_shoulder"] == "rShldr"


def test_read_header_fps_and_scale(modern_dir: Path, modern):
    sk = modern.skeleton
    assert sk.n_joints == 31 and sk.names[0] == "Hips"
    assert modern.fps == 120.0  # "Frame Time: .0083333"
    assert sk.canonical["left_toe"] == "LeftToeBase"
    raw = read_bvh(modern_dir / "05_04.bvh")
    np.testing.assert_allclose(raw.skeleton.offsets * CMU_SCALE, sk.offsets)
    np.testing.assert_allclose(raw.root_positions * CMU_SCALE, modern.root_positions)
    # a person: 1.4-2.0 m from the feet to the head top at the first frame
    pos, _ = forward_kinematics(modern.slice(0, 1))
    assert 1.2 < pos[0, :, 1].max() - pos[0, :, 1].min() < 2.0


@pytest.mark.parametrize("which", ["salsa", "modern"])
def test_write_read_round_trip(which, salsa, modern, tmp_path: Path):
    motion = (salsa if which == "salsa" else modern).slice(100, 400)
    out = tmp_path / "a.bvh"
    write_bvh(motion, out)
    back = read_bvh(out)
    assert back.skeleton == motion.skeleton  # names, parents, offsets, channels, end sites
    assert back.skeleton.channels == motion.skeleton.channels
    assert back.fps == motion.fps and back.n_frames == motion.n_frames
    np.testing.assert_allclose(back.root_positions, motion.root_positions, atol=1e-6)
    dots = np.abs(np.sum(back.rotations * motion.rotations, axis=-1))
    assert np.degrees(2 * np.arccos(np.clip(dots, -1, 1))).max() < 1e-4
    p0, _ = forward_kinematics(motion)
    p1, _ = forward_kinematics(back)
    assert np.abs(p0 - p1).max() < 1e-5
    # writing what was read gives the same text: printed precision is a fixed point
    out2 = tmp_path / "b.bvh"
    write_bvh(back, out2)
    assert out2.read_text() == out.read_text()


def test_channel_values_round_trip_to_printed_precision(salsa_dir: Path, tmp_path: Path):
    """The original file's channel values come back (within 1e-6 or an equivalent angle set)."""
    src = salsa_dir / "61_05_scaled.bvh"
    motion = read_bvh(src).slice(0, 200)
    out = tmp_path / "c.bvh"
    write_bvh(motion, out)
    lines_src = src.read_text().split("\n")
    first = next(i for i, line in enumerate(lines_src) if line.startswith("Frame Time")) + 1
    orig = np.array([[float(v) for v in line.split()] for line in lines_src[first : first + 200]])
    lines_out = out.read_text().split("\n")
    first = next(i for i, line in enumerate(lines_out) if line.startswith("Frame Time")) + 1
    new = np.array([[float(v) for v in line.split()] for line in lines_out[first : first + 200]])
    assert new.shape == orig.shape
    same = np.isclose(new, orig, atol=2e-6) | np.isclose(np.abs(new - orig) % 360, 0, atol=2e-6)
    assert same.mean() > 0.999


def test_large_file_reads(tmp_path: Path, salsa_dir: Path):
    """A 100,000-frame file works (built by repeating a real take's frame lines)."""
    lines = (salsa_dir / "60_03_scaled.bvh").read_text().split("\n")
    first = next(i for i, line in enumerate(lines) if line.startswith("Frame Time")) + 1
    frames = [line for line in lines[first:] if line.strip()]
    n = 100_000
    body = (frames * (n // len(frames) + 1))[:n]
    header = lines[: first - 2] + [f"Frames: {n}", lines[first - 1]]
    out = tmp_path / "big.bvh"
    out.write_text("\n".join(header + body) + "\n")
    big = read_bvh(out, fps=60)
    assert big.n_frames == n
    small = read_bvh(salsa_dir / "60_03_scaled.bvh", fps=60)
    k = (n - 1) % small.n_frames
    np.testing.assert_allclose(big.root_positions[-1], small.root_positions[k])
    np.testing.assert_allclose(big.rotations[-1], small.rotations[k])


# --- bad files, each made from real data --------------------------------------------------


@pytest.fixture()
def small_text(salsa, tmp_path: Path) -> str:
    out = tmp_path / "small.bvh"
    write_bvh(salsa.slice(0, 20), out)
    return out.read_text()


def _frame_lines(text: str) -> tuple[list[str], int]:
    lines = text.split("\n")
    return lines, next(i for i, line in enumerate(lines) if line.startswith("Frame Time")) + 1


def _expect(tmp_path: Path, content: str | bytes, code: str, line: int | None = None):
    bad = tmp_path / "bad.bvh"
    if isinstance(content, bytes):
        bad.write_bytes(content)
    else:
        bad.write_text(content)
    with pytest.raises(MotionFileError) as info:
        read_bvh(bad)
    err = info.value
    assert err.code == code, err.message
    assert err.path == str(bad) and "bad.bvh" in err.message
    if line is not None:
        assert err.line == line, err.message
    return err


def test_truncated_mid_frame(small_text, tmp_path):
    cut = small_text[: int(len(small_text) * 0.8)]
    _expect(tmp_path, cut, "bvh_truncated", line=cut.count("\n") + 1)


def test_truncated_missing_frames(small_text, tmp_path):
    lines, first = _frame_lines(small_text)
    _expect(tmp_path, "\n".join(lines[: first + 10]) + "\n", "bvh_truncated")


def test_truncated_in_hierarchy(small_text, tmp_path):
    _expect(tmp_path, small_text[:1500], "bvh_truncated")


def test_channel_count_mismatch(small_text, tmp_path):
    lines, first = _frame_lines(small_text)
    lines[first + 5] = lines[first + 5] + " 0.0 0.0"
    _expect(tmp_path, "\n".join(lines), "bvh_channel_count", line=first + 6)


def test_channel_count_short_line(small_text, tmp_path):
    lines, first = _frame_lines(small_text)
    lines[first + 3] = " ".join(lines[first + 3].split()[:-3])
    _expect(tmp_path, "\n".join(lines), "bvh_channel_count", line=first + 4)


@pytest.mark.parametrize("token", ["nan", "inf", "-inf", "NaN"])
def test_nan_values(small_text, tmp_path, token):
    lines, first = _frame_lines(small_text)
    vals = lines[first + 7].split()
    vals[10] = token
    lines[first + 7] = " ".join(vals)
    err = _expect(tmp_path, "\n".join(lines), "bvh_nan", line=first + 8)
    assert "frame 7" in err.message


def test_zero_frames(small_text, tmp_path):
    lines, first = _frame_lines(small_text)
    head = lines[: first - 2] + ["Frames: 0", lines[first - 1]]
    _expect(tmp_path, "\n".join(head) + "\n", "bvh_no_frames", line=first - 1)


def test_unknown_rotation_order(small_text, tmp_path):
    text = small_text.replace(
        "CHANNELS 3 Zrotation Xrotation Yrotation", "CHANNELS 3 Zrotation Xrotation Wrotation", 1
    )
    line = text.split("\n").index(next(x for x in text.split("\n") if "Wrotation" in x)) + 1
    _expect(tmp_path, text, "bvh_rotation_order", line=line)
    repeated = small_text.replace(
        "CHANNELS 3 Zrotation Xrotation Yrotation", "CHANNELS 3 Zrotation Xrotation Xrotation", 1
    )
    _expect(tmp_path, repeated, "bvh_rotation_order")


def test_duplicate_joint_names(small_text, tmp_path):
    text = small_text.replace("JOINT lShin", "JOINT lThigh")
    line = [i for i, x in enumerate(text.split("\n"), start=1) if x.strip() == "JOINT lThigh"][1]
    err = _expect(tmp_path, text, "bvh_duplicate_joint", line=line)
    assert "lThigh" in err.message


def test_binary_junk(tmp_path):
    junk = np.random.default_rng(3).integers(0, 256, 4096, dtype=np.uint8).tobytes()
    _expect(tmp_path, junk, "bvh_not_text")
    _expect(tmp_path, b"\x89PNG\r\n\x1a\n" + junk, "bvh_not_text")


def test_missing_file(tmp_path):
    with pytest.raises(MotionFileError) as info:
        read_bvh(tmp_path / "absent.bvh")
    assert info.value.code == "bvh_unreadable"


def test_any_channel_order_and_layout(salsa, tmp_path: Path):
    """Every Euler order, a root without position channels, a joint without channels."""
    from itertools import permutations

    from dancegraph.motion.skeleton import Motion, Skeleton

    motion = salsa.slice(0, 50)
    sk = motion.skeleton
    orders = ["".join(p) for p in permutations("XYZ")]
    channels = [("Zrotation", "Xposition", "Yrotation", "Yposition", "Xrotation", "Zposition")]
    for j in range(1, sk.n_joints):
        order = orders[j % 6]
        channels.append(tuple(f"{a}rotation" for a in order))
    still = sk.index("leftEye")
    channels[still] = ()
    custom = Skeleton(sk.names, sk.parents, sk.offsets, channels, sk.end_sites)
    rotations = motion.rotations.copy()
    rotations[:, still] = [0.0, 0.0, 0.0, 1.0]
    moved = Motion(custom, motion.fps, motion.root_positions, rotations)
    out = tmp_path / "orders.bvh"
    write_bvh(moved, out)
    back = read_bvh(out)
    assert back.skeleton.channels == channels
    p0, _ = forward_kinematics(moved)
    p1, _ = forward_kinematics(back)
    assert np.abs(p0 - p1).max() < 1e-5
    # a root with rotations only: its position is its offset
    no_pos = [("Zrotation", "Xrotation", "Yrotation")] + channels[1:]
    fixed = Skeleton(sk.names, sk.parents, sk.offsets.copy(), no_pos, sk.end_sites)
    fixed.offsets[0] = [0.1, 0.9, 0.2]
    write_bvh(Motion(fixed, 30.0, np.tile(fixed.offsets[0], (50, 1)), rotations), out)
    back = read_bvh(out)
    np.testing.assert_allclose(back.root_positions, np.tile([0.1, 0.9, 0.2], (50, 1)))


def test_crlf_and_tabs(small_text, tmp_path: Path):
    good = tmp_path / "good.bvh"
    good.write_text(small_text)
    crlf = tmp_path / "crlf.bvh"
    crlf.write_bytes(small_text.replace(" ", "\t").replace("\n", "\r\n").encode())
    a, b = read_bvh(good), read_bvh(crlf)
    assert a.skeleton == b.skeleton
    np.testing.assert_array_equal(a.rotations, b.rotations)
