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
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import soundfile as sf

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

#: Drum grooves as eighth-note slots within the bar, per meter: (kick, snare, hat).
GROOVES: dict[int, dict[str, tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]]] = {
    4: {
        "rock": ((0, 4), (2, 6), (0, 1, 2, 3, 4, 5, 6, 7)),
        "four_floor": ((0, 2, 4, 6), (2, 6), (1, 3, 5, 7)),
        "funk": ((0, 3, 5), (2, 6), (0, 1, 2, 3, 4, 5, 6, 7)),
        "half_time": ((0, 5), (4,), (0, 2, 4, 6)),
        "disco": ((0, 2, 4, 6), (2, 6), (0, 1, 2, 3, 4, 5, 6, 7)),
    },
    3: {
        "waltz": ((0,), (2, 4), (0, 1, 2, 3, 4, 5)),
        "waltz_push": ((0, 3), (2, 4), (0, 2, 4)),
        "jazz_waltz": ((0,), (4,), (0, 2, 3, 4, 5)),
    },
}

#: Hard grooves: no kick on the downbeat.
HARD_GROOVES: dict[int, dict[str, tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]]] = {
    4: {
        "one_drop": ((4,), (4,), (0, 1, 2, 3, 4, 5, 6, 7)),
        "backbeat_only": ((3, 6), (2, 6), (0, 1, 2, 3, 4, 5, 6, 7)),
    },
    3: {
        "waltz_offbeat": ((2,), (2, 4), (0, 1, 2, 3, 4, 5)),
    },
}

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
# Instruments: each returns a mono waveform (float64) starting at its onset.


def _midi_hz(m: float) -> float:
    return 440.0 * 2.0 ** ((m - 69) / 12)


def _kick(sr: int) -> np.ndarray:
    t = np.arange(int(0.35 * sr)) / sr
    f = 48 + 110 * np.exp(-t * 35)
    return np.sin(2 * np.pi * np.cumsum(f) / sr) * np.exp(-t * 9)


def _snare(sr: int, rng: np.random.Generator) -> np.ndarray:
    t = np.arange(int(0.2 * sr)) / sr
    noise = np.diff(rng.standard_normal(len(t) + 1))  # first difference: a bright noise
    return 0.45 * noise * np.exp(-t * 22) + 0.6 * np.sin(2 * np.pi * 190 * t) * np.exp(-t * 30)


def _hat(sr: int, rng: np.random.Generator) -> np.ndarray:
    t = np.arange(int(0.06 * sr)) / sr
    noise = np.diff(rng.standard_normal(len(t) + 2), n=2)
    return 0.25 * noise * np.exp(-t * 70)


def _tone(sr: int, hz: float, dur: float, kind: str) -> np.ndarray:
    """A pitched note of ``dur`` seconds: ``kind`` picks the timbre and the envelope."""
    n = max(int(dur * sr), 16)
    t = np.arange(n) / sr
    if kind == "sine_bass":
        w = np.sin(2 * np.pi * hz * t) + 0.25 * np.sin(4 * np.pi * hz * t)
        env = np.exp(-t * 2.5)
    elif kind == "saw_bass":
        w = sum((np.sin(2 * np.pi * hz * k * t) / k for k in range(1, 7)), np.zeros(n))
        env = np.exp(-t * 4)
    elif kind == "pad":
        w = sum((np.sin(2 * np.pi * hz * k * t) / k**1.5 for k in range(1, 5)), np.zeros(n))
        env = np.minimum(t / 0.06, 1.0) * 0.8
    elif kind == "piano":
        w = sum(
            (np.sin(2 * np.pi * hz * k * t) * np.exp(-t * k * 1.5) / k for k in range(1, 6)),
            np.zeros(n),
        )
        env = np.exp(-t * 3)
    elif kind == "organ":
        w = (
            np.sin(2 * np.pi * hz * t)
            + 0.5 * np.sin(4 * np.pi * hz * t)
            + 0.3 * np.sin(6 * np.pi * hz * t)
        )
        env = np.minimum(t / 0.01, 1.0) * 0.6
    elif kind == "square_lead":
        w = sum((np.sin(2 * np.pi * hz * k * t) / k for k in (1, 3, 5, 7)), np.zeros(n))
        env = np.minimum(t / 0.008, 1.0) * np.exp(-t * 2)
    elif kind == "pluck_lead":
        w = sum((np.sin(2 * np.pi * hz * k * t) / k**2 for k in range(1, 5)), np.zeros(n))
        env = np.exp(-t * 8)
    else:
        raise ValueError(f"unknown instrument {kind!r}")
    rel = min(n, int(0.015 * sr))  # short release: no clicks at note ends
    env = env * np.ones(n)
    env[-rel:] *= np.linspace(1.0, 0.0, rel)
    return w * env


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
        melody: list[list[tuple[int, int, int]]] = []
        motif = _melody_bars(rng, 4, eighths)
        second = _melody_bars(rng, 4, eighths) if rng.random() < 0.6 else [list(b) for b in motif]
        if second == motif:  # a varied answer: same rhythm, last bar changed
            second[-1] = _melody_bars(rng, 1, eighths)[0]
        for b in range(n_bars):
            src = motif if (b // 4) % 2 == 0 else second
            melody.append(src[b % 4])
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


def generate(cfg: SongConfig) -> Song:
    """Synthesise the song of ``cfg`` and its ground truth."""
    rng = np.random.default_rng(cfg.seed + 7919)
    sr = cfg.sr
    m = cfg.meter
    sections = _make_sections(cfg, rng)
    bar_list: list[tuple[_Section, int, int]] = []  # (section, occurrence, index in section)
    occ: dict[str, int] = {}
    for label in cfg.form:
        o = occ.get(label, 0)
        occ[label] = o + 1
        for b in range(sections[label].n_bars):
            bar_list.append((sections[label], o, b))
    n_bars = len(bar_list)
    n_beats = cfg.pickup_beats + n_bars * m
    times = _beat_times(cfg, n_beats)
    tail_s = 1.5
    y = np.zeros(int((times[-1] + tail_s) * sr) + 1)
    kick, snare, hat = _kick(sr), _snare(sr, rng), _hat(sr, rng)
    sample_cache: dict[tuple, np.ndarray] = {}

    def t_of(beat: float) -> float:
        """Global beat position (0 = first downbeat) → seconds, with swing on offbeat eighths."""
        frac = beat - np.floor(beat)
        if abs(frac - 0.5) < 1e-6:
            beat = beat + cfg.swing
        pos = beat + cfg.pickup_beats
        return float(
            np.interp(
                pos,
                np.arange(n_beats + 1),
                times,
                right=times[-1] + (pos - n_beats) * (times[-1] - times[-2]),
            )
        )

    def add(wave: np.ndarray, t: float, gain: float) -> None:
        i = int(round(t * sr))
        if i < 0 or i >= len(y):
            return
        j = min(len(y), i + len(wave))
        y[i:j] += gain * wave[: j - i]

    def note(kind: str, midi: float, beat: float, dur_beats: float, gain: float) -> None:
        t0, t1 = t_of(beat), t_of(beat + dur_beats)
        key = (kind, round(midi, 2), round(t1 - t0, 2))
        if key not in sample_cache:
            sample_cache[key] = _tone(sr, _midi_hz(midi), t1 - t0, kind)
        add(sample_cache[key], t0, gain)

    def chord_root(sec: _Section, bar_idx: int) -> tuple[int, int]:
        deg = sec.progression[bar_idx % len(sec.progression)]
        return deg, int(MAJOR[deg % 7] + sec.key_shift)

    key_root = 40 + int(rng.integers(0, 8))  # E2..B2
    truth_bars: list[dict[str, Any]] = []
    for gbar, (sec, o, b) in enumerate(bar_list):
        start = float(gbar * m)
        deg, root = chord_root(sec, b)
        last_of_section = b == sec.n_bars - 1
        is_break = (
            cfg.breaks
            and last_of_section
            and sec.label not in ("intro", "outro")
            and rng.random() < 0.3
        )
        is_fill = (
            (not is_break)
            and cfg.fills
            and last_of_section
            and sec.groove is not None
            and rng.random() < 0.5
        )
        nxt = bar_list[gbar + 1] if gbar + 1 < n_bars else None
        lvl = sec.level
        accents = np.zeros(8, dtype=int)  # slots with a note or drum onset, hi-hats aside (4/4)

        def mark(pos: float, accents: np.ndarray = accents) -> None:
            if m == 4 and 0 <= pos < 4 and abs(pos * 2 - round(pos * 2)) < 1e-6:
                accents[int(round(pos * 2))] = 1

        # Drums.
        if sec.groove is not None:
            grooves = {**GROOVES[m], **HARD_GROOVES[m]}
            kicks, snares, hats = grooves[sec.groove]
            limit = 2 * m if not is_break else 1  # a break: the downbeat hit, then silence
            fill_from = 2 * m - 4 if is_fill else 2 * m
            for s in kicks:
                if s < limit and s < fill_from:
                    add(kick, t_of(start + s / 2), 0.9 * lvl)
                    mark(s / 2)
            for s in snares:
                if s < limit and s < fill_from:
                    add(snare, t_of(start + s / 2), 0.5 * lvl)
                    mark(s / 2)
            for s in hats:
                if s < limit:
                    add(hat, t_of(start + s / 2), (0.5 if s % 2 else 0.7) * lvl)
            if is_fill:  # sixteenth-note snare fill over the last two beats
                for k in range(8):
                    pos = start + m - 2 + k / 4
                    add(snare, t_of(pos), (0.25 + 0.05 * k) * lvl)
                    mark(pos - start)
        # Bass.
        bass_midi = key_root + root
        for pos, dur, semi in _bass_notes(sec.bass, m):
            if is_break and pos > 0:
                continue
            if semi == 100:  # anticipation of the next bar's root
                if nxt is None or is_break:
                    continue
                _, nroot = chord_root(nxt[0], nxt[2])
                note(sec.bass_kind, key_root + nroot, start + m + pos, dur, 0.55 * lvl)
                continue
            note(sec.bass_kind, bass_midi + semi, start + pos, dur, 0.55 * lvl)
            mark(pos)
        # Chords: a triad in the scale of the section, voiced around C4.
        triad = [
            int(MAJOR[(deg + k) % 7] + 12 * ((deg + k) // 7)) + sec.key_shift for k in (0, 2, 4)
        ]
        chord_midi = [key_root + 12 + n + (12 if n < 6 else 0) for n in triad]
        anticipate = "anticipated_chords" in cfg.hard_cases
        if sec.comp == "sustain" or anticipate:
            t_start = start - 0.5 if anticipate and gbar > 0 else start
            length = (start + m - 0.5 if anticipate else start + m) - t_start
            if is_break:
                length = min(length, 1.0)
            for n in chord_midi:
                note(sec.chords, n, t_start, length, 0.22 * lvl)
            if not anticipate:
                mark(0.0)
            elif sec.comp == "beats" and not is_break:
                # Anticipated chord, then soft stabs of it on every beat: a pulse, no downbeat.
                for k in range(m):
                    for n in chord_midi:
                        note("piano", n, start + k, 0.3, 0.12 * lvl)
                    mark(float(k))
        else:
            slots = range(0, 2 * m, 2) if sec.comp == "beats" else range(1, 2 * m, 2)
            for s in slots:
                if is_break and s > 0:
                    continue
                for n in chord_midi:
                    note(sec.chords, n, start + s / 2, 0.4, 0.2 * lvl)
                mark(s / 2)
        # Lead.
        if sec.lead_kind is not None and not is_break:
            for slot, dur, d in sec.melody[b]:
                midi = key_root + 24 + int(MAJOR[d % 7]) + 12 * (d // 7) + sec.key_shift
                note(sec.lead_kind, midi, start + slot / 2, dur / 2 * 0.95, 0.22 * lvl)
                mark(slot / 2)
        content = (
            sec.label,
            deg,
            sec.melody[b] if sec.lead_kind else None,
            bool(is_break),
            bool(is_fill),
        )
        truth_bars.append(
            {
                "start_s": round(t_of(start), 6),
                "end_s": round(t_of(start + m), 6),
                "label": sec.label,
                "occurrence": o,
                "index": b,
                "content": repr(content),
                "break": bool(is_break),
                "fill": bool(is_fill),
                "drums": sec.groove is not None,
                "accent_signature": "".join(str(int(v)) for v in accents[::-1]) if m == 4 else None,
            }
        )

    # Pickup: a few lead notes (and no chord) before the first downbeat.
    for k in range(cfg.pickup_beats):
        note("pluck_lead", key_root + 24 + int(MAJOR[k % 7]), -cfg.pickup_beats + k, 0.9, 0.25)
    # Outro fade: the last section fades out over its length.
    if cfg.form[-1] == "outro":
        t0 = truth_bars[-sections["outro"].n_bars]["start_s"]
        i0 = int(t0 * sr)
        y[i0:] *= np.linspace(1.0, 0.15, len(y) - i0)
    y += 1e-4 * rng.standard_normal(len(y))  # a noise floor, as in any recording
    y = (0.9 * y / max(np.abs(y).max(), 1e-9)).astype(np.float32)

    beats = times[:-1]
    positions = ((np.arange(n_beats) - cfg.pickup_beats) % m) + 1
    downbeats = beats[positions == 1]
    sections_truth = []
    gbar = 0
    occ = {}
    for label in cfg.form:
        n = sections[label].n_bars
        o = occ.get(label, 0)
        occ[label] = o + 1
        sections_truth.append(
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
    truth = {
        "config": asdict(cfg),
        "sr": sr,
        "duration_s": round(len(y) / sr, 6),
        "meter": m,
        "tempo_bpm": float(60.0 / np.median(np.diff(times))),
        "beats": [round(float(t), 6) for t in beats],
        "beat_positions": [int(p) for p in positions],
        "downbeats": [round(float(t), 6) for t in downbeats],
        "bars": truth_bars,
        "sections": sections_truth,
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
