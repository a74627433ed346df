"""Fixtures of the service tests, shared by the API and worker tests.

- ``pg_url``: a fresh PostgreSQL database ``dancegraph_test_<random>`` on 127.0.0.1:5432 (trust
  auth), migrated with ``alembic upgrade head``, dropped at the end of the session.
- ``make_settings(database_url, **overrides)``: Settings for one test with its own object store
  and filesystem-broker folders under ``tmp_path``; it also exports them as ``DANCEGRAPH_*``
  environment variables (and clears the settings cache), so code that calls ``get_settings()``
  — ``session_scope()``, child processes — sees the same configuration.
- ``pg_settings`` / ``sqlite_settings``: those settings on PostgreSQL / on a migrated SQLite file.
- ``celery_enqueue(settings)``: a real Celery publisher (``dancegraph.run_job`` on ``analysis``)
  bound to the settings' broker.
- ``api`` / ``sqlite_api``: a TestClient on ``create_app(settings)`` plus a tenant's API key and
  a registered dataset ``cmu-salsa``; ``api.new_tenant()`` makes another tenant's client.
- ``wav_bytes(seconds)``: a click track as WAV bytes (120 BPM, 22.05 kHz mono).
"""

from __future__ import annotations

import io
import json
import os
import secrets
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

PG_ADMIN_URL = os.environ.get(
    "DANCEGRAPH_TEST_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
)
TEST_DATASET = "cmu-salsa"
# Private-looking secrets of the test deployments (a non-embedded deployment refuses defaults).
TEST_WEBHOOK_SECRET = "test-webhook-secret-" + "w" * 32
TEST_PREVIEW_SECRET = "test-preview-secret-" + "p" * 32


def _pg_admin_dsn() -> str:
    return PG_ADMIN_URL.replace("postgresql+psycopg://", "postgresql://")


@pytest.fixture(scope="session")
def pg_admin() -> str:
    """The PostgreSQL admin DSN; the service tests are skipped where no server answers."""
    import psycopg

    try:
        with psycopg.connect(_pg_admin_dsn(), connect_timeout=3):
            pass
    except psycopg.OperationalError as exc:
        pytest.skip(f"PostgreSQL not reachable at {PG_ADMIN_URL} ({exc}); .ci/run starts it")
    return _pg_admin_dsn()


def create_database(admin_dsn: str, name: str) -> str:
    import psycopg

    with psycopg.connect(admin_dsn, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    return PG_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"


def drop_database(admin_dsn: str, name: str) -> None:
    import psycopg

    from services.db import reset_caches

    reset_caches()
    with psycopg.connect(admin_dsn, autocommit=True) as conn:
        conn.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s AND pid <> pg_backend_pid()",
            (name,),
        )
        conn.execute(f'DROP DATABASE IF EXISTS "{name}"')


@pytest.fixture(scope="session")
def pg_url(pg_admin: str) -> Iterator[str]:
    """A migrated, empty PostgreSQL database for this test session."""
    from services.db import upgrade_schema

    name = f"dancegraph_test_{secrets.token_hex(4)}"
    url = create_database(pg_admin, name)
    try:
        upgrade_schema(url)
        yield url
    finally:
        drop_database(pg_admin, name)


@pytest.fixture()
def make_settings(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Callable[..., object]:
    from services.config import Settings, get_settings

    def make(database_url: str, **overrides):
        values = {
            "database_url": database_url,
            "broker_url": "filesystem://",
            "broker_folder": str(tmp_path / "broker"),
            "store_root": str(tmp_path / "store"),
            "graphstore_url": "local",
            "webhook_secret": TEST_WEBHOOK_SECRET,
            "preview_secret": TEST_PREVIEW_SECRET,
            "webhook_allow_networks": ["127.0.0.1/32"],  # the local test receivers
        }
        values.update(overrides)
        monkeypatch.setenv("DANCEGRAPH_HOME", str(tmp_path / "home"))
        monkeypatch.setenv("DANCEGRAPH_STORE_ROOT", str(values["store_root"]))
        for key, value in values.items():
            text = json.dumps(value) if isinstance(value, list) else str(value)
            monkeypatch.setenv(f"DANCEGRAPH_{key.upper()}", text)
        get_settings.cache_clear()
        return Settings(**values)

    yield make
    get_settings.cache_clear()


@pytest.fixture()
def pg_settings(pg_url: str, make_settings):
    return make_settings(pg_url)


@pytest.fixture()
def sqlite_settings(tmp_path: Path, make_settings):
    from services.db import upgrade_schema

    settings = make_settings(f"sqlite:///{tmp_path / 'dancegraph.db'}")
    upgrade_schema(settings.database_url)
    return settings


def celery_enqueue(settings) -> Callable[[str], None]:
    """Publish ``dancegraph.run_job(job_id)`` through a Celery app bound to ``settings``' broker."""
    from services.config import QUEUE_ANALYSIS
    from services.worker.celery_app import TASK_RUN_JOB, make_celery

    app = make_celery(settings)

    def enqueue(job_id: str) -> None:
        app.send_task(TASK_RUN_JOB, args=[job_id], queue=QUEUE_ANALYSIS, routing_key=QUEUE_ANALYSIS)

    return enqueue


def broker_messages(settings) -> list[Path]:
    """Messages waiting in a filesystem broker's folder."""
    folder = Path(settings.broker_folder) / "queue"
    return sorted(p for p in folder.glob("*") if p.is_file()) if folder.is_dir() else []


def click_track(seconds: float, sr: int = 22050, bpm: float = 120.0) -> np.ndarray:
    """A (N,) float32 click track: a 1 kHz blip on every beat, louder on every fourth."""
    n = int(round(seconds * sr))
    y = np.zeros(n, dtype=np.float32)
    blip = (
        np.sin(2 * np.pi * 1000 * np.arange(int(0.03 * sr)) / sr) * np.hanning(int(0.03 * sr))
    ).astype(np.float32)
    for i, t in enumerate(np.arange(0.0, seconds, 60.0 / bpm)):
        start = int(t * sr)
        seg = y[start : start + len(blip)]
        seg += blip[: len(seg)] * (0.9 if i % 4 == 0 else 0.5)
    return y


def wav_bytes(seconds: float, sr: int = 22050) -> bytes:
    buf = io.BytesIO()
    sf.write(buf, click_track(seconds, sr), sr, format="WAV", subtype="PCM_16")
    return buf.getvalue()


@pytest.fixture(scope="session")
def song_wav() -> bytes:
    """A 12-second WAV, long enough to pass the upload checks."""
    return wav_bytes(12.0)


@dataclass
class ApiClient:
    """A TestClient with one tenant's key in its default headers."""

    client: object
    settings: object
    key: str
    tenant_id: str
    tenant_name: str
    app: object = None
    _others: list = field(default_factory=list)

    @property
    def headers(self) -> dict[str, str]:
        return {"X-API-Key": self.key}

    def get(self, url, **kw):
        return self.client.get(url, headers={**self.headers, **kw.pop("headers", {})}, **kw)

    def delete(self, url, **kw):
        return self.client.delete(url, headers={**self.headers, **kw.pop("headers", {})}, **kw)

    def post(self, url, **kw):
        return self.client.post(url, headers={**self.headers, **kw.pop("headers", {})}, **kw)

    def submit(
        self,
        audio: bytes | None,
        spec: dict | str | None = None,
        *,
        filename: str = "song.wav",
        **kw,
    ):
        """POST /v1/jobs with an ``audio`` part (None: none) and a ``spec`` part (dict → JSON)."""
        import json

        files: list = []
        if audio is not None:
            files.append(("audio", (filename, audio, "application/octet-stream")))
        if spec is not None:
            files.append(("spec", (None, spec if isinstance(spec, str) else json.dumps(spec))))
        if not files:
            files.append(("note", (None, "no parts")))
        return self.post("/v1/jobs", files=files, **kw)

    def new_tenant(self) -> ApiClient:
        """A client of another tenant, on the same app."""
        tenant_name, key, tenant_id = _new_key(self.settings)
        return ApiClient(self.client, self.settings, key, tenant_id, tenant_name, self.app)


def _new_key(settings) -> tuple[str, str, str]:
    from services import jobs
    from services.db import session_scope

    name = f"tenant-{uuid.uuid4().hex[:10]}"
    with session_scope(settings.database_url) as session:
        tenant, key = jobs.create_api_key(session, name)
        return name, key, tenant.id


def register_dataset(settings, name: str = TEST_DATASET) -> None:
    from services import jobs
    from services.db import session_scope

    with session_scope(settings.database_url) as session:
        jobs.upsert_dataset(
            session, name=name, version="test-v1", licence="test", stats={"nodes": 0}
        )


def _make_api(settings) -> Iterator[ApiClient]:
    from fastapi.testclient import TestClient

    from services.api.app import create_app
    from services.common import catalog

    catalog.reset()
    register_dataset(settings)
    app = create_app(settings, enqueue=celery_enqueue(settings), migrate=False)
    with TestClient(app, raise_server_exceptions=False) as client:
        name, key, tenant_id = _new_key(settings)
        yield ApiClient(client, settings, key, tenant_id, name, app)


@pytest.fixture()
def api(pg_settings) -> Iterator[ApiClient]:
    """The API on PostgreSQL with a filesystem broker (production code paths, no worker)."""
    yield from _make_api(pg_settings)


@pytest.fixture()
def sqlite_api(sqlite_settings) -> Iterator[ApiClient]:
    """The API on SQLite: the embedded default."""
    yield from _make_api(sqlite_settings)
