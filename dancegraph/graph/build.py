"""Build a motion graph from bars of dance (ChoreoMaster §4, DESIGN.md §4).

Nodes are bars, resampled beat-aligned to ``frames_per_bar`` frames (beat k at frame
k·F/4), plus augmentations flagged by tag so users can exclude them:

- ``mirror`` (every bar): the bar mirrored left/right, id ``<clip>:<bar>~m``;
- ``blend`` (capped): upper body of bar a over the lower body (and root) of bar b, id ``<a>~b<k>``;
- ``shuffle`` (capped): beats 1–2 of bar a followed by beats 3–4 of bar b (root re-aligned at the
  seam), id ``<a>~s<k>``;

blends and shuffles only between bars with the same (nearest common) rhythm signature whose styles
are close (within the ``style_quantile`` of all pair distances). All augmentations also carry the
tag ``augmented``.

A node's rhythm signature is the slot pattern of its own kinematic beats (the dataset's per-bar
label, ``BarSet.signature``, not snapped to a common signature): a mirror keeps its bar's, a blend
its upper body's bar's (the pair shares the signature), a shuffle has beats 1–2 of bar a's and
beats 3–4 of bar b's.

Edges p → q where T = λ8·T_d + λ9·T_z < δT. T_d compares p's last ``window`` frames with the
``window`` frames that *precede* q in its own take (Kovar et al.'s criterion: q may follow p when
p ends the way q's true predecessor ends; every bar is resampled with ``lead`` frames before its
downbeat for this), each window expressed in its own heading frame: position (m), rotation (rad,
chordal: 2‖Δq‖ ≈ angle for small angles) and velocity (m/s) differences of the main joints,
summed over the joints and averaged over the transition frames. Each part is
``sqrt(K/W)·‖Δ‖₂`` over its K joints × W frames, which equals that sum-over-joints,
mean-over-frames when the per-joint-frame differences are even, and keeps the distance a
Euclidean norm so a chunk of rows against all columns is three matrix products. Consecutive bars of a take thus cost ≈ λ9·T_z. T_z = ‖z_p − z_q‖ of the style embeddings.
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
from dancegraph.errors import ModelFileError
from dancegraph.graph import artifact, choreography
from dancegraph.motion import quat
from dancegraph.motion.fk import canonical_positions, fk_arrays
from dancegraph.motion.skeleton import CANONICAL_JOINTS, Motion, Skeleton
from dancegraph.rhythm.signatures import COMMON_SIGNATURES, nearest_common, to_bits, to_pattern
from dancegraph.store import ObjectStore

Progress = Callable[[str, float], None]
PATH_SAMPLES = 8


@dataclass
class BuildParams:
    """Graph build parameters (defaults from DESIGN.md §4 where it has them)."""

    threshold: float = 20.0  # δT
    w_pose: float = 1.0  # λ8
    w_style: float = 1.5  # λ9
    frames_per_bar: int = 48
    window: int = 4
    max_out_degree: int = 24
    min_degree: int = 2
    mirror: bool = True
    blend_ratio: float = 0.25
    shuffle_ratio: float = 0.25
    style_quantile: float = 0.1
    n_motifs: int | None = None
    seed: int = 0
    chunk: int = 512

    def __post_init__(self) -> None:
        if self.frames_per_bar % 4 or self.frames_per_bar < 16:
            raise ValueError("frames_per_bar must be a multiple of 4, at least 16")
        if not 1 <= self.window < self.frames_per_bar // 2:
            raise ValueError("window must be between 1 and frames_per_bar / 2")
        if self.threshold <= 0:
            raise ValueError("threshold must be positive")


@dataclass
class BarSet:
    """Bars of dance as arrays, the input of ``build_arrays``.

    ``root (Nb, lead + F, 3)`` metres and ``rotations (Nb, lead + F, J, 4)`` local rotations, each
    bar resampled beat-aligned with ``lead`` frames before its downbeat; ``clip (Nb,)`` index into
    ``clips``; ``bar (Nb,)`` bar index in its take; ``duration (Nb,)`` seconds; ``signature``
    8-character strings, the slots of the bar's kinematic beats (any pattern); ``frames (Nb, 2)``
    source frame range [start, end) for provenance.
    """

    skeleton: Skeleton
    clips: list[str]
    clip: np.ndarray
    bar: np.ndarray
    root: np.ndarray
    rotations: np.ndarray
    duration: np.ndarray
    signature: list[str]
    frames: np.ndarray
    lead: int
    clip_tags: dict[str, list[str]] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# resampling and augmentation


def beat_sample_times(beat_times: np.ndarray, n: int, lead: int = 0) -> np.ndarray:
    """``(lead + n,)`` times (s): ``lead`` samples before the downbeat at the first beat's rate,
    then n/4 samples evenly over each of the 4 beats in ``beat_times (5,)``."""
    beat_times = np.asarray(beat_times, dtype=float)
    per = n // 4
    frac = np.arange(per) / per
    bar = (beat_times[:4, None] + frac[None, :] * np.diff(beat_times)[:, None]).reshape(-1)
    step = (beat_times[1] - beat_times[0]) / per
    return np.concatenate([beat_times[0] - step * np.arange(lead, 0, -1), bar])


def resample(
    root: np.ndarray, rotations: np.ndarray, fps: float, times: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Sample a take (``root (F, 3)``, ``rotations (F, J, 4)`` at ``fps``) at ``times (n,)`` s:
    linear for the root, slerp for rotations; times outside the take are clamped."""
    f = np.clip(np.asarray(times) * fps, 0.0, root.shape[0] - 1.0)
    i0 = np.floor(f).astype(int)
    i1 = np.minimum(i0 + 1, root.shape[0] - 1)
    t = f - i0
    r = root[i0] * (1 - t)[:, None] + root[i1] * t[:, None]
    q = quat.slerp(
        rotations[i0], rotations[i1], np.broadcast_to(t[:, None], rotations[i0].shape[:2])
    )
    return r, q


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


def _yaw(rot_root: np.ndarray) -> np.ndarray:
    return quat.heading_angle(rot_root)


def _shuffle_motion(
    root_a: np.ndarray,
    rot_a: np.ndarray,
    root_b: np.ndarray,
    rot_b: np.ndarray,
    lead: int,
    blend: int = 4,
) -> tuple[np.ndarray, np.ndarray]:
    """Beats 1–2 of bar a (with its lead frames) then beats 3–4 of bar b, b re-aligned (position,
    heading) at the seam; arrays ``(lead + F, ...)``."""
    n = root_a.shape[0]
    h = lead + (n - lead) // 2
    yaw_a = _yaw(rot_a[h - 1, 0])
    yaw_b = _yaw(rot_b[h, 0])
    turn = quat.from_y_angle(yaw_a - yaw_b)
    step = root_a[h - 1] - root_a[h - 2]
    rel = root_b[h:] - root_b[h]
    rel = quat.rotate(np.broadcast_to(turn, rel.shape[:-1] + (4,)), rel)
    start = root_a[h - 1] + step
    start[1] = root_b[h, 1]
    root = np.concatenate([root_a[:h], start + rel])
    rot = np.concatenate([rot_a[:h], rot_b[h:]]).copy()
    rot[h:, 0] = quat.multiply(np.broadcast_to(turn, rot[h:, 0].shape), rot[h:, 0])
    # short cross-fade after the seam so joints do not jump
    for k in range(blend):
        w = (k + 1) / (blend + 1)
        rot[h + k] = quat.slerp(rot[h - 1], rot[h + k], np.full(rot.shape[1], w))
    return root, rot


def _mirror_bars(
    skeleton: Skeleton, root: np.ndarray, rot: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mirror bars ``root (N, F, 3)``, ``rot (N, F, J, 4)`` left/right (all frames at once)."""
    from dancegraph.motion.mirror import mirror

    n, f = root.shape[:2]
    m = mirror(
        Motion(
            skeleton=skeleton,
            fps=30.0,
            root_positions=root.reshape(n * f, 3),
            rotations=rot.reshape(n * f, *rot.shape[2:]),
        )
    )
    return m.root_positions.reshape(root.shape), m.rotations.reshape(rot.shape)


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


def main_joint_keys(skeleton: Skeleton) -> list[str]:
    return [k for k in CANONICAL_JOINTS if k in skeleton.canonical]


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


def node_features(
    skeleton: Skeleton,
    root: np.ndarray,
    rotations: np.ndarray,
    duration: np.ndarray,
    window: int,
    lead: int,
) -> dict[str, np.ndarray]:
    """Per-node features from bars ``root (N, lead + F, 3)``, ``rotations (N, lead + F, J, 4)``
    (``lead`` frames before the downbeat, then the bar) and ``duration (N,)`` seconds.

    Returns ``entry (N, D)``: the ``window`` frames before the bar; ``exit (N, D)``: the bar's last
    ``window`` frames (blocks in ``"blocks"``); ``positions (N, F, K, 3)`` main-joint world
    positions over the bar; ``disp (N, 3)``, ``radius (N,)``, ``path (N, S, 2)``.
    """
    if lead < window + 1:
        raise ValueError("lead must be at least window + 1 frames")
    n, f_ext = root.shape[:2]
    f = f_ext - lead
    keys = main_joint_keys(skeleton)
    joints = np.array([skeleton.index(k) for k in keys])
    pos_w, rot_w = fk_arrays(
        skeleton, root.reshape(n * f_ext, 3), rotations.reshape(n * f_ext, -1, 4).astype(np.float64)
    )
    main = canonical_positions(skeleton, pos_w, rot_w, keys).reshape(n, f_ext, len(keys), 3)
    yaw = _yaw(rot_w[:, 0]).reshape(n, f_ext)
    dt = np.asarray(duration, dtype=float) / f

    def window_features(vel_frames: np.ndarray, pose_frames: np.ndarray, ref: int) -> np.ndarray:
        # positions/rotations on pose_frames (W,), velocities over vel_frames (W+1,), all in the
        # heading frame of frame ``ref``
        local = _to_local(main[:, vel_frames], root[:, ref], yaw[:, ref])
        vel = np.diff(local, axis=1) / dt[:, None, None, None]
        pos = _to_local(main[:, pose_frames], root[:, ref], yaw[:, ref])
        rot = rotations[:, pose_frames][:, :, joints].astype(np.float64)
        # root rotation without its heading: heading is free (root alignment when stitching)
        unturn = quat.from_y_angle(-yaw[:, ref])[:, None, :]
        rot[:, :, 0] = quat.multiply(np.broadcast_to(unturn, rot[:, :, 0].shape), rot[:, :, 0])
        rot = np.where(rot[..., 3:4] < 0, -rot, rot) * 2.0
        # sum over the main joints, mean over the transition frames (see the module docstring)
        scale = np.sqrt(len(keys) / window)
        return np.concatenate(
            [pos.reshape(n, -1) * scale, rot.reshape(n, -1) * scale, vel.reshape(n, -1) * scale],
            axis=1,
        )

    entry = window_features(
        np.arange(lead - window - 1, lead), np.arange(lead - window, lead), lead - window
    )
    exit_ = window_features(
        np.arange(f_ext - window - 1, f_ext), np.arange(f_ext - window, f_ext), f_ext - window
    )
    # the rest describes the bar itself
    root, yaw, main = root[:, lead:], yaw[:, lead:], main[:, lead:]
    k = len(keys)
    blocks = [window * k * 3, window * k * 4, window * k * 3]
    # root displacement and path in the bar's start heading frame
    origin = root[:, 0]
    local_root = _to_local(root[:, :, None, :], origin, yaw[:, 0])[:, :, 0]
    end = 2 * local_root[:, -1] - local_root[:, -2]  # where the next bar's first frame lands
    dyaw = np.angle(np.exp(1j * (2 * yaw[:, -1] - yaw[:, -2] - yaw[:, 0])))
    disp = np.stack([end[:, 0], end[:, 2], dyaw], axis=1)
    radius = np.linalg.norm(local_root[:, :, [0, 2]], axis=-1).max(axis=1)
    idx = np.linspace(0, f, PATH_SAMPLES, endpoint=False).astype(int)
    path = local_root[:, idx][:, :, [0, 2]]
    return {
        "entry": entry.astype(np.float32),
        "exit": exit_.astype(np.float32),
        "blocks": np.array(blocks),
        "positions": main,
        "disp": disp.astype(np.float32),
        "radius": radius.astype(np.float32),
        "root_path": path.astype(np.float32),
    }


# --------------------------------------------------------------------------------------------
# edges


def _block_distance(a: np.ndarray, b: np.ndarray, blocks: list[int]) -> np.ndarray:
    """Σ over blocks of ‖a_blk − b_blk‖ for rows ``a (m, D)`` against rows ``b (n, D)`` → (m, n)."""
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
    """T = λ8·T_d + λ9·T_z for paired rows: ``exit_p (n, D)`` with ``entry_q (n, D)`` → (n,)."""
    t_d = np.zeros(exit_p.shape[0])
    start = 0
    for size in blocks:
        t_d += np.linalg.norm(
            exit_p[:, start : start + size] - entry_q[:, start : start + size], axis=1
        )
        start += size
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

    ``forced (M, 2)``: pairs always linked at their true cost (consecutive bars of a take).
    """
    n = entry.shape[0]
    k = params.max_out_degree
    srcs, dsts, costs = [], [], []
    best_in = np.full((n, params.min_degree), np.inf, dtype=np.float32)
    best_in_src = np.full((n, params.min_degree), -1, dtype=np.int64)
    below = 0
    forced_out = 0
    for i0 in range(0, n, params.chunk):
        i1 = min(n, i0 + params.chunk)
        c = params.w_pose * _block_distance(exit_[i0:i1], entry, blocks)
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
            exit_[fp], entry[fq], style[fp], style[fq], blocks, params.w_pose, params.w_style
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
            exit_[ps], entry[qs], style[ps], style[qs], blocks, params.w_pose, params.w_style
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
    structure copies) are costed from these, reading ~8× less memory.
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
    root = np.asarray(bars.root, dtype=np.float64)
    rot = np.asarray(bars.rotations, dtype=np.float64)
    dur = np.asarray(bars.duration, dtype=np.float64)
    sigs = list(bars.signature)

    # originals first: their style decides which pairs may blend or shuffle
    lead = int(bars.lead)
    feats0 = node_features(sk, root, rot, dur, params.window, lead)
    raw0 = descriptor.dance_descriptors(feats0["positions"], dur)
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

    kinds = [np.zeros(nb, np.int8)]
    sources = [np.stack([np.arange(nb), np.full(nb, -1)], axis=1)]
    roots, rots = [root], [rot]
    clips_, bars_, sig_, aug_no = [clip], [bar], [sigs], [np.zeros(nb, np.int32)]
    if params.mirror:
        mr, mq = _mirror_bars(sk, root, rot)
        roots.append(mr)
        rots.append(mq)
        kinds.append(np.ones(nb, np.int8))
        sources.append(sources[0].copy())
        clips_.append(clip)
        bars_.append(bar)
        sig_.append(sigs)  # mirroring keeps the timing, so the signature
        aug_no.append(np.zeros(nb, np.int32))
    lower = _lower_body(sk)
    # pairs to blend or shuffle share the nearest common signature
    common = [COMMON_SIGNATURES[k] for k in nearest_common(np.stack([to_bits(x) for x in sigs]))]
    blend_pairs = _augment_pairs(
        style0, common, clip, params.style_quantile, int(params.blend_ratio * nb), params.seed
    )
    if blend_pairs:
        a = np.array([p[0] for p in blend_pairs])
        b = np.array([p[1] for p in blend_pairs])
        br = root[b].copy()
        bq = rot[a].copy()
        bq[:, :, lower] = rot[b][:, :, lower]
        roots.append(br)
        rots.append(bq)
        kinds.append(np.full(len(a), 2, np.int8))
        sources.append(np.stack([a, b], axis=1))
        clips_.append(clip[a])
        bars_.append(bar[a])
        sig_.append([sigs[i] for i in a])
        aug_no.append(np.arange(len(a), dtype=np.int32))
    shuffle_pairs = _augment_pairs(
        style0, common, clip, params.style_quantile, int(params.shuffle_ratio * nb), params.seed + 1
    )
    if shuffle_pairs:
        sr, sq = [], []
        for i, j in shuffle_pairs:
            r_, q_ = _shuffle_motion(root[i], rot[i], root[j], rot[j], lead)
            sr.append(r_)
            sq.append(q_)
        a = np.array([p[0] for p in shuffle_pairs])
        b = np.array([p[1] for p in shuffle_pairs])
        roots.append(np.stack(sr))
        rots.append(np.stack(sq))
        kinds.append(np.full(len(a), 3, np.int8))
        sources.append(np.stack([a, b], axis=1))
        clips_.append(clip[a])
        bars_.append(bar[a])
        # slots 0-3 (beats 1-2) of a, 4-7 of b; a signature string has slot 0 rightmost
        sig_.append([sigs[j][:4] + sigs[i][4:] for i, j in zip(a, b, strict=True)])
        aug_no.append(np.arange(len(a), dtype=np.int32))
    if progress:
        progress("augment", 1.0)

    kind = np.concatenate(kinds)
    n = kind.shape[0]
    all_root = np.concatenate(roots)
    all_rot = np.concatenate(rots)
    all_dur = np.concatenate(
        [dur]
        + [
            dur[s[:, 1] if k[0] == 2 else s[:, 0]]
            for k, s in zip(kinds[1:], sources[1:], strict=True)
        ]
    )
    feats = node_features(sk, all_root, all_rot, all_dur, params.window, lead) if n > nb else feats0
    all_root, all_rot = all_root[:, lead:], all_rot[:, lead:]  # nodes keep the bar itself
    if "style_model" in embedding:  # augmentations keep the learned style of their source bar
        style = style0[np.concatenate(sources)[:, 0]]
    else:
        style = descriptor.embed(descriptor.dance_descriptors(feats["positions"], all_dur), stats)
        style[:nb] = style0
    if progress:
        progress("features", 1.0)

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

    takes = [np.nonzero(clip == c)[0] for c in range(len(bars.clips))]
    takes = [t[np.argsort(bar[t])] for t in takes if t.size]
    motifs = choreography.fit_motifs(
        feats["positions"],
        all_root,
        all_rot[:, :, 0],
        kind == 0,
        params.n_motifs,
        params.seed,
        take_sequences=takes,
    )

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
    blocks = [int(b) for b in feats["blocks"]]
    src, dst, cost, report = compute_edges(
        feats["entry"], feats["exit"], style, blocks, params, forced_arr, progress
    )
    indptr, indices, costs = to_csr(n, src, dst, cost)
    entry_pc, exit_pc, pc_blocks = compress_features(feats["entry"], feats["exit"], blocks)

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
        "entry": feats["entry"],
        "exit": feats["exit"],
        "entry_pc": entry_pc,
        "exit_pc": exit_pc,
        "disp": feats["disp"],
        "radius": feats["radius"],
        "root_path": feats["root_path"],
        "duration": all_dur.astype(np.float32),
        "indptr": indptr,
        "indices": indices,
        "costs": costs,
        "motion_row": np.arange(n, dtype=np.int32),
        "root": all_root.astype(np.float32),
        "rotations": all_rot.astype(np.float16),
    }
    manifest = {
        "clips": list(bars.clips),
        "tags": tag_names,
        "skeleton": sk.to_dict(),
        "params": asdict(params),
        "embedding": embedding,
        "feature_blocks": blocks,
        "pc_blocks": pc_blocks,
        "main_joints": main_joint_keys(sk),
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
    dataset, frames_per_bar: int = 48, lead: int = 5, progress: Progress | None = None
) -> BarSet:
    """Resample every bar of an imported ``Dataset`` beat-aligned into a ``BarSet``."""
    clips = [c.id for c in dataset.clips]
    cindex = {c: i for i, c in enumerate(clips)}
    by_clip: dict[str, list] = {}
    for b in dataset.bars:
        by_clip.setdefault(b.clip_id, []).append(b)
    roots, rots, clip, bar, dur, sig, frames = [], [], [], [], [], [], []
    for k, cid in enumerate(clips):
        bl = by_clip.get(cid, [])
        if not bl:
            continue
        motion = dataset.motion(cid)
        for b in bl:
            times = beat_sample_times(np.asarray(b.beat_times, dtype=float), frames_per_bar, lead)
            r, q = resample(motion.root_positions, motion.rotations, motion.fps, times)
            roots.append(r)
            rots.append(q)
            clip.append(cindex[cid])
            bar.append(b.index)
            dur.append(float(b.beat_times[4] - b.beat_times[0]))
            sig.append(b.signature_raw or b.signature)
            frames.append((b.start_frame, b.end_frame))
        if progress:
            progress("bars", (k + 1) / len(clips))
    tags = {
        c.id: list(c.flags) + ([f"style:{c.style}"] if getattr(c, "style", None) else [])
        for c in dataset.clips
    }
    return BarSet(
        skeleton=dataset.skeleton,
        clips=clips,
        clip=np.array(clip),
        bar=np.array(bar),
        root=np.stack(roots),
        rotations=np.stack(rots),
        duration=np.array(dur),
        signature=sig,
        frames=np.array(frames),
        lead=lead,
        clip_tags=tags,
    )


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
    bars = bars_from_dataset(dataset, params.frames_per_bar, params.window + 1, progress)
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
