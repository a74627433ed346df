"""The preview page's server side: pose tracks, the API routes and their auth (API key or signed
token), and the local ``dancegraph preview`` server, on a real synthesize output."""

from __future__ import annotations

import gzip
import json
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fk import forward_kinematics
from dancegraph.preview import find_audio, pose_track_file
from services import jobs
from services.db import session_scope
from services.models import SUCCEEDED
from tests.services.preview_result import synthesized
from tests.services.test_worker_harness import VENV_BIN, free_port, wait_for


@pytest.fixture(scope="module")
def result(tmp_path_factory) -> Path:
    return synthesized(tmp_path_factory)


def finish_with(api, job_id: str, out: Path) -> None:
    """Put a synthesize output where the worker writes a job's results; mark the job succeeded."""
    store = api.app.state.ctx.store
    files = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    folder = store.temp_dir("result")
    shutil.copytree(out, folder, dirs_exist_ok=True)
    assert store.publish(jobs.result_key(job_id), folder)
    timeline = json.loads((out / "timeline.json").read_text())
    alternatives = [
        {"nodes": [b["node"] for b in a["bars"]], "cost": a["cost"], "violations": []}
        for a in timeline["alternatives"]
    ]
    with session_scope(api.settings.database_url) as session:
        assert jobs.claim_job(session, job_id, "test-worker", stale_after_s=600)
        assert jobs.set_status(
            session, job_id, SUCCEEDED, result={"alternatives": alternatives, "files": files}
        )


def page_config(html: str) -> dict:
    found = re.search(r'<script id="preview-config" type="application/json">(.*?)</script>', html)
    assert found, "the page carries its config"
    return json.loads(found.group(1))


@pytest.fixture()
def built():
    """The built page template (scripts/install-frontend.sh); skipped where it is not built."""
    from services.preview_server import STATIC_DIR

    if not (STATIC_DIR / "index.html").is_file():
        if os.environ.get("DANCEGRAPH_REQUIRE_BROWSER") == "1":
            pytest.fail(f"the preview page is not built in {STATIC_DIR}")
        pytest.skip("the preview page is not built (bash scripts/install-frontend.sh)")
    return STATIC_DIR


def test_pose_track_is_forward_kinematics_in_mm(result):
    bvh = result / "out/alternatives/0.bvh"
    track = pose_track_file(bvh)
    motion = read_bvh(bvh)
    positions, _ = forward_kinematics(motion)
    n_joints = len(track["joints"])
    assert n_joints == motion.skeleton.n_joints + len(motion.skeleton.end_sites)
    assert track["frames"] == motion.n_frames and track["fps"] == motion.fps
    assert len(track["parents"]) == n_joints and track["parents"][0] == -1
    assert all(p < j for j, p in enumerate(track["parents"]))  # parents come first
    got = np.array(track["positions"]).reshape(motion.n_frames, n_joints, 3) / 1000.0
    assert np.abs(got[:, : motion.skeleton.n_joints] - positions).max() <= 0.0005 + 1e-9
    # end sites hang below their joint: the bone length is the End Site offset's
    head = motion.skeleton.index("Head")
    end = track["joints"].index("Head_end")
    assert track["parents"][end] == head
    length = np.linalg.norm(got[:, end] - got[:, head], axis=1)
    assert np.allclose(length, np.linalg.norm(motion.skeleton.end_sites[head]), atol=0.002)
    timeline = json.loads((result / "out/timeline.json").read_text())
    assert track["frames"] == timeline["alternatives"][0]["frames"]


def test_find_audio_uses_the_recorded_name_and_hash(result, tmp_path):
    out = result / "out"
    timeline = json.loads((out / "timeline.json").read_text())
    assert find_audio(out, timeline) == (result / "song.wav").resolve()
    # a different file under the same name is not taken for the song
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    (tmp_path / "song.wav").write_bytes(b"RIFF other song")
    with pytest.raises(Exception) as err:
        find_audio(copy, timeline, cwd=tmp_path)
    assert getattr(err.value, "code", None) == "preview_audio_missing"


def test_preview_routes_and_auth(api, result, built):
    from services.api.preview_tokens import make_token

    song = (result / "song.wav").read_bytes()
    job = api.submit(song, {"alternatives": 2}, filename="song.wav").json()
    job_id = job["id"]
    page_url = f"/v1/jobs/{job_id}/preview"
    plain = api.client  # a browser: no API key header

    # before the job succeeds: no preview link, and the page answers 409
    assert api.get(f"/v1/jobs/{job_id}").json()["preview_url"] is None
    early = api.get(page_url)
    assert early.status_code == 409 and early.json()["code"] == "job_not_finished"

    finish_with(api, job_id, result / "out")
    got = api.get(f"/v1/jobs/{job_id}").json()
    assert got["preview_url"].startswith(page_url + "?token=")

    # the link opens the page without a key; the page's data URLs work without a key too
    resp = plain.get(got["preview_url"])
    assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/html")
    config = page_config(resp.text)
    assert config["title"] == "song.wav" and len(config["poses"]) == 2
    timeline = plain.get(config["timeline"])
    assert timeline.status_code == 200
    assert timeline.json() == json.loads((result / "out/timeline.json").read_text())
    audio = plain.get(config["audio"])
    assert audio.status_code == 200 and audio.content == song
    assert audio.headers["content-type"] == "audio/wav"
    ranged = plain.get(config["audio"], headers={"Range": "bytes=0-99"})
    assert ranged.status_code == 206 and ranged.content == song[:100]  # seeking needs ranges
    poses = [plain.get(url).json() for url in config["poses"]]
    assert poses[0] == pose_track_file(result / "out/alternatives/0.bvh")
    assert poses[0]["positions"] != poses[1]["positions"]
    for asset in ("preview.js", "style.css"):
        assert plain.get(f"/preview-static/{asset}").status_code == 200
    assert plain.get("/preview-static/index.html").status_code == 404

    # the API key works as for every job route
    assert api.get(page_url).status_code == 200
    assert api.get(f"{page_url}/poses/1.json").json() == poses[1]

    def problem(resp, status: int, code: str) -> None:
        assert resp.status_code == status, resp.text
        assert resp.headers["content-type"].startswith("application/problem+json")
        assert resp.json()["code"] == code

    # no key, no token → 401; a bad key → 401
    problem(plain.get(page_url), 401, "auth_missing")
    problem(plain.get(f"{page_url}/audio"), 401, "auth_missing")
    problem(plain.get(page_url, headers={"X-API-Key": "dg_nope"}), 401, "auth_invalid")
    # another tenant's key, or a job that does not exist → 404
    stranger = api.new_tenant()
    problem(stranger.get(page_url), 404, "job_not_found")
    problem(api.get("/v1/jobs/00000000-0000-4000-8000-000000000000/preview"), 404, "job_not_found")
    settings = api.settings
    ghost = "00000000-0000-4000-8000-000000000000"
    ghost_token = make_token(settings, ghost)
    problem(plain.get(f"/v1/jobs/{ghost}/preview?token={ghost_token}"), 404, "job_not_found")
    # expired, forged, malformed, or another job's token → 401 with its code (never a 500)
    expired = make_token(settings, job_id, now=time.time() - settings.preview_token_ttl_s - 5)
    problem(plain.get(f"{page_url}?token={expired}"), 401, "preview_token_expired")
    problem(plain.get(f"{page_url}/timeline.json?token={expired}"), 401, "preview_token_expired")
    other = api.submit(song, {"alternatives": 1}).json()["id"]
    problem(
        plain.get(f"{page_url}?token={make_token(settings, other)}"), 401, "preview_token_invalid"
    )
    good = make_token(settings, job_id)
    expires, sig = good.split(".")
    for bad in (f"{int(expires) + 60}.{sig}", "abc", "1.", ".x", "9" * 40 + ".x", good[:-2]):
        problem(plain.get(page_url, params={"token": bad}), 401, "preview_token_invalid")
    problem(plain.get(page_url, params={"token": "x" * 300}), 422, "request_invalid")
    # a valid token for an unfinished job → 409; missing alternative → 404; bad index → 422
    early_token = make_token(settings, other)
    problem(plain.get(f"/v1/jobs/{other}/preview?token={early_token}"), 409, "job_not_finished")
    problem(plain.get(f"{page_url}/poses/7.json?token={good}"), 404, "result_not_found")
    problem(plain.get(f"{page_url}/poses/x.json?token={good}"), 422, "request_invalid")


def raw_get(client, url: str, accept_encoding: str, **headers):
    """GET ``url`` and return (response, body bytes as sent on the wire, not decoded)."""
    with client.stream("GET", url, headers={"Accept-Encoding": accept_encoding, **headers}) as r:
        return r, b"".join(r.iter_raw())


def test_accepts_gzip():
    from services.preview_server import accepts_gzip

    for header in ("gzip", "gzip, deflate, br", "deflate;q=0.5, GZIP;q=0.8", "*", "br, *;q=1"):
        assert accepts_gzip(header), header
    for header in ("", "identity", "br", "gzip;q=0", "*, gzip;q=0", "gzip;q=x", "*;q=0"):
        assert not accepts_gzip(header), header


def test_pose_and_timeline_routes_gzip_and_cache_the_poses(api, result):
    from services.api.routers.preview import pose_cache_prefix
    from services.preview_server import pose_cache_key

    job_id = api.submit((result / "song.wav").read_bytes(), {"alternatives": 2}).json()["id"]
    finish_with(api, job_id, result / "out")
    store = api.app.state.ctx.store
    bvh = store.local_path(jobs.result_files(store, job_id)["alternatives/0.bvh"])
    key = pose_cache_key(pose_cache_prefix(job_id), bvh)
    url = f"/v1/jobs/{job_id}/preview/poses/0.json"
    expected = pose_track_file(bvh)
    assert not store.exists(key)

    # first request: computed, sent gzip-encoded, and kept in the store
    resp, raw = raw_get(api.client, url, "gzip, deflate", **api.headers)
    assert resp.status_code == 200 and resp.headers["content-encoding"] == "gzip"
    assert resp.headers["content-type"] == "application/json"
    assert "accept-encoding" in resp.headers["vary"].lower()
    assert json.loads(gzip.decompress(raw)) == expected
    assert len(raw) * 3 < len(json.dumps(expected))  # the point of compressing
    assert store.exists(key) and store.get_bytes(key) == raw
    # a client without gzip gets the same JSON, plain
    resp, plain = raw_get(api.client, url, "identity", **api.headers)
    assert "content-encoding" not in resp.headers and json.loads(plain) == expected
    # later requests read the stored track instead of recomputing it from the BVH
    store.put_bytes(key, gzip.compress(b'{"from": "the store"}'))
    assert api.get(url).json() == {"from": "the store"}
    # ... but a changed BVH has another key: recomputed, never a stale track
    shutil.copy(result / "out/alternatives/1.bvh", bvh)
    assert api.get(url).json() == pose_track_file(result / "out/alternatives/1.bvh")

    # the timeline too; the song's byte ranges stay unencoded (seeking needs them)
    base = f"/v1/jobs/{job_id}/preview"
    resp, raw = raw_get(api.client, f"{base}/timeline.json", "gzip", **api.headers)
    assert resp.headers["content-encoding"] == "gzip"
    assert gzip.decompress(raw) == (result / "out/timeline.json").read_bytes()
    resp, raw = raw_get(api.client, f"{base}/timeline.json", "identity", **api.headers)
    assert "content-encoding" not in resp.headers
    assert raw == (result / "out/timeline.json").read_bytes()
    resp, raw = raw_get(api.client, f"{base}/audio", "gzip", Range="bytes=0-99", **api.headers)
    assert resp.status_code == 206 and "content-encoding" not in resp.headers
    assert raw == (result / "song.wav").read_bytes()[:100]


def test_page_without_dance_or_build_is_a_clear_error(api, result, tmp_path, monkeypatch):
    from services import preview_server

    # a result without any BVH has no dance to show: 404, not an empty page
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(result / "out/timeline.json", bare / "timeline.json")
    no_dance = api.submit((result / "song.wav").read_bytes(), {"alternatives": 2}).json()["id"]
    finish_with(api, no_dance, bare)
    resp = api.get(f"/v1/jobs/{no_dance}/preview")
    assert resp.status_code == 404 and resp.json()["code"] == "result_not_found"
    job_id = api.submit((result / "song.wav").read_bytes(), {"alternatives": 2}).json()["id"]
    finish_with(api, job_id, result / "out")
    monkeypatch.setattr(preview_server, "STATIC_DIR", tmp_path / "not-built")
    resp = api.get(f"/v1/jobs/{job_id}/preview")
    assert resp.status_code == 503 and resp.json()["code"] == "preview_not_built"
    assert "install-frontend.sh" in resp.json()["detail"]


def test_local_preview_server(result, built, tmp_path, capsys):
    from fastapi.testclient import TestClient

    from dancegraph.cli import main as cli_main
    from services.preview_server import create_local_app

    out = result / "out"
    with TestClient(create_local_app(out)) as client:  # the song found through timeline.json
        config = page_config(client.get("/").text)
        assert config["poses"] == ["poses/0.json", "poses/1.json"]
        assert client.get(config["audio"]).content == (result / "song.wav").read_bytes()
        assert client.get(config["timeline"]).json()["alternatives"][1]["index"] == 1
        track = pose_track_file(out / "alternatives/1.bvh")
        resp, raw = raw_get(client, config["poses"][1], "gzip")
        assert resp.headers["content-encoding"] == "gzip"
        assert json.loads(gzip.decompress(raw)) == track
        # kept in the server's own cache folder (not in the result folder), reused after
        cached = list(Path(client.app.state.pose_cache.name).rglob("*.json.gz"))
        assert [p.read_bytes() for p in cached] == [raw]
        assert json.loads(raw_get(client, config["poses"][1], "identity")[1]) == track
        assert not list(out.rglob("*.json.gz"))
        assert client.get("/poses/9.json").json()["code"] == "result_not_found"
        assert client.get("/preview-static/preview.js").status_code == 200

    # the CLI's errors: no timeline; a song that cannot be found (and --audio naming a missing file)
    assert cli_main(["preview", str(tmp_path)]) == 2
    assert "result_not_found" in capsys.readouterr().err
    moved = tmp_path / "elsewhere" / "out"
    shutil.copytree(out, moved)
    assert cli_main(["preview", str(moved)]) == 2
    err = capsys.readouterr().err
    assert "preview_audio_missing" in err and "--audio" in err
    assert cli_main(["preview", str(moved), "--audio", str(tmp_path / "none.wav")]) == 2
    assert "preview_audio_missing" in capsys.readouterr().err
    # with --audio the folder previews wherever the song lies
    with TestClient(create_local_app(moved, result / "song.wav")) as client:
        assert client.get("/audio").headers["content-type"] == "audio/wav"


def test_preview_command_serves_until_interrupted(result, built, tmp_path):
    """``dancegraph preview`` as a real process: serves the page and its data over HTTP on the
    given port, stops cleanly on Ctrl+C (SIGINT) and leaves no cache folder behind."""
    import httpx

    port = free_port()
    base = f"http://127.0.0.1:{port}"
    proc = subprocess.Popen(
        [str(VENV_BIN / "dancegraph"), "preview", str(result / "out"), "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "TMPDIR": str(tmp_path)},
    )
    try:

        def page():
            if proc.poll() is not None:
                pytest.fail(
                    f"dancegraph preview exited with {proc.returncode}: {proc.stderr.read()}"
                )
            try:
                return httpx.get(base + "/", timeout=5)
            except httpx.TransportError:
                return None

        resp = wait_for(page, 90, "dancegraph preview to answer")
        assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/html")
        config = page_config(resp.text)
        poses = httpx.get(f"{base}/{config['poses'][0]}", timeout=30)
        assert poses.headers["content-encoding"] == "gzip"
        assert poses.json() == pose_track_file(result / "out/alternatives/0.bvh")
        song = httpx.get(f"{base}/{config['audio']}", headers={"Range": "bytes=4-11"}, timeout=30)
        assert song.status_code == 206 and song.content == (result / "song.wav").read_bytes()[4:12]
        assert list(tmp_path.glob("dancegraph-preview-*"))  # the server's pose cache
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            pytest.fail(f"dancegraph preview did not stop on SIGINT: {err[-2000:]}")
    assert proc.returncode == 0, err[-2000:]
    assert f"http://127.0.0.1:{port}/" in out
    assert not list(tmp_path.glob("dancegraph-preview-*"))


def test_preview_shows_the_dance_on_the_rig(result, built, tmp_path):
    """A result with ``<k>.rig.bvh`` files: the page offers the rig's skeleton, in metres."""
    from fastapi.testclient import TestClient

    from dancegraph.motion.retarget import RigOutput
    from dancegraph.motion.rig import load_rig
    from services.preview_server import create_local_app
    from tests.motion.rigs import make_rigs

    out = tmp_path / "out"
    shutil.copytree(result / "out", out)
    rig_path = make_rigs(tmp_path / "rigs", blender=False) / "cmu_cm.bvh"  # centimetres
    rig = load_rig(rig_path)
    hook = RigOutput(rig, rig_path, ["bvh"])
    timeline = json.loads((out / "timeline.json").read_text())
    for k in range(2):
        _, report = hook(k, read_bvh(out / f"alternatives/{k}.bvh"), out)
        timeline["alternatives"][k]["rig"] = report
    (out / "timeline.json").write_text(json.dumps(timeline))
    with TestClient(create_local_app(out, result / "song.wav")) as client:
        config = page_config(client.get("/").text)
        assert config["poses"] == ["poses/0.json", "poses/1.json"]
        assert config["rig_poses"] == ["poses/0.json?skeleton=rig", "poses/1.json?skeleton=rig"]
        track = client.get(config["rig_poses"][1]).json()
        assert track["joints"][: rig.skeleton.n_joints] == rig.skeleton.names
        pos = np.asarray(track["positions"]).reshape(track["frames"], len(track["joints"]), 3)
        hips = pos[:, rig.joint("hips"), 1] / 1000.0  # metres, although the file is in cm
        assert 0.6 < np.median(hips) < 1.2
        library = client.get(config["poses"][1]).json()
        assert library["joints"] != track["joints"]
    # without rig files the page offers none
    with TestClient(create_local_app(result / "out", result / "song.wav")) as client:
        assert "rig_poses" not in page_config(client.get("/").text)


def test_preview_serves_the_character_of_a_job_on_a_rig(api, result, built, tmp_path):
    """A job with ``<k>.rig.glb`` files: the page gets their URLs (the character it draws), and
    the signed URL answers the GLB itself; another index is a 404, no token a 401."""
    from dancegraph.motion.retarget import RigOutput
    from dancegraph.motion.rig import load_rig
    from tests.motion.rigs import make_rigs

    out = tmp_path / "out"
    shutil.copytree(result / "out", out)
    rig_path = make_rigs(tmp_path / "rigs", blender=False) / "cmu_cm.bvh"
    hook = RigOutput(load_rig(rig_path), rig_path, ["bvh", "glb"])
    for k in range(2):
        hook(k, read_bvh(out / f"alternatives/{k}.bvh"), out)
    job_id = api.submit((result / "song.wav").read_bytes(), {"alternatives": 2}).json()["id"]
    finish_with(api, job_id, out)
    page = api.client.get(api.get(f"/v1/jobs/{job_id}").json()["preview_url"])
    config = page_config(page.text)
    assert len(config["rig_models"]) == 2
    glb = api.client.get(config["rig_models"][1])
    assert glb.status_code == 200 and glb.headers["content-type"] == "model/gltf-binary"
    assert glb.content == (out / "alternatives/1.rig.glb").read_bytes()
    missing = config["rig_models"][1].replace("/rig/1.glb", "/rig/5.glb")
    assert api.client.get(missing).json()["code"] == "result_not_found"
    bare = config["rig_models"][0].split("?")[0]
    assert api.client.get(bare).status_code == 401
