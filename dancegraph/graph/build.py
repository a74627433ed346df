"""Build a motion graph from bars of dance (ChoreoMaster §4, DESIGN.md §4).

Every node is one bar of dance stored with the frames of its take from about a beat before its
downbeat to a beat after its closing downbeat, at the take's own frame rate, and the frames of its
beats -2 .. 6 in them (``retime.NODE_BEATS``; those outside the bar are the neighbouring bars' where
they adjoin, else whole beat intervals beyond): all the renderer's time-warp and cut choice need
(``motion.stitch``, docs/rendering.md). Nodes are the bars plus augmentations flagged by tag so
users can exclude them:

- ``mirror`` (every bar): the bar mirrored left/right, id ``<clip>:<bar>~m``;
- ``blend`` (capped): upper body of bar a, time-warped beat to beat onto bar b, over the lower
  body (and root) of bar b, id ``<a>~b<k>``;
- ``shuffle`` (capped): beats 1–2 of bar a followed by beats 3–4 of bar b, joined at a's beat 2
  by the renderer's own hand-over (root alignment and inertialization), id ``<a>~s<k>``;

blends and shuffles only between bars with the same (nearest common) rhythm signature whose styles
are close (within the ``style_quantile`` of all pair distances). All augmentations also carry the
tag ``augmented``.

A node's rhythm signature is the slot pattern of its own kinematic beats (the dataset's per-bar
label, ``BarSet.signature``, not snapped to a common signature): a mirror keeps its bar's, a blend
its upper body's bar's (the pair shares the signature), a shuffle has beats 1–2 of bar a's and
beats 3–4 of bar b's. Where the takes' beats were read from their motion, each node also
stores its ``anchoring``, how well its stops sit on its beats (``node_anchoring``), which the
search's rhythm term prefers.
Style descriptors, motifs and root displacement read each node sampled beat-aligned
(``frames_per_bar`` samples, beat k at sample k·F/4).

Edges p → q where T = λ8·T_d + λ9·T_z < δT. T_d is the seam distance the renderer cuts by
(``stitch.seam_distance`` of ``stitch.seam_features``: main-joint positions, rotations and
velocities, each node in its own heading frame): between p at phase 4 + o of its bar (dancing on
past it) and q at phase o (its own lead-in), the least over the offsets o within ``cut_beats`` of
the bar line in steps of ``cut_step`` beats, where both nodes have the frames (o = 0 always, the
frames clamped). Velocities are taken at the library's median beat length, the song's tempo being
unknown at build. So consecutive bars of a take cost ≈ λ9·T_z, and an edge below δT is a
hand-over the renderer can blend (it searches the same window frame by frame). T_z = ‖z_p − z_q‖
of the style embeddings. ``entry``/``exit`` keep the features at o = 0 (the bar line) for the
search's costs of transitions that are not edges.
Each node keeps at most ``max_out_degree`` cheapest edges; consecutive bars of one take (and their
mirrors) are always linked at their true cost; a node left without out-edges (or in-edges) gets
its ``min_degree`` cheapest ones regardless of δT, counted as ``forced`` in the build report.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from dancegraph.embed import descriptor
from dancegraph.errors import DanceGraphError, ModelFileError
from dancegraph.graph import artifact, choreography
from dancegraph.motion import quat
from dancegraph.motion.fk import canonical_positions, fk_arrays
from dancegraph.motion.mirror import mirror
from dancegraph.motion.retime import (
    BEAT0,
    NODE_BEATS,
    Warp,
    accent_anchors,
    node_warp,
    sample,
)
from dancegraph.motion.skeleton import Motion, Skeleton
from dancegraph.motion.stitch import (
    CUT_BEATS,
    hand_over,
    main_joint_keys,
    seam_distance,
    seam_features,
)
from dancegraph.rhythm.motion import motion_stops
from dancegraph.rhythm.signatures import COMMON_SIGNATURES, nearest_common, to_bits, to_pattern
from dancegraph.store import ObjectStore

Progress = Callable[[str, float], None]
PATH_SAMPLES = 8
#: frames a node keeps beyond its beats -1 and 5 (for velocities at the cut window's ends)
EDGE_FRAMES = 2
#: step (beats) of the central differences of the seam features at build
VELOCITY_STEP_BEATS = 1.0 / 16.0


@dataclass
class BuildParams:
    """Graph build parameters (defaults from DESIGN.md §4 where it has them)."""

    threshold: float = 20.0  # δT
    w_pose: float = 1.0  # λ8
    w_style: float = 1.5  # λ9
    frames_per_bar: int = 48
    cut_beats: float = CUT_BEATS  # half-width of the cut window around a bar line (beats)
    cut_step: float = 0.25  # step of the offsets within it (beats)
    max_out_degree: int = 24
    min_degree: int = 2
    mirror: bool = True
    blend_ratio: float = 0.25
    shuffle_ratio: float = 0.25
    style_quantile: float = 0.1
    n_motifs: int | None = None
    seed: int = 0
    chunk: int = 512
    accent_anchors: bool = True  # move motion-read grids' beats onto the take's stops
    accent_tolerance: float = 0.45  # beats: how far from a grid beat an accent may anchor it
    accent_max_speed: float = 1.5  # bound on a beat interval's stretch or squeeze by the anchors

    def __post_init__(self) -> None:
        if self.frames_per_bar % 4 or self.frames_per_bar < 16:
            raise ValueError("frames_per_bar must be a multiple of 4, at least 16")
        if not 0.0 <= self.cut_beats <= 1.0:
            raise ValueError("cut_beats must be between 0 and 1 (beats)")
        if not 0.0 < self.cut_step <= 1.0:
            raise ValueError("cut_step must be in (0, 1] beats")
        if self.threshold <= 0:
            raise ValueError("threshold must be positive")
        if not 0.0 < self.accent_tolerance < 0.5:
            raise ValueError("accent_tolerance must be in (0, 0.5) beats")
        if not self.accent_max_speed > 1.0:
            raise ValueError("accent_max_speed must be above 1")

    def offsets(self) -> np.ndarray:
        """The cut offsets (beats) the edge distance is the least over: 0 first."""
        k = int(np.floor(self.cut_beats / self.cut_step + 1e-9))
        steps = np.arange(1, k + 1) * self.cut_step
        return np.concatenate([[0.0], -steps, steps])


@dataclass
class BarSet:
    """Bars of dance with the frames of their takes around them, the input of ``build_arrays``.

    Bar i's frames are rows ``ptr[i]:ptr[i+1]`` of ``root (R, 3)`` (metres, the take's world
    frame) and ``rotations (R, J, 4)`` (local, x y z w) at ``fps[i]``: the take's own frames from
    ``EDGE_FRAMES`` before its beat -1 to ``EDGE_FRAMES`` after its beat 5 (clipped to the take);
    ``beats (Nb, 9)`` the frames (fractional, counted from the bar's first row) of its beats
    -2 .. 6 (``retime.NODE_BEATS``). ``clip (Nb,)`` index into ``clips``; ``bar (Nb,)`` bar index in its take;
    ``signature`` 8-character strings, the slots of the bar's kinematic beats (any pattern);
    ``frames (Nb, 2)`` source frame range [start, end) for
    provenance. ``grid_from_motion``: some take's beats were read from its motion (not
    annotated), so the build stores every node's ``anchoring`` for the search; annotated grids
    are the takes' music's beats, where the rhythm signatures already say how the dance sits on
    them (on the beat or syncopated).
    """

    skeleton: Skeleton
    clips: list[str]
    clip: np.ndarray
    bar: np.ndarray
    ptr: np.ndarray
    root: np.ndarray
    rotations: np.ndarray
    beats: np.ndarray
    fps: np.ndarray
    signature: list[str]
    frames: np.ndarray
    clip_tags: dict[str, list[str]] = field(default_factory=dict)
    grid_from_motion: bool = True

    @property
    def duration(self) -> np.ndarray:
        """``(Nb,)`` seconds from each bar's downbeat to its closing downbeat."""
        return (self.beats[:, BEAT0 + 4] - self.beats[:, BEAT0]) / self.fps

    @classmethod
    def from_takes(
        cls,
        skeleton: Skeleton,
        clips: list[str],
        takes: list[tuple[Motion, np.ndarray, np.ndarray, list[str], np.ndarray]],
        clip_tags: dict[str, list[str]] | None = None,
    ) -> BarSet:
        """Bars of whole takes: per clip of ``clips`` a ``(motion, bar_beats (n, 5) s, bar index
        (n,), signatures, source frames (n, 2))`` in bar order (``take_bars``)."""
        roots, rots, beats, fps, clip, bar, sig, frames, ptr = [], [], [], [], [], [], [], [], [0]
        for c, (motion, bar_beats, index, sigs, fr) in enumerate(takes):
            b7, spans = take_bars(motion, bar_beats)
            for lo, hi in spans:
                roots.append(motion.root_positions[lo:hi])
                rots.append(motion.rotations[lo:hi].astype(np.float32))
                ptr.append(ptr[-1] + hi - lo)
            beats.append(b7)
            fps.append(np.full(len(spans), motion.fps))
            clip.append(np.full(len(spans), c))
            bar.append(np.asarray(index))
            sig.extend(sigs)
            frames.append(np.asarray(fr).reshape(-1, 2))
        if not roots:
            raise ValueError("no bars to build from")
        return cls(
            skeleton=skeleton,
            clips=list(clips),
            clip=np.concatenate(clip),
            bar=np.concatenate(bar),
            ptr=np.asarray(ptr, dtype=np.int64),
            root=np.concatenate(roots),
            rotations=np.concatenate(rots),
            beats=np.concatenate(beats),
            fps=np.concatenate(fps),
            signature=sig,
            frames=np.concatenate(frames),
            clip_tags=dict(clip_tags or {}),
        )


#: the phase concentration the dance's stops should reach on the song's beats (issue 24's R
#: target): a node's stop counts for its anchoring by how much nearer its beat it sits than that
ANCHOR_TARGET_R = 0.5
#: frames per second a node is played at, at a steady tempo, to read its stops (the rate the
#: evaluation renders at)
ANCHOR_FPS = 60.0


def node_anchoring(skeleton: Skeleton, nodes: _Nodes, index: np.ndarray) -> np.ndarray:
    """``(len(index),) float32``: how well each node of ``index`` has its stops on its stored
    beats, which the renderer lands on the song's beats.

    Per node: its stored motion played through its own beat warp (``retime.node_warp``) at a
    steady tempo, its bar's mean beat, at ``ANCHOR_FPS``, from beat -1 to beat 5 where it has
    the frames (what the renderer makes of it on an even song); its stops
    (``rhythm.motion.motion_stops``) at bar phases ``φ_k`` in ``[-0.5, 3.5)`` (the windows of
    beats 0..3); returns ``Σ_k (cos 2πφ_k − ANCHOR_TARGET_R) / 4``: a stop on a beat adds, one
    between two beats takes away, most for one on the half beat. Why: the dance's phase
    concentration R is ``Σ cos 2πφ / K`` over all its stops, so a path whose nodes' sums are
    positive has R above the target, and the search can reach it by choosing nodes, not by
    cycling through a few. Raises ``DanceGraphError(code="skeleton_unmapped")`` where the
    skeleton lacks a canonical joint."""
    out = np.empty(len(index), dtype=np.float32)
    for k, i in enumerate(np.asarray(index, dtype=np.int64).tolist()):
        root, rot = nodes.frames(i)
        beats = nodes.beats[i]
        fps = float(nodes.fps[i])
        beat_s = (beats[BEAT0 + 4] - beats[BEAT0]) / 4.0 / fps
        phase = np.arange(-1.0, 5.0, 1.0 / (beat_s * ANCHOR_FPS))
        frames = node_warp(beats)(phase)
        inside = (frames >= 0.0) & (frames <= len(root) - 1)
        phase = phase[inside]
        steady = sample(Motion(skeleton, fps, root, rot), frames[inside])
        steady.fps = ANCHOR_FPS
        stops = np.interp(motion_stops(steady) * ANCHOR_FPS, np.arange(phase.size), phase)
        stops = stops[(stops >= -0.5) & (stops < 3.5)]
        out[k] = np.sum(np.cos(2.0 * np.pi * stops) - ANCHOR_TARGET_R) / 4.0
    return out


def _anchoring(
    skeleton: Skeleton, nodes: _Nodes, kind: np.ndarray, mirror_of: np.ndarray
) -> np.ndarray | None:
    """``node_anchoring`` of every node ``(N,)``, None where the skeleton lacks a canonical
    joint (no stops to read: the graph gets no ``anchoring`` array and the search no anchoring
    term). A mirror copies its bar's: the stop curve weighs left and right alike."""
    mirrored = np.flatnonzero(kind == 1)
    own = np.flatnonzero(kind != 1)
    out = np.empty(nodes.n, dtype=np.float32)
    try:
        out[own] = node_anchoring(skeleton, nodes, own)
    except DanceGraphError as exc:
        if exc.code != "skeleton_unmapped":
            raise
        return None
    out[mirrored] = out[mirror_of[mirrored]]
    return out


def take_bars(motion: Motion, bar_beats: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Where each bar of a take lies in its frames: ``(beats (n, 9), spans [(lo, hi)])``.

    ``bar_beats (n, 5)``: the bars' beat times (s) in take order. Beats -2 and -1 of a bar are the
    previous bar's beats 2 and 3 where that bar ends on this one's downbeat (else whole first-beat
    intervals before the downbeat); beats 5 and 6 likewise the next bar's beats 1 and 2. So two
    adjoining bars of a take warp their shared beats alike. A bar's span is ``[lo, hi)`` frames
    from ``EDGE_FRAMES`` before its beat -1 to ``EDGE_FRAMES`` after beat 5, clipped to the take,
    and its beats are frames counted from ``lo``.
    """
    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    n = len(bb)
    if n == 0:
        return np.zeros((0, len(NODE_BEATS))), []
    tol = 0.25 * np.median(np.diff(bb, axis=1))
    first, last = bb[:, 1] - bb[:, 0], bb[:, 4] - bb[:, 3]
    before = bb[:, :1] - first[:, None] * np.array([2.0, 1.0])  # beats -2, -1
    after = bb[:, 4:] + last[:, None] * np.array([1.0, 2.0])  # beats 5, 6
    if n > 1:
        adjoin = (np.abs(bb[:-1, 4] - bb[1:, 0]) <= tol)[:, None]
        before[1:] = np.where(adjoin, bb[:-1, 2:4], before[1:])
        after[:-1] = np.where(adjoin, bb[1:, 1:3], after[:-1])
    beats = np.concatenate([before, bb, after], axis=1) * motion.fps
    lo = np.floor(beats[:, BEAT0 - 1]).astype(np.int64) - EDGE_FRAMES
    lo = np.clip(lo, 0, motion.n_frames - 1)
    hi = np.ceil(beats[:, BEAT0 + 5]).astype(np.int64) + EDGE_FRAMES + 1
    hi = np.clip(hi, lo + 1, motion.n_frames)
    return beats - lo[:, None], list(zip(lo.tolist(), hi.tolist(), strict=True))


# --------------------------------------------------------------------------------------------
# node motion: ragged frames


@dataclass
class _Nodes:
    """Per-node frames (ragged, like ``BarSet``): the originals and every augmentation."""

    ptr: np.ndarray
    root: np.ndarray
    rotations: np.ndarray
    beats: np.ndarray
    fps: np.ndarray

    @property
    def n(self) -> int:
        return len(self.beats)

    def frames(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        a, b = self.ptr[i], self.ptr[i + 1]
        return self.root[a:b], self.rotations[a:b]

    def sample(self, node: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, ...]:
        """Nodes ``node (M,)`` at their fractional frames ``frames (M,)`` (clamped to each node's
        frames): ``root (M, 3)``, ``rotations (M, J, 4)``, ``inside (M,)`` (not clamped)."""
        first, last = self.ptr[node], self.ptr[node + 1] - 1
        f = first + frames
        inside = (frames >= 0.0) & (f <= last)
        f = np.clip(f, first, last)
        lo = np.floor(f).astype(np.int64)
        hi = np.minimum(lo + 1, last)
        t = f - lo
        root = self.root[lo] + t[:, None] * (self.root[hi] - self.root[lo])
        rot = quat.slerp(
            self.rotations[lo].astype(np.float64), self.rotations[hi].astype(np.float64), t[:, None]
        )
        return root, rot, inside

    def at_phases(self, node: np.ndarray, phases: np.ndarray) -> tuple[np.ndarray, ...]:
        """Every node of ``node (M,)`` at bar phases ``phases (M, P)`` (beats, through its own
        ``node_warp``): ``root (M, P, 3)``, ``rotations (M, P, J, 4)``, ``inside (M, P)``."""
        m, p = phases.shape
        frames = np.stack([node_warp(self.beats[i])(phases[k]) for k, i in enumerate(node)])
        root, rot, inside = self.sample(np.repeat(node, p), frames.reshape(-1))
        return root.reshape(m, p, 3), rot.reshape(m, p, *rot.shape[1:]), inside.reshape(m, p)


def _concat(parts: list[_Nodes]) -> _Nodes:
    sizes = [p.root.shape[0] for p in parts]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    ptr = np.concatenate(
        [parts[0].ptr[:1]] + [p.ptr[1:] + o for p, o in zip(parts, offsets, strict=True)]
    )
    return _Nodes(
        ptr=ptr,
        root=np.concatenate([p.root for p in parts]),
        rotations=np.concatenate([p.rotations for p in parts]),
        beats=np.concatenate([p.beats for p in parts]),
        fps=np.concatenate([p.fps for p in parts]),
    )


def _from_list(items: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]) -> _Nodes:
    sizes = [len(r) for r, _, _, _ in items]
    return _Nodes(
        ptr=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        root=np.concatenate([r for r, _, _, _ in items]),
        rotations=np.concatenate([q for _, q, _, _ in items]).astype(np.float32),
        beats=np.stack([b for _, _, b, _ in items]),
        fps=np.array([f for _, _, _, f in items], dtype=float),
    )


def _mirrored(skeleton: Skeleton, nodes: _Nodes) -> _Nodes:
    """Every node mirrored left/right (same beats)."""
    m = mirror(Motion(skeleton, 30.0, nodes.root, nodes.rotations))
    return _Nodes(
        nodes.ptr.copy(),
        m.root_positions,
        m.rotations.astype(np.float32),
        nodes.beats.copy(),
        nodes.fps.copy(),
    )


def _blended(nodes: _Nodes, a: int, b: int, lower: np.ndarray) -> tuple:
    """Bar a's upper body over bar b's lower body and root: b's frames and beats, a's upper-body
    rotations time-warped onto them beat to beat (the renderer's warp)."""
    root, rot = nodes.frames(b)
    to_a = Warp(nodes.beats[b], nodes.beats[a])(np.arange(len(root), dtype=float))
    _, upper, _ = nodes.sample(np.full(len(root), a), to_a)
    out = rot.astype(np.float64).copy()
    out[:, ~lower] = upper[:, ~lower]
    return root.copy(), out, nodes.beats[b].copy(), float(nodes.fps[b])


def _shuffled(skeleton: Skeleton, nodes: _Nodes, a: int, b: int) -> tuple:
    """Bar a up to its beat 2, then bar b from its beat 2 on (its own frames, shifted by whole
    frames, so it runs on into b's next bar unchanged), joined at a's beat 2 by the renderer's
    hand-over (b's root continues a's; offsets inertialized)."""
    root_a, rot_a = nodes.frames(a)
    root_b, rot_b = nodes.frames(b)
    two = BEAT0 + 2
    cut = int(np.floor(nodes.beats[a, two])) + 1  # a's first frame after its beat 2
    shift = int(round(nodes.beats[b, two] - nodes.beats[a, two]))  # b's frame = ours + shift
    if cut - 1 + shift < 0 or cut + 2 > len(root_a) or cut + 2 + shift > len(root_b):
        raise ValueError("a shuffle needs frames on both sides of the join")
    fps = float(nodes.fps[a])

    def part(root: np.ndarray, rot: np.ndarray, lo: int, hi: int | None = None) -> Motion:
        return Motion(skeleton, fps, root[lo:hi].astype(float), rot[lo:hi].astype(float))

    # the offsets are gone two frames before b's closing downbeat: from there on it is b's take
    most = int(np.floor(nodes.beats[b, BEAT0 + 4])) - 2 - (cut + shift)
    joined, _, _ = hand_over(
        part(root_a, rot_a, cut - 1, cut + 2),
        part(root_b, rot_b, cut - 1 + shift, cut + 2 + shift),
        part(root_b, rot_b, cut + shift),
        most=max(most, 1),
    )
    root = np.concatenate([root_a[:cut], joined.root_positions])
    rot = np.concatenate([rot_a[:cut].astype(np.float64), joined.rotations])
    beats = np.concatenate([nodes.beats[a, : two + 1], nodes.beats[b, two + 1 :] - shift])
    return root, rot, beats, fps


# --------------------------------------------------------------------------------------------
# augmentation


def _lower_body(skeleton: Skeleton) -> np.ndarray:
    """Bool ``(J,)``: the root plus every joint below the hips (legs)."""
    mask = np.zeros(skeleton.n_joints, dtype=bool)
    mask[skeleton.parents < 0] = True
    for key in ("left_hip", "right_hip"):
        if key not in skeleton.canonical:
            continue
        stack = [skeleton.index(key)]
        while stack:
            j = stack.pop()
            mask[j] = True
            stack.extend(skeleton.children(j))
    return mask


def _augment_pairs(
    style: np.ndarray, sig: list[str], clip: np.ndarray, quantile: float, cap: int, seed: int
) -> list[tuple[int, int]]:
    """Ordered pairs (a, b) of different takes, same signature, close style; at most ``cap``,
    each bar used at most twice, closest first (ties broken by ``seed``)."""
    if cap <= 0 or len(sig) < 2:
        return []
    st = np.asarray(style, dtype=np.float64)
    sq = (st * st).sum(1)
    d = np.sqrt(np.maximum(sq[:, None] + sq[None, :] - 2.0 * st @ st.T, 0.0))  # (Nb, Nb)
    same = np.array(sig)[:, None] == np.array(sig)[None, :]
    ok = same & (clip[:, None] != clip[None, :])
    if not ok.any():
        return []
    radius = np.quantile(d[np.triu_indices(len(sig), 1)], quantile)
    a, b = np.nonzero(ok & (d <= radius))
    rng = np.random.default_rng(seed)
    order = np.lexsort((rng.random(a.size), d[a, b]))
    used = np.zeros(len(sig), dtype=int)
    out = []
    for k in order:
        i, j = int(a[k]), int(b[k])
        if used[i] >= 2 or used[j] >= 2:
            continue
        out.append((i, j))
        used[i] += 1
        used[j] += 1
        if len(out) >= cap:
            break
    return out


# --------------------------------------------------------------------------------------------
# node features


def _to_local(points: np.ndarray, origin: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Points ``(N, W, K, 3)`` into frames at ``origin (N, 3)`` (x, z only) turned by ``-yaw (N,)``."""
    shifted = (
        points
        - np.stack([origin[:, 0], np.zeros(len(origin)), origin[:, 2]], axis=1)[:, None, None, :]
    )
    c, s = np.cos(-yaw)[:, None, None], np.sin(-yaw)[:, None, None]
    x, z = shifted[..., 0], shifted[..., 2]
    # rotation about +Y by angle a: x' = x cos a + z sin a, z' = -x sin a + z cos a
    return np.stack([x * c + z * s, shifted[..., 1], -x * s + z * c], axis=-1)


def bar_samples(
    skeleton: Skeleton, nodes: _Nodes, frames_per_bar: int, chunk: int = 256
) -> dict[str, np.ndarray]:
    """Every node sampled beat-aligned over its bar: beat k at sample k·F/4 (F =
    ``frames_per_bar``), plus the closing downbeat. Returns ``root (N, F, 3)``, ``root_rot (N, F,
    4)`` (the root's rotation), ``positions (N, F, K, 3)`` main-joint world positions, ``disp
    (N, 3)`` the root's displacement to the closing downbeat (dx, dz in the bar's start heading
    frame, dyaw), ``radius (N,)`` and ``root_path (N, S, 2)``."""
    keys = main_joint_keys(skeleton)
    phases = np.arange(frames_per_bar + 1) * 4.0 / frames_per_bar
    roots, root_rots, mains = [], [], []
    for a in range(0, nodes.n, chunk):
        idx = np.arange(a, min(nodes.n, a + chunk))
        root, rot, _ = nodes.at_phases(idx, np.broadcast_to(phases, (len(idx), len(phases))))
        m, p = root.shape[:2]
        pos, world = fk_arrays(skeleton, root.reshape(-1, 3), rot.reshape(m * p, -1, 4))
        mains.append(canonical_positions(skeleton, pos, world, keys).reshape(m, p, len(keys), 3))
        roots.append(root)
        root_rots.append(rot[:, :, 0])
    root = np.concatenate(roots)
    root_rot = np.concatenate(root_rots)
    main = np.concatenate(mains)
    yaw = quat.heading_angle(root_rot)
    local_root = _to_local(root[:, :, None, :], root[:, 0], yaw[:, 0])[:, :, 0]
    end = local_root[:, -1]  # where the next bar's first frame lands
    dyaw = np.angle(np.exp(1j * (yaw[:, -1] - yaw[:, 0])))
    f = frames_per_bar
    idx = np.linspace(0, f, PATH_SAMPLES, endpoint=False).astype(int)
    return {
        "root": root[:, :f],
        "root_rot": root_rot[:, :f],
        "positions": main[:, :f],
        "disp": np.stack([end[:, 0], end[:, 2], dyaw], axis=1).astype(np.float32),
        "radius": np.linalg.norm(local_root[:, :f, [0, 2]], axis=-1).max(axis=1).astype(np.float32),
        "root_path": local_root[:, idx][:, :, [0, 2]].astype(np.float32),
    }


def transition_features(
    skeleton: Skeleton, nodes: _Nodes, offsets: np.ndarray, beat_s: float, chunk: int = 256
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Seam features of every node at the cut offsets: ``exit (O, N, D)`` at bar phase 4 + o
    (dancing on past the bar), ``entry (O, N, D)`` at phase o (the lead-in), for o in ``offsets
    (O,)`` beats; velocities over ±``VELOCITY_STEP_BEATS`` at ``beat_s`` seconds per beat. Rows
    whose frames the node does not have are NaN (never at o = 0: clamped there). Returns exit,
    entry and the feature blocks."""
    h = VELOCITY_STEP_BEATS
    out = {}
    blocks: list[int] = []
    for side, base in (("exit", 4.0), ("entry", 0.0)):
        centre = base + np.asarray(offsets, dtype=float)  # (O,)
        trip = (centre[:, None] + np.array([-h, 0.0, h])[None, :]).reshape(-1)  # (O*3,)
        rows = []
        for a in range(0, nodes.n, chunk):
            idx = np.arange(a, min(nodes.n, a + chunk))
            root, rot, inside = nodes.at_phases(idx, np.broadcast_to(trip, (len(idx), len(trip))))
            m, o = len(idx), len(centre)
            feats, blocks = seam_features(
                skeleton,
                root.reshape(m * o, 3, 3),
                rot.reshape(m * o, 3, *rot.shape[2:]),
                h * beat_s,
            )
            feats = feats[:, 0].reshape(m, o, -1)
            ok = np.asarray(inside.reshape(m, o, 3).all(axis=2))
            ok[:, np.asarray(offsets) == 0.0] = True
            feats[~ok] = np.nan
            rows.append(feats.transpose(1, 0, 2))
        out[side] = np.concatenate(rows, axis=1)
    return out["exit"], out["entry"], blocks


# --------------------------------------------------------------------------------------------
# edges


def _block_distance(a: np.ndarray, b: np.ndarray, blocks: list[int]) -> np.ndarray:
    """Σ over blocks of ‖a_blk − b_blk‖ for rows ``a (m, D)`` against rows ``b (n, D)`` → (m, n)
    (``stitch.seam_distance`` of every pair; NaN rows give NaN)."""
    out = np.zeros((a.shape[0], b.shape[0]), dtype=np.float32)
    start = 0
    for size in blocks:
        x = a[:, start : start + size].astype(np.float64)
        y = b[:, start : start + size].astype(np.float64)
        sq = (x * x).sum(1)[:, None] + (y * y).sum(1)[None, :] - 2.0 * (x @ y.T)
        out += np.sqrt(np.maximum(sq, 0.0))
        start += size
    return out


def pair_cost(
    exit_p: np.ndarray,
    entry_q: np.ndarray,
    style_p: np.ndarray,
    style_q: np.ndarray,
    blocks: list[int],
    w_pose: float,
    w_style: float,
) -> np.ndarray:
    """T = λ8·T_d + λ9·T_z for paired rows ``exit_p``, ``entry_q`` ``(n, D)`` or, over cut
    offsets, ``(O, n, D)`` (T_d the least over the offsets where both rows exist) → (n,)."""
    t_d = seam_distance(np.asarray(exit_p), np.asarray(entry_q), blocks)
    if t_d.ndim == 2:
        t_d = np.nanmin(t_d, axis=0)
    return w_pose * t_d + w_style * np.linalg.norm(style_p - style_q, axis=1)


def compute_edges(
    entry: np.ndarray,
    exit_: np.ndarray,
    style: np.ndarray,
    blocks: list[int],
    params: BuildParams,
    forced: np.ndarray,
    progress: Progress | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Edges ``(src, dst, cost)`` sorted by (src, dst), and a report.

    ``entry``, ``exit_ (O, N, D)``: transition features at the cut offsets
    (``transition_features``; NaN where a node has no frames); the pose term of p → q is the
    least over the offsets. ``forced (M, 2)``: pairs always linked at their true cost
    (consecutive bars of a take).
    """
    n = entry.shape[1]
    k = params.max_out_degree
    srcs, dsts, costs = [], [], []
    best_in = np.full((n, params.min_degree), np.inf, dtype=np.float32)
    best_in_src = np.full((n, params.min_degree), -1, dtype=np.int64)
    below = 0
    forced_out = 0
    for i0 in range(0, n, params.chunk):
        i1 = min(n, i0 + params.chunk)
        c = _block_distance(exit_[0, i0:i1], entry[0], blocks)
        for o in range(1, entry.shape[0]):
            c = np.fmin(c, _block_distance(exit_[o, i0:i1], entry[o], blocks))
        c = params.w_pose * np.nan_to_num(c, nan=np.inf)
        sq = (
            (style[i0:i1] ** 2).sum(1)[:, None]
            + (style**2).sum(1)[None, :]
            - 2 * style[i0:i1] @ style.T
        )
        c += params.w_style * np.sqrt(np.maximum(sq, 0.0))
        rows = np.arange(i1 - i0)
        c[rows, rows + i0] = np.inf  # no self loops
        ok = c < params.threshold
        below += int(ok.sum())
        m = min(k, n - 1)
        part = np.argpartition(c, m - 1, axis=1)[:, :m] if m < n else np.argsort(c, axis=1)
        pc = np.take_along_axis(c, part, axis=1)
        keep = pc < params.threshold
        # dead ends: rows with nothing below δT keep their cheapest min_degree
        dead = ~keep.any(axis=1)
        if dead.any():
            order = np.argsort(pc[dead], axis=1)[:, : params.min_degree]
            fix = np.zeros_like(keep[dead])
            np.put_along_axis(fix, order, True, axis=1)
            keep[dead] = fix & np.isfinite(pc[dead])
            forced_out += int(dead.sum())
        r, col = np.nonzero(keep)
        srcs.append(r + i0)
        dsts.append(part[r, col])
        costs.append(pc[r, col])
        # best in-edges per column, for nodes nobody reaches
        for _ in range(params.min_degree):
            arg = np.argmin(c, axis=0)
            val = c[arg, np.arange(n)]
            better = val < best_in[:, -1]
            best_in[better, -1] = val[better]
            best_in_src[better, -1] = arg[better] + i0
            order = np.argsort(best_in, axis=1)
            best_in = np.take_along_axis(best_in, order, axis=1)
            best_in_src = np.take_along_axis(best_in_src, order, axis=1)
            c[arg, np.arange(n)] = np.inf
        if progress:
            progress("edges", i1 / n)
    src = np.concatenate(srcs) if srcs else np.zeros(0, int)
    dst = np.concatenate(dsts) if dsts else np.zeros(0, int)
    cost = np.concatenate(costs) if costs else np.zeros(0, np.float32)
    indeg = np.bincount(dst, minlength=n)
    no_in = np.nonzero(indeg == 0)[0]
    extra_s, extra_d, extra_c = [], [], []
    for q in no_in:
        for j in range(params.min_degree):
            if best_in_src[q, j] >= 0 and np.isfinite(best_in[q, j]):
                extra_s.append(best_in_src[q, j])
                extra_d.append(q)
                extra_c.append(best_in[q, j])
    if len(forced):
        fp, fq = forced[:, 0], forced[:, 1]
        fc = pair_cost(
            exit_[:, fp], entry[:, fq], style[fp], style[fq], blocks, params.w_pose, params.w_style
        )
        extra_s.extend(fp.tolist())
        extra_d.extend(fq.tolist())
        extra_c.extend(fc.tolist())
    src = np.concatenate([src, np.array(extra_s, dtype=int)])
    dst = np.concatenate([dst, np.array(extra_d, dtype=int)])
    cost = np.concatenate([cost, np.array(extra_c, dtype=np.float32)])
    # dedupe (src, dst), keep the first occurrence (costs agree)
    key = src.astype(np.int64) * n + dst
    _, first = np.unique(key, return_index=True)
    src, dst = src[first], dst[first]
    # exact costs for the kept edges (the chunked products only choose them)
    cost = np.empty(len(src), dtype=np.float32)
    for a in range(0, len(src), 1 << 15):
        sl = slice(a, a + (1 << 15))
        ps, qs = src[sl], dst[sl]
        cost[sl] = pair_cost(
            exit_[:, ps], entry[:, qs], style[ps], style[qs], blocks, params.w_pose, params.w_style
        )
    report = {
        "pairs_below_threshold": below,
        "forced_out": forced_out,
        "forced_in": int(len(no_in)),
        "consecutive": int(len(forced)),
    }
    return src, dst, cost, report


def to_csr(
    n: int, src: np.ndarray, dst: np.ndarray, cost: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edge lists → CSR ``(indptr (n+1,) int64, indices (E,) int32, costs (E,) float32)``, rows sorted."""
    order = np.lexsort((dst, src))
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(src, minlength=n), out=indptr[1:])
    return indptr, dst[order].astype(np.int32), cost[order].astype(np.float32)


# --------------------------------------------------------------------------------------------
# the build


def compress_features(
    entry: np.ndarray, exit_: np.ndarray, blocks: list[int], dims: int = 32
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Per-block PCA of the transition features for on-demand costs at search time.

    Each block of ``entry``/``exit (N, D)`` is projected onto the ``dims`` leading principal
    axes of the two stacked (one shared mean and basis, so differences are preserved up to the
    dropped variance). Returns ``entry_pc``, ``exit_pc (N, Σ dims) float32`` and their block sizes.
    The graph's edges keep their exact costs; only transitions that are not edges (between
    structure copies) are costed from these, reading about half the memory.
    """
    outs_e, outs_x, sizes = [], [], []
    start = 0
    for size in blocks:
        e = entry[:, start : start + size].astype(np.float64)
        x = exit_[:, start : start + size].astype(np.float64)
        both = np.concatenate([e, x])
        mean = both.mean(axis=0)
        k = min(dims, size, both.shape[0])
        # principal axes from the covariance (size × size), cheap for these block sizes
        cov = np.cov((both - mean).T) if both.shape[0] > 1 else np.eye(size)
        w, v = np.linalg.eigh(np.atleast_2d(cov))
        basis = v[:, np.argsort(w)[::-1][:k]]
        outs_e.append((e - mean) @ basis)
        outs_x.append((x - mean) @ basis)
        sizes.append(k)
        start += size
    return (
        np.concatenate(outs_e, axis=1).astype(np.float32),
        np.concatenate(outs_x, axis=1).astype(np.float32),
        sizes,
    )


def build_arrays(
    bars: BarSet,
    params: BuildParams | None = None,
    progress: Progress | None = None,
    learned: Callable[[np.ndarray], dict] | None = None,
) -> tuple[dict, list[str], dict]:
    """Nodes, features and edges from ``bars``; returns ``(arrays, node_ids, manifest)``.

    ``learned``: maps the originals' descriptor style ``(Nb, 32)`` to learned ``style`` and
    ``signature`` (either None) and manifest ``entry`` parts (``embed.learned.node_embeddings``).
    """
    params = params or BuildParams()
    t0 = time.perf_counter()
    sk = bars.skeleton
    nb = len(bars.signature)
    if nb < 2:
        raise ValueError("a graph needs at least 2 bars")
    clip = np.asarray(bars.clip, dtype=np.int32)
    bar = np.asarray(bars.bar, dtype=np.int32)
    dur = np.asarray(bars.duration, dtype=np.float64)
    sigs = list(bars.signature)
    originals = _Nodes(
        ptr=np.asarray(bars.ptr, dtype=np.int64),
        root=np.asarray(bars.root, dtype=np.float64),
        rotations=np.asarray(bars.rotations, dtype=np.float32),
        beats=np.asarray(bars.beats, dtype=np.float64),
        fps=np.asarray(bars.fps, dtype=np.float64),
    )

    # originals first: their style decides which pairs may blend or shuffle
    samples0 = bar_samples(sk, originals, params.frames_per_bar)
    raw0 = descriptor.dance_descriptors(samples0["positions"], dur)
    stats = descriptor.fit_stats(raw0)
    style0 = descriptor.embed(raw0, stats)
    embedding = {"version": descriptor.VERSION, "dance_stats": stats}
    if learned is not None:
        got = learned(style0)
        embedding.update(got["entry"])
        if got["signature"] is not None:
            sigs = [COMMON_SIGNATURES[int(k)] for k in got["signature"]]
        if got["style"] is not None:
            style0 = got["style"]

    parts = [originals]
    kinds = [np.zeros(nb, np.int8)]
    sources = [np.stack([np.arange(nb), np.full(nb, -1)], axis=1)]
    clips_, bars_, sig_, aug_no = [clip], [bar], [sigs], [np.zeros(nb, np.int32)]
    if params.mirror:
        parts.append(_mirrored(sk, originals))
        kinds.append(np.ones(nb, np.int8))
        sources.append(sources[0].copy())
        clips_.append(clip)
        bars_.append(bar)
        sig_.append(sigs)  # mirroring keeps the timing, so the signature
        aug_no.append(np.zeros(nb, np.int32))
    lower = _lower_body(sk)
    # pairs to blend or shuffle share the nearest common signature
    common = [COMMON_SIGNATURES[k] for k in nearest_common(np.stack([to_bits(x) for x in sigs]))]
    for kind_no, ratio, seed in (
        (2, params.blend_ratio, params.seed),
        (3, params.shuffle_ratio, params.seed + 1),
    ):
        pairs = _augment_pairs(style0, common, clip, params.style_quantile, int(ratio * nb), seed)
        if not pairs:
            continue
        if kind_no == 2:
            made = [_blended(originals, i, j, lower) for i, j in pairs]
        else:
            made = [_shuffled(sk, originals, i, j) for i, j in pairs]
        a = np.array([p[0] for p in pairs])
        b = np.array([p[1] for p in pairs])
        parts.append(_from_list(made))
        kinds.append(np.full(len(a), kind_no, np.int8))
        sources.append(np.stack([a, b], axis=1))
        clips_.append(clip[a])
        bars_.append(bar[a])
        if kind_no == 2:
            sig_.append([sigs[i] for i in a])
        else:  # slots 0-3 (beats 1-2) of a, 4-7 of b; a signature string has slot 0 rightmost
            sig_.append([sigs[j][:4] + sigs[i][4:] for i, j in zip(a, b, strict=True)])
        aug_no.append(np.arange(len(a), dtype=np.int32))
    if progress:
        progress("augment", 1.0)

    nodes = _concat(parts) if len(parts) > 1 else originals
    kind = np.concatenate(kinds)
    n = nodes.n
    all_dur = (nodes.beats[:, BEAT0 + 4] - nodes.beats[:, BEAT0]) / nodes.fps
    samples = bar_samples(sk, nodes, params.frames_per_bar) if n > nb else samples0
    if "style_model" in embedding:  # augmentations keep the learned style of their source bar
        style = style0[np.concatenate(sources)[:, 0]]
    else:
        style = descriptor.embed(descriptor.dance_descriptors(samples["positions"], all_dur), stats)
        style[:nb] = style0
    if progress:
        progress("features", 0.5)

    # tags: base tags + clip flags
    flag_names = sorted(
        {t for tags in bars.clip_tags.values() for t in tags} - set(artifact.BASE_TAGS)
    )
    tag_names = list(artifact.BASE_TAGS) + flag_names
    tag_bits = np.zeros(n, np.uint32)
    for k, name in enumerate(artifact.KINDS):
        tag_bits[kind == k] |= np.uint32(1 << tag_names.index(name))
    tag_bits[kind > 0] |= np.uint32(1 << tag_names.index("augmented"))
    node_clip = np.concatenate(clips_).astype(np.int32)
    for c, name in enumerate(bars.clips):
        for t in bars.clip_tags.get(name, []):
            if t in tag_names:
                tag_bits[node_clip == c] |= np.uint32(1 << tag_names.index(t))

    mirror_of = np.full(n, -1, np.int32)
    if params.mirror:
        mirror_of[:nb] = np.arange(nb) + nb
        mirror_of[nb : 2 * nb] = np.arange(nb)
    signature = to_pattern(np.stack([to_bits(x) for x in (y for part in sig_ for y in part)]))
    anchoring = _anchoring(sk, nodes, kind, mirror_of) if bars.grid_from_motion else None

    takes = [np.nonzero(clip == c)[0] for c in range(len(bars.clips))]
    takes = [t[np.argsort(bar[t])] for t in takes if t.size]
    motifs = choreography.fit_motifs(
        samples["positions"],
        samples["root"],
        samples["root_rot"],
        kind == 0,
        params.n_motifs,
        params.seed,
        take_sequences=takes,
    )

    # the seam distance at the cut offsets; velocities at the library's median beat
    beat_s = float(np.median(dur)) / 4.0
    offsets = params.offsets()
    exit_, entry, blocks = transition_features(sk, nodes, offsets, beat_s)
    if progress:
        progress("features", 1.0)

    # consecutive bars of one take (and their mirrors) are always linked
    nxt = {(int(c), int(b)): i for i, (c, b) in enumerate(zip(clip, bar, strict=True))}
    forced = [
        (i, nxt[(int(clip[i]), int(bar[i]) + 1)])
        for i in range(nb)
        if (int(clip[i]), int(bar[i]) + 1) in nxt
    ]
    if params.mirror:
        forced += [(p + nb, q + nb) for p, q in forced]
    forced_arr = np.array(forced, dtype=np.int64).reshape(-1, 2)
    src, dst, cost, report = compute_edges(
        entry, exit_, style, blocks, params, forced_arr, progress
    )
    indptr, indices, costs = to_csr(n, src, dst, cost)
    entry_pc, exit_pc, pc_blocks = compress_features(entry[0], exit_[0], blocks)

    ids = []
    node_bar = np.concatenate(bars_).astype(np.int32)
    aug_index = np.concatenate(aug_no)
    for i in range(n):
        base = f"{bars.clips[node_clip[i]]}:{node_bar[i]}"
        suffix = ("", "~m", f"~b{aug_index[i]}", f"~s{aug_index[i]}")[kind[i]]
        ids.append(base + suffix)

    arrays = {
        "node_clip": node_clip,
        "node_bar": node_bar,
        "node_kind": kind,
        "node_tags": tag_bits,
        "node_source": np.concatenate(sources).astype(np.int32),
        "mirror_of": mirror_of,
        "style": style.astype(np.float32),
        "signature": signature,
        "motif": motifs["labels"].astype(np.int32),
        "entry": entry[0],
        "exit": exit_[0],
        "entry_pc": entry_pc,
        "exit_pc": exit_pc,
        "disp": samples["disp"],
        "radius": samples["radius"],
        "root_path": samples["root_path"],
        "duration": all_dur.astype(np.float32),
        "indptr": indptr,
        "indices": indices,
        "costs": costs,
        "motion_row": np.arange(n, dtype=np.int32),
        "motion_ptr": nodes.ptr.astype(np.int64),
        "motion_beats": nodes.beats.astype(np.float32),
        "motion_fps": nodes.fps.astype(np.float32),
        "root": nodes.root.astype(np.float32),
        "rotations": nodes.rotations.astype(np.float32),
    }
    if anchoring is not None:
        arrays["anchoring"] = anchoring
    manifest = {
        "clips": list(bars.clips),
        "tags": tag_names,
        "skeleton": sk.to_dict(),
        "params": asdict(params),
        "embedding": embedding,
        "feature_blocks": blocks,
        "pc_blocks": pc_blocks,
        "main_joints": main_joint_keys(sk),
        "seam": {
            "cut_beats": params.cut_beats,
            "offsets": offsets.tolist(),
            "beat_s": beat_s,
            "velocity_step_beats": VELOCITY_STEP_BEATS,
        },
        "bar_frames": {
            name: {
                str(int(b)): [int(x) for x in fr]
                for b, fr, c in zip(bar, bars.frames, clip, strict=True)
                if c == ci
            }
            for ci, name in enumerate(bars.clips)
        },
        "motifs": {
            "k": int(motifs["k"]),
            "centroids": motifs["centroids"].tolist(),
            "signature": motifs["signature"].tolist(),
            "transitions": motifs["transitions"].tolist(),
        },
        "build": dict(
            report, seconds=round(time.perf_counter() - t0, 3), nodes=n, edges=int(len(indices))
        ),
    }
    return arrays, ids, manifest


def bars_from_dataset(
    dataset, progress: Progress | None = None, params: BuildParams | None = None
) -> BarSet:
    """Every bar of an imported ``Dataset`` with the frames of its take around it (``BarSet``);
    with ``params.accent_anchors`` (the default) the beats of each take whose grid was read from
    its motion (``beat_source`` not ``annotation``) moved onto the moments it stops
    (``accent_anchors`` on ``rhythm.motion.motion_stops``); an annotated grid is where the take's
    music had its beats, and the take's own relation to them is kept. ``grid_from_motion``:
    whether any take's grid was read from its motion."""
    params = params or BuildParams()
    clips = [c.id for c in dataset.clips]
    by_clip: dict[str, list] = {}
    for b in dataset.bars:
        by_clip.setdefault(b.clip_id, []).append(b)
    read_from_motion = {c.id: c.beat_source != "annotation" for c in dataset.clips}
    takes = []
    for k, cid in enumerate(clips):
        bl = sorted(by_clip.get(cid, []), key=lambda b: b.index)
        motion = dataset.motion(cid)
        bar_beats = np.array([b.beat_times for b in bl], dtype=float).reshape(-1, 5)
        if params.accent_anchors and read_from_motion[cid] and len(bl):
            bar_beats = accent_anchors(
                bar_beats,
                motion_stops(motion),
                params.accent_tolerance,
                params.accent_max_speed,
            )
        takes.append(
            (
                motion,
                bar_beats,
                np.array([b.index for b in bl], dtype=np.int64),
                [b.signature_raw or b.signature for b in bl],
                np.array([(b.start_frame, b.end_frame) for b in bl], dtype=np.int64).reshape(-1, 2),
            )
        )
        if progress:
            progress("bars", (k + 1) / len(clips))
    tags = {
        c.id: list(c.flags) + ([f"style:{c.style}"] if getattr(c, "style", None) else [])
        for c in dataset.clips
    }
    bars = BarSet.from_takes(dataset.skeleton, clips, takes, tags)
    bars.grid_from_motion = any(read_from_motion.values())
    return bars


def build_graph(
    dataset,
    store: ObjectStore,
    params: BuildParams | None = None,
    progress: Progress | None = None,
    style_model=None,
    rhythm_model=None,
) -> str:
    """Build the graph of an imported dataset and store it as a new version; returns its key.

    ``style_model`` / ``rhythm_model``: loaded learned models (``embed.model.load_model``) for
    the node styles / signatures instead of the descriptor and the dataset's signatures.
    """
    params = params or BuildParams()
    bars = bars_from_dataset(dataset, progress, params)
    learned = None
    if style_model is not None or rhythm_model is not None:
        from functools import partial

        from dancegraph.embed.learned import node_embeddings, store_models

        store_models(store, style_model, rhythm_model)
        learned = partial(
            node_embeddings,
            dataset,
            bars.clips,
            bars.clip,
            bars.bar,
            style_model=style_model,
            rhythm_model=rhythm_model,
        )
    arrays, ids, manifest = build_arrays(bars, params, progress, learned)
    manifest["dataset"] = {
        "name": dataset.name,
        "version": dataset.version,
        "licence": getattr(dataset, "licence", None),
        # carried into every result's timeline.json provenance (CMU asks for it in derived works)
        "acknowledgement": dataset.meta.get("acknowledgement"),
        # the style's danced tempo range: a song's bars count the octave that fits it
        "style_tempo_bpm": dataset.meta.get("style_tempo_bpm"),
        # the library's style label, for choosing a library by style (graph.style_choice)
        "style": dataset.meta.get("style"),
    }
    return artifact.write_graph(store, dataset.name, arrays, manifest, node_ids=ids)


def build_dataset_graph(
    store: ObjectStore,
    name: str,
    params: BuildParams | None = None,
    progress: Progress | None = None,
    embedding: str | None = None,
    rhythm_model: str | None = None,
) -> dict:
    """Load dataset ``name`` from ``store``, build and store its graph; returns a report with the
    artifact key, version, node/edge counts, degree distribution and build seconds.

    ``embedding``: 'descriptor' (default) or the path of a learned style model file;
    ``rhythm_model``: the path of a learned rhythm model file (node signatures). Both are
    validated before any work (``ModelFileError``).
    """
    from dancegraph.motion.dataset import load_dataset

    t0 = time.perf_counter()
    style = rhythm = None
    if embedding not in (None, "descriptor") or rhythm_model:
        from dancegraph.embed.model import load_model  # torch: only for learned models

        style = load_model(embedding) if embedding not in (None, "descriptor") else None
        rhythm = load_model(rhythm_model) if rhythm_model else None
    for m, kind in ((style, "style"), (rhythm, "rhythm")):
        if m is not None and m.kind != kind:
            raise ModelFileError(f"{m.path} is a {m.kind} model, expected a {kind} model")
    dataset = load_dataset(store, name)
    key = build_graph(dataset, store, params, progress, style, rhythm)
    graph = artifact.load_graph(store.local_dir(key))
    return {
        "key": key,
        "version": graph.version,
        "dataset_version": dataset.version,
        "embedding": graph.manifest["embedding"]["version"],
        **graph.stats(),
        "build": graph.manifest["build"],
        "seconds": round(time.perf_counter() - t0, 2),
    }
