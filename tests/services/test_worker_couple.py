"""A couple job through the API and the worker (SQLite embedded default, ``run_job`` in this
process): two partner pairs of the shared salsa takes imported as the test dataset, its solo
and couple graphs built; ``spec.couple`` answers with each alternative's lead and follow."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dancegraph.couple.graph import build_couple_graph
from dancegraph.graph.build import build_graph
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.dataset import import_dataset, load_dataset
from services.worker import pipeline
from tests.demo import demo_song
from tests.motion.rigs import make_rigs

MANIFEST = {
    "files": "6?_0[34]_scaled.bvh",
    "strip_suffix": "_scaled",
    "fps": 60,
    "fps_reason": "captured at 60 fps",
    "style": "salsa",
    "tempo_prior_bpm": [150, 220],
    "partners": [["60_03", "61_03"], ["60_04", "61_04"]],
}


def couple_library(api, salsa_dir: Path) -> None:
    """Import the two salsa pairs (``MANIFEST``) as the test dataset of ``api``'s store and
    build its solo and couple graphs."""
    from tests.services.conftest import TEST_DATASET

    store = api.app.state.ctx.store
    import_dataset(salsa_dir, TEST_DATASET, store, MANIFEST)
    build_graph(load_dataset(store, TEST_DATASET), store)
    build_couple_graph(store, TEST_DATASET)


def upload_rig(api, folder: Path) -> tuple[Path, str]:
    """The generated centimetre rig ``cmu_cm.bvh`` written into ``folder`` and registered
    through ``POST /v1/rigs``; its file and id."""
    rig_file = make_rigs(folder, blender=False) / "cmu_cm.bvh"
    files = [("rig", (rig_file.name, rig_file.read_bytes(), "application/octet-stream"))]
    return rig_file, api.post("/v1/rigs", files=files).json()["id"]


def test_a_couple_job_returns_both_dancers(sqlite_api, salsa_dir: Path, tmp_path: Path):
    from tests.services.conftest import TEST_DATASET

    couple_library(sqlite_api, salsa_dir)
    wav, song = demo_song(tmp_path)
    _, rig = upload_rig(sqlite_api, tmp_path / "rigs")
    unknown = {"dataset": TEST_DATASET, "couple": True, "output": {"follow_rig": "nope"}}
    refused = sqlite_api.submit(wav.read_bytes(), unknown)
    assert refused.status_code == 422 and refused.json()["code"] == "unknown_rig"
    spec = {
        "dataset": TEST_DATASET,
        "couple": True,
        "alternatives": 2,
        "output": {"formats": ["bvh"], "follow_rig": rig},
    }
    resp = sqlite_api.submit(wav.read_bytes(), spec)
    assert resp.status_code == 202, resp.text
    job_id = resp.json()["id"]
    assert pipeline.run_job(job_id, sqlite_api.settings).status == "succeeded"
    timeline = sqlite_api.get(f"/v1/jobs/{job_id}/timeline.json").json()
    assert timeline["couple"] is True and len(timeline["alternatives"]) == 2
    n_frames = round(song.duration_s * 30)
    for k in range(2):
        got = {}
        for partner in ("lead", "follow"):
            resp = sqlite_api.get(f"/v1/jobs/{job_id}/alternatives/{k}/{partner}.bvh")
            assert resp.status_code == 200, resp.text
            (tmp_path / f"{k}-{partner}.bvh").write_bytes(resp.content)
            got[partner] = read_bvh(tmp_path / f"{k}-{partner}.bvh")
        assert got["lead"].n_frames == got["follow"].n_frames == n_frames
        hips = np.linalg.norm(got["lead"].root_positions - got["follow"].root_positions, axis=1)
        assert 0.1 < np.median(hips) < 1.5
        # the follow on its rig (output.follow_rig), both dancers in one GLB; no lead rig asked
        on_rig = sqlite_api.get(f"/v1/jobs/{job_id}/alternatives/{k}/follow.rig.bvh")
        assert on_rig.status_code == 200, on_rig.text
        lead_rig = sqlite_api.get(f"/v1/jobs/{job_id}/alternatives/{k}/lead.rig.bvh")
        assert lead_rig.status_code == 404
        glb = sqlite_api.get(f"/v1/jobs/{job_id}/alternatives/{k}/couple.glb")
        assert glb.status_code == 200 and glb.content[:4] == b"glTF"
    missing = sqlite_api.get(f"/v1/jobs/{job_id}/alternatives/5/lead.bvh")
    assert missing.status_code == 404 and missing.json()["code"] == "result_not_found"
    bad = sqlite_api.get(f"/v1/jobs/{job_id}/alternatives/0/partner.bvh")
    assert bad.status_code == 422
