"""Rhythm signatures (ChoreoMaster §3.2, DESIGN.md §4).

A signature marks which of the 8 half-beat slots of a 4-beat bar carry an accent. It is written
as an 8-character string whose *rightmost* character is slot 0 (the downbeat); slot ``i`` sits at
beat ``i / 2``. Even slots are regular beats, odd slots half beats. As arrays, signatures are
``(8,)`` (or ``(N, 8)``) 0/1 vectors indexed by slot, so ``bits[0]`` is the downbeat, or packed into one
*pattern* byte (bit ``i`` = slot ``i``): any of the 256 slot patterns, not only the common ones
(a bar of dance has the pattern its kinematic beats make).
"""

from __future__ import annotations

import numpy as np

N_SLOTS = 8

#: The 13 common signatures of ChoreoMaster Table 2, in the table's order.
COMMON_SIGNATURES: tuple[str, ...] = (
    "00000001",
    "00000101",
    "00010001",
    "00010101",
    "01000001",
    "01000101",
    "01010001",
    "01010101",
    "01010111",
    "01110111",
    "01111111",
    "11111101",
    "11111111",
)

#: Hamming weight per slot: 1.0 for regular beats (even slots), 0.5 for half beats (odd slots).
SLOT_WEIGHTS = np.array([1.0 if i % 2 == 0 else 0.5 for i in range(N_SLOTS)])


def to_bits(signature: str) -> np.ndarray:
    """Signature string → ``(8,)`` int array indexed by slot (``bits[0]`` is the downbeat)."""
    if len(signature) != N_SLOTS or set(signature) - {"0", "1"}:
        raise ValueError(f"a rhythm signature is 8 characters of 0/1, got {signature!r}")
    return np.array([int(c) for c in reversed(signature)], dtype=np.int8)


def to_string(bits: np.ndarray) -> str:
    """``(8,)`` 0/1 array indexed by slot → signature string (slot 0 rightmost)."""
    bits = np.asarray(bits).astype(int).reshape(N_SLOTS)
    return "".join(str(int(b)) for b in bits[::-1])


#: ``(13, 8)`` int8: the common signatures as slot-indexed bit arrays.
COMMON_BITS = np.stack([to_bits(s) for s in COMMON_SIGNATURES])


def distance(a: np.ndarray | str, b: np.ndarray | str) -> np.ndarray:
    """Weighted Hamming distance, 1.0 per differing regular slot and 0.5 per half slot.

    ``a``, ``b``: strings or slot-indexed arrays of shape ``(..., 8)``; broadcast. Returns ``(...)``.
    """
    a_bits = to_bits(a) if isinstance(a, str) else np.asarray(a)
    b_bits = to_bits(b) if isinstance(b, str) else np.asarray(b)
    return (np.abs(a_bits.astype(float) - b_bits.astype(float)) * SLOT_WEIGHTS).sum(axis=-1)


#: ``(13, 13)`` pairwise distances between the common signatures.
COMMON_DISTANCES = distance(COMMON_BITS[:, None, :], COMMON_BITS[None, :, :])


#: ``(256, 8)`` int8: every slot pattern's bits (row p is pattern p).
PATTERN_BITS = ((np.arange(256)[:, None] >> np.arange(N_SLOTS)[None, :]) & 1).astype(np.int8)

#: ``(13, 256)`` distances from each common signature to every slot pattern.
PATTERN_DISTANCES = distance(COMMON_BITS[:, None, :], PATTERN_BITS[None, :, :])


def to_pattern(signature: np.ndarray | str) -> np.ndarray:
    """Signature string or slot-indexed bits ``(..., 8)`` → pattern byte(s) ``(...)`` uint8."""
    bits = to_bits(signature) if isinstance(signature, str) else np.asarray(signature)
    return (bits.astype(np.int64) << np.arange(N_SLOTS)).sum(axis=-1).astype(np.uint8)


def nearest_common(bits: np.ndarray) -> np.ndarray:
    """Index into ``COMMON_SIGNATURES`` of the nearest common signature, for ``(..., 8)`` bits."""
    d = distance(np.asarray(bits)[..., None, :], COMMON_BITS)
    return np.argmin(d, axis=-1)


def scores_from_slot_evidence(evidence: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Score each common signature against per-slot accent evidence.

    ``evidence``: ``(N, 8)`` accent strengths in [0, 1] per half-beat slot (slot 0 = downbeat).
    Returns ``(N, 13)`` scores in [0, 1] (higher is a better match): one minus the weighted soft
    Hamming distance between the evidence and each signature, normalised by the largest possible
    distance (6.0). ``threshold`` shifts the evidence so that values above it count as accents.
    """
    evidence = np.clip(np.asarray(evidence, dtype=float), 0.0, 1.0)
    # Soft bits: evidence at the threshold is maximally uncertain (0.5).
    soft = np.clip(0.5 + (evidence - threshold) / (2 * max(threshold, 1 - threshold)), 0.0, 1.0)
    d = (np.abs(soft[:, None, :] - COMMON_BITS[None, :, :]) * SLOT_WEIGHTS).sum(axis=-1)
    return 1.0 - d / SLOT_WEIGHTS.sum()


def top_k(scores: np.ndarray, k: int = 3) -> np.ndarray:
    """``(N, 13)`` scores → ``(N, k)`` indices into ``COMMON_SIGNATURES``, best first."""
    return np.argsort(-np.asarray(scores), axis=-1, kind="stable")[:, :k]
