"""A real ``dancegraph synthesize`` output for the preview tests, made once per test session with
the project's own code: the generated demo library imported and built into a graph, a generated
song (8 bars, 124 BPM), and the CLI's analysis → search → render (2 alternatives, a stage)."""

from __future__ import annotations

import json
from pathlib import Path

_made: dict[str, Path] = {}


def synthesized(tmp_path_factory) -> Path:
    """The folder holding ``song.wav`` and the synthesize output ``out/`` (timeline, 2 BVH)."""
    if "root" in _made:
        return _made["root"]
    from tests.demo import demo_cli, demo_song, demo_store

    root = tmp_path_factory.mktemp("preview")
    store = demo_store(root)
    wav, _ = demo_song(root, form=("A", "B"))
    spec = root / "spec.json"
    spec.write_text(
        json.dumps(
            {
                "seed": 1,
                "output": {"formats": ["bvh"], "fps": 30},
                "stage": {"x": [-2, 2], "z": [-2, 2]},
            }
        )
    )
    argv = ("--spec", str(spec), "--alternatives", "2")
    assert demo_cli("synthesize", wav, store, root / "out", *argv) == 0
    _made["root"] = root
    return root


def switch_time(timeline: dict) -> float:
    """Mid-time of the first bar whose chosen node differs between alternatives 0 and 1."""
    alts = timeline["alternatives"]
    for b, bar in enumerate(timeline["bars"]):
        if alts[0]["bars"][b]["node"] != alts[1]["bars"][b]["node"]:
            return (bar["start_s"] + bar["end_s"]) / 2
    raise AssertionError("the two alternatives choose the same node in every bar")
