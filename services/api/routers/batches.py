"""Batches: many songs, one spec."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.encoders import jsonable_encoder
from fastapi.responses import JSONResponse
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
from services.api.routers.jobs import PROBLEM, IdempotencyKey
from services.api.schemas import BatchOut
from services.api.views import batch_out
from services.common.submit import submit_batch
from services.config import Settings
from services.models import Tenant

router = APIRouter(prefix="/v1/batches", tags=["batches"])

BATCH_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["audio"],
                    "properties": {
                        "audio": {
                            "type": "array",
                            "items": {"type": "string", "format": "binary"},
                            "description": "one part per song",
                        },
                        "spec": {
                            "type": "string",
                            "description": "JSON text of a Spec, applied to every song",
                        },
                    },
                }
            }
        },
    }
}


@router.post(
    "",
    status_code=202,
    response_model=BatchOut,
    summary="Submit many songs with one spec",
    openapi_extra=BATCH_BODY,
    responses={
        200: {"model": BatchOut, "description": "idempotent replay"},
        400: PROBLEM,
        401: PROBLEM,
        409: PROBLEM,
        413: PROBLEM,
        415: PROBLEM,
        422: PROBLEM,
        503: PROBLEM,
    },
)
async def create_batch(
    request: Request,
    idempotency_key: IdempotencyKey = None,
    tenant: Tenant = Depends(get_tenant),
    settings: Settings = Depends(get_settings_dep),
    store: ObjectStore = Depends(get_store),
    enqueue=Depends(get_enqueue),
    graphstore=Depends(get_graphstore),
):
    form = await read_multipart(request, settings, store, max_audio=settings.max_batch_items)
    try:
        spec = form_spec(form)
        parts = audio_parts(form)
        batch, rows, created = await run_in_threadpool(
            submit_batch,
            settings,
            store,
            enqueue,
            tenant_id=tenant.id,
            spec=spec,
            uploads=parts,
            idempotency_key=idempotency_key,
            graphstore=graphstore,
        )
    finally:
        form.discard()
    if created:
        metrics.JOBS_CREATED.inc(len(rows))
        metrics.UPLOAD_BYTES.inc(sum(j.audio_bytes or 0 for j in rows))
    body = batch_out(settings, batch, rows)
    return JSONResponse(
        jsonable_encoder(body), status_code=202 if created else 200, headers={"Location": body.url}
    )


@router.get(
    "/{batch_id}",
    response_model=BatchOut,
    summary="Batch status and its jobs",
    responses={401: PROBLEM, 404: PROBLEM},
)
def get_batch(
    batch_id: str,
    tenant: Tenant = Depends(get_tenant),
    db: Session = Depends(get_db),
    settings: Settings = Depends(get_settings_dep),
):
    batch = jobs.get_batch_for_tenant(db, tenant.id, batch_id)
    return batch_out(settings, batch, jobs.batch_jobs(db, batch.id))
