"""Datasets, health, readiness, metrics, the schema migrations and the OpenAPI export."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from sqlalchemy import create_engine, inspect

from dancegraph.paths import REPO_ROOT
from tests.services.conftest import (
    TEST_PREVIEW_SECRET,
    TEST_WEBHOOK_SECRET,
    create_database,
    drop_database,
)


def test_datasets(api):
    listed = api.get("/v1/datasets").json()["items"]
    assert [d["name"] for d in listed] == ["cmu-salsa"]
    one = api.get("/v1/datasets/cmu-salsa").json()
    assert one["version"] == "test-v1" and one["licence"] == "test"
    resp = api.get("/v1/datasets/nothing-here")
    assert resp.status_code == 404 and resp.json()["code"] == "unknown_dataset"


def test_health_ready_metrics(api, song_wav):
    assert api.client.get("/healthz").json()["status"] == "ok"
    ready = api.client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json() == {
        "status": "ready",
        "checks": {"database": "ok", "broker": "ok", "store": "ok"},
    }
    api.submit(song_wav, {})
    text = api.client.get("/metrics").text
    assert 'dancegraph_http_requests_total{method="POST",route="/v1/jobs",status="202"}' in text
    assert "dancegraph_jobs_created_total" in text
    assert 'dancegraph_jobs{status="queued"}' in text


def test_readyz_reports_a_broken_broker(make_settings, pg_url):
    from fastapi.testclient import TestClient

    from services.api.app import create_app

    settings = make_settings(pg_url, broker_url="redis://127.0.0.1:1/0")
    with TestClient(create_app(settings, migrate=False)) as client:
        resp = client.get("/readyz")
    assert resp.status_code == 503
    body = resp.json()
    assert body["status"] == "not_ready" and body["checks"]["database"] == "ok"
    assert body["checks"]["broker"].startswith("error")


def test_unknown_route_is_a_problem(api):
    resp = api.client.get("/v2/nothing")
    assert resp.status_code == 404 and resp.json()["code"] == "not_found"
    resp = api.client.put("/v1/jobs")
    assert resp.status_code == 405 and resp.json()["code"] == "method_not_allowed"


def test_alembic_upgrade_head_on_empty_postgres(pg_admin):
    """`alembic upgrade head` (the CLI) builds the whole schema on an empty database, and the
    models and migrations agree (`alembic check`)."""
    import secrets

    name = f"dancegraph_test_mig_{secrets.token_hex(4)}"
    url = create_database(pg_admin, name)
    try:
        env = {
            "DANCEGRAPH_DATABASE_URL": url,
            "DANCEGRAPH_WEBHOOK_SECRET": TEST_WEBHOOK_SECRET,
            "DANCEGRAPH_PREVIEW_SECRET": TEST_PREVIEW_SECRET,
            "PATH": "/usr/bin:/bin",
        }
        alembic = str(Path(sys.executable).parent / "alembic")
        for cmd in (["upgrade", "head"], ["check"], ["downgrade", "base"], ["upgrade", "head"]):
            out = subprocess.run(
                [alembic, *cmd], cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=120
            )
            assert out.returncode == 0, out.stderr
        engine = create_engine(url)
        tables = set(inspect(engine).get_table_names())
        engine.dispose()
        assert {"tenants", "api_keys", "jobs", "batches", "datasets", "alembic_version"} <= tables
    finally:
        drop_database(pg_admin, name)


def test_openapi_yaml_matches_the_app():
    out = subprocess.run(
        [sys.executable, str(REPO_ROOT / "scripts" / "export_openapi.py"), "--check"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr


def test_operation_ids_are_clean_and_unique():
    """A generated client gets functions named createJob, downloadAlternative, ... (not FastAPI's
    create_job_v1_jobs_post)."""
    from services.api.app import create_app

    ids = [
        op["operationId"]
        for item in create_app().openapi()["paths"].values()
        for op in item.values()
        if isinstance(op, dict) and "operationId" in op
    ]
    assert len(ids) == len(set(ids))
    assert all(re.fullmatch(r"[a-z]+(?:[A-Z][a-z0-9]*)*", i) for i in ids), ids
    assert {"createJob", "getJob", "listJobs", "cancelJob", "downloadAlternative"} <= set(ids)
    assert {"createBatch", "getBatch", "listDatasets", "getDataset"} <= set(ids)


def test_openapi_check_detects_drift(tmp_path):
    stale = tmp_path / "openapi.yaml"
    stale.write_text(
        (REPO_ROOT / "openapi.yaml").read_text().replace("Submit a song and a spec", "Old words")
    )
    out = subprocess.run(
        [
            sys.executable,
            str(REPO_ROOT / "scripts" / "export_openapi.py"),
            "--check",
            "--out",
            str(stale),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 1 and "out of date" in out.stderr


def test_keys_create_cli(tmp_path):
    """`dancegraph keys create --tenant NAME` prints a key once; only its hash is stored."""
    import json
    import sqlite3

    db = tmp_path / "keys.db"
    env = {"DANCEGRAPH_HOME": str(tmp_path / "home"), "PATH": "/usr/bin:/bin"}
    cmd = [
        sys.executable,
        "-m",
        "dancegraph.cli",
        "keys",
        "create",
        "--tenant",
        "studio-a",
        "--database-url",
        f"sqlite:///{db}",
    ]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env, cwd=REPO_ROOT)
    assert out.returncode == 0, out.stderr
    key = json.loads(out.stdout)["api_key"]
    assert key.startswith("dg_") and len(key) > 30
    rows = sqlite3.connect(db).execute("SELECT key_hash, prefix FROM api_keys").fetchall()
    assert len(rows) == 1 and key not in rows[0][0] and rows[0][1] == key[:10]
    bad = subprocess.run(
        [*cmd[:-2], "--tenant", "bad name!"] + cmd[-2:],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO_ROOT,
    )
    assert bad.returncode == 2 and "tenant_invalid" in bad.stderr


def test_sqlite_schema_from_migrations_matches_the_models(sqlite_settings):
    """The embedded default gets its schema from the same migrations, and they match the models."""
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    from services.db import get_engine
    from services.models import Base

    with get_engine(sqlite_settings.database_url).connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
    assert diff == []
