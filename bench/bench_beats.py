"""Beat, downbeat and meter tracking: accuracy on generated songs, outputs for the CC songs,
the non-music outcomes, and CPU time per minute of audio.

Usage: ``python bench/bench_beats.py [--songs N] [--hard N] [--no-cc]``.

Trackers compared on the generated set (exact truth from ``dancegraph.music.generator``):
- ``default``: ``track_beats`` as the service runs it (BeatNet models 1-3 averaged, bar-pointer
  decoder with bar restarts, bar-phase vote);
- ``beatnet-1.1.3``: model 1 with BeatNet's own decoder settings (what BeatNet itself outputs);
- ``librosa``: the fallback (librosa beats + Gainza-style bar phase).
Beat F and downbeat F at +-70 ms, meter accuracy (tracked meter == generated meter).
CPU: ``time.process_time`` around ``track_beats`` after a warm-up, per minute of audio.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from dancegraph.errors import AudioError  # noqa: E402
from dancegraph.music.beats import track_beats, warm_up  # noqa: E402
from dancegraph.music.decode import load_audio  # noqa: E402
from dancegraph.music.generator import generate_song  # noqa: E402
from dancegraph.music.params import BEATNET_1_1_3  # noqa: E402
from dancegraph.music.signal import beat_f_measure  # noqa: E402
from dancegraph.paths import shared_dir  # noqa: E402

TRACKERS = {
    "default": {},
    "beatnet-1.1.3": {"params": BEATNET_1_1_3},
    "librosa": {"method": "librosa"},
}


def _row(cells: list, widths: list[int]) -> str:
    return "  ".join(str(c).ljust(w) for c, w in zip(cells, widths, strict=True))


def bench_generated(n_songs: int, hard: bool) -> None:
    scores = {k: [] for k in TRACKERS}
    cpu = {k: 0.0 for k in TRACKERS}
    minutes = 0.0
    for i in range(n_songs):
        song = generate_song(2000 + i, hard=hard)
        minutes += song.duration_s / 60
        for name, kw in TRACKERS.items():
            t0 = time.process_time()
            try:
                res = track_beats(song.y, song.sr, **kw)
                beats, downs, meter = res.beats, res.downbeats, res.meter
            except AudioError:
                beats, downs, meter = np.empty(0), np.empty(0), 0
            cpu[name] += time.process_time() - t0
            scores[name].append(
                (
                    beat_f_measure(song.truth["beats"], beats),
                    beat_f_measure(song.truth["downbeats"], downs),
                    float(meter == song.truth["meter"]),
                )
            )
    label = "hard" if hard else "normal"
    print(f"\ngenerated songs ({label}): {n_songs} songs, {minutes:.1f} min")
    widths = [14, 8, 11, 7, 9]
    print(_row(["tracker", "beat F", "downbeat F", "meter", "CPU s/min"], widths))
    for name in TRACKERS:
        a = np.array(scores[name])
        print(
            _row(
                [
                    name,
                    f"{a[:, 0].mean():.3f}",
                    f"{a[:, 1].mean():.3f}",
                    f"{a[:, 2].mean():.0%}",
                    f"{cpu[name] / minutes:.2f}",
                ],
                widths,
            )
        )


def bench_cc() -> None:
    cc = shared_dir() / "datasets" / "music" / "cc"
    files = sorted(cc.glob("*.ogg"))
    if not files:
        print("\nCC songs not found; skipped")
        return
    print("\nCC songs (default tracker)")
    widths = [34, 7, 6, 6, 7, 5, 9, 30]
    print(_row(["song", "dur s", "beats", "downs", "BPM", "conf", "CPU s/min", "warnings"], widths))
    for path in files:
        y, sr = load_audio(path)
        t0 = time.process_time()
        res = track_beats(y, sr)
        cpu = time.process_time() - t0
        print(
            _row(
                [
                    path.name[:34],
                    f"{len(y) / sr:.1f}",
                    len(res.beats),
                    len(res.downbeats),
                    f"{res.tempo_bpm:.1f}",
                    f"{res.tempo_confidence:.2f}",
                    f"{cpu / (len(y) / sr / 60):.2f}",
                    "; ".join(w.split(":")[0] for w in res.warnings) or "-",
                ],
                widths,
            )
            + f" meter {res.meter}, first downbeats {np.round(res.downbeats[:3], 2).tolist()}"
        )
        if path.name.startswith("Kevin_MacLeod_-_Vibe_Ace"):
            ref_path = shared_dir() / "reference" / "beatnet" / "vibe_ace.npz"
            if ref_path.is_file():
                ref = np.load(ref_path)["beats"]
                one = track_beats(y, sr, params=BEATNET_1_1_3)
                same = len(one.beats) == len(ref) and np.allclose(one.beats, ref[:, 0])
                print(
                    f"  vs BeatNet 1.1.3 reference: default beat F {beat_f_measure(ref[:, 0], res.beats):.3f}, "
                    f"downbeat F {beat_f_measure(ref[ref[:, 1] == 1, 0], res.downbeats):.3f}; "
                    f"model 1 + BeatNet decoder identical: {same}"
                )


def bench_nonmusic() -> None:
    nm = shared_dir() / "datasets" / "music" / "nonmusic"
    sr = 22050
    rng = np.random.default_rng(0)
    t = np.arange(20 * sr) / sr
    cases: list[tuple[str, object]] = [(p.name[:34], p) for p in sorted(nm.glob("*.ogg"))]
    cases += [
        ("digital silence", np.zeros(len(t), np.float32)),
        ("white noise", (rng.standard_normal(len(t)) * 0.3).astype(np.float32)),
        (
            "clipped square 220 Hz",
            np.clip(2 * np.sign(np.sin(2 * np.pi * 220 * t)), -1, 1).astype(np.float32),
        ),
    ]
    print("\nnon-music inputs")
    for name, src in cases:
        try:
            if isinstance(src, Path):
                y, rate = load_audio(src)
            else:
                y, rate = src, sr
            res = track_beats(y, rate)
            outcome = f"beats found ({len(res.beats)}, {res.tempo_bpm:.0f} BPM)"
        except AudioError as err:
            outcome = f"{err.code}: {err.message.split(': ', 1)[-1]}"
        print(f"  {name:34s} {outcome}")


def bench_speed() -> None:
    song = generate_song(7)
    res_cpu = []
    for _ in range(3):
        t0 = time.process_time()
        track_beats(song.y, song.sr)
        res_cpu.append(time.process_time() - t0)
    per_min = min(res_cpu) / (song.duration_s / 60)
    print(
        f"\nspeed: {song.duration_s:.0f} s song, best of 3: {per_min:.2f} CPU s per minute of audio (target <= 1.5)"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--songs", type=int, default=12)
    ap.add_argument("--hard", type=int, default=12)
    ap.add_argument("--no-cc", action="store_true")
    args = ap.parse_args()
    t0 = time.process_time()
    warm_up()
    print(f"warm-up: {time.process_time() - t0:.2f} CPU s (numba cache + model load)")
    bench_speed()
    if args.songs:
        bench_generated(args.songs, hard=False)
    if args.hard:
        bench_generated(args.hard, hard=True)
    if not args.no_cc:
        bench_cc()
        bench_nonmusic()


if __name__ == "__main__":
    main()
