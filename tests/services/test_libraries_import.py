"""Uploaded takes and archives are untrusted: each bad input of the import (opened on the worker,
in the sandbox) fails the version with a named reason per take, and nothing of it is published
(no dataset, no graph; jobs cannot use it). Takes are generated from the project's demo library;
the import runs in this process (``library_build.run_import``) on the SQLite embedded default."""

from __future__ import annotations

import io
import json
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from dancegraph.motion.bvh import read_bvh, write_bvh
from dancegraph.motion.demo import write_demo_library
from dancegraph.motion.skeleton import Motion, Skeleton
from tests.services.conftest import wav_bytes
from tests.services.test_libraries import build, enqueued, row_of

pytestmark = pytest.mark.services

TAKES = ["groove_100.bvh", "pop_120.bvh"]


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory) -> Path:
    return write_demo_library(tmp_path_factory.mktemp("lib") / "demo")


def _manifest(demo_dir: Path, takes: list[str], **changes) -> dict:
    data = json.loads((demo_dir / "manifest.json").read_text())
    data["clips"] = {k: v for k, v in data["clips"].items() if v.get("file") in takes}
    data.update(changes)
    return data


def _import(client, files: list, manifest: dict | None) -> dict:
    """Upload, run the import, return the library's resource (and check nothing published)."""
    sent = enqueued(client)
    parts = [("name", (None, "untrusted"))]
    if manifest is not None:
        parts.append(
            ("manifest", ("manifest.json", json.dumps(manifest).encode(), "application/json"))
        )
    resp = client.post("/v1/datasets", files=parts + files)
    assert resp.status_code == 202, resp.text
    build(client, sent)
    got = client.get("/v1/datasets/untrusted").json()
    if got["status"] == "failed":
        row = row_of(client, got["version"])
        store = client.app.state.ctx.store
        assert not list(store.list(f"graphs/{row.graph_name}"))
        assert not list(store.list(f"datasets/{row.graph_name}"))
        assert not list(store.list(f"uploads/libraries/{row.version}"))  # nothing kept
        assert (
            client.submit(wav_bytes(12.0), {"dataset": "untrusted"}).json()["code"]
            == "unknown_dataset"
        )
    return got


def _take(name: str, data: bytes) -> tuple:
    return ("takes", (name, data, "application/octet-stream"))


def _failed_take(got: dict, file: str) -> str:
    assert got["status"] == "failed" and got["error"]["code"] == "dataset_takes_failed", got
    return {t["file"]: t for t in got["takes"]}[file]["code"]


def _short_take(src: Path, seconds: float) -> bytes:
    motion = read_bvh(src)
    n = int(seconds * motion.fps)
    cut = Motion(motion.skeleton, motion.fps, motion.root_positions[:n], motion.rotations[:n])
    return _bvh_bytes(cut)


def _bvh_bytes(motion: Motion) -> bytes:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "t.bvh"
        write_bvh(motion, path)
        return path.read_bytes()


def _snake(seconds: float = 8.0, fps: float = 30.0) -> bytes:
    """A take on a chain of eight segments: no humanoid roles by name or by shape."""
    names = [f"seg{i}" for i in range(8)]
    skel = Skeleton(
        names,
        np.arange(-1, 7),
        np.array([[0.0, 0.0, 0.3]] * 8),
        [("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")]
        + [("Zrotation", "Xrotation", "Yrotation")] * 7,
    )
    n = int(seconds * fps)
    t = np.arange(n) / fps
    rot = np.zeros((n, 8, 4))
    rot[..., 1] = np.sin(0.3 * np.sin(2 * np.pi * 2 * t))[:, None]
    rot[..., 3] = np.sqrt(1 - rot[..., 1] ** 2)
    root = np.stack([np.zeros(n), 0.1 + 0.05 * np.sin(2 * np.pi * 2 * t), np.zeros(n)], axis=1)
    return _bvh_bytes(Motion(skel, fps, root, rot))


def _other_fps(src: Path) -> bytes:
    text = src.read_text()
    head, _, rest = text.partition("Frame Time:")
    value, _, body = rest.lstrip().partition("\n")
    return (head + f"Frame Time: {float(value) / 2:.6f}\n" + body).encode()


@pytest.mark.parametrize(
    ("case", "code"),
    [
        ("malformed_bvh", "bvh_syntax"),
        ("truncated_bvh", "bvh_truncated"),
        ("malformed_glb", "gltf_invalid"),
        ("malformed_fbx", "rig_no_armature"),
        ("under_one_bar", "take_under_one_bar"),
        ("mixed_fps", "fps_mixed"),
        ("non_humanoid", "skeleton_unmapped"),
        ("audio_undecodable", "audio_undecodable"),
    ],
)
def test_a_bad_take_fails_the_import_with_its_named_reason(sqlite_api, demo_dir, case, code):
    good = demo_dir / TAKES[0]
    files = [_take(good.name, good.read_bytes())]
    manifest = _manifest(demo_dir, [good.name])
    bad = "zz_bad.bvh"  # after the good take: the library's skeleton and rate are the good one's
    if case == "malformed_bvh":
        data = b"HIERARCHY\nROOT hips\n{\n  OFFSET 0 0\n}}}\n"
    elif case == "truncated_bvh":
        raw = (demo_dir / TAKES[1]).read_bytes()
        data = raw[: len(raw) // 2]
    elif case == "malformed_glb":
        bad, data = "zz_bad.glb", b"glTF\x02\x00\x00\x00" + b"\xff" * 64
    elif case == "malformed_fbx":
        bad, data = "zz_bad.fbx", b"Kaydara FBX Binary  \x00\x1a\x00" + b"\x00" * 64
    elif case == "under_one_bar":  # 3 s at a declared 60 BPM: a bar is 4 s
        data = _short_take(demo_dir / TAKES[1], 3.0)
        manifest["clips"]["zz_bad"] = {"file": bad, "tempo_bpm": 60}
    elif case == "mixed_fps":  # twice the other take's rate, no fps declared
        data = _other_fps(demo_dir / TAKES[1])
        del manifest["fps"]
    elif case == "non_humanoid":
        data = _snake()
    else:  # audio_undecodable: the music a take was danced to is not audio
        data = (demo_dir / TAKES[1]).read_bytes()
        manifest["clips"]["zz_bad"] = {"file": bad, "audio": "music.wav"}
        files.append(("audio", ("music.wav", b"RIFF\x00\x00\x00\x00WAVEjunk" * 8, "audio/wav")))
    files.append(_take(bad, data))
    got = _import(sqlite_api, files, manifest)
    assert _failed_take(got, bad) == code
    assert [t["file"] for t in got["takes"] if t["status"] == "failed"] == [bad]


def _zip(members: dict[str, bytes], *, symlink: str | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
        if symlink:
            info = zipfile.ZipInfo(symlink)
            info.external_attr = 0o120777 << 16
            zf.writestr(info, "/etc/passwd")
    return buf.getvalue()


def _tar(members: dict[str, bytes], *, symlink: str | None = None) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
        if symlink:
            info = tarfile.TarInfo(symlink)
            info.type = tarfile.SYMTYPE
            info.linkname = "/etc/passwd"
            tar.addfile(info)
    return buf.getvalue()


def test_an_archive_upload_imports_like_the_parts(sqlite_api, demo_dir):
    members = {f"lib/{n}": (demo_dir / n).read_bytes() for n in TAKES}
    members["lib/manifest.json"] = json.dumps(_manifest(demo_dir, TAKES)).encode()
    got = _import(
        sqlite_api, [("archive", ("lib.tar.gz", _tar(members), "application/gzip"))], None
    )
    assert got["status"] == "succeeded", got
    assert sorted(t["file"] for t in got["takes"]) == TAKES


@pytest.mark.parametrize(
    ("case", "code"),
    [
        ("zip_traversal", "archive_path_unsafe"),
        ("zip_absolute", "archive_path_unsafe"),
        ("tar_traversal", "archive_path_unsafe"),
        ("zip_symlink", "archive_link"),
        ("tar_symlink", "archive_link"),
        ("zip_bomb", "archive_bomb"),
        ("tar_too_big", "archive_bomb"),
        ("too_many_members", "archive_too_many_members"),
        ("not_an_archive", "archive_unreadable"),
    ],
)
def test_an_unsafe_archive_is_refused_before_extracting(sqlite_api, demo_dir, tmp_path, case, code):
    take = (demo_dir / TAKES[0]).read_bytes()
    name = "lib.zip"
    if case == "zip_traversal":
        data = _zip({"ok.bvh": take, "../../escape.bvh": take})
    elif case == "zip_absolute":
        data = _zip({"/tmp/escape.bvh": take})
    elif case == "tar_traversal":
        name, data = "lib.tar.gz", _tar({"ok.bvh": take, "../escape.bvh": take})
    elif case == "zip_symlink":
        data = _zip({"ok.bvh": take}, symlink="link.bvh")
    elif case == "tar_symlink":
        name, data = "lib.tar.gz", _tar({"ok.bvh": take}, symlink="link.bvh")
    elif case == "zip_bomb":
        data = _zip({"ok.bvh": take, "zeros.bvh": bytes(50 * 1024 * 1024)})
    elif case == "tar_too_big":
        sqlite_api.settings.library_archive_max_bytes = 100_000
        name, data = "lib.tar.gz", _tar({"ok.bvh": take})
    elif case == "too_many_members":
        sqlite_api.settings.library_archive_max_members = 3
        data = _zip({f"{i}.bvh": take for i in range(4)})
    else:
        data = b"PK\x03\x04 this is not a zip"
    got = _import(sqlite_api, [("archive", (name, data, "application/octet-stream"))], None)
    assert got["status"] == "failed" and got["error"]["code"] == code, got
    assert not (tmp_path.parent / "escape.bvh").exists()


def test_a_library_over_the_minutes_limit_fails_and_publishes_nothing(sqlite_api, demo_dir):
    sqlite_api.settings.library_max_minutes = 0.1
    files = [_take(n, (demo_dir / n).read_bytes()) for n in TAKES]
    got = _import(sqlite_api, files, _manifest(demo_dir, TAKES))
    assert got["status"] == "failed" and got["error"]["code"] == "library_too_long", got
