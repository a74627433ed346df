"""Build the test rigs of ``rigs.py`` in Blender and write them as FBX (and GLB).

Runs ONLY under Blender's Python (``.venv-blender``): ``python blender_rigs.py SPECS.json OUT_DIR``.
Each spec: ``name``, ``bones`` (name, parent, head, tail; Blender axes, metres), ``mesh`` (a
skinned box per bone), ``formats`` (default ``["fbx"]``), ``cm`` (the armature object scaled
0.01 with bones in centimetres, as Mixamo's files are), ``face_y`` (the character turned to face
+Y), ``z_up`` (the FBX written with Z up, Y forward), ``parent`` (the armature under an empty
node ``{"name", "rotation_x_deg", "scale"}``, its bones and mesh in that node's units and axes, as a
centimetre, Z-up export from a DCC tool is), ``fbx_cm`` (the FBX written in centimetres,
``UnitScaleFactor`` 1) and ``prerot`` (every bone's local rotation moved into FBX pre- and
post-rotations, as Maya's joint orients are, the rest pose unchanged), ``shape_key`` (the mesh
gets a blend shape set to 0.25).
"""

from __future__ import annotations

import json
import math
import os
import sys

import bpy
from mathutils import Euler, Matrix, Vector


def clear() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


def box_mesh(bones: list[dict], arm_obj, to_local=None) -> None:
    """A mesh of one 8-vertex box per bone, skinned to it (the box's start also to the parent).

    ``to_local``: world → the armature object's space (the mesh is its child)."""
    verts, faces, groups = [], [], []
    for b in bones:
        head, tail = Vector(b["head"]), Vector(b["tail"])
        axis = tail - head
        if axis.length < 1e-6:
            continue
        r = max(0.015, min(0.06, 0.25 * axis.length))
        d = axis.normalized()
        side = d.cross(Vector((0, 0, 1)) if abs(d.z) < 0.9 else Vector((1, 0, 0))).normalized()
        up = d.cross(side).normalized()
        base = len(verts)
        for end, p in enumerate((head, tail)):
            for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                verts.append(p + r * (sx * side + sy * up))
                w = {b["name"]: 1.0}
                if end == 0 and b["parent"]:
                    w = {b["name"]: 0.6, b["parent"]: 0.4}
                groups.append(w)
        faces += [
            (base + 0, base + 1, base + 2, base + 3),
            (base + 4, base + 7, base + 6, base + 5),
            (base + 0, base + 4, base + 5, base + 1),
            (base + 1, base + 5, base + 6, base + 2),
            (base + 2, base + 6, base + 7, base + 3),
            (base + 3, base + 7, base + 4, base + 0),
        ]
    if not bones:  # a mesh with no armature at all
        verts = [Vector(v) for v in ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1))]
        faces = [(0, 1, 2, 3), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)]
    if to_local is not None:
        verts = [to_local @ v for v in verts]
    me = bpy.data.meshes.new("body")
    me.from_pydata([tuple(v) for v in verts], [], faces)
    me.update()
    ob = bpy.data.objects.new("body", me)
    bpy.context.scene.collection.objects.link(ob)
    if arm_obj is None:
        return
    for name in {n for w in groups for n in w}:
        ob.vertex_groups.new(name=name)
    for i, w in enumerate(groups):
        for name, weight in w.items():
            ob.vertex_groups[name].add([i], weight, "REPLACE")
    ob.parent = arm_obj
    mod = ob.modifiers.new("Armature", "ARMATURE")
    mod.object = arm_obj


def build(spec: dict, out_dir: str) -> None:
    clear()
    scene = bpy.context.scene
    scene.unit_settings.system = "METRIC"
    bones = spec["bones"]
    arm_obj = None
    turn = Matrix.Rotation(math.pi, 4, "Z") if spec.get("face_y") else Matrix.Identity(4)
    parent = spec.get("parent")
    parent_world = Matrix.Identity(4)
    if parent:
        parent_world = Matrix.Rotation(
            math.radians(parent["rotation_x_deg"]), 4, "X"
        ) @ Matrix.Scale(parent["scale"], 4)
    arm_world = parent_world @ Matrix.Scale(0.01 if spec.get("cm") else 1.0, 4)
    to_local = arm_world.inverted()  # world metres → the armature's own space
    if bones:
        arm = bpy.data.armatures.new("Armature")
        arm_obj = bpy.data.objects.new("Armature", arm)
        scene.collection.objects.link(arm_obj)
        bpy.context.view_layer.objects.active = arm_obj
        bpy.ops.object.mode_set(mode="EDIT")
        made = {}
        for b in bones:
            eb = arm.edit_bones.new(b["name"])
            eb.head = to_local @ (turn @ Vector(b["head"]))
            eb.tail = to_local @ (turn @ Vector(b["tail"]))
            made[b["name"]] = eb
        for b in bones:
            if b["parent"]:
                made[b["name"]].parent = made[b["parent"]]
        bpy.ops.object.mode_set(mode="OBJECT")
        if spec.get("cm"):
            arm_obj.scale = (0.01, 0.01, 0.01)
        if parent:
            empty = bpy.data.objects.new(parent["name"], None)
            scene.collection.objects.link(empty)
            empty.matrix_world = parent_world
            arm_obj.parent = empty
    if spec.get("mesh"):
        turned = [
            dict(b, head=list(turn @ Vector(b["head"])), tail=list(turn @ Vector(b["tail"])))
            for b in bones
        ]
        box_mesh(turned, arm_obj, to_local if arm_obj is not None else None)
        if spec.get("shape_key"):  # a blend shape, as faces of real characters carry
            body = bpy.data.objects["body"]
            body.shape_key_add(name="Basis")
            key = body.shape_key_add(name="wide")
            for point in key.data:
                point.co.x *= 1.1
            key.value = 0.25
    for fmt in spec.get("formats", ["fbx"]):
        write(spec, os.path.join(out_dir, f"{spec['name']}.{fmt}"), fmt)


def write(spec: dict, path: str, fmt: str) -> None:
    """The scene as FBX (the spec's axes and units, pre-rotations if asked) or GLB."""
    if fmt == "fbx":
        up, fwd = ("Z", "Y") if spec.get("z_up") else ("Y", "-Z")
        bpy.ops.export_scene.fbx(
            filepath=path,
            object_types={"ARMATURE", "MESH", "EMPTY"},
            axis_up=up,
            axis_forward=fwd,
            add_leaf_bones=False,
            bake_anim=False,
            apply_scale_options="FBX_SCALE_NONE" if spec.get("fbx_cm") else "FBX_SCALE_ALL",
        )
        if spec.get("prerot"):
            move_to_pre_rotations(path)
    else:
        bpy.ops.export_scene.gltf(
            filepath=path, export_format="GLB", export_animations=False, export_skins=True
        )


def move_to_pre_rotations(path: str) -> None:
    """Rewrite an FBX so every bone's local rotation ``R`` is ``Pre · R' · Post⁻¹`` (the same
    rest pose): ``Pre = R · Q``, ``R' = Q⁻¹ · W``, ``Post = W`` with fixed turns ``Q`` and ``W``,
    ``RotationActive`` on, through Blender's own FBX ⇄ JSON tools."""
    sys.path.insert(0, os.path.dirname(_fbx_tools()))
    import encode_bin
    import fbx2json
    import json2fbx

    fbx2json.fbx2json(path)
    json_path = os.path.splitext(path)[0] + ".json"
    with open(json_path) as fh:
        root = json.load(fh)
    os.unlink(json_path)
    q = Euler((math.radians(12), math.radians(-25), math.radians(17))).to_matrix()
    w = Euler((math.radians(-8), math.radians(30), math.radians(5))).to_matrix()

    def deg(m) -> list[float]:
        return [math.degrees(a) for a in m.to_euler("XYZ")]

    objects = next(e for e in root if e[0] == "Objects")
    for model in (e for e in objects[3] if e[0] == "Model" and e[1][2] == "LimbNode"):
        props = next(e for e in model[3] if e[0] == "Properties70")
        rows = {p[1][0]: p for p in props[3]}
        r = Euler([math.radians(a) for a in rows.get("Lcl Rotation", [0, [0] * 7])[1][4:7]])
        r = r.to_matrix()
        for name, value, kind in (
            ("PreRotation", deg(r @ q), ("Vector3D", "Vector", "")),
            ("PostRotation", deg(w), ("Vector3D", "Vector", "")),
            ("Lcl Rotation", deg(q.inverted() @ w), ("Lcl Rotation", "", "A")),
        ):
            row = ["P", [name, *kind, *value], "SSSSDDD", []]
            if name in rows:
                props[3][props[3].index(rows[name])] = row
            else:
                props[3].append(row)
        props[3].append(["P", ["RotationActive", "bool", "", "", 1], "SSSSI", []])
    out, version = json2fbx.parse_json(root)
    encode_bin.write(path, out, version)


def _fbx_tools() -> str:
    """A file inside Blender's FBX add-on folder (its FBX ⇄ JSON tools import each other flat)."""
    import io_scene_fbx

    return os.path.join(os.path.dirname(io_scene_fbx.__file__), "json2fbx.py")


def main() -> int:
    specs = json.loads(open(sys.argv[1]).read())
    for spec in specs:
        build(spec, sys.argv[2])
    return 0


if __name__ == "__main__":
    sys.exit(main())
