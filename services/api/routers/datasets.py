"""Datasets: the motion libraries a spec may name — the public ones the operator installs and
each tenant's own uploads (``services.common.libraries``)."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Depends, Request, Response
from fastapi.concurrency import run_in_threadpool
from sqlalchemy.orm import Session

from dancegraph.store import ObjectStore
from services.api.deps import get_db, get_graphstore, get_settings_dep, get_store, get_tenant
from services.api.forms import _limited
from services.api.multipart import Form, read_form
from services.api.routers.jobs import AUTH_ERRORS, PROBLEM
from services.api.schemas import (
    DatasetList,
    DatasetOut,
    DatasetTakeOut,
    DatasetVersionOut,
    ErrorOut,
)
from services.common import catalog, libraries
from services.common.problems import ApiError
from services.config import Settings
from services.db import session_scope
from services.models import QUEUED, Dataset, Tenant, new_id

log = logging.getLogger("dancegraph.api")

router = APIRouter(prefix="/v1/datasets", tags=["datasets"])

LIBRARY_UPLOAD = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "properties": {
                        "name": {
                            "type": "string",
                            "description": "the library's name (else the manifest's)",
                        },
                        "manifest": {
                            "type": "string",
                            "description": "YAML or JSON (docs/libraries.md)",
                        },
                        "takes": {
                            "type": "array",
                            "items": {"type": "string", "format": "binary"},
                            "description": "motion takes: .bvh, .glb/.gltf (.fbx: refused per take for now)",
                        },
                        "audio": {
                            "type": "array",
                            "items": {"type": "string", "format": "binary"},
                            "description": "the music takes were danced to, named by the manifest",
                        },
                        "archive": {
                            "type": "string",
                            "format": "binary",
                            "description": "instead of the parts: one .zip/.tar/.tar.gz holding them",
                        },
                    },
                }
            }
        },
    }
}


def _takes(report: dict) -> list[DatasetTakeOut]:
    out = [
        DatasetTakeOut(
            file=c.get("file", ""),
            id=c.get("id"),
            status="imported",
            duration_s=c.get("duration_s"),
            tempo_bpm=c.get("tempo_bpm"),
            bars=c.get("bars"),
            beat_source=c.get("beat_source"),
            flags=c.get("flags") or [],
        )
        for c in report.get("clips", [])
    ]
    out += [
        DatasetTakeOut(
            file=f.get("file", ""), status="failed", code=f.get("code"), message=f.get("error")
        )
        for f in report.get("failed", [])
    ]
    out += [
        DatasetTakeOut(
            file=e.get("file", ""), id=e.get("id"), status="excluded", message=e.get("reason")
        )
        for e in report.get("excluded", [])
    ]
    return out


def _out(row: Dataset, versions: list[Dataset] | None = None) -> DatasetOut:
    report = row.report or {}
    graph = report.get("graph") or {}
    stats = row.stats or {}
    error = (
        ErrorOut(code=row.error_code, message=row.error_message or "", field=row.error_field)
        if row.error_code
        else None
    )
    return DatasetOut(
        name=row.name,
        version=row.version,
        licence=row.licence,
        embedding=row.embedding,
        stats=stats,
        created_at=row.created_at,
        public=row.tenant_id is None,
        url=f"/v1/datasets/{row.name}",
        status=row.status,  # type: ignore[arg-type]
        stage=row.stage,
        progress=row.progress,
        graph_version=graph.get("version") or (row.version if row.tenant_id is None else None),
        nodes=stats.get("nodes"),
        edges=stats.get("edges"),
        takes=_takes(report),
        warnings=[str(w) for w in report.get("warnings", [])],
        seconds=report.get("seconds") or {},
        error=error,
        finished_at=row.finished_at,
        versions=[
            DatasetVersionOut(
                version=v.version,
                status=v.status,  # type: ignore[arg-type]
                created_at=v.created_at,
                graph_version=libraries.graph_version(v),
            )
            for v in versions or []
        ],
    )


@router.get(
    "",
    response_model=DatasetList,
    summary="Your libraries and the public ones",
    responses=AUTH_ERRORS,
)
def list_datasets(
    tenant: Tenant = Depends(get_tenant),
    db: Session = Depends(get_db),
    graphstore=Depends(get_graphstore),
):
    catalog.refresh_catalog(db, graphstore)
    return DatasetList(items=[_out(r) for r in libraries.visible_rows(db, tenant.id)])


@router.get(
    "/{name}",
    response_model=DatasetOut,
    summary="One library: its newest version's state, per-take results, graph; every version",
    responses={**AUTH_ERRORS, 404: PROBLEM},
)
def get_dataset(
    name: str,
    tenant: Tenant = Depends(get_tenant),
    db: Session = Depends(get_db),
    graphstore=Depends(get_graphstore),
):
    if not libraries.LOOKUP_NAME.match(name):
        raise ApiError(404, "unknown_dataset", f"no dataset named {name!r}", field="name")
    row = libraries.shown_row(db, tenant.id, name)
    if row is None:
        catalog.find_dataset(db, name, graphstore)  # a public graph the table has not seen yet
        row = libraries.public_row(db, name)
    if row is None:
        raise ApiError(404, "unknown_dataset", f"no dataset named {name!r}", field="name")
    versions = libraries.own_rows(db, tenant.id, name) if row.tenant_id is not None else []
    return _out(row, versions)


@router.post(
    "",
    status_code=202,
    response_model=DatasetOut,
    summary="Upload a library (a new version under an existing name); import and build are queued",
    openapi_extra=LIBRARY_UPLOAD,
    responses={**AUTH_ERRORS, 403: PROBLEM, 413: PROBLEM, 415: PROBLEM, 422: PROBLEM, 503: PROBLEM},
)
async def create_dataset(
    request: Request,
    response: Response,
    tenant: Tenant = Depends(get_tenant),
    settings: Settings = Depends(get_settings_dep),
    store: ObjectStore = Depends(get_store),
):
    form = await _read_form(request, settings, store)
    try:
        out = await run_in_threadpool(_accept, request, settings, store, tenant.id, form)
    finally:
        form.discard()
    response.headers["Location"] = out.url
    return out


async def _read_form(request: Request, settings: Settings, store: ObjectStore) -> Form:
    """The multipart body streamed to scratch files, refused at the first byte past
    ``library_max_upload_bytes`` (413 ``upload_too_large``)."""
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("multipart/form-data"):
        raise ApiError(
            415,
            "content_type_unsupported",
            "send multipart/form-data (docs/libraries.md)",
            field="header.Content-Type",
        )
    limit = settings.library_max_upload_bytes
    declared = request.headers.get("content-length", "")
    if declared.isascii() and declared.isdigit() and int(declared) > limit:
        raise ApiError(
            413, "upload_too_large", f"the upload is larger than {limit} bytes", field="body"
        )
    return await read_form(
        _limited(request.stream(), limit),
        ctype,
        store.scratch,
        max_file_bytes=limit,
        max_files=2 * settings.library_max_takes + 2,
        too_many_code="library_too_many_takes",
    )


def _upload(form: Form) -> tuple[libraries.Upload, dict | None]:
    """The form's parts as an ``Upload`` and its manifest, parsed and checked."""
    archives = form.files_named("archive")
    if len(archives) > 1:
        raise ApiError(422, "upload_mixed", "send one 'archive' part at most", field="archive")
    raw: str | bytes | None = form.text("manifest")
    manifest_name = "manifest.yaml"
    files = form.files_named("manifest")
    if raw is None and files:
        raw = files[0].read_text(libraries.MANIFEST_MAX_BYTES)
        manifest_name = files[0].filename or manifest_name
        if raw is None:
            raise ApiError(413, "manifest_too_large", "the manifest is too large", field="manifest")
    manifest = None
    if raw is not None:
        manifest = libraries.parse_manifest_text(
            raw.encode() if isinstance(raw, str) else raw, manifest_name
        )
    up = libraries.Upload(
        name=form.text("name") or (manifest or {}).get("name"),
        takes=form.files_named("takes"),
        audio=form.files_named("audio"),
        archive=archives[0] if archives else None,
    )
    return up, manifest


def _accept(
    request: Request, settings: Settings, store: ObjectStore, tenant_id: str, form: Form
) -> DatasetOut:
    """Check, store, write the version's row, enqueue its import; a refusal keeps nothing."""
    up, manifest = _upload(form)
    with session_scope(settings.database_url) as session:
        name = libraries.check_name(session, settings, tenant_id, up.name)
    libraries.check_upload(settings, up, manifest)
    version = new_id()
    upload = libraries.store_upload(store, up, version, manifest)
    with session_scope(settings.database_url) as session:
        row = Dataset(
            tenant_id=tenant_id,
            name=name,
            version=version,
            graph_name=libraries.new_graph_name(),
            status=QUEUED,
            stage="queued",
            progress=0.0,
            upload=upload,
            licence=str((manifest or {}).get("licence") or ""),
        )
        session.add(row)
        session.flush()
        row_id = row.id
    try:
        _enqueue(request)(row_id)
    except Exception as exc:
        log.error("enqueue of library import %s failed: %s", row_id, exc)
        with session_scope(settings.database_url) as session:
            session.query(Dataset).filter_by(id=row_id).delete()
        store.delete_prefix(libraries.upload_prefix(version))
        raise ApiError(
            503,
            "queue_unavailable",
            "the job queue is not reachable; try again later",
            headers={"Retry-After": "5"},
        ) from exc
    log.info(
        "library upload accepted",
        extra={"tenant_id": tenant_id, "library": name, "version": version},
    )
    with session_scope(settings.database_url) as session:
        fresh = session.get(Dataset, row_id)
        assert fresh is not None
        return _out(fresh, libraries.own_rows(session, tenant_id, name))


def _enqueue(request: Request):
    """What hands a version's import to the queue (``app.state.enqueue_library`` in tests)."""
    fn = getattr(request.app.state, "enqueue_library", None)
    if fn is not None:
        return fn
    from services.worker.enqueue import enqueue_library

    return enqueue_library


@router.delete(
    "/{name}",
    status_code=204,
    summary="Delete your library: every version (jobs already running finish on theirs)",
    responses={**AUTH_ERRORS, 403: PROBLEM, 404: PROBLEM},
)
def delete_dataset(
    name: str,
    tenant: Tenant = Depends(get_tenant),
    db: Session = Depends(get_db),
    store: ObjectStore = Depends(get_store),
    settings: Settings = Depends(get_settings_dep),
    graphstore=Depends(get_graphstore),
):
    if not libraries.LOOKUP_NAME.match(name):
        raise ApiError(404, "unknown_dataset", f"no dataset named {name!r}", field="name")
    libraries.delete_library(db, tenant.id, name)
    db.commit()
    removed = libraries.purge_deleted(db, store, settings.job_timeout_s)
    db.commit()
    for graph in removed:
        forget = getattr(graphstore, "forget", None)
        if forget is not None:
            forget(graph)
    return Response(status_code=204)
