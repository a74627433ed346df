"""The readers' limits before allocation (issue 33): each refused with its code, and a file just
inside each limit still read."""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.errors import MotionFileError
from dancegraph.motion import bvh, gltf
from dancegraph.motion.rig import RigError, check_hierarchy, load_rig
from tests.motion.hostile_rigs import glb_bytes, glb_parts, nested_bvh, valid_bvh, valid_glb


def _code(fn, *args, **kwargs) -> str:
    with pytest.raises((MotionFileError, RigError)) as info:
        fn(*args, **kwargs)
    return info.value.code


def test_bvh_frames_times_channels_refused_before_parsing(tmp_path):
    path = valid_bvh(tmp_path / "long.bvh", frames=100)
    values = 100 * 60  # 19 joints: 6 root channels and 3 for each of the others
    assert bvh.read_bvh(path, max_values=values).n_frames == 100
    assert _code(bvh.read_bvh, path, max_values=values - 1) == "bvh_too_complex"


def test_bvh_nesting_and_joint_count(tmp_path):
    path = tmp_path / "deep.bvh"
    path.write_bytes(nested_bvh(bvh.MAX_DEPTH - 1))  # the root and 255 joints below it
    assert bvh.read_bvh(path).skeleton.n_joints == bvh.MAX_DEPTH
    path.write_bytes(nested_bvh(bvh.MAX_DEPTH))
    assert _code(bvh.read_bvh, path) == "bvh_too_complex"
    assert _code(bvh.read_bvh_skeleton, path) == "bvh_too_complex"
    head = [
        "HIERARCHY",
        "ROOT hip",
        "{",
        "OFFSET 0 0 0",
        "CHANNELS 3 Zrotation Xrotation Yrotation",
    ]
    for k in range(bvh.MAX_JOINTS):
        head += [f"JOINT j{k}", "{", "OFFSET 0 1 0", "CHANNELS 0", "}"]
    path.write_text("\n".join([*head, "}", "MOTION", "Frames: 1", "Frame Time: 0.03", "0 0 0", ""]))
    assert _code(bvh.read_bvh_skeleton, path) == "bvh_too_complex"


def test_bvh_nul_anywhere_and_unicode_digits(tmp_path):
    path = valid_bvh(tmp_path / "rig.bvh", frames=3000)
    raw = path.read_bytes()
    path.write_bytes(raw[:-10] + b"\0" + raw[-9:])  # far past the first 64 KiB
    assert len(raw) > 65536
    assert _code(bvh.read_bvh, path) == "bvh_not_text"
    assert _code(bvh.read_bvh_skeleton, path) == "bvh_not_text"
    path.write_bytes(raw.replace(b"Frames: 3000", "Frames: ²".encode()))
    assert _code(bvh.read_bvh, path) == "bvh_syntax"


def test_bvh_rig_reads_only_its_hierarchy(tmp_path):
    """A rig's frames are not parsed: a broken frame block does not matter to the rig."""
    path = valid_bvh(tmp_path / "rig.bvh", frames=10)
    path.write_text(path.read_text() + "not a number\n")
    assert _code(bvh.read_bvh, path) in {"bvh_syntax", "bvh_frame_count"}
    assert load_rig(path).skeleton.n_joints == 19


def test_glb_decoded_bytes_are_counted_over_all_accessors(tmp_path, monkeypatch):
    path = valid_glb(tmp_path / "rig.glb")
    assert gltf.read_gltf_rig(path)[3].n_vertices > 0
    doc, _ = glb_parts(path.read_bytes())
    largest = max(
        a["count"]
        * np.dtype(gltf._COMPONENTS[a["componentType"]]).itemsize
        * gltf._WIDTH[a["type"]]
        for a in doc["accessors"]
    )
    monkeypatch.setattr(gltf, "MAX_DECODED_BYTES", largest)  # each accessor fits, all do not
    assert _code(gltf.read_gltf_rig, path) == "rig_too_complex"


def test_glb_chunk_past_the_end_and_json_not_an_object(tmp_path):
    raw = valid_glb(tmp_path / "rig.glb").read_bytes()
    path = tmp_path / "bad.glb"
    path.write_bytes(raw[:-100])  # the BIN chunk's length now runs past the file
    assert _code(gltf.read_gltf_rig, path) == "rig_unreadable"
    _, blob = glb_parts(raw)
    path.write_bytes(glb_bytes(b"[1, 2, 3]", blob))
    assert _code(gltf.read_gltf_rig, path) == "rig_unreadable"


@pytest.mark.parametrize(
    "names,parents,code",
    [
        (["a", "b", "c"], [2, 0, 1], "rig_unreadable"),  # a cycle
        (["a", "b"], [-1, 5], "rig_unreadable"),  # a parent that is not a joint
        (["a", "b\0"], [-1, 0], "rig_name_invalid"),
        (["a", "b\ud800"], [-1, 0], "rig_name_invalid"),
        (["a", "b" * 256], [-1, 0], "rig_name_invalid"),
        (["a", 7], [-1, 0], "rig_name_invalid"),
        ([f"j{k}" for k in range(300)], [k - 1 for k in range(300)], "rig_too_complex"),
    ],
)
def test_check_hierarchy(names, parents, code):
    assert _code(check_hierarchy, names, np.array(parents)) == code


def test_check_hierarchy_accepts_a_forest_at_the_limits():
    n = bvh.MAX_DEPTH
    check_hierarchy([f"j{k}" for k in range(n)], np.array([k - 1 for k in range(n)]))
    check_hierarchy(["a", "b", "c"], np.array([-1, -1, 0]))
