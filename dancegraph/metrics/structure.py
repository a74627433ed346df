"""Structure and control satisfaction of a path, and its motif-signature distance to a target.

A path is ``nodes (T,)``: the graph node index danced on each music bar. Structure pairs come
from the music's tags by the search's own rule (``problem.structure_pairs``): a repeat pair is
satisfied when both bars dance the same node, a mirror pair when the later bar dances the
earlier one's mirror. Controls are the spec's include / exclude / waypoints / stage / motifs /
signature / recreate entries, each checked on the path (and on the rendered root trajectory for
positions); the signature, a soft target, is reported as its distance, not as pass or fail.
"""

from __future__ import annotations

import numpy as np

from dancegraph.graph import choreography
from dancegraph.graph.artifact import MotionGraph
from dancegraph.graph.problem import bars_in, match_nodes, structure_pairs, target_signature
from dancegraph.metrics.physical import stage_report
from dancegraph.spec import Spec


def structure_satisfaction(nodes: np.ndarray, tags: list[dict], mirror_of: np.ndarray) -> dict:
    """Per rule (``repeat``, ``mirror``): ``pairs``, ``satisfied``, ``share`` (None without
    pairs); and ``violated``: ``[{bars: [a, b], rule}]``. ``tags``: per-bar structure tags."""
    nodes = np.asarray(nodes, dtype=np.int64)
    mirror_of = np.asarray(mirror_of)
    out: dict = {"repeat": {"pairs": 0, "satisfied": 0}, "mirror": {"pairs": 0, "satisfied": 0}}
    violated = []
    for a, b, parity, rule in structure_pairs(tags, True, True):
        want = nodes[a] if parity == 0 else mirror_of[nodes[a]]
        out[rule]["pairs"] += 1
        if nodes[b] == want:
            out[rule]["satisfied"] += 1
        else:
            violated.append({"bars": [int(a), int(b)], "rule": rule})
    for rule in ("repeat", "mirror"):
        r = out[rule]
        r["share"] = r["satisfied"] / r["pairs"] if r["pairs"] else None
    out["violated"] = violated
    return out


def signature_distance(graph: MotionGraph, nodes: np.ndarray, target: str = "dataset") -> dict:
    """Chi-square distance of the path's motif histogram to ``target``'s signature ('dataset' or a
    take id). Returns ``chi2``, ``histogram (k,)`` and ``target (k,)`` (normalised)."""
    goal = np.asarray(target_signature(graph, target, "signature.target"), dtype=float)
    hist = choreography.motif_signature(np.asarray(graph.motif)[np.asarray(nodes)], goal.size)
    return {
        "chi2": choreography.chi_square(hist, goal),
        "histogram": hist.tolist(),
        "target": goal.tolist(),
    }


def control_satisfaction(
    graph: MotionGraph,
    spec: Spec,
    bars: np.ndarray,
    nodes: np.ndarray,
    root_xz: np.ndarray,
    fps: float,
) -> dict:
    """Check every control of ``spec`` on a path.

    ``bars (T, 2)`` music bars (s), ``nodes (T,)`` node indices, ``root_xz (F, 2)`` the rendered
    root on the ground plane at ``fps`` (frame 0 = t 0 of the song). Returns ``items``: one
    ``{control, satisfied, detail}`` per control, plus ``count``, ``satisfied`` and ``share``
    over the hard controls (None when there are none). The signature is a soft target: its item
    carries the chi-square distance and ``satisfied`` None.
    """
    bars = np.asarray(bars, dtype=float).reshape(-1, 2)
    nodes = np.asarray(nodes, dtype=np.int64)
    items = []
    for i, inc in enumerate(spec.include):
        name = f"include[{i}]"
        at = bars_in(inc.bars, inc.seconds, bars, name)
        want = graph.node_index(inc.node) if graph.has_node(inc.node) else -1
        hits = int((nodes[at] == want).sum())
        items.append(
            {"control": name, "satisfied": hits == at.size, "detail": f"{hits}/{at.size} bars"}
        )
    for i, exc in enumerate(spec.exclude):
        name = f"exclude[{i}]"
        at = bars_in(exc.bars, exc.seconds, bars, name)
        banned = match_nodes(graph, exc.node, exc.tag, name)
        used = int(np.isin(nodes[at], banned).sum())
        items.append(
            {"control": name, "satisfied": used == 0, "detail": f"{used} bars use excluded nodes"}
        )
    xz = np.asarray(root_xz, dtype=float).reshape(-1, 2)
    for i, wp in enumerate(spec.waypoints):
        f = int(np.clip(round(wp.second * fps), 0, len(xz) - 1))
        d = float(np.hypot(*(xz[f] - np.asarray(wp.position, dtype=float))))
        items.append(
            {
                "control": f"waypoints[{i}]",
                "satisfied": d <= wp.tolerance + 1e-6,
                "detail": f"{d:.3f} m from the waypoint (tolerance {wp.tolerance} m)",
            }
        )
    stage = stage_report(xz, spec.stage)
    if stage is not None:
        items.append(
            {
                "control": "stage",
                "satisfied": stage["inside_share"] == 1.0,
                "detail": f"{stage['inside_share']:.1%} of frames inside, "
                f"{stage['max_outside_m']:.3f} m out at most",
            }
        )
    motifs = np.asarray(graph.motif)
    for i, pin in enumerate(spec.motifs):
        ok = pin.bar < len(nodes) and int(motifs[nodes[pin.bar]]) == pin.motif
        items.append({"control": f"motifs[{i}]", "satisfied": bool(ok), "detail": ""})
    if spec.signature is not None:
        chi2 = signature_distance(graph, nodes, spec.signature.target)["chi2"]
        items.append(
            {
                "control": "signature",
                "satisfied": None,  # a soft target: its distance is the measure
                "chi2": chi2,
                "detail": f"chi-square {chi2:.4f} to {spec.signature.target!r}",
            }
        )
    if spec.recreate is not None:
        ref = choreography.take_motif_sequence(graph, spec.recreate)
        n = min(len(ref), len(nodes))
        same = int((motifs[nodes[:n]] == ref[:n]).sum())
        items.append(
            {
                "control": "recreate",
                "satisfied": same == n,
                "detail": f"{same}/{n} bars follow {spec.recreate}'s motifs",
            }
        )
    hard = [it for it in items if it["satisfied"] is not None]
    done = sum(bool(it["satisfied"]) for it in hard)
    return {
        "count": len(hard),
        "satisfied": done,
        "share": done / len(hard) if hard else None,
        "items": items,
    }
