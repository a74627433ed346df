"""Every parameter of the music analysis's beat, tempo, bar-grouping and no-beat steps, in one
typed, frozen object: :class:`AnalysisParams`.

The defaults are the numbers the analysis was tuned with (the measurements behind each:
docs/music.md, "Measurements behind the steps"). Each step reads only the part of the
parameters it is given, so a tuning round is a new :class:`AnalysisParams`, never an edit to
shared state: ``analyze(audio, params=AnalysisParams(group=GroupParams(net_confident=0.75)))``,
``dancegraph analyze song.ogg --params p.yaml``, or a spec's ``analysis`` section, all read by
:meth:`AnalysisParams.from_dict`, which refuses unknown keys and wrong types
(``SpecError`` ``analysis_params_invalid`` naming the key).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import typing
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from dancegraph.errors import SpecError
from dancegraph.music.barpointer import DEFAULT as DEFAULT_DECODER
from dancegraph.music.barpointer import MADMOM, BarPointerParams

__all__ = [
    "BEATNET_1_1_3",
    "DEFAULT_STEPS",
    "STEP_NAMES",
    "AnalysisParams",
    "ConfidenceParams",
    "DottedParams",
    "DoubleParams",
    "EvidenceParams",
    "FallbackParams",
    "GroupParams",
    "NoBeatParams",
    "OctaveParams",
    "OffBeatParams",
    "PulseLimits",
    "SlipParams",
    "SoundParams",
    "SpeechParams",
    "SplitParams",
    "SwingParams",
    "TempoParams",
    "load_params",
]

#: the steps after the decoder, in the order they run (:data:`dancegraph.music.steps.STEPS`)
STEP_NAMES = (
    "dotted_pulse",
    "one_octave",
    "halve",
    "swing",
    "slips",
    "off_beat_grid",
    "within_sound",
    "group",
    "split",
)

#: The steps that run by default: those that do not cost real recordings with human annotations
#: and keep the generated regression suite on target. Off: ``one_octave`` and ``split`` double
#: grids the networks track steadily and ``halve`` halves them, ``swing`` and ``off_beat_grid``
#: move right grids onto the off-beats. What each does to both: docs/music.md.
DEFAULT_STEPS = frozenset({"dotted_pulse", "slips", "group", "within_sound"})


@dataclass(frozen=True)
class EvidenceParams:
    """What the evidence is computed from (:func:`dancegraph.music.evidence.beat_evidence`)."""

    #: loud-part RMS (-20 dBFS) quiet input is raised to: BeatNet's log-magnitude features are
    #: not level-invariant, and a mastered song plays at about this level
    target_rms: float = 0.1
    #: the most quiet input is raised (x1000, +60 dB): noise is not made music
    max_gain: float = 1000.0
    #: Hz band whose noise onsets are taken for snares and claps (hi-hats sit above it)
    snare_band_hz: tuple[float, float] = (1000.0, 5000.0)


@dataclass(frozen=True)
class PulseLimits:
    """The no-beat test's limits on one tracker's curve (BeatNet's summed activation, or
    librosa's onset strength): below a ``min_`` value there is no beat; a pulse under a
    ``clear_`` value is faint (``weak_pulse``)."""

    #: mean curve peak at the beats (activation units): a network that hardly fires
    min_peak: float = 0.0
    #: peak at the beats / curve mean: the beats stand out of the curve
    min_contrast: float = 0.0
    #: autocorrelation at the beat period (0..1): the curve repeats at the beat
    min_salience: float = 0.0
    #: contrast x salience: the pulse strength, one number that separates music from speech
    min_strength: float = 0.0
    #: contrast under this: a faint pulse
    clear_contrast: float = 0.0
    #: salience under this: a faint pulse
    clear_salience: float = 0.0


@dataclass(frozen=True)
class SpeechParams:
    """A faint pulse in sound that pauses like speech and whose harmony does not hold is refused
    (:func:`dancegraph.music.nobeat.speech_evidence`)."""

    #: a frame is a pause where its RMS is under this share (-14 dB) of the level about it: a
    #: gap between words, deeper than the dips of a rhythm part
    pause_ratio: float = 0.2
    #: seconds the level about a frame is averaged over (a syllable and its gap)
    pause_context_s: float = 1.0
    #: seconds ahead the chroma is compared with itself: a held chord outlasts it, a syllable not
    chroma_lag_s: float = 0.25
    #: share of pause frames from which the sound pauses like speech
    min_pauses: float = 0.14
    #: chroma persistence (0..1) under which the harmony does not hold; both needed
    max_chroma: float = 0.7


@dataclass(frozen=True)
class NoBeatParams:
    """The usable-beat test (:func:`dancegraph.music.nobeat.usable`): silence, noise, speech,
    birdsong and steady tones get ``no_beat``; real music does not."""

    #: fewer decoded beats than this: no beat
    min_beats: int = 8
    #: the beats must span this share of the non-silent audio
    min_coverage: float = 0.5
    #: share of inter-beat intervals within 10 % of the local median: the decoder's grid is steady
    min_regularity: float = 0.6
    #: RMS under this (-80 dBFS) is silence
    silence_rms: float = 1e-4
    #: on BeatNet's activation: the non-music clips and noise reach a strength of 0.22, real
    #: music starts at 0.28; contrast under 2.4 or salience under 0.2 is faint
    beatnet: PulseLimits = PulseLimits(
        min_peak=0.3, min_strength=0.25, clear_contrast=2.4, clear_salience=0.2
    )
    #: on librosa's onset strength (fallback only): contrast and salience each, no faint zone
    #: (speech reaches a strength of 0.33 there, on a salience under 0.08)
    librosa: PulseLimits = PulseLimits(
        min_contrast=1.5, min_salience=0.1, clear_contrast=1.5, clear_salience=0.1
    )
    speech: SpeechParams = SpeechParams()


@dataclass(frozen=True)
class SwingParams:
    """Beats on the swung off-beats (step ``swing``; also what a slow song's swing looks like
    to ``split``)."""

    #: beat-phase resolution of the onset profile (bins per beat)
    bins: int = 50
    #: where the eighth note between two beats is looked for (beats)
    window: tuple[float, float] = (0.3, 0.7)
    #: it comes before this (beats, after the grid's own onset lag): swung off-beats
    max_phase: float = 0.46
    #: a section moves where the rest of the grid has its eighth after this (beats)
    min_swung: float = 0.54
    #: ... and the two phases add up to one beat within this (beats)
    mirror_tol: float = 0.08
    #: and its onset is at least this share of the profile's peak: a real onset
    min_rel: float = 0.2


@dataclass(frozen=True)
class DoubleParams:
    """A grid at twice the tactus (step ``halve``; ``split`` reads ``max_subdivision``)."""

    #: beat-phase resolution of the onset profile (bins per beat)
    bins: int = 16
    #: nothing between the beats above this share of the beat's own onset: they are eighths
    max_subdivision: float = 0.14
    #: BPM the half tempo must reach: still a beat one counts
    min_half_bpm: float = 60.0


@dataclass(frozen=True)
class DottedParams:
    """A grid on a dotted pulse of the song (step ``dotted_pulse``)."""

    #: the x3/2 or x2/3 level's pulse salience over the tracked level's: right levels reach 1.22
    #: on generated songs, dotted ones 2.03 and more
    min_ratio: float = 1.6


@dataclass(frozen=True)
class OctaveParams:
    """A grid that changes its tempo octave between sections (step ``one_octave``)."""

    #: each of the two levels held for this share of the grid's span
    min_share: float = 0.15
    #: tempos between the two for at most this share of the span (else a ritardando)
    max_between: float = 0.25
    #: somewhere the 4-interval median changes this much (ratio) within 4 beats: it jumps
    min_jump: float = 1.35


@dataclass(frozen=True)
class SplitParams:
    """A grid at half the tactus (step ``split``)."""

    #: BPM under which 2 beats per bar may be a half-time count
    max_bpm: float = 95.0
    #: 4-beat bars whose third beat is marked almost as their first (z-units)
    max_contrast: float = 1.2
    #: 3-beat bars: the split grid repeats after 3 beats at least as closely as after 6 ...
    max_repeat_gap: float = 0.0
    #: ... and the harmony changes half-way through the bar almost as at its start (z-units)
    max_harmony_contrast: float = 1.0


@dataclass(frozen=True)
class SoundParams:
    """Beats before the music starts or after it has stopped (step ``within_sound``)."""

    #: an onset: onset strength at least this share of its median at the beats
    min_onset: float = 0.1
    #: beats kept up to this share of a beat interval outside the first/last onset
    slack: float = 0.1


@dataclass(frozen=True)
class OffBeatParams:
    """A whole grid on the straight off-beats (step ``off_beat_grid``)."""

    #: mean off-beat gain (z-units) above which the grid moves: the middle of the gap between
    #: grids on the beat (0.77 at most) and on the off-beats (0.89 and up) on generated songs
    min_score: float = 0.83


@dataclass(frozen=True)
class SlipParams:
    """Half-beat slips of the beat grid (step ``slips``; ``swing`` reads the slip finder too)."""

    #: beats each side of a slip
    window: int = 4
    #: beats each side of a slower slide, looked for where the window found none (a decoder
    #: can slide onto the off-beats over ten beats, each interval a few per cent short)
    slow_window: int = 8
    #: ... between phases steady to this (beats) over slow_window beats before and after (a
    #: ritardando keeps drifting after its "slide"; a slip does not)
    slow_steady: float = 0.12
    #: phase change (beats) over 2 * window beats that counts as a slip ...
    min: float = 0.3
    #: ... up to this (beats)
    max: float = 0.7
    #: relative tempo difference allowed before/after (else a tempo change)
    same_tempo: float = 0.04
    #: beats of the running interval the phase drift is measured against
    context: int = 33
    #: F-measure by which the other tracker must prefer the moved beats
    agree_margin: float = 0.2
    #: its median interval / the section's, to count as a vote at the same tempo ...
    same_level: tuple[float, float] = (0.8, 1.25)
    #: ... or at half the tempo (every other beat: F at most 2/3)
    half_level: tuple[float, float] = (1.6, 2.5)
    #: or the section's mean off-beat gain (z-units; a slip bounds it: less than a grid)
    min_gain: float = 0.2
    #: the body of a song gives way to its intro/outro only above this gain (z-units) ...
    body_min_gain: float = 0.6
    #: ... where the two sides' mean gains differ by more than this (z-units)
    side_margin: float = 0.2
    #: one slip: an intro/outro of this many beats or more ...
    edge_beats: int = 12
    #: ... up to this many (beats: the intros/outros trackers put on the off-beats are shorter;
    #: a longer first part is as likely a tempo change read as a slip) moves on no cue ...
    edge_max_beats: int = 28
    #: ... against a body of this many beats or more (16 bars of 4): the body sets the pulse; in
    #: beats, not a share of the song, so that an excerpt decides as the whole song does
    body_beats: int = 64
    #: a section this many times as long as its neighbours together is a body too: it gives way
    #: to its gain alone (a long body between two short slipped ends)
    body_ratio: float = 2.0
    #: a slide: half the window's intervals hold this share of its phase change (a steady
    #: grid's frame jitter spreads its drift evenly; a decoder's slide concentrates it) ...
    min_concentration: float = 0.75
    #: ... or a jump: one interval this far (relative) off the running one
    min_jump: float = 0.11


@dataclass(frozen=True)
class GroupParams:
    """The bar grouping (step ``group``, :mod:`dancegraph.music.bargroup`)."""

    #: mean lag-distance difference (feature units) by which 3 or 4 must win to override the
    #: network: between the margins of right and wrong overrides on generated songs
    meter_margin: float = 0.15
    #: the same for a halved grid (no network prior; 3 must win against 4 by this)
    halved_meter_margin: float = 0.075
    #: the margin by which 4 must win where the network counted 3: 4/4 is the commoner meter
    meter_margin_to_4: float = 0.075
    #: how much more clearly (z-units) the downbeat evidence must form bars of 4 than of 3 to
    #: outweigh the bar-length self-similarity
    clarity_margin: float = 1.0
    #: weight of the harmonic change against the network's downbeat logit (both z-scored): the
    #: least that keeps every generated regression case; real recordings prefer the network
    harmony_weight: float = 1.25
    #: weight of the snare-band onsets (the backbeat, never on the downbeat), subtracted
    backbeat_weight: float = 0.75
    #: the network's mean downbeat activation at its own downbeats from which its bar phase
    #: stands: generated hard songs, built to mislead it, reach 0.66 at most
    net_confident: float = 0.7
    #: mean downbeat evidence (z-units) by which 4-beat downbeats must beat the half-bar beats
    duple_margin: float = 0.3
    #: log probability of restarting the bar at a beat (about 10 nats: several bars of evidence)
    log_restart: float = -10.0
    #: log probability of a restart next to a glitch of the grid (the count is least sure there)
    log_restart_glitch: float = -2.0
    #: mean downbeat evidence a bar (z-units) by which the sections on both sides of a bar
    #: restart must each prefer their own phase for it to stand
    #: (:func:`~dancegraph.music.bargroup.section_phases`): between the restarts full-length
    #: songs need and the weak ones a whole song bought that its excerpts did not (docs/music.md)
    min_section_gain: float = 1.5
    #: a glitch: an interval off the running median interval by this share ...
    glitch_dev: float = 0.15
    #: ... over this many intervals
    glitch_context: int = 33
    #: beats this close to a glitch may restart cheaply
    glitch_reach: int = 2
    #: beats over which the evidence's moving average is removed (a section's level says
    #: nothing about where its bars start)
    local_beats: int = 12


@dataclass(frozen=True)
class TempoParams:
    """Tempo, its metrical alternatives and the dance octave (:mod:`dancegraph.music.tempo`)."""

    #: centre (BPM) of the log-normal dance-tempo prior on the counted beat
    dance_center_bpm: float = 112.0
    #: its spread (octaves): 90-140 BPM lie within one standard deviation
    dance_sigma_octaves: float = 0.35
    #: an x3/2 or x2/3 pulse this much stronger than the tracked one competes with it
    dotted_competes: float = 1.1
    #: an x1/2 pulse this much stronger than the tracked one competes with it
    half_competes: float = 1.5
    #: the confidence is scaled by this where another level competes
    ambiguous_confidence: float = 0.5
    #: relative tempo tolerance of a metrical relation (x1, x2, x1/2, x3/2, x2/3)
    relation_tol: float = 0.06


@dataclass(frozen=True)
class ConfidenceParams:
    """The tempo confidence reported with the beats."""

    #: weight of the beat intervals' regularity; the rest is the librosa tracker's agreement
    regularity_weight: float = 0.6
    #: agreement credited where librosa counts another metrical level of the same pulse
    other_level_credit: float = 0.5
    #: a faint pulse's (``weak_pulse``) confidence is scaled by this: beats, but not sure ones
    weak_pulse: float = 0.5
    #: the fallback's confidence is scaled by this: its bar phase is right about half the time
    fallback: float = 0.7


@dataclass(frozen=True)
class FallbackParams:
    """The librosa fallback's global bar phase (:mod:`dancegraph.music.fallback`)."""

    #: accent score 3/4 gives up against 4/4: 4/4 unless 3/4 is clearly better supported
    triple_penalty: float = 0.1


@dataclass(frozen=True)
class AnalysisParams:
    """The parameters of the beat, tempo, bar-grouping and no-beat steps of one analysis.

    ``models``: the BeatNet models whose activations are averaged (an ensemble: fewer of one
    model's mistakes); ``decoder``: the bar-pointer decoder's (``barpointer.MADMOM`` reproduces
    BeatNet); ``steps``: the names of :data:`STEP_NAMES` that run, in that order whatever the
    order here; ``level_band``: the decoder's tempo range (+- this share) where a step decodes
    again at one metrical level; the rest, one frozen dataclass per step or test. Raises
    ``ValueError`` for an unknown step name.
    """

    models: tuple[int, ...] = (1, 2, 3)
    decoder: BarPointerParams = DEFAULT_DECODER
    steps: frozenset[str] = DEFAULT_STEPS
    level_band: float = 0.15
    evidence: EvidenceParams = EvidenceParams()
    no_beat: NoBeatParams = NoBeatParams()
    swing: SwingParams = SwingParams()
    double: DoubleParams = DoubleParams()
    dotted: DottedParams = DottedParams()
    octave: OctaveParams = OctaveParams()
    split: SplitParams = SplitParams()
    sound: SoundParams = SoundParams()
    off_beat: OffBeatParams = OffBeatParams()
    slip: SlipParams = SlipParams()
    group: GroupParams = GroupParams()
    tempo: TempoParams = TempoParams()
    confidence: ConfidenceParams = ConfidenceParams()
    fallback: FallbackParams = FallbackParams()

    def __post_init__(self) -> None:
        unknown = set(self.steps) - set(STEP_NAMES)
        if unknown:
            raise ValueError(f"unknown steps {sorted(unknown)}; known: {list(STEP_NAMES)}")

    def without(self, *names: str) -> AnalysisParams:
        """These parameters with the steps ``names`` switched off."""
        return replace(self, steps=self.steps - set(names))

    def with_steps(self, *names: str) -> AnalysisParams:
        """These parameters with the steps ``names`` switched on (ValueError for unknown ones)."""
        return replace(self, steps=self.steps | set(names))

    def to_dict(self) -> dict[str, Any]:
        """JSON-able nested dict (``steps`` a sorted list); :meth:`from_dict` reverses it."""
        return _plain(self)

    def digest(self) -> str:
        """12 hex digits naming these values (sha256 of the sorted JSON of :meth:`to_dict`):
        what a cache of analyses made with other parameters is keyed by."""
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:12]

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> AnalysisParams:
        """Parameters from a nested dict of overrides (missing keys keep their defaults).

        Raises ``SpecError`` (code ``analysis_params_invalid``, ``field`` the dotted key) for an
        unknown key, a value of the wrong type, or an unknown step.
        """
        return _build(cls, data or {}, "")


#: BeatNet 1.1.3 itself: model 1, its own decoder settings, no step after the decoder
BEATNET_1_1_3 = AnalysisParams(models=(1,), decoder=MADMOM, steps=frozenset())


def load_params(path: str | Path) -> AnalysisParams:
    """:class:`AnalysisParams` from a YAML or JSON file of overrides (:meth:`from_dict`).

    Raises ``SpecError`` (``analysis_params_invalid``) for a file that cannot be read or parsed,
    is not a mapping, or names an unknown key."""
    import yaml

    p = Path(path)
    try:
        text = p.read_text()
        data = json.loads(text) if p.suffix.lower() == ".json" else yaml.safe_load(text)
    except (OSError, ValueError, yaml.YAMLError) as exc:
        raise _invalid(f"cannot read analysis parameters {p}: {exc}", str(p)) from exc
    if data is not None and not isinstance(data, dict):
        raise _invalid(f"{p}: analysis parameters must be a mapping of keys", str(p))
    return AnalysisParams.from_dict(data)


def _invalid(message: str, where: str) -> SpecError:
    return SpecError(message, code="analysis_params_invalid", field=where or None)


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, frozenset):
        return sorted(value)
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value


def _build(cls: type, data: Any, where: str) -> Any:
    """An instance of the frozen dataclass ``cls`` from the overrides ``data``."""
    if not isinstance(data, dict):
        raise _invalid(f"{where or 'analysis parameters'}: expected a mapping", where)
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        key = f"{where}.{unknown[0]}" if where else unknown[0]
        raise _invalid(f"unknown analysis parameter {key!r}; known here: {names}", key)
    values = {}
    for name, raw in data.items():
        key = f"{where}.{name}" if where else name
        values[name] = _value(hints[name], raw, key)
    try:
        return cls(**values)
    except ValueError as exc:  # an unknown step
        raise _invalid(str(exc), f"{where}.steps" if where else "steps") from exc


def _value(hint: Any, raw: Any, key: str) -> Any:
    """``raw`` checked against the type ``hint`` (a dataclass, a tuple, a frozenset of str, a
    number or a str) and converted to it."""
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return _build(hint, raw, key)
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (tuple, frozenset):
        if not isinstance(raw, list | tuple):
            raise _invalid(f"{key}: expected a list, got {raw!r}", key)
        if origin is frozenset:
            return frozenset(_value(args[0], v, key) for v in raw)
        kinds = [args[0]] * len(raw) if args[-1] is Ellipsis else list(args)
        if len(kinds) != len(raw):
            raise _invalid(f"{key}: expected {len(kinds)} values, got {len(raw)}", key)
        return tuple(_value(k, v, key) for k, v in zip(kinds, raw, strict=True))
    if hint is float and isinstance(raw, int | float) and not isinstance(raw, bool):
        return float(raw)
    if hint in (int, str) and type(raw) is hint:
        return raw
    raise _invalid(f"{key}: expected {getattr(hint, '__name__', hint)}, got {raw!r}", key)
