"""Couple path → two dancers: the lead and the follow of each search alternative on one clock.

For a path of couple nodes (``couple.graph``) each partner is stitched on its own
(``motion.stitch.stitch``) through the same beat-anchored time-warp (the pair's nodes share one
beat grid) and cut at the same frames (the stitch is given the other partner's pieces, so each
cut is where the two partners' seam distances summed are least), and each partner's hand-overs
are inertialized. The follow is then put where the couple's relative placement says: the
placement the nodes show (``couple.placement``: the follow's ground position and heading in
the lead's frame) jumps at a seam from the earlier node's to the later's, and that jump is
decayed to zero over the seam's blend (a quintic: no jump in value or velocity); the follow
stands at the blended placement from the lead on every frame. The couple's centre (the mid
point of the two roots, facing the lead's way) is what the search planned (the couple graph's
root paths are the centre's): it is moved onto the plan as ``render.follow_plan`` moves a solo
dancer, and both partners move with it on the ground, so their placement is kept. Then both
dancers' feet are cleaned (``contacts.clean_foot_skate``) and the first and last poses held so
frame 0 is t = 0 of the song. The re-timing of a solo render (``output.stops_on_beats``,
``output.beat_accent``) is not applied to couples: a spec that asks for it gets a warning.

Files per alternative k: ``alternatives/<k>/lead.bvh`` and ``alternatives/<k>/follow.bvh``
(same frame count, frame rate and world frame), and with ``"fbx"`` in ``output.formats``
``alternatives/<k>/lead.fbx`` and ``follow.fbx`` (Blender); both dancers in one
``alternatives/<k>/couple.glb`` (``couple.glb``; with ``"fbx"`` also ``couple.fbx``);
``timeline.json`` as for one dancer
with ``couple: true`` and both partners' takes per bar.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from dancegraph.couple.glb import write_couple_glb
from dancegraph.couple.graph import follow_frames, follow_take, is_couple
from dancegraph.couple.placement import place_follow, relative_placement, wrap
from dancegraph.errors import DanceGraphError
from dancegraph.graph.artifact import MotionGraph
from dancegraph.motion import quat
from dancegraph.motion.bvh import write_bvh
from dancegraph.motion.retime import node_warp, sample_runs, song_phase
from dancegraph.motion.skeleton import Motion
from dancegraph.motion.stitch import CUT_BEATS, _decay, _quintic, stitch, turn_on_ground
from dancegraph.render import (
    TIMELINE,
    TIMELINE_FORMAT,
    _bar_entry,
    _json_default,
    _music_bar,
    _provenance,
    bar_frames,
    check_path,
    fbx_exporter,
    follow_plan,
    ground_extent,
    hold,
    place,
    search_alternatives,
    song_summary,
    stage_violation,
    to_json_types,
)
from dancegraph.spec import Spec

#: least frames' worth (seconds) over which a seam's jump of relative placement is decayed
PLACEMENT_BLEND_S = 0.25
PARTNERS = ("lead", "follow")


def _pieces(graph: MotionGraph, nodes: list[str]) -> tuple[list, list]:
    """Both partners' stored frames and beats per bar (``node_frames``, ``follow_frames``)."""
    lead, follow = [], []
    for b, node_id in enumerate(nodes):
        if not graph.has_node(node_id):
            raise DanceGraphError(
                f"node {node_id!r} (bar {b}) is not in graph {graph.name} {graph.version}",
                code="unknown_node",
                field=f"nodes[{b}]",
            )
        i = graph.node_index(node_id)
        lead.append(graph.node_frames(i))
        follow.append(follow_frames(graph, i, lead[-1][0].skeleton))
    return lead, follow


def _source_placement(
    lead: list, follow: list, bar_beats: np.ndarray, frames: np.ndarray, fps: float, cuts
) -> tuple[np.ndarray, np.ndarray]:
    """The relative placement each output frame's node shows ``(F, 3)`` (frames
    ``[frames[0, 0], frames[-1, 1])``), and the earlier node's at the frame before each cut and
    at the cut ``(B-1, 2, 3)``."""
    phase = song_phase(bar_beats)
    bounds = np.concatenate([[frames[0, 0]], cuts, [frames[-1, 1]]]).astype(np.int64)
    runs = []
    for b, (_, beats) in enumerate(lead):
        k = np.arange(bounds[b], bounds[b + 1] + 1)  # one past: this node at the next cut
        runs.append(node_warp(beats)(phase(k / fps) - 4.0 * b))
    lr, lq = sample_runs([m for m, _ in lead], runs, [0])
    fr, fq = sample_runs([m for m, _ in follow], runs, [0])
    rel = relative_placement(lr, lq[:, 0], fr, fq[:, 0])
    ends = np.cumsum([len(r) for r in runs])
    own = np.concatenate([np.arange(e - len(r), e - 1) for r, e in zip(runs, ends, strict=True)])
    at_cut = np.stack([rel[ends[:-1] - 2], rel[ends[:-1] - 1]], axis=1)
    return rel[own], at_cut


def _blend_placement(
    rel: np.ndarray, at_cut: np.ndarray, starts: np.ndarray, seams: np.ndarray, fps: float
) -> np.ndarray:
    """``rel (F, 3)`` with each seam's offset inertialized: the earlier node's placement and
    its velocity at the cut (``at_cut (S, 2, 3)``: the frame before and at it) against the
    later node's (``rel`` at frames ``starts (S,)``, counted from frame 0 of ``rel``), decayed
    along Bollo's quintic (``stitch``'s) to zero by the next cut (at least
    ``PLACEMENT_BLEND_S``)."""
    out = rel.copy()
    for s in np.flatnonzero(seams):
        c = int(starts[s])
        if c + 1 >= len(rel):
            continue
        nxt = int(starts[s + 1]) if s + 1 < len(starts) else len(rel)
        n = min(max(int(round(PLACEMENT_BLEND_S * fps)), nxt - c), len(rel) - c)
        x0 = at_cut[s, 1] - rel[c]
        v0 = (at_cut[s, 1] - at_cut[s, 0]) - (rel[c + 1] - rel[c])
        x0[2], v0[2] = wrap(x0[2]), wrap(v0[2])
        t = np.arange(n, dtype=float)[:, None]
        out[c : c + n] += _decay(_quintic(x0, v0, np.full(3, float(n))), t)
    out[:, 2] = wrap(out[:, 2])
    return out


def _centre(lead: Motion, follow: Motion) -> Motion:
    """The couple's centre as a motion: root at the mid point of the two roots (the lead's
    height), the lead's rotations (its heading is the couple's)."""
    root = 0.5 * (lead.root_positions + follow.root_positions)
    root[:, 1] = lead.root_positions[:, 1]
    return Motion(lead.skeleton, lead.fps, root, lead.rotations)


def _move_with(dancer: Motion, before: Motion, after: Motion) -> Motion:
    """``dancer`` moved on the ground frame by frame as the centre moved from ``before`` to
    ``after`` (turned about the centre, then carried with it)."""
    turn = quat.heading_angle(after.rotations[:, 0]) - quat.heading_angle(before.rotations[:, 0])
    rot = dancer.rotations.copy()
    root, rot0 = turn_on_ground(
        dancer.root_positions[:, None],
        rot[:, None, 0],
        turn,
        before.root_positions,
        after.root_positions,
    )
    rot[:, 0] = rot0[:, 0]
    return Motion(dancer.skeleton, dancer.fps, root[:, 0], rot)


def _plan_couple(
    lead: Motion, follow: Motion, plan: np.ndarray | None, starts: np.ndarray
) -> tuple[Motion, Motion, dict | None]:
    """Both dancers moved so the couple's centre starts each bar where the search planned it
    (``plan (B, 3)``: x, z, yaw; None: the origin facing +Z); returns them and the drift."""
    centre = _centre(lead, follow)
    if plan is None:
        moved, drift = place(centre, (0.0, 0.0), 0.0), None
    else:
        moved = place(centre, (plan[0, 0], plan[0, 1]), plan[0, 2])
        moved, drift = follow_plan(moved, starts, plan)
    return _move_with(lead, centre, moved), _move_with(follow, centre, moved), drift


def _check_path(nodes: list[str], bar_beats: np.ndarray, plan) -> None:
    check_path(nodes, bar_beats)
    if plan is not None and len(plan) != len(bar_beats):
        raise DanceGraphError(
            f"{len(plan)} placements for {len(bar_beats)} bars",
            code="render_mismatch",
            field="placements",
        )


def render_couple_path(
    graph: MotionGraph,
    nodes: list[str],
    bar_beats: np.ndarray,
    fps: float,
    *,
    duration_s: float | None = None,
    placements: np.ndarray | None = None,
    foot_cleanup: bool = True,
) -> tuple[Motion, Motion, dict]:
    """The lead's and the follow's dance of one path of couple nodes (module docstring):
    ``nodes[b]`` on music bar b with beats ``bar_beats[b]`` (``(B, 5)`` s), at ``fps``.

    Returns both motions (same frame count, frame 0 = t 0 of the song, ``duration_s`` long when
    given) and a report as ``render.render_path``'s (``frames``, ``seams``, ``seam_bars``,
    ``cut_beats``, ``drift``, ``stage`` of the centre) with ``foot_skate`` per partner and
    ``placement_jump`` (the largest jump of relative placement blended at a seam: ``m``,
    ``rad``). Raises ``DanceGraphError`` (``render_mismatch``, ``render_empty``,
    ``unknown_node``)."""
    from dancegraph.motion.contacts import clean_foot_skate

    bar_beats = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    plan = None if placements is None else np.asarray(placements, dtype=float).reshape(-1, 3)
    _check_path(nodes, bar_beats, plan)
    frames = bar_frames(bar_beats[:, [0, 4]], fps)
    lead_p, follow_p = _pieces(graph, nodes)
    cut = float((graph.manifest.get("seam") or {}).get("cut_beats", CUT_BEATS))
    lead, cuts = stitch(lead_p, bar_beats, frames, fps, cut_beats=cut, partners=[follow_p])
    follow, _ = stitch(follow_p, bar_beats, frames, fps, cut_beats=cut, cut_at=cuts)
    seam = ~cuts["continuous"]
    first = int(frames[0, 0])
    rel, at_cut = _source_placement(lead_p, follow_p, bar_beats, frames, fps, cuts["cuts"])
    blended = _blend_placement(rel, at_cut, cuts["cuts"] - first, seam, fps)
    root, rot0 = place_follow(
        lead.root_positions,
        lead.rotations[:, 0],
        follow.root_positions,
        follow.rotations[:, 0],
        blended,
    )
    follow.root_positions[:] = root
    follow.rotations[:, 0] = rot0
    lead, follow, drift = _plan_couple(lead, follow, plan, frames[:, 0] - first)
    report: dict = {
        "seams": [int(s) for s in cuts["cuts"][seam]],
        "seam_bars": [int(b) + 1 for b in np.flatnonzero(seam)],
        "cut_beats": [round(float(x), 3) for x in cuts["cut_beats"][seam]],
        "drift": drift,
        "placement_jump": _jump(rel, at_cut, cuts["cuts"][seam] - first, seam),
    }
    dancers = {"lead": lead, "follow": follow}
    if foot_cleanup:
        report["foot_skate"] = {}
        for key in PARTNERS:
            dancers[key], skate = clean_foot_skate(dancers[key])
            report["foot_skate"][key] = to_json_types(skate)
    total = int(frames[-1, 1])
    if duration_s is not None:
        total = max(total, int(round(duration_s * fps)))
    for key in PARTNERS:
        dancers[key] = hold(dancers[key], first, total - int(frames[-1, 1]))
    report["frames"] = frames.tolist()
    report["stage"] = ground_extent(
        _centre(dancers["lead"], dancers["follow"]).root_positions[:, [0, 2]]
    )
    return dancers["lead"], dancers["follow"], report


def _jump(rel: np.ndarray, at_cut: np.ndarray, starts: np.ndarray, seam: np.ndarray) -> dict:
    """The largest jump of relative placement at the seams (before blending): metres, radians."""
    if not seam.any():
        return {"m": 0.0, "rad": 0.0}
    d = at_cut[seam, 1] - rel[starts]
    return {
        "m": round(float(np.linalg.norm(d[:, :2], axis=1).max()), 4),
        "rad": round(float(np.abs(wrap(d[:, 2])).max()), 4),
    }


def _write_partners(
    k: int, lead: Motion, follow: Motion, out: Path, formats: list[str], exporter
) -> dict[str, str]:
    """Alternative ``k``'s files: ``alternatives/<k>/lead.bvh|follow.bvh`` (and ``.fbx``) and
    both in ``alternatives/<k>/couple.glb`` (and with FBX ``couple.fbx``, Blender's import of
    that GLB)."""
    files: dict[str, str] = {}
    (out / "alternatives" / str(k)).mkdir(parents=True, exist_ok=True)
    for key, dance in (("lead", lead), ("follow", follow)):
        bvh = f"alternatives/{k}/{key}.bvh"
        write_bvh(dance, out / bvh)
        if "fbx" in formats:
            exporter.convert(out / bvh, out / f"alternatives/{k}/{key}.fbx", fps=dance.fps)
            files[f"{key}_fbx"] = f"alternatives/{k}/{key}.fbx"
        if "bvh" in formats:
            files[f"{key}_bvh"] = bvh
        else:
            (out / bvh).unlink()
    write_couple_glb({"lead": lead, "follow": follow}, out / f"alternatives/{k}/couple.glb")
    files["glb"] = f"alternatives/{k}/couple.glb"
    if "fbx" in formats:
        fbx = f"alternatives/{k}/couple.fbx"
        exporter.glb_to_fbx(out / files["glb"], out / fbx, fps=lead.fps, frames=lead.n_frames)
        files["fbx"] = fbx
    return files


def _couple_bar(graph: MotionGraph, alt: dict, b: int, node_id: str) -> dict:
    """``render``'s timeline entry of a bar with both partners' takes (``partners``)."""
    entry = _bar_entry(graph, alt, b, node_id)
    i = graph.node_index(node_id)
    frames = entry["source"]["frames"]
    entry["partners"] = {
        "lead": {"take": entry["source"]["take"], "frames": frames},
        "follow": {"take": follow_take(graph, i), "frames": frames},
    }
    return entry


def render_couple(
    graph: MotionGraph,
    analysis,
    result,
    spec: Spec,
    out_dir: str | Path,
    *,
    exporter=None,
    extra_provenance: dict | None = None,
    on_rig: dict | None = None,
) -> dict:
    """Write every alternative of ``result`` (the search on the couple ``graph``) into
    ``out_dir`` as two dancers (module docstring); returns ``{"files", "timeline"}`` as
    ``render.render``. ``on_rig``: per partner (``"lead"``, ``"follow"``) a hook as
    ``render.render``'s (``motion.retarget.RigOutput``), called with ``"<k>/<partner>"``: that
    dancer is also written on its rig as ``alternatives/<k>/<partner>.rig.<fmt>``. Raises
    ``DanceGraphError(code="not_a_couple_graph")`` for a solo graph, ``render_empty`` for a
    result without alternatives, ``FbxError(code="fbx_unavailable")`` for FBX without
    Blender."""
    if not is_couple(graph):
        raise DanceGraphError(
            f"graph {graph.name} is not a couple graph", code="not_a_couple_graph", field="couple"
        )
    t0 = time.perf_counter()
    out = Path(out_dir)
    found, alternatives = search_alternatives(result)
    fps = float(spec.output.fps)
    formats = [str(f) for f in spec.output.formats]
    exporter = fbx_exporter(formats, exporter)
    entries: list[dict] = []
    files: list[str] = []
    for k, alt in enumerate(alternatives):
        lead, follow, report = render_couple_path(
            graph,
            list(alt["nodes"]),
            analysis.bar_beats,
            fps,
            duration_s=float(analysis.duration_s),
            placements=alt.get("placements"),
            foot_cleanup=spec.output.foot_cleanup,
        )
        report["stage"]["outside_m"] = stage_violation(
            _centre(lead, follow).root_positions[:, [0, 2]], spec.stage
        )
        entry_files = _write_partners(k, lead, follow, out, formats, exporter)
        for key, hook in (on_rig or {}).items():
            rig_files, report.setdefault("rig", {})[key] = hook(
                f"{k}/{key}", {"lead": lead, "follow": follow}[key], out
            )
            entry_files.update({f"{key}_{name}": rel for name, rel in rig_files.items()})
        files.extend(entry_files.values())
        entries.append(_couple_entry(graph, k, alt, report, entry_files, lead.n_frames))
    timeline = _couple_timeline(graph, analysis, spec, found, entries, extra_provenance)
    timeline["render_seconds"] = round(time.perf_counter() - t0, 3)
    (out / TIMELINE).write_text(json.dumps(timeline, indent=1, default=_json_default))
    return {"files": [*files, TIMELINE], "timeline": timeline}


def _couple_entry(
    graph: MotionGraph, k: int, alt: dict, report: dict, files: dict, n_frames: int
) -> dict:
    skip = {"nodes", "index", "per_bar", "cost", "violations", "placements"}
    return {
        "index": k,
        "files": files,
        "cost": to_json_types(alt.get("cost")),
        "violations": to_json_types(alt.get("violations", [])),
        "frames": n_frames,
        "bars": [_couple_bar(graph, alt, b, n) for b, n in enumerate(alt["nodes"])],
        **{key: to_json_types(v) for key, v in report.items() if key != "frames"},
        **{key: to_json_types(v) for key, v in alt.items() if key not in skip},
    }


def _couple_timeline(graph, analysis, spec, found, entries, extra) -> dict:
    bars = np.asarray(analysis.bars, dtype=float).reshape(-1, 2)
    frames = bar_frames(bars, float(spec.output.fps))
    warnings = []
    if spec.output.stops_on_beats or spec.output.beat_accent > 0.0:
        warnings.append(
            "output.stops_on_beats and output.beat_accent are not applied to couple dances"
        )
    return {
        "format": TIMELINE_FORMAT,
        "couple": True,
        "partners": list(PARTNERS),
        "fps": float(spec.output.fps),
        "duration_s": float(analysis.duration_s),
        "frames": max(e["frames"] for e in entries),
        "song": song_summary(analysis),
        "warnings": warnings,
        "bars": [_music_bar(analysis, frames, b) for b in range(len(bars))],
        "phrases": to_json_types(list(analysis.phrases)),
        "alternatives": entries,
        "constraints": to_json_types(found.get("constraints", {})),
        "provenance": _provenance(graph, spec, analysis, extra),
    }


def synthesize_couple(
    audio,
    graph: MotionGraph,
    spec: Spec,
    out_dir: str | Path,
    *,
    analysis=None,
    exporter=None,
    on_rig: dict | None = None,
) -> dict:
    """Song → couple dance files: analysis (unless given) → the search on the couple ``graph``
    (``graph.search.search``, the solo search on the couple's arrays) → ``render_couple``.
    ``audio``: a path (or samples, then pass ``analysis``); ``on_rig``: see ``render_couple``. Returns ``render_couple``'s dict plus
    ``analysis`` (the summary) and ``search``."""
    from dancegraph.embed.learned import add_music_terms
    from dancegraph.graph.search import search
    from dancegraph.music.analysis import analyze
    from dancegraph.render import _audio_provenance, style_tempo_range

    if analysis is None:
        analysis = analyze(audio, tempo_range=style_tempo_range(spec, graph))
    if isinstance(audio, str | Path):
        analysis = add_music_terms(analysis, graph, audio)
    found = search(graph, analysis, spec)
    source = {"audio": _audio_provenance(Path(audio))} if isinstance(audio, str | Path) else None
    rendered = render_couple(
        graph,
        analysis,
        found,
        spec,
        out_dir,
        exporter=exporter,
        extra_provenance=source,
        on_rig=on_rig,
    )
    return {**rendered, "analysis": analysis.summary(), "search": found.to_dict()}
