"""One GLB holding a couple: each dancer's skeleton as its own character, animated on one clock.

The file (glTF 2.0, binary) has one scene with a node per dancer (named ``lead``, ``follow``),
each the parent of its skeleton's joint nodes (named ``<dancer>:<joint>``; the library's
skeleton, metres, Y up; the root joint's translation is its world position, the others'
translations their bone offsets) and a skin naming them (so importers make each an armature;
its bind pose the skeleton's zero pose), and one animation: every joint's rotation (x, y, z, w) and each
root's translation at every frame, sharing one time input (seconds). No mesh: a DCC tool or
the retargeter puts characters on the joints. Why one file: an artist drops the couple into a
scene at once, both dancers in one world frame.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from dancegraph.motion.skeleton import Motion

_FLOAT = 5126
_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942


class _Buffer:
    """The binary chunk with its buffer views and float accessors."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, kind: str, bounds: bool = False) -> int:
        data = np.ascontiguousarray(array, dtype=np.float32)
        self.views.append({"buffer": 0, "byteOffset": len(self.blob), "byteLength": data.nbytes})
        self.blob.extend(data.tobytes())
        acc = {
            "bufferView": len(self.views) - 1,
            "componentType": _FLOAT,
            "count": int(data.shape[0]),
            "type": kind,
        }
        if bounds:
            flat = data.reshape(len(data), -1)
            acc["min"], acc["max"] = flat.min(axis=0).tolist(), flat.max(axis=0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _inverse_binds(motion: Motion) -> np.ndarray:
    """``(J, 16)`` column-major inverse bind matrices of the skeleton's rest pose (every joint
    unrotated at its bone offsets from the origin: the BVH convention's zero pose)."""
    sk = motion.skeleton
    rest = np.zeros((sk.n_joints, 3))
    for j, p in enumerate(sk.parents):
        if p >= 0:
            rest[j] = rest[p] + sk.offsets[j]
    mats = np.tile(np.eye(4), (sk.n_joints, 1, 1))
    mats[:, :3, 3] = -rest
    return mats.transpose(0, 2, 1).reshape(-1, 16)


def _dancer(
    name: str, motion: Motion, buf: _Buffer, nodes: list, channels: list, skins: list
) -> int:
    """Add one dancer's group node, joint nodes, skin and animation channels; its group node."""
    sk = motion.skeleton
    first = len(nodes) + 1
    skins.append(
        {
            "name": name,
            "joints": list(range(first, first + sk.n_joints)),
            "skeleton": first + int(np.flatnonzero(sk.parents < 0)[0]),
            "inverseBindMatrices": buf.add(_inverse_binds(motion), "MAT4"),
        }
    )
    group = {"name": name, "children": [first + int(np.flatnonzero(sk.parents < 0)[0])]}
    nodes.append(group)
    for j, joint in enumerate(sk.names):
        root = sk.parents[j] < 0
        offset = motion.root_positions[0] if root else sk.offsets[j]
        node = {
            "name": f"{name}:{joint}",
            "translation": [float(x) for x in offset],
            "rotation": [float(x) for x in motion.rotations[0, j]],
        }
        kids = [first + c for c in sk.children(j)]
        if kids:
            node["children"] = kids
        nodes.append(node)
        out = buf.add(motion.rotations[:, j], "VEC4")
        channels.append((first + j, "rotation", out))
        if root:
            channels.append((first + j, "translation", buf.add(motion.root_positions, "VEC3")))
    return first - 1


def write_couple_glb(dancers: dict[str, Motion], path: str | Path) -> dict:
    """Write ``dancers`` (name → motion, the same frame count and rate) as one GLB at ``path``
    (module docstring); returns ``{"dancers", "frames", "bytes"}``. Raises ``ValueError``
    when the motions' frame counts or rates differ."""
    motions = list(dancers.values())
    if len({(m.n_frames, m.fps) for m in motions}) != 1:
        raise ValueError("the dancers of one GLB need the same frame count and rate")
    buf = _Buffer()
    nodes: list[dict] = []
    channels: list[tuple[int, str, int]] = []
    skins: list[dict] = []
    times = np.arange(motions[0].n_frames) / motions[0].fps
    groups = [_dancer(name, m, buf, nodes, channels, skins) for name, m in dancers.items()]
    t_in = buf.add(times, "SCALAR", bounds=True)
    doc = {
        "asset": {"version": "2.0", "generator": "dancegraph couple"},
        "scene": 0,
        "scenes": [{"nodes": groups}],
        "nodes": nodes,
        "skins": skins,
        "animations": [
            {
                "name": "dance",
                "samplers": [{"input": t_in, "output": o} for _, _, o in channels],
                "channels": [
                    {"sampler": k, "target": {"node": n, "path": p}}
                    for k, (n, p, _) in enumerate(channels)
                ],
            }
        ],
        "buffers": [{"byteLength": len(buf.blob)}],
        "bufferViews": buf.views,
        "accessors": buf.accessors,
    }
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    blob = bytes(buf.blob) + b"\0" * (-len(buf.blob) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    data = struct.pack("<III", _GLB_MAGIC, 2, total)
    data += struct.pack("<II", len(text), _JSON_CHUNK) + text
    data += struct.pack("<II", len(blob), _BIN_CHUNK) + blob
    Path(path).write_bytes(data)
    return {"dancers": len(motions), "frames": int(motions[0].n_frames), "bytes": total}
