"""Service benchmark: end-to-end latency through the API, embedded and Redis modes.

Measures, on the demo motion library and songs made by the project's generator:
- cold start: ``dancegraph serve --embedded`` launched → API answering and worker ready;
- first job after a cold start (nothing warm: analysis, graph, Blender);
- latency of one new song (``--song-seconds``, default 180 s) submitted through the API until
  ``succeeded``: BVH only and BVH+FBX, embedded mode and Redis mode (PostgreSQL + Redis + uvicorn
  + Celery worker processes), warm workers, p50 / max over ``--runs`` songs;
- the same song again (its analysis cached), and the first FBX job of a worker (Blender starts);
- throughput with 2 worker processes (Redis mode, BVH only): ``--songs`` new songs at once.

Run: ``.venv/bin/python bench/bench_service.py [--runs 3 --songs 6]`` (``make bench``). Prints a
table. The first job after a cold start also pays numba compilation when the JIT cache is stale
(after an edit of the numeric code); later starts load it from ``__pycache__``. Redis-mode rows
need PostgreSQL and Redis on 127.0.0.1 (skipped otherwise). Numbers are for the machine it runs
on; they are not asserted anywhere.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from tests.services import test_worker_harness as h  # noqa: E402  (the same process harness as the tests)

BVH = {"dataset": h.DATASET, "alternatives": 3, "output": {"formats": ["bvh"]}}
FBX = {"dataset": h.DATASET, "alternatives": 3, "output": {"formats": ["bvh", "fbx"]}}


class Songs:
    """New songs on demand (each a different seed, so each one is analysed)."""

    def __init__(self, folder: Path, seconds: float):
        self.folder, self.seconds, self.seed = folder, seconds, 1000

    def new(self) -> Path:
        self.seed += 1
        return h.write_test_song(self.folder, self.seed, self.seconds)


def one_job(cluster: h.Cluster, wav: Path, spec: dict) -> float:
    t0 = time.perf_counter()
    job_id = cluster.submit(wav, spec)["id"]
    job = cluster.wait_final([job_id], timeout_s=1800)[job_id]
    if job["status"] != "succeeded":
        raise RuntimeError(f"job {job_id} {job['status']}: {job.get('error')}")
    return time.perf_counter() - t0


def latencies(cluster: h.Cluster, songs: Songs, spec: dict, runs: int) -> list[float]:
    return [one_job(cluster, songs.new(), spec) for _ in range(runs)]


def row(rows: list, mode: str, what: str, values: list[float] | float, unit: str = "s") -> None:
    vals = values if isinstance(values, list) else [values]
    p50 = statistics.median(vals)
    rows.append((mode, what, len(vals), f"{p50:.2f}", f"{max(vals):.2f}", unit))
    print(f"  {mode:9s} {what:42s} p50 {p50:8.2f} {unit}", flush=True)


def bench_embedded(work: Path, demo: Path, songs: Songs, runs: int, rows: list) -> None:
    home = work / "embedded"
    store = h.copy_store(demo, home / "store")
    c = h.make_cluster(home, f"sqlite:///{home / 'dancegraph.db'}", "filesystem://", store)
    for name in ("DANCEGRAPH_DATABASE_URL", "DANCEGRAPH_BROKER_URL", "DANCEGRAPH_BROKER_FOLDER"):
        c.env.pop(name)
    c.env["DANCEGRAPH_JOB_TIMEOUT_S"] = "600"
    try:
        t0 = time.perf_counter()
        c.start_embedded()
        row(rows, "embedded", "cold start (serve → API + worker ready)", time.perf_counter() - t0)
        c.api_key = h.create_key(c.database_url, "bench")
        row(rows, "embedded", "first job after cold start, BVH", one_job(c, songs.new(), BVH))
        row(rows, "embedded", "new song, BVH only (warm)", latencies(c, songs, BVH, runs))
        wav = songs.new()
        one_job(c, wav, BVH)
        row(rows, "embedded", "same song again, BVH (analysis cached)", one_job(c, wav, BVH))
        row(rows, "embedded", "first FBX job (Blender starts)", one_job(c, wav, FBX))
        row(rows, "embedded", "new song, BVH+FBX (warm)", latencies(c, songs, FBX, runs))
    finally:
        c.stop_all()


def bench_redis(work: Path, demo: Path, songs: Songs, runs: int, n_songs: int, rows: list) -> None:
    if not (h.port_open("127.0.0.1", 6379) and h.port_open("127.0.0.1", 5432)):
        print("  redis mode skipped: PostgreSQL or Redis not running", flush=True)
        return
    h.flush_redis()
    url = h.create_pg_database()
    home = work / "redis"
    store = h.copy_store(demo, home / "store")
    c = h.make_cluster(home, url, h.redis_url(), store)
    c.env["DANCEGRAPH_JOB_TIMEOUT_S"] = "600"
    try:
        c.api_key = h.create_key(url, "bench")
        t0 = time.perf_counter()
        c.start_api()
        c.start_worker("w1")
        row(rows, "redis", "cold start (API + 1 worker ready)", time.perf_counter() - t0)
        row(rows, "redis", "first job after cold start, BVH", one_job(c, songs.new(), BVH))
        row(rows, "redis", "new song, BVH only (warm)", latencies(c, songs, BVH, runs))
        wav = songs.new()
        one_job(c, wav, BVH)
        row(rows, "redis", "same song again, BVH (analysis cached)", one_job(c, wav, BVH))
        row(rows, "redis", "first FBX job (Blender starts)", one_job(c, wav, FBX))
        row(rows, "redis", "new song, BVH+FBX (warm)", latencies(c, songs, FBX, runs))
        c.start_worker("w2")
        one_job(c, songs.new(), BVH)  # warm the second worker's graph
        wavs = [songs.new() for _ in range(n_songs)]
        t0 = time.perf_counter()
        ids = [c.submit(w, BVH)["id"] for w in wavs]
        done = c.wait_final(ids, timeout_s=3600)
        elapsed = time.perf_counter() - t0
        ok = sum(d["status"] == "succeeded" for d in done.values())
        row(
            rows,
            "redis",
            f"throughput, 2 workers, {n_songs} new songs",
            ok / elapsed * 60.0,
            "songs/min",
        )
    finally:
        c.stop_all()
        h.drop_pg_database(url)
        h.flush_redis()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--song-seconds", type=float, default=180.0)
    p.add_argument("--runs", type=int, default=3, help="songs per latency row")
    p.add_argument("--songs", type=int, default=6, help="songs in the throughput row")
    p.add_argument("--modes", default="embedded,redis")
    args = p.parse_args(argv)
    rows: list = []
    with tempfile.TemporaryDirectory(prefix="bench-service-") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        demo = h.build_demo_store(work / "demo" / "store")
        print(
            f"demo library imported and graph built in {time.perf_counter() - t0:.1f} s", flush=True
        )
        songs = Songs(work / "songs", args.song_seconds)
        modes = args.modes.split(",")
        if "embedded" in modes:
            bench_embedded(work, demo, songs, args.runs, rows)
        if "redis" in modes:
            bench_redis(work, demo, songs, args.runs, args.songs, rows)
    print()
    print(f"song: {args.song_seconds:.0f} s generated, dataset: demo, 3 alternatives")
    print(f"| {'mode':9s} | {'measure':44s} | {'n':>2s} | {'p50':>8s} | {'max':>8s} | unit      |")
    print(f"|{'-' * 11}|{'-' * 46}|{'-' * 4}|{'-' * 10}|{'-' * 10}|{'-' * 11}|")
    for mode, what, n, p50, mx, unit in rows:
        print(f"| {mode:9s} | {what:44s} | {n:2d} | {p50:>8s} | {mx:>8s} | {unit:9s} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
