"""Retargeting benchmark and quality table: a 3-minute, 30 fps salsa dance on every test rig (issue 21).

Target: retargeting (FBX/GLB writing aside) <= 1.5 s of CPU per 3-minute dance. Beside the time,
each row shows issue 21's checks on that rig: the foot's lowest point at contacts against the
floor, foot sliding at contacts (target and source), the median and p95 world-direction error of
the mapped limb bones, and the largest frame-to-frame joint rotation (target and source). Then
the file writing: BVH, GLB (and FBX through Blender where it is installed).

The dance is real salsa: the 60_NN takes read at their true 60 fps, cut into bars of a nominal
168 BPM beat and stitched onto an even 168 BPM song at 30 fps as the renderer stitches bars
(cuts near the bar lines, root alignment and seam blending), feet cleaned as the renderer cleans
them, cut at 3 minutes. The rigs are the project's test rigs (tests/motion/rigs.py),
Blender-made where Blender is installed. CPU seconds: median of 3 runs (``time.process_time``).
A second table is the baseline row: the same transfer without the foot step.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.contacts import clean_foot_skate
from dancegraph.motion.fbx import fbx_available
from dancegraph.motion.retarget import RetargetParams, plan_retarget, retarget, write_on_rig
from dancegraph.motion.retime import NODE_BEATS
from dancegraph.motion.rig import load_rig
from dancegraph.motion.skeleton import Motion
from dancegraph.motion.stitch import stitch
from dancegraph.paths import shared_dir
from dancegraph.render import bar_frames

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from tests.motion.rigs import GOOD_BVH_RIGS, GOOD_RIGS, GOOD_RIGS_MESH, make_rigs  # noqa: E402

FPS = 30.0
SECONDS = 180
TARGET_CPU_S = 1.5
BEAT_S = 60.0 / 168.0  # a salsa beat (s) at the takes' ~168 BPM


def take_bars(take: Motion) -> list[tuple[Motion, np.ndarray]]:
    """Consecutive bars of ``take`` on a nominal ``BEAT_S`` beat: per bar the frames around it and
    where its beats -2 .. 6 fall in them (``stitch``'s pieces)."""
    beat = BEAT_S * take.fps
    pieces = []
    for start in np.arange(2 * beat + 3, take.n_frames - 6 * beat - 3, 4 * beat):
        lo, hi = int(np.floor(start - 2 * beat)) - 2, int(np.ceil(start + 6 * beat)) + 2
        pieces.append((take.slice(lo, hi), start + NODE_BEATS * beat - lo))
    return pieces


def three_minute_salsa() -> Motion:
    """Real salsa bars stitched onto an even 168 BPM song of 3 minutes at 30 fps, feet cleaned
    (as a rendered dance); a take's bars follow each other, the takes follow in turn."""
    takes = sorted((shared_dir() / "datasets/mocap/cmu-salsa").glob("60_*_scaled.bvh"))
    n_bars = int(np.ceil(SECONDS / (4 * BEAT_S)))
    pieces: list[tuple[Motion, np.ndarray]] = []
    while len(pieces) < n_bars:
        for path in takes:
            pieces.extend(take_bars(read_bvh(path, fps=60.0)))
            if len(pieces) >= n_bars:
                break
    beats = np.arange(4 * n_bars + 1) * BEAT_S
    bar_beats = np.stack([beats[4 * b : 4 * b + 5] for b in range(n_bars)])
    frames = bar_frames(bar_beats[:, [0, 4]], FPS)
    dance, _ = stitch(pieces[:n_bars], bar_beats, frames, FPS)
    dance, _ = clean_foot_skate(dance.slice(0, int(SECONDS * FPS)))
    return dance


def main() -> int:
    if not (shared_dir() / "datasets").is_dir():
        print("shared datasets not found: skipped")
        return 0
    dance = three_minute_salsa()
    blender = fbx_available()
    names = (GOOD_RIGS + GOOD_RIGS_MESH if blender else ()) + GOOD_BVH_RIGS
    print(
        f"3-minute salsa: {dance.n_frames} frames at {dance.fps:g} fps, {dance.skeleton.n_joints} "
        f"joints; target <= {TARGET_CPU_S} s CPU; machine shared by other jobs"
    )
    print(
        "| rig | joints | CPU s (median of 3) | floor max cm | sliding mm/s (source) "
        "| direction median / p95 deg | max step deg (source) | BVH s | GLB s | FBX s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    worst = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        rigs = make_rigs(Path(tmp) / "rigs", blender=blender)
        for name in names:
            rig = load_rig(rigs / name)
            plan_retarget(dance.skeleton, rig)  # warm the imports
            times, report = [], None
            for _ in range(3):
                t0 = time.process_time()
                motion, report = retarget(dance, rig)
                times.append(time.process_time() - t0)
            cpu = statistics.median(times)
            worst = max(worst, cpu)
            writes = []
            for ext in (".bvh", ".glb", ".fbx"):
                if ext == ".fbx" and not blender:
                    writes.append("-")
                    continue
                t0 = time.perf_counter()
                write_on_rig(motion, rig, rigs / name, Path(tmp) / f"out{ext}")
                writes.append(f"{time.perf_counter() - t0:.2f}")
            d = report["direction_error_deg"]
            s = report["max_joint_step_deg"]
            print(
                f"| {name} | {rig.skeleton.n_joints} | {cpu:.3f} "
                f"| {100 * report['floor_error_m']['max_abs']:.3f} "
                f"| {1000 * report['sliding_m_s']:.3f} ({1000 * report['source_sliding_m_s']:.3f}) "
                f"| {d['median']:.2f} / {d['p95']:.2f} | {s['target']:.1f} ({s['source']:.1f}) "
                f"| {' | '.join(writes)} |"
            )
        print(
            "\nbaseline row: the same rotations and root path without the foot step "
            "(what the feet do when only rotations are transferred)"
        )
        print("| rig | floor max cm | floor median cm | sliding mm/s (source) |")
        print("|---|---|---|---|")
        for name in names:
            rig = load_rig(rigs / name)
            _, report = retarget(dance, rig, RetargetParams(foot_ik=False))
            f = report["floor_error_m"]
            print(
                f"| {name} | {100 * f['max_abs']:.2f} | {100 * f['median_abs']:.2f} "
                f"| {1000 * report['sliding_m_s']:.1f} ({1000 * report['source_sliding_m_s']:.1f}) |"
            )
    print(f"worst CPU {worst:.3f} s: {'OK' if worst <= TARGET_CPU_S else 'OVER TARGET'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
