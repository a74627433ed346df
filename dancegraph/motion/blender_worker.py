"""FBX writing inside Blender (runs ONLY under Blender's Python, never imported by dancegraph).

This script is the child process behind ``dancegraph.motion.fbx.FbxExporter``. It imports only
``bpy``, numpy (Blender's own) and the standard library, because it runs in its own virtual
environment (``bpy`` 5.0.1 is GPL and pins numpy<2; the service code stays apart from it).

Protocol: JSON lines. The parent writes one request per line on stdin; the worker answers one
line per request on its protocol channel (the original stdout; everything Blender itself prints
is sent to stderr so it can never corrupt the protocol). The first line the worker writes is
``{"ready": true, "blender": "5.0.1"}``.

Requests:
- ``{"id": 4, "op": "animate_rig", "rig": RIG, "anim": NPZ, "fbx": OUT}`` → ``{"id": 4, "ok": true,
  "frames": F, "fps": 30.0, "joints": J, "meshes": M, "first_frame": {bone: [x, y, z]},
  "seconds": 1.2}``: a rig file (FBX, GLB/glTF or BVH) imported as it is, with its skinned
  meshes, posed by a dance and written as FBX (see :func:`animate_rig`); a BVH dance is sent as
  its own rest pose (the rig) and its frames (the parent's ``FbxExporter.convert``);
- ``{"id": 5, "op": "glb_to_fbx", "glb": GLB, "fbx": OUT, "fps": 30.0, "frames": F}`` →
  ``{"id": 5, "ok": true, "frames": F, "fps": 30.0, "armatures": {name: bones}, "seconds": 0.9}``:
  every skinned skeleton of an animated GLB (a couple's ``couple.glb``: ``lead`` and ``follow``)
  imported by Blender's glTF importer and written as one FBX (see :func:`glb_to_fbx`);
- ``{"id": 2, "op": "ping"}`` → ``{"id": 2, "ok": true}``
- ``{"id": 3, "op": "quit"}`` → ``{"id": 3, "ok": true}`` and the process exits.
A failed request answers ``{"id": N, "ok": false, "error": "..."}`` and the worker keeps serving.

The FBX: the scene's range is exactly the dance's frames, the first at t = 0, at its rate; the
scene unit is the metre and the FBX is written in metres (``UnitScaleFactor`` 100, i.e. 1 unit =
100 cm), Y up, -Z forward; every bone keyed on every frame. The keys are written in bulk
(``keyframe_points.add`` + ``foreach_set``), and the exporter's frame-by-frame bake is answered
from the same numbers computed in bulk (:func:`bone_channels`, :class:`baked_from`).
"""

from __future__ import annotations

import json
import os
import sys
import time
import traceback

# Keep a private handle on the real stdout for the protocol, then point fd 1 at stderr so that
# anything Blender prints (importer progress, warnings) goes to the log, never into the protocol.
_PROTOCOL = os.fdopen(os.dup(1), "w", buffering=1, encoding="utf-8")
os.dup2(2, 1)
sys.stdout = sys.stderr

import bpy  # noqa: E402  (after the redirect on purpose)
from mathutils import Matrix  # noqa: E402


def _send(obj: dict) -> None:
    _PROTOCOL.write(json.dumps(obj) + "\n")
    _PROTOCOL.flush()


def clear_scene() -> None:
    """Remove everything a previous conversion left, so each file starts from an empty scene."""
    for collection in (
        bpy.data.objects,
        bpy.data.armatures,
        bpy.data.actions,
        bpy.data.meshes,
        bpy.data.materials,
    ):
        for item in list(collection):
            collection.remove(item)


def export_fbx(fbx_path: str, object_types: set[str]) -> None:
    """Write the scene's ``object_types`` as FBX, atomically: metres, Y up, -Z forward, the
    armature's animation baked on every frame of the scene's range."""
    out_dir = os.path.dirname(os.path.abspath(fbx_path))
    os.makedirs(out_dir, exist_ok=True)
    tmp_path = os.path.join(out_dir, f".tmp-{os.getpid()}-{os.path.basename(fbx_path)}")
    try:
        result = bpy.ops.export_scene.fbx(
            filepath=tmp_path,
            use_selection=False,
            object_types=object_types,
            apply_scale_options="FBX_SCALE_ALL",
            global_scale=1.0,
            apply_unit_scale=True,
            axis_forward="-Z",
            axis_up="Y",
            add_leaf_bones=False,
            primary_bone_axis="Y",
            secondary_bone_axis="X",
            armature_nodetype="NULL",
            bake_anim=True,
            bake_anim_use_all_bones=True,
            bake_anim_use_nla_strips=False,
            bake_anim_use_all_actions=False,
            bake_anim_force_startend_keying=True,
            bake_anim_step=1.0,
            bake_anim_simplify_factor=0.0,
            use_custom_props=False,
            path_mode="AUTO",
        )
        if "FINISHED" not in result:
            raise RuntimeError(f"{fbx_path}: Blender's FBX exporter failed ({result})")
        os.replace(tmp_path, fbx_path)
    finally:
        if os.path.exists(tmp_path):
            os.unlink(tmp_path)


# Blender's world (Z up, -Y forward) → the Y-up frame of the BVH and glTF conventions, in which
# DanceGraph hands over rigs and dances: (x, y, z) → (x, z, -y).
_Y_UP = Matrix(((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0))).to_4x4()


_LOADED: dict = {}  # the rig file in the scene now: its identity and its armature's name


def _loaded_rig(path: str, unit_scale: float):
    """The rig's armature: the one already in the scene when the same file (path, size, time)
    was the last one imported (a job's alternatives share their rig), else imported afresh into
    an empty scene. Every call sets every bone's pose, so nothing of the last dance remains."""
    stat = os.stat(path)
    key = (os.path.abspath(path), stat.st_size, stat.st_mtime_ns, unit_scale)
    armature = bpy.data.objects.get(_LOADED.get("armature", ""))
    if _LOADED.get("key") == key and armature is not None:
        return armature
    _LOADED.clear()
    clear_scene()
    armature = _import_rig(path, unit_scale)
    _LOADED.update(key=key, armature=armature.name)
    return armature


def _import_rig(path: str, unit_scale: float):
    """Import a rig file into the empty scene; returns its armature object (the one with most bones)."""
    suffix = os.path.splitext(path)[1].lower()
    if suffix == ".fbx":
        result = bpy.ops.import_scene.fbx(
            filepath=path, use_anim=False, automatic_bone_orientation=False, ignore_leaf_bones=False
        )
    elif suffix in (".glb", ".gltf"):
        result = bpy.ops.import_scene.gltf(filepath=path)
    elif suffix == ".bvh":
        result = bpy.ops.import_anim.bvh(
            filepath=path,
            global_scale=unit_scale,
            axis_forward="-Z",
            axis_up="Y",
            rotate_mode="NATIVE",
        )
    else:
        raise ValueError(f"{path}: not a rig file (fbx, glb, gltf, bvh)")
    if "FINISHED" not in result:
        raise RuntimeError(f"{path}: Blender could not import the rig ({result})")
    armatures = [ob for ob in bpy.context.scene.objects if ob.type == "ARMATURE"]
    if not armatures:
        raise RuntimeError(f"{path}: no armature after import")
    return max(armatures, key=lambda ob: len(ob.data.bones))


def animate_rig(rig_path: str, anim_path: str, fbx_path: str) -> dict:
    """Pose the rig in ``rig_path`` by the dance in ``anim_path`` and write ``fbx_path``.

    ``anim_path`` (numpy ``.npz``): ``names (J,)`` joint names, ``g (F, J, 4)`` each joint's world
    rotation from its bind pose (x, y, z, w; Y-up frame), ``positions (F, J, 3)`` world joint
    positions (m, Y-up frame), ``fps``, ``unit_scale`` (metres per unit of a BVH rig). Each bone's
    pose per frame comes from :func:`bone_poses`; the scene holds the first frame's pose (the
    FBX's static values, and ``first_frame``: each joint's world position, the parent's read-back
    check), and the exporter's per-frame sampling is answered from :func:`bone_channels`, so
    Blender never evaluates the scene frame by frame.
    """
    import numpy as np

    t0 = time.perf_counter()
    data = np.load(anim_path, allow_pickle=False)
    names = [str(n) for n in data["names"]]
    fps = float(data["fps"])
    scene = bpy.context.scene
    armature = _loaded_rig(rig_path, float(data["unit_scale"]))
    if armature.animation_data is not None:
        armature.animation_data_clear()
    poses = bone_poses(armature, names, np.asarray(data["g"]), np.asarray(data["positions"]))
    for name, (rot, loc) in poses.items():
        pb = armature.pose.bones[name]
        pb.rotation_mode = "QUATERNION"
        pb.rotation_quaternion = rot[0]
        if loc is not None:
            pb.location = loc[0]
    n_frames = len(data["g"])
    scene.render.fps = max(1, int(round(fps)))
    scene.render.fps_base = scene.render.fps / fps
    scene.frame_start = 0
    scene.frame_end = n_frames - 1
    scene.frame_set(0)
    to_world = _Y_UP @ armature.matrix_world
    first = {n: list(to_world @ armature.pose.bones[n].head) for n in names if n in poses}
    meshes = [ob for ob in scene.objects if ob.type == "MESH"]
    with baked_from(bone_channels(armature, poses)):
        export_fbx(fbx_path, {"ARMATURE", "MESH", "EMPTY"})
    return {
        "frames": n_frames,
        "fps": scene.render.fps / scene.render.fps_base,
        "joints": len(poses),
        "meshes": len(meshes),
        "first_frame": first,
        "seconds": round(time.perf_counter() - t0, 4),
    }


def glb_to_fbx(glb_path: str, fbx_path: str, fps: float, frames: int) -> dict:
    """Import the animated GLB ``glb_path`` into an empty scene at ``fps`` and write its
    armatures (their animation baked on frames ``0 .. frames - 1``) as ``fbx_path``; the glTF
    importer's bone display shapes are left out. Raises RuntimeError when the import fails or
    brings no armature."""
    t0 = time.perf_counter()
    _LOADED.clear()
    clear_scene()
    scene = bpy.context.scene
    scene.render.fps = max(1, int(round(fps)))
    scene.render.fps_base = scene.render.fps / fps
    result = bpy.ops.import_scene.gltf(filepath=glb_path)
    if "FINISHED" not in result:
        raise RuntimeError(f"{glb_path}: Blender could not import the GLB ({result})")
    armatures = {ob.name: len(ob.data.bones) for ob in scene.objects if ob.type == "ARMATURE"}
    if not armatures:
        raise RuntimeError(f"{glb_path}: no armature after import")
    scene.frame_start = 0
    scene.frame_end = frames - 1
    scene.frame_set(0)
    export_fbx(fbx_path, {"ARMATURE"})
    clear_scene()
    return {
        "frames": frames,
        "fps": scene.render.fps / scene.render.fps_base,
        "armatures": armatures,
        "seconds": round(time.perf_counter() - t0, 4),
    }


def bone_poses(armature, names: list[str], g, positions) -> dict[str, tuple]:
    """Every bone's pose per frame: bone → (quaternions ``(F, 4)`` wxyz, locations ``(F, 3)``
    or None).

    ``g (F, J, 4)``: each joint ``names[j]``'s world rotation from bind (xyzw, Y-up world);
    ``positions (F, J, 3)``: its world position (m). A bone turns by its joint's world rotation
    from bind: its pose is ``Rest⁻¹ · G_parent⁻¹ · G · Rest`` in its own rest frame (``Rest``: its
    rest orientation in the Y-up world), sign-continuous in time; a root bone also moves to its
    joint's position. Bones without a joint keep their bind pose to their parent.
    """
    import numpy as np

    world = _Y_UP @ armature.matrix_world  # armature space → Y-up world
    index = {n: i for i, n in enumerate(names)}
    n_frames = g.shape[0]
    identity = np.tile([0.0, 0.0, 0.0, 1.0], (n_frames, 1))
    g_bone: dict[str, np.ndarray] = {}  # world rotation from bind: its joint's, else its parent's
    poses: dict[str, tuple] = {}
    for bone in armature.data.bones:  # Blender lists parents before children
        if bone.name in index:
            g_bone[bone.name] = g[:, index[bone.name]]
        else:
            g_bone[bone.name] = g_bone[bone.parent.name] if bone.parent else identity
        rest_w = np.array(world @ bone.matrix_local)
        q = (world @ bone.matrix_local).to_quaternion()
        rest = np.array([q.x, q.y, q.z, q.w])
        g_parent = g_bone[bone.parent.name] if bone.parent else identity
        local = _qmul(_conj(g_parent), g_bone[bone.name])
        basis = _qmul(_qmul(_conj(rest), local), rest)
        basis = basis / np.linalg.norm(basis, axis=-1, keepdims=True)
        basis = np.concatenate([basis[:, 3:], basis[:, :3]], axis=1)  # wxyz
        flips = np.cumsum(np.sum(basis[1:] * basis[:-1], axis=-1) < 0) % 2
        basis[1:][flips.astype(bool)] *= -1.0
        loc = None
        if bone.parent is None and bone.name in index:
            # the root bone's world transform from bind, X = [G | p - G p_rest], in its rest frame
            wxyz = np.concatenate([g_bone[bone.name][:, 3:], g_bone[bone.name][:, :3]], axis=1)
            xf = np.tile(np.eye(4), (n_frames, 1, 1))
            xf[:, :3, :3] = _quat_matrices(wxyz)
            xf[:, :3, 3] = positions[:, index[bone.name]] - xf[:, :3, :3] @ rest_w[:3, 3]
            loc = (np.linalg.inv(rest_w)[None] @ xf @ rest_w[None])[:, :3, 3]
        poses[bone.name] = (basis, loc)
    return poses


def _qmul(a, b):
    """Hamilton products of quaternions ``(..., 4)`` (x, y, z, w), broadcast."""
    import numpy as np

    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def _conj(q):
    return q * [-1.0, -1.0, -1.0, 1.0]


def bone_channels(armature, poses: dict[str, tuple]) -> dict[str, tuple]:
    """Every bone's FBX channels per frame, computed in bulk instead of baked frame by frame.

    Blender's FBX exporter writes a bone's local transform as ``parent_pose⁻¹ · pose`` in
    armature space, which is ``rest_rel · T(location) · R(rotation)`` (``rest_rel`` the bone's
    rest matrix relative to its parent's); ``poses``: bone → (quaternions ``(F, 4)`` wxyz,
    locations ``(F, 3)`` or None). Returns bone → (location, Euler XYZ radians continuous in
    time, scale), each ``(F, 3)``, as the exporter's own bake gives them.
    """
    import numpy as np

    names, moves, eulers, scales = [], [], [], []
    for bone in armature.data.bones:
        if bone.name not in poses:
            continue
        rot, loc = poses[bone.name]
        rest = bone.matrix_local
        if bone.parent is not None:
            rest = bone.parent.matrix_local.inverted_safe() @ rest
        rest = np.array(rest)
        m = rest[None, :3, :3] @ _quat_matrices(np.asarray(rot, dtype=float))
        moved = np.zeros((len(m), 3)) if loc is None else np.asarray(loc, dtype=float)
        scale = np.linalg.norm(m, axis=1)
        m = m / scale[:, None, :]
        names.append(bone.name)
        moves.append(moved @ rest[:3, :3].T + rest[:3, 3])
        scales.append(scale)
        eulers.append(  # Blender's XYZ order: R = Rz · Ry · Rx
            np.stack(
                [
                    np.arctan2(m[:, 2, 1], m[:, 2, 2]),
                    np.arcsin(np.clip(-m[:, 2, 0], -1.0, 1.0)),
                    np.arctan2(m[:, 1, 0], m[:, 0, 0]),
                ],
                axis=1,
            )
        )
    if not names:
        return {}
    smooth = _euler_continuous(np.stack(eulers, axis=1))
    return {n: (moves[k], smooth[:, k], scales[k]) for k, n in enumerate(names)}


def _quat_matrices(q):
    """``(F, 3, 3)`` rotation matrices of unit quaternions ``(F, 4)`` (w, x, y, z)."""
    import numpy as np

    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def _euler_continuous(e):
    """``(F, B, 3)`` XYZ Euler angles, each frame's the equivalent nearest the previous frame's
    (the other solution ``(x + π, π - y, z + π)`` and whole turns), as Blender's compat does.

    Which solution is nearer depends only on the angles modulo whole turns, so the choice per
    frame is a two-state walk over booleans (scanned in bulk); the whole turns are then
    unwrapped at once."""
    import numpy as np

    turn = 2 * np.pi
    alt = np.stack([e[..., 0] + np.pi, np.pi - e[..., 1], e[..., 2] + np.pi], axis=-1)
    both = (e, alt)

    def apart(t: int, s: int):  # (F - 1, B): solution t at f from solution s at f - 1
        d = both[t][1:] - both[s][:-1]
        return np.abs(d - turn * np.round(d / turn)).sum(axis=-1)

    # each step maps the previous solution (0 or 1) to the next: (from 0, from 1); the steps are
    # composed by a prefix scan (log F rounds), so no Python loop runs over the frames
    step0, step1 = apart(1, 0) < apart(0, 0), apart(1, 1) < apart(0, 1)
    shift = 1
    while shift < len(step0):
        before0, before1 = step0[:-shift], step1[:-shift]
        after0, after1 = step0[shift:], step1[shift:]
        step0 = np.concatenate([step0[:shift], np.where(before0, after1, after0)])
        step1 = np.concatenate([step1[:shift], np.where(before1, after1, after0)])
        shift *= 2
    on_alt = np.concatenate([np.zeros((1, e.shape[1]), dtype=bool), step0])  # frame 0: principal
    return np.unwrap(np.where(on_alt[..., None], alt, e), axis=0)


class baked_from:
    """While exporting: the FBX exporter's per-frame sampling (its ``frame_values_gen``, which
    sets every frame and decomposes every object's matrix) is answered from ``table`` (see
    :func:`bone_channels`) for the bones in it and each other object's, shape key's and
    camera's one value (they do not move). Only the numpy its module sees is swapped; Blender's
    code runs unchanged. A scene with animated instances (duplis) is refused.
    """

    def __init__(self, table: dict[str, tuple]) -> None:
        self.table = table

    def __enter__(self):
        from io_scene_fbx import export_fbx_bin

        self._module, self._numpy = export_fbx_bin, export_fbx_bin.np
        export_fbx_bin.np = _NumpyFromTable(self._numpy, self.table)
        return self

    def __exit__(self, *exc) -> None:
        self._module.np = self._numpy


class _NumpyFromTable:
    """numpy, except ``fromiter`` on the exporter's frame sampler, which reads the table."""

    def __init__(self, numpy, table: dict[str, tuple]) -> None:
        self._np, self._table = numpy, table

    def __getattr__(self, name: str):
        return getattr(self._np, name)

    def fromiter(self, values, dtype=float, count=-1):
        if getattr(values, "__name__", "") == "frame_values_gen":
            return self._sampled(values)
        return self._np.fromiter(values, dtype=dtype, count=count)

    def _sampled(self, gen):
        """The sampler's values ``(F · per-frame values,)`` from the table: the table's bones,
        every other object's, shape key's and camera's one value (nothing else moves)."""
        np = self._np
        scope = gen.gi_frame.f_locals  # the sampler's closure: what it would have sampled
        if scope.get("has_animated_duplis", True):
            raise RuntimeError("the rig's scene has animated instances (duplis): not supported")
        scene_data, frames = scope["scene_data"], scope["currframes"]
        index = frames.astype(int) - scene_data.scene.frame_start
        columns = []
        for ob in scope["animdata_ob"]:
            if ob.is_bone and ob.bdata.name in self._table:
                loc, rot, scale = self._table[ob.bdata.name]
                columns.append(np.concatenate([loc, rot, scale], axis=1)[index])
            else:
                loc, rot, scale, _m, _mr = ob.fbx_object_tx(scene_data)
                columns.append(np.tile([*loc, *rot, *scale], (len(index), 1)))
        for _acnode, _me, shape in scope["animdata_shapes"].values():
            columns.append(np.full((len(index), 1), shape.value))
        for _lens, _focus, camera in scope["animdata_cameras"].values():
            columns.append(np.tile([camera.lens, camera.dof.focus_distance], (len(index), 1)))
        gen.close()
        return np.concatenate(columns, axis=1).ravel() if columns else np.zeros(0)


def _short_error(exc: Exception) -> str:
    """One line for the caller: an operator's error arrives as a whole traceback in the message."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    lines = [ln for ln in lines if not ln.startswith(("Location:", "File ", "^", "~"))]
    if isinstance(exc, RuntimeError) and len(lines) > 1:
        return f"Blender: {lines[-1]} (malformed file?)"
    return f"{type(exc).__name__}: {lines[0] if lines else ''}"


def serve() -> int:
    """Answer requests from stdin until EOF or a ``quit`` request."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = 1.0
    _send({"ready": True, "blender": bpy.app.version_string, "pid": os.getpid()})
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        req_id = None
        try:
            req = json.loads(line)
            req_id = req.get("id")
            op = req.get("op")
            if op == "animate_rig":
                summary = animate_rig(str(req["rig"]), str(req["anim"]), str(req["fbx"]))
                _send({"id": req_id, "ok": True, **summary})
            elif op == "glb_to_fbx":
                summary = glb_to_fbx(
                    str(req["glb"]), str(req["fbx"]), float(req["fps"]), int(req["frames"])
                )
                _send({"id": req_id, "ok": True, **summary})
            elif op == "ping":
                _send({"id": req_id, "ok": True})
            elif op == "quit":
                _send({"id": req_id, "ok": True})
                return 0
            else:
                _send({"id": req_id, "ok": False, "error": f"unknown op {op!r}"})
        except Exception as exc:  # one bad file must not end the worker
            traceback.print_exc(file=sys.stderr)
            _send({"id": req_id, "ok": False, "error": _short_error(exc)})
    return 0


if __name__ == "__main__":
    sys.exit(serve())
