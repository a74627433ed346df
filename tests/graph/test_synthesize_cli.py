"""``dancegraph synthesize`` end to end: demo library → import → build → a generated song → files.

Everything is the project's own code: the demo library and the song are generated, the dataset
is imported and its graph built into a temporary object store, and the CLI runs analysis,
search and render on the song's WAV file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dancegraph.cli import main as cli_main
from dancegraph.graph.artifact import load_current
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.dataset import load_dataset
from dancegraph.motion.fbx import fbx_available
from tests.demo import demo_cli, demo_song, demo_store


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    store = demo_store(root)
    wav, song = demo_song(root)
    return root, store, wav, song


def test_synthesize_writes_dance_files(setup, capsys):
    root, store, wav, song = setup
    formats = ["bvh", "fbx"] if fbx_available() else ["bvh"]
    spec = root / "spec.json"
    spec.write_text(json.dumps({"seed": 1, "output": {"formats": formats, "fps": 30}}))
    out = root / "out"
    rc = demo_cli("synthesize", wav, store, out, "--spec", str(spec), "--alternatives", "2")
    assert rc == 0, capsys.readouterr().err
    printed = json.loads(capsys.readouterr().out)
    assert len(printed["alternatives"]) == 2 and printed["graph"]["name"] == "demo"

    timeline = json.loads((out / "timeline.json").read_text())
    graph = load_current(store, "demo")
    n_frames = round(song.duration_s * 30)
    for k in range(2):
        motion = read_bvh(out / f"alternatives/{k}.bvh")
        assert motion.skeleton == graph.skeleton and motion.n_frames == n_frames
        assert np.all(np.isfinite(motion.rotations))
        if "fbx" in formats:
            assert (out / f"alternatives/{k}.fbx").stat().st_size > 10_000
    # the bars found in the audio are the generated song's bars (the analysis really ran)
    truth_downbeats = np.asarray(song.truth["downbeats"])
    starts = np.array([b["start_s"] for b in timeline["bars"]])
    assert len(starts) >= 8
    assert np.median(np.abs(starts[:, None] - truth_downbeats[None, :]).min(axis=1)) < 0.07
    prov = timeline["provenance"]
    assert (
        prov["dataset"]["name"] == "demo"
        and prov["dataset"]["version"] == load_dataset(store, "demo").version
    )
    assert prov["dataset"]["licence"] and prov["graph"]["version"] == graph.version
    assert "acknowledgement" in prov["dataset"]  # the dataset's credit line travels with results
    assert prov["spec"]["alternatives"] == 2 and prov["spec"]["seed"] == 1
    assert prov["audio"]["file"] == "song.wav" and len(prov["audio"]["sha256"]) == 64
    assert isinstance(timeline["constraints"], dict) and timeline["constraints"]
    # the demo dataset declares no style tempo range: the bars count the tracked tempo
    assert graph.tempo_range is None and timeline["song"]["grid_octave"] == "x1"
    assert not any(w.startswith("grid_octave") for w in timeline["song"]["warnings"])
    alts = timeline["alternatives"]
    assert [b["node"] for b in alts[0]["bars"]] != [b["node"] for b in alts[1]["bars"]]


def test_synthesize_errors_are_clear(setup, capsys, tmp_path: Path):
    root, store, wav, _ = setup
    base = ["synthesize", str(wav), "--out", str(tmp_path / "o"), "--store", str(store.root)]
    assert cli_main([*base, "--dataset", "nope"]) == 2
    assert "unknown_dataset" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text('{"alternatives": 99}')
    assert cli_main([*base, "--dataset", "demo", "--spec", str(bad)]) == 2
    assert "spec.alternatives" in capsys.readouterr().err
    assert cli_main([*base, "--dataset", "demo", "--spec", str(tmp_path / "absent.json")]) == 2
    assert "absent.json" in capsys.readouterr().err
    junk = tmp_path / "junk.wav"
    junk.write_bytes(b"not audio at all" * 100)
    assert demo_cli("synthesize", junk, store, tmp_path / "o2") == 2
    assert "audio_" in capsys.readouterr().err
    assert not (tmp_path / "o").exists() and not (tmp_path / "o2").exists()


def test_synthesize_on_a_rig(setup, capsys, tmp_path: Path):
    """``--rig``: every alternative also on the user's rig (BVH and GLB here), beside the library's."""
    from dancegraph.motion.rig import load_rig
    from tests.motion.rigs import make_rigs

    root, store, wav, _ = setup
    rigs = make_rigs(tmp_path / "rigs", blender=False)
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"seed": 2, "output": {"formats": ["bvh"], "fps": 30}}))
    out = tmp_path / "out"
    rc = demo_cli(
        "synthesize", wav, store, out, "--spec", str(spec), "--alternatives", "1",
        "--rig", str(rigs / "cmu_cm.bvh"),
    )  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    printed = json.loads(capsys.readouterr().out)
    assert (
        "alternatives/0.rig.bvh" in printed["files"]
        and "alternatives/0.rig.glb" in printed["files"]
    )
    library = read_bvh(out / "alternatives/0.bvh")
    on_rig = read_bvh(out / "alternatives/0.rig.bvh", scale=0.01)
    rig = load_rig(rigs / "cmu_cm.bvh")
    assert on_rig.skeleton.names == rig.skeleton.names and on_rig.n_frames == library.n_frames
    entry = json.loads((out / "timeline.json").read_text())["alternatives"][0]
    assert entry["files"]["rig.glb"] == "alternatives/0.rig.glb"
    assert entry["rig"]["floor_error_m"]["max_abs"] <= 0.01
    assert entry["rig"]["direction_error_deg"]["median"] <= 5.0
    bad = ["--rig", str(rigs / "bad_zero_length.bvh")]
    assert demo_cli("synthesize", wav, store, tmp_path / "o2", *bad) == 2
    assert "rig_zero_length" in capsys.readouterr().err


def test_a_dataset_style_tempo_range_sets_the_octave_of_the_song_bars(setup, capsys, tmp_path):
    """A dataset whose manifest declares its style's tempo range (``style_tempo_bpm``) carries it
    into its graph; a song at half that tempo is then danced on bars counted at twice the
    tracked tempo, and the timeline says so. The same song against the same library without the
    range (the ``setup`` store) keeps the tracked tempo (``test_synthesize_writes_dance_files``)."""
    from dancegraph.graph.build import build_graph
    from dancegraph.motion.dataset import import_dataset
    from dancegraph.motion.demo import write_demo_library
    from dancegraph.store import FileStore

    _, _, wav, song = setup  # 124 BPM
    lib = write_demo_library(tmp_path / "lib")
    manifest = json.loads((lib / "manifest.json").read_text())
    store = FileStore(tmp_path / "store")
    import_dataset(lib, "demo", store, {**manifest, "style_tempo_bpm": [220, 270]})
    build_graph(load_dataset(store, "demo"), store)
    assert load_current(store, "demo").tempo_range == (220.0, 270.0)

    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"seed": 1, "output": {"formats": ["bvh"], "fps": 30}}))
    out = tmp_path / "out"
    rc = demo_cli("synthesize", wav, store, out, "--spec", str(spec), "--alternatives", "1")
    assert rc == 0, capsys.readouterr().err
    printed = json.loads(capsys.readouterr().out)
    timeline = json.loads((out / "timeline.json").read_text())
    assert timeline["song"]["grid_octave"] == "x2" and printed["analysis"]["grid_octave"] == "x2"
    assert 220 <= timeline["song"]["tempo_bpm"] <= 270
    assert any(w.startswith("grid_octave") for w in timeline["song"]["warnings"])
    # bars of 4 beats at twice the tempo: half a 124-BPM bar each, as many as the song holds
    lengths = np.array([b["end_s"] - b["start_s"] for b in timeline["bars"]])
    assert np.median(lengths) == pytest.approx(120.0 / 124.0, rel=0.05)
    assert len(lengths) >= 2 * (song.duration_s * 124.0 / 240.0) - 4
    # a spec's own tempo range overrides the dataset's: here the tracked tempo fits it
    spec.write_text(
        json.dumps({"seed": 1, "tempo_range": [100, 140], "output": {"formats": ["bvh"]}})
    )
    spec_json = ["--spec", str(spec), "--alternatives", "1"]
    assert demo_cli("synthesize", wav, store, tmp_path / "own", *spec_json) == 0
    capsys.readouterr()
    timeline = json.loads((tmp_path / "own" / "timeline.json").read_text())
    assert timeline["song"]["grid_octave"] == "x1" and timeline["song"]["tempo_bpm"] < 140
    # `dancegraph eval` analyses its songs by the same rule (render.style_tempo_range)
    from dancegraph.eval.harness import load_song
    from dancegraph.spec import parse_spec

    graph = load_current(store, "demo")
    assert load_song(wav, graph=graph).analysis.grid_octave == "x2"
    own = parse_spec({"tempo_range": [100, 140]}, dataset="demo")
    assert load_song(wav, graph=graph, spec=own).analysis.grid_octave == "x1"
