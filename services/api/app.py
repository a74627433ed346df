"""The FastAPI application: ``uvicorn services.api.app:app``.

``create_app(settings)`` builds an app around explicit settings (tests, the embedded launcher);
the module-level ``app`` reads them from the environment on first use, so importing it (e.g. to
export ``openapi.yaml``) touches no database, folder or broker.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from contextlib import asynccontextmanager
from functools import cached_property

from fastapi import FastAPI
from fastapi.routing import APIRoute

from dancegraph import __version__
from dancegraph.spec import Spec
from dancegraph.store import ObjectStore
from services.api import metrics
from services.api.routers import batches, datasets, health, jobs, preview, rigs
from services.common import problems
from services.config import Settings, get_settings, object_store
from services.preview_server import static_router

log = logging.getLogger("dancegraph.api")

DESCRIPTION = """Music in, dance out. Upload a song with a constraint spec; get ranked dance
alternatives as BVH and FBX cut from a motion-capture library, locked to the song's bars.

Authenticate with an API key (`X-API-Key: dg_…` or `Authorization: Bearer dg_…`); create one with
`dancegraph keys create --tenant NAME`. A tenant sees only its own jobs and batches (another
tenant's id answers 404 like a missing one).

Errors are RFC 9457 problem details (`application/problem+json`) with a stable `code` and the
offending `field`; a failed job carries the same codes in `error`:

| status | code | when |
|---|---|---|
| 401 | `auth_missing`, `auth_invalid` | no or unknown API key |
| 401 | `preview_token_invalid`, `preview_token_expired` | a preview link's `?token=` |
| 404 | `job_not_found`, `batch_not_found`, `unknown_dataset`, `result_not_found` | no such thing (for you) |
| 409 | `idempotency_key_reused`, `job_finished`, `job_not_finished`, `job_failed`, `job_cancelled` | state conflicts |
| 413 | `upload_too_large`, `spec_too_large` | over the size limit (checked while streaming) |
| 415 | `content_type_unsupported`, `audio_undecodable`, `audio_unsupported_codec` | not multipart, not audio |
| 422 | `audio_missing`, `audio_multiple`, `audio_empty`, `audio_too_short`, `audio_too_long` | the audio part |
| 422 | `spec_malformed`, `spec_invalid`, `spec_unknown_field`, `unknown_dataset` | the spec part (also: non-finite numbers, text PostgreSQL cannot store, nesting deeper than 32, loose types) |
| 422 | `callback_url_forbidden` | a `callback_url` at (or resolving to) a loopback, private, link-local or metadata address |
| 422 | `request_invalid`, `cursor_invalid`, `batch_too_large` | query, headers, batch size |
| 503 | `queue_unavailable` | the broker is down; nothing was kept (`Retry-After`) |
| 503 | `database_busy`, `database_unavailable`, `store_unavailable`, `store_full` | a burst, an outage or a full disk: try again after `Retry-After` |
| 503 | `preview_not_built` | the preview page's front end is not built on this server |

Job failures add codes of the pipeline, e.g. `no_beat`, `constraint_conflict`, `fbx_export_failed`,
`result_missing` (the result left the store under the job), `store_full` (the disk stayed full)."""


def operation_id(route: APIRoute) -> str:
    """An operation's id in ``openapi.yaml``: its handler's name in camelCase (``create_job`` →
    ``createJob``), so generated clients get short, stable function names."""
    head, *rest = route.name.split("_")
    return head + "".join(word.capitalize() for word in rest)


class AppContext:
    """What requests share: settings, object store, graph store client, enqueue function."""

    def __init__(
        self,
        settings: Settings | None = None,
        *,
        enqueue: Callable[[str], object] | None = None,
        graphstore=None,
    ):
        self._settings = settings
        self.enqueue = enqueue
        self._graphstore = graphstore

    @cached_property
    def settings(self) -> Settings:
        return self._settings or get_settings()

    @cached_property
    def store(self) -> ObjectStore:
        return object_store(self.settings)

    def graphstore(self):
        """The graph store client per ``Settings.graphstore_url``; None when none is available."""
        if self._graphstore is None:
            try:
                from services.graphstore.client import HttpGraphStore, LocalGraphStore
            except ImportError:
                return None
            url = self.settings.graphstore_url
            self._graphstore = (
                LocalGraphStore(self.store, self.settings.graphstore_memory_bytes)
                if url == "local"
                else HttpGraphStore(url)
            )
        return self._graphstore


def create_app(
    settings: Settings | None = None,
    *,
    enqueue: Callable[[str], object] | None = None,
    graphstore=None,
    migrate: bool | None = None,
    configure_logging: bool = False,
) -> FastAPI:
    """Build the API. ``migrate``: run ``alembic upgrade head`` at start-up (default: on SQLite)."""
    ctx = AppContext(settings, enqueue=enqueue, graphstore=graphstore)

    @asynccontextmanager
    async def lifespan(_app: FastAPI):
        if configure_logging:  # JSON lines with the job id, as the worker writes them
            import os

            from services.worker.logs import configure

            configure(
                os.environ.get("DANCEGRAPH_LOG_LEVEL", "INFO"), json_logs=ctx.settings.log_json
            )
        # Warm what the first uploads would otherwise import under the import lock all at once
        # (a burst on a fresh process queued seconds behind it): the decoder, the graph-store
        # client, the broker transport.
        import dancegraph.music.decode  # noqa: F401

        ctx.graphstore()
        if ctx.enqueue is None:
            from services.worker.enqueue import warm_up as warm_broker

            warm_broker()

        do_migrate = ctx.settings.is_sqlite if migrate is None else migrate
        if do_migrate:
            from services.db import upgrade_schema

            upgrade_schema(ctx.settings.database_url)
        yield

    app = FastAPI(
        title="DanceGraph API",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        generate_unique_id_function=operation_id,
        openapi_tags=[
            {"name": "jobs", "description": "one song → dance alternatives"},
            {"name": "preview", "description": "watch a job's dance on its song in the browser"},
            {"name": "batches", "description": "many songs, one spec"},
            {"name": "datasets", "description": "motion libraries with built graphs"},
            {"name": "rigs", "description": "your own characters, to retarget the dance onto"},
            {"name": "health", "description": "liveness, readiness, metrics"},
        ],
    )
    app.state.ctx = ctx
    problems.install(app)
    for module in (jobs, preview, batches, datasets, rigs, health):
        app.include_router(module.router)
    app.include_router(static_router)

    app.add_middleware(ObserveMiddleware)

    def openapi():
        if app.openapi_schema is None:
            from fastapi.openapi.utils import get_openapi

            schema = get_openapi(
                title=app.title,
                version=app.version,
                description=app.description,
                routes=app.routes,
                tags=app.openapi_tags,
            )
            comps = schema.setdefault("components", {}).setdefault("schemas", {})
            comps["Problem"] = problems.Problem.model_json_schema(
                ref_template="#/components/schemas/{model}"
            )
            comps["FieldError"] = (
                comps["Problem"].pop("$defs", {}).get("FieldError")
                or problems.FieldError.model_json_schema()
            )
            spec_schema = Spec.model_json_schema(ref_template="#/components/schemas/{model}")
            for name, sub in spec_schema.pop("$defs", {}).items():
                comps.setdefault(name, sub)
            comps["Spec"] = spec_schema
            _problem_validation_responses(schema)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented override
    return app


class ObserveMiddleware:
    """Request metrics, and the last word on an unexpected error (a pure ASGI middleware).

    An error that escapes the app is answered with the 500 problem here and *not* raised on:
    Starlette's outermost error middleware would send the same 500 and then re-raise, and
    uvicorn closes a connection whose request raised, so the client's next request on that
    keep-alive connection would find it reset.
    """

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        state = {"status": 500, "started": False}

        async def send_wrapper(message):
            if message["type"] == "http.response.start":
                state["status"], state["started"] = message["status"], True
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        except Exception:
            log.exception("unhandled error on %s %s", scope.get("method"), scope.get("path"))
            if state["started"]:
                raise  # half a response is out: only closing the connection can end it
            await problems.internal_error_response(scope.get("path"))(scope, receive, send)
        finally:
            template = getattr(scope.get("route"), "path", "unmatched")
            method = scope.get("method", "")
            metrics.HTTP_REQUESTS.labels(method, template, str(state["status"])).inc()
            metrics.HTTP_LATENCY.labels(method, template).observe(time.perf_counter() - start)


def _problem_validation_responses(schema: dict) -> None:
    """Document 422s as the problem+json they are (FastAPI assumes its own error shape)."""
    problem = {
        "description": "problem details",
        "content": {
            "application/problem+json": {"schema": {"$ref": "#/components/schemas/Problem"}}
        },
    }
    for path_item in schema.get("paths", {}).values():
        for op in path_item.values():
            responses = op.get("responses", {})
            body = responses.get("422", {}).get("content", {})
            if "application/json" in body and "HTTPValidationError" in str(body):
                responses["422"] = problem
    comps = schema.get("components", {}).get("schemas", {})
    for name in ("HTTPValidationError", "ValidationError"):
        comps.pop(name, None)


app = create_app(configure_logging=True)
