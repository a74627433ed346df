"""BVH → FBX conversion inside Blender (runs ONLY under Blender's Python, never imported by dancegraph).

This script is the child process behind ``dancegraph.motion.fbx.FbxExporter``. It imports only
``bpy`` and the standard library, because it runs in its own virtual environment (``bpy`` 5.0.1 is
GPL and pins numpy<2; the service code stays apart from it).

Protocol: JSON lines. The parent writes one request per line on stdin; the worker answers one
line per request on its protocol channel (the original stdout; everything Blender itself prints
is sent to stderr so it can never corrupt the protocol). The first line the worker writes is
``{"ready": true, "blender": "5.0.1"}``.

Requests:
- ``{"id": 1, "op": "convert", "bvh": IN, "fbx": OUT, "fps": 30.0 | null, "scale": 1.0}``
  → ``{"id": 1, "ok": true, "frames": F, "fps": 30.0, "joints": J, "seconds": 0.8}``
- ``{"id": 2, "op": "ping"}`` → ``{"id": 2, "ok": true}``
- ``{"id": 3, "op": "quit"}`` → ``{"id": 3, "ok": true}`` and the process exits.
A failed request answers ``{"id": N, "ok": false, "error": "..."}`` and the worker keeps serving.

What the conversion corrects, compared with Blender's importer used as is:
- the importer stretches the scene to one frame more than the file holds: the scene range is set
  to exactly the file's frames;
- a BVH ``Frame Time`` printed to 6 decimals (0.033333) gives a fractional rate (30.0003 fps):
  a rate within 0.1 % of a whole number is snapped to it (or the caller passes the exact rate);
- the importer starts keys at frame 1: keys are shifted so the first BVH frame is at t = 0;
- units: BVH values are metres (DanceGraph writes metres); Blender's scene unit is the metre and
  the FBX is written in metres (``UnitScaleFactor`` 100, i.e. 1 unit = 100 cm), Y up, -Z forward
  (the BVH convention), with the armature's animation baked on every frame.
"""

from __future__ import annotations

import array
import json
import math
import os
import sys
import time
import traceback

# Keep a private handle on the real stdout for the protocol, then point fd 1 at stderr so that
# anything Blender prints (importer progress, warnings) goes to the log, never into the protocol.
_PROTOCOL = os.fdopen(os.dup(1), "w", buffering=1, encoding="utf-8")
os.dup2(2, 1)
sys.stdout = sys.stderr

import bpy  # noqa: E402  (after the redirect on purpose)
from bpy_extras import anim_utils  # noqa: E402

FPS_SNAP_TOLERANCE = 1e-3  # relative: 1/0.033333 = 30.0003 is 30, 29.97 stays 29.97


def _send(obj: dict) -> None:
    _PROTOCOL.write(json.dumps(obj) + "\n")
    _PROTOCOL.flush()


def read_bvh_timing(path: str) -> tuple[int, float]:
    """``(frame count, frame time in s)`` from a BVH's MOTION header, read without the frames."""
    frames = frame_time = None
    with open(path, encoding="utf-8", errors="replace") as fh:
        in_motion = False
        for line in fh:
            words = line.split()
            if not words:
                continue
            if words[0].upper() == "MOTION":
                in_motion = True
            elif in_motion and words[0].lower() == "frames:" and len(words) == 2:
                frames = int(words[1])
            elif in_motion and words[0].lower() == "frame" and len(words) == 3:
                frame_time = float(words[2])
                break
    if frames is None or frame_time is None:
        raise ValueError(f"{path}: no 'Frames:' / 'Frame Time:' lines in the MOTION section")
    if frames < 1:
        raise ValueError(f"{path}: the file has no frames")
    if not (frame_time > 0 and math.isfinite(frame_time)):
        raise ValueError(f"{path}: invalid Frame Time {frame_time}")
    return frames, frame_time


def snap_fps(fps: float) -> float:
    """A rate within FPS_SNAP_TOLERANCE of a whole number becomes that number."""
    nearest = round(fps)
    if nearest > 0 and abs(fps - nearest) <= FPS_SNAP_TOLERANCE * nearest:
        return float(nearest)
    return fps


def clear_scene() -> None:
    """Remove everything a previous conversion left, so each file starts from an empty scene."""
    for collection in (bpy.data.objects, bpy.data.armatures, bpy.data.actions):
        for item in list(collection):
            collection.remove(item)


def _shift_keys(action, slot, frames: float) -> None:
    """Move every key of ``action`` (for ``slot``) by ``frames``."""
    channelbag = anim_utils.action_get_channelbag_for_slot(action, slot)
    for fcurve in channelbag.fcurves:
        points = fcurve.keyframe_points
        # The importer's keys are linear, so the Bézier handles play no part: move the keys only.
        buf = array.array("f", bytes(8 * len(points)))
        points.foreach_get("co", buf)
        buf[0::2] = array.array("f", (x + frames for x in buf[0::2]))
        points.foreach_set("co", buf)
        fcurve.update()


def convert(bvh_path: str, fbx_path: str, fps: float | None = None, scale: float = 1.0) -> dict:
    """Import ``bvh_path`` (``scale`` × file units = metres) and write ``fbx_path``; returns a summary."""
    t0 = time.perf_counter()
    if not os.path.isfile(bvh_path):
        raise FileNotFoundError(f"{bvh_path}: no such file")
    n_frames, frame_time = read_bvh_timing(bvh_path)
    rate = float(fps) if fps else snap_fps(1.0 / frame_time)

    clear_scene()
    scene = bpy.context.scene
    result = bpy.ops.import_anim.bvh(
        filepath=bvh_path,
        global_scale=float(scale),
        frame_start=1,
        use_fps_scale=False,
        update_scene_fps=False,
        update_scene_duration=False,
        use_cyclic=False,
        rotate_mode="NATIVE",
        axis_forward="-Z",
        axis_up="Y",
    )
    if "FINISHED" not in result:
        raise RuntimeError(f"{bvh_path}: Blender's BVH importer failed ({result})")
    armatures = [ob for ob in scene.objects if ob.type == "ARMATURE"]
    if len(armatures) != 1:
        raise RuntimeError(f"{bvh_path}: expected one armature after import, got {len(armatures)}")
    armature = armatures[0]
    adt = armature.animation_data
    if adt is None or adt.action is None:
        raise RuntimeError(f"{bvh_path}: the import produced no animation")

    # Rate: a whole number where possible (fps_base carries a fractional rate exactly).
    scene.render.fps = max(1, int(round(rate)))
    scene.render.fps_base = scene.render.fps / rate
    # First BVH frame at frame 0 (t = 0), last at n_frames - 1: no extra frame.
    _shift_keys(adt.action, adt.action_slot, -1.0)
    scene.frame_start = 0
    scene.frame_end = n_frames - 1
    scene.frame_set(0)

    out_dir = os.path.dirname(os.path.abspath(fbx_path))
    os.makedirs(out_dir, exist_ok=True)
    tmp_path = os.path.join(out_dir, f".tmp-{os.getpid()}-{os.path.basename(fbx_path)}")
    try:
        result = bpy.ops.export_scene.fbx(
            filepath=tmp_path,
            use_selection=False,
            object_types={"ARMATURE"},
            apply_scale_options="FBX_SCALE_ALL",
            global_scale=1.0,
            apply_unit_scale=True,
            axis_forward="-Z",
            axis_up="Y",
            add_leaf_bones=False,
            primary_bone_axis="Y",
            secondary_bone_axis="X",
            armature_nodetype="NULL",
            bake_anim=True,
            bake_anim_use_all_bones=True,
            bake_anim_use_nla_strips=False,
            bake_anim_use_all_actions=False,
            bake_anim_force_startend_keying=True,
            bake_anim_step=1.0,
            bake_anim_simplify_factor=0.0,
            use_custom_props=False,
            path_mode="AUTO",
        )
        if "FINISHED" not in result:
            raise RuntimeError(f"{fbx_path}: Blender's FBX exporter failed ({result})")
        os.replace(tmp_path, fbx_path)
    finally:
        if os.path.exists(tmp_path):
            os.unlink(tmp_path)
    return {
        "frames": n_frames,
        "fps": scene.render.fps / scene.render.fps_base,
        "joints": len(armature.data.bones),
        "seconds": round(time.perf_counter() - t0, 4),
    }


def _short_error(exc: Exception) -> str:
    """One line for the caller: an operator's error arrives as a whole traceback in the message."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    lines = [ln for ln in lines if not ln.startswith(("Location:", "File ", "^", "~"))]
    if isinstance(exc, RuntimeError) and len(lines) > 1:
        return f"Blender: {lines[-1]} (malformed file?)"
    return f"{type(exc).__name__}: {lines[0] if lines else ''}"


def serve() -> int:
    """Answer requests from stdin until EOF or a ``quit`` request."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = 1.0
    _send({"ready": True, "blender": bpy.app.version_string, "pid": os.getpid()})
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        req_id = None
        try:
            req = json.loads(line)
            req_id = req.get("id")
            op = req.get("op")
            if op == "convert":
                summary = convert(
                    str(req["bvh"]), str(req["fbx"]), req.get("fps"), req.get("scale") or 1.0
                )
                _send({"id": req_id, "ok": True, **summary})
            elif op == "ping":
                _send({"id": req_id, "ok": True})
            elif op == "quit":
                _send({"id": req_id, "ok": True})
                return 0
            else:
                _send({"id": req_id, "ok": False, "error": f"unknown op {op!r}"})
        except Exception as exc:  # one bad file must not end the worker
            traceback.print_exc(file=sys.stderr)
            _send({"id": req_id, "ok": False, "error": _short_error(exc)})
    return 0


if __name__ == "__main__":
    sys.exit(serve())
