"""Load benchmark of one API process (issue 22's targets): a burst of uploads, a burst of reads.

- ``--uploads`` (default 50) concurrent ``POST /v1/jobs`` of one generated ``--song-seconds``
  (default 180) song, each with its own spec (so each is a new job): status counts, accept
  latency p50 / p95 / max (target: 0 responses 5xx, p95 <= 2 s);
- ``--reads`` (default 200) concurrent ``GET /v1/jobs`` (target: 0 errors).

Production wiring: PostgreSQL and Redis on 127.0.0.1, the API as one ``uvicorn`` process asking
a graph-store process for the catalog (no worker: jobs stay queued; only accepting is
measured), the filesystem object store, or the S3 store with ``--s3-endpoint URL`` (a running
S3-protocol server, e.g. ``moto_server``).
Run: ``.venv/bin/python bench/bench_load.py``. Prints one table; nothing is asserted. Numbers are
for the machine it runs on (a shared 2-core machine gives slower accepts than a server).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from tests.services import test_worker_harness as h  # noqa: E402  (the tests' process harness)

SPEC = {"dataset": h.DATASET, "alternatives": 2, "output": {"formats": ["bvh"]}}


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(q * (len(ordered) - 1))))]


def cpu_seconds(pid: int) -> float:
    """CPU time (user + system) the process has used so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def burst(n: int, call) -> tuple[Counter, list[float]]:
    """``n`` concurrent calls of ``call(i)`` → status (or error kind) counts and latencies."""

    def timed(i: int):
        t0 = time.perf_counter()
        try:
            status = str(call(i).status_code)
        except httpx.HTTPError as exc:
            status = type(exc).__name__
        return status, time.perf_counter() - t0

    with ThreadPoolExecutor(max_workers=n) as pool:
        results = list(pool.map(timed, range(n)))
    return Counter(s for s, _ in results), [t for _, t in results]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--uploads", type=int, default=50)
    ap.add_argument("--reads", type=int, default=200)
    ap.add_argument("--song-seconds", type=float, default=180.0)
    ap.add_argument("--s3-endpoint", default="", help="use the S3 store on this server")
    args = ap.parse_args()
    if not (h.port_open("127.0.0.1", 5432) and h.port_open("127.0.0.1", 6379)):
        print("skipped: needs PostgreSQL and Redis on 127.0.0.1")
        return 0
    with tempfile.TemporaryDirectory(prefix="dg-bench-load-") as tmp:
        home = Path(tmp)
        demo = h.build_demo_store(home / "demo" / "store")
        url = h.create_pg_database()
        h.flush_redis()
        if args.s3_endpoint:
            from tests.conftest import S3_ENV, new_bucket

            store_env = {"AWS_ENDPOINT_URL": args.s3_endpoint, **S3_ENV}
            os.environ.update(store_env)  # this process reads the store too
            bucket = new_bucket(args.s3_endpoint)
            c = h.make_cluster(
                home, url, h.redis_url(), home / "scratch", f"s3://{bucket}/store", store_env
            )
            h.upload_store(demo, c.store)
        else:
            c = h.make_cluster(home, url, h.redis_url(), h.copy_store(demo, home / "store"))
        try:
            song = h.write_test_song(home / "songs", seed=4242, seconds=args.song_seconds)
            data = song.read_bytes()
            c.api_key = h.create_key(url, "bench")
            # as deployed: the graph store is its own process the API asks for the catalog
            port = h.free_port()
            c._spawn(
                "graphstore",
                [str(h.VENV_BIN / "uvicorn"), "services.graphstore.app:app", "--port", str(port)],
            )
            c.env["DANCEGRAPH_GRAPHSTORE_URL"] = f"http://127.0.0.1:{port}"
            h.wait_for(lambda: h.port_open("127.0.0.1", port), 120, "the graph store")
            c.start_api()
            headers = c.headers()

            def upload(i: int) -> httpx.Response:
                spec = json.dumps({**SPEC, "seed": i})
                return httpx.post(
                    c.api_url + "/v1/jobs",
                    headers=headers,
                    files={"audio": (song.name, data), "spec": (None, spec)},
                    timeout=300,
                )

            def read(_i: int) -> httpx.Response:
                return httpx.get(c.api_url + "/v1/jobs?limit=50", headers=headers, timeout=300)

            api_pid = c.procs["api"].pid
            cpu0 = cpu_seconds(api_pid)
            up_status, up_times = burst(args.uploads, upload)
            cpu1 = cpu_seconds(api_pid)
            rd_status, rd_times = burst(args.reads, read)
            cpu2 = cpu_seconds(api_pid)
            load = os.getloadavg()[0]
            if any(k.startswith("5") for k in up_status):  # say why, from the API's log
                errors_logged = [x for x in c.log_text("api").splitlines() if '"error"' in x]
                print("\n".join(errors_logged[-5:])[-3000:])
        finally:
            c.stop_all()
            h.drop_pg_database(url)
            h.flush_redis()
    five = sum(v for k, v in up_status.items() if not k.isdigit() or k.startswith("5"))
    errors = sum(v for k, v in rd_status.items() if k != "200")
    store = "S3 (" + args.s3_endpoint + ")" if args.s3_endpoint else "filesystem"
    print(f"one API process, PostgreSQL + Redis, {store} store; song {len(data) / 1e6:.1f} MB")
    print(f"machine: {os.cpu_count()} cores, load average {load:.1f} after the bursts")
    print("| burst | n | statuses | p50 s | p95 s | max s | API CPU s per request | target |")
    print("|---|---|---|---|---|---|---|---|")
    print(
        f"| POST /v1/jobs | {args.uploads} | {dict(up_status)} | "
        f"{statistics.median(up_times):.2f} | {_percentile(up_times, 0.95):.2f} | "
        f"{max(up_times):.2f} | {(cpu1 - cpu0) / args.uploads:.3f} | "
        f"0 × 5xx ({five}), p95 <= 2 s |"
    )
    print(
        f"| GET /v1/jobs | {args.reads} | {dict(rd_status)} | "
        f"{statistics.median(rd_times):.2f} | {_percentile(rd_times, 0.95):.2f} | "
        f"{max(rd_times):.2f} | {(cpu2 - cpu1) / args.reads:.3f} | 0 errors ({errors}) |"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
