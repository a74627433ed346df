"""Couple dances (issue 35): the couple checks on real and generated songs, and the couple's
search and render time against the solo's.

Usage: ``python bench/bench_couple.py [--generated N] [--no-cc] [--alternatives K]
[--long-s S] [--out DIR]``.

The cmu-salsa library is imported from the shared mocap into the data folder
(``DANCEGRAPH_HOME``) and its solo and couple graphs built there when absent. For each song
(the four CC recordings and N generated songs, ``music.generator`` seeds 3500…) the analysis
runs once; then the solo search and render (``render.render``, BVH only) and the couple search
and render (``couple.render.render_couple``) are timed, and every couple alternative is scored
(``eval.couple.evaluate_couple_result``): hips distance inside the library's p1-p99, body-to-body
distance below its p1, each partner's seams above the library's p99, structure satisfaction
(``metrics.structure``), and the chance row (the lead of one alternative with the follow of
the next). ``--long-s`` (default 180) adds a generated song of that length for the timing row
alone. Prints a table per song and the totals; writes ``bench_couple.json`` to ``--out``.
``DANCEGRAPH_SHARED`` points at the shared datasets (default ../shared).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dancegraph.couple.graph import build_couple_graph, couple_graph_name, open_couple_graph
from dancegraph.couple.render import render_couple
from dancegraph.errors import NotFoundError
from dancegraph.eval.couple import couple_reference, evaluate_couple_result
from dancegraph.eval.harness import load_library
from dancegraph.graph.artifact import list_graphs, open_graph
from dancegraph.graph.build import build_dataset_graph
from dancegraph.graph.search import search
from dancegraph.metrics.structure import structure_satisfaction
from dancegraph.motion.dataset import import_dataset, load_dataset, load_manifest
from dancegraph.music.analysis import analyze
from dancegraph.music.generator import generate_song, write_song
from dancegraph.paths import default_store, shared_dir
from dancegraph.render import render, style_tempo_range
from dancegraph.spec import parse_spec

ROOT = Path(__file__).resolve().parents[1]
NAME = "cmu-salsa"


def library(store) -> None:
    """Import cmu-salsa and build its solo and couple graphs where the store lacks them."""
    try:
        load_dataset(store, NAME)
    except NotFoundError:
        manifest = load_manifest(ROOT / "datasets/manifests/cmu-salsa.yaml")
        import_dataset(shared_dir() / "datasets/mocap/cmu-salsa", NAME, store, manifest)
    graphs = list_graphs(store)
    if NAME not in graphs:
        build_dataset_graph(store, NAME)
    if couple_graph_name(NAME) not in graphs:
        build_couple_graph(store, NAME)


def songs(args, tmp: Path) -> list[tuple[str, Path, bool]]:
    """``(name, path, scored)``: the CC songs, the generated ones and the long timing song."""
    out = []
    if not args.no_cc:
        cc = sorted((shared_dir() / "datasets/music/cc").glob("*.ogg"))
        out += [(p.name[:28], p, True) for p in cc]
    for k in range(args.generated):
        song = generate_song(3500 + k, meter=4)
        out.append((f"generated-{3500 + k}", write_song(song, tmp, f"g{k}")[0], True))
    if args.long_s > 0:
        bars = max(4, int(round(args.long_s * 120.0 / 60.0 / 4.0 / 6.0)))
        song = generate_song(
            3999,
            meter=4,
            tempo_bpm=120.0,
            form=list("ABABCA"),
            section_bars=dict.fromkeys("ABC", bars),
        )
        out.append(
            (f"generated-long-{song.duration_s:.0f}s", write_song(song, tmp, "long")[0], False)
        )
    return out


def one_song(name: str, path: Path, graphs, spec, tmp: Path, lib, ref) -> dict:
    """Time solo and couple search + render of one song; score the couple."""
    solo, couple = graphs
    analysis = analyze(path, tempo_range=style_tempo_range(spec, solo))
    t0 = time.perf_counter()
    render(solo, analysis, search(solo, analysis, spec), spec, tmp / f"{name}-solo")
    t1 = time.perf_counter()
    found = search(couple, analysis, spec)
    render_couple(couple, analysis, found, spec, tmp / f"{name}-couple")
    t2 = time.perf_counter()
    row = {"song": name, "bars": len(analysis.bars), "solo_s": t1 - t0, "couple_s": t2 - t1}
    if lib is None:
        return row
    metrics = evaluate_couple_result(tmp / f"{name}-couple", lib, ref)
    structure = [
        structure_satisfaction(np.asarray([couple.node_index(n) for n in a.nodes]),
                               list(analysis.tags), np.asarray(couple.mirror_of))
        for a in found.alternatives
    ]  # fmt: skip
    row["alternatives"] = [
        {
            **{k: r["couple"][k] for k in ("hips_within", "body_below_p1", "hands_within")},
            "lead_seams_flagged": r["lead"]["seam_flagged_share"],
            "follow_seams_flagged": r["follow"]["seam_flagged_share"],
            "seams": r["lead"]["seams"],
            "structure_violated": len(s["violated"]),
        }
        for r, s in zip(metrics["alternatives"], structure, strict=True)
    ]
    row["chance"] = [{k: c[k] for k in ("hips_within", "body_below_p1")} for c in metrics["chance"]]
    return row


def print_row(row: dict) -> None:
    print(
        f"{row['song']:<30}{row['bars']:>5}  solo {row['solo_s']:6.1f} s  couple "
        f"{row['couple_s']:6.1f} s  ({row['couple_s'] / max(row['solo_s'], 1e-9):.2f}x)"
    )
    for k, a in enumerate(row.get("alternatives", [])):
        print(
            f"    alt {k}: hips in p1-p99 {100 * a['hips_within']:5.1f} %  body < p1 "
            f"{100 * a['body_below_p1']:4.1f} %  hands in band {100 * a['hands_within']:5.1f} %  "
            f"seams > p99 lead {100 * a['lead_seams_flagged']:4.1f} % follow "
            f"{100 * a['follow_seams_flagged']:4.1f} % of {a['seams']}  structure violated "
            f"{a['structure_violated']}"
        )
    for c in row.get("chance", []):
        print(
            f"    chance: hips in p1-p99 {100 * c['hips_within']:5.1f} %  body < p1 "
            f"{100 * c['body_below_p1']:4.1f} %"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generated", type=int, default=2)
    ap.add_argument("--no-cc", action="store_true")
    ap.add_argument("--alternatives", type=int, default=3)
    ap.add_argument("--long-s", type=float, default=180.0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    store = default_store()
    library(store)
    graphs = (open_graph(store, NAME), open_couple_graph(store, NAME))
    dataset = load_dataset(store, NAME)
    lib, ref = load_library(graphs[1], dataset), couple_reference(dataset)
    spec = parse_spec({"dataset": NAME, "alternatives": args.alternatives,
                       "output": {"formats": ["bvh"]}})  # fmt: skip
    print(f"library: {json.dumps(ref.to_dict())}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, path, scored in songs(args, Path(tmp)):
            row = one_song(name, path, graphs, spec, Path(tmp), lib if scored else None, ref)
            print_row(row)
            rows.append(row)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "bench_couple.json").write_text(
            json.dumps({"library": ref.to_dict(), "rows": rows}, indent=1)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
