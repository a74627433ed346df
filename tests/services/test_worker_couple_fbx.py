"""FBX for a couple job through the API and the worker's fbx stage (SQLite embedded default,
``run_job`` then ``run_fbx`` in this process, Blender): two real salsa partner pairs imported as
the test dataset; each dancer's ``alternatives/<k>/<partner>.fbx`` read back with ufbx holds
that dancer's BVH to the millimetre, ``alternatives/<k>/couple.fbx`` both dancers, and with
``output.rig`` / ``output.follow_rig`` each ``<partner>.rig.fbx`` its ``<partner>.rig.bvh``."""

from __future__ import annotations

from pathlib import Path

import pytest

from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fbx import fbx_available
from services.worker import pipeline
from tests.demo import demo_song
from tests.services.test_worker_couple import couple_library, upload_rig

pytest.importorskip("ufbx")


def _download(api, url: str, path: Path) -> Path:
    """The result at ``url`` (200 asserted), written to ``path``."""
    resp = api.get(url)
    assert resp.status_code == 200, resp.text
    path.write_bytes(resp.content)
    return path


def test_a_couple_job_gets_an_fbx_per_dancer(sqlite_api, salsa_dir: Path, tmp_path: Path):
    from tests.couple.test_couple_fbx import check_couple_fbx
    from tests.motion.test_fbx import check_fbx_against_fk
    from tests.services.conftest import TEST_DATASET

    if not fbx_available():
        pytest.skip("Blender's Python not installed (scripts/install-blender.sh)")
    couple_library(sqlite_api, salsa_dir)
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
            got = {
                fmt: _download(sqlite_api, f"{base}.{fmt}", tmp_path / f"{k}-{partner}.{fmt}")
                for fmt in ("bvh", "fbx")
            }
            dancers[partner] = read_bvh(got["bvh"])
            worst = check_fbx_against_fk(got["fbx"], dancers[partner])
            assert worst < 1e-3
        url = f"/v1/jobs/{job_id}/alternatives/{k}/couple.fbx"
        both = _download(sqlite_api, url, tmp_path / f"{k}-couple.fbx")
        n = dancers["lead"].n_frames
        check_couple_fbx(both, dancers, [0, n // 3, n // 2, n - 1])
    missing = sqlite_api.get(f"/v1/jobs/{job_id}/alternatives/2/follow.fbx")
    assert missing.status_code == 404 and missing.json()["code"] == "result_not_found"


def test_a_couple_job_gets_each_dancer_on_its_rig_as_fbx(
    sqlite_api, salsa_dir: Path, tmp_path: Path
):
    """``output.rig`` (lead) and ``output.follow_rig`` (follow) with ``fbx``: each dancer's
    ``alternatives/<k>/<partner>.rig.fbx`` is the rig's own file posed in Blender, every joint
    within 1 mm of its ``<partner>.rig.bvh`` (read at the rig's unit scale) at three frames."""
    import numpy as np

    from dancegraph.motion.fk import forward_kinematics
    from dancegraph.motion.rig import load_rig
    from tests.motion.test_retarget import _UFBX_READER
    from tests.motion.ufbx_child import ufbx_json
    from tests.services.conftest import TEST_DATASET

    if not fbx_available():
        pytest.skip("Blender's Python not installed (scripts/install-blender.sh)")
    couple_library(sqlite_api, salsa_dir)
    wav, _ = demo_song(tmp_path)
    rig_file, rig_id = upload_rig(sqlite_api, tmp_path / "rigs")
    output = {"formats": ["bvh", "fbx"], "rig": rig_id, "follow_rig": rig_id}
    spec = {"dataset": TEST_DATASET, "couple": True, "alternatives": 1, "output": output}
    resp = sqlite_api.submit(wav.read_bytes(), spec)
    assert resp.status_code == 202, resp.text
    job_id = resp.json()["id"]
    assert pipeline.run_job(job_id, sqlite_api.settings).status == "fbx_queued"
    assert pipeline.run_fbx(job_id, sqlite_api.settings).status == "succeeded"
    rig = load_rig(rig_file)
    for partner in ("lead", "follow"):
        base = f"/v1/jobs/{job_id}/alternatives/0/{partner}.rig"
        got = {
            fmt: _download(sqlite_api, f"{base}.{fmt}", tmp_path / f"{partner}.rig.{fmt}")
            for fmt in ("bvh", "fbx")
        }
        motion = read_bvh(got["bvh"], scale=rig.unit_scale)
        frames = [0, motion.n_frames // 2, motion.n_frames - 1]
        fbx = ufbx_json(_UFBX_READER, got["fbx"], frames)
        assert round(fbx["duration"] * fbx["fps"]) + 1 == motion.n_frames
        positions, _ = forward_kinematics(motion)
        for f in frames:
            drawn = fbx["positions"][str(f)]
            err = max(
                np.linalg.norm(np.array(drawn[n]) - positions[f, j])
                for j, n in enumerate(rig.skeleton.names)
            )
            assert err < 1e-3, (partner, f, err)
