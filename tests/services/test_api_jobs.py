"""Job lifecycle through the API: create (202 + Location, queued, enqueued), read, list with
cursor paging and filters, cancel, idempotency, tenant isolation, result downloads."""

from __future__ import annotations

import json

import pytest

from services import jobs
from services.db import session_scope
from services.models import RUNNING, SUCCEEDED
from tests.services.conftest import broker_messages, wav_bytes


def test_create_job_returns_202_location_and_enqueues(api, song_wav):
    resp = api.submit(song_wav, {"alternatives": 2, "output": {"formats": ["bvh"]}})
    assert resp.status_code == 202, resp.text
    job = resp.json()
    assert resp.headers["location"] == f"/v1/jobs/{job['id']}" == job["url"]
    assert job["status"] == "queued" and job["progress"] == 0.0
    assert job["spec"]["alternatives"] == 2 and job["spec"]["dataset"] == "cmu-salsa"
    assert job["audio"]["container"] == "wav" and job["audio"]["duration_s"] == pytest.approx(12.0)
    assert job["audio"]["bytes"] == len(song_wav)
    # the upload is stored content-addressed, and one message waits on the broker
    store = api.app.state.ctx.store
    key = f"blobs/sha256/{job['audio']['sha256'][:2]}/{job['audio']['sha256']}"
    assert store.get_bytes(key) == song_wav
    messages = broker_messages(api.settings)
    assert len(messages) == 1
    assert job["id"] in messages[0].read_text()
    again = api.get(resp.headers["location"])
    assert again.status_code == 200 and again.json()["id"] == job["id"]


def test_create_job_on_sqlite_embedded(sqlite_api, song_wav):
    resp = sqlite_api.submit(song_wav, {})
    assert resp.status_code == 202, resp.text
    got = sqlite_api.get(resp.headers["location"]).json()
    assert got["status"] == "queued"
    assert got["created_at"].endswith("Z") or got["created_at"].endswith("+00:00")
    assert len(broker_messages(sqlite_api.settings)) == 1


def test_idempotency_key(api, song_wav):
    first = api.submit(song_wav, {"seed": 3}, headers={"Idempotency-Key": "upload-42"})
    again = api.submit(song_wav, {"seed": 3}, headers={"Idempotency-Key": "upload-42"})
    assert first.status_code == 202 and again.status_code == 200
    assert first.json()["id"] == again.json()["id"]
    assert len(broker_messages(api.settings)) == 1  # enqueued once
    other = api.submit(wav_bytes(10.0), {"seed": 3}, headers={"Idempotency-Key": "upload-42"})
    assert other.status_code == 409 and other.json()["code"] == "idempotency_key_reused"
    # the same key belongs to each tenant separately
    stranger = api.new_tenant()
    theirs = stranger.submit(song_wav, {"seed": 3}, headers={"Idempotency-Key": "upload-42"})
    assert theirs.status_code == 202 and theirs.json()["id"] != first.json()["id"]
    assert len(api.get("/v1/jobs").json()["items"]) == 1


def test_tenant_isolation(api, song_wav):
    mine = api.submit(song_wav, {}).json()
    stranger = api.new_tenant()
    for resp in (
        stranger.get(f"/v1/jobs/{mine['id']}"),
        stranger.delete(f"/v1/jobs/{mine['id']}"),
        stranger.get(f"/v1/jobs/{mine['id']}/timeline.json"),
        stranger.get(f"/v1/jobs/{mine['id']}/alternatives/0.bvh"),
    ):
        assert resp.status_code == 404, resp.text
        assert resp.json()["code"] == "job_not_found"
    assert stranger.get("/v1/jobs").json()["items"] == []
    # a missing id answers exactly like another tenant's
    missing = stranger.get("/v1/jobs/00000000-0000-0000-0000-000000000000").json()
    assert {k: v for k, v in missing.items() if k not in ("detail", "instance")} == {
        k: v
        for k, v in stranger.get(f"/v1/jobs/{mine['id']}").json().items()
        if k not in ("detail", "instance")
    }
    assert api.get(f"/v1/jobs/{mine['id']}").json()["status"] == "queued"


def test_cancel(api, song_wav):
    job = api.submit(song_wav, {}).json()
    resp = api.delete(f"/v1/jobs/{job['id']}")
    assert resp.status_code == 200
    assert resp.json()["status"] == "cancelled" and resp.json()["error"]["code"] == "cancelled"
    assert api.delete(f"/v1/jobs/{job['id']}").json()["status"] == "cancelled"  # idempotent
    # a worker that picks it up afterwards cannot revive it
    with session_scope(api.settings.database_url) as session:
        assert jobs.claim_job(session, job["id"], "late-worker", stale_after_s=600) is None
        assert not jobs.set_status(session, job["id"], SUCCEEDED)
    assert api.get(f"/v1/jobs/{job['id']}").json()["status"] == "cancelled"


def test_cancel_running_then_finished_job(api, song_wav):
    job = api.submit(song_wav, {}).json()
    with session_scope(api.settings.database_url) as session:
        assert jobs.claim_job(session, job["id"], "w1", stale_after_s=600).status == RUNNING
        assert jobs.heartbeat(session, job["id"], stage="analysis", progress=30)
    got = api.get(f"/v1/jobs/{job['id']}").json()
    assert (got["status"], got["stage"], got["progress"], got["attempts"]) == (
        "running",
        "analysis",
        30.0,
        1,
    )
    assert api.delete(f"/v1/jobs/{job['id']}").json()["status"] == "cancelled"
    with session_scope(api.settings.database_url) as session:
        assert not jobs.heartbeat(session, job["id"], progress=50)  # the worker learns to stop
    done = api.submit(wav_bytes(11.0), {}).json()
    _finish(api, done["id"], files={})
    resp = api.delete(f"/v1/jobs/{done['id']}")
    assert resp.status_code == 409 and resp.json()["code"] == "job_finished"


def test_list_paging_and_filters(api):
    ids = [api.submit(wav_bytes(9.0 + 0.25 * i), {}).json()["id"] for i in range(5)]
    with session_scope(api.settings.database_url) as session:
        jobs.cancel_job(session, api.tenant_id, ids[1])
    seen, cursor = [], None
    while True:
        page = api.get(
            "/v1/jobs", params={"limit": 2, **({"cursor": cursor} if cursor else {})}
        ).json()
        assert len(page["items"]) <= 2
        seen += [j["id"] for j in page["items"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == ids[::-1]  # newest first, each once
    cancelled = api.get("/v1/jobs", params={"status": "cancelled"}).json()["items"]
    assert [j["id"] for j in cancelled] == [ids[1]]
    assert len(api.get("/v1/jobs", params={"status": "queued"}).json()["items"]) == 4


def _finish(api, job_id: str, files: dict[str, bytes], alternatives=None) -> None:
    """Publish result files as the worker does and mark the job succeeded."""
    store = api.app.state.ctx.store
    folder = store.temp_dir("result")
    for name, data in files.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(data)
    assert store.publish(jobs.result_key(job_id), folder)
    alternatives = alternatives or [
        {"nodes": ["60_03:1", "60_03:2"], "cost": 1.5, "violations": []}
    ]
    with session_scope(api.settings.database_url) as session:
        assert jobs.claim_job(session, job_id, "w", stale_after_s=600)
        assert jobs.set_status(
            session,
            job_id,
            SUCCEEDED,
            analysis_summary={"tempo_bpm": 120.0, "bars": 6},
            result={
                "alternatives": alternatives,
                "files": sorted(files),
                "constraint_report": {"ok": True},
            },
        )


def test_results_and_downloads(api, song_wav):
    job = api.submit(song_wav, {"alternatives": 2}).json()
    early = api.get(f"/v1/jobs/{job['id']}/alternatives/0.bvh")
    assert early.status_code == 409 and early.json()["code"] == "job_not_finished"
    bvh = b"HIERARCHY\nROOT Hips\n{\n}\nMOTION\nFrames: 0\nFrame Time: 0.033333\n"
    timeline = json.dumps({"bars": [[0.0, 2.0]]}).encode()
    _finish(
        api,
        job["id"],
        {
            "alternatives/0.bvh": bvh,
            "alternatives/1.bvh": bvh + b"\n",
            "alternatives/0.fbx": b"Kaydara FBX Binary  \0",
            "timeline.json": timeline,
        },
        alternatives=[
            {"nodes": ["a:1", "a:2", "a:3"], "cost": 2.0, "violations": []},
            {"nodes": ["b:1", "b:2", "b:3"], "cost": 3.5, "violations": [{"constraint": "stage"}]},
        ],
    )
    got = api.get(f"/v1/jobs/{job['id']}").json()
    assert got["status"] == "succeeded" and got["progress"] == 100.0
    assert got["analysis"] == {"tempo_bpm": 120.0, "bars": 6}
    assert [(a["index"], a["cost"], a["bars"]) for a in got["alternatives"]] == [
        (0, 2.0, 3),
        (1, 3.5, 3),
    ]
    assert got["alternatives"][0]["downloads"] == {
        "bvh": f"/v1/jobs/{job['id']}/alternatives/0.bvh",
        "fbx": f"/v1/jobs/{job['id']}/alternatives/0.fbx",
    }
    assert set(got["alternatives"][1]["downloads"]) == {"bvh"}
    assert got["constraint_report"] == {"ok": True}
    resp = api.get(got["alternatives"][0]["downloads"]["bvh"])
    assert resp.status_code == 200 and resp.content == bvh
    assert resp.headers["content-type"].startswith("text/plain")
    assert api.get(got["alternatives"][0]["downloads"]["fbx"]).content.startswith(
        b"Kaydara FBX Binary"
    )
    assert api.get(got["timeline_url"]).json() == {"bars": [[0.0, 2.0]]}
    missing = api.get(f"/v1/jobs/{job['id']}/alternatives/1.fbx")
    assert missing.status_code == 404 and missing.json()["code"] == "result_not_found"
    bad = api.get(f"/v1/jobs/{job['id']}/alternatives/0.obj")
    assert bad.status_code == 422 and bad.json()["field"] == "path.fmt"


def test_failed_job_shows_its_error(api, song_wav):
    job = api.submit(song_wav, {}).json()
    with session_scope(api.settings.database_url) as session:
        jobs.claim_job(session, job["id"], "w", stale_after_s=600)
        jobs.fail_job(session, job["id"], "no_beat", "no usable beat in song.wav", field="audio")
    got = api.get(f"/v1/jobs/{job['id']}").json()
    assert got["status"] == "failed"
    assert got["error"] == {
        "code": "no_beat",
        "message": "no usable beat in song.wav",
        "field": "audio",
    }
    resp = api.get(f"/v1/jobs/{job['id']}/timeline.json")
    assert resp.status_code == 409 and resp.json()["code"] == "job_failed"


def test_enqueue_failure_leaves_no_job(api, song_wav):
    def broken(_job_id):
        raise ConnectionError("broker down")

    api.app.state.ctx.enqueue = broken
    resp = api.submit(song_wav, {})
    assert resp.status_code == 503 and resp.json()["code"] == "queue_unavailable"
    assert resp.headers["retry-after"] == "5"
    assert api.get("/v1/jobs").json()["items"] == []
