"""The worker's analysis stage counts a song's bars in the style tempo range of the dataset's
graph, and caches each range's analysis apart (no servers: a file store and the demo library)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dancegraph.errors import SpecError
from dancegraph.graph.build import build_graph
from dancegraph.motion.dataset import import_dataset, load_dataset
from dancegraph.motion.demo import write_demo_library
from dancegraph.spec import parse_spec
from dancegraph.store import FileStore
from services.worker import pipeline
from tests.demo import demo_song


def test_the_analysis_stage_counts_the_octave_of_the_graphs_style_range(tmp_path: Path):
    lib = write_demo_library(tmp_path / "lib")
    manifest = json.loads((lib / "manifest.json").read_text())
    store = FileStore(tmp_path / "store")
    import_dataset(lib, "demo", store, {**manifest, "tempo_prior_bpm": [220, 270]})
    build_graph(load_dataset(store, "demo"), store)
    rng = pipeline.style_tempo_range(store, parse_spec({}, dataset="demo"))
    assert rng == (220.0, 270.0)
    assert pipeline.style_tempo_range(store, parse_spec({}, dataset="nope")) is None
    # the spec's own range wins over the dataset's
    own = parse_spec({"tempo_range": [100, 130]}, dataset="demo")
    assert pipeline.style_tempo_range(store, own) == (100.0, 130.0)
    with pytest.raises(SpecError) as err:
        parse_spec({"tempo_range": [130, 100]})
    assert err.value.field == "spec.tempo_range"

    wav, _ = demo_song(tmp_path)  # 124 BPM: half the style's tempo
    with open(wav, "rb") as fh:
        key, _ = store.put_stream(fh)
    sha = key.rsplit("/", 1)[-1]
    fast = pipeline.analyze(store, key, sha, "song.wav", rng)
    plain = pipeline.analyze(store, key, sha, "song.wav")
    assert fast.grid_octave == "x2" and 220 <= fast.tempo_bpm <= 270
    assert any(w.startswith("grid_octave") for w in fast.warnings)
    assert plain.grid_octave == "x1" and plain.tempo_bpm < 130
    assert fast.summary()["grid_octave"] == "x2"
    # each range's analysis is cached under its own key
    assert pipeline.analysis_key(sha, rng) != pipeline.analysis_key(sha)
    assert store.exists(pipeline.analysis_key(sha, rng)) and store.exists(
        pipeline.analysis_key(sha)
    )
