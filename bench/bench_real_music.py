"""Beat, downbeat, meter and tempo accuracy on real recordings with human annotations, per genre,
for the default analysis and for each step of the beat pipeline switched off (or, for the steps
off by default, on).

Usage: ``python bench/bench_real_music.py [--root DIR] [--held-out-last K] [--batch]
[--non-music DIR] [--music DIR] [--lead-silence S ...] [--excerpt-start S ...]
[--reference DIR] [--full DIR]``; the annotated folder comes from
``--root`` or ``$DANCEGRAPH_REAL_MUSIC`` and its part skips (exit 0) when neither names one.
The recordings are copyrighted: they live outside the repository, are never committed, and
only the numbers go to docs/music.md.

Folder layout: ``audio/<name>.wav`` (any format ``load_audio`` reads) and ``beats/<name>.beats``
or, for GTZAN, ``beats/gtzan_<genre>_<id>.beats`` beside ``audio/<genre>.<id>.wav`` (the GTZAN
clips of ``zenny126/py`` with the annotations of ``TempoBeatDownbeat/gtzan_tempo_beat``). A
``.beats`` line is ``time beat-in-bar`` (1 = downbeat) or ``time bar.beat`` (Ballroom);
annotations past the end of the audio are dropped; a file without beat-in-bar numbers is
left out of the tables and scored apart, for beat F and ``no_beat`` only (the default analysis).
The genre is the name up to its first ``.`` or ``_``.

Metrics: the headline is downbeat F at the metrical level the analysis counts (``counted``,
below); beat F and downbeat F at ±70 ms (``signal.beat_f_measure``); meter accuracy (the
annotated beats per bar; a 2/4 piece reported in 4 counts as right: the dance bar is 4 beats)
and the music meter's (``music``: the meter reported beside the dance bar, exactly);
tempo-octave errors (the reported tempo more than 8 % off the annotated one, 60 / median
interval: counted at x2, x1/2 or other); false ``no_beat`` (every file is music); and the
default's downbeat F at the metrical level it counts (where the annotation's tempo is twice or
half the tracked one, its bars are half or twice the tracked ones: every other annotated or
tracked downbeat, the better phase). Chance rows:
the default's beats moved half a beat, and its downbeats moved one beat (the wrong phase at the
right tempo). ``--held-out-last K`` keeps the last K files of each genre apart: the steps were
chosen on the rest and are reported on both. ``--batch`` also times ``dancegraph analyze
--jsonl`` over all the files in one process (wall seconds, and per 30 s of audio). The
recordings that are not music (the shared non-music clips, and each ``--non-music DIR``) run
first: each should be refused, and the count given beats is printed; then each ``--music
DIR`` of music without annotations, where each should get beats (false ``no_beat`` counted).
``--lead-silence S ...`` scores the default again with S seconds of silence before each clip,
``--excerpt-start S ...`` with each clip's first S seconds cut off (consistency checks: the same
music starting later, or an excerpt of it, must get the same bars). ``--reference DIR`` scores
another tracker's output (``DIR/<clip>.beats``, ``time beat-in-bar``, e.g. a public
implementation run outside the project) as a row beside the default, with the same metrics.
``--full DIR`` (repeatable; annotations not needed) scores the excerpt consistency of full
songs: each analysed whole and from a third and from half of its length.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from dancegraph.errors import AudioError  # noqa: E402
from dancegraph.music.beats import track_beats, track_evidence, warm_up  # noqa: E402
from dancegraph.music.decode import load_audio  # noqa: E402
from dancegraph.music.evidence import Evidence, beat_evidence  # noqa: E402
from dancegraph.music.params import (  # noqa: E402
    BEATNET_1_1_3,
    DEFAULT_STEPS,
    STEP_NAMES,
    AnalysisParams,
)
from dancegraph.music.signal import beat_f_measure  # noqa: E402
from dancegraph.paths import shared_dir  # noqa: E402

OCTAVE_TOL = 0.08


@dataclass
class Clip:
    """One annotated recording: beat times (K,) s, their beat-in-bar numbers (K,), the audio's
    duration and its evidence (or the AudioError that refused it)."""

    name: str
    genre: str
    beats: np.ndarray
    positions: np.ndarray
    duration_s: float
    evidence: Evidence | AudioError
    evidence_1: Evidence | AudioError  # BeatNet's model 1 alone (the BeatNet 1.1.3 row)
    held_out: bool = False

    @property
    def downbeats(self) -> np.ndarray:
        return self.beats[self.positions == 1]

    @property
    def meter(self) -> int:
        return int(self.positions.max())

    @property
    def tempo_bpm(self) -> float:
        return 60.0 / float(np.median(np.diff(self.beats)))


def read_beats(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(times (K,), beat-in-bar (K,)) from a ``.beats`` file, or None without beat numbers."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    if not rows or any(len(r) < 2 for r in rows):
        return None
    times = np.array([float(r[0]) for r in rows])
    marks = [float(r[1]) for r in rows]
    # "9.3" is bar 9, beat 3 (Ballroom); "3" is beat 3 (GTZAN)
    pos = np.array([round((m - np.floor(m)) * 10) if m != int(m) else int(m) for m in marks])
    return times, pos.astype(np.int64)


def _annotation(root: Path, audio: Path) -> Path | None:
    own = root / "beats" / f"{audio.stem}.beats"
    if own.is_file():
        return own
    gtzan = root / "beats" / f"gtzan_{audio.stem.replace('.', '_')}.beats"
    return gtzan if gtzan.is_file() else None


def read_beat_times(path: Path) -> np.ndarray:
    """Beat times (K,) s from a ``.beats`` file's first column (with or without beat numbers)."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    return np.array([float(r[0]) for r in rows])


def load_beat_only(root: Path) -> list[tuple[str, np.ndarray]]:
    """``(name, beat times (K,) s)`` of the recordings of ``root`` whose annotation has beat
    times but no beat-in-bar numbers: scored for beat F and ``no_beat`` only (``run_beat_only``)."""
    out = []
    for audio in sorted((root / "audio").iterdir()):
        ann = _annotation(root, audio)
        if ann is not None and read_beats(ann) is None:
            out.append((audio.name, read_beat_times(ann)))
    return out


def run_beat_only(root: Path, clips: list[tuple[str, np.ndarray]]) -> None:
    """The default analysis on the recordings annotated with beats only: beat F, and which are
    refused (``no_beat`` on music counts against issue 23's target like any other)."""
    if not clips:
        return
    print(f"\nbeats annotated without bar numbers ({len(clips)} clips): default analysis")
    for name, times in clips:
        y, sr = load_audio(root / "audio" / name)
        try:
            bt = track_beats(y, sr)
        except AudioError as exc:
            print(f"  {name:<26} refused: {exc.code}")
            continue
        f = beat_f_measure(times[times <= len(y) / sr], bt.beats)
        print(f"  {name:<26} beat F {f:.3f}, {bt.tempo_bpm:.1f} BPM")


def run_unannotated(folders: list[Path], music: bool) -> None:
    """The default analysis on recordings without annotations: music (every one should get
    beats: a refusal is a false ``no_beat``) or not music (speech, noise, animals: every one
    should be refused, ``no_beat``, or ``audio_too_short`` under 3 s). Prints each file's
    outcome with its pulse strength and speech evidence, and the count of wrong outcomes."""
    files = [
        p
        for folder in folders
        if folder.is_dir()
        for p in sorted(folder.iterdir())
        if p.suffix.lower() in {".wav", ".ogg", ".flac", ".mp3"}
    ]
    if not files:
        return
    kind = "music without annotations" if music else "not music"
    print(f"\n{kind} ({len(files)} files in {', '.join(map(str, folders))}): default analysis")
    wrong, analysed = 0, 0
    for path in files:
        try:
            y, sr = load_audio(path)
            bt = track_beats(y, sr)
        except AudioError as exc:
            analysed += exc.code != "audio_too_short"
            wrong += music and exc.code == "no_beat"
            mark = "REFUSED" if music else "refused"
            print(f"  {path.name[:44]:<44} {mark}: {exc.code} {exc.message[:70]}")
            continue
        analysed += 1
        wrong += not music
        ev = bt.evidence
        speech = (  # measured for a faint pulse only
            f", pauses {ev['pause_share']:.2f}, chroma persistence {ev['chroma_persistence']:.2f}"
            if "pause_share" in ev
            else ""
        )
        strength = ev.get(f"{bt.method}_strength", float("nan"))
        mark = "beats" if music else "GIVEN BEATS"
        print(
            f"  {path.name[:44]:<44} {mark}: {bt.tempo_bpm:.1f} BPM, strength "
            f"{strength:.2f}{speech}"
        )
    what = "false no_beat" if music else "non-music given beats"
    print(f"  {what}: {wrong} of {analysed} analysed (3 s or longer)")


def load_clips(root: Path, held_out_last: int) -> list[Clip]:
    """The recordings of ``root`` annotated with beat-in-bar numbers, their evidence computed
    once (those with beat times only: ``load_beat_only``)."""
    clips: list[Clip] = []
    for audio in sorted((root / "audio").iterdir()):
        ann = _annotation(root, audio)
        read = read_beats(ann) if ann else None
        if read is None:
            print(f"{audio.name}: no beat-in-bar annotation (scored apart, below, if it has beats)")
            continue
        y, sr = load_audio(audio)
        times, pos = read
        keep = times <= len(y) / sr
        evs: list[Evidence | AudioError] = []
        for params in (AnalysisParams(), BEATNET_1_1_3):
            try:
                evs.append(beat_evidence(y, sr, params=params))
            except AudioError as exc:
                evs.append(exc)
        genre = re.split(r"[._]", audio.stem)[0]
        clips.append(Clip(audio.stem, genre, times[keep], pos[keep], len(y) / sr, *evs))
    for genre in {c.genre for c in clips}:
        mine = [c for c in clips if c.genre == genre]
        for c in mine[len(mine) - held_out_last :] if held_out_last else []:
            c.held_out = True
    return clips


def score(clip: Clip, params: AnalysisParams) -> dict:
    """One clip's metrics under ``params`` (a refused clip scores 0 and counts as no_beat)."""
    try:
        ev = clip.evidence if params.models == AnalysisParams().models else clip.evidence_1
        if isinstance(ev, AudioError):
            raise ev
        bt = track_evidence(ev, params)
    except AudioError:
        return REFUSED
    return metrics(clip, bt.beats, bt.beat_positions, bt.meter, bt.tempo_bpm, bt.music_meter)


REFUSED = {
    "beat_f": 0.0,
    "down_f": 0.0,
    "down_f_level": 0.0,
    "meter": False,
    "music_meter": False,
    "octave": "none",
    "no_beat": True,
}


def read_reference(folder: Path, clip: Clip) -> dict:
    """The metrics of another tracker's output for ``clip``: ``folder/<clip name>.beats``
    (``time beat-in-bar``, as the annotations); a missing or empty file scores as refused."""
    path = folder / f"{clip.name}.beats"
    read = read_beats(path) if path.is_file() else None
    if read is None or len(read[0]) < 2:
        return REFUSED
    times, pos = read
    return metrics(clip, times, pos, int(pos.max()), 60.0 / float(np.median(np.diff(times))))


def metrics(
    clip: Clip,
    beats: np.ndarray,
    positions: np.ndarray,
    meter: int,
    tempo_bpm: float,
    music_meter: int | None = None,
) -> dict:
    """Beat F, downbeat F (at the annotators' level and at the level counted), meter (the
    dance bar's: 2/4 reported in 4 is right; and the ``music_meter`` reported beside it, which
    must equal the annotated one; default ``meter``), tempo level and the chance scores of
    tracked ``beats`` (K,) s with their ``positions`` (K,)."""
    downbeats = beats[positions == 1]
    ratio = tempo_bpm / clip.tempo_bpm
    level = next(
        (
            name
            for name, r in (("x1", 1.0), ("x2", 2.0), ("x1/2", 0.5))
            if abs(ratio / r - 1) <= OCTAVE_TOL
        ),
        "other",
    )
    meter_ok = meter == clip.meter or (clip.meter == 2 and meter == 4)
    down_f = beat_f_measure(clip.downbeats, downbeats)
    # at the level the analysis counts: where the annotators count twice (half) the tracked
    # tempo, their bars are half (twice) the tracked ones: every other downbeat, either phase
    if level == "x1/2":
        level_f = max(beat_f_measure(clip.downbeats[k::2], downbeats) for k in (0, 1))
    elif level == "x2":
        level_f = max(beat_f_measure(clip.downbeats, downbeats[k::2]) for k in (0, 1))
    else:
        level_f = down_f
    half = np.r_[np.diff(beats), np.median(np.diff(beats))] / 2 if len(beats) > 1 else 0
    rotated = beats[np.roll(positions, 1) == 1]
    return {
        "beat_f": beat_f_measure(clip.beats, beats),
        "down_f": down_f,
        "down_f_level": level_f,
        "meter": meter_ok,
        "music_meter": (music_meter or meter) == clip.meter,
        "octave": level,
        "no_beat": False,
        "chance_beat_f": beat_f_measure(clip.beats, beats + half),
        "chance_down_f": beat_f_measure(clip.downbeats, rotated),
    }


def _summary(rows: list[dict]) -> str:
    n = len(rows)
    mean = lambda k: float(np.mean([r[k] for r in rows]))  # noqa: E731
    octave = sum(r["octave"] != "x1" for r in rows)
    return (
        f"{n:>4} {mean('down_f_level'):8.3f} {mean('down_f'):7.3f} {mean('beat_f'):7.3f}"
        f" {mean('meter'):6.3f} {mean('music_meter'):6.3f} {100 * octave / n:6.1f}"
        f" {sum(r['no_beat'] for r in rows):>7}"
    )


#: the headline is the downbeat F at the level the analysis counts (``counted``: an annotation
#: at twice or half the counted tempo brought to it); ``down F`` at the annotators' level,
#: ``meter`` the dance bar's (2/4 in 4 is right), ``music`` the music's own meter beside it
HEADER = (
    f"{'':<28} {'n':>4} {'counted':>8} {'down F':>7} {'beat F':>7} {'meter':>6} {'music':>6}"
    f" {'oct %':>6} {'no_beat':>7}"
)


def variants() -> dict[str, AnalysisParams]:
    """The default, BeatNet 1.1.3, the decoder alone, and each step switched off (or on)."""
    out = {
        "default": AnalysisParams(),
        "decoder alone (no step)": AnalysisParams(steps=frozenset()),
        "BeatNet 1.1.3": BEATNET_1_1_3,
    }
    for name in STEP_NAMES:
        if name in DEFAULT_STEPS:
            out[f"  - {name}"] = AnalysisParams().without(name)
        else:
            out[f"  + {name}"] = AnalysisParams().with_steps(name)
    return out


def parts(clips: list[Clip]) -> dict[str, np.ndarray]:
    """(len(clips),) bool masks of the parts reported apart: all, dev and held-out."""
    held_out = np.array([c.held_out for c in clips], dtype=bool)
    return {"all": np.ones(len(clips), dtype=bool), "dev": ~held_out, "held-out": held_out}


def run(clips: list[Clip], references: list[Path]) -> None:
    """The tables: every variant and each reference folder's tracker, per part and genre."""
    results = {label: [score(c, p) for c in clips] for label, p in variants().items()}
    for folder in references:
        results[f"reference: {folder.name}"] = [read_reference(folder, c) for c in clips]
    for group, mask in parts(clips).items():
        if not mask.any():
            continue
        idx = np.flatnonzero(mask)
        print(f"\n{group} ({len(idx)} clips)\n{HEADER}")
        for label, rows in results.items():
            print(f"{label:<28} {_summary([rows[i] for i in idx])}")
        base = [results["default"][i] for i in idx]
        print(
            f"{'chance (default moved)':<28} {len(base):>4} {'':>8}"
            f" {np.mean([r.get('chance_down_f', 0) for r in base]):7.3f}"
            f" {np.mean([r.get('chance_beat_f', 0) for r in base]):7.3f}"
            "   (downbeats one beat late, beats half a beat late)"
        )
    print(f"\ndefault per genre\n{'genre':<28} {HEADER.strip()}")
    default = results["default"]
    for genre in sorted({c.genre for c in clips}):
        rows = [default[i] for i, c in enumerate(clips) if c.genre == genre]
        print(f"{genre:<28} {_summary(rows)}")
    levels = [r["octave"] for r in default]
    print(
        "default tempo levels against the annotation: "
        + ", ".join(f"{k} {levels.count(k)}" for k in ("x1", "x2", "x1/2", "other", "none"))
    )
    print(
        "targets (issue 23): downbeat F >= 0.92, beat F >= 0.92, meter >= 0.95, "
        "tempo-octave errors <= 5 %, no false no_beat"
    )


def moved_clip(clip: Clip, y: np.ndarray, sr: int, kind: str, seconds: float) -> Clip:
    """``clip`` with ``seconds`` of silence put before it (``kind`` 'lead') or its first
    ``seconds`` cut off (``kind`` 'start'): the evidence recomputed, the annotation moved (and,
    for 'start', the beats before the cut dropped)."""
    n = int(round(seconds * sr))
    if kind == "lead":
        audio, shift = np.concatenate([np.zeros(n, dtype=y.dtype), y]), n / sr
    else:
        audio, shift = y[n:], -n / sr
    try:
        ev: Evidence | AudioError = beat_evidence(audio, sr)
    except AudioError as exc:
        ev = exc
    keep = clip.beats + shift >= 0
    return replace(
        clip, beats=clip.beats[keep] + shift, positions=clip.positions[keep], evidence=ev
    )


def run_moved(root: Path, clips: list[Clip], kind: str, amounts: list[float]) -> None:
    """Consistency without labels of its own: downbeat F (at the annotators' and at the counted
    level) and beat F of the default analysis and of the decoder alone with each of ``amounts``
    seconds of silence put before each clip (``kind`` 'lead') or cut from its start (``kind``
    'start'), beside the clip as it is. A recording that starts a little later, or an excerpt of
    it, must get the same bars. Prints, per part (all, dev, held-out), the mean per amount, the
    mean over all, and the clips whose downbeat F differs by more than 0.3 between amounts."""
    params = {
        "default": AnalysisParams(),
        "decoder alone (no step)": AnalysisParams(steps=frozenset()),
    }
    shape = (len(clips), len(amounts) + 1)
    down = {k: np.zeros(shape) for k in params}
    level = {k: np.zeros(shape) for k in params}
    beat = {k: np.zeros(shape) for k in params}
    for i, clip in enumerate(clips):
        y, sr = load_audio(next((root / "audio").glob(f"{clip.name}.*")))
        for j, amount in enumerate([0.0, *amounts]):
            moved = moved_clip(clip, y, sr, kind, amount) if amount else clip
            for label, p in params.items():
                r = score(moved, p)
                down[label][i, j], beat[label][i, j] = r["down_f"], r["beat_f"]
                level[label][i, j] = r["down_f_level"]
    cols = " ".join(f"{a:>7.2f}" for a in [0.0, *amounts])
    what = "silence before each clip" if kind == "lead" else "each clip cut from"
    print(f"\n{what} (s): downbeat F per amount, mean over all; at its level; beat F")
    for part, mask in parts(clips).items():
        if not mask.any():
            continue
        print(f"{part} ({int(mask.sum())} clips)\n{'':<28} {cols}    mean  level  beat F  unstable")
        for label in params:
            d, b = down[label][mask], beat[label][mask]
            unstable = int(np.sum(d.max(axis=1) - d.min(axis=1) > 0.3))
            per = " ".join(f"{v:7.3f}" for v in d.mean(axis=0))
            lv = level[label][mask].mean()
            print(f"{label:<28} {per} {d.mean():7.3f} {lv:6.3f} {b.mean():7.3f} {unstable:>9}")
    d = down["default"]
    apart = [c.name for c, row in zip(clips, d, strict=True) if row.max() - row.min() > 0.3]
    print(f"default, downbeat F apart by more than 0.3: {' '.join(apart) or '-'}")


#: where the excerpts of a full song start, as shares of its length
EXCERPT_SHARES = (1 / 3, 1 / 2)


def _audio_files(folder: Path) -> list[Path]:
    """The audio files of ``folder`` (or of its ``audio/`` folder), sorted."""
    base = folder / "audio" if (folder / "audio").is_dir() else folder
    return sorted(
        p for p in base.iterdir() if p.suffix.lower() in {".wav", ".ogg", ".flac", ".mp3"}
    )


def excerpt_agreement(
    whole: tuple[np.ndarray, np.ndarray], part: tuple[np.ndarray, np.ndarray], start: float
) -> tuple[float, float]:
    """(beat F, downbeat F) at ±70 ms of an excerpt's ``part`` (beats (K,), downbeats (M,) s,
    in the excerpt's time) against the ``whole`` song's, the excerpt moved by ``start`` s and
    both taken from the excerpt's first second on (its first beats have no context)."""
    after = start + 1.0
    pick = lambda t: t[t >= after]  # noqa: E731
    return (
        beat_f_measure(pick(whole[0]), pick(part[0] + start)),
        beat_f_measure(pick(whole[1]), pick(part[1] + start)),
    )


def run_excerpts(folders: list[Path]) -> None:
    """Excerpt consistency of full songs, no labels needed: each song analysed whole and from
    each of :data:`EXCERPT_SHARES` of its length, the excerpt's beats and downbeats against the
    whole song's (:func:`excerpt_agreement`), for the default and the decoder alone. An upload
    of part of a song must get the bars the whole song gets there."""
    files = [p for folder in folders for p in _audio_files(folder)]
    params = {"default": AnalysisParams(), "decoder alone": AnalysisParams(steps=frozenset())}
    rows: dict[str, list[tuple[float, float]]] = {k: [] for k in params}
    print(f"\nexcerpt consistency, {len(files)} full songs (beat / downbeat agreement per start)")
    for path in files:
        y, sr = load_audio(path)
        cuts = [0] + [int(round(share * len(y))) for share in EXCERPT_SHARES]
        evs = [beat_evidence(y[n:], sr) for n in cuts]
        cells = []
        for label, p in params.items():
            tracked = [track_evidence(ev, p) for ev in evs]
            whole = (tracked[0].beats, tracked[0].downbeats)
            for n, bt in zip(cuts[1:], tracked[1:], strict=True):
                rows[label].append(excerpt_agreement(whole, (bt.beats, bt.downbeats), n / sr))
                cells.append(f"{rows[label][-1][0]:.2f}/{rows[label][-1][1]:.2f}")
        print(f"  {path.stem[:40]:<40} {len(y) / sr:6.1f} s  " + "  ".join(cells))
    for label, r in rows.items():
        if r:
            beat, down = np.mean(r, axis=0)
            print(f"  {label:<40} beats {beat:.3f}  downbeats {down:.3f}  (target >= 0.9)")


def run_batch(root: Path) -> None:
    """Wall time of one ``dancegraph analyze --jsonl`` process over every audio file."""
    files = sorted(str(p) for p in (root / "audio").iterdir())
    seconds = 0.0
    for f in files:
        y, sr = load_audio(f)
        seconds += len(y) / sr
    cmd = [sys.executable, "-m", "dancegraph.cli", "analyze", *files, "--jsonl"]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    lines = out.stdout.splitlines()
    print(
        f"\nbatch: {len(files)} files, {seconds / 60:.1f} min of audio, {len(lines)} lines, "
        f"{wall:.1f} s wall in one process ({wall / (seconds / 30):.2f} s per 30 s of audio; "
        "target: 100 files of 30 s in <= 60 s)"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=os.environ.get("DANCEGRAPH_REAL_MUSIC"))
    ap.add_argument("--held-out-last", type=int, default=4, metavar="K")
    ap.add_argument("--batch", action="store_true", help="also time a batch analyze")
    ap.add_argument(
        "--non-music",
        action="append",
        default=[],
        metavar="DIR",
        help="a folder of recordings that are not music, all to be refused (repeatable; the "
        "shared non-music clips always run)",
    )
    for flag, what in (
        ("--lead-silence", "with S seconds of silence before each clip"),
        ("--excerpt-start", "on each clip with its first S seconds cut off"),
    ):
        ap.add_argument(
            flag,
            type=float,
            nargs="+",
            default=[],
            metavar="S",
            help=f"also score the default {what}",
        )
    ap.add_argument(
        "--reference",
        action="append",
        default=[],
        metavar="DIR",
        help="a folder of another tracker's output, DIR/<clip>.beats (time beat-in-bar), "
        "scored as a row beside the default (repeatable)",
    )
    ap.add_argument(
        "--full",
        action="append",
        default=[],
        metavar="DIR",
        help="a folder of full-length songs (annotated or not) for the excerpt consistency: "
        "each analysed whole and from a third and from half of its length (repeatable)",
    )
    ap.add_argument(
        "--music",
        action="append",
        default=[],
        metavar="DIR",
        help="a folder of music without annotations, all to get beats (repeatable)",
    )
    args = ap.parse_args(argv)
    non_music = [shared_dir() / "datasets" / "music" / "nonmusic", *map(Path, args.non_music)]
    root = Path(args.root) if args.root else None
    warm_up()
    run_unannotated(non_music, music=False)
    run_unannotated([Path(d) for d in args.music], music=True)
    if args.full:
        run_excerpts([Path(d) for d in args.full])
    if root is None or not (root / "audio").is_dir():
        print("real-music benchmark skipped: no folder (--root or $DANCEGRAPH_REAL_MUSIC)")
        return 0
    clips = load_clips(root, args.held_out_last)
    run(clips, [Path(d) for d in args.reference])
    if args.lead_silence:
        run_moved(root, clips, "lead", args.lead_silence)
    if args.excerpt_start:
        run_moved(root, clips, "start", args.excerpt_start)
    run_beat_only(root, load_beat_only(root))
    if args.batch:
        run_batch(root)
    return 0


if __name__ == "__main__":
    sys.exit(main())
