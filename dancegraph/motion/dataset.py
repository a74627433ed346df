"""Dataset import: a folder of motion files (+ an optional manifest) → a normalised dataset of bars.

``import_dataset`` reads every take of a folder (BVH, animated GLB/glTF or FBX), puts takes on
other skeletons onto the library's skeleton with the retargeter, estimates or reads each take's
beat and bar grid (from the music the take was danced to where the manifest names it, else from the
motion), cuts 4-beat bars, labels each bar's rhythm signature from its kinematic beats, and
stores the result in the object store:

- ``datasets/<name>/dataset.json``: name, version (content hash), licence, the skeleton, the
  clips (``ClipInfo``), the bars (``BarInfo``) and the import report;
- ``<data_prefix>/clips/<clip_id>.npz``: ``root_positions (F, 3)`` m, ``rotations (F, J, 4)``
  (x, y, z, w) float32, ``beats (N,)`` s, ``kinematic_beats (K,)`` s;
- ``<data_prefix>/audio/<clip_id><ext>``: paired audio, where the manifest names one;

where ``data_prefix`` (``datasets/<name>/data-<stamp>``, named in dataset.json) is fresh for
every import, so a reader never mixes two imports' files. The version is a hash of the content
(records and clip arrays), the same for the same input.

A take that cannot be imported is listed in the report (``failed``: file, code, message) and
the other takes are published (``import_dataset(..., strict=True)`` publishes nothing unless
every take passed, and raises ``dataset_takes_failed`` listing each take's code). Either way no
reader sees a half-written dataset: clip data goes to a fresh folder that ``dataset.json`` names,
written last. Failure codes per take: the reader's (``bvh_syntax``, ``bvh_truncated``, ...,
``gltf_invalid``, ``fbx_invalid``, ``take_no_animation``), ``take_format_unsupported`` (not a
BVH, GLB/glTF or FBX file), ``take_under_one_bar``, ``fps_mixed`` (a frame rate other than the library's
without a declared ``fps``), ``skeleton_unmapped`` (no humanoid roles by name or structure and
no ``roles`` map), ``manifest_file_missing`` (a manifest entry naming an absent take or audio
file), ``audio_undecodable`` (and the other ``audio_*`` codes of the decoder),
``duplicate_clip_id``, ``manifest_invalid``. ``load_dataset`` reads a stored dataset back.

Manifest (YAML or JSON; ``manifest.yaml``/``.yml``/``.json`` in the folder is used when none is
given). Every key is optional; unknown keys are an error (``manifest_invalid``) so that typos
do not pass silently::

    name: cmu-salsa                  # informative; the import's --name wins
    licence: "..."                   # stored with the dataset
    acknowledgement: "..."
    source: "http://mocap.cs.cmu.edu"
    files: "*.bvh"                   # glob inside the folder (default: every .bvh, .glb,
                                     # .gltf and .fbx file)
    skeleton: "60_01"                # the library's skeleton: one of its takes (clip id) or a
                                     # rig file in the folder (FBX, GLB, BVH; not a take);
                                     # default the first take's. Takes on other skeletons are
                                     # retargeted onto it (dancegraph.motion.retarget)
    roles: {hips: pelvis_jnt, ...}   # role -> joint name, for skeletons whose names and shape
                                     # do not tell the humanoid roles (used for every skeleton
                                     # that has all these joints)
    audio_offset_s: 0.0              # default of the clips' audio_offset_s
    strip_suffix: "_scaled"          # clip id = file stem without this suffix
    fps: 60                          # override the files' header frame rate ...
    fps_reason: "..."                # ... and say why (kept in the dataset)
    scale: 1.0                       # file units → metres (CMU ASF units: 0.056444)
    style: salsa                     # style label of every clip
    tempo_prior_bpm: [150, 220]      # plausible tempo range for the kinematic estimate
    style_tempo_bpm: [160, 220]      # the style's danced tempo range (BPM of the counted beat),
                                     # carried into the graph: a song tracked at half or twice
                                     # a tempo in it gets its bars counted at that tempo
    tempo_bpm: 120                   # fixed tempo: bars from it instead of an estimate
    first_downbeat_s: 0.0            # with tempo_bpm: where the first bar starts (default:
                                     # on the kinematic beats, or 0 without a steady beat)
    steady_beat: false               # the clips have no steady beat: bars from tempo_bpm,
                                     # every clip flagged no_steady_beat
    flags: [no_music]                # flags given to every clip
    partners: [["60_01", "61_01"]]   # takes danced together to the same music: the report
                                     # lists how well each pair's grids agree
    clips:                           # per clip (key: clip id), all optional
      "60_01":
        file: 60_01_scaled.bvh       # default: <id><strip_suffix>.bvh or the matching stem
        style: salsa
        fps: 60
        scale: 1.0
        tempo_prior_bpm: [150, 220]
        tempo_bpm: 168
        first_downbeat_s: 0.12
        beats: [0.12, 0.48, ...]     # annotated beat times (s): override every estimate
        downbeats: [0.12, 1.55, ...] # bar starts among the beats (default: the first beat)
        bars: [[0.12, 0.48, 0.83, 1.19, 1.55], ...]  # or explicit 4-beat bars (+ next downbeat)
        signatures: ["00010101", ...]  # one per bar: override the kinematic labels
        audio: 60_01.ogg             # the music the take was danced to, relative to the
                                     # folder: the take's grid comes from the music tracker
        audio_offset_s: 1.25         # the audio's time (s) at the take's first frame
        roles: {hips: pelvis_jnt}    # this take's role map (overrides the library's)
        exclude: true                # not imported (listed in the report)
        reason: "..."                # why excluded / flagged
        flags: [walk]                # extra flags for this clip

Beat sources, in order of precedence: ``annotation`` (beats/bars in the manifest), ``music``
(``dancegraph.music.analysis.analyze`` of the take's audio, counted at the manifest's
``style_tempo_bpm`` where given, moved by ``audio_offset_s`` onto the take's clock; the motion
estimate is kept as a check: ``ClipInfo.grid_check``), ``manifest_tempo`` (a fixed tempo, e.g.
for takes without a steady beat; its phase and downbeat from the motion unless
``first_downbeat_s`` is given), ``kinematic`` (the grid of
``dancegraph.motion.tempo.estimate_grid``: tempo per section, sub-frame beats). Each take is
gridded from its own motion (or music) only, so a take imported alone gets the same grid.

Stored format 2 (format 1 had whole-frame kinematic grids and no sections): a store written
by an older version fails to load with ``dataset_format_old``; import it again.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import time
import uuid
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from dancegraph.errors import DanceGraphError, MotionFileError, NotFoundError
from dancegraph.motion import quat
from dancegraph.motion import tempo as tempo_mod
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.features import MAIN_JOINTS, kinematic_beats
from dancegraph.motion.fk import canonical_positions, fk_arrays, forward_kinematics
from dancegraph.motion.rig import (
    REQUIRED_ROLES,
    Rig,
    RigError,
    RoleMap,
    build_rig,
    check_mapping,
    map_roles,
)
from dancegraph.motion.skeleton import CANONICAL_JOINTS, Motion, Skeleton, find_canonical
from dancegraph.rhythm import signatures as sig
from dancegraph.store import ObjectStore

FORMAT_VERSION = 2
MANIFEST_NAMES = ("manifest.yaml", "manifest.yml", "manifest.json")
_SAFE_ID = re.compile(r"[^A-Za-z0-9._-]+")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
#: Frame rates a suggested fps correction snaps to.
_COMMON_FPS = (24.0, 25.0, 30.0, 48.0, 50.0, 60.0, 100.0, 120.0, 240.0)
#: Share of the estimated clips whose motion tempo leaves the prior that raises an fps warning.
_FPS_WARNING_SHARE = 0.3
#: Canonical joints of the grid's step evidence (``tempo.step_signals``): trunk and legs, and
#: the four foot points. The arms are left out (partners hold hands; see ``tempo``).
STEP_BODY_JOINTS = tuple(
    j for j in MAIN_JOINTS if j.rsplit("_", 1)[-1] not in ("shoulder", "elbow", "wrist")
)
STEP_FOOT_JOINTS = ("left_ankle", "left_toe", "right_ankle", "right_toe")


def step_evidence(
    skeleton: Skeleton,
    positions: np.ndarray,
    world: np.ndarray,
    fps: float,
    main_joints: tuple[str, ...] = MAIN_JOINTS,
    kinematic_beats_fn: Callable[[np.ndarray, float], np.ndarray] = kinematic_beats,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The importer's evidence of a take's beat: its kinematic beats ``(K,)`` s (of the
    ``main_joints``) and ``tempo.step_signals`` ``(F, 5)`` (None under 2 s), from world
    ``positions (F, J, 3)`` and rotations ``world (F, J, 4)`` at ``fps``. One function for the
    import and for a rendered dance read back as a take (``metrics.naturalness``)."""
    main = canonical_positions(skeleton, positions, world, main_joints)
    kb = np.asarray(kinematic_beats_fn(main, fps), dtype=float)
    if positions.shape[0] < 2.0 * fps:
        return kb, None
    index = {k: i for i, k in enumerate(main_joints)}
    signals = tempo_mod.step_signals(
        main[:, [index[k] for k in STEP_BODY_JOINTS]],
        main[:, [index[k] for k in STEP_FOOT_JOINTS]],
        kb,
        fps,
    )
    return kb, signals


ProgressFn = Callable[[int, int, str], None]
#: dataset.json keys the version hash covers (with the clip arrays).
_CONTENT_KEYS = (
    "format",
    "licence",
    "acknowledgement",
    "fps_override",
    "scale",
    "skeleton",
    "clips",
    "bars",
)


# --------------------------------------------------------------------------------------------
# Manifest
# --------------------------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _check_range(v: list[float] | None) -> list[float] | None:
    if v is not None and (len(v) != 2 or not 0 < v[0] < v[1]):
        raise ValueError("a tempo range is [lo, hi] BPM with 0 < lo < hi")
    return v


def _check_roles(v: dict[str, str] | None) -> dict[str, str] | None:
    """A role map (role → joint name) with known roles only (``rig.check_mapping``)."""
    if v is not None:
        try:
            check_mapping(v)
        except RigError as exc:
            raise ValueError(exc.message) from None
    return v


class ClipManifest(_Strict):
    """Per-clip manifest entry (see the module docstring)."""

    file: str | None = None
    style: str | None = None
    fps: float | None = Field(default=None, gt=0, le=10000)
    scale: float | None = Field(default=None, gt=0)
    tempo_prior_bpm: list[float] | None = None
    tempo_bpm: float | None = Field(default=None, gt=0, le=1000)
    first_downbeat_s: float | None = Field(default=None, ge=0)
    beats: list[float] | None = None
    downbeats: list[float] | None = None
    bars: list[list[float]] | None = None
    signatures: list[str] | None = None
    audio: str | None = None
    audio_offset_s: float | None = Field(default=None, ge=-3600, le=3600)
    roles: dict[str, str] | None = None
    exclude: bool = False
    reason: str | None = None
    flags: list[str] = Field(default_factory=list)

    _range = field_validator("tempo_prior_bpm")(_check_range)
    _roles = field_validator("roles")(_check_roles)

    @field_validator("bars")
    @classmethod
    def _bars_have_five(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is not None and any(len(b) != 5 for b in v):
            raise ValueError("each bar is 5 times: its 4 beats and the next downbeat")
        return v

    @field_validator("signatures")
    @classmethod
    def _signatures_valid(cls, v: list[str] | None) -> list[str] | None:
        if v is not None:
            for s in v:
                sig.to_bits(s)
        return v

    @field_validator("beats", "downbeats")
    @classmethod
    def _increasing(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and (np.any(np.diff(v) <= 0) or not np.all(np.isfinite(v))):
            raise ValueError("times must be finite and strictly increasing")
        return v


class Manifest(_Strict):
    """Dataset manifest (see the module docstring)."""

    name: str | None = None
    licence: str | None = None
    acknowledgement: str | None = None
    source: str | None = None
    description: str | None = None
    files: str | None = None
    skeleton: str | None = None
    roles: dict[str, str] | None = None
    audio_offset_s: float = Field(default=0.0, ge=-3600, le=3600)
    strip_suffix: str | None = None
    fps: float | None = Field(default=None, gt=0, le=10000)
    fps_reason: str | None = None
    scale: float = Field(default=1.0, gt=0)
    style: str | None = None
    tempo_prior_bpm: list[float] | None = None
    style_tempo_bpm: list[float] | None = None
    tempo_bpm: float | None = Field(default=None, gt=0, le=1000)
    first_downbeat_s: float | None = Field(default=None, ge=0)
    steady_beat: bool = True
    flags: list[str] = Field(default_factory=list)
    partners: list[list[str]] = Field(default_factory=list)
    clips: dict[str, ClipManifest] = Field(default_factory=dict)

    _range = field_validator("tempo_prior_bpm", "style_tempo_bpm")(_check_range)
    _roles = field_validator("roles")(_check_roles)

    @field_validator("partners")
    @classmethod
    def _pairs(cls, v: list[list[str]]) -> list[list[str]]:
        for pair in v:
            if len(pair) != 2 or pair[0] == pair[1]:
                raise ValueError("each partner entry is a pair of two different clip ids")
        return v


def load_manifest(path: str | Path) -> dict:
    """Read a manifest file (YAML or JSON) into a dict; ``manifest_invalid`` if unreadable."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DanceGraphError(
            f"{path}: cannot read the manifest ({exc})", code="manifest_invalid", field=str(path)
        ) from None
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise DanceGraphError(
            f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'YAML'}: {exc}",
            code="manifest_invalid",
            field=str(path),
        ) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise DanceGraphError(
            f"{path}: a manifest is a mapping of keys", code="manifest_invalid", field=str(path)
        )
    return data


def parse_manifest(data: dict | Manifest | None) -> Manifest:
    """Validate a manifest dict; errors name the offending field (``manifest_invalid``)."""
    if isinstance(data, Manifest):
        return data
    try:
        return Manifest.model_validate(data or {})
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        raise DanceGraphError(
            f"manifest field {where!r}: {err['msg']}", code="manifest_invalid", field=where
        ) from None


# --------------------------------------------------------------------------------------------
# Dataset records
# --------------------------------------------------------------------------------------------


@dataclass
class ClipInfo:
    """One imported take.

    ``beat_source``: ``annotation`` | ``kinematic`` | ``manifest_tempo``. ``tempo_bpm`` is the
    tempo the bars were cut at (of the longest section where the tempo changes);
    ``motion_tempo_bpm`` the prior-free frame-rate check (NaN where not measured);
    ``sections``: the stretches of steady tempo of a grid read from the motion
    (``tempo.Section.to_dict``: start_s, end_s, tempo_bpm, confidence, downbeat_clarity),
    empty for annotated and fixed grids. ``header_fps`` is the file's own rate, ``fps`` the
    one used. ``source_format``: bvh | glb | fbx; ``source_joints``: the take's own skeleton's
    joints; ``retarget``: empty for a take on the library's skeleton, else the retargeter's
    checks (``from_joints``, ``foot_sliding_m_s``, ``direction_error_deg``, ``cpu_seconds``).
    ``audio_offset_s``: the audio's time at the take's first frame (music takes);
    ``grid_check``: for a grid from music, how the motion's own estimate agrees with it
    (``tempo.partner_agreement``'s numbers, ``motion_tempo_bpm`` and ``agree``); empty
    otherwise.
    """

    id: str
    file: str
    fps: float
    n_frames: int
    tempo_bpm: float
    tempo_confidence: float
    beat_source: str
    flags: list[str]
    style: str
    header_fps: float = 0.0
    scale: float = 1.0
    duration_s: float = 0.0
    motion_tempo_bpm: float = float("nan")
    n_bars: int = 0
    grid_fit: float = 0.0
    sections: list[dict] = field(default_factory=list)
    audio: str | None = None
    source_format: str = "bvh"
    source_joints: int = 0
    retarget: dict = field(default_factory=dict)
    audio_offset_s: float | None = None
    grid_check: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("motion_tempo_bpm", "tempo_bpm", "tempo_confidence", "grid_fit"):
            if isinstance(d[k], float) and not math.isfinite(d[k]):
                d[k] = None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ClipInfo:
        d = dict(d)
        for k in ("motion_tempo_bpm", "tempo_bpm", "tempo_confidence", "grid_fit"):
            if d.get(k) is None:
                d[k] = float("nan")
        return cls(**d)


@dataclass
class BarInfo:
    """One 4-beat bar of a clip: a graph node's motion.

    ``end_frame`` is exclusive; ``beat_times``: the 4 beats and the next downbeat (s, clip
    time); ``signature``: the nearest common rhythm signature; ``signature_raw``: the label
    read from the kinematic beats (or the annotation).
    """

    clip_id: str
    index: int
    start_frame: int
    end_frame: int
    start_s: float
    end_s: float
    beat_times: np.ndarray
    signature: str
    style: str
    signature_raw: str = ""

    @property
    def node_id(self) -> str:
        return f"{self.clip_id}:{self.index}"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["beat_times"] = [round(float(t), 6) for t in self.beat_times]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> BarInfo:
        d = dict(d)
        d["beat_times"] = np.asarray(d["beat_times"], dtype=float)
        return cls(**d)


@dataclass
class ImportReport:
    """What an import did: per-clip rows, failures (file, code, message), warnings, and the
    agreement of the manifest's partner takes (``partner_rows``)."""

    name: str
    version: str
    clips: list[ClipInfo]
    failed: list[dict]
    excluded: list[dict]
    warnings: list[str]
    n_bars: int
    signature_counts: dict[str, int]
    elapsed_s: float
    partners: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "version": self.version,
            "n_clips": len(self.clips),
            "n_bars": self.n_bars,
            "elapsed_s": round(self.elapsed_s, 3),
            "clips": [
                {
                    "id": c.id,
                    "file": c.file,
                    "fps": c.fps,
                    "header_fps": c.header_fps,
                    "duration_s": round(c.duration_s, 3),
                    "tempo_bpm": _round(c.tempo_bpm, 1),
                    "motion_tempo_bpm": _round(c.motion_tempo_bpm, 1),
                    "tempo_confidence": _round(c.tempo_confidence, 2),
                    "beat_source": c.beat_source,
                    "bars": c.n_bars,
                    "style": c.style,
                    "flags": c.flags,
                    "source_format": c.source_format,
                    "source_joints": c.source_joints,
                    "retarget": c.retarget,
                    "audio_offset_s": c.audio_offset_s,
                    "grid_check": c.grid_check,
                }
                for c in self.clips
            ],
            "failed": self.failed,
            "excluded": self.excluded,
            "warnings": self.warnings,
            "signature_counts": self.signature_counts,
            "partners": self.partners,
        }

    def table(self) -> str:
        """A plain-text table of the clips, then failures and warnings."""
        head = f"{'clip':<14}{'fps':>6}{'hdr':>6}{'dur s':>8}{'tempo':>8}{'motion':>8}{'conf':>6}  {'source':<15}{'bars':>5}  {'style':<10}flags"
        lines = [f"dataset {self.name}  version {self.version[:12]}", head, "-" * len(head)]
        for c in self.clips:
            lines.append(
                f"{c.id:<14}{c.fps:>6.0f}{c.header_fps:>6.0f}{c.duration_s:>8.1f}"
                f"{_fmt(c.tempo_bpm):>8}{_fmt(c.motion_tempo_bpm):>8}{_fmt(c.tempo_confidence, 2):>6}  "
                f"{c.beat_source:<15}{c.n_bars:>5}  {c.style:<10}{','.join(c.flags)}"
            )
        lines.append(
            f"{len(self.clips)} clips, {self.n_bars} bars, {len(self.failed)} failed, "
            f"{len(self.excluded)} excluded, {self.elapsed_s:.1f} s"
        )
        for f in self.failed:
            lines.append(f"FAILED {f['file']}: [{f['code']}] {f['error']}")
        for e in self.excluded:
            lines.append(f"excluded {e['file']}: {e.get('reason') or 'manifest'}")
        for p in self.partners:
            pair = "/".join(p["pair"])
            if p.get("missing"):
                lines.append(f"partners {pair}: not compared ({', '.join(p['missing'])} absent)")
                continue
            lines.append(
                f"partners {pair}: tempo {_fmt(p['tempo_bpm'][0])}/{_fmt(p['tempo_bpm'][1])} BPM"
                f" ({_fmt(p['tempo_diff_pct'], 2)} %), median beat offset"
                f" {_fmt(p['median_offset_ms'], 0)} ms, downbeats agree"
                f" {_fmt(100 * p['downbeat_agreement'], 0)} % (else {p['downbeat_shift_beats']}"
                f" beats apart): {'agree' if p['agree'] else 'DISAGREE'}"
            )
        lines.extend(check_line(c) for c in self.clips if c.grid_check)
        for w in self.warnings:
            lines.append(f"WARNING {w}")
        return "\n".join(lines)


def check_line(c: ClipInfo) -> str:
    """One line: how a music take's grid and its motion's own estimate agree."""
    g = c.grid_check
    share = g["downbeat_agreement"]
    return (
        f"music/motion {c.id}: tempo {_fmt(g['music_tempo_bpm'])}/{_fmt(g['motion_tempo_bpm'])} BPM"
        f" ({_fmt(g['tempo_diff_pct'], 2)} %), median beat offset"
        f" {_fmt(g['median_offset_ms'], 0)} ms, downbeats agree"
        f" {_fmt(100 * share if share is not None else float('nan'), 0)} %"
        f" (else {g['downbeat_shift_beats']} beats apart): {'agree' if g['agree'] else 'DISAGREE'}"
    )


#: Partner takes agree when their tempi are this close (%) ...
PARTNER_TEMPO_PCT = 1.0
#: ... and the median offset between their beats is at most this (ms).
PARTNER_OFFSET_MS = 40.0


def partner_rows(pairs: list[list[str]], grids: dict[str, tuple]) -> list[dict]:
    """Agreement rows of partner ``pairs`` from ``grids``: clip id → (beats, bar starts, tempo).

    Each row: ``pair``, ``tempo_bpm`` (both), ``tempo.partner_agreement``'s numbers and
    ``agree`` (tempo within ``PARTNER_TEMPO_PCT`` and median offset within
    ``PARTNER_OFFSET_MS``); a pair with a clip absent from ``grids`` gets ``missing``.
    """
    rows: list[dict[str, object]] = []
    for a, b in pairs:
        missing = [c for c in (a, b) if c not in grids]
        if missing:
            rows.append({"pair": [a, b], "missing": missing})
            continue
        (ba, da, ta), (bb, db, tb) = grids[a], grids[b]
        row = tempo_mod.partner_agreement(ba, da, ta, bb, db, tb)
        row = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}
        agree = row["tempo_diff_pct"] <= PARTNER_TEMPO_PCT and (
            row["median_offset_ms"] <= PARTNER_OFFSET_MS
        )
        rows.append(
            {"pair": [a, b], "tempo_bpm": [round(ta, 3), round(tb, 3)], **row, "agree": bool(agree)}
        )
    return rows


def _round(x: float, n: int) -> float | None:
    return round(float(x), n) if x is not None and math.isfinite(x) else None


def _fmt(x: float, n: int = 1) -> str:
    return f"{x:.{n}f}" if x is not None and math.isfinite(x) else "-"


@dataclass
class Dataset:
    """A stored dataset: clips, bars (graph nodes ``"<clip_id>:<bar index>"``) and motions."""

    name: str
    version: str
    licence: str | None
    skeleton: Skeleton
    clips: list[ClipInfo]
    bars: list[BarInfo]
    store: ObjectStore
    meta: dict = field(default_factory=dict)
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self._clips = {c.id: c for c in self.clips}
        self._bars = {b.node_id: b for b in self.bars}

    def clip(self, clip_id: str) -> ClipInfo:
        try:
            return self._clips[clip_id]
        except KeyError:
            raise NotFoundError(
                f"dataset {self.name!r} has no clip {clip_id!r}", code="unknown_clip", field="clip"
            ) from None

    def bar(self, node_id: str) -> BarInfo:
        try:
            return self._bars[node_id]
        except KeyError:
            raise NotFoundError(
                f"dataset {self.name!r} has no node {node_id!r}", code="unknown_node", field="node"
            ) from None

    def node_ids(self) -> list[str]:
        return [b.node_id for b in self.bars]

    def _arrays(self, clip_id: str) -> dict[str, np.ndarray]:
        self.clip(clip_id)
        if clip_id not in self._cache:
            key = f"{self.meta['data_prefix']}/clips/{clip_id}.npz"
            try:
                with np.load(io.BytesIO(self.store.get_bytes(key))) as z:
                    self._cache[clip_id] = {k: z[k] for k in z.files}
            except (OSError, ValueError, KeyError) as exc:
                raise DanceGraphError(
                    f"dataset {self.name!r}: clip {clip_id!r} data unreadable ({exc})",
                    code="dataset_corrupt",
                    field=key,
                ) from None
        return self._cache[clip_id]

    def motion(self, clip_id: str) -> Motion:
        """The clip's motion (float64), loaded once and cached: shared, copy before changing it."""
        key = ("motion", clip_id)
        if key not in self._cache:
            a = self._arrays(clip_id)
            self._cache[key] = Motion(
                self.skeleton,
                self.clip(clip_id).fps,
                a["root_positions"].astype(float),
                a["rotations"].astype(float),
            )
        return self._cache[key]

    def bar_motion(self, node_id: str) -> Motion:
        """The frames ``[start_frame, end_frame)`` of a bar."""
        b = self.bar(node_id)
        return self.motion(b.clip_id).slice(b.start_frame, b.end_frame)

    def beats(self, clip_id: str) -> np.ndarray:
        """``(N,)`` beat times (s) of the clip's grid."""
        return self._arrays(clip_id)["beats"].astype(float)

    def kinematic_beats(self, clip_id: str) -> np.ndarray:
        """``(K,)`` kinematic beat times (s) of the clip."""
        return self._arrays(clip_id)["kinematic_beats"].astype(float)


# --------------------------------------------------------------------------------------------
# Import
# --------------------------------------------------------------------------------------------


def _clip_id(stem: str, strip_suffix: str | None) -> str:
    if strip_suffix and stem.endswith(strip_suffix) and len(stem) > len(strip_suffix):
        stem = stem[: -len(strip_suffix)]
    cid = _SAFE_ID.sub("_", stem).lstrip("._-")
    return cid or "clip"


def _motion_joints(skeleton: Skeleton, path: str) -> tuple[int, tuple[int, int], tuple[int, int]]:
    """Root, (left, right) ankle and (left, right) wrist joint indices for the tempo signals."""
    need = ("hips", "left_ankle", "right_ankle", "left_wrist", "right_wrist")
    missing = [k for k in need if k not in skeleton.canonical]
    if missing:
        raise MotionFileError(
            f"cannot find the joints {', '.join(missing)} by name (hips, feet and hands are "
            "needed for the kinematic tempo)",
            path=path,
            code="skeleton_unmapped",
        )
    ix = {k: skeleton.index(skeleton.canonical[k]) for k in need}
    return (
        ix["hips"],
        (ix["left_ankle"], ix["right_ankle"]),
        (ix["left_wrist"], ix["right_wrist"]),
    )


def _annotation_bars(cm: ClipManifest, fps: float) -> np.ndarray | None:
    """``(B, 5)`` bars from a clip's beat/bar annotations, or None when it has none."""
    if cm.bars is not None:
        return np.asarray(cm.bars, dtype=float).reshape(-1, 5)
    if cm.beats is None:
        return None
    beats = np.asarray(cm.beats, dtype=float)
    if cm.downbeats is None:
        return tempo_mod.bars_from_beats(beats, 0)
    tol = 1.5 / fps
    rows = []
    for d in cm.downbeats:
        i = int(np.argmin(np.abs(beats - d)))
        if abs(beats[i] - d) > tol:
            raise ValueError(f"downbeat {d} s is not one of the annotated beats")
        if i + 4 < len(beats):
            rows.append(beats[i : i + 5])
    return np.stack(rows) if rows else np.zeros((0, 5))


def _bpm_range(bpm: Sequence[float] | None) -> tuple[float, float] | None:
    """A manifest's ``[low, high]`` tempo prior as a pair (None when not given)."""
    return (float(bpm[0]), float(bpm[1])) if bpm else None


def _fps_warning(rows: list[ClipInfo], prior: tuple[float, float] | None) -> str | None:
    """A warning when many clips move much faster (or slower) than the tempo prior allows."""
    est = [c for c in rows if c.beat_source == "kinematic" and math.isfinite(c.motion_tempo_bpm)]
    flagged = [c for c in est if "tempo_outside_prior" in c.flags]
    if not est or len(flagged) < max(2, _FPS_WARNING_SHARE * len(est)):
        return None
    lo, hi = prior or tempo_mod.DEFAULT_PRIOR_BPM
    motion = float(np.median([c.motion_tempo_bpm for c in flagged]))
    ratio = motion / math.sqrt(lo * hi)
    fps = float(np.median([c.fps for c in flagged]))
    suggest = min(_COMMON_FPS, key=lambda f: abs(math.log(f / (fps / ratio))))
    return (
        f"{len(flagged)} of {len(est)} clips move about {ratio:.1f}x faster than the tempo prior "
        f"{lo:.0f}-{hi:.0f} BPM (median motion tempo {motion:.0f} BPM at {fps:.0f} fps): is the "
        f"frame rate right? At {suggest:.0f} fps these clips would move at about "
        f"{motion * suggest / fps:.0f} BPM. Set 'fps' in the manifest if the files' header is wrong."
    )


def _find_files(src: Path, pattern: str | None) -> list[Path]:
    """Files matching ``pattern`` inside ``src`` (a pattern cannot reach outside it); without
    a pattern every file with a take suffix (``TAKE_SUFFIXES``)."""
    root = _norm(src)
    try:
        found = list(src.glob(pattern or "*"))
    except (ValueError, NotImplementedError) as exc:
        raise DanceGraphError(
            f"manifest 'files': bad pattern {pattern!r} ({exc})",
            code="manifest_invalid",
            field="files",
        ) from None
    return sorted(
        p
        for p in found
        if p.is_file()
        and not p.name.startswith(".")
        and _norm(p).is_relative_to(root)
        and (pattern or p.suffix.lower() in TAKE_SUFFIXES)
    )


def _norm(path: Path) -> Path:
    """Absolute, with ``..`` resolved lexically (symlinked files inside a folder stay inside)."""
    return Path(os.path.normpath(path.absolute()))


def _local(message: str, src: Path) -> str:
    """An error message with the import folder's path left out (reports name files only)."""
    return message.replace(str(src) + "/", "").replace(str(src.resolve()) + "/", "")


def _clip_manifest(m: Manifest, cid: str, path: Path) -> ClipManifest:
    """The manifest entry of a clip: by id, by file name or by file stem."""
    for key in (cid, path.name, path.stem):
        if key in m.clips:
            return m.clips[key]
    return ClipManifest()


def _npz_bytes(**arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)  # type: ignore[arg-type]  # numpy's stub reads **kwds as allow_pickle
    return buf.getvalue()


def _inside(src: Path, rel: str, field_name: str) -> Path:
    """``src / rel``, refused (``manifest_invalid``) when it lies outside ``src``."""
    path = _norm(src / rel)
    if not path.is_relative_to(_norm(src)):
        raise DanceGraphError(
            f"{rel!r} lies outside the import folder", code="manifest_invalid", field=field_name
        )
    return path


def _audio_path(src: Path, cm: ClipManifest, cid: str) -> Path | None:
    """The take's music file, or None; ``manifest_file_missing`` when the manifest names an
    absent one."""
    if not cm.audio:
        return None
    path = _inside(src, cm.audio, f"clips.{cid}.audio")
    if not path.is_file():
        raise DanceGraphError(
            f"the manifest names the audio {cm.audio!r}, which is not in the upload",
            code="manifest_file_missing",
            field=f"clips.{cid}.audio",
        )
    return path


def _library_source(src: Path, m: Manifest, files: list[Path]) -> tuple[_Library, list[Path]]:
    """The library's skeleton source (``skeleton``: a rig file in the folder, or a take) and the
    takes in import order (the skeleton's take first, the rig file left out). Raises
    ``manifest_file_missing`` (naming neither), ``skeleton_source_invalid`` (unreadable rig)."""
    from dancegraph.motion.rig import load_rig

    if not m.skeleton:
        return _Library(), files
    path = _inside(src, m.skeleton, "skeleton")
    if path.is_file():
        try:
            rig = load_rig(path, mapping=m.roles)
        except RigError as exc:
            raise DanceGraphError(
                f"skeleton {m.skeleton!r}: {exc.message}",
                code="skeleton_source_invalid",
                field="skeleton",
            ) from None
        rest = [f for f in files if _norm(f) != path]
        rig.skeleton.canonical = _canonical(rig.skeleton, rig.roles, bool(m.roles))
        return _Library(rig.skeleton, rig.roles, rig, f"rig:{path.name}"), rest
    first = [f for f in files if m.skeleton in (f.name, f.stem, _clip_id(f.stem, m.strip_suffix))]
    if not first:
        raise DanceGraphError(
            f"skeleton {m.skeleton!r} is neither a rig file nor a take of the upload",
            code="manifest_file_missing",
            field="skeleton",
        )
    return _Library(), first[:1] + [f for f in files if f != first[0]]


def _absent_files(src: Path, m: Manifest) -> list[dict]:
    """Failure rows of manifest clip entries whose ``file`` is not in the folder."""
    return [
        {
            "file": cm.file,
            "id": key,
            "code": "manifest_file_missing",
            "error": f"the manifest names the take {cm.file!r}, which is not in the upload",
        }
        for key, cm in m.clips.items()
        if cm.file and not cm.exclude and not _inside(src, cm.file, f"clips.{key}.file").is_file()
    ]


@dataclass
class _Takes:
    """What the import has gathered so far (per-take rows, bars, failures, ...)."""

    rows: list[ClipInfo] = field(default_factory=list)
    bars: list[BarInfo] = field(default_factory=list)
    failed: list[dict] = field(default_factory=list)
    excluded: list[dict] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    digests: list[str] = field(default_factory=list)
    grids: dict[str, tuple] = field(default_factory=dict)


def _import_take(
    src: Path,
    path: Path,
    m: Manifest,
    lib: _Library,
    store: ObjectStore,
    data_prefix: str,
    got: _Takes,
) -> None:
    """Import one take into ``got`` (its data under ``data_prefix``), or record its failure."""
    cid = _clip_id(path.stem, m.strip_suffix)
    cm = _clip_manifest(m, cid, path)
    try:
        if cm.exclude:
            got.excluded.append({"file": path.name, "id": cid, "reason": cm.reason})
            return
        if any(r.id == cid for r in got.rows):
            raise DanceGraphError(
                f"clip id {cid!r} is already used by another file", code="duplicate_clip_id"
            )
        audio = _audio_path(src, cm, cid)
        row, clip_bars, arrays = _import_clip(
            path, cid, cm, m, lib, audio, MAIN_JOINTS, kinematic_beats
        )
        if audio is not None:
            row.audio = f"{data_prefix}/audio/{cid}{audio.suffix.lower()}"
            store.put_file(row.audio, audio)
        data = _npz_bytes(**arrays)
        store.put_bytes(f"{data_prefix}/clips/{cid}.npz", data)
        got.digests.append(cid + hashlib.sha256(data).hexdigest())
        got.rows.append(row)
        got.bars.extend(clip_bars)
        starts = np.array([b.start_s for b in clip_bars])
        got.grids[cid] = (arrays["beats"], starts, row.tempo_bpm)
    except DanceGraphError as exc:
        got.failed.append({"file": path.name, "code": exc.code, "error": _local(exc.message, src)})
    except (ValueError, OSError, MemoryError) as exc:
        got.failed.append(
            {"file": path.name, "code": "motion_file_invalid", "error": _local(str(exc), src)}
        )


def _data_prefix(prefix: str) -> str:
    """A fresh folder for one import's clip data: microsecond stamps sort by time, so cleanup
    can tell earlier imports from later ones."""
    now_ns = time.time_ns()
    stamp = (
        time.strftime("%Y%m%dT%H%M%S", time.gmtime(now_ns // 10**9))
        + f"{now_ns // 1000 % 10**6:06d}"
    )
    return f"{prefix}/data-{stamp}-{uuid.uuid4().hex[:8]}"


def import_dataset(
    src_dir: str | Path,
    name: str,
    store: ObjectStore,
    manifest: dict | Manifest | None = None,
    progress: ProgressFn | None = None,
    *,
    strict: bool = False,
) -> ImportReport:
    """Import the takes of ``src_dir`` as dataset ``name`` into ``store``.

    ``manifest``: a dict (see the module docstring) or None to use ``manifest.yaml`` (or .yml,
    .json) in ``src_dir`` when present. ``progress(done, total, file)`` is called after each file.
    ``strict``: publish nothing unless every take passes. Raises ``NotFoundError``
    (``dataset_source_not_found``) for a missing folder, ``DanceGraphError``
    ``manifest_invalid`` / ``dataset_empty`` / ``dataset_name_invalid`` /
    ``skeleton_source_invalid`` / ``skeleton_source_failed`` (the named skeleton take failed) /
    ``dataset_takes_failed`` (strict, ``errors`` lists each take); otherwise takes that fail are
    listed in the report with their code, not raised.
    """
    t0 = time.perf_counter()
    src = _source_folder(src_dir, name)
    if manifest is None:
        for mname in MANIFEST_NAMES:
            if (src / mname).is_file():
                manifest = load_manifest(src / mname)
                break
    m = parse_manifest(manifest)
    lib, files = _library_source(src, m, _find_files(src, m.files))
    if not files:
        raise DanceGraphError(
            f"{src}: no motion files matching {m.files or '*' + '/*'.join(TAKE_SUFFIXES)!r}",
            code="dataset_empty",
            field=str(src),
        )
    prefix = f"datasets/{name}"
    # Clip data goes to a fresh folder that dataset.json names; the previous import stays
    # readable until the new dataset.json replaces it, then its folder is removed.
    data_prefix = _data_prefix(prefix)
    got = _Takes(failed=_absent_files(src, m))
    for done, path in enumerate(files, start=1):
        _import_take(src, path, m, lib, store, data_prefix, got)
        if done == 1 and m.skeleton and lib.skeleton is None:
            store.delete_prefix(data_prefix)
            f = got.failed[-1]
            raise DanceGraphError(
                f"the skeleton take {f['file']} failed: [{f['code']}] {f['error']}",
                code="skeleton_source_failed",
                field="skeleton",
            )
        if progress is not None:
            progress(done, len(files), path.name)
    _refuse_failed(got, src, strict, store, data_prefix)
    return _publish(src, name, store, m, lib, got, data_prefix, t0)


def _source_folder(src_dir: str | Path, name: str) -> Path:
    """The import's folder, after checking the dataset ``name`` (``dataset_name_invalid``) and
    that the folder exists (``dataset_source_not_found``)."""
    if not _NAME.match(name):
        raise DanceGraphError(
            f"dataset name {name!r}: use letters, digits, '.', '_' or '-'",
            code="dataset_name_invalid",
            field="name",
        )
    src = Path(src_dir)
    if not src.is_dir():
        raise NotFoundError(
            f"{src}: no such folder", code="dataset_source_not_found", field=str(src)
        )
    return src


def _refuse_failed(
    got: _Takes, src: Path, strict: bool, store: ObjectStore, data_prefix: str
) -> None:
    """Raise (nothing published) when no take passed, or any failed under ``strict``."""
    if got.rows and not (strict and got.failed):
        return
    store.delete_prefix(data_prefix)
    errors = [{"field": f["file"], "code": f["code"], "message": f["error"]} for f in got.failed]
    detail = "; ".join(f"{f['file']}: [{f['code']}] {f['error']}" for f in got.failed[:5])
    if not got.rows:
        raise DanceGraphError(
            f"{src}: no clip could be imported ({len(got.failed)} failed, "
            f"{len(got.excluded)} excluded)" + (f": {detail}" if detail else ""),
            code="dataset_empty",
            field=str(src),
            errors=errors,
        )
    raise DanceGraphError(
        f"{len(got.failed)} of {len(got.failed) + len(got.rows)} takes failed, nothing was "
        f"published: {detail}",
        code="dataset_takes_failed",
        field=got.failed[0]["file"],
        errors=errors,
    )


def _publish(
    src: Path,
    name: str,
    store: ObjectStore,
    m: Manifest,
    lib: _Library,
    got: _Takes,
    data_prefix: str,
    t0: float,
) -> ImportReport:
    """Write ``dataset.json`` (the import becomes visible), drop older imports' data, report."""
    prefix = f"datasets/{name}"
    fps_warning = _fps_warning(got.rows, _bpm_range(m.tempo_prior_bpm))
    if fps_warning:
        got.warnings.append(fps_warning)
    counts = Counter(b.signature for b in got.bars)
    signature_counts = {s: counts.get(s, 0) for s in sig.COMMON_SIGNATURES}
    doc = _dataset_doc(name, m, lib, got, signature_counts)
    # The version hashes what a graph is built from, not how the import went.
    content = {k: doc[k] for k in _CONTENT_KEYS}
    body = json.dumps(content, sort_keys=True, allow_nan=False).encode()
    version = hashlib.sha256(body + "".join(sorted(got.digests)).encode()).hexdigest()
    doc["version"] = version
    doc["data_prefix"] = data_prefix
    store.put_bytes(f"{prefix}/dataset.json", json.dumps(doc, indent=1, allow_nan=False).encode())
    # Remove the data of earlier imports only (names sort by time): a concurrent, later import
    # of the same name keeps its folder.
    ours = data_prefix.split("/")[2]
    for old in {k.split("/")[2] for k in store.list(prefix)}:
        if old.startswith("data-") and old < ours:
            store.delete_prefix(f"{prefix}/{old}")
    return ImportReport(
        name=name,
        version=version,
        clips=got.rows,
        failed=got.failed,
        excluded=got.excluded,
        warnings=got.warnings,
        n_bars=len(got.bars),
        signature_counts=signature_counts,
        elapsed_s=time.perf_counter() - t0,
        partners=doc["partners"],
    )


def _dataset_doc(
    name: str, m: Manifest, lib: _Library, got: _Takes, signature_counts: dict[str, int]
) -> dict[str, Any]:
    """``dataset.json``'s content before its version and data folder are added."""
    assert lib.skeleton is not None  # set by the first imported take, and rows holds one
    return {
        "format": FORMAT_VERSION,
        "name": name,
        "licence": m.licence,
        "acknowledgement": m.acknowledgement,
        "source": m.source,
        "description": m.description,
        "fps_override": m.fps,
        "fps_reason": m.fps_reason,
        "scale": m.scale,
        "tempo_prior_bpm": m.tempo_prior_bpm,
        "style_tempo_bpm": m.style_tempo_bpm,
        "style": m.style,
        "skeleton_source": lib.source,
        "skeleton": lib.skeleton.to_dict(),
        "clips": [c.to_dict() for c in got.rows],
        "bars": [b.to_dict() for b in got.bars],
        "failed": got.failed,
        "excluded": got.excluded,
        "warnings": got.warnings,
        "signature_counts": signature_counts,
        "partners": partner_rows(m.partners, got.grids),
    }


def _import_clip(
    path: Path,
    cid: str,
    cm: ClipManifest,
    m: Manifest,
    lib: _Library,
    audio: Path | None,
    main_joints: tuple[str, ...],
    kinematic_beats_fn: Callable[[np.ndarray, float], np.ndarray],
) -> tuple[ClipInfo, list[BarInfo], dict[str, np.ndarray]]:
    """Read, put on the library's skeleton, grid, cut and label one take; raise
    DanceGraphError (a named code) on a bad take. ``audio``: the music it was danced to."""
    pname = str(path)
    scale = cm.scale or m.scale
    motion, take = _take_on_library(path, cm, m, lib)
    header_fps, fps = take["header_fps"], motion.fps
    n = motion.n_frames
    duration = n / fps
    positions, world = forward_kinematics(motion)
    root, feet, hands = _motion_joints(motion.skeleton, pname)
    kb, signals = step_evidence(
        motion.skeleton, positions, world, fps, main_joints, kinematic_beats_fn
    )

    flags = list(dict.fromkeys([*m.flags, *cm.flags]))
    style = cm.style or m.style or "unknown"
    prior = cm.tempo_prior_bpm or m.tempo_prior_bpm
    params = tempo_mod.GridParams(
        prior_bpm=(float(prior[0]), float(prior[1])) if prior else tempo_mod.DEFAULT_PRIOR_BPM
    )
    tempo_bpm = cm.tempo_bpm or m.tempo_bpm
    motion_tempo = float("nan")
    confidence = float("nan")
    sections: list[dict] = []
    try:
        ann = _annotation_bars(cm, fps)
    except ValueError as exc:
        raise DanceGraphError(
            f"{path.name}: {exc}", code="manifest_invalid", field=f"clips.{cid}"
        ) from None

    # The grid's evidence and the frame-rate check whenever the clip is long enough: the
    # motion tempo is what lets a user see a wrong frame rate, whatever the bars are cut from.
    if signals is not None:
        motion_tempo = tempo_mod.motion_tempo_bpm(
            tempo_mod.periodicity_signals(positions, fps, root=root, feet=feet, hands=hands), fps
        )
    too_fast = tempo_mod.outside_prior(motion_tempo, params.prior_bpm)

    check: dict = {}
    offset = cm.audio_offset_s if cm.audio_offset_s is not None else m.audio_offset_s
    if ann is not None:
        source = "annotation"
        bar_beats = ann
        beats = np.unique(bar_beats.ravel())
        if len(bar_beats):
            tempo_bpm = float(240.0 / np.median(bar_beats[:, 4] - bar_beats[:, 0]))
        confidence = 1.0
    elif audio is not None:
        source = "music"
        beats, bar_beats, tempo_bpm, confidence = _music_grid(audio, offset, m.style_tempo_bpm)
        if signals is not None:
            check = _grid_check(
                beats, bar_beats, tempo_bpm, tempo_mod.estimate_grid(signals, fps, params)
            )
            if not check["agree"]:
                flags.append("music_motion_disagree")
    elif tempo_bpm is not None or not m.steady_beat:
        source = "manifest_tempo"
        if tempo_bpm is None:
            raise DanceGraphError(
                f"{path.name}: 'steady_beat: false' needs a 'tempo_bpm' to cut bars",
                code="manifest_invalid",
                field="tempo_bpm",
            )
        first = cm.first_downbeat_s if cm.first_downbeat_s is not None else m.first_downbeat_s
        if m.steady_beat and first is None and signals is not None:
            # Known tempo, unknown grid: phase and downbeat from the motion.
            grid = tempo_mod.estimate_grid(signals, fps, params, tempo_bpm=tempo_bpm)
            beats, bar_beats = grid.beats, grid.bars
            sections = [sec.to_dict() for sec in grid.sections]
        else:
            beats = tempo_mod.grid_from_tempo(duration, tempo_bpm, first or 0.0)
            bar_beats = tempo_mod.bars_from_beats(beats)
        confidence = 1.0 if m.steady_beat else 0.0
        if not m.steady_beat:
            flags.append("no_steady_beat")
        elif too_fast:
            # A fixed tempo on a steady dance is only as right as the frame rate.
            flags.append("tempo_outside_prior")
    else:
        source = "kinematic"
        if signals is None:
            raise DanceGraphError(
                f"{path.name}: {duration:.2f} s is too short to estimate a tempo (2 s at least); "
                "give 'tempo_bpm' or beats in the manifest",
                code="clip_too_short",
                field=pname,
            )
        grid = tempo_mod.estimate_grid(signals, fps, params)
        beats, bar_beats = grid.beats, grid.bars
        tempo_bpm, confidence = grid.tempo_bpm, grid.confidence
        sections = [sec.to_dict() for sec in grid.sections]
        flags.extend(grid.flags)
        if too_fast:
            flags.append("tempo_outside_prior")

    bar_beats = _bars_inside(bar_beats, n, fps, cm, cid, path.name, f"{tempo_bpm} BPM, {source}")
    clip_bars = _cut_bars(cid, bar_beats, kb, cm.signatures, fps, n, style)
    fit = tempo_mod.grid_fit(kb, bar_beats)
    row = ClipInfo(
        id=cid,
        file=path.name,
        fps=fps,
        n_frames=n,
        tempo_bpm=float(tempo_bpm) if tempo_bpm is not None else float("nan"),
        tempo_confidence=float(confidence),
        beat_source=source,
        flags=list(dict.fromkeys(flags)),
        style=style,
        header_fps=float(header_fps),
        scale=float(scale),
        duration_s=float(duration),
        motion_tempo_bpm=float(motion_tempo),
        n_bars=len(clip_bars),
        grid_fit=float(fit),
        sections=sections,
        source_format=take["format"],
        source_joints=take["joints"],
        retarget=take["retarget"],
        audio_offset_s=float(offset) if audio is not None else None,
        grid_check=check,
    )
    arrays = {
        "root_positions": motion.root_positions.astype(np.float32),
        "rotations": motion.rotations.astype(np.float32),
        "beats": np.asarray(beats, dtype=float),
        "kinematic_beats": kb,
    }
    return row, clip_bars, arrays


def _bars_inside(
    bar_beats: np.ndarray, n: int, fps: float, cm: ClipManifest, cid: str, name: str, grid: str
) -> np.ndarray:
    """The bars ``(B, 5)`` s lying inside the take's ``n`` frames (an annotation or a music
    grid may run past them); ``take_under_one_bar`` when none does (``grid`` says which grid),
    ``manifest_invalid`` when the manifest's signatures do not count them."""
    last_t = (n - 1) / fps
    if len(bar_beats):
        bar_beats = bar_beats[
            (bar_beats[:, 0] >= -0.5 / fps) & (bar_beats[:, 4] <= last_t + 0.5 / fps)
        ]
    if cm.signatures is not None and len(cm.signatures) != len(bar_beats):
        raise DanceGraphError(
            f"{name}: {len(cm.signatures)} signatures for {len(bar_beats)} bars",
            code="manifest_invalid",
            field=f"clips.{cid}.signatures",
        )
    if len(bar_beats) == 0:
        raise DanceGraphError(
            f"{name}: {n / fps:.2f} s holds no whole 4-beat bar of its grid ({grid})",
            code="take_under_one_bar",
            field=name,
        )
    return bar_beats


def _cut_bars(
    cid: str,
    bar_beats: np.ndarray,
    kb: np.ndarray,
    signatures: list[str] | None,
    fps: float,
    n: int,
    style: str,
) -> list[BarInfo]:
    """The take's bars ``(B, 5)`` s as ``BarInfo``: frames ``[start, end)`` of ``n`` at
    ``fps``, each labelled with the rhythm signature of its kinematic beats ``kb`` (s) snapped
    to the nearest common one, or with the manifest's ``signatures``."""
    bits = tempo_mod.bar_signature_bits(kb, bar_beats)
    nearest = sig.nearest_common(bits) if len(bits) else np.zeros(0, dtype=int)
    out: list[BarInfo] = []
    for i, bb in enumerate(bar_beats):
        if signatures is not None:
            raw = snapped = signatures[i]
        else:
            raw = sig.to_string(bits[i])
            snapped = sig.COMMON_SIGNATURES[int(nearest[i])]
        start_f = int(np.clip(round(bb[0] * fps), 0, n - 1))
        end_f = int(np.clip(round(bb[4] * fps), start_f + 1, n))
        out.append(
            BarInfo(
                clip_id=cid,
                index=i,
                start_frame=start_f,
                end_frame=end_f,
                start_s=float(bb[0]),
                end_s=float(bb[4]),
                beat_times=np.asarray(bb, dtype=float),
                signature=snapped,
                style=style,
                signature_raw=raw,
            )
        )
    return out


def _music_grid(
    audio: Path, offset_s: float, style_range: list[float] | None
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """``(beats (N,), bar_beats (B, 5), tempo BPM, confidence)`` of the music a take was danced
    to, on the take's clock (audio time − ``offset_s``), counted at ``style_range`` where given.

    Raises ``AudioError`` (``audio_undecodable`` and the decoder's codes, ``no_beat``).
    """
    from dancegraph.music.analysis import analyze

    rng = (float(style_range[0]), float(style_range[1])) if style_range else None
    a = analyze(audio, tempo_range=rng)
    return (
        np.asarray(a.beats, dtype=float) - offset_s,
        np.asarray(a.bar_beats, dtype=float).reshape(-1, 5) - offset_s,
        float(a.tempo_bpm),
        float(a.tempo_confidence),
    )


def _grid_check(
    beats: np.ndarray, bar_beats: np.ndarray, tempo_bpm: float, motion: tempo_mod.BeatGrid
) -> dict:
    """How the motion's own grid agrees with a music grid: ``tempo.partner_agreement``'s
    numbers (music first), ``agree`` by the partner thresholds (``PARTNER_TEMPO_PCT``,
    ``PARTNER_OFFSET_MS``, and downbeats agreeing on at least half the bars)."""
    row = tempo_mod.partner_agreement(
        beats, bar_beats[:, 0], tempo_bpm, motion.beats, motion.bars[:, 0], motion.tempo_bpm
    )
    agree = (
        row["tempo_diff_pct"] <= PARTNER_TEMPO_PCT
        and row["median_offset_ms"] <= PARTNER_OFFSET_MS
        and row["downbeat_agreement"] >= 0.5
    )
    row = {k: (_round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}
    tempi = {
        "music_tempo_bpm": _round(tempo_bpm, 2),
        "motion_tempo_bpm": _round(motion.tempo_bpm, 2),
    }
    return {**row, **tempi, "agree": bool(agree)}


# --------------------------------------------------------------------------------------------
# Takes on the library's skeleton
# --------------------------------------------------------------------------------------------

#: File suffixes read as takes (the default of the manifest's ``files``).
TAKE_SUFFIXES = (".bvh", ".glb", ".gltf", ".fbx")


@dataclass
class _Library:
    """The library's skeleton, its roles and the rig other takes are retargeted onto (set by
    the manifest's ``skeleton`` rig file, else by the first take imported; a take's rig is
    built when the first take on another skeleton comes); ``header_fps``: the frame rate of
    the first take without a declared fps (``fps_mixed`` for another)."""

    skeleton: Skeleton | None = None
    roles: RoleMap | None = None
    rig: Rig | None = None
    source: str | None = None
    header_fps: float | None = None


def _rest(skeleton: Skeleton) -> np.ndarray:
    """``(J, 3)`` rest-pose joint positions (m): forward kinematics of no rotation, the root at
    its offset."""
    still = quat.identity((1, skeleton.n_joints))
    return fk_arrays(skeleton, skeleton.offsets[:1], still)[0][0]


def _take_roles(skeleton: Skeleton, mapping: dict[str, str] | None, name: str) -> RoleMap:
    """The humanoid roles of a take's skeleton (``mapping``, names, then structure);
    ``MotionFileError`` ``skeleton_unmapped`` where the required ones are not found. The
    skeleton's canonical joints are set (``_canonical``)."""
    try:
        roles = map_roles(skeleton.names, skeleton.parents, _rest(skeleton), mapping)
    except RigError as exc:
        raise _unmapped(exc.message, name) from None
    missing = [r for r in REQUIRED_ROLES if r not in roles.roles]
    if missing:
        raise _unmapped(f"no joint for {', '.join(missing)}", name)
    skeleton.canonical = _canonical(skeleton, roles, bool(mapping))
    return roles


def _canonical(skeleton: Skeleton, roles: RoleMap, mapped: bool) -> dict[str, str]:
    """The canonical joints of the import's features: by name (``find_canonical``), the gaps
    filled from the roles (which win where the user ``mapped`` them); a missing chest is the
    upper chest or the spine, a missing toe the ankle."""
    canon = dict(find_canonical(skeleton.names))
    for k in CANONICAL_JOINTS:
        if k in roles.roles and (mapped or k not in canon):
            canon[k] = roles.roles[k]
    canon.setdefault("chest", roles.roles.get("upper_chest") or canon["spine"])
    for side in ("left", "right"):
        canon.setdefault(f"{side}_toe", canon[f"{side}_ankle"])
    return canon


def _unmapped(why: str, name: str) -> MotionFileError:
    """A take whose skeleton shows no humanoid body: ``skeleton_unmapped``."""
    return MotionFileError(
        f"no humanoid body found ({why}); name its joints in the manifest's 'roles' "
        "(role -> joint name)",
        path=name,
        code="skeleton_unmapped",
    )


def _library_rig(lib: _Library) -> Rig:
    """The rig of the library's skeleton at rest, standing on the floor (y = 0, so that
    retargeted takes stand where the library's own takes do), built once;
    ``skeleton_source_invalid`` when it cannot be a retarget target (e.g. a bone of no
    length)."""
    if lib.rig is None:
        assert lib.skeleton is not None and lib.roles is not None
        sk = lib.skeleton
        mats = np.tile(np.eye(4), (sk.n_joints, 1, 1))
        mats[:, :3, 3] = _rest(sk)
        user = {r: n for r, n in lib.roles.roles.items() if lib.roles.how[r] == "user"}
        ends = {sk.names[j]: v for j, v in sk.end_sites.items()}
        try:
            for _ in range(2):  # the second time with the rest pose standing on the floor
                lib.rig = build_rig(
                    sk.names,
                    sk.parents,
                    mats,
                    mapping=user,
                    source={"format": "bvh"},
                    end_sites=ends,
                )
                mats[:, 1, 3] -= lib.rig.floor
        except RigError as exc:
            raise DanceGraphError(
                f"the library's skeleton ({lib.source}) cannot take retargeted takes: "
                f"{exc.message}; name another take or a rig file in 'skeleton'",
                code="skeleton_source_invalid",
                field="skeleton",
            ) from None
    assert lib.rig is not None
    return lib.rig


def _take_mapping(names: list[str], cm: ClipManifest, m: Manifest) -> dict[str, str] | None:
    """The role map of a take: its own, else the library's where the take has all its joints."""
    if cm.roles is not None:
        return cm.roles
    if m.roles and set(m.roles.values()) <= set(names):
        return m.roles
    return None


def _read_take(
    path: Path, cm: ClipManifest, m: Manifest
) -> tuple[Motion, RoleMap, Rig | None, float]:
    """``(motion in metres at the declared or the file's fps, its roles, its rig where the
    file is one (GLB), the file's own fps)``."""
    suffix = path.suffix.lower()
    declared = cm.fps or m.fps
    rig = None
    if suffix == ".bvh":
        motion = read_bvh(path, scale=float(cm.scale or m.scale))
        roles = _take_roles(motion.skeleton, _take_mapping(motion.skeleton.names, cm, m), path.name)
    elif suffix in (".glb", ".gltf", ".fbx"):  # ufbx and glTF read metres: no scale
        from dancegraph.motion.fbx_anim import read_fbx_motion
        from dancegraph.motion.gltf_anim import read_gltf_motion

        read = read_fbx_motion if suffix == ".fbx" else read_gltf_motion
        try:
            motion, rig = read(path, fps=declared, mapping=cm.roles or m.roles)
        except RigError as exc:
            if exc.code in ("rig_missing_roles", "rig_disconnected", "rig_map_invalid"):
                raise _unmapped(exc.message, path.name) from None
            raise MotionFileError(exc.message, path=path.name, code=exc.code) from None
        roles = rig.roles
    else:
        raise MotionFileError(
            f"a take is a BVH, GLB/glTF or FBX file, not {suffix or 'a file without suffix'}",
            path=path.name,
            code="take_format_unsupported",
        )
    header = motion.fps
    fps = float(declared or header)
    return Motion(motion.skeleton, fps, motion.root_positions, motion.rotations), roles, rig, header


def _check_fps(header: float, declared: bool, lib: _Library, name: str) -> None:
    """``fps_mixed`` for a take at another frame rate than the library's, none declared."""
    if declared:
        return
    if lib.header_fps is not None and abs(header - lib.header_fps) > 1e-3 * header:
        raise MotionFileError(
            f"{header:g} fps, the library's takes {lib.header_fps:g} fps: declare the "
            "take's 'fps' in the manifest",
            path=name,
            code="fps_mixed",
        )
    lib.header_fps = lib.header_fps or header


def _same_body(a: Skeleton, b: Skeleton) -> bool:
    """Same joints, hierarchy and bone offsets (to 0.1 mm): one body, whatever the file's
    channel layout or end sites."""
    return (
        a.names == b.names
        and np.array_equal(a.parents, b.parents)
        and np.allclose(a.offsets[1:], b.offsets[1:], rtol=0, atol=1e-4)
    )


def _take_on_library(
    path: Path, cm: ClipManifest, m: Manifest, lib: _Library
) -> tuple[Motion, dict]:
    """A take read and put on the library's skeleton (retargeted when on another one).

    Returns the motion and ``{format, joints, header_fps, retarget}`` (``retarget`` empty for a
    take already on the library's skeleton). Sets ``lib`` from the first take when unset.
    """
    from dancegraph.motion.retarget import plan_retarget, retarget

    motion, roles, rig, header = _read_take(path, cm, m)
    _check_fps(header, bool(cm.fps or m.fps), lib, path.name)
    take = {
        "format": path.suffix.lower().lstrip(".").replace("gltf", "glb"),
        "joints": motion.skeleton.n_joints,
        "header_fps": float(header),
        "retarget": {},
    }
    if lib.skeleton is None:
        lib.skeleton, lib.roles, lib.rig = motion.skeleton, roles, rig
        lib.source = f"take:{path.name}"
        return motion, take
    if _same_body(motion.skeleton, lib.skeleton):
        return Motion(lib.skeleton, motion.fps, motion.root_positions, motion.rotations), take
    target = _library_rig(lib)
    out, report = retarget(motion, target, plan=plan_retarget(motion.skeleton, target, roles))
    order = [target.skeleton.index(nm) for nm in lib.skeleton.names]
    take["retarget"] = {
        "from_joints": motion.skeleton.n_joints,
        "foot_sliding_m_s": _round(report["sliding_m_s"], 4),
        "direction_error_deg": _round(report["direction_error_deg"]["median"], 2),
        "cpu_seconds": report["cpu_seconds"],
    }
    on_lib = Motion(lib.skeleton, motion.fps, out.root_positions, out.rotations[:, order])
    return on_lib, take


# --------------------------------------------------------------------------------------------
# Loading and listing
# --------------------------------------------------------------------------------------------


def load_dataset(store: ObjectStore, name: str) -> Dataset:
    """The dataset ``name`` from ``store``; ``NotFoundError`` (``unknown_dataset``) if absent."""
    if not _NAME.match(name):
        raise NotFoundError(f"no dataset {name!r}", code="unknown_dataset", field="dataset")
    key = f"datasets/{name}/dataset.json"
    if not store.exists(key):
        raise NotFoundError(f"no dataset {name!r}", code="unknown_dataset", field="dataset")
    try:
        doc = json.loads(store.get_bytes(key))
        if isinstance(doc.get("format"), int) and doc["format"] < FORMAT_VERSION:
            raise DanceGraphError(
                f"dataset {name!r} was imported by an older DanceGraph (format {doc['format']},"
                f" this one reads {FORMAT_VERSION}: sub-frame beat grids); import it again",
                code="dataset_format_old",
                field=key,
            )
        if doc.get("format") != FORMAT_VERSION:
            raise ValueError(f"format {doc.get('format')!r}, expected {FORMAT_VERSION}")
        return Dataset(
            name=doc["name"],
            version=doc["version"],
            licence=doc.get("licence"),
            skeleton=Skeleton.from_dict(doc["skeleton"]),
            clips=[ClipInfo.from_dict(c) for c in doc["clips"]],
            bars=[BarInfo.from_dict(b) for b in doc["bars"]],
            store=store,
            meta={
                k: doc.get(k)
                for k in (
                    "data_prefix",
                    "acknowledgement",
                    "source",
                    "description",
                    "fps_override",
                    "fps_reason",
                    "scale",
                    "tempo_prior_bpm",
                    "style_tempo_bpm",
                    "style",
                    "skeleton_source",
                    "failed",
                    "excluded",
                    "warnings",
                    "signature_counts",
                    "partners",
                )
            },
        )
    except (ValueError, KeyError, TypeError) as exc:
        raise DanceGraphError(
            f"dataset {name!r}: {key} is unreadable ({exc})", code="dataset_corrupt", field=key
        ) from None


def grid_report(ds: Dataset) -> dict:
    """The beat grids of a stored dataset, as ``dataset show`` prints them.

    Per clip: ``id``, ``fps``, ``tempo_bpm``, ``confidence``, ``beat_source``, ``flags``,
    ``sections`` (steady-tempo stretches of an estimated grid), ``beats`` (s) and ``bars``
    (``[start_s, end_s]`` each); then the import's partner agreement rows. Times rounded to
    0.1 ms.
    """
    by_clip: dict[str, list[list[float]]] = {}
    for b in ds.bars:
        by_clip.setdefault(b.clip_id, []).append([round(b.start_s, 4), round(b.end_s, 4)])
    return {
        "name": ds.name,
        "version": ds.version,
        "clips": [
            {
                "id": c.id,
                "fps": c.fps,
                "tempo_bpm": _round(c.tempo_bpm, 3),
                "confidence": _round(c.tempo_confidence, 3),
                "beat_source": c.beat_source,
                "grid_check": c.grid_check,
                "audio_offset_s": c.audio_offset_s,
                "source_format": c.source_format,
                "retarget": c.retarget,
                "flags": c.flags,
                "sections": c.sections,
                "beats": [round(float(t), 4) for t in ds.beats(c.id)],
                "bars": by_clip.get(c.id, []),
            }
            for c in ds.clips
        ],
        "partners": ds.meta.get("partners") or [],
    }


def list_datasets(store: ObjectStore) -> list[dict]:
    """Summaries of the stored datasets: name, version, clips, bars, joints, licence."""
    out: list[dict] = []
    for name in store.children("datasets"):
        try:
            ds = load_dataset(store, name)
        except DanceGraphError:
            continue
        out.append(
            {
                "name": ds.name,
                "version": ds.version,
                "clips": len(ds.clips),
                "bars": len(ds.bars),
                "joints": ds.skeleton.n_joints,
                "styles": sorted({c.style for c in ds.clips}),
                "licence": ds.licence,
            }
        )
    return out
