"""Retargeting: a dance on the motion library's skeleton → the same dance on a user's rig.

The method follows the usual production retargeter (Unreal's IK Retargeter, HumanIK): a
retarget pose aligns the two rest poses bone by bone, rotations are transferred per humanoid
role in world space, the root's path is scaled by the hip-height ratio, and two-bone IK on the
target's legs plants its feet where the source's feet are planted and keeps them on the floor.

:func:`retarget` runs these named steps over one :class:`RetargetParams`:

1. ``plan`` (:func:`plan_retarget`) — both skeletons in one canonical frame (Y up, facing +Z);
   per target joint the source joint playing the same role and the alignment rotation that
   turns the target's rest bone direction onto the source's (T-pose vs A-pose, other rolls
   and axes); the hip-height ratio; the target's foot points and floor;
2. ``transfer`` — each mapped target joint takes its source joint's world rotation (from rest)
   times its alignment; unmapped joints (twist bones, extra spine or finger segments, face)
   keep their bind pose relative to their parent;
3. ``root`` — the hips' path scaled by the ratio, its height measured from the floor;
4. ``feet`` — at the source's foot contacts, each target foot is pinned to one place with its
   lowest point on the floor; elsewhere no foot point goes below the floor; the pelvis is
   lowered where a leg could not reach, then two-bone IK bends the legs onto the targets;
5. ``output`` — local rotations in the rig's own axes, continuous in time (no sign flips).

The report carries the checks of issue 21: the lowest foot point's distance to the floor at
contacts, foot sliding at contacts (target and source), the world-direction error of the mapped
limb bones, the largest frame-to-frame joint rotation, and the time taken.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d, maximum_filter1d

from dancegraph.errors import DanceGraphError
from dancegraph.motion import quat
from dancegraph.motion.contacts import _segments, foot_contacts, two_bone_ik
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.rig import (
    LIMB_ROLES,
    SIDES,
    Rig,
    RoleMap,
    bone_end,
    canonical_frame,
    foot_points,
    skeleton_roles,
)
from dancegraph.motion.skeleton import Motion, Skeleton


@dataclass(frozen=True)
class RetargetParams:
    """Parameters of :func:`retarget`.

    - ``foot_ik``: plant the feet at the source's contacts and keep them above the floor;
    - ``hand_ik``: put the wrists where the source's are relative to the hips (scaled by the
      ratio) by two-bone IK on the arms, instead of where the arms' rotations take them;
    - ``root_scale``: scale of the root's path (None: the hip-height ratio of the two rigs);
    - ``contact_blend_s``: seconds over which a foot correction fades in and out around a contact;
    - ``pelvis_smooth_s``: smoothing (Gaussian sigma, s) of the pelvis drop that lets legs reach;
    - ``reach``: share of a leg's length the IK may stretch it to (a straight leg pops).
    """

    foot_ik: bool = True
    hand_ik: bool = False
    root_scale: float | None = None
    contact_blend_s: float = 0.1
    pelvis_smooth_s: float = 0.08
    reach: float = 0.995


@dataclass
class RetargetPlan:
    """What :func:`plan_retarget` works out once per (source skeleton, rig) pair.

    ``source_joint``: ``(Jt,)`` source joint per target joint (-1: unmapped);
    ``align``: ``(Jt, 4)`` alignment rotations (canonical frame); ``target``: the rig's skeleton
    with offsets in the canonical frame; ``src_to_canon`` / ``tgt_to_canon``: ``(4,)``;
    ``ratio``: hip-height ratio target / source; ``hips``: target hips joint; ``root_chain``:
    canonical offset from the root joint to the hips at rest; ``feet``: per side the target foot
    points ``[(joint, offset)]`` and their rest clearance above the floor; ``limbs``: mapped
    limb bones as ``(role, src joint, src end, tgt joint, tgt end)``.
    """

    source_joint: np.ndarray
    align: np.ndarray
    target: Skeleton
    src_to_canon: np.ndarray
    tgt_to_canon: np.ndarray
    ratio: float
    hips: int
    src_hips: int
    root_chain: np.ndarray
    feet: list[tuple[list[tuple[int, np.ndarray]], np.ndarray]]
    src_feet: list[list[tuple[int, np.ndarray]]]
    legs: list[tuple[int, int, int]]
    arms: list[tuple[int, int, int, int]]
    limbs: list[tuple[str, int, int, int, int]]
    floor: float
    src_sole: float
    tgt_sole: float


def _rotate_all(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    return quat.rotate(np.broadcast_to(q, v.shape[:-1] + (4,)), v)


def _mapped_offsets(sk: Skeleton, f) -> Skeleton:
    """``sk`` with ``f`` applied to its offsets and End Sites (a rotation, a change of units)."""
    ends = {j: f(v) for j, v in sk.end_sites.items()}
    return Skeleton(sk.names, sk.parents, f(sk.offsets), sk.channels, ends, dict(sk.canonical))


def _rest_positions(sk: Skeleton) -> np.ndarray:
    pos = np.zeros((sk.n_joints, 3))
    for j in range(sk.n_joints):
        p = sk.parents[j]
        pos[j] = sk.offsets[j] if p < 0 else pos[p] + sk.offsets[j]
    return pos


def _bone_direction(sk: Skeleton, roles: dict[str, str], role: str, pos: np.ndarray):
    """Unit rest direction of a role's bone (canonical positions ``pos``), or None when unclear."""
    j = sk.index(roles[role])
    if role == "head":
        return None  # a head's children (eyes, jaw, top) point anywhere: it follows the neck
    end = bone_end(sk, roles, role)
    if end is not None and (len(sk.children(j)) == 1 or _is_role_child(sk, roles, role, end)):
        v = pos[end] - pos[j]
    elif not sk.children(j) and j in sk.end_sites:
        v = sk.end_sites[j]
    else:
        return None
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else None


def _is_role_child(sk: Skeleton, roles: dict[str, str], role: str, end: int) -> bool:
    return sk.names[end] in set(roles.values())


def _frame(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """Orthonormal basis (columns) with ``primary`` first and ``secondary`` made orthogonal."""
    a = primary / np.linalg.norm(primary)
    if abs(a @ secondary) > 0.95:
        secondary = np.array([0.0, 1.0, 0.0]) if abs(a[1]) < 0.95 else np.array([0.0, 0.0, 1.0])
    b = secondary - (secondary @ a) * a
    b /= np.linalg.norm(b)
    return np.stack([a, b, np.cross(a, b)], axis=1)


def plan_retarget(source: Skeleton, rig: Rig, source_roles: RoleMap | None = None) -> RetargetPlan:
    """Step 1 of :func:`retarget` (see the module docstring); RetargetError if roles are missing."""
    from scipy.spatial.transform import Rotation

    src_roles = (source_roles or skeleton_roles(source)).roles
    tgt_roles = rig.roles.roles
    missing = [r for r in ("hips", "left_hip", "right_hip", "spine") if r not in src_roles]
    if missing:
        raise DanceGraphError(
            f"the source skeleton has no joint for {', '.join(missing)}",
            code="retarget_source_unmapped",
            field=missing[0],
        )
    src_rest = _rest_positions(source)
    src_to_canon = canonical_frame(src_rest, {n: i for i, n in enumerate(source.names)}, src_roles)
    tgt_to_canon = np.asarray(rig.to_canonical, dtype=float)
    src_pos = _rotate_all(src_to_canon, src_rest)
    tgt_sk = rig.skeleton
    target = _mapped_offsets(tgt_sk, lambda v: _rotate_all(tgt_to_canon, v))
    src_canon_sk = _mapped_offsets(source, lambda v: _rotate_all(src_to_canon, v))
    tgt_pos = _rest_positions(target)
    n_t = target.n_joints
    source_joint = np.full(n_t, -1, dtype=np.int64)
    align = np.zeros((n_t, 4))
    align[:, 3] = 1.0
    has_align = np.zeros(n_t, dtype=bool)
    for role, name in tgt_roles.items():
        if role not in src_roles:
            continue
        j = target.index(name)
        s = source.index(src_roles[role])
        source_joint[j] = s
        dt = _bone_direction(target, tgt_roles, role, tgt_pos)
        ds = _bone_direction(src_canon_sk, src_roles, role, src_pos)
        if dt is None or ds is None:
            continue
        second = (
            np.array([0.0, 1.0, 0.0])
            if role.endswith(("_ankle", "_toe"))
            else np.array([0.0, 0.0, 1.0])
        )
        m = _frame(ds, second) @ _frame(dt, second).T
        align[j] = Rotation.from_matrix(m).as_quat()
        has_align[j] = True
    for j in range(n_t):  # a mapped joint without a direction takes its nearest ancestor's
        if source_joint[j] >= 0 and not has_align[j]:
            a = target.parents[j]
            while a >= 0 and not has_align[a]:
                a = target.parents[a]
            if a >= 0:
                align[j] = align[a]
            has_align[j] = True

    def sole(sk: Skeleton, roles: dict, pos: np.ndarray) -> tuple[float, list]:
        pts = [foot_points(sk, roles, side) for side in SIDES]
        heights = [pos[j, 1] + off[1] for side in pts for j, off in side]
        return float(min(heights)), pts

    src_sole, src_feet = sole(src_canon_sk, src_roles, src_pos)
    tgt_sole, tgt_feet = sole(target, tgt_roles, tgt_pos)
    hips = target.index(tgt_roles["hips"])
    src_hips = source.index(src_roles["hips"])
    src_height = src_pos[src_hips, 1] - src_sole
    tgt_height = tgt_pos[hips, 1] - tgt_sole
    if src_height <= 0 or tgt_height <= 0:
        raise DanceGraphError(
            "the hips are not above the feet in the rest pose", code="rig_degenerate", field="hips"
        )
    floor = float(rig.floor)
    feet = []
    for side_pts in tgt_feet:
        clearance = np.array([tgt_pos[j, 1] + off[1] - floor for j, off in side_pts])
        feet.append((side_pts, clearance))
    legs = [
        (
            target.index(tgt_roles[f"{side}_hip"]),
            target.index(tgt_roles[f"{side}_knee"]),
            target.index(tgt_roles[f"{side}_ankle"]),
        )
        for side in SIDES
    ]
    arms = [
        (
            target.index(tgt_roles[f"{side}_shoulder"]),
            target.index(tgt_roles[f"{side}_elbow"]),
            target.index(tgt_roles[f"{side}_wrist"]),
            source.index(src_roles[f"{side}_wrist"]),
        )
        for side in SIDES
        if all(
            f"{side}_{p}" in tgt_roles and f"{side}_{p}" in src_roles
            for p in ("shoulder", "elbow", "wrist")
        )
    ]
    limbs = []
    for role in LIMB_ROLES:
        if role in tgt_roles and role in src_roles:
            te = bone_end(target, tgt_roles, role)
            se = bone_end(source, src_roles, role)
            if te is not None and se is not None:
                limbs.append(
                    (role, source.index(src_roles[role]), se, target.index(tgt_roles[role]), te)
                )
    root = 0
    return RetargetPlan(
        source_joint=source_joint,
        align=quat.normalize(align),
        target=target,
        src_to_canon=src_to_canon,
        tgt_to_canon=tgt_to_canon,
        ratio=float(tgt_height / src_height),
        hips=hips,
        src_hips=src_hips,
        root_chain=tgt_pos[hips] - tgt_pos[root],
        feet=feet,
        src_feet=src_feet,
        legs=legs,
        arms=arms,
        limbs=limbs,
        floor=floor,
        src_sole=src_sole,
        tgt_sole=tgt_sole,
    )


def _propagate(target: Skeleton, g: np.ndarray, driven: np.ndarray) -> None:
    """Joints not ``driven`` keep their bind pose relative to their parent: ``G_j = G_parent``."""
    for j in range(target.n_joints):
        p = target.parents[j]
        if not driven[j]:
            g[:, j] = g[:, p] if p >= 0 else quat.identity((g.shape[0],))


def _fk(target: Skeleton, root: np.ndarray, g: np.ndarray) -> np.ndarray:
    """World positions ``(F, J, 3)`` from world deltas ``g`` (BVH convention)."""
    pos = np.empty(g.shape[:2] + (3,))
    for j in range(target.n_joints):
        p = target.parents[j]
        pos[:, j] = root if p < 0 else pos[:, p] + quat.rotate(g[:, p], target.offsets[j])
    return pos


def _point(pos: np.ndarray, g: np.ndarray, joint: int, off: np.ndarray) -> np.ndarray:
    if not np.any(off):
        return pos[:, joint]
    return pos[:, joint] + quat.rotate(g[:, joint], np.broadcast_to(off, pos[:, joint].shape))


def _foot_targets(
    plan: RetargetPlan,
    pos: np.ndarray,
    g: np.ndarray,
    contacts: np.ndarray,
    blend: int,
    *,
    pin: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per side the foot's correction ``(F, 2, 3)``, its weight ``(F, 2)`` and anchor point index.

    At contacts: the anchor point (the lower one, on average over the run) is held at its mean
    ground-plane position and the foot's lowest point (less its rest clearance) on the floor;
    elsewhere the foot is lifted only where it would go below the floor. Corrections fade in
    and out over ``blend`` frames around each run.
    """
    n = pos.shape[0]
    corr = np.zeros((n, 2, 3))
    weight = np.zeros((n, 2))
    anchors = np.zeros((n, 2), dtype=np.int64)
    for side, (points, clearance) in enumerate(plan.feet):
        pts = np.stack([_point(pos, g, j, off) for j, off in points], axis=1)  # (F, P, 3)
        above = pts[..., 1] - clearance[None, :] - plan.floor  # (F, P)
        sole = above.min(axis=1)
        lift = np.maximum(0.0, -sole)
        corr[:, side, 1] = lift
        weight[:, side] = (lift > 0).astype(float)
        if not pin:
            continue
        for start, stop in _segments(contacts[:, side]):
            a = int(np.argmin(above[start:stop].mean(axis=0)))
            anchors[start:stop, side] = a
            p = pts[start:stop, a]
            corr[start:stop, side, 0] = p[:, 0].mean() - p[:, 0]
            corr[start:stop, side, 2] = p[:, 2].mean() - p[:, 2]
            corr[start:stop, side, 1] = -sole[start:stop]
            weight[start:stop, side] = 1.0
            for edge, frames in (
                (start, range(start - blend, start)),
                (stop - 1, range(stop, stop + blend)),
            ):
                for f in frames:
                    if 0 <= f < n and not contacts[f, side]:
                        w = 1.0 - abs(f - edge) / (blend + 1)
                        w = w * w * (3.0 - 2.0 * w)
                        c = corr[edge, side].copy()
                        c[1] = max(c[1] * w, lift[f])  # never into the floor
                        c[[0, 2]] *= w
                        if w >= weight[f, side] or lift[f] > 0:
                            corr[f, side] = c
                            weight[f, side] = max(w, weight[f, side])
    return corr, weight, anchors


def retarget(
    source: Motion,
    rig: Rig,
    params: RetargetParams | None = None,
    *,
    plan: RetargetPlan | None = None,
) -> tuple[Motion, dict]:
    """The dance ``source`` on ``rig``: a motion on ``rig.skeleton`` (rig axes, metres) and a report.

    ``source``: a motion on a skeleton whose roles :func:`~dancegraph.motion.rig.skeleton_roles`
    finds (the CMU libraries do), Y up. ``plan``: a precomputed :func:`plan_retarget` for this
    pair. Raises ``DanceGraphError`` (``retarget_source_unmapped``, ``retarget_failed`` when a
    non-finite value appears). Report: see :func:`retarget_report`.
    """
    t0 = time.process_time()
    params = params or RetargetParams()
    plan = plan or plan_retarget(source.skeleton, rig)
    target = plan.target
    n = source.n_frames
    fps = source.fps

    # 2. transfer: world rotations (from rest) per role, in the canonical frame
    src_pos, src_g = forward_kinematics(source)
    c = plan.src_to_canon
    src_g_c = quat.multiply(quat.multiply(c, src_g), quat.conjugate(c))
    src_pos_c = _rotate_all(c, src_pos)
    driven = plan.source_joint >= 0
    g = np.empty((n, target.n_joints, 4))
    g[:, driven] = quat.multiply(src_g_c[:, plan.source_joint[driven]], plan.align[driven][None])
    _propagate(target, g, driven)

    # 3. root: the hips' path scaled by the hip-height ratio, height above the floor
    ratio = params.root_scale if params.root_scale is not None else plan.ratio
    src_floor = float(np.percentile(_src_sole(plan, src_pos_c, src_g_c), 5))
    hips_path = src_pos_c[:, plan.src_hips].copy()
    hips_path[:, [0, 2]] *= ratio
    hips_path[:, 1] = plan.tgt_sole + ratio * (hips_path[:, 1] - src_floor)
    root = hips_path - plan.root_chain  # joints above the hips are unmapped: they keep rest
    pos = _fk(target, root, g)

    # 4. feet: contacts of the source, pelvis drop where a leg cannot reach, two-bone IK
    contacts = foot_contacts(src_pos, fps, source.skeleton, src_g)
    extra_report: dict[str, object] = {}
    if params.foot_ik:
        blend = max(1, int(round(params.contact_blend_s * fps)))
        corr, weight, anchors = _foot_targets(plan, pos, g, contacts, blend)
        drop = np.zeros(n)
        for side, (hip, knee, ankle) in enumerate(plan.legs):
            length = params.reach * (
                np.linalg.norm(pos[0, knee] - pos[0, hip])
                + np.linalg.norm(pos[0, ankle] - pos[0, knee])
            )
            goal = pos[:, ankle] + corr[:, side] * (weight[:, side] > 0)[:, None]
            d_xz = np.linalg.norm(goal[:, [0, 2]] - pos[:, hip][:, [0, 2]], axis=1)
            v = pos[:, hip, 1] - goal[:, 1]
            reach_v = np.sqrt(np.maximum(length**2 - d_xz**2, 0.0))
            drop = np.maximum(drop, v - reach_v)
        if drop.max() > 0:
            width = max(1, int(round(3 * params.pelvis_smooth_s * fps)))
            drop = maximum_filter1d(np.maximum(drop, 0.0), 2 * width + 1)
            drop = gaussian_filter1d(drop, max(0.5, params.pelvis_smooth_s * fps), mode="nearest")
            root[:, 1] -= drop
            pos = _fk(target, root, g)
            corr, weight, anchors = _foot_targets(plan, pos, g, contacts, blend)
        for side, chain in enumerate(plan.legs):
            active = weight[:, side] > 0
            if active.any():
                goal = pos[active, chain[2]] + corr[active, side]
                _limb_ik(target, g, pos, chain, goal, active)
        _propagate(target, g, driven | _chain_mask(target, plan.legs))
        pos = _fk(target, root, g)
        extra_report["pelvis_drop_max_m"] = float(drop.max())
    else:
        anchors = np.zeros((n, 2), dtype=np.int64)
    if params.hand_ik and plan.arms:
        # the wrists where the source's are, relative to the hips, scaled by the ratio
        everywhere = np.ones(n, dtype=bool)
        misses = []
        for shoulder, elbow, wrist, src_wrist in plan.arms:
            offset = src_pos_c[:, src_wrist] - src_pos_c[:, plan.src_hips]
            goal = pos[:, plan.hips] + ratio * offset
            _limb_ik(target, g, pos, (shoulder, elbow, wrist), goal, everywhere)
            misses.append(goal)
        _propagate(target, g, driven | _chain_mask(target, plan.legs + [a[:3] for a in plan.arms]))
        pos = _fk(target, root, g)
        err = np.concatenate(
            [
                np.linalg.norm(pos[:, a[2]] - goal, axis=1)
                for a, goal in zip(plan.arms, misses, strict=True)
            ]
        )
        extra_report["hand_error_m"] = {"median": float(np.median(err)), "max": float(err.max())}

    # 5. output: local rotations in the rig's axes
    local = g.copy()
    parents = target.parents
    nonroot = parents >= 0
    local[:, nonroot] = quat.multiply(quat.conjugate(g[:, parents[nonroot]]), g[:, nonroot])
    back = quat.conjugate(plan.tgt_to_canon)
    local = quat.multiply(quat.multiply(back, local), plan.tgt_to_canon)
    local = _continuous(quat.normalize(local))
    root_rig = _rotate_all(back, root)
    if not (np.isfinite(local).all() and np.isfinite(root_rig).all()):
        raise DanceGraphError("retargeting produced non-finite values", code="retarget_failed")
    motion = Motion(rig.skeleton, fps, root_rig, local)
    report = retarget_report(plan, src_pos_c, src_g_c, pos, g, contacts, anchors, fps)
    report.update(extra_report)
    report["ratio"] = ratio
    report["world"] = {  # the rig as it stands in its file: metres, world space
        "height_m": round(rig.height(), 4),
        "hip_height_m": round(float(_rest_positions(target)[plan.hips, 1] - plan.tgt_sole), 4),
        "up_axis": rig.up_axis(),
        "ancestors": [name for name, _ in rig.ancestors],
    }
    report["cpu_seconds"] = round(time.process_time() - t0, 4)
    return motion, report


def _chain_mask(target: Skeleton, chains) -> np.ndarray:
    """Joints on the ``(top, middle, end)`` limb chains (set by the IK; kept by propagation)."""
    mask = np.zeros(target.n_joints, dtype=bool)
    for top, _middle, end in chains:
        j = end
        while j >= 0 and j != target.parents[top]:
            mask[j] = True
            j = target.parents[j]
    return mask


def _limb_ik(
    target: Skeleton,
    g: np.ndarray,
    pos: np.ndarray,
    chain: tuple[int, int, int],
    goal: np.ndarray,
    active: np.ndarray,
) -> None:
    """Two-bone IK on ``chain`` (thigh, shin, foot or upper arm, forearm, hand) at ``active``
    frames so its end reaches ``goal (A, 3)``; updates ``g`` in place. Joints between the chain's
    joints (split bones) turn with the bone they sit on; the end keeps its world rotation."""
    top, middle, end = chain
    new_top, new_middle = two_bone_ik(
        pos[active, top],
        pos[active, middle],
        pos[active, end],
        goal,
        g[active, top],
        g[active, middle],
    )
    g[active, top] = new_top
    for lower, upper, value in ((middle, top, new_top), (end, middle, new_middle)):
        j = target.parents[lower]
        while j != upper and j >= 0:
            g[active, j] = value
            j = target.parents[j]
    g[active, middle] = new_middle


def _src_sole(plan: RetargetPlan, pos: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``(F,)`` the source's lowest foot point per frame (canonical heights)."""
    heights = []
    for side_pts in plan.src_feet:
        for j, off in side_pts:
            heights.append(_point(pos, g, j, off)[:, 1])
    return np.min(np.stack(heights, axis=1), axis=1)


def _continuous(q: np.ndarray) -> np.ndarray:
    """``(F, J, 4)`` with each frame's sign chosen nearest to the previous frame (no flips)."""
    out = q.copy()
    flips = np.cumsum(np.sum(q[1:] * q[:-1], axis=-1) < 0, axis=0) % 2
    out[1:][flips.astype(bool)] *= -1.0
    return out


def _angle(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    cos = np.sum(u * v, axis=-1) / np.maximum(
        np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1), 1e-12
    )
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _sliding(points: np.ndarray, mask: np.ndarray, fps: float) -> tuple[float, int]:
    step = np.linalg.norm(np.diff(points[:, [0, 2]], axis=0), axis=-1)
    both = mask[1:] & mask[:-1]
    return (float(step[both].mean() * fps), int(both.sum())) if both.any() else (0.0, 0)


def retarget_report(
    plan: RetargetPlan,
    src_pos: np.ndarray,
    src_g: np.ndarray,
    pos: np.ndarray,
    g: np.ndarray,
    contacts: np.ndarray,
    anchors: np.ndarray,
    fps: float,
) -> dict:
    """The checks of a retargeted dance (canonical frame), all from world positions.

    - ``floor_error_m``: at contact frames, the foot's lowest point (each point less its rest
      clearance) minus the floor: ``median_abs``, ``p95_abs``, ``max_abs``; ``penetration_m``: the
      deepest any foot point goes below the floor at any frame;
    - ``sliding_m_s`` / ``source_sliding_m_s``: mean ground-plane speed of the planted point over
      contact frames (target, and the source's own lower foot point);
    - ``direction_error_deg``: angle between source and target world directions of the mapped
      limb bones: ``median`` over frames and bones, ``p95``, ``per_bone`` medians;
    - ``max_joint_step_deg``: largest rotation of any joint between two frames (target and
      source), which a sign flip or a pop would blow up.
    """
    sole_err, target_slide, source_slide = [], [], []
    penetration = 0.0
    for side, (points, clearance) in enumerate(plan.feet):
        pts = np.stack([_point(pos, g, j, off) for j, off in points], axis=1)
        above = pts[..., 1] - clearance[None, :] - plan.floor
        penetration = max(penetration, float(max(0.0, -(pts[..., 1] - plan.floor).min() - 1e-9)))
        mask = contacts[:, side]
        sole_err.append(above.min(axis=1)[mask])
        for a in range(len(points)):
            m = mask & (anchors[:, side] == a)
            target_slide.append(_sliding(pts[:, a], m, fps))
        src_pts = np.stack(
            [_point(src_pos, src_g, j, off) for j, off in plan.src_feet[side]], axis=1
        )
        for start, stop in _segments(mask):
            a = int(np.argmin(src_pts[start:stop, :, 1].mean(axis=0)))
            m = np.zeros_like(mask)
            m[start:stop] = True
            source_slide.append(_sliding(src_pts[:, a], m, fps))
    err = np.abs(np.concatenate(sole_err)) if sole_err else np.zeros(0)

    def mean_speed(rows: list[tuple[float, int]]) -> float:
        total = sum(k for _, k in rows)
        return float(sum(s * k for s, k in rows) / total) if total else 0.0

    per_bone = {}
    angles = []
    for role, s, se, t, te in plan.limbs:
        angle = _angle(src_pos[:, se] - src_pos[:, s], pos[:, te] - pos[:, t])
        per_bone[role] = round(float(np.median(angle)), 3)
        angles.append(angle)
    all_angles = np.concatenate(angles) if angles else np.zeros(1)

    def max_step(q: np.ndarray) -> float:
        if q.shape[0] < 2:
            return 0.0
        d = np.abs(np.sum(q[1:] * q[:-1], axis=-1))
        return float(np.degrees(2 * np.arccos(np.clip(d, -1.0, 1.0))).max())

    return {
        "frames": int(pos.shape[0]),
        "contact_frames": [int(contacts[:, 0].sum()), int(contacts[:, 1].sum())],
        "floor_error_m": {
            "median_abs": float(np.median(err)) if err.size else 0.0,
            "p95_abs": float(np.percentile(err, 95)) if err.size else 0.0,
            "max_abs": float(err.max()) if err.size else 0.0,
        },
        "penetration_m": penetration,
        "sliding_m_s": mean_speed(target_slide),
        "source_sliding_m_s": mean_speed(source_slide),
        "direction_error_deg": {
            "median": float(np.median(all_angles)),
            "p95": float(np.percentile(all_angles, 95)),
            "per_bone": per_bone,
        },
        "max_joint_step_deg": {"target": max_step(g), "source": max_step(src_g)},
    }


#: Output formats of a dance on a rig, by file suffix.
RIG_OUTPUTS = (".bvh", ".fbx", ".glb", ".usd", ".usda", ".usdc")
#: Largest relative difference of the written character's height from the dance's.
HEIGHT_TOLERANCE = 0.10
#: Largest angle (deg) between the written character's up and the dance's.
UPRIGHT_TOLERANCE_DEG = 30.0


def write_on_rig(
    motion: Motion, rig: Rig, rig_path: str | Path, out_path: str | Path, *, exporter=None
) -> dict:
    """Write a retargeted ``motion`` (on ``rig.skeleton``) by ``out_path``'s suffix, then check it.

    BVH: the rig's joints in its world axes and its own units (a rig read from centimetres is
    written in centimetres); GLB: :func:`~dancegraph.motion.gltf.write_glb` and USD:
    :func:`~dancegraph.motion.usd.write_usd` (the skeleton under the rig's ancestor nodes, with
    the skinned mesh); FBX: the rig file ``rig_path`` itself posed in Blender (its own process,
    ``exporter`` or the shared warm one), meshes included. The written first frame is read back
    and compared with the dance (:func:`check_placement`); a misplaced file is removed. Returns a
    small summary with ``placement``; raises ``DanceGraphError`` (``rig_output_format``),
    ``RigError`` (``rig_output_scale``, ``rig_output_not_upright``, ``rig_output_floor``) or
    ``FbxError``.
    """
    out = Path(out_path)
    suffix = out.suffix.lower()
    if suffix not in RIG_OUTPUTS:
        raise DanceGraphError(
            f"{out.name}: a dance on a rig is written as {', '.join(RIG_OUTPUTS)}",
            code="rig_output_format",
            field=out.name,
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    summary, first = _write(motion, rig, Path(rig_path), out, suffix, exporter)
    try:
        summary["placement"] = check_placement(rig, motion, first)
    except DanceGraphError:
        out.unlink(missing_ok=True)
        raise
    return summary


def _write(motion: Motion, rig: Rig, rig_path: Path, out: Path, suffix: str, exporter):
    """Write one file; returns its summary and its first frame's world joint positions
    ``(J, 3)`` (metres, skeleton order) as read back from what was written."""
    if suffix == ".bvh":
        from dancegraph.motion.bvh import read_bvh, write_bvh

        k = 1.0 / rig.unit_scale
        scaled = _mapped_offsets(motion.skeleton, lambda v: v * k)
        write_bvh(Motion(scaled, motion.fps, motion.root_positions * k, motion.rotations), out)
        back = read_bvh(out, scale=rig.unit_scale)
        first, _ = forward_kinematics(back.slice(0, 1))
        return {"frames": motion.n_frames, "joints": scaled.n_joints}, first[0]
    if suffix == ".glb":
        from dancegraph.motion.gltf import node_worlds, write_glb

        summary = write_glb(motion, rig, out)
        worlds = node_worlds(out)
        return summary, np.array([worlds[n][:3, 3] for n in motion.skeleton.names])
    if suffix in (".usd", ".usda", ".usdc"):
        from dancegraph.motion.usd import joint_world_positions, write_usd

        summary = write_usd(motion, out, rig)
        return summary, joint_world_positions(out, [0])[1][0]
    from dancegraph.motion.fbx import shared_exporter

    positions, g = forward_kinematics(motion)
    with tempfile.TemporaryDirectory(prefix="dg-rig-") as tmp:
        anim = Path(tmp) / "anim.npz"
        np.savez(
            anim,
            names=np.array(motion.skeleton.names, dtype=str),
            g=g,
            positions=positions,
            fps=np.float64(motion.fps),
            unit_scale=np.float64(rig.unit_scale),
        )
        summary = (exporter or shared_exporter()).animate_rig(rig_path, anim, out)
    heads = summary.pop("first_frame")  # a bone Blender renamed is missing: NaN
    return summary, np.array([heads.get(n, [np.nan] * 3) for n in motion.skeleton.names])


def check_placement(rig: Rig, motion: Motion, written: np.ndarray) -> dict:
    """The written file's first frame against the dance's, in world space (metres).

    ``written``: ``(J, 3)`` world joint positions read back from the file, skeleton order (NaN
    rows: joints the file does not name; the others are compared).
    Returns ``height_m`` (the written joints' extent along the rig's world up), ``rig_height_m``
    (the rig's own bind-pose height), ``height_ratio`` (written / dance), ``up_error_deg`` (the
    hips-to-head direction, written against dance), ``floor_offset_m`` (lowest written joint
    less the dance's) and ``upright`` (the written character's up within 30° of world +Y).
    Raises ``RigError``: ``rig_output_scale`` (height off by more than 10 %),
    ``rig_output_not_upright``, ``rig_output_floor`` (more than 5 % of the height off the floor),
    ``rig_output_unreadable`` (fewer than two of the rig's joints found in the file).
    """
    from dancegraph.motion.rig import RigError

    expected = forward_kinematics(motion.slice(0, 1))[0][0]
    seen = np.isfinite(written).all(axis=1)
    if seen.sum() < 2:
        raise RigError(
            "the written file names (almost) none of the rig's joints",
            code="rig_output_unreadable",
            field="joints",
        )
    up = quat.rotate(quat.conjugate(rig.to_canonical), np.array([0.0, 1.0, 0.0]))
    h_exp, h_got = float(np.ptp(expected[seen] @ up)), float(np.ptp(written[seen] @ up))
    hips = rig.joint("hips")
    tops = (j for j in map(rig.joint, ("head", "neck", "chest", "spine")) if j is not None)
    top = next((j for j in tops if seen[j]), hips)  # the spine's highest joint the file names
    figure = written[top] - written[hips] if top != hips else np.full(3, np.nan)  # NaN: unchecked
    out = {
        "height_m": round(h_got, 4),
        "rig_height_m": round(rig.height(), 4),
        "height_ratio": round(h_got / h_exp, 4) if h_exp > 0 else float("inf"),
        "up_error_deg": round(float(_angle(figure, expected[top] - expected[hips])), 3),
        "floor_offset_m": round(float((written[seen] @ up).min() - (expected[seen] @ up).min()), 5),
        "upright": bool(_angle(figure, np.array([0.0, 1.0, 0.0])) <= UPRIGHT_TOLERANCE_DEG),
    }
    if not abs(out["height_ratio"] - 1.0) <= HEIGHT_TOLERANCE:
        raise RigError(
            f"the written character is {h_got:.3f} m tall where the dance on the rig is "
            f"{h_exp:.3f} m (ratio {out['height_ratio']:g})",
            code="rig_output_scale",
            field="height_m",
        )
    if out["up_error_deg"] > UPRIGHT_TOLERANCE_DEG:
        raise RigError(
            f"the written character is turned {out['up_error_deg']:g} degrees from upright",
            code="rig_output_not_upright",
            field="up_error_deg",
        )
    if not abs(out["floor_offset_m"]) <= 0.05 * h_exp:
        raise RigError(
            f"the written character stands {out['floor_offset_m']:g} m off the rig's floor",
            code="rig_output_floor",
            field="floor_offset_m",
        )
    return out


class RigOutput:
    """The render hook that puts each rendered alternative on a user's rig (``render(on_rig=...)``).

    ``rig``: the loaded :class:`~dancegraph.motion.rig.Rig`; ``rig_path``: its file (FBX output
    poses that file in Blender); ``formats``: of ``bvh``, ``fbx``, ``glb``. Calling it with
    ``(k, dance, out_dir)`` retargets ``dance`` and writes ``alternatives/<k>.rig.<fmt>`` (``k``
    an alternative's index, or ``"<index>/<partner>"`` for one dancer of a couple); it
    returns ``(files, report)``: ``{"rig.<fmt>": relative path}`` and the retarget report (with
    each file's ``placement`` check under ``placement.<fmt>``). ``usd`` is written as ``.usd``.
    """

    def __init__(
        self,
        rig: Rig,
        rig_path: str | Path,
        formats: list[str] | tuple[str, ...] = ("bvh", "fbx", "glb", "usd"),
        *,
        exporter=None,
        params: RetargetParams | None = None,
    ):
        self.rig = rig
        self.rig_path = Path(rig_path)
        self.formats = [f for f in ("bvh", "fbx", "glb", "usd") if f in formats]
        self.exporter = exporter
        self.params = params
        self._plan: tuple[int, RetargetPlan] | None = None

    def __call__(self, k: int | str, dance: Motion, out_dir: str | Path) -> tuple[dict, dict]:
        key = id(dance.skeleton)
        if self._plan is None or self._plan[0] != key:
            self._plan = (key, plan_retarget(dance.skeleton, self.rig))
        motion, report = retarget(dance, self.rig, self.params, plan=self._plan[1])
        report["unit_scale"] = self.rig.unit_scale  # the .rig.bvh is in the rig's own units
        files, placement = {}, {}
        for fmt in self.formats:
            rel = f"alternatives/{k}.rig.{fmt}"
            written = write_on_rig(
                motion, self.rig, self.rig_path, Path(out_dir) / rel, exporter=self.exporter
            )
            files[f"rig.{fmt}"] = rel
            placement[fmt] = written["placement"]
        report["placement"] = placement
        return files, report
