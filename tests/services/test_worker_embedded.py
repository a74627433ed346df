"""The embedded default end to end: ``dancegraph serve --embedded`` alone (SQLite, filesystem
broker, in-process graph store, worker child, reaper thread) runs a real job through the API."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
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
    from dancegraph.motion.fk import forward_kinematics
    from dancegraph.motion.usd import joint_world_positions

    wav = write_test_song(songs, seed=3, seconds=12.0, name="embedded")
    spec = {"dataset": DATASET, "alternatives": 2, "output": {"formats": ["bvh", "usd"]}}
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
        # the same dance as USD (output.formats usd), downloaded through the API
        usd = tmp_path / f"{k}.usd"
        usd.write_bytes(embedded.download(job_id, f"alternatives/{k}.usd"))
        _, got = joint_world_positions(usd, [0, motion.n_frames - 1])
        pos, _ = forward_kinematics(motion)
        assert np.abs(got - pos[[0, -1]]).max() < 1e-3
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


def test_job_on_a_rig_in_embedded_mode(embedded, songs, tmp_path):  # noqa: F811
    """A rig uploaded through the API, a job naming it: the dance on the rig beside the library's."""
    import httpx

    from dancegraph.motion.bvh import read_bvh
    from dancegraph.motion.fbx import fbx_available
    from dancegraph.motion.rig import load_rig
    from tests.motion.rigs import make_rigs

    rigs = make_rigs(tmp_path / "rigs", blender=False)
    with open(rigs / "cmu_cm.bvh", "rb") as fh:
        r = httpx.post(
            f"{embedded.api_url}/v1/rigs",
            headers=embedded.headers(),
            files={"rig": ("cmu_cm.bvh", fh)},
            timeout=60,
        )
    assert r.status_code == 201, r.text
    rig_id = r.json()["id"]
    formats = ["bvh", "fbx"] if fbx_available() else ["bvh"]
    wav = write_test_song(songs, seed=5, seconds=12.0, name="on-rig")
    spec = {"dataset": DATASET, "alternatives": 1, "output": {"formats": formats, "rig": rig_id}}
    job_id = embedded.submit(wav, spec)["id"]
    job = embedded.wait_final([job_id], timeout_s=600)[job_id]
    assert job["status"] == "succeeded", job
    rig = load_rig(rigs / "cmu_cm.bvh")
    path = tmp_path / "0.rig.bvh"
    path.write_bytes(embedded.download(job_id, "alternatives/0.rig.bvh"))
    on_rig = read_bvh(path, scale=rig.unit_scale)
    library = tmp_path / "0.bvh"
    library.write_bytes(embedded.download(job_id, "alternatives/0.bvh"))
    assert on_rig.skeleton.names == rig.skeleton.names
    assert on_rig.n_frames == read_bvh(library).n_frames
    assert embedded.download(job_id, "alternatives/0.rig.glb")[:4] == b"glTF"
    if "fbx" in formats:
        assert len(embedded.download(job_id, "alternatives/0.rig.fbx")) > 10_000
    timeline = json.loads(embedded.download(job_id, "timeline.json"))
    assert timeline["alternatives"][0]["rig"]["floor_error_m"]["max_abs"] <= 0.01


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
