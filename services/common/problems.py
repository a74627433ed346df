"""RFC 9457 problem details for every error the API and the graph store answer.

Every problem carries a stable ``code`` and, where one input is at fault, ``field`` (``audio``,
``spec.alternatives``, ``query.limit``, ``header.Idempotency-Key``, ``job_id`` …). Validation
problems also list every failure in ``errors``. Bad input is never a 500.
"""

from __future__ import annotations

import errno
import logging
import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from sqlalchemy import exc as sa_exc
from starlette.exceptions import HTTPException as StarletteHTTPException

from dancegraph.errors import DanceGraphError, field_errors
from dancegraph.store import StoreUnavailableError

log = logging.getLogger("dancegraph.api")

PROBLEM_JSON = "application/problem+json"
TYPE_BASE = "https://dancegraph.dev/problems/"


class FieldError(BaseModel):
    field: str
    code: str
    message: str


class Problem(BaseModel):
    """An RFC 9457 problem detail with DanceGraph's ``code`` and ``field`` extensions."""

    type: str = Field(..., description="URI naming the problem kind")
    title: str
    status: int
    detail: str
    code: str = Field(..., description="stable machine-readable error code")
    field: str | None = Field(None, description="the offending input, when one is at fault")
    instance: str | None = None
    errors: list[FieldError] | None = None


class ApiError(DanceGraphError):
    """An error raised by the API layer itself, with its HTTP status."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        *,
        field: str | None = None,
        headers: dict | None = None,
        errors: list[dict] | None = None,
    ):
        super().__init__(message, code=code, field=field, errors=errors)
        self.status = status
        self.headers = headers or {}


_TITLES = {
    400: "Bad Request",
    401: "Unauthorized",
    403: "Forbidden",
    404: "Not Found",
    405: "Method Not Allowed",
    409: "Conflict",
    411: "Length Required",
    413: "Content Too Large",
    415: "Unsupported Media Type",
    422: "Unprocessable Content",
    429: "Too Many Requests",
    500: "Internal Server Error",
    503: "Service Unavailable",
}


# What a problem echoes of the request is bounded: a 1 MB spec key or a 60 KB job id comes back
# as its first ECHO_CHARS characters and "…", so an answer stays a few kilobytes whatever was sent.
ECHO_CHARS = 96
TEXT_CHARS = 1024  # one detail, field or message at most
MAX_ERRORS = 32  # listed failures at most (a spec of 10,000 unknown keys lists the first 32)
_LONG_RUN = re.compile(rf"\S{{{ECHO_CHARS + 1},}}")


def bounded(text: str, limit: int = TEXT_CHARS) -> str:
    """``text`` with each run of non-blank characters longer than ``ECHO_CHARS`` cut to its first
    ``ECHO_CHARS`` and ``…``, and the whole cut to ``limit`` characters (``…`` included)."""
    text = _LONG_RUN.sub(lambda m: m.group()[:ECHO_CHARS] + "…", text)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _bounded_errors(errors: list[dict]) -> list[dict]:
    return [
        {k: bounded(v) if isinstance(v, str) else v for k, v in err.items()}
        for err in errors[:MAX_ERRORS]
    ]


def problem_response(
    status: int,
    code: str,
    detail: str,
    *,
    field: str | None = None,
    instance: str | None = None,
    errors: list[dict] | None = None,
    headers: dict | None = None,
) -> JSONResponse:
    """The problem+json answer; every text in it is ``bounded`` (they may echo the request)."""
    body: dict[str, Any] = {
        "type": TYPE_BASE + code,
        "title": _TITLES.get(status, "Error"),
        "status": status,
        "detail": bounded(detail),
        "code": code,
        "field": None if field is None else bounded(field),
        "instance": None if instance is None else bounded(instance),
    }
    if errors:
        body["errors"] = _bounded_errors(errors)
    return JSONResponse(body, status_code=status, media_type=PROBLEM_JSON, headers=headers)


def install(app: FastAPI) -> None:
    """Register the handlers that turn every error into problem+json."""

    @app.exception_handler(DanceGraphError)
    async def _domain(request: Request, exc: DanceGraphError):
        status = int(getattr(exc, "status", 400) or 400)
        headers = getattr(exc, "headers", None)
        if status >= 500:
            log.error("server error %s: %s", exc.code, exc.message)
        return problem_response(
            status,
            exc.code,
            exc.message,
            field=exc.field,
            instance=request.url.path,
            headers=headers,
            errors=getattr(exc, "errors", None),
        )

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errors = field_errors(exc.errors())
        first = errors[0] if errors else {"field": "request", "message": "invalid request"}
        return problem_response(
            422,
            "request_invalid",
            f"{first['field']}: {first['message']}",
            field=first["field"],
            instance=request.url.path,
            errors=errors,
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        code = {404: "not_found", 405: "method_not_allowed"}.get(
            exc.status_code, f"http_{exc.status_code}"
        )
        return problem_response(
            exc.status_code,
            code,
            str(exc.detail),
            instance=request.url.path,
            headers=getattr(exc, "headers", None),
        )

    for exc_types, code, detail, retry_after in _UNAVAILABLE:
        for exc_type in exc_types:
            app.add_exception_handler(exc_type, _unavailable(code, detail, retry_after))

    store_full = _unavailable(*STORE_FULL)

    @app.exception_handler(OSError)
    async def _os_error(request: Request, exc: OSError):
        if is_disk_full(exc):  # the upload's scratch file or the store's disk
            return await store_full(request, exc)
        log.error("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
        return internal_error_response(request.url.path)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return internal_error_response(request.url.path)


# Overload and outages: 503 with Retry-After and a fixed text; the exception's own words (the
# driver's text names hosts and ports) go to the log only.
_UNAVAILABLE = (
    ((sa_exc.TimeoutError,), "database_busy", "the service is busy; try again shortly", 2),
    (
        (sa_exc.OperationalError, sa_exc.InterfaceError),
        "database_unavailable",
        "the database is not reachable; try again later",
        5,
    ),
    (
        (StoreUnavailableError,),
        "store_unavailable",
        "the object store is not reachable; try again later",
        5,
    ),
)


# A full disk or quota: space comes back (the reaper sweeps scratch, an operator adds some).
DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
STORE_FULL = ("store_full", "the object store has no space left; try again later", 60)


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc``, or an error it was raised from, is a full disk or quota (ENOSPC, EDQUOT)."""
    seen: BaseException | None = exc
    for _ in range(8):  # a short cause chain; never a cycle
        if seen is None:
            return False
        if isinstance(seen, OSError) and seen.errno in DISK_FULL_ERRNOS:
            return True
        seen = seen.__cause__ or seen.__context__
    return False


def _unavailable(code: str, detail: str, retry_after: int):
    async def handler(request: Request, exc: Exception) -> JSONResponse:
        log.error("%s on %s %s: %r", code, request.method, request.url.path, exc)
        return problem_response(
            503,
            code,
            detail,
            instance=request.url.path,
            headers={"Retry-After": str(retry_after)},
        )

    return handler


def internal_error_response(instance: str | None = None) -> JSONResponse:
    """The 500 of an unexpected error: a fixed text, never the exception's own words."""
    return problem_response(500, "internal_error", "internal server error", instance=instance)
