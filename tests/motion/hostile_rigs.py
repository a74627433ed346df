"""Rig files built to break a reader, generated here from the project's own valid rigs.

:func:`valid_bvh` and :func:`valid_glb` write a valid humanoid rig (the CMU-named BVH rig of
``tests.motion.rigs``, and the same rig written as a skinned GLB by ``dancegraph.motion.gltf``);
:func:`glb_parts` / :func:`glb_bytes` take a GLB apart and put it together again, so each hostile
file is a valid one with one thing changed. :func:`probe_files` writes the attacker's probe
files of issue 33 (rows 1 to 8), each with the codes a hardened reader answers.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from dancegraph.motion.gltf import write_glb
from dancegraph.motion.rig import RigMesh, load_rig
from dancegraph.motion.skeleton import Motion
from tests.motion.rigs import _CMU, _template, write_bvh_rig


def valid_bvh(path: Path, frames: int = 1) -> Path:
    """The CMU-named BVH rig (centimetres) with ``frames`` frames of its bind pose."""
    write_bvh_rig(path, _CMU, _template(legs=1.05, arms=1.1), 0.01)
    if frames > 1:
        text = path.read_text()
        head, rest = text.split("Frames: 1\n", 1)
        frame_time, row = rest.split("\n")[:2]
        body = (row + "\n") * frames
        path.write_text(f"{head}Frames: {frames}\n{frame_time}\n{body}")
    return path


def valid_glb(path: Path) -> Path:
    """The BVH rig as a GLB with a small skinned mesh (one quad per bone)."""
    rig = load_rig(valid_bvh(path.with_suffix(".bvh")))
    sk = rig.skeleton
    pos = np.zeros((sk.n_joints, 3))
    for j in range(sk.n_joints):
        p = sk.parents[j]
        pos[j] = sk.offsets[j] if p < 0 else pos[p] + sk.offsets[j]
    verts, tris, joints = [], [], []
    for j in range(1, sk.n_joints):
        a, b = pos[sk.parents[j]], pos[j]
        k = len(verts)
        verts += [a + [0.01, 0, 0], a - [0.01, 0, 0], b + [0.01, 0, 0], b - [0.01, 0, 0]]
        tris += [[k, k + 1, k + 2], [k + 1, k + 3, k + 2]]
        joints += [[sk.parents[j], 0, 0, 0]] * 2 + [[j, 0, 0, 0]] * 2
    weights = np.zeros((len(verts), 4))
    weights[:, 0] = 1.0
    rig.mesh = RigMesh(np.array(verts), np.array(tris), np.array(joints), weights)
    rot = np.zeros((1, sk.n_joints, 4))
    rot[..., 3] = 1.0
    write_glb(Motion(sk, 30.0, sk.offsets[:1].copy(), rot), rig, path)
    return path


def glb_parts(raw: bytes) -> tuple[dict, bytes]:
    """A GLB's JSON document and binary chunk."""
    n_json = struct.unpack_from("<I", raw, 12)[0]
    doc = json.loads(raw[20 : 20 + n_json])
    bin_at = 20 + n_json
    n_bin = struct.unpack_from("<I", raw, bin_at)[0] if bin_at + 8 <= len(raw) else 0
    return doc, raw[bin_at + 8 : bin_at + 8 + n_bin]


def glb_bytes(doc: dict | bytes, blob: bytes) -> bytes:
    """A GLB of a JSON document (a dict, or JSON text as it is) and a binary chunk."""
    text = doc if isinstance(doc, bytes) else json.dumps(doc, ensure_ascii=True).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    return (
        struct.pack("<III", 0x46546C67, 2, total)
        + struct.pack("<II", len(text), 0x4E4F534A)
        + text
        + struct.pack("<II", len(blob), 0x004E4942)
        + blob
    )


def _ibm_accessor(doc: dict) -> int:
    return doc["skins"][0]["inverseBindMatrices"]


def negative_stride(doc: dict, blob: bytes) -> bytes:
    """Row 1: the inverse-bind matrices' view strides backwards by 1 GiB."""
    acc = doc["accessors"][_ibm_accessor(doc)]
    doc["bufferViews"][acc["bufferView"]]["byteStride"] = -(2**30)
    return glb_bytes(doc, blob)


def cycle_above_skin(doc: dict, blob: bytes) -> bytes:
    """Row 2: two nodes, each the other's child, above the skeleton's root joint."""
    nodes = doc["nodes"]
    a, b = len(nodes), len(nodes) + 1
    root = doc["skins"][0]["joints"][0]
    nodes.append({"name": "loop_a", "children": [b]})
    nodes.append({"name": "loop_b", "children": [a, root]})
    return glb_bytes(doc, blob)


def stride_one(doc: dict, blob: bytes, mib: int = 4) -> bytes:
    """Row 4: a MAT4 accessor with byteStride 1 over a ``mib`` MiB buffer."""
    big = blob + b"\0" * (mib * 2**20)
    doc["buffers"][0]["byteLength"] = len(big)
    doc["bufferViews"].append(
        {"buffer": 0, "byteOffset": 0, "byteLength": len(big), "byteStride": 1}
    )
    acc = doc["accessors"][_ibm_accessor(doc)]
    acc["bufferView"] = len(doc["bufferViews"]) - 1
    acc["count"] = len(big) - 64
    acc.pop("byteOffset", None)
    return glb_bytes(doc, big)


def deep_chain(doc: dict, blob: bytes, depth: int) -> bytes:
    """Row 5: the root joint hung under a chain of ``depth`` nodes."""
    nodes = doc["nodes"]
    root = doc["skins"][0]["joints"][0]
    first = len(nodes)
    for k in range(depth):
        nodes.append({"name": f"chain_{k}", "children": [first + k + 1]})
    nodes[-1]["children"] = [root]
    doc["scenes"][0]["nodes"] = [first]
    return glb_bytes(doc, blob)


def cycle_without_skin(doc: dict, blob: bytes) -> bytes:
    """Row 6: no skin; two nodes each the other's child."""
    for key in ("skins", "meshes"):
        doc.pop(key, None)
    doc["nodes"] = [n for n in doc["nodes"] if "mesh" not in n]
    n = len(doc["nodes"])
    doc["nodes"] += [{"name": "loop_a", "children": [n + 1]}, {"name": "loop_b", "children": [n]}]
    return glb_bytes(doc, blob)


def deep_json(doc: dict, blob: bytes, depth: int = 100_000) -> bytes:
    """Row 6: the JSON chunk nests an array ``depth`` deep."""
    text = json.dumps(doc)[:-1] + ', "extras": ' + "[" * depth + "]" * depth + "}"
    return glb_bytes(text.encode(), blob)


def nested_bvh(joints: int = 10_000) -> bytes:
    """Row 6: a BVH whose joints nest ``joints`` deep."""
    head = [
        "HIERARCHY",
        "ROOT hip",
        "{",
        "OFFSET 0 0 0",
        "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
    ]
    for k in range(joints):
        head += [f"JOINT j{k}", "{", "OFFSET 0 1 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    head += ["}"] * (joints + 1)
    values = " ".join(["0"] * (6 + 3 * joints))
    return ("\n".join(head) + f"\nMOTION\nFrames: 1\nFrame Time: 0.0333\n{values}\n").encode()


def huge_count(doc: dict, blob: bytes) -> bytes:
    """Row 7: the inverse-bind matrices claim 10⁹ elements and no buffer view."""
    acc = doc["accessors"][_ibm_accessor(doc)]
    acc.pop("bufferView")
    acc["count"] = 10**9
    return glb_bytes(doc, blob)


def bad_name(doc: dict, blob: bytes, name: str) -> bytes:
    """Row 8: the first skin joint renamed to ``name`` (a NUL, a lone surrogate)."""
    doc["nodes"][doc["skins"][0]["joints"][1]]["name"] = name
    return glb_bytes(doc, blob)


def bvh_nul_after(raw: bytes, at: int = 70_000) -> bytes:
    """Row 8: a BVH rig whose hierarchy is padded past ``at`` bytes, then a NUL in a name."""
    text = raw.decode()
    pad = "\n" * at
    return text.replace("ROOT hip", f"ROOT hip{pad}", 1).replace("lShin", "lSh\0in", 1).encode()


#: The probe files :func:`probe_files` writes (row number first).
PROBE_NAMES = (
    "1_negative_stride.glb",
    "2_cycle_above_skin.glb",
    "4_stride_one.glb",
    "5_chain_10000.glb",
    "5_chain_20000.glb",
    "6_cycle_no_skin.glb",
    "6_deep_json.glb",
    "6_nested_joints.bvh",
    "7_huge_count.glb",
    "8_nul_name.glb",
    "8_surrogate_name.glb",
    "8_nul_after_64k.bvh",
)


def probe_files(out: Path) -> dict[str, tuple[bytes, set[str]]]:
    """The probe files of issue 33 by row name: ``(bytes, codes a hardened reader may answer)``."""
    glb = valid_glb(out / "base.glb").read_bytes()
    bvh = valid_bvh(out / "base.bvh").read_bytes()

    def g(fn, *args):
        return fn(*glb_parts(glb), *args)

    return {
        "1_negative_stride.glb": (g(negative_stride), {"rig_unreadable"}),
        "2_cycle_above_skin.glb": (g(cycle_above_skin), {"rig_unreadable"}),
        "4_stride_one.glb": (g(stride_one), {"rig_unreadable"}),
        "5_chain_10000.glb": (g(deep_chain, 10_000), {"rig_too_complex"}),
        "5_chain_20000.glb": (g(deep_chain, 20_000), {"rig_too_complex"}),
        "6_cycle_no_skin.glb": (g(cycle_without_skin), {"rig_unreadable"}),
        "6_deep_json.glb": (g(deep_json), {"rig_too_complex"}),
        "6_nested_joints.bvh": (nested_bvh(), {"rig_too_complex"}),
        "7_huge_count.glb": (g(huge_count), {"rig_too_complex"}),
        "8_nul_name.glb": (g(bad_name, "hip\0x"), {"rig_name_invalid"}),
        "8_surrogate_name.glb": (g(bad_name, "hip\ud800"), {"rig_name_invalid"}),
        "8_nul_after_64k.bvh": (bvh_nul_after(bvh), {"rig_unreadable"}),
    }
