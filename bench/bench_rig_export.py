"""Rig output benchmark (issue 38): a 3-minute dance written on a skinned Mixamo-style rig.

Targets: FBX <= 3 s with a warm exporter (one Blender child kept between files), USD <= 1 s.
The dance is bench_fbx's real salsa: the 60_NN takes read at 60 fps, every 2nd frame (30 fps),
laid end to end to 3 minutes (5,400 frames; this times the writers, not a stitch); the rig is the
project's ``prerot.fbx`` test rig (tests/motion/rigs.py: Mixamo names, a skinned mesh,
centimetres, pre- and post-rotations on every bone), Blender-made. Each number is the wall time
of ``write_on_rig`` (writing plus the read-back placement check), median of 3 runs after one
warm-up run, in one process, on a machine shared with other jobs. Also BVH and GLB, and each
file's placement check.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from dancegraph.motion.fbx import FbxExporter, fbx_available
from dancegraph.motion.retarget import retarget, write_on_rig
from dancegraph.motion.rig import load_rig
from dancegraph.paths import shared_dir

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bench.bench_fbx import three_minute_motion  # noqa: E402
from tests.motion.rigs import make_rigs  # noqa: E402

TARGETS_S = {".fbx": 3.0, ".usd": 1.0}
RIG = "prerot.fbx"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--rig", type=Path, help="a character file of your own (FBX/GLB) instead of prerot.fbx"
    )
    args = ap.parse_args(argv)
    if not (shared_dir() / "datasets").is_dir() or not fbx_available():
        print("shared datasets or Blender not found: skipped")
        return 0
    dance = three_minute_motion()
    with tempfile.TemporaryDirectory() as tmp, FbxExporter() as exporter:
        rig_file = args.rig.resolve() if args.rig else make_rigs(Path(tmp) / "rigs") / RIG
        rig = load_rig(rig_file)
        motion, report = retarget(dance, rig)
        n_vertices = rig.mesh.n_vertices if rig.mesh is not None else 0
        print(
            f"{rig_file.name}: {rig.skeleton.n_joints} joints, {n_vertices} skinned vertices, "
            f"{rig.height():.3f} m; dance {motion.n_frames} frames at {motion.fps:g} fps"
        )
        print("| file | median s (3 runs, warm) | runs s | target s | height ratio | upright |")
        print("|---|---|---|---|---|---|")
        missed = []
        for ext in (".bvh", ".glb", ".usd", ".fbx"):
            out = Path(tmp) / f"dance{ext}"
            write_on_rig(motion, rig, rig_file, out, exporter=exporter)  # warm-up
            runs, summary = [], {}
            for _ in range(3):
                t0 = time.perf_counter()
                summary = write_on_rig(motion, rig, rig_file, out, exporter=exporter)
                runs.append(time.perf_counter() - t0)
            median = statistics.median(runs)
            target = TARGETS_S.get(ext)
            if target is not None and median > target:
                missed.append(ext)
            place = summary["placement"]
            print(
                f"| {ext} | {median:.2f} | {', '.join(f'{r:.2f}' for r in runs)} | "
                f"{'-' if target is None else target} | {place['height_ratio']} | "
                f"{place['upright']} |"
            )
    if missed:
        print(f"over target: {', '.join(missed)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
