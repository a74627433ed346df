"""Production mode end to end: PostgreSQL, Redis, the API (uvicorn) and Celery worker processes,
the real pipeline (analysis, graph search, render, FBX through Blender) on a generated song and
the demo motion library — once on the filesystem object store, once on the S3 store (a real
S3-protocol server over HTTP, every process with its own local scratch: no shared folder)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import uuid
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from services import webhooks
from services.worker import pipeline
from tests.conftest import S3_ENV, new_bucket
from tests.services.test_worker_harness import (  # noqa: F401 (fixtures)
    DATASET,
    REDIS_DB,
    VENV_BIN,
    WEBHOOK_SECRET,
    copy_store,
    create_key,
    create_pg_database,
    demo_store,
    drop_pg_database,
    flush_redis,
    free_port,
    job_row,
    make_cluster,
    redis_url,
    require_servers,
    restart_redis,
    songs,
    upload_store,
    wait_for,
    write_test_song,
)
from tests.services.test_worker_webhooks import Receiver

pytestmark = [pytest.mark.services, pytest.mark.slow]

BVH_SPEC = {"dataset": DATASET, "alternatives": 2, "output": {"formats": ["bvh"]}}


def _seed_analysis(store, wav: Path) -> None:
    """Analyse ``wav`` once into the store's cache (``pipeline.analysis_key``), as a job would."""
    with open(wav, "rb") as fh:
        key, _ = store.put_stream(fh)
    pipeline.analyze(store, key, key.rsplit("/", 1)[-1])


@pytest.fixture(scope="module", params=["fs", "s3"])
def cluster(request, tmp_path_factory, demo_store, songs):  # noqa: F811
    require_servers()
    flush_redis()
    home = tmp_path_factory.mktemp(f"redis-mode-{request.param}")
    url = create_pg_database()
    with pytest.MonkeyPatch.context() as mp:
        if request.param == "fs":
            c = make_cluster(home, url, redis_url(), copy_store(demo_store, home / "store"))
        else:
            endpoint = request.getfixturevalue("s3_endpoint")
            store_env = {"AWS_ENDPOINT_URL": endpoint, **S3_ENV}
            for name, value in store_env.items():
                mp.setenv(name, value)  # the test process reads the store too
            bucket = new_bucket(endpoint)
            c = make_cluster(
                home, url, redis_url(), home / "scratch", f"s3://{bucket}/store", store_env
            )
            upload_store(demo_store, c.store)
        try:  # whatever started is stopped, also when a start fails
            c.song = write_test_song(songs, seed=1, seconds=16.0)
            _seed_analysis(c.store, c.song)  # the shared song is analysed once for the module
            c.api_key = create_key(url, "acme")
            c.start_api()
            c._spawn("reaper", [str(VENV_BIN / "dancegraph"), "reaper", "--interval", "1"])
            c.start_worker("w1")
            yield c
        finally:
            c.stop_all()
    drop_pg_database(url)
    flush_redis()


def _check_bvh(data: bytes, tmp_path: Path, name: str) -> None:
    from dancegraph.motion.bvh import read_bvh

    path = tmp_path / name
    path.write_bytes(data)
    motion = read_bvh(path)
    assert motion.n_frames > 30 and motion.rotations.shape[1] == len(motion.skeleton.names)


_UFBX_SUMMARY = r"""
import json, sys, ufbx
scene = ufbx.load_file(sys.argv[1])
nodes = scene.nodes
keep = [nodes[i] for i in range(len(nodes))]
stacks = scene.anim_stacks
stack = stacks[0]
print(json.dumps({"bones": sum(n.bone is not None for n in keep), "stacks": len(stacks),
                  "seconds": stack.time_end - stack.time_begin}))
"""


def _fbx_summary(data: bytes, path: Path) -> dict:
    """Read an FBX back with ufbx (in a child Python: the binding is safest used that way)."""
    path.write_bytes(data)
    out = subprocess.run(
        [sys.executable, "-c", _UFBX_SUMMARY, str(path)], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_job_through_api_in_redis_mode_with_fbx_and_signed_webhook(cluster, tmp_path):
    with Receiver([503]) as rx:  # the first delivery fails: the webhook must be retried
        spec = {
            "dataset": DATASET,
            "alternatives": 2,
            "output": {"formats": ["bvh", "fbx"]},
            "callback_url": rx.url,
        }
        created = cluster.submit(cluster.song, spec)
        job = cluster.wait_final([created["id"]], timeout_s=300)[created["id"]]
        assert job["status"] == "succeeded", job
        wait_for(lambda: len(rx.calls) >= 2, 60, "the webhook retry")
    assert job["progress"] == 100.0
    assert len(job["alternatives"]) == 2
    for k in range(2):
        _check_bvh(cluster.download(job["id"], f"alternatives/{k}.bvh"), tmp_path, f"{k}.bvh")
        fbx = cluster.download(job["id"], f"alternatives/{k}.fbx")
        summary = _fbx_summary(fbx, tmp_path / f"{k}.fbx")
        assert summary["stacks"] == 1 and summary["bones"] >= 15 and summary["seconds"] > 5
    timeline = json.loads(cluster.download(job["id"], "timeline.json"))
    assert len(timeline["alternatives"]) == 2 and timeline["bars"]

    calls = rx.calls
    assert len(calls) == 2  # 503, then 200: delivered once, not again
    for call in calls:
        assert webhooks.verify(
            call["body"], call["headers"][webhooks.SIGNATURE_HEADER], WEBHOOK_SECRET
        )
    assert (
        calls[0]["headers"][webhooks.DELIVERY_HEADER]
        == calls[1]["headers"][webhooks.DELIVERY_HEADER]
    )
    body = json.loads(calls[1]["body"])
    assert body["event"] == "job.succeeded" and body["job"]["id"] == job["id"]
    assert [a["cost"] for a in body["job"]["alternatives"]] == [
        a["cost"] for a in job["alternatives"]
    ]
    row = job_row(cluster.database_url, job["id"])
    assert row.webhook_status == "delivered" and row.webhook_attempts == 2


def test_public_submit_task_with_a_plain_celery_client(cluster):
    from celery import Celery

    client = Celery(broker=redis_url())
    good, bad_spec, bad_audio = (str(uuid.uuid4()) for _ in range(3))
    base = {"audio": str(cluster.song), "tenant": "acme"}
    client.send_task(
        "dancegraph.submit", kwargs={**base, "spec": BVH_SPEC, "job_id": good}, queue="analysis"
    )
    client.send_task(
        "dancegraph.submit",
        kwargs={**base, "spec": {"dataset": DATASET, "colour": "red"}, "job_id": bad_spec},
        queue="analysis",
    )
    client.send_task(
        "dancegraph.submit",
        kwargs={**base, "audio": "/nonexistent/song.wav", "spec": BVH_SPEC, "job_id": bad_audio},
        queue="analysis",
    )
    client.close()
    done = cluster.wait_final([good, bad_spec, bad_audio], timeout_s=180, allow_missing=True)
    assert done[good]["status"] == "succeeded"
    assert len(done[good]["alternatives"]) == 2
    assert cluster.download(good, "alternatives/0.bvh").startswith(b"HIERARCHY")
    assert done[bad_spec]["status"] == "failed"
    assert done[bad_spec]["error"]["code"] == "spec_unknown_field"
    assert done[bad_audio]["error"]["code"] == "audio_missing"

    # Idempotent: the same submission again, and the finished job's tasks sent again, change nothing.
    before = list(cluster.store.entries(f"jobs/{good}"))
    row = job_row(cluster.database_url, good)
    log0 = cluster.log_text("w1")
    n_dropped, n_fbx = log0.count("not claimed"), log0.count("dancegraph.export_fbx")
    client = Celery(broker=redis_url())
    client.send_task(
        "dancegraph.submit", kwargs={**base, "spec": BVH_SPEC, "job_id": good}, queue="analysis"
    )
    client.send_task("dancegraph.run_job", args=[good], queue="analysis")
    client.send_task("dancegraph.export_fbx", args=[good], queue="fbx")
    client.close()

    def ignored():
        log = cluster.log_text("w1")
        return (
            log.count("not claimed") > n_dropped
            and log.count("dancegraph.export_fbx") >= n_fbx + 2  # received, then done
        )

    wait_for(ignored, 60, "the worker to drop the repeated tasks")
    again = job_row(cluster.database_url, good)
    assert (again.status, again.attempts, again.finished_at) == (
        "succeeded",
        row.attempts,
        row.finished_at,
    )
    assert list(cluster.store.entries(f"jobs/{good}")) == before


def test_twenty_concurrent_submissions_all_complete(cluster):
    with ThreadPoolExecutor(max_workers=10) as pool:
        created = list(pool.map(lambda _: cluster.submit(cluster.song, BVH_SPEC), range(20)))
    ids = [c["id"] for c in created]
    assert len(set(ids)) == 20
    done = cluster.wait_final(ids, timeout_s=400)
    assert {d["status"] for d in done.values()} == {"succeeded"}, [
        d.get("error") for d in done.values()
    ]
    assert cluster.download(ids[-1], "alternatives/1.bvh").startswith(b"HIERARCHY")
    direct = httpx.get(
        f"{cluster.api_url}/v1/jobs/{ids[0]}/alternatives/0.bvh", headers=cluster.headers()
    )
    if cluster.env.get("DANCEGRAPH_STORE_URL"):  # S3: a presigned URL, the bytes skip the API
        assert direct.status_code == 307, direct.text
        assert direct.headers["location"].startswith(cluster.env["AWS_ENDPOINT_URL"])
        assert "X-Amz-Signature=" in direct.headers["location"]
    else:
        assert direct.status_code == 200 and direct.content.startswith(b"HIERARCHY")


def test_sigkill_mid_job_still_completes_once_with_intact_files(cluster, songs, tmp_path):  # noqa: F811
    wav = write_test_song(songs, seed=7, seconds=10.0, name="kill-me")  # not cached: a long analyze
    job_id = cluster.submit(wav, BVH_SPEC)["id"]

    def mid_job():
        row = job_row(cluster.database_url, job_id)
        return row.status == "running" and row.stage in ("analyze", "search", "render")

    wait_for(mid_job, 120, "the job to be mid-pipeline", interval_s=0.05)
    cluster.kill("w1")  # SIGKILL to the worker's whole process group, pool child included
    assert job_row(cluster.database_url, job_id).status == "running"
    cluster.start_worker("w2")
    job = cluster.wait_final([job_id], timeout_s=300)[job_id]
    assert job["status"] == "succeeded", (
        job,
        cluster.log_text("w2")[-5000:],
        cluster.log_text("reaper")[-3000:],
    )
    row = job_row(cluster.database_url, job_id)
    assert row.attempts == 2  # the first try died; the reaper gave it a second one
    logs = cluster.log_text("w1") + cluster.log_text("w2")
    finished = [json.loads(line) for line in logs.splitlines() if '"job succeeded"' in line]
    assert [e["job_id"] for e in finished].count(job_id) == 1  # completed once
    assert sorted(cluster.store.published(f"jobs/{job_id}")) == [
        "alternatives/0.bvh",
        "alternatives/1.bvh",
        "search.json",
        "timeline.json",
    ]
    for k in range(2):
        _check_bvh(cluster.download(job_id, f"alternatives/{k}.bvh"), tmp_path, f"{k}.bvh")
    json.loads(cluster.download(job_id, "timeline.json"))
    cluster.procs["w1"] = cluster.procs.pop("w2")  # later tests stop "w1"
    cluster.logs["w1"] = cluster.logs["w2"]


def test_redis_restart_while_jobs_wait_loses_no_job(cluster):
    import redis

    cluster.kill("w1", sig=signal.SIGTERM)  # no worker: the jobs wait in Redis
    ids = [cluster.submit(cluster.song, BVH_SPEC)["id"] for _ in range(3)]
    r = redis.Redis(host="127.0.0.1", port=6379, db=REDIS_DB)
    assert r.llen("analysis") == 3
    restart_redis()  # no persistence: the three messages are gone
    r = redis.Redis(host="127.0.0.1", port=6379, db=REDIS_DB)
    assert r.llen("analysis") == 0
    assert {job_row(cluster.database_url, j).status for j in ids} == {"queued"}
    cluster.start_worker("w3")
    done = cluster.wait_final(ids, timeout_s=300)
    assert {d["status"] for d in done.values()} == {"succeeded"}


def test_graph_store_over_http_down_then_up_is_retried_not_failed(cluster):
    """Production wiring: the worker asks the graph-store service over HTTP. While it is down
    the job is requeued and retried with backoff; once it is up the job succeeds."""
    import httpx

    for name in [n for n in cluster.procs if n.startswith("w")]:
        cluster.kill(name, sig=signal.SIGTERM)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    cluster.start_worker("wh", env={"DANCEGRAPH_GRAPHSTORE_URL": url})
    job_id = cluster.submit(cluster.song, BVH_SPEC)["id"]
    wait_for(lambda: "transient error; retrying" in cluster.log_text("wh"), 120, "a retry")
    row = job_row(cluster.database_url, job_id)
    assert row.status in ("queued", "running") and row.error_code is None
    cluster._spawn(
        "graphstore",
        [str(VENV_BIN / "uvicorn"), "services.graphstore.app:app", "--port", str(port)],
    )

    def graphstore_up():
        try:
            return httpx.get(url + "/healthz", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    wait_for(graphstore_up, 60, "the graph store to answer")
    job = cluster.wait_final([job_id], timeout_s=180)[job_id]
    assert job["status"] == "succeeded", job
    assert job_row(cluster.database_url, job_id).attempts >= 2
    assert cluster.download(job_id, "alternatives/0.bvh").startswith(b"HIERARCHY")
