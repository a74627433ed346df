"""The preview page of a succeeded job and the data it loads (song, timeline, poses).

Each route takes the job's API key (``X-API-Key`` / Bearer) like every other job route, or the
signed ``?token=`` of the job's ``preview_url`` (``services.api.preview_tokens``): a browser
opening a link cannot send a header (``services.api.deps.get_tenant_or_preview_token``). The
page's data URLs always carry a fresh token. Pose tracks are computed once per BVH and kept
under ``jobs/<id>/preview/`` (``services.preview_server.pose_json_gz``); the JSON routes answer
gzip-encoded when the client accepts it.
"""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import FileResponse, HTMLResponse
from sqlalchemy.orm import Session

from dancegraph.errors import NotFoundError
from dancegraph.render import TIMELINE
from dancegraph.store import ObjectStore
from services import jobs
from services.api.deps import get_db, get_settings_dep, get_store, get_tenant_or_preview_token
from services.api.preview_tokens import make_token
from services.api.routers.jobs import PROBLEM, require_succeeded, result_response
from services.api.views import job_url
from services.common.problems import ApiError
from services.config import Settings
from services.models import Job, Tenant
from services.preview_server import (
    audio_media_type,
    couple_pose_file,
    json_bytes_response,
    json_response,
    pose_file,
    pose_json_gz,
    render_page,
    rig_unit_scale,
)

router = APIRouter(prefix="/v1/jobs", tags=["preview"])

ERRORS: dict[int | str, dict[str, Any]] = {401: PROBLEM, 404: PROBLEM, 409: PROBLEM}
JSON_OK: dict[int | str, dict[str, Any]] = {200: {"content": {"application/json": {}}}}


def preview_job(
    job_id: str,
    tenant: Tenant | None = Depends(get_tenant_or_preview_token),
    db: Session = Depends(get_db),
) -> Job:
    """The succeeded job: the tenant's (API key) or the one the preview token was made for."""
    if tenant is not None:
        return require_succeeded(jobs.get_job_for_tenant(db, tenant.id, job_id))
    job = jobs.get_job(db, job_id) if jobs.is_id(job_id) else None
    if job is None:
        raise NotFoundError(f"no job {job_id!r}", code="job_not_found", field="job_id")
    return require_succeeded(job)


def pose_cache_prefix(job_id: str) -> str:
    """Where a job's computed pose tracks are kept: next to its result, gone with it."""
    return jobs.result_key(job_id, "preview")


def _alternatives(store: ObjectStore, job: Job) -> tuple[int, bool, bool, bool]:
    """How many alternatives the job has (library ``<k>.bvh``, or a couple's
    ``<k>/lead.bvh``), whether they are on a rig, whether as the rig's character too
    (``<k>.rig.glb``), and whether it is a couple (the rig views are offered for solo jobs)."""
    files = jobs.result_files(store, job.id)
    n_couple = sum(1 for k in range(100) if couple_pose_file(k, "lead") in files)
    if n_couple:
        return n_couple, False, False, True
    on_rig = bool(jobs.bvh_files(store, job.id, rig=True))
    models = on_rig and "alternatives/0.rig.glb" in files
    return len(jobs.bvh_files(store, job.id)), on_rig, models, False


@router.get(
    "/{job_id}/preview",
    summary="Preview page: the dance on the song in the browser",
    response_class=HTMLResponse,
    responses={**ERRORS, 503: PROBLEM},
)
def preview_page(
    job: Job = Depends(preview_job),
    settings: Settings = Depends(get_settings_dep),
    store: ObjectStore = Depends(get_store),
):
    n_alternatives, on_rig, models, couple = _alternatives(store, job)
    if not n_alternatives:
        raise ApiError(
            404, "result_not_found", f"job {job.id} has no dance to show", field="job_id"
        )
    q = f"?token={make_token(settings, job.id)}"
    base = job_url(settings, job.id, "/preview")
    lead = "&partner=lead" if couple else ""
    return render_page(
        title=job.audio_filename or job.id,
        audio=f"{base}/audio{q}",
        timeline=f"{base}/timeline.json{q}",
        poses=[f"{base}/poses/{k}.json{q}{lead}" for k in range(n_alternatives)],
        follow_poses=[f"{base}/poses/{k}.json{q}&partner=follow" for k in range(n_alternatives)]
        if couple
        else None,
        assets=f"{settings.public_base_url}/preview-static",
        rig_poses=[f"{base}/poses/{k}.json{q}&skeleton=rig" for k in range(n_alternatives)]
        if on_rig
        else None,
        rig_models=[f"{base}/rig/{k}.glb{q}" for k in range(n_alternatives)] if models else None,
    )


@router.get(
    "/{job_id}/preview/audio",
    summary="The job's song, for the preview page",
    response_class=FileResponse,
    responses={200: {"content": {"audio/*": {}}}, **ERRORS},
)
def preview_audio(
    job: Job = Depends(preview_job),
    store: ObjectStore = Depends(get_store),
    settings: Settings = Depends(get_settings_dep),
):
    if not store.exists(job.audio_key):
        raise ApiError(404, "result_not_found", f"job {job.id} has no stored song", field="job_id")
    media = audio_media_type(job.audio_format or job.audio_filename)
    return result_response(store, settings, job.audio_key, job.audio_filename or "audio", media)


@router.get(
    "/{job_id}/preview/timeline.json",
    summary="The timeline, for the preview page",
    responses={**JSON_OK, **ERRORS},
)
def preview_timeline(
    request: Request, job: Job = Depends(preview_job), store: ObjectStore = Depends(get_store)
):
    key = jobs.result_files(store, job.id).get(TIMELINE)
    if key is None:
        raise ApiError(404, "result_not_found", f"job {job.id} has no timeline", field="job_id")
    return json_bytes_response(request, store.get_bytes(key))


@router.get(
    "/{job_id}/preview/rig/{k}.glb",
    summary="Alternative k on the job's rig as GLB (the character the preview page draws)",
    response_class=FileResponse,
    responses={200: {"content": {"model/gltf-binary": {}}}, **ERRORS},
)
def preview_rig_model(
    k: int = Path(..., ge=0, le=99, description="alternative index from 0"),
    job: Job = Depends(preview_job),
    store: ObjectStore = Depends(get_store),
    settings: Settings = Depends(get_settings_dep),
):
    key = jobs.result_files(store, job.id).get(f"alternatives/{k}.rig.glb")
    if key is None:
        raise ApiError(404, "result_not_found", f"no alternative {k} on a rig", field="k")
    return result_response(store, settings, key, f"{job.id}-{k}.rig.glb", "model/gltf-binary")


@router.get(
    "/{job_id}/preview/poses/{k}.json",
    summary="World joint positions of alternative k (of a couple: one dancer) per frame",
    responses={**JSON_OK, **ERRORS, 422: PROBLEM},
)
def preview_poses(
    request: Request,
    k: int = Path(..., ge=0, le=99, description="alternative index from 0"),
    skeleton: Literal["library", "rig"] = Query(
        "library", description="the motion library's skeleton, or the job's rig (output.rig)"
    ),
    partner: Literal["lead", "follow"] | None = Query(
        None, description="a couple job's dancer (alternatives/<k>/<partner>.bvh)"
    ),
    job: Job = Depends(preview_job),
    store: ObjectStore = Depends(get_store),
):
    files = jobs.result_files(store, job.id)
    name = pose_file(k, skeleton, partner)
    key = files.get(name)
    if key is None:
        raise ApiError(404, "result_not_found", f"no alternative {k} ({name})", field="k")
    scale = 1.0
    if skeleton == "rig" and TIMELINE in files:
        scale = rig_unit_scale(store.local_path(files[TIMELINE]), k, partner)
    gz = pose_json_gz(store.local_path(key), k, store, pose_cache_prefix(job.id), scale=scale)
    return json_response(request, gz)
