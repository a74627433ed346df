"""Sync of the rendered dance to its music (issue 24): the seeds' metrics beside their chance rows.

Usage: ``python bench/bench_sync.py [--generated N] [--no-cc] [--real DIR [--real-per-genre K]]
[--alternatives K] [--stops-on-beats] [--beat-accent A] [--accent-row A] [--rows ROW...]
[--out DIR]``.

The harness's Table-3 analog (``dancegraph.eval``: rows ``ours``, ``no_rhythm``,
``random_walk``, every dance rendered and measured at 60 fps) on the cmu-salsa graph, imported
and built here from the shared mocap, for two song sets: the CC recordings and N generated songs
(``music.generator``, seeds 3000…); on the generated songs also the generated demo library,
whose accents sit exactly on its bars' signatures (the exact-truth reference); with ``--real``
(default ``$DANCEGRAPH_REAL_MUSIC``) also real recordings from outside the project: the audio
files of ``DIR/audio`` (or ``DIR``), the first K of each genre (the name up to its first ``.``
or ``_``; GTZAN's 15-20 s clips in ``bench_real_music``'s layout: many short dances, so the
mean over songs is steadier than the four CC songs alone). Per set it prints
the sync table (value, half-beat and other-song chance rows) and, per song, ``ours``'s phase
concentration R, BAS (Bailando) gain over its half-beat chance (beside the song's ceiling,
``bas_ceiling``, and the gain of BAS on the tracker's beats) and CM beat accuracy (beside its
ceiling, ``cm_ceiling``): reported rows, no longer targets (issue 37). Beside the sync rows,
naturalness (issue 37; ``metrics.naturalness``), with its targets checked on the cmu-salsa sets:
per row the pulse depth (mean joint speed folded on the song's beats, 8 bins, 1 - min/max)
beside the library's on its own grids, the speed factor of the whole map from song time to the
takes' time outside the seams (within [0.8, 1.25]), the recovered-grid check (the
importer's estimator on the dance: tempo within 1 %, median offset <= 40 ms, downbeats >= 80 %)
(passed on >= 90 % of the dances) and its other-song chance row (<= 20 %), FID_k, and the
two-sample classifier's balanced accuracy per song (<= 0.65 on songs in salsa's tempo range)
against the library's takes and against the same takes with the renderer's foot cleanup, beside
its library-against-library chance rows; the ``ours`` row is danced again with the beat
accent ``--accent-row`` (default 0.4; 0: not run) for the stylization's cost.
``metrics.json`` and ``report.html`` of each run go to ``--out`` (default: a temporary folder,
removed).
``DANCEGRAPH_SHARED`` points at the shared datasets (default ../shared).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from dancegraph.errors import DanceGraphError  # noqa: E402
from dancegraph.eval import harness  # noqa: E402
from dancegraph.graph import artifact  # noqa: E402
from dancegraph.graph.build import build_graph  # noqa: E402
from dancegraph.metrics import beats as mbeats  # noqa: E402
from dancegraph.motion.dataset import import_dataset, load_dataset, load_manifest  # noqa: E402
from dancegraph.motion.demo import write_demo_library  # noqa: E402
from dancegraph.music.generator import generate_song, write_song  # noqa: E402
from dancegraph.paths import shared_dir  # noqa: E402
from dancegraph.spec import Spec  # noqa: E402
from dancegraph.store import FileStore, ObjectStore  # noqa: E402

ROWS = ["ours", "no_rhythm", "random_walk"]
NATURAL = (
    ("pulse_depth", "pulse"),
    ("speed_factor_min", "speed min"),
    ("speed_factor_max", "speed max"),
    ("grid_passed", "grid ok"),
    ("grid_passed_other", "chance"),
    ("fid_k", "FID_k"),
    ("classifier", "classifier"),
    ("classifier_cleaned", "vs cleaned"),
)
METRICS = ("cm_accuracy", "beat_accuracy", "bas_bailando", "bas_fact", "bas_beats", "phase_r")
TARGET_GRID = 0.9
TARGET_GRID_CHANCE = 0.2
TARGET_SPEED = (0.8, 1.25)
TARGET_CLASSIFIER = 0.65
#: salsa's tempo range (the cmu-salsa manifest's prior): songs inside it are danced near the
#: takes' own tempo, where the two-sample test's target applies
STYLE_RANGE_BPM = (150.0, 220.0)


def _library(store: ObjectStore, name: str, folder: Path, manifest: dict) -> harness.Library:
    import_dataset(folder, name, store, manifest)
    dataset = load_dataset(store, name)
    build_graph(dataset, store)
    return harness.load_library(artifact.load_current(store, name), dataset)


def _fmt(v) -> str:
    return "   –  " if v is None else f"{v:6.3f}"


def _print_sync(title: str, metrics: dict) -> None:
    print(f"\n{title}: value / half-beat chance / other-song chance")
    print("row          " + "  ".join(f"{m:<22}" for m in METRICS))
    for row, entry in metrics["sync"].items():
        cells = [
            f"{_fmt(entry[m]['value'])}{_fmt(entry[m]['half_beat'])}{_fmt(entry[m]['other_song'])}"
            for m in METRICS
        ]
        print(f"{row:<12} " + "  ".join(cells))


def _print_natural(title: str, runs: dict[str, dict]) -> None:
    """The naturalness rows of each run (label: its ``metrics.json``), then per song ``ours``'s
    pulse depth, recovered-grid passes and classifier accuracy in every run."""
    library = next(iter(runs.values()))["library"]
    pulse = library["pulse"] or {}
    print(
        f"\n{title}: naturalness (library's takes on their own grids: pulse depth median "
        f"{_fmt(pulse.get('median'))}; two-sample test library against library "
        f"{_fmt(library['classifier_chance'])}, cleaned takes against cleaned "
        f"{_fmt(library.get('classifier_chance_cleaned'))})"
    )
    print("run      row          " + "".join(f"{name:>11}" for _, name in NATURAL))
    for label, metrics in runs.items():
        for row, entry in metrics["rows"].items():
            print(
                f"{label:<8} {row:<12} " + "".join(f"{_fmt(entry.get(k)):>11}" for k, _ in NATURAL)
            )
    for song_no, song in enumerate(next(iter(runs.values()))["songs"]):
        cells = []
        for label, metrics in runs.items():
            ours = metrics["songs"][song_no]["rows"]["ours"]
            dances = ours["dances"]
            depth = sum(d.get("pulse_depth", 0.0) for d in dances) / max(len(dances), 1)
            passed = sum(bool(d.get("grid_passed")) for d in dances)
            chance = sum(bool(d.get("grid_passed_other")) for d in dances)
            cells.append(
                f"{label}: pulse {depth:.3f} grid {passed}/{len(dances)} (chance {chance}) "
                f"classifier {_fmt(ours.get('classifier'))} / "
                f"{_fmt(ours.get('classifier_cleaned'))}"
            )
        print(f"  {song['song'][:30]:<30} " + " | ".join(cells))


def bas_ceiling(grid: mbeats.SyncGrid) -> float:
    """The BAS (Bailando) gain over its half-beat chance row of a dance whose motion beats are
    exactly the tracker's beats: what the best dance on the song's grid can reach where
    librosa's percussive beats (the BAS's music side) disagree with the tracker's."""
    a, b = grid.span
    music = mbeats.within(grid.percussive_beats, a, b)
    beats = mbeats.within(grid.beats, a, b)
    half = mbeats.half_beat_shift(music, grid.beats)
    return mbeats.beat_align_score(music, beats, "bailando") - mbeats.beat_align_score(
        half, beats, "bailando"
    )


def cm_ceiling(grid: mbeats.SyncGrid) -> float:
    """The CM beat accuracy of a dance whose motion beats are exactly the tracker's beats: the
    share of the song's rhythm points that lie on a beat (the rest are on half beats), what a
    dance that stops on the beats and nowhere else can reach."""
    a, b = grid.span
    points = mbeats.within(grid.rhythm_points, a, b)
    if points.size == 0:
        return float("nan")
    return mbeats.beat_accuracy(points, mbeats.within(grid.beats, a, b))


def _sync_per_song(metrics: dict, songs: list[harness.Song]) -> None:
    """Print ours' sync numbers per song, reported rows beside their ceilings (issue 37 retired
    them as targets): R, the BAS (Bailando) gain over its half-beat chance with the song's
    ceiling (``bas_ceiling``) and the gain of BAS on the tracker's beats, CM beat accuracy with
    its ceiling (``cm_ceiling``) and its ratio to the half-beat chance."""
    ceilings = {song.name: bas_ceiling(song.grid) for song in songs}
    cm_ceilings = {song.name: cm_ceiling(song.grid) for song in songs}
    print("per song, ours (mean of alternatives; reported, not targets):")
    for song in metrics["songs"]:
        dances = song["rows"]["ours"]["dances"]

        def mean(key: str, ds=dances) -> float:
            vals = [d[key] for d in ds if d.get(key) is not None]
            return sum(vals) / len(vals) if vals else float("nan")

        r, cm, cm_half = mean("phase_r"), mean("cm_accuracy"), mean("cm_accuracy_half")
        gain = mean("bas_bailando") - mean("bas_bailando_half")
        on_beats = mean("bas_beats") - mean("bas_beats_half")
        ratio = cm / cm_half if cm_half > 0 else float("inf")
        print(
            f"  {song['song'][:44]:<44} R {r:.3f}  BAS gain {gain:+.3f} "
            f"(ceiling {ceilings.get(song['song'], float('nan')):+.3f}; beats {on_beats:+.3f})  "
            f"CM acc {cm:.3f} (ceiling {cm_ceilings.get(song['song'], float('nan')):.3f}; "
            f"{ratio:.2f} x chance)"
        )


def _natural_targets(metrics: dict) -> int:
    """Print the spec's ``ours`` row against issue 37's targets: recovered-grid check passed on
    >= ``TARGET_GRID`` of the dances and its chance row on <= ``TARGET_GRID_CHANCE``, speed
    factor within ``TARGET_SPEED``, the two-sample classifier <= ``TARGET_CLASSIFIER`` on the
    songs inside ``STYLE_RANGE_BPM``; the number missed."""
    dances = [d for song in metrics["songs"] for d in song["rows"]["ours"]["dances"]]
    passed = sum(bool(d.get("grid_passed")) for d in dances) / max(len(dances), 1)
    chance = sum(bool(d.get("grid_passed_other")) for d in dances) / max(len(dances), 1)
    lo = min(d.get("speed_factor_min", 1.0) for d in dances) if dances else 1.0
    hi = max(d.get("speed_factor_max", 1.0) for d in dances) if dances else 1.0
    inside = [
        s["rows"]["ours"].get("classifier")
        for s in metrics["songs"]
        if STYLE_RANGE_BPM[0] <= s["analysis"]["tempo_bpm"] <= STYLE_RANGE_BPM[1]
    ]
    worst = max((c for c in inside if c is not None), default=None)
    checks = [
        (f"recovered grid passed {passed:.2f} >= {TARGET_GRID}", passed >= TARGET_GRID),
        (f"its chance row {chance:.2f} <= {TARGET_GRID_CHANCE}", chance <= TARGET_GRID_CHANCE),
        (
            f"speed factor {lo:.2f}-{hi:.2f} within {TARGET_SPEED}",
            TARGET_SPEED[0] <= lo and hi <= TARGET_SPEED[1],
        ),
        (
            f"classifier on songs in {STYLE_RANGE_BPM} BPM {_fmt(worst).strip()} <= "
            f"{TARGET_CLASSIFIER}",
            worst is None or worst <= TARGET_CLASSIFIER,
        ),
    ]
    for text, ok in checks:
        print(f"  {'ok  ' if ok else 'MISS'} {text}")
    return sum(not ok for _, ok in checks)


def real_songs(folder: Path, per_genre: int) -> list[Path]:
    """The first ``per_genre`` audio files (by name) of each genre in ``folder/audio`` (or
    ``folder``); the genre is the name up to its first ``.`` or ``_``."""
    audio = folder / "audio" if (folder / "audio").is_dir() else folder
    suffixes = {".wav", ".ogg", ".flac", ".mp3"}
    picked: dict[str, list[Path]] = {}
    for path in sorted(p for p in audio.iterdir() if p.suffix.lower() in suffixes):
        genre = re.split(r"[._]", path.name, maxsplit=1)[0]
        if len(picked.setdefault(genre, [])) < per_genre:
            picked[genre].append(path)
    return [p for paths in picked.values() for p in paths]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generated", type=int, default=4, help="generated songs (default 4)")
    ap.add_argument("--no-cc", action="store_true", help="skip the CC recordings")
    ap.add_argument("--alternatives", type=int, default=3)
    ap.add_argument("--out", default=None, help="folder for metrics.json / report.html")
    ap.add_argument(
        "--real",
        default=os.environ.get("DANCEGRAPH_REAL_MUSIC"),
        help="folder of real recordings (default $DANCEGRAPH_REAL_MUSIC; none: skipped)",
    )
    ap.add_argument("--real-per-genre", type=int, default=3, help="real songs per genre")
    ap.add_argument(
        "--stops-on-beats",
        action="store_true",
        help="render with the renderer's stops on the beats (spec output.stops_on_beats)",
    )
    ap.add_argument(
        "--beat-accent",
        type=float,
        default=None,
        help="the renderer's beat accent (spec output.beat_accent; default the spec's, 0: off)",
    )
    ap.add_argument(
        "--accent-row",
        type=float,
        default=0.4,
        help="dance ours again with this beat accent for the naturalness table (0: not run)",
    )
    ap.add_argument("--rows", nargs="+", default=ROWS, help=f"harness rows (default {ROWS})")
    args = ap.parse_args()
    shared = shared_dir() / "datasets"
    if not (shared / "mocap" / "cmu-salsa").is_dir():
        print(f"shared mocap not found under {shared}: set DANCEGRAPH_SHARED")
        return 1
    output: dict = {"stops_on_beats": args.stops_on_beats}
    if args.beat_accent is not None:
        output["beat_accent"] = args.beat_accent
    spec = Spec.model_validate({"alternatives": args.alternatives, "output": output})
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        out = Path(args.out) if args.out else tmp / "out"
        store = FileStore(tmp / "store")
        salsa = _library(
            store,
            "cmu-salsa",
            shared / "mocap" / "cmu-salsa",
            load_manifest(ROOT / "datasets" / "manifests" / "cmu-salsa.yaml"),
        )
        sets: list[tuple[str, harness.Library, list[harness.Song]]] = []
        if not args.no_cc:
            cc = sorted((shared / "music" / "cc").glob("*.ogg"))
            sets.append(("CC songs, cmu-salsa", salsa, [harness.load_song(p) for p in cc]))
        if args.real:
            real = []
            for path in real_songs(Path(args.real), args.real_per_genre):
                try:
                    real.append(harness.load_song(path))
                except DanceGraphError as exc:  # reported, the rest go on
                    print(f"{path.name}: skipped ({exc.code})")
            sets.append(("real recordings, cmu-salsa", salsa, real))
        if args.generated:
            wavs = [
                write_song(generate_song(3000 + i), tmp / "songs", f"generated-{3000 + i}")[0]
                for i in range(args.generated)
            ]
            songs = [harness.load_song(p) for p in wavs]
            sets.append(("generated songs, cmu-salsa", salsa, songs))
            lib = write_demo_library(tmp / "demo")
            demo = _library(store, "demo", lib, json.loads((lib / "manifest.json").read_text()))
            sets.append(("generated songs, demo library", demo, songs))
        missed = 0
        accented = spec.model_copy(
            update={"output": spec.output.model_copy(update={"beat_accent": args.accent_row})}
        )
        for k, (title, lib, songs) in enumerate(sets):
            metrics = harness.evaluate(songs, lib, spec, out / f"set{k}", rows=args.rows)
            _print_sync(title, metrics)
            _sync_per_song(metrics, songs)
            runs = {"spec": metrics}
            if args.accent_row > 0:
                runs[f"acc {args.accent_row:g}"] = harness.evaluate(
                    songs, lib, accented, out / f"set{k}-accent", rows=["ours"]
                )
            _print_natural(title, runs)
            if lib is salsa:
                missed += _natural_targets(metrics)
    print(f"\n{missed} naturalness targets missed; {time.perf_counter() - t0:.0f} s wall")
    return 0


if __name__ == "__main__":
    sys.exit(main())
