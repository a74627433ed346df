"""A seeded mutation fuzz of the rig readers: thousands of files, each a valid generated rig
(GLB, BVH) with a few things changed, must each end in a valid rig within the readers' limits
or a coded ``RigError`` (HTTP 4xx), never another exception, a crash or a hang."""

from __future__ import annotations

import json
import random
from pathlib import Path

import numpy as np
import pytest

from dancegraph.motion.bvh import MAX_JOINTS
from dancegraph.motion.rig import RigError, load_rig, name_problem, rig_summary
from dancegraph.sandbox import SandboxError, run_sandboxed
from tests.motion.hostile_rigs import glb_bytes, glb_parts, valid_bvh, valid_glb

pytestmark = pytest.mark.timeout(300)

N_GLB = 1500
N_BVH = 2000
N_SANDBOXED = 12

_HOSTILE_VALUES = [
    -1,
    0,
    1,
    3,
    2**31,
    -(2**31),
    10**12,
    1.5,
    float("-0"),
    "x",
    None,
    True,
    [],
    {},
    [0, 0, 0],
    [1, 2, 3, 4],
    "hip\0",
    "\ud800",
    "a" * 300,
    "data:application/octet-stream;base64,AAAA",
    "../../etc/passwd",
]
_HOSTILE_TOKENS = [
    "{",
    "}",
    "JOINT",
    "End",
    "Site",
    "ROOT",
    "OFFSET",
    "CHANNELS",
    "MOTION",
    "Xrotation",
    "Xposition",
    "nan",
    "1e999",
    "-0",
    "99999999999",
    "\0",
    "²",
    "Frames:",
    "",
]


def _paths(doc, rng: random.Random) -> tuple[dict | list, object]:
    """A random container in the JSON and one of its keys or indices (None: it is empty)."""
    node = doc
    while True:
        keys = list(node) if isinstance(node, dict) else list(range(len(node)))
        if not keys:
            return node, None
        key = rng.choice(keys)
        child = node[key]
        if isinstance(child, (dict, list)) and child and rng.random() < 0.7:
            node = child
            continue
        return node, key


def mutate_glb(raw: bytes, rng: random.Random) -> bytes:
    """A GLB with one to three of: a JSON value replaced or removed, a node made another's
    child, bytes flipped, the file truncated."""
    doc, blob = glb_parts(raw)
    for _ in range(rng.randint(1, 3)):
        kind = rng.random()
        container, key = _paths(doc, rng)
        if kind < 0.55 and key is not None:
            container[key] = rng.choice(_HOSTILE_VALUES)  # type: ignore[index]
        elif kind < 0.7 and key is not None and isinstance(container, dict):
            container.pop(key)
        elif kind < 0.85 and isinstance(doc.get("nodes"), list) and doc["nodes"]:
            nodes = doc["nodes"]
            a, b = rng.randrange(len(nodes)), rng.randrange(len(nodes))
            if isinstance(nodes[a], dict) and isinstance(nodes[a].get("children", []), list):
                nodes[a].setdefault("children", []).append(b)
        else:
            blob = bytearray(blob)
            for _ in range(rng.randint(1, 16)):
                if blob:
                    blob[rng.randrange(len(blob))] = rng.randrange(256)
            blob = bytes(blob)
    out = glb_bytes(json.dumps(doc, ensure_ascii=True).encode(), blob)
    if rng.random() < 0.1:
        out = out[: rng.randrange(len(out))]
    return out


def mutate_bvh(raw: bytes, rng: random.Random) -> bytes:
    """A BVH with one to four of: a token replaced, a line deleted, doubled or moved, bytes
    flipped."""
    lines = raw.decode().split("\n")
    for _ in range(rng.randint(1, 4)):
        kind = rng.random()
        i = rng.randrange(len(lines))
        if kind < 0.5:
            toks = lines[i].split(" ") or [""]
            toks[rng.randrange(len(toks))] = rng.choice(_HOSTILE_TOKENS)
            lines[i] = " ".join(toks)
        elif kind < 0.65:
            del lines[i]
        elif kind < 0.8:
            lines.insert(i, lines[rng.randrange(len(lines))])
        else:
            j = rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        if not lines:
            lines = [""]
    out = bytearray("\n".join(lines).encode("utf-8", "surrogatepass"))
    if rng.random() < 0.15 and out:
        out[rng.randrange(len(out))] = rng.randrange(256)
    return bytes(out)


def _outcome(path: Path) -> str:
    """``rig`` (a valid rig within the limits), ``refused`` (a coded 4xx ``RigError`` naming
    no server path), else what broke."""
    try:
        rig = load_rig(path)
    except RigError as exc:
        server_path = str(path.parent) in exc.message
        if exc.code.startswith("rig_") and 400 <= exc.status < 500 and not server_path:
            return "refused"
        return f"RigError {exc.code} {exc.message[:80]!r}"
    except Exception as exc:  # noqa: BLE001 - the fuzz's finding
        return f"{type(exc).__name__}: {str(exc)[:80]}"
    sk = rig.skeleton
    if sk.n_joints > MAX_JOINTS or any(name_problem(n) for n in sk.names):
        return "a rig past the limits"
    ends = [np.asarray(v) for v in sk.end_sites.values()]
    ends += [np.asarray(m) for _, m in rig.ancestors]
    if not all(np.isfinite(a).all() for a in [sk.offsets, rig.rest_rotations, *ends]):
        return "a rig with non-finite offsets or rotations"
    if not np.isfinite(rig.floor) or not np.isfinite(rig.height()):
        return "a rig with a non-finite floor or height"
    return "rig"


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("fuzz")
    return {
        "glb": valid_glb(out / "seed.glb").read_bytes(),
        "bvh": valid_bvh(out / "seed.bvh").read_bytes(),
    }


@pytest.mark.parametrize("fmt,count", [("glb", N_GLB), ("bvh", N_BVH)])
def test_mutated_rigs_end_in_a_rig_or_a_coded_4xx(seeds, tmp_path, fmt, count):
    mutate = mutate_glb if fmt == "glb" else mutate_bvh
    path = tmp_path / f"mutant.{fmt}"
    found, outcomes = [], {"rig": 0, "refused": 0}
    for seed in range(count):
        path.write_bytes(mutate(seeds[fmt], random.Random(seed)))
        what = _outcome(path)
        if what in outcomes:
            outcomes[what] += 1
        else:
            found.append((seed, what))
    assert not found, f"{len(found)} of {count} mutants broke the reader: {found[:5]}"
    assert min(outcomes.values()) > 0, outcomes  # the mutants reach both outcomes


def test_mutants_through_the_sandbox(seeds, tmp_path):
    """A few mutants through ``run_sandboxed``: a summary or the same ``RigError``, no crash."""
    for seed in range(N_SANDBOXED):
        fmt = ("glb", "bvh")[seed % 2]
        mutate = mutate_glb if fmt == "glb" else mutate_bvh
        path = tmp_path / f"mutant{seed}.{fmt}"
        path.write_bytes(mutate(seeds[fmt], random.Random(10_000 + seed)))
        try:
            out = run_sandboxed(rig_summary, str(path))
            assert out["joints"] <= MAX_JOINTS
        except RigError as exc:
            assert exc.status == 422 and exc.code.startswith("rig_")
        except SandboxError as exc:
            pytest.fail(f"seed {10_000 + seed}: the reader {exc.code} in the sandbox")
