"""Secrets: a deployment that is not the embedded default refuses public or short ones."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import yaml
from pydantic import ValidationError

from dancegraph.paths import REPO_ROOT
from services.config import Settings

PG = "postgresql+psycopg://postgres@127.0.0.1:5432/none"
GOOD = "5f0c9e2a7b41d83e6a9c0f17b2d4e85a3c6f9b0e"  # 40 hex digits, as openssl rand -hex gives


@pytest.mark.parametrize(
    "webhook,preview",
    [
        ("dancegraph-dev-secret", GOOD),  # the embedded defaults, public in the code
        (GOOD, "dancegraph-dev-preview-secret"),
        ("change-me", GOOD),  # the old compose fallbacks
        (GOOD, "change-me-too"),
        ("short-but-private", GOOD),
    ],
)
def test_a_deployment_refuses_public_or_short_secrets(webhook, preview):
    with pytest.raises(ValidationError, match="DANCEGRAPH_(WEBHOOK|PREVIEW)_SECRET"):
        Settings(
            database_url=PG,
            broker_url="redis://127.0.0.1:6379/0",
            webhook_secret=webhook,
            preview_secret=preview,
        )


def test_private_secrets_and_the_embedded_default_start():
    Settings(
        database_url=PG, broker_url="redis://x:6379/0", webhook_secret=GOOD, preview_secret=GOOD
    )
    embedded = Settings(database_url="sqlite:///x.db", broker_url="filesystem://")
    assert embedded.webhook_secret == "dancegraph-dev-secret"  # one machine, nobody else's


def test_the_api_process_refuses_to_start_with_the_defaults(tmp_path):
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith("DANCEGRAPH_") or k in ("DANCEGRAPH_SHARED",)
    }
    env.update({"DANCEGRAPH_HOME": str(tmp_path), "DANCEGRAPH_DATABASE_URL": PG})
    uvicorn = str(os.path.join(os.path.dirname(sys.executable), "uvicorn"))
    out = subprocess.run(
        [uvicorn, "services.api.app:app", "--port", "1"],
        cwd=REPO_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode != 0
    assert "DANCEGRAPH_WEBHOOK_SECRET must be set" in out.stderr


def test_compose_requires_every_secret():
    text = (REPO_ROOT / "docker-compose.yml").read_text()
    doc = yaml.safe_load(text)
    env = doc["x-dancegraph-env"]
    for name in ("DANCEGRAPH_WEBHOOK_SECRET", "DANCEGRAPH_PREVIEW_SECRET"):
        assert env[name].startswith("${" + name + ":?"), env[name]
    assert env["AWS_SECRET_ACCESS_KEY"].startswith("${MINIO_ROOT_PASSWORD:?")
    assert "change-me" not in text
