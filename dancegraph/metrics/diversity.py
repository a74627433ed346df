"""Diversity of dances: among the alternatives for one song, and across songs.

- ``feature_diversity``: mean pairwise Euclidean distance of (normalised) kinetic feature vectors,
  one per dance (Bailando's Div_k, on the features of ``kinetic.py``).
- ``path_diversity``: mean over pairs of paths of the share of bars where they dance different
  nodes (1 = no bar in common, 0 = the same dance).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.distance import pdist


def feature_diversity(features: np.ndarray) -> float | None:
    """Mean pairwise distance of ``features (N, D)``; None for fewer than two dances."""
    f = np.asarray(features, dtype=float)
    if f.ndim != 2 or len(f) < 2:
        return None
    return float(pdist(f).mean())


def path_diversity(paths: list[np.ndarray]) -> float | None:
    """Mean share of differing bars over pairs of equal-length ``paths`` (``(T,)`` node indices);
    None for fewer than two paths."""
    if len(paths) < 2:
        return None
    shares = []
    for i in range(len(paths)):
        for j in range(i + 1, len(paths)):
            a, b = np.asarray(paths[i]), np.asarray(paths[j])
            n = min(len(a), len(b))
            shares.append(float(np.mean(a[:n] != b[:n])) if n else 0.0)
    return float(np.mean(shares))
