"""Run a ufbx reader script in a child process (the binding can crash while freeing scenes, and
an FBX must be read by code independent of the writer) and take what it prints as JSON."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def ufbx_json(script: str, path: Path | str, frames: list[int]) -> dict:
    """What ``script`` prints (one JSON document) when run as ``python -c script path frames``,
    ``frames`` given as a JSON list of ints; asserts the child exits 0 (its stderr's tail as the
    message)."""
    proc = subprocess.run(
        [sys.executable, "-c", script, str(path), json.dumps([int(f) for f in frames])],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, f"ufbx could not read {path}: {proc.stderr[-2000:]}"
    return json.loads(proc.stdout)
