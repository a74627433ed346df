"""The task layer's failure policy: which errors are retried, and how long it waits."""

from __future__ import annotations

import httpx
import pytest
import sqlalchemy.exc

from dancegraph.errors import AudioError, DanceGraphError, SpecError
from services.worker import tasks
from services.worker.celery_app import TASK_QUEUES, app


def _graphstore_down() -> DanceGraphError:
    err = DanceGraphError("graph store unreachable", code="graphstore_unavailable")
    err.status = 503
    return err


@pytest.mark.parametrize(
    "exc,transient",
    [
        (_graphstore_down(), True),
        (sqlalchemy.exc.OperationalError("SELECT 1", {}, Exception("server closed")), True),
        (httpx.ConnectError("refused"), True),
        (ConnectionRefusedError(), True),
        (AudioError("no beat", code="no_beat"), False),
        (SpecError("conflict", code="constraint_conflict"), False),
        (ValueError("a bug"), False),
    ],
)
def test_only_machinery_failures_are_retried(exc, transient):
    assert tasks.is_transient(exc) is transient


def test_retry_backoff_doubles_and_is_bounded():
    delays = [tasks.retry_delay(n) for n in range(tasks.MAX_RETRIES + 3)]
    assert delays[:5] == [2.0, 4.0, 8.0, 16.0, 32.0]
    assert max(delays) <= tasks.RETRY_MAX_S
    assert sum(delays[: tasks.MAX_RETRIES]) < 120  # a job gives up within two minutes


def test_public_tasks_are_registered_on_their_queues():
    for name, queue in TASK_QUEUES.items():
        assert name in app.tasks
        assert app.amqp.router.route({}, name)["queue"].name == queue
    assert TASK_QUEUES["dancegraph.export_fbx"] == "fbx"
    conf = app.conf
    assert conf.task_acks_late and conf.task_reject_on_worker_lost
    assert conf.worker_prefetch_multiplier == 1
    assert conf.task_time_limit > conf.task_soft_time_limit


def test_a_full_disk_is_transient_not_the_jobs_fault(tmp_path):
    """The OSError of a real full filesystem (a 64 KiB tmpfs) is retried later, not a failure."""
    import subprocess

    from dancegraph.store import FileStore

    root = tmp_path / "tiny"
    root.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(root)], capture_output=True
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        store = FileStore(root)
        with pytest.raises(OSError) as full:
            store.put_bytes("jobs/x/timeline.json", b"x" * 200_000)
        assert tasks.is_transient(full.value)
        assert list(store.list("jobs")) == []  # nothing half-written
    finally:
        subprocess.run(["umount", str(root)], capture_output=True)
