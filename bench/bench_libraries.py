"""Libraries benchmark: a tenant's motion library uploaded, imported and built through the API,
and the graph store holding many libraries under its memory budget.

- ``--salsa``: cmu-salsa (28 takes, ``$DANCEGRAPH_SHARED/datasets/mocap/cmu-salsa`` with
  ``datasets/manifests/cmu-salsa.yaml``) pushed through ``POST /v1/datasets`` to a running
  service until built: the embedded default (``dancegraph serve --embedded``: SQLite, filesystem
  broker, one Celery worker) and Redis mode (PostgreSQL + Redis + uvicorn + a Celery worker);
  seconds to the 202, in the import, in the build, in all.
- ``--music``: the same for 30 generated takes with the music each is danced to
  (``write_demo_library(n_takes=30, with_music=True)``: grids from the music), embedded.
- ``--graphstore N``: N generated libraries imported and built as the worker does, then a
  graph store (``LocalGraphStore``) under a budget of ``--budget-graphs`` graphs' arrays serves
  a search on each in turn (each one cold): resident bytes after each against the budget,
  seconds to load a graph not in memory, seconds from the load to the search's answer.

Run: ``.venv/bin/python bench/bench_libraries.py [--salsa] [--music] [--graphstore 20]``.
Redis-mode rows need PostgreSQL and Redis on 127.0.0.1. Numbers are for the machine it runs on.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from tests.services import test_worker_harness as h  # noqa: E402  (the tests' process harness)


def push(cluster: h.Cluster, folder: Path, name: str, manifest: Path | None) -> dict:
    """Upload ``folder`` and poll until built; the phases' seconds and the final resource."""
    import httpx

    from services.cli import push_library

    stages: dict[str, float] = {}
    t0 = time.perf_counter()
    with httpx.Client(base_url=cluster.api_url, timeout=600) as client:
        get, post = client.get, client.post

        def timed_get(url, **kw):
            r = get(url, **kw)
            stages.setdefault(r.json().get("stage", ""), time.perf_counter() - t0)
            return r

        def timed_post(url, **kw):
            r = post(url, **kw)
            stages["accepted"] = time.perf_counter() - t0
            return r

        client.get, client.post = timed_get, timed_post  # type: ignore[method-assign]
        out = push_library(
            client, folder, cluster.api_key, name=name, manifest=manifest, poll_s=0.25
        )
    total = time.perf_counter() - t0
    if out.get("status") != "succeeded":
        raise RuntimeError(f"{name}: {out}")
    return {"total_s": total, "stages": stages, "library": out}


def service(kind: str, home: Path) -> h.Cluster:
    """A running deployment: 'embedded' (serve --embedded) or 'redis' (PG, Redis, uvicorn, Celery)."""
    if kind == "embedded":
        c = h.make_cluster(
            home, f"sqlite:///{home / 'dancegraph.db'}", "filesystem://", home / "store"
        )
        c.start_embedded()
    else:
        h.require_servers()
        h.flush_redis()
        c = h.make_cluster(home, h.create_pg_database(), h.redis_url(), home / "store")
        c.start_api()
        c.start_worker("w1")
    c.api_key = h.create_key(c.database_url, "bench")
    return c


def bench_upload(kind: str, folder: Path, name: str, manifest: Path | None) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        c = service(kind, Path(tmp))
        try:
            got = push(c, folder, name, manifest)
        finally:
            c.stop_all()
            if kind == "redis":
                h.drop_pg_database(c.database_url)
    lib, st = got["library"], got["stages"]
    takes = len(lib["takes"])
    minutes = sum(t["duration_s"] or 0 for t in lib["takes"]) / 60
    print(
        f"{kind:<9} {name:<14} {takes:>5} {minutes:>6.1f} {lib['nodes']:>6} {lib['edges']:>7}"
        f" {st.get('accepted', 0):>7.1f} {st.get('build', float('nan')):>9.1f}"
        f" {got['total_s']:>7.1f}  worker: {lib.get('seconds') or '-'}"
    )


def bench_graphstore(n: int, budget_graphs: float) -> None:
    from dancegraph.graph import artifact
    from dancegraph.graph.build import build_dataset_graph
    from dancegraph.motion.dataset import import_dataset
    from dancegraph.motion.demo import write_demo_library
    from dancegraph.music.analysis import analyze
    from dancegraph.music.generator import generate_song
    from dancegraph.spec import parse_spec
    from dancegraph.store import FileStore
    from services.common.libraries import new_graph_name
    from services.graphstore.client import LocalGraphStore, graph_nbytes

    with tempfile.TemporaryDirectory() as tmp:
        store = FileStore(Path(tmp) / "store")
        names = []
        t0 = time.perf_counter()
        for i in range(n):  # each a different library: other seeds, other take counts
            lib = write_demo_library(Path(tmp) / f"lib{i}", seed=i, n_takes=6 + i % 5)
            name = new_graph_name()
            import_dataset(lib, name, store, strict=True)
            build_dataset_graph(store, name)
            names.append(name)
        made = time.perf_counter() - t0
        sizes = [graph_nbytes(artifact.load_current(store, nm)) for nm in names]
        budget = int(budget_graphs * statistics.mean(sizes))
        y = generate_song(
            3, meter=4, tempo_bpm=118.0, form=["A", "B", "A"], section_bars={"A": 8, "B": 8}
        )
        song = analyze(y.y, y.sr)
        local = LocalGraphStore(store, budget)
        loads, searches, peak = [], [], 0
        for name in names + names[:5]:  # a second round: evicted ones load again
            t = time.perf_counter()
            local.graph(name)
            loads.append(time.perf_counter() - t)
            t = time.perf_counter()
            local.search(song, parse_spec({"alternatives": 1}, dataset=name))
            searches.append(time.perf_counter() - t)
            peak = max(peak, local.memory()["resident_bytes"])
        mem = local.memory()
    print(
        f"{n} libraries made (import + build) in {made:.1f} s; graph arrays {min(sizes) / 2**20:.1f}-"
        f"{max(sizes) / 2**20:.1f} MiB"
    )
    print(
        f"budget {budget / 2**20:.1f} MiB ({budget_graphs:g} graphs): peak resident {peak / 2**20:.1f} MiB"
        f" ({'under' if peak <= budget else 'OVER'}), {mem['graphs']} loaded at the end, {mem['evictions']} evictions"
    )
    print(
        f"cold load s: p50 {statistics.median(loads):.3f} max {max(loads):.3f}; load -> search answered s:"
        f" p50 {statistics.median(searches):.3f} max {max(searches):.3f} (search starts at the load's end)"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--salsa", action="store_true")
    ap.add_argument("--music", action="store_true")
    ap.add_argument("--modes", default="embedded,redis")
    ap.add_argument("--graphstore", type=int, default=0, metavar="N")
    ap.add_argument("--budget-graphs", type=float, default=4.0)
    args = ap.parse_args()
    if args.salsa or args.music:
        print(
            f"{'mode':<9} {'library':<14} {'takes':>5} {'min':>6} {'nodes':>6} {'edges':>7} {'202 s':>7} {'build@ s':>9} {'total s':>7}"
        )
    if args.salsa:
        shared = Path(os.environ.get("DANCEGRAPH_SHARED", REPO.parent / "shared"))
        salsa = shared / "datasets" / "mocap" / "cmu-salsa"
        for kind in args.modes.split(","):
            bench_upload(
                kind, salsa, "salsa-upload", REPO / "datasets" / "manifests" / "cmu-salsa.yaml"
            )
    if args.music:
        from dancegraph.motion.demo import write_demo_library

        with tempfile.TemporaryDirectory() as tmp:
            lib = write_demo_library(Path(tmp) / "music", n_takes=30, with_music=True)
            bench_upload("embedded", lib, "music-takes", None)
    if args.graphstore:
        bench_graphstore(args.graphstore, args.budget_graphs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
