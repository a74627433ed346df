"""The steps after the bar-pointer decoder: each a function from the grid and the evidence to a
new grid and its warnings, run in the order of :data:`STEPS`, each switched by name in
``AnalysisParams.steps`` (default ``params.DEFAULT_STEPS``).

``dotted_pulse`` (decode again at the song's pulse, ``beat_level_corrected``), ``one_octave``
(decode again at one tempo octave, ``beat_level_unified``), ``halve`` (every other beat of a
grid with nothing between its beats, ``beats_halved``), ``swing`` (``beat_swing_mended``),
``slips`` (``beat_slip_mended``), ``off_beat_grid`` (``beat_phase_shifted``), ``within_sound``
(beats where the music sounds), ``group`` (meter and bar phase, :mod:`dancegraph.music.
bargroup`: ``meter_regrouped``, ``downbeat_rephased``) and ``split`` (``beats_split``). Each
reads only the parameters it is given. What each does to real recordings and to generated
songs, and why some are off by default: docs/music.md.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from dancegraph.music import barpointer
from dancegraph.music.bargroup import group_beats
from dancegraph.music.evidence import Evidence, librosa_times_between
from dancegraph.music.levels import (
    dotted_pulse,
    octave_switch,
    split_beats,
    subdivision_strength,
    two_bars_per_bar,
    within_sound,
)
from dancegraph.music.mends import (
    half_beat_parity,
    mend_half_beat_slips,
    mend_off_beat_grid,
    mend_swing_off_beats,
    off_beat_gain,
)
from dancegraph.music.nobeat import usable
from dancegraph.music.params import AnalysisParams
from dancegraph.music.signal import FPS, nearest
from dancegraph.music.tempo import tempo_from_beats

__all__ = ["STEPS", "Grid", "StepFn", "decode_at_level", "frames_tracked", "run_steps"]


def frames_tracked(times: np.ndarray, decoded: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K,) frame index of each beat of ``times`` (K,) and (K,) bool: the decoder's own beat
    (``decoded`` (M,) s) is within 2 frames — where a mend moved or inserted a beat, the
    network's downbeat activation is not about it."""
    frames = np.round(times * FPS).astype(np.int64)
    return frames, np.abs(times[:, None] - decoded[None, :]).min(axis=1) <= 2 / FPS


def decode_at_level(
    ev: Evidence, params: AnalysisParams, bpm: float
) -> barpointer.DecodedBeats | None:
    """The bar-pointer decode of ``ev.act`` with its tempo held within ``params.level_band`` of ``bpm`` or
    of twice it (when that fits under the decoder's ``max_bpm``), whichever path is likelier, or
    None when it fails the no-beat test (:func:`~dancegraph.music.nobeat.usable`; ``ev.values`` is not touched): a dotted
    pulse found in the onsets (:func:`dotted_pulse`) may be the beat or every other beat (the
    likelier path tells which), and of the two octaves a grid switched between
    (:func:`octave_switch`) one is kept for the whole song."""
    act = ev.act
    assert act is not None  # the re-decode steps run only on a BeatNet grid
    band = 1.0 + params.level_band
    dp = params.decoder
    levels = [bpm] + ([2 * bpm] if 2 * bpm <= dp.max_bpm else [])
    decodes = [
        barpointer.decode(act, replace(dp, min_bpm=level / band, max_bpm=level * band))
        for level in levels
    ]
    best = max(decodes, key=lambda d: d.log_prob)
    ok = usable(best.times, act, ev.spec, dict(ev.values), "beatnet", params.no_beat)[0]
    return best if ok else None


@dataclass(frozen=True)
class Grid:
    """A beat grid between steps: ``times`` (K,) s, ``positions`` (K,) (1 = downbeat) and
    ``meters`` (K,) beats per bar; ``decoded`` (M,) s the decoder's own beats (where the
    network's downbeat activation is about the beat); ``halved``: a step kept every other beat
    of the decoder's (its meter is no prior); ``subdivision``: what sounds between the decoder's
    beats (:func:`subdivision_strength`), once measured; ``music_meter``: the music's own meter
    where the bar grouping paired 2/4 measures into bars of 4 (None: the reported meter)."""

    times: np.ndarray
    positions: np.ndarray
    meters: np.ndarray
    decoded: np.ndarray
    halved: bool = False
    subdivision: float | None = None
    music_meter: int | None = None

    @classmethod
    def from_decoded(cls, dec: barpointer.DecodedBeats) -> Grid:
        return cls(dec.times, dec.positions, dec.meters, dec.times)

    def moved(self, times: np.ndarray) -> Grid:
        """The grid with its beats moved to ``times`` (K',) s, each taking the position and
        meter of the nearest beat before the move."""
        near = nearest(np.asarray(times, dtype=np.float64), self.times)
        return replace(self, times=times, positions=self.positions[near], meters=self.meters[near])

    def frames(self) -> tuple[np.ndarray, np.ndarray]:
        """(K,) frame of each beat and (K,) bool: the decoder's own beat (:func:`_frames_tracked`)."""
        return frames_tracked(self.times, self.decoded)


#: a step: (grid, evidence, params) -> (new grid, warnings)
StepFn = Callable[[Grid, Evidence, "AnalysisParams"], tuple[Grid, list[str]]]


def _redecoded(
    grid: Grid, ev: Evidence, params: AnalysisParams, bpm: float | None, message: str
) -> tuple[Grid, list[str]]:
    """The grid decoded again at ``bpm`` (:func:`_decode_at_level`; unchanged for None or where
    that fails), with ``message`` as its warning, ``{new}`` formatted with the new tempo."""
    again = None if bpm is None else decode_at_level(ev, params, bpm)
    if again is None:
        return grid, []
    return Grid.from_decoded(again), [message.format(new=tempo_from_beats(again.times)[0])]


def _dotted_pulse_step(grid: Grid, ev: Evidence, params: AnalysisParams) -> tuple[Grid, list[str]]:
    """Decode again where the decoder held a dotted pulse of the song (:func:`dotted_pulse`)."""
    pulse = dotted_pulse(grid.decoded, ev.spec.onset_env, params.dotted, params.tempo)
    message = (
        f"beat_level_corrected: the tracked beat at {tempo_from_beats(grid.decoded)[0]:.1f} BPM "
        f"was a dotted pulse (3:2) of the song's, whose onsets repeat at {pulse or 0:.1f} BPM; "
        "decoded again at that level or its double: {new:.1f} BPM"
    )
    return _redecoded(grid, ev, params, pulse, message)


def _one_octave_step(grid: Grid, ev: Evidence, params: AnalysisParams) -> tuple[Grid, list[str]]:
    """Decode again at one level a grid that jumps between two tempo octaves
    (:func:`octave_switch`)."""
    slow = octave_switch(grid.decoded, params.octave) or 0.0
    message = (
        f"beat_level_unified: the decoder counted some sections at twice the tempo of others "
        f"({slow:.1f} and {2 * slow:.1f} BPM); decoded again at one level: {{new:.1f}} BPM"
    )
    return _redecoded(grid, ev, params, slow or None, message)


def _halve_step(grid: Grid, ev: Evidence, params: AnalysisParams) -> tuple[Grid, list[str]]:
    """Keep every other beat of a grid with nothing sounding between its beats
    (:func:`subdivision_strength`, :func:`half_beat_parity`)."""
    spec = ev.spec
    p = params.double
    sub = subdivision_strength(spec.onset_env, grid.times, p)
    grid = replace(grid, subdivision=sub)
    half_bpm = tempo_from_beats(grid.times)[0] / 2
    if sub >= p.max_subdivision or half_bpm < p.min_half_bpm or ev.act is None:
        return grid, []
    # the beats are the half the notes start on (the other half: the "and"s)
    parity = half_beat_parity(
        grid.times,
        ev.act,
        spec.onset_env,
        spec.bass_onset,
        spec.chroma,
        spec.snare_onset,
        params.group,
    )
    keep = np.arange(len(grid.times)) % 2 == (0 if parity >= 0 else 1)
    # the kept beats counted in 4 from the first that was a downbeat (the bar grouping, which
    # needs 16 beats, decides again): the decoder's positions of every other eighth (1 3 1 3)
    # form no bar
    downbeats = np.flatnonzero(grid.positions[keep] == 1)
    first = int(downbeats[0]) if len(downbeats) else 0
    counted = (np.arange(int(keep.sum())) - first) % 4 + 1
    halved = replace(
        grid,
        times=grid.times[keep],
        positions=counted.astype(np.int64),
        meters=np.full(len(counted), 4, dtype=np.int64),
        halved=True,
    )
    note = (
        f"beats_halved: nothing sounds between the tracked beats (subdivision {sub:.2f}): they "
        f"were the eighths; every other one kept, {half_bpm:.1f} BPM"
    )
    return halved, [note]


def _swing_step(grid: Grid, ev: Evidence, params: AnalysisParams) -> tuple[Grid, list[str]]:
    """Move onto the beat a grid or sections on the swung off-beats (:func:`mend_swing_off_beats`)."""
    times, swing = mend_swing_off_beats(grid.times, ev.spec.onset_env, params.swing, params.slip)
    if not swing:
        return grid, []
    note = (
        f"beat_swing_mended: beats sat on the swung off-beats (the whole grid, or sections "
        f"between slips); moved up to {swing:.2f} beat later, onto the onsets the swing leads to"
    )
    return grid.moved(times), [note]


def _slip_step(grid: Grid, ev: Evidence, params: AnalysisParams) -> tuple[Grid, list[str]]:
    """Move back the sections a tracker put on the off-beats (:func:`mend_half_beat_slips`)."""
    gain = off_beat_gain(grid.times, ev.spec.onset_env, ev.spec.chroma)

    def reference(lo: float, hi: float, bpm: float) -> np.ndarray:
        return librosa_times_between(ev.spec, lo, hi, bpm)

    times, moved = mend_half_beat_slips(grid.times, reference, gain, params.slip)
    if not moved:
        return grid, []
    note = (
        f"beat_slip_mended: {moved} beats a section put on the off-beats moved half a beat, "
        "onto the pulse of the rest of the song"
    )
    return grid.moved(times), [note]


def _off_beat_grid_step(grid: Grid, ev: Evidence, params: AnalysisParams) -> tuple[Grid, list[str]]:
    """Move a whole grid on the straight off-beats half a beat (:func:`mend_off_beat_grid`)."""
    times, score = mend_off_beat_grid(
        grid.times, ev.spec.onset_env, ev.spec.chroma, params.off_beat
    )
    if score <= params.off_beat.min_score:
        return grid, []
    note = (
        f"beat_phase_shifted: the whole grid sat on the off-beats (pitched onsets and onset "
        f"strength prefer the beats half a beat later, score {score:.2f}); all moved half a beat"
    )
    return grid.moved(times), [note]


def _group_step(grid: Grid, ev: Evidence, params: AnalysisParams) -> tuple[Grid, list[str]]:
    """Meter and bar phase from the music (:func:`~dancegraph.music.bargroup.group_beats`)."""
    if ev.act is None:
        return grid, []
    spec = ev.spec
    frames, tracked = grid.frames()
    g = group_beats(
        grid.positions, grid.meters, ev.act, frames, spec.onset_env, spec.bass_onset, spec.chroma,
        tracked, meter_prior=not grid.halved, snare_onset=spec.snare_onset, p=params.group,
    )  # fmt: skip
    return replace(grid, positions=g.positions, meters=g.meters, music_meter=g.music_meter), g.notes


def _split_step(grid: Grid, ev: Evidence, params: AnalysisParams) -> tuple[Grid, list[str]]:
    """Split every beat of a slow grid whose bars hold two bars of the music
    (:func:`~dancegraph.music.levels.two_bars_per_bar`, :func:`split_beats`) and group the bars again."""
    if ev.act is None:
        return grid, []
    spec = ev.spec
    sub = grid.subdivision
    if sub is None:
        sub = subdivision_strength(spec.onset_env, grid.times, params.double)
    bpm = tempo_from_beats(grid.times)[0]
    per_bar = int(grid.meters[0])
    if bpm >= params.split.max_bpm or not (grid.halved or sub >= params.double.max_subdivision):
        return grid, []
    frames, tracked = grid.frames()
    why = two_bars_per_bar(
        grid.times, grid.positions, per_bar, grid.halved, ev.act, frames, tracked, spec, params
    )
    if not why:
        return grid, []
    times, positions = split_beats(grid.times, grid.positions, per_bar)
    frames, tracked = frames_tracked(times, grid.decoded)
    g = group_beats(
        positions, np.full(len(times), 3 if per_bar == 3 else 4), ev.act, frames, spec.onset_env,
        spec.bass_onset, spec.chroma, tracked, meter_prior=False, snare_onset=spec.snare_onset,
        p=params.group,
    )  # fmt: skip
    note = (
        f"beats_split: {why} at {bpm:.1f} BPM: the beats were half notes; each split in two, "
        f"{2 * bpm:.1f} BPM, bars regrouped"
    )
    new = replace(
        grid, times=times, positions=g.positions, meters=g.meters, music_meter=g.music_meter
    )
    return new, [note, *g.notes]


def _within_sound_step(grid: Grid, ev: Evidence, params: AnalysisParams) -> tuple[Grid, list[str]]:
    """Drop the beats before the first onset and after the last (:func:`within_sound`)."""
    sounding = within_sound(grid.times, ev.spec.onset_env, params.sound)
    if sounding.all():
        return grid, []
    ev.values["beats_outside_sound"] = int((~sounding).sum())
    kept = replace(
        grid,
        times=grid.times[sounding],
        positions=grid.positions[sounding],
        meters=grid.meters[sounding],
    )
    return kept, []


#: The steps after the decoder, in the order they run; each can be switched off by name
#: (``AnalysisParams.steps``). What each does to real and generated music: docs/music.md.
#: ``within_sound`` runs before ``group``: beats the decoder counted in a leading or trailing
#: silence are no evidence of where the bars start (with them in, a second of silence before a
#: recording moved its downbeats: docs/music.md).
STEPS: tuple[tuple[str, StepFn], ...] = (
    ("dotted_pulse", _dotted_pulse_step),
    ("one_octave", _one_octave_step),
    ("halve", _halve_step),
    ("swing", _swing_step),
    ("slips", _slip_step),
    ("off_beat_grid", _off_beat_grid_step),
    ("within_sound", _within_sound_step),
    ("group", _group_step),
    ("split", _split_step),
)


def run_steps(grid: Grid, ev: Evidence, params: AnalysisParams) -> tuple[Grid, list[str]]:
    """Run the steps of :data:`STEPS` that ``params.steps`` names, in order, on ``grid``.
    Returns the last grid and the steps' warnings in order."""
    warnings: list[str] = []
    for name, step in STEPS:
        if name in params.steps:
            grid, notes = step(grid, ev, params)
            warnings.extend(notes)
    return grid, warnings
