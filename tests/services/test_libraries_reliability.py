"""A library's import and build through the production processes (PostgreSQL, Redis, the API on
uvicorn, Celery workers, the reaper), once on the filesystem object store and once on the S3
store: a worker SIGKILLed mid-build is taken over and the version is built once, the previous
version serving until then; a Redis restart that loses the queued import loses no library.
Takes: a 12-take generated library (``dancegraph.motion.demo``), its graph's arrays under the S3
store's multipart threshold; the stuck timeout is 20 s here (the reaper also aborts multipart
uploads older than twice the timeout, which a build's upload must outlast)."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import httpx
import pytest

from dancegraph.motion.demo import write_demo_library
from tests.conftest import S3_ENV, new_bucket
from tests.services.test_worker_harness import (
    REDIS_DB,
    VENV_BIN,
    create_key,
    create_pg_database,
    drop_pg_database,
    flush_redis,
    make_cluster,
    redis_url,
    require_servers,
    restart_redis,
    wait_for,
)

pytestmark = [pytest.mark.services, pytest.mark.slow]


@pytest.fixture(scope="module")
def takes(tmp_path_factory) -> Path:
    return write_demo_library(tmp_path_factory.mktemp("takes") / "lib", n_takes=12)


@pytest.fixture(scope="module", params=["fs", "s3"])
def cluster(request, tmp_path_factory):
    require_servers()
    flush_redis()
    home = tmp_path_factory.mktemp(f"libraries-{request.param}")
    url = create_pg_database()
    with pytest.MonkeyPatch.context() as mp:
        if request.param == "fs":
            c = make_cluster(home, url, redis_url(), home / "store")
        else:
            endpoint = request.getfixturevalue("s3_endpoint")
            store_env = {"AWS_ENDPOINT_URL": endpoint, **S3_ENV}
            for name, value in store_env.items():
                mp.setenv(name, value)
            bucket = new_bucket(endpoint)
            c = make_cluster(
                home, url, redis_url(), home / "scratch", f"s3://{bucket}/store", store_env
            )
        c.env["DANCEGRAPH_JOB_TIMEOUT_S"] = "20"
        try:
            c.api_key = create_key(url, "studio")
            c.start_api()
            c._spawn("reaper", [str(VENV_BIN / "dancegraph"), "reaper", "--interval", "1"])
            c.start_worker("w1")
            yield c
        finally:
            c.stop_all()
    drop_pg_database(url)
    flush_redis()


def upload(cluster, folder: Path, name: str) -> dict:
    files = [("name", (None, name))]
    files.append(
        ("manifest", ("manifest.json", (folder / "manifest.json").read_bytes(), "application/json"))
    )
    files += [
        ("takes", (p.name, p.read_bytes(), "application/octet-stream"))
        for p in sorted(folder.glob("*.bvh"))
    ]
    r = httpx.post(
        cluster.api_url + "/v1/datasets", headers=cluster.headers(), files=files, timeout=120
    )
    assert r.status_code == 202, r.text
    return r.json()


def library(cluster, name: str) -> dict:
    r = httpx.get(f"{cluster.api_url}/v1/datasets/{name}", headers=cluster.headers(), timeout=30)
    assert r.status_code == 200, r.text
    return r.json()


def wait_built(cluster, name: str, version: str, timeout_s: float = 300) -> dict:
    def done():
        body = library(cluster, name)
        return (
            body
            if body["version"] == version and body["status"] in ("succeeded", "failed")
            else None
        )

    return wait_for(done, timeout_s, f"library {name} {version} to be built", interval_s=0.5)


def row(cluster, version: str):
    from services.db import session_scope
    from services.models import Dataset

    with session_scope(cluster.database_url) as session:
        got = session.query(Dataset).filter_by(version=version).one()
        session.expunge(got)
        return got


def usable_version(cluster, name: str) -> str:
    from services.common import libraries
    from services.db import session_scope
    from services.models import Tenant

    with session_scope(cluster.database_url) as session:
        tenant = session.query(Tenant).filter_by(name="studio").one()
        return libraries.usable_row(session, tenant.id, name).version


def test_worker_killed_mid_build_resumes_and_the_previous_version_serves(cluster, takes):
    v1 = upload(cluster, takes, "big")["version"]
    assert wait_built(cluster, "big", v1)["status"] == "succeeded"
    v2 = upload(cluster, takes, "big")["version"]

    def mid_build():
        r = row(cluster, v2)
        return r.status == "running" and r.stage in ("fetch", "import", "build")

    wait_for(mid_build, 120, "the import to be under way", interval_s=0.05)
    cluster.kill("w1")  # SIGKILL to the worker's process group
    assert row(cluster, v2).status == "running"
    assert usable_version(cluster, "big") == v1  # the previous version keeps serving
    cluster.start_worker("w2")
    got = wait_built(cluster, "big", v2)
    assert got["status"] == "succeeded", (got, cluster.log_text("w2")[-4000:])
    r = row(cluster, v2)
    assert r.attempts == 2 and r.crashes == 1
    assert usable_version(cluster, "big") == v2
    logs = cluster.log_text("w1") + cluster.log_text("w2")
    built = [json.loads(line) for line in logs.splitlines() if '"library built"' in line]
    assert [e["dataset_row"] for e in built].count(r.id) == 1  # published once
    store = cluster.store
    assert store.exists(f"graphs/{r.graph_name}/current")
    cluster.procs["w1"] = cluster.procs.pop("w2")
    cluster.logs["w1"] = cluster.logs["w2"]


def test_redis_restart_while_an_import_waits_loses_no_library(cluster, takes):
    import redis

    cluster.kill("w1", sig=signal.SIGTERM)  # no worker: the import waits in Redis
    version = upload(cluster, takes, "waiting")["version"]
    r = redis.Redis(host="127.0.0.1", port=6379, db=REDIS_DB)
    assert r.llen("analysis") == 1
    restart_redis()  # no persistence: the message is gone
    r = redis.Redis(host="127.0.0.1", port=6379, db=REDIS_DB)
    assert r.llen("analysis") == 0
    assert row(cluster, version).status == "queued"
    cluster.start_worker("w3")
    assert wait_built(cluster, "waiting", version)["status"] == "succeeded"
