"""The job service layer, shared by the API and the worker: every state change of a job goes
through here, so both sides agree on the rules.

Rules:
- A job moves queued → running → succeeded | failed, or to cancelled from queued/running.
  Final states (succeeded, failed, cancelled) never change again: every write is a conditional
  ``UPDATE … WHERE status NOT IN (final)``, so a late worker cannot overwrite a cancel.
- ``claim_job`` takes a job's lease (queued, or running with a stale heartbeat) and counts
  attempts; the worker calls ``heartbeat`` while it works; the reaper looks
  for running jobs whose heartbeat is older than ``Settings.job_timeout_s``.
- Results live in the object store under ``jobs/<job_id>/`` (``result_key``):
  ``alternatives/<k>.bvh``, ``alternatives/<k>.fbx`` (k counts from 0) and ``timeline.json``.
  ``Job.result`` holds ``SearchResult.to_dict()`` (``alternatives`` with ``cost`` …) plus
  ``files``: the written keys relative to ``jobs/<job_id>/``.
- API keys are ``dg_<32 url-safe chars>``; only their sha256 is stored.
"""

from __future__ import annotations

import hashlib
import re
import secrets
from datetime import datetime, timedelta
from typing import Any, cast

from sqlalchemy import CursorResult, and_, func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from dancegraph.errors import NotFoundError
from dancegraph.store import ObjectStore, check_key
from services.common.problems import bounded
from services.common.uploads import StoredAudio
from services.models import (
    CANCELLED,
    FAILED,
    FINAL_STATUSES,
    QUEUED,
    RUNNING,
    SUCCEEDED,
    WEBHOOK_NONE,
    WEBHOOK_PENDING,
    ApiKey,
    Batch,
    Dataset,
    Job,
    Tenant,
    utcnow,
)

KEY_PREFIX = "dg_"
_ID = re.compile(r"^[0-9a-fA-F-]{1,36}$")


def is_id(text: str) -> bool:
    """Whether ``text`` can be a job/batch id (UUID characters); anything else is simply not found."""
    return bool(_ID.match(text))


# --- tenants and API keys -------------------------------------------------------------------


def hash_key(key: str) -> str:
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


def create_api_key(session: Session, tenant_name: str) -> tuple[Tenant, str]:
    """Create (or reuse) the tenant ``tenant_name`` and a new key for it; returns the plain key once."""
    tenant = session.scalar(select(Tenant).where(Tenant.name == tenant_name))
    if tenant is None:
        tenant = Tenant(name=tenant_name)
        session.add(tenant)
        session.flush()
    key = KEY_PREFIX + secrets.token_urlsafe(24)
    session.add(ApiKey(tenant_id=tenant.id, prefix=key[:10], key_hash=hash_key(key)))
    session.flush()
    return tenant, key


def tenant_for_key(session: Session, key: str) -> Tenant | None:
    """The tenant owning a live key, or None (unknown or revoked)."""
    if not key or len(key) > 200 or not key.isascii() or not key.isprintable():
        return None
    row = session.execute(
        select(Tenant)
        .join(ApiKey, ApiKey.tenant_id == Tenant.id)
        .where(ApiKey.key_hash == hash_key(key), ApiKey.revoked_at.is_(None))
    ).scalar_one_or_none()
    return row


# --- jobs -----------------------------------------------------------------------------------


def create_job(
    session: Session,
    *,
    tenant_id: str,
    spec: dict[str, Any],
    audio: StoredAudio,
    idempotency_key: str | None = None,
    batch_id: str | None = None,
) -> tuple[Job, bool]:
    """Insert a queued job for the stored song ``audio``; returns ``(job, created)``.

    With an ``idempotency_key`` already used by this tenant, returns the existing job and
    ``created=False`` (also when two requests race: the unique constraint decides).
    """
    if idempotency_key is not None:
        existing = find_job_by_idempotency_key(session, tenant_id, idempotency_key)
        if existing is not None:
            return existing, False
    callback = spec.get("callback_url")
    job = Job(
        tenant_id=tenant_id,
        batch_id=batch_id,
        status=QUEUED,
        stage="queued",
        progress=0.0,
        spec=spec,
        audio_key=check_key(audio.key),
        audio_sha256=audio.sha256,
        audio_filename=audio.filename[:255],
        audio_bytes=audio.size,
        audio_format=audio.container,
        audio_duration_s=audio.duration_s,
        idempotency_key=idempotency_key,
        callback_url=str(callback) if callback else None,
        webhook_status=WEBHOOK_NONE,
    )
    try:
        with session.begin_nested():
            session.add(job)
    except IntegrityError:
        if idempotency_key is None:
            raise
        existing = find_job_by_idempotency_key(session, tenant_id, idempotency_key)
        if existing is None:
            raise
        return existing, False
    return job, True


def find_job_by_idempotency_key(session: Session, tenant_id: str, key: str) -> Job | None:
    return session.scalar(select(Job).where(Job.tenant_id == tenant_id, Job.idempotency_key == key))


def get_job(session: Session, job_id: str) -> Job | None:
    return session.get(Job, job_id)


def get_job_for_tenant(session: Session, tenant_id: str, job_id: str) -> Job:
    """The tenant's job; another tenant's job is reported exactly like a missing one."""
    job = session.get(Job, job_id) if is_id(job_id) else None
    if job is None or job.tenant_id != tenant_id:
        raise NotFoundError(f"no job {job_id!r}", code="job_not_found", field="job_id")
    return job


def list_jobs(
    session: Session,
    tenant_id: str,
    *,
    status: str | None = None,
    batch_id: str | None = None,
    cursor: tuple[datetime, str] | None = None,
    limit: int = 50,
) -> tuple[list[Job], tuple[datetime, str] | None]:
    """Newest first, keyset-paged on (created_at, id); returns the page and the next cursor."""
    q = select(Job).where(Job.tenant_id == tenant_id)
    if status is not None:
        q = q.where(Job.status == status)
    if batch_id is not None:
        q = q.where(Job.batch_id == batch_id)
    if cursor is not None:
        created, last_id = cursor
        q = q.where(
            or_(Job.created_at < created, and_(Job.created_at == created, Job.id < last_id))
        )
    rows = list(session.scalars(q.order_by(Job.created_at.desc(), Job.id.desc()).limit(limit + 1)))
    next_cursor = None
    if len(rows) > limit:
        rows = rows[:limit]
        next_cursor = (rows[-1].created_at, rows[-1].id)
    return rows, next_cursor


def _update_live(
    session: Session,
    job_id: str,
    values: dict[str, Any],
    *,
    only: tuple[str, ...] | None = None,
    worker: str | None = None,
) -> bool:
    """Conditional update of a job that is not final (and, with ``only``, in one of those states;
    with ``worker``, held by that worker)."""
    cond = [Job.id == job_id, Job.status.not_in(FINAL_STATUSES)]
    if only is not None:
        cond.append(Job.status.in_(only))
    if worker is not None:
        cond.append(Job.worker == worker)
    values = {**values, "updated_at": utcnow()}
    res = cast(
        CursorResult[Any],
        session.execute(
            update(Job).where(*cond).values(**values).execution_options(synchronize_session=False)
        ),
    )
    session.flush()
    return res.rowcount == 1


def claim_job(
    session: Session,
    job_id: str,
    worker: str,
    *,
    stale_after_s: float,
    stages: tuple[str, ...] | None = None,
) -> Job | None:
    """Take the lease of a job for ``worker``; the fresh row, or None when it is not ours to run.

    Claims a ``queued`` job, or a ``running`` one whose heartbeat is older than
    ``stale_after_s`` (its worker died); a duplicate delivery of a job that a live worker holds
    claims nothing. ``stages``: a ``running`` job in one of these stages is also claimable with a
    fresh heartbeat (the hand-over from the analysis queue to the FBX queue, which does not
    count as a new attempt).
    """
    now = utcnow()
    stale = now - timedelta(seconds=stale_after_s)
    running_free = and_(
        Job.status == RUNNING, or_(Job.heartbeat_at.is_(None), Job.heartbeat_at < stale)
    )
    if stages:
        running_free = or_(running_free, and_(Job.status == RUNNING, Job.stage.in_(stages)))
    res = cast(
        CursorResult[Any],
        session.execute(
            update(Job)
            .where(Job.id == job_id, or_(Job.status == QUEUED, running_free))
            .values(
                status=RUNNING,
                worker=worker[:200],
                attempts=Job.attempts + (0 if stages else 1),
                started_at=func.coalesce(Job.started_at, now),
                heartbeat_at=now,
                updated_at=now,
            )
            .execution_options(synchronize_session=False)
        ),
    )
    session.flush()
    if res.rowcount != 1:
        return None
    job = session.get(Job, job_id)
    session.refresh(job)
    return job


def heartbeat(
    session: Session,
    job_id: str,
    *,
    stage: str | None = None,
    progress: float | None = None,
    worker: str | None = None,
) -> bool:
    """Record progress of a running job; False when it is no longer running (e.g. cancelled) or,
    with ``worker``, no longer held by that worker (requeued by the reaper and claimed anew)."""
    values: dict[str, Any] = {"heartbeat_at": utcnow()}
    if stage is not None:
        values["stage"] = stage
    if progress is not None:
        values["progress"] = float(max(0.0, min(100.0, progress)))
    return _update_live(session, job_id, values, only=(RUNNING,), worker=worker)


def set_status(
    session: Session,
    job_id: str,
    status: str,
    *,
    stage: str | None = None,
    progress: float | None = None,
    analysis_summary: dict | None = None,
    result: dict | None = None,
    error_code: str | None = None,
    error_message: str | None = None,
    error_field: str | None = None,
) -> bool:
    """Move a live job to ``status`` (with its details); False when the job is already final.
    A failure's message and field are stored bounded (:func:`~services.common.problems.bounded`:
    a worker error may quote what the client sent).

    Reaching a final state stamps ``finished_at`` and, for a job with a callback URL, marks the
    webhook ``pending`` for delivery.
    """
    values: dict[str, Any] = {"status": status}
    for name, value in (
        ("stage", stage),
        ("analysis_summary", analysis_summary),
        ("result", result),
        ("error_code", error_code and error_code[:64]),
        ("error_message", error_message and bounded(error_message)),
        ("error_field", error_field and bounded(error_field, 200)),
    ):
        if value is not None:
            values[name] = value
    if progress is not None:
        values["progress"] = float(max(0.0, min(100.0, progress)))
    if status in FINAL_STATUSES:
        values["finished_at"] = utcnow()
        values.setdefault("stage", status)
        if status == SUCCEEDED:
            values["progress"] = 100.0
    ok = _update_live(session, job_id, values)
    if ok and status in FINAL_STATUSES:
        session.execute(
            update(Job)
            .where(Job.id == job_id, Job.callback_url.is_not(None))
            .values(webhook_status=WEBHOOK_PENDING)
            .execution_options(synchronize_session=False)
        )
    job = session.get(Job, job_id)
    if job is not None:
        session.refresh(job)
    return ok


def fail_job(
    session: Session, job_id: str, code: str, message: str, field: str | None = None
) -> bool:
    return set_status(
        session, job_id, FAILED, error_code=code, error_message=message, error_field=field
    )


def cancel_job(session: Session, tenant_id: str, job_id: str) -> Job:
    """Cancel the tenant's job if it is still live; returns the job (unchanged when final)."""
    job = get_job_for_tenant(session, tenant_id, job_id)
    set_status(
        session, job.id, CANCELLED, error_code="cancelled", error_message="cancelled by the client"
    )
    session.refresh(job)
    return job


def stuck_jobs(session: Session, timeout_s: float, now: datetime | None = None) -> list[Job]:
    """Running jobs whose last heartbeat is older than ``timeout_s`` (for the reaper)."""
    limit = (now or utcnow()) - timedelta(seconds=timeout_s)
    return list(session.scalars(select(Job).where(Job.status == RUNNING, Job.heartbeat_at < limit)))


def requeue_job(session: Session, job_id: str) -> bool:
    """Put a stuck running job back to queued (the caller re-enqueues it)."""
    return _update_live(
        session, job_id, {"status": QUEUED, "stage": "requeued", "worker": None}, only=(RUNNING,)
    )


def result_key(job_id: str, name: str = "") -> str:
    """Object-store key of a job's result prefix (``name`` empty) or of a file under it that is
    not part of the published result (e.g. the preview's pose cache)."""
    return check_key(f"jobs/{job_id}/{name}".rstrip("/"))


def result_files(store: ObjectStore, job_id: str) -> dict[str, str]:
    """The published result of a job (``ObjectStore.publish``): file name
    (``alternatives/0.bvh``, ``timeline.json``) → object key; empty while nothing is published."""
    return store.published(result_key(job_id)) or {}


def bvh_files(store: ObjectStore, job_id: str, *, rig: bool = False) -> list[str]:
    """Names of a job's published BVH files in order of k: the library skeleton's
    ``alternatives/<k>.bvh``, or with ``rig`` the job rig's ``alternatives/<k>.rig.bvh``."""
    tail = ".rig.bvh" if rig else ".bvh"
    names = []
    for name in result_files(store, job_id):
        folder, _, base = name.rpartition("/")
        if folder == "alternatives" and base.endswith(tail) and base[: -len(tail)].isdigit():
            names.append(name)
    return sorted(names, key=lambda n: int(n.rsplit("/", 1)[1][: -len(tail)]))


def unreferenced(session: Session, audio_keys: list[str]) -> list[str]:
    """The upload keys among ``audio_keys`` that no job row references (safe to remove)."""
    used = set(session.scalars(select(Job.audio_key).where(Job.audio_key.in_(set(audio_keys)))))
    return sorted(set(audio_keys) - used)


# --- batches --------------------------------------------------------------------------------


def create_batch(
    session: Session, *, tenant_id: str, spec: dict, idempotency_key: str | None = None
) -> tuple[Batch, bool]:
    if idempotency_key is not None:
        existing = session.scalar(
            select(Batch).where(
                Batch.tenant_id == tenant_id, Batch.idempotency_key == idempotency_key
            )
        )
        if existing is not None:
            return existing, False
    batch = Batch(tenant_id=tenant_id, spec=spec, idempotency_key=idempotency_key)
    session.add(batch)
    session.flush()
    return batch, True


def get_batch_for_tenant(session: Session, tenant_id: str, batch_id: str) -> Batch:
    batch = session.get(Batch, batch_id) if is_id(batch_id) else None
    if batch is None or batch.tenant_id != tenant_id:
        raise NotFoundError(f"no batch {batch_id!r}", code="batch_not_found", field="batch_id")
    return batch


def batch_jobs(session: Session, batch_id: str) -> list[Job]:
    return list(
        session.scalars(
            select(Job).where(Job.batch_id == batch_id).order_by(Job.created_at, Job.id)
        )
    )


# --- datasets -------------------------------------------------------------------------------


def upsert_dataset(
    session: Session,
    *,
    name: str,
    version: str,
    graph_key: str | None = None,
    stats: dict | None = None,
    licence: str = "",
    embedding: str = "descriptor",
) -> Dataset:
    """Register (or update) a public library's built version (``tenant_id`` NULL, its graph
    under its own name) in the catalog the API lists; tenants' libraries are
    ``services.common.libraries``'."""
    row = session.scalar(select(Dataset).where(Dataset.name == name, Dataset.version == version))
    if row is None:
        row = Dataset(name=name, version=version, tenant_id=None, graph_name=name)
        session.add(row)
    row.graph_key = graph_key
    row.stats = stats or {}
    row.licence = licence
    row.embedding = embedding
    session.flush()
    return row


__all__ = [
    "CANCELLED",
    "FAILED",
    "QUEUED",
    "RUNNING",
    "SUCCEEDED",
    "cancel_job",
    "claim_job",
    "create_api_key",
    "create_batch",
    "create_job",
    "fail_job",
    "get_job",
    "get_job_for_tenant",
    "heartbeat",
    "list_jobs",
    "requeue_job",
    "result_key",
    "set_status",
    "stuck_jobs",
    "tenant_for_key",
    "upsert_dataset",
]
