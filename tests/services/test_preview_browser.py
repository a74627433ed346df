"""The preview page in real headless Chromium: a job's ``preview_url`` opened with no API key (the
signed token), served by the API under uvicorn, driven by ``frontend/tests/browser.mjs``
(playwright-core on Debian's /usr/bin/chromium).

Skipped only where Chromium, Node.js or the built front end is missing; with
``DANCEGRAPH_REQUIRE_BROWSER=1`` (set by .ci/run, which installs Chromium) it fails instead.
The screenshot goes to ``$DANCEGRAPH_TEST_ARTIFACTS`` (default ``test-artifacts/``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from dancegraph.preview import pose_track_file
from tests.services.preview_result import switch_time, synthesized
from tests.services.test_preview import finish_with, page_config
from tests.services.test_worker_harness import free_port

REPO = Path(__file__).resolve().parents[2]
FRONTEND = REPO / "frontend"
CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")


def _require_browser() -> str:
    from services.preview_server import STATIC_DIR

    node = shutil.which("node")
    missing = [
        what
        for what, ok in (
            (f"chromium ({CHROMIUM}; apt-get install chromium)", Path(CHROMIUM).is_file()),
            ("node", node is not None),
            (
                "playwright-core (bash scripts/install-frontend.sh)",
                (FRONTEND / "node_modules/playwright-core").is_dir(),
            ),
            (
                "the built page (bash scripts/install-frontend.sh)",
                (STATIC_DIR / "preview.js").is_file(),
            ),
        )
        if not ok
    ]
    if missing:
        reason = "browser test needs " + ", ".join(missing)
        if os.environ.get("DANCEGRAPH_REQUIRE_BROWSER") == "1":
            pytest.fail(reason + " (DANCEGRAPH_REQUIRE_BROWSER=1)")
        pytest.skip(reason)
    return node


def _serve(app):
    """Run ``app`` under uvicorn in a thread; returns (base URL, stop function)."""
    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("the test server did not start")
        time.sleep(0.05)

    def stop() -> None:
        server.should_exit = True
        thread.join(10)

    return f"http://127.0.0.1:{port}", stop


def _browse(node: str, app, path: str, shot: Path, switch_s: float) -> dict:
    """Serve ``app``, drive the page at ``path`` in Chromium (``tests/browser.mjs``); what it saw."""
    base, stop = _serve(app)
    try:
        run = subprocess.run(
            [node, "tests/browser.mjs", base + path, str(shot), str(switch_s)],
            cwd=FRONTEND,
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "CHROMIUM": CHROMIUM},
        )
    finally:
        stop()
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


def _moved(a: list[float], b: list[float]) -> float:
    """Largest joint displacement (m) between two poses."""
    return float(np.abs(np.asarray(a) - np.asarray(b)).max())


def test_preview_page_in_chromium(api, tmp_path_factory):
    node = _require_browser()
    root = synthesized(tmp_path_factory)
    timeline = json.loads((root / "out/timeline.json").read_text())
    job_id = api.submit((root / "song.wav").read_bytes(), {"alternatives": 2}).json()["id"]
    finish_with(api, job_id, root / "out")
    preview_url = api.get(f"/v1/jobs/{job_id}").json()["preview_url"]

    artifacts = Path(os.environ.get("DANCEGRAPH_TEST_ARTIFACTS", REPO / "test-artifacts"))
    artifacts.mkdir(parents=True, exist_ok=True)
    shot = artifacts / "preview.png"
    shot.unlink(missing_ok=True)
    t_switch = switch_time(timeline)
    seen = _browse(node, api.app, preview_url, shot, t_switch)

    # loads cleanly: no console errors, no page errors, every request answered
    assert seen["error"] is None
    assert seen["console_errors"] == [] and seen["page_errors"] == []
    assert seen["failed_requests"] == []
    assert seen["alternatives"] == 2
    # the WebGL canvas shows something: grid, stage, skeleton (many pixels, many colours)
    canvas = seen["canvas"]
    assert canvas["non_background"] > 0.01 * canvas["width"] * canvas["height"]
    assert canvas["colours"] > 20
    # seeking moves the skeleton; the current bar follows the clock
    a, b = seen["seek_a"], seen["seek_b"]
    joints = pose_track_file(root / "out/alternatives/0.bvh")["joints"]
    assert len(a["pose"]) == len(b["pose"]) == 3 * len(joints)
    assert _moved(a["pose"], b["pose"]) > 0.01
    bars = timeline["bars"]
    expected_bar = next(
        i for i, bar in enumerate(bars) if bar["start_s"] <= t_switch < bar["end_s"]
    )
    assert b["bar"] == expected_bar and seen["current_bars"] == [expected_bar]
    # real playback: the audio clock advances and the drawn pose follows it
    play = seen["play"]
    assert seen["play_error"] is None
    assert play["after"]["time"] - play["before"]["time"] > 0.5
    assert _moved(play["before"]["pose"], play["after"]["pose"]) > 0.005
    # switching the alternative at the same time changes the pose
    switch = seen["switch"]
    assert switch["after"]["alternative"] == 1 and switch["after"]["selected"] == "1"
    assert _moved(switch["before"]["pose"], switch["after"]["pose"]) > 0.01
    # clicking bar 1 shows its cost breakdown (of alternative 1, the one shown)
    cost = timeline["alternatives"][1]["bars"][1]["cost"]
    rows = dict(row.split("\t") for row in seen["breakdown"]["rows"][1:])
    assert {k: float(v) for k, v in rows.items() if k != "sum"} == pytest.approx(cost, abs=1e-4)
    assert timeline["alternatives"][1]["bars"][1]["node"] in seen["breakdown"]["text"]
    assert shot.is_file() and shot.stat().st_size > 10_000
    assert seen["rig"] is None  # no rig files: no Skeleton switch


def test_preview_page_switches_to_the_rig_in_chromium(tmp_path_factory, tmp_path):
    """A ``synthesize --rig`` folder in ``dancegraph preview``: the page draws the rig's joints."""
    from dancegraph.motion.bvh import read_bvh
    from dancegraph.motion.retarget import RigOutput
    from dancegraph.motion.rig import load_rig
    from services.preview_server import create_local_app
    from tests.motion.rigs import make_rigs

    node = _require_browser()
    root = synthesized(tmp_path_factory)
    out = tmp_path / "out"
    shutil.copytree(root / "out", out)
    rig_path = make_rigs(tmp_path / "rigs", blender=False) / "cmu_cm.bvh"
    rig = load_rig(rig_path)
    hook = RigOutput(rig, rig_path, ["bvh"])
    timeline = json.loads((out / "timeline.json").read_text())
    for k in range(2):
        timeline["alternatives"][k]["rig"] = hook(k, read_bvh(out / f"alternatives/{k}.bvh"), out)[
            1
        ]
    (out / "timeline.json").write_text(json.dumps(timeline))
    app = create_local_app(out, root / "song.wav")
    seen = _browse(node, app, "/", tmp_path / "shot.png", 1.0)
    assert seen["error"] is None and seen["console_errors"] == [] and seen["page_errors"] == []
    library_joints = pose_track_file(out / "alternatives/0.bvh")["joints"]
    rig_joints = pose_track_file(out / "alternatives/1.rig.bvh", 0.01)["joints"]
    assert seen["rig"]["before"] == 3 * len(library_joints)
    pose = np.asarray(seen["rig"]["after"]).reshape(-1, 3)
    assert len(pose) == len(rig_joints) != len(library_joints)
    assert 0.5 < pose[rig.joint("hips"), 1] < 1.3  # metres: the centimetre rig drawn to scale


def test_preview_page_shows_the_character_in_chromium(tmp_path_factory, tmp_path):
    """A result on a rig with a skinned mesh: the page opens on the character (its ``.rig.glb``
    skinned by three.js), standing on the floor at its size; one click shows the skeleton."""
    from dancegraph.motion.bvh import read_bvh
    from dancegraph.motion.fbx import fbx_available
    from dancegraph.motion.retarget import RigOutput
    from dancegraph.motion.rig import load_rig
    from services.preview_server import create_local_app
    from tests.motion.rigs import make_rigs

    node = _require_browser()
    if not fbx_available():
        pytest.skip("the skinned test rig is made by Blender (scripts/install-blender.sh)")
    root = synthesized(tmp_path_factory)
    out = tmp_path / "out"
    shutil.copytree(root / "out", out)
    rig_path = make_rigs(tmp_path / "rigs") / "parented.glb"  # cm, Z up under a parent node
    rig = load_rig(rig_path)
    hook = RigOutput(rig, rig_path, ["bvh", "glb"])
    for k in range(2):
        hook(k, read_bvh(out / f"alternatives/{k}.bvh"), out)
    artifacts = Path(os.environ.get("DANCEGRAPH_TEST_ARTIFACTS", REPO / "test-artifacts"))
    artifacts.mkdir(parents=True, exist_ok=True)
    shot = artifacts / "preview-rig.png"  # the character's: preview-rig-character.png
    seen = _browse(node, create_local_app(out, root / "song.wav"), "/", shot, 1.0)
    assert seen["error"] is None and seen["console_errors"] == [] and seen["page_errors"] == []
    assert seen["failed_requests"] == []
    shown, toggled = seen["character"]["shown"], seen["character"]["toggled"]
    assert shown["view"] == "character" and shown["box"] is not None
    low, high = np.asarray(shown["box"]["min"]), np.asarray(shown["box"]["max"])
    assert abs(low[1] - rig.floor) < 0.05  # on the floor, in metres (not centimetres)
    assert 0.8 * rig.height() < high[1] - low[1] < 1.2 * rig.height()  # upright, at its size
    assert toggled["view"] == "skeleton" and toggled["box"] is None
    assert Path(seen["character"]["screenshot"]).stat().st_size > 10_000
    assert seen["rig"] is not None  # the skeleton switch still works beside it


@pytest.fixture(scope="module")
def couple_result(salsa_dir: Path, tmp_path_factory) -> tuple[Path, Path]:
    """``dancegraph synthesize --couple`` (2 alternatives) of the generated test song on the
    couple graph of two real salsa pairs (60_03/61_03, 60_04/61_04): (output folder, song)."""
    from dancegraph.cli import main
    from dancegraph.couple.graph import build_couple_graph
    from dancegraph.motion.dataset import import_dataset
    from dancegraph.store import FileStore
    from tests.demo import demo_song
    from tests.services.test_worker_couple import MANIFEST

    root = tmp_path_factory.mktemp("couple_preview")
    store = FileStore(root / "store")
    import_dataset(salsa_dir, "pairs", store, MANIFEST)
    build_couple_graph(store, "pairs")
    wav, _ = demo_song(root)
    spec = root / "spec.json"
    spec.write_text(json.dumps({"output": {"formats": ["bvh"]}, "alternatives": 2}))
    argv = ["synthesize", str(wav), "--dataset", "pairs", "--couple", "--out", str(root / "out")]
    assert main([*argv, "--spec", str(spec), "--store", str(store.root)]) == 0
    return root / "out", wav


def test_preview_page_draws_a_couple_in_chromium(api, couple_result):
    """A couple job's preview (``alternatives/<k>/lead.bvh``, ``follow.bvh``) draws two
    skeletons in one world: each pose the page draws is its BVH's, the hips 0.2-1.9 m apart
    (the library's p1-p99 band is 0.200-1.869 m)."""
    from services.preview_server import create_local_app

    node = _require_browser()
    out, wav = couple_result
    job_id = api.submit(wav.read_bytes(), {"alternatives": 2}).json()["id"]
    finish_with(api, job_id, out)
    preview_url = api.get(f"/v1/jobs/{job_id}").json()["preview_url"]
    artifacts = Path(os.environ.get("DANCEGRAPH_TEST_ARTIFACTS", REPO / "test-artifacts"))
    artifacts.mkdir(parents=True, exist_ok=True)
    shot = artifacts / "preview-couple.png"
    shot.unlink(missing_ok=True)
    seen = _browse(node, api.app, preview_url, shot, 1.5)
    assert seen["error"] is None and seen["console_errors"] == [] and seen["page_errors"] == []
    assert seen["failed_requests"] == [] and seen["alternatives"] == 2
    assert seen["couple"]["skeletons"] == 2
    tracks = {p: pose_track_file(out / f"alternatives/0/{p}.bvh") for p in ("lead", "follow")}
    follow_first = tracks["follow"]["positions"]
    for at in seen["couple"]["at"]:
        drawn = {"lead": at["pose"], "follow": at["follow"]}
        for partner, track in tracks.items():
            frame = min(round(at["time"] * track["fps"]), track["frames"] - 1)
            n = 3 * len(track["joints"])
            want = np.asarray(track["positions"][frame * n : (frame + 1) * n]) / 1000.0
            assert _moved(drawn[partner], want) < 0.1  # the file's pose, within a frame's motion
        hips = np.linalg.norm(np.subtract(at["pose"][:3], at["follow"][:3]))
        assert 0.2 < hips < 1.9
    assert shot.is_file() and shot.stat().st_size > 10_000
    poses = f"/v1/jobs/{job_id}/preview/poses/0.json"
    assert api.get(poses + "?partner=follow").json()["positions"][:n] == follow_first[:n]
    missing = api.get(poses)  # a couple has no solo alternatives/0.bvh
    assert missing.status_code == 404 and missing.json()["code"] == "result_not_found"
    assert api.get(poses + "?partner=both").status_code == 422
    # the local server of the same folder names both dancers' tracks; a solo name is a 404
    from fastapi.testclient import TestClient

    local = TestClient(create_local_app(out, wav))
    config = page_config(local.get("/").text)
    assert config["poses"][1] == "poses/1.json?partner=lead"
    assert config["follow_poses"][1] == "poses/1.json?partner=follow"
    follow = local.get(config["follow_poses"][0]).json()
    assert follow["positions"][:n] == tracks["follow"]["positions"][:n]
    assert local.get("/poses/0.json").status_code == 404
    assert local.get("/poses/0.json?partner=both").status_code == 422
