"""The constraint spec: what a user asks of a dance (DESIGN.md §5).

One pydantic model shared by the API (request validation and ``openapi.yaml``), the CLI
(``--spec FILE``) and the graph search, and one validator, :func:`parse_spec`, that every entry
point (API, ``dancegraph.submit`` task, graph-store service, CLI) calls once. Every field has a default, so ``{}`` plus a dataset is a
valid spec; unknown fields are rejected (``extra="forbid"``) so typos never pass silently.
Types are strict (``true`` is not 1, ``"3"`` is not 3; an integer is a valid float), numbers
finite, and every string bounded. Times are seconds from the start of the song; bar indices
count from 0.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    HttpUrl,
    UrlConstraints,
    ValidationError,
    field_validator,
    model_validator,
)

from dancegraph.errors import SpecError, field_errors
from dancegraph.motion.retime import BEAT_ACCENT, STOPS_ON_BEATS

if TYPE_CHECKING:
    from dancegraph.music.params import AnalysisParams

_NODE_PATTERN = re.compile(r"^[A-Za-z0-9._-]+:(\*|\d+)(~[a-z0-9]+)?$")


MAX_SPEC_DEPTH = 32  # a spec nests 4 deep; anything deeper is an attack or a mistake
MAX_ID_CHARS = 100  # node ids, take ids, tags: the longest real one is far shorter
MAX_URL_CHARS = 2000


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


class Weights(_Strict):
    """Cost weights: C = data·Σ C_d + transition·Σ C_t + structure·Σ C_s (DESIGN.md §4)."""

    data: float = Field(1.0, ge=0, description="λ10: weight of the per-bar data term")
    transition: float = Field(2.0, ge=0, description="λ11: weight of the transition term (novelty)")
    style: float = Field(1.0, ge=0, description="λ12: style distance inside the data term")
    rhythm: float = Field(
        1.5,
        ge=0,
        description=(
            "λ13: rhythm term inside the data term (rhythm-signature distance plus the "
            "node's anchoring cost: how far its motion stops sit off its beats)"
        ),
    )
    structure: float = Field(1000.0, ge=0, description="ζ: penalty per violated repeat/mirror pair")


class StructureRules(_Strict):
    repeat: bool = Field(
        True, description="same phrase label and index in different occurrences → same node"
    )
    mirror: bool = Field(True, description="same occurrence, same meter identity → mirrored nodes")


BarRange = Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=2, max_length=2)]
SecondRange = Annotated[list[Annotated[float, Field(ge=0)]], Field(min_length=2, max_length=2)]
#: a tempo range [lo, hi] BPM; 20-400 spans every danced tempo and the tracker's octaves of it
#: A motion library's name (a dataset).
LibraryName = Annotated[str, Field(pattern=r"^[a-z0-9][a-z0-9_-]{0,63}$")]

BpmRange = Annotated[
    list[Annotated[float, Field(ge=20, le=400)]], Field(min_length=2, max_length=2)
]


class _Ranged(_Strict):
    bars: BarRange | None = Field(None, description="inclusive bar range [first, last]")
    seconds: SecondRange | None = Field(None, description="time range [start, end] in seconds")

    @model_validator(mode="after")
    def _ordered(self):
        for name in ("bars", "seconds"):
            rng = getattr(self, name)
            if rng is not None and rng[0] > rng[1]:
                raise ValueError(f"{name} range must be [start, end] with start <= end")
        if self.bars is not None and self.seconds is not None:
            raise ValueError("give either bars or seconds, not both")
        return self


class Include(_Ranged):
    """Pin a node (``TAKE:BAR``, optionally ``~AUG``) at the given bars."""

    node: str = Field(
        ...,
        max_length=MAX_ID_CHARS,
        description="node id, e.g. '60_03:12' or '60_03:12~m' (mirrored)",
    )

    @field_validator("node")
    @classmethod
    def _node_id(cls, value: str) -> str:
        if "*" in value or not _NODE_PATTERN.match(value):
            raise ValueError("node must look like 'TAKE:BAR' or 'TAKE:BAR~AUG'")
        return value


class Exclude(_Ranged):
    """Never use the matching nodes (optionally only inside a bar or time range)."""

    node: str | None = Field(
        None, max_length=MAX_ID_CHARS, description="node id or take wildcard, e.g. '61_07:*'"
    )
    tag: str | None = Field(
        None,
        max_length=MAX_ID_CHARS,
        description="a node tag, e.g. 'augmented', 'blend', 'shuffle', 'mirror'",
    )

    @model_validator(mode="after")
    def _one_target(self):
        if (self.node is None) == (self.tag is None):
            raise ValueError("an exclude names exactly one of node or tag")
        if self.node is not None and not _NODE_PATTERN.match(self.node):
            raise ValueError("node must look like 'TAKE:BAR', 'TAKE:BAR~AUG' or 'TAKE:*'")
        return self


class Waypoint(_Strict):
    """The root must pass within ``tolerance`` metres of ``position`` (x, z) at ``second``."""

    second: float = Field(..., ge=0)
    position: Annotated[list[float], Field(min_length=2, max_length=2)]
    tolerance: float = Field(0.5, gt=0)


class Stage(_Strict):
    """Rectangle on the ground plane (metres) that the root trajectory must stay inside."""

    x: Annotated[list[float], Field(min_length=2, max_length=2)]
    z: Annotated[list[float], Field(min_length=2, max_length=2)]

    @model_validator(mode="after")
    def _ordered(self):
        if self.x[0] >= self.x[1] or self.z[0] >= self.z[1]:
            raise ValueError("stage bounds must be [min, max] with min < max")
        return self


class SignatureTarget(_Strict):
    """Follow a motif signature: the dataset's own, or a reference take's."""

    target: str = Field(
        "dataset",
        max_length=MAX_ID_CHARS,
        description="'dataset' or a take id of the dataset, e.g. '60_03'",
    )
    weight: float = Field(0.5, ge=0)


class MotifPin(_Strict):
    bar: int = Field(..., ge=0)
    motif: int = Field(..., ge=0)


Format = Literal["bvh", "fbx", "usd"]


def _all_formats() -> list[Format]:
    return ["bvh", "fbx"]


class Output(_Strict):
    formats: list[Format] = Field(default_factory=_all_formats, min_length=1)
    fps: Literal[30, 60] = 30
    foot_cleanup: bool = True
    stops_on_beats: bool = Field(
        STOPS_ON_BEATS,
        description="a stylization: re-time the stitched dance so its stops (the moments the "
        "dancer halts) that lie within 0.45 beat of a song beat land on it, no beat interval "
        "sped up or slowed down more than 1.5x (default off: the nodes' own beats are laid on "
        "the song's and the dance keeps its takes' pulse)",
    )
    beat_accent: float = Field(
        BEAT_ACCENT,
        ge=0,
        le=0.8,
        description="a stylization, 'hit the beats harder': how much the dance slows into every "
        "beat and speeds up between, as a share of its pace (0.4: 0.6x on the beat, 1.4x "
        "half-way; counting what the dance already has; the seams keep their own pace); beats "
        "and bar lines do not move; the timeline reports the pulse it adds; default 0: off, "
        "the dance keeps its takes' pulse",
    )
    rig: str | None = Field(
        None,
        pattern=r"^[A-Za-z0-9-]{1,36}$",
        description="id of one of your rigs (POST /v1/rigs): each alternative is also written on "
        "it as alternatives/<k>.rig.bvh and .rig.glb (and .rig.fbx / .rig.usd when formats has "
        "fbx / usd)",
    )
    follow_rig: str | None = Field(
        None,
        pattern=r"^[A-Za-z0-9-]{1,36}$",
        description="with couple: id of one of your rigs for the follow (output.rig is the "
        "lead's): alternatives/<k>/follow.rig.bvh and .rig.glb",
    )


class Spec(_Strict):
    """A user's constraint spec. Only ``dataset`` is needed, and it has a default."""

    dataset: LibraryName | Annotated[list[LibraryName], Field(min_length=1, max_length=50)] = Field(
        "cmu-salsa",
        description="the motion library, or a list of libraries to choose from by how the "
        "song fits each (graph.style_choice); the timeline names the one chosen and why",
    )
    style: LibraryName | None = Field(
        None,
        description="a style name (the library whose manifest declares that style dances), or "
        "'auto': choose among the tenant's and the public libraries (or the dataset list) by "
        "the song's tempo against each style's tempo range and the music-to-motion style "
        "distance (graph.style_choice)",
    )
    alternatives: int = Field(3, ge=1, le=10)
    seed: int = Field(0, ge=0)
    weights: Weights = Field(default_factory=Weights)
    transition_threshold: float = Field(
        20.0, gt=0, description="δT: largest transition cost of an edge"
    )
    structure: StructureRules = Field(default_factory=StructureRules)
    include: list[Include] = Field(default_factory=list, max_length=1000)
    exclude: list[Exclude] = Field(default_factory=list, max_length=1000)
    waypoints: list[Waypoint] = Field(default_factory=list, max_length=1000)
    stage: Stage | None = None
    signature: SignatureTarget | None = None
    motifs: list[MotifPin] = Field(default_factory=list, max_length=1000)
    recreate: str | None = Field(
        None,
        max_length=MAX_ID_CHARS,
        description="take id whose motif sequence to re-create on this music",
    )
    tempo_range: BpmRange | None = Field(
        None,
        description="the dance style's tempo range [lo, hi] in BPM of the counted beat: a song "
        "tracked at half or twice a tempo inside it gets its beats and bars counted at that "
        "tempo (analysis grid_octave x2 or x1/2, with a warning). Default: the range the "
        "dataset declares (its manifest's style_tempo_bpm), else the tracked tempo",
    )
    analysis: dict[str, Any] | None = Field(
        None,
        description="overrides of the music analysis's parameters: nested keys of "
        'dancegraph.music.params.AnalysisParams, e.g. {"group": {"net_confident": 0.75}} '
        "(docs/music.md); unknown keys and wrong types are refused. Default: the tuned values",
    )
    couple: bool = Field(
        False,
        description="dance as a couple, the lead and the follow together, from the dataset's "
        "takes danced together (its couple graph: dancegraph dataset build NAME --couple); "
        "files alternatives/<k>/lead.bvh and follow.bvh",
    )
    output: Output = Field(default_factory=Output)
    callback_url: Annotated[HttpUrl, UrlConstraints(max_length=MAX_URL_CHARS)] | None = Field(
        None, description="POSTed when the job ends; must name a public address"
    )

    @field_validator("dataset")
    @classmethod
    def _libraries_unique(cls, value: str | list[str]) -> str | list[str]:
        if isinstance(value, list) and len(set(value)) != len(value):
            raise ValueError("dataset: each library once")
        return value

    def libraries(self) -> list[str]:
        """The library names ``dataset`` gives, as a list (one name: a list of one)."""
        return [self.dataset] if isinstance(self.dataset, str) else list(self.dataset)

    @field_validator("tempo_range")
    @classmethod
    def _tempo_range_ordered(cls, value: list[float] | None) -> list[float] | None:
        if value is not None and value[0] >= value[1]:
            raise ValueError("tempo_range must be [lo, hi] BPM with lo < hi")
        return value

    @field_validator("analysis")
    @classmethod
    def _analysis_params_known(cls, value: dict[str, Any] | None) -> dict[str, Any] | None:
        if value is not None:
            from dancegraph.music.params import AnalysisParams

            try:
                AnalysisParams.from_dict(value)
            except SpecError as exc:
                raise ValueError(exc.message) from exc
        return value

    def analysis_params(self) -> AnalysisParams | None:
        """The music analysis's parameters this spec asks for (None: the defaults)."""
        from dancegraph.music.params import AnalysisParams

        return None if self.analysis is None else AnalysisParams.from_dict(self.analysis)

    @model_validator(mode="after")
    def _waypoints_on_stage(self):
        if self.stage is not None:
            for i, wp in enumerate(self.waypoints):
                x, z = wp.position
                if not (
                    self.stage.x[0] <= x <= self.stage.x[1]
                    and self.stage.z[0] <= z <= self.stage.z[1]
                ):
                    raise ValueError(f"waypoints[{i}] lies outside the stage")
        return self


def parse_spec(data: str | bytes | Mapping | Spec | None, *, dataset: str | None = None) -> Spec:
    """The one validator of a constraint spec; entry points call it once and pass the ``Spec`` on.

    ``data``: JSON text (``str`` or UTF-8 ``bytes``; blank or None means ``{}``), a decoded JSON
    object, or a ``Spec`` (re-validated only when ``dataset`` changes it). ``dataset``: when
    given it replaces the spec's dataset (a graph-store path or ``--dataset`` wins).

    Raises ``SpecError`` (status 422) with ``code`` ``spec_malformed`` (not UTF-8, not JSON, not
    an object, a non-finite number such as ``NaN``, ``Infinity`` or ``1e309``, nesting deeper
    than ``MAX_SPEC_DEPTH``), ``spec_unknown_field`` (a field the model does not know) or
    ``spec_invalid`` (also: text with NUL or a lone surrogate, which PostgreSQL's JSON cannot
    hold); ``field`` is the first failure's path (``spec.weights.rhythm``), ``errors`` all of
    them.
    """
    if isinstance(data, Spec):
        if dataset is None or dataset == data.dataset:
            return data
        data = data.model_dump(mode="json")
    obj = _decode(data)
    check_json_value(obj)
    if dataset is not None:
        obj = {**obj, "dataset": dataset}
    try:
        return Spec.model_validate(obj)
    except ValidationError as exc:
        errors = field_errors(exc.errors(), prefix="spec")
        first = errors[0]
        unknown = any(e["code"] == "extra_forbidden" for e in errors)
        raise SpecError(
            f"{first['field']}: {first['message']}",
            code="spec_unknown_field" if unknown else "spec_invalid",
            field=first["field"],
            errors=errors,
        ) from exc


def _decode(data: str | bytes | Mapping | None) -> dict:
    """The spec as a JSON object (dict), or SpecError ``spec_malformed``."""
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise SpecError("spec is not UTF-8 text", code="spec_malformed", field="spec") from exc
    if data is None or (isinstance(data, str) and data.strip() == ""):
        return {}
    if isinstance(data, str):
        try:
            data = json.loads(data, parse_float=_finite, parse_constant=_no_constant)
        except json.JSONDecodeError as exc:
            raise SpecError(
                f"spec is not valid JSON: {exc.msg} at char {exc.pos}",
                code="spec_malformed",
                field="spec",
            ) from exc
        except RecursionError as exc:
            raise SpecError(
                f"spec is nested more than {MAX_SPEC_DEPTH} levels deep",
                code="spec_malformed",
                field="spec",
            ) from exc
        except ValueError as exc:  # a non-finite number, an integer with too many digits
            raise SpecError(f"spec: {exc}", code="spec_malformed", field="spec") from exc
    if not isinstance(data, Mapping):
        raise SpecError("spec must be a JSON object", code="spec_malformed", field="spec")
    return dict(data)


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text[:40]} is out of range")
    return value


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number")


def _bad_text(text: str) -> str | None:
    if "\x00" in text:
        return "text may not contain NUL characters"
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return "text may not contain lone UTF-16 surrogates"
    return None


def check_json_value(data: object) -> None:
    """Raise ``SpecError`` for the first thing in a decoded JSON value that PostgreSQL's JSON
    type cannot store (NUL, a lone surrogate, a non-finite number) or that nests deeper than
    ``MAX_SPEC_DEPTH``; walks without recursion, so depth alone cannot crash it."""
    stack: list[tuple[object, str, int]] = [(data, "spec", 1)]
    while stack:
        value, path, depth = stack.pop()
        if depth > MAX_SPEC_DEPTH:
            raise SpecError(
                f"spec is nested more than {MAX_SPEC_DEPTH} levels deep",
                code="spec_malformed",
                field="spec",
            )
        if isinstance(value, str):
            why = _bad_text(value)
            if why:
                raise SpecError(f"{path}: {why}", field=path)
        elif isinstance(value, float) and not math.isfinite(value):
            raise SpecError(f"{path}: numbers must be finite", code="spec_malformed", field=path)
        elif isinstance(value, Mapping):
            for key, item in value.items():
                why = _bad_text(str(key))
                if why:
                    raise SpecError(f"{path}: key {why}", field=path)
                stack.append((item, f"{path}.{key}", depth + 1))
        elif isinstance(value, list | tuple):
            stack.extend((item, f"{path}[{i}]", depth + 1) for i, item in enumerate(value))
