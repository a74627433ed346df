"""Rigs: a tenant's own characters, which a job's dance is retargeted onto (``output.rig``)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response
from fastapi.concurrency import run_in_threadpool
from sqlalchemy.orm import Session

from dancegraph.store import ObjectStore
from services.api.deps import get_db, get_settings_dep, get_store, get_tenant
from services.api.forms import read_multipart
from services.api.routers.jobs import AUTH_ERRORS, PROBLEM
from services.api.schemas import RigList, RigOut
from services.common import rigs
from services.common.problems import ApiError
from services.config import Settings
from services.db import session_scope
from services.models import Rig, Tenant

router = APIRouter(prefix="/v1/rigs", tags=["rigs"])

RIG_UPLOAD = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["rig"],
                    "properties": {
                        "rig": {
                            "type": "string",
                            "format": "binary",
                            "description": "the rig: .fbx, .glb (or .gltf with embedded buffers), .bvh",
                        },
                        "mapping": {
                            "type": "string",
                            "description": "optional JSON object: humanoid role → joint name",
                        },
                    },
                }
            }
        },
    }
}


def rig_out(row: Rig) -> RigOut:
    s = row.summary or {}
    return RigOut(
        id=row.id,
        filename=row.filename,
        format=row.format,
        created_at=row.created_at,
        size_bytes=row.size_bytes,
        joints=s.get("joints", 0),
        root=s.get("root", ""),
        roles=s.get("roles", {}),
        how=s.get("how", {}),
        unmapped=s.get("unmapped", []),
        missing_optional=s.get("missing_optional", []),
        mapping=row.mapping or {},
        height_m=s.get("height_m", 0.0),
        mesh=s.get("mesh"),
        up_axis=s.get("up_axis"),
        unit_scale=s.get("unit_scale"),
        ancestors=s.get("ancestors"),
    )


def _upload(settings: Settings, store: ObjectStore, tenant_id: str, form) -> RigOut:
    parts = form.files_named("rig")
    if len(parts) != 1:
        raise ApiError(422, "rig_missing", "send exactly one 'rig' file part", field="rig")
    raw = form.text("mapping")
    files = form.files_named("mapping")
    if raw is None and files:
        raw = files[0].read_text(rigs.MAX_MAPPING_BYTES + 1)
    mapping = rigs.parse_mapping(raw)
    limits = rigs.rig_limits(settings)
    key = None
    try:
        with session_scope(settings.database_url) as session:
            row = rigs.register_rig(session, store, tenant_id, parts[0], mapping, limits)
            key = row.file_key
            out = rig_out(row)
    except BaseException:
        if key is not None:  # stored, but the row was not committed
            rigs.discard_rig_file(store, key)
        raise
    return out


@router.post(
    "",
    status_code=201,
    response_model=RigOut,
    summary="Upload a rig (FBX, GLB, BVH); its humanoid roles are found and checked now",
    openapi_extra=RIG_UPLOAD,
    responses={**AUTH_ERRORS, 413: PROBLEM, 415: PROBLEM, 422: PROBLEM, 503: PROBLEM},
)
async def create_rig(
    request: Request,
    response: Response,
    tenant: Tenant = Depends(get_tenant),
    settings: Settings = Depends(get_settings_dep),
    store: ObjectStore = Depends(get_store),
):
    form = await read_multipart(request, settings, store, max_audio=1)
    try:
        out = await run_in_threadpool(_upload, settings, store, tenant.id, form)
    finally:
        form.discard()
    response.headers["Location"] = f"/v1/rigs/{out.id}"
    return out


@router.get("", response_model=RigList, summary="The tenant's rigs", responses=AUTH_ERRORS)
def list_rigs(tenant: Tenant = Depends(get_tenant), db: Session = Depends(get_db)):
    return RigList(items=[rig_out(r) for r in rigs.list_rigs(db, tenant.id)])


def _found(db: Session, tenant: Tenant, rig_id: str) -> Rig:
    row = rigs.find_rig(db, tenant.id, rig_id) if len(rig_id) <= 36 else None
    if row is None:
        raise ApiError(404, "unknown_rig", f"no rig {rig_id!r}", field="rig_id")
    return row


@router.get(
    "/{rig_id}",
    response_model=RigOut,
    summary="One rig with the mapping found on it",
    responses={**AUTH_ERRORS, 404: PROBLEM},
)
def get_rig(rig_id: str, tenant: Tenant = Depends(get_tenant), db: Session = Depends(get_db)):
    return rig_out(_found(db, tenant, rig_id))


@router.delete(
    "/{rig_id}",
    status_code=204,
    summary="Delete a rig (jobs already rendered on it keep their files)",
    responses={**AUTH_ERRORS, 404: PROBLEM},
)
def delete_rig(
    rig_id: str,
    tenant: Tenant = Depends(get_tenant),
    db: Session = Depends(get_db),
    store: ObjectStore = Depends(get_store),
):
    rigs.delete_rig(db, store, _found(db, tenant, rig_id))
    db.commit()
    return Response(status_code=204)
