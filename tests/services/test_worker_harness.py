"""Real services for the worker tests: PostgreSQL database, Redis db, API and Celery worker
processes, a demo motion dataset with a built graph, and generated songs.

No test lives here; the ``test_worker_*`` modules import these fixtures and helpers. Every
process is a real one (``uvicorn``, ``celery worker``, ``dancegraph serve --embedded``), started
with its own environment and stopped at the end of its test module.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest

from dancegraph.paths import REPO_ROOT

REDIS_HOST, REDIS_PORT = "127.0.0.1", 6379
# a db number of its own (other tests and services use 0); overridable where several test runs
# share one Redis
REDIS_DB = int(os.environ.get("DANCEGRAPH_TEST_REDIS_DB", "11"))
PG_ADMIN_URL = "postgresql://postgres@127.0.0.1:5432/postgres"
DATASET = "demo"
WORKER_START_S = 180.0
JOB_TIMEOUT_S = 10.0  # the stuck timeout in these tests: the reaper acts within seconds
FINAL = {"succeeded", "failed", "cancelled"}
VENV_BIN = Path(sys.executable).parent
WEBHOOK_SECRET = "worker-test-webhook-secret-" + "w" * 32


def port_open(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=1):
            return True
    except OSError:
        return False


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate, timeout_s: float, what: str, interval_s: float = 0.1):
    """Poll ``predicate`` until it returns something truthy; fail the test after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(interval_s)


# --- databases and broker -------------------------------------------------------------------


def require_servers() -> None:
    """Skip (with the reason) where PostgreSQL or Redis is not running; CI starts both."""
    if not port_open(REDIS_HOST, REDIS_PORT):
        pytest.skip("Redis is not running on 127.0.0.1:6379 (.ci/run starts it)")
    if not port_open("127.0.0.1", 5432):
        pytest.skip("PostgreSQL is not running on 127.0.0.1:5432 (.ci/run starts it)")


def redis_url() -> str:
    return f"redis://{REDIS_HOST}:{REDIS_PORT}/{REDIS_DB}"


def flush_redis() -> None:
    import redis

    redis.Redis(host=REDIS_HOST, port=REDIS_PORT, db=REDIS_DB).flushdb()


def create_pg_database() -> str:
    """A fresh PostgreSQL database with the schema from ``alembic upgrade head``; returns its URL."""
    import psycopg

    name = f"dg_worker_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(PG_ADMIN_URL, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    url = f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}"
    from services.db import upgrade_schema

    upgrade_schema(url)
    return url


def drop_pg_database(url: str) -> None:
    import psycopg

    from services import db

    db.reset_caches()
    name = url.rsplit("/", 1)[-1]
    with psycopg.connect(PG_ADMIN_URL, autocommit=True) as conn:
        conn.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (name,)
        )
        conn.execute(f'DROP DATABASE IF EXISTS "{name}"')


def restart_redis() -> None:
    """Stop Redis (no save) and start it again with the CI's command line: the queues are lost."""
    subprocess.run(
        ["redis-cli", "-h", REDIS_HOST, "-p", str(REDIS_PORT), "shutdown", "nosave"],
        capture_output=True,
        timeout=30,
    )
    wait_for(lambda: not port_open(REDIS_HOST, REDIS_PORT), 20, "Redis to stop")
    os.makedirs("/var/lib/redis", exist_ok=True)
    os.makedirs("/var/log/redis", exist_ok=True)
    subprocess.run(
        [
            "redis-server",
            "--daemonize",
            "yes",
            "--bind",
            "127.0.0.1",
            "-::1",
            "--port",
            str(REDIS_PORT),
            "--save",
            "",
            "--appendonly",
            "no",
            "--dir",
            "/var/lib/redis",
            "--logfile",
            "/var/log/redis/ci.log",
        ],
        check=True,
        timeout=30,
    )
    wait_for(lambda: port_open(REDIS_HOST, REDIS_PORT), 20, "Redis to start")


# --- demo dataset and songs -----------------------------------------------------------------


def build_demo_store(root: Path) -> Path:
    """An object store holding the demo motion library, imported and with its graph built."""
    from dancegraph.graph.build import build_graph
    from dancegraph.motion.dataset import import_dataset, load_dataset
    from dancegraph.motion.demo import write_demo_library
    from dancegraph.store import FileStore

    store = FileStore(root)
    src = write_demo_library(root.parent / "demo-src", seed=0)
    import_dataset(src, DATASET, store)  # reads the library's own manifest.json
    build_graph(load_dataset(store, DATASET), store)
    return root


def write_test_song(
    out_dir: Path, seed: int, seconds: float = 16.0, name: str | None = None
) -> Path:
    """A generated 4/4 song of about ``seconds`` (WAV, 16-bit) written by the project's generator."""
    from dancegraph.music.generator import generate_song, write_song

    tempo = 120.0
    bars = max(2, round(seconds * tempo / 60.0 / 4))
    song = generate_song(
        seed,
        meter=4,
        tempo_bpm=tempo,
        form=["A", "B"],
        section_bars={"A": bars // 2, "B": bars - bars // 2},
    )
    wav, _ = write_song(song, out_dir, name or f"song-{seed}")
    return wav


# --- processes ------------------------------------------------------------------------------


@dataclass
class Cluster:
    """One service deployment under test: its environment and the processes it started."""

    home: Path
    env: dict[str, str]
    database_url: str
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    logs: dict[str, Path] = field(default_factory=dict)
    api_url: str = ""
    api_key: str = ""

    @property
    def store_root(self) -> Path:
        return Path(self.env["DANCEGRAPH_STORE_ROOT"])

    @property
    def store(self):
        """The deployment's object store, as the test reads it (S3: its own scratch folder)."""
        from dancegraph.store import open_store

        url = self.env.get("DANCEGRAPH_STORE_URL") or self.store_root
        return open_store(url, self.home / "test-scratch")

    def _spawn(self, name: str, cmd: list[str], env: dict | None = None) -> subprocess.Popen:
        log = self.home / f"{name}.log"
        self.logs[name] = log
        own = {}
        if self.env.get("DANCEGRAPH_STORE_URL"):  # S3: no folder shared between processes
            own["DANCEGRAPH_STORE_ROOT"] = str(self.home / f"scratch-{name}")
        proc = subprocess.Popen(
            cmd,
            env={**self.env, **own, **(env or {})},
            cwd=str(REPO_ROOT),
            stdout=open(log, "ab"),  # noqa: SIM115 (the child owns it)
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group: a SIGKILL reaches the pool too
        )
        self.procs[name] = proc
        return proc

    def start_worker(
        self,
        name: str = "w1",
        queues: str = "analysis,fbx",
        concurrency: int = 1,
        env: dict | None = None,
    ) -> subprocess.Popen:
        cmd = [
            str(VENV_BIN / "celery"),
            "-A",
            "services.worker.celery_app",
            "worker",
            "-Q",
            queues,
            "-c",
            str(concurrency),
            "--pool",
            "prefork",
            "-n",
            f"{name}-{uuid.uuid4().hex[:6]}@%h",
            "--without-gossip",
            "--without-mingle",
        ]
        proc = self._spawn(name, cmd, env)
        wait_for(  # a hang bound, not a speed test: the kernel warm-up is slow on a busy host
            lambda: "worker process ready" in self.log_text(name) or proc.poll() is not None,
            WORKER_START_S,
            f"worker {name} to start",
        )
        assert proc.poll() is None, self.log_text(name)[-3000:]
        return proc

    def start_api(self) -> None:
        port = free_port()
        self._spawn(
            "api",
            [
                str(VENV_BIN / "uvicorn"),
                "services.api.app:app",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
            ],
        )
        self.api_url = f"http://127.0.0.1:{port}"
        self.wait_http("api")

    def start_embedded(self) -> None:
        port = free_port()
        self._spawn(
            "serve",
            [
                str(VENV_BIN / "dancegraph"),
                "serve",
                "--embedded",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
            ],
        )
        self.api_url = f"http://127.0.0.1:{port}"
        self.wait_http("serve")
        wait_for(
            lambda: "worker process ready" in self.log_text("serve"), 60, "the embedded worker"
        )

    def wait_http(self, name: str) -> None:
        def up():
            proc = self.procs[name]
            if proc.poll() is not None:
                pytest.fail(f"{name} exited: {self.log_text(name)[-3000:]}")
            try:
                return httpx.get(self.api_url + "/healthz", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for(up, 60, f"{name} to answer /healthz", interval_s=0.25)

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """SIGKILL: the whole process group of ``name`` (main process and pool children) dies at
        once; another signal goes to the main process only (e.g. SIGTERM: a warm shutdown)."""
        proc = self.procs.pop(name)
        try:
            if sig == signal.SIGKILL:
                os.killpg(proc.pid, sig)
            else:
                proc.send_signal(sig)
        except ProcessLookupError:
            pass
        proc.wait(timeout=60)

    def stop_all(self) -> None:
        for name in list(self.procs):
            proc = self.procs[name]
            if proc.poll() is None:
                try:
                    proc.terminate()  # the main process only: it shuts its children down itself
                    proc.wait(timeout=20)
                except (ProcessLookupError, subprocess.TimeoutExpired):
                    try:
                        os.killpg(proc.pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                    proc.wait(timeout=10)
            del self.procs[name]

    def log_text(self, name: str) -> str:
        path = self.logs.get(name)
        return path.read_text(errors="replace") if path and path.exists() else ""

    # --- the API, as a client uses it

    def headers(self, key: str | None = None) -> dict[str, str]:
        return {"X-API-Key": key or self.api_key}

    def submit(self, wav: Path, spec: dict | None = None, key: str | None = None) -> dict:
        with open(wav, "rb") as fh:
            r = httpx.post(
                self.api_url + "/v1/jobs",
                headers=self.headers(key),
                files={"audio": (wav.name, fh, "audio/wav")},
                data={
                    "spec": json.dumps(
                        spec
                        or {"dataset": DATASET, "alternatives": 2, "output": {"formats": ["bvh"]}}
                    )
                },
                timeout=60,
            )
        assert r.status_code == 202, r.text
        return r.json()

    def job(self, job_id: str, *, allow_missing: bool = False) -> dict | None:
        r = httpx.get(f"{self.api_url}/v1/jobs/{job_id}", headers=self.headers(), timeout=30)
        if allow_missing and r.status_code == 404:
            return None  # e.g. a ``dancegraph.submit`` message not handled yet
        assert r.status_code == 200, r.text
        return r.json()

    def wait_final(
        self, job_ids: list[str], timeout_s: float = 180, allow_missing: bool = False
    ) -> dict[str, dict]:
        done: dict[str, dict] = {}

        def all_final():
            for jid in job_ids:
                if jid not in done:
                    body = self.job(jid, allow_missing=allow_missing)
                    if body is not None and body["status"] in FINAL:
                        done[jid] = body
            return len(done) == len(job_ids)

        wait_for(all_final, timeout_s, f"{len(job_ids)} jobs to finish", interval_s=0.5)
        return done

    def download(self, job_id: str, name: str) -> bytes:
        """A result file as a client gets it (following the S3 store's presigned redirect)."""
        r = httpx.get(
            f"{self.api_url}/v1/jobs/{job_id}/{name}",
            headers=self.headers(),
            timeout=60,
            follow_redirects=True,
        )
        assert r.status_code == 200, (name, r.status_code, r.text[:500])
        return r.content


def make_cluster(
    home: Path,
    database_url: str,
    broker_url: str,
    store_root: Path,
    store_url: str = "",
    store_env: dict[str, str] | None = None,
) -> Cluster:
    """A deployment's environment: the filesystem store at ``store_root``, or with
    ``store_url`` the S3 store (``store_env``: its endpoint and credentials)."""
    home.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.pop("DANCEGRAPH_STORE_URL", None)
    env.update(store_env or {})
    if store_url:
        env["DANCEGRAPH_STORE_URL"] = store_url
    env.update(
        {
            "DANCEGRAPH_HOME": str(home),
            "DANCEGRAPH_DATABASE_URL": database_url,
            "DANCEGRAPH_BROKER_URL": broker_url,
            "DANCEGRAPH_BROKER_FOLDER": str(home / "broker"),
            "DANCEGRAPH_STORE_ROOT": str(store_root),
            "DANCEGRAPH_GRAPHSTORE_URL": "local",
            "DANCEGRAPH_JOB_TIMEOUT_S": str(JOB_TIMEOUT_S),
            "DANCEGRAPH_WEBHOOK_BACKOFF_S": "0.5",
            "DANCEGRAPH_WEBHOOK_SECRET": WEBHOOK_SECRET,
            "DANCEGRAPH_PREVIEW_SECRET": "worker-test-preview-secret-" + "p" * 32,
            "DANCEGRAPH_WEBHOOK_ALLOW_NETWORKS": '["127.0.0.1/32"]',  # the local test receivers
            "PYTHONUNBUFFERED": "1",
        }
    )
    return Cluster(home=home, env=env, database_url=database_url)


def create_key(database_url: str, tenant: str) -> str:
    from services import jobs
    from services.db import session_scope

    with session_scope(database_url) as session:
        _, key = jobs.create_api_key(session, tenant)
    return key


def register_dataset(database_url: str) -> None:
    from services import jobs
    from services.db import session_scope

    with session_scope(database_url) as session:
        jobs.upsert_dataset(session, name=DATASET, version="test", graph_key=f"graphs/{DATASET}")


def job_row(database_url: str, job_id: str):
    from services.db import session_scope
    from services.models import Job

    with session_scope(database_url) as session:
        job = session.get(Job, job_id)
        if job is not None:
            session.expunge(job)
        return job


def copy_store(src: Path, dst: Path) -> Path:
    """A private copy of a prepared store (graphs and datasets), so tests never share results."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("jobs", "tmp"))
    return dst


def upload_store(src: Path, store) -> None:
    """A prepared filesystem store's objects (graphs, datasets) copied into another store."""
    for path in sorted(src.rglob("*")):
        rel = path.relative_to(src).as_posix()
        if path.is_file() and not rel.startswith(("jobs/", "tmp/")):
            store.put_file(rel, path)


# --- fixtures -------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def demo_store(tmp_path_factory) -> Path:
    """The demo dataset imported and its graph built, once per test session."""
    return build_demo_store(tmp_path_factory.mktemp("demo") / "store")


@pytest.fixture(scope="session")
def songs(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("songs")
