"""Liveness, readiness and metrics."""

from __future__ import annotations

import logging
import os

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, Response

from dancegraph import __version__
from services.api import metrics
from services.api.deps import get_settings_dep
from services.api.schemas import Health, Readiness
from services.config import Settings

router = APIRouter(tags=["health"])
log = logging.getLogger("dancegraph.api")


@router.get("/healthz", response_model=Health, summary="The process is alive")
def healthz():
    return Health(status="ok", version=__version__)


def _check_db(settings: Settings) -> str:
    from services.db import ping

    ping(settings.database_url)
    return "ok"


def _check_broker(settings: Settings) -> str:
    if settings.is_embedded_broker:
        folder = settings.broker_transport_options()["data_folder_in"]
        if not os.access(folder, os.W_OK):
            raise OSError(f"broker folder {folder} is not writable")
        return "ok"
    if settings.broker_url.startswith(("redis://", "rediss://")):
        import redis

        client = redis.Redis.from_url(
            settings.broker_url, socket_timeout=2, socket_connect_timeout=2
        )
        try:
            client.ping()
        finally:
            client.close()
        return "ok"
    from kombu import Connection

    with Connection(
        settings.broker_url, connect_timeout=2, transport_options={"socket_timeout": 2}
    ) as conn:
        conn.ensure_connection(max_retries=1, timeout=2)
    return "ok"


def _check_store(request: Request, settings: Settings) -> str:
    store = request.app.state.ctx.store
    store.check()
    free = store.free_bytes()
    if free < settings.min_free_bytes:
        return f"error: low disk space ({free // 2**20} MiB free, {settings.min_free_bytes // 2**20} MiB needed)"
    return "ok"


@router.get(
    "/readyz",
    response_model=Readiness,
    summary="Database, broker and object store answer; the store's disk has room",
    responses={503: {"model": Readiness, "description": "a component is not ready"}},
)
def readyz(request: Request, settings: Settings = Depends(get_settings_dep)):
    checks = {}
    for name, fn in (
        ("database", lambda: _check_db(settings)),
        ("broker", lambda: _check_broker(settings)),
        ("store", lambda: _check_store(request, settings)),
    ):
        try:
            checks[name] = fn()
        except Exception as exc:  # report, never raise: readiness is an answer, not an error
            # the kind of failure only: the driver's own text names hosts, ports and paths
            log.warning("readiness check %s failed: %s", name, exc)
            checks[name] = f"error: {name} unreachable ({type(exc).__name__})"
    ready = all(v == "ok" for v in checks.values())
    body = Readiness(status="ready" if ready else "not_ready", checks=checks)
    return JSONResponse(body.model_dump(), status_code=200 if ready else 503)


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}}},
)
def prometheus_metrics(settings: Settings = Depends(get_settings_dep)):
    from prometheus_client import CONTENT_TYPE_LATEST

    metrics.JOB_STATUS.database_url = settings.database_url
    return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)
