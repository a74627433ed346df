"""Database models (SQLAlchemy 2): tenants, API keys, jobs, batches, datasets (motion libraries).

The ``jobs`` row is the source of truth for a job's state; Celery messages only carry its id.
Every schema change gets an Alembic migration in ``migrations/versions``.
"""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

JSONType = JSON().with_variant(JSONB(), "postgresql")

# Job states. Final states never change again.
QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED = (
    "queued",
    "running",
    "succeeded",
    "failed",
    "cancelled",
)
JOB_STATUSES = (QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELLED)
FINAL_STATUSES = frozenset({SUCCEEDED, FAILED, CANCELLED})

# Webhook delivery states of a job with a callback_url.
WEBHOOK_NONE, WEBHOOK_PENDING, WEBHOOK_DELIVERED, WEBHOOK_FAILED = (
    "none",
    "pending",
    "delivered",
    "failed",
)


def utcnow() -> datetime:
    return datetime.now(UTC)


def new_id() -> str:
    return str(uuid.uuid4())


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSONType}


class Tenant(Base):
    __tablename__ = "tenants"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class ApiKey(Base):
    """An API key, stored as the sha256 of the full key (keys are 32 random bytes: no salt needed)."""

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"), index=True)
    prefix: Mapped[str] = mapped_column(String(16), comment="first characters, shown in listings")
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)


class Batch(Base):
    """Many songs, one spec: a batch owns its jobs."""

    __tablename__ = "batches"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"), index=True)
    spec: Mapped[dict[str, Any]] = mapped_column(JSONType)
    idempotency_key: Mapped[str | None] = mapped_column(String(200), nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    __table_args__ = (
        UniqueConstraint("tenant_id", "idempotency_key", name="uq_batches_tenant_idem"),
    )


class Job(Base):
    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"))
    batch_id: Mapped[str | None] = mapped_column(
        ForeignKey("batches.id", ondelete="SET NULL"), nullable=True, index=True
    )
    status: Mapped[str] = mapped_column(String(16), default=QUEUED)
    stage: Mapped[str] = mapped_column(String(32), default="queued")
    progress: Mapped[float] = mapped_column(Float, default=0.0, comment="percent, 0..100")
    spec: Mapped[dict[str, Any]] = mapped_column(JSONType)
    audio_key: Mapped[str] = mapped_column(String(200), comment="object-store key of the upload")
    audio_sha256: Mapped[str] = mapped_column(String(64), index=True)
    audio_filename: Mapped[str] = mapped_column(String(255), default="")
    audio_bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    audio_format: Mapped[str] = mapped_column(String(16), default="", comment="sniffed container")
    audio_duration_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    idempotency_key: Mapped[str | None] = mapped_column(String(200), nullable=True)
    analysis_summary: Mapped[dict[str, Any] | None] = mapped_column(JSONType, nullable=True)
    result: Mapped[dict[str, Any] | None] = mapped_column(
        JSONType, nullable=True, comment="search result + rendered file keys"
    )
    error_code: Mapped[str | None] = mapped_column(String(64), nullable=True)
    error_message: Mapped[str | None] = mapped_column(Text, nullable=True)
    error_field: Mapped[str | None] = mapped_column(String(200), nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    crashes: Mapped[int] = mapped_column(
        Integer,
        default=0,
        server_default="0",
        comment="times the reaper found the job abandoned by its worker",
    )
    worker: Mapped[str | None] = mapped_column(
        String(200), nullable=True, comment="hostname/pid running it"
    )
    callback_url: Mapped[str | None] = mapped_column(Text, nullable=True)
    dataset_graph: Mapped[str | None] = mapped_column(
        String(64), nullable=True, comment="graph the job pinned when it started"
    )
    dataset_version: Mapped[str | None] = mapped_column(
        String(64), nullable=True, comment="graph version the job pinned when it started"
    )
    webhook_status: Mapped[str] = mapped_column(String(16), default=WEBHOOK_NONE)
    webhook_attempts: Mapped[int] = mapped_column(Integer, default=0)
    webhook_last_error: Mapped[str | None] = mapped_column(Text, nullable=True)
    webhook_delivered_at: Mapped[datetime | None] = mapped_column(
        DateTime(timezone=True), nullable=True
    )
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(
        DateTime(timezone=True), default=utcnow, onupdate=utcnow
    )
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)

    __table_args__ = (
        UniqueConstraint("tenant_id", "idempotency_key", name="uq_jobs_tenant_idem"),
        Index("ix_jobs_tenant_created", "tenant_id", "created_at", "id"),
        Index("ix_jobs_status_heartbeat", "status", "heartbeat_at"),
    )

    @property
    def is_final(self) -> bool:
        return self.status in FINAL_STATUSES


class Dataset(Base):
    """One version of a motion library: a public one the operator installed (``tenant_id``
    NULL, built from a shell, always ``succeeded``), or a tenant's upload (``POST
    /v1/datasets``), which is also the import-and-build job of that version: the same
    queued → running → succeeded | failed lifecycle, lease, heartbeat and crash count as a
    dance job (``services.common.libraries``)."""

    __tablename__ = "datasets"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    tenant_id: Mapped[str | None] = mapped_column(
        ForeignKey("tenants.id", ondelete="CASCADE"),
        nullable=True,
        index=True,
        comment="owner; NULL: a public library (read-only to tenants)",
    )
    name: Mapped[str] = mapped_column(String(64), index=True)
    version: Mapped[str] = mapped_column(String(64))
    graph_name: Mapped[str | None] = mapped_column(
        String(64), nullable=True, comment="the graph store's name of this version's graph"
    )
    graph_key: Mapped[str | None] = mapped_column(
        String(300), nullable=True, comment="object-store key"
    )
    stats: Mapped[dict[str, Any]] = mapped_column(JSONType, default=dict)
    licence: Mapped[str] = mapped_column(Text, default="")
    embedding: Mapped[str] = mapped_column(
        String(64), default="descriptor", comment="style embedding kind"
    )
    status: Mapped[str] = mapped_column(String(16), default=SUCCEEDED, server_default=SUCCEEDED)
    stage: Mapped[str] = mapped_column(String(32), default="done", server_default="done")
    progress: Mapped[float] = mapped_column(
        Float, default=100.0, server_default="100", comment="percent, 0..100"
    )
    upload: Mapped[dict[str, Any] | None] = mapped_column(
        JSONType, nullable=True, comment="the uploaded files' keys and the manifest"
    )
    report: Mapped[dict[str, Any] | None] = mapped_column(
        JSONType, nullable=True, comment="per-take results, warnings, graph build"
    )
    error_code: Mapped[str | None] = mapped_column(String(64), nullable=True)
    error_message: Mapped[str | None] = mapped_column(Text, nullable=True)
    error_field: Mapped[str | None] = mapped_column(String(200), nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    crashes: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    worker: Mapped[str | None] = mapped_column(String(200), nullable=True)
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    deleted_at: Mapped[datetime | None] = mapped_column(
        DateTime(timezone=True),
        nullable=True,
        comment="deleted by its owner; objects removed once no live job pins it",
    )
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    updated_at: Mapped[datetime | None] = mapped_column(
        DateTime(timezone=True), nullable=True, default=utcnow, onupdate=utcnow
    )

    __table_args__ = (
        UniqueConstraint("name", "version", name="uq_datasets_name_version"),
        Index("ix_datasets_status_heartbeat", "status", "heartbeat_at"),
    )


class Rig(Base):
    """A tenant's character rig (``POST /v1/rigs``): the file in the object store, its roles."""

    __tablename__ = "rigs"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"), index=True)
    filename: Mapped[str] = mapped_column(String(255))
    format: Mapped[str] = mapped_column(String(8), comment="fbx, glb or bvh")
    file_key: Mapped[str] = mapped_column(String(300), comment="object-store key of the file")
    sha256: Mapped[str] = mapped_column(String(64))
    size_bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    mapping: Mapped[dict[str, Any]] = mapped_column(
        JSONType, default=dict, comment="the user's role → joint overrides"
    )
    summary: Mapped[dict[str, Any]] = mapped_column(
        JSONType, default=dict, comment="roles found, unmapped joints, mesh (Rig.summary)"
    )
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
