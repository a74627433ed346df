"""Couple checks: is it two people dancing together, judged against the library's own pairs.

Per frame of a couple (the lead's and the follow's world joint positions):

- ``hips``: the distance (m) between the two dancers' root joints;
- ``hands``: the distance (m) between the nearest pair of their wrists (of the four left/right
  pairings: the hands a couple joins change during a dance, the nearest pair is the joined one
  where any is);
- ``body``: the least distance (m) between the two bodies' limb segments (every bone and End
  Site segment, the forearms and hands left out: joined hands touch by design); below the
  library's p1 the bodies pass through each other or nearly so.

``CoupleReference.from_pairs`` pools these over the library's partner takes (danced together)
and keeps the p1 and p99 of hips and hands and the p1 of body; ``couple_scores`` gives a dance's
shares: ``hips_within`` and ``hands_within`` (inside p1-p99), ``body_below_p1``. The library's
own takes score about 98 %, 98 % and 1 % by definition; two takes that were not danced together
(the chance row) score far worse.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dancegraph.motion.fk import end_site_positions
from dancegraph.motion.skeleton import Skeleton

#: frames per chunk of the segment-distance computation (memory: chunk × S² × 3 floats)
CHUNK = 256


def _excluded(skeleton: Skeleton) -> np.ndarray:
    """Bool ``(J,)``: the elbows and every joint below them (forearm and hand bones start there)."""
    out = np.zeros(skeleton.n_joints, dtype=bool)
    for key in ("left_elbow", "right_elbow"):
        if key not in skeleton.canonical:
            continue
        stack = [skeleton.index(skeleton.canonical[key])]
        while stack:
            j = stack.pop()
            out[j] = True
            stack.extend(skeleton.children(j))
    return out


def body_segments(skeleton: Skeleton, positions: np.ndarray, world: np.ndarray) -> np.ndarray:
    """``(F, S, 2, 3)`` the body's limb segments (bone start, end; metres) from forward
    kinematics ``positions (F, J, 3)``, ``world (F, J, 4)``: every bone and End Site whose
    parent joint is not an elbow or below it."""
    off = _excluded(skeleton)
    segs = [
        np.stack([positions[:, p], positions[:, j]], axis=1)
        for j, p in enumerate(skeleton.parents)
        if p >= 0 and not off[p]
    ]
    ends = end_site_positions(skeleton, positions, world)
    segs += [np.stack([positions[:, j], e], axis=1) for j, e in ends.items() if not off[j]]
    return np.stack(segs, axis=1)


def segment_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least distance between segments ``a (..., 2, 3)`` and ``b (..., 2, 3)`` (broadcast) →
    ``(...)`` (closest points clamped to both segments; Ericson, Real-Time Collision Detection,
    5.1.9)."""
    p, u = a[..., 0, :], a[..., 1, :] - a[..., 0, :]
    q, v = b[..., 0, :], b[..., 1, :] - b[..., 0, :]
    w = p - q
    aa, bb, cc = (u * u).sum(-1), (u * v).sum(-1), (v * v).sum(-1)
    d, e = (u * w).sum(-1), (v * w).sum(-1)
    eps = 1e-12
    denom = aa * cc - bb * bb
    s = np.where(denom > eps, np.clip((bb * e - cc * d) / np.maximum(denom, eps), 0.0, 1.0), 0.0)
    t = np.where(cc > eps, (bb * s + e) / np.maximum(cc, eps), 0.0)
    t = np.clip(t, 0.0, 1.0)
    s = np.where(aa > eps, np.clip((bb * t - d) / np.maximum(aa, eps), 0.0, 1.0), 0.0)
    gap = w + s[..., None] * u - t[..., None] * v
    return np.sqrt((gap * gap).sum(-1))


def couple_frames(
    skeleton: Skeleton,
    lead: tuple[np.ndarray, np.ndarray],
    follow: tuple[np.ndarray, np.ndarray],
) -> dict[str, np.ndarray]:
    """Per-frame ``hips``, ``hands`` and ``body`` distances ``(F,)`` (m) of a couple from each
    partner's forward kinematics ``(positions (F, J, 3), world (F, J, 4))`` (same frames)."""
    (lp, lw), (fp, fw) = lead, follow
    n = min(len(lp), len(fp))
    root = int(np.flatnonzero(skeleton.parents < 0)[0])
    hips = np.linalg.norm(lp[:n, root] - fp[:n, root], axis=-1)
    wrists = [skeleton.index(skeleton.canonical[k]) for k in ("left_wrist", "right_wrist")]
    hands = np.min(
        [np.linalg.norm(lp[:n, i] - fp[:n, j], axis=-1) for i in wrists for j in wrists], axis=0
    )
    sa, sb = body_segments(skeleton, lp[:n], lw[:n]), body_segments(skeleton, fp[:n], fw[:n])
    body = np.empty(n)
    for c in range(0, n, CHUNK):
        d = segment_distance(sa[c : c + CHUNK, :, None], sb[c : c + CHUNK, None, :])
        body[c : c + CHUNK] = d.reshape(len(d), -1).min(axis=1)
    return {"hips": hips, "hands": hands, "body": body}


@dataclass
class CoupleReference:
    """The library's couple distributions: ``hips`` and ``hands`` (p1, p99) m, ``body_p1`` m,
    and the library's own ``scores`` (``couple_scores`` of its pooled frames)."""

    hips: tuple[float, float]
    hands: tuple[float, float]
    body_p1: float
    scores: dict

    @classmethod
    def from_pairs(cls, frames: list[dict[str, np.ndarray]]) -> CoupleReference:
        """Pool ``couple_frames`` of the library's partner takes."""
        pooled = {k: np.concatenate([f[k] for f in frames]) for k in ("hips", "hands", "body")}
        ref = cls(
            hips=(
                float(np.percentile(pooled["hips"], 1)),
                float(np.percentile(pooled["hips"], 99)),
            ),
            hands=(
                float(np.percentile(pooled["hands"], 1)),
                float(np.percentile(pooled["hands"], 99)),
            ),
            body_p1=float(np.percentile(pooled["body"], 1)),
            scores={},
        )
        ref.scores = couple_scores(pooled, ref)
        return ref

    def to_dict(self) -> dict:
        return {
            "hips_p1_p99_m": list(self.hips),
            "hands_p1_p99_m": list(self.hands),
            "body_p1_m": self.body_p1,
            "library": self.scores,
        }


def couple_scores(frames: dict[str, np.ndarray], ref: CoupleReference) -> dict:
    """Shares of a couple's frames (``couple_frames``) inside the library's bands:
    ``hips_within``, ``hands_within`` (p1-p99), ``body_below_p1``; and the medians (m)."""
    hips, hands, body = frames["hips"], frames["hands"], frames["body"]
    if hips.size == 0:
        return {"frames": 0}
    return {
        "frames": int(hips.size),
        "hips_within": float(np.mean((hips >= ref.hips[0]) & (hips <= ref.hips[1]))),
        "hands_within": float(np.mean((hands >= ref.hands[0]) & (hands <= ref.hands[1]))),
        "body_below_p1": float(np.mean(body < ref.body_p1)),
        "hips_median_m": float(np.median(hips)),
        "hands_median_m": float(np.median(hands)),
        "body_min_m": float(body.min()),
    }
