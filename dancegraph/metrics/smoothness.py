"""Seam smoothness: joint jumps and acceleration spikes at the seams of a stitched dance, judged
against the library's own frame-to-frame distribution.

A dance from the graph is bars laid end to end; a bad transition shows as a pop at the seam. Per
frame the largest joint speed (m/s, from consecutive positions) and the largest joint
acceleration (m/s², second differences) are taken; the library's real takes give the reference
distribution of both. A seam scores the percentile of its value in that distribution and is
flagged when either value lies above ``FLAG_PERCENTILE`` (a pop the library itself almost never
shows). Positions ``(F, J, 3)`` are metres; compare dances and library at the same ``fps``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Seams above this percentile of the library's frame-to-frame distribution are flagged.
FLAG_PERCENTILE = 99.0


def frame_jumps(positions: np.ndarray) -> np.ndarray:
    """``(F-1, J)`` per-joint position change between consecutive frames (m)."""
    return np.linalg.norm(np.diff(positions, axis=0), axis=-1)


def frame_signals(positions: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame largest joint speed ``(F-1,)`` m/s (sample i: frames i → i+1) and largest joint
    acceleration ``(F-2,)`` m/s² (sample i: centred on frame i+1) of ``positions (F, J, 3)``."""
    pos = np.asarray(positions, dtype=float)
    speed = frame_jumps(pos).max(axis=1) * fps if pos.shape[0] > 1 else np.zeros(0)
    if pos.shape[0] > 2:
        acc = np.linalg.norm(np.diff(pos, n=2, axis=0), axis=-1).max(axis=1) * fps * fps
    else:
        acc = np.zeros(0)
    return speed, acc


@dataclass
class Reference:
    """The library's sorted per-frame joint speeds and accelerations (``frame_signals``), and
    the chance row of the seam scores: every frame of the library scored as if it were a seam
    (``median_percentile``, ``flagged_share``; by definition about 1-2 % lie above p99)."""

    speed: np.ndarray
    acc: np.ndarray
    fps: float
    chance: dict | None = None

    @classmethod
    def from_takes(cls, positions: list[np.ndarray], fps: float) -> Reference:
        """Pool ``frame_signals`` of every take ``(F, J, 3)`` at ``fps``."""
        parts = [frame_signals(p, fps) for p in positions]
        ref = cls(
            speed=np.sort(np.concatenate([s for s, _ in parts])),
            acc=np.sort(np.concatenate([a for _, a in parts])),
            fps=float(fps),
        )
        scores = np.concatenate([ref._scores(s, a, np.arange(2, s.size + 1)) for s, a in parts])
        ref.chance = {
            "frames": int(scores.size),
            "median_percentile": float(np.median(scores)) if scores.size else None,
            "flagged_share": float((scores > FLAG_PERCENTILE).mean()) if scores.size else None,
        }
        return ref

    def percentile(self, value, kind: str):
        """Percentile (0–100) of ``value`` (scalar or array) in the library's ``kind`` ("speed"
        or "acc") values."""
        ref = self.speed if kind == "speed" else self.acc
        if ref.size == 0:
            return np.zeros(np.shape(value))
        return 100.0 * np.searchsorted(ref, value, side="left") / ref.size

    def _scores(self, speed: np.ndarray, acc: np.ndarray, seams: np.ndarray) -> np.ndarray:
        """Seam score (the larger percentile of ``seam_report``) at frames ``seams``."""
        a = np.maximum(acc[np.maximum(seams - 2, 0)], acc[np.minimum(seams - 1, acc.size - 1)])
        return np.maximum(self.percentile(speed[seams - 1], "speed"), self.percentile(a, "acc"))


def seam_report(positions: np.ndarray, fps: float, seams, reference: Reference) -> dict:
    """Score every seam of ``positions (F, J, 3)``; ``seams``: frame indices where a new bar starts.

    Per seam s: ``speed`` = the largest joint speed from frame s−1 to s (m/s), ``acc`` = the
    largest joint acceleration centred on s−1 or s (m/s²), their percentiles in ``reference``,
    and ``flagged`` when either percentile exceeds ``FLAG_PERCENTILE``. Summary: ``count``,
    ``flagged`` (count), ``flagged_share``, ``median_percentile`` (of the larger of the two
    percentiles per seam), ``max_speed_m_s``, ``max_acc_m_s2``.
    """
    if abs(reference.fps - fps) > 1e-6:
        raise ValueError(f"reference at {reference.fps} fps, dance at {fps} fps")
    speed, acc = frame_signals(positions, fps)
    rows = []
    for s in sorted(int(x) for x in seams):
        if s < 1 or s > speed.size:
            continue
        v = float(speed[s - 1])
        window = acc[max(0, s - 2) : min(acc.size, s)]
        a = float(window.max()) if window.size else 0.0
        ps, pa = float(reference.percentile(v, "speed")), float(reference.percentile(a, "acc"))
        rows.append(
            {
                "frame": s,
                "speed_m_s": v,
                "acc_m_s2": a,
                "speed_percentile": ps,
                "acc_percentile": pa,
                "flagged": bool(max(ps, pa) > FLAG_PERCENTILE),
            }
        )
    flagged = sum(r["flagged"] for r in rows)
    return {
        "count": len(rows),
        "flagged": flagged,
        "flagged_share": flagged / len(rows) if rows else 0.0,
        "median_percentile": (
            float(np.median([max(r["speed_percentile"], r["acc_percentile"]) for r in rows]))
            if rows
            else None
        ),
        "max_speed_m_s": max((r["speed_m_s"] for r in rows), default=None),
        "max_acc_m_s2": max((r["acc_m_s2"] for r in rows), default=None),
        "seams": rows,
    }
