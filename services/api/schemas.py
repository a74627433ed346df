"""Response models of the v1 API (they define ``openapi.yaml``)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, Field


def _as_utc(value: datetime) -> datetime:
    # SQLite hands back naive datetimes; every stored time is UTC
    return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


UtcDatetime = Annotated[datetime, AfterValidator(_as_utc)]

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class AudioOut(BaseModel):
    filename: str
    sha256: str
    bytes: int
    container: str
    duration_s: float | None = Field(None, description="from the file header")


class ErrorOut(BaseModel):
    code: str = Field(..., description="stable error code, as in problem details")
    message: str
    field: str | None = None


class AlternativeOut(BaseModel):
    index: int = Field(..., description="k in the download URLs, from 0 (best first)")
    cost: float | None = Field(None, description="total cost C of the path (lower is better)")
    bars: int | None = Field(None, description="number of bars (nodes) in the path")
    violations: list[Any] = Field(default_factory=list)
    downloads: dict[str, str] = Field(default_factory=dict, description="format → URL")


class WebhookOut(BaseModel):
    status: str
    attempts: int
    last_error: str | None = None
    delivered_at: UtcDatetime | None = None


class JobOut(BaseModel):
    id: str
    url: str
    status: JobStatus
    stage: str
    progress: float = Field(..., ge=0, le=100, description="percent")
    batch_id: str | None = None
    created_at: UtcDatetime
    updated_at: UtcDatetime
    started_at: UtcDatetime | None = None
    finished_at: UtcDatetime | None = None
    attempts: int
    audio: AudioOut
    spec: dict[str, Any]
    analysis: dict[str, Any] | None = Field(None, description="music analysis summary")
    alternatives: list[AlternativeOut] = Field(default_factory=list)
    constraint_report: Any | None = None
    timeline_url: str | None = None
    preview_url: str | None = Field(
        None, description="the preview page, with a signed token (open it in a browser)"
    )
    error: ErrorOut | None = None
    webhook: WebhookOut | None = None


class JobPage(BaseModel):
    items: list[JobOut]
    next_cursor: str | None = Field(
        None, description="pass as ?cursor= for the next page; null at the end"
    )


class BatchOut(BaseModel):
    id: str
    url: str
    status: Literal["queued", "running", "completed"]
    created_at: UtcDatetime
    spec: dict[str, Any]
    counts: dict[str, int] = Field(..., description="jobs per status")
    jobs: list[JobOut]


class DatasetTakeOut(BaseModel):
    """One take of an import: imported (its grid) or failed (its code)."""

    file: str
    id: str | None = None
    status: Literal["imported", "failed", "excluded"]
    code: str | None = Field(None, description="why it failed, as a stable code")
    message: str | None = None
    duration_s: float | None = None
    tempo_bpm: float | None = None
    bars: int | None = None
    beat_source: str | None = None
    flags: list[str] = Field(default_factory=list)


class DatasetVersionOut(BaseModel):
    version: str
    status: JobStatus
    created_at: UtcDatetime
    graph_version: str | None = None


class DatasetOut(BaseModel):
    name: str
    version: str = Field(..., description="this version's id (public libraries: the graph version)")
    licence: str
    embedding: str
    stats: dict[str, Any]
    created_at: UtcDatetime | None = None
    public: bool = Field(True, description="installed by the operator: read-only to tenants")
    url: str = ""
    status: JobStatus = Field("succeeded", description="this version's import and build")
    stage: str = "done"
    progress: float = Field(100.0, ge=0, le=100, description="percent")
    graph_version: str | None = Field(None, description="the built graph's version")
    nodes: int | None = None
    edges: int | None = None
    takes: list[DatasetTakeOut] = Field(default_factory=list)
    warnings: list[str] = Field(default_factory=list)
    seconds: dict[str, float] = Field(
        default_factory=dict, description="the worker's seconds per phase: fetch, import, build"
    )
    error: ErrorOut | None = None
    finished_at: UtcDatetime | None = None
    versions: list[DatasetVersionOut] = Field(
        default_factory=list, description="every live version of a tenant library, newest first"
    )


class DatasetList(BaseModel):
    items: list[DatasetOut]


class Health(BaseModel):
    status: Literal["ok"]
    version: str


class Readiness(BaseModel):
    status: Literal["ready", "not_ready"]
    checks: dict[str, str] = Field(..., description="component → 'ok' or the reason it is not")


class RigOut(BaseModel):
    """A character rig: the humanoid roles found on it and what was left unmapped."""

    id: str
    filename: str
    format: Literal["fbx", "glb", "bvh"]
    created_at: UtcDatetime
    size_bytes: int
    joints: int = Field(..., description="joints in the hips' hierarchy")
    root: str
    roles: dict[str, str] = Field(..., description="humanoid role → joint name")
    how: dict[str, str] = Field(
        ..., description="per role: 'user', 'preset:<name>' (mixamo, unreal, ...) or 'structure'"
    )
    unmapped: list[str] = Field(..., description="joints that keep their bind pose (twist, face)")
    missing_optional: list[str] = Field(..., description="optional roles the rig has no joint for")
    mapping: dict[str, str] = Field(..., description="the mapping sent with the upload")
    height_m: float
    mesh: dict[str, int] | None = Field(None, description="the skinned mesh: vertices, triangles")
    up_axis: str | None = Field(
        None, description="the file's axis the character stands along: +Y (upright) or e.g. +Z"
    )
    unit_scale: float | None = Field(
        None, description="metres per unit of the file (0.01: centimetres); height_m is in metres"
    )
    ancestors: list[str] | None = Field(
        None,
        description="nodes above the skeleton's root, outermost first (kept in written files)",
    )


class RigList(BaseModel):
    items: list[RigOut]
