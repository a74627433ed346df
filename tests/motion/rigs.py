"""Test rigs made by the project: humanoid armatures in several naming schemes, poses and sizes.

:func:`rig_specs` describes each rig as bones (name, parent, head, tail in Blender's Z-up metres,
the character facing -Y with its left on +X) plus how to write it; ``blender_rigs.py`` builds them
in Blender (its own process) and writes FBX and GLB files; :func:`write_bvh_rig` writes the BVH
ones with DanceGraph's own writer. :func:`make_rigs` does both into one folder.

Rigs: ``mixamo`` (Mixamo names, long legs and short arms, centimetres), ``unreal`` (Unreal
Mannequin names, A-pose, a ``root`` bone and twist bones, Z up and facing +Y in the file),
``rigify`` (Rigify DEF bones, split upper arms and thighs), ``child`` (0.6 x, big head),
``fingers`` (Mixamo names with twist bones and three-segment fingers), ``skinned`` (Unity
humanoid names with a skinned mesh; also as ``skinned.glb``), ``parented`` (a skinned GLB whose
armature sits under a node scaled 0.01 and turned -90 degrees about X), ``prerot`` (a skinned
Mixamo-named FBX in centimetres with pre- and post-rotations and a blend shape), ``cmu_cm``
(BVH in centimetres with CMU names), and the bad ones: ``bad_no_armature`` (a mesh only), ``bad_no_legs``,
``bad_disconnected`` (legs in trees of their own), ``bad_zero_length`` (a BVH knee on its hip).
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np

from dancegraph.motion.bvh import write_bvh
from dancegraph.motion.fbx import blender_python
from dancegraph.motion.skeleton import Motion, Skeleton

BLENDER_SCRIPT = Path(__file__).with_name("blender_rigs.py")
GOOD_RIGS = ("mixamo.fbx", "unreal.fbx", "rigify.fbx", "child.fbx", "fingers.fbx")
GOOD_RIGS_MESH = ("skinned.fbx", "skinned.glb")
#: Rigs whose skeleton sits under parent transforms: a glTF armature under a node scaled 0.01 and
#: turned -90 degrees about X (a centimetre, Z-up export), an FBX in centimetres with pre- and
#: post-rotations on every bone (Maya's joint orients).
PARENTED_RIGS = ("parented.glb", "prerot.fbx")
GOOD_BVH_RIGS = ("cmu_cm.bvh",)
BAD_RIGS = {
    "bad_no_armature.fbx": "rig_no_armature",
    "bad_no_legs.fbx": "rig_missing_roles",
    "bad_disconnected.fbx": "rig_disconnected",
    "bad_zero_length.bvh": "rig_zero_length",
}


def _template(
    legs: float = 1.0,
    arms: float = 1.0,
    torso: float = 1.0,
    head: float = 1.0,
    a_pose: bool = False,
) -> dict[str, tuple[tuple[float, float, float], tuple[float, float, float], str | None]]:
    """Role → (head, tail, parent role) of a humanoid in T-pose (or A-pose), Blender axes."""
    hip_z = 0.92 * legs
    b: dict = {}
    b["hips"] = ((0, 0, hip_z), (0, 0, hip_z + 0.1 * torso), None)
    z = hip_z + 0.1 * torso
    b["spine"] = ((0, 0.0, z), (0, 0.01, z + 0.14 * torso), "hips")
    z += 0.14 * torso
    b["chest"] = ((0, 0.01, z), (0, 0.01, z + 0.14 * torso), "spine")
    z += 0.14 * torso
    b["upper_chest"] = ((0, 0.01, z), (0, 0.0, z + 0.12 * torso), "chest")
    z += 0.12 * torso
    b["neck"] = ((0, 0.0, z), (0, -0.01, z + 0.1 * head), "upper_chest")
    z += 0.1 * head
    b["head"] = ((0, -0.01, z), (0, -0.01, z + 0.2 * head), "neck")
    b["head_end"] = ((0, -0.01, z + 0.2 * head), (0, -0.01, z + 0.25 * head), "head")
    sz = z - 0.1 * head - 0.04 * torso
    for side, sx in (("left", 1.0), ("right", -1.0)):
        b[f"{side}_collar"] = ((sx * 0.02, 0.0, sz), (sx * 0.17, 0.02, sz), "upper_chest")
        upper, fore, hand = 0.28 * arms, 0.26 * arms, 0.08 * arms
        pts = [0.17, 0.17 + upper, 0.17 + upper + fore, 0.17 + upper + fore + hand]
        ang = np.radians(45.0 if a_pose else 0.0)

        def arm(d: float, y: float = 0.0, dz: float = 0.0, _sx=sx, _ang=ang) -> tuple:
            r = d - 0.17
            return (
                _sx * (0.17 + r * np.cos(_ang)),
                y,
                sz + dz - r * np.sin(_ang),
            )

        b[f"{side}_shoulder"] = (arm(pts[0]), arm(pts[1], 0.02), f"{side}_collar")
        b[f"{side}_elbow"] = (arm(pts[1], 0.02), arm(pts[2]), f"{side}_shoulder")
        b[f"{side}_wrist"] = (arm(pts[2]), arm(pts[3]), f"{side}_elbow")
        for f, (fy, start) in enumerate(
            ((-0.035, -0.02), (-0.02, 0.0), (0.0, 0.0), (0.02, 0.0), (0.035, -0.005))
        ):
            name = ("thumb", "index", "middle", "ring", "pinky")[f]
            d0 = pts[3] + start
            seg = 0.025 * arms
            parent = f"{side}_wrist"
            for k in (1, 2, 3):
                h, t = arm(d0 + (k - 1) * seg, fy), arm(d0 + k * seg, fy)
                b[f"{side}_{name}_{k}"] = (h, t, parent)
                parent = f"{side}_{name}_{k}"
        lx = sx * 0.09
        knee_z = hip_z * 0.52
        b[f"{side}_hip"] = ((lx, 0.0, hip_z - 0.04), (lx, -0.01, knee_z), "hips")
        b[f"{side}_knee"] = ((lx, -0.01, knee_z), (lx, 0.01, 0.09 * legs), f"{side}_hip")
        b[f"{side}_ankle"] = ((lx, 0.01, 0.09 * legs), (lx, -0.11, 0.025), f"{side}_knee")
        b[f"{side}_toe"] = ((lx, -0.11, 0.025), (lx, -0.17, 0.02), f"{side}_ankle")
    return b


_MIXAMO = {
    "hips": "Hips",
    "spine": "Spine",
    "chest": "Spine1",
    "upper_chest": "Spine2",
    "neck": "Neck",
    "head": "Head",
    "head_end": "HeadTop_End",
    **{
        f"{s}_{r}": f"{S}{n}"
        for s, S in (("left", "Left"), ("right", "Right"))
        for r, n in (
            ("collar", "Shoulder"),
            ("shoulder", "Arm"),
            ("elbow", "ForeArm"),
            ("wrist", "Hand"),
            ("hip", "UpLeg"),
            ("knee", "Leg"),
            ("ankle", "Foot"),
            ("toe", "ToeBase"),
        )
    },
    **{
        f"{s}_{f}_{k}": f"{S}Hand{f.capitalize()}{k}"
        for s, S in (("left", "Left"), ("right", "Right"))
        for f in ("thumb", "index", "middle", "ring", "pinky")
        for k in (1, 2, 3)
    },
}
_UNREAL = {
    "hips": "pelvis",
    "spine": "spine_01",
    "chest": "spine_02",
    "upper_chest": "spine_03",
    "neck": "neck_01",
    "head": "head",
    **{
        f"{s}_{r}": f"{n}_{t}"
        for s, t in (("left", "l"), ("right", "r"))
        for r, n in (
            ("collar", "clavicle"),
            ("shoulder", "upperarm"),
            ("elbow", "lowerarm"),
            ("wrist", "hand"),
            ("hip", "thigh"),
            ("knee", "calf"),
            ("ankle", "foot"),
            ("toe", "ball"),
        )
    },
    **{
        f"{s}_{f}_{k}": f"{f}_0{k}_{t}"
        for s, t in (("left", "l"), ("right", "r"))
        for f in ("thumb", "index", "middle", "ring", "pinky")
        for k in (1, 2, 3)
    },
}
_RIGIFY = {
    "hips": "DEF-spine",
    "spine": "DEF-spine.001",
    "chest": "DEF-spine.002",
    "upper_chest": "DEF-spine.003",
    "neck": "DEF-spine.004",
    "head": "DEF-spine.006",
    **{
        f"{s}_{r}": f"DEF-{n}.{t}"
        for s, t in (("left", "L"), ("right", "R"))
        for r, n in (
            ("collar", "shoulder"),
            ("shoulder", "upper_arm"),
            ("elbow", "forearm"),
            ("wrist", "hand"),
            ("hip", "thigh"),
            ("knee", "shin"),
            ("ankle", "foot"),
            ("toe", "toe"),
        )
    },
    **{
        f"{s}_{f}_{k}": f"DEF-{n}.0{k}.{t}"
        for s, t in (("left", "L"), ("right", "R"))
        for f, n in (
            ("thumb", "thumb"),
            ("index", "f_index"),
            ("middle", "f_middle"),
            ("ring", "f_ring"),
            ("pinky", "f_pinky"),
        )
        for k in (1, 2, 3)
    },
}
_UNITY = {
    "hips": "Hips",
    "spine": "Spine",
    "chest": "Chest",
    "upper_chest": "UpperChest",
    "neck": "Neck",
    "head": "Head",
    **{
        f"{s}_{r}": f"{S}{n}"
        for s, S in (("left", "Left"), ("right", "Right"))
        for r, n in (
            ("collar", "Shoulder"),
            ("shoulder", "UpperArm"),
            ("elbow", "LowerArm"),
            ("wrist", "Hand"),
            ("hip", "UpperLeg"),
            ("knee", "LowerLeg"),
            ("ankle", "Foot"),
            ("toe", "Toes"),
        )
    },
}


def _bones(template: dict, names: dict[str, str], keep: set[str] | None = None) -> list[dict]:
    """Bones (name, parent, head, tail) of the template roles that ``names`` names."""
    out = []
    for role, (head, tail, parent) in template.items():
        if role not in names or (keep is not None and role not in keep):
            continue
        p = parent
        while p is not None and p not in names:
            p = template[p][2]
        out.append(
            {
                "name": names[role],
                "parent": names[p] if p is not None else None,
                "head": [float(v) for v in head],
                "tail": [float(v) for v in tail],
            }
        )
    return out


def _split(bones: list[dict], name: str, new: str) -> None:
    """Split bone ``name`` in two halves: ``name`` then ``new`` (Rigify's .001 segments)."""
    i = next(k for k, b in enumerate(bones) if b["name"] == name)
    b = bones[i]
    mid = [(h + t) / 2 for h, t in zip(b["head"], b["tail"], strict=True)]
    second = {"name": new, "parent": name, "head": mid, "tail": b["tail"]}
    b["tail"] = mid
    for other in bones:
        if other["parent"] == name:
            other["parent"] = new
    bones.insert(i + 1, second)


def _twist(bones: list[dict], name: str, new: str) -> None:
    """A twist bone: child of ``name``, from its middle to its end, animated by nobody."""
    b = next(b for b in bones if b["name"] == name)
    mid = [(h + t) / 2 for h, t in zip(b["head"], b["tail"], strict=True)]
    bones.append({"name": new, "parent": name, "head": mid, "tail": b["tail"]})


def _parented_specs(mixamo: dict[str, str], no_fingers: set[str]) -> list[dict]:
    """The rigs whose skeleton sits under parent transforms (see ``PARENTED_RIGS``)."""
    return [
        {
            "name": "parented",
            "bones": _bones(_template(legs=1.02), _UNITY),
            "mesh": True,
            "formats": ["glb"],
            "parent": {"name": "Root", "rotation_x_deg": -90.0, "scale": 0.01},
        },
        {
            "name": "prerot",
            "bones": _bones(_template(legs=1.08, arms=0.95), mixamo, no_fingers),
            "mesh": True,
            "cm": True,
            "fbx_cm": True,
            "prerot": True,
            "shape_key": True,
        },
    ]


def rig_specs() -> list[dict]:
    """Every Blender-made rig: ``name``, ``bones``, ``mesh`` (bool), ``formats``, ``cm``, ``face_y``."""
    specs = []
    mixamo = {k: f"mixamorig:{v}" for k, v in _MIXAMO.items()}
    no_fingers = {
        k for k in _MIXAMO if not any(f in k for f in ("thumb", "index", "ring", "pinky", "middle"))
    }
    specs.append(
        {
            "name": "mixamo",
            "bones": _bones(_template(legs=1.12, arms=0.85, torso=0.95), mixamo, no_fingers),
            "cm": True,
        }
    )
    bones = _bones(_template(a_pose=True, torso=1.05), _UNREAL)
    bones.insert(0, {"name": "root", "parent": None, "head": [0, 0, 0], "tail": [0, 0.15, 0]})
    next(b for b in bones if b["name"] == "pelvis")["parent"] = "root"
    for side in ("l", "r"):
        _twist(bones, f"upperarm_{side}", f"upperarm_twist_01_{side}")
        _twist(bones, f"thigh_{side}", f"thigh_twist_01_{side}")
    bones.append({"name": "ik_foot_root", "parent": "root", "head": [0, 0, 0], "tail": [0, 0, 0.1]})
    specs.append({"name": "unreal", "bones": bones, "face_y": True, "z_up": True})
    bones = _bones(_template(), _RIGIFY)
    for part in ("upper_arm", "forearm", "thigh", "shin"):
        for side in ("L", "R"):
            _split(bones, f"DEF-{part}.{side}", f"DEF-{part}.{side}.001")
    head = next(b for b in bones if b["name"] == "DEF-spine.006")
    head["name"] = "DEF-spine.005"
    bones.append(
        {
            "name": "DEF-spine.006",
            "parent": "DEF-spine.005",
            "head": head["tail"],
            "tail": [head["tail"][0], head["tail"][1], head["tail"][2] + 0.05],
        }
    )
    specs.append({"name": "rigify", "bones": bones})
    child = _template(legs=0.55, arms=0.58, torso=0.6, head=0.8)
    specs.append({"name": "child", "bones": _bones(child, mixamo, no_fingers)})
    bones = _bones(_template(legs=0.97, arms=1.05), mixamo)
    for s in ("Left", "Right"):
        _twist(bones, f"mixamorig:{s}Arm", f"mixamorig:{s}ArmTwist")
        _twist(bones, f"mixamorig:{s}ForeArm", f"mixamorig:{s}ForeArmTwist")
    specs.append({"name": "fingers", "bones": bones})
    specs.append(
        {
            "name": "skinned",
            "bones": _bones(_template(legs=1.05), _UNITY),
            "mesh": True,
            "formats": ["fbx", "glb"],
        }
    )
    specs += _parented_specs(mixamo, no_fingers)
    # bad rigs
    specs.append({"name": "bad_no_armature", "bones": [], "mesh": True})
    keep = {k for k in _MIXAMO if not k.endswith(("hip", "knee", "ankle", "toe"))} & no_fingers
    specs.append({"name": "bad_no_legs", "bones": _bones(_template(), mixamo, keep)})
    bones = _bones(_template(), mixamo, no_fingers)
    for b in bones:
        if b["name"].endswith(("LeftUpLeg", "RightUpLeg")):
            b["parent"] = None
    specs.append({"name": "bad_disconnected", "bones": bones})
    return specs


def write_bvh_rig(
    path: Path, names: dict[str, str], template: dict, unit: float, knee_on_hip: bool = False
) -> None:
    """A one-frame BVH rig (Y up, facing +Z) of the template's roles, in ``unit`` metres per unit."""
    roles = [r for r in template if r in names]
    index = {r: i for i, r in enumerate(roles)}
    parents, offsets = [], []
    for r in roles:
        head = np.asarray(template[r][0], dtype=float)
        p = template[r][2]
        while p is not None and p not in names:
            p = template[p][2]
        parents.append(-1 if p is None else index[p])
        base = np.zeros(3) if p is None else np.asarray(template[p][0], dtype=float)
        if knee_on_hip and r.endswith("_knee"):
            head = np.asarray(template[r.replace("knee", "hip")][0], dtype=float)
        if knee_on_hip and r.endswith("_ankle"):
            base = np.asarray(template[r.replace("ankle", "hip")][0], dtype=float)
        d = head - base
        offsets.append([d[0], d[2], -d[1]])  # Blender (x, y, z) → Y up, facing +Z
    offsets = np.asarray(offsets) / unit
    channels = [("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")] + [
        ("Zrotation", "Xrotation", "Yrotation")
    ] * (len(roles) - 1)
    ends = {}
    for i, r in enumerate(roles):
        if i not in parents:
            t = np.asarray(template[r][1]) - np.asarray(template[r][0])
            ends[i] = np.array([t[0], t[2], -t[1]]) / unit
    sk = Skeleton([names[r] for r in roles], np.array(parents), offsets, channels, ends)
    rot = np.zeros((1, len(roles), 4))
    rot[..., 3] = 1.0
    write_bvh(Motion(sk, 30.0, offsets[:1].copy(), rot), path)


_CMU = {
    "hips": "hip",
    "spine": "abdomen",
    "chest": "chest",
    "neck": "neck",
    "head": "head",
    **{
        f"{s}_{r}": f"{t}{n}"
        for s, t in (("left", "l"), ("right", "r"))
        for r, n in (
            ("collar", "Collar"),
            ("shoulder", "Shldr"),
            ("elbow", "ForeArm"),
            ("wrist", "Hand"),
            ("hip", "Thigh"),
            ("knee", "Shin"),
            ("ankle", "Foot"),
        )
    },
}


def make_rigs(out: Path, *, blender: bool = True) -> Path:
    """Write every test rig into ``out`` (FBX/GLB through Blender when ``blender``); returns ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    write_bvh_rig(out / "cmu_cm.bvh", _CMU, _template(legs=1.05, arms=1.1), 0.01)
    write_bvh_rig(out / "bad_zero_length.bvh", _CMU, _template(), 1.0, knee_on_hip=True)
    if blender:
        spec_path = out / "specs.json"
        spec_path.write_text(json.dumps(rig_specs()))
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        proc = subprocess.run(
            [str(blender_python()), "-I", str(BLENDER_SCRIPT), str(spec_path), str(out)],
            capture_output=True,
            text=True,
            timeout=600,
            env=env,
        )
        if proc.returncode != 0:
            raise RuntimeError(f"blender_rigs.py failed: {proc.stderr[-3000:]}")
        skin_in_armature_space(out / "parented.glb")
    return out


def skin_in_armature_space(path: Path) -> None:
    """Rewrite a GLB's skin in its armature node's own space (centimetres, Z up under ``Root``).

    Blender writes inverse-bind matrices and vertices in the world; DCC exporters as often write
    them in the armature's space, the other form glTF's skinning rule ``world · ibm · v`` allows:
    ``ibm' = ibm · A`` and ``v' = A⁻¹ · v`` with ``A`` the armature node's world matrix, so the
    character stands where it did.
    """
    import struct

    from scipy.spatial.transform import Rotation

    raw = bytearray(path.read_bytes())
    (n_json,) = struct.unpack_from("<I", raw, 12)
    doc = json.loads(bytes(raw[20 : 20 + n_json]))
    blob_at = 20 + n_json + 8
    nodes = doc["nodes"]
    parent = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}

    skin = doc["skins"][0]
    top = next(j for j in skin["joints"] if parent.get(j) not in skin["joints"])
    arm, a = np.eye(4), parent.get(top)
    while a is not None:  # the armature's world matrix: its nodes' scale, rotation, translation
        local = np.eye(4)
        rotation = Rotation.from_quat(nodes[a].get("rotation", [0, 0, 0, 1])).as_matrix()
        local[:3, :3] = rotation * np.asarray(nodes[a].get("scale", [1, 1, 1]))[None, :]
        local[:3, 3] = nodes[a].get("translation", [0, 0, 0])
        arm, a = local @ arm, parent.get(a)

    def view(k: int, width: int) -> np.ndarray:
        acc = doc["accessors"][k]
        bv = doc["bufferViews"][acc["bufferView"]]
        start = blob_at + bv.get("byteOffset", 0) + acc.get("byteOffset", 0)
        return np.frombuffer(bytes(raw), np.float32, acc["count"] * width, start).reshape(-1, width)

    def put(k: int, values: np.ndarray) -> None:
        acc = doc["accessors"][k]
        bv = doc["bufferViews"][acc["bufferView"]]
        start = blob_at + bv.get("byteOffset", 0) + acc.get("byteOffset", 0)
        data = values.astype(np.float32).tobytes()
        raw[start : start + len(data)] = data

    ibm = view(skin["inverseBindMatrices"], 16).reshape(-1, 4, 4).transpose(0, 2, 1)
    put(skin["inverseBindMatrices"], (ibm @ arm).transpose(0, 2, 1).reshape(-1, 16))
    inv = np.linalg.inv(arm)
    for prim in doc["meshes"][0]["primitives"]:
        k = prim["attributes"]["POSITION"]
        pos = view(k, 3) @ inv[:3, :3].T + inv[:3, 3]
        put(k, pos)
        doc["accessors"][k]["min"] = pos.min(axis=0).tolist()
        doc["accessors"][k]["max"] = pos.max(axis=0).tolist()
        if "NORMAL" in prim["attributes"]:
            n = view(prim["attributes"]["NORMAL"], 3) @ arm[:3, :3]
            length = np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            put(prim["attributes"]["NORMAL"], n / length)
    text = json.dumps(doc).encode("utf-8")
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + bytes(raw[20 + n_json :])
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
