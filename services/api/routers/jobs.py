"""Jobs: create (multipart upload), read, list, cancel, download results."""

from __future__ import annotations

import base64
import json
from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Header, Path, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.encoders import jsonable_encoder
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse, Response
from sqlalchemy.orm import Session

from dancegraph.store import ObjectStore
from services import jobs
from services.api import metrics
from services.api.deps import (
    get_db,
    get_enqueue,
    get_graphstore,
    get_settings_dep,
    get_store,
    get_tenant,
)
from services.api.forms import audio_parts, form_spec, read_multipart
from services.api.schemas import JobOut, JobPage, JobStatus
from services.api.views import job_out, job_url
from services.common.problems import ApiError
from services.common.submit import submit_job
from services.config import Settings
from services.models import CANCELLED, FAILED, SUCCEEDED, Tenant

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

PROBLEM: dict[str, Any] = {
    "description": "problem details",
    "content": {"application/problem+json": {"schema": {"$ref": "#/components/schemas/Problem"}}},
}
AUTH_ERRORS: dict[int | str, dict[str, Any]] = {401: PROBLEM}

IdempotencyKey = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        max_length=200,
        pattern=r"^[\x21-\x7e]+$",
        description="repeat a creation safely: the same key returns the same job",
    ),
]

UPLOAD_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["audio"],
                    "properties": {
                        "audio": {
                            "type": "string",
                            "format": "binary",
                            "description": "the song (WAV, FLAC, OGG, MP3, M4A …)",
                        },
                        "spec": {
                            "type": "string",
                            "description": "JSON text of a Spec object (components/schemas/Spec); default {}",
                        },
                    },
                }
            }
        },
    }
}


def _encode_cursor(cursor: tuple[datetime, str]) -> str:
    created, job_id = cursor
    raw = json.dumps([created.isoformat(), job_id]).encode()
    return base64.urlsafe_b64encode(raw).decode().rstrip("=")


def _decode_cursor(text: str) -> tuple[datetime, str]:
    try:
        raw = base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))
        created, job_id = json.loads(raw)
        if not jobs.is_id(job_id):
            raise ValueError("not an id")
        return datetime.fromisoformat(created), job_id
    except Exception as exc:
        raise ApiError(
            422, "cursor_invalid", "the cursor is not one this API returned", field="query.cursor"
        ) from exc


@router.post(
    "",
    status_code=202,
    response_model=JobOut,
    summary="Submit a song and a spec",
    openapi_extra=UPLOAD_BODY,
    responses={
        200: {
            "model": JobOut,
            "description": "idempotent replay: the job created earlier with this key",
        },
        400: PROBLEM,
        401: PROBLEM,
        409: PROBLEM,
        413: PROBLEM,
        415: PROBLEM,
        422: PROBLEM,
        503: PROBLEM,
    },
)
async def create_job(
    request: Request,
    idempotency_key: IdempotencyKey = None,
    tenant: Tenant = Depends(get_tenant),
    settings: Settings = Depends(get_settings_dep),
    store: ObjectStore = Depends(get_store),
    enqueue=Depends(get_enqueue),
    graphstore=Depends(get_graphstore),
):
    form = await read_multipart(request, settings, store, max_audio=1)
    try:
        spec = form_spec(form)
        parts = audio_parts(form)
        if len(parts) != 1:
            raise ApiError(
                422,
                "audio_multiple",
                "send one 'audio' part per job (use /v1/batches for many)",
                field="audio",
            )
        job, created = await run_in_threadpool(
            submit_job,
            settings,
            store,
            enqueue,
            tenant_id=tenant.id,
            spec=spec,
            upload=parts[0],
            idempotency_key=idempotency_key,
            graphstore=graphstore,
        )
    finally:
        form.discard()
    if created:
        metrics.JOBS_CREATED.inc()
        metrics.UPLOAD_BYTES.inc(job.audio_bytes or 0)
    body = jsonable_encoder(job_out(settings, job))
    return JSONResponse(
        body, status_code=202 if created else 200, headers={"Location": job_url(settings, job.id)}
    )


@router.get(
    "",
    response_model=JobPage,
    summary="List the tenant's jobs, newest first",
    responses={**AUTH_ERRORS, 422: PROBLEM},
)
def list_jobs(
    status: JobStatus | None = Query(None, description="only jobs in this state"),
    batch_id: str | None = Query(
        None, pattern=r"^[0-9a-fA-F-]{1,36}$", description="only jobs of this batch"
    ),
    cursor: str | None = Query(
        None, max_length=400, description="next_cursor of the previous page"
    ),
    limit: int = Query(50, ge=1, le=200),
    tenant: Tenant = Depends(get_tenant),
    db: Session = Depends(get_db),
    settings: Settings = Depends(get_settings_dep),
):
    after = _decode_cursor(cursor) if cursor else None
    rows, nxt = jobs.list_jobs(
        db, tenant.id, status=status, batch_id=batch_id, cursor=after, limit=limit
    )
    return JobPage(
        items=[job_out(settings, j) for j in rows], next_cursor=_encode_cursor(nxt) if nxt else None
    )


@router.get(
    "/{job_id}",
    response_model=JobOut,
    summary="Job status, progress and results",
    responses={**AUTH_ERRORS, 404: PROBLEM},
)
def get_job(
    job_id: str,
    tenant: Tenant = Depends(get_tenant),
    db: Session = Depends(get_db),
    settings: Settings = Depends(get_settings_dep),
):
    return job_out(settings, jobs.get_job_for_tenant(db, tenant.id, job_id))


@router.delete(
    "/{job_id}",
    response_model=JobOut,
    summary="Cancel a queued or running job",
    responses={**AUTH_ERRORS, 404: PROBLEM, 409: PROBLEM},
)
def cancel_job(
    job_id: str,
    tenant: Tenant = Depends(get_tenant),
    db: Session = Depends(get_db),
    settings: Settings = Depends(get_settings_dep),
):
    job = jobs.get_job_for_tenant(db, tenant.id, job_id)
    if job.status in (SUCCEEDED, FAILED):
        raise ApiError(
            409,
            "job_finished",
            f"job {job_id} already {job.status}; nothing to cancel",
            field="job_id",
        )
    if job.status != CANCELLED:
        jobs.cancel_job(db, tenant.id, job_id)
        db.commit()
        db.refresh(job)
    return job_out(settings, job)


def require_succeeded(job):
    """The job itself when it succeeded; 409 (job_failed, job_cancelled, job_not_finished) else."""
    job_id = job.id
    if job.status != SUCCEEDED:
        code = {"failed": "job_failed", "cancelled": "job_cancelled"}.get(
            job.status, "job_not_finished"
        )
        raise ApiError(
            409,
            code,
            f"job {job_id} is {job.status}; results exist only for succeeded jobs",
            field="job_id",
        )
    return job


_MEDIA = {
    "bvh": "text/plain; charset=utf-8",
    "fbx": "application/octet-stream",
    "glb": "model/gltf-binary",
    "usd": "application/octet-stream",  # USD's binary crate format
}


REDIRECT: dict[int | str, dict[str, Any]] = {
    307: {"description": "S3 store: the file at a presigned URL (Location)"}
}


_DOWNLOAD_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"content": {"application/octet-stream": {}, "text/plain": {}}},
    **REDIRECT,
    **AUTH_ERRORS,
    404: PROBLEM,
    409: PROBLEM,
    422: PROBLEM,
}


class ResultFiles:
    """The dependency of the download routes: the caller's tenant, the database, the store and
    the settings, and :meth:`serve`, which answers with one of a succeeded job's files."""

    def __init__(
        self,
        tenant: Tenant = Depends(get_tenant),
        db: Session = Depends(get_db),
        store: ObjectStore = Depends(get_store),
        settings: Settings = Depends(get_settings_dep),
    ):
        self.tenant, self.db, self.store, self.settings = tenant, db, store, settings

    def serve(
        self, job_id: str, name: str, what: str, suffix: str, field: str = "k", media: str = ""
    ) -> Response:
        """The tenant's job ``job_id``'s result file ``name`` as ``<job id><suffix>`` (media type
        ``media``, default by the suffix's extension): 404 ``result_not_found`` naming ``what``
        (``field``) when the job has no such file, 409 when the job did not succeed."""
        job = require_succeeded(jobs.get_job_for_tenant(self.db, self.tenant.id, job_id))
        key = jobs.result_files(self.store, job.id).get(name)
        if key is None:
            raise ApiError(404, "result_not_found", f"job {job.id} has no {what}", field=field)
        media = media or _MEDIA[suffix.rsplit(".", 1)[1]]
        return result_response(self.store, self.settings, key, f"{job.id}{suffix}", media)


@router.get(
    "/{job_id}/alternatives/{k}.rig.{fmt}",
    summary="Download alternative k on the job's rig (spec output.rig) as BVH, FBX, GLB or USD",
    response_class=FileResponse,
    responses=_DOWNLOAD_RESPONSES,
)
def download_alternative_on_rig(
    job_id: str,
    k: int = Path(..., ge=0, le=99, description="alternative index from 0"),
    fmt: Literal["bvh", "fbx", "glb", "usd"] = Path(..., description="file format"),
    results: ResultFiles = Depends(),
):
    what = f"alternative {k} on a rig as {fmt} (spec output.rig)"
    return results.serve(job_id, f"alternatives/{k}.rig.{fmt}", what, f"-{k}.rig.{fmt}")


def result_response(
    store: ObjectStore, settings: Settings, key: str, filename: str, media_type: str
) -> Response:
    """A stored file as the answer: a 307 redirect to a presigned URL where the store hands
    them out (S3: the bytes never pass through the API), else the file itself."""
    url = store.download_url(key, filename, media_type, settings.presigned_url_ttl_s)
    if url is not None:
        return RedirectResponse(url, status_code=307, headers={"Cache-Control": "no-store"})
    return FileResponse(store.local_path(key), media_type=media_type, filename=filename)


@router.get(
    "/{job_id}/alternatives/{k}.{fmt}",
    summary="Download alternative k as BVH, FBX or USD",
    response_class=FileResponse,
    responses=_DOWNLOAD_RESPONSES,
)
def download_alternative(
    job_id: str,
    k: int = Path(..., ge=0, le=99, description="alternative index from 0"),
    fmt: Literal["bvh", "fbx", "usd"] = Path(..., description="file format"),
    results: ResultFiles = Depends(),
):
    what = f"alternative {k} as {fmt}"
    return results.serve(job_id, f"alternatives/{k}.{fmt}", what, f"-{k}.{fmt}")


@router.get(
    "/{job_id}/alternatives/{k}/{partner}.rig.{fmt}",
    summary="Download one dancer of couple alternative k on its rig (output.rig for the lead, "
    "output.follow_rig for the follow) as BVH, GLB or (output.formats fbx) FBX",
    response_class=FileResponse,
    responses=_DOWNLOAD_RESPONSES,
)
def download_partner_on_rig(
    job_id: str,
    k: int = Path(..., ge=0, le=99, description="alternative index from 0"),
    partner: Literal["lead", "follow"] = Path(..., description="which dancer of the couple"),
    fmt: Literal["bvh", "glb", "fbx"] = Path(..., description="file format"),
    results: ResultFiles = Depends(),
):
    what = f"couple alternative {k}'s {partner} on a rig as {fmt}"
    name = f"alternatives/{k}/{partner}.rig.{fmt}"
    return results.serve(job_id, name, what, f"-{k}-{partner}.rig.{fmt}")


@router.get(
    "/{job_id}/alternatives/{k}/{partner}.{fmt}",
    summary="Download one dancer of couple alternative k (spec couple: true) as BVH or FBX "
    "(output.formats fbx), or both dancers as couple.glb or couple.fbx",
    response_class=FileResponse,
    responses=_DOWNLOAD_RESPONSES,
)
def download_partner(
    job_id: str,
    k: int = Path(..., ge=0, le=99, description="alternative index from 0"),
    partner: Literal["lead", "follow", "couple"] = Path(
        ..., description="lead or follow (BVH, FBX), or couple (GLB, FBX: both dancers)"
    ),
    fmt: Literal["bvh", "glb", "fbx"] = Path(..., description="file format"),
    results: ResultFiles = Depends(),
):
    what = f"couple alternative {k}'s {partner} as {fmt} (spec couple)"
    return results.serve(job_id, f"alternatives/{k}/{partner}.{fmt}", what, f"-{k}-{partner}.{fmt}")


@router.get(
    "/{job_id}/timeline.json",
    summary="Download the timeline (bars, phrases, chosen nodes, costs)",
    response_class=FileResponse,
    responses={
        200: {"content": {"application/json": {}}},
        **REDIRECT,
        **AUTH_ERRORS,
        404: PROBLEM,
        409: PROBLEM,
    },
)
def download_timeline(job_id: str, results: ResultFiles = Depends()):
    return results.serve(
        job_id, "timeline.json", "timeline", "-timeline.json", "job_id", "application/json"
    )
