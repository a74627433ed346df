"""The embedded default end to end: ``dancegraph serve --embedded`` alone (SQLite, filesystem
broker, in-process graph store, worker child, reaper thread) runs a real job through the API."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.services.test_worker_harness import (  # noqa: F401 (fixtures)
    DATASET,
    copy_store,
    create_key,
    demo_store,
    make_cluster,
    songs,
    write_test_song,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def embedded(tmp_path_factory, demo_store):  # noqa: F811
    home = tmp_path_factory.mktemp("embedded")
    store_root = copy_store(demo_store, home / "store")
    db_url = f"sqlite:///{home / 'dancegraph.db'}"  # where serve --embedded puts it
    c = make_cluster(home, db_url, "filesystem://", store_root)
    for name in ("DANCEGRAPH_DATABASE_URL", "DANCEGRAPH_BROKER_URL", "DANCEGRAPH_BROKER_FOLDER"):
        c.env.pop(name)  # --embedded chooses them itself, under DANCEGRAPH_HOME
    try:  # a start that times out still stops what it started (no orphans loading the machine)
        c.start_embedded()
        c.api_key = create_key(db_url, "acme")
        yield c
    finally:
        c.stop_all()


def test_job_through_api_in_embedded_mode(embedded, songs, tmp_path):  # noqa: F811
    from dancegraph.motion.bvh import read_bvh

    wav = write_test_song(songs, seed=3, seconds=12.0, name="embedded")
    spec = {"dataset": DATASET, "alternatives": 2, "output": {"formats": ["bvh"]}}
    job_id = embedded.submit(wav, spec)["id"]
    job = embedded.wait_final([job_id], timeout_s=300)[job_id]
    assert job["status"] == "succeeded", job
    assert job["analysis"]["n_bars"] >= 4
    costs = [a["cost"] for a in job["alternatives"]]
    assert len(costs) == 2 and costs == sorted(costs)
    for k in range(2):
        path = tmp_path / f"{k}.bvh"
        path.write_bytes(embedded.download(job_id, f"alternatives/{k}.bvh"))
        motion = read_bvh(path)
        assert motion.n_frames > 30
    timeline = json.loads(embedded.download(job_id, "timeline.json"))
    assert [a["index"] for a in timeline["alternatives"]] == [0, 1]
    # the embedded default really ran without servers: SQLite file and broker folders exist
    home = Path(embedded.env["DANCEGRAPH_HOME"])
    assert (home / "dancegraph.db").is_file() and (home / "broker" / "queue").is_dir()
    assert (embedded.store_root / "analysis").is_dir()


def test_cancel_while_running_stops_the_worker_and_publishes_nothing(embedded, songs):  # noqa: F811
    import httpx

    from tests.services.test_worker_harness import job_row, wait_for

    # A new 2-minute song: its analysis (about a second warm) is the window the cancel lands in.
    wav = write_test_song(songs, seed=11, seconds=120.0, name="cancel-me")
    spec = {"dataset": DATASET, "alternatives": 1, "output": {"formats": ["bvh"]}}
    job_id = embedded.submit(wav, spec)["id"]
    wait_for(
        lambda: job_row(embedded.database_url, job_id).stage == "analyze",
        120,
        "analysis to start",
        interval_s=0.02,
    )
    r = httpx.delete(f"{embedded.api_url}/v1/jobs/{job_id}", headers=embedded.headers(), timeout=30)
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    wait_for(lambda: "no longer ours" in embedded.log_text("serve"), 120, "the worker to stop")
    row = job_row(embedded.database_url, job_id)
    assert row.status == "cancelled" and row.result is None
    assert not (embedded.store_root / "jobs" / job_id).exists()
    assert not list((embedded.store_root / "tmp").glob(f"job-{job_id}-*"))


def test_killed_serve_leaves_no_worker_behind(embedded):
    """Runs last in this module: SIGKILL only the ``serve`` process; its worker child gets a
    SIGTERM from the kernel (PR_SET_PDEATHSIG) and ends instead of polling its broker forever."""
    import os
    import signal

    from tests.services.test_worker_harness import wait_for

    serve = embedded.procs["serve"]
    children = Path(f"/proc/{serve.pid}/task/{serve.pid}/children").read_text().split()
    assert len(children) == 1, children  # the Celery worker's main process
    worker = int(children[0])
    os.kill(serve.pid, signal.SIGKILL)
    serve.wait(timeout=30)
    wait_for(lambda: not Path(f"/proc/{worker}").exists(), 120, "the worker to stop")
