"""The object stores: the filesystem one and the S3 one (against a real S3-protocol server over
HTTP), through the same interface and the same tests."""

from __future__ import annotations

import io
import os
import time
from pathlib import Path

import httpx
import pytest

from dancegraph.store import FileStore, InvalidKeyError, ObjectStore, blob_key, open_store


@pytest.fixture(params=["fs", "s3"])
def store(request, tmp_path: Path) -> ObjectStore:
    if request.param == "fs":
        return FileStore(tmp_path / "store")
    url = request.getfixturevalue("s3_url")
    return open_store(url, tmp_path / "scratch")


def _folder(root: Path, files: dict[str, bytes]) -> Path:
    root.mkdir(parents=True)
    for name, data in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
    return root


def test_objects_round_trip(store: ObjectStore, tmp_path: Path):
    store.put_bytes("a/b/one.txt", b"1")
    src = tmp_path / "two.bin"
    src.write_bytes(b"22")
    store.put_file("a/two.bin", src)
    assert store.exists("a/b/one.txt") and not store.exists("a/b/none")
    assert store.get_bytes("a/two.bin") == b"22"
    with pytest.raises(FileNotFoundError):
        store.get_bytes("a/none")
    assert list(store.list("a")) == ["a/b/one.txt", "a/two.bin"]
    assert store.children("a") == ["b"]
    assert store.local_path("a/two.bin").read_bytes() == b"22"
    assert store.put_bytes_if_absent("a/once", b"first")
    assert not store.put_bytes_if_absent("a/once", b"second")
    assert store.get_bytes("a/once") == b"first"
    store.delete("a/once")
    store.delete_prefix("a/b")
    assert list(store.list("a")) == ["a/two.bin"]
    with pytest.raises(InvalidKeyError):
        store.put_bytes("../escape", b"")
    key, size = store.put_stream(io.BytesIO(b"song"))
    assert key == blob_key(key.rsplit("/", 1)[1]) and size == 4 and store.get_bytes(key) == b"song"
    with pytest.raises(OverflowError):
        store.put_stream(io.BytesIO(b"x" * 100), max_bytes=10)
    assert list(store.list("blobs")) == [key]  # the refused stream left nothing
    assert not [p for p in store.scratch.iterdir()] if store.scratch.is_dir() else True


def test_publish_is_all_or_nothing_and_first_wins(store: ObjectStore, tmp_path: Path):
    prefix = "jobs/j1"
    assert store.published(prefix) is None
    first = _folder(tmp_path / "r1", {"timeline.json": b"{}", "alternatives/0.bvh": b"H1"})
    assert store.publish(prefix, first)
    files = store.published(prefix)
    assert sorted(files) == ["alternatives/0.bvh", "timeline.json"]
    assert store.get_bytes(files["alternatives/0.bvh"]) == b"H1"
    second = _folder(tmp_path / "r2", {"timeline.json": b"{}", "alternatives/0.bvh": b"H2"})
    assert not store.publish(prefix, second)  # another worker finished first: its result stands
    assert store.get_bytes(store.published(prefix)["alternatives/0.bvh"]) == b"H1"
    assert not first.exists() and not second.exists()
    fbx = tmp_path / "0.fbx"
    fbx.write_bytes(b"FBX")
    store.publish_more(prefix, {"alternatives/0.fbx": fbx})
    assert store.get_bytes(store.published(prefix)["alternatives/0.fbx"]) == b"FBX"


def test_the_sweeper_removes_unpublished_versions_only_when_stale(store: ObjectStore):
    store.publish("jobs/j1", _folder(store.scratch / "x1", {"t.json": b"1"}))
    # a publisher killed before its manifest: files under a version nobody names
    store.put_bytes("jobs/j2/r-dead/t.json", b"2")
    store.put_bytes("jobs/j1/r-lost/t.json", b"3")  # the loser of a race on j1
    assert store.published("jobs/j2") is None  # readers do not see it
    assert store.sweep_orphans("jobs", older_than_s=3600) == 0  # too recent: maybe still writing
    time.sleep(1.1)
    assert store.sweep_orphans("jobs", older_than_s=1) == 2
    left = list(store.list("jobs"))
    assert not [k for k in left if "r-dead" in k or "r-lost" in k]
    assert store.get_bytes(store.published("jobs/j1")["t.json"]) == b"1"


def test_put_tree_writes_the_marker_last_and_once(store: ObjectStore, tmp_path: Path):
    files = {"manifest.json": b"{}", "a.npy": b"A", "b.npy": b"B"}
    assert store.put_tree("graphs/g/v1", _folder(tmp_path / "t1", files), last="manifest.json")
    assert not store.put_tree("graphs/g/v1", _folder(tmp_path / "t2", files), last="manifest.json")
    assert store.children("graphs/g") == ["v1"]
    local = store.local_dir("graphs/g/v1")
    assert (local / "a.npy").read_bytes() == b"A" and (local / "manifest.json").is_file()


def test_s3_large_files_go_up_in_parts_and_downloads_are_presigned(s3_url: str, tmp_path: Path):
    import boto3

    from dancegraph.store_s3 import MIN_PART, S3Store

    base = S3Store.from_url(s3_url, tmp_path / "scratch")
    store = S3Store(base.bucket, base.prefix, tmp_path / "scratch", multipart_threshold=MIN_PART)
    big = tmp_path / "song.wav"
    big.write_bytes(os.urandom(2 * MIN_PART + 1000))
    store.put_file("blobs/big", big)
    client = boto3.client("s3", endpoint_url=os.environ["AWS_ENDPOINT_URL"])
    head = client.head_object(Bucket=store.bucket, Key="store/blobs/big")
    assert head["ETag"].strip('"').endswith("-3")  # three parts
    url = store.download_url("blobs/big", "my song.wav", "audio/wav", 60)
    got = httpx.get(url, timeout=30)
    assert got.status_code == 200 and got.content == big.read_bytes()
    assert "my%20song.wav" in got.headers["content-disposition"]
    # an upload a killed writer left open is aborted by the sweeper once stale (moto dates
    # every upload 2010-11-10, so "not yet stale" cannot be shown against it)
    client.create_multipart_upload(Bucket=store.bucket, Key="store/tmp-upload")
    assert store.sweep_uploads(older_than_s=60) == 1
    assert client.list_multipart_uploads(Bucket=store.bucket).get("Uploads", []) == []


def test_s3_local_copies_are_bounded_least_recently_used_first(s3_url: str, tmp_path: Path):
    """The local cache of an S3 store keeps at most its budget: the least recently used copies
    go first (never one used within the keep window); an evicted copy, or a folder that lost a
    member, is downloaded again when next asked for."""
    from dancegraph.store_s3 import S3Store

    base = S3Store.from_url(s3_url, tmp_path / "scratch")
    store = S3Store(
        base.bucket, base.prefix, tmp_path / "scratch", cache_max_bytes=2500, cache_keep_s=0.0
    )
    data = {f"blobs/b{i}": bytes([i]) * 1000 for i in range(3)}
    for key, value in data.items():
        store.put_bytes(key, value)
    store.put_bytes("graphs/g/1/nodes.bin", b"n" * 1000)
    a = store.local_path("blobs/b0")
    os.utime(a, (time.time() - 300, time.time() - 300))
    b = store.local_path("blobs/b1")
    os.utime(b, (time.time() - 200, time.time() - 200))
    store.local_path("blobs/b0")  # used again: now the most recent
    assert store.local_path("blobs/b2").read_bytes() == data["blobs/b2"]
    assert a.is_file() and not b.is_file()  # b1, least recently used, went to fit 2500 bytes
    assert store.local_path("blobs/b1").read_bytes() == data["blobs/b1"]  # downloaded again
    # a folder copy loses its completeness marker with a member, and is completed again
    folder = store.local_dir("graphs/g/1")
    for path in store.cache.rglob("*"):
        if path.is_file():
            os.utime(path, (time.time() - 100, time.time() - 100))
    store.cache_max_bytes = 500
    assert store.trim_cache() > 0
    assert not (folder / "nodes.bin").is_file() and not (folder / ".complete").exists()
    store.cache_max_bytes = 2500
    assert (store.local_dir("graphs/g/1") / "nodes.bin").read_bytes() == b"n" * 1000
    # within the keep window nothing goes, even above the budget
    keeping = S3Store(base.bucket, base.prefix, tmp_path / "scratch", cache_max_bytes=0)
    assert keeping.trim_cache() == 0 and keeping.local_path("blobs/b0").is_file()
