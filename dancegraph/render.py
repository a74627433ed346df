"""Path → motion → files: the dance of each search alternative as BVH (and FBX) plus ``timeline.json``.

For every alternative of a search result, bar ``b``'s node is laid on the music bar through the
beat-anchored time-warp (every beat of the node on the song's beat of the same number), the nodes
hand over to each other where they match best within a beat of each bar line, with root alignment
and inertialized offsets (``motion.stitch``; docs/rendering.md), the stitched dance is re-timed
on the song's beats (``beat_timing``: its stops onto the beats, and slowing into every beat), it
is placed on the stage where the search planned the path, and the feet are cleaned
(``clean_foot_skate``). Frame 0 of every file is t = 0 of the song: before the first bar the
first pose is held, after the last bar the last pose, so an artist can drop the audio and the
animation on one timeline. Bar ``b`` occupies frames ``[round(start_b·fps),
round(start_{b+1}·fps))``; the frames where its node takes over (``seams``) lie within a beat
of its first.

Files in ``out_dir``:

- ``alternatives/<k>.bvh`` — the dataset's skeleton, metres, ``spec.output.fps``;
- ``alternatives/<k>.fbx`` — when ``"fbx"`` is in ``spec.output.formats`` (through Blender:
  ``dancegraph.motion.fbx``);
- ``alternatives/<k>.usd`` — when ``"usd"`` is in ``spec.output.formats`` (UsdSkel, metres, Y
  up: ``dancegraph.motion.usd``);
- ``timeline.json`` — the song's bars and phrases, per alternative the chosen node per bar with
  its cost breakdown and provenance (source take, frame range, augmentation), foot-skate and stage
  reports, and the provenance of the whole result: dataset name, version and licence, graph build
  version and parameters, model versions, and the spec used.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dancegraph import __version__
from dancegraph.errors import DanceGraphError
from dancegraph.graph.artifact import KINDS, MotionGraph
from dancegraph.motion import quat
from dancegraph.motion.bvh import write_bvh
from dancegraph.motion.retime import BEAT_ACCENT, STOPS_ON_BEATS, sample
from dancegraph.motion.skeleton import Motion
from dancegraph.spec import Spec

if TYPE_CHECKING:
    from dancegraph.graph.search import SearchResult
    from dancegraph.music.analysis import MusicAnalysis

TIMELINE_FORMAT = 1
TIMELINE = "timeline.json"


def bar_frames(bars: np.ndarray, fps: float) -> np.ndarray:
    """``(B, 2)`` int frame ranges ``[start, end)`` of the music bars at ``fps``.

    ``bars`` is ``(B, 2)`` seconds. Consecutive bars share their boundary frame (a gap between two
    bars, which the bar rule allows at a downbeat correction, is given to the earlier bar), so
    the ranges tile the dance without holes; each range holds at least one frame.
    """
    bars = np.asarray(bars, dtype=float).reshape(-1, 2)
    starts = np.round(bars[:, 0] * fps).astype(np.int64)
    ends = np.round(bars[:, 1] * fps).astype(np.int64)
    if len(bars) > 1:
        ends[:-1] = starts[1:]
    ends = np.maximum(ends, starts + 1)
    if len(bars) > 1:
        starts[1:] = np.maximum(starts[1:], ends[:-1])
        ends = np.maximum(ends, starts + 1)
    return np.stack([starts, ends], axis=1)


def root_heading(motion: Motion, frame: int = 0) -> float:
    """Heading (radians about +Y, 0 = facing +Z) of the root at ``frame``."""
    return float(quat.heading_angle(motion.rotations[frame, 0]))


def place(motion: Motion, position_xz: tuple[float, float], heading: float) -> Motion:
    """Move and turn ``motion`` about the vertical so frame 0's root is at ``position_xz`` facing ``heading``."""
    from dancegraph.motion.stitch import turn_on_ground

    rot = motion.rotations.copy()
    root, rot[:, 0] = turn_on_ground(
        motion.root_positions,
        rot[:, 0],
        heading - root_heading(motion, 0),
        motion.root_positions[0],
        np.array([position_xz[0], 0.0, position_xz[1]]),
    )
    return Motion(motion.skeleton, motion.fps, root, rot)


def follow_plan(motion: Motion, bar_starts: np.ndarray, plan: np.ndarray) -> tuple[Motion, dict]:
    """Bend ``motion``'s root path so bar ``b`` starts at ``plan[b]`` (x, z, yaw).

    ``bar_starts``: ``(B,)`` frame of each bar's first frame. The error at each bar start
    (position and heading, unwrapped) is interpolated between bar starts by a monotone cubic
    (PCHIP: C1, so the correction adds no velocity jump at a bar start) and removed; before the
    first and after the last bar start it stays constant. Returns the motion and ``{max_m,
    max_rad}`` of the drift.
    """
    from scipy.interpolate import PchipInterpolator

    starts = np.asarray(bar_starts, dtype=np.int64)
    root = motion.root_positions.copy()
    rot = motion.rotations.copy()
    got_xz = root[starts][:, [0, 2]]
    got_yaw = quat.heading_angle(rot[starts, 0])
    err_xz = plan[:, :2] - got_xz
    err_yaw = np.angle(np.exp(1j * (plan[:, 2] - got_yaw)))
    errors = np.column_stack([err_xz, np.unwrap(err_yaw)])
    t = np.clip(np.arange(motion.n_frames), starts[0], starts[-1])
    if len(starts) > 1:
        fix = PchipInterpolator(starts, errors, axis=0)(t)
    else:
        fix = np.broadcast_to(errors[0], (len(t), 3))
    fix_x, fix_z, fix_yaw = fix[:, 0], fix[:, 1], fix[:, 2]
    root[:, 0] += fix_x
    root[:, 2] += fix_z
    rot[:, 0] = quat.multiply(quat.from_y_angle(fix_yaw), rot[:, 0])
    drift = {
        "max_m": float(np.linalg.norm(err_xz, axis=1).max()),
        "max_rad": float(np.abs(err_yaw).max()),
    }
    return Motion(motion.skeleton, motion.fps, root, rot), drift


def hold(motion: Motion, before: int, after: int) -> Motion:
    """``motion`` with its first pose repeated ``before`` times and its last ``after`` times."""
    idx = np.concatenate(
        [
            np.zeros(before, dtype=np.int64),
            np.arange(motion.n_frames),
            np.full(after, motion.n_frames - 1),
        ]
    )
    return Motion(motion.skeleton, motion.fps, motion.root_positions[idx], motion.rotations[idx])


def check_path(nodes: Sequence[str], bar_beats: np.ndarray) -> None:
    """Raise ``DanceGraphError`` unless ``nodes`` name one node per bar of ``bar_beats (B, 5)``
    (``render_mismatch``) and there is a bar (``render_empty``)."""
    if len(nodes) != len(bar_beats):
        raise DanceGraphError(
            f"the path has {len(nodes)} nodes for {len(bar_beats)} music bars",
            code="render_mismatch",
            field="nodes",
        )
    if len(bar_beats) == 0:
        raise DanceGraphError("the song has no bars to dance", code="render_empty", field="bars")


def ground_extent(xz: np.ndarray) -> dict:
    """``{"x": [min, max], "z": [min, max]}`` (m) of ground positions ``xz (F, 2)``."""
    return {
        "x": [float(xz[:, 0].min()), float(xz[:, 0].max())],
        "z": [float(xz[:, 1].min()), float(xz[:, 1].max())],
    }


def search_alternatives(result: SearchResult) -> tuple[dict, list[dict]]:
    """``result.to_dict()`` and its alternatives; ``DanceGraphError(code="render_empty")`` when
    it has none."""
    found = result.to_dict()
    alternatives = found.get("alternatives") or []
    if not alternatives:
        raise DanceGraphError(
            "the search result has no alternatives to render", code="render_empty"
        )
    return found, alternatives


def render_path(
    graph: MotionGraph,
    nodes: list[str],
    bar_beats: np.ndarray,
    fps: float,
    *,
    duration_s: float | None = None,
    placements: np.ndarray | None = None,
    foot_cleanup: bool = True,
    land_stops: bool = STOPS_ON_BEATS,
    beat_accent: float = BEAT_ACCENT,
) -> tuple[Motion, dict]:
    """The dance of one path: ``nodes[b]`` (node ids) danced on music bar b, whose beats are
    ``bar_beats[b]`` (``(B, 5)`` s: 4 beats and the next downbeat, ``analysis.bar_beats``).

    Returns the motion (frame 0 = t 0 of the song, ``duration_s`` long when given) and a report:
    ``frames`` per bar, ``seams`` (frames where a later bar's node takes over; not where a take
    simply continues into its next bar), ``seam_bars`` (the bar each seam starts), ``cut_beats``
    (each seam's offset from its bar line, beats), ``foot_skate`` (before/after), ``stage``
    (root ground-plane extent), ``drift`` (how far stitching strayed from the plan, corrected),
    ``retime`` (``beat_timing``'s report: the accent asked, had and added, the pulse depth it
    adds, the re-timing's local speed factor outside the seams).

    ``placements``: ``(B, 3)`` (x, z, yaw) of each bar's first frame as the search planned it
    (``Alternative.placements``; default: the origin facing +Z, chained by the stitch). The
    stitched dance is moved there and the small drift between stitching and the plan is spread
    linearly over each bar, so stage bounds and waypoints the search honoured hold on the file.
    ``land_stops``, ``beat_accent``: the stitched dance's stops are moved onto the song's beats,
    and it slows into every beat by ``beat_accent`` ([0, 0.8]), before it is placed and its feet
    cleaned (``beat_timing``).
    """
    from dancegraph.motion.contacts import clean_foot_skate
    from dancegraph.motion.stitch import CUT_BEATS, stitch

    bar_beats = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    check_path(nodes, bar_beats)
    frames = bar_frames(bar_beats[:, [0, 4]], fps)
    pieces = []
    for b, node_id in enumerate(nodes):
        try:
            i = graph.node_index(node_id)
        except KeyError:
            raise DanceGraphError(
                f"node {node_id!r} (bar {b}) is not in graph {graph.name} {graph.version}",
                code="unknown_node",
                field=f"nodes[{b}]",
            ) from None
        pieces.append(graph.node_frames(i))
    cut_beats = float((graph.manifest.get("seam") or {}).get("cut_beats", CUT_BEATS))
    dance, cuts = stitch(pieces, bar_beats, frames, fps, cut_beats=cut_beats)
    expected = int(frames[-1, 1] - frames[0, 0])
    if dance.n_frames != expected:
        raise DanceGraphError(
            f"stitching returned {dance.n_frames} frames for {expected} bar frames",
            code="render_failed",
        )
    seam = ~cuts["continuous"]
    seams = cuts["cuts"][seam]
    warp = warp_speed(pieces, bar_beats, frames, cuts["cuts"], fps)
    dance, seams, retimed = beat_timing(
        dance,
        bar_beats,
        int(frames[0, 0]),
        seams,
        land_stops=land_stops,
        accent=beat_accent,
        warp_rate=warp,
    )
    report: dict = {
        "retime": retimed,
        "seams": [int(s) for s in seams],
        "seam_bars": [int(b) + 1 for b in np.flatnonzero(seam)],
        "cut_beats": [round(float(x), 3) for x in cuts["cut_beats"][seam]],
    }
    if placements is None:
        dance = place(dance, (0.0, 0.0), 0.0)
        report["drift"] = None
    else:
        plan = np.asarray(placements, dtype=float).reshape(-1, 3)
        if len(plan) != len(bar_beats):
            raise DanceGraphError(
                f"{len(plan)} placements for {len(bar_beats)} bars",
                code="render_mismatch",
                field="placements",
            )
        dance = place(dance, (plan[0, 0], plan[0, 1]), plan[0, 2])
        dance, report["drift"] = follow_plan(dance, frames[:, 0] - frames[0, 0], plan)
    if foot_cleanup:
        dance, skate = clean_foot_skate(dance)
        report["foot_skate"] = to_json_types(skate)
    total = expected + int(frames[0, 0])
    if duration_s is not None:
        total = max(total, int(round(duration_s * fps)))
    dance = hold(dance, int(frames[0, 0]), total - int(frames[-1, 1]))
    report["frames"] = frames.tolist()
    report["stage"] = ground_extent(dance.root_positions[:, [0, 2]])
    return dance, report


#: beats: how far from a song beat a stop of the stitched dance may be moved onto it (the
#: build's ``BuildParams.accent_tolerance``: a stop nearer the half beat is left where it is)
STOP_TOLERANCE = 0.45
#: bound on how much landing the stops may speed up or slow down a beat interval (the build's
#: ``accent_max_speed``: the stop moves back until the interval is at it)
STOP_MAX_SPEED = 1.5
#: frames per second (at most) the stitched dance's stops and speed are read at: every k-th
#: frame of a faster dance, for half the forward kinematics at 60 fps; the stops' sub-frame
#: refinement keeps them within a few milliseconds, far inside ``STOP_TOLERANCE``
STOP_FPS = 30.0


def beat_timing(
    dance: Motion,
    bar_beats: np.ndarray,
    start_frame: int,
    frames: np.ndarray,
    *,
    land_stops: bool = STOPS_ON_BEATS,
    accent: float = BEAT_ACCENT,
    warp_rate: np.ndarray | None = None,
) -> tuple[Motion, np.ndarray, dict]:
    """The stitched ``dance`` (song frames from ``start_frame`` on, at ``dance.fps``) re-timed on
    the song's beats ``bar_beats (B, 5)`` s, in one resampling through two steps, each a map
    from song time to the time of the dance before it (both off by default: the dance keeps the
    pulse of its takes; docs/rendering.md):

    1. stops on the beats (``land_stops``): the dance's stops (``rhythm.motion.motion_stops``)
       within ``STOP_TOLERANCE`` beat of a song beat land on it (``retime.accent_anchors``: no
       beat interval sped up or slowed down beyond ``STOP_MAX_SPEED``; ``retime.beat_map``);
    2. the beat accent (``accent`` > 0, a stylization): the landed dance slows into every beat
       and speeds up between (``retime.accent_map``), by ``accent`` less the accent it already
       has (``retime.accent_depth`` of its ``stop_curve``), fading out within
       ``retime.ACCENT_FADE_BEATS`` of each of ``frames`` (the seams keep their pace); beats and
       bar lines stay where they are.

    ``accent`` in [0, 0.8]. Returns the re-timed dance (same frame count and rate), ``frames
    (K,)`` (song frame numbers of the input, e.g. its seams) where they now fall, and a report:
    ``stops_on_beats``, ``accent`` (asked), ``accent_had`` (what the dance had, None when not
    read), ``accent_added`` (the depth applied), ``pulse_depth`` (``{"without", "with"}``: the
    mean joint speed's fold on the song's beats without and with the accent,
    ``metrics.naturalness``; None without an accent), ``retime_speed_factor`` (``[min, max]`` of
    the re-timing's rate, source time per song time, outside ``SEAM_CLEAR_BEATS`` of the seams)
    and ``speed_factor`` (the same of the whole map from song time to the takes' time: the
    re-timing's rate times ``warp_rate (N,)``, the stitched dance's own relative rate per frame,
    ``warp_speed``; the re-timing's alone without it). A dance on a skeleton without the
    canonical joints, or with nothing to move, is returned as it is."""
    from dancegraph.motion.retime import accent_anchors, beat_map
    from dancegraph.rhythm.motion import motion_rhythm

    fps = float(dance.fps)
    frames = np.asarray(frames)
    bar_beats = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    song = (start_frame + np.arange(dance.n_frames)) / fps
    rate = np.ones(dance.n_frames) if warp_rate is None else np.asarray(warp_rate, dtype=float)
    info: dict[str, Any] = {
        "stops_on_beats": bool(land_stops),
        "accent": float(accent),
        "accent_had": None,
        "accent_added": 0.0,
        "pulse_depth": None,
        "retime_speed_factor": [1.0, 1.0],
        "speed_factor": speed_factor(np.cumsum(rate) / fps, song, frames / fps, bar_beats),
    }
    if not land_stops and accent <= 0.0:
        return dance, frames, info
    step = max(1, int(fps // STOP_FPS))
    coarse = Motion(
        dance.skeleton, fps / step, dance.root_positions[::step], dance.rotations[::step]
    )
    try:
        curve, stops = motion_rhythm(coarse)
    except DanceGraphError as exc:
        if exc.code != "skeleton_unmapped":
            raise
        return dance, frames, info
    moved = bar_beats
    if land_stops:
        moved = accent_anchors(bar_beats, stops + start_frame / fps, STOP_TOLERANCE, STOP_MAX_SPEED)
    landed = not np.array_equal(moved, bar_beats)

    def to_dance(t: np.ndarray) -> np.ndarray:  # song time -> time in the stitched dance
        return beat_map(bar_beats, moved, t) if landed else t

    coarse_t = (start_frame + step * np.arange(curve.size)) / fps
    if accent > 0.0 and curve.any():
        info["accent_had"] = _accent_had(curve, coarse_t, to_dance, bar_beats)
        info["accent_added"] = float(np.clip(accent - info["accent_had"], 0.0, accent))
    depth = info["accent_added"]
    if not landed and depth == 0.0:
        if accent > 0.0:  # asked, and nothing to add: the dance's own pulse, reported
            info["pulse_depth"] = _pulse_with_accent(coarse, coarse_t, song, song, song, bar_beats)
        return dance, frames, info
    landed_song = to_dance(song)
    if depth > 0.0:  # the frames given (the seams) keep the dance's pace, where they now fall
        from dancegraph.motion.retime import accent_map

        landed_at = np.interp(frames / fps, landed_song, song)
        source_t = to_dance(accent_map(bar_beats, song, depth, fade_at=landed_at))
    else:
        source_t = landed_song
    source = source_t * fps - start_frame
    warped = sample(dance, source)
    warped.fps = fps
    now = np.interp(frames - start_frame, source, np.arange(dance.n_frames)) + start_frame
    info["retime_speed_factor"] = speed_factor(source_t, song, now / fps, bar_beats)
    whole = np.cumsum(np.interp(source_t, song, rate) * np.gradient(source_t, song)) / fps
    info["speed_factor"] = speed_factor(whole, song, now / fps, bar_beats)
    if accent > 0.0:
        info["pulse_depth"] = _pulse_with_accent(
            coarse, coarse_t, song, landed_song, source_t, bar_beats
        )
    return warped, np.round(now).astype(np.int64), info


def warp_speed(
    pieces: list[tuple[Motion, np.ndarray]],
    bar_beats: np.ndarray,
    frames: np.ndarray,
    cuts: np.ndarray,
    fps: float,
) -> np.ndarray:
    """``(N,)`` the stitched dance's relative rate per output frame (``frames[0, 0]`` on, N the
    dance's frames): the take's time per song time where the frame shows bar b's node (from the
    cut ``cuts[b - 1]`` on, ``stitch``'s; ``pieces`` as for ``stitch``), through
    ``node_warp(beats_b)`` and ``song_phase(bar_beats)``, divided by that bar's mean (the node's
    bar in its take's time over the music bar's length): 1 where the dance keeps its take's own
    pace, whatever the tempo it is danced at. Why: the build's accent anchors and uneven song
    beats re-time the takes within a bar; this says by how much."""
    from dancegraph.motion.retime import BEAT0, node_warp, song_phase

    song = np.arange(frames[0, 0], frames[-1, 1]) / fps
    phase = song_phase(bar_beats)(song)
    dphase = np.gradient(phase, song)
    owner = np.searchsorted(np.asarray(cuts, dtype=float), song * fps, side="right")
    out = np.ones(song.size)
    h = 1e-3
    for b, (_, beats) in enumerate(pieces):
        sel = owner == b
        if not sel.any():
            continue
        warp, x = node_warp(beats), phase[sel] - 4 * b
        frames_per_beat = (warp(x + h) - warp(x - h)) / (2 * h)
        mean = (beats[BEAT0 + 4] - beats[BEAT0]) / (bar_beats[b, 4] - bar_beats[b, 0])
        out[sel] = frames_per_beat * dphase[sel] / mean
    return out


#: Beats either side of a seam left out of the re-timing's speed factor (a hand-over's own
#: offsets decay there; the accent fades out within a beat of it).
SEAM_CLEAR_BEATS = 0.5


def speed_factor(
    source_t: np.ndarray, song_t: np.ndarray, seams_t: np.ndarray, bar_beats: np.ndarray
) -> list[float]:
    """``[min, max]`` of a re-timing's local speed factor ``d source_t / d song_t`` (``(N,)`` s
    each: the time shown at each song time) inside the bars of ``bar_beats (B, 5)`` and farther
    than ``SEAM_CLEAR_BEATS`` (of the median beat) from every ``seams_t (K,)`` s; ``[1, 1]``
    where no sample is left. Why: a re-timing should keep the dancers' own pace (a factor near
    1), and this is its largest departure from it."""
    rate = np.gradient(np.asarray(source_t, dtype=float), np.asarray(song_t, dtype=float))
    beat = float(np.median(np.diff(bar_beats, axis=1)))
    keep = (song_t >= bar_beats[0, 0]) & (song_t <= bar_beats[-1, 4])
    for s in np.asarray(seams_t, dtype=float).reshape(-1):
        keep &= np.abs(song_t - s) > SEAM_CLEAR_BEATS * beat
    if not keep.any():
        return [1.0, 1.0]
    return [round(float(rate[keep].min()), 4), round(float(rate[keep].max()), 4)]


def _accent_had(curve: np.ndarray, t: np.ndarray, to_dance, bar_beats: np.ndarray) -> float:
    """``retime.accent_depth`` of the landed dance: its stop curve ``curve (N,)``, read at song
    times ``t (N,)`` s of the stitched dance, through the landing ``to_dance``."""
    from dancegraph.motion.retime import accent_depth, song_phase

    inside = (t >= bar_beats[0, 0]) & (t <= bar_beats[-1, 4])
    source = to_dance(t)
    speed = np.interp(source, t, curve) * np.gradient(source, t)
    return accent_depth(speed[inside], song_phase(bar_beats)(t[inside]))


def _pulse_with_accent(
    coarse: Motion,
    coarse_t: np.ndarray,
    song: np.ndarray,
    without: np.ndarray,
    with_accent: np.ndarray,
    bar_beats: np.ndarray,
) -> dict:
    """Pulse depth (``metrics.naturalness``) of the dance at song times ``song (N,)`` s shown
    through two re-timings (the stitched dance's times ``without`` and ``with_accent``, ``(N,)``
    s), from the mean joint speed of ``coarse`` (the stitched dance read at times ``coarse_t``)."""
    from dancegraph.metrics.naturalness import pulse_depth, pulse_profile
    from dancegraph.motion.features import joint_speed
    from dancegraph.motion.fk import forward_kinematics

    speed = joint_speed(forward_kinematics(coarse)[0], coarse.fps, 0.0)
    fps = 1.0 / float(np.median(np.diff(song)))
    lead = np.zeros(int(round(song[0] * fps)))
    out = {}
    for key, src in (("without", without), ("with", with_accent)):
        v = np.interp(src, coarse_t, speed) * np.gradient(src, song)
        out[key] = round(pulse_depth(pulse_profile(np.concatenate([lead, v]), fps, bar_beats)), 4)
    return out


def stage_violation(root_xz: np.ndarray, stage) -> float:
    """Largest distance (m) the root ``(F, 2)`` (x, z) goes outside ``stage`` (0 when inside)."""
    if stage is None:
        return 0.0
    x, z = np.asarray(root_xz)[:, 0], np.asarray(root_xz)[:, 1]
    over = np.maximum.reduce(
        [stage.x[0] - x, x - stage.x[1], stage.z[0] - z, z - stage.z[1], np.zeros_like(x)]
    )
    return float(over.max()) if over.size else 0.0


def fbx_exporter(formats: Sequence[str], exporter=None):
    """``exporter`` where given; else, when ``formats`` asks for FBX, the shared warm Blender
    exporter (``motion.fbx.shared_exporter``), raising ``FbxError(code="fbx_unavailable")``
    without Blender; else None. One check for every renderer that writes FBX."""
    if "fbx" not in formats or exporter is not None:
        return exporter
    from dancegraph.motion.fbx import FbxError, fbx_available, shared_exporter

    if not fbx_available():
        raise FbxError(
            "FBX output needs Blender (scripts/install-blender.sh); or ask for "
            'output.formats ["bvh"] only',
            code="fbx_unavailable",
            field="spec.output.formats",
        )
    return shared_exporter()


def song_summary(analysis: MusicAnalysis) -> dict:
    """The timeline's ``song``: tempo (BPM) and its confidence, meter, the tracker, the grid
    octave and the analysis's warnings."""
    return {
        "tempo_bpm": float(analysis.tempo_bpm),
        "tempo_confidence": float(analysis.tempo_confidence),
        "meter": int(analysis.meter),
        "method": analysis.method,
        "grid_octave": analysis.grid_octave,
        "warnings": list(analysis.warnings),
    }


def render(
    graph: MotionGraph,
    analysis: MusicAnalysis,
    result: SearchResult,
    spec: Spec,
    out_dir: str | Path,
    *,
    exporter=None,
    extra_provenance: dict | None = None,
    on_rig=None,
) -> dict:
    """Write every alternative of ``result`` (the search on ``graph``) into ``out_dir``.

    ``analysis``: the song's analysis the search answered. FBX files are written through ``exporter`` (a
    ``dancegraph.motion.fbx.FbxExporter``; default the shared warm one) when the spec asks for
    them. ``on_rig``: a hook called as ``on_rig(k, dance, out_dir)`` after alternative ``k`` is
    written on the library skeleton; it returns ``(files, report)`` (the dance on a user's rig:
    ``dancegraph.motion.retarget.RigOutput``), added to the alternative's files and ``rig``.
    Returns ``{"files": [paths relative to out_dir], "timeline": {...}}``.
    """
    t0 = time.perf_counter()
    out = Path(out_dir)
    found, alternatives = search_alternatives(result)
    fps = float(spec.output.fps)
    formats = list(spec.output.formats)
    exporter = fbx_exporter(formats, exporter)
    bars = np.asarray(analysis.bars, dtype=float).reshape(-1, 2)
    frames = bar_frames(bars, fps) if len(bars) else np.zeros((0, 2), dtype=np.int64)
    (out / "alternatives").mkdir(parents=True, exist_ok=True)

    files: list[str] = []
    alt_entries = []
    for k, alt in enumerate(alternatives):
        nodes = list(alt["nodes"])
        dance, report = render_path(
            graph,
            nodes,
            analysis.bar_beats,
            fps,
            duration_s=float(analysis.duration_s),
            placements=alt.get("placements"),
            foot_cleanup=spec.output.foot_cleanup,
            land_stops=spec.output.stops_on_beats,
            beat_accent=spec.output.beat_accent,
        )
        outside = stage_violation(dance.root_positions[:, [0, 2]], spec.stage)
        report["stage"]["outside_m"] = outside
        entry_files = {}
        if "bvh" in formats or "fbx" in formats:
            bvh_rel = f"alternatives/{k}.bvh"
            write_bvh(dance, out / bvh_rel)
            entry_files["bvh"] = bvh_rel
        if "fbx" in formats:
            fbx_rel = f"alternatives/{k}.fbx"
            exporter.convert(out / bvh_rel, out / fbx_rel, fps=fps)
            entry_files["fbx"] = fbx_rel
        if "bvh" not in formats and "bvh" in entry_files:
            (out / bvh_rel).unlink()
            del entry_files["bvh"]
        if "usd" in formats:
            from dancegraph.motion.usd import write_usd

            usd_rel = f"alternatives/{k}.usd"
            write_usd(dance, out / usd_rel)
            entry_files["usd"] = usd_rel
        rig_report = None
        if on_rig is not None:
            rig_files, rig_report = on_rig(k, dance, out)
            entry_files.update(rig_files)
        files.extend(entry_files.values())
        alt_entries.append(
            {
                "index": k,
                "files": entry_files,
                "cost": to_json_types(alt.get("cost")),
                "violations": to_json_types(alt.get("violations", [])),
                "frames": dance.n_frames,
                "bars": [_bar_entry(graph, alt, b, node) for b, node in enumerate(nodes)],
                "seams": report["seams"],
                "seam_bars": report["seam_bars"],
                "cut_beats": report["cut_beats"],
                "foot_skate": report.get("foot_skate"),
                "stage": report["stage"],
                "drift": report["drift"],
                "retime": report["retime"],
                **({"rig": to_json_types(rig_report)} if rig_report is not None else {}),
                **{
                    key: to_json_types(v)
                    for key, v in alt.items()
                    if key not in {"nodes", "index", "per_bar", "cost", "violations", "placements"}
                },
            }
        )

    timeline = {
        "format": TIMELINE_FORMAT,
        "fps": fps,
        "duration_s": float(analysis.duration_s),
        "frames": int(round(float(analysis.duration_s) * fps)) if alt_entries else 0,
        "song": song_summary(analysis),
        "bars": [_music_bar(analysis, frames, b) for b in range(len(bars))],
        "phrases": to_json_types(list(analysis.phrases)),
        "alternatives": alt_entries,
        "constraints": to_json_types(found.get("constraints", {})),
        "provenance": _provenance(graph, spec, analysis, extra_provenance),
        "render_seconds": round(time.perf_counter() - t0, 3),
    }
    timeline["frames"] = max(a["frames"] for a in alt_entries)
    (out / TIMELINE).write_text(json.dumps(timeline, indent=1, default=_json_default))
    files.append(TIMELINE)
    return {"files": files, "timeline": timeline}


def _music_bar(analysis, frames: np.ndarray, b: int) -> dict:
    entry: dict[str, Any] = {
        "index": b,
        "start_s": float(analysis.bars[b][0]),
        "end_s": float(analysis.bars[b][1]),
        "start_frame": int(frames[b, 0]),
        "end_frame": int(frames[b, 1]),
    }
    if b < len(analysis.bar_beats):
        entry["beats"] = [float(x) for x in analysis.bar_beats[b]]
    if b < len(analysis.tags):
        entry["tag"] = to_json_types(dict(analysis.tags[b]))
    return entry


def _bar_entry(graph: MotionGraph, alt: dict, b: int, node_id: str) -> dict:
    i = graph.node_index(node_id)
    clip = graph.clips[int(graph.node_clip[i])]
    bar = int(graph.node_bar[i])
    kind = KINDS[int(graph.node_kind[i])]
    sources = [graph.node_ids[int(s)] for s in np.asarray(graph.node_source[i]) if s >= 0]
    entry = {
        "bar": b,
        "node": node_id,
        "source": {
            "take": clip,
            "bar": bar,
            "frames": _source_frames(graph, clip, bar),
            "augmentation": None if kind == "original" else kind,
            "from_nodes": sources,
        },
        "motif": int(graph.motif[i]),
    }
    per_bar = alt.get("per_bar") or []
    if b < len(per_bar):
        entry["cost"] = to_json_types(
            {k: v for k, v in per_bar[b].items() if k not in {"node", "bar"}}
        )
    return entry


def _source_frames(graph: MotionGraph, clip: str, bar: int) -> list[int] | None:
    """``[start, end)`` frames of the bar in its source take (the dataset's frame numbering)."""
    table = (graph.manifest.get("bar_frames") or {}).get(clip)
    if table is None:
        return None
    entry = (
        table.get(str(bar), table.get(bar))
        if isinstance(table, dict)
        else (table[bar] if 0 <= bar < len(table) else None)
    )
    return [int(x) for x in entry] if entry is not None else None


def _provenance(graph: MotionGraph, spec: Spec, analysis, extra: dict | None) -> dict:
    manifest = graph.manifest
    dataset = dict(manifest.get("dataset") or {})
    dataset.setdefault("name", graph.name)
    embedding = manifest.get("embedding") or {}
    prov = {
        "dataset": dataset,
        "graph": {
            "name": graph.name,
            "version": graph.version,
            "format": manifest.get("format"),
            "created": manifest.get("created"),
            "params": manifest.get("params", {}),
        },
        "models": {
            "style_embedding": embedding.get("version"),
            "rhythm_model": (embedding.get("rhythm_model") or {}).get("version"),
            "beat_tracker": analysis.method,
            "beat_tracker_weights": _beatnet_version() if analysis.method == "beatnet" else None,
            "dancegraph": __version__,
        },
        "spec": spec.model_dump(mode="json"),
        "rendered_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    if extra:
        prov.update(to_json_types(extra))
    return prov


def _beatnet_version() -> str | None:
    try:
        from dancegraph.music.weights import BEATNET_VERSION
    except ImportError:
        return None
    return f"BeatNet {BEATNET_VERSION} (CC BY 4.0)"


def to_json_types(obj):
    """Numpy scalars/arrays and tuples inside ``obj`` → JSON types (NaN/inf → None)."""
    if isinstance(obj, dict):
        return {str(k): to_json_types(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_json_types(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_json_types(obj.tolist())
    if isinstance(obj, np.generic):
        return to_json_types(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj)}")


def _audio_provenance(path: Path) -> dict:
    from dancegraph.store import file_sha256

    return {"file": path.name, "sha256": file_sha256(path)}


def style_tempo_range(spec: Spec | None, graph: MotionGraph | None) -> tuple[float, float] | None:
    """The dance style's tempo range (lo, hi) BPM a song is analysed in for ``spec`` on
    ``graph`` (its bars then count the octave that fits it, ``music.analysis.analyze``): the
    spec's ``tempo_range``, else the one the graph's dataset declares
    (``MotionGraph.tempo_range``), else None (no graph, or neither declares one)."""
    if spec is not None and spec.tempo_range is not None:
        return (spec.tempo_range[0], spec.tempo_range[1])
    return graph.tempo_range if graph is not None else None


def synthesize(
    audio,
    graph: MotionGraph,
    spec: Spec,
    out_dir: str | Path,
    *,
    analysis=None,
    sr: int | None = None,
    exporter=None,
    on_rig=None,
) -> dict:
    """Song → dance files: analysis (unless given) → graph search → :func:`render`.

    ``audio``: a path or mono ``(N,)`` samples at ``sr`` Hz (then pass ``analysis``). The
    analysis counts the octave of the style's tempo range (:func:`style_tempo_range`);
    ``grid_octave`` and a warning say when that is not the tracked one. A graph
    built with learned models gets their music terms from the audio (``add_music_terms``; for
    samples only with ``sr``). ``on_rig``: see :func:`render`. Returns render's dict plus ``analysis`` (the summary) and
    ``search`` (``SearchResult.to_dict()``).
    """
    from dancegraph.embed.learned import add_music_terms
    from dancegraph.graph.search import search
    from dancegraph.music.analysis import analyze

    if analysis is None:
        analysis = analyze(
            audio, tempo_range=style_tempo_range(spec, graph), params=spec.analysis_params()
        )
    if isinstance(audio, str | Path) or sr is not None:
        analysis = add_music_terms(analysis, graph, audio if sr is None else (audio, sr))
    found = search(graph, analysis, spec)
    source = {"audio": _audio_provenance(Path(audio))} if isinstance(audio, str | Path) else {}
    rendered = render(
        graph,
        analysis,
        found,
        spec,
        out_dir,
        exporter=exporter,
        extra_provenance=source or None,
        on_rig=on_rig,
    )
    return {**rendered, "analysis": analysis.summary(), "search": found.to_dict()}
