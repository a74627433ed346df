"""Motion libraries as a tenant resource: names, visibility, upload checks, versions and their
import-and-build lifecycle. Shared by the API (upload, list, delete), the worker (claim,
progress, publish) and the reaper (stuck builds, deleted versions).

- A library is a name; each upload under it is a new *version*: one ``datasets`` row, which is
  also the import-and-build job of that version (queued → running → succeeded | failed, lease,
  heartbeat, crash count, as a dance job). Its takes are imported and its graph built under a
  graph name of its own (``lib-<20 hex>``), so versions never share objects: a build in
  progress is invisible, and the previous version serves until the new one has succeeded.
- Visibility: a tenant sees and uses its own libraries and the public ones (``tenant_id``
  NULL: installed by the operator from a shell, read-only to tenants). Another tenant's library
  is answered exactly like a missing one. A tenant library may not take a public name
  (``403 dataset_read_only``); a public library installed later under a name a tenant already
  uses is shadowed for that tenant by its own.
- A dance job pins (graph name, graph version) when it starts (``resolve``); deleting a library
  hides it at once, and its objects go once no live job pins them (``purge_deleted``).
- The API checks only what needs no parsing of a take: names, sizes, counts, the manifest's
  syntax and the files it names. Archives and takes are opened on the worker, in the sandbox.
"""

from __future__ import annotations

import json
import re
import uuid
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import PurePosixPath
from typing import Any, cast

import yaml
from sqlalchemy import CursorResult, and_, func, or_, select, update
from sqlalchemy.orm import Session

from dancegraph.errors import DanceGraphError, NotFoundError
from dancegraph.store import ObjectStore
from services.common.problems import ApiError, bounded
from services.common.uploads import FilePart
from services.config import Settings
from services.models import FAILED, FINAL_STATUSES, QUEUED, RUNNING, SUCCEEDED, Dataset, Job, utcnow

NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,47}$")  # a tenant library's
LOOKUP_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")  # any library's, as Spec.dataset
GRAPH_PREFIX = "lib-"
TAKE_SUFFIXES = (".bvh", ".fbx", ".glb", ".gltf")
AUDIO_SUFFIXES = (".wav", ".flac", ".ogg", ".mp3", ".m4a", ".aiff", ".aif")
ARCHIVE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz")
MANIFEST_MAX_BYTES = 256 * 1024
_FILE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._ ()+-]{0,150}$")

# Stages of an import and the percent reached when each starts (GET /v1/datasets/{name}).
STAGES = {"fetch": 2.0, "import": 5.0, "build": 70.0, "publish": 98.0}


def new_graph_name() -> str:
    """A fresh graph-store name for one library version (matches ``Spec.dataset``)."""
    return GRAPH_PREFIX + uuid.uuid4().hex[:20]


def is_library_graph(name: str) -> bool:
    """Whether a graph-store name belongs to a tenant library version (never listed as public)."""
    return name.startswith(GRAPH_PREFIX)


def upload_prefix(version: str) -> str:
    """Object-store prefix of one version's uploaded files."""
    return f"uploads/libraries/{version}"


# --- visibility -----------------------------------------------------------------------------


def _live(q):
    return q.where(Dataset.deleted_at.is_(None))


def _newest(q):
    return q.order_by(Dataset.created_at.desc(), Dataset.id.desc())


def public_row(session: Session, name: str) -> Dataset | None:
    """The newest public version of ``name``."""
    q = _live(select(Dataset).where(Dataset.name == name, Dataset.tenant_id.is_(None)))
    return session.scalar(_newest(q).limit(1))


def own_rows(session: Session, tenant_id: str, name: str) -> list[Dataset]:
    """Every live version of the tenant's library ``name``, newest first."""
    q = _live(select(Dataset).where(Dataset.name == name, Dataset.tenant_id == tenant_id))
    return list(session.scalars(_newest(q)))


def usable_row(session: Session, tenant_id: str | None, name: str) -> Dataset | None:
    """The version a job of this tenant uses for ``name``: its own newest built version, else
    the public one; None when neither exists (another tenant's library is not seen)."""
    if tenant_id is not None:
        for row in own_rows(session, tenant_id, name):
            if row.status == SUCCEEDED:
                return row
    return public_row(session, name)


def shown_row(session: Session, tenant_id: str, name: str) -> Dataset | None:
    """What ``GET /v1/datasets/{name}`` shows: the tenant's newest version (any state), else
    the public library."""
    rows = own_rows(session, tenant_id, name)
    return rows[0] if rows else public_row(session, name)


def visible_rows(session: Session, tenant_id: str) -> list[Dataset]:
    """The tenant's libraries (newest version each, any state) and the public ones it does not
    shadow, by name."""
    q = _live(
        select(Dataset).where(or_(Dataset.tenant_id == tenant_id, Dataset.tenant_id.is_(None)))
    )
    latest: dict[str, Dataset] = {}
    for row in session.scalars(_newest(q)):
        held = latest.get(row.name)
        if held is None or (held.tenant_id is None and row.tenant_id is not None):
            latest[row.name] = row
    return [latest[n] for n in sorted(latest)]


def graph_version(row: Dataset) -> str | None:
    """The graph version a built tenant version published (from its graph key)."""
    return (
        row.graph_key.rsplit("/", 1)[1] if row.graph_key and row.graph_key.count("/") == 2 else None
    )


def resolve(
    session: Session, store: ObjectStore, tenant_id: str | None, name: str
) -> tuple[str, str]:
    """``(graph name, graph version)`` a job of this tenant runs on for library ``name``: the
    tenant's newest built version, else the public library's current graph. Raises
    NotFoundError ``unknown_dataset`` (also for another tenant's library)."""
    from dancegraph.graph.artifact import current_version

    row = usable_row(session, tenant_id, name)
    if row is None:
        raise NotFoundError(
            f"no dataset named {name!r}", code="unknown_dataset", field="spec.dataset"
        )
    if row.tenant_id is None:
        graph = row.graph_name or row.name
        return graph, current_version(store, graph)
    version = graph_version(row)
    assert row.graph_name is not None and version is not None  # set when it succeeded
    return row.graph_name, version


# --- upload checks (API side: no take or archive is opened here) ----------------------------


@dataclass
class Upload:
    """The parts of a ``POST /v1/datasets`` body, as the router found them."""

    name: str | None
    takes: list[FilePart] = field(default_factory=list)
    audio: list[FilePart] = field(default_factory=list)
    archive: FilePart | None = None
    manifest_text: bytes | None = None
    manifest_filename: str = "manifest.yaml"


class _NoAliasLoader(yaml.SafeLoader):
    """YAML without anchors and aliases: a manifest never needs them, and they make the
    'billion laughs' expansion possible."""

    def compose_node(self, parent, index):  # type: ignore[no-untyped-def]
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.constructor.ConstructorError(
                None, None, "aliases are not allowed in a manifest", event.start_mark
            )
        return super().compose_node(parent, index)


def parse_manifest_text(raw: bytes, filename: str) -> dict:
    """The manifest's mapping (JSON, else YAML without aliases), checked against the library's
    schema (``dancegraph.motion.dataset.parse_manifest``); 413 ``manifest_too_large``, 422
    ``manifest_invalid`` naming the field."""
    from dancegraph.motion.dataset import parse_manifest

    if len(raw) > MANIFEST_MAX_BYTES:
        raise ApiError(
            413,
            "manifest_too_large",
            f"the manifest is over {MANIFEST_MAX_BYTES} bytes",
            field="manifest",
        )
    try:
        text = raw.decode("utf-8")
        is_json = filename.lower().endswith(".json") or text.lstrip().startswith("{")
        data = json.loads(text) if is_json else yaml.load(text, Loader=_NoAliasLoader)  # noqa: S506
    except (UnicodeDecodeError, ValueError, yaml.YAMLError) as exc:
        raise ApiError(
            422,
            "manifest_invalid",
            f"the manifest is not valid JSON or YAML: {exc}",
            field="manifest",
        ) from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ApiError(422, "manifest_invalid", "a manifest is a mapping of keys", field="manifest")
    try:
        parse_manifest(data)
    except DanceGraphError as exc:
        raise ApiError(
            422, "manifest_invalid", exc.message, field=f"manifest.{exc.field}"
        ) from None
    return data


def check_file_name(filename: str, part: str) -> str:
    """A part's file name as a plain base name; 422 ``file_name_invalid`` for a path, a
    traversal, a hidden or empty name."""
    base = PurePosixPath(filename.replace("\\", "/")).name
    if base != filename or not _FILE_NAME.match(filename) or ".." in filename:
        raise ApiError(
            422,
            "file_name_invalid",
            f"{filename!r}: a file name without folders, starting with a letter or digit",
            field=part,
        )
    return filename


def _suffix(filename: str, allowed: tuple[str, ...]) -> str | None:
    low = filename.lower()
    return next((s for s in sorted(allowed, key=len, reverse=True) if low.endswith(s)), None)


def check_upload(settings: Settings, up: Upload, manifest: dict | None) -> None:
    """Every check that needs no take opened: the parts present, file names and formats,
    duplicate takes, the take limit, the files the manifest names. Raises ApiError (4xx)."""
    if up.archive is not None:
        if up.takes or up.audio:
            raise ApiError(
                422,
                "upload_mixed",
                "send either one 'archive' or 'takes' parts, not both",
                field="archive",
            )
        check_file_name(up.archive.filename, "archive")
        if _suffix(up.archive.filename, ARCHIVE_SUFFIXES) is None:
            raise ApiError(
                415,
                "archive_format",
                f"an archive is one of {', '.join(ARCHIVE_SUFFIXES)}",
                field="archive",
            )
        return
    if not up.takes:
        raise ApiError(
            422, "takes_missing", "send 'takes' file parts or one 'archive'", field="takes"
        )
    if len(up.takes) > settings.library_max_takes:
        raise ApiError(
            422,
            "library_too_many_takes",
            f"at most {settings.library_max_takes} takes per library",
            field="takes",
        )
    strip = (manifest or {}).get("strip_suffix") or ""
    stems: dict[str, str] = {}
    for part in up.takes:
        name = check_file_name(part.filename, "takes")
        if _suffix(name, TAKE_SUFFIXES) is None:
            raise ApiError(
                415,
                "take_format",
                f"{name}: a take is one of {', '.join(TAKE_SUFFIXES)}",
                field="takes",
            )
        stem = PurePosixPath(name).stem
        clip = stem[: -len(strip)] if strip and stem.endswith(strip) else stem
        if clip.lower() in stems:
            raise ApiError(
                422,
                "take_duplicate",
                f"{name} and {stems[clip.lower()]} are the same take {clip!r}",
                field="takes",
            )
        stems[clip.lower()] = name
    for part in up.audio:
        if _suffix(check_file_name(part.filename, "audio"), AUDIO_SUFFIXES) is None:
            raise ApiError(
                415,
                "audio_format",
                f"{part.filename}: audio is one of {', '.join(AUDIO_SUFFIXES)}",
                field="audio",
            )
    _check_named_files(
        manifest or {}, {p.filename for p in up.takes}, {p.filename for p in up.audio}
    )


def _check_named_files(manifest: dict, takes: set[str], audio: set[str]) -> None:
    """422 ``manifest_file_missing`` for a take or audio file the manifest names but the upload
    lacks."""
    for cid, entry in (manifest.get("clips") or {}).items():
        entry = entry or {}
        for key, have in (("file", takes), ("audio", audio)):
            named = entry.get(key)
            if named and named not in have:
                raise ApiError(
                    422,
                    "manifest_file_missing",
                    f"the manifest's clips.{cid}.{key} names {named!r}, which is not in the upload",
                    field=f"manifest.clips.{cid}.{key}",
                )


def read_only(name: str) -> ApiError:
    """403 ``dataset_read_only``: ``name`` is a public library, which tenants cannot change."""
    return ApiError(
        403,
        "dataset_read_only",
        f"{name!r} is a public library: it cannot be changed",
        field="name",
    )


def check_name(session: Session, settings: Settings, tenant_id: str, name: str | None) -> str:
    """The library name an upload goes to: valid, not a public library's (403
    ``dataset_read_only``), within the tenant's library limit (422 ``library_limit``)."""
    if not name or not NAME.match(name):
        raise ApiError(
            422,
            "dataset_name_invalid",
            "a library name is 1-48 of a-z, 0-9, '_' and '-', starting with a letter or digit",
            field="name",
        )
    if public_row(session, name) is not None:
        raise read_only(name)
    names = set(
        session.scalars(
            _live(select(Dataset.name).where(Dataset.tenant_id == tenant_id)).distinct()
        )
    )
    if name not in names and len(names) >= settings.library_max_per_tenant:
        raise ApiError(
            422,
            "library_limit",
            f"a tenant keeps at most {settings.library_max_per_tenant} libraries; delete one first",
            field="name",
        )
    return name


def store_upload(store: ObjectStore, up: Upload, version: str, manifest: dict | None) -> dict:
    """Move the checked parts into the object store under ``upload_prefix(version)`` (object
    keys by position; the names stay in the returned record) and describe them."""
    prefix = upload_prefix(version)
    files = []
    parts = [("archive", up.archive)] if up.archive is not None else []
    parts += [("take", p) for p in up.takes] + [("audio", p) for p in up.audio]
    for i, (role, part) in enumerate(parts):
        key = f"{prefix}/{i:04d}"
        store.move_in(key, part.path)
        files.append(
            {
                "role": role,
                "name": part.filename,
                "key": key,
                "bytes": part.size,
                "sha256": part.sha256,
            }
        )
    return {"prefix": prefix, "files": files, "manifest": manifest}


# --- lifecycle (worker and reaper) ----------------------------------------------------------


def _update_live(
    session: Session, row_id: int, values: dict[str, Any], *, worker: str | None = None
) -> bool:
    """Conditional update of a version whose import is not final (and, with ``worker``, held by it)."""
    cond = [Dataset.id == row_id, Dataset.status.not_in(FINAL_STATUSES)]
    if worker is not None:
        cond.append(Dataset.worker == worker)
    res = cast(
        CursorResult[Any],
        session.execute(
            update(Dataset)
            .where(*cond)
            .values(**values, updated_at=utcnow())
            .execution_options(synchronize_session=False)
        ),
    )
    session.flush()
    return res.rowcount == 1


def claim(session: Session, row_id: int, worker: str, *, stale_after_s: float) -> Dataset | None:
    """Take the lease of a version's import (queued, or running with a stale heartbeat, and not
    deleted); the fresh row, or None when it is not ours to run."""
    now = utcnow()
    stale = now - timedelta(seconds=stale_after_s)
    free = or_(
        Dataset.status == QUEUED,
        and_(
            Dataset.status == RUNNING,
            or_(Dataset.heartbeat_at.is_(None), Dataset.heartbeat_at < stale),
        ),
    )
    res = cast(
        CursorResult[Any],
        session.execute(
            update(Dataset)
            .where(Dataset.id == row_id, Dataset.deleted_at.is_(None), free)
            .values(
                status=RUNNING,
                worker=worker[:200],
                attempts=Dataset.attempts + 1,
                heartbeat_at=now,
                updated_at=now,
            )
            .execution_options(synchronize_session=False)
        ),
    )
    session.flush()
    if res.rowcount != 1:
        return None
    row = session.get(Dataset, row_id)
    assert row is not None
    session.refresh(row)
    return row


def beat(
    session: Session,
    row_id: int,
    worker: str,
    stage: str | None = None,
    progress: float | None = None,
) -> bool:
    """Refresh the heartbeat (and stage, percent); False once the import is not ours (final,
    deleted, or taken over)."""
    values: dict[str, Any] = {"heartbeat_at": utcnow()}
    if stage is not None:
        values["stage"] = stage
    if progress is not None:
        values["progress"] = float(max(0.0, min(100.0, progress)))
    ok = _update_live(session, row_id, values, worker=worker)
    row = session.get(Dataset, row_id)
    return ok and row is not None and row.deleted_at is None


def succeed(
    session: Session, row_id: int, *, graph_key: str, report: dict, stats: dict, licence: str
) -> bool:
    """Publish a built version: the row becomes ``succeeded`` (and usable by jobs) with its
    graph key, report and stats; False when it was already final."""
    return _update_live(
        session,
        row_id,
        {
            "status": SUCCEEDED,
            "stage": "done",
            "progress": 100.0,
            "graph_key": graph_key,
            "report": report,
            "stats": stats,
            "licence": licence,
            "finished_at": utcnow(),
        },
    )


def fail(
    session: Session,
    row_id: int,
    code: str,
    message: str,
    field: str | None = None,
    report: dict | None = None,
) -> bool:
    """A named failure of a version's import (nothing of it is published); its message and
    field are stored bounded (:func:`~services.common.problems.bounded`)."""
    values: dict[str, Any] = {
        "status": FAILED,
        "stage": FAILED,
        "error_code": code[:64],
        "error_message": bounded(message),
        "error_field": (field or None) and bounded(field, 200),
        "finished_at": utcnow(),
    }
    if report is not None:
        values["report"] = report
    return _update_live(session, row_id, values)


def requeue(session: Session, row_id: int) -> bool:
    """Put a running import back to queued (a transient error, or the reaper found it stuck)."""
    return _update_live(session, row_id, {"status": QUEUED, "stage": "requeued", "worker": None})


def stuck(session: Session, timeout_s: float, now: datetime) -> list[Dataset]:
    """Running imports whose heartbeat is older than ``timeout_s``."""
    limit = now - timedelta(seconds=timeout_s)
    return list(
        session.scalars(
            select(Dataset).where(Dataset.status == RUNNING, Dataset.heartbeat_at < limit)
        )
    )


def waiting(session: Session, timeout_s: float, now: datetime) -> list[int]:
    """Queued imports untouched for ``timeout_s`` (their message may be lost)."""
    limit = now - timedelta(seconds=timeout_s)
    return list(
        session.scalars(
            select(Dataset.id).where(
                Dataset.status == QUEUED,
                Dataset.deleted_at.is_(None),
                func.coalesce(Dataset.updated_at, Dataset.created_at) < limit,
            )
        )
    )


# --- deletion -------------------------------------------------------------------------------


def delete_library(session: Session, tenant_id: str, name: str) -> int:
    """Hide every version of the tenant's library ``name`` (jobs can no longer start on it);
    returns how many. 403 ``dataset_read_only`` for a public library, 404 ``unknown_dataset``
    when the tenant has none by that name."""
    rows = own_rows(session, tenant_id, name)
    if not rows:
        if public_row(session, name) is not None:
            raise read_only(name)
        raise ApiError(404, "unknown_dataset", f"no dataset named {name!r}", field="name")
    now = utcnow()
    for row in rows:
        row.deleted_at = now
    session.flush()
    return len(rows)


def purge_deleted(session: Session, store: ObjectStore, stale_after_s: float) -> list[str]:
    """Remove the objects and rows of deleted versions that no live job pins and no live import
    holds (an import's heartbeat older than ``stale_after_s`` no longer holds); returns the
    graph names removed."""
    stale = utcnow() - timedelta(seconds=stale_after_s)
    rows = session.scalars(select(Dataset).where(Dataset.deleted_at.is_not(None)))
    removed = []
    for row in rows:
        building = row.status in (QUEUED, RUNNING) and (
            row.heartbeat_at is None or row.heartbeat_at > stale
        )
        pinned = row.graph_name and session.scalar(
            select(func.count())
            .select_from(Job)
            .where(Job.dataset_graph == row.graph_name, Job.status.not_in(FINAL_STATUSES))
        )
        if (building and row.status == RUNNING) or pinned:
            continue
        if row.graph_name:
            store.delete_prefix(f"graphs/{row.graph_name}")
            store.delete_prefix(f"datasets/{row.graph_name}")
            removed.append(row.graph_name)
        store.delete_prefix(upload_prefix(row.version))
        session.delete(row)
    session.flush()
    return removed


def pin_job(session: Session, store: ObjectStore, job: Job, name: str) -> tuple[str, str]:
    """The (graph name, graph version) job ``job`` runs on: the one it pinned when it first
    started, else ``resolve``'s answer, recorded on the row now (a retry keeps it)."""
    if job.dataset_graph and job.dataset_version:
        return job.dataset_graph, job.dataset_version
    graph, version = resolve(session, store, job.tenant_id, name)
    session.execute(
        update(Job)
        .where(Job.id == job.id)
        .values(dataset_graph=graph, dataset_version=version)
        .execution_options(synchronize_session=False)
    )
    return graph, version


def requeue_waiting(session: Session, row_id: int, now: datetime) -> None:
    """Restart the clock of a queued import whose message is sent again (reaper)."""
    session.execute(
        update(Dataset)
        .where(Dataset.id == row_id, Dataset.status == QUEUED)
        .values(stage="requeued", updated_at=now)
        .execution_options(synchronize_session=False)
    )


def candidates(
    session: Session, store: ObjectStore, tenant_id: str | None, names: list[str] | None
) -> dict[str, tuple[str, str]]:
    """Library name → (graph name, graph version) of the libraries a style choice picks among:
    ``names`` (a spec's list; each must resolve, else ``unknown_dataset``), or with None every
    library the tenant may use (its own built ones and the public ones with a graph)."""
    from dancegraph.errors import NotFoundError as Missing

    if names is not None:
        return {n: resolve(session, store, tenant_id, n) for n in names}
    out = {}
    for row in visible_rows(session, tenant_id) if tenant_id else []:
        try:
            out[row.name] = resolve(session, store, tenant_id, row.name)
        except Missing:  # still building, failed, or a public name without a graph
            continue
    return out
