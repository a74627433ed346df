"""Database rows → response models (one place, shared by the jobs and batches routers)."""

from __future__ import annotations

from collections import Counter

from services.api.preview_tokens import make_token
from services.api.schemas import AlternativeOut, AudioOut, BatchOut, ErrorOut, JobOut, WebhookOut
from services.config import Settings
from services.models import FINAL_STATUSES, QUEUED, SUCCEEDED, WEBHOOK_NONE, Batch, Job


def job_url(settings: Settings, job_id: str, suffix: str = "") -> str:
    return f"{settings.public_base_url}/v1/jobs/{job_id}{suffix}"


def _alternatives(settings: Settings, job: Job) -> list[AlternativeOut]:
    result = job.result or {}
    alts = result.get("alternatives") or []
    files = result.get("files")
    formats = (job.spec.get("output") or {}).get("formats") or ["bvh", "fbx"]
    out = []
    for k, alt in enumerate(alts):
        alt = alt if isinstance(alt, dict) else {}
        downloads = {}
        if job.status == SUCCEEDED:
            for fmt in ("bvh", "fbx"):
                name = f"alternatives/{k}.{fmt}"
                if (files is not None and name in files) or (files is None and fmt in formats):
                    downloads[fmt] = job_url(settings, job.id, f"/alternatives/{k}.{fmt}")
        cost = alt.get("cost")
        out.append(
            AlternativeOut(
                index=k,
                cost=float(cost) if isinstance(cost, int | float) else None,
                bars=len(alt["nodes"]) if isinstance(alt.get("nodes"), list) else None,
                violations=alt.get("violations") or [],
                downloads=downloads,
            )
        )
    return out


def job_out(settings: Settings, job: Job) -> JobOut:
    result = job.result or {}
    error = None
    if job.error_code:
        error = ErrorOut(
            code=job.error_code, message=job.error_message or "", field=job.error_field
        )
    webhook = None
    if job.webhook_status != WEBHOOK_NONE:
        webhook = WebhookOut(
            status=job.webhook_status,
            attempts=job.webhook_attempts,
            last_error=job.webhook_last_error,
            delivered_at=job.webhook_delivered_at,
        )
    files = result.get("files")
    has_timeline = job.status == SUCCEEDED and (files is None or "timeline.json" in files)
    return JobOut(
        id=job.id,
        url=job_url(settings, job.id),
        status=job.status,
        stage=job.stage,
        progress=round(float(job.progress or 0.0), 1),
        batch_id=job.batch_id,
        created_at=job.created_at,
        updated_at=job.updated_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
        attempts=job.attempts,
        audio=AudioOut(
            filename=job.audio_filename,
            sha256=job.audio_sha256,
            bytes=job.audio_bytes,
            container=job.audio_format,
            duration_s=job.audio_duration_s,
        ),
        spec=job.spec,
        analysis=job.analysis_summary,
        alternatives=_alternatives(settings, job),
        constraint_report=result.get("constraint_report") or result.get("report"),
        timeline_url=job_url(settings, job.id, "/timeline.json") if has_timeline else None,
        preview_url=job_url(settings, job.id, f"/preview?token={make_token(settings, job.id)}")
        if has_timeline
        else None,
        error=error,
        webhook=webhook,
    )


def batch_out(settings: Settings, batch: Batch, jobs: list[Job]) -> BatchOut:
    counts = Counter(j.status for j in jobs)
    if jobs and all(j.status in FINAL_STATUSES for j in jobs):
        status = "completed"
    elif all(j.status == QUEUED for j in jobs):
        status = "queued"
    else:
        status = "running"
    return BatchOut(
        id=batch.id,
        url=f"{settings.public_base_url}/v1/batches/{batch.id}",
        status=status,
        created_at=batch.created_at,
        spec=batch.spec,
        counts=dict(counts),
        jobs=[job_out(settings, j) for j in jobs],
    )
