"""One command, whole service: ``dancegraph serve --embedded``.

Starts, on one machine with no server installed:
- the API (uvicorn, in this process);
- a Celery worker as a child process, consuming both queues (``analysis`` and ``fbx``) from
  kombu's filesystem broker (a folder under ``DANCEGRAPH_HOME``);
- the reaper, as a thread of this process;
- the graph store in-process (``LocalGraphStore`` behind the same client interface).
Database: SQLite in ``DANCEGRAPH_HOME``. The code paths are the production ones; only the URLs
differ. Without ``--embedded``, ``serve`` uses whatever the environment configures (e.g. Redis,
PostgreSQL and an HTTP graph store) and still starts the worker child and reaper thread.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass

from services.config import QUEUE_ANALYSIS, QUEUE_FBX, Settings, get_settings

log = logging.getLogger("dancegraph.embedded")

EMBEDDED_ENV = {
    "DANCEGRAPH_BROKER_URL": "filesystem://",
    "DANCEGRAPH_GRAPHSTORE_URL": "local",
}


def embedded_settings() -> Settings:
    """Settings of the embedded default: filesystem broker, in-process graph store, SQLite."""
    os.environ.update(EMBEDDED_ENV)
    if not os.environ.get("DANCEGRAPH_DATABASE_URL", "").startswith("sqlite"):
        os.environ.pop("DANCEGRAPH_DATABASE_URL", None)  # SQLite under DANCEGRAPH_HOME
    get_settings.cache_clear()
    return get_settings()


def child_env(settings: Settings) -> dict[str, str]:
    """The environment for child processes: every location pinned to what this process resolved."""
    env = dict(os.environ)
    env.update(
        {
            "DANCEGRAPH_DATABASE_URL": settings.database_url,
            "DANCEGRAPH_BROKER_URL": settings.broker_url,
            "DANCEGRAPH_BROKER_FOLDER": settings.broker_folder,
            "DANCEGRAPH_STORE_ROOT": settings.store_root,
            "DANCEGRAPH_GRAPHSTORE_URL": settings.graphstore_url,
        }
    )
    return env


def worker_command(
    queues: tuple[str, ...] = (QUEUE_ANALYSIS, QUEUE_FBX),
    concurrency: int = 1,
    name: str | None = None,
    loglevel: str = "INFO",
) -> list[str]:
    """The ``celery worker`` command line of one worker process (prefork pool)."""
    cmd = [
        sys.executable,
        "-m",
        "celery",
        "-A",
        "services.worker.celery_app",
        "worker",
        "-Q",
        ",".join(queues),
        "-c",
        str(concurrency),
        "--pool",
        "prefork",
        "--loglevel",
        loglevel,
        "--without-gossip",
        "--without-mingle",
    ]
    if name:
        cmd += ["-n", name]
    return cmd


def prepare(settings: Settings) -> None:
    """Create the schema (SQLite: migrations at start) and the object store's folders."""
    from services.db import upgrade_schema

    if settings.is_sqlite:
        upgrade_schema(settings.database_url)
    os.makedirs(settings.store_root, exist_ok=True)


@dataclass
class Service:
    """Handles on the processes and threads ``start_background`` started."""

    worker: subprocess.Popen
    reaper_stop: threading.Event
    reaper_thread: threading.Thread

    def stop(self, timeout_s: float = 20.0) -> None:
        self.reaper_stop.set()
        if self.worker.poll() is None:
            self.worker.send_signal(signal.SIGTERM)  # warm shutdown: finish the current task
            try:
                self.worker.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.worker.kill()
                self.worker.wait()
        self.reaper_thread.join(timeout=5)


def _stop_with_parent() -> None:
    """In the worker child before it runs: ask Linux for a SIGTERM (Celery's warm shutdown) when
    the process that started it dies, so a killed ``serve``/``quickstart`` leaves no worker
    behind polling its broker. Elsewhere a no-op."""
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM)


def start_background(settings: Settings, concurrency: int = 1) -> Service:
    """Start the worker child process and the reaper thread."""
    from services.worker import reaper

    worker = subprocess.Popen(
        worker_command(concurrency=concurrency, name=f"embedded-{os.getpid()}@%h"),
        env=child_env(settings),
        preexec_fn=_stop_with_parent,
    )
    stop = threading.Event()
    thread = threading.Thread(
        target=reaper.run_forever,
        args=(reaper.default_interval(settings), stop, settings),
        name="reaper",
        daemon=True,
    )
    thread.start()
    log.info("worker and reaper started", extra={"worker_pid": worker.pid})
    return Service(worker, stop, thread)


def serve(
    host: str = "127.0.0.1", port: int = 8000, *, embedded: bool = True, concurrency: int = 1
) -> int:
    """Run API + worker + reaper (+ in-process graph store) until interrupted; returns an exit code."""
    import uvicorn

    from services.worker import logs

    settings = embedded_settings() if embedded else get_settings()
    logs.configure(os.environ.get("DANCEGRAPH_LOG_LEVEL", "INFO"), json_logs=settings.log_json)
    os.environ.update(child_env(settings))  # the API in this process sees the same locations
    prepare(settings)
    service = start_background(settings, concurrency=concurrency)
    log.info(
        "serving",
        extra={
            "url": f"http://{host}:{port}",
            "database": settings.database_url,
            "broker": settings.broker_url,
            "store": settings.store_root,
        },
    )
    # uvicorn re-raises the SIGTERM it caught once it has shut down; exit through ``finally``
    # so the worker child gets its warm shutdown instead of being orphaned.
    signal.signal(signal.SIGTERM, _exit_on_signal)
    try:
        uvicorn.run("services.api.app:app", host=host, port=port, log_config=None)
    finally:
        service.stop()
    return 0


def _exit_on_signal(signum, _frame) -> None:
    raise SystemExit(128 + signum)
