"""Object stores: one interface, a filesystem folder (``FileStore``) or an S3-compatible bucket
(``dancegraph.store_s3.S3Store``), chosen by URL (``open_store``).

Keys are relative POSIX paths made of safe segments (``[A-Za-z0-9._-]``, no ``..``); a store
never joins a key built from user input without validating it. Uploads are content-addressed by
sha256 (``blobs/sha256/ab/abcdef...``). Every single write is atomic (a reader sees all of an
object or none of it). A *set* of objects is published atomically by a manifest written last:

- ``put_tree(prefix, folder, last=...)``: a folder's files under ``prefix``, the file ``last``
  (e.g. a graph's ``manifest.json``) written last and only if absent: readers that look for
  ``last`` see either nothing or everything (graph artifacts).
- ``publish(prefix, folder)``: a result: the files go to a fresh version prefix
  ``<prefix>/r-<random>/``, then ``<prefix>/manifest.json`` (``{"version", "files": {name:
  key}}``) is created if absent. Readers trust only the manifest (``published``); a second
  publisher of the same prefix loses and its files are removed; files no manifest names are
  orphans that ``sweep_orphans`` removes.

Local work needs files: ``scratch`` is a local folder for temporary files (the filesystem
store's own ``tmp/``, so renames into place are atomic), ``local_path``/``local_dir`` give a
readable local copy of an object or of an immutable prefix (the filesystem store's own files;
a download cache for S3).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

_SEGMENT = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,199}$")
MANIFEST = "manifest.json"
TMP_PREFIX = "tmp"  # the filesystem store's scratch folder (never a key users can name)


class InvalidKeyError(ValueError):
    """A key with an unsafe or malformed segment."""


class StoreUnavailableError(ConnectionError):
    """The object store did not answer, or answered with a server error: try again later."""


def check_key(key: str) -> str:
    """Return ``key`` if every ``/``-separated segment is safe, else raise InvalidKeyError."""
    parts = key.split("/")
    if not parts or any(not _SEGMENT.match(p) or p in {".", ".."} for p in parts):
        raise InvalidKeyError(f"invalid object key {key!r}")
    return key


@dataclass(frozen=True)
class Entry:
    """One stored object: key, size in bytes, last-modified time (Unix seconds)."""

    key: str
    size: int
    mtime: float


class ObjectStore(ABC):
    """What the services and the library need from an object store (see the module docstring)."""

    url: str
    scratch: Path

    # --- single objects ---------------------------------------------------------------------

    @abstractmethod
    def exists(self, key: str) -> bool:
        """Whether an object is stored at ``key``."""

    @abstractmethod
    def get_bytes(self, key: str) -> bytes:
        """The object's bytes; ``FileNotFoundError`` when absent."""

    @abstractmethod
    def put_bytes(self, key: str, data: bytes) -> None:
        """Store ``data`` at ``key`` atomically (replacing what was there)."""

    @abstractmethod
    def put_file(self, key: str, source: str | os.PathLike) -> None:
        """Store the local file ``source`` at ``key`` atomically (large files: multipart)."""

    def put_blob(self, key: str, local: Path) -> None:
        """Store the scratch file ``local`` at the content-addressed ``key`` and remove it; a
        blob already there is kept (same content) and its time refreshed, so the sweeper of
        unreferenced blobs sees it as new."""
        self.move_in(key, local)

    @abstractmethod
    def put_bytes_if_absent(self, key: str, data: bytes) -> bool:
        """Create ``key`` with ``data`` unless it exists; True when this call created it."""

    @abstractmethod
    def delete(self, key: str) -> None:
        """Remove one object (absent: nothing happens)."""

    @abstractmethod
    def delete_prefix(self, prefix: str) -> None:
        """Remove every object under ``prefix``."""

    @abstractmethod
    def entries(self, prefix: str) -> Iterator[Entry]:
        """The objects under ``prefix`` (any depth), sorted by key."""

    @abstractmethod
    def children(self, prefix: str) -> list[str]:
        """Names of the sub-prefixes ("folders") right under ``prefix``, sorted."""

    @abstractmethod
    def local_path(self, key: str) -> Path:
        """A readable local file with the object's bytes (``FileNotFoundError`` when absent).
        S3: a cached download, so use it for immutable keys only (blobs, published results)."""

    @abstractmethod
    def local_dir(self, prefix: str) -> Path:
        """A local folder holding every object under an immutable ``prefix`` (a graph version)."""

    @abstractmethod
    def put_tree(self, prefix: str, folder: Path, *, last: str) -> bool:
        """Store the files of local ``folder`` under ``prefix``, the file ``last`` written last
        and only if ``prefix/last`` is absent; False (nothing kept) when it was there already.
        ``folder`` is consumed (moved or removed)."""

    @abstractmethod
    def download_url(self, key: str, filename: str, media_type: str, ttl_s: int) -> str | None:
        """A presigned URL a client can GET the object from directly; None for a store that
        cannot hand one out (the API then streams the file itself)."""

    @abstractmethod
    def check(self) -> None:
        """Raise when the store cannot be reached or written (readiness)."""

    def sweep_uploads(self, older_than_s: float) -> int:
        """Abort multipart uploads left open longer than ``older_than_s``; returns how many.
        A filesystem store has none (its partial files lie in ``scratch``)."""
        return 0

    def free_bytes(self) -> int:
        """Free space on the disk of ``scratch`` (uploads and renders pass through it)."""
        self.scratch.mkdir(parents=True, exist_ok=True)
        return shutil.disk_usage(self.scratch).free

    # --- derived operations -----------------------------------------------------------------

    def list(self, prefix: str) -> Iterator[str]:
        """Keys of the objects under ``prefix``, sorted."""
        return (e.key for e in self.entries(prefix))

    def temp_dir(self, kind: str) -> Path:
        """A fresh private folder in ``scratch`` named ``<kind>-<random>`` (swept when stale)."""
        self.scratch.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(dir=self.scratch, prefix=f"{kind}-"))

    def put_stream(self, stream: BinaryIO, max_bytes: int | None = None) -> tuple[str, int]:
        """Store a stream content-addressed; returns ``(key, size)``.

        Raises ``OverflowError`` (and keeps nothing) when the stream exceeds ``max_bytes``.
        """
        self.scratch.mkdir(parents=True, exist_ok=True)
        digest = hashlib.sha256()
        size = 0
        fd, tmp = tempfile.mkstemp(dir=self.scratch, prefix=".upload-")
        try:
            with os.fdopen(fd, "wb") as fh:
                while chunk := stream.read(1 << 20):
                    size += len(chunk)
                    if max_bytes is not None and size > max_bytes:
                        raise OverflowError(f"upload larger than {max_bytes} bytes")
                    digest.update(chunk)
                    fh.write(chunk)
            key = blob_key(digest.hexdigest())
            self.put_blob(key, Path(tmp))
        finally:
            Path(tmp).unlink(missing_ok=True)
        return key, size

    def move_in(self, key: str, local: Path) -> None:
        """Store the scratch file ``local`` at ``key`` and remove it (a rename where possible)."""
        try:
            self.put_file(key, local)
        finally:
            local.unlink(missing_ok=True)

    def publish(self, prefix: str, folder: Path) -> bool:
        """Publish the files of ``folder`` as the result at ``prefix`` (see the module
        docstring); False when another publisher got there first (``folder`` is consumed)."""
        if self.exists(f"{prefix}/{MANIFEST}"):
            shutil.rmtree(folder, ignore_errors=True)
            return False
        version = f"r-{uuid.uuid4().hex[:16]}"
        files = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
        for name in files:
            check_key(name)
        manifest = {
            "version": version,
            "files": {name: f"{prefix}/{version}/{name}" for name in files},
            "published_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        self._put_version(f"{prefix}/{version}", folder)
        if self.put_bytes_if_absent(f"{prefix}/{MANIFEST}", _manifest_bytes(manifest)):
            return True
        self.delete_prefix(f"{prefix}/{version}")
        return False

    def _put_version(self, prefix: str, folder: Path) -> None:
        """Store a folder's files under a fresh prefix nobody reads yet (consumes ``folder``)."""
        try:
            for path in sorted(p for p in folder.rglob("*") if p.is_file()):
                self.put_file(f"{prefix}/{path.relative_to(folder).as_posix()}", path)
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def published(self, prefix: str) -> dict[str, str] | None:
        """The published result at ``prefix``: file name → key; None when nothing is published."""
        try:
            manifest = json.loads(self.get_bytes(f"{prefix}/{MANIFEST}"))
        except FileNotFoundError:
            return None
        return dict(manifest["files"])

    def publish_more(self, prefix: str, files: dict[str, Path]) -> dict[str, str]:
        """Add local ``files`` (name → path) to the published result at ``prefix``: stored in
        its version folder, then the manifest is replaced naming them too. Only the holder of
        the result's job may call it (the FBX stage). Returns the new name → key map."""
        manifest = json.loads(self.get_bytes(f"{prefix}/{MANIFEST}"))
        for name, path in sorted(files.items()):
            key = f"{prefix}/{manifest['version']}/{check_key(name)}"
            self.put_file(key, path)
            manifest["files"][name] = key
        self.put_bytes(f"{prefix}/{MANIFEST}", _manifest_bytes(manifest))
        return dict(manifest["files"])

    def sweep_orphans(self, prefix: str, older_than_s: float) -> int:
        """Remove result versions under ``prefix/<id>/`` that no manifest names, last written
        more than ``older_than_s`` ago (killed publishers, lost races); returns how many."""
        limit = time.time() - older_than_s
        removed = 0
        for child in self.children(prefix):
            base = f"{prefix}/{child}"
            versions = [v for v in self.children(base) if v.startswith("r-")]
            if not versions:
                continue
            files = self.published(base) or {}
            live = {key.split("/")[len(base.split("/"))] for key in files.values()}
            for version in versions:
                if version in live:
                    continue
                stamps = [e.mtime for e in self.entries(f"{base}/{version}")]
                if stamps and max(stamps) < limit:
                    self.delete_prefix(f"{base}/{version}")
                    removed += 1
        return removed

    def sweep_scratch(self, older_than_s: float) -> int:
        """Remove entries of ``scratch`` (partial uploads, render folders, temporary files of
        any kind) untouched for ``older_than_s``; returns how many."""
        if not self.scratch.is_dir():
            return 0
        limit = time.time() - older_than_s
        removed = 0
        for entry in self.scratch.iterdir():
            try:
                if entry.lstat().st_mtime >= limit:
                    continue
                if entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry, ignore_errors=True)
                else:
                    entry.unlink(missing_ok=True)
                removed += 1
            except FileNotFoundError:
                continue
        return removed


def _manifest_bytes(manifest: dict) -> bytes:
    return json.dumps(manifest, indent=1, sort_keys=True).encode("utf-8")


class FileStore(ObjectStore):
    """Objects as files under a root folder; ``scratch`` is ``<root>/tmp`` (same filesystem)."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        self.scratch = self.root / TMP_PREFIX
        self.url = self.root.as_uri()

    def path(self, key: str) -> Path:
        """Filesystem path of ``key`` (which need not exist yet)."""
        return self.root / check_key(key)

    def exists(self, key: str) -> bool:
        return self.path(key).is_file()

    def get_bytes(self, key: str) -> bytes:
        return self.path(key).read_bytes()

    def _tmp_file(self) -> Path:
        self.scratch.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.scratch, prefix=".tmp-")
        os.close(fd)
        return Path(tmp)

    def put_bytes(self, key: str, data: bytes) -> None:
        self._write(key, lambda tmp: tmp.write_bytes(data))

    def put_file(self, key: str, source: str | os.PathLike) -> None:
        self._write(key, lambda tmp: shutil.copyfile(source, tmp))

    def _write(self, key: str, fill) -> None:
        """``fill`` a scratch file, then rename it to ``key``: readers see all or nothing."""
        target = self.path(key)
        tmp = self._tmp_file()
        try:
            fill(tmp)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)

    def move_in(self, key: str, local: Path) -> None:
        target = self.path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.replace(local, target)  # same content at the same key: replacing is harmless
        except OSError:  # another filesystem: copy
            super().move_in(key, local)

    def put_bytes_if_absent(self, key: str, data: bytes) -> bool:
        target = self.path(key)
        tmp = self._tmp_file()
        try:
            tmp.write_bytes(data)
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.link(tmp, target)  # fails when the target exists: the create is exclusive
            except FileExistsError:
                return False
            return True
        finally:
            tmp.unlink(missing_ok=True)

    def delete(self, key: str) -> None:
        self.path(key).unlink(missing_ok=True)

    def delete_prefix(self, prefix: str) -> None:
        shutil.rmtree(self.path(prefix), ignore_errors=True)

    def entries(self, prefix: str) -> Iterator[Entry]:
        base = self.path(prefix)
        if not base.is_dir():
            return iter(())
        out = []
        for p in base.rglob("*"):
            if p.is_file() and not p.name.startswith("."):
                st = p.stat()
                out.append(Entry(p.relative_to(self.root).as_posix(), st.st_size, st.st_mtime))
        return iter(sorted(out, key=lambda e: e.key))

    def children(self, prefix: str) -> list[str]:
        base = self.path(prefix)
        if not base.is_dir():
            return []
        return sorted(p.name for p in base.iterdir() if p.is_dir() and _SEGMENT.match(p.name))

    def local_path(self, key: str) -> Path:
        path = self.path(key)
        if not path.is_file():
            raise FileNotFoundError(key)
        return path

    def local_dir(self, prefix: str) -> Path:
        return self.path(prefix)

    def put_tree(self, prefix: str, folder: Path, *, last: str) -> bool:
        final = self.path(prefix)
        final.parent.mkdir(parents=True, exist_ok=True)
        if (final / last).exists():
            shutil.rmtree(folder, ignore_errors=True)
            return False
        try:
            os.rename(folder, final)  # one step: readers see all of it or none of it
            return True
        except OSError:
            if not final.is_dir():
                raise
        # a folder of that name exists without ``last`` (a killed writer): fill it, last last
        for path in sorted(folder.rglob("*"), key=lambda p: p.name == last):
            if path.is_file():
                rel = path.relative_to(folder).as_posix()
                if rel != last:
                    self.move_in(f"{prefix}/{rel}", path)
        src = folder / last
        if src.is_file():
            won = self.put_bytes_if_absent(f"{prefix}/{last}", src.read_bytes())
        else:
            won = True
        shutil.rmtree(folder, ignore_errors=True)
        return won

    def _put_version(self, prefix: str, folder: Path) -> None:
        target = self.path(prefix)
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.rename(folder, target)  # the render folder lies in scratch: same filesystem
        except OSError:
            super()._put_version(prefix, folder)

    def download_url(self, key: str, filename: str, media_type: str, ttl_s: int) -> str | None:
        return None

    def check(self) -> None:
        self.scratch.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=self.scratch, prefix=".tmp-ready-"):
            pass


def open_store(url: str | os.PathLike, scratch: str | os.PathLike | None = None) -> ObjectStore:
    """The store named by ``url``: ``s3://bucket/prefix`` (``dancegraph.store_s3``; ``scratch``
    is its local scratch and cache folder), ``file:///path`` or a plain folder path."""
    text = os.fspath(url)
    if text.startswith("s3://"):
        from dancegraph.store_s3 import S3Store

        if scratch is None:
            raise ValueError("an S3 store needs a local scratch folder")
        return S3Store.from_url(text, Path(scratch))
    if text.startswith("file://"):
        text = text[len("file://") :]
    return FileStore(text)


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
