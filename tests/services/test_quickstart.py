"""The README's main job (`make demo` → `dancegraph quickstart`) runs end to end.

Run as a child process with ``DANCEGRAPH_SHARED`` pointing at an empty folder, so it takes the
path of a machine without ``../shared``: the generated demo library and a synthesised song,
through the embedded service (SQLite, filesystem broker, in-process graph store).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from fastapi.testclient import TestClient

from dancegraph.motion.bvh import read_bvh
from services.preview_server import create_local_app


def test_quickstart_without_shared_data(tmp_path: Path):
    env = dict(os.environ)
    for key in list(env):
        if key.startswith("DANCEGRAPH_"):
            del env[key]
    env.update(
        {
            "DANCEGRAPH_HOME": str(tmp_path / "home"),
            "DANCEGRAPH_SHARED": str(tmp_path / "no-shared"),
        }
    )
    out = tmp_path / "out"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "dancegraph.cli",
            "quickstart",
            "--out",
            str(out),
            "--formats",
            "bvh",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=540,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "importing demo" in done.stdout
    assert f"results in {out}" in done.stdout
    timeline = json.loads((out / "timeline.json").read_text())
    assert len(timeline["alternatives"]) == 2
    for k in (0, 1):  # the layout `dancegraph synthesize` writes
        motion = read_bvh(out / "alternatives" / f"{k}.bvh")
        assert motion.n_frames > 30 * 10  # the synthesised song lasts well over 10 s
    assert not (out / "alternatives" / "0.fbx").exists()  # only the formats asked for

    # the README's next step, `dancegraph preview out/`, finds the dance and the song
    preview = TestClient(create_local_app(out))
    for k in (0, 1):
        poses = preview.get(f"/poses/{k}.json")
        assert poses.status_code == 200 and poses.json()["frames"] == motion.n_frames
    song = preview.get("/audio")
    assert song.status_code == 200 and song.content[:4] == b"RIFF"
