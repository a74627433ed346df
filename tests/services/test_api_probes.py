"""The hostile probes of issue 22 against the API, each as it was run: what broke then is
answered now with a specific status and code, and leaves nothing behind."""

from __future__ import annotations

import json
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from tests.services.conftest import celery_enqueue, register_dataset, wav_bytes


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def served(app):
    """``app`` on a real uvicorn server in a thread (real sockets, real keep-alive)."""
    import uvicorn

    port = _free_port()
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)


def _left_behind(settings) -> list[str]:
    """Uploaded songs and scratch files in the test's store."""
    from services.config import object_store

    store = object_store(settings)
    scratch = [p.name for p in store.scratch.iterdir()] if store.scratch.is_dir() else []
    return list(store.list("blobs")) + scratch


def _job_count(settings) -> int:
    from sqlalchemy import func, select

    from services.db import session_scope
    from services.models import Job

    with session_scope(settings.database_url) as session:
        return session.scalar(select(func.count()).select_from(Job))


# --- row 1: a burst of uploads against a small pool ------------------------------------------


def test_thirty_concurrent_uploads_are_accepted_or_told_to_retry(make_settings, pg_url):
    from services.api.app import create_app
    from services.common import catalog
    from tests.services.conftest import _new_key

    settings = make_settings(pg_url, db_pool_size=2, db_max_overflow=0, db_pool_timeout_s=3.0)
    from services import db

    db.reset_caches()
    catalog.reset()
    register_dataset(settings)
    _, key, _ = _new_key(settings)
    app = create_app(settings, enqueue=celery_enqueue(settings), migrate=False)
    song = wav_bytes(10.0)

    def upload(i: int) -> httpx.Response:
        return httpx.post(
            f"{base}/v1/jobs",
            headers={"X-API-Key": key},
            files={"audio": (f"s{i}.wav", song), "spec": (None, json.dumps({"seed": i}))},
            timeout=120,
        )

    with served(app) as base, ThreadPoolExecutor(max_workers=30) as pool:
        answers = list(pool.map(upload, range(30)))
    statuses = [r.status_code for r in answers]
    assert set(statuses) <= {202, 503}, [r.text[:200] for r in answers if r.status_code >= 500]
    for r in answers:
        if r.status_code == 503:
            assert r.headers["Retry-After"] and r.json()["code"] == "database_busy"
    assert statuses.count(202) >= 20  # a key check holding no connection: the pool keeps up
    db.reset_caches()


# --- row 2: an internal port scanner ---------------------------------------------------------


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:8001/v1/graphs",
        "http://10.0.0.5/hook",
        "http://[::1]:5432/",
        "http://169.254.169.254/latest/meta-data/",
        "http://metadata.google.internal/",
    ],
)
def test_callback_urls_at_internal_addresses_are_refused(make_settings, pg_url, url, song_wav):
    from fastapi.testclient import TestClient

    from services.api.app import create_app
    from services.common import catalog
    from tests.services.conftest import ApiClient, _new_key

    settings = make_settings(pg_url, webhook_allow_networks=[])  # no test receiver allowed here
    catalog.reset()
    register_dataset(settings)
    before = _job_count(settings)
    app = create_app(settings, enqueue=celery_enqueue(settings), migrate=False)
    with TestClient(app) as client:
        name, key, tenant_id = _new_key(settings)
        resp = ApiClient(client, settings, key, tenant_id, name).submit(
            song_wav, {"callback_url": url}
        )
    assert resp.status_code == 422, resp.text
    body = resp.json()
    assert body["code"] == "callback_url_forbidden" and body["field"] == "spec.callback_url"
    assert _job_count(settings) == before and _left_behind(settings) == []


# --- rows 5 and 11: specs PostgreSQL cannot store, and loose types -----------------------------

BAD_SPECS = [
    ('{"weights": {"data": Infinity}}', "spec_malformed"),
    ('{"weights": {"data": -Infinity}}', "spec_malformed"),
    ('{"weights": {"data": NaN}}', "spec_malformed"),
    ('{"transition_threshold": 1e309}', "spec_malformed"),
    ('{"recreate": "\\ud800"}', "spec_invalid"),
    ('{"include": [{"node": "a:1", "x": "\\udfff"}]}', "spec_invalid"),
    ("[" * 5000 + "]" * 5000, "spec_malformed"),
    ('{"a":' * 5000 + "1" + "}" * 5000, "spec_malformed"),
    ('{"exclude": ' + "[" * 40 + "]" * 40 + "}", "spec_malformed"),
    (json.dumps({"recreate": "x" * 1_000_000}), "spec_invalid"),
    ('{"alternatives": true}', "spec_invalid"),
    ('{"alternatives": "3"}', "spec_invalid"),
    ('{"structure": {"repeat": 1}}', "spec_invalid"),
    ('{"seed": 7.0}', "spec_invalid"),
]


@pytest.mark.parametrize("text,code", BAD_SPECS, ids=range(len(BAD_SPECS)))
def test_unstorable_or_loose_specs_are_refused_and_nothing_is_kept(api, song_wav, text, code):
    before = _job_count(api.settings)
    resp = api.submit(song_wav, text)
    assert resp.status_code == 422, resp.text[:300]
    body = resp.json()
    assert body["code"] == code, body
    assert len(resp.content) < 5000  # the refused value is not echoed back
    assert _job_count(api.settings) == before and _left_behind(api.settings) == []


def test_a_spec_with_an_integer_where_a_float_goes_is_fine(api, song_wav):
    resp = api.submit(song_wav, '{"weights": {"data": 2}, "transition_threshold": 15}')
    assert resp.status_code == 202, resp.text


# --- row 6: the queue refuses: nothing is kept -----------------------------------------------


def test_a_refused_enqueue_keeps_no_song(make_settings, pg_url):
    from fastapi.testclient import TestClient

    from services.api.app import create_app
    from services.common import catalog
    from tests.services.conftest import ApiClient, _new_key

    settings = make_settings(pg_url)
    catalog.reset()
    register_dataset(settings)
    down = make_settings(pg_url, broker_url="redis://127.0.0.1:1/0")  # nothing listens there
    app = create_app(settings, enqueue=celery_enqueue(down), migrate=False)
    with TestClient(app) as client:
        name, key, tenant_id = _new_key(settings)
        api = ApiClient(client, settings, key, tenant_id, name)
        before = _job_count(settings)
        resp = api.submit(wav_bytes(11.25), {})  # a song no other job of the database has
    assert resp.status_code == 503 and resp.json()["code"] == "queue_unavailable"
    assert resp.headers["Retry-After"]
    assert _job_count(settings) == before and _left_behind(settings) == []


# --- row 7: the database is down; the disk is full -------------------------------------------


def test_an_unreachable_database_is_503_and_names_no_host(make_settings, song_wav):
    from fastapi.testclient import TestClient

    from services import db
    from services.api.app import create_app

    url = "postgresql+psycopg://postgres@127.0.0.1:1/nowhere"  # nothing listens on port 1
    settings = make_settings(url)
    db.reset_caches()
    with TestClient(create_app(settings, migrate=False)) as client:
        headers = {"X-API-Key": "dg_" + "a" * 32}
        answers = [
            client.get("/v1/jobs", headers=headers),
            client.post("/v1/jobs", headers=headers, files={"audio": ("s.wav", song_wav)}),
            client.get("/readyz"),
        ]
    for resp in answers:
        assert resp.status_code == 503, resp.text
        assert "127.0.0.1" not in resp.text and ":1" not in resp.text.replace('":1', "")
    assert answers[0].json()["code"] == "database_unavailable"
    assert answers[0].headers["Retry-After"]
    assert (
        answers[2].json()["checks"]["database"] == "error: database unreachable (OperationalError)"
    )
    db.reset_caches()


def test_readyz_is_not_ready_when_the_disk_is_nearly_full(make_settings, pg_url):
    from fastapi.testclient import TestClient

    from services.api.app import create_app

    settings = make_settings(pg_url, min_free_bytes=1 << 60)  # more than any disk has
    with TestClient(create_app(settings, migrate=False)) as client:
        resp = client.get("/readyz")
    assert resp.status_code == 503
    assert resp.json()["checks"]["store"].startswith("error: low disk space")


# --- row 8: a batch key reused with another body ---------------------------------------------


def test_batch_idempotency_key_reused_with_another_body_is_409(api):
    def batch(songs: list[bytes], spec: dict):
        files = [("audio", (f"s{i}.wav", s)) for i, s in enumerate(songs)]
        files.append(("spec", (None, json.dumps(spec))))
        return api.post("/v1/batches", files=files, headers={"Idempotency-Key": "batch-1"})

    a, b = wav_bytes(9.0), wav_bytes(10.0)
    first = batch([a, b], {})
    assert first.status_code == 202
    assert batch([a, b], {}).status_code == 200  # the same request again: the same batch
    for songs, spec in (([a], {}), ([b, a], {}), ([a, b], {"seed": 3})):
        resp = batch(songs, spec)
        assert resp.status_code == 409, resp.text
        assert resp.json()["code"] == "idempotency_key_reused"


# --- row 9: the request after a 500 on a keep-alive connection -------------------------------


def _exchange(sock: socket.socket, path: str) -> tuple[int, bytes]:
    """One HTTP/1.1 request on an open socket; the status and body of its answer."""
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: t\r\nConnection: keep-alive\r\n\r\n".encode())
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionResetError("closed before the answer")
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    length = int(
        next(v for k, _, v in (x.partition(": ") for x in lines) if k.lower() == "content-length")
    )
    while len(body) < length:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionResetError("closed mid-answer")
        body += chunk
    return int(lines[0].split()[1]), body


def test_the_request_after_a_500_on_the_same_connection_is_answered(pg_settings):
    from services.api.app import create_app

    app = create_app(pg_settings, migrate=False)

    def broken():
        raise RuntimeError("secret detail /srv/data/password.txt")

    app.add_api_route("/broken", broken)
    with served(app) as base:
        port = int(base.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            status, body = _exchange(sock, "/broken")
            assert status == 500
            problem = json.loads(body)
            assert problem["code"] == "internal_error" and b"secret" not in body
            status, body = _exchange(sock, "/healthz")  # the same connection
            assert status == 200 and json.loads(body)["status"] == "ok"


# --- row 10: a corrupt FLAC --------------------------------------------------------------------


def test_a_corrupt_flac_fails_naming_the_uploaded_file(tmp_path: Path):
    import io

    import soundfile as sf

    from dancegraph.errors import AudioError
    from dancegraph.store import FileStore
    from services.worker import pipeline
    from tests.services.conftest import click_track

    buf = io.BytesIO()
    sf.write(buf, click_track(30.0), 22050, format="FLAC")
    data = bytearray(buf.getvalue())
    mid = len(data) // 2
    data[mid : mid + 4096] = bytes(4096)  # one corrupt 4 KB region
    store = FileStore(tmp_path / "store")
    key, _ = store.put_stream(io.BytesIO(bytes(data)))
    sha = key.rsplit("/", 1)[1]
    try:
        analysis = pipeline.analyze(store, key, sha, "Studio Take 3.flac")
    except AudioError as exc:
        assert "Studio Take 3.flac" in exc.message and sha not in exc.message
        assert exc.field == "audio"
    else:  # decoded around the damage
        assert analysis.duration_s > 20


def test_an_unreachable_object_store_is_503_and_keeps_nothing(
    make_settings, pg_url, song_wav, monkeypatch
):
    from fastapi.testclient import TestClient

    from services.api.app import create_app
    from services.common import catalog
    from tests.conftest import S3_ENV
    from tests.services.conftest import ApiClient, _new_key

    monkeypatch.setenv("AWS_ENDPOINT_URL", "http://127.0.0.1:1")  # nothing listens there
    for name, value in S3_ENV.items():
        monkeypatch.setenv(name, value)
    settings = make_settings(pg_url, store_url="s3://nowhere/store")
    catalog.reset()
    register_dataset(settings)
    before = _job_count(settings)
    with TestClient(create_app(settings, enqueue=celery_enqueue(settings), migrate=False)) as c:
        name, key, tenant_id = _new_key(settings)
        resp = ApiClient(c, settings, key, tenant_id, name).submit(song_wav, {})
        ready = c.get("/readyz")
    assert resp.status_code == 503 and resp.json()["code"] == "store_unavailable"
    assert resp.headers["Retry-After"] and "127.0.0.1" not in resp.text
    assert _job_count(settings) == before
    from services.config import object_store

    assert list(object_store(settings).scratch.glob("*")) == []
    assert ready.status_code == 503
    assert ready.json()["checks"]["store"] == "error: store unreachable (StoreUnavailableError)"
