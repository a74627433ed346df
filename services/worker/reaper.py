"""The reaper: the job row is the source of truth, the queue only a hint.

One sweep (``reap_once``):
1. ``running`` jobs whose heartbeat is older than ``Settings.job_timeout_s`` (their worker died:
   SIGKILL, OOM, a lost machine) count one crash (``Job.crashes``) and go back to ``queued``
   and are re-enqueued — or fail with ``worker_lost`` at their ``Settings.job_max_attempts``-th
   crash. Transient retries (a service down for a while) are not crashes and do not count.
2. ``queued`` jobs untouched for ``job_timeout_s`` are enqueued again when the broker holds fewer
   messages than there are such jobs: their messages are gone (Redis restarted without
   persistence). A duplicate message is harmless: ``state.claim`` lets only one worker run a job.
   Jobs rendered and waiting in the ``fbx`` queue (stage ``fbx_queued``) are not stuck: their
   FBX task is re-sent only when the ``fbx`` queue holds fewer messages than such jobs.
   Library versions' imports get the same two rules, and deleted libraries' versions that no
   live job pins are removed (``library_build.reap``).
3. final jobs whose webhook is still ``pending`` long after they finished get their webhook
   queued again (its task was lost).
4. what killed processes leave behind, untouched for ``2 × job_timeout_s``, is removed: every
   entry of the store's scratch folder (partial uploads, render and build folders, temporary
   files), result versions no manifest names, unfinished multipart uploads (S3), and uploaded
   songs (``blobs/``) that no job row references (an API killed between storing and writing
   the row), and stored rig files (``rigs/``) whose rig has no row (an upload whose row could
   not be written).

Run it as ``dancegraph reaper`` (a loop), as the Celery beat task ``dancegraph.reap``, or inside
``dancegraph serve --embedded``.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict, dataclass, field
from datetime import timedelta
from typing import Any, cast

from sqlalchemy import CursorResult, select, update

from dancegraph.store import ObjectStore
from services import jobs
from services.config import QUEUE_ANALYSIS, QUEUE_FBX, Settings, get_settings
from services.db import session_scope
from services.models import FINAL_STATUSES, QUEUED, WEBHOOK_PENDING, Job, utcnow
from services.worker import enqueue, library_build, pipeline

log = logging.getLogger("dancegraph.reaper")

WEBHOOK_GRACE_S = 600.0  # a webhook still pending this long after the job ended was lost


@dataclass
class ReapReport:
    """Job ids acted on in one sweep."""

    requeued: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    reenqueued: list[str] = field(default_factory=list)
    webhooks: list[str] = field(default_factory=list)
    fbx_resent: list[str] = field(default_factory=list)
    tmp_removed: int = 0
    orphans_removed: int = 0
    libraries: dict[str, list] = field(default_factory=dict)  # library_build.reap's actions

    def to_dict(self) -> dict:
        return asdict(self)

    def __bool__(self) -> bool:
        return bool(
            self.requeued
            or self.failed
            or self.reenqueued
            or self.webhooks
            or self.fbx_resent
            or self.tmp_removed
            or self.orphans_removed
            or any(self.libraries.values())
        )


def reap_once(
    settings: Settings | None = None, *, webhook_grace_s: float = WEBHOOK_GRACE_S
) -> ReapReport:
    """One sweep over the jobs table (see the module docstring)."""
    settings = settings or get_settings()
    report = ReapReport()
    now = utcnow()
    timeout = timedelta(seconds=settings.job_timeout_s)

    with session_scope() as session:
        stuck = jobs.stuck_jobs(session, settings.job_timeout_s, now=now)
        # Rendered jobs waiting for the fbx queue have no heartbeat while they wait: a long FBX
        # backlog is not a dead worker. Re-send their FBX task only if the queue lost messages.
        waiting_fbx = [j.id for j in stuck if j.stage == "fbx_queued"]
        stuck = [j for j in stuck if j.stage != "fbx_queued"]
        if waiting_fbx:
            held = enqueue.queue_size(QUEUE_FBX)
            if held is None or held < len(waiting_fbx):
                report.fbx_resent = waiting_fbx
            session.execute(
                update(Job)
                .where(Job.id.in_(waiting_fbx), Job.stage == "fbx_queued")
                .values(heartbeat_at=now)
                .execution_options(synchronize_session=False)
            )
        for job in stuck:
            crashes = (job.crashes or 0) + 1
            session.execute(
                update(Job)
                .where(Job.id == job.id)
                .values(crashes=Job.crashes + 1)
                .execution_options(synchronize_session=False)
            )
            if crashes >= settings.job_max_attempts:
                jobs.fail_job(
                    session,
                    job.id,
                    "worker_lost",
                    f"the job's worker stopped responding {crashes} times",
                )
                report.failed.append(job.id)
            elif jobs.requeue_job(session, job.id):
                report.requeued.append(job.id)
        waiting = list(
            session.scalars(
                select(Job.id).where(Job.status == QUEUED, Job.updated_at < now - timeout)
            )
        )
        if waiting:
            # A backlog longer than the timeout is not a loss: re-send only when the broker holds
            # fewer messages than there are waiting jobs (None: unknown, re-send).
            held = enqueue.queue_size(QUEUE_ANALYSIS)
            if held is not None and held >= len(waiting):
                waiting = []
        for job_id in waiting:
            res = cast(
                CursorResult[Any],
                session.execute(
                    update(Job)
                    .where(Job.id == job_id, Job.status == QUEUED)
                    .values(stage="requeued", updated_at=now)
                    .execution_options(synchronize_session=False)
                ),
            )
            if res.rowcount == 1:
                report.reenqueued.append(job_id)
        lost_hooks = list(
            session.scalars(
                select(Job.id).where(
                    Job.status.in_(FINAL_STATUSES),
                    Job.webhook_status == WEBHOOK_PENDING,
                    Job.finished_at < now - timedelta(seconds=webhook_grace_s),
                )
            )
        )
        if lost_hooks:
            # Restart the clock so the next sweep does not send it again.
            session.execute(
                update(Job)
                .where(Job.id.in_(lost_hooks))
                .values(finished_at=now)
                .execution_options(synchronize_session=False)
            )
    # Enqueue after the commit, so a worker never sees the row before its new state.
    for job_id in report.requeued + report.reenqueued:
        enqueue.requeue_job(job_id)
    for job_id in report.fbx_resent:
        enqueue.enqueue_fbx(job_id)
    for job_id in report.failed:
        enqueue.enqueue_webhook_if_pending(job_id)
    for job_id in lost_hooks:
        if enqueue.enqueue_webhook(job_id):
            report.webhooks.append(job_id)
    report.libraries = library_build.reap(settings)
    store = pipeline.object_store(settings)
    grace = 2 * settings.job_timeout_s
    report.tmp_removed = store.sweep_scratch(grace)
    report.orphans_removed = (
        store.sweep_orphans("jobs", grace)
        + store.sweep_uploads(grace)
        + sweep_blobs(store, grace)
        + sweep_rigs(store, grace)
    )
    if report:
        log.info("reaped", extra=report.to_dict())
    return report


def sweep_blobs(store: ObjectStore, older_than_s: float) -> int:
    """Remove uploaded songs that no job references, stored more than ``older_than_s`` ago."""
    limit = time.time() - older_than_s
    old = {
        e.key.rsplit("/", 1)[-1]: e.key for e in store.entries("blobs/sha256") if e.mtime < limit
    }
    if not old:
        return 0
    with session_scope() as session:
        used: set[str] = set()
        shas = list(old)
        for i in range(0, len(shas), 500):
            used.update(
                session.scalars(
                    select(Job.audio_sha256).where(Job.audio_sha256.in_(shas[i : i + 500]))
                )
            )
    for sha in set(old) - used:
        store.delete(old[sha])
    return len(set(old) - used)


def sweep_rigs(store: ObjectStore, older_than_s: float) -> int:
    """Remove stored rig files (``rigs/<tenant>/<rig id>/``) whose rig has no row, stored more
    than ``older_than_s`` ago; returns how many rigs' files went."""
    from services.models import Rig

    limit = time.time() - older_than_s
    old: dict[str, str] = {}
    for e in store.entries("rigs"):
        parts = e.key.split("/")
        if len(parts) == 4 and e.mtime < limit:
            old[parts[2]] = "/".join(parts[:3])
    if not old:
        return 0
    with session_scope() as session:
        ids = list(old)
        known: set[str] = set()
        for i in range(0, len(ids), 500):
            known.update(session.scalars(select(Rig.id).where(Rig.id.in_(ids[i : i + 500]))))
    for rig_id in set(old) - known:
        store.delete_prefix(old[rig_id])
    return len(set(old) - known)


def run_forever(
    interval_s: float, stop: threading.Event | None = None, settings: Settings | None = None
) -> None:
    """Sweep every ``interval_s`` seconds until ``stop`` is set; a failed sweep is logged and retried."""
    stop = stop or threading.Event()
    while not stop.is_set():
        try:
            reap_once(settings)
        except Exception:  # the database may be restarting; try again next round
            log.exception("reaper sweep failed")
        stop.wait(interval_s)


def default_interval(settings: Settings | None = None) -> float:
    """Sweep a few times per stuck timeout, at most every 60 s."""
    settings = settings or get_settings()
    return max(0.5, min(60.0, settings.job_timeout_s / 3.0))
