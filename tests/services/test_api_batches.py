"""Batches: many songs, one spec; all-or-nothing validation; status counts; isolation."""

from __future__ import annotations

import json

from services import jobs
from services.db import session_scope
from services.models import SUCCEEDED
from tests.services.conftest import broker_messages, wav_bytes


def _post_batch(api, songs: list[tuple[str, bytes]], spec: dict | str, **kw):
    files = [("audio", (name, data, "application/octet-stream")) for name, data in songs]
    files.append(("spec", (None, spec if isinstance(spec, str) else json.dumps(spec))))
    return api.post("/v1/batches", files=files, **kw)


def test_batch_creates_one_job_per_song(api):
    songs = [(f"song{i}.wav", wav_bytes(9.0 + i)) for i in range(3)]
    resp = _post_batch(api, songs, {"alternatives": 1})
    assert resp.status_code == 202, resp.text
    batch = resp.json()
    assert resp.headers["location"] == f"/v1/batches/{batch['id']}"
    assert batch["status"] == "queued" and batch["counts"] == {"queued": 3}
    assert [j["audio"]["filename"] for j in batch["jobs"]] == [
        "song0.wav",
        "song1.wav",
        "song2.wav",
    ]
    assert all(
        j["batch_id"] == batch["id"] and j["spec"]["alternatives"] == 1 for j in batch["jobs"]
    )
    assert len(broker_messages(api.settings)) == 3
    listed = api.get("/v1/jobs", params={"batch_id": batch["id"]}).json()["items"]
    assert sorted(j["id"] for j in listed) == sorted(j["id"] for j in batch["jobs"])
    # progress of the batch follows its jobs
    with session_scope(api.settings.database_url) as session:
        for j in batch["jobs"]:
            jobs.claim_job(session, j["id"], "w", stale_after_s=600)
            jobs.set_status(session, j["id"], SUCCEEDED, result={"alternatives": [], "files": []})
    done = api.get(f"/v1/batches/{batch['id']}").json()
    assert done["status"] == "completed" and done["counts"] == {"succeeded": 3}


def test_batch_is_all_or_nothing(api):
    songs = [("good.wav", wav_bytes(10.0)), ("bad.mp3", b"not audio at all" * 20)]
    resp = _post_batch(api, songs, {})
    assert resp.status_code == 415 and resp.json()["code"] == "audio_undecodable"
    assert resp.json()["field"] == "audio[1]"
    assert api.get("/v1/jobs").json()["items"] == []
    store = api.app.state.ctx.store
    assert not store.exists("blobs") or list(store.list("blobs")) == []
    assert broker_messages(api.settings) == []


def test_batch_bad_spec_and_missing_audio(api):
    resp = _post_batch(api, [("a.wav", wav_bytes(10.0))], {"alternatives": 0})
    assert resp.status_code == 422 and resp.json()["field"] == "spec.alternatives"
    resp = api.post("/v1/batches", files=[("spec", (None, "{}"))])
    assert resp.status_code == 422 and resp.json()["code"] == "audio_missing"


def test_batch_too_large(api):
    api.app.state.ctx.settings.max_batch_items = 2
    resp = _post_batch(api, [(f"s{i}.wav", wav_bytes(8.5)) for i in range(3)], {})
    assert resp.status_code == 422 and resp.json()["code"] == "batch_too_large"
    assert api.get("/v1/jobs").json()["items"] == []


def test_batch_idempotency_and_isolation(api):
    songs = [("a.wav", wav_bytes(10.0))]
    first = _post_batch(api, songs, {}, headers={"Idempotency-Key": "nightly-7"})
    again = _post_batch(api, songs, {}, headers={"Idempotency-Key": "nightly-7"})
    assert (first.status_code, again.status_code) == (202, 200)
    assert first.json()["id"] == again.json()["id"]
    stranger = api.new_tenant()
    resp = stranger.get(f"/v1/batches/{first.json()['id']}")
    assert resp.status_code == 404 and resp.json()["code"] == "batch_not_found"
