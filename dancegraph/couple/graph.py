"""The couple graph: a node is the same bar of both partners of a take danced together.

A dataset whose manifest declares ``partners`` (takes danced together to the same music, e.g.
cmu-salsa's 60_NN with 61_NN) builds, beside its solo graph, a couple graph stored as the graph
``<dataset>.couple`` (``couple_graph_name``; the same versioned artifact, ``graph.artifact``):

- one beat grid per pair from both bodies' evidence: the two takes' ``tempo.step_signals``
  summed (each column is unit-variance, the sum scaled by 1/√2) into ``tempo.estimate_grid``, the
  beats moved onto the stops of either partner (``retime.accent_anchors``), and each bar's rhythm
  signature from both partners' kinematic beats;
- the solo build (``build.build_arrays``) run on each partner's bars over that grid, with
  mirrors and without blends and shuffles (a blend or shuffle of two takes would part the
  hands): nodes line up one to one; a mirror mirrors both partners about the same plane, so the
  follow stays the follow on the mirrored side;
- the couple's arrays: the lead's node table, motion, motifs and node ids (``<lead take>:<bar>``,
  shared with the solo graph), the follow's motion as ``follow_root``/``follow_rotations`` on the
  same rows and beats, the relative placement of the follow at each node's downbeat
  (``rel_entry``) and closing downbeat (``rel_exit``) (``couple.placement``), the mean of the
  two styles and anchorings, both partners' seam features side by side (each scaled by ½, so a
  transition's distance is the mean of the two partners'), and the couple's centre (the mid
  point of the two roots, in the lead's heading) as the root displacement and path the search's
  stage and waypoint terms read;
- edges p → q where each partner's own transition T = λ8·T_d + λ9·T_z at the bar line is below
  δT and the relative placement at the cut matches: ``rel_exit[p]`` against ``rel_entry[q]``
  within the library's own change of relative placement over one beat (``PLACEMENT_QUANTILE``
  of the partner takes' frames, in metres and radians, in ``manifest["couple"]``); cost the
  mean of the two partners' T. Consecutive bars of a take are always linked; a node left
  without out- or in-edges gets its ``min_degree`` cheapest placement-matching ones (else the
  cheapest).
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace

import numpy as np

from dancegraph.couple.placement import relative_placement, wrap
from dancegraph.errors import DanceGraphError
from dancegraph.graph import artifact
from dancegraph.graph.artifact import MotionGraph
from dancegraph.graph.build import (
    PATH_SAMPLES,
    BarSet,
    BuildParams,
    _block_distance,
    _Nodes,
    build_arrays,
    to_csr,
    transition_features,
)
from dancegraph.metrics.couple import CoupleReference, couple_frames
from dancegraph.motion import quat
from dancegraph.motion import tempo as tempo_mod
from dancegraph.motion.dataset import Dataset, step_evidence
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.retime import accent_anchors, node_warp
from dancegraph.motion.skeleton import Motion, Skeleton
from dancegraph.rhythm.motion import motion_stops
from dancegraph.rhythm.signatures import to_string
from dancegraph.store import ObjectStore

#: the couple graph of dataset ``<name>`` is stored as the graph ``<name>.couple``
COUPLE_SUFFIX = ".couple"
#: quantile of the library's change of relative placement over one beat that a cut may show
PLACEMENT_QUANTILE = 0.75
#: arrays a couple graph holds beyond ``artifact.ARRAYS``
COUPLE_ARRAYS = ("follow_root", "follow_rotations", "rel_entry", "rel_exit")


def couple_graph_name(dataset: str) -> str:
    """The graph name of ``dataset``'s couple graph."""
    return f"{dataset}{COUPLE_SUFFIX}"


def partner_pairs(dataset: Dataset) -> list[tuple[str, str]]:
    """The (lead, follow) clip ids the dataset's manifest declares danced together and both
    imported. Raises ``DanceGraphError(code="dataset_no_partners")`` when there are none."""
    clips = {c.id for c in dataset.clips}
    rows = dataset.meta.get("partners") or []
    pairs = [tuple(r["pair"]) for r in rows if all(c in clips for c in r["pair"])]
    if not pairs:
        raise DanceGraphError(
            f"dataset {dataset.name!r} declares no partner takes (manifest 'partners'): "
            "it has no couple dances",
            code="dataset_no_partners",
            field="couple",
        )
    return [(str(a), str(b)) for a, b in pairs]


def _pair_evidence(motion: Motion) -> tuple[np.ndarray, np.ndarray | None]:
    positions, world = forward_kinematics(motion)
    return step_evidence(motion.skeleton, positions, world, motion.fps)


def shared_grid(
    lead: Motion, follow: Motion, prior_bpm: tuple[float, float] | None, params: BuildParams
) -> tuple[np.ndarray, list[str]]:
    """One bar grid for two takes danced together (same frames, same rate): ``bar_beats (B,
    5)`` s and the bars' rhythm signatures (8-character strings) from both partners' kinematic
    beats. Raises ``DanceGraphError(code="clip_too_short")`` under 2 s of frames."""
    if lead.n_frames != follow.n_frames or lead.fps != follow.fps:
        raise DanceGraphError(
            "partner takes must have the same frame count and rate", code="partners_unsynchronised"
        )
    kb_l, sig_l = _pair_evidence(lead)
    kb_f, sig_f = _pair_evidence(follow)
    if sig_l is None or sig_f is None:
        raise DanceGraphError("a partner take under 2 s has no grid", code="clip_too_short")
    grid_params = tempo_mod.GridParams(prior_bpm=prior_bpm or tempo_mod.DEFAULT_PRIOR_BPM)
    grid = tempo_mod.estimate_grid((sig_l + sig_f) / np.sqrt(2.0), lead.fps, grid_params)
    bars = np.asarray(grid.bars, dtype=float).reshape(-1, 5)
    last = (lead.n_frames - 1) / lead.fps
    bars = bars[(bars[:, 0] >= 0.0) & (bars[:, 4] <= last)]
    if params.accent_anchors and len(bars):
        stops = np.sort(np.concatenate([motion_stops(lead), motion_stops(follow)]))
        bars = accent_anchors(bars, stops, params.accent_tolerance, params.accent_max_speed)
    kb = np.sort(np.concatenate([kb_l, kb_f]))
    sigs = [to_string(b) for b in tempo_mod.bar_signature_bits(kb, bars)]
    return bars, sigs


def pair_frames(dataset: Dataset, pairs: list[tuple[str, str]]) -> list[dict[str, np.ndarray]]:
    """``metrics.couple.couple_frames`` of every partner pair's takes (per-frame hips, hands and
    body distances of the real couples)."""
    out = []
    for a, b in pairs:
        lead, follow = dataset.motion(a), dataset.motion(b)
        out.append(
            couple_frames(dataset.skeleton, forward_kinematics(lead), forward_kinematics(follow))
        )
    return out


def _inside(frames: dict[str, np.ndarray], spans: np.ndarray, ref: CoupleReference) -> np.ndarray:
    """Bool ``(B,)``: bars (frame ``spans (B, 2)`` [start, end)) whose every frame has the
    real pair's hips distance in the library's p1-p99 and their bodies no nearer than its p1."""
    ok = (frames["hips"] >= ref.hips[0]) & (frames["hips"] <= ref.hips[1])
    ok &= frames["body"] >= ref.body_p1
    bad = np.concatenate([[0], np.cumsum(~ok)])
    lo = np.clip(spans[:, 0], 0, len(ok))
    hi = np.clip(spans[:, 1], lo, len(ok))
    return bad[hi] - bad[lo] == 0


def _partner_bars(
    dataset: Dataset, pairs: list[tuple[str, str]], params: BuildParams
) -> tuple[BarSet, BarSet, CoupleReference, dict]:
    """The lead's and the follow's ``BarSet`` over each pair's shared grid, bar for bar, of the
    bars inside the library's couple bands (``_inside``); the library's ``CoupleReference``
    and a report (bars kept and left out)."""
    prior = dataset.meta.get("tempo_prior_bpm")
    prior_bpm = (float(prior[0]), float(prior[1])) if prior else None
    frames = pair_frames(dataset, pairs)
    ref = CoupleReference.from_pairs(frames)
    lead_takes, follow_takes = [], []
    kept = dropped = 0
    for (a, b), pair in zip(pairs, frames, strict=True):
        lead, follow = dataset.motion(a), dataset.motion(b)
        bars, sigs = shared_grid(lead, follow, prior_bpm, params)
        spans = np.round(bars[:, [0, 4]] * lead.fps).astype(np.int64)
        keep = _inside(pair, spans, ref)
        kept, dropped = kept + int(keep.sum()), dropped + int((~keep).sum())
        index = np.flatnonzero(keep).astype(np.int64)
        sig = [sigs[i] for i in index]
        lead_takes.append((lead, bars[keep], index, sig, spans[keep]))
        follow_takes.append((follow, bars[keep], index, sig, spans[keep]))
    lead_set = BarSet.from_takes(dataset.skeleton, [a for a, _ in pairs], lead_takes)
    follow_set = BarSet.from_takes(dataset.skeleton, [b for _, b in pairs], follow_takes)
    return lead_set, follow_set, ref, {"bars": kept, "bars_outside_bands": dropped}


def _root_at(arrays: dict, prefix: str, phases: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every node's root position ``(N, P, 3)`` and root rotation ``(N, P, 4)`` at bar phases
    ``phases (P,)`` through its own beat warp (nearest frame for the rotation)."""
    ptr, beats = arrays["motion_ptr"], arrays["motion_beats"]
    root, rot = arrays[f"{prefix}root"], arrays[f"{prefix}rotations"]
    n = len(arrays["motion_row"])
    pos, rot0 = np.empty((n, len(phases), 3)), np.empty((n, len(phases), 4))
    for i in range(n):
        a, b = int(ptr[i]), int(ptr[i + 1])
        f = np.clip(node_warp(beats[i].astype(float))(phases), 0.0, b - a - 1.0)
        frames = np.arange(b - a)
        for k in range(3):
            pos[i, :, k] = np.interp(f, frames, root[a:b, k])
        rot0[i] = rot[a + np.round(f).astype(np.int64), 0]
    return pos, rot0


def _placements(arrays: dict, phases: np.ndarray) -> np.ndarray:
    """``(N, P, 3)`` the follow's placement in the lead's frame (``relative_placement``) at bar
    phases ``phases (P,)`` of every node."""
    lead, lead_rot = _root_at(arrays, "", phases)
    follow, follow_rot = _root_at(arrays, "follow_", phases)
    return relative_placement(lead, lead_rot, follow, follow_rot)


def _centre_paths(arrays: dict, frames_per_bar: int) -> dict[str, np.ndarray]:
    """The couple centre's ``disp (N, 3)``, ``radius (N,)`` and ``root_path (N, S, 2)`` in the
    lead's heading frame at each node's downbeat (what ``build.bar_samples`` gives a dancer),
    and ``rel_entry``/``rel_exit (N, 3)``."""
    phases = np.arange(frames_per_bar + 1) * 4.0 / frames_per_bar
    lead, lead_rot = _root_at(arrays, "", phases)
    follow, follow_rot = _root_at(arrays, "follow_", phases)
    centre = 0.5 * (lead + follow)
    yaw = quat.heading_angle(lead_rot)
    turn = quat.from_y_angle(-yaw[:, :1])
    local = quat.rotate(np.broadcast_to(turn, centre.shape[:2] + (4,)), centre - centre[:, :1])
    path = local[:, np.linspace(0, frames_per_bar, PATH_SAMPLES, endpoint=False).astype(int)]
    rel = relative_placement(lead, lead_rot, follow, follow_rot)
    return {
        "disp": np.stack(
            [local[:, -1, 0], local[:, -1, 2], wrap(yaw[:, -1] - yaw[:, 0])], axis=1
        ).astype(np.float32),
        "radius": np.linalg.norm(local[:, :-1][..., [0, 2]], axis=-1)
        .max(axis=1)
        .astype(np.float32),
        "root_path": path[..., [0, 2]].astype(np.float32),
        "rel_entry": rel[:, 0].astype(np.float32),
        "rel_exit": rel[:, -1].astype(np.float32),
    }


def placement_tolerance(dataset: Dataset, pairs: list[tuple[str, str]], beat_s: float) -> dict:
    """The library's own spread of relative placement: ``PLACEMENT_QUANTILE`` of how far the
    follow's placement in the lead's frame moves (``xz_m``, metres) and turns (``yaw_rad``) over
    one beat (``beat_s`` seconds) across every frame of the partner takes."""
    moved, turned = [], []
    for a, b in pairs:
        lead, follow = dataset.motion(a), dataset.motion(b)
        rel = relative_placement(
            lead.root_positions, lead.rotations[:, 0], follow.root_positions, follow.rotations[:, 0]
        )
        lag = max(1, int(round(beat_s * lead.fps)))
        moved.append(np.linalg.norm(rel[lag:, :2] - rel[:-lag, :2], axis=1))
        turned.append(np.abs(wrap(rel[lag:, 2] - rel[:-lag, 2])))
    return {
        "quantile": PLACEMENT_QUANTILE,
        "xz_m": float(np.quantile(np.concatenate(moved), PLACEMENT_QUANTILE)),
        "yaw_rad": float(np.quantile(np.concatenate(turned), PLACEMENT_QUANTILE)),
    }


def _keep_cheapest(cost: np.ndarray, allowed: np.ndarray, k: int) -> np.ndarray:
    """Bool ``(N, N)``: per row the ``k`` cheapest allowed entries."""
    masked = np.where(allowed, cost, np.inf)
    order = np.argsort(masked, axis=1, kind="stable")[:, :k]
    keep = np.zeros_like(allowed)
    np.put_along_axis(keep, order, True, axis=1)
    return np.asarray(keep & allowed, dtype=bool)


def _offset_features(
    arrays: dict, prefix: str, skeleton: Skeleton, params: BuildParams, beat_s: float
):
    """One partner's seam features at the cut offsets: ``exit``, ``entry (O, N, D)``
    (``build.transition_features``; NaN where a node lacks the frames) and the blocks."""
    nodes = _Nodes(
        ptr=np.asarray(arrays["motion_ptr"], dtype=np.int64),
        root=np.asarray(arrays[f"{prefix}root"], dtype=np.float64),
        rotations=np.asarray(arrays[f"{prefix}rotations"], dtype=np.float32),
        beats=np.asarray(arrays["motion_beats"], dtype=np.float64),
        fps=np.asarray(arrays["motion_fps"], dtype=np.float64),
    )
    return transition_features(skeleton, nodes, params.offsets(), beat_s)


def couple_edges(
    arrays: dict,
    skeleton: Skeleton,
    params: BuildParams,
    tol: dict,
    forced: np.ndarray,
    beat_s: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Edges ``(src, dst, cost)`` of the couple graph and a report (module docstring).

    ``arrays``: the couple's arrays so far (both partners' motion, ``style (N, 32)``);
    ``tol``: ``placement_tolerance``; ``forced (M, 2)`` pairs always linked (consecutive
    bars); ``beat_s``: the library's median beat (velocities of the seam features). Per cut
    offset o (``params.offsets()``) each partner's T of p at bar phase 4 + o against q at
    phase o, and the follow's placement there; the cost is the least over the offsets where
    both partners are smooth and the placement matches."""
    w, s = params.w_pose, params.w_style
    style = arrays["style"].astype(np.float64)
    t_z = s * np.sqrt(np.maximum(((style[:, None, :] - style[None, :, :]) ** 2).sum(-1), 0.0))
    x_l, e_l, blocks = _offset_features(arrays, "", skeleton, params, beat_s)
    x_f, e_f, _ = _offset_features(arrays, "follow_", skeleton, params, beat_s)
    offsets = params.offsets()
    rel_x = _placements(arrays, 4.0 + offsets)  # (N, O, 3)
    rel_e = _placements(arrays, offsets)
    n = len(style)
    cost, match = np.full((n, n), np.inf), np.zeros((n, n), dtype=bool)
    for o in range(len(offsets)):
        t_l = np.nan_to_num(w * _block_distance(x_l[o], e_l[o], blocks), nan=np.inf) + t_z
        t_f = np.nan_to_num(w * _block_distance(x_f[o], e_f[o], blocks), nan=np.inf) + t_z
        d = rel_x[:, o, None, :] - rel_e[None, :, o, :]
        here = (np.linalg.norm(d[..., :2], axis=-1) <= tol["xz_m"]) & (
            np.abs(wrap(d[..., 2])) <= tol["yaw_rad"]
        )
        smooth = here & (t_l < params.threshold) & (t_f < params.threshold)
        cost = np.where(smooth, np.minimum(cost, 0.5 * (t_l + t_f)), cost)
        match |= here
        if o == 0:  # the bar line: the cost of a transition no offset makes smooth
            line = 0.5 * (t_l + t_f)
    np.fill_diagonal(match, False)
    smooth = np.isfinite(cost) & match
    cost = np.where(smooth, cost, line)
    keep = _keep_cheapest(cost, smooth, params.max_out_degree)
    keep[forced[:, 0], forced[:, 1]] = True
    dead_out = ~keep.any(axis=1)
    has_match = np.asarray(match.any(axis=1), dtype=bool)
    fallback = np.where(has_match[:, None], match, ~np.eye(n, dtype=bool))
    keep[dead_out] |= _keep_cheapest(cost, fallback, params.min_degree)[dead_out]
    dead_in = ~keep.any(axis=0)
    keep[:, dead_in] |= _keep_cheapest(cost.T, fallback.T, params.min_degree).T[:, dead_in]
    src, dst = np.nonzero(keep)
    report = {
        "pairs_below_threshold": int(smooth.sum()),
        "placement_match_share": float(match.mean()),
        "forced_out": int(dead_out.sum()),
        "forced_in": int(dead_in.sum()),
        "consecutive": int(len(forced)),
    }
    return src, dst, cost[src, dst].astype(np.float32), report


def _consecutive(clip: np.ndarray, bar: np.ndarray, nb: int, mirrored: bool) -> np.ndarray:
    """``(M, 2)`` node pairs (bar b, bar b+1 of one take) among the ``nb`` originals, and the
    same pairs of their mirrors (nodes ``nb ..``) when ``mirrored``."""
    nxt = {(int(c), int(b)): i for i, (c, b) in enumerate(zip(clip[:nb], bar[:nb], strict=True))}
    pairs = [
        (i, nxt[(int(clip[i]), int(bar[i]) + 1)])
        for i in range(nb)
        if (int(clip[i]), int(bar[i]) + 1) in nxt
    ]
    if mirrored:
        pairs += [(p + nb, q + nb) for p, q in pairs]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def couple_params(params: BuildParams | None = None) -> BuildParams:
    """``params`` (default ``BuildParams()``) without blends and shuffles: a couple's node is a
    bar both partners danced together."""
    return replace(params or BuildParams(), blend_ratio=0.0, shuffle_ratio=0.0)


def build_couple_arrays(
    dataset: Dataset, pairs: list[tuple[str, str]] | None = None, params: BuildParams | None = None
) -> tuple[dict, list[str], dict]:
    """The couple graph of ``dataset``'s partner takes (``pairs``, default all it declares):
    ``(arrays, node_ids, manifest)`` for ``artifact.write_graph`` (module docstring)."""
    t0 = time.perf_counter()
    params = couple_params(params)
    pairs = pairs or partner_pairs(dataset)
    lead_set, follow_set, ref, bar_report = _partner_bars(dataset, pairs, params)
    lead, ids, manifest = build_arrays(lead_set, params)
    follow, _, _ = build_arrays(follow_set, params)
    arrays = dict(lead)
    arrays["follow_root"] = follow["root"]
    arrays["follow_rotations"] = follow["rotations"]
    arrays.update(_centre_paths(arrays, params.frames_per_bar))
    arrays["style"] = (0.5 * (lead["style"] + follow["style"])).astype(np.float32)
    if "anchoring" in lead and "anchoring" in follow:
        arrays["anchoring"] = (0.5 * (lead["anchoring"] + follow["anchoring"])).astype(np.float32)
    for key in ("entry", "exit", "entry_pc", "exit_pc"):
        arrays[key] = (0.5 * np.concatenate([lead[key], follow[key]], axis=1)).astype(np.float32)
    beat_s = float(manifest["seam"]["beat_s"])
    tol = placement_tolerance(dataset, pairs, beat_s)
    nb = len(lead_set.signature)
    forced = _consecutive(lead["node_clip"], lead["node_bar"], nb, params.mirror)
    blocks = list(manifest["feature_blocks"])
    src, dst, cost, report = couple_edges(arrays, dataset.skeleton, params, tol, forced, beat_s)
    arrays["indptr"], arrays["indices"], arrays["costs"] = to_csr(len(ids), src, dst, cost)
    manifest["feature_blocks"] = blocks + blocks
    manifest["pc_blocks"] = list(manifest["pc_blocks"]) * 2
    manifest["params"] = asdict(params)
    manifest["couple"] = {
        "partners": [list(p) for p in pairs],
        "placement_tolerance": tol,
        "grid": "shared: both partners' step evidence",
        "reference": ref.to_dict(),
        **bar_report,
    }
    manifest["build"] = dict(
        report, seconds=round(time.perf_counter() - t0, 3), nodes=len(ids), edges=len(src)
    )
    return arrays, ids, manifest


def build_couple_graph(
    store: ObjectStore, name: str, params: BuildParams | None = None, pairs=None
) -> dict:
    """Load dataset ``name``, build its couple graph and store it as a new version of the graph
    ``couple_graph_name(name)``; returns ``{key, version, nodes, edges, build}``. Raises
    ``DanceGraphError(code="dataset_no_partners")`` for a dataset without partner takes."""
    from dancegraph.motion.dataset import load_dataset

    dataset = load_dataset(store, name)
    arrays, ids, manifest = build_couple_arrays(dataset, pairs, params)
    manifest["dataset"] = {
        "name": dataset.name,
        "version": dataset.version,
        "licence": dataset.licence,
        "acknowledgement": dataset.meta.get("acknowledgement"),
        "style_tempo_bpm": dataset.meta.get("style_tempo_bpm"),
    }
    key = artifact.write_graph(store, couple_graph_name(name), arrays, manifest, node_ids=ids)
    graph = artifact.load_graph(store.local_dir(key))
    return {"key": key, "version": graph.version, **graph.stats(), "build": manifest["build"]}


def is_couple(graph: MotionGraph) -> bool:
    """Whether ``graph`` is a couple graph (it holds the follow's motion)."""
    return "couple" in graph.manifest and all(k in graph.arrays for k in COUPLE_ARRAYS)


def follow_take(graph: MotionGraph, i: int) -> str:
    """The follow's take of couple node ``i``."""
    return str(graph.manifest["couple"]["partners"][int(graph.node_clip[i])][1])


def follow_frames(
    graph: MotionGraph, i: int, skeleton: Skeleton | None = None
) -> tuple[Motion, np.ndarray]:
    """The follow's stored motion of couple node ``i`` and the frames ``(9,)`` of its beats
    -2 .. 6 (the lead's: one grid), as ``MotionGraph.node_frames`` gives the lead's.
    ``skeleton``: the graph's, where the caller has it (``graph.skeleton`` builds it anew)."""
    row = int(graph.motion_row[i])
    a, b = int(graph.motion_ptr[row]), int(graph.motion_ptr[row + 1])
    rot = np.asarray(graph.follow_rotations[a:b], dtype=np.float64)
    rot /= np.linalg.norm(rot, axis=-1, keepdims=True)
    root = np.asarray(graph.follow_root[a:b], dtype=np.float64)
    motion = Motion(skeleton or graph.skeleton, float(graph.motion_fps[row]), root, rot)
    return motion, np.asarray(graph.motion_beats[row], dtype=np.float64)


def open_couple_graph(store: ObjectStore, name: str, version: str | None = None) -> MotionGraph:
    """Dataset ``name``'s couple graph ready to search (``artifact.open_graph`` of
    ``couple_graph_name(name)``). Raises ``NotFoundError(code="couple_graph_missing")`` when
    none was built (``unknown_graph_version`` for a version that does not exist)."""
    from dancegraph.errors import NotFoundError

    try:
        return artifact.open_graph(store, couple_graph_name(name), version)
    except NotFoundError as exc:
        if exc.code != "unknown_dataset":
            raise
        raise NotFoundError(
            f"dataset {name!r} has no couple graph; build it: dancegraph dataset build {name} "
            "--couple (its manifest must declare 'partners')",
            code="couple_graph_missing",
            field="couple",
        ) from None
