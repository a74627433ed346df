"""Audio upload checks shared by the API and the ``dancegraph.submit`` task: size, container
sniffed by magic bytes, duration read from the header, then the move to the object store.

An audio file arrives as a :class:`FilePart` (a temporary file in the store's ``tmp/``, hashed
while it streamed in: ``services.api.multipart``) or as any ``UploadFile`` (copied to one first).
It is sniffed (the first bytes must name a known audio container, whatever the file name says),
its header read for the duration (too short / too long), and only then moved to its content
address (sha256) in the object store. A refused upload leaves nothing in the store.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

from starlette.datastructures import UploadFile

from dancegraph.errors import AudioError
from dancegraph.store import ObjectStore, blob_key
from services.common.problems import ApiError
from services.config import Settings

SNIFF_BYTES = 64  # enough for every container signature ``sniff_container`` knows


@dataclass
class FilePart:
    """One uploaded file, already on disk in a temporary file (``size`` bytes, ``sha256`` hex
    digest when it was hashed while streaming in, else "")."""

    name: str
    filename: str
    path: Path
    size: int = 0
    sha256: str = ""

    def read_text(self, limit: int) -> bytes | None:
        """The file's bytes when at most ``limit`` long, else None."""
        if self.size > limit:
            return None
        return self.path.read_bytes()

    def discard(self) -> None:
        self.path.unlink(missing_ok=True)


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


def check_container(head: bytes, filename: str, field: str) -> str:
    """The audio container named by a file's first ``SNIFF_BYTES`` bytes; 415
    ``audio_undecodable`` (naming ``filename`` and ``field``) when none matches."""
    container = sniff_container(head)
    if container is None:
        raise ApiError(
            415,
            "audio_undecodable",
            f"{filename} is not an audio file (unknown container signature)",
            field=field,
        )
    return container


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
            store.put_blob(key, self.path)
            size = self.size
        else:
            with open(self.path, "rb") as fh:
                key, size = store.put_stream(fh)
        return StoredAudio(
            key, key.rsplit("/", 1)[-1], size, self.filename, self.container, self.duration_s
        )

    def discard(self) -> None:
        self.path.unlink(missing_ok=True)


def safe_filename(name: str | None) -> str:
    """The client's file name, kept only for display: base name, printable characters, ≤ 255."""
    base = (name or "audio").replace("\\", "/").rsplit("/", 1)[-1]
    cleaned = "".join(ch for ch in base if ch.isprintable())
    return cleaned[:255] or "audio"


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
        container = check_container(fh.read(SNIFF_BYTES), filename, field)
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
