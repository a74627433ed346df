"""Shared test fixtures: the shared datasets folder and per-test working folders."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from dancegraph.paths import shared_dir

# Compiled kernels: the per-user cache (dancegraph.paths.kernel_cache_dir) that the install step
# filled, shared by the test process and every worker it starts whatever their DANCEGRAPH_HOME.


@pytest.fixture(scope="session")
def shared() -> Path:
    """The shared datasets root; tests that need it are skipped where it is absent."""
    root = shared_dir()
    if not (root / "datasets").is_dir():
        pytest.skip(f"shared datasets not found at {root} (set DANCEGRAPH_SHARED)")
    return root


@pytest.fixture(scope="session")
def salsa_dir(shared: Path) -> Path:
    return shared / "datasets" / "mocap" / "cmu-salsa"


@pytest.fixture(scope="session")
def modern_dir(shared: Path) -> Path:
    return shared / "datasets" / "mocap" / "cmu-modern"


@pytest.fixture(scope="session")
def cc_music_dir(shared: Path) -> Path:
    return shared / "datasets" / "music" / "cc"


@pytest.fixture(scope="session")
def nonmusic_dir(shared: Path) -> Path:
    return shared / "datasets" / "music" / "nonmusic"


@pytest.fixture()
def home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A fresh DANCEGRAPH_HOME for one test."""
    monkeypatch.setenv("DANCEGRAPH_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("DANCEGRAPH_STORE_ROOT", raising=False)
    return tmp_path / "home"


# --- an S3-protocol server ---------------------------------------------------------------------

S3_ENV = {
    "AWS_ACCESS_KEY_ID": "dancegraph-test",
    "AWS_SECRET_ACCESS_KEY": "dancegraph-test-secret",
    "AWS_REGION": "us-east-1",
}


def _answers(url: str) -> bool:
    import httpx

    try:
        httpx.get(url, timeout=2)
        return True
    except httpx.HTTPError:
        return False


@pytest.fixture(scope="session")
def s3_endpoint(tmp_path_factory):
    """The URL of a real S3-protocol server over HTTP: the one ``.ci/run`` started
    (``DANCEGRAPH_TEST_S3_ENDPOINT``), else a ``moto_server`` process started here."""
    import socket
    import subprocess
    import sys
    import time

    endpoint = os.environ.get("DANCEGRAPH_TEST_S3_ENDPOINT", "")
    if endpoint and _answers(endpoint):
        yield endpoint
        return
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    log = tmp_path_factory.mktemp("moto") / "moto_server.log"
    server = Path(sys.executable).parent / "moto_server"
    proc = subprocess.Popen(
        [str(server), "-H", "127.0.0.1", "-p", str(port)],
        stdout=open(log, "wb"),  # noqa: SIM115 (the child owns it)
        stderr=subprocess.STDOUT,
    )
    endpoint = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while not _answers(endpoint):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"moto_server did not start: {log.read_text()[-2000:]}")
        time.sleep(0.2)
    yield endpoint
    proc.terminate()
    proc.wait(timeout=20)


def new_bucket(endpoint: str) -> str:
    """A fresh, empty bucket on the S3 server; returns its name."""
    import uuid

    import boto3

    name = f"dg-test-{uuid.uuid4().hex[:12]}"
    boto3.client("s3", endpoint_url=endpoint, **_boto_credentials()).create_bucket(Bucket=name)
    return name


def _boto_credentials() -> dict:
    return {
        "aws_access_key_id": S3_ENV["AWS_ACCESS_KEY_ID"],
        "aws_secret_access_key": S3_ENV["AWS_SECRET_ACCESS_KEY"],
        "region_name": S3_ENV["AWS_REGION"],
    }


@pytest.fixture()
def s3_url(s3_endpoint: str, monkeypatch: pytest.MonkeyPatch) -> str:
    """``s3://<fresh bucket>/store`` with the server's endpoint and credentials in the
    environment (as a deployment sets them)."""
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3_endpoint)
    for name, value in S3_ENV.items():
        monkeypatch.setenv(name, value)
    return f"s3://{new_bucket(s3_endpoint)}/store"
