"""The S3-compatible object store (AWS S3, MinIO, any server speaking the S3 protocol), via boto3.

``s3://bucket/prefix``: objects live at ``<prefix>/<key>`` in ``bucket``. Endpoint and
credentials come from the environment as boto3 reads them (``AWS_ENDPOINT_URL``,
``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_REGION``); path-style addressing, so
MinIO and other self-hosted servers work without DNS tricks. ``DANCEGRAPH_S3_PUBLIC_ENDPOINT_URL``
names the endpoint clients use for presigned downloads when it differs from the services' one.

- Writes of one object are atomic in S3 itself; files above ``multipart_threshold`` bytes go up
  as multipart uploads (parts of that size, at least 5 MiB), so a 200 MB song never travels in
  one PUT and a lost part is sent again, not the whole file.
- "Create if absent" (``put_bytes_if_absent``: manifests, graph manifests) is a conditional PUT
  (``If-None-Match: *``); the server decides which of two racing writers wins.
- Local copies (``local_path``, ``local_dir``) are downloaded once into ``<scratch>/cache/`` and
  reused: only immutable keys are read this way (content-addressed blobs, published result
  versions, graph versions, model files). The cache is bounded (``cache_max_bytes``,
  ``DANCEGRAPH_S3_CACHE_MAX_BYTES``): after each download the least recently used copies are
  evicted (``trim_cache``), never one used within ``CACHE_KEEP_S``; an evicted copy is simply
  downloaded again when next asked for.
- ``sweep_uploads`` aborts multipart uploads a killed writer left open.
"""

from __future__ import annotations

import os
import shutil
import stat
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import quote

from dancegraph.store import Entry, ObjectStore, StoreUnavailableError, check_key

MULTIPART_THRESHOLD = 16 * 1024 * 1024  # default; DANCEGRAPH_S3_MULTIPART_THRESHOLD overrides
MIN_PART = 5 * 1024 * 1024  # S3's smallest part (all but the last)
_COMPLETE = ".complete"
CACHE_MAX_BYTES = 20 * 1024**3  # default; DANCEGRAPH_S3_CACHE_MAX_BYTES overrides
# a local copy used this recently is never evicted: its caller may be about to open it
CACHE_KEEP_S = 600.0


def _client(endpoint_url: str | None = None):
    import boto3
    from botocore.config import Config

    config = Config(
        s3={"addressing_style": "path"},
        signature_version="s3v4",
        retries={"max_attempts": 3, "mode": "standard"},
        connect_timeout=5,
        read_timeout=60,
    )
    kwargs = {"config": config}
    if endpoint_url:
        kwargs["endpoint_url"] = endpoint_url
    return boto3.session.Session().client("s3", **kwargs)


_RETRY_CODES = {"SlowDown", "RequestTimeout", "ServiceUnavailable", "InternalError", "503", "500"}


def _unavailable(exc: BaseException) -> bool:
    """A failure of the server or the network (worth retrying later), not of the request."""
    from boto3.exceptions import S3TransferFailedError, S3UploadFailedError
    from botocore.exceptions import ClientError, HTTPClientError
    from botocore.exceptions import ConnectionError as BotoConnectionError

    failed = (HTTPClientError, BotoConnectionError, S3UploadFailedError, S3TransferFailedError)
    if isinstance(exc, failed):
        return True  # connection refused, reset, timed out; a transfer that gave up retrying
    if isinstance(exc, ClientError):
        status = exc.response.get("ResponseMetadata", {}).get("HTTPStatusCode") or 0
        return status >= 500 or exc.response.get("Error", {}).get("Code") in _RETRY_CODES
    return False


def _translated(method):
    """Raise ``StoreUnavailableError`` for a server or network failure inside ``method``."""
    import functools

    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        try:
            return method(*args, **kwargs)
        except Exception as exc:
            if _unavailable(exc):
                raise StoreUnavailableError(
                    f"object store unavailable ({type(exc).__name__})"
                ) from exc
            raise

    return wrapper


def _missing(exc: Exception) -> bool:
    from botocore.exceptions import ClientError

    if not isinstance(exc, ClientError):
        return False
    code = str(exc.response.get("Error", {}).get("Code", ""))
    return code in ("404", "NoSuchKey", "NotFound")


class S3Store(ObjectStore):
    """Objects in an S3 bucket under a prefix; ``scratch`` a local folder (temp files, cache)."""

    def __init__(
        self,
        bucket: str,
        prefix: str,
        scratch: Path,
        multipart_threshold: int = MULTIPART_THRESHOLD,
        cache_max_bytes: int = CACHE_MAX_BYTES,
        cache_keep_s: float = CACHE_KEEP_S,
    ):
        self.bucket = bucket
        self.prefix = prefix.strip("/")
        if self.prefix:
            check_key(self.prefix)
        self.url = f"s3://{bucket}/{self.prefix}".rstrip("/")
        self.scratch = Path(scratch).resolve() / "tmp"
        self.cache = Path(scratch).resolve() / "cache"
        self.cache_max_bytes = int(cache_max_bytes)
        self.cache_keep_s = float(cache_keep_s)
        self.client = _client()
        self._lock = threading.Lock()
        self._trim_lock = threading.Lock()
        self._blob_locks: dict[str, list] = {}  # key -> [lock, holders and waiters]
        public = os.environ.get("DANCEGRAPH_S3_PUBLIC_ENDPOINT_URL", "")
        self._signer = _client(public) if public else self.client
        from boto3.s3.transfer import TransferConfig

        self._transfer = TransferConfig(
            multipart_threshold=max(MIN_PART, multipart_threshold),
            multipart_chunksize=max(MIN_PART, multipart_threshold),
            use_threads=False,
        )

    @classmethod
    def from_url(cls, url: str, scratch: Path) -> S3Store:
        """``s3://bucket[/prefix]``."""
        rest = url[len("s3://") :]
        bucket, _, prefix = rest.partition("/")
        if not bucket:
            raise ValueError(f"no bucket in store URL {url!r}")
        threshold = int(os.environ.get("DANCEGRAPH_S3_MULTIPART_THRESHOLD") or MULTIPART_THRESHOLD)
        budget = int(os.environ.get("DANCEGRAPH_S3_CACHE_MAX_BYTES") or CACHE_MAX_BYTES)
        return cls(bucket, prefix, scratch, threshold, budget)

    def _k(self, key: str) -> str:
        check_key(key)
        return f"{self.prefix}/{key}" if self.prefix else key

    def _unk(self, full: str) -> str:
        return full[len(self.prefix) + 1 :] if self.prefix else full

    # --- single objects ---------------------------------------------------------------------

    @_translated
    def exists(self, key: str) -> bool:
        try:
            self.client.head_object(Bucket=self.bucket, Key=self._k(key))
            return True
        except Exception as exc:
            if _missing(exc):
                return False
            raise

    @_translated
    def get_bytes(self, key: str) -> bytes:
        try:
            return self.client.get_object(Bucket=self.bucket, Key=self._k(key))["Body"].read()
        except Exception as exc:
            if _missing(exc):
                raise FileNotFoundError(key) from None
            raise

    @_translated
    def put_bytes(self, key: str, data: bytes) -> None:
        self.client.put_object(Bucket=self.bucket, Key=self._k(key), Body=data)

    @_translated
    def put_file(self, key: str, source: str | os.PathLike) -> None:
        self.client.upload_file(os.fspath(source), self.bucket, self._k(key), Config=self._transfer)

    @_translated
    def put_blob(self, key: str, local: Path) -> None:
        # one upload per blob at a time in this process: the same song sent by many requests
        # at once travels once, the others find it stored
        with self._lock:
            entry = self._blob_locks.setdefault(key, [threading.Lock(), 0])
            entry[1] += 1  # waiters: the entry goes when the last one is done
        try:
            with entry[0]:
                self._put_blob(key, local)
        finally:
            with self._lock:
                entry[1] -= 1
                if entry[1] == 0:
                    del self._blob_locks[key]

    def _put_blob(self, key: str, local: Path) -> None:
        try:
            if self.exists(key):  # same content: refresh its time, do not send it again
                full = self._k(key)
                self.client.copy_object(
                    Bucket=self.bucket,
                    Key=full,
                    CopySource={"Bucket": self.bucket, "Key": full},
                    MetadataDirective="REPLACE",
                )
            else:
                self.put_file(key, local)
        finally:
            local.unlink(missing_ok=True)

    @_translated
    def put_bytes_if_absent(self, key: str, data: bytes) -> bool:
        from botocore.exceptions import ClientError

        try:
            self.client.put_object(Bucket=self.bucket, Key=self._k(key), Body=data, IfNoneMatch="*")
            return True
        except ClientError as exc:
            status = exc.response.get("ResponseMetadata", {}).get("HTTPStatusCode")
            code = exc.response.get("Error", {}).get("Code", "")
            if status in (409, 412) or code in ("PreconditionFailed", "ConditionalRequestConflict"):
                return False
            raise

    @_translated
    def delete(self, key: str) -> None:
        self.client.delete_object(Bucket=self.bucket, Key=self._k(key))

    @_translated
    def delete_prefix(self, prefix: str) -> None:
        keys = [self._k(e.key) for e in self.entries(prefix)]
        for i in range(0, len(keys), 1000):
            self.client.delete_objects(
                Bucket=self.bucket,
                Delete={"Objects": [{"Key": k} for k in keys[i : i + 1000]], "Quiet": True},
            )

    @_translated
    def entries(self, prefix: str) -> Iterator[Entry]:
        paginator = self.client.get_paginator("list_objects_v2")
        out = []
        for page in paginator.paginate(Bucket=self.bucket, Prefix=self._k(prefix) + "/"):
            for obj in page.get("Contents", []):
                out.append(
                    Entry(self._unk(obj["Key"]), int(obj["Size"]), obj["LastModified"].timestamp())
                )
        return iter(sorted(out, key=lambda e: e.key))

    @_translated
    def children(self, prefix: str) -> list[str]:
        paginator = self.client.get_paginator("list_objects_v2")
        base = self._k(prefix) + "/"
        names = set()
        for page in paginator.paginate(Bucket=self.bucket, Prefix=base, Delimiter="/"):
            for common in page.get("CommonPrefixes", []):
                names.add(common["Prefix"][len(base) :].rstrip("/"))
        return sorted(names)

    # --- local copies -----------------------------------------------------------------------

    @_translated
    def local_path(self, key: str) -> Path:
        target = self.cache / check_key(key)
        if target.is_file():
            try:
                os.utime(target)  # its recency, for trim_cache
                return target
            except FileNotFoundError:  # evicted by another process just now: download again
                pass
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".part-")
        os.close(fd)
        try:
            self.client.download_file(self.bucket, self._k(key), tmp, Config=self._transfer)
            os.replace(tmp, target)
        except Exception as exc:
            if _missing(exc):
                raise FileNotFoundError(key) from None
            raise
        finally:
            Path(tmp).unlink(missing_ok=True)
        self.trim_cache(spare=target)
        return target

    def trim_cache(self, spare: Path | None = None) -> int:
        """Evict the least recently used local copies until the cache holds at most
        ``cache_max_bytes``; copies used within ``cache_keep_s``, and ``spare`` (the copy just
        made), stay even above the budget.
        Evicting a file of a ``local_dir`` folder first removes that folder's completeness
        marker, so the next ``local_dir`` downloads what is missing. Returns the bytes freed.
        Why: a worker reads every song and graph version it is given; unbounded, its disk fills.
        """
        with self._trim_lock:
            files = []
            for path in self.cache.rglob("*"):
                if path.name == _COMPLETE or path.name.startswith(".part-"):
                    continue
                try:
                    st = path.stat()
                except FileNotFoundError:
                    continue
                if stat.S_ISREG(st.st_mode):
                    files.append((st.st_mtime, st.st_size, path))
            total = sum(size for _, size, _ in files)
            freed = 0
            recent = time.time() - self.cache_keep_s
            for mtime, size, path in sorted(files, key=lambda f: f[0]):
                if total - freed <= self.cache_max_bytes or mtime >= recent:
                    break
                if path == spare:
                    continue
                for folder in path.parents:  # rglob's paths lie under the cache
                    if folder == self.cache:
                        break
                    (folder / _COMPLETE).unlink(missing_ok=True)
                path.unlink(missing_ok=True)
                freed += size
            return freed

    @_translated
    def local_dir(self, prefix: str) -> Path:
        folder = self.cache / check_key(prefix)
        if (folder / _COMPLETE).is_file():
            try:
                for path in folder.rglob("*"):
                    os.utime(path)  # its recency, for trim_cache
                return folder
            except FileNotFoundError:  # a member evicted by another process: complete it again
                pass
        found = list(self.entries(prefix))
        for entry in found:
            self.local_path(entry.key)
        folder.mkdir(parents=True, exist_ok=True)
        if found:  # an absent prefix may appear later: not marked
            (folder / _COMPLETE).touch()
        return folder

    # --- sets of objects --------------------------------------------------------------------

    @_translated
    def put_tree(self, prefix: str, folder: Path, *, last: str) -> bool:
        try:
            if self.exists(f"{prefix}/{last}"):
                return False
            files = sorted(p for p in folder.rglob("*") if p.is_file())
            for path in files:
                rel = path.relative_to(folder).as_posix()
                if rel != last:
                    self.put_file(f"{prefix}/{rel}", path)
            src = folder / last
            return self.put_bytes_if_absent(f"{prefix}/{last}", src.read_bytes())
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def download_url(self, key: str, filename: str, media_type: str, ttl_s: int) -> str | None:
        return self._signer.generate_presigned_url(
            "get_object",
            Params={
                "Bucket": self.bucket,
                "Key": self._k(key),
                "ResponseContentDisposition": f"attachment; filename*=UTF-8''{quote(filename)}",
                "ResponseContentType": media_type,
            },
            ExpiresIn=int(ttl_s),
        )

    @_translated
    def check(self) -> None:
        self.client.head_bucket(Bucket=self.bucket)

    @_translated
    def sweep_uploads(self, older_than_s: float) -> int:
        """Abort multipart uploads under the prefix begun more than ``older_than_s`` ago."""
        limit = time.time() - older_than_s
        aborted = 0
        paginator = self.client.get_paginator("list_multipart_uploads")
        prefix = f"{self.prefix}/" if self.prefix else ""
        for page in paginator.paginate(Bucket=self.bucket, Prefix=prefix):
            for up in page.get("Uploads", []):
                if up["Initiated"].timestamp() < limit:
                    self.client.abort_multipart_upload(
                        Bucket=self.bucket, Key=up["Key"], UploadId=up["UploadId"]
                    )
                    aborted += 1
        return aborted
