"""Request dependencies in one place: settings, database session, object store, graph store,
the calling tenant (API key, or a preview token on the preview routes), and the enqueue
function."""

from __future__ import annotations

from collections.abc import Iterator

from fastapi import Depends, Query, Request, Security
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from dancegraph.store import ObjectStore
from services import jobs
from services.api.preview_tokens import check_token
from services.common.problems import ApiError
from services.config import Settings
from services.db import get_sessionmaker, session_scope
from services.models import Tenant

_api_key_header = APIKeyHeader(
    name="X-API-Key", auto_error=False, description="API key (or use Bearer)"
)
_bearer = HTTPBearer(auto_error=False, description="API key as a bearer token")


def get_settings_dep(request: Request) -> Settings:
    return request.app.state.ctx.settings


def get_db(request: Request) -> Iterator[Session]:
    session = get_sessionmaker(request.app.state.ctx.settings.database_url)()
    try:
        yield session
    finally:
        session.close()


def get_store(request: Request) -> ObjectStore:
    return request.app.state.ctx.store


def get_api_key(
    api_key: str | None = Security(_api_key_header),
    bearer: HTTPAuthorizationCredentials | None = Security(_bearer),
) -> str | None:
    """The request's API key (``X-API-Key`` or ``Authorization: Bearer``), or None."""
    return api_key or (bearer.credentials if bearer is not None else None)


def get_tenant(request: Request, key: str | None = Depends(get_api_key)) -> Tenant:
    """The tenant owning the request's API key; 401 when the key is missing or unknown.

    The key check takes a connection of its own and gives it back at once (the tenant comes
    back detached): a request must not hold one connection for its whole life while its work
    takes others, or a burst of uploads exhausts the pool.
    """
    challenge = {"WWW-Authenticate": 'Bearer realm="dancegraph"'}
    if not key:
        raise ApiError(
            401,
            "auth_missing",
            "an API key is required (X-API-Key or Authorization: Bearer)",
            field="header.X-API-Key",
            headers=challenge,
        )
    with session_scope(request.app.state.ctx.settings.database_url) as session:
        tenant = jobs.tenant_for_key(session, key)
        if tenant is not None:
            session.expunge(tenant)
    if tenant is None:
        raise ApiError(
            401,
            "auth_invalid",
            "the API key is not valid",
            field="header.X-API-Key",
            headers=challenge,
        )
    return tenant


def get_tenant_or_preview_token(
    job_id: str,
    request: Request,
    token: str | None = Query(
        None,
        max_length=200,
        description="signed preview token from the job's preview_url (instead of an API key)",
    ),
    key: str | None = Depends(get_api_key),
    settings: Settings = Depends(get_settings_dep),
) -> Tenant | None:
    """Auth of the preview routes: the tenant when the request carries an API key (401 as
    ``get_tenant``), else None once ``token`` is checked to be a valid preview token for
    ``job_id`` (401 ``preview_token_invalid`` / ``preview_token_expired``;
    ``services.api.preview_tokens``). Neither key nor token: 401 ``auth_missing``."""
    if key or not token:
        return get_tenant(request, key)
    check_token(settings, job_id, token)
    return None


def get_enqueue(request: Request):
    """The function that hands a job id to the queue (overridable in ``app.state.enqueue``)."""
    enqueue = request.app.state.ctx.enqueue
    if enqueue is not None:
        return enqueue
    from services.worker.enqueue import enqueue_job

    return enqueue_job


def get_graphstore(request: Request):
    """The graph store client (in-process or HTTP per ``Settings.graphstore_url``), or None."""
    return request.app.state.ctx.graphstore()
