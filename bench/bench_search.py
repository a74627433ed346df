"""Graph build and search benchmark (issue 5; ChoreoMaster Table 6 for comparison).

1. Full build of every shared mocap dataset (import, then graph build), timed.
2. Search on graphs of about 100k and 750k edges, made from the salsa graph by repetition: the
   graph is tiled R times (copy r of take T is take ``T#r``; styles jittered so copies differ),
   and every copy of node p keeps 8 of p's edges, each to a random copy of its target (about 8
   edges per node, as the paper's 728k edges over ~92k nodes imply). Songs of 61 s and 148 s at
   124 BPM with phrase structure AABA... (repeat and mirror constraints on), 3 alternatives.
3. Peak RSS of a fresh process that loads the 750k-edge graph from its artifact (memory-mapped)
   and answers a 148 s search: the graph-store's footprint.

Prints a table. ``DANCEGRAPH_SHARED`` points at the shared datasets (default ../shared).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from dancegraph.graph import artifact  # noqa: E402
from dancegraph.graph.build import build_dataset_graph  # noqa: E402
from dancegraph.graph.search import search  # noqa: E402
from dancegraph.motion.dataset import import_dataset, load_manifest  # noqa: E402
from dancegraph.music.analysis import MusicAnalysis  # noqa: E402
from dancegraph.paths import shared_dir  # noqa: E402
from dancegraph.spec import Spec  # noqa: E402
from dancegraph.store import FileStore  # noqa: E402

EDGES_PER_NODE = 8


def song(seconds: float, tempo: float = 124.0, seed: int = 0) -> MusicAnalysis:
    """A synthetic 4/4 song: 8-bar phrases A A B A C A B A ..., meter ids (0, 1, 0, 2) repeating."""
    rng = np.random.default_rng(seed)
    bar_s = 240.0 / tempo
    n = int(seconds // bar_s)
    labels = "AABACABA"
    starts = np.arange(n) * bar_s
    curves = {lab: rng.random((8, 2, 200)) for lab in sorted(set(labels))}
    tags, onset, seen = [], [], {}
    for t in range(n):
        p, i = divmod(t, 8)
        lab = labels[p % len(labels)]
        if i == 0:
            seen[lab] = seen.get(lab, -1) + 1
        tags.append(
            {"label": lab, "occurrence": seen[lab], "index": i, "meter_id": (0, 1, 0, 2)[i % 4]}
        )
        onset.append(curves[lab][i])
    scores = rng.random((n, 13))
    bar_beats = starts[:, None] + np.arange(5)[None, :] * bar_s / 4
    return MusicAnalysis(
        duration_s=n * bar_s,
        tempo_bpm=tempo,
        tempo_confidence=1.0,
        meter=4,
        beats=bar_beats[:, :4].ravel(),
        beat_positions=np.tile([1, 2, 3, 4], n),
        downbeats=starts,
        bars=np.stack([starts, starts + bar_s], 1),
        bar_beats=bar_beats,
        phrases=[],
        tags=tags,
        signature_scores=scores,
        signature_topk=np.argsort(-scores, 1)[:, :3],
        bar_onset_rms=np.stack(onset),
        method="synthetic",
    )


def scale_graph(
    g: artifact.MotionGraph, target_edges: int, seed: int = 0
) -> tuple[dict, list[str], dict]:
    """Tile graph ``g`` into about ``target_edges`` edges (see the module docstring)."""
    rng = np.random.default_rng(seed)
    n = g.n_nodes
    reps = max(1, int(np.ceil(target_edges / (EDGES_PER_NODE * n))))
    a = {k: np.asarray(v) for k, v in g.arrays.items()}
    out = {}
    # per-node arrays: every artifact array but the CSR edges and the per-frame motion
    node_keys = [
        k
        for k in artifact.ARRAYS
        if k not in {"indptr", "indices", "costs"} | set(artifact.MOTION_ARRAYS)
    ]
    if "anchoring" in a:  # the optional per-node array (artifact docstring)
        node_keys.append("anchoring")
    for k in node_keys:
        out[k] = np.concatenate([a[k]] * reps)
    n_clips = len(g.clips)
    offs = np.repeat(np.arange(reps), n)
    out["node_clip"] = (out["node_clip"] + offs * n_clips).astype(np.int32)
    out["mirror_of"] = np.where(out["mirror_of"] >= 0, out["mirror_of"] + offs * n, -1).astype(
        np.int32
    )
    out["node_source"] = np.where(
        out["node_source"] >= 0, out["node_source"] + offs[:, None] * n, -1
    ).astype(np.int32)
    out["style"] = (out["style"] + rng.normal(0, 0.05, out["style"].shape)).astype(np.float32)
    # edges: each copy keeps EDGES_PER_NODE of its original's out-edges, to random copies
    deg = np.diff(a["indptr"])
    pick = (
        rng.integers(0, 1 << 30, (reps * n, EDGES_PER_NODE))
        % np.maximum(np.tile(deg, reps), 1)[:, None]
    )
    e = np.tile(a["indptr"][:-1], reps)[:, None] + pick
    dst = a["indices"][e] + rng.integers(0, reps, e.shape) * n
    src = np.repeat(np.arange(reps * n), EDGES_PER_NODE)
    dst = dst.ravel()
    cost = a["costs"][e].ravel()
    key = src.astype(np.int64) * (reps * n) + dst
    _, first = np.unique(key, return_index=True)
    src, dst, cost = src[first], dst[first], cost[first]
    out["indptr"] = np.zeros(reps * n + 1, np.int64)
    np.cumsum(np.bincount(src, minlength=reps * n), out=out["indptr"][1:])
    out["indices"] = dst.astype(np.int32)
    out["costs"] = cost.astype(np.float32)
    for k in artifact.MOTION_ARRAYS:
        out[k] = a[k]
    manifest = dict(g.manifest)
    manifest["clips"] = [f"{c}#{r}" if r else c for r in range(reps) for c in g.clips]
    manifest["bar_frames"] = {}
    ids = []
    for r in range(reps):
        for nid in g.node_ids:
            take, rest = nid.split(":", 1)
            ids.append(f"{take}#{r}:{rest}" if r else nid)
    return out, ids, manifest


def peak_rss_child(path: Path, seconds: float) -> dict:
    code = f"""
import json, time, sys
sys.path.insert(0, {str(ROOT)!r})
from bench.bench_search import song
from dancegraph.graph.artifact import load_graph
from dancegraph.graph.search import search
from dancegraph.spec import Spec
t = time.perf_counter(); g = load_graph({str(path)!r}); load = time.perf_counter() - t
s = song({seconds}); search(g, s, Spec(alternatives=3))
t = time.perf_counter(); search(g, s, Spec(alternatives=3)); q = time.perf_counter() - t
# VmHWM, not getrusage's ru_maxrss: Linux carries ru_maxrss over from the parent (this bench, with
# its graphs in memory) through fork and exec
hwm = next(int(x.split()[1]) for x in open("/proc/self/status") if x.startswith("VmHWM:"))
print(json.dumps({{"load_s": load, "search_s": q, "peak_rss_mb": hwm / 1024}}))
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def timed(fn, repeats: int = 5) -> tuple[float, float]:
    """Median wall and CPU seconds of ``fn()`` (CPU time is what a loaded, shared machine can
    still measure fairly; on an idle machine the two agree)."""
    fn()  # warm (numba cache load)
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return float(np.median(wall)), float(np.median(cpu))


def main() -> int:
    mocap = shared_dir() / "datasets" / "mocap"
    if not mocap.is_dir():
        print(f"shared mocap not found at {mocap}: set DANCEGRAPH_SHARED")
        return 1
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        store = FileStore(Path(tmp) / "store")
        for name in ("cmu-salsa", "cmu-modern"):
            t = time.perf_counter()
            rep = import_dataset(
                mocap / name,
                name,
                store,
                load_manifest(ROOT / "datasets" / "manifests" / f"{name}.yaml"),
            )
            t_imp = time.perf_counter() - t
            info = build_dataset_graph(store, name)
            rows.append(
                (
                    f"build {name}",
                    f"{rep.n_bars} bars → {info['nodes']} nodes, {info['edges']} edges",
                    f"import {t_imp:.1f} s + graph {info['build']['seconds']:.1f} s",
                )
            )
        base = artifact.load_current(store, "cmu-salsa")
        for target, limit in ((100_000, 0.1), (750_000, 0.4)):
            arrays, ids, manifest = scale_graph(base, target)
            key = artifact.write_graph(
                store, f"bench-{target // 1000}k", arrays, manifest, node_ids=ids, version="v1"
            )
            g = artifact.load_graph(store.path(key))
            for seconds in (61.0, 148.0):
                s = song(seconds)
                spec = Spec(alternatives=3)
                t, c = timed(lambda g=g, s=s, spec=spec: search(g, s, spec))
                r = search(g, s, spec)
                viol = sum(len(a.violations) for a in r.alternatives)
                shared = max(
                    len(set(a.nodes) & set(b.nodes)) / len(a.nodes)
                    for i, a in enumerate(r.alternatives)
                    for b in r.alternatives[i + 1 :]
                )
                target_s = f"≤ {limit} s" if seconds == 148.0 else ""
                rows.append(
                    (
                        f"search {g.n_edges / 1000:.0f}k edges, {g.n_nodes} nodes, {seconds:.0f} s song ({s.n_bars} bars)",
                        f"3 alternatives, structure on: {viol} violations, max shared nodes {shared:.0%}",
                        f"wall {t:.3f} s, CPU {c:.3f} s {target_s}",
                    )
                )
            if target == 750_000:
                rss = peak_rss_child(store.path(key), 148.0)
                rows.append(
                    (
                        "graph-store process, 750k-edge graph",
                        f"load (mmap) {rss['load_s']:.2f} s, search {rss['search_s']:.3f} s",
                        f"peak RSS {rss['peak_rss_mb']:.0f} MB (≤ 1500)",
                    )
                )
    w = [max(len(r[i]) for r in rows) for i in range(3)]
    print(f"{'case':<{w[0]}}  {'details':<{w[1]}}  result")
    print("-" * (sum(w) + 10))
    for r in rows:
        print(f"{r[0]:<{w[0]}}  {r[1]:<{w[1]}}  {r[2]}")
    print(
        f"\nmachine: {os.cpu_count()} CPUs ({numba.get_num_threads()} search threads, NUMBA_NUM_THREADS), load average {os.getloadavg()[0]:.1f}; paper (i7-8700): 103k edges 148 s song 1.88 s, 728k edges 11.2 s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
