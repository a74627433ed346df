"""Evaluation of couple dances: the couple checks (``metrics.couple``) and each partner's seams
and foot sliding as for one dancer (``harness.seam_metrics``), beside their chance row.

``evaluate_couple_result(result_dir, lib, ref)`` scores a ``synthesize --couple`` folder (or a
couple job's result): per alternative the lead and the follow read back from their BVH files at
``harness.EVAL_FPS``; the chance row pairs the lead of alternative k with the follow of
alternative k+1 (two dances that were not danced together). It writes ``couple_metrics.json``
into the folder and returns the same dict.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dancegraph.couple.graph import pair_frames, partner_pairs
from dancegraph.eval.harness import EVAL_FPS, Library, seam_metrics
from dancegraph.metrics.couple import CoupleReference, couple_frames, couple_scores
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.retime import resample
from dancegraph.motion.skeleton import Motion

COUPLE_METRICS = "couple_metrics.json"


def couple_reference(dataset, pairs: list[tuple[str, str]] | None = None) -> CoupleReference:
    """The library's couple distributions from ``dataset``'s partner takes (``pairs``, default
    every pair it declares; ``couple.graph.partner_pairs``)."""
    return CoupleReference.from_pairs(pair_frames(dataset, pairs or partner_pairs(dataset)))


def score_couple(
    lead: Motion,
    follow: Motion,
    seams: list[int],
    bars: np.ndarray | None,
    lib: Library,
    ref: CoupleReference,
) -> dict:
    """The couple checks of one dance and each partner's seam metrics. ``lead``, ``follow``: the
    two dancers (same frames, any rate: read at ``EVAL_FPS``); ``seams``: frames (at their
    rate) where a node takes over; ``bars (T, 2)`` s."""
    fk = {}
    for key, dancer in (("lead", lead), ("follow", follow)):
        m = resample(dancer, EVAL_FPS) if dancer.fps != EVAL_FPS else dancer
        fk[key] = (m.skeleton, forward_kinematics(m))
    skeleton = fk["lead"][0]
    out = {"couple": couple_scores(couple_frames(skeleton, fk["lead"][1], fk["follow"][1]), ref)}
    scale = EVAL_FPS / float(lead.fps)
    at = [int(round(s * scale)) for s in seams]
    if lib.seams is not None:
        for key, (sk, (pos, world)) in fk.items():
            metrics, _ = seam_metrics(lib, pos, world, sk, at, bars)
            out[key] = {
                "seam_flagged_share": metrics["seam_flagged_share"],
                "seam_median_percentile": metrics["seam_median_percentile"],
                "seam_skate_m_s": metrics["seam_skate_m_s"],
                "seams": metrics["seams"]["count"],
            }
    return out


def evaluate_couple_result(result_dir: str | Path, lib: Library, ref: CoupleReference) -> dict:
    """Score every alternative of a couple result folder and the chance row (module
    docstring); writes ``couple_metrics.json`` there and returns it."""
    from dancegraph.preview import read_timeline

    folder = Path(result_dir)
    timeline = read_timeline(folder)
    bars = np.array([[b["start_s"], b["end_s"]] for b in timeline.get("bars", [])]).reshape(-1, 2)
    alts = timeline.get("alternatives", [])
    dancers = [
        tuple(read_bvh(folder / a["files"][f"{key}_bvh"]) for key in ("lead", "follow"))
        for a in alts
    ]
    rows = [
        {"index": a["index"], **score_couple(lead, follow, a.get("seams", []), bars, lib, ref)}
        for a, (lead, follow) in zip(alts, dancers, strict=True)
    ]
    chance = [
        couple_scores(_frames(dancers[k][0], dancers[(k + 1) % len(alts)][1]), ref)
        for k in range(len(alts))
        if len(alts) > 1
    ]
    metrics = {"reference": ref.to_dict(), "alternatives": rows, "chance": chance}
    (folder / COUPLE_METRICS).write_text(json.dumps(metrics, indent=1))
    return metrics


def _frames(lead: Motion, follow: Motion) -> dict[str, np.ndarray]:
    return couple_frames(lead.skeleton, forward_kinematics(lead), forward_kinematics(follow))
