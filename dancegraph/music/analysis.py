"""Music analysis of one song: beats, meter, 4-beat bars, phrases, structure tags, per-bar features
and rhythm signatures — everything the graph search needs from the music.

``analyze(path_or_array, sr=None) -> MusicAnalysis`` chains: ``load_audio`` (decode, mono,
22.05 kHz) → ``track_beats`` (beats, downbeats, meter, tempo) → 4-beat bars (the rule below) →
frame features → structure (phrases and tags) → per-bar onset/RMS curves → rhythm signatures.

The bar rule (a graph node is one 4-beat bar of dance, DESIGN.md §4):

- Bars hold exactly 4 tracked beats and start at the first downbeat; beats before it are a
  pickup and belong to no bar. ``bar_beats[b]`` = the bar's 4 beat times and the next bar's
  first beat.
- 4/4: one bar per measure. 2/4 (and 6/8, which the tracker reports as 2 beats of a dotted
  quarter): two measures per bar.
- 3/4: bars of 4 beats run across the measures; 4 measures (12 beats) make exactly 3 bars, so
  every third bar starts on a downbeat again and the preferred phrase unit is 3 bars (4
  measures) instead of 4. Every dance beat still falls on a music beat.
- Where the tracked downbeat phase changes (an inserted 2-beat measure, a tracker correction),
  the beats left over before the new downbeat (1 to 3) are absorbed by the previous bar, whose
  5 beat times are then spaced evenly over its longer span; the next bar starts on the new
  downbeat. A warning names the bar.
- At the end a bar short of at most 2 beat times (of its 5) is completed by extrapolating the
  last beat period if the audio lasts that long; otherwise the leftover beats are an outro
  tail in no bar.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from functools import lru_cache
from math import gcd
from pathlib import Path

import numpy as np

from dancegraph.errors import AudioError
from dancegraph.music.features import FEATURE_SR, bar_onset_rms, frame_features
from dancegraph.music.params import AnalysisParams
from dancegraph.music.structure import analyze_structure
from dancegraph.rhythm.music import song_signatures

BEATS_PER_BAR = 4


@dataclass
class MusicAnalysis:
    """The analysis of one song. Times in seconds; ``B`` bars, ``N`` beats, ``M`` downbeats.

    ``beats`` (N,), ``beat_positions`` (N,) 1 = downbeat, ``downbeats`` (M,) are the tracker's
    musical beats and measures; ``bars`` (B, 2) and ``bar_beats`` (B, 5) are the 4-beat dance
    bars of the module's bar rule. ``phrases``: ``{label, occurrence, start_bar, end_bar}``
    (end exclusive, occurrence from 0); ``tags`` per bar ``{label, occurrence, index,
    meter_id}``; ``signature_scores`` (B, 13) and ``signature_topk`` (B, 3) index
    ``COMMON_SIGNATURES``; ``bar_onset_rms`` (B, 2, 200). ``grid_octave``: ``x1``, or ``x2`` /
    ``x1/2`` where a dance style's tempo range (``analyze(..., tempo_range=)``) made the beats,
    bars and tempo count twice or half the tracked tempo (warning ``grid_octave``).
    ``music_meter``: the music's own meter beside the dance bar of 4 beats (2 for 2/4 music
    whose measures the bars pair; ``to_dict`` and ``summary`` give ``meters: {music, dance}``);
    ``meter`` stays the meter the beat positions count.

    Optional, per learned model (keyed by the model file's sha256, added where the audio is at
    hand by ``embed.learned.add_music_terms``, absent from ``to_dict`` when empty so the cached
    analysis of a song stays what ``analyze`` wrote): ``learned_style`` (B, 32) the style
    model's E_M style per bar, ``learned_topk`` (B, 3) the rhythm model's top-3 signatures.
    """

    duration_s: float
    tempo_bpm: float
    tempo_confidence: float
    meter: int
    beats: np.ndarray
    beat_positions: np.ndarray
    downbeats: np.ndarray
    bars: np.ndarray
    bar_beats: np.ndarray
    phrases: list[dict]
    tags: list[dict]
    signature_scores: np.ndarray
    signature_topk: np.ndarray
    bar_onset_rms: np.ndarray
    method: str
    warnings: list[str] = field(default_factory=list)
    grid_octave: str = "x1"
    music_meter: int = 0
    learned_style: dict[str, np.ndarray] = field(default_factory=dict)
    learned_topk: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.music_meter = int(self.music_meter or self.meter)

    @property
    def n_bars(self) -> int:
        return len(self.bars)

    def meters(self) -> dict[str, int]:
        """The meter pair: ``{"music": the music's own meter, "dance": 4}`` (the dance bar)."""
        return {"music": int(self.music_meter), "dance": BEATS_PER_BAR}

    def phrase_starts_s(self) -> np.ndarray:
        """``(P,)`` start time in seconds of each phrase: where the style encoder's 8-s log-mel
        windows go (``features.phrase_logmel_windows(y, sr, analysis.phrase_starts_s())``)."""
        return np.array([self.bars[p["start_bar"], 0] for p in self.phrases], dtype=float)

    def to_dict(self) -> dict:
        """JSON-able dict (floats rounded to 0.1 ms / 4 decimals); ``from_dict`` reverses it."""

        def r(a: np.ndarray, nd: int = 4) -> list:
            return np.round(np.asarray(a, dtype=float), nd).tolist()

        out = {
            "duration_s": round(float(self.duration_s), 4),
            "tempo_bpm": round(float(self.tempo_bpm), 3),
            "tempo_confidence": round(float(self.tempo_confidence), 4),
            "meter": int(self.meter),
            "beats": r(self.beats),
            "beat_positions": np.asarray(self.beat_positions, dtype=int).tolist(),
            "downbeats": r(self.downbeats),
            "bars": r(self.bars),
            "bar_beats": r(self.bar_beats),
            "phrases": [dict(p) for p in self.phrases],
            "tags": [dict(t) for t in self.tags],
            "signature_scores": r(self.signature_scores),
            "signature_topk": np.asarray(self.signature_topk, dtype=int).tolist(),
            "bar_onset_rms": r(self.bar_onset_rms),
            "method": self.method,
            "warnings": list(self.warnings),
            "grid_octave": self.grid_octave,
            "meters": self.meters(),
        }
        if self.learned_style:
            out["learned_style"] = {k: r(v) for k, v in self.learned_style.items()}
        if self.learned_topk:
            out["learned_topk"] = {
                k: np.asarray(v, dtype=int).tolist() for k, v in self.learned_topk.items()
            }
        return out

    @classmethod
    def from_dict(cls, d: dict) -> MusicAnalysis:
        """Rebuild from ``to_dict`` output (arrays get their documented shapes, even when empty)."""

        def a(key: str, shape_tail: tuple[int, ...], dtype=float) -> np.ndarray:
            return np.asarray(d.get(key, []), dtype=dtype).reshape((-1, *shape_tail))

        return cls(
            duration_s=float(d["duration_s"]),
            tempo_bpm=float(d["tempo_bpm"]),
            tempo_confidence=float(d["tempo_confidence"]),
            meter=int(d["meter"]),
            beats=a("beats", ()),
            beat_positions=a("beat_positions", (), int),
            downbeats=a("downbeats", ()),
            bars=a("bars", (2,)),
            bar_beats=a("bar_beats", (5,)),
            phrases=[dict(p) for p in d.get("phrases", [])],
            tags=[dict(t) for t in d.get("tags", [])],
            signature_scores=a("signature_scores", (13,)),
            signature_topk=a("signature_topk", (3,), int),
            bar_onset_rms=a("bar_onset_rms", (2, 200)),
            method=str(d.get("method", "")),
            warnings=list(d.get("warnings", [])),
            grid_octave=str(d.get("grid_octave", "x1")),
            music_meter=int((d.get("meters") or {}).get("music", d["meter"])),
            learned_style={
                str(k): np.asarray(v, dtype=np.float32).reshape(-1, 32)
                for k, v in (d.get("learned_style") or {}).items()
            },
            learned_topk={
                str(k): np.asarray(v, dtype=int).reshape(-1, 3)
                for k, v in (d.get("learned_topk") or {}).items()
            },
        )

    def summary(self) -> dict:
        """A short dict for job status: tempo, meter, counts, the phrase form (e.g. ``ABAB``), the
        grid octave and the warnings."""
        return {
            "duration_s": round(float(self.duration_s), 2),
            "tempo_bpm": round(float(self.tempo_bpm), 1),
            "tempo_confidence": round(float(self.tempo_confidence), 3),
            "meter": int(self.meter),
            "meters": self.meters(),
            "n_beats": len(self.beats),
            "n_bars": self.n_bars,
            "n_phrases": len(self.phrases),
            "form": "".join(p["label"] for p in self.phrases),
            "method": self.method,
            "grid_octave": self.grid_octave,
            "warnings": list(self.warnings),
        }


def _extend_beats(beats: np.ndarray, duration_s: float, n_extra: int = 2) -> np.ndarray:
    """Append up to ``n_extra`` beats at the last beat period, those within the audio."""
    if len(beats) < 2:
        return beats
    period = float(np.median(np.diff(beats[-5:])))
    extra = beats[-1] + period * np.arange(1, n_extra + 1)
    return np.concatenate([beats, extra[extra <= duration_s + 1e-6]])


def four_beat_bars(
    beats: np.ndarray, beat_positions: np.ndarray, meter: int, duration_s: float
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Group tracked beats into 4-beat bars by the module's bar rule.

    ``beats`` (N,) s; ``beat_positions`` (N,) 1 = downbeat; ``meter`` beats per measure.
    Returns ``bars`` (B, 2) start/end s, ``bar_beats`` (B, 5) s, and warnings.
    """
    beats = np.asarray(beats, dtype=float).reshape(-1)
    pos = np.asarray(beat_positions, dtype=int).reshape(-1)
    warnings: list[str] = []
    down = np.flatnonzero(pos == 1)
    start = int(down[0]) if len(down) else 0
    ext = _extend_beats(beats, duration_s)
    meter = max(int(meter), 1)
    bars: list[tuple[float, float]] = []
    grid: list[np.ndarray] = []
    anchor, i = start, start
    while i + BEATS_PER_BAR < len(ext):
        # A downbeat inside this group that is out of phase with the current anchor: the
        # tracker's measure grid shifted; the bar grid follows it.
        shift = [d for d in down if i < d < i + BEATS_PER_BAR and (d - anchor) % meter != 0]
        if shift:
            d = int(shift[0])
            if grid:
                lo = grid[-1][0]
                grid[-1] = np.linspace(lo, ext[d], BEATS_PER_BAR + 1)
                bars[-1] = (lo, float(ext[d]))
                warnings.append(
                    f"bar {len(bars) - 1}: downbeat phase changed; {d - i} beat(s) absorbed"
                )
            anchor = i = d
            continue
        g = ext[i : i + BEATS_PER_BAR + 1]
        grid.append(g.copy())
        bars.append((float(g[0]), float(g[-1])))
        i += BEATS_PER_BAR
    if meter not in (2, 4):
        cycle = meter * BEATS_PER_BAR // gcd(meter, BEATS_PER_BAR)
        warnings.append(
            f"meter {meter}: 4-beat bars run across the measures; they realign with the "
            f"downbeats every {cycle} beats"
        )
    if not bars:
        return np.zeros((0, 2)), np.zeros((0, 5)), warnings
    return np.asarray(bars), np.stack(grid), warnings


def fit_tempo_range(
    beats: np.ndarray, positions: np.ndarray, meter: int, tempo_range: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, int, str, list[str]]:
    """The beat grid at the tempo octave that fits a dance style's ``tempo_range`` (lo, hi) BPM.

    ``beats`` (N,) s and ``positions`` (N,) (1 = downbeat) in bars of ``meter``. A tracked tempo
    outside the range whose double lies inside is split (every interval halved, bars of 4 or 3
    of the new beats: :func:`~dancegraph.music.beats.split_beats`); one whose half lies inside
    keeps every other beat from the first downbeat (bars of 4 become bars of 2 beats; 2 and 3
    are not halved). Otherwise the tracker's level stays: the networks count it steadily, and a style's
    range only picks the octave the dance bars count. Returns (beats, positions, meter, octave
    ``x1`` | ``x2`` | ``x1/2``, warnings).
    """
    from dancegraph.music.levels import split_beats
    from dancegraph.music.tempo import tempo_from_beats

    lo, hi = tempo_range
    bpm = tempo_from_beats(beats)[0]
    if bpm <= 0 or lo <= bpm <= hi:
        return beats, positions, meter, "x1", []
    if lo <= 2 * bpm <= hi:
        new, new_pos = split_beats(beats, positions, meter)
        octave, new_meter = "x2", 3 if meter == 3 else 4
    elif lo <= bpm / 2 <= hi and meter == 4:
        down = np.flatnonzero(positions == 1)
        first = int(down[0]) if len(down) else 0
        keep = (np.arange(len(beats)) - first) % 2 == 0
        new, new_pos = beats[keep], (np.asarray(positions)[keep] - 1) // 2 + 1
        octave, new_meter = "x1/2", 2
    else:
        return beats, positions, meter, "x1", []
    note = (
        f"grid_octave: the bars count {octave} the tracked tempo ({bpm:.1f} -> "
        f"{tempo_from_beats(new)[0]:.1f} BPM) to fit the style's {lo:.0f}-{hi:.0f} BPM"
    )
    return new, np.asarray(new_pos, dtype=np.int64), new_meter, octave, [note]


def phrase_unit(meter: int) -> int:
    """Preferred phrase length in 4-beat bars: 4 measures where they fill whole bars (3/4: 3 bars),
    else 4 bars."""
    meter = int(meter)
    if meter in (2, 4):
        return 4
    cycle = 4 * meter // gcd(4, meter)
    bars = cycle // BEATS_PER_BAR
    return bars if 2 <= bars <= 8 else 4


@lru_cache(maxsize=1)
def analysis_version() -> str:
    """12 hex digits naming the code and the models that make an analysis.

    The sha256 over the source files of ``dancegraph.music`` and ``dancegraph.rhythm`` (sorted
    by name) and the BeatNet weights in use: their pinned hashes where all three files are
    present, ``librosa`` where they are missing and the tracker falls back. Computed once per
    process. Why: a stored analysis is reusable only by the code that made it; callers that
    cache analyses (the worker's object-store cache) key them by this, so a deployment with
    changed analysis code, or with the weights newly installed, never serves an old result.
    """
    from dancegraph.music import weights

    package = Path(__file__).resolve().parent.parent
    digest = hashlib.sha256()
    for folder in ("music", "rhythm"):
        for source in sorted((package / folder).glob("*.py")):
            digest.update(f"{folder}/{source.name}\0".encode())
            digest.update(source.read_bytes())
    present = all(weights.weight_path(m).is_file() for m in (1, 2, 3))
    models = sorted(weights.FILE_SHA256.values()) if present else ["librosa"]
    digest.update("\0".join(models).encode())
    return digest.hexdigest()[:12]


def _samples(path_or_array: str | os.PathLike | np.ndarray, sr: int | None) -> np.ndarray:
    """Mono float32 samples at ``FEATURE_SR`` Hz from a file or an array (see :func:`analyze`)."""
    from dancegraph.music.decode import load_audio

    if not isinstance(path_or_array, np.ndarray):
        return load_audio(path_or_array, sr=FEATURE_SR)[0]
    if sr is None:
        raise AudioError(
            "a sample array needs its sample rate", code="audio_undecodable", field="sr"
        )
    y = np.asarray(path_or_array)
    if np.issubdtype(y.dtype, np.integer):  # PCM integers → [-1, 1]
        y = y / float(np.iinfo(y.dtype).max + 1)
    y = y.astype(np.float32)
    if y.ndim == 2:
        y = y.mean(axis=0)
    if y.ndim != 1 or y.size == 0:
        raise AudioError("expected (N,) or (C, N) samples", code="audio_empty", field="audio")
    y = np.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0)
    if sr != FEATURE_SR:
        import librosa

        y = librosa.resample(y, orig_sr=int(sr), target_sr=FEATURE_SR)
    return y


def analyze(
    path_or_array: str | os.PathLike | np.ndarray,
    sr: int | None = None,
    *,
    tempo_range: tuple[float, float] | None = None,
    params: AnalysisParams | None = None,
) -> MusicAnalysis:
    """Analyse a song given as a file path or as samples.

    ``path_or_array``: an audio file (any format ``load_audio`` decodes) or samples ``(N,)`` /
    ``(C, N)`` (float in [-1, 1], or PCM integers) at ``sr`` Hz (required for arrays; ignored
    for files, which are decoded at 22.05 kHz). ``tempo_range``: a dance style's (lo, hi) BPM;
    the beats and bars then count the octave of the tracked tempo that fits it
    (:func:`fit_tempo_range`). ``params``: every threshold of the beat, tempo, bar-grouping and
    no-beat steps (:class:`~dancegraph.music.params.AnalysisParams`; default its defaults).
    Raises ``AudioError`` (codes of ``load_audio``, ``no_beat`` when no 4-beat bar can be
    formed).
    """
    from dancegraph import jit
    from dancegraph.music.beats import track_beats  # the tracker loads torch: only when used
    from dancegraph.music.tempo import tempo_from_beats

    jit.ensure("music")  # librosa's kernels load under the cache lock, before the features use them
    y = _samples(path_or_array, sr)
    duration = len(y) / FEATURE_SR
    bt = track_beats(y, FEATURE_SR, params=params)
    beats, positions, meter = bt.beats, bt.beat_positions, bt.meter
    octave, tempo_bpm, warnings = "x1", float(bt.tempo_bpm), list(bt.warnings)
    if tempo_range is not None:
        beats, positions, meter, octave, notes = fit_tempo_range(
            beats, positions, meter, tempo_range
        )
        if octave != "x1":
            tempo_bpm, warnings = tempo_from_beats(beats)[0], warnings + notes
    bars, bar_beats, bar_warnings = four_beat_bars(beats, positions, meter, duration)
    if len(bars) == 0:
        raise AudioError("too few beats to form a single 4-beat bar", code="no_beat", field="audio")
    ff = frame_features(y, FEATURE_SR)
    st = analyze_structure(ff, bars, unit=phrase_unit(meter))
    scores, topk, _ = song_signatures(ff, bar_beats)
    return MusicAnalysis(
        duration_s=duration,
        tempo_bpm=float(tempo_bpm),
        tempo_confidence=float(bt.tempo_confidence),
        meter=int(meter),
        beats=np.asarray(beats, dtype=float),
        beat_positions=np.asarray(positions, dtype=int),
        downbeats=np.asarray(beats[positions == 1], dtype=float),
        bars=bars,
        bar_beats=bar_beats,
        phrases=st.phrases,
        tags=st.tags,
        signature_scores=scores,
        signature_topk=topk,
        bar_onset_rms=bar_onset_rms(ff, bars),
        method=str(bt.method),
        warnings=warnings + bar_warnings,
        grid_octave=octave,
        music_meter=bt.music_meter,
    )
