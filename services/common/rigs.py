"""Tenants' character rigs: checked at upload, stored, found again for a job.

A rig is validated when it arrives (``dancegraph.motion.rig.load_rig``: the file is read, its
humanoid roles found), so a bad rig is a 4xx at ``POST /v1/rigs`` with the library's code and
never a failed job later. The API process never parses a rig file: the upload is streamed to
scratch and parsed in a sandboxed child (``dancegraph.sandbox``, limits from
``Settings.rig_parse_*``), which hands back only the summary; a crash, a limit or a timeout
there is a 422 (``rig_unreadable``, ``rig_too_complex``). The file is kept in the object store
under ``rigs/<tenant>/<rig id>/rig.<fmt>`` only once it passed, and is removed again when the
row cannot be written; the row keeps the user's mapping and the summary.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session

from dancegraph.motion.rig import (
    RIG_SUFFIXES,
    Rig,
    RigError,
    check_mapping,
    load_rig,
    name_problem,
    rig_summary,
)
from dancegraph.sandbox import SandboxError, SandboxLimits, run_sandboxed
from dancegraph.store import ObjectStore, file_sha256
from services.common.problems import ApiError
from services.common.uploads import FilePart
from services.config import Settings, get_settings
from services.models import Rig as RigRow
from services.models import new_id

MAX_MAPPING_BYTES = 64 * 1024


def rig_key(tenant_id: str, rig_id: str, fmt: str) -> str:
    return f"rigs/{tenant_id}/{rig_id}/rig.{fmt}"


def parse_mapping(raw: str | bytes | None) -> dict[str, str]:
    """The optional ``mapping`` form part (JSON object: role → joint name); 422 when malformed."""
    if raw is None or not str(raw).strip():
        return {}
    if len(raw) > MAX_MAPPING_BYTES:
        raise ApiError(413, "rig_map_too_large", "the mapping is too large", field="mapping")
    try:
        data = json.loads(raw)
    except ValueError as exc:
        raise ApiError(
            422, "rig_map_invalid", f"mapping is not JSON: {str(exc)[:100]}", field="mapping"
        ) from None
    except RecursionError:
        raise ApiError(
            422, "rig_map_invalid", "mapping is nested too deep", field="mapping"
        ) from None
    return check_mapping(data)


def rig_limits(settings: Settings) -> SandboxLimits:
    """The sandbox limits of parsing one rig file (``Settings.rig_parse_*``)."""
    return SandboxLimits(
        memory_bytes=settings.rig_parse_memory_bytes,
        cpu_seconds=settings.rig_parse_cpu_s,
        wall_seconds=settings.rig_parse_wall_s,
    )


def _sandboxed(fn, path: Path, mapping: dict[str, str] | None, limits: SandboxLimits):
    """``fn(path, mapping)`` in the sandbox; its failures as ``RigError`` (422):
    ``rig_too_complex`` past a limit, ``rig_unreadable`` for a crash; ``ApiError`` 503
    ``rig_parse_busy`` when every sandbox slot stayed taken."""
    try:
        return run_sandboxed(fn, str(path), mapping=mapping or None, limits=limits)
    except SandboxError as exc:
        if exc.code == "busy":
            raise ApiError(
                503, "rig_parse_busy", exc.message, field="rig", headers={"Retry-After": "5"}
            ) from None
        code = "rig_unreadable" if exc.code == "crashed" else "rig_too_complex"
        raise RigError(f"{path.name}: {exc.message}", code=code, field="rig") from None


def register_rig(
    session: Session,
    store: ObjectStore,
    tenant_id: str,
    part: FilePart,
    mapping: dict[str, str],
    limits: SandboxLimits,
) -> RigRow:
    """Check an uploaded rig file (its name's suffix says the format) in the sandbox under
    ``limits`` and store it; the new row (flushed; the caller commits, and removes the file
    with :func:`discard_rig_file` should the commit fail).

    Raises ``ApiError`` 415 ``rig_format`` for a suffix other than .fbx/.glb/.gltf/.bvh, and the
    library's ``RigError`` (422: ``rig_unreadable``, ``rig_too_complex``, ``rig_name_invalid``,
    ``rig_no_armature``, ``rig_missing_roles`` naming the roles, ``rig_disconnected``,
    ``rig_zero_length``, ``rig_map_invalid``, ...).
    """
    suffix = Path(part.filename or "").suffix.lower()
    if suffix not in RIG_SUFFIXES:
        raise ApiError(
            415,
            "rig_format",
            f"a rig file must end in one of {', '.join(RIG_SUFFIXES)} (got {part.filename!r})",
            field="rig",
        )
    fmt = "glb" if suffix == ".gltf" else suffix.lstrip(".")
    if suffix == ".gltf":
        with open(part.path, "rb") as fh:
            suffix = ".glb" if fh.read(4) == b"glTF" else ".gltf"
    filename = part.filename or ""
    if name_problem(filename) is not None:
        filename = f"rig{suffix}"  # a name the database could not hold: keep none
    tmp = store.temp_dir("rig")
    try:
        named = Path(tmp) / f"rig{suffix}"
        shutil.copyfile(part.path, named)
        summary = _sandboxed(rig_summary, named, mapping, limits)  # RigError → 422
        rig_id = new_id()
        key = rig_key(tenant_id, rig_id, suffix.lstrip("."))
        row = RigRow(
            id=rig_id,
            tenant_id=tenant_id,
            filename=filename,
            format=fmt,
            file_key=key,
            sha256=file_sha256(named),
            size_bytes=named.stat().st_size,
            mapping=dict(mapping),
            summary=summary,
        )
        try:
            store.put_file(key, named)
            session.add(row)
            session.flush()
        except BaseException:
            discard_rig_file(store, key)
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return row


def discard_rig_file(store: ObjectStore, key: str) -> None:
    """Remove a rig's stored file whose row could not be written."""
    store.delete_prefix(key.rsplit("/", 1)[0])


def find_rig(session: Session, tenant_id: str, rig_id: str) -> RigRow | None:
    """The tenant's rig ``rig_id``, or None (another tenant's rig is not found either)."""
    return session.scalar(select(RigRow).where(RigRow.id == rig_id, RigRow.tenant_id == tenant_id))


def list_rigs(session: Session, tenant_id: str) -> list[RigRow]:
    return list(
        session.scalars(
            select(RigRow).where(RigRow.tenant_id == tenant_id).order_by(RigRow.created_at)
        )
    )


def delete_rig(session: Session, store: ObjectStore, row: RigRow) -> None:
    store.delete_prefix(f"rigs/{row.tenant_id}/{row.id}")
    session.delete(row)


def load_stored_rig(store: ObjectStore, row: RigRow) -> tuple[Rig, Path]:
    """The stored rig, loaded with its mapping in the sandbox (``Settings.rig_parse_*``), and
    its file's path (FBX output poses that file)."""
    try:
        path = store.local_path(row.file_key)
    except FileNotFoundError:
        raise RigError(
            f"rig {row.id} has no file any more", code="unknown_rig", field="rig"
        ) from None
    limits = rig_limits(get_settings())
    return _sandboxed(load_rig, path, dict(row.mapping), limits), path


def _job_rig(
    store: ObjectStore, database_url: str, tenant_id: str, rig_id: str
) -> tuple[Rig, Path]:
    """A job's rig, loaded; ``RigError`` ``unknown_rig`` when it was deleted after submission."""
    from services.db import session_scope

    with session_scope(database_url) as session:
        row = find_rig(session, tenant_id, rig_id)
        if row is None:
            raise RigError(
                f"the rig {rig_id} was deleted", code="unknown_rig", field="spec.output.rig"
            )
        return load_stored_rig(store, row)


def job_rig_output(
    store: ObjectStore,
    database_url: str,
    tenant_id: str,
    rig_id: str | None,
    formats: tuple[str, ...] = ("bvh", "glb"),
):
    """The render hook that writes a job's alternatives on its rig (``formats`` of BVH, GLB and
    USD), or None.

    FBX on the rig is the ``fbx`` queue's work (:func:`write_rig_fbx`). Raises ``RigError``
    ``unknown_rig`` when the rig was deleted after the job was submitted.
    """
    if rig_id is None:
        return None
    from dancegraph.motion.retarget import RigOutput

    rig, path = _job_rig(store, database_url, tenant_id, rig_id)
    return RigOutput(rig, path, [f for f in formats if f in ("bvh", "glb", "usd")])


def write_rig_fbx(
    store: ObjectStore, database_url: str, tenant_id: str, rig_id: str, bvh: Path, fbx: Path
) -> dict:
    """``alternatives/<k>.rig.fbx`` from ``<k>.rig.bvh``: the rig's own file posed in Blender."""
    from dancegraph.motion.bvh import read_bvh
    from dancegraph.motion.retarget import write_on_rig
    from dancegraph.motion.skeleton import Motion

    rig, path = _job_rig(store, database_url, tenant_id, rig_id)

    motion = read_bvh(bvh, scale=rig.unit_scale)
    on_rig = Motion(rig.skeleton, motion.fps, motion.root_positions, motion.rotations)
    return write_on_rig(on_rig, rig, path, fbx)
