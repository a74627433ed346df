"""Choreography level after "Rhythm is a Dancer" (Aristidou et al., TVCG 2022).

Motion words are cut on beats: a word is one 4-beat bar whose beats are each time-scaled to the
same number of frames (the graph's beat-aligned resampling does exactly that). Words are
clustered by K-means into motifs; a dance's *signature* is its normalised motif histogram and the
distance between signatures is chi-square, ½ Σ (a − b)² / (a + b). A motif transition matrix counts
consecutive motifs within takes. The search uses these as optional terms (``search.py``): follow a
target signature, pin motifs at bars, re-create a take's motif sequence.
"""

from __future__ import annotations

import numpy as np
from scipy.cluster.vq import kmeans2

from dancegraph.motion import quat

WORD_SAMPLES = 16  # samples kept per word (4 per beat)


def word_features(positions: np.ndarray, root: np.ndarray, root_rot: np.ndarray) -> np.ndarray:
    """``(N, D)`` word features: main-joint positions ``(N, F, K, 3)`` relative to the root and
    turned into the bar's start heading, at ``WORD_SAMPLES`` beat-aligned samples, plus the root's
    path in that frame. ``root (N, F, 3)``, ``root_rot (N, F, 4)``."""
    n, f = positions.shape[:2]
    idx = np.linspace(0, f, WORD_SAMPLES, endpoint=False).astype(int)
    yaw = quat.heading_angle(np.asarray(root_rot[:, 0], dtype=float))
    c, s = np.cos(-yaw)[:, None, None], np.sin(-yaw)[:, None, None]
    rel = positions[:, idx] - root[:, idx][:, :, None, :]
    x, z = rel[..., 0], rel[..., 2]
    body = np.stack([x * c + z * s, rel[..., 1], -x * s + z * c], axis=-1)
    path = root[:, idx] - root[:, :1]
    px, pz = path[..., 0], path[..., 2]
    c2, s2 = c[:, :, 0], s[:, :, 0]
    path_l = np.stack([px * c2 + pz * s2, -px * s2 + pz * c2], axis=-1)
    return np.concatenate([body.reshape(n, -1), path_l.reshape(n, -1)], axis=1)


def chi_square(a: np.ndarray, b: np.ndarray) -> float:
    """½ Σ (a − b)² / (a + b) over bins where a + b > 0 (signatures are normalised histograms)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    s = a + b
    m = s > 0
    return float(0.5 * np.sum((a[m] - b[m]) ** 2 / s[m]))


def motif_signature(labels: np.ndarray, k: int) -> np.ndarray:
    """Normalised motif histogram ``(k,)`` of a motif sequence."""
    h = np.bincount(np.asarray(labels, dtype=int), minlength=k).astype(float)
    return h / max(h.sum(), 1.0)


def transition_matrix(sequences: list[np.ndarray], k: int) -> np.ndarray:
    """Row-normalised counts ``(k, k)`` of consecutive motifs over ``sequences``."""
    m = np.zeros((k, k))
    for seq in sequences:
        seq = np.asarray(seq, dtype=int)
        if seq.size > 1:
            np.add.at(m, (seq[:-1], seq[1:]), 1.0)
    rows = m.sum(axis=1, keepdims=True)
    return np.divide(m, rows, out=np.zeros_like(m), where=rows > 0)


def fit_motifs(
    positions: np.ndarray,
    root: np.ndarray,
    root_rot: np.ndarray,
    original: np.ndarray,
    k: int | None = None,
    seed: int = 0,
    take_sequences: list[np.ndarray] | None = None,
) -> dict:
    """K-means motifs over the original bars' words; every node gets its nearest motif.

    Returns ``labels (N,)``, ``k``, ``centroids (k, D)`` (standardised feature space),
    ``signature (k,)`` (histogram over original bars) and ``transitions (k, k)``.
    ``take_sequences``: node indices of each take in bar order (for the transition matrix);
    default: consecutive original nodes.
    """
    feats = word_features(positions, root, root_rot)
    orig = np.nonzero(np.asarray(original))[0]
    mu = feats[orig].mean(axis=0)
    sd = feats[orig].std(axis=0).mean() + 1e-9  # one scale keeps the geometry
    z = (feats - mu) / sd
    if k is None:
        k = int(np.clip(len(orig) // 10, 2, 32))
    k = max(1, min(k, len(orig)))
    centroids, _ = kmeans2(z[orig], k, minit="++", seed=seed, iter=30)
    d = ((z[:, None, :] - centroids[None, :, :]) ** 2).sum(-1)
    labels = np.argmin(d, axis=1)
    seqs = [labels[s] for s in take_sequences] if take_sequences else [labels[orig]]
    return {
        "labels": labels,
        "k": k,
        "centroids": centroids,
        "signature": motif_signature(labels[orig], k),
        "transitions": transition_matrix(seqs, k),
    }


def take_motif_sequence(graph, take: str) -> np.ndarray:
    """Motif ids of a take's original bars in bar order; KeyError for an unknown take."""
    clips = graph.clips
    c = clips.index(take)
    nodes = np.nonzero((np.asarray(graph.node_clip) == c) & (np.asarray(graph.node_kind) == 0))[0]
    nodes = nodes[np.argsort(np.asarray(graph.node_bar)[nodes])]
    return np.asarray(graph.motif)[nodes]


def plan_motifs(cost: np.ndarray, count: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Assign one motif to each variable so the motif histogram follows ``target``.

    ``cost (V, K)``: the cheapest way (data term) to dance variable v with motif k (inf where no
    node has it); ``count (V,)``: song bars per variable; ``target (K,)`` a normalised
    histogram. Motif k gets ``round(target_k · V)`` slots at the variable's cost, plus overflow
    slots at a high price so every variable has one; an optimal assignment (Hungarian) picks
    the plan. Returns ``(V,)`` motif ids.
    """
    from scipy.optimize import linear_sum_assignment

    cost = np.asarray(cost, dtype=float)
    count = np.asarray(count, dtype=float)
    n_vars, k = cost.shape
    finite = np.isfinite(cost)
    big = (np.abs(cost[finite]).max() + 1.0) * count.max() * 10.0 if finite.any() else 1.0
    slots = np.rint(np.asarray(target, dtype=float) * n_vars).astype(int)
    cols, owner = [], []
    for m in range(k):
        base = np.where(finite[:, m], cost[:, m] * count, 1e12)
        for _ in range(slots[m]):
            cols.append(base)
            owner.append(m)
        for _ in range(n_vars):  # overflow: usable, but only when the quota cannot hold
            cols.append(base + big)
            owner.append(m)
    matrix = np.stack(cols, axis=1)
    rows, chosen = linear_sum_assignment(matrix)
    plan = np.empty(n_vars, dtype=np.int64)
    plan[rows] = np.asarray(owner)[chosen]
    return plan
