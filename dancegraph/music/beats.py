"""Beats, downbeats, meter and tempo of a song: ``track_beats(y, sr) -> BeatTracking``.

An explicit pipeline over one parameters object (:class:`~dancegraph.music.params.
AnalysisParams`), each part in its own module:

1. :func:`~dancegraph.music.evidence.beat_evidence`: checks the audio (length, silence), raises
   quiet input to a mastered level, and computes what every step reads: the activations of
   BeatNet's CRNN models averaged and the spectral curves.
2. The bar-pointer decoder (:mod:`dancegraph.music.barpointer`) over meters 2, 3 and 4, bar
   restarts allowed between sections; then the no-beat decision
   (:func:`~dancegraph.music.nobeat.usable`).
3. The steps (:mod:`dancegraph.music.steps`), each switched by name in ``params.steps``.
4. Tempo from the beats with its metrical alternatives (:mod:`dancegraph.music.tempo`) and a
   confidence that the librosa tracker's agreement raises.

Fallback (``method='librosa'``, or BeatNet's weights missing: warning
``beatnet_weights_missing``): librosa's beats with one bar phase and meter
(:mod:`dancegraph.music.fallback`). No usable beat: ``AudioError(code='no_beat')`` — silence,
noise, speech, birdsong, a steady tone. All times in seconds from the start of ``y``; ``y`` at
any rate, BeatNet works at 22,050 Hz, 50 frames per second.
"""

from __future__ import annotations

import warnings as _warnings
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from dancegraph import jit
from dancegraph.errors import AudioError, ModelFileError
from dancegraph.music import barpointer
from dancegraph.music.evidence import Evidence, beat_evidence
from dancegraph.music.fallback import librosa_bars
from dancegraph.music.levels import within_sound
from dancegraph.music.nobeat import usable
from dancegraph.music.params import AnalysisParams
from dancegraph.music.signal import FPS, SR, beat_f_measure
from dancegraph.music.steps import Grid, run_steps
from dancegraph.music.tempo import (
    TempoEstimate,
    estimate_tempo,
    metrical_relation,
    tempo_from_beats,
)

__all__ = ["BeatTracking", "track_beats", "track_evidence", "warm_up"]


@dataclass
class BeatTracking:
    """Beat tracking result; times in seconds.

    beats (K,), beat_positions (K,) int (1 = downbeat), downbeats (M,), meter (2|3|4, the meter
    in force for most beats), tempo_bpm, tempo_confidence (0..1), method ('beatnet'|'librosa'),
    warnings (codes with a short text), ``evidence`` (the numbers behind the no-beat test and
    the confidence) and ``music_meter``: the music's own meter, 2 where 2/4 measures were paired
    into the 4-beat bars ``meter`` reports (else ``meter``).
    """

    beats: np.ndarray
    beat_positions: np.ndarray
    downbeats: np.ndarray
    meter: int
    tempo_bpm: float
    tempo_confidence: float
    method: str
    warnings: list[str] = field(default_factory=list)
    evidence: dict = field(default_factory=dict)
    music_meter: int = 0

    def __post_init__(self) -> None:
        self.music_meter = int(self.music_meter or self.meter)

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("beats", "downbeats"):
            d[k] = [round(float(t), 4) for t in d[k]]
        d["beat_positions"] = [int(p) for p in self.beat_positions]
        return d


def track_beats(
    y: np.ndarray, sr: int, *, method: str = "auto", params: AnalysisParams | None = None
) -> BeatTracking:
    """Beats, downbeats, meter and tempo of mono audio.

    Args:
        y: (N,) float mono samples.
        sr: their sample rate in Hz.
        method: 'auto' (BeatNet, librosa as fallback), 'beatnet' (no fallback) or 'librosa'.
        params: the models, the decoder, the steps and every threshold
            (:class:`~dancegraph.music.params.AnalysisParams`; default its defaults).

    Raises:
        AudioError: ``no_beat`` when no usable beat is found; ``audio_too_short`` under 3 s;
            ``audio_too_long`` over 20 minutes (as :func:`~dancegraph.music.decode.load_audio`).
        ModelFileError: ``model_missing`` with ``method='beatnet'`` and no weights installed.
    """
    jit.ensure("music")  # compiles into the shared kernel cache only under its lock
    params = params or AnalysisParams()
    return track_evidence(beat_evidence(y, sr, method=method, params=params), params)


def _weak(why: str, warnings: list[str]) -> bool:
    """Whether a usable pulse is faint (``why`` not empty), with its ``weak_pulse`` warning."""
    if why:
        warnings.append(f"weak_pulse: the beat is faint ({why}); beats and bars less sure")
    return bool(why)


def _beatnet_grid(
    ev: Evidence, params: AnalysisParams, values: dict, warnings: list[str]
) -> tuple[Grid, bool]:
    """The decoder's grid through the no-beat test and the steps: (grid, faint pulse)."""
    assert ev.act is not None
    dec = barpointer.decode(ev.act, params.decoder)
    ok, why = usable(dec.times, ev.act, ev.spec, values, "beatnet", params.no_beat)
    if not ok:  # BeatNet's verdict is final: librosa is no better judge of "no beat"
        raise AudioError(f"no beat: {why}", code="no_beat")
    weak = _weak(why, warnings)
    grid, notes = run_steps(Grid.from_decoded(dec), ev, params)
    warnings.extend(notes)
    return grid, weak


def _fallback_grid(
    ev: Evidence, params: AnalysisParams, values: dict, warnings: list[str]
) -> tuple[Grid, bool]:
    """librosa's grid with one bar phase (:func:`~dancegraph.music.fallback.librosa_bars`),
    through the no-beat test and ``within_sound`` only: (grid, faint pulse)."""
    times = ev.librosa_times()
    positions, meter = librosa_bars(times, ev.spec, params.fallback)
    ok, why = usable(times, None, ev.spec, values, "librosa", params.no_beat)
    if not ok:
        raise AudioError(f"no beat: {why}", code="no_beat")
    weak = _weak(why, warnings)
    if "within_sound" in params.steps:
        sounding = within_sound(times, ev.spec.onset_env, params.sound)
        if not sounding.all():
            values["beats_outside_sound"] = int((~sounding).sum())
            times, positions = times[sounding], positions[sounding]
    return Grid(times, positions, np.full(len(times), meter), times), weak


def _confidence(
    tempo: TempoEstimate, times: np.ndarray, ev: Evidence, params: AnalysisParams, values: dict
) -> float:
    """The tempo confidence: the beats' regularity and salience (``tempo``), raised by the
    librosa tracker's agreement with BeatNet's beats ``times`` (K,) s; the fallback's scaled."""
    p = params.confidence
    if ev.act is None:
        return tempo.confidence * p.fallback
    lib_times = ev.librosa_times()
    agree = beat_f_measure(times, lib_times)
    # None where librosa found under 3 beats (no tempo)
    rel = metrical_relation(tempo.bpm, tempo_from_beats(lib_times)[0], params.tempo.relation_tol)
    values["librosa_agreement"] = agree
    values["librosa_relation"] = rel
    # librosa at another metrical level still supports the pulse: part credit
    vote = max(agree, p.other_level_credit if rel not in (None, "x1") else 0.0)
    mixed = p.regularity_weight * tempo.confidence + (1.0 - p.regularity_weight) * vote
    return float(np.clip(mixed, 0.0, 1.0))


def track_evidence(ev: Evidence, params: AnalysisParams | None = None) -> BeatTracking:
    """:func:`track_beats` on evidence already computed (:func:`~dancegraph.music.evidence.
    beat_evidence` with the same ``params.models`` and ``params.evidence``, else ValueError):
    decode, the no-beat test, the steps, tempo and confidence. The evidence is not changed, so
    one evidence serves many parameters (the benchmarks). Raises ``AudioError`` ``no_beat`` as
    :func:`track_beats`."""
    params = params or AnalysisParams()
    if ev.act is not None and tuple(ev.models) != tuple(params.models):
        raise ValueError(f"evidence of models {ev.models}, parameters of {params.models}")
    if ev.params != params.evidence:
        raise ValueError(f"evidence computed with {ev.params}, parameters of {params.evidence}")
    values = dict(ev.values)
    ev = replace(ev, values=values)
    warnings = list(ev.notes)
    build = _beatnet_grid if ev.act is not None else _fallback_grid
    grid, weak = build(ev, params, values, warnings)
    times, positions = grid.times, grid.positions
    meters, counts = np.unique(grid.meters, return_counts=True)
    meter = int(meters[np.argmax(counts)])
    if len(meters) > 1:
        warnings.append(f"meter_change: beats in meters {', '.join(map(str, meters.tolist()))}")
    tempo = estimate_tempo(times, ev.spec.onset_env, FPS, params.tempo)
    warnings.extend(tempo.warnings)
    confidence = _confidence(tempo, times, ev, params, values)
    if weak:
        confidence *= params.confidence.weak_pulse
    values["tempo"] = {
        "regularity": tempo.regularity,
        "salience": tempo.salience,
        "alternatives": tempo.alternatives,
        "octave": tempo.octave,
    }
    return BeatTracking(
        beats=np.asarray(times, dtype=np.float64),
        beat_positions=np.asarray(positions, dtype=np.int64),
        downbeats=np.asarray(times[positions == 1], dtype=np.float64),
        meter=meter,
        tempo_bpm=float(tempo.bpm),
        tempo_confidence=float(confidence),
        method="beatnet" if ev.act is not None else "librosa",
        warnings=warnings,
        evidence=values,
        music_meter=grid.music_meter or meter,
    )


def warm_up() -> None:
    """Compile the decoder, load the models and run librosa's kernels once, so the first song
    does not pay for compilation; never raises. Registered as ``music`` with ``dancegraph.jit``,
    which runs it under the kernel cache's lock."""
    jit.import_cached("librosa.beat")  # its one uncached gufunc, cached (see jit.import_cached)
    barpointer.warm_up()
    try:
        from dancegraph.music.beatnet import load_model

        load_model(1)
    except ModelFileError as exc:
        _warnings.warn(
            f"BeatNet weights missing, librosa fallback will be used: {exc.message}", stacklevel=2
        )
    # 6 s of clicks at 120 BPM through the whole path (librosa's numba kernels included)
    y = np.zeros(6 * SR, dtype=np.float32)
    click = np.exp(-np.arange(400) / 60.0).astype(np.float32) * np.sin(np.arange(400) * 0.6).astype(
        np.float32
    )
    for t in np.arange(0.25, 6.0, 0.5):
        i = int(t * SR)
        y[i : i + 400] += click
    try:
        track_beats(y, SR)
    except AudioError:
        pass


jit.register("music", warm_up)
