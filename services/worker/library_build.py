"""A library version's import and graph build, behind the ``dancegraph.import_library`` task.

``run_import(row_id)``: claim the version's row (``libraries.claim``), copy its uploaded files
into a scratch folder, then in the sandbox (``dancegraph.sandbox.run_sandboxed``: a child under
memory, CPU and wall-clock limits) open the archive safely, read the manifest and import the
takes (``dancegraph.motion.dataset.import_dataset``, strict: any failed take fails the import,
each take's code in the report); then build the graph (``build_dataset_graph``) under the
version's own graph name and mark the row ``succeeded`` last: until then no job can use it,
and the previous version keeps serving. A re-run after a crash starts over on the same graph
name (the import writes a fresh data folder, the build a content-named version), so the task is
idempotent; the reaper requeues a version whose worker stopped beating.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tarfile
import time
import zipfile
from pathlib import Path, PurePosixPath

from dancegraph.errors import DanceGraphError
from dancegraph.store import ObjectStore, open_store
from services.common import libraries
from services.config import Settings, get_settings
from services.config import object_store as settings_store
from services.db import session_scope
from services.worker import state

log = logging.getLogger("dancegraph.worker")

PROGRESS_FILE = "progress.json"


class ArchiveError(DanceGraphError):
    """An uploaded archive refused before anything was extracted (codes ``archive_*``)."""

    code = "archive_invalid"
    status = 422


def run_task(task, row_id: int) -> None:
    """The ``dancegraph.import_library`` task body under the tasks' failure policy
    (``services.worker.tasks``): the upload's fault is recorded by ``run_import``; a transient
    error requeues the version and retries the task with backoff (``service_unavailable`` once
    the retries are spent); the soft time limit fails it with ``job_timeout``; a bug with
    ``internal_error``."""
    from celery.exceptions import SoftTimeLimitExceeded

    from services.worker.tasks import MAX_RETRIES, is_transient, retry_delay

    try:
        run_import(row_id)
    except SoftTimeLimitExceeded:
        _fail(row_id, "job_timeout", "the import ran past its time limit")
    except Exception as exc:
        if is_transient(exc) and task.request.retries < MAX_RETRIES:
            log.warning(
                "transient error; retrying", extra={"dataset_row": row_id, "error": str(exc)}
            )
            with session_scope() as session:
                libraries.requeue(session, row_id)
            raise task.retry(countdown=retry_delay(task.request.retries), exc=exc) from exc
        if is_transient(exc):
            _fail(
                row_id,
                "service_unavailable",
                f"a service stayed unavailable ({type(exc).__name__})",
            )
        else:
            log.exception("internal error in a library import")
            _fail(row_id, "internal_error", "an internal error stopped the import (see the logs)")


def _failed_takes(exc: DanceGraphError) -> dict | None:
    """The report of an import refused take by take (``dataset_takes_failed``'s ``errors``)."""
    if not exc.errors:
        return None
    failed = [
        {"file": e.get("field") or "", "code": e.get("code"), "error": e.get("message")}
        for e in exc.errors
    ]
    return {"clips": [], "failed": failed, "warnings": []}


def _fail(
    row_id: int, code: str, message: str, field: str | None = None, report: dict | None = None
) -> None:
    try:
        with session_scope() as session:
            libraries.fail(session, row_id, code, message, field, report)
    except Exception:  # the reaper fails or requeues it from the row later
        log.exception("could not record the import's failure")


def run_import(row_id: int, settings: Settings | None = None) -> str:
    """Import and build one library version; returns 'succeeded', 'failed' (the upload's
    fault: a DanceGraphError, recorded on the row with its code and each failed take's, and
    what the version had stored removed) or 'skipped' (not ours: final, deleted, or held by a
    live worker). Other errors are raised (the task retries transient ones)."""
    settings = settings or get_settings()
    store = settings_store(settings)
    worker = state.worker_name()
    with session_scope() as session:
        row = libraries.claim(session, row_id, worker, stale_after_s=settings.job_timeout_s)
        if row is None:
            return "skipped"
        graph_name, upload, version = row.graph_name, dict(row.upload or {}), row.version
    assert graph_name is not None
    scratch = store.temp_dir(f"library-{row_id}")
    try:
        report, built = _work(settings, store, row_id, worker, graph_name, upload, scratch)
    except DanceGraphError as exc:
        if getattr(exc, "status", 400) == 503:
            raise  # a service is down, not the upload at fault: the task retries
        log.info("library import failed", extra={"dataset_row": row_id, "error_code": exc.code})
        _fail(row_id, exc.code, exc.message, exc.field, _failed_takes(exc))
        for prefix in (f"datasets/{graph_name}", f"graphs/{graph_name}"):
            store.delete_prefix(prefix)
        store.delete_prefix(libraries.upload_prefix(version))
        return "failed"
    except state.JobCancelled:
        log.info(
            "library import no longer ours (deleted, taken over)", extra={"dataset_row": row_id}
        )
        return "skipped"
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    with session_scope() as session:
        ok = libraries.succeed(
            session,
            row_id,
            graph_key=built["key"],
            report={**report, "graph": _graph_summary(built)},
            stats={"nodes": built["nodes"], "edges": built["edges"], "takes": len(report["clips"])},
            licence=str(report.get("licence") or ""),
        )
    log.info("library built", extra={"dataset_row": row_id, "graph": graph_name, "published": ok})
    return "succeeded"


def _work(
    settings: Settings,
    store: ObjectStore,
    row_id: int,
    worker: str,
    graph_name: str,
    upload: dict,
    scratch: Path,
) -> tuple[dict, dict]:
    """Fetch, import (sandboxed) and build under a heartbeat that also carries the stage and
    percent the sandboxed child writes; ``(import report with seconds per phase, build)``.
    Raises ``state.JobCancelled`` once the version is no longer ours."""
    progress = scratch / PROGRESS_FILE

    def beat() -> bool:
        os.utime(scratch)  # in use: the reaper's scratch sweep keeps it
        stage, percent = _read_progress(progress)
        with session_scope() as session:
            return libraries.beat(session, row_id, worker, stage, percent)

    def stage(name: str) -> None:  # a new phase is shown at once, not at the next heartbeat
        _stage(progress, name, libraries.STAGES[name])
        beat()

    interval = state.heartbeat_interval(settings.job_timeout_s)
    with state.Heartbeat(str(row_id), interval, beat) as hb:
        stage("fetch")
        t0 = time.perf_counter()
        src, archive = _fetch(store, upload, scratch)
        t1 = time.perf_counter()
        report = _import(settings, store, graph_name, src, archive, upload, progress)
        hb.check()
        stage("build")
        t2 = time.perf_counter()
        built = _build(store, graph_name)
        hb.check()
        report["seconds"] = {
            "fetch": round(t1 - t0, 2),
            "import": round(t2 - t1, 2),
            "build": round(time.perf_counter() - t2, 2),
        }
        _stage(progress, "publish", libraries.STAGES["publish"])
        if not beat():
            raise state.JobCancelled(str(row_id))
    return report, built


def _stage(progress: Path, stage: str, percent: float) -> None:
    progress.write_text(json.dumps({"stage": stage, "progress": percent}))


def _read_progress(progress: Path) -> tuple[str | None, float | None]:
    try:
        data = json.loads(progress.read_text())
        return data.get("stage"), data.get("progress")
    except (OSError, ValueError):
        return None, None


def _fetch(store: ObjectStore, upload: dict, scratch: Path) -> tuple[Path, Path | None]:
    """The uploaded files copied into ``scratch/src`` under their names (an archive beside it)."""
    src = scratch / "src"
    src.mkdir()
    archive = None
    for f in upload.get("files", []):
        name = PurePosixPath(f["name"]).name  # checked at upload; never a path here
        if f["role"] == "archive":
            archive = scratch / ("upload" + _archive_suffix(name))
            shutil.copyfile(store.local_path(f["key"]), archive)
        else:
            shutil.copyfile(store.local_path(f["key"]), src / name)
    return src, archive


def _archive_suffix(name: str) -> str:
    low = name.lower()
    return next(
        s for s in sorted(libraries.ARCHIVE_SUFFIXES, key=len, reverse=True) if low.endswith(s)
    )


def _import(
    settings: Settings,
    store: ObjectStore,
    graph_name: str,
    src: Path,
    archive: Path | None,
    upload: dict,
    progress: Path,
) -> dict:
    """The sandboxed part: the archive opened, the manifest read, the takes imported."""
    from dancegraph.sandbox import SandboxError, SandboxLimits, run_sandboxed

    limits = SandboxLimits(
        memory_bytes=settings.library_sandbox_memory_bytes,
        cpu_seconds=settings.library_sandbox_cpu_s,
        wall_seconds=settings.library_sandbox_wall_s,
    )
    caps = {
        "max_bytes": settings.library_archive_max_bytes,
        "max_ratio": settings.library_archive_max_ratio,
        "max_members": settings.library_archive_max_members,
        "max_takes": settings.library_max_takes,
        "max_minutes": settings.library_max_minutes,
    }
    where = {"url": settings.store_url or settings.store_root, "scratch": settings.store_root}
    try:
        return run_sandboxed(
            import_upload,
            where,
            graph_name,
            str(src),
            str(archive) if archive else None,
            upload.get("manifest"),
            caps,
            str(progress),
            limits=limits,
        )
    except SandboxError as exc:
        store.delete_prefix(f"datasets/{graph_name}")  # what the killed child wrote
        raise DanceGraphError(
            f"the import stopped: {exc.message}", code=f"import_{exc.code}", field="takes"
        ) from None


def import_upload(
    where: dict,
    graph_name: str,
    src: str,
    archive: str | None,
    manifest: dict | None,
    caps: dict,
    progress: str,
) -> dict:
    """In the sandbox child: extract ``archive`` into ``src`` (checked first), find the manifest
    (the uploaded one, else ``manifest.yaml|yml|json`` in the upload), check the take count, and
    import strictly; returns the import report (``ImportReport.to_dict()`` plus ``licence``).
    Raises ``ArchiveError``, ``DanceGraphError`` (``library_too_many_takes``,
    ``library_too_long``, ``manifest_invalid``, ``dataset_takes_failed`` with each take's code
    in ``errors``...)."""
    from dancegraph.motion.dataset import import_dataset, load_manifest, parse_manifest

    folder = Path(src)
    if archive is not None:
        extract_archive(Path(archive), folder, caps)
        folder = _single_root(folder)
    if manifest is None:
        found = [
            folder / n
            for n in ("manifest.yaml", "manifest.yml", "manifest.json")
            if (folder / n).is_file()
        ]
        manifest = load_manifest(found[0]) if found else {}
    parsed = parse_manifest(manifest)
    takes = [p for p in folder.iterdir() if p.suffix.lower() in libraries.TAKE_SUFFIXES]
    if len(takes) > caps["max_takes"]:
        raise DanceGraphError(
            f"{len(takes)} takes; at most {caps['max_takes']} per library",
            code="library_too_many_takes",
            field="takes",
        )
    store = open_store(where["url"], where["scratch"])
    out = Path(progress)

    def on_take(done: int, total: int, _name: str) -> None:
        span = libraries.STAGES["build"] - libraries.STAGES["import"]
        out.write_text(
            json.dumps(
                {
                    "stage": "import",
                    "progress": libraries.STAGES["import"] + span * done / max(1, total),
                }
            )
        )

    try:
        report = import_dataset(folder, graph_name, store, manifest, on_take, strict=True).to_dict()
    except DanceGraphError as exc:
        raise _without_paths(exc, folder) from None
    minutes = sum(c["duration_s"] for c in report["clips"]) / 60.0
    if minutes > caps["max_minutes"]:
        store.delete_prefix(f"datasets/{graph_name}")
        raise DanceGraphError(
            f"{minutes:.1f} minutes of takes; at most {caps['max_minutes']:g} per library",
            code="library_too_long",
            field="takes",
        )
    report["licence"] = parsed.licence
    return report


def _without_paths(exc: DanceGraphError, folder: Path) -> DanceGraphError:
    """``exc`` with the worker's scratch folder taken out of its message and field (a user
    sees the names of the files it sent, never the worker's paths)."""

    def strip(text: str | None) -> str | None:
        return text and text.replace(f"{folder}/", "").replace(str(folder), "the upload")

    exc.message = strip(exc.message) or ""
    exc.args = (exc.message,)
    exc.field = strip(exc.field)
    return exc


def extract_archive(archive: Path, dest: Path, caps: dict) -> None:
    """Extract a zip or tar into ``dest`` after checking every member first: no absolute or
    parent-relative names, no links or devices, at most ``max_members`` members, a total
    uncompressed size of at most ``max_bytes`` and (zip) no member compressed more than
    ``max_ratio`` times. Raises ``ArchiveError`` (``archive_unreadable``,
    ``archive_path_unsafe``, ``archive_link``, ``archive_too_many_members``, ``archive_bomb``)."""
    if zipfile.is_zipfile(archive):
        _extract_zip(archive, dest, caps)
        return
    try:
        with tarfile.open(archive, "r:*") as tar:
            members = tar.getmembers()
            _check_members([(m.name, m.size, None, m.isfile() or m.isdir()) for m in members], caps)
            for m in members:
                if m.isfile():
                    target = dest / _safe_path(m.name)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    with tar.extractfile(m) as fh, open(target, "wb") as out:  # type: ignore[union-attr]
                        _copy_bounded(fh, out, m.size)
    except (tarfile.TarError, EOFError, OSError) as exc:
        raise ArchiveError(
            f"the archive cannot be read: {exc}", code="archive_unreadable", field="archive"
        ) from None


def _extract_zip(archive: Path, dest: Path, caps: dict) -> None:
    try:
        with zipfile.ZipFile(archive) as zf:
            infos = zf.infolist()
            rows: list[tuple[str, int, int | None, bool]] = []
            for i in infos:
                is_link = (i.external_attr >> 16) & 0o170000 == 0o120000
                rows.append((i.filename, i.file_size, i.compress_size, not is_link))
            _check_members(rows, caps)
            for i in infos:
                if not i.is_dir():
                    target = dest / _safe_path(i.filename)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    with zf.open(i) as fh, open(target, "wb") as out:
                        _copy_bounded(fh, out, i.file_size)
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        EOFError,
        OSError,
        NotImplementedError,
    ) as exc:
        raise ArchiveError(
            f"the archive cannot be read: {exc}", code="archive_unreadable", field="archive"
        ) from None


def _check_members(rows: list[tuple[str, int, int | None, bool]], caps: dict) -> None:
    """``(name, size, compressed size or None, regular)`` of every member, checked."""
    if len(rows) > caps["max_members"]:
        raise ArchiveError(
            f"{len(rows)} members; at most {caps['max_members']}",
            code="archive_too_many_members",
            field="archive",
        )
    total = 0
    for name, size, packed, regular in rows:
        _safe_path(name)
        if not regular:
            raise ArchiveError(
                f"{name!r} is a link or a device", code="archive_link", field="archive"
            )
        total += size
        if packed is not None and size > 1024 * 1024 and size > caps["max_ratio"] * max(1, packed):
            raise ArchiveError(
                f"{name!r} expands {size / max(1, packed):.0f} times (at most {caps['max_ratio']:g})",
                code="archive_bomb",
                field="archive",
            )
    if total > caps["max_bytes"]:
        raise ArchiveError(
            f"the archive expands to {total} bytes (at most {caps['max_bytes']})",
            code="archive_bomb",
            field="archive",
        )


def _safe_path(name: str) -> PurePosixPath:
    """A member name as a relative path inside the extraction folder; ``archive_path_unsafe``
    for an absolute name, a drive, a backslash path or a '..' segment."""
    path = PurePosixPath(name)
    if (
        not name
        or path.is_absolute()
        or "\\" in name
        or ":" in path.parts[0]
        or any(p == ".." for p in path.parts)
        or "\x00" in name
    ):
        raise ArchiveError(
            f"member name {name!r} points outside the archive",
            code="archive_path_unsafe",
            field="archive",
        )
    return path


def _copy_bounded(src, dst, size: int) -> None:
    """Copy at most ``size`` bytes (the size the member declared); more is a lying header."""
    left = size
    while chunk := src.read(min(1 << 20, left + 1)):
        left -= len(chunk)
        if left < 0:
            raise ArchiveError(
                "a member is larger than it declares", code="archive_bomb", field="archive"
            )
        dst.write(chunk)


def _single_root(folder: Path) -> Path:
    """The folder holding the takes: ``folder`` itself, or its one subfolder when the archive
    wrapped everything in one."""
    entries = [p for p in folder.iterdir() if not p.name.startswith(".")]
    if len(entries) == 1 and entries[0].is_dir():
        return entries[0]
    return folder


def _build(store: ObjectStore, graph_name: str) -> dict:
    """The version's graph, built and published under its own graph name."""
    from dancegraph.graph.build import build_dataset_graph

    return build_dataset_graph(store, graph_name)


def _graph_summary(built: dict) -> dict:
    return {k: built.get(k) for k in ("key", "version", "nodes", "edges", "seconds", "embedding")}


def reap(settings: Settings) -> dict[str, list]:
    """The reaper's sweep over library versions (as over jobs, ``services.worker.reaper``):
    a running import whose heartbeat is older than ``job_timeout_s`` counts a crash and is
    requeued (failed ``worker_lost`` at ``job_max_attempts`` crashes); a queued one untouched
    that long is sent again when the analysis queue holds fewer messages (a broker restart
    lost it); deleted versions no live job pins are removed. Returns the row ids (and graph
    names removed) per action."""
    from services.config import QUEUE_ANALYSIS
    from services.models import utcnow
    from services.worker import enqueue

    now = utcnow()
    out: dict[str, list] = {"requeued": [], "failed": [], "reenqueued": [], "purged": []}
    with session_scope() as session:
        for row in libraries.stuck(session, settings.job_timeout_s, now):
            row.crashes = (row.crashes or 0) + 1
            if row.crashes >= settings.job_max_attempts:
                libraries.fail(
                    session,
                    row.id,
                    "worker_lost",
                    f"the import's worker stopped {row.crashes} times",
                )
                out["failed"].append(row.id)
            elif libraries.requeue(session, row.id):
                out["requeued"].append(row.id)
        waiting = libraries.waiting(session, settings.job_timeout_s, now)
        held = enqueue.queue_size(QUEUE_ANALYSIS) if waiting else None
        if waiting and (held is None or held < len(waiting)):
            for row_id in waiting:
                libraries.requeue_waiting(session, row_id, now)
            out["reenqueued"] = waiting
        out["purged"] = libraries.purge_deleted(
            session, settings_store(settings), settings.job_timeout_s
        )
    for row_id in out["requeued"] + out["reenqueued"]:
        enqueue.requeue_library(row_id)
    return out
