"""Putting work on the queues: the API and the reaper call these, never ``apply_async`` directly.

Messages carry only the job id (JSON); everything else is read from the job row, so a message
that is lost (a Redis restart) or delivered twice (a killed worker) changes nothing: the reaper
re-enqueues lost jobs and the claim in ``state.claim`` drops duplicates.
"""

from __future__ import annotations

import logging

import kombu.exceptions

from services.worker.celery_app import (
    TASK_DELIVER_WEBHOOK,
    TASK_EXPORT_FBX,
    TASK_IMPORT_LIBRARY,
    TASK_QUEUES,
    TASK_RUN_JOB,
    app,
)

log = logging.getLogger("dancegraph.worker")


def _send(name: str, job_id: str) -> None:
    """Publish ``name(job_id)`` on its queue; raises when the broker is unreachable."""
    queue = TASK_QUEUES[name]
    app.send_task(
        name,
        args=[job_id],
        queue=queue,
        routing_key=queue,
        retry=True,
        retry_policy={"max_retries": 3, "interval_start": 0.2, "interval_step": 0.5},
    )
    log.info("enqueued", extra={"job_id": job_id, "task": name, "queue": queue})


def try_send(name: str, job_id: str) -> bool:
    """Like ``_send`` but a broker outage is logged and answered False (the reaper tries again)."""
    try:
        _send(name, job_id)
    except (kombu.exceptions.OperationalError, OSError) as exc:
        log.warning(
            "broker unreachable; left for the reaper",
            extra={"job_id": job_id, "task": name, "error": str(exc)},
        )
        return False
    return True


def warm_up() -> None:
    """Load the broker transport now (an import, no connection): a process that will enqueue
    calls it at start so its first burst of requests does not wait on that import."""
    app.connection_for_write().release()


def enqueue_job(job_id: str) -> None:
    """Queue a job's pipeline (``dancegraph.run_job`` on the ``analysis`` queue).

    Raises (kombu ``OperationalError``) when the broker is unreachable, so the API can refuse
    the request (503) instead of keeping a job nobody will run.
    """
    _send(TASK_RUN_JOB, job_id)


def enqueue_fbx(job_id: str) -> bool:
    """Queue the FBX export of a rendered job (``dancegraph.export_fbx`` on the ``fbx`` queue)."""
    return try_send(TASK_EXPORT_FBX, job_id)


def enqueue_webhook(job_id: str) -> bool:
    return try_send(TASK_DELIVER_WEBHOOK, job_id)


def requeue_job(job_id: str) -> bool:
    """Queue a job again (reaper); False when the broker is unreachable (next sweep retries)."""
    return try_send(TASK_RUN_JOB, job_id)


def enqueue_library(row_id: int) -> None:
    """Queue a library version's import and graph build (``dancegraph.import_library`` on the
    ``analysis`` queue; the message carries the ``datasets`` row id). Raises when the broker is
    unreachable, so the API can refuse the upload (503) instead of keeping it."""
    _send(TASK_IMPORT_LIBRARY, str(row_id))


def requeue_library(row_id: int) -> bool:
    """Queue a library version's import again (reaper); False when the broker is unreachable."""
    return try_send(TASK_IMPORT_LIBRARY, str(row_id))


def enqueue_webhook_if_pending(job_id: str) -> None:
    """Queue the completion webhook when the job is final and its webhook still pending."""
    from services.db import session_scope
    from services.models import FINAL_STATUSES, WEBHOOK_PENDING, Job

    try:
        with session_scope() as session:
            job = session.get(Job, job_id)
            pending = (
                job is not None
                and job.status in FINAL_STATUSES
                and job.webhook_status == WEBHOOK_PENDING
            )
        if pending:
            enqueue_webhook(job_id)
    except Exception:  # the reaper sends pending webhooks it finds later
        log.warning("could not queue the webhook", extra={"job_id": job_id}, exc_info=True)


def queue_size(queue: str) -> int | None:
    """Messages waiting in ``queue`` on the broker (0 when it has none); None when unreachable."""
    try:
        with app.connection_for_read() as conn:
            conn.ensure_connection(max_retries=1)
            with conn.channel() as channel:
                try:
                    _name, count, _consumers = channel.queue_declare(queue=queue, passive=True)
                except Exception:  # a queue that does not exist holds no message
                    return 0
                return int(count)
    except Exception:
        log.warning("could not read the queue size", extra={"queue": queue}, exc_info=True)
        return None
