"""The public batch-pipeline entry point behind the ``dancegraph.submit`` task.

A pipeline that already speaks Celery can skip HTTP: it sends ``dancegraph.submit`` with a spec,
an audio file and a tenant, and the job it creates is the same as one made by ``POST /v1/jobs``:
the same checks (the functions the API calls: ``dancegraph.spec.parse_spec``, known dataset,
size, container sniffing, duration limits; ``services.common``), the same row, the same queue, the same results and webhook.

Where the outcome lands: the ``jobs`` row whose id is the ``job_id`` argument (a UUID the caller
chooses, so it can poll ``GET /v1/jobs/{job_id}`` right away). A submission refused by the checks
becomes a ``failed`` job with the check's error code (``spec_invalid``, ``unknown_dataset``,
``audio_too_short`` …), exactly the codes the API answers with.
"""

from __future__ import annotations

import logging
import uuid
from pathlib import Path

from sqlalchemy import select
from starlette.datastructures import UploadFile

from dancegraph.errors import DanceGraphError
from dancegraph.spec import check_json_value, parse_spec
from dancegraph.store import InvalidKeyError, check_key
from services import jobs
from services.common.submit import check_callback, check_dataset
from services.common.uploads import StoredAudio, check_audio
from services.config import Settings, get_settings
from services.db import session_scope
from services.models import Job, Tenant
from services.worker import enqueue, pipeline

log = logging.getLogger("dancegraph.worker")


class SubmitError(DanceGraphError):
    """A refused submission (the code and field say which check refused it)."""

    status = 422


def _tenant_id(session, tenant: str) -> str:
    row = session.scalar(select(Tenant).where((Tenant.name == tenant) | (Tenant.id == tenant)))
    if row is None:
        raise SubmitError(f"no tenant {tenant!r}", code="unknown_tenant", field="tenant")
    return row.id


def _audio_path(settings: Settings, audio: str) -> Path:
    """The file behind ``audio``: an object-store key (``blobs/sha256/…``) or an absolute path."""
    if not isinstance(audio, str) or not audio:
        raise SubmitError(
            "audio must be an object-store key or an absolute path",
            code="audio_missing",
            field="audio",
        )
    if Path(audio).is_absolute():
        path = Path(audio)
        if not path.is_file():
            raise SubmitError(f"no audio file at {audio!r}", code="audio_missing", field="audio")
        return path
    try:
        return pipeline.object_store(settings).local_path(check_key(audio))
    except InvalidKeyError as exc:
        raise SubmitError(
            f"invalid object key {audio!r}", code="audio_missing", field="audio"
        ) from exc
    except FileNotFoundError:
        raise SubmitError(
            f"no audio file at {audio!r}", code="audio_missing", field="audio"
        ) from None


def submit(
    spec: dict | str,
    audio: str,
    tenant: str,
    *,
    job_id: str | None = None,
    idempotency_key: str | None = None,
    filename: str | None = None,
    settings: Settings | None = None,
) -> str | None:
    """Validate and create one job, enqueue it; returns its id (None: refused without a row).

    ``spec``: the constraint spec (a JSON object, or its text); ``audio``: an object-store key
    or an absolute path readable by the worker; ``tenant``: the tenant's name or id; ``job_id``:
    the id to give the job (default: a new UUID); ``idempotency_key``: as the API header — a
    second submission with the same key returns the first job and creates nothing.
    """
    settings = settings or get_settings()
    job_id = str(uuid.UUID(job_id)) if job_id else str(uuid.uuid4())
    store = pipeline.object_store(settings)
    with session_scope() as session:
        tenant_id = _tenant_id(session, tenant)
        existing = session.get(Job, job_id)
        if existing is not None:
            if existing.tenant_id != tenant_id:
                raise SubmitError(f"job id {job_id} is taken", code="job_id_taken", field="job_id")
            return existing.id  # a redelivered submit: the job exists already
    try:
        parsed = parse_spec(spec)
        check_callback(settings, parsed)
        check_dataset(settings, parsed, pipeline.graphstore_client(settings), tenant_id)
        path = _audio_path(settings, audio)
        with open(path, "rb") as fh:
            checked = check_audio(UploadFile(fh, filename=filename or path.name), settings, store)
        try:
            stored = checked.store(store)
        finally:
            checked.discard()
    except DanceGraphError as exc:
        if getattr(exc, "status", 400) >= 500:
            raise  # the machinery failed (graph store down…), not the input: the task retries
        _record_refusal(job_id, tenant_id, spec, exc, idempotency_key)
        log.info(
            "submission refused",
            extra={"job_id": job_id, "error_code": exc.code, "field": exc.field},
        )
        return job_id
    with session_scope() as session:
        job, created = jobs.create_job(
            session,
            tenant_id=tenant_id,
            spec=parsed.model_dump(mode="json"),
            audio=stored,
            idempotency_key=idempotency_key,
        )
        if not created:
            return job.id
        job.id = job_id  # the caller's id; nobody has seen the row yet (same transaction)
        session.flush()
    enqueue.enqueue_job(job_id)
    return job_id


def _storable(spec: object) -> dict:
    """The refused spec as the failed row keeps it: itself when PostgreSQL's JSON type can hold
    it, else an escaped excerpt of its text (no NUL, surrogate or non-finite number)."""
    if isinstance(spec, dict):
        try:
            check_json_value(spec)
            return spec
        except DanceGraphError:
            pass
    return {"raw": ascii(spec)[:1000]}


def _record_refusal(
    job_id: str, tenant_id: str, spec: object, exc: DanceGraphError, key: str | None
) -> None:
    """A failed row for a refused submission, so its status lands where the caller looks."""
    with session_scope() as session:
        job, created = jobs.create_job(
            session,
            tenant_id=tenant_id,
            spec=_storable(spec),
            audio=StoredAudio(
                "rejected", sha256="", size=0, filename="", container="", duration_s=None
            ),
            idempotency_key=key,
        )
        if not created:
            return
        job.id = job_id
        session.flush()
        jobs.fail_job(session, job_id, exc.code, exc.message, exc.field)
