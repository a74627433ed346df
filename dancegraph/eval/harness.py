"""Evaluation harness: ChoreoMaster's Table 3 on our own graph, songs and metrics.

For every song the harness dances the rows below and scores each dance with ``dancegraph.metrics``
(every dance rendered and measured at 60 fps, the rate the published beat scores assume):

- ``real``: the library's own dances (ground truth): takes from the start, cut to the song's
  length, scored against the take's own beats where the dataset has annotated ones, else against
  the song's;
- ``random_walk``: a beat-synchronous random walk on the graph (a uniformly random out-edge per
  music bar, from a random original bar);
- ``clip_concat``: tempo-matched clip concatenation: runs of 8 consecutive original bars of random
  takes, each bar time-warped onto its music bar;
- ``ours``: the graph search with the spec;
- ``no_style`` / ``no_rhythm`` / ``no_structure``: the search without the style term, without
  the rhythm term, without the repeat/mirror constraints.

Each row dances ``spec.alternatives`` dances per song (takes, seeds or search alternatives).
``metrics.json`` holds every dance's numbers, per-song means and the per-row aggregate (means
over songs and alternatives, FID_k against the library, diversity), and ``sync``: per row every
sync metric (``metrics.beats``) beside its chance rows — the same dances against the song's
beats shifted by half a beat, and against the next song's beats — with the gain over each;
``report.html`` is self-contained (inline PNG plots) with the tables and, per song, the plots
of our dance.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dancegraph.errors import DanceGraphError
from dancegraph.eval import ROWS
from dancegraph.graph.artifact import MotionGraph
from dancegraph.metrics import beats as mbeats
from dancegraph.metrics import diversity, kinetic, naturalness, physical, smoothness, structure
from dancegraph.motion.features import joint_speed, kinematic_beats
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.retime import resample
from dancegraph.motion.skeleton import Motion
from dancegraph.render import style_tempo_range, to_json_types
from dancegraph.rhythm.signatures import COMMON_SIGNATURES
from dancegraph.spec import Spec

if TYPE_CHECKING:
    from dancegraph.motion.dataset import Dataset
    from dancegraph.music.analysis import MusicAnalysis

ROW_TITLES = {
    "real": "Real library dances (ground truth)",
    "random_walk": "Beat-synchronous random walk",
    "clip_concat": "Tempo-matched clip concatenation",
    "ours": "Ours (graph search)",
    "no_style": "Ours without style term",
    "no_rhythm": "Ours without rhythm term",
    "no_structure": "Ours without structure constraints",
    "result": "Scored result",
}
EVAL_FPS = 60.0
FID_WINDOW_S = 5.0  # FID_k samples: non-overlapping windows of this length
CONCAT_RUN_BARS = 8  # bars per clip in the clip-concatenation baseline
#: Takes drawn as the "dances" of the two-sample test's library-against-library chance row (as
#: many as a song's default alternatives).
CLASSIFIER_FILES = 3
#: Scalar metrics of one dance, in table order, with their column titles.
SCALARS: dict[str, str] = {
    "cm_accuracy": "CM beat acc.",
    "beat_accuracy": "Beat acc. (all beats)",
    "bas_bailando": "BAS (Bailando)",
    "bas_fact": "BAS (FACT)",
    "bas_beats": "BAS (tracker's beats)",
    "phase_r": "Phase R",
    "seam_flagged_share": "Seams > p99",
    "seam_median_percentile": "Seam pct. (median)",
    "seam_skate_m_s": "Skate at seams m/s",
    "skate_speed_m_s": "Skate m/s",
    "repeat_share": "Repeat ok",
    "mirror_share": "Mirror ok",
    "controls_share": "Controls ok",
    "signature_chi2": "Signature χ²",
    "stage_inside_share": "On stage",
    "pulse_depth": "Pulse depth",
    "speed_factor_min": "Speed factor min",
    "speed_factor_max": "Speed factor max",
    "grid_passed": "Grid check ok",
    "grid_passed_other": "Grid check ok (other song)",
}
AGGREGATES: dict[str, str] = {
    "fid_k": "FID_k",
    "classifier": "Classifier bal. acc.",
    "classifier_cleaned": "Classifier vs cleaned takes",
    "div_alternatives": "Div. alts",
    "div_paths": "Bars differ (alts)",
    "div_songs": "Div. songs",
}


class EvalError(DanceGraphError):
    """An evaluation that cannot run (codes eval_*)."""

    code = "eval_failed"


# --------------------------------------------------------------------------------------------
# the library: reference distributions


@dataclass
class Library:
    """The graph plus what the metrics compare against, from the dataset's real takes at 60 fps:
    the frame-to-frame reference of seam smoothness and the kinetic features of FID_k."""

    graph: MotionGraph
    dataset: Dataset | None
    seams: smoothness.Reference | None
    kinetic_windows: np.ndarray | None  # (N, 72) raw features of the takes' windows
    norm: tuple[np.ndarray, np.ndarray] | None
    contact_skate: dict | None = None  # the takes' own foot sliding at contacts (``seam_metrics``)
    pulse: dict | None = None  # the steady takes' pulse on their own grids (``naturalness``)
    descriptors: list[np.ndarray] = field(default_factory=list)  # per take: its 2-s windows
    #: per take: the same with the renderer's foot cleanup (``contacts.clean_foot_skate``)
    descriptors_cleaned: list[np.ndarray] = field(default_factory=list)
    classifier_chance: float | None = None  # the two-sample test, library against library
    classifier_chance_cleaned: float | None = None  # ... the cleaned takes against themselves
    _takes: dict = field(default_factory=dict, repr=False)

    def take(self, clip: str) -> Motion:
        """A take at 60 fps (cached)."""
        if clip not in self._takes:
            assert self.dataset is not None, "a library without its dataset has no takes"
            self._takes[clip] = resample(self.dataset.motion(clip), EVAL_FPS)
        return self._takes[clip]


def load_library(graph: MotionGraph, dataset=None) -> Library:
    """Reference distributions from ``dataset``'s takes (a ``motion.dataset.Dataset``); without a
    dataset, seam smoothness and FID_k are not measured."""
    if dataset is None:
        return Library(graph, None, None, None, None)
    lib = Library(graph, dataset, None, None, None)
    positions, windows, skates, pulses = [], [], [], []
    for clip in dataset.clips:
        motion = lib.take(clip.id)
        pos, world = forward_kinematics(motion)
        positions.append(pos)
        smpl = kinetic.smpl_positions(motion.skeleton, pos, world)
        windows.append(kinetic.window_features(smpl, EVAL_FPS, FID_WINDOW_S))
        lib.descriptors.append(naturalness.window_descriptors(smpl, EVAL_FPS))
        lib.descriptors_cleaned.append(_cleaned_descriptors(motion))
        skates.append(physical.foot_skating(pos, world, motion.skeleton, EVAL_FPS))
        if "no_steady_beat" not in clip.flags:
            bars = np.array([b.beat_times for b in dataset.bars if b.clip_id == clip.id])
            pulses.append((joint_speed(pos, EVAL_FPS, 0.0), EVAL_FPS, bars.reshape(-1, 5)))
    lib.pulse = naturalness.library_pulse(pulses)
    lib.classifier_chance = naturalness.library_chance(lib.descriptors, CLASSIFIER_FILES)
    lib.classifier_chance_cleaned = naturalness.library_chance(
        lib.descriptors_cleaned, CLASSIFIER_FILES
    )
    lib.seams = smoothness.Reference.from_takes(positions, EVAL_FPS)
    lib.contact_skate = _pooled_skate(skates)
    lib.kinetic_windows = np.concatenate(windows)
    lib.norm = kinetic.normaliser(lib.kinetic_windows)
    return lib


def _cleaned_descriptors(take: Motion) -> np.ndarray:
    """The two-sample test's windows of a take with the renderer's foot cleanup: the reference
    that tells the synthesis from the cleanup (the library's raw takes slide, a render does not)."""
    from dancegraph.motion.contacts import clean_foot_skate

    cleaned, _ = clean_foot_skate(take)
    pos, world = forward_kinematics(cleaned)
    smpl = kinetic.smpl_positions(cleaned.skeleton, pos, world)
    return naturalness.window_descriptors(smpl, EVAL_FPS)


# --------------------------------------------------------------------------------------------
# one dance


@dataclass
class Song:
    """A song to dance: its analysis and the music side of the sync metrics (``grid``)."""

    name: str
    analysis: MusicAnalysis
    grid: mbeats.SyncGrid

    @property
    def beats(self) -> np.ndarray:
        """The tracker's beats (s)."""
        return self.grid.beats


def sync_grid(
    bar_beats: np.ndarray, signatures: np.ndarray, percussive: np.ndarray
) -> mbeats.SyncGrid:
    """The ``SyncGrid`` of a song's 4-beat bars ``bar_beats (B, 5)`` s, their rhythm signatures
    ``(B,)`` (indices into ``COMMON_SIGNATURES``) and librosa's percussive beats ``(M,)`` s:
    the bars' beats, the active slots of their signatures, and the bars' span."""
    from dancegraph.rhythm.music import rhythm_points

    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    beats = np.unique(bb.ravel()) if len(bb) else np.zeros(0)
    return mbeats.SyncGrid(
        beats=beats,
        percussive_beats=np.asarray(percussive, dtype=float),
        rhythm_points=rhythm_points(bb, signatures),
        span=(float(bb[0, 0]), float(bb[-1, 4])) if len(bb) else (0.0, 0.0),
    )


@dataclass
class Dance:
    """One scored dance: the flat ``metrics`` and what the report and aggregates need."""

    metrics: dict
    windows: np.ndarray  # (W, 72) kinetic features of its windows
    features: np.ndarray  # (72,) kinetic features of the whole dance
    nodes: np.ndarray | None
    plot: dict
    #: (W', 37) the two-sample test's 2-s windows (``naturalness.window_descriptors``)
    descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 37)))


def score_dance(
    lib: Library,
    motion: Motion,
    spec: Spec,
    *,
    span: tuple[float, float],
    grid: mbeats.SyncGrid,
    other: mbeats.SyncGrid | None = None,
    bars: np.ndarray | None = None,
    nodes: np.ndarray | None = None,
    tags: list[dict] | None = None,
    seams=None,
    bar_beats: np.ndarray | None = None,
    other_bar_beats: np.ndarray | None = None,
    seed: list[int] | None = None,
) -> Dance:
    """Every metric of one dance ``motion`` (60 fps, frame 0 = t 0 of the song).

    ``span`` (s): where the dance moves (beats outside it are not counted); ``grid``: the music
    the dance is scored against, ``other``: another song's (a chance row; none: not measured).
    ``bars (T, 2)``, ``nodes (T,)`` and ``tags``: the path on the music bars, when there is
    one (structure, controls); ``seams``: frames where bars meet. ``bar_beats (T, 5)``: the
    song's bars the dance was laid on (the pulse depth and the recovered-grid check,
    ``naturalness_metrics``); ``other_bar_beats``: another song's, the check's chance row (at a
    phase drawn from ``seed``).
    """
    if abs(motion.fps - EVAL_FPS) > 1e-6:
        raise ValueError(f"score_dance needs {EVAL_FPS} fps, got {motion.fps}")
    fps = motion.fps
    pos, world = forward_kinematics(motion)
    a, b = span
    smpl_all = kinetic.smpl_positions(motion.skeleton, pos, world)
    kin = kinematic_beats(pos, fps)
    m: dict = sync_metrics(mbeats.DanceBeats.of(smpl_all, fps, kin), span, grid, other)
    seam_rows = None
    if seams is not None and lib.seams is not None:
        seam_m, seam_rows = seam_metrics(lib, pos, world, motion.skeleton, seams, bars)
        m.update(seam_m)
    skate = physical.foot_skating(pos, world, motion.skeleton, fps)
    m["skate_speed_m_s"] = skate["mean_speed_m_s"]
    m["foot_skating"] = skate
    root_xz = motion.root_positions[:, [0, 2]]
    stage = physical.stage_report(root_xz, spec.stage)
    if stage is not None:
        m["stage_inside_share"] = stage["inside_share"]
        m["stage"] = stage
    if nodes is not None:
        target = spec.signature.target if spec.signature is not None else "dataset"
        sig = structure.signature_distance(lib.graph, nodes, target)
        m["signature_chi2"] = sig["chi2"]
    if nodes is not None and bars is not None and tags is not None and len(tags) == len(nodes):
        st = structure.structure_satisfaction(nodes, tags, lib.graph.mirror_of)
        m["repeat_share"] = st["repeat"]["share"]
        m["mirror_share"] = st["mirror"]["share"]
        m["structure"] = st
        ctl = structure.control_satisfaction(lib.graph, spec, bars, nodes, root_xz, fps)
        m["controls_share"] = ctl["share"]
        m["controls"] = ctl
    if bar_beats is not None:
        m.update(naturalness_metrics(motion.skeleton, pos, world, bar_beats, other_bar_beats, seed))
    lo, hi = int(round(a * fps)), max(int(round(b * fps)), int(round(a * fps)) + 3)
    smpl = smpl_all[lo:hi]
    plot = {
        "kinematic_beats": kin,
        "speed": joint_speed(pos, fps, 0.03),
        "fps": fps,
        "signature": sig if nodes is not None else None,
        "node_ids": lib.graph.node_ids if nodes is not None else None,
        "seams": seam_rows,
    }
    return Dance(
        metrics=m,
        windows=kinetic.window_features(smpl, fps, FID_WINDOW_S),
        descriptors=naturalness.window_descriptors(smpl, fps),
        features=kinetic.kinetic_features(smpl, fps),
        nodes=None if nodes is None else np.asarray(nodes),
        plot=plot,
    )


def sync_metrics(
    dance: mbeats.DanceBeats,
    span: tuple[float, float],
    grid: mbeats.SyncGrid,
    other: mbeats.SyncGrid | None,
) -> dict:
    """The sync metrics of one dance (``mbeats.SYNC_METRICS``) against ``grid``, each with its
    chance rows: ``<name>_half`` against the grid shifted by half a beat (None for ``phase_r``,
    which a constant shift leaves as it is) and ``<name>_other`` against ``other`` (None without
    one); plus ``phase``, the motion beats' mean beat phase."""
    own = mbeats.sync_scores(dance, grid, span)
    half = mbeats.sync_scores(dance, grid.half_beat(), span)
    far = mbeats.sync_scores(dance, other, span) if other is not None else {}
    out: dict = {"phase": own["phase"]}
    for key in mbeats.SYNC_METRICS:
        out[key] = own[key]
        out[f"{key}_half"] = None if key == "phase_r" else half[key]
        out[f"{key}_other"] = far.get(key)
    return out


def naturalness_metrics(
    skeleton,
    pos: np.ndarray,
    world: np.ndarray,
    bar_beats: np.ndarray,
    other=None,
    seed: list[int] | None = None,
) -> dict:
    """The pulse depth of a dance (world ``pos``/``world`` at ``EVAL_FPS``, frame 0 = t 0) on
    the song's beat phase (``bar_beats (B, 5)`` s) and the recovered-grid check
    (``naturalness.recovered_grid``, ``grid_check``): ``pulse_depth``, ``pulse_profile``,
    ``recovered_grid`` (the check's numbers), ``grid_passed``, and with ``other`` (another
    song's bars, scaled to this song's tempo at a phase drawn from ``seed``:
    ``naturalness.scaled_grid``) its chance row
    ``grid_passed_other`` and ``recovered_grid_other``."""
    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    profile = naturalness.pulse_profile(joint_speed(pos, EVAL_FPS, 0.0), EVAL_FPS, bb)
    out: dict = {
        "pulse_depth": naturalness.pulse_depth(profile),
        "pulse_profile": [round(float(x), 4) for x in profile],
    }
    span = (float(bb[0, 0]), float(bb[-1, 4]))
    tempo = 60.0 / naturalness.beat_period(bb)
    try:
        grid = naturalness.recovered_grid(skeleton, pos, world, EVAL_FPS, span, tempo)
    except ValueError:  # a dance under 2 s has no grid to recover
        return out
    out["recovered_grid"] = naturalness.grid_check(grid, bb)
    out["grid_passed"] = float(out["recovered_grid"]["passed"])
    if other is not None:
        chance = naturalness.grid_check(grid, naturalness.scaled_grid(other, bb, seed or 0))
        out["recovered_grid_other"] = chance
        out["grid_passed_other"] = float(chance["passed"])
    return out


# --------------------------------------------------------------------------------------------
# seams

#: Seconds either side of a seam in which foot sliding is measured.
SEAM_SKATE_S = 0.2


def _pooled_skate(parts: list[dict]) -> dict:
    """``physical.foot_skating`` results pooled over dances (weighted by their counted steps)."""
    steps = sum(p["steps"] for p in parts)
    mean = sum(p["mean_speed_m_s"] * p["steps"] for p in parts) / steps if steps else 0.0
    share = sum(p["skating_share"] * p["steps"] for p in parts) / steps if steps else 0.0
    return {"mean_speed_m_s": float(mean), "skating_share": float(share), "steps": int(steps)}


def seam_metrics(
    lib: Library, pos: np.ndarray, world: np.ndarray, skeleton, seams, bars: np.ndarray | None
) -> tuple[dict, list[dict]]:
    """The seam section of one dance (``pos``, ``world``: its forward kinematics at 60 fps).

    ``seams``: frames where a node takes over (``render_path``'s ``seams``: not where a take
    continues into its own next bar); ``bars (T, 2)`` s. Returns the metrics: the share of
    seams above the library's p99 and the median seam percentile (``smoothness.seam_report``),
    foot sliding of planted feet within ±``SEAM_SKATE_S`` of the seams beside the library's own
    sliding at contacts (``seam_skate_m_s``; ``seams.skate`` / ``seams.library_skate``), the
    worst seam with the bar it starts (the nearest bar line), the same scores at every bar line
    (``seams.bar_lines``, a take continuing included) and the library's chance row (every frame
    of its takes scored as a seam); and the per-seam rows (for the report's timeline).
    """
    assert lib.seams is not None  # score_dance calls this only with the library's reference
    fps = EVAL_FPS
    rep = smoothness.seam_report(pos, fps, seams, lib.seams)
    rows = rep["seams"]
    lines = (
        np.round(np.asarray(bars, dtype=float)[:, 0] * fps).astype(np.int64)
        if bars is not None and len(bars)
        else np.zeros(0, dtype=np.int64)
    )
    for r in rows:
        r["percentile"] = max(r["speed_percentile"], r["acc_percentile"])
        r["bar"] = int(np.argmin(np.abs(lines - r["frame"]))) if lines.size else None
    near = np.zeros(len(pos), dtype=bool)
    w = int(round(SEAM_SKATE_S * fps))
    for r in rows:
        near[max(0, r["frame"] - w) : r["frame"] + w + 1] = True
    skate = physical.foot_skating(pos, world, skeleton, fps, frames=near)
    summary = {k: v for k, v in rep.items() if k != "seams"}
    summary["flagged_frames"] = [r["frame"] for r in rows if r["flagged"]]
    summary["worst"] = (
        {
            k: max(rows, key=lambda r: r["percentile"])[k]
            for k in ("frame", "bar", "percentile", "speed_m_s", "acc_m_s2")
        }
        if rows
        else None
    )
    summary["skate"] = skate
    summary["library_skate"] = lib.contact_skate
    if lines.size > 1:
        at_lines = smoothness.seam_report(pos, fps, lines[1:], lib.seams)
        summary["bar_lines"] = {
            k: at_lines[k] for k in ("count", "flagged", "flagged_share", "median_percentile")
        }
    summary["chance"] = lib.seams.chance
    metrics = {
        "seam_flagged_share": rep["flagged_share"],
        "seam_median_percentile": rep["median_percentile"],
        "seam_skate_m_s": skate["mean_speed_m_s"] if skate["steps"] else None,
        "seams": summary,
    }
    return metrics, rows


# --------------------------------------------------------------------------------------------
# the rows


def row_spec(spec: Spec, row: str) -> Spec:
    """The spec a search row runs with (ablations switch one term off)."""
    data = spec.model_dump()
    if row == "no_style":
        data["weights"]["style"] = 0.0
    elif row == "no_rhythm":
        data["weights"]["rhythm"] = 0.0
    elif row == "no_structure":
        data["structure"] = {"repeat": False, "mirror": False}
    return Spec.model_validate(data)


def _originals(graph: MotionGraph) -> dict[tuple[int, int], int]:
    """(clip index, bar) → node index of every original bar."""
    kind = np.asarray(graph.node_kind)
    clip, bar = np.asarray(graph.node_clip), np.asarray(graph.node_bar)
    return {(int(clip[i]), int(bar[i])): int(i) for i in np.nonzero(kind == 0)[0]}


def random_walk(graph: MotionGraph, n_bars: int, rng: np.random.Generator) -> np.ndarray:
    """``(n_bars,)`` nodes: a random original bar, then a uniformly random out-edge per bar (a
    random original bar again where a node has none)."""
    originals = np.nonzero(np.asarray(graph.node_kind) == 0)[0]
    path = [int(rng.choice(originals))]
    while len(path) < n_bars:
        targets, _ = graph.out_edges(path[-1])
        path.append(int(rng.choice(targets)) if len(targets) else int(rng.choice(originals)))
    return np.asarray(path, dtype=np.int64)


def clip_concatenation(graph: MotionGraph, n_bars: int, rng: np.random.Generator) -> np.ndarray:
    """``(n_bars,)`` nodes: runs of ``CONCAT_RUN_BARS`` consecutive original bars of random takes
    (shorter where a take ends)."""
    table = _originals(graph)
    by_clip: dict[int, list[int]] = {}
    for c, b in table:
        by_clip.setdefault(c, []).append(b)
    clips = sorted(by_clip)
    path: list[int] = []
    while len(path) < n_bars:
        c = clips[int(rng.integers(len(clips)))]
        bars = sorted(by_clip[c])
        start = int(rng.integers(len(bars)))
        for b in bars[start : start + CONCAT_RUN_BARS]:
            if (c, b) not in table or len(path) >= n_bars:
                break
            path.append(table[(c, b)])
    return np.asarray(path, dtype=np.int64)


def _search_paths(graph: MotionGraph, analysis, spec: Spec) -> list[dict]:
    from dancegraph.graph.search import search

    found = search(graph, analysis, spec)
    return [
        {"nodes": np.asarray(a.index), "placements": a.placements, "per_bar": a.per_bar}
        for a in found.alternatives
    ]


def _render(lib: Library, song: Song, nodes: np.ndarray, placements, spec: Spec):
    from dancegraph.render import render_path

    analysis = song.analysis
    ids = [lib.graph.node_ids[int(n)] for n in nodes]
    return render_path(
        lib.graph,
        ids,
        analysis.bar_beats,
        EVAL_FPS,
        duration_s=float(analysis.duration_s),
        placements=placements,
        foot_cleanup=spec.output.foot_cleanup,
        land_stops=spec.output.stops_on_beats,
        beat_accent=spec.output.beat_accent,
    )


def _real_dances(
    lib: Library, song: Song, spec: Spec, song_no: int, other: mbeats.SyncGrid | None
) -> list[Dance]:
    if lib.dataset is None:
        return []
    clips = sorted(lib.dataset.clips, key=lambda c: c.id)
    graph = lib.graph
    out = []
    n = spec.alternatives
    for k in range(n):
        clip = clips[(song_no * n + k) % len(clips)]
        take = lib.take(clip.id)
        cut = min(take.n_frames, int(round(song.analysis.duration_s * EVAL_FPS)))
        motion = take.slice(0, cut)
        # the take's original bars that start inside the cut, for its motif signature
        bars = [b for b in lib.dataset.bars if b.clip_id == clip.id and b.start_s < cut / EVAL_FPS]
        grid = song.grid
        if clip.beat_source == "annotation" and bars:
            # the take's own music: its annotated beats (for the BAS too) and signatures
            grid = sync_grid(
                np.array([b.beat_times for b in bars]),
                np.array([COMMON_SIGNATURES.index(b.signature) for b in bars]),
                lib.dataset.beats(clip.id),
            )
        nodes = np.array(
            [graph.node_index(b.node_id) for b in bars if graph.has_node(b.node_id)],
            dtype=np.int64,
        )
        d = score_dance(
            lib,
            motion,
            spec,
            span=(0.0, cut / EVAL_FPS),
            grid=grid,
            other=other,
            nodes=nodes if nodes.size else None,
        )
        d.metrics["take"] = clip.id
        out.append(d)
    return out


def _row_dances(
    lib: Library, song: Song, spec: Spec, row: str, song_no: int, other: Song | None
) -> list[Dance]:
    analysis = song.analysis
    n_bars = len(analysis.bars)
    if row == "real":
        return _real_dances(lib, song, spec, song_no, other.grid if other else None)
    if row in ("random_walk", "clip_concat"):
        make = random_walk if row == "random_walk" else clip_concatenation
        paths: list[dict[str, Any]] = []
        for k in range(spec.alternatives):
            rng = np.random.default_rng([spec.seed, song_no, k, ROWS.index(row)])
            paths.append({"nodes": make(lib.graph, n_bars, rng), "placements": None})
    else:
        paths = _search_paths(lib.graph, analysis, row_spec(spec, row))
    span = (float(analysis.bars[0][0]), float(analysis.bars[-1][1]))
    out = []
    for k, p in enumerate(paths):
        motion, report = _render(lib, song, p["nodes"], p["placements"], spec)
        d = score_dance(
            lib,
            motion,
            spec,
            span=span,
            grid=song.grid,
            other=other.grid if other else None,
            bars=np.asarray(analysis.bars),
            nodes=p["nodes"],
            tags=list(analysis.tags),
            seams=report["seams"],
            bar_beats=analysis.bar_beats,
            other_bar_beats=other.analysis.bar_beats if other else None,
            seed=[song_no, k],
        )
        d.metrics["retime"] = report["retime"]
        d.metrics["speed_factor_min"], d.metrics["speed_factor_max"] = report["retime"][
            "speed_factor"
        ]
        d.plot["per_bar"] = p.get("per_bar")
        out.append(d)
    return out


# --------------------------------------------------------------------------------------------
# aggregation


def _mean(values) -> float | None:
    vals = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return float(np.mean(vals)) if vals else None


def _norm(lib: Library, f: np.ndarray) -> np.ndarray:
    if lib.norm is None:
        return f
    mu, sd = lib.norm
    return (f - mu) / sd


def aggregate(lib: Library, per_song: list[dict[str, list[Dance]]], rows: list[str]) -> dict:
    """Per row: the mean of every scalar over songs and alternatives, FID_k of the row's windows
    against the library's, feature and path diversity among alternatives (mean over songs) and
    feature diversity across songs (first dance of each song)."""
    table = {}
    for row in rows:
        dances = [d for song in per_song for d in song.get(row, [])]
        entry: dict = {"dances": len(dances)}
        for key in SCALARS:
            entry[key] = _mean(d.metrics.get(key) for d in dances)
        windows = [d.windows for d in dances if len(d.windows)]
        entry["fid_k"] = None
        if lib.kinetic_windows is not None and windows:
            gen = np.concatenate(windows)
            if len(gen) >= 2:
                entry["fid_k"] = kinetic.frechet_distance(
                    _norm(lib, gen), _norm(lib, lib.kinetic_windows)
                )
        entry["div_alternatives"] = _mean(
            diversity.feature_diversity(np.stack([_norm(lib, d.features) for d in song[row]]))
            for song in per_song
            if len(song.get(row, [])) > 1
        )
        entry["div_paths"] = _mean(
            diversity.path_diversity([d.nodes for d in song[row] if d.nodes is not None])
            for song in per_song
            if row not in ("real",) and len(song.get(row, [])) > 1
        )
        firsts = [_norm(lib, song[row][0].features) for song in per_song if song.get(row)]
        entry["div_songs"] = diversity.feature_diversity(np.stack(firsts)) if firsts else None
        entry["classifier"] = _mean(classifier_scores(lib, per_song, [row])[row])
        entry["classifier_cleaned"] = _mean(
            classifier_scores(lib, per_song, [row], cleaned=True)[row]
        )
        table[row] = entry
    return table


def classifier_scores(
    lib: Library, per_song: list[dict[str, list[Dance]]], rows: list[str], cleaned: bool = False
) -> dict[str, list[float | None]]:
    """Per row, per song: the two-sample test (``naturalness.two_sample_accuracy``) of the
    song's dances of that row against the library's takes (``cleaned``: the takes with the
    renderer's foot cleanup); None without the takes, with fewer than two dances, or without
    scikit-learn."""
    reference = lib.descriptors_cleaned if cleaned else lib.descriptors
    return {
        row: [
            naturalness.two_sample_accuracy([d.descriptors for d in song.get(row, [])], reference)
            if reference
            else None
            for song in per_song
        ]
        for row in rows
    }


def library_summary(lib: Library) -> dict:
    """The library's own numbers the naturalness rows stand beside: its steady takes' pulse on
    their own grids (``naturalness.library_pulse``) and the two-sample test's chance row."""
    return to_json_types(
        {
            "pulse": lib.pulse,
            "classifier_chance": lib.classifier_chance,
            "classifier_chance_cleaned": lib.classifier_chance_cleaned,
        }
    )


def sync_table(per_song: list[dict[str, list[Dance]]], rows: list[str]) -> dict:
    """Per row and sync metric (``mbeats.SYNC_METRICS``): ``value`` (mean over songs and
    alternatives), ``half_beat`` and ``other_song`` (the chance rows' means) and, per chance row,
    ``gain_*`` (mean of value − chance over the dances that have it) and ``ratio_*`` (their
    mean value / mean chance); None where a chance row was not measured."""
    table: dict = {}
    for row in rows:
        dances = [d.metrics for song in per_song for d in song.get(row, [])]
        entry: dict = {}
        for key in mbeats.SYNC_METRICS:
            cell: dict = {"value": _mean(m.get(key) for m in dances)}
            for chance in ("half_beat", "other_song"):
                suffix = "_half" if chance == "half_beat" else "_other"
                pairs = [
                    (m[key], m[key + suffix])
                    for m in dances
                    if m.get(key) is not None and m.get(key + suffix) is not None
                ]
                value = _mean(v for v, _ in pairs)
                base = _mean(c for _, c in pairs)
                cell[chance] = base
                cell[f"gain_{chance}"] = _mean(v - c for v, c in pairs)
                cell[f"ratio_{chance}"] = (
                    value / base if pairs and value is not None and base else None
                )
            entry[key] = cell
        table[row] = entry
    return table


# --------------------------------------------------------------------------------------------
# entry points


def load_song(
    path: str | Path,
    analysis=None,
    graph: MotionGraph | None = None,
    spec: Spec | None = None,
) -> Song:
    """Analyse a song (unless ``analysis`` is given) and find librosa's percussive beats; count
    the octave of the style tempo range of ``spec`` and ``graph`` as ``synthesize`` does
    (``render.style_tempo_range``); with ``graph``, add its learned models' music terms
    (``embed.learned.add_music_terms``)."""
    from dancegraph.embed.learned import add_music_terms
    from dancegraph.music.analysis import analyze
    from dancegraph.music.decode import load_audio

    if analysis is None:
        params = spec.analysis_params() if spec is not None else None
        analysis = analyze(path, tempo_range=style_tempo_range(spec, graph), params=params)
    if graph is not None:
        analysis = add_music_terms(analysis, graph, path)
    y, sr = load_audio(path, sr=22050)
    grid = sync_grid(
        analysis.bar_beats,
        np.asarray(analysis.signature_topk, dtype=int).reshape(len(analysis.bars), -1)[:, 0],
        mbeats.librosa_beats(y, sr),
    )
    return Song(name=Path(path).name, analysis=analysis, grid=grid)


def evaluate(
    songs: list[Song],
    lib: Library,
    spec: Spec,
    out_dir: str | Path,
    rows: list[str] | None = None,
    progress=None,
) -> dict:
    """Run ``rows`` (default all of ``ROWS``) on every song; write ``metrics.json`` and
    ``report.html`` into ``out_dir``; return the metrics dict."""
    t0 = time.perf_counter()
    rows = list(rows or ROWS)
    unknown = [r for r in rows if r not in ROWS]
    if unknown:
        raise EvalError(
            f"unknown rows {', '.join(unknown)} (known: {', '.join(ROWS)})",
            code="eval_unknown_row",
            field="rows",
        )
    if not songs:
        raise EvalError("no songs to evaluate", code="eval_no_songs", field="audio")
    if "real" in rows and lib.dataset is None:
        raise EvalError(
            "the real-dance row needs the dataset's takes", code="eval_no_dataset", field="rows"
        )
    per_song: list[dict[str, list[Dance]]] = []
    songs_out: list[dict[str, Any]] = []
    for s, song in enumerate(songs):
        dances: dict[str, list[Dance]] = {}
        # the other-song chance row: the same dances against the next song's music
        other = songs[(s + 1) % len(songs)] if len(songs) > 1 else None
        for row in rows:
            if progress:
                progress(song.name, row)
            dances[row] = _row_dances(lib, song, spec, row, s, other)
        per_song.append(dances)
        songs_out.append(
            {
                "song": song.name,
                "analysis": song.analysis.summary(),
                "librosa_beats": len(song.grid.percussive_beats),
                "rhythm_points": len(song.grid.rhythm_points),
                "rows": {
                    row: {
                        "mean": {k: _mean(d.metrics.get(k) for d in ds) for k in SCALARS},
                        "dances": [to_json_types(d.metrics) for d in ds],
                    }
                    for row, ds in dances.items()
                },
            }
        )
    table = aggregate(lib, per_song, rows)
    for key, cleaned in (("classifier", False), ("classifier_cleaned", True)):
        for row, scores in classifier_scores(lib, per_song, rows, cleaned).items():
            for song_out, score in zip(songs_out, scores, strict=True):
                song_out["rows"][row][key] = score
    metrics = {
        "format": 1,
        "graph": {"name": lib.graph.name, "version": lib.graph.version},
        "spec": spec.model_dump(mode="json"),
        "fps": EVAL_FPS,
        "library": library_summary(lib),
        "rows": to_json_types(table),
        "sync": to_json_types(sync_table(per_song, rows)),
        "songs": songs_out,
        "seconds": round(time.perf_counter() - t0, 2),
    }
    _write(out_dir, metrics, songs, per_song)
    return metrics


def evaluate_result(result_dir: str | Path, lib: Library, audio: str | Path | None = None) -> dict:
    """Score one existing synthesize/job result folder (``timeline.json`` + ``alternatives/*.bvh``)
    against ``lib`` (the graph it was danced from); writes ``metrics.json`` and ``report.html``
    into the folder. The music side comes from ``audio`` (default: the song recorded in the
    timeline, when it is found beside the result): librosa's percussive beats for the Beat Align
    Scores and the rhythm signatures of the timeline's bars for the rhythm points; without
    audio, the timeline's bars' beats stand in for the BAS's music beats (labelled so in the
    metrics) and there are no rhythm points (CM beat accuracy not measured)."""
    from dancegraph.errors import NotFoundError
    from dancegraph.motion.bvh import read_bvh
    from dancegraph.music.analysis import MusicAnalysis
    from dancegraph.preview import find_audio, read_timeline

    folder = Path(result_dir)
    timeline = read_timeline(folder)
    if audio is None:
        try:
            audio = find_audio(folder, timeline)
        except NotFoundError:
            audio = None
    spec = Spec.model_validate(timeline.get("provenance", {}).get("spec", {}))
    bar_rows = timeline.get("bars", [])
    bars = np.array([[b["start_s"], b["end_s"]] for b in bar_rows], dtype=float).reshape(-1, 2)
    bar_beats = np.array([b.get("beats", [0] * 5) for b in bar_rows], dtype=float).reshape(-1, 5)
    beats = np.array([t for b in bar_rows for t in b.get("beats", [])[:4]], dtype=float)
    tags = [b.get("tag", {}) for b in bar_rows]
    topk = np.zeros((len(bars), 3), dtype=int)
    if audio is not None:
        from dancegraph.music.decode import load_audio
        from dancegraph.music.features import FEATURE_SR, frame_features
        from dancegraph.rhythm.music import song_signatures

        y, sr = load_audio(audio, sr=FEATURE_SR)
        ff = frame_features(y, sr)
        _, topk, _ = song_signatures(ff, bar_beats)
        grid = sync_grid(bar_beats, topk[:, 0], mbeats.librosa_beats(y, sr))
        source = "librosa_percussive"
    else:
        grid = replace(sync_grid(bar_beats, topk[:, 0], beats), rhythm_points=np.zeros(0))
        source = "timeline"
    fps = float(timeline["fps"])
    dances = []
    for alt in timeline.get("alternatives", []):
        bvh = alt.get("files", {}).get("bvh")
        if bvh is None:
            continue
        motion = resample(read_bvh(folder / bvh), EVAL_FPS)
        ids = [b["node"] for b in alt["bars"]]
        missing = [n for n in ids if not lib.graph.has_node(n)]
        if missing:
            raise EvalError(
                f"node {missing[0]} of the result is not in graph {lib.graph.name} "
                f"{lib.graph.version}",
                code="eval_graph_mismatch",
                field="result",
            )
        nodes = np.array([lib.graph.node_index(n) for n in ids], dtype=np.int64)
        seams = [int(round(s * EVAL_FPS / fps)) for s in alt.get("seams", [])]
        d = score_dance(
            lib,
            motion,
            spec,
            span=(float(bars[0, 0]), float(bars[-1, 1])) if len(bars) else (0.0, 0.0),
            grid=grid,
            bars=bars,
            nodes=nodes,
            tags=tags,
            seams=seams,
            bar_beats=bar_beats if len(bar_beats) else None,
        )
        if alt.get("retime"):
            d.metrics["speed_factor_min"], d.metrics["speed_factor_max"] = alt["retime"][
                "speed_factor"
            ]
        d.plot["per_bar"] = [dict(b.get("cost", {}), node=b["node"]) for b in alt["bars"]]
        dances.append(d)
    if not dances:
        raise EvalError(
            f"{folder}: the result has no BVH alternatives to score",
            code="eval_bad_result",
            field="result",
        )
    analysis = MusicAnalysis(
        duration_s=float(timeline["duration_s"]),
        tempo_bpm=float(timeline["song"]["tempo_bpm"]),
        tempo_confidence=float(timeline["song"]["tempo_confidence"]),
        meter=int(timeline["song"]["meter"]),
        beats=beats,
        beat_positions=np.tile([1, 2, 3, 4], len(bars)),
        downbeats=bars[:, 0],
        bars=bars,
        bar_beats=bar_beats,
        phrases=list(timeline.get("phrases", [])),
        tags=tags,
        signature_scores=np.zeros((len(bars), 13)),
        signature_topk=topk,
        bar_onset_rms=np.zeros((len(bars), 2, 200)),
        method=timeline["song"].get("method", ""),
    )
    song = Song(folder.name, analysis, grid)
    per_song = [{"result": dances}]
    lib_rows = aggregate(lib, per_song, ["result"])
    metrics = {
        "format": 1,
        "graph": {"name": lib.graph.name, "version": lib.graph.version},
        "spec": spec.model_dump(mode="json"),
        "fps": EVAL_FPS,
        "library": library_summary(lib),
        "music_beats": source,
        "rows": to_json_types(lib_rows),
        "sync": to_json_types(sync_table(per_song, ["result"])),
        "songs": [
            {
                "song": folder.name,
                "rows": {"result": {"dances": [to_json_types(d.metrics) for d in dances]}},
            }
        ],
    }
    _write(folder, metrics, [song], per_song, our_row="result")
    return metrics


# --------------------------------------------------------------------------------------------
# output


def _write(out_dir, metrics: dict, songs: list[Song], per_song, our_row: str = "ours") -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    from dancegraph.eval.report import write_report

    write_report(out / "report.html", metrics, songs, per_song, our_row)
