"""glTF 2.0 in and out: a rig's joints and skinned mesh from GLB/glTF, a dance on a rig as GLB.

Reading (:func:`read_gltf_rig`): the joints are every skin's joints (their bind pose is the
inverse of the inverse-bind matrices, taken from the skin's bind space into the world: see
:func:`_skin_space`), or every node that holds no mesh when the file has no skin (bind pose: the
nodes' own transforms); the nodes above the skeleton are kept as its ancestors; the mesh is each skinned primitive's triangles with
``JOINTS_0``/``WEIGHTS_0``. glTF is metres and Y up by definition. Sparse accessors and external
buffers other than files beside a ``.gltf`` are refused (``rig_unreadable``).

Writing (:func:`write_glb`): the rig's ancestor nodes (its file's nodes above the skeleton, as
matrices), under them one node per rig joint (translation and rotation in the joint's own bind
frame, in the ancestors' units), one linear animation (every joint's rotation, the root's
translation, one key per frame) and, when the rig has a mesh, that mesh skinned to the joints,
so the character itself dances in any glTF viewer or DCC tool, standing where it stood.
"""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

from dancegraph.motion import quat

_GLB_MAGIC = 0x46546C67
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_COMPONENTS = {
    5120: np.int8,
    5121: np.uint8,
    5122: np.int16,
    5123: np.uint16,
    5125: np.uint32,
    5126: np.float32,
}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
#: Most nodes a rig file may hold.
MAX_NODES = 20_000
#: Most bytes all of a rig file's accessors may decode together.
MAX_DECODED_BYTES = 256 * 1024 * 1024


def _unreadable(path: Path, why: str):
    from dancegraph.motion.rig import RigError

    return RigError(f"{path.name}: {why}", code="rig_unreadable", field=path.name)


class _Buffers(list[bytes]):
    """A file's buffers' bytes, and how many more bytes its accessors may still decode."""

    decode_left: int = 0


def _json(text: bytes, path: Path):
    """The glTF JSON object; ``rig_too_complex`` when nested past Python's recursion limit."""
    from dancegraph.motion.rig import RigError

    try:
        doc = json.loads(text.decode("utf-8"))
    except RecursionError:
        raise RigError(
            f"{path.name}: its JSON is nested too deep", code="rig_too_complex", field=path.name
        ) from None
    except ValueError:
        raise _unreadable(path, "its JSON is not readable") from None
    if not isinstance(doc, dict):
        raise _unreadable(path, "its JSON is not an object")
    return doc


def _glb_chunks(raw: bytes, path: Path) -> tuple[dict, bytes]:
    """The JSON and BIN chunks of a GLB, each checked against the file's real length."""
    if len(raw) < 20:
        raise _unreadable(path, "truncated GLB header")
    _magic, version, length = struct.unpack_from("<III", raw, 0)
    if version != 2 or length > len(raw):
        raise _unreadable(path, f"GLB version {version} or length {length} not readable")
    offset, doc, bin_chunk = 12, None, b""
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<II", raw, offset)
        if offset + 8 + size > length:
            raise _unreadable(path, f"a chunk of {size} bytes runs past the file's end")
        chunk = raw[offset + 8 : offset + 8 + size]
        if kind == _CHUNK_JSON and doc is None:
            doc = _json(chunk, path)
        elif kind == _CHUNK_BIN and not bin_chunk:
            bin_chunk = chunk
        offset += 8 + size
    if doc is None:
        raise _unreadable(path, "no JSON chunk")
    return doc, bin_chunk


def _load(path: Path) -> tuple[dict, _Buffers]:
    """The glTF JSON and its buffers' bytes, from a GLB or a ``.gltf`` (data URIs, files beside).

    The buffers come as a list whose ``decode_left`` is :data:`MAX_DECODED_BYTES`, the most
    :func:`_accessor` decodes from them in all.
    """
    raw = path.read_bytes()
    if raw[:4] == b"glTF":
        doc, bin_chunk = _glb_chunks(raw, path)
    else:
        doc, bin_chunk = _json(raw, path), b""
    buffers = _Buffers()
    buffers.decode_left = MAX_DECODED_BYTES
    for k, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if uri is None:
            buffers.append(bin_chunk)
        elif not isinstance(uri, str):
            raise _unreadable(path, f"buffer {k} has a uri that is not text")
        elif uri.startswith("data:"):
            buffers.append(base64.b64decode(uri.split(",", 1)[1]))
        else:
            beside = (path.parent / uri).resolve()
            if beside.parent != path.parent.resolve() or not beside.is_file():
                raise _unreadable(path, f"buffer {k} refers to a file that is not beside it")
            buffers.append(beside.read_bytes())
    return doc, buffers


def _count(value, what: str, path: Path) -> int:
    """A non-negative integer of the JSON (not a bool, a float or text)."""
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise _unreadable(path, f"{what} is not a non-negative integer")
    return value


def _view(
    doc: dict, buffers: _Buffers, acc: dict, count: int, elem: int, path: Path
) -> tuple[bytes, int, int]:
    """``(buffer, first byte, byte stride)`` of an accessor's ``count`` elements of ``elem``
    bytes, once its stride is in ``[elem, 252]`` and its last element ends inside its buffer
    view, and the view inside the buffer's real bytes."""
    view = doc["bufferViews"][_count(acc["bufferView"], "a buffer view index", path)]
    data = buffers[_count(view["buffer"], "a buffer index", path)]
    view_start = _count(view.get("byteOffset", 0), "a byteOffset", path)
    view_end = view_start + _count(view["byteLength"], "a byteLength", path)
    start = view_start + _count(acc.get("byteOffset", 0), "a byteOffset", path)
    stride = view.get("byteStride", elem)
    if not isinstance(stride, int) or isinstance(stride, bool) or not elem <= stride <= 252:
        raise _unreadable(path, f"a byteStride is not in [{elem}, 252]")
    need = start + stride * (count - 1) + elem if count else start
    if view_end > len(data) or need > view_end:
        raise _unreadable(path, "an accessor runs past its buffer view or buffer")
    return data, start, stride


def _accessor(doc: dict, buffers: _Buffers, k: int, path: Path) -> np.ndarray:
    """Accessor ``k`` as a ``(count, width)`` array. Its byte stride, offsets and count are
    checked against its buffer view and the buffer's real size, and its size against what the
    file may still decode (``buffers.decode_left``), before anything is allocated."""
    from dancegraph.motion.rig import RigError

    acc = doc["accessors"][_count(k, "an accessor index", path)]
    if "sparse" in acc:
        raise _unreadable(path, f"accessor {k} is sparse (not supported)")
    dtype = np.dtype(_COMPONENTS[acc["componentType"]])
    width = _WIDTH[acc["type"]]
    count = _count(acc["count"], f"accessor {k}'s count", path)
    elem = dtype.itemsize * width
    view = _view(doc, buffers, acc, count, elem, path) if "bufferView" in acc else None
    if count * elem > buffers.decode_left:
        raise RigError(
            f"{path.name}: accessor {k} would decode {count * elem} bytes, more than the "
            f"{MAX_DECODED_BYTES} a rig file may",
            code="rig_too_complex",
            field=path.name,
        )
    buffers.decode_left -= count * elem
    if view is None:
        return np.zeros((count, width), dtype=dtype)
    data, start, stride = view
    rows = np.lib.stride_tricks.as_strided(
        np.frombuffer(data, dtype=np.uint8, count=len(data) - start, offset=start),
        shape=(count, elem),
        strides=(stride, 1),
        writeable=False,
    )
    out = np.ascontiguousarray(rows).view(dtype).reshape(count, width)
    if acc.get("normalized") and dtype.kind in "iu":
        out = out.astype(float) / np.iinfo(dtype.str).max
    return out


def _local_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=float).reshape(4, 4).T  # column-major
    from scipy.spatial.transform import Rotation

    m = np.eye(4)
    r = Rotation.from_quat(node.get("rotation", [0, 0, 0, 1])).as_matrix()
    m[:3, :3] = r * np.asarray(node.get("scale", [1, 1, 1]), dtype=float)[None, :]
    m[:3, 3] = node.get("translation", [0, 0, 0])
    return m


def _node_parents(nodes, path: Path) -> dict[int, int]:
    """Each child node's parent. Refuses (before any walk) a node list past :data:`MAX_NODES`,
    a child index out of range, a node with two parents, a cycle and a nesting deeper than
    ``bvh.MAX_DEPTH``; the walk is iterative."""
    from dancegraph.motion.bvh import MAX_DEPTH
    from dancegraph.motion.rig import RigError

    if not isinstance(nodes, list):
        raise _unreadable(path, "nodes is not a list")
    if len(nodes) > MAX_NODES:
        raise RigError(
            f"{path.name}: more than {MAX_NODES} nodes", code="rig_too_complex", field=path.name
        )
    parent_of: dict[int, int] = {}
    for i, n in enumerate(nodes):
        for c in n.get("children", []):
            if not isinstance(c, int) or isinstance(c, bool) or not 0 <= c < len(nodes):
                raise _unreadable(path, f"node {i} has a child that is not a node index")
            if c in parent_of or c == i:
                raise _unreadable(path, f"node {c} has two parents or is its own child")
            parent_of[c] = i
    depth: dict[int, int] = {}
    for i in range(len(nodes)):
        chain, a = [], i
        while a not in depth and a in parent_of:
            chain.append(a)
            a = parent_of[a]
            if len(chain) > len(nodes):
                raise _unreadable(path, f"the nodes above node {i} form a cycle")
        base = depth.get(a, 0)
        for k, j in enumerate(reversed(chain), start=1):
            depth[j] = base + k
        if base + len(chain) > MAX_DEPTH:
            raise RigError(
                f"{path.name}: nodes nested more than {MAX_DEPTH} deep",
                code="rig_too_complex",
                field=path.name,
            )
    return parent_of


def _check_skins(skins, n_nodes: int, path: Path) -> None:
    """Each skin names at most ``bvh.MAX_JOINTS`` distinct nodes that exist."""
    from dancegraph.motion.bvh import MAX_JOINTS
    from dancegraph.motion.rig import RigError

    for s, skin in enumerate(skins):
        joints = skin["joints"]
        if len(joints) > MAX_JOINTS:
            raise RigError(
                f"{path.name}: skin {s} has more than {MAX_JOINTS} joints",
                code="rig_too_complex",
                field=path.name,
            )
        if any(
            not isinstance(j, int) or isinstance(j, bool) or not 0 <= j < n_nodes for j in joints
        ):
            raise _unreadable(path, f"skin {s} names a joint that is not a node index")
        if len(set(joints)) != len(joints):
            raise _unreadable(path, f"skin {s} names a joint twice")


def read_gltf_rig(path: str | Path):
    """``(names, parents (J,), bind (J, 4, 4), RigMesh | None, ancestors)`` of a GLB/glTF file.

    Bind matrices and mesh are in the file's world (metres, Y up), parent nodes applied.
    ``ancestors``: per top joint's name, the nodes above it from the scene root down, as
    ``[(name, local (4, 4))]`` (how the skeleton is placed in the scene).
    """
    from dancegraph.motion.rig import RigMesh

    path = Path(path)
    try:
        doc, buffers = _load(path)
        nodes = doc.get("nodes", [])
        parent_of = _node_parents(nodes, path)
        _check_skins(doc.get("skins", []), len(nodes), path)
        world: dict[int, np.ndarray] = {}

        def world_of(i: int) -> np.ndarray:
            if i not in world:
                p = parent_of.get(i)
                local = _local_matrix(nodes[i])
                world[i] = local if p is None else world_of(p) @ local
            return world[i]

        skins = doc.get("skins", [])
        bind: dict[int, np.ndarray] = {}
        spaces = []  # per skin: its bind space (inverse-bind matrices, vertices) → world
        for skin in skins:
            ibm = None
            space = np.eye(4)
            if "inverseBindMatrices" in skin:
                ibm = _accessor(doc, buffers, skin["inverseBindMatrices"], path).astype(float)
                ibm = ibm.reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
                space = _skin_space(np.stack([world_of(j) for j in skin["joints"]]), ibm)
            spaces.append(space)
            for k, j in enumerate(skin["joints"]):
                if j in bind:
                    continue
                if ibm is not None:
                    bind[j] = space @ np.linalg.inv(ibm[k])
                else:
                    bind[j] = world_of(j)
        if skins:
            joint_nodes = sorted(bind)
        else:
            joint_nodes = [i for i, n in enumerate(nodes) if "mesh" not in n and "camera" not in n]
            bind = {i: world_of(i) for i in joint_nodes}
        index = {j: k for k, j in enumerate(joint_nodes)}
        parents = []
        for j in joint_nodes:
            p = parent_of.get(j)
            while p is not None and p not in index:
                p = parent_of.get(p)
            parents.append(-1 if p is None else index[p])
        names = [nodes[j].get("name") or f"joint_{j}" for j in joint_nodes]
        tops = [j for j, p in zip(joint_nodes, parents, strict=True) if p < 0]
        ancestors = {
            nodes[j].get("name") or f"joint_{j}": _chain(nodes, parent_of, j) for j in tops
        }
        mats = np.stack([bind[j] for j in joint_nodes]) if joint_nodes else np.zeros((0, 4, 4))

        pos_all, tri_all, jnt_all, wgt_all, base = [], [], [], [], 0
        for node in nodes:
            if "mesh" not in node or "skin" not in node:
                continue
            skin_joints = skins[node["skin"]]["joints"]
            for prim in doc["meshes"][node["mesh"]].get("primitives", []):
                attrs = prim.get("attributes", {})
                if prim.get("mode", 4) != 4 or "JOINTS_0" not in attrs or "WEIGHTS_0" not in attrs:
                    continue
                pos = _accessor(doc, buffers, attrs["POSITION"], path).astype(float)
                space = spaces[node["skin"]]
                pos = pos @ space[:3, :3].T + space[:3, 3]
                if "indices" in prim:
                    idx = _accessor(doc, buffers, prim["indices"], path).astype(np.int64).ravel()
                else:
                    idx = np.arange(len(pos))
                jts = _accessor(doc, buffers, attrs["JOINTS_0"], path).astype(np.int64)
                wts = _accessor(doc, buffers, attrs["WEIGHTS_0"], path).astype(float)
                _check_primitive(pos, idx, jts, wts, path)
                lookup = np.array([index[j] for j in skin_joints])
                pos_all.append(pos)
                tri_all.append(idx.reshape(-1, 3) + base)
                jnt_all.append(lookup[np.clip(jts, 0, len(lookup) - 1)])
                wgt_all.append(wts / np.maximum(wts.sum(axis=1, keepdims=True), 1e-12))
                base += len(pos)
    except (
        KeyError,
        IndexError,
        TypeError,
        ValueError,
        AttributeError,
        np.linalg.LinAlgError,
    ) as exc:
        raise _unreadable(
            path, f"malformed glTF ({type(exc).__name__}: {str(exc)[:100]})"
        ) from None
    mesh = None
    if pos_all:
        mesh = RigMesh(
            positions=np.concatenate(pos_all),
            triangles=np.concatenate(tri_all),
            joints=np.concatenate(jnt_all),
            weights=np.concatenate(wgt_all),
        )
    return names, np.array(parents, dtype=np.int64), mats, mesh, ancestors


def _chain(nodes: list, parent_of: dict[int, int], j: int) -> list[tuple[str, np.ndarray]]:
    """The nodes above node ``j``, from the scene's root down: ``[(name, local (4, 4))]``."""
    chain, a = [], parent_of.get(j)
    while a is not None:
        chain.append((nodes[a].get("name") or f"node_{a}", _local_matrix(nodes[a])))
        a = parent_of.get(a)
    return chain[::-1]


def node_worlds(path: str | Path) -> dict[str, np.ndarray]:
    """Every named node's world matrix ``(4, 4)`` as the file places it (its static transforms:
    in a GLB written by :func:`write_glb`, the dance's first frame). Raises ``RigError``
    (``rig_unreadable``)."""
    path = Path(path)
    try:
        doc, _ = _load(path)
        nodes = doc.get("nodes", [])
        out: dict[str, np.ndarray] = {}
        stack = [(i, np.eye(4)) for i in doc["scenes"][doc.get("scene", 0)]["nodes"]]
        while stack:
            i, above = stack.pop()
            world = above @ _local_matrix(nodes[i])
            out.setdefault(nodes[i].get("name") or f"node_{i}", world)
            stack.extend((c, world) for c in nodes[i].get("children", []))
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise _unreadable(path, f"malformed glTF ({type(exc).__name__}: {exc})") from None
    return out


def _skin_space(worlds: np.ndarray, ibm: np.ndarray) -> np.ndarray:
    """The ``(4, 4)`` matrix taking a skin's bind space to the world.

    glTF skins a vertex by ``world(joint) · ibm · v``, so the inverse-bind matrices and the
    vertices may live in the world (``ibm`` = inverse world bind) or in an armature's own space
    (a centimetre, Z-up export under a scaled, turned node). At the bind pose every joint gives
    the same ``world · ibm``; the matrix most joints agree on wins (the identity on a tie, so a
    file saved in another pose keeps reading its bind pose from ``ibm`` alone).
    ``worlds``, ``ibm``: ``(J, 4, 4)``.
    """
    cands = worlds @ ibm
    options = np.concatenate([np.eye(4)[None], cands])
    size = np.maximum(1.0, np.abs(cands).max(axis=(1, 2)))
    diff = np.abs(options[:, None] - cands[None]).max(axis=(2, 3))  # (1 + J, J)
    votes = (diff <= 1e-4 * size[None]).sum(axis=1)
    return options[int(np.argmax(votes))]


def _check_primitive(pos, idx, jts, wts, path: Path) -> None:
    """A skinned primitive whose attributes agree: one joint and weight row per finite vertex,
    whole triangles, every index a vertex."""
    if not (len(jts) == len(wts) == len(pos)) or len(idx) % 3:
        raise _unreadable(path, "a skinned primitive's attributes disagree in length")
    if idx.size and (idx.min() < 0 or idx.max() >= len(pos)):
        raise _unreadable(path, "a triangle names a vertex that is not there")
    if not (np.isfinite(pos).all() and np.isfinite(wts).all()):
        raise _unreadable(path, "a skinned mesh holds NaN or infinite values")


class _Builder:
    """Accumulates one binary buffer, its views and accessors."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(
        self, array: np.ndarray, kind: str, target: int | None = None, minmax: bool = False
    ) -> int:
        array = np.ascontiguousarray(array)
        comp = {np.dtype(v): k for k, v in _COMPONENTS.items()}[array.dtype]
        while len(self.blob) % 4:
            self.blob.append(0)
        view = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": array.nbytes}
        if target is not None:
            view["target"] = target
        self.blob.extend(array.tobytes())
        self.views.append(view)
        acc = {
            "bufferView": len(self.views) - 1,
            "componentType": comp,
            "count": int(array.shape[0]),
            "type": {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}[
                int(np.prod(array.shape[1:])) if array.ndim > 1 else 1
            ],
        }
        if minmax:
            flat = array.reshape(array.shape[0], -1)
            acc["min"] = flat.min(axis=0).tolist()
            acc["max"] = flat.max(axis=0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _vertex_normals(pos: np.ndarray, tris: np.ndarray) -> np.ndarray:
    n = np.zeros_like(pos)
    face = np.cross(pos[tris[:, 1]] - pos[tris[:, 0]], pos[tris[:, 2]] - pos[tris[:, 0]])
    for k in range(3):
        np.add.at(n, tris[:, k], face)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 1e-12, n / np.maximum(length, 1e-12), [0.0, 1.0, 0.0])
    return n


def joint_locals(motion, rig) -> tuple[np.ndarray, np.ndarray, float]:
    """A dance on a rig as its file's nodes carry it, under ``rig.ancestors``.

    ``motion``: on ``rig.skeleton`` (BVH convention, metres, the rig's world). Returns local
    rotations ``(F, J, 4)`` of each joint's own bind frame (sign-continuous), local translations
    ``(F, J, 3)`` in the ancestors' units (the root's moves, the others are their bind offsets)
    and the ancestors' scale (metres per unit; they are assumed uniformly scaled). Shared by the
    GLB and USD writers.
    """
    sk = rig.skeleton
    rest = quat.normalize(np.asarray(rig.rest_rotations, dtype=float))
    top, top_q, sigma = _placement(rig)
    parents = sk.parents
    nonroot = parents >= 0
    # world frame G_j · R_j with G_j = G_parent · q_j, so the local one is R_parent⁻¹ · q_j · R_j
    # (the root's parent: the ancestors' turn): no forward kinematics needed
    above = np.where(nonroot[:, None], rest[np.maximum(parents, 0)], top_q[None])
    local = quat.multiply(quat.multiply(quat.conjugate(above)[None], motion.rotations), rest[None])
    local = _continuous(quat.normalize(local))
    moves = np.zeros((motion.n_frames, sk.n_joints, 3))
    moves[:, nonroot] = quat.rotate(quat.conjugate(rest[parents[nonroot]]), sk.offsets[nonroot])
    moves[:, 0] = _rotate_all(quat.conjugate(top_q), motion.root_positions - top[:3, 3])
    return local, moves / sigma, sigma


def write_glb(motion, rig, path: str | Path) -> dict:
    """Write ``motion`` (on ``rig.skeleton``, BVH convention, metres) as a GLB on the rig.

    The skeleton hangs from ``rig.ancestors`` (assumed uniformly scaled): its translations are
    in their units. Returns ``{frames, joints, vertices, bytes}``. Written atomically
    (temporary file, rename).
    """
    sk = rig.skeleton
    n_joints = sk.n_joints
    parents = sk.parents
    rest = quat.normalize(np.asarray(rig.rest_rotations, dtype=float))
    local, moves, sigma = joint_locals(motion, rig)
    translation, root_path = moves[0], moves[:, 0]
    b = _Builder()
    n_up = len(rig.ancestors)
    nodes = [
        {"name": name, "matrix": np.asarray(m, dtype=float).T.ravel().tolist(), "children": [k + 1]}
        for k, (name, m) in enumerate(rig.ancestors)
    ]
    for j in range(n_joints):
        node = {
            "name": sk.names[j],
            "translation": (translation[j] if j else root_path[0]).tolist(),
            "rotation": local[0, j].tolist(),
        }
        kids = sk.children(j)
        if kids:
            node["children"] = [n_up + c for c in kids]
        nodes.append(node)
    times = (np.arange(motion.n_frames) / motion.fps).astype(np.float32)
    t_acc = b.add(times[:, None], "SCALAR", minmax=True)
    samplers, channels = [], []
    for j in range(n_joints):
        out = b.add(local[:, j].astype(np.float32), "VEC4")
        samplers.append({"input": t_acc, "output": out, "interpolation": "LINEAR"})
        target = {"node": n_up + j, "path": "rotation"}
        channels.append({"sampler": len(samplers) - 1, "target": target})
    out = b.add(root_path.astype(np.float32), "VEC3")
    samplers.append({"input": t_acc, "output": out, "interpolation": "LINEAR"})
    target = {"node": n_up, "path": "translation"}
    channels.append({"sampler": len(samplers) - 1, "target": target})
    doc: dict = {
        "asset": {"version": "2.0", "generator": "DanceGraph"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": nodes,
        "animations": [{"name": "dance", "samplers": samplers, "channels": channels}],
    }
    n_vertices = 0
    if rig.mesh is not None and rig.mesh.n_vertices:
        mesh = rig.mesh
        n_vertices = mesh.n_vertices
        bind = np.tile(np.eye(4), (n_joints, 1, 1))
        from scipy.spatial.transform import Rotation

        bind[:, :3, :3] = Rotation.from_quat(rest).as_matrix() * sigma
        pos = np.zeros((n_joints, 3))
        for j in range(n_joints):
            pos[j] = sk.offsets[j] if parents[j] < 0 else pos[parents[j]] + sk.offsets[j]
        bind[:, :3, 3] = pos
        ibm = np.linalg.inv(bind).transpose(0, 2, 1).reshape(n_joints, 16)  # column-major
        attrs = {
            "POSITION": b.add(mesh.positions.astype(np.float32), "VEC3", 34962, minmax=True),
            "NORMAL": b.add(
                _vertex_normals(mesh.positions, mesh.triangles).astype(np.float32), "VEC3", 34962
            ),
            "JOINTS_0": b.add(mesh.joints.astype(np.uint16), "VEC4", 34962),
            "WEIGHTS_0": b.add(mesh.weights.astype(np.float32), "VEC4", 34962),
        }
        indices = b.add(mesh.triangles.astype(np.uint32).reshape(-1, 1), "SCALAR", 34963)
        doc["meshes"] = [
            {"name": "body", "primitives": [{"attributes": attrs, "indices": indices}]}
        ]
        doc["skins"] = [
            {
                "joints": list(range(n_up, n_up + n_joints)),
                "skeleton": n_up,
                "inverseBindMatrices": b.add(ibm.astype(np.float32), "MAT4"),
            }
        ]
        nodes.append({"name": "body", "mesh": 0, "skin": 0})
        doc["scenes"][0]["nodes"].append(len(nodes) - 1)
    while len(b.blob) % 4:
        b.blob.append(0)
    doc["buffers"] = [{"byteLength": len(b.blob)}]
    doc["bufferViews"] = b.views
    doc["accessors"] = b.accessors
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(b.blob)
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(struct.pack("<III", _GLB_MAGIC, 2, total))
        fh.write(struct.pack("<II", len(text), _CHUNK_JSON))
        fh.write(text)
        fh.write(struct.pack("<II", len(b.blob), _CHUNK_BIN))
        fh.write(bytes(b.blob))
    tmp.replace(path)
    return {"frames": motion.n_frames, "joints": n_joints, "vertices": n_vertices, "bytes": total}


def _placement(rig) -> tuple[np.ndarray, np.ndarray, float]:
    """The skeleton's parent in the world: its ``(4, 4)`` matrix, rotation ``(4,)`` and scale."""
    from scipy.spatial.transform import Rotation

    top = rig.ancestors_world()
    sigma = float(np.cbrt(abs(np.linalg.det(top[:3, :3])))) or 1.0
    return top, Rotation.from_matrix(top[:3, :3] / sigma).as_quat(), sigma


def _rotate_all(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    return quat.rotate(np.broadcast_to(q, v.shape[:-1] + (4,)), v)


def _continuous(q: np.ndarray) -> np.ndarray:
    """``(F, J, 4)`` with each frame's sign chosen nearest to the previous frame (no flips)."""
    out = q.copy()
    dots = np.sum(out[1:] * out[:-1], axis=-1)
    flips = np.cumsum(dots < 0, axis=0) % 2  # flips accumulate along time
    out[1:][flips.astype(bool)] *= -1.0
    return out
