"""A user's character rig: joints, hierarchy, bind pose, humanoid roles and (optionally) a skinned mesh.

A rig comes from FBX (read by ufbx in a child process, ``dancegraph.motion.ufbx_reader``), glTF
binary (``dancegraph.motion.gltf``) or BVH. Every reader hands :func:`build_rig` the same thing:
joint names, parents and each joint's world bind matrix (metres, the file's own up axis), plus
the skinned mesh when there is one. :func:`build_rig` then

1. orders the joints parents-first and keeps the tree that holds the hips;
2. finds the humanoid roles (:func:`map_roles`): a user mapping first, then the name presets
   (Mixamo, Unreal, Unity, Rigify, CMU/Daz, SMPL), then the hierarchy's shape;
3. refuses a rig that lacks a required role, whose roles lie in separate trees, or whose mapped
   bones have no length (``RigError`` with a stable code, HTTP 422);
4. finds the rig's up and forward axes and its floor, so retargeting can work in one canonical
   frame (Y up, facing +Z, the character's left on +X) whatever the rig's axes.

The rig's :class:`~dancegraph.motion.skeleton.Skeleton` is in BVH convention: offsets are the
bind pose's joint-to-joint vectors in the rig's world axes and a zero rotation is the bind pose,
so a motion on it writes as BVH directly; ``rest_rotations`` keep each joint's own bind frame for
formats whose nodes carry it (glTF, FBX).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dancegraph.errors import DanceGraphError
from dancegraph.motion import quat
from dancegraph.motion.bvh import MAX_DEPTH, MAX_JOINTS
from dancegraph.motion.skeleton import CANONICAL_JOINTS, Skeleton

SIDES = ("left", "right")
FINGERS = ("thumb", "index", "middle", "ring", "pinky")

#: Humanoid roles. They extend ``CANONICAL_JOINTS`` and mean the same: a role names the joint at
#: the start of a bone (``left_shoulder`` is the upper arm's joint, ``left_hip`` the thigh's).
ROLES: tuple[str, ...] = (
    *CANONICAL_JOINTS,
    "upper_chest",
    "left_collar",
    "right_collar",
    *(f"{s}_{f}_{k}" for s in SIDES for f in FINGERS for k in (1, 2, 3)),
)
#: Roles every rig must have: without them there is no body to dance with.
REQUIRED_ROLES: tuple[str, ...] = (
    "hips",
    "spine",
    "left_hip",
    "left_knee",
    "left_ankle",
    "right_hip",
    "right_knee",
    "right_ankle",
)
#: Bones whose world direction is compared against the source (the limbs).
LIMB_ROLES: tuple[str, ...] = tuple(
    f"{s}_{p}" for s in SIDES for p in ("shoulder", "elbow", "hip", "knee")
)

# The role whose joint a role's bone points at, in order of preference.
_CHILD_ROLES: dict[str, tuple[str, ...]] = {
    "hips": ("spine", "chest", "upper_chest", "neck"),
    "spine": ("chest", "upper_chest", "neck", "head"),
    "chest": ("upper_chest", "neck", "head"),
    "upper_chest": ("neck", "head"),
    "neck": ("head",),
    **{
        f"{s}_{a}": (f"{s}_{b}",)
        for s in SIDES
        for a, b in (
            ("collar", "shoulder"),
            ("shoulder", "elbow"),
            ("elbow", "wrist"),
            ("wrist", "middle_1"),
            ("hip", "knee"),
            ("knee", "ankle"),
            ("ankle", "toe"),
        )
    },
    **{f"{s}_{f}_{k}": (f"{s}_{f}_{k + 1}",) for s in SIDES for f in FINGERS for k in (1, 2)},
}


class RigError(DanceGraphError):
    """A rig that cannot be used; ``code`` says why (rig_*), ``field`` names the culprit."""

    code = "rig_invalid"
    status = 422


#: Longest joint name (characters); names are stored and echoed, so they are bounded.
MAX_NAME_CHARS = 255


def name_problem(name: object) -> str | None:
    """Why ``name`` cannot be a joint name (not text, empty, longer than
    :data:`MAX_NAME_CHARS`, a control character such as NUL, a lone surrogate), or None."""
    if not isinstance(name, str) or not name:
        return "is not a non-empty text"
    if len(name) > MAX_NAME_CHARS:
        return f"is longer than {MAX_NAME_CHARS} characters"
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return "holds a control character (such as NUL)"
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return "holds a lone surrogate"
    return None


def check_hierarchy(names: list, parents: np.ndarray) -> None:
    """Refuse joints a rig cannot have, before anything walks them.

    At most :data:`MAX_JOINTS` joints nested at most :data:`MAX_DEPTH` deep
    (``rig_too_complex``); every name valid (:func:`name_problem`, ``rig_name_invalid``); every
    parent an index or -1, and no cycle (``rig_unreadable``). One pass, no recursion.
    """
    n = len(names)
    if n > MAX_JOINTS:
        raise RigError(f"more than {MAX_JOINTS} joints", code="rig_too_complex")
    for j, name in enumerate(names):
        why = name_problem(name)
        if why is not None:
            raise RigError(f"joint {j}'s name {why}", code="rig_name_invalid", field=f"joint {j}")
    parents = np.asarray(parents, dtype=np.int64)
    if len(parents) != n or ((parents < -1) | (parents >= n)).any():
        raise RigError("a joint's parent is not a joint", code="rig_unreadable")
    depth = np.full(n, -1, dtype=np.int64)
    for j in range(n):
        chain, a = [], j
        while a >= 0 and depth[a] < 0:
            chain.append(a)
            a = int(parents[a])
            if len(chain) > n:
                raise RigError("the joints' parents form a cycle", code="rig_unreadable")
        base = -1 if a < 0 else int(depth[a])
        for k, i in enumerate(reversed(chain), start=1):
            depth[i] = base + k
        if base + len(chain) >= MAX_DEPTH:
            raise RigError(f"joints nested more than {MAX_DEPTH} deep", code="rig_too_complex")


# ------------------------------------------------------------------------------------------------
# name presets


def _sided(table: dict[str, tuple[str, ...]], left: str, right: str) -> dict[str, tuple[str, ...]]:
    """Expand ``{S}`` in a per-part table into left and right roles."""
    out: dict[str, tuple[str, ...]] = {}
    for role, names in table.items():
        if role.startswith("{s}_"):
            for side, tok in (("left", left), ("right", right)):
                out[role.replace("{s}", side)] = tuple(n.replace("{S}", tok) for n in names)
        else:
            out[role] = names
    return out


def _merge(*tables: dict[str, tuple[str, ...]]) -> dict[str, tuple[str, ...]]:
    """Tables joined role by role: each role's candidates from every table, in order."""
    out: dict[str, tuple[str, ...]] = {}
    for table in tables:
        for role, names in table.items():
            out[role] = out.get(role, ()) + tuple(n for n in names if n not in out.get(role, ()))
    return out


def _fingers(pattern: str, left: str, right: str, names: dict[str, str]) -> dict:
    """Finger roles from ``pattern`` with ``{S}`` (side), ``{F}`` (finger name) and ``{K}``."""
    out = {}
    for side, tok in (("left", left), ("right", right)):
        for finger, fname in names.items():
            for k in (1, 2, 3):
                out[f"{side}_{finger}_{k}"] = (
                    pattern.replace("{S}", tok).replace("{F}", fname).replace("{K}", str(k)),
                )
    return out


_FINGER_NAMES = {f: f for f in FINGERS}
# Mixamo's limb names, also those of CMU's MotionBuilder-friendly layout (LeftUpLeg, ...)
_MIXAMO_LIMBS: dict[str, tuple[str, ...]] = {
    "{s}_collar": ("{S}shoulder",),
    "{s}_shoulder": ("{S}arm",),
    "{s}_elbow": ("{S}forearm",),
    "{s}_wrist": ("{S}hand",),
    "{s}_hip": ("{S}upleg",),
    "{s}_knee": ("{S}leg",),
    "{s}_ankle": ("{S}foot",),
    "{s}_toe": ("{S}toebase",),
}

# SMPL's joint names (left_knee, or L_Knee in some exports); its "foot" is the toe joint
_SMPL_LIMBS: dict[str, tuple[str, ...]] = {
    f"{{s}}_{part}": (f"{{S}}{name}",)
    for part, name in (
        ("collar", "collar"),
        ("shoulder", "shoulder"),
        ("elbow", "elbow"),
        ("wrist", "wrist"),
        ("hip", "hip"),
        ("knee", "knee"),
        ("ankle", "ankle"),
        ("toe", "foot"),
    )
}

#: Name presets: role → candidate joint names (compared after :func:`normalize_name`).
PRESETS: dict[str, dict[str, tuple[str, ...]]] = {
    "mixamo": {
        **_sided(_MIXAMO_LIMBS, "left", "right"),
        "hips": ("hips",),
        "spine": ("spine",),
        "chest": ("spine1",),
        "upper_chest": ("spine2",),
        "neck": ("neck",),
        "head": ("head",),
        **_fingers("{S}hand{F}{K}", "left", "right", _FINGER_NAMES),
    },
    "unreal": {
        **_sided(
            {
                "{s}_collar": ("clavicle_{S}",),
                "{s}_shoulder": ("upperarm_{S}",),
                "{s}_elbow": ("lowerarm_{S}",),
                "{s}_wrist": ("hand_{S}",),
                "{s}_hip": ("thigh_{S}",),
                "{s}_knee": ("calf_{S}",),
                "{s}_ankle": ("foot_{S}",),
                "{s}_toe": ("ball_{S}",),
            },
            "l",
            "r",
        ),
        "hips": ("pelvis",),
        "spine": ("spine_01",),
        "chest": ("spine_03", "spine_02"),
        "upper_chest": ("spine_05", "spine_04"),
        "neck": ("neck_01",),
        "head": ("head",),
        **_fingers("{F}_0{K}_{S}", "l", "r", _FINGER_NAMES),
    },
    "unity": {
        **_sided(
            {
                "{s}_collar": ("{S}shoulder",),
                "{s}_shoulder": ("{S}upperarm",),
                "{s}_elbow": ("{S}lowerarm",),
                "{s}_wrist": ("{S}hand",),
                "{s}_hip": ("{S}upperleg",),
                "{s}_knee": ("{S}lowerleg",),
                "{s}_ankle": ("{S}foot",),
                "{s}_toe": ("{S}toes",),
            },
            "left",
            "right",
        ),
        "hips": ("hips",),
        "spine": ("spine",),
        "chest": ("chest",),
        "upper_chest": ("upperchest",),
        "neck": ("neck",),
        "head": ("head",),
        **{
            f"{side}_{finger}_{k}": (f"{side}{finger}{stage}",)
            for side in SIDES
            for finger in FINGERS
            for k, stage in ((1, "proximal"), (2, "intermediate"), (3, "distal"))
        },
    },
    "rigify": {
        **_sided(
            {
                "{s}_collar": ("shoulder{S}",),
                "{s}_shoulder": ("upper_arm{S}",),
                "{s}_elbow": ("forearm{S}",),
                "{s}_wrist": ("hand{S}",),
                "{s}_hip": ("thigh{S}",),
                "{s}_knee": ("shin{S}",),
                "{s}_ankle": ("foot{S}",),
                "{s}_toe": ("toe{S}",),
            },
            ".l",
            ".r",
        ),
        "hips": ("spine",),
        "spine": ("spine.001",),
        "chest": ("spine.003", "spine.002"),
        "upper_chest": (),
        "neck": ("spine.004",),
        "head": ("spine.006", "spine.005"),
        **_fingers(
            "{F}.0{K}{S}",
            ".l",
            ".r",
            {"thumb": "thumb", "index": "f_index", "middle": "f_middle", "ring": "f_ring"}
            | {"pinky": "f_pinky"},
        ),
    },
    "cmu": {
        **_merge(
            _sided(
                {
                    "{s}_collar": ("{S}collar", "{S}shoulder"),
                    "{s}_shoulder": ("{S}shldr", "{S}arm"),
                    "{s}_elbow": ("{S}forearm",),
                    "{s}_wrist": ("{S}hand",),
                    "{s}_hip": ("{S}thigh", "{S}upleg"),
                    "{s}_knee": ("{S}shin", "{S}leg"),
                    "{s}_ankle": ("{S}foot",),
                    "{s}_toe": ("{S}toebase", "{S}toe"),
                },
                "l",
                "r",
            ),
            _sided(_MIXAMO_LIMBS, "left", "right"),  # CMU's ASF/MotionBuilder layout
        ),
        "hips": ("hip", "hips"),
        "spine": ("abdomen", "lowerback"),
        "chest": ("chest", "spine"),
        "upper_chest": ("spine1",),
        "neck": ("neck",),
        "head": ("head",),
        **{
            f"{side}_{finger}_{k}": (f"{tok}{finger}{k}",)
            for side, tok in (("left", "l"), ("right", "r"))
            for finger, k in (
                *((f, k) for f in ("thumb", "index", "ring", "pinky") for k in (1, 2)),
                ("mid", 1),
                ("mid", 2),
            )
        },
    },
    "smpl": {
        **_merge(_sided(_SMPL_LIMBS, "left_", "right_"), _sided(_SMPL_LIMBS, "l_", "r_")),
        "hips": ("pelvis",),
        "spine": ("spine1",),
        "chest": ("spine2",),
        "upper_chest": ("spine3",),
        "neck": ("neck",),
        "head": ("head",),
    },
}
# the CMU/Daz finger names: lMid1 is the middle finger
for _side, _tok in (("left", "l"), ("right", "r")):
    for _k in (1, 2):
        PRESETS["cmu"][f"{_side}_middle_{_k}"] = (f"{_tok}mid{_k}",)
        PRESETS["cmu"].pop(f"{_side}_mid_{_k}", None)

_PREFIXES = ("mixamorig", "def-", "org-", "bip01", "bip001", "b_", "j_", "jnt_")


def normalize_name(name: str) -> str:
    """A joint name as presets compare it: namespace (``a:b``, ``a|b``) and rig prefix dropped, lower case.

    ``mixamorig:LeftArm``, ``mixamorig_LeftArm`` and ``Armature|mixamorig:LeftArm`` all become
    ``leftarm``; ``DEF-thigh.L`` becomes ``thigh.l``; spaces become underscores.
    """
    n = re.split(r"[:|]", name)[-1].strip().lower().replace(" ", "_")
    for prefix in _PREFIXES:
        if n.startswith(prefix) and len(n) > len(prefix):
            rest = n[len(prefix) :]
            n = rest[1:] if rest[0] in "_:-" and prefix[-1] not in "-_" else rest
            break
    return n


def _preset_roles(names: list[str]) -> tuple[str | None, dict[str, str]]:
    """The preset that names the most required roles, and the roles it finds."""
    norm: dict[str, str] = {}
    # two joints with one normalised name (Rigify's DEF-thigh.L and ORG-thigh.L): the deforming
    # one wins, else the first
    for n in sorted(names, key=lambda n: not n.upper().startswith("DEF-")):
        norm.setdefault(normalize_name(n), n)
    best_name, best, best_score = None, {}, (0, 0)
    for preset, table in PRESETS.items():
        found: dict[str, str] = {}
        for role, cands in table.items():
            for cand in cands:
                if cand in norm and norm[cand] not in found.values():
                    found[role] = norm[cand]
                    break
        score = (sum(r in found for r in REQUIRED_ROLES), len(found))
        if score > best_score:
            best_name, best, best_score = preset, found, score
    return best_name, best


# ------------------------------------------------------------------------------------------------
# the hierarchy's shape


def _children(parents: np.ndarray) -> list[list[int]]:
    kids: list[list[int]] = [[] for _ in range(len(parents))]
    for j, p in enumerate(parents):
        if p >= 0:
            kids[int(p)].append(j)
    return kids


def _subtree_size(parents: np.ndarray) -> np.ndarray:
    size = np.ones(len(parents), dtype=np.int64)
    for j in range(len(parents) - 1, -1, -1):  # parents come first
        if parents[j] >= 0:
            size[parents[j]] += size[j]
    return size


def _chain(start: int, kids: list[list[int]], size: np.ndarray) -> list[int]:
    """``start`` and then, at each joint, the child with the largest subtree."""
    out = [start]
    while kids[out[-1]]:
        out.append(max(kids[out[-1]], key=lambda c: size[c]))
    return out


def _structure_roles(names: list[str], parents: np.ndarray, pos: np.ndarray) -> dict[str, str]:
    """Roles from the hierarchy's shape and the bind pose, for rigs whose names no preset knows.

    The hips are the first joint (from the root) with three or more branches of depth ≥ 3; the
    spine is the largest of them (it carries the arms and the head), the legs the next two; up
    is the world axis nearest to the direction from the legs to the spine. Left is
    the side of ``up × forward``, forward being where the toes point (without toes: where the
    knees bend). Arms branch from the spine
    sideways; a chain's joints are read from its bends (collar, upper arm, forearm, hand; thigh,
    shin, foot, toe).
    """
    kids = _children(parents)
    size = _subtree_size(parents)

    def depth(j: int) -> int:
        return len(_chain(j, kids, size))

    extent = float(np.ptp(pos, axis=0).max()) or 1.0
    for hips in range(len(names)):
        if sum(depth(c) >= 3 for c in kids[hips]) >= 3:
            found = _structure_from_hips(hips, names, pos, kids, size, depth, extent)
            if found:
                return found
    return {}


def _structure_from_hips(hips, names, pos, kids, size, depth, extent) -> dict[str, str]:
    """The roles below a hips candidate, or {} when its branches do not make a body."""
    branches = [c for c in kids[hips] if depth(c) >= 3]
    # the spine carries the arms and the head: the largest subtree; the legs are the other two
    branches.sort(key=lambda c: -size[c])
    spine_root, legs = branches[0], branches[1:3]

    def members(c: int) -> list[int]:
        out, stack = [], [c]
        while stack:
            j = stack.pop()
            out.append(j)
            stack.extend(kids[j])
        return out

    up = _snap_axis(
        pos[members(spine_root)].mean(axis=0)
        - np.concatenate([pos[members(c)] for c in legs]).mean(axis=0)
    )
    height = pos @ up
    roles: dict[str, int] = {"hips": hips}

    leg_chains = []
    for c in legs:
        ch = _chain(c, kids, size)
        top = height[ch[0]]
        # the ankle: the end of the last bone that runs mostly down (feet and toes run forward)
        seg = np.diff(pos[ch], axis=0)
        down = -(seg @ up) > 0.7 * np.linalg.norm(seg, axis=1)
        ankle_i = int(np.flatnonzero(down)[-1]) + 1 if down.any() else 0
        if ankle_i < 2 or top - height[ch[ankle_i]] < 0.25 * extent:
            return {}  # not a leg: too short, or no joint between hip and ankle
        knee_i = min(
            range(ankle_i), key=lambda i: abs(height[ch[i]] - 0.5 * (top + height[ch[ankle_i]]))
        )
        hip_i = max(0, knee_i - 1)
        leg_chains.append((ch, hip_i, knee_i, ankle_i))
    # forward: where the feet point (ankle → last joint of the foot), projected off the up axis
    fwd = np.zeros(3)
    for ch, _, _, a in leg_chains:
        if a + 1 < len(ch):
            fwd += pos[ch[-1]] - pos[ch[a]]
    fwd -= (fwd @ up) * up
    if np.linalg.norm(fwd) < 1e-6 * extent:  # no toes: the knees bend forward
        for ch, h, k, a in leg_chains:
            fwd += pos[ch[k]] - 0.5 * (pos[ch[h]] + pos[ch[a]])
        fwd -= (fwd @ up) * up
    if np.linalg.norm(fwd) < 1e-6 * extent:
        return {}
    left_axis = np.cross(up, fwd / np.linalg.norm(fwd))
    leg_chains.sort(key=lambda t: -(pos[t[0][t[2]]] @ left_axis))  # left leg first
    for side, (ch, hip_i, knee_i, ankle_i) in zip(SIDES, leg_chains, strict=True):
        roles[f"{side}_hip"] = ch[hip_i]
        roles[f"{side}_knee"] = ch[knee_i]
        roles[f"{side}_ankle"] = ch[ankle_i]
        if ankle_i + 1 < len(ch):
            roles[f"{side}_toe"] = ch[ankle_i + 1]

    # the spine runs up the middle: at each joint, the child whose subtree is nearest the midline
    mid = pos[hips] @ left_axis
    spine = [spine_root]
    while kids[spine[-1]]:
        spine.append(
            min(kids[spine[-1]], key=lambda c: abs(pos[members(c)].mean(axis=0) @ left_axis - mid))
        )
    # the arms branch off where the spine chain has side branches of depth >= 3
    branch_i = None
    for i, j in enumerate(spine):
        if sum(depth(c) >= 3 for c in kids[j] if c not in spine) >= 2:
            branch_i = i
            break
    head_i = len(spine) - 1
    if branch_i is not None:
        arms = [c for c in kids[spine[branch_i]] if c not in spine and depth(c) >= 3]
        arms.sort(key=lambda c: -(pos[_chain(c, kids, size)[-1]] @ left_axis))
        for side, c in zip(SIDES, arms[:2], strict=False):
            ch = _chain(c, kids, size)
            # the hand: the first joint with two or more children (fingers); else the 4th joint
            # when the chain starts with a clavicle (a first bone much shorter than the second)
            hand_i = next((i for i, j in enumerate(ch) if len(kids[j]) >= 2), None)
            if hand_i is None or hand_i < 2:
                seg = np.linalg.norm(np.diff(pos[ch], axis=0), axis=1)
                collar = len(seg) >= 2 and seg[0] < 0.6 * seg[1]
                hand_i = min(len(ch) - 1, 3 if collar else 2)
            roles[f"{side}_wrist"] = ch[hand_i]
            roles[f"{side}_elbow"] = ch[hand_i - 1]
            roles[f"{side}_shoulder"] = ch[hand_i - 2]
            if hand_i >= 3:
                roles[f"{side}_collar"] = ch[hand_i - 3]
        head_i = max(branch_i + 1, head_i)
        if branch_i >= 1:
            roles["chest"] = spine[branch_i]
        roles["spine"] = spine[0]
        above = spine[branch_i + 1 :]
        if len(above) >= 2:
            # the head is the last joint of the neck chain that is not a tip end
            roles["neck"] = above[0]
            roles["head"] = above[1]
        elif len(above) == 1:
            roles["head"] = above[0]
    else:
        roles["spine"] = spine[0]
        if len(spine) >= 3:
            roles["head"] = spine[-2]
            roles["neck"] = spine[-3] if len(spine) >= 4 else spine[-2]
    return {r: names[j] for r, j in roles.items() if not (r == "neck" and roles.get("head") == j)}


# ------------------------------------------------------------------------------------------------
# mapping


@dataclass
class RoleMap:
    """Humanoid roles found on a skeleton.

    - ``roles``: role → joint name;
    - ``how``: role → ``"user"``, ``"preset:<name>"`` or ``"structure"``;
    - ``unmapped``: joints no role names (twist bones, fingers, face): they keep their bind pose
      relative to their parent.
    """

    roles: dict[str, str]
    how: dict[str, str]
    unmapped: list[str]

    def to_dict(self) -> dict:
        return {"roles": dict(self.roles), "how": dict(self.how), "unmapped": list(self.unmapped)}


def read_mapping(path: str | Path) -> dict[str, str]:
    """A user mapping file (JSON or YAML object: role → joint name); RigError ``rig_map_invalid``."""
    text = Path(path).read_text(encoding="utf-8") if Path(path).is_file() else None
    if text is None:
        raise RigError(f"no mapping file {path}", code="rig_map_invalid", field=str(path))
    try:
        if str(path).lower().endswith((".yaml", ".yml")):
            import yaml

            data = yaml.safe_load(text)
        else:
            data = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise RigError(
            f"{path}: not a JSON/YAML mapping ({str(exc)[:100]})",
            code="rig_map_invalid",
            field=str(path),
        ) from None
    return check_mapping(data)


def check_mapping(data) -> dict[str, str]:
    """Validate a user mapping (role → joint name): RigError ``rig_map_invalid`` naming the key."""
    if not isinstance(data, dict):
        raise RigError("a mapping is an object of role → joint name", code="rig_map_invalid")
    out = {}
    for role, joint in data.items():
        if role not in ROLES:
            raise RigError(
                f"unknown role {str(role)[:40]!r} in the mapping (roles: "
                f"{', '.join(ROLES[:22])}, ...)",
                code="rig_map_invalid",
                field=str(role)[:40],
            )
        why = name_problem(joint)
        if why is not None:
            raise RigError(
                f"mapping[{role!r}] must be a joint name: it {why}",
                code="rig_map_invalid",
                field=role,
            )
        out[role] = joint
    return out


def map_roles(
    names: list[str],
    parents: np.ndarray,
    positions: np.ndarray,
    user: dict[str, str] | None = None,
) -> RoleMap:
    """Humanoid roles of a skeleton: ``user`` mapping, then name presets, then structure.

    ``positions``: ``(J, 3)`` bind-pose world positions (any axes). A user mapping naming a joint that is not there raises
    ``RigError`` (``rig_map_invalid``).
    """
    parents = np.asarray(parents)
    positions = np.asarray(positions, dtype=float)
    roles: dict[str, str] = {}
    how: dict[str, str] = {}
    for role, joint in (user or {}).items():
        if joint not in names:
            raise RigError(
                f"the mapping names joint {joint!r} for {role}, but the rig has no such joint",
                code="rig_map_invalid",
                field=role,
            )
        roles[role], how[role] = joint, "user"
    preset, found = _preset_roles(names)
    used = set(roles.values())
    for role, joint in found.items():
        if role not in roles and joint not in used:
            roles[role], how[role] = joint, f"preset:{preset}"
            used.add(joint)
    if any(r not in roles for r in REQUIRED_ROLES):
        for role, joint in _structure_roles(names, parents, positions).items():
            if role not in roles and joint not in used:
                roles[role], how[role] = joint, "structure"
                used.add(joint)
    ordered = {r: roles[r] for r in ROLES if r in roles}
    unmapped = [n for n in names if n not in used]
    return RoleMap(ordered, {r: how[r] for r in ordered}, unmapped)


def _snap_axis(v: np.ndarray) -> np.ndarray:
    out = np.zeros(3)
    k = int(np.argmax(np.abs(v)))
    out[k] = np.sign(v[k])
    return out


# ------------------------------------------------------------------------------------------------
# the rig


@dataclass
class RigMesh:
    """A skinned mesh at the bind pose, in the rig's world (metres).

    ``positions (V, 3)``, ``normals (V, 3)`` or None, ``triangles (T, 3)`` int, ``joints (V, 4)``
    skeleton joint indices, ``weights (V, 4)`` summing to 1 per vertex.
    """

    positions: np.ndarray
    triangles: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    normals: np.ndarray | None = None

    @property
    def n_vertices(self) -> int:
        return int(self.positions.shape[0])


@dataclass
class Rig:
    """A character rig ready for retargeting (see the module docstring).

    - ``skeleton``: BVH-convention skeleton (metres, the rig's world axes; ``canonical`` filled
      from the roles);
    - ``rest_rotations``: ``(J, 4)`` each joint's own frame at bind, in world axes;
    - ``roles``: the :class:`RoleMap`;
    - ``to_canonical``: ``(4,)`` rotation from the rig's world to the canonical frame (Y up,
      facing +Z); ``floor``: the floor's height in the canonical frame (m);
    - ``unit_scale``: metres per unit of the file (a BVH in centimetres: 0.01);
    - ``mesh``: the skinned mesh, or None; ``source``: the file's format (fbx, glb, bvh) and name;
      ``dropped``: joints outside the hips' tree (kept at bind in FBX output, absent elsewhere);
    - ``ancestors``: the file's nodes above the skeleton's root, top first, as
      ``[(name, local (4, 4))]`` (an armature node, a unit or axis change): the writers place the
      skeleton under them, so the character lands where it stood in the user's file.
    """

    skeleton: Skeleton
    rest_rotations: np.ndarray
    roles: RoleMap
    to_canonical: np.ndarray
    floor: float
    unit_scale: float = 1.0
    mesh: RigMesh | None = None
    source: dict = field(default_factory=dict)
    dropped: list[str] = field(default_factory=list)
    ancestors: list[tuple[str, np.ndarray]] = field(default_factory=list)

    def joint(self, role: str) -> int | None:
        """Skeleton index of the joint playing ``role``, or None."""
        name = self.roles.roles.get(role)
        return None if name is None else self.skeleton.index(name)

    def summary(self) -> dict:
        """What the API and CLI report about a rig: joints, roles, how they were found, gaps."""
        sk = self.skeleton
        return {
            "format": self.source.get("format"),
            "joints": sk.n_joints,
            "root": sk.names[0],
            "roles": dict(self.roles.roles),
            "how": dict(self.roles.how),
            "unmapped": list(self.roles.unmapped),
            "missing_optional": [r for r in ROLES[:22] if r not in self.roles.roles],
            "dropped": list(self.dropped),
            "height_m": round(float(self.height()), 4),
            "up_axis": self.up_axis(),
            "ancestors": [name for name, _ in self.ancestors],
            "unit_scale": self.unit_scale,
            "mesh": None
            if self.mesh is None
            else {"vertices": self.mesh.n_vertices, "triangles": int(len(self.mesh.triangles))},
        }

    def canonical_positions(self) -> np.ndarray:
        """``(J, 3)`` bind-pose joint positions in the canonical frame (m)."""
        return quat.rotate(
            np.broadcast_to(self.to_canonical, (self.skeleton.n_joints, 4)), bind_positions(self)
        )

    def height(self) -> float:
        """Bind-pose height (m): the highest joint above the floor."""
        return float(self.canonical_positions()[:, 1].max() - self.floor)

    def up_axis(self) -> str:
        """The world axis the character's up runs along in its file (``"+Y"`` is upright)."""
        up = quat.rotate(quat.conjugate(self.to_canonical), np.array([0.0, 1.0, 0.0]))
        k = int(np.argmax(np.abs(up)))
        return ("+" if up[k] > 0 else "-") + "XYZ"[k]

    def ancestors_world(self) -> np.ndarray:
        """``(4, 4)`` world matrix of the skeleton root's parent (identity without ancestors)."""
        world = np.eye(4)
        for _name, local in self.ancestors:
            world = world @ np.asarray(local, dtype=float)
        return world


def bind_positions(rig: Rig) -> np.ndarray:
    """``(J, 3)`` bind-pose world joint positions (m), summed from the skeleton's offsets."""
    sk = rig.skeleton
    pos = np.zeros((sk.n_joints, 3))
    for j in range(sk.n_joints):
        p = sk.parents[j]
        pos[j] = sk.offsets[j] if p < 0 else pos[p] + sk.offsets[j]
    return pos


def _rotation_part(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit quaternions ``(J, 4)`` and scales ``(J,)`` of ``(J, 3, 3)`` matrices (polar part)."""
    from scipy.spatial.transform import Rotation

    u, s, vt = np.linalg.svd(m)
    r = u @ vt
    det = np.linalg.det(r)
    u[det < 0, :, -1] *= -1.0  # a mirrored frame: keep a proper rotation
    r = u @ vt
    return Rotation.from_matrix(r).as_quat(), np.cbrt(np.abs(np.linalg.det(m)))


def _depth_first(parents: np.ndarray, root: int) -> list[int]:
    kids = _children(parents)
    order, stack = [], [root]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(kids[j]))
    return order


def canonical_frame(pos: np.ndarray, index: dict[str, int], roles: dict[str, str]) -> np.ndarray:
    """Rotation ``(4,)`` from the rig's world to Y up, facing +Z, snapped to the nearest axes."""
    from scipy.spatial.transform import Rotation

    hips = pos[index[roles["hips"]]]
    top = next(r for r in ("head", "neck", "upper_chest", "chest", "spine") if r in roles)
    up = _snap_axis(pos[index[roles[top]]] - hips)
    left = pos[index[roles["left_hip"]]] - pos[index[roles["right_hip"]]]
    left -= (left @ up) * up
    if np.linalg.norm(left) < 1e-9:
        raise RigError(
            "the left and right legs start at the same place: cannot tell left from right",
            code="rig_degenerate",
            field="left_hip",
        )
    left = _snap_axis(left)
    if abs(left @ up) > 0.5:
        raise RigError(
            "the rig's left-right axis runs along its up axis", code="rig_degenerate", field="hips"
        )
    fwd = np.cross(left, up)
    m = np.stack([left, up, fwd])  # rows: where X, Y, Z of the canonical frame point in the rig
    return Rotation.from_matrix(m).as_quat()


def build_rig(
    names: list[str],
    parents: np.ndarray,
    bind_world: np.ndarray,
    *,
    mesh: RigMesh | None = None,
    mapping: dict[str, str] | None = None,
    unit_scale: float = 1.0,
    source: dict | None = None,
    end_sites: dict[str, np.ndarray] | None = None,
    ancestors: dict[str, list] | None = None,
) -> Rig:
    """A :class:`Rig` from joints and their world bind matrices (see the module docstring).

    ``bind_world``: ``(J, 4, 4)`` world matrices (metres; columns are the joint's axes and
    position). ``mesh.joints`` index ``names``. Raises ``RigError``: ``rig_no_armature`` (no
    joints), ``rig_missing_roles`` (``field`` lists them), ``rig_disconnected`` (roles in separate
    trees), ``rig_zero_length`` (a mapped bone without length), ``rig_degenerate``.
    ``ancestors``: per top joint's name, the nodes above it (see :class:`Rig`).
    """
    names = list(names)
    parents = np.asarray(parents, dtype=np.int64)
    bind_world = np.asarray(bind_world, dtype=float)
    if not names:
        raise RigError("the file holds no armature (no joints)", code="rig_no_armature")
    check_hierarchy(names, parents)
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise RigError(f"two joints are named {dup!r}", code="rig_duplicate_joint", field=dup)
    if not np.isfinite(bind_world).all():
        raise RigError("the bind pose holds NaN or infinite values", code="rig_degenerate")
    pos = bind_world[:, :3, 3]
    rot, _scale = _rotation_part(bind_world[:, :3, :3])

    # the roles first, on all joints: a role in another tree makes the rig disconnected
    found = map_roles(names, parents, pos, mapping)
    missing = [r for r in REQUIRED_ROLES if r not in found.roles]
    if missing:
        raise RigError(
            f"the rig has no joint for the required role(s) {', '.join(missing)} "
            "(name them in a mapping file if they are there)",
            code="rig_missing_roles",
            field=",".join(missing),
        )
    index = {n: i for i, n in enumerate(names)}
    hips = index[found.roles["hips"]]
    root = hips
    while parents[root] >= 0:
        root = int(parents[root])
    order = _depth_first(parents, root)
    in_tree = set(order)
    apart = [r for r, n in found.roles.items() if index[n] not in in_tree]
    if apart:
        raise RigError(
            f"the joints of {', '.join(apart)} are not connected to the hips' hierarchy",
            code="rig_disconnected",
            field=",".join(apart),
        )
    dropped = [n for i, n in enumerate(names) if i not in in_tree]

    # reorder parents-first (depth first from the root)
    new_of = {old: new for new, old in enumerate(order)}
    names_o = [names[i] for i in order]
    parents_o = np.array([-1 if parents[i] < 0 else new_of[int(parents[i])] for i in order])
    pos_o, rot_o = pos[order], rot[order]
    offsets = pos_o.copy()
    offsets[1:] = pos_o[1:] - pos_o[parents_o[1:]]
    if mesh is not None:
        remap = np.full(len(names), 0, dtype=np.int64)
        for old, new in new_of.items():
            remap[old] = new
        mesh = RigMesh(
            positions=np.asarray(mesh.positions, dtype=float),
            triangles=np.asarray(mesh.triangles, dtype=np.int64),
            joints=remap[np.asarray(mesh.joints, dtype=np.int64)],
            weights=np.asarray(mesh.weights, dtype=float),
            normals=None if mesh.normals is None else np.asarray(mesh.normals, dtype=float),
        )
    roles = RoleMap(found.roles, found.how, [n for n in found.unmapped if n in set(names_o)])
    channels: list[tuple[str, ...]] = [
        ("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")
        if j == 0
        else ("Zrotation", "Xrotation", "Yrotation")
        for j in range(len(names_o))
    ]
    canonical = {k: roles.roles[k] for k in CANONICAL_JOINTS if k in roles.roles}
    for side in SIDES:
        canonical.setdefault(f"{side}_toe", canonical[f"{side}_ankle"])
    ends = {
        idx: np.asarray((end_sites or {})[n], dtype=float)
        for idx, n in enumerate(names_o)
        if n in (end_sites or {})
    }
    skeleton = Skeleton(names_o, parents_o, offsets, channels, ends, canonical)
    idx_o = {n: i for i, n in enumerate(names_o)}
    to_canon = canonical_frame(pos_o, idx_o, roles.roles)
    canon_pos = quat.rotate(np.broadcast_to(to_canon, pos_o.shape[:-1] + (4,)), pos_o)

    # every mapped bone must have a length (relative to the rig's size)
    size = float(np.ptp(canon_pos[:, 1])) or 1.0
    for role, name in roles.roles.items():
        j = idx_o[name]
        child = bone_end(skeleton, roles.roles, role)
        if child is not None and np.linalg.norm(canon_pos[child] - canon_pos[j]) < 1e-4 * size:
            raise RigError(
                f"the {role} bone ({name!r}) has no length: its end sits on its start",
                code="rig_zero_length",
                field=name,
            )
    for role in REQUIRED_ROLES:
        j = idx_o[roles.roles[role]]
        p = parents_o[j]
        if role != "hips" and p >= 0 and np.linalg.norm(offsets[j]) < 1e-4 * size:
            if role.endswith(("_knee", "_ankle")):
                raise RigError(
                    f"the bone ending at {role} ({names_o[j]!r}) has no length",
                    code="rig_zero_length",
                    field=names_o[j],
                )

    feet = [
        canon_pos[j] + quat.rotate(to_canon, off)
        for side in SIDES
        for j, off in foot_points(skeleton, roles.roles, side)
    ]
    if mesh is not None and mesh.n_vertices:
        canon_mesh = quat.rotate(
            np.broadcast_to(to_canon, mesh.positions.shape[:-1] + (4,)), mesh.positions
        )
        floor = float(canon_mesh[:, 1].min())
    else:
        floor = float(np.min(np.asarray(feet)[:, 1]))
    return Rig(
        skeleton=skeleton,
        rest_rotations=rot_o,
        roles=roles,
        to_canonical=to_canon,
        floor=floor,
        unit_scale=float(unit_scale),
        mesh=mesh,
        source=dict(source or {}),
        dropped=dropped,
        ancestors=list((ancestors or {}).get(names_o[0], [])),
    )


def bone_end(skeleton: Skeleton, roles: dict[str, str], role: str) -> int | None:
    """The joint a role's bone points at: its child role's joint, else its only/largest child.

    None when the joint is a leaf (the caller then uses the parent's direction).
    """
    j = skeleton.index(roles[role])
    for child_role in _CHILD_ROLES.get(role, ()):
        if child_role in roles:
            c = skeleton.index(roles[child_role])
            # only a descendant counts
            a = c
            while a >= 0 and a != j:
                a = int(skeleton.parents[a])
            if a == j:
                return c
    kids = skeleton.children(j)
    if not kids:
        return None
    if len(kids) == 1:
        return kids[0]
    size = _subtree_size(skeleton.parents)
    return max(kids, key=lambda c: size[c])


def foot_points(
    skeleton: Skeleton, roles: dict[str, str], side: str
) -> list[tuple[int, np.ndarray]]:
    """One foot's points as ``(joint, offset)``: a point sits at ``offset`` (bind-pose world
    axes, m) from that joint and moves with it.

    The ankle; the toe joint (or, without one, the foot bone's end); the toe's tip (its child
    joint or End Site) where there is one.
    """
    ankle = skeleton.index(roles[f"{side}_ankle"])
    points = [(ankle, np.zeros(3))]
    toe = skeleton.index(roles[f"{side}_toe"]) if f"{side}_toe" in roles else None
    chain = [ankle] if toe is None else [toe]
    if toe is not None:
        points.append((toe, np.zeros(3)))
    for j in chain:
        role = f"{side}_toe" if toe is not None else f"{side}_ankle"
        end = bone_end(skeleton, roles, role)
        if end is not None:
            points.append((end, np.zeros(3)))
        elif j in skeleton.end_sites:
            points.append((j, np.asarray(skeleton.end_sites[j], dtype=float)))
    return points


def skeleton_roles(skeleton: Skeleton) -> RoleMap:
    """:func:`map_roles` on a skeleton's names, hierarchy and rest pose (e.g. a motion library's)."""
    pos = np.zeros((skeleton.n_joints, 3))
    for j in range(skeleton.n_joints):
        p = skeleton.parents[j]
        pos[j] = skeleton.offsets[j] if p < 0 else pos[p] + skeleton.offsets[j]
    return map_roles(skeleton.names, skeleton.parents, pos)


# ------------------------------------------------------------------------------------------------
# loading

#: Formats :func:`load_rig` reads, by file suffix.
RIG_SUFFIXES = (".fbx", ".glb", ".gltf", ".bvh")


def _bvh_unit_scale(height: float) -> float:
    """Metres per file unit of a BVH rig from its height in file units (metres or centimetres)."""
    if 0.3 <= height <= 3.0:
        return 1.0
    if 30.0 <= height <= 300.0:
        return 0.01
    raise RigError(
        f"cannot tell the rig's units from its height ({height:g} units): give its scale "
        "(metres per unit)",
        code="rig_units",
        field="scale",
    )


def _bvh_skeleton(path: Path) -> Skeleton:
    """A BVH rig's hierarchy (its frames are not read); the reader's errors as ``RigError``
    (``rig_too_complex`` past its limits, else ``rig_unreadable``) naming the file, not its
    folder."""
    from dancegraph.errors import MotionFileError
    from dancegraph.motion.bvh import read_bvh_skeleton

    try:
        return read_bvh_skeleton(path)
    except MotionFileError as exc:
        where = exc.path if exc.line is None else f"{exc.path}:{exc.line}"
        why = exc.message.removeprefix(f"{where}: ")
        line = "" if exc.line is None else f":{exc.line}"
        code = "rig_too_complex" if exc.code == "bvh_too_complex" else "rig_unreadable"
        raise RigError(f"{path.name}{line}: {why}", code=code, field=path.name) from None


def rig_summary(path: str | Path, mapping: dict[str, str] | None = None) -> dict:
    """:meth:`Rig.summary` of the rig file at ``path`` (what an upload keeps): the function a
    sandboxed child runs, so the mesh never travels back."""
    return load_rig(path, mapping=mapping).summary()


def load_rig(
    path: str | Path,
    *,
    mapping: dict[str, str] | None = None,
    scale: float | None = None,
) -> Rig:
    """Read a rig file (FBX, GLB/glTF, BVH) and map its roles.

    ``mapping`` overrides roles (role → joint name). ``scale``: metres per file unit; default
    the file's own unit for FBX and glTF (metres), and for BVH guessed from the rig's height
    (m or cm). Raises ``RigError`` (``rig_unreadable``, ``rig_format`` and the codes of
    :func:`build_rig`).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in RIG_SUFFIXES:
        raise RigError(
            f"{path.name}: a rig must be one of {', '.join(RIG_SUFFIXES)}",
            code="rig_format",
            field=path.name,
        )
    if not path.is_file():
        raise RigError(f"no such file {path.name}", code="rig_unreadable", field=path.name)
    source = {"format": suffix.lstrip(".").replace("gltf", "glb"), "file": path.name}
    if suffix == ".bvh":
        sk = _bvh_skeleton(path)
        pos = np.zeros((sk.n_joints, 3))
        for j in range(sk.n_joints):
            p = sk.parents[j]
            pos[j] = sk.offsets[j] if p < 0 else pos[p] + sk.offsets[j]
        if scale is None:
            scale = _bvh_unit_scale(float(np.ptp(pos, axis=0).max()))
        mats = np.tile(np.eye(4), (sk.n_joints, 1, 1))
        mats[:, :3, 3] = pos * scale
        return build_rig(
            sk.names,
            sk.parents,
            mats,
            mapping=mapping,
            unit_scale=scale,
            source=source,
            end_sites={sk.names[j]: v * scale for j, v in sk.end_sites.items()},
        )
    if suffix in (".glb", ".gltf"):
        from dancegraph.motion.gltf import read_gltf_rig

        names, parents, mats, mesh, ancestors = read_gltf_rig(path)
    else:
        from dancegraph.motion.ufbx_reader import read_fbx_rig

        names, parents, mats, mesh, ancestors = read_fbx_rig(path)
    if scale is not None:
        mats = mats.copy()
        mats[:, :3, 3] *= scale
        if mesh is not None:
            mesh.positions = mesh.positions * scale
        # the world is scaled: so is the top node the skeleton hangs from
        top = np.diag([scale, scale, scale, 1.0])
        ancestors = {j: [("scale", top)] + chain for j, chain in ancestors.items()}
    return build_rig(
        names,
        parents,
        mats,
        mesh=mesh,
        mapping=mapping,
        unit_scale=1.0 if scale is None else scale,
        source=source,
        ancestors=ancestors,
    )
