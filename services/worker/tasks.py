"""Celery tasks — thin shells over ``services.worker.pipeline`` (public names in docs/tasks.md).

Failure policy, the same for every task:
- ``DanceGraphError`` (the input's fault: bad audio, no beat, unknown dataset, impossible
  constraint) → the job fails with the error's stable ``code``; no retry.
- transient errors (database, broker, object-store or graph-store connection; a
  DanceGraphError with status 503 such as ``graphstore_unavailable``) → the job goes back to
  ``queued`` and the task retries with exponential backoff, at most ``MAX_RETRIES`` times; then
  the job fails with ``service_unavailable``. These retries are not crashes: the reaper's
  ``worker_lost`` budget counts only jobs it found abandoned (``Job.crashes``).
- a full disk or quota (ENOSPC, EDQUOT) → the same, but on a slower schedule that outlasts a
  disk-full episode (``disk_full_delay``: 30 s doubling to 5 min, ``DISK_FULL_RETRIES`` tries,
  about two hours in all) until an operator or the reaper frees space; then the job fails with
  ``store_full``.
- the soft time limit → the job fails with ``job_timeout``; any other exception (a bug) → the
  job fails with ``internal_error`` and the traceback is logged.
A job's error message never carries an exception's own text (it may name hosts, ports or
paths): that goes to the log.
"""

from __future__ import annotations

import logging
import uuid

import httpx
import kombu.exceptions
import sqlalchemy.exc
from celery.exceptions import SoftTimeLimitExceeded

from dancegraph.errors import DanceGraphError
from services import jobs, webhooks
from services.common.problems import is_disk_full
from services.config import get_settings
from services.db import session_scope
from services.worker import enqueue, logs, pipeline, state
from services.worker.celery_app import (
    TASK_DELIVER_WEBHOOK,
    TASK_EXPORT_FBX,
    TASK_IMPORT_LIBRARY,
    TASK_REAP,
    TASK_RUN_JOB,
    TASK_SUBMIT,
    app,
)

log = logging.getLogger("dancegraph.worker")

MAX_RETRIES = 5
RETRY_BASE_S = 2.0
RETRY_MAX_S = 120.0
DISK_FULL_RETRIES = 30
DISK_FULL_BASE_S = 30.0
DISK_FULL_MAX_S = 300.0  # under the reaper's job_timeout_s, which re-sends older queued jobs

TRANSIENT_ERRORS: tuple[type[BaseException], ...] = (
    sqlalchemy.exc.OperationalError,
    sqlalchemy.exc.InterfaceError,
    sqlalchemy.exc.DisconnectionError,
    httpx.TransportError,
    kombu.exceptions.OperationalError,
    ConnectionError,
    TimeoutError,
)


def retry_delay(retries: int) -> float:
    """Seconds before retry number ``retries`` (0-based): 2, 4, 8, … capped at 120."""
    return min(RETRY_MAX_S, RETRY_BASE_S * (2**retries))


def disk_full_delay(retries: int) -> float:
    """Seconds before retry number ``retries`` (0-based) of a job stopped by a full disk: 30, 60,
    120, 240, then 300 each; ``DISK_FULL_RETRIES`` of them wait 8,250 s (2.3 h) in all."""
    return min(DISK_FULL_MAX_S, DISK_FULL_BASE_S * (2**retries))


def is_transient(exc: BaseException) -> bool:
    """A failure of the machinery, not of the input: worth retrying later."""
    if is_disk_full(exc):  # space comes back (the reaper sweeps, an operator adds some)
        return True
    if isinstance(exc, DanceGraphError):
        # e.g. graphstore_unavailable: the graph store's client answers 503 for a lost connection
        return getattr(exc, "status", 400) == 503
    return isinstance(exc, TRANSIENT_ERRORS)


def _run(task, job_id: str, step) -> None:
    """Run one pipeline step for ``job_id`` under the failure policy above."""
    with logs.job_context(job_id):
        try:
            outcome = step(job_id)
        except state.JobCancelled:
            log.info("job is no longer ours (cancelled or taken over); stopping")
        except SoftTimeLimitExceeded:
            log.warning("soft time limit exceeded")
            pipeline.fail(
                job_id, DanceGraphError("the job ran past its time limit", code="job_timeout")
            )
        except Exception as exc:
            if is_transient(exc):
                _retry_or_give_up(task, job_id, exc)
            elif isinstance(exc, DanceGraphError):
                log.info("job failed", extra={"error_code": exc.code, "error": exc.message})
                pipeline.fail(job_id, exc)
            else:
                log.exception("internal error")
                _fail_quietly(
                    job_id, "internal_error", "an internal error stopped the job (see the logs)"
                )
        else:
            if outcome.status == "fbx_queued":
                enqueue.enqueue_fbx(job_id)
                return
            if outcome.status == "skipped":
                return
        enqueue.enqueue_webhook_if_pending(job_id)


def _retry_or_give_up(task, job_id: str, exc: Exception) -> None:
    """Requeue the job and retry the task with backoff (the disk-full schedule for a full disk);
    fail it (``store_full`` / ``service_unavailable``) once the retries are spent."""
    disk_full = is_disk_full(exc)
    budget = DISK_FULL_RETRIES if disk_full else MAX_RETRIES
    retries = task.request.retries
    if retries >= budget:
        log.error("transient errors exhausted the retries", exc_info=True)
        code, what = (
            ("store_full", "the store stayed full")
            if disk_full
            else ("service_unavailable", "a service stayed unavailable")
        )
        _fail_quietly(job_id, code, f"{what} through {budget} retries ({type(exc).__name__})")
        return
    delay = disk_full_delay(retries) if disk_full else retry_delay(retries)
    log.warning("transient error; retrying", extra={"delay_s": delay, "error": str(exc)})
    _requeue_quietly(job_id)
    raise task.retry(countdown=delay, exc=exc, max_retries=budget) from exc


def _fail_quietly(job_id: str, code: str, message: str) -> None:
    try:
        with session_scope() as session:
            jobs.fail_job(session, job_id, code, message)
    except Exception:  # the reaper fails it later from the row
        log.exception("could not record the failure")


def _requeue_quietly(job_id: str) -> None:
    try:
        with session_scope() as session:
            jobs.requeue_job(session, job_id)
    except Exception:  # the row stays running; the reaper requeues it once its heartbeat is stale
        log.warning("could not requeue before retry", exc_info=True)


@app.task(name=TASK_RUN_JOB, bind=True, max_retries=MAX_RETRIES)
def run_job(self, job_id: str) -> None:
    """Analyze, search and render job ``job_id``; hand over to the fbx queue or finalize."""
    _run(self, job_id, pipeline.run_job)


@app.task(
    name=TASK_IMPORT_LIBRARY,
    bind=True,
    max_retries=MAX_RETRIES,
    # the sandboxed import's own wall-clock limit, then the graph build
    soft_time_limit=get_settings().library_sandbox_wall_s + get_settings().job_soft_time_limit_s,
    time_limit=get_settings().library_sandbox_wall_s + get_settings().job_soft_time_limit_s + 60,
)
def import_library(self, row_id: str) -> None:
    """Import and build one uploaded library version (``services.worker.library_build``),
    under the failure policy above (its row fails with the error's code)."""
    from services.worker import library_build

    library_build.run_task(self, int(row_id))


@app.task(name=TASK_EXPORT_FBX, bind=True, max_retries=MAX_RETRIES)
def export_fbx(self, job_id: str) -> None:
    """Write the FBX files of a rendered job (the ``fbx`` queue) and finalize it."""
    _run(self, job_id, pipeline.run_fbx)


@app.task(name=TASK_DELIVER_WEBHOOK, bind=True, max_retries=None)
def deliver_webhook(self, job_id: str, delivery_id: str | None = None, attempt: int = 0) -> None:
    """One try of a job's completion webhook; retried with backoff while transient, bounded."""
    settings = get_settings()
    delivery_id = delivery_id or str(uuid.uuid4())
    final = attempt + 1 >= settings.webhook_max_attempts
    with logs.job_context(job_id):
        result = webhooks.deliver_job_webhook(job_id, delivery_id=delivery_id, final_attempt=final)
        if result is None or result.ok or final or not result.retryable:
            return
        delay = webhooks.backoff_delay(attempt, settings.webhook_backoff_s, 300.0)
        raise self.retry(
            countdown=delay,
            kwargs={"job_id": job_id, "delivery_id": delivery_id, "attempt": attempt + 1},
        )


@app.task(name=TASK_SUBMIT, bind=True, max_retries=MAX_RETRIES)
def submit(self, spec: dict, audio: str, tenant: str, **options) -> str | None:
    """Public batch-pipeline entry: validate like the API, create the job, enqueue it.

    See ``services.worker.submit.submit`` and docs/tasks.md for the arguments.
    """
    from services.worker import submit as submit_mod

    try:
        return submit_mod.submit(spec, audio, tenant, **options)
    except Exception as exc:
        if not is_transient(exc):
            raise
        raise self.retry(countdown=retry_delay(self.request.retries), exc=exc) from exc


@app.task(name=TASK_REAP)
def reap() -> dict:
    """One sweep of the reaper (for Celery beat; ``dancegraph reaper`` runs the same in a loop)."""
    from services.worker import reaper

    return reaper.reap_once().to_dict()
