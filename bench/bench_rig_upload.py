"""Rig upload benchmark: what parsing an untrusted rig in the sandbox costs, and what it spares.

Measures:
- the sandbox's cost per call (``dancegraph.sandbox.run_sandboxed`` of ``os.getpid``: fork from
  the fork server, limits, one message back), and the fork server's start;
- a small BVH rig's summary read in-process and in the sandbox;
- a small BVH rig's upload through the API (warm), and the largest allowed valid BVH rig (``Settings.max_upload_bytes``, 256 MiB: about 470,000
  frames of the CMU-named test rig) uploaded to a real API process (``uvicorn``, embedded
  SQLite and filesystem store): the API's resident memory before and its peak (VmHWM) after,
  the answer and its time; and the parse child's own peak memory and CPU time against its
  limits (``Settings.rig_parse_memory_bytes``, ``rig_parse_cpu_s``).

Run: ``.venv/bin/python bench/bench_rig_upload.py [--mib 256]``. Prints a table. It writes the
file (and the store's copies, about 1 GB) under a temporary folder it removes. Numbers are for
the machine it runs on; they are not asserted anywhere.
"""

from __future__ import annotations

import argparse
import importlib
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from dancegraph.motion.rig import rig_summary  # noqa: E402
from dancegraph.sandbox import run_sandboxed  # noqa: E402
from tests.motion.hostile_rigs import valid_bvh  # noqa: E402

# this file as an importable module: a sandboxed child finds its functions by module name
this = importlib.import_module("bench.bench_rig_upload")


def _summary_and_cost(path: str) -> tuple[dict, float, float]:
    """In the child: the rig's summary, the child's peak resident memory (MiB), its CPU (s)."""
    summary = rig_summary(path)
    use = resource.getrusage(resource.RUSAGE_SELF)
    return summary, use.ru_maxrss / 1024, use.ru_utime + use.ru_stime


def write_long_bvh(path: Path, size_bytes: int) -> int:
    """The test rig with its one frame repeated until the file is ``size_bytes``; frames."""
    valid_bvh(path)
    head, rest = path.read_text().split("Frames: 1\n", 1)
    frame_time, row = rest.split("\n")[:2]
    row += "\n"
    frames = (size_bytes - len(head) - 64) // len(row)
    with open(path, "w") as fh:
        fh.write(f"{head}Frames: {frames}\n{frame_time}\n")
        chunk = row * 10_000
        for _ in range(frames // 10_000):
            fh.write(chunk)
        fh.write(row * (frames % 10_000))
    return frames


def _kib(pid: int, field: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise KeyError(field)


def bench_sandbox(work: Path, rows: list) -> None:
    t0 = time.perf_counter()
    run_sandboxed(os.getpid)
    rows.append(("fork server start + first call", time.perf_counter() - t0, "s"))
    times = []
    for _ in range(30):
        t0 = time.perf_counter()
        run_sandboxed(os.getpid)  # a call that does nothing and imports nothing
        times.append(time.perf_counter() - t0)
    rows.append(("sandbox call, p50 of 30", 1000 * statistics.median(times), "ms"))
    rows.append(("sandbox call, max of 30", 1000 * max(times), "ms"))
    small = valid_bvh(work / "small.bvh")
    for where, call in (
        ("in-process", lambda: rig_summary(small)),
        ("sandboxed", lambda: run_sandboxed(rig_summary, str(small))),
    ):
        times = []
        for _ in range(10):
            t0 = time.perf_counter()
            call()
            times.append(time.perf_counter() - t0)
        rows.append(
            (f"small BVH rig summary, {where}, p50 of 10", 1000 * statistics.median(times), "ms")
        )


def bench_upload(work: Path, mib: int, rows: list) -> None:
    import httpx

    from services.db import upgrade_schema
    from tests.services import test_worker_harness as h

    big = work / "big.bvh"
    frames = write_long_bvh(big, mib * 2**20 - 4096)
    rows.append((f"largest rig: BVH of {frames} frames", big.stat().st_size / 2**20, "MiB"))
    t0 = time.perf_counter()
    summary, child_mib, child_cpu = run_sandboxed(this._summary_and_cost, str(big))
    rows.append(("  parse child alone: time", time.perf_counter() - t0, "s"))
    rows.append(("  parse child: peak resident memory (limit 2048)", child_mib, "MiB"))
    rows.append(("  parse child: CPU time (limit 30)", child_cpu, "s"))
    db = f"sqlite:///{work / 'dg.db'}"
    upgrade_schema(db)
    cluster = h.make_cluster(work / "home", db, "filesystem://", work / "store")
    try:
        cluster.start_api()
        pid = cluster.procs["api"].pid
        headers = {"X-API-Key": h.create_key(db, "bench")}
        small = valid_bvh(work / "warm.bvh")
        with open(small, "rb") as fh:  # warm: the fork server and the readers are up
            resp = httpx.post(f"{cluster.api_url}/v1/rigs", files={"rig": fh}, headers=headers)
        assert resp.status_code == 201, resp.text
        before = _kib(pid, "VmRSS")
        t0 = time.perf_counter()
        with open(big, "rb") as fh:
            resp = httpx.post(
                f"{cluster.api_url}/v1/rigs",
                files={"rig": ("big.bvh", fh)},
                headers=headers,
                timeout=600,
            )
        took = time.perf_counter() - t0
        assert resp.status_code == 201, resp.text
        peak = _kib(pid, "VmHWM")
        rows.append(("  upload through the API: answer 201 in", took, "s"))
        rows.append(("  API resident memory before", before, "MiB"))
        rows.append(("  API peak resident memory (VmHWM) after", peak, "MiB"))
        rows.append(("  API memory growth (target <= 100)", peak - before, "MiB"))
        times = []
        for _ in range(8):
            with open(small, "rb") as fh:
                t0 = time.perf_counter()
                resp = httpx.post(f"{cluster.api_url}/v1/rigs", files={"rig": fh}, headers=headers)
                times.append(time.perf_counter() - t0)
            assert resp.status_code == 201, resp.text
        rows.append(
            (
                "small BVH rig upload through the API, p50 of 8",
                1000 * statistics.median(times),
                "ms",
            )
        )
        assert summary["joints"] == resp.json()["joints"]
    finally:
        cluster.stop_all()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mib", type=int, default=256, help="size of the largest rig (MiB)")
    args = parser.parse_args(argv)
    rows: list = []
    with tempfile.TemporaryDirectory(prefix="dg-bench-rig-") as tmp:
        bench_sandbox(Path(tmp), rows)
        bench_upload(Path(tmp), args.mib, rows)
    width = max(len(r[0]) for r in rows)
    for what, value, unit in rows:
        print(f"{what:<{width}}  {value:10.2f} {unit}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
