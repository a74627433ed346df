"""Grids from the takes' own music (issue 34): generated takes danced to generated songs at a
known offset; the music grid matches the truth, a wrong declared offset shows as disagreement
with the motion's own estimate, and takes without music keep the motion estimate."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from bench.bench_library import music_truth
from dancegraph.cli import main as cli_main
from dancegraph.motion.dataset import import_dataset, load_dataset
from dancegraph.store import FileStore


@pytest.fixture(scope="module")
def lib(tmp_path_factory) -> Path:
    """Two generated takes with their music, written by ``motion demo --with-music``."""
    out = tmp_path_factory.mktemp("music") / "lib"
    cli_main(["motion", "demo", str(out), "--seed", "3", "--takes", "2", "--with-music"])
    assert sorted(p.suffix for p in out.iterdir()).count(".ogg") == 2
    return out


@pytest.fixture(scope="module")
def manifest(lib) -> dict:
    return json.loads((lib / "manifest.json").read_text())


def test_music_grid_matches_the_truth_and_the_motion_agrees(lib, tmp_path, capsys):
    store = FileStore(tmp_path / "store")
    report = import_dataset(lib, "music", store)
    assert report.failed == [] and len(report.clips) == 2
    truth = json.loads((lib / "truth.json").read_text())
    for c in report.clips:
        assert c.beat_source == "music" and c.audio_offset_s == truth[c.id]["audio_offset_s"]
        assert abs(c.tempo_bpm - truth[c.id]["tempo_bpm"]) < 0.005 * c.tempo_bpm
        check = c.grid_check
        assert check["agree"] and check["median_offset_ms"] < 30
        assert check["downbeat_agreement"] >= 0.85 and check["downbeat_shift_beats"] == 0
    score = music_truth(store, "music", lib)
    assert score["median_ms"] <= 20 and score["max_ms"] <= 40
    assert score["bars_on_downbeats"] == 1.0
    assert load_dataset(store, "music").clip(report.clips[0].id).audio  # the music is kept

    rc = cli_main(["dataset", "show", "music", "--store", str(tmp_path / "store")])
    out = capsys.readouterr().out
    assert rc == 0 and "music" in out and "agree" in out


@pytest.mark.parametrize("shift", ["half_beat", "one_beat"])
def test_a_wrong_declared_offset_shows_as_disagreement(lib, manifest, tmp_path, shift):
    wrong = copy.deepcopy(manifest)
    cid = next(iter(wrong["clips"]))
    beat_s = 60.0 / json.loads((lib / "truth.json").read_text())[cid]["tempo_bpm"]
    wrong["clips"][cid]["audio_offset_s"] += beat_s * (0.5 if shift == "half_beat" else 1.0)
    report = import_dataset(lib, "wrong", FileStore(tmp_path / "store"), wrong)
    row = {c.id: c for c in report.clips}[cid]
    assert row.beat_source == "music" and not row.grid_check["agree"]
    assert "music_motion_disagree" in row.flags
    if shift == "half_beat":  # every beat half a beat off the motion's
        assert row.grid_check["median_offset_ms"] > 0.3 * beat_s * 1000
    else:  # the beats line up, the bars start a beat off
        assert row.grid_check["median_offset_ms"] < 40
        assert row.grid_check["downbeat_agreement"] < 0.5
        assert row.grid_check["downbeat_shift_beats"] in (1, 3)


def test_takes_without_music_keep_the_motion_estimate(lib, manifest, tmp_path):
    bare = copy.deepcopy(manifest)
    for entry in bare["clips"].values():
        entry.pop("audio")
        entry.pop("audio_offset_s")
    report = import_dataset(lib, "bare", FileStore(tmp_path / "store"), bare)
    assert {c.beat_source for c in report.clips} == {"kinematic"}
    assert all(c.grid_check == {} and c.audio is None for c in report.clips)
