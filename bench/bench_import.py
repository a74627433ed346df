"""Benchmark: import all shared mocap (cmu-salsa + cmu-modern) with the repo's manifests.

Target: ≤ 60 s for both. Prints each import's report table, a timing table, the rhythm
signature distribution next to ChoreoMaster's Table 2 (its 13 common signatures, in the table's
order), and the salsa import at the files' 120 fps header (the frame-rate check).
Run: ``python -m bench import`` (or ``make bench``).
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections import Counter

from dancegraph.motion.dataset import import_dataset, load_dataset, load_manifest
from dancegraph.paths import REPO_ROOT, shared_dir
from dancegraph.rhythm.signatures import COMMON_SIGNATURES
from dancegraph.store import FileStore, ObjectStore

TARGET_S = 60.0


def main() -> int:
    mocap = shared_dir() / "datasets" / "mocap"
    if not mocap.is_dir():
        print(f"shared mocap not found at {mocap}; set DANCEGRAPH_SHARED")
        return 0
    with tempfile.TemporaryDirectory(prefix="bench-import-") as tmp:
        return run(mocap, FileStore(tmp))


def run(mocap, store: ObjectStore) -> int:
    reports = {}
    total = 0.0
    for name in ("cmu-salsa", "cmu-modern"):
        manifest = load_manifest(REPO_ROOT / "datasets" / "manifests" / f"{name}.yaml")
        t0 = time.perf_counter()
        reports[name] = import_dataset(mocap / name, name, store, manifest)
        total += time.perf_counter() - t0
        print(reports[name].table(), "\n", flush=True)

    print(f"{'dataset':<12}{'clips':>6}{'frames':>9}{'bars':>6}{'failed':>7}{'seconds':>9}")
    for name, r in reports.items():
        frames = sum(c.n_frames for c in r.clips)
        print(
            f"{name:<12}{len(r.clips):>6}{frames:>9}{r.n_bars:>6}{len(r.failed):>7}{r.elapsed_s:>9.1f}"
        )
    verdict = "ok" if total <= TARGET_S else "OVER TARGET"
    print(
        f"{'both':<12}{'':>6}{'':>9}{'':>6}{'':>7}{total:>9.1f}   target <= {TARGET_S:.0f} s: {verdict}\n"
    )

    print("rhythm signatures (snapped to ChoreoMaster Table 2's 13 common ones, table order)")
    print(f"{'signature':<11}" + "".join(f"{n:>16}" for n in reports))
    for s in COMMON_SIGNATURES:
        cells = []
        for r in reports.values():
            n = r.signature_counts.get(s, 0)
            cells.append(f"{n:>7} ({100 * n / max(1, r.n_bars):4.1f} %)")
        print(f"{s:<11}" + "".join(f"{c:>16}" for c in cells))
    for name in reports:
        bars = load_dataset(store, name).bars
        exact = sum(b.signature_raw == b.signature for b in bars)
        raw = Counter(b.signature_raw for b in bars if b.signature_raw not in COMMON_SIGNATURES)
        top = ", ".join(f"{s} x{n}" for s, n in raw.most_common(5))
        print(
            f"{name}: {exact}/{len(bars)} bars read exactly a common signature; "
            f"most frequent others: {top or '-'}"
        )
    print()

    # The frame-rate check: salsa read at its 120 fps header.
    manifest = load_manifest(REPO_ROOT / "datasets" / "manifests" / "cmu-salsa.yaml")
    manifest.pop("fps")
    wrong = import_dataset(mocap / "cmu-salsa", "salsa-at-120", store, manifest)
    flagged = sum("tempo_outside_prior" in c.flags for c in wrong.clips)
    print(f"salsa at the 120 fps header: {flagged}/{len(wrong.clips)} clips tempo_outside_prior")
    for w in wrong.warnings:
        print(f"  WARNING {w}")
    return 0 if total <= TARGET_S else 1


if __name__ == "__main__":
    sys.exit(main())
