"""Filesystem object store.

Keys are relative POSIX paths made of safe segments (``[A-Za-z0-9._-]``, no ``..``); the store
never joins a path built from user input without validating it. Uploads are content-addressed by
sha256 (``blobs/sha256/ab/abcdef...``). Writes go to a temporary file and are renamed into place,
so a reader never sees a half-written object.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

_SEGMENT = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,199}$")


class InvalidKeyError(ValueError):
    """A key with an unsafe or malformed segment."""


def check_key(key: str) -> str:
    """Return ``key`` if every ``/``-separated segment is safe, else raise InvalidKeyError."""
    parts = key.split("/")
    if not parts or any(not _SEGMENT.match(p) or p in {".", ".."} for p in parts):
        raise InvalidKeyError(f"invalid object key {key!r}")
    return key


class ObjectStore:
    """Objects under a root folder, addressed by validated keys."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        """Filesystem path of ``key`` (which need not exist yet)."""
        return self.root / check_key(key)

    def exists(self, key: str) -> bool:
        return self.path(key).exists()

    def put_bytes(self, key: str, data: bytes) -> Path:
        """Write ``data`` at ``key`` atomically; returns the path."""
        target = self.path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".tmp-")
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return target

    def put_file(self, key: str, source: str | os.PathLike) -> Path:
        """Copy the file ``source`` to ``key`` atomically; returns the path."""
        target = self.path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".tmp-")
        os.close(fd)
        try:
            shutil.copyfile(source, tmp)
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return target

    def put_stream(self, stream: BinaryIO, max_bytes: int | None = None) -> tuple[str, int]:
        """Store a stream content-addressed; returns ``(key, size)``.

        Raises ``OverflowError`` (and keeps nothing) when the stream exceeds ``max_bytes``.
        """
        tmp_dir = self.root / "tmp"
        tmp_dir.mkdir(parents=True, exist_ok=True)
        digest = hashlib.sha256()
        size = 0
        fd, tmp = tempfile.mkstemp(dir=tmp_dir, prefix=".upload-")
        try:
            with os.fdopen(fd, "wb") as fh:
                while chunk := stream.read(1 << 20):
                    size += len(chunk)
                    if max_bytes is not None and size > max_bytes:
                        raise OverflowError(f"upload larger than {max_bytes} bytes")
                    digest.update(chunk)
                    fh.write(chunk)
            key = blob_key(digest.hexdigest())
            target = self.path(key)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return key, size

    def get_bytes(self, key: str) -> bytes:
        return self.path(key).read_bytes()

    def delete_prefix(self, prefix: str) -> None:
        """Remove every object under ``prefix`` (a folder key)."""
        shutil.rmtree(self.path(prefix), ignore_errors=True)

    def list(self, prefix: str) -> Iterator[str]:
        """Keys of the files under ``prefix``, sorted."""
        base = self.path(prefix)
        if not base.exists():
            return iter(())
        return iter(
            sorted(
                p.relative_to(self.root).as_posix()
                for p in base.rglob("*")
                if p.is_file() and not p.name.startswith(".tmp-")
            )
        )


def file_sha256(path: str | Path) -> str:
    """sha256 hex digest of a file's content (read in 1 MiB chunks): the project's content hash."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def blob_key(sha256_hex: str) -> str:
    """Content-addressed key of a blob with the given sha256 hex digest."""
    if not re.fullmatch(r"[0-9a-f]{64}", sha256_hex):
        raise InvalidKeyError(f"not a sha256 hex digest: {sha256_hex!r}")
    return f"blobs/sha256/{sha256_hex[:2]}/{sha256_hex}"
