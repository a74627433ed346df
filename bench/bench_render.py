"""Render benchmark: a 3-minute song danced on the salsa graph, written at 60 fps.

Imports cmu-salsa into a temporary store, builds its graph, searches one path for a synthetic
3-minute 4/4 song (``bench_search.song``: 124 BPM, phrase structure on) and times
``render.render_path`` (time warp, seams, stage plan, foot cleanup) and ``render.render`` (the
same plus the BVH file and ``timeline.json``) at 60 fps: medians of 5 runs after a warm one, wall
and CPU seconds (``bench_search.timed``; CPU time is what a shared, busy machine still measures
fairly).
Run: ``python -m bench render``.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.bench_search import song, timed  # noqa: E402
from dancegraph.graph import artifact  # noqa: E402
from dancegraph.graph.build import build_dataset_graph  # noqa: E402
from dancegraph.graph.search import search  # noqa: E402
from dancegraph.motion.dataset import import_dataset, load_manifest  # noqa: E402
from dancegraph.paths import shared_dir  # noqa: E402
from dancegraph.render import render, render_path  # noqa: E402
from dancegraph.spec import Spec  # noqa: E402
from dancegraph.store import FileStore  # noqa: E402

FPS = 60.0
SONG_S = 180.0


def main() -> int:
    mocap = shared_dir() / "datasets" / "mocap" / "cmu-salsa"
    if not mocap.is_dir():
        print(f"shared mocap not found at {mocap}: set DANCEGRAPH_SHARED")
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        store = FileStore(Path(tmp) / "store")
        import_dataset(
            mocap,
            "cmu-salsa",
            store,
            load_manifest(ROOT / "datasets" / "manifests" / "cmu-salsa.yaml"),
        )
        build_dataset_graph(store, "cmu-salsa")
        graph = artifact.load_current(store, "cmu-salsa")
        music = song(SONG_S)
        spec = Spec.model_validate(
            {"dataset": "cmu-salsa", "alternatives": 1, "output": {"formats": ["bvh"], "fps": FPS}}
        )
        found = search(graph, music, spec)
        alt = found.alternatives[0]
        rows = [
            (
                "render_path",
                timed(
                    lambda: render_path(
                        graph,
                        alt.nodes,
                        music.bar_beats,
                        FPS,
                        duration_s=music.duration_s,
                        placements=alt.placements,
                    )
                ),
            )
        ]
        out = Path(tmp) / "out"
        rows.append(
            ("render (+ BVH, timeline)", timed(lambda: render(graph, music, found, spec, out)))
        )
    print(f"{SONG_S:.0f} s song, {len(music.bars)} bars, {FPS:.0f} fps, medians of 5 runs")
    print(f"{'step':<28}{'wall s':>10}{'CPU s':>10}")
    for name, (wall, cpu) in rows:
        print(f"{name:<28}{wall:>10.3f}{cpu:>10.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
