"""Accepting uploads as jobs: validate everything, store, write rows, enqueue — in that order,
so a refused request leaves nothing behind and a stored job is always enqueued or removed."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

from sqlalchemy import select
from starlette.datastructures import UploadFile

from dancegraph.spec import Spec
from dancegraph.store import ObjectStore
from services import jobs, webhooks
from services.common import catalog
from services.common.problems import ApiError
from services.common.uploads import CheckedAudio, FilePart, check_audio
from services.config import Settings
from services.db import session_scope
from services.models import Batch, Job

log = logging.getLogger("dancegraph.api")


def check_callback(settings: Settings, spec: Spec) -> None:
    """Refuse a callback_url that names a non-public address (422 ``callback_url_forbidden``)."""
    if spec.callback_url is not None:
        webhooks.check_callback_url(str(spec.callback_url), settings.webhook_allow_networks)


def check_dataset(settings: Settings, spec: Spec, graphstore, tenant_id: str | None = None) -> None:
    """422 ``unknown_dataset`` unless each library ``spec.dataset`` names (one, or a list) is a
    public library (the catalog, or the graph store) or a built library of the tenant
    ``tenant_id``."""
    with session_scope(settings.database_url) as session:
        for name in spec.libraries():
            if catalog.find_dataset(session, name, graphstore, tenant_id) is None:
                raise ApiError(
                    422, "unknown_dataset", f"no dataset named {name!r}", field="spec.dataset"
                )


def spec_json(spec: Spec) -> dict:
    """The spec as stored on the job row: every field, defaults filled in, JSON types."""
    return spec.model_dump(mode="json")


def check_rig(settings: Settings, tenant_id: str, spec: Spec) -> None:
    """422 ``unknown_rig`` when ``spec.output.rig`` (or a couple's ``output.follow_rig``) names
    no rig of this tenant."""
    from services.common.rigs import find_rig

    named = {"rig": spec.output.rig, "follow_rig": spec.output.follow_rig}
    if not any(named.values()):
        return
    with session_scope(settings.database_url) as session:
        for field, rig_id in named.items():
            if rig_id is not None and find_rig(session, tenant_id, rig_id) is None:
                raise ApiError(
                    422,
                    "unknown_rig",
                    f"you have no rig {rig_id!r} (POST /v1/rigs first)",
                    field=f"spec.output.{field}",
                )


def _key_reused() -> ApiError:
    return ApiError(
        409,
        "idempotency_key_reused",
        "this Idempotency-Key was used for a different request",
        field="header.Idempotency-Key",
    )


def submit_job(
    settings: Settings,
    store: ObjectStore,
    enqueue: Callable[[str], object],
    *,
    tenant_id: str,
    spec: Spec,
    upload: UploadFile | FilePart,
    idempotency_key: str | None,
    graphstore,
) -> tuple[Job, bool]:
    """Validate, store and enqueue one job; returns ``(job, created)`` (False: idempotent replay)."""
    check_callback(settings, spec)
    check_dataset(settings, spec, graphstore, tenant_id)
    check_rig(settings, tenant_id, spec)
    checked = check_audio(upload, settings, store)
    spec_dict = spec_json(spec)
    try:
        if idempotency_key is not None:
            with session_scope(settings.database_url) as session:
                existing = jobs.find_job_by_idempotency_key(session, tenant_id, idempotency_key)
                if existing is not None:
                    if existing.audio_sha256 != checked.sha256 or existing.spec != spec_dict:
                        raise _key_reused()
                    return existing, False
        stored = checked.store(store)
    finally:
        checked.discard()
    with session_scope(settings.database_url) as session:
        job, created = jobs.create_job(
            session,
            tenant_id=tenant_id,
            spec=spec_dict,
            audio=stored,
            idempotency_key=idempotency_key,
        )
    if not created:  # lost a race with the same key: the other request enqueued it
        if job.audio_sha256 != stored.sha256 or job.spec != spec_dict:
            raise _key_reused()
        return job, False
    _enqueue_or_remove(settings, store, enqueue, [job.id])
    log.info("job accepted", extra={"job_id": job.id, "tenant_id": tenant_id, "bytes": stored.size})
    return job, True


def submit_batch(
    settings: Settings,
    store: ObjectStore,
    enqueue: Callable[[str], object],
    *,
    tenant_id: str,
    spec: Spec,
    uploads: Sequence[UploadFile | FilePart],
    idempotency_key: str | None,
    graphstore,
) -> tuple[Batch, list[Job], bool]:
    """Validate every song first, then store them all, write the batch and jobs, enqueue."""
    if len(uploads) > settings.max_batch_items:
        raise ApiError(
            422,
            "batch_too_large",
            f"at most {settings.max_batch_items} songs per batch",
            field="audio",
        )
    check_callback(settings, spec)
    check_dataset(settings, spec, graphstore, tenant_id)
    check_rig(settings, tenant_id, spec)
    spec_dict = spec_json(spec)
    if idempotency_key is not None:
        with session_scope(settings.database_url) as session:
            batch = (
                session.query(Batch)
                .filter_by(tenant_id=tenant_id, idempotency_key=idempotency_key)
                .one_or_none()
            )
            if batch is not None:
                rows = jobs.batch_jobs(session, batch.id)
                sent = [getattr(u, "sha256", None) for u in uploads]
                if batch.spec != spec_dict or sent != [j.audio_sha256 for j in rows]:
                    raise _key_reused()
                return batch, rows, False
    checked: list[CheckedAudio] = []
    try:
        for i, upload in enumerate(uploads):
            checked.append(check_audio(upload, settings, store, field=f"audio[{i}]"))
        stored = [c.store(store) for c in checked]
    finally:
        for c in checked:
            c.discard()
    with session_scope(settings.database_url) as session:
        batch, _ = jobs.create_batch(
            session, tenant_id=tenant_id, spec=spec_dict, idempotency_key=idempotency_key
        )
        rows = []
        for s in stored:
            job, _ = jobs.create_job(
                session,
                tenant_id=tenant_id,
                spec=spec_dict,
                audio=s,
                batch_id=batch.id,
            )
            rows.append(job)
    _enqueue_or_remove(settings, store, enqueue, [j.id for j in rows], batch_id=batch.id)
    with session_scope(settings.database_url) as session:
        fresh = session.get(Batch, batch.id)
        assert fresh is not None  # written above, never deleted once enqueued
        return fresh, jobs.batch_jobs(session, batch.id), True


def _enqueue_or_remove(
    settings: Settings,
    store: ObjectStore,
    enqueue,
    job_ids: list[str],
    batch_id: str | None = None,
) -> None:
    """Enqueue each job; if the queue refuses the first, remove the rows and the songs only
    they referenced (503: nothing kept), else fail the rest."""
    for i, job_id in enumerate(job_ids):
        try:
            enqueue(job_id)
        except Exception as exc:
            log.error("enqueue failed for job %s: %s", job_id, exc)
            with session_scope(settings.database_url) as session:
                if i == 0:
                    keys = list(session.scalars(select(Job.audio_key).where(Job.id.in_(job_ids))))
                    for jid in job_ids:
                        session.query(Job).filter_by(id=jid).delete()
                    if batch_id is not None:
                        session.query(Batch).filter_by(id=batch_id).delete()
                    session.flush()
                    for key in jobs.unreferenced(session, keys):
                        store.delete(key)
                else:
                    for jid in job_ids[i:]:
                        jobs.fail_job(
                            session, jid, "queue_unavailable", "the job queue refused the job"
                        )
            if i == 0:
                raise ApiError(
                    503,
                    "queue_unavailable",
                    "the job queue is not reachable; try again later",
                    headers={"Retry-After": "5"},
                ) from exc
            return
