"""One data folder for every working folder: the per-user data folder, or ``DANCEGRAPH_HOME``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


def _run(cwd: Path, env: dict, *args: str) -> str:
    out = subprocess.run(
        [sys.executable, "-m", "dancegraph.cli", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def test_a_dataset_imported_in_one_folder_is_seen_from_another(tmp_path: Path):
    env = {
        k: v for k, v in os.environ.items() if k not in ("DANCEGRAPH_HOME", "DANCEGRAPH_STORE_ROOT")
    }
    env["XDG_DATA_HOME"] = str(tmp_path / "xdg")  # platformdirs' per-user data folder on Linux
    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir()
    second.mkdir()
    _run(first, env, "motion", "demo", "lib")
    _run(first, env, "dataset", "import", "lib", "--name", "demo", "--json")
    assert [d["name"] for d in json.loads(_run(second, env, "dataset", "list"))] == ["demo"]
    assert (tmp_path / "xdg" / "dancegraph" / "store").is_dir()
    assert not (first / "var").exists() and not (second / "var").exists()

    env["DANCEGRAPH_HOME"] = str(tmp_path / "elsewhere")  # still overrides
    assert json.loads(_run(second, env, "dataset", "list")) == []
