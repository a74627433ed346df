"""Benchmark: the beat grids of the shared mocap, judged by partner takes and by the takes' own
kinematic beats (docs/mocap-beats.md).

1. cmu-salsa imported as two datasets, the leaders' takes (60_NN) and the followers' (61_NN),
   so that every take is gridded from its own motion only; per partner pair: tempi, tempo
   difference, median beat offset, downbeat agreement (target: 14 of 14 pairs within 1 % and
   40 ms, downbeats agreeing on 80 % of bars).
   The same with each take cut in halves, each half gridded alone.
2. Each take's kinematic beats on its own grid: phase concentration R (beside R of as many
   uniformly random events) and the share of grid beats with a kinematic beat within 0.1 s
   (beside the same grid shifted by half a beat); where the feet land (contact starts) within
   the grid's beats.
3. The whole cmu-salsa import with its manifest (partner rows in the report; target: 60 s),
   cmu-modern with its manifest and gridded from its motion, and the generated demo library
   gridded from its motion against its exact annotations.

Run: ``python -m bench mocap_grid``. The machine's load is printed beside the timings.
"""

from __future__ import annotations

import copy
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dancegraph.motion.contacts import foot_points, point_contacts, step_onsets
from dancegraph.motion.dataset import (
    STEP_BODY_JOINTS,
    STEP_FOOT_JOINTS,
    Dataset,
    import_dataset,
    load_dataset,
    load_manifest,
)
from dancegraph.motion.demo import write_demo_library
from dancegraph.motion.fk import canonical_positions, forward_kinematics
from dancegraph.motion.tempo import (
    STEADY_MIN_CONFIDENCE,
    BeatGrid,
    GridParams,
    estimate_grid,
    nearest_distance,
    partner_agreement,
    step_signals,
)
from dancegraph.paths import REPO_ROOT, shared_dir
from dancegraph.store import FileStore, ObjectStore

TARGET_S = 60.0
MANIFESTS = REPO_ROOT / "datasets" / "manifests"
#: Accuracy tolerance: a grid beat is hit by a kinematic beat within this (s), as the harness.
HIT_S = 0.1


def phase_concentration(events: np.ndarray, beats: np.ndarray) -> float:
    """|mean e^{2πiφ}| of the events' phases φ within the beat intervals that hold them."""
    ev = events[(events >= beats[0]) & (events < beats[-1])]
    if len(ev) == 0:
        return 0.0
    i = np.searchsorted(beats, ev, side="right") - 1
    phase = (ev - beats[i]) / (beats[i + 1] - beats[i])
    return float(abs(np.mean(np.exp(2j * np.pi * phase))))


def mean_phase(events: np.ndarray, beats: np.ndarray) -> float:
    """Circular mean (0 … 1 beat) of the events' phases within the beat intervals."""
    ev = events[(events >= beats[0]) & (events < beats[-1])]
    i = np.searchsorted(beats, ev, side="right") - 1
    phase = (ev - beats[i]) / (beats[i + 1] - beats[i])
    return float(np.angle(np.mean(np.exp(2j * np.pi * phase))) / (2 * np.pi) % 1.0)


def own_grid_sync(ds: Dataset, rng: np.random.Generator) -> list[tuple[float, ...]]:
    """Per clip: R, R of random events, accuracy, accuracy of the half-beat-shifted grid, and
    the step onsets' R and circular mean phase (beats after the grid's beat)."""
    rows = []
    for clip in ds.clips:
        beats, kb = ds.beats(clip.id), ds.kinematic_beats(clip.id)
        if len(beats) < 2:
            continue
        positions, world = forward_kinematics(ds.motion(clip.id))
        points = foot_points(positions, ds.skeleton, world)
        onsets = step_onsets(point_contacts(points, clip.fps), clip.fps)
        n = int(np.sum((kb >= beats[0]) & (kb < beats[-1])))
        chance = np.mean(
            [
                phase_concentration(np.sort(rng.uniform(beats[0], beats[-1], n)), beats)
                for _ in range(200)
            ]
        )
        half = 0.5 * np.diff(beats)
        rows.append(
            (
                phase_concentration(kb, beats),
                float(chance),
                float(np.mean(nearest_distance(beats, kb) <= HIT_S)),
                float(np.mean(nearest_distance(beats[:-1] + half, kb) <= HIT_S)),
                phase_concentration(onsets, beats),
                mean_phase(onsets, beats),
            )
        )
    return rows


def grids(ds: Dataset) -> dict[str, tuple]:
    """clip id → (beats, bar starts, tempo, confidence) of a stored dataset."""
    return {
        c.id: (
            ds.beats(c.id),
            np.array([b.start_s for b in ds.bars if b.clip_id == c.id]),
            c.tempo_bpm,
            c.tempo_confidence,
        )
        for c in ds.clips
    }


def salsa_partners(mocap: Path, store: ObjectStore) -> int:
    manifest = load_manifest(MANIFESTS / "cmu-salsa.yaml")
    seconds, found = {}, {}
    for who in ("60", "61"):
        m = copy.deepcopy(manifest)
        m["files"] = f"{who}_*_scaled.bvh"
        t0 = time.perf_counter()
        import_dataset(mocap / "cmu-salsa", f"salsa-{who}", store, m)
        seconds[who] = time.perf_counter() - t0
        found |= grids(load_dataset(store, f"salsa-{who}"))
    print(
        f"cmu-salsa gridded as two datasets: 60_NN {seconds['60']:.1f} s, 61_NN "
        f"{seconds['61']:.1f} s (load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)"
    )
    head = f"{'pair':<12}{'tempo a':>9}{'tempo b':>9}{'diff %':>8}{'offset ms':>11}{'downbeats %':>13}{'shift':>7}  verdict"
    print(head + "\n" + "-" * len(head))
    n_tempo = n_offset = n_both = n_down = n_steady = n_steady_both = 0
    for a, b in manifest["partners"]:
        (ba, da, ta, ca), (bb, db, tb, cb) = found[a], found[b]
        r = partner_agreement(ba, da, ta, bb, db, tb)
        ok_t, ok_o = r["tempo_diff_pct"] <= 1.0, r["median_offset_ms"] <= 40.0
        n_tempo, n_offset, n_both = n_tempo + ok_t, n_offset + ok_o, n_both + (ok_t and ok_o)
        n_down += r["downbeat_agreement"] >= 0.8
        steady = min(ca, cb) >= STEADY_MIN_CONFIDENCE
        n_steady, n_steady_both = n_steady + steady, n_steady_both + (steady and ok_t and ok_o)
        print(
            f"{a[3:]:<12}{ta:>9.2f}{tb:>9.2f}{r['tempo_diff_pct']:>8.2f}{r['median_offset_ms']:>11.0f}"
            f"{100 * r['downbeat_agreement']:>13.0f}{r['downbeat_shift_beats']:>7}  "
            f"{'agree' if ok_t and ok_o else '-'}"
        )
    n = len(manifest["partners"])
    print(
        f"pairs: tempo within 1 %: {n_tempo}/{n}; median offset <= 40 ms: {n_offset}/{n}; both: "
        f"{n_both}/{n} (target {n}/{n}); downbeats agreeing on >= 80 % of bars: {n_down}/{n}\n"
        f"pairs whose two takes are both steady (confidence >= {STEADY_MIN_CONFIDENCE}): "
        f"{n_steady_both}/{n_steady} agree; with a take flagged no_steady_beat: "
        f"{n_both - n_steady_both}/{n - n_steady} agree\n"
    )

    rng = np.random.default_rng(0)
    rows = np.array(
        [r for who in ("60", "61") for r in own_grid_sync(load_dataset(store, f"salsa-{who}"), rng)]
    )
    med = np.median(rows, axis=0)
    print("kinematic beats on their own take's grid (median over 28 takes)")
    print(
        f"  phase concentration R        {med[0]:.2f}   chance (as many random events) {med[1]:.2f}"
    )
    print(
        f"  beats hit within 0.1 s       {med[2]:.2f}   chance (grid shifted half a beat) {med[3]:.2f}"
    )
    middle = int(np.sum((rows[:, 5] >= 0.3) & (rows[:, 5] <= 0.7)))
    print(
        f"  step onsets (contact starts): R {med[4]:.2f}; their mean phase lies 0.3-0.7 beat "
        f"after the grid's beat in {middle}/{len(rows)} takes (median {med[5]:.2f})\n"
    )
    return n_both


def half_takes(store: ObjectStore, manifest: dict) -> None:
    """Partner agreement on each take's first and second half, each half gridded alone: the
    same takes over other spans than the whole-take numbers the rules were chosen on."""
    pairs = manifest["partners"]
    params = GridParams(prior_bpm=tuple(manifest["tempo_prior_bpm"]))
    halves: dict[str, list[BeatGrid]] = {}
    for who in ("60", "61"):
        ds = load_dataset(store, f"salsa-{who}")
        for clip in ds.clips:
            positions, world = forward_kinematics(ds.motion(clip.id))
            signals = step_signals(
                canonical_positions(ds.skeleton, positions, world, STEP_BODY_JOINTS),
                canonical_positions(ds.skeleton, positions, world, STEP_FOOT_JOINTS),
                ds.kinematic_beats(clip.id),
                clip.fps,
            )
            n = len(signals) // 2
            halves[clip.id] = [
                estimate_grid(part, clip.fps, params) for part in (signals[:n], signals[n:])
            ]
    counts = []
    for half in (0, 1):
        n_tempo = n_both = n_down = 0
        for a, b in pairs:
            ga, gb = halves[a][half], halves[b][half]
            r = partner_agreement(
                ga.beats, ga.bars[:, 0], ga.tempo_bpm, gb.beats, gb.bars[:, 0], gb.tempo_bpm
            )
            ok_t = r["tempo_diff_pct"] <= 1.0
            n_tempo, n_both = n_tempo + ok_t, n_both + (ok_t and r["median_offset_ms"] <= 40.0)
            n_down += r["downbeat_agreement"] >= 0.8
        counts.append((n_both, n_tempo, n_down))
    (b1, t1, d1), (b2, t2, d2) = counts
    print(
        f"takes cut in halves, each half gridded alone: pairs agreeing {b1} + {b2} of "
        f"{2 * len(pairs)} (tempo within 1 %: {t1} + {t2}; downbeats on >= 80 % of bars: "
        f"{d1} + {d2})\n"
    )


def whole_imports(mocap: Path, store: ObjectStore) -> float:
    total = 0.0
    for name in ("cmu-salsa", "cmu-modern"):
        t0 = time.perf_counter()
        report = import_dataset(
            mocap / name, name, store, load_manifest(MANIFESTS / f"{name}.yaml")
        )
        total += time.perf_counter() - t0
        agree = sum(p.get("agree", False) for p in report.partners)
        flagged = sum("no_steady_beat" in c.flags for c in report.clips)
        print(
            f"{name}: {len(report.clips)} clips, {report.n_bars} bars, {len(report.failed)} failed, "
            f"{flagged} no_steady_beat, {report.elapsed_s:.1f} s"
            + (
                f"; partner pairs agreeing in the report: {agree}/{len(report.partners)}"
                if report.partners
                else ""
            )
        )
    manifest = load_manifest(MANIFESTS / "cmu-modern.yaml")
    for key in ("steady_beat", "tempo_bpm", "first_downbeat_s"):
        manifest.pop(key)
    report = import_dataset(mocap / "cmu-modern", "modern-gridded", store, manifest)
    conf = [c.tempo_confidence for c in report.clips]
    flagged = sum("no_steady_beat" in c.flags for c in report.clips)
    print(
        f"cmu-modern gridded from its motion: {flagged}/{len(report.clips)} no_steady_beat, "
        f"confidence median {np.median(conf):.2f} (max {max(conf):.2f})"
    )
    return total


def demo(store: ObjectStore, tmp: Path) -> None:
    folder = write_demo_library(tmp / "demo", seed=0)
    truth = json.loads((folder / "manifest.json").read_text())
    manifest = copy.deepcopy(truth)
    for clip in manifest["clips"].values():
        for key in ("bars", "signatures", "tempo_bpm"):
            clip.pop(key)
    import_dataset(folder, "demo-gridded", store, manifest)
    ds = load_dataset(store, "demo-gridded")
    print("generated demo library gridded from its motion, against its exact annotations")
    for clip in ds.clips:
        t = truth["clips"][clip.id]
        true_bars = np.array(t["bars"])
        starts = np.array([b.start_s for b in ds.bars if b.clip_id == clip.id])
        on_downbeat = np.mean(nearest_distance(starts, true_bars[:, 0]) <= 1.5 / clip.fps)
        offset = np.median(nearest_distance(np.unique(true_bars), ds.beats(clip.id))) * 1000
        print(
            f"  {clip.id:<12} tempo {clip.tempo_bpm:7.2f} (true {t['tempo_bpm']:.0f}, "
            f"{100 * (clip.tempo_bpm / t['tempo_bpm'] - 1):+.2f} %), beats {offset:4.1f} ms off, "
            f"bars on a true downbeat {100 * on_downbeat:.0f} %"
        )


def main() -> int:
    mocap = shared_dir() / "datasets" / "mocap"
    with tempfile.TemporaryDirectory(prefix="bench-grid-") as tmp:
        store = FileStore(Path(tmp) / "store")
        demo(store, Path(tmp))
        if not mocap.is_dir():
            print(f"shared mocap not found at {mocap}; set DANCEGRAPH_SHARED")
            return 0
        print()
        salsa_partners(mocap, store)
        half_takes(store, load_manifest(MANIFESTS / "cmu-salsa.yaml"))
        total = whole_imports(mocap, store)
    verdict = "ok" if total <= TARGET_S else "OVER TARGET"
    print(f"salsa + modern imports: {total:.1f} s, target <= {TARGET_S:.0f} s: {verdict}")
    return 0 if total <= TARGET_S else 1


if __name__ == "__main__":
    sys.exit(main())
