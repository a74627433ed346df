"""Motion libraries as a tenant resource (``POST/GET/DELETE /v1/datasets``): upload, the queued
import and build (run in this process with ``library_build.run_import``, the sandbox included),
versions, jobs pinned to a version, isolation between tenants, limits.

Takes are the project's generated demo library (``dancegraph.motion.demo``: six BVH takes on
one skeleton with an annotated manifest); the API runs on PostgreSQL (``api``) and on the
SQLite embedded default (``sqlite_api``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dancegraph.motion.demo import write_demo_library
from services.models import Dataset, Job
from services.worker import library_build, pipeline
from tests.demo import demo_song

pytestmark = pytest.mark.services


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory) -> Path:
    return write_demo_library(tmp_path_factory.mktemp("lib") / "demo")


def take_parts(folder: Path, names: list[str] | None = None) -> list:
    """``takes`` file parts of a library folder (all its BVH files, or ``names``)."""
    files = sorted(folder.glob("*.bvh")) if names is None else [folder / n for n in names]
    return [("takes", (p.name, p.read_bytes(), "application/octet-stream")) for p in files]


def manifest_part(folder: Path, **changes) -> tuple:
    data = json.loads((folder / "manifest.json").read_text())
    data.update(changes)
    return ("manifest", ("manifest.json", json.dumps(data).encode(), "application/json"))


def upload(
    client, folder: Path, name: str, *, extra: list | None = None, takes: list | None = None
):
    """POST /v1/datasets of ``folder``'s takes (or ``takes``) with its manifest (its clips cut
    to the takes sent)."""
    takes = take_parts(folder) if takes is None else takes
    sent = {part[1][0] for part in takes}
    clips = json.loads((folder / "manifest.json").read_text())["clips"]
    kept = {k: v for k, v in clips.items() if v.get("file") in sent}
    files = [("name", (None, name)), manifest_part(folder, clips=kept), *takes]
    return client.post("/v1/datasets", files=files + (extra or []))


def enqueued(client) -> list[int]:
    """Row ids the API handed to the queue (the test's enqueue function records them)."""
    sent: list[int] = []
    client.app.state.enqueue_library = sent.append
    return sent


def build(client, sent: list[int]) -> None:
    """Run every queued import and build, as the worker would."""
    while sent:
        library_build.run_import(sent.pop(0), client.settings)


def row_of(client, version: str) -> Dataset:
    from services.db import session_scope

    with session_scope(client.settings.database_url) as session:
        row = session.query(Dataset).filter_by(version=version).one()
        session.expunge(row)
        return row


def test_upload_builds_a_version_that_a_job_dances_on(sqlite_api, demo_dir, tmp_path):
    sent = enqueued(sqlite_api)
    resp = upload(sqlite_api, demo_dir, "studio-moves")
    assert resp.status_code == 202, resp.text
    body = resp.json()
    assert resp.headers["Location"] == "/v1/datasets/studio-moves"
    assert body["status"] == "queued" and body["public"] is False and len(sent) == 1
    assert sqlite_api.get("/v1/datasets/studio-moves").json()["status"] == "queued"
    build(sqlite_api, sent)
    got = sqlite_api.get("/v1/datasets/studio-moves").json()
    assert got["status"] == "succeeded" and got["progress"] == 100.0, got
    assert got["nodes"] > 0 and got["edges"] > 0 and got["graph_version"]
    assert {t["file"] for t in got["takes"]} == {p.name for p in demo_dir.glob("*.bvh")}
    assert all(t["status"] == "imported" and t["bars"] > 0 for t in got["takes"])
    listed = {d["name"]: d for d in sqlite_api.get("/v1/datasets").json()["items"]}
    assert listed["studio-moves"]["public"] is False and listed["cmu-salsa"]["public"] is True

    wav, _ = demo_song(tmp_path)
    spec = {"dataset": "studio-moves", "alternatives": 1, "output": {"formats": ["bvh"]}}
    job = sqlite_api.submit(wav.read_bytes(), spec)
    assert job.status_code == 202, job.text
    job_id = job.json()["id"]
    assert pipeline.run_job(job_id, sqlite_api.settings).status == "succeeded"
    timeline = sqlite_api.get(f"/v1/jobs/{job_id}/timeline.json").json()
    row = row_of(sqlite_api, got["version"])
    library = timeline["provenance"]["library"]
    assert library == {
        "name": "studio-moves",
        "graph": row.graph_name,
        "graph_version": got["graph_version"],
    }


def test_a_new_upload_is_a_new_version_and_a_job_keeps_the_version_it_pinned(sqlite_api, demo_dir):
    from services.common import libraries
    from services.db import session_scope

    sent = enqueued(sqlite_api)
    v1 = upload(sqlite_api, demo_dir, "moves").json()["version"]
    build(sqlite_api, sent)
    v2 = upload(sqlite_api, demo_dir, "moves", takes=take_parts(demo_dir)[:3]).json()["version"]
    store = sqlite_api.app.state.ctx.store
    with session_scope(sqlite_api.settings.database_url) as session:
        # v2 is queued: jobs still get v1, never a half-built graph
        tenant = sqlite_api.tenant_id
        assert libraries.usable_row(session, tenant, "moves").version == v1
        graph1, version1 = libraries.resolve(session, store, tenant, "moves")
    build(sqlite_api, sent)
    got = sqlite_api.get("/v1/datasets/moves").json()
    assert got["version"] == v2 and [v["version"] for v in got["versions"]] == [v2, v1]
    assert len(got["takes"]) == 3
    with session_scope(sqlite_api.settings.database_url) as session:
        graph2, _ = libraries.resolve(session, store, sqlite_api.tenant_id, "moves")
        # a running job pinned to v1, then the library is deleted
        job = Job(
            tenant_id=sqlite_api.tenant_id,
            status="running",
            spec={},
            audio_key="blobs/x",
            audio_sha256="0" * 64,
            dataset_graph=graph1,
            dataset_version=version1,
        )
        session.add(job)
        session.flush()
        job_id = job.id
    assert graph2 != graph1
    assert sqlite_api.delete("/v1/datasets/moves").status_code == 204
    assert sqlite_api.get("/v1/datasets/moves").status_code == 404
    assert store.exists(f"graphs/{graph1}/current")  # the running job's version stays
    assert not store.exists(f"graphs/{graph2}/current")  # the other is gone
    with session_scope(sqlite_api.settings.database_url) as session:
        session.get(Job, job_id).status = "succeeded"
    library_build.reap(sqlite_api.settings)
    assert not store.exists(f"graphs/{graph1}/current")
    assert not list(store.list(f"datasets/{graph1}"))
    assert not list(store.list("uploads/libraries"))
    with session_scope(sqlite_api.settings.database_url) as session:
        assert session.query(Dataset).filter_by(name="moves").count() == 0


def test_no_tenant_reads_uses_or_deletes_another_tenants_library(api, demo_dir, song_wav, tmp_path):
    sent = enqueued(api)
    assert upload(api, demo_dir, "private-moves").status_code == 202
    build(api, sent)
    row = row_of(api, api.get("/v1/datasets/private-moves").json()["version"])
    other = api.new_tenant()
    names = {d["name"] for d in other.get("/v1/datasets").json()["items"]}
    assert "private-moves" not in names and row.graph_name not in names
    for path in (f"/v1/datasets/{'private-moves'}", f"/v1/datasets/{row.graph_name}"):
        got = other.get(path)
        assert got.status_code == 404 and got.json()["code"] == "unknown_dataset"
        gone = other.delete(path)
        assert gone.status_code == 404 and gone.json()["code"] == "unknown_dataset"
    for name in ("private-moves", row.graph_name):  # by its name or its graph's
        job = other.submit(song_wav, {"dataset": name})
        assert job.status_code == 422 and job.json()["code"] == "unknown_dataset", job.text
        batch = other.post(
            "/v1/batches",
            files=[
                ("audio", ("a.wav", song_wav, "audio/wav")),
                ("spec", (None, json.dumps({"dataset": name}))),
            ],
        )
        assert batch.status_code == 422 and batch.json()["code"] == "unknown_dataset"
    # the batch pipelines' Celery entry (dancegraph.submit) refuses it the same way
    from services.worker.submit import submit

    wav = tmp_path / "song.wav"
    wav.write_bytes(song_wav)
    job_id = submit(
        {"dataset": "private-moves"}, str(wav), other.tenant_name, settings=api.settings
    )
    assert other.get(f"/v1/jobs/{job_id}").json()["error"]["code"] == "unknown_dataset"
    # the same name is the other tenant's own library, apart from the first one's
    assert upload(other, demo_dir, "private-moves").status_code == 202
    build(other, sent)
    assert other.get("/v1/datasets/private-moves").json()["version"] != row.version
    assert api.get("/v1/datasets/private-moves").json()["version"] == row.version
    assert other.delete("/v1/datasets/private-moves").status_code == 204
    assert api.get("/v1/datasets/private-moves").json()["status"] == "succeeded"
    assert api.submit(song_wav, {"dataset": "private-moves"}).status_code == 202


def test_public_libraries_are_read_only(api, demo_dir):
    sent = enqueued(api)
    gone = api.delete("/v1/datasets/cmu-salsa")
    assert gone.status_code == 403 and gone.json()["code"] == "dataset_read_only"
    over = upload(api, demo_dir, "cmu-salsa")
    assert over.status_code == 403 and over.json()["code"] == "dataset_read_only"
    assert sent == [] and api.get("/v1/datasets/cmu-salsa").json()["public"] is True


def _nothing_stored(client) -> None:
    from services.db import session_scope

    store = client.app.state.ctx.store
    assert not list(store.list("uploads/libraries"))
    with session_scope(client.settings.database_url) as session:
        assert session.query(Dataset).filter(Dataset.tenant_id.is_not(None)).count() == 0


@pytest.mark.parametrize(
    ("limit", "value", "status", "code"),
    [
        ("library_max_takes", 2, 422, "library_too_many_takes"),
        ("library_max_upload_bytes", 1_000_000, 413, "upload_too_large"),
    ],
)
def test_over_a_limit_nothing_is_stored(sqlite_api, demo_dir, limit, value, status, code):
    sent = enqueued(sqlite_api)
    setattr(sqlite_api.settings, limit, value)
    resp = upload(sqlite_api, demo_dir, "too-much")
    assert resp.status_code == status and resp.json()["code"] == code, resp.text
    assert sent == []
    _nothing_stored(sqlite_api)


def test_libraries_per_tenant_limit(sqlite_api, demo_dir):
    sent = enqueued(sqlite_api)
    sqlite_api.settings.library_max_per_tenant = 1
    assert upload(sqlite_api, demo_dir, "first").status_code == 202
    assert upload(sqlite_api, demo_dir, "first").status_code == 202  # a new version: allowed
    second = upload(sqlite_api, demo_dir, "second")
    assert second.status_code == 422 and second.json()["code"] == "library_limit"
    assert len(sent) == 2


BOMB_YAML = b'a: &a ["x","x","x","x","x","x","x","x","x"]\nb: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]\n'


@pytest.mark.parametrize(
    ("case", "status", "code"),
    [
        ("traversal", 422, "file_name_invalid"),
        ("absolute", 422, "file_name_invalid"),
        ("duplicate", 422, "take_duplicate"),
        ("not_a_take", 415, "take_format"),
        ("manifest_syntax", 422, "manifest_invalid"),
        ("manifest_alias_bomb", 422, "manifest_invalid"),
        ("manifest_unknown_field", 422, "manifest_invalid"),
        ("manifest_names_absent_take", 422, "manifest_file_missing"),
        ("manifest_names_absent_audio", 422, "manifest_file_missing"),
        ("no_takes", 422, "takes_missing"),
        ("archive_and_takes", 422, "upload_mixed"),
        ("archive_format", 415, "archive_format"),
        ("bad_name", 422, "dataset_name_invalid"),
    ],
)
def test_bad_uploads_get_a_coded_4xx_and_nothing_is_stored(
    sqlite_api, demo_dir, case, status, code
):
    sent = enqueued(sqlite_api)
    takes = take_parts(demo_dir)
    name, manifest = "bad-upload", manifest_part(demo_dir)
    first = takes[0][1]
    extra: list = []
    if case == "traversal":
        takes[0] = ("takes", ("../" + first[0], first[1], first[2]))
    elif case == "absolute":
        takes[0] = ("takes", ("/etc/" + first[0], first[1], first[2]))
    elif case == "duplicate":
        takes.append(("takes", (first[0].upper().replace(".BVH", ".bvh"), first[1], first[2])))
    elif case == "not_a_take":
        takes[0] = ("takes", ("notes.txt", b"hello", "text/plain"))
    elif case == "manifest_syntax":
        manifest = ("manifest", ("manifest.yaml", b"clips: [unclosed\n", "text/yaml"))
    elif case == "manifest_alias_bomb":
        manifest = ("manifest", ("manifest.yaml", BOMB_YAML, "text/yaml"))
    elif case == "manifest_unknown_field":
        manifest = manifest_part(demo_dir, tempo_bmp=120)
    elif case == "manifest_names_absent_take":
        takes = takes[1:]
    elif case == "manifest_names_absent_audio":
        data = json.loads(manifest[1][1])
        next(iter(data["clips"].values()))["audio"] = "missing.wav"
        manifest = ("manifest", ("manifest.json", json.dumps(data).encode(), "application/json"))
    elif case == "no_takes":
        takes = []
    elif case == "archive_and_takes":
        extra = [("archive", ("lib.zip", b"PK\x03\x04", "application/zip"))]
    elif case == "archive_format":
        takes, extra = [], [("archive", ("lib.rar", b"Rar!", "application/octet-stream"))]
    elif case == "bad_name":
        name = "../Bad Name"
    files = [("name", (None, name)), manifest, *takes, *extra]
    resp = sqlite_api.post("/v1/datasets", files=files)
    assert resp.status_code == status, resp.text
    assert resp.json()["code"] == code
    assert sent == []
    _nothing_stored(sqlite_api)


def test_not_multipart_is_refused(sqlite_api):
    resp = sqlite_api.post(
        "/v1/datasets", content=b"{}", headers={"Content-Type": "application/json"}
    )
    assert resp.status_code == 415 and resp.json()["code"] == "content_type_unsupported"


def test_dataset_push_uploads_a_folder_and_waits_for_the_build(sqlite_api, demo_dir):
    from services.cli import push_library

    def build_now(row_id: int) -> None:  # the worker, run as soon as the upload is queued
        library_build.run_import(row_id, sqlite_api.settings)

    sqlite_api.app.state.enqueue_library = build_now
    out = push_library(sqlite_api.client, demo_dir, sqlite_api.key, name="pushed", poll_s=0.1)
    assert out["status"] == "succeeded" and out["name"] == "pushed", out
    assert len(out["takes"]) == len(list(demo_dir.glob("*.bvh"))) and out["nodes"] > 0
    refused = push_library(sqlite_api.client, demo_dir, sqlite_api.key, name="cmu-salsa")
    assert refused["status"] == "refused" and refused["problem"]["code"] == "dataset_read_only"


def test_a_style_or_a_list_picks_among_the_tenants_libraries_and_says_why(
    sqlite_api, demo_dir, tmp_path
):
    sent = enqueued(sqlite_api)
    for name, style in (("grooves", "groove"), ("pops", "pop")):
        takes = [p for p in take_parts(demo_dir) if p[1][0].startswith(style)]
        sent_names = {t[1][0] for t in takes}
        clips = json.loads((demo_dir / "manifest.json").read_text())["clips"]
        manifest = manifest_part(
            demo_dir, style=style, clips={k: v for k, v in clips.items() if v["file"] in sent_names}
        )
        files = [("name", (None, name)), manifest, *takes]
        assert sqlite_api.post("/v1/datasets", files=files).status_code == 202
    build(sqlite_api, sent)
    wav, _ = demo_song(tmp_path)
    chosen = {}
    for key, spec in (
        ("auto", {"style": "auto"}),
        ("pop", {"style": "pop"}),
        ("list", {"dataset": ["grooves", "pops"]}),
    ):
        full = {**spec, "alternatives": 1, "output": {"formats": ["bvh"]}}
        if "dataset" not in spec:
            full["dataset"] = "grooves"
        resp = sqlite_api.submit(wav.read_bytes(), full)
        assert resp.status_code == 202, resp.text
        job_id = resp.json()["id"]
        assert pipeline.run_job(job_id, sqlite_api.settings).status == "succeeded"
        library = sqlite_api.get(f"/v1/jobs/{job_id}/timeline.json").json()["provenance"]["library"]
        choice = library["choice"]
        assert choice["chosen"] == library["name"] and choice["reason"].startswith(library["name"])
        names = {c["name"] for c in choice["candidates"]}
        assert names == ({"pops"} if key == "pop" else {"grooves", "pops"}), choice
        assert all(
            {"tempo_cost", "style_distance", "score"} <= set(c) for c in choice["candidates"]
        )
        chosen[key] = library["name"]
    assert chosen["pop"] == "pops" and chosen["auto"] == chosen["list"]
    unknown = sqlite_api.submit(wav.read_bytes(), {"dataset": "grooves", "style": "waltz"})
    job_id = unknown.json()["id"]
    from services.worker import tasks

    tasks.run_job.apply(args=[job_id])
    failed = sqlite_api.get(f"/v1/jobs/{job_id}").json()
    assert failed["status"] == "failed" and failed["error"]["code"] == "style_unknown", failed
