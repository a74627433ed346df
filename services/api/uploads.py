"""Uploads: streamed with byte limits, sniffed by magic bytes, checked by header, then stored.

The request body streams to temporary files (``services.api.multipart``) and is refused (413) at
the first byte past a limit, so an over-limit upload never fills memory or disk. An audio part is
then sniffed (the first bytes must name a known audio container, whatever the file name says),
its header read for the duration (too short / too long), and only then moved to its
content address (sha256) in the object store. A refused upload leaves nothing in the store.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

from fastapi import Request
from pydantic import ValidationError
from starlette.datastructures import UploadFile

from dancegraph.errors import AudioError
from dancegraph.spec import Spec
from dancegraph.store import ObjectStore, blob_key
from services.api.multipart import MAX_TEXT_BYTES, FilePart, Form, read_form
from services.api.problems import ApiError, spec_problem_code, validation_errors
from services.config import Settings

# room for boundaries, part headers and a spec of the largest size around the audio parts
_FORM_OVERHEAD = MAX_TEXT_BYTES + 256 * 1024
_SNIFF_BYTES = 64


def sniff_container(head: bytes) -> str | None:
    """The audio container named by the first bytes of a file, or None if none matches."""
    if len(head) >= 12 and head[:4] in (b"RIFF", b"RF64") and head[8:12] == b"WAVE":
        return "wav"
    if head[:4] == b"fLaC":
        return "flac"
    if head[:4] == b"OggS":
        return "ogg"
    if len(head) >= 12 and head[:4] == b"FORM" and head[8:12] in (b"AIFF", b"AIFC"):
        return "aiff"
    if len(head) >= 8 and head[4:8] == b"ftyp":
        return "mp4"
    if head[:4] == b"\x1a\x45\xdf\xa3":
        return "matroska"
    if head[:3] == b"ID3":
        return "mp3"
    if len(head) >= 2 and head[0] == 0xFF and (head[1] & 0xE0) == 0xE0:
        # MPEG audio frame sync (MP3) or ADTS AAC: layer bits 00 with version 11 means ADTS
        layer = (head[1] >> 1) & 0x3
        if layer != 0:
            return "mp3"
        return "aac"
    return None


@dataclass
class StoredAudio:
    key: str
    sha256: str
    size: int
    filename: str
    container: str
    duration_s: float | None


@dataclass
class CheckedAudio:
    """An upload that passed every check, still in a temporary file (``path``)."""

    path: Path
    size: int
    sha256: str
    filename: str
    container: str
    duration_s: float | None

    def store(self, store: ObjectStore) -> StoredAudio:
        """Move the checked file to its content address (``blob_key(sha256)``).

        The file was hashed while it streamed in and already lies in the store's scratch, so it
        is moved into place (a rename on the filesystem store, a multipart upload for a large
        file on S3; no second hashing read); ``put_stream`` is the fallback for a file whose
        hash is not known.
        """
        if self.sha256 and self.path.parent == store.scratch:
            key = blob_key(self.sha256)
            store.move_in(key, self.path)
            size = self.size
        else:
            with open(self.path, "rb") as fh:
                key, size = store.put_stream(fh)
        return StoredAudio(
            key, key.rsplit("/", 1)[-1], size, self.filename, self.container, self.duration_s
        )

    def discard(self) -> None:
        self.path.unlink(missing_ok=True)


async def _limited(stream: AsyncIterator[bytes], limit: int) -> AsyncIterator[bytes]:
    total = 0
    async for chunk in stream:
        total += len(chunk)
        if total > limit:
            raise ApiError(
                413, "upload_too_large", f"the upload is larger than {limit} bytes", field="audio"
            )
        yield chunk


async def read_multipart(
    request: Request, settings: Settings, store: ObjectStore, *, max_audio: int
) -> Form:
    """Stream a multipart/form-data body to temporary files, refusing it at the first byte past
    a limit (per file: ``max_upload_bytes``; whole body: that times ``max_audio`` plus room for
    the form). The caller owns the returned form's temporary files (``Form.discard``)."""
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("multipart/form-data"):
        raise ApiError(
            415,
            "content_type_unsupported",
            "send multipart/form-data with an 'audio' file part",
            field="header.Content-Type",
        )
    limit = settings.max_upload_bytes * max(1, max_audio) + _FORM_OVERHEAD
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise ApiError(
            413, "upload_too_large", f"the upload is larger than {limit} bytes", field="audio"
        )
    return await read_form(
        _limited(request.stream(), limit),
        ctype,
        store.scratch,
        max_file_bytes=settings.max_upload_bytes,
        max_files=max_audio + 1,  # the spec may come as a file part too
        too_many_code="batch_too_large" if max_audio > 1 else "audio_multiple",
    )


def parse_spec(form: Form, settings: Settings) -> Spec:
    """The ``spec`` part (a text field, or a file as ``curl -F spec=@spec.json`` sends it) as a
    validated Spec; absent: all defaults."""
    raw = form.text("spec")
    spec_files = form.files_named("spec")
    if raw is None and spec_files:
        data_bytes = spec_files[0].read_text(MAX_TEXT_BYTES)
        if data_bytes is None:
            raise ApiError(
                413, "spec_too_large", f"spec is larger than {MAX_TEXT_BYTES} bytes", field="spec"
            )
        try:
            raw = data_bytes.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ApiError(422, "spec_malformed", "spec is not UTF-8 text", field="spec") from exc
    return validate_spec(raw)


MAX_SPEC_DEPTH = 32  # a spec nests 4 deep; anything deeper is an attack or a mistake


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text[:40]} is out of range")
    return value


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number")


def validate_spec(raw: str | dict | None) -> Spec:
    """A spec given as JSON text (None or blank: ``{}``) or as a decoded object, validated.

    The one spec check of the service: the API and the ``dancegraph.submit`` task both use it,
    so they refuse the same specs with the same codes (``spec_malformed``, ``spec_invalid``,
    ``spec_unknown_field``) and field paths (``spec.weights.rhythm``). Before the model sees it
    the value must be storable as PostgreSQL JSON: finite numbers only (``NaN``, ``Infinity``,
    ``1e309``: ``spec_malformed``), text without NUL or lone surrogates (``spec_invalid``),
    nesting at most ``MAX_SPEC_DEPTH`` deep (``spec_malformed``).
    """
    if isinstance(raw, dict):
        data: object = raw
    elif raw is None or raw.strip() == "":
        data = {}
    else:
        try:
            data = json.loads(raw, parse_float=_finite, parse_constant=_no_constant)
        except json.JSONDecodeError as exc:
            raise ApiError(
                422,
                "spec_malformed",
                f"spec is not valid JSON: {exc.msg} at char {exc.pos}",
                field="spec",
            ) from exc
        except RecursionError as exc:
            raise ApiError(
                422,
                "spec_malformed",
                f"spec is nested more than {MAX_SPEC_DEPTH} levels deep",
                field="spec",
            ) from exc
        except ValueError as exc:  # a non-finite number, an integer with too many digits
            raise ApiError(422, "spec_malformed", f"spec: {exc}", field="spec") from exc
    if not isinstance(data, dict):
        raise ApiError(422, "spec_malformed", "spec must be a JSON object", field="spec")
    check_json_value(data)
    try:
        return Spec.model_validate(data)
    except ValidationError as exc:
        errors = validation_errors(exc, prefix="spec")
        first = errors[0]
        err = ApiError(
            422,
            spec_problem_code(errors),
            f"{first['field']}: {first['message']}",
            field=first["field"],
            errors=errors,
        )
        raise err from exc


def _bad_text(text: str) -> str | None:
    if "\x00" in text:
        return "text may not contain NUL characters"
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return "text may not contain lone UTF-16 surrogates"
    return None


def check_json_value(data: object) -> None:
    """Walk a decoded JSON value without recursion; raise the first problem PostgreSQL's JSON
    type (or the depth limit) would have with it."""
    stack: list[tuple[object, str, int]] = [(data, "spec", 1)]
    while stack:
        value, path, depth = stack.pop()
        if depth > MAX_SPEC_DEPTH:
            raise ApiError(
                422,
                "spec_malformed",
                f"spec is nested more than {MAX_SPEC_DEPTH} levels deep",
                field="spec",
            )
        if isinstance(value, str):
            why = _bad_text(value)
            if why:
                raise ApiError(422, "spec_invalid", f"{path}: {why}", field=path)
        elif isinstance(value, float) and not math.isfinite(value):
            raise ApiError(422, "spec_malformed", f"{path}: numbers must be finite", field=path)
        elif isinstance(value, dict):
            for key, item in value.items():
                why = _bad_text(str(key))
                if why:
                    raise ApiError(422, "spec_invalid", f"{path}: key {why}", field=path)
                stack.append((item, f"{path}.{key}", depth + 1))
        elif isinstance(value, list):
            stack.extend((item, f"{path}[{i}]", depth + 1) for i, item in enumerate(value))


def safe_filename(name: str | None) -> str:
    """The client's file name, kept only for display: base name, printable characters, ≤ 255."""
    base = (name or "audio").replace("\\", "/").rsplit("/", 1)[-1]
    cleaned = "".join(ch for ch in base if ch.isprintable())
    return cleaned[:255] or "audio"


def audio_parts(form: Form) -> list[FilePart]:
    parts = form.files_named("audio")
    if not parts:
        if form.text("audio") is not None:
            raise ApiError(
                422, "audio_missing", "'audio' must be a file part, not a text field", field="audio"
            )
        raise ApiError(422, "audio_missing", "the request has no 'audio' file part", field="audio")
    return parts


def check_audio(
    upload: UploadFile | FilePart, settings: Settings, store: ObjectStore, field: str = "audio"
) -> CheckedAudio:
    """Check one upload: size, container signature and header duration.

    ``upload``: a streamed ``FilePart`` (checked where it lies, its temporary file handed on) or
    any ``UploadFile`` (copied to a temporary file first). Raises ApiError/AudioError (413, 415,
    422) and leaves nothing behind on failure.
    """
    part = upload if isinstance(upload, FilePart) else _copy_upload(upload, settings, store, field)
    try:
        return _check_file(part, settings, field)
    except BaseException:
        part.discard()
        raise


def _copy_upload(
    upload: UploadFile, settings: Settings, store: ObjectStore, field: str
) -> FilePart:
    store.scratch.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=store.scratch, prefix=".upload-")
    part = FilePart(field, upload.filename or "audio", Path(tmp))
    try:
        digest = hashlib.sha256()
        upload.file.seek(0)
        with os.fdopen(fd, "wb") as out:
            while chunk := upload.file.read(1 << 20):
                part.size += len(chunk)
                if part.size > settings.max_upload_bytes:
                    raise ApiError(
                        413,
                        "upload_too_large",
                        f"{safe_filename(part.filename)} is larger than {settings.max_upload_bytes} bytes",
                        field=field,
                    )
                digest.update(chunk)
                out.write(chunk)
        part.sha256 = digest.hexdigest()
        return part
    except BaseException:
        part.discard()
        raise


def _check_file(part: FilePart, settings: Settings, field: str) -> CheckedAudio:
    filename = safe_filename(part.filename)
    if part.size > settings.max_upload_bytes:
        raise ApiError(
            413,
            "upload_too_large",
            f"{filename} is larger than {settings.max_upload_bytes} bytes",
            field=field,
        )
    if part.size == 0:
        raise AudioError(f"{filename} is empty (0 bytes)", code="audio_empty", field=field)
    with open(part.path, "rb") as fh:
        head = fh.read(_SNIFF_BYTES)
    container = sniff_container(head)
    if container is None:
        raise ApiError(
            415,
            "audio_undecodable",
            f"{filename} is not an audio file (unknown container signature)",
            field=field,
        )
    duration = _header_duration(part.path, filename, field)
    if duration is not None and duration < settings.min_audio_seconds:
        raise AudioError(
            f"{filename} lasts {duration:.1f} s; at least {settings.min_audio_seconds:g} s needed",
            code="audio_too_short",
            field=field,
        )
    if duration is not None and duration > settings.max_audio_seconds:
        raise AudioError(
            f"{filename} lasts {duration:.0f} s; at most {settings.max_audio_seconds:g} s allowed",
            code="audio_too_long",
            field=field,
        )
    return CheckedAudio(part.path, part.size, part.sha256, filename, container, duration)


def _header_duration(path: Path, filename: str, field: str) -> float | None:
    from dancegraph.music.decode import audio_info

    try:
        info = audio_info(path)
    except AudioError as exc:
        exc.message = exc.message.replace(path.name, filename)
        exc.args = (exc.message,)
        exc.field = field
        if exc.code in ("audio_undecodable", "audio_unsupported_codec"):
            exc.status = 415
        raise
    return info.duration_s
