"""Seams: where one bar's node hands over to the next, the distance that judges a hand-over, and
the inertialized blend that hides it (docs/rendering.md).

A dance is its bars' nodes laid on the song through one time-warp (``retime.song_phase`` and
``retime.node_warp``): every output frame of bar b shows bar b's node at the source frame whose
beat phase is the song's phase there, and a node's stored frames reach about a beat past both
ends of its bar. So the hand-over from bar b-1's node p to bar b's node q need not sit on the bar
line. ``stitch`` cuts at the frame within ``cut_beats`` of the bar line where p and q, each at
the phase the song has reached there, match best by ``seam_distance`` (pose and velocity of the
main joints, each in its own heading frame): before the cut p dances on past its bar, after it q
starts early or late, and the beats stay where the warp puts them. The graph build links nodes
by the same distance (its minimum over the same window, on a coarser grid), so an edge that
exists is a hand-over the renderer can make smoothly. Where q is the next bar of p's take (the
two show the same motion at the bar line) the take simply continues: no cut, no blend, no seam.

At the cut (``hand_over``) q is turned about +Y and moved on the ground so that its root's
heading and ground position equal p's at the cut frame, then the remaining offsets between p and
q at the cut, of every joint rotation and the root position and of their velocities, are added to
q and decayed to zero over the frames after the cut (inertialization, Bollo, GDC 2016 and 2018):
the cut frame shows p's own pose moving at p's own velocity, and q takes over without a pop. Each
offset decays along Bollo's quintic (zero value, velocity and acceleration at its end) over a
length chosen so that the offset's own acceleration stays below ``MAX_OFFSET_ACC`` at the joint
and the limb below it, never past the next cut.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from dancegraph.motion import quat
from dancegraph.motion.fk import canonical_positions, fk_arrays, with_ancestors
from dancegraph.motion.retime import node_warp, sample_runs, song_phase
from dancegraph.motion.skeleton import CANONICAL_JOINTS, Motion, Skeleton

#: Half-width (beats) of the window around a bar line where the cut may fall.
CUT_BEATS = 1.0
#: Largest acceleration (m/s²) an offset's decay may add to a body point.
MAX_OFFSET_ACC = 6.0
#: Seam distances closer than this count as equal: the cut nearer the bar line wins.
TIE = 0.01
#: Two nodes whose seam distance at the bar line is below this show the same motion there (the
#: next bar of the same take, up to interpolation: about 2.5 mm or mm/s per main joint): the take
#: continues and there is no seam.
SAME = 0.05
#: Least and most decay length of an offset, seconds.
BLEND_MIN_S = 0.1
BLEND_MAX_S = 1.0


# --------------------------------------------------------------------------------------------
# the distance


def main_joint_keys(skeleton: Skeleton) -> list[str]:
    """The canonical joints the skeleton maps, in ``CANONICAL_JOINTS`` order: the joints the seam
    distance (and the graph's transition features) compare."""
    return [k for k in CANONICAL_JOINTS if k in skeleton.canonical]


def seam_features(
    skeleton: Skeleton, root: np.ndarray, rotations: np.ndarray, dt: float | np.ndarray
) -> tuple[np.ndarray, list[int]]:
    """Pose and velocity features of the inner frames of runs of frames.

    ``root (S, W, 3)`` metres and ``rotations (S, W, J, 4)`` local rotations: S runs of W >= 3
    frames, ``dt`` seconds apart (scalar or ``(S,)``). For each of the W-2 inner frames, in the
    heading frame of its root (ground position and heading factored out): the main joints'
    positions (m), their local rotations (the root's without its heading; chordal, 2‖Δq‖ ≈ the
    angle in radians) and their velocities (m/s, central difference of the frames either
    side). Each block is scaled by √K (K main joints), so a block's Euclidean distance equals
    the sum over the joints of the per-joint distances when these are even. Returns
    ``(S, W-2, 10K) float32`` and the block sizes ``[3K, 4K, 3K]`` for ``seam_distance``.
    """
    keys = main_joint_keys(skeleton)
    joints = np.array([skeleton.index(skeleton.canonical[k]) for k in keys])
    s, w = root.shape[:2]
    if w < 3:
        raise ValueError(f"seam_features needs runs of at least 3 frames, got {w}")
    n_j = rotations.shape[-2]
    root = np.asarray(root, dtype=np.float64)
    rot = np.asarray(rotations, dtype=np.float64)
    pos, world = fk_arrays(skeleton, root.reshape(-1, 3), rot.reshape(-1, n_j, 4), joints)
    main = canonical_positions(skeleton, pos, world, keys).reshape(s, w, len(keys), 3)
    yaw = quat.heading_angle(world[:, 0]).reshape(s, w)[:, 1:-1]
    cos, sin = np.cos(yaw)[:, :, None], np.sin(yaw)[:, :, None]  # (S, W-2, 1)
    ox, oz = root[:, 1:-1, None, 0], root[:, 1:-1, None, 2]

    def turned(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:  # by -yaw about +Y
        return np.stack([x * cos - z * sin, y, x * sin + z * cos], axis=-1)

    dt = np.broadcast_to(np.asarray(dt, dtype=np.float64), (s,))
    inner = main[:, 1:-1]
    here = turned(inner[..., 0] - ox, inner[..., 1], inner[..., 2] - oz)
    step = (main[:, 2:] - main[:, :-2]) / (2.0 * dt)[:, None, None, None]
    vel = turned(step[..., 0], step[..., 1], step[..., 2])
    r = rot[:, 1:-1][:, :, joints]  # (S, W-2, K, 4)
    roots = skeleton.parents[joints] < 0
    turn = quat.from_y_angle(-yaw)[:, :, None]  # (S, W-2, 1, 4)
    r[:, :, roots] = quat.multiply(np.broadcast_to(turn, r[:, :, roots].shape), r[:, :, roots])
    r = np.where(r[..., 3:4] < 0.0, -r, r) * 2.0
    k = len(keys)
    feats = np.concatenate(
        [here.reshape(s, w - 2, -1), r.reshape(s, w - 2, -1), vel.reshape(s, w - 2, -1)], axis=2
    )
    return (feats * np.sqrt(k)).astype(np.float32), [3 * k, 4 * k, 3 * k]


def seam_distance(a: np.ndarray, b: np.ndarray, blocks: Sequence[int]) -> np.ndarray:
    """Σ over the feature blocks of ‖a_blk − b_blk‖ for paired rows ``a, b (..., D)`` → ``(...)``:
    the pose term T_d of a hand-over (ChoreoMaster's λ8 term, DESIGN.md §4)."""
    out = np.zeros(np.broadcast_shapes(a.shape[:-1], b.shape[:-1]))
    start = 0
    for size in blocks:
        d = np.asarray(a[..., start : start + size], np.float64) - b[..., start : start + size]
        out += np.sqrt(np.einsum("...i,...i->...", d, d))
        start += size
    return out


# --------------------------------------------------------------------------------------------
# the blend


def limb_reach(skeleton: Skeleton) -> np.ndarray:
    """``(J,)`` metres: the longest chain of bones (End Sites included) below each joint."""
    reach = np.zeros(skeleton.n_joints)
    for j, off in skeleton.end_sites.items():
        reach[j] = np.linalg.norm(off)
    for j in range(skeleton.n_joints - 1, 0, -1):  # children come after parents
        p = skeleton.parents[j]
        reach[p] = max(reach[p], reach[j] + np.linalg.norm(skeleton.offsets[j]))
    return reach


def _quintic(x0: np.ndarray, v0: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """``(7, ...)`` Bollo's quintic from offsets ``x0`` with velocities ``v0`` (per frame) to
    zero value, velocity and acceleration at frame ``lengths`` (broadcast to ``x0``): its
    coefficients of t⁵, t⁴, t³, t², t, 1 and its length, for ``_decay``."""
    T = np.broadcast_to(np.asarray(lengths, dtype=float), x0.shape)
    a0 = (-8.0 * v0 * T - 20.0 * x0) / T**2
    A = -(a0 * T**2 + 6.0 * v0 * T + 12.0 * x0) / (2.0 * T**5)
    B = (3.0 * a0 * T**2 + 16.0 * v0 * T + 30.0 * x0) / (2.0 * T**4)
    C = -(3.0 * a0 * T**2 + 12.0 * v0 * T + 20.0 * x0) / (2.0 * T**3)
    return np.stack([A, B, C, 0.5 * a0, v0, x0, T])


def _decay(quintic: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The offsets of ``_quintic``'s coefficients ``(7, ...)`` at ``t`` frames after the cut
    (broadcast), zero from each one's length on."""
    A, B, C, half_a0, v0, x0, T = quintic
    x = (((A * t + B) * t + C) * t + half_a0) * t * t + v0 * t + x0
    return np.where(t < T, x, 0.0)


def _lengths(
    size: np.ndarray, speed: np.ndarray, fps: float, least: int, most: int | np.ndarray
) -> np.ndarray:
    """Decay length (frames) of offsets that move a body point ``size`` metres at ``speed`` m/s:
    the shortest T whose initial acceleration |8·v/T + 20·x/T²| stays below ``MAX_OFFSET_ACC``,
    between ``least`` and ``most`` (broadcast)."""
    a = MAX_OFFSET_ACC
    t = (8.0 * speed + np.sqrt(64.0 * speed**2 + 80.0 * a * size)) / (2.0 * a)
    return np.clip(np.ceil(t * fps), least, np.maximum(least, most))


def turn_on_ground(
    root: np.ndarray,
    rot0: np.ndarray,
    turn: float | np.ndarray,
    pivot: np.ndarray,
    target: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Root positions ``(..., F, 3)`` and root rotations ``(..., F, 4)`` turned by ``turn``
    radians ``(...)`` about +Y around ground point ``pivot (..., 3)`` and moved so that the
    pivot lands on ground point ``target (..., 3)`` (heights kept). Why one function: a seam's
    hand-over, the render's start placement (``render.place``) and the search's placed bars
    (``search.placed_motion``) all put a motion on the ground this way."""
    q = quat.from_y_angle(np.asarray(turn, dtype=np.float64))[..., None, :]
    ground = np.array([1.0, 0.0, 1.0])
    rel = root - np.asarray(pivot)[..., None, :] * ground
    moved = quat.rotate(np.broadcast_to(q, rel.shape[:-1] + (4,)), rel)
    moved = moved + np.asarray(target)[..., None, :] * ground
    return moved, quat.multiply(np.broadcast_to(q, rot0.shape), rot0)


class _Offsets(NamedTuple):
    """What ``_offsets`` returns for S seams."""

    x0: np.ndarray  # (S, 3) root position offset at the cut, m
    v0: np.ndarray  # (S, 3) its velocity, m per frame
    n_pos: np.ndarray  # (S,) its decay length, frames
    x0r: np.ndarray  # (S, J, 3) joint rotation offsets (rotation vectors)
    v0r: np.ndarray  # (S, J, 3) their velocities, per frame
    n_rot: np.ndarray  # (S, J, 1) their decay lengths, frames
    n: np.ndarray  # (S,) int the longest decay, frames


def _offsets(
    p_root: np.ndarray,
    p_rot: np.ndarray,
    q_root: np.ndarray,
    q_rot: np.ndarray,
    room: np.ndarray,
    length: np.ndarray,
    fps: float,
    reach: np.ndarray,
) -> _Offsets:
    """The offsets between p and q at S cuts and how long each decays.

    ``p_root (S, 3, 3)``, ``p_rot (S, 3, J, 4)``: p's frames before, at and after each cut;
    ``q_root``, ``q_rot``: q's, already on p's ground (``turn_on_ground``); ``room (S,)`` frames a
    decay may take (``BLEND_MAX_S`` caps it), ``length (S,)`` frames of q's segment after the
    cut; ``reach (J,)`` the skeleton's ``limb_reach``."""
    x0 = p_root[:, 1] - q_root[:, 1]
    v0 = 0.5 * ((p_root[:, 2] - p_root[:, 0]) - (q_root[:, 2] - q_root[:, 0]))
    q_rot = quat.same_hemisphere(q_rot, p_rot)
    x0r = quat.to_rotvec(quat.multiply(p_rot[:, 1], quat.conjugate(q_rot[:, 1])))
    v0r = 0.5 * (
        quat.to_rotvec(quat.multiply(p_rot[:, 2], quat.conjugate(p_rot[:, 0])))
        - quat.to_rotvec(quat.multiply(q_rot[:, 2], quat.conjugate(q_rot[:, 0])))
    )
    least = max(1, int(round(BLEND_MIN_S * fps)))
    top = np.maximum(least, np.minimum(room, int(round(BLEND_MAX_S * fps))))
    reach = np.maximum(reach, 0.1)[:, None]
    n_pos = _lengths(
        np.linalg.norm(x0, axis=-1), np.linalg.norm(v0, axis=-1) * fps, fps, least, top
    )
    n_rot = _lengths(
        np.linalg.norm(x0r, axis=-1, keepdims=True) * reach,
        np.linalg.norm(v0r, axis=-1, keepdims=True) * reach * fps,
        fps,
        least,
        top[:, None, None],
    )
    n = np.minimum(length, np.maximum(n_pos, n_rot.max(axis=(1, 2)))).astype(np.int64)
    return _Offsets(x0, v0, n_pos, x0r, v0r, n_rot, n)


def _blend(root: np.ndarray, rot: np.ndarray, cuts: np.ndarray, off: _Offsets) -> None:
    """Add the decaying offsets ``off`` of S seams to the dance ``root (F, 3)``, ``rot (F, J,
    4)`` in place, seam s over its ``off.n[s]`` frames from frame ``cuts[s]`` on."""
    n = off.n
    seam = np.repeat(np.arange(len(n)), n)
    t = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)  # frames after the cut
    rows = np.repeat(np.asarray(cuts, dtype=np.int64), n) + t
    # each seam's coefficients, then every frame's value
    root[rows] += _decay(_quintic(off.x0, off.v0, off.n_pos[:, None])[:, seam], t[:, None])
    offsets = quat.from_rotvec(
        _decay(_quintic(off.x0r, off.v0r, off.n_rot)[:, seam], t[:, None, None])
    )  # (rows, J, 4)
    rot[rows] = quat.normalize(quat.multiply(offsets, quat.same_hemisphere(rot[rows], offsets)))


def hand_over(
    before: Motion,
    after: Motion,
    segment: Motion,
    *,
    blend: bool = True,
    most: int | None = None,
    reach: np.ndarray | None = None,
) -> tuple[Motion, tuple[float, np.ndarray, np.ndarray], int]:
    """q's ``segment`` (its frames from the cut on) continuing p's motion at the cut.

    ``before`` and ``after``: 3 frames each, p's and q's at the frames before, at and after the
    cut (the cut frame is ``segment``'s first). The segment is turned and moved on the ground so
    q's root heading and ground position at the cut equal p's; with ``blend`` the offsets of the
    root position and every joint rotation and of their velocities are decayed over the frames
    after the cut (at most ``most``, default the segment's length); ``reach``: the skeleton's
    ``limb_reach`` when the caller has it. Returns the segment, the
    ground transform applied (turn, pivot, target: see ``turn_on_ground``) and the longest decay in
    frames.
    """
    fps = segment.fps
    turn = float(
        quat.heading_angle(before.rotations[1, 0]) - quat.heading_angle(after.rotations[1, 0])
    )
    pivot, target = after.root_positions[1].copy(), before.root_positions[1].copy()
    rot = segment.rotations.copy()
    root, rot[:, 0] = turn_on_ground(segment.root_positions, rot[:, 0], turn, pivot, target)
    if not blend or segment.n_frames < 2:
        return Motion(segment.skeleton, fps, root, rot), (turn, pivot, target), 0
    q_rot = after.rotations.copy()
    q_root, q_rot[:, 0] = turn_on_ground(after.root_positions, q_rot[:, 0], turn, pivot, target)
    off = _offsets(
        before.root_positions[None],
        before.rotations[None],
        q_root[None],
        q_rot[None],
        np.array([segment.n_frames if most is None else min(most, segment.n_frames)]),
        np.array([segment.n_frames]),
        fps,
        limb_reach(segment.skeleton) if reach is None else reach,
    )
    _blend(root, rot, np.zeros(1, dtype=np.int64), off)
    return Motion(segment.skeleton, fps, root, rot), (turn, pivot, target), int(off.n[0])


# --------------------------------------------------------------------------------------------
# a path of bars


def stitch(
    pieces: Sequence[tuple[Motion, np.ndarray]],
    bar_beats: np.ndarray,
    frames: np.ndarray,
    fps: float,
    *,
    cut_beats: float = CUT_BEATS,
    blend: bool = True,
    partners: Sequence[Sequence[tuple[Motion, np.ndarray]]] = (),
    cut_at: dict | None = None,
) -> tuple[Motion, dict]:
    """The dance of bars laid on the song: one node per music bar, cut where they match best.

    ``pieces``: per bar the node's stored motion (any frame rate) and the frames (fractional) of
    its beats -2 .. 6 in it (``retime.NODE_BEATS``); ``bar_beats (B, 5)`` the song's beat times
    of each bar (s); ``frames (B, 2)`` each bar's output frames ``[start, end)`` at ``fps``
    (``render.bar_frames``). Output frame k shows bar b's node at source frame
    ``node_warp(beats_b)(song_phase(bar_beats)(k / fps) - 4b)``. Each hand-over is cut at the
    frame within ``cut_beats`` of its bar line (and where both nodes have stored frames) with
    the least ``seam_distance``, then joined by ``hand_over`` (``blend`` off: root alignment
    only). Where the two nodes show the same motion at the bar line (distance below ``SAME``: bar
    b's node is the next bar of bar b-1's take) the take simply continues: the cut stays on the
    line, nothing is blended, and it is no seam. ``partners``: the pieces of other dancers on
    the same beats (a couple's other partner) whose seam distances are added to the choice, so
    every dancer stitched with the others as partners is cut at the same frames; ``cut_at``:
    the report of such a stitch, whose ``cuts``, ``distance`` and ``continuous`` are taken
    instead of choosing again (the couple's second dancer).

    Returns the motion of frames ``[frames[0, 0], frames[-1, 1])`` at ``fps`` and a report:
    ``cuts`` (B-1,) output frame where each later bar's node takes over, ``cut_beats`` (B-1,)
    the cut's offset from the bar line in beats, ``distance`` (B-1,) the seam distance at the
    cut, ``continuous`` (B-1,) bool where the take continues (no seam), ``blend_frames``
    (B-1,) the longest offset decay.
    """
    if not pieces:
        raise ValueError("stitch needs at least one bar")
    bar_beats = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    frames = np.asarray(frames, dtype=np.int64).reshape(-1, 2)
    if not len(pieces) == len(bar_beats) == len(frames):
        raise ValueError(
            f"stitch: {len(pieces)} pieces, {len(bar_beats)} bars of beats, {len(frames)} ranges"
        )
    sk = pieces[0][0].skeleton
    for m, _ in pieces[1:]:
        if m.skeleton.names != sk.names:
            raise ValueError("stitch: pieces have different skeletons")
    phase = song_phase(bar_beats)
    warps = [node_warp(b) for _, b in pieces]
    first = int(frames[0, 0]) - 2  # the song's phase at every output frame (and 2 either side)
    u = phase(np.arange(first, int(frames[-1, 1]) + 2) / fps)

    def source(b: int, k: np.ndarray) -> np.ndarray:
        return warps[b](u[np.asarray(k) - first] - 4.0 * b)

    if cut_at is None:
        cuts, distance, flow = _choose_cuts(
            [pieces, *partners], frames, fps, lambda k: u[k - first], source, cut_beats
        )
    else:
        cuts, distance, flow = cut_at["cuts"], cut_at["distance"], cut_at["continuous"]
    bounds = np.concatenate([[frames[0, 0]], cuts, [frames[-1, 1]]])
    # each bar's source frames over its segment [bounds[b], bounds[b+1]) and one frame either
    # side: the three frames about each of its cuts
    src = [source(b, np.arange(bounds[b] - 1, bounds[b + 1] + 2)) for b in range(len(pieces))]
    motions = [m for m, _ in pieces]
    root, rot = sample_runs(motions, [f[1:-2] for f in src])
    n_seams = len(pieces) - 1
    if n_seams:
        # p's three frames about each cut, then q's: (seam, 3 frames)
        p_root, p_rot = sample_runs(motions[:-1], [f[-3:] for f in src[:-1]])
        q_root, q_rot = sample_runs(motions[1:], [f[:3] for f in src[1:]])
        p_root, q_root = p_root.reshape(n_seams, 3, 3), q_root.reshape(n_seams, 3, 3)
        p_rot = p_rot.reshape(n_seams, 3, *p_rot.shape[1:])
        q_rot = q_rot.reshape(n_seams, 3, *q_rot.shape[1:])
        # the ground transform of each later bar (q onto p, p on its own bar's ground): a chain
        turns, targets = np.zeros(n_seams), np.zeros((n_seams, 3))
        pivots = q_root[:, 1].copy()
        q_heading = quat.heading_angle(q_rot[:, 1, 0])
        for s in range(n_seams):
            if s > 0:
                p_root[s], p_rot[s, :, 0] = turn_on_ground(
                    p_root[s], p_rot[s, :, 0], turns[s - 1], pivots[s - 1], targets[s - 1]
                )
            turns[s] = float(quat.heading_angle(p_rot[s, 1, 0]) - q_heading[s])
            targets[s] = p_root[s, 1]
        q_root, q_rot[:, :, 0] = turn_on_ground(q_root, q_rot[:, :, 0], turns, pivots, targets)
        # every later bar's segment onto its ground
        start = bounds[1:-1] - bounds[0]  # the cuts, in the dance's frames
        length = np.diff(bounds)[1:]
        bar = np.repeat(np.arange(n_seams), length)
        later = slice(int(start[0]), None)
        moved, turned = turn_on_ground(
            root[later, None], rot[later, 0, None], turns[bar], pivots[bar], targets[bar]
        )
        root[later], rot[later, 0] = moved[:, 0], turned[:, 0]
        blend_here = np.flatnonzero(blend & ~flow & (length >= 2))
        blends = np.zeros(n_seams, dtype=np.int64)
        if len(blend_here):
            off = _offsets(
                p_root[blend_here],
                p_rot[blend_here],
                q_root[blend_here],
                q_rot[blend_here],
                length[blend_here],
                length[blend_here],
                fps,
                limb_reach(sk),
            )
            _blend(root, rot, start[blend_here], off)
            blends[blend_here] = off.n
    else:
        blends = np.zeros(0, dtype=np.int64)
    dance = Motion(sk, float(fps), root, rot)
    line = frames[1:, 0]
    report = {
        "cuts": cuts,
        "cut_beats": u[cuts - first] - u[line - first],
        "distance": distance,
        "continuous": flow,
        "blend_frames": blends,
    }
    return dance, report


def _choose_cuts(piece_sets, frames, fps, phase, source, cut_beats) -> tuple[np.ndarray, ...]:
    """Per bar line b >= 1: the output frame within ``cut_beats`` of it (and inside both nodes'
    stored frames) where ``seam_distance`` between bar b-1's and bar b's nodes, summed over the
    dancers of ``piece_sets`` (each a list of pieces on the same beats), is least (within
    ``TIE``: the frame nearest the line); each bar keeps at least one frame. Returns the cuts,
    their distances and where the take continues (the distance on the line below ``SAME``: no
    window is searched there)."""
    n_seams = len(piece_sets[0]) - 1
    if n_seams < 1:
        return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0, dtype=bool)
    lines = frames[1:, 0].astype(np.int64)
    on_line, _ = _summed_distances(
        piece_sets, source, fps, np.arange(n_seams), [lines[s : s + 1] for s in range(n_seams)]
    )
    flow = on_line[:, 0] < SAME
    cuts, best = lines.copy(), on_line[:, 0].copy()
    todo = np.flatnonzero(~flow)
    windows = []
    for s in todo:
        k = np.arange(int(frames[s, 0]) + 1, int(frames[s + 1, 1]))
        near = np.abs(phase(k) - 4.0 * (s + 1)) <= cut_beats + 1e-9
        windows.append(k[near | (k == lines[s])])
    if len(todo):
        dist, valid = _summed_distances(piece_sets, source, fps, todo, windows)
    last = int(frames[0, 0])
    for row, s in enumerate(todo):
        k = windows[row]
        ok = (valid[row, : len(k)] | (k == lines[s])) & (k > last)
        d = np.where(ok, dist[row, : len(k)], np.inf)
        i = int(np.lexsort((np.abs(k - lines[s]), np.round(d / TIE)))[0])
        cuts[s], best[s] = k[i], d[i]
        last = int(cuts[s])
    return cuts, best, flow


def _summed_distances(piece_sets, source, fps, seams, candidates):
    """``_distances`` summed over the dancers of ``piece_sets``; valid where valid for all."""
    parts = [_distances(p, source, fps, seams, candidates) for p in piece_sets]
    return sum(d for d, _ in parts), np.logical_and.reduce([v for _, v in parts])


def _distances(pieces, source, fps, seams, candidates):
    """``seam_distance`` between bar s's and bar s+1's nodes at each candidate output frame of
    each seam s of ``seams``: ``(S, W)`` distances and ``(S, W)`` bool where both nodes have the
    frames (padded past each seam's candidates with False)."""
    width = max(len(k) for k in candidates) + 2
    sk = pieces[0][0].skeleton
    needed = with_ancestors(sk, [sk.index(sk.canonical[k]) for k in main_joint_keys(sk)])
    sub = _sub_skeleton(sk, needed)
    # each candidate with the frames either side; padded past the window (masked)
    runs = [np.arange(k[0] - 1, k[0] - 1 + width) for k in candidates]
    valid = np.arange(width - 2) < np.array([len(k) for k in candidates])[:, None]
    n = len(seams)
    feats = []
    for side in (0, 1):
        motions = [pieces[s + side][0] for s in seams]
        idx = np.stack([source(s + side, r) for s, r in zip(seams, runs, strict=True)])
        inside = (idx >= 0.0) & (idx <= np.array([m.n_frames - 1 for m in motions])[:, None])
        valid &= inside[:, :-2] & inside[:, 1:-1] & inside[:, 2:]
        root, rot = sample_runs(motions, idx, needed)
        feats.append(
            seam_features(sub, root.reshape(n, width, 3), rot.reshape(n, width, -1, 4), 1.0 / fps)
        )
    return seam_distance(feats[0][0], feats[1][0], feats[0][1]), valid


def _sub_skeleton(skeleton: Skeleton, joints: Sequence[int]) -> Skeleton:
    """The skeleton of ``joints`` alone (each with its ancestors, in skeleton order): a body
    whose forward kinematics gives the same positions and rotations for them."""
    new = {j: i for i, j in enumerate(joints)}
    names = [skeleton.names[j] for j in joints]
    kept = set(names)
    return Skeleton(
        names=names,
        parents=np.array([new.get(int(skeleton.parents[j]), -1) for j in joints]),
        offsets=skeleton.offsets[list(joints)],
        channels=[skeleton.channels[j] for j in joints],
        end_sites={new[j]: off for j, off in skeleton.end_sites.items() if j in new},
        canonical={k: v for k, v in skeleton.canonical.items() if v in kept},
    )
