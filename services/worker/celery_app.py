"""The Celery application, built from ``services.config.Settings``.

- Broker: Redis in production (``DANCEGRAPH_BROKER_URL=redis://127.0.0.1:6379/0``), kombu's
  ``filesystem://`` transport in the embedded default (folders under ``Settings.broker_folder``).
- Queues: ``analysis`` (analysis, graph search, render, webhooks) and ``fbx`` (FBX export through
  Blender), each on its own exchange, so ``celery worker -Q fbx`` scales apart from ``-Q analysis``.
- Reliability: ``acks_late`` + ``reject_on_worker_lost`` (a message is acknowledged only after its
  task returns; a killed child puts it back), prefetch 1 (a slow job never holds others hostage),
  soft/hard time limits. No result backend: the ``jobs`` row is the only record of a result.

Start a worker with ``dancegraph worker`` (or ``celery -A services.worker.celery_app worker``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from celery import Celery, signals
from kombu import Exchange, Queue

from services.config import QUEUE_ANALYSIS, QUEUE_FBX, Settings, get_settings
from services.worker import logs

# Public task names (documented in docs/tasks.md; stable within v1).
TASK_RUN_JOB = "dancegraph.run_job"
TASK_EXPORT_FBX = "dancegraph.export_fbx"
TASK_DELIVER_WEBHOOK = "dancegraph.deliver_webhook"
TASK_SUBMIT = "dancegraph.submit"
TASK_REAP = "dancegraph.reap"
TASK_IMPORT_LIBRARY = "dancegraph.import_library"

TASK_QUEUES = {
    TASK_RUN_JOB: QUEUE_ANALYSIS,
    TASK_SUBMIT: QUEUE_ANALYSIS,
    TASK_DELIVER_WEBHOOK: QUEUE_ANALYSIS,
    TASK_REAP: QUEUE_ANALYSIS,
    TASK_IMPORT_LIBRARY: QUEUE_ANALYSIS,
    TASK_EXPORT_FBX: QUEUE_FBX,
}

# Seconds between polls of the filesystem broker (it has no push); 1 s would add latency.
_FILESYSTEM_POLL_S = 0.2


def broker_transport_options(settings: Settings) -> dict:
    """The settings' transport options plus the filesystem broker's control folder."""
    options = dict(settings.broker_transport_options())
    if settings.is_embedded_broker:
        control = Path(settings.broker_folder) / "control"
        control.mkdir(parents=True, exist_ok=True)
        # Without it kombu keeps exchange bindings in ./control of whatever the cwd is.
        options.setdefault("control_folder", str(control))
        options.setdefault("polling_interval", _FILESYSTEM_POLL_S)
    return options


def make_celery(settings: Settings | None = None) -> Celery:
    """A Celery app configured from ``settings`` (default: the process's settings)."""
    settings = settings or get_settings()
    app = Celery("dancegraph", broker=settings.broker_url, include=["services.worker.tasks"])
    app.conf.update(**celery_config(settings))
    return app


def reconfigure(settings: Settings) -> Celery:
    """Point the module's ``app`` at new settings (embedded launcher, tests); drops pooled connections."""
    app.conf.update(broker_url=settings.broker_url, **celery_config(settings))
    if app._pool is not None:
        app._pool.force_close_all()
        app._pool = None
    app.amqp._producer_pool = None
    return app


def celery_config(settings: Settings) -> dict:
    """Celery settings derived from ``settings`` (see the module docstring)."""
    soft = float(settings.job_soft_time_limit_s)
    return dict(
        broker_transport_options=broker_transport_options(settings),
        broker_connection_retry_on_startup=True,
        broker_connection_max_retries=None,  # keep reconnecting while Redis restarts
        result_backend=settings.result_backend,
        task_ignore_result=settings.result_backend is None,
        task_queues=(
            Queue(
                QUEUE_ANALYSIS, Exchange(QUEUE_ANALYSIS, type="direct"), routing_key=QUEUE_ANALYSIS
            ),
            Queue(QUEUE_FBX, Exchange(QUEUE_FBX, type="direct"), routing_key=QUEUE_FBX),
        ),
        task_default_queue=QUEUE_ANALYSIS,
        task_default_exchange=QUEUE_ANALYSIS,
        task_default_routing_key=QUEUE_ANALYSIS,
        task_routes={name: {"queue": q, "routing_key": q} for name, q in TASK_QUEUES.items()},
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_acks_on_failure_or_timeout=True,
        worker_prefetch_multiplier=1,
        task_soft_time_limit=soft,
        task_time_limit=soft + 60.0,
        task_serializer="json",
        accept_content=["json"],
        task_track_started=False,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
        worker_max_tasks_per_child=200,  # bounds slow leaks; a recycled child re-warms Blender
        # The filesystem broker would poll a pidbox folder for remote control: not worth it there.
        worker_enable_remote_control=not settings.is_embedded_broker,
        enable_utc=True,
        # ``celery -A services.worker.celery_app beat`` runs the reaper on this schedule (an
        # alternative to the ``dancegraph reaper`` loop; run one of the two, once per cluster).
        beat_schedule={
            "reap-stuck-jobs": {
                "task": TASK_REAP,
                "schedule": max(0.5, min(60.0, settings.job_timeout_s / 3.0)),
            }
        },
    )


app = make_celery()


@signals.setup_logging.connect
def _setup_logging(**_kwargs) -> None:
    # Connecting this signal stops Celery from installing its own plain-text handlers.
    settings = get_settings()
    logs.configure(os.environ.get("DANCEGRAPH_LOG_LEVEL", "INFO"), json_logs=settings.log_json)


@signals.worker_init.connect
def _warm_up(**_kwargs) -> None:
    # In the main worker process, before the pool forks: children inherit the compiled kernels,
    # and only this process writes numba's cache (under its lock; see dancegraph.jit).
    if get_settings().warm_up:
        from dancegraph import jit

        log = logging.getLogger("dancegraph.worker")
        try:
            jit.warm_kernels()
        except Exception:  # a job still compiles on demand; the log says why start-up was slow
            log.exception("kernel warm-up failed")
        else:
            log.info("kernels warm")


@signals.worker_process_init.connect
def _after_fork(**_kwargs) -> None:
    # A forked pool child must not share the parent's database connections.
    from services import db

    db.reset_caches()
    # billiard leaves its own authkey type on multiprocessing's current process, which
    # multiprocessing refuses to pickle: the sandbox's forkserver children (dancegraph.sandbox,
    # e.g. a library import) could not start from a pool child.
    import multiprocessing.process as mp_process

    me = mp_process.current_process()
    plain = mp_process.AuthenticationString  # type: ignore[attr-defined]
    if not isinstance(me.authkey, plain):
        me._config["authkey"] = plain(bytes(me.authkey))  # type: ignore[attr-defined]
    logging.getLogger("dancegraph.worker").info("worker process ready", extra={"pid": os.getpid()})


@signals.worker_process_shutdown.connect
def _before_exit(**_kwargs) -> None:
    from services.worker import fbx_export

    fbx_export.close_exporter()
