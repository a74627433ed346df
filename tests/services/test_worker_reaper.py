"""The job row as source of truth: claims, the reaper, enqueueing — on SQLite and the
filesystem broker of the embedded default (no servers needed)."""

from __future__ import annotations

import base64
import io
import json
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import update

from services import db, jobs
from services.common.uploads import StoredAudio
from services.config import get_settings
from services.models import Job, utcnow
from services.worker import celery_app, enqueue, reaper, state

TIMEOUT_S = 30.0


@pytest.fixture()
def embedded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """SQLite + filesystem broker in a temporary home; yields the settings."""
    (tmp_path / "home").mkdir()
    monkeypatch.setenv("DANCEGRAPH_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("DANCEGRAPH_DATABASE_URL", f"sqlite:///{tmp_path / 'home' / 'db.sqlite'}")
    monkeypatch.setenv("DANCEGRAPH_BROKER_URL", "filesystem://")
    monkeypatch.setenv("DANCEGRAPH_BROKER_FOLDER", str(tmp_path / "home" / "broker"))
    monkeypatch.setenv("DANCEGRAPH_STORE_ROOT", str(tmp_path / "home" / "store"))
    monkeypatch.setenv("DANCEGRAPH_JOB_TIMEOUT_S", str(TIMEOUT_S))
    monkeypatch.setenv("DANCEGRAPH_JOB_MAX_ATTEMPTS", "3")
    get_settings.cache_clear()
    db.reset_caches()
    settings = get_settings()
    db.upgrade_schema(settings.database_url)
    celery_app.reconfigure(settings)
    yield settings
    db.reset_caches()
    get_settings.cache_clear()
    celery_app.reconfigure(get_settings())


def _tenant() -> str:
    with db.session_scope() as session:
        tenant, _ = jobs.create_api_key(session, "acme")
        return tenant.id


def _song(key: str) -> StoredAudio:
    """A stored song record for ``key`` (content-addressed: its name is its sha256)."""
    return StoredAudio(
        key, key.rsplit("/", 1)[1], size=1, filename="song.wav", container="wav", duration_s=1.0
    )


def _job(tenant_id: str, **values) -> str:
    with db.session_scope() as session:
        job, _ = jobs.create_job(
            session,
            tenant_id=tenant_id,
            spec={"dataset": "demo"},
            audio=_song("blobs/sha256/00/" + "0" * 64),
        )
        job_id = job.id
    if values:
        with db.session_scope() as session:
            session.execute(update(Job).where(Job.id == job_id).values(**values))
    return job_id


def _queued_messages(settings) -> list[tuple[str, str]]:
    """(task name, job id) of every message waiting in the filesystem broker's queue folder."""
    out = []
    for path in sorted(Path(settings.broker_folder, "queue").glob("*.msg")):
        msg = json.loads(path.read_text())
        args, _kwargs, _embed = json.loads(base64.b64decode(msg["body"]))
        out.append((msg["headers"]["task"], args[0], path.name.rsplit(".", 2)[1]))
    return out


def test_claim_is_exclusive_until_the_heartbeat_goes_stale(embedded):
    job_id = _job(_tenant())
    first = state.claim(job_id, stale_after_s=TIMEOUT_S)
    assert first is not None and first.status == "running" and first.attempts == 1
    assert state.claim(job_id, stale_after_s=TIMEOUT_S) is None  # a duplicate delivery
    with db.session_scope() as session:
        session.execute(
            update(Job)
            .where(Job.id == job_id)
            .values(heartbeat_at=utcnow() - timedelta(seconds=2 * TIMEOUT_S))
        )
    second = state.claim(job_id, stale_after_s=TIMEOUT_S)  # its worker died: take it over
    assert second is not None and second.attempts == 2
    with db.session_scope() as session:
        jobs.set_status(session, job_id, "succeeded")
    assert state.claim(job_id, stale_after_s=0.0) is None  # final: never again


def test_fbx_hand_over_claims_without_counting_an_attempt(embedded):
    job_id = _job(
        _tenant(), status="running", stage="fbx_queued", attempts=1, heartbeat_at=utcnow()
    )
    assert state.claim(job_id, stale_after_s=TIMEOUT_S) is None
    job = state.claim(job_id, stale_after_s=TIMEOUT_S, stages=("fbx_queued",))
    assert job is not None and job.attempts == 1


def test_progress_raises_when_the_job_was_cancelled(embedded):
    tenant = _tenant()
    job_id = _job(tenant)
    state.claim(job_id, stale_after_s=TIMEOUT_S)
    state.progress(job_id, "analyze", 5.0)
    assert state.load(job_id).stage == "analyze"
    with db.session_scope() as session:
        jobs.cancel_job(session, tenant, job_id)
    with pytest.raises(state.JobCancelled):
        state.progress(job_id, "search", 40.0)
    assert state.load(job_id).status == "cancelled"


def test_reaper_requeues_fails_and_reenqueues_from_the_rows(embedded):
    tenant = _tenant()
    old = utcnow() - timedelta(seconds=3 * TIMEOUT_S)
    stuck = _job(tenant, status="running", attempts=1, heartbeat_at=old)
    exhausted = _job(tenant, status="running", attempts=3, crashes=2, heartbeat_at=old)
    lost = _job(tenant, updated_at=old)  # queued, but its message is gone
    alive = _job(tenant, status="running", attempts=1, heartbeat_at=utcnow())
    fresh = _job(tenant)  # queued just now
    done = _job(tenant, status="succeeded", heartbeat_at=old)

    report = reaper.reap_once(embedded)

    assert report.requeued == [stuck]
    assert report.failed == [exhausted]
    assert report.reenqueued == [lost]
    rows = {jid: state.load(jid) for jid in (stuck, exhausted, lost, alive, fresh, done)}
    assert rows[stuck].status == "queued" and rows[stuck].stage == "requeued"
    assert rows[exhausted].status == "failed" and rows[exhausted].error_code == "worker_lost"
    assert rows[lost].status == "queued"
    assert rows[alive].status == "running" and rows[fresh].status == "queued"
    assert rows[done].status == "succeeded"
    messages = _queued_messages(embedded)
    assert sorted(m[1] for m in messages) == sorted([stuck, lost])
    assert {(m[0], m[2]) for m in messages} == {("dancegraph.run_job", "analysis")}
    # A second sweep right away finds nothing new: no duplicate storm.
    assert not reaper.reap_once(embedded)


def test_enqueue_routes_fbx_to_its_own_queue(embedded):
    tenant = _tenant()
    a, b = _job(tenant), _job(tenant)
    enqueue.enqueue_job(a)
    assert enqueue.enqueue_fbx(b)
    got = {(m[0], m[1], m[2]) for m in _queued_messages(embedded)}
    assert got == {("dancegraph.run_job", a, "analysis"), ("dancegraph.export_fbx", b, "fbx")}


def test_reaper_removes_temporary_folders_of_killed_workers(embedded):
    import os
    import time

    tmp = Path(embedded.store_root) / "tmp"
    stale, recent = tmp / "job-a-1", tmp / "job-b-2"
    for folder in (stale, recent):
        (folder / "alternatives").mkdir(parents=True)
        (folder / "alternatives" / "0.bvh").write_text("HIERARCHY")
    past = time.time() - 3 * TIMEOUT_S
    os.utime(stale, (past, past))
    report = reaper.reap_once(embedded)
    assert report.tmp_removed == 1 and not stale.exists() and recent.exists()


def test_reaper_resends_only_when_the_broker_lost_messages(embedded):
    tenant = _tenant()
    old = utcnow() - timedelta(seconds=3 * TIMEOUT_S)
    waiting = _job(tenant)
    enqueue.enqueue_job(waiting)
    with db.session_scope() as session:
        session.execute(update(Job).where(Job.id == waiting).values(updated_at=old))
    assert reaper.reap_once(embedded).reenqueued == []  # a long backlog, nothing lost
    for path in Path(embedded.broker_folder, "queue").glob("*.msg"):
        path.unlink()  # the broker forgets it (as Redis does on a restart without persistence)
    assert reaper.reap_once(embedded).reenqueued == [waiting]
    assert [m[1] for m in _queued_messages(embedded)] == [waiting]


def test_a_worker_whose_job_was_taken_over_stops(embedded):
    job_id = _job(_tenant())
    state.claim(job_id, stale_after_s=TIMEOUT_S)
    assert state.beat(job_id)
    with db.session_scope() as session:  # the reaper requeued it and another worker claimed it
        session.execute(update(Job).where(Job.id == job_id).values(worker="elsewhere:1"))
    assert not state.beat(job_id)
    with pytest.raises(state.JobCancelled):
        state.progress(job_id, "render", 60.0)
    assert state.load(job_id).worker == "elsewhere:1"


def test_jobs_waiting_for_the_fbx_queue_are_not_stuck(embedded):
    tenant = _tenant()
    old = utcnow() - timedelta(seconds=3 * TIMEOUT_S)
    waiting = _job(tenant, status="running", stage="fbx_queued", attempts=3, heartbeat_at=old)
    enqueue.enqueue_fbx(waiting)  # its FBX message is still in the queue: a backlog
    report = reaper.reap_once(embedded)
    assert not report.requeued and not report.failed and not report.fbx_resent
    row = state.load(waiting)
    assert row.status == "running" and row.attempts == 3
    for path in Path(embedded.broker_folder, "queue").glob("*.msg"):
        path.unlink()  # the message is lost
    with db.session_scope() as session:
        session.execute(update(Job).where(Job.id == waiting).values(heartbeat_at=old))
    assert reaper.reap_once(embedded).fbx_resent == [waiting]
    assert [(m[0], m[1], m[2]) for m in _queued_messages(embedded)] == [
        ("dancegraph.export_fbx", waiting, "fbx")
    ]


def test_transient_retries_do_not_use_up_the_crash_budget(embedded):
    """A graph-store outage retried a job 4 times (4 claims); then its worker died once. That is
    one crash, not the fourth: the job is requeued, and fails only at its third crash."""
    tenant = _tenant()
    old = utcnow() - timedelta(seconds=3 * TIMEOUT_S)
    job_id = _job(tenant, status="running", attempts=4, heartbeat_at=old)
    report = reaper.reap_once(embedded)
    assert report.requeued == [job_id] and not report.failed
    row = state.load(job_id)
    assert (row.status, row.crashes, row.error_code) == ("queued", 1, None)
    for crashes in (2, 3):
        with db.session_scope() as session:
            session.execute(
                update(Job).where(Job.id == job_id).values(status="running", heartbeat_at=old)
            )
        report = reaper.reap_once(embedded)
        assert state.load(job_id).crashes == crashes
    row = state.load(job_id)
    assert report.failed == [job_id] and row.error_code == "worker_lost"
    assert row.error_message == "the job's worker stopped responding 3 times"


def test_reaper_sweeps_every_kind_of_leftover(embedded):
    """What killed processes leave: a partial upload, a temporary file, a song stored by an API
    killed before its row, a result version no manifest names. Live things stay."""
    import os
    import time

    from services.config import object_store

    store = object_store(embedded)
    past = time.time() - 3 * TIMEOUT_S
    store.scratch.mkdir(parents=True, exist_ok=True)
    upload = store.scratch / ".upload-abc"
    upload.write_bytes(b"x" * 1000)
    tmp_file = store.scratch / ".tmp-def"
    tmp_file.write_bytes(b"y")
    fresh_upload = store.scratch / ".upload-live"
    fresh_upload.write_bytes(b"z")
    orphan_key, _ = store.put_stream(io.BytesIO(b"a song nobody owns"))
    used_key, _ = store.put_stream(io.BytesIO(b"a song a job owns"))
    tenant = _tenant()
    with db.session_scope() as session:
        jobs.create_job(
            session,
            tenant_id=tenant,
            spec={"dataset": "demo"},
            audio=_song(used_key),
        )
    store.put_bytes("jobs/j-dead/r-0123/alternatives/0.bvh", b"HIERARCHY")
    for path in (upload, tmp_file, store.path(orphan_key), store.path(used_key)):
        os.utime(path, (past, past))
    os.utime(store.path("jobs/j-dead/r-0123/alternatives/0.bvh"), (past, past))

    report = reaper.reap_once(embedded)

    assert report.tmp_removed == 2 and not upload.exists() and not tmp_file.exists()
    assert fresh_upload.exists()
    assert report.orphans_removed == 2  # the unowned song and the unpublished result version
    assert not store.exists(orphan_key) and store.exists(used_key)
    assert list(store.list("jobs")) == []


def test_a_failure_quoting_a_huge_input_is_stored_bounded(embedded):
    """A worker error that quotes what the client sent (a 1 MB name) is stored and served a
    kilobyte long, not a megabyte; the code and field are cut too."""
    job_id = _job(_tenant())
    huge = "x" * 1_000_000
    with db.session_scope() as session:
        assert jobs.fail_job(session, job_id, "bad_" + huge, f"no joint named {huge}", huge)
    with db.session_scope() as session:
        row = session.get(Job, job_id)
        assert row.error_message.startswith("no joint named x") and len(row.error_message) <= 1024
        assert len(row.error_code) == 64 and len(row.error_field) <= 200
