"""Music analysis accuracy and speed on generated songs with exact ground truth, and the outputs
for the CC recordings in ../shared/datasets/music/cc.

Usage: ``python bench/bench_music.py [--songs N] [--hard N] [--seed-base S S]
[--tempo-range LO HI] [--meter 3|4] [--no-cc]`` (default: 24 normal songs from seed 1000, 40 hard from seed
2000, tempos drawn by the seed, about 3 minutes). The analysis' thresholds were measured on
seeds 1000-1029, 2000-2039, 3000-3029, 4000-4029, 6000-6059, 7000-7039, 8000-8039 and (the
whole-grid off-beat threshold) 13000-13029 (``--seed-base NORMAL HARD``); normal 9000-9019 and
hard 12000-12039 were run only after them, as a fresh check, and normal 15000-15029, hard
14000-14039 after the halving parity and the swing mend by sections (2026-11-30), with slow
songs (``--tempo-range 70 95``: normal 17000-17029, hard 16000-16059) and fast ones
(``--tempo-range 150 180``: normal 18000-18039, hard 19000-19029); the split of half-tempo
grids (``beats_split``) was then checked on normal 21000-21029, hard 20000-20039 and, at 150-180
BPM, normal 23000-23029 and hard 22000-22029. The split of fast waltzes counted at half tempo
was checked on 3/4 songs drawn for it (``--meter 3``): normal 28000-28029 and hard 28100-28119
at 150-180 BPM, normal 29000-29029 and hard 29100-29119 at 70-95 BPM; the backbeat term of the
bar grouping was then checked on hard 30000-30039, normal 31000-31029 and (150-180 BPM) hard
32000-32029. Drawn before the next changes (2026-11-30, night): normal 34000-34029, hard
33000-33039, hard 35000-35029 (150-180 BPM) and 36000-36029 (70-95 BPM), where the meter test's
chroma at one-bar lags showed (34024); the slip finder's interquartile mean was then checked
on hard 37000-37039, hard 38000-38029 (150-180), normal 39000-39029 (150-180) and hard
40000-40029 (70-95). Drawn before the dotted-pulse re-decode was checked on them (2026-11-30,
late): hard 41000-41079, 42000-42039 (70-95), 44000-44039 (150-180), normal 43000-43039;
3/4 hard 45000-45029 (150-180) and 46000-46029 (70-95); before the one-octave re-decode was
checked on them: hard 47000-47059, 49000-49039 (150-180), 50000-50039 (70-95), normal
48000-48039, 51000-51039 (70-95), 52000-52039 (150-180); before the bar-clarity meter rule
was checked on them (2026-12-01): hard 53000-53059, 54000-54039 (150-180), 3/4 hard
56000-56029 (150-180), normal 55000-55039 (150-180) and 57000-57039.

Metrics (generated set, each song written as WAV and analysed from the file by ``analyze``):
- beat F and downbeat F: F-measure at ±70 ms against the generator's beats / downbeats;
- meter accuracy: tracked meter == generated meter;
- tempo %: median relative error of the reported tempo, at the metrical level (x1, x2, x1/2)
  nearest the generated one (songs more than 6 % off at every level left out);
- boundary F: inner phrase boundaries at ±3 s against the generated section starts;
- repeats alike: share of pairs of same-label sections whose (majority) labels agree;
  distinct apart: share of pairs of different-label sections whose labels differ;
- signature top-3: share of 4/4 bars whose generated accent pattern (nearest common signature)
  is among the top 3 — on the generated bar grid, so tracker errors do not count;
- "structure on true bars": boundary F / repeats alike with the generator's bars given, i.e. the
  structure stage alone;
- CPU seconds per minute of audio (``time.process_time``, warm: after one song analysed).

Stability on the CC recordings (real music, no annotations; ``--stability``): each recording is
analysed again after a change a listener would not notice — its first 0.73 s or first 10 s cut,
18 dB quieter, resampled to 16 or 48 kHz, through MP3 at 128 kb/s — and the beats and downbeats
are compared with the original's (F at ±70 ms, after the cut's offset, beats in the first second
of either left out) with tempo, meter and bar count. A tracker built for the generator alone
would drift here.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import soundfile as sf

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from dancegraph.music.analysis import (  # noqa: E402
    MusicAnalysis,
    analyze,
    four_beat_bars,
    phrase_unit,
)
from dancegraph.music.decode import load_audio, resample  # noqa: E402
from dancegraph.music.features import frame_features  # noqa: E402
from dancegraph.music.generator import bar_grid, generate_song, write_song  # noqa: E402
from dancegraph.music.signal import beat_f_measure  # noqa: E402
from dancegraph.music.structure import analyze_structure  # noqa: E402
from dancegraph.paths import shared_dir  # noqa: E402
from dancegraph.rhythm.music import music_signatures  # noqa: E402
from dancegraph.rhythm.signatures import nearest_common, to_bits  # noqa: E402


def tempo_error(est_bpm: float, true_bpm: float) -> float:
    """Relative error of a tempo at the metrical level nearest to the truth's (x1, x2 or x1/2:
    a tracker may count either; the level is scored by downbeat F), NaN beyond 6 %."""
    err = min(abs(est_bpm / (true_bpm * level) - 1.0) for level in (1.0, 2.0, 0.5))
    return err if err <= 0.06 else float("nan")


def label_agreement(
    sections: list[dict], bar_starts: np.ndarray, tags: list[dict]
) -> tuple[list[bool], list[bool]]:
    """(alike, apart) pair outcomes: same-label section pairs labelled alike, different-label
    pairs labelled apart, using each section's majority label over the bars starting inside it."""

    def majority(sec: dict) -> str | None:
        labs = [
            tags[i]["label"]
            for i, t in enumerate(bar_starts)
            if sec["start_s"] - 0.05 <= t < sec["end_s"] - 0.05
        ]
        return max(sorted(set(labs)), key=labs.count) if labs else None

    maj = [majority(s) for s in sections]
    alike, apart = [], []
    for i in range(len(sections)):
        for j in range(i + 1, len(sections)):
            if sections[i]["label"] == sections[j]["label"]:
                alike.append(maj[i] is not None and maj[i] == maj[j])
            else:
                apart.append(maj[i] != maj[j])
    return alike, apart


def true_dance_bars(truth: dict) -> tuple[np.ndarray, np.ndarray]:
    """The generator's beats grouped by the analysis bar rule (exact beats, exact meter)."""
    beats = np.asarray(truth["beats"])
    pos = np.asarray(truth["beat_positions"])
    bars, grid, _ = four_beat_bars(beats, pos, truth["meter"], truth["duration_s"])
    return bars, grid


def run_generated(
    n_songs: int,
    n_hard: int,
    out: Path,
    bases: tuple[int, int] = (1000, 2000),
    tempo_range: tuple[int, int] | None = None,
    meter: int | None = None,
) -> list[dict]:
    """Analyse generated songs; with ``tempo_range`` (LO, HI) BPM each song's tempo is pinned
    to ``LO + (7 * seed) % (HI - LO)`` (spread over the range), else drawn from the seed; with
    ``meter`` (3 or 4) every song has that meter."""
    rows = []
    seeds = [(bases[0] + i, False) for i in range(n_songs)]
    seeds += [(bases[1] + i, True) for i in range(n_hard)]
    # Warm-up: the tracker's first call loads weights and compiles; not counted.
    warm = generate_song(
        999, form=["A", "B"], section_bars={"A": 4, "B": 4}, tempo_bpm=120, meter=4
    )
    analyze(warm.y, warm.sr)
    for seed, hard in seeds:
        pinned = {}
        if tempo_range is not None:
            lo, hi = tempo_range
            pinned["tempo_bpm"] = float(lo + (7 * seed) % (hi - lo))
        if meter is not None:
            pinned["meter"] = meter
        song = generate_song(seed, hard=hard, **pinned)
        wav, _ = write_song(song, out, f"song_{seed}")
        tr = song.truth
        t0 = time.process_time()
        a = analyze(wav)
        cpu = time.process_time() - t0
        ref_bounds = [s["start_s"] for s in tr["sections"][1:]]
        est_bounds = [a.bars[p["start_bar"], 0] for p in a.phrases[1:]]
        alike, apart = label_agreement(tr["sections"], a.bars[:, 0], a.tags)
        # The structure stage alone, on the true bars.
        tbars, tgrid = true_dance_bars(tr)
        ff = frame_features(song.y, song.sr)
        st = analyze_structure(ff, tbars, unit=phrase_unit(tr["meter"]))
        t_alike, _ = label_agreement(tr["sections"], tbars[:, 0], st.tags)
        t_bounds = [tbars[p["start_bar"], 0] for p in st.phrases[1:]]
        sig_hits = []
        if tr["meter"] == 4:
            _, g = bar_grid(tr)
            _, topk, _ = music_signatures(ff.accent, ff.frame_rate, g)
            for b, bar in enumerate(tr["bars"]):
                sig_hits.append(int(nearest_common(to_bits(bar["accent_signature"]))) in topk[b])
        rows.append(
            {
                "seed": seed,
                "hard": hard,
                "cases": ",".join(c.split("_")[0] for c in tr["hard_cases"]),
                "bpm": tr["tempo_bpm"],
                "meter": tr["meter"],
                "est_bpm": a.tempo_bpm,
                "tempo_err": tempo_error(a.tempo_bpm, tr["tempo_bpm"]),
                "est_meter": a.meter,
                "dur": song.duration_s,
                "beat_f": beat_f_measure(a.beats, tr["beats"], 0.07),
                "down_f": beat_f_measure(a.downbeats, tr["downbeats"], 0.07),
                "bound_f": beat_f_measure(est_bounds, ref_bounds, 3.0),
                "alike": alike,
                "apart": apart,
                "true_bound_f": beat_f_measure(t_bounds, ref_bounds, 3.0),
                "true_alike": t_alike,
                "sig_top3": sig_hits,
                "cpu_per_min": cpu / (song.duration_s / 60),
                "form": "".join(s["label"][0] for s in tr["sections"]),
                "est_form": "".join(p["label"] for p in a.phrases),
            }
        )
        r = rows[-1]
        print(
            f"{seed:5d} {'hard' if hard else '    '} {r['cases']:<22} {r['bpm']:6.1f} {r['meter']}"
            f" | {r['est_bpm']:6.1f} {r['est_meter']} | beatF {r['beat_f']:.2f} downF {r['down_f']:.2f}"
            f" boundF {r['bound_f']:.2f} (true bars {r['true_bound_f']:.2f}) alike {_mean(r['alike']):.2f}"
            f" | {r['form']:<9} {r['est_form']:<12} | {r['cpu_per_min']:.2f} s/min",
            flush=True,
        )
    return rows


def _mean(xs) -> float:
    xs = list(xs)
    return float(np.mean(xs)) if xs else float("nan")


def _median_tempo_error(rows: list[dict]) -> float:
    errs = [r["tempo_err"] for r in rows if np.isfinite(r["tempo_err"])]
    return 100 * statistics.median(errs) if errs else float("nan")


def summarise(rows: list[dict]) -> None:
    print()
    print(
        f"{'set':<8} {'songs':>5} {'beat F':>7} {'down F':>7} {'meter':>6} {'tempo %':>8} {'bound F':>8} {'alike':>6} {'apart':>6}"
        f" {'bF true':>8} {'alike true':>10} {'sig top3':>9} {'CPU s/min':>10}"
    )
    for name, sel in (
        ("normal", [r for r in rows if not r["hard"]]),
        ("hard", [r for r in rows if r["hard"]]),
        ("all", rows),
    ):
        if not sel:
            continue
        print(
            f"{name:<8} {len(sel):>5} {_mean(r['beat_f'] for r in sel):7.3f} {_mean(r['down_f'] for r in sel):7.3f}"
            f" {_mean(r['meter'] == r['est_meter'] for r in sel):6.2f} {_median_tempo_error(sel):8.2f}"
            f" {_mean(r['bound_f'] for r in sel):8.3f}"
            f" {_mean(x for r in sel for x in r['alike']):6.3f} {_mean(x for r in sel for x in r['apart']):6.3f}"
            f" {_mean(r['true_bound_f'] for r in sel):8.3f} {_mean(x for r in sel for x in r['true_alike']):10.3f}"
            f" {_mean(x for r in sel for x in r['sig_top3']):9.3f} {statistics.median(r['cpu_per_min'] for r in sel):10.2f}"
        )
    print(
        "targets: downbeat F >= 0.95 (>= 0.85 hard), meter 100 %, boundary F >= 0.85, repeats alike >= 0.9,"
        " <= 1.5 s CPU per minute (median, warm)"
    )


def run_cc() -> dict[Path, MusicAnalysis]:
    """Analyse and print the CC recordings; returns the analyses by file."""
    files = _cc_files()
    analyses: dict[Path, MusicAnalysis] = {}
    if not files:
        print("\nCC tracks: not found under", shared_dir() / "datasets" / "music")
        return analyses
    print(
        f"\n{'CC track':<44} {'dur':>6} {'BPM':>6} {'conf':>5} {'meter':>5} {'bars':>5} {'phrases':>7}  form / phrase lengths   CPU s/min"
    )
    for f in files:
        t0 = time.process_time()
        try:
            a = analyze(f)
        except Exception as exc:  # report and go on: one track must not hide the others
            print(f"{f.name[:44]:<44} error: {exc}")
            continue
        cpu = time.process_time() - t0
        analyses[f] = a
        lens = ",".join(str(p["end_bar"] - p["start_bar"]) for p in a.phrases)
        form = "".join(p["label"] for p in a.phrases)
        print(
            f"{f.name[:44]:<44} {a.duration_s:6.1f} {a.tempo_bpm:6.1f} {a.tempo_confidence:5.2f} {a.meter:>5} {a.n_bars:>5}"
            f" {len(a.phrases):>7}  {form} [{lens}]  {cpu / (a.duration_s / 60):.2f}"
        )
        if a.warnings:
            print(f"{'':<44} warnings: {'; '.join(a.warnings)}")
    return analyses


def _cc_files() -> list[Path]:
    cc = shared_dir() / "datasets" / "music" / "cc"
    return sorted(cc.glob("*.ogg")) if cc.is_dir() else []


def _after(times: np.ndarray, cut: float) -> np.ndarray:
    return times[times >= cut + 1.0]


def run_cc_stability(tmp: Path, originals: dict[Path, MusicAnalysis]) -> None:
    """The CC recordings re-analysed after inaudible changes, against their ``originals`` (the
    analyses of :func:`run_cc`; decoding the file or analysing its samples gives the same)."""
    print(
        f"\n{'CC track (stability)':<32} {'variant':<10} {'beat F':>6} {'down F':>6}"
        f" {'BPM':>6} {'meter':>5} {'bars':>5}"
    )
    for f, base in originals.items():
        y, sr = load_audio(f)
        mp3 = tmp / f"{f.stem}.mp3"
        sf.write(mp3, y, sr, format="MP3", subtype="MPEG_LAYER_III")  # 128 kb/s by default
        variants = {
            "original": (base, 0.0),
            "cut 0.73s": (analyze(y[int(0.73 * sr) :], sr), 0.73),
            "cut 10s": (analyze(y[int(10 * sr) :], sr), 10.0),
            "-18 dB": (analyze(y * np.float32(10 ** (-18 / 20)), sr), 0.0),
            "16 kHz": (analyze(resample(y, sr, 16_000), 16_000), 0.0),
            "48 kHz": (analyze(resample(y, sr, 48_000), 48_000), 0.0),
            "mp3 128k": (analyze(mp3), 0.0),
        }
        for name, (a, cut) in variants.items():
            # both sides from one second after the cut: a tracker needs a beat or two to lock on
            beat_f = beat_f_measure(_after(a.beats + cut, cut), _after(base.beats, cut), 0.07)
            down_f = beat_f_measure(
                _after(a.downbeats + cut, cut), _after(base.downbeats, cut), 0.07
            )
            print(
                f"{f.name[:32]:<32} {name:<10} {beat_f:6.3f} {down_f:6.3f} {a.tempo_bpm:6.1f}"
                f" {a.meter:>5} {a.n_bars:>5}",
                flush=True,
            )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--songs", type=int, default=24, help="normal generated songs")
    ap.add_argument("--hard", type=int, default=40, help="hard generated songs")
    ap.add_argument(
        "--seed-base",
        type=int,
        nargs=2,
        default=(1000, 2000),
        metavar=("NORMAL", "HARD"),
        help="first seed of the normal and of the hard songs",
    )
    ap.add_argument(
        "--tempo-range",
        type=int,
        nargs=2,
        metavar=("LO", "HI"),
        help="pin each song's tempo within LO-HI BPM (by the seed) instead of drawing it",
    )
    ap.add_argument("--meter", type=int, choices=(3, 4), help="pin every song's meter")
    ap.add_argument("--no-cc", action="store_true", help="skip the CC recordings")
    ap.add_argument(
        "--stability",
        action="store_true",
        help="also re-analyse the CC recordings after inaudible changes (about 1 minute)",
    )
    args = ap.parse_args(argv)
    tempo_range = tuple(args.tempo_range) if args.tempo_range else None
    with tempfile.TemporaryDirectory() as tmp:
        rows = run_generated(
            args.songs, args.hard, Path(tmp), tuple(args.seed_base), tempo_range, args.meter
        )
        summarise(rows)
        if not args.no_cc:
            originals = run_cc()
            if args.stability:
                run_cc_stability(Path(tmp), originals)
    return 0


if __name__ == "__main__":
    sys.exit(main())
