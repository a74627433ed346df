"""FBX for a couple job through the API and the worker's fbx stage (SQLite embedded default,
``run_job`` then ``run_fbx`` in this process, Blender): two real salsa partner pairs imported as
the test dataset; each dancer's ``alternatives/<k>/<partner>.fbx`` read back with ufbx holds
that dancer's BVH to the millimetre, and ``alternatives/<k>/couple.fbx`` both dancers."""

from __future__ import annotations

from pathlib import Path

import pytest

from dancegraph.couple.graph import build_couple_graph
from dancegraph.graph.build import build_graph
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.dataset import import_dataset, load_dataset
from dancegraph.motion.fbx import fbx_available
from services.worker import pipeline
from tests.demo import demo_song
from tests.services.test_worker_couple import MANIFEST

pytest.importorskip("ufbx")


def test_a_couple_job_gets_an_fbx_per_dancer(sqlite_api, salsa_dir: Path, tmp_path: Path):
    from tests.couple.test_couple_fbx import check_couple_fbx
    from tests.motion.test_fbx import check_fbx_against_fk
    from tests.services.conftest import TEST_DATASET

    if not fbx_available():
        pytest.skip("Blender's Python not installed (scripts/install-blender.sh)")
    store = sqlite_api.app.state.ctx.store
    import_dataset(salsa_dir, TEST_DATASET, store, MANIFEST)
    build_graph(load_dataset(store, TEST_DATASET), store)
    build_couple_graph(store, TEST_DATASET)
    wav, _ = demo_song(tmp_path)
    spec = {"dataset": TEST_DATASET, "couple": True, "alternatives": 2}
    spec["output"] = {"formats": ["bvh", "fbx"]}
    resp = sqlite_api.submit(wav.read_bytes(), spec)
    assert resp.status_code == 202, resp.text
    job_id = resp.json()["id"]
    assert pipeline.run_job(job_id, sqlite_api.settings).status == "fbx_queued"
    waiting = sqlite_api.get(f"/v1/jobs/{job_id}/alternatives/0/lead.fbx")
    assert waiting.status_code == 409  # not finished before its FBX are written
    assert pipeline.run_fbx(job_id, sqlite_api.settings).status == "succeeded"
    for k in range(2):
        dancers = {}
        for partner in ("lead", "follow"):
            base = f"/v1/jobs/{job_id}/alternatives/{k}/{partner}"
            got = {}
            for fmt in ("bvh", "fbx"):
                resp = sqlite_api.get(f"{base}.{fmt}")
                assert resp.status_code == 200, resp.text
                got[fmt] = tmp_path / f"{k}-{partner}.{fmt}"
                got[fmt].write_bytes(resp.content)
            dancers[partner] = read_bvh(got["bvh"])
            worst = check_fbx_against_fk(got["fbx"], dancers[partner])
            assert worst < 1e-3
        both = sqlite_api.get(f"/v1/jobs/{job_id}/alternatives/{k}/couple.fbx")
        assert both.status_code == 200, both.text
        (tmp_path / f"{k}-couple.fbx").write_bytes(both.content)
        n = dancers["lead"].n_frames
        check_couple_fbx(tmp_path / f"{k}-couple.fbx", dancers, [0, n // 3, n // 2, n - 1])
    missing = sqlite_api.get(f"/v1/jobs/{job_id}/alternatives/2/follow.fbx")
    assert missing.status_code == 404 and missing.json()["code"] == "result_not_found"
