"""Read an FBX rig with ufbx in a sandboxed child process: joints, bind pose and skinned mesh.

The ufbx Python binding (0.0.5) can crash on temporary objects, so the caller never imports it:
:func:`read_fbx_rig` runs the reader in a ``dancegraph.sandbox`` child (inline when the caller
already is one, as a rig upload's parse is) and gets its arrays back; a crash, a limit or a
broken file becomes ``RigError`` (``rig_unreadable``). ufbx converts the file to metres, Y up,
right-handed.

Joints are the file's bone nodes (``LimbNode``) and every node a skin cluster binds to. A joint's
bind matrix is its skin cluster's bind matrix where it has one, else its parent joint's bind
matrix times its own transform relative to that parent (so bones without skin, such as end
bones, follow their parent into the bind pose even when the file was saved in another pose).
The mesh is every skinned mesh, merged and triangulated (fans), with each vertex's four largest
weights renormalised.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dancegraph.sandbox import SandboxError, SandboxLimits, run_sandboxed

#: The reader's own limits when it is not already inside a sandboxed parse.
READ_LIMITS = SandboxLimits(memory_bytes=4 * 1024**3, cpu_seconds=120.0, wall_seconds=120.0)

# Every ufbx object a child took: the binding crashes when a scene is freed before the objects
# taken from it, so nothing here is freed before the child exits (it never runs a finaliser).
_ALIVE: list = []


def read_fbx_rig(path: str | Path):
    """``(names, parents (J,), bind (J, 4, 4), RigMesh | None, ancestors)`` of an FBX file
    (metres, Y up). ``ancestors``: per top joint's name, the nodes above it from the top down,
    as ``[(name, node-to-parent (4, 4))]``; the top one carries the unit and axis conversion."""
    from dancegraph.motion.rig import RigError, RigMesh

    path = Path(path)
    try:
        data = run_sandboxed(_read_arrays, str(path), limits=READ_LIMITS)
    except SandboxError as exc:
        raise RigError(
            f"{path.name}: not a readable FBX file ({exc.message})",
            code="rig_unreadable",
            field=path.name,
        ) from None
    names = [str(n) for n in data["names"]]
    mesh = None
    if "mesh_positions" in data and len(data["mesh_positions"]):
        mesh = RigMesh(
            positions=data["mesh_positions"],
            triangles=data["mesh_triangles"],
            joints=data["mesh_joints"],
            weights=data["mesh_weights"],
            normals=None,
        )
    ancestors: dict[str, list] = {}
    if "anc_joint" in data:
        for joint, name, local in zip(
            data["anc_joint"], data["anc_name"], data["anc_local"], strict=True
        ):
            ancestors.setdefault(str(joint), []).append((str(name), local))
    return names, data["parents"], data["bind"], mesh, ancestors


def _read_arrays(path: str) -> dict[str, np.ndarray]:  # pragma: no cover - in the child
    """The rig's arrays (:func:`_read`); ufbx's own failure as ``RigError`` naming the file
    only."""
    from dancegraph.motion.rig import RigError

    name = Path(path).name
    try:
        return _read(path, _ALIVE)
    except Exception as exc:  # noqa: BLE001 - ufbx raises its own error types
        why = str(exc).replace(path, name).replace(str(Path(path).parent), "")[:200]
        raise RigError(
            f"{name}: not a readable FBX file ({why})", code="rig_unreadable", field=name
        ) from None


def _matrix(m) -> np.ndarray:
    out = np.eye(4)
    for k, col in enumerate((m.c0, m.c1, m.c2, m.c3)):
        out[:3, k] = (col.x, col.y, col.z)
    return out


def _read(path: str, keep: list) -> dict[str, np.ndarray]:  # pragma: no cover - in the child
    """The rig's arrays. Every ufbx object is appended to ``keep``: the binding crashes when a
    scene is freed before the objects taken from it, so nothing is freed before the child exits."""
    import ufbx

    scene = ufbx.load_file(
        path,
        target_axes=ufbx.axes_right_handed_y_up,
        target_unit_meters=1.0,
        space_conversion=ufbx.SpaceConversion.ADJUST_TRANSFORMS,
    )
    nodes_list = scene.nodes
    nodes = [nodes_list[i] for i in range(len(nodes_list))]
    meshes_list = scene.meshes
    meshes = [meshes_list[i] for i in range(len(meshes_list))]
    keep.extend([scene, nodes_list, nodes, meshes_list, meshes])
    bind: dict[int, np.ndarray] = {}
    skinned: set[int] = set()
    skins = []
    for mesh in meshes:
        deformers = mesh.skin_deformers
        if len(deformers) == 0:
            continue
        skin = deformers[0]
        clusters_list = skin.clusters
        clusters = [clusters_list[i] for i in range(len(clusters_list))]
        for c in clusters:
            bone = c.bone_node
            if bone is not None:
                bind.setdefault(bone.typed_id, _matrix(c.bind_to_world))
                skinned.add(bone.typed_id)
        skins.append((mesh, skin, clusters))
        keep.extend([deformers, skin, clusters_list, clusters])
    joints = [n for n in nodes if n.bone is not None or n.typed_id in skinned]
    index = {n.typed_id: k for k, n in enumerate(joints)}
    parents = []
    for n in joints:
        p = n.parent
        keep.append(p)
        while p is not None and p.typed_id not in index:
            p = p.parent
            keep.append(p)
        parents.append(-1 if p is None else index[p.typed_id])
    # a joint without a bind matrix keeps its place relative to its parent joint's bind
    mats: dict[int, np.ndarray] = {}

    def bind_of(k: int) -> np.ndarray:
        if k not in mats:
            n = joints[k]
            if n.typed_id in bind:
                mats[k] = bind[n.typed_id]
            elif parents[k] >= 0:
                parent = joints[parents[k]]
                rel = np.linalg.inv(_matrix(parent.node_to_world)) @ _matrix(n.node_to_world)
                mats[k] = bind_of(parents[k]) @ rel
            else:
                mats[k] = _matrix(n.node_to_world)
        return mats[k]

    binds = np.stack([bind_of(k) for k in range(len(joints))]) if joints else np.zeros((0, 4, 4))
    out: dict[str, np.ndarray] = {
        "names": np.array([n.name for n in joints], dtype=str),
        "parents": np.array(parents, dtype=np.int64),
        "bind": binds,
        **_ancestors(joints, parents, keep),
    }
    pos_all, tri_all, jnt_all, wgt_all = [], [], [], []
    base = 0
    for mesh, skin, clusters in skins:
        instances = mesh.instances
        node = instances[0] if len(instances) else None
        to_world = (
            _matrix(clusters[0].geometry_to_world)
            if clusters
            else (_matrix(node.geometry_to_world) if node is not None else np.eye(4))
        )
        verts_list = mesh.vertices
        verts = np.array([(v.x, v.y, v.z) for v in verts_list], dtype=float).reshape(-1, 3)
        verts = verts @ to_world[:3, :3].T + to_world[:3, 3]
        vi = mesh.vertex_indices
        vidx = np.array([vi[i] for i in range(len(vi))], dtype=np.int64)
        faces_list = mesh.faces
        tris = []
        for f in (faces_list[i] for i in range(len(faces_list))):
            first, count = f.index_begin, f.num_indices
            for k in range(1, count - 1):
                tris.append((vidx[first], vidx[first + k], vidx[first + k + 1]))
        sv, sw = skin.vertices, skin.weights
        joints_v = np.zeros((len(verts), 4), dtype=np.int64)
        weights_v = np.zeros((len(verts), 4))
        bones = [c.bone_node for c in clusters]
        keep.extend([instances, verts_list, vi, faces_list, sv, sw, bones])
        cluster_joint = [index.get(b.typed_id, 0) if b is not None else 0 for b in bones]
        for v in range(min(len(verts), len(sv))):
            rec = sv[v]
            ws = sorted(
                (
                    (sw[rec.weight_begin + k].weight, sw[rec.weight_begin + k].cluster_index)
                    for k in range(rec.num_weights)
                ),
                reverse=True,
            )[:4]
            total = sum(w for w, _ in ws) or 1.0
            for k, (w, c) in enumerate(ws):
                joints_v[v, k] = cluster_joint[c]
                weights_v[v, k] = w / total
        pos_all.append(verts)
        tri_all.append(np.array(tris, dtype=np.int64).reshape(-1, 3) + base)
        jnt_all.append(joints_v)
        wgt_all.append(weights_v)
        base += len(verts)
    if pos_all:
        out["mesh_positions"] = np.concatenate(pos_all)
        out["mesh_triangles"] = np.concatenate(tri_all)
        out["mesh_joints"] = np.concatenate(jnt_all)
        out["mesh_weights"] = np.concatenate(wgt_all)
    return out


def _ancestors(joints: list, parents: list[int], keep: list) -> dict[str, np.ndarray]:
    """The nodes above each top joint, top first: ``anc_joint``, ``anc_name``, ``anc_local``
    (``(K, 4, 4)`` node-to-parent matrices; the top node's carries the unit and axis change)."""
    rows: list[tuple[str, str, np.ndarray]] = []
    for n, p in zip(joints, parents, strict=True):
        if p >= 0:
            continue
        chain, a = [], n.parent
        while a is not None and not a.is_root:
            keep.append(a)
            chain.append((n.name, a.name, _matrix(a.node_to_parent)))
            a = a.parent
        rows.extend(chain[::-1])
    return {
        "anc_joint": np.array([r[0] for r in rows], dtype=str),
        "anc_name": np.array([r[1] for r in rows], dtype=str),
        "anc_local": np.array([r[2] for r in rows], dtype=float).reshape(-1, 4, 4),
    }
