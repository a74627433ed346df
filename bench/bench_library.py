"""Benchmark: a library of two skeletons, and a generated library with its music.

1. Mixed skeletons: takes of cmu-salsa (43 joints, metres, 60 fps) and cmu-modern (31 joints,
   CMU units, 120 fps) imported as one library on the salsa skeleton (the modern takes are
   retargeted at import), built as one graph and danced to the CC songs; each library is also
   built alone. Per graph: import and build seconds, nodes and edges, edges between the two
   styles, and the rendered dances' seams scored against the library's own frame-to-frame
   distribution (``metrics.smoothness``: the share of seams above its p99 and the median seam
   percentile), beside the chance row (the takes' own frames scored as seams).
2. The generated library with music (``motion demo --takes 30 --with-music``): write, import
   (every take's grid from its music) and build seconds, and how the music grids match the
   truth. Run: ``python -m bench library``.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dancegraph.eval.harness import EVAL_FPS, load_library
from dancegraph.graph.artifact import load_current
from dancegraph.graph.build import build_dataset_graph
from dancegraph.metrics.smoothness import seam_report
from dancegraph.motion.dataset import import_dataset, load_dataset
from dancegraph.motion.fk import forward_kinematics
from dancegraph.paths import shared_dir
from dancegraph.store import FileStore, ObjectStore

SALSA_TAKES = ("60_01", "61_01", "60_03", "61_03")
MODERN_TAKES = ("05_02", "05_04", "05_06", "05_10", "05_12")
_SALSA = {"fps": 60, "style": "salsa", "tempo_prior_bpm": [150, 220]}
_MODERN = {"scale": 0.056444, "style": "modern", "tempo_bpm": 120, "first_downbeat_s": 0.0}


def library_folder(out: Path, salsa: tuple[str, ...], modern: tuple[str, ...]) -> tuple[Path, dict]:
    """A folder of links to the shared takes and its manifest (salsa's skeleton first)."""
    mocap = shared_dir() / "datasets" / "mocap"
    out.mkdir(parents=True, exist_ok=True)
    clips = {}
    for take in salsa:
        (out / f"{take}_scaled.bvh").symlink_to(mocap / "cmu-salsa" / f"{take}_scaled.bvh")
        clips[take] = _SALSA
    for take in modern:
        (out / f"{take}.bvh").symlink_to(mocap / "cmu-modern" / f"{take}.bvh")
        clips[take] = _MODERN
    manifest = {
        "strip_suffix": "_scaled",
        "skeleton": salsa[0] if salsa else None,
        "clips": clips,
    }
    return out, manifest


def dance_seams(store: ObjectStore, name: str, analysis, only: str | None = None) -> dict:
    """Search and render ``name``'s graph on a song's ``analysis`` (``only``: a style whose
    takes alone may dance, the others excluded); the dance's seams scored against the frames of
    the library's own takes of the styles it danced (``seam_report``: each library's own p99),
    the chance row, and the seams where the dance crosses from one style to the other."""
    from dancegraph.graph.search import search
    from dancegraph.render import render_path
    from dancegraph.spec import parse_spec

    graph = load_current(store, name)
    dataset = load_dataset(store, name)
    style = {c.id: c.style for c in dataset.clips}
    spec: dict = {"dataset": name, "alternatives": 1}
    if only:
        spec["exclude"] = [{"node": f"{c}:*"} for c, s in style.items() if s != only]
    found = search(graph, analysis, parse_spec(spec))
    alt = found.alternatives[0]
    ids = [graph.node_ids[int(n)] for n in alt.index]
    motion, rep = render_path(
        graph,
        ids,
        analysis.bar_beats,
        EVAL_FPS,
        duration_s=float(analysis.duration_s),
        placements=alt.placements,
    )
    bar_style = [style[i.split(":")[0]] for i in ids]
    danced = set(bar_style)
    lib = load_library(graph, _styles_only(dataset, danced))
    assert lib.seams is not None and lib.seams.chance is not None
    pos = forward_kinematics(motion)[0]
    seams = seam_report(pos, EVAL_FPS, rep["seams"], lib.seams)
    cross = [
        s
        for s, b in zip(rep["seams"], rep["seam_bars"], strict=True)
        if b > 0 and bar_style[b] != bar_style[b - 1]
    ]
    return {
        "styles": {s: bar_style.count(s) for s in sorted(danced)},
        "seams": seams["count"],
        "flagged_share": round(seams["flagged_share"], 3),
        "median_percentile": _r(seams["median_percentile"]),
        "chance_flagged_share": round(lib.seams.chance["flagged_share"], 3),
        "chance_median_percentile": _r(lib.seams.chance["median_percentile"]),
        "cross_seams": len(cross),
    }


def _styles_only(dataset, styles: set[str]):
    """``dataset`` with only the takes of ``styles`` (the reference of those libraries)."""
    from dataclasses import replace

    clips = [c for c in dataset.clips if c.style in styles]
    keep = {c.id for c in clips}
    return replace(dataset, clips=clips, bars=[b for b in dataset.bars if b.clip_id in keep])


def _r(x: float | None) -> float | None:
    return None if x is None else round(float(x), 1)


def cross_edges(store: ObjectStore, name: str) -> int:
    """Edges of ``name``'s graph between nodes of two different styles."""
    graph = load_current(store, name)
    style = {c.id: c.style for c in load_dataset(store, name).clips}
    node_style = np.array(
        [style[graph.node_ids[i].split(":")[0].split("~")[0]] for i in range(graph.n_nodes)]
    )
    n = 0
    for p in range(graph.n_nodes):
        q, _ = graph.out_edges(p)
        n += int(np.sum(node_style[q] != node_style[p]))
    return n


def _mixed(tmp: Path, songs: list[Path]) -> None:
    from dancegraph.music.analysis import analyze

    store = FileStore(tmp / "store")
    libs = {
        "salsa": (SALSA_TAKES, ()),
        "modern": ((), MODERN_TAKES),
        "mixed": (SALSA_TAKES, MODERN_TAKES),
    }
    analyses = {s.name: analyze(s) for s in songs}
    for name, (salsa, modern) in libs.items():
        src, manifest = library_folder(tmp / name, salsa, modern)
        if not salsa:
            manifest.pop("skeleton")
        t0 = time.perf_counter()
        report = import_dataset(src, name, store, manifest)
        t1 = time.perf_counter()
        built = build_dataset_graph(store, name)
        t2 = time.perf_counter()
        print(
            f"{name}: {len(report.clips)} takes, {report.n_bars} bars, import {t1 - t0:.1f} s,"
            f" build {t2 - t1:.1f} s, {built['nodes']} nodes, {built['edges']} edges,"
            f" {cross_edges(store, name)} between styles"
        )
        for c in report.clips:
            if c.retarget:
                print(f"  retargeted {c.id}: {c.retarget}")
        for song, analysis in analyses.items():
            for only in (None, "modern") if name == "mixed" else (None,):
                row = dance_seams(store, name, analysis, only)
                label = f"{song[:32]}" + (f" ({only} only)" if only else "")
                print(f"  {label}: {json.dumps(row, default=str)}")


def _generated(tmp: Path) -> None:
    from dancegraph.motion.demo import write_demo_library

    store = FileStore(tmp / "store-gen")
    t0 = time.perf_counter()
    lib = write_demo_library(tmp / "gen", seed=0, n_takes=30, with_music=True)
    t1 = time.perf_counter()
    report = import_dataset(lib, "generated", store)
    t2 = time.perf_counter()
    built = build_dataset_graph(store, "generated")
    t3 = time.perf_counter()
    agree = sum(bool(c.grid_check.get("agree")) for c in report.clips)
    music = sum(c.beat_source == "music" for c in report.clips)
    print(
        f"generated: write {t1 - t0:.1f} s, import {t2 - t1:.1f} s ({music} of "
        f"{len(report.clips)} takes gridded from music, {agree} agree with the motion), build "
        f"{t3 - t2:.1f} s ({built['nodes']} nodes, {built['edges']} edges); failed "
        f"{len(report.failed)}"
    )
    print(json.dumps(music_truth(store, "generated", lib), default=str))


def music_truth(store: ObjectStore, name: str, lib: Path) -> dict:
    """How the music grids of a generated library match its truth (``truth.json``): the median
    and largest |beat - true beat| (ms, each grid beat to the nearest true beat) and the share of
    bars starting on a true downbeat (within 1/8 beat)."""
    ds = load_dataset(store, name)
    truth = json.loads((lib / "truth.json").read_text())
    errs, on = [], []
    for c in ds.clips:
        t = truth[c.id]
        true_beats = np.asarray(t["beats"])
        beats = ds.beats(c.id)
        beats = beats[(beats >= true_beats[0] - 0.05) & (beats <= true_beats[-1] + 0.05)]
        errs.append(np.min(np.abs(beats[:, None] - true_beats[None]), axis=1))
        beat_s = 60.0 / t["tempo_bpm"]
        down = np.asarray(t["downbeats"])
        starts = np.array([b.start_s for b in ds.bars if b.clip_id == c.id])
        on.append(np.min(np.abs(starts[:, None] - down[None]), axis=1) <= beat_s / 8)
    e = np.concatenate(errs) * 1000
    return {
        "beats": int(e.size),
        "median_ms": round(float(np.median(e)), 2),
        "max_ms": round(float(e.max()), 2),
        "bars_on_downbeats": round(float(np.concatenate(on).mean()), 3),
    }


def main() -> int:
    cc = shared_dir() / "datasets" / "music" / "cc"
    with tempfile.TemporaryDirectory(prefix="dg-bench-library-") as tmp:
        if cc.is_dir():
            _mixed(Path(tmp), sorted(cc.glob("*.ogg")))
        else:
            print("shared datasets absent: mixed-skeleton rows skipped")
        _generated(Path(tmp))
    return 0


if __name__ == "__main__":
    sys.exit(main())
