"""FBX export benchmark: a 3-minute, 30 fps result on the 43-joint salsa skeleton (issue 3).

Target: ≤ 6 s per export in a warm Blender process. Also shown: the cold start (a new Blender
child process: start plus the first export) and a short 8-bar clip in the warm process.
The motion is real salsa (60_NN takes read at 60 fps, every 2nd frame → 30 fps, concatenated).
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dancegraph.motion.bvh import read_bvh, write_bvh
from dancegraph.motion.fbx import FbxExporter, fbx_available
from dancegraph.motion.skeleton import Motion
from dancegraph.paths import shared_dir

FPS = 30.0
SECONDS = 180


def three_minute_motion() -> Motion:
    takes = sorted((shared_dir() / "datasets/mocap/cmu-salsa").glob("60_*_scaled.bvh"))
    roots, rots, skeleton, need = [], [], None, int(SECONDS * FPS)
    for path in takes:
        m = read_bvh(path, fps=60.0)
        skeleton = m.skeleton
        roots.append(m.root_positions[::2])
        rots.append(m.rotations[::2])
        need -= len(roots[-1])
        if need <= 0:
            break
    n = int(SECONDS * FPS)
    return Motion(skeleton, FPS, np.concatenate(roots)[:n], np.concatenate(rots)[:n])


def main() -> int:
    if not fbx_available():
        print("Blender's Python not installed (scripts/install-blender.sh): skipped")
        return 0
    motion = three_minute_motion()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        long_bvh = tmp / "long.bvh"
        write_bvh(motion, long_bvh)
        short_bvh = tmp / "short.bvh"
        write_bvh(motion.slice(0, 8 * 60), short_bvh)  # 8 bars at ~120 BPM

        t0 = time.perf_counter()
        ex = FbxExporter()
        ex.start()
        t_start = time.perf_counter() - t0
        ex.convert(long_bvh, tmp / "cold.fbx")
        t_cold = time.perf_counter() - t0
        rows.append(("cold start: Blender child ready", "-", t_start))
        rows.append(("cold: start + first 3-min export", motion.n_frames, t_cold))

        warm = []
        for k in range(3):
            t = time.perf_counter()
            ex.convert(long_bvh, tmp / f"warm{k}.fbx")
            warm.append(time.perf_counter() - t)
        rows.append(("warm: 3-min export (median of 3)", motion.n_frames, statistics.median(warm)))
        short = []
        for k in range(5):
            t = time.perf_counter()
            ex.convert(short_bvh, tmp / f"short{k}.fbx")
            short.append(time.perf_counter() - t)
        rows.append(("warm: 16 s clip (median of 5)", 480, statistics.median(short)))
        size_mb = (tmp / "warm0.fbx").stat().st_size / 1e6
        ex.close()

    print(
        f"FBX export, {motion.skeleton.n_joints} joints, {FPS:.0f} fps, Blender {ex.blender_version}"
    )
    print(f"{'case':<38} {'frames':>7} {'seconds':>8}")
    for name, frames, secs in rows:
        print(f"{name:<38} {frames!s:>7} {secs:8.2f}")
    warm_s = statistics.median(warm)
    print(
        f"3-min FBX size: {size_mb:.1f} MB; warm target ≤ 6 s: {'met' if warm_s <= 6.0 else 'NOT met'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
