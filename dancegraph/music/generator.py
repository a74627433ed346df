"""A music generator with exact ground truth: beats, downbeats, meter, sections, labels.

Songs are synthesised with numpy (synth drums, bass, chords, lead) on a beat grid that the
generator itself lays out, so every beat, downbeat and section boundary is known exactly. They
serve as fixtures for tests and as the benchmark set for beat, downbeat, meter and structure
analysis (there are no annotations for the real recordings at hand).

What varies, all drawn from one seed: tempo (70–180 BPM), meter (4/4 or 3/4), song form with
repeats (``intro A B A B C B outro`` and others), swing, a gradual tempo drift, a pickup (beats
before the first downbeat), breaks (stop-time bars) and drum fills, the instruments of each
section. *Hard* songs add cases where the downbeat is marked neither by a kick nor by a chord
change: syncopated bass that avoids beat 1 and anticipates the next root, chords that change
half a beat early, a one-drop or backbeat-only drum groove, and drumless sections (whose chords
then sound on every beat alike: the beat stays audible, only the downbeat is unmarked).

A repeated section is the same music each time (same chords, bass, drums, melody); only fills
and breaks vary between occurrences, as in real songs. Units: seconds, Hz, BPM; audio is
``(N,)`` float32 mono at ``sr`` (22050 Hz by default), peak 0.9.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import soundfile as sf

from dancegraph.music.synth import Renderer

SR = 22050

#: Song forms (section labels in order). Labels ``intro``/``outro`` are sections like any other.
FORMS: tuple[tuple[str, ...], ...] = (
    ("intro", "A", "B", "A", "B", "C", "B", "outro"),
    ("intro", "A", "A", "B", "A", "B", "outro"),
    ("A", "B", "A", "C", "A"),
    ("intro", "A", "B", "C", "A", "B", "outro"),
    ("intro", "A", "B", "A", "B", "outro"),
)

#: Chord progressions as scale degrees (0 = I ... 6 = vii), one chord per bar.
PROGRESSIONS: tuple[tuple[int, ...], ...] = (
    (0, 5, 3, 4),
    (0, 4, 5, 3),
    (5, 3, 0, 4),
    (1, 4, 0, 0),
    (3, 4, 2, 5),
    (0, 3, 0, 4),
    (3, 0, 4, 5),
    (0, 2, 3, 4),
)

MAJOR = np.array([0, 2, 4, 5, 7, 9, 11])
MAJOR.flags.writeable = False
#: a drum groove: (kick, snare, hat) eighth-note slots within the bar
Groove = tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]

#: Drum grooves as eighth-note slots within the bar, per meter: (kick, snare, hat).
GROOVES: Mapping[int, Mapping[str, Groove]] = MappingProxyType(
    {
        4: MappingProxyType(
            {
                "rock": ((0, 4), (2, 6), (0, 1, 2, 3, 4, 5, 6, 7)),
                "four_floor": ((0, 2, 4, 6), (2, 6), (1, 3, 5, 7)),
                "funk": ((0, 3, 5), (2, 6), (0, 1, 2, 3, 4, 5, 6, 7)),
                "half_time": ((0, 5), (4,), (0, 2, 4, 6)),
                "disco": ((0, 2, 4, 6), (2, 6), (0, 1, 2, 3, 4, 5, 6, 7)),
            }
        ),
        3: MappingProxyType(
            {
                "waltz": ((0,), (2, 4), (0, 1, 2, 3, 4, 5)),
                "waltz_push": ((0, 3), (2, 4), (0, 2, 4)),
                "jazz_waltz": ((0,), (4,), (0, 2, 3, 4, 5)),
            }
        ),
    }
)

#: Hard grooves: no kick on the downbeat.
HARD_GROOVES: Mapping[int, Mapping[str, Groove]] = MappingProxyType(
    {
        4: MappingProxyType(
            {
                "one_drop": ((4,), (4,), (0, 1, 2, 3, 4, 5, 6, 7)),
                "backbeat_only": ((3, 6), (2, 6), (0, 1, 2, 3, 4, 5, 6, 7)),
            }
        ),
        3: MappingProxyType({"waltz_offbeat": ((2,), (2, 4), (0, 1, 2, 3, 4, 5))}),
    }
)

HARD_CASES = ("syncopated_bass", "anticipated_chords", "offbeat_drums", "drumless_sections")


@dataclass
class SongConfig:
    """Everything that defines one generated song (all of it drawn from ``seed`` by default)."""

    seed: int
    tempo_bpm: float
    meter: int
    form: list[str]
    section_bars: dict[str, int]
    swing: float = 0.0  # offbeat eighths delayed by this fraction of a beat (1/6 = triplet swing)
    drift: float = 0.0  # relative tempo change from first to last beat (+0.05 = 5 % faster)
    pickup_beats: int = 0  # beats before the first downbeat
    hard_cases: list[str] = field(default_factory=list)
    breaks: bool = True
    fills: bool = True
    lead_in_s: float = 0.25  # silence before the first note
    sr: int = SR


@dataclass
class Song:
    """A generated song: audio and its exact ground truth (``truth`` is JSON-able)."""

    y: np.ndarray
    sr: int
    truth: dict

    @property
    def duration_s(self) -> float:
        return len(self.y) / self.sr


def random_config(
    seed: int,
    *,
    hard: bool = False,
    meter: int | None = None,
    tempo_bpm: float | None = None,
    form: list[str] | None = None,
    section_bars: dict[str, int] | None = None,
) -> SongConfig:
    """Draw a song configuration from ``seed``; keyword arguments pin the named choices."""
    rng = np.random.default_rng(seed)
    meter = int(meter if meter is not None else rng.choice([4, 4, 4, 3]))
    tempo = float(tempo_bpm if tempo_bpm is not None else rng.uniform(70, 180))
    form = list(form if form is not None else FORMS[rng.integers(len(FORMS))])
    if section_bars is None:
        section_bars = {}
        for label in dict.fromkeys(form):
            if label in ("intro", "outro"):
                section_bars[label] = 4
            else:
                section_bars[label] = int(rng.choice([4, 8, 8]))
    swing = float(rng.choice([0.0, 0.0, rng.uniform(0.08, 1 / 6)]))
    drift = float(rng.choice([0.0, rng.uniform(-0.06, 0.06)]))
    pickup = int(rng.integers(0, meter)) if rng.random() < 0.5 else 0
    hard_cases: list[str] = []
    if hard:
        k = int(rng.integers(2, 4))
        hard_cases = sorted(rng.choice(HARD_CASES, size=k, replace=False).tolist())
    return SongConfig(
        seed=seed,
        tempo_bpm=round(tempo, 2),
        meter=meter,
        form=form,
        section_bars={k: int(v) for k, v in section_bars.items()},
        swing=round(swing, 4),
        drift=round(drift, 4),
        pickup_beats=pickup,
        hard_cases=hard_cases,
    )


# ----------------------------------------------------------------------------------------------
# Section content.


@dataclass
class _Section:
    label: str
    n_bars: int
    progression: tuple[int, ...]
    key_shift: int
    groove: str | None  # None: no drums
    bass: str
    chords: str  # instrument of the chords
    comp: str  # "sustain" | "beats" | "offbeats"
    bass_kind: str
    lead_kind: str | None
    melody: list[list[tuple[int, int, int]]]  # per bar: (eighth slot, n eighths, scale degree)
    level: float


def _make_sections(cfg: SongConfig, rng: np.random.Generator) -> dict[str, _Section]:
    m = cfg.meter
    eighths = 2 * m
    grooves = list(GROOVES[m])
    progs = rng.permutation(len(PROGRESSIONS)).tolist()
    hard = set(cfg.hard_cases)
    labels = list(dict.fromkeys(cfg.form))
    drumless: set[str] = set()
    if "drumless_sections" in hard:
        # The intro (or the first section) and one more section play without drums.
        cand = [lab for lab in labels if lab != "outro"]
        drumless = {cand[0]}
        if len(cand) > 2:
            drumless.add(str(rng.choice(cand[1:])))
    out: dict[str, _Section] = {}
    for i, label in enumerate(labels):
        n_bars = cfg.section_bars[label]
        prog = PROGRESSIONS[progs[i % len(progs)]]
        if label in ("intro", "outro"):
            groove = None if rng.random() < 0.5 else str(rng.choice(grooves))
        else:
            groove = str(rng.choice(grooves))
        if groove is not None and "offbeat_drums" in hard:
            groove = str(rng.choice(list(HARD_GROOVES[m])))
        if label in drumless:
            groove = None
        bass = (
            "synco"
            if "syncopated_bass" in hard
            else str(rng.choice(["roots", "beats", "root_fifth", "eighths"]))
        )
        comp = str(rng.choice(["sustain", "beats", "offbeats"]))
        if label in drumless:
            comp = "beats"  # without drums the chords keep the pulse (on every beat alike)
        lead_kind = (
            None
            if label in ("intro", "outro") or rng.random() < 0.25
            else str(rng.choice(["square_lead", "pluck_lead"]))
        )
        melody = _section_melody(rng, n_bars, eighths)
        out[label] = _Section(
            label=label,
            n_bars=n_bars,
            progression=prog,
            key_shift=int(rng.choice([0, 0, 5, 7, -3])) if i > 0 else 0,
            groove=groove,
            bass=bass,
            chords=str(rng.choice(["pad", "piano", "organ"])),
            comp=comp,
            bass_kind=str(rng.choice(["sine_bass", "saw_bass"])),
            lead_kind=lead_kind,
            melody=melody,
            level=float(rng.uniform(0.75, 1.0)),
        )
    return out


def _section_melody(
    rng: np.random.Generator, n_bars: int, eighths: int
) -> list[list[tuple[int, int, int]]]:
    """A section's melody, per bar: a 4-bar motif and its answer (a new one, or the motif with
    its last bar changed), alternating every 4 bars."""
    motif = _melody_bars(rng, 4, eighths)
    second = _melody_bars(rng, 4, eighths) if rng.random() < 0.6 else [list(b) for b in motif]
    if second == motif:  # a varied answer: same rhythm, last bar changed
        second[-1] = _melody_bars(rng, 1, eighths)[0]
    return [(motif if (b // 4) % 2 == 0 else second)[b % 4] for b in range(n_bars)]


def _melody_bars(
    rng: np.random.Generator, n_bars: int, eighths: int
) -> list[list[tuple[int, int, int]]]:
    bars = []
    degree = int(rng.integers(0, 7))
    for _ in range(n_bars):
        notes = []
        slot = 0
        while slot < eighths:
            dur = int(rng.choice([1, 1, 2, 2, 3, 4]))
            dur = min(dur, eighths - slot)
            if rng.random() < 0.8:
                degree = int(np.clip(degree + rng.integers(-2, 3), -3, 10))
                notes.append((slot, dur, degree))
            slot += dur
        bars.append(notes)
    return bars


def _bass_notes(style: str, meter: int) -> list[tuple[float, float, int]]:
    """Bass notes in one bar as (beat position, duration in beats, semitones above the root).

    A negative position belongs to the next bar's root played early (an anticipation); it is
    given relative to the *next* bar's start and marked by ``semitones = 100``.
    """
    if style == "roots":
        return [(0.0, meter - 0.1, 0)]
    if style == "beats":
        return [(float(b), 0.9, 0) for b in range(meter)]
    if style == "root_fifth":
        return [(0.0, 1.4, 0), (1.5, 0.5, 7)] + [
            (float(b), 0.9, 12 if b % 2 else 0) for b in range(2, meter)
        ]
    if style == "eighths":
        return [(k / 2, 0.45, 12 if k % 4 == 2 else 0) for k in range(2 * meter)]
    if style == "synco":
        # Nothing on beat 1: offbeat notes, and the next root half a beat before the barline.
        notes = [(0.5 + b, 0.45, 7 if b % 2 else 0) for b in range(meter - 1)]
        return notes + [(-0.5, 1.0, 100)]
    raise ValueError(style)


# ----------------------------------------------------------------------------------------------


def _beat_times(cfg: SongConfig, n_beats: int) -> np.ndarray:
    """``(n_beats + 1,)`` onset times of every beat (the last one ends the song)."""
    k = np.arange(n_beats)
    bpm = cfg.tempo_bpm * (1.0 + cfg.drift * k / max(n_beats - 1, 1))
    return cfg.lead_in_s + np.concatenate([[0.0], np.cumsum(60.0 / bpm)])


@dataclass
class _Bar:
    """One bar being rendered: its section, place and what it plays (break, fill), and the
    eighth slots (4/4) that get a note or a drum onset, hi-hats aside."""

    sec: _Section
    occurrence: int
    index: int
    start: float  # global beat position of its downbeat
    is_break: bool
    is_fill: bool
    accents: np.ndarray

    def mark(self, pos: float, meter: int) -> None:
        if meter == 4 and 0 <= pos < 4 and abs(pos * 2 - round(pos * 2)) < 1e-6:
            self.accents[int(round(pos * 2))] = 1


def _chord_root(sec: _Section, bar_idx: int) -> tuple[int, int]:
    """(scale degree, semitones above the key) of the chord of bar ``bar_idx`` of ``sec``."""
    deg = sec.progression[bar_idx % len(sec.progression)]
    return deg, int(MAJOR[deg % 7] + sec.key_shift)


def _drums(r: Renderer, bar: _Bar, m: int) -> None:
    sec, start, lvl = bar.sec, bar.start, bar.sec.level
    if sec.groove is None:
        return
    kicks, snares, hats = {**GROOVES[m], **HARD_GROOVES[m]}[sec.groove]
    limit = 2 * m if not bar.is_break else 1  # a break: the downbeat hit, then silence
    fill_from = 2 * m - 4 if bar.is_fill else 2 * m
    for s in kicks:
        if s < limit and s < fill_from:
            r.add(r.kick, r.t_of(start + s / 2), 0.9 * lvl)
            bar.mark(s / 2, m)
    for s in snares:
        if s < limit and s < fill_from:
            r.add(r.snare, r.t_of(start + s / 2), 0.5 * lvl)
            bar.mark(s / 2, m)
    for s in hats:
        if s < limit:
            r.add(r.hat, r.t_of(start + s / 2), (0.5 if s % 2 else 0.7) * lvl)
    if bar.is_fill:  # sixteenth-note snare fill over the last two beats
        for k in range(8):
            pos = start + m - 2 + k / 4
            r.add(r.snare, r.t_of(pos), (0.25 + 0.05 * k) * lvl)
            bar.mark(pos - start, m)


def _bass(r: Renderer, bar: _Bar, m: int, key_root: int, nxt: tuple | None) -> None:
    sec, start, lvl = bar.sec, bar.start, bar.sec.level
    bass_midi = key_root + _chord_root(sec, bar.index)[1]
    for pos, dur, semi in _bass_notes(sec.bass, m):
        if bar.is_break and pos > 0:
            continue
        if semi == 100:  # anticipation of the next bar's root
            if nxt is None or bar.is_break:
                continue
            _, nroot = _chord_root(nxt[0], nxt[2])
            r.note(sec.bass_kind, key_root + nroot, start + m + pos, dur, 0.55 * lvl)
            continue
        r.note(sec.bass_kind, bass_midi + semi, start + pos, dur, 0.55 * lvl)
        bar.mark(pos, m)


def _chords(r: Renderer, bar: _Bar, cfg: SongConfig, key_root: int, gbar: int) -> None:
    """A triad in the scale of the section, voiced around C4: held, struck on the beats or on
    the offbeats, or anticipated by an eighth (hard case)."""
    sec, start, lvl, m = bar.sec, bar.start, bar.sec.level, cfg.meter
    deg = _chord_root(sec, bar.index)[0]
    triad = [int(MAJOR[(deg + k) % 7] + 12 * ((deg + k) // 7)) + sec.key_shift for k in (0, 2, 4)]
    chord_midi = [key_root + 12 + n + (12 if n < 6 else 0) for n in triad]
    anticipate = "anticipated_chords" in cfg.hard_cases
    if sec.comp == "sustain" or anticipate:
        t_start = start - 0.5 if anticipate and gbar > 0 else start
        length = (start + m - 0.5 if anticipate else start + m) - t_start
        if bar.is_break:
            length = min(length, 1.0)
        for n in chord_midi:
            r.note(sec.chords, n, t_start, length, 0.22 * lvl)
        if not anticipate:
            bar.mark(0.0, m)
        elif sec.comp == "beats" and not bar.is_break:
            # Anticipated chord, then soft stabs of it on every beat: a pulse, no downbeat.
            for k in range(m):
                for n in chord_midi:
                    r.note("piano", n, start + k, 0.3, 0.12 * lvl)
                bar.mark(float(k), m)
        return
    slots = range(0, 2 * m, 2) if sec.comp == "beats" else range(1, 2 * m, 2)
    for s in slots:
        if bar.is_break and s > 0:
            continue
        for n in chord_midi:
            r.note(sec.chords, n, start + s / 2, 0.4, 0.2 * lvl)
        bar.mark(s / 2, m)


def _lead(r: Renderer, bar: _Bar, m: int, key_root: int) -> None:
    sec = bar.sec
    if sec.lead_kind is None or bar.is_break:
        return
    for slot, dur, d in sec.melody[bar.index]:
        midi = key_root + 24 + int(MAJOR[d % 7]) + 12 * (d // 7) + sec.key_shift
        r.note(sec.lead_kind, midi, bar.start + slot / 2, dur / 2 * 0.95, 0.22 * sec.level)
        bar.mark(slot / 2, m)


def _new_bar(
    cfg: SongConfig, place: tuple[_Section, int, int], gbar: int, rng: np.random.Generator
) -> _Bar:
    """Bar ``gbar`` at ``place`` (section, occurrence, index); a section's last bar may be a
    break (drums and notes stop after the downbeat) or get a drum fill, drawn from ``rng``."""
    sec, o, b = place
    last_of_section = b == sec.n_bars - 1
    is_break = bool(
        cfg.breaks
        and last_of_section
        and sec.label not in ("intro", "outro")
        and rng.random() < 0.3
    )
    is_fill = bool(
        (not is_break)
        and cfg.fills
        and last_of_section
        and sec.groove is not None
        and rng.random() < 0.5
    )
    return _Bar(sec, o, b, float(gbar * cfg.meter), is_break, is_fill, np.zeros(8, dtype=int))


def _bar_truth(r: Renderer, bar: _Bar, m: int) -> dict[str, Any]:
    sec = bar.sec
    deg = _chord_root(sec, bar.index)[0]
    melody = sec.melody[bar.index] if sec.lead_kind else None
    content = (sec.label, deg, melody, bar.is_break, bar.is_fill)
    return {
        "start_s": round(r.t_of(bar.start), 6),
        "end_s": round(r.t_of(bar.start + m), 6),
        "label": sec.label,
        "occurrence": bar.occurrence,
        "index": bar.index,
        "content": repr(content),
        "break": bar.is_break,
        "fill": bar.is_fill,
        "drums": sec.groove is not None,
        "accent_signature": "".join(str(int(v)) for v in bar.accents[::-1]) if m == 4 else None,
    }


def _bar_list(cfg: SongConfig, sections: dict[str, _Section]) -> list[tuple[_Section, int, int]]:
    """Every bar of the form in order: (section, occurrence, index in the section)."""
    out: list[tuple[_Section, int, int]] = []
    occ: dict[str, int] = {}
    for label in cfg.form:
        o = occ.get(label, 0)
        occ[label] = o + 1
        out.extend((sections[label], o, b) for b in range(sections[label].n_bars))
    return out


def _sections_truth(
    cfg: SongConfig, sections: dict[str, _Section], truth_bars: list[dict[str, Any]]
) -> list[dict[str, Any]]:
    """The ground truth of each section occurrence of the form, in order."""
    out = []
    gbar = 0
    occ: dict[str, int] = {}
    for label in cfg.form:
        n = sections[label].n_bars
        o = occ.get(label, 0)
        occ[label] = o + 1
        out.append(
            {
                "label": label,
                "occurrence": o,
                "start_bar": gbar,
                "end_bar": gbar + n,
                "start_s": truth_bars[gbar]["start_s"],
                "end_s": truth_bars[gbar + n - 1]["end_s"],
                "drums": sections[label].groove is not None,
                "groove": sections[label].groove,
                "bass": sections[label].bass,
            }
        )
        gbar += n
    return out


def _render_bars(
    r: Renderer, cfg: SongConfig, bars: list, key_root: int, rng: np.random.Generator
) -> list[dict[str, Any]]:
    """Every bar into ``r``'s buffer; returns the bars' ground truth."""
    truth_bars = []
    for gbar, place in enumerate(bars):
        bar = _new_bar(cfg, place, gbar, rng)
        nxt = bars[gbar + 1] if gbar + 1 < len(bars) else None
        _drums(r, bar, cfg.meter)
        _bass(r, bar, cfg.meter, key_root, nxt)
        _chords(r, bar, cfg, key_root, gbar)
        _lead(r, bar, cfg.meter, key_root)
        truth_bars.append(_bar_truth(r, bar, cfg.meter))
    # Pickup: a few lead notes (and no chord) before the first downbeat.
    for k in range(cfg.pickup_beats):
        r.note("pluck_lead", key_root + 24 + int(MAJOR[k % 7]), -cfg.pickup_beats + k, 0.9, 0.25)
    return truth_bars


def generate(cfg: SongConfig) -> Song:
    """Synthesise the song of ``cfg`` and its ground truth."""
    rng = np.random.default_rng(cfg.seed + 7919)
    sr, m = cfg.sr, cfg.meter
    sections = _make_sections(cfg, rng)
    bars = _bar_list(cfg, sections)
    n_beats = cfg.pickup_beats + len(bars) * m
    times = _beat_times(cfg, n_beats)
    r = Renderer(sr, times, cfg.pickup_beats, cfg.swing, rng)
    key_root = 40 + int(rng.integers(0, 8))  # E2..B2
    truth_bars = _render_bars(r, cfg, bars, key_root, rng)
    y = r.y
    if cfg.form[-1] == "outro":  # the last section fades out over its length
        i0 = int(truth_bars[-sections["outro"].n_bars]["start_s"] * sr)
        y[i0:] *= np.linspace(1.0, 0.15, len(y) - i0)
    y += 1e-4 * rng.standard_normal(len(y))  # a noise floor, as in any recording
    y = (0.9 * y / max(np.abs(y).max(), 1e-9)).astype(np.float32)
    beats = times[:-1]
    positions = ((np.arange(n_beats) - cfg.pickup_beats) % m) + 1
    truth = {
        "config": asdict(cfg),
        "sr": sr,
        "duration_s": round(len(y) / sr, 6),
        "meter": m,
        "tempo_bpm": float(60.0 / np.median(np.diff(times))),
        "beats": [round(float(t), 6) for t in beats],
        "beat_positions": [int(p) for p in positions],
        "downbeats": [round(float(t), 6) for t in beats[positions == 1]],
        "bars": truth_bars,
        "sections": _sections_truth(cfg, sections, truth_bars),
        "hard_cases": list(cfg.hard_cases),
    }
    return Song(y=y, sr=sr, truth=truth)


def generate_song(seed: int, **kwargs) -> Song:
    """Shortcut: ``generate(random_config(seed, **kwargs))``."""
    return generate(random_config(seed, **kwargs))


def write_song(song: Song, out_dir: str | Path, name: str) -> tuple[Path, Path]:
    """Write ``<name>.wav`` (16-bit PCM) and ``<name>.json`` (the ground truth) into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    wav, js = out / f"{name}.wav", out / f"{name}.json"
    sf.write(wav, song.y, song.sr, subtype="PCM_16")
    js.write_text(json.dumps(song.truth, indent=1))
    return wav, js


def bar_grid(truth: dict) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth bars of a song: ``(B, 2)`` start/end seconds and ``(B, meter + 1)`` beat times."""
    bars = np.array([[b["start_s"], b["end_s"]] for b in truth["bars"]])
    beats = np.asarray(truth["beats"])
    m = truth["meter"]
    first = int(np.searchsorted(beats, bars[0, 0] - 1e-6))
    allb = np.concatenate([beats, [bars[-1, 1]]])
    grid = np.stack([allb[first + i * m : first + i * m + m + 1] for i in range(len(bars))])
    return bars, grid
