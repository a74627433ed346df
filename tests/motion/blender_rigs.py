"""Build the test rigs of ``rigs.py`` in Blender and write them as FBX (and GLB).

Runs ONLY under Blender's Python (``.venv-blender``): ``python blender_rigs.py SPECS.json OUT_DIR``.
Each spec: ``name``, ``bones`` (name, parent, head, tail; Blender axes, metres), ``mesh`` (a
skinned box per bone), ``formats`` (default ``["fbx"]``), ``cm`` (the armature object scaled
0.01 with bones in centimetres, as Mixamo's files are), ``face_y`` (the character turned to face
+Y), ``z_up`` (the FBX written with Z up, Y forward).
"""

from __future__ import annotations

import json
import math
import os
import sys

import bpy
from mathutils import Matrix, Vector


def clear() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


def box_mesh(bones: list[dict], arm_obj) -> None:
    """A mesh of one 8-vertex box per bone, skinned to it (the box's start also to the parent)."""
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
    k = 100.0 if spec.get("cm") else 1.0
    turn = Matrix.Rotation(math.pi, 4, "Z") if spec.get("face_y") else Matrix.Identity(4)
    if bones:
        arm = bpy.data.armatures.new("Armature")
        arm_obj = bpy.data.objects.new("Armature", arm)
        scene.collection.objects.link(arm_obj)
        bpy.context.view_layer.objects.active = arm_obj
        bpy.ops.object.mode_set(mode="EDIT")
        made = {}
        for b in bones:
            eb = arm.edit_bones.new(b["name"])
            eb.head = turn @ Vector(b["head"]) * k
            eb.tail = turn @ Vector(b["tail"]) * k
            made[b["name"]] = eb
        for b in bones:
            if b["parent"]:
                made[b["name"]].parent = made[b["parent"]]
        bpy.ops.object.mode_set(mode="OBJECT")
        if spec.get("cm"):
            arm_obj.scale = (0.01, 0.01, 0.01)
    if spec.get("mesh"):
        turned = [
            dict(b, head=list(turn @ Vector(b["head"])), tail=list(turn @ Vector(b["tail"])))
            for b in bones
        ]
        box_mesh(turned, arm_obj)
    for fmt in spec.get("formats", ["fbx"]):
        path = os.path.join(out_dir, f"{spec['name']}.{fmt}")
        if fmt == "fbx":
            up, fwd = ("Z", "Y") if spec.get("z_up") else ("Y", "-Z")
            bpy.ops.export_scene.fbx(
                filepath=path,
                object_types={"ARMATURE", "MESH"},
                axis_up=up,
                axis_forward=fwd,
                add_leaf_bones=False,
                bake_anim=False,
                apply_scale_options="FBX_SCALE_ALL",
            )
        else:
            bpy.ops.export_scene.gltf(
                filepath=path, export_format="GLB", export_animations=False, export_skins=True
            )


def main() -> int:
    specs = json.loads(open(sys.argv[1]).read())
    for spec in specs:
        build(spec, sys.argv[2])
    return 0


if __name__ == "__main__":
    sys.exit(main())
