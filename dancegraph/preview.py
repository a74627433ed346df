"""What the preview page loads, computed from a rendered result: joint positions and the song.

The browser draws bones between world joint positions, so it never parses BVH nor runs forward
kinematics: ``pose_track`` turns a dance into a compact JSON-ready dict (positions in integer
millimetres, frame-major). ``find_audio`` locates the song of a ``dancegraph synthesize`` output
folder from the ``provenance.audio`` entry of its ``timeline.json``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dancegraph.errors import DanceGraphError, NotFoundError
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fk import end_site_positions, forward_kinematics
from dancegraph.motion.skeleton import Motion
from dancegraph.render import TIMELINE
from dancegraph.store import file_sha256

POSE_FORMAT = 1


def pose_track(motion: Motion) -> dict:
    """World joint positions of every frame as a JSON-ready dict.

    Keys: ``format``; ``fps``; ``frames`` (F); ``joints`` (J names: the skeleton's joints, then
    one ``<joint>_end`` per End Site); ``parents`` (J ints, -1 for the root); ``unit`` ("mm");
    ``positions``: F·J·3 ints, millimetres, frame-major (frame f, joint j, axis a at
    ``(f·J + j)·3 + a``), Y up.
    """
    skeleton = motion.skeleton
    positions, world = forward_kinematics(motion)
    names = list(skeleton.names)
    parents = [int(p) for p in skeleton.parents]
    ends = end_site_positions(skeleton, positions, world)
    extra = []
    for j in sorted(ends):
        names.append(f"{skeleton.names[j]}_end")
        parents.append(j)
        extra.append(ends[j])
    if extra:
        positions = np.concatenate([positions, np.stack(extra, axis=1)], axis=1)
    mm = np.round(positions * 1000.0).astype(np.int64)
    return {
        "format": POSE_FORMAT,
        "fps": motion.fps,
        "frames": int(motion.n_frames),
        "joints": names,
        "parents": parents,
        "unit": "mm",
        "positions": mm.reshape(-1).tolist(),
    }


def pose_track_file(bvh_path: str | Path, scale: float = 1.0) -> dict:
    """``pose_track`` of a BVH file (``scale``: metres per file unit, e.g. 0.01 for a dance on a
    rig in centimetres); raises ``MotionFileError`` for a bad file."""
    return pose_track(read_bvh(bvh_path, scale=scale))


def read_timeline(result_dir: str | Path) -> dict:
    """The ``timeline.json`` of a result folder; ``NotFoundError`` (``result_not_found``) if absent."""
    path = Path(result_dir) / TIMELINE
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise NotFoundError(
            f"{result_dir} has no {TIMELINE} (is it a `dancegraph synthesize` output folder?)",
            code="result_not_found",
            field=str(result_dir),
        ) from exc
    except ValueError as exc:
        raise DanceGraphError(
            f"{path} is not valid JSON: {exc}", code="timeline_invalid", field=str(path)
        ) from exc


def find_audio(result_dir: str | Path, timeline: dict, cwd: str | Path = ".") -> Path:
    """The song of a synthesize output: ``provenance.audio.file`` looked up in the result folder,
    its parent, then ``cwd``; a candidate whose sha256 differs from the recorded one is skipped.

    Raises ``NotFoundError`` (``preview_audio_missing``) naming the places looked in.
    """
    audio = (timeline.get("provenance") or {}).get("audio") or {}
    name, sha = audio.get("file"), audio.get("sha256")
    result = Path(result_dir)
    places = [result, result.parent, Path(cwd)]
    if name:
        for folder in places:
            candidate = folder / Path(name).name
            if candidate.is_file() and (not sha or file_sha256(candidate) == sha):
                return candidate.resolve()
    where = ", ".join(str(p) for p in places)
    raise NotFoundError(
        f"the song of {result_dir} ({name or 'not recorded in timeline.json'}) was not found in "
        f"{where}; pass it with --audio FILE",
        code="preview_audio_missing",
        field="--audio",
    )
