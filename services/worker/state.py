"""Job-row bookkeeping on the worker side: leases, heartbeats, progress.

The ``jobs`` row is the source of truth. A worker may only work on a job it has *claimed*:

- ``claim`` moves a job to ``running`` only if it is ``queued``, or ``running`` with a heartbeat
  older than the stuck timeout (its worker died). A duplicate delivery of a job that another
  live worker holds therefore claims nothing and is dropped; this is what makes "the job
  completes once" hold when a broker redelivers a message.
- While a task works, a ``Heartbeat`` thread refreshes ``heartbeat_at``; it also notices when the
  job stopped being ``running`` (cancelled through the API) so the pipeline can stop early.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Callable

from services import jobs
from services.db import session_scope
from services.models import FINAL_STATUSES, Job

log = logging.getLogger("dancegraph.worker")


def worker_name() -> str:
    """``host:pid`` of this process, recorded on the rows it works on."""
    return f"{socket.gethostname()}:{os.getpid()}"


class JobCancelled(Exception):
    """The job left the ``running`` state (cancelled, or taken over) while a task worked on it."""


def claim(
    job_id: str, *, stale_after_s: float, stages: tuple[str, ...] | None = None
) -> Job | None:
    """Take the lease of a job for this process (``jobs.claim_job``); a detached copy of the
    fresh row, or None when it is not ours to run."""
    with session_scope() as session:
        job = jobs.claim_job(
            session, job_id, worker_name(), stale_after_s=stale_after_s, stages=stages
        )
        if job is not None:
            session.expunge(job)
        return job


def load(job_id: str) -> Job | None:
    """A detached copy of the job row (None when it does not exist)."""
    with session_scope() as session:
        job = session.get(Job, job_id)
        if job is not None:
            session.expunge(job)
        return job


def is_final(job_id: str) -> bool:
    job = load(job_id)
    return job is None or job.status in FINAL_STATUSES


def beat(job_id: str, *, stage: str | None = None, percent: float | None = None) -> bool:
    """Refresh the heartbeat (and stage/percent) of a job this process holds.

    False when the job is no longer ours: cancelled, finished, or requeued by the reaper and
    claimed by another worker (the ``worker`` column names the holder).
    """
    with session_scope() as session:
        return jobs.heartbeat(session, job_id, stage=stage, progress=percent, worker=worker_name())


def progress(job_id: str, stage: str, percent: float) -> None:
    """Record stage and percent; raise JobCancelled when the job is no longer ours."""
    if not beat(job_id, stage=stage, percent=percent):
        raise JobCancelled(job_id)
    log.info("stage", extra={"job_id": job_id, "stage": stage, "progress": percent})


class Heartbeat:
    """A daemon thread that refreshes the job's heartbeat every ``interval_s`` while alive
    (``beat_fn``: what one beat does, default ``beat(job_id)``; False means the work is no
    longer ours, e.g. a library version's import, ``services.worker.library_build``)."""

    def __init__(self, job_id: str, interval_s: float, beat_fn: Callable[[], bool] | None = None):
        self.job_id = job_id
        self.beat_fn = beat_fn or (lambda: beat(job_id))
        self.interval_s = max(0.2, float(interval_s))
        self.lost = threading.Event()  # set when the job stopped being running
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"heartbeat-{job_id}", daemon=True)

    def __enter__(self) -> Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *_exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                if not self.beat_fn():
                    self.lost.set()
                    return
            except Exception:  # a DB blip: the next beat tries again
                log.warning("heartbeat failed", extra={"job_id": self.job_id}, exc_info=True)

    def check(self) -> None:
        """Raise JobCancelled if the job stopped being ours."""
        if self.lost.is_set():
            raise JobCancelled(self.job_id)


def heartbeat_interval(stuck_timeout_s: float) -> float:
    """Beat often enough that a live job is never mistaken for a stuck one."""
    return min(30.0, stuck_timeout_s / 4.0)
