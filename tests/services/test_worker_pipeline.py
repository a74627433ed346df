"""The worker's analysis stage counts a song's bars in the style tempo range of the dataset's
graph (or the spec's), and caches each range's analysis apart (a file store and the demo
library; the job test runs ``run_job`` in this process on the SQLite embedded default)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dancegraph.errors import SpecError
from dancegraph.graph.build import build_graph
from dancegraph.motion.dataset import import_dataset, load_dataset
from dancegraph.motion.demo import write_demo_library
from dancegraph.spec import parse_spec
from dancegraph.store import FileStore, ObjectStore
from services.worker import pipeline
from tests.demo import demo_song

STYLE = [220, 270]  # the demo song (124 BPM) is at half this style's tempo


def _ranged_demo(store: ObjectStore, root: Path, name: str = "demo") -> None:
    """The demo library imported as ``name`` with the style range ``STYLE``, its graph built."""
    lib = write_demo_library(root / "lib")
    manifest = json.loads((lib / "manifest.json").read_text())
    import_dataset(lib, name, store, {**manifest, "style_tempo_bpm": STYLE})
    build_graph(load_dataset(store, name), store)


def test_the_analysis_stage_counts_the_octave_of_the_graphs_style_range(tmp_path: Path):
    store = FileStore(tmp_path / "store")
    _ranged_demo(store, tmp_path)
    rng = pipeline.style_tempo_range(store, parse_spec({}, dataset="demo"))
    assert rng == (220.0, 270.0)
    assert pipeline.style_tempo_range(store, parse_spec({}, dataset="nope")) is None
    # the spec's own range wins over the dataset's
    own = parse_spec({"tempo_range": [100, 130]}, dataset="demo")
    assert pipeline.style_tempo_range(store, own) == (100.0, 130.0)
    with pytest.raises(SpecError) as err:
        parse_spec({"tempo_range": [130, 100]})
    assert err.value.field == "spec.tempo_range"

    wav, _ = demo_song(tmp_path)
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


def test_a_job_dances_on_bars_in_the_datasets_style_range(sqlite_api, tmp_path: Path):
    from tests.services.conftest import TEST_DATASET

    _ranged_demo(sqlite_api.app.state.ctx.store, tmp_path, TEST_DATASET)
    wav, _ = demo_song(tmp_path)
    spec = {"dataset": TEST_DATASET, "alternatives": 1, "output": {"formats": ["bvh"]}}
    resp = sqlite_api.submit(wav.read_bytes(), spec)
    assert resp.status_code == 202, resp.text
    job_id = resp.json()["id"]
    assert pipeline.run_job(job_id, sqlite_api.settings).status == "succeeded"
    job = sqlite_api.get(f"/v1/jobs/{job_id}").json()
    assert job["status"] == "succeeded" and job["analysis"]["grid_octave"] == "x2"
    song = sqlite_api.get(f"/v1/jobs/{job_id}/timeline.json").json()["song"]
    assert song["grid_octave"] == "x2" and 220 <= song["tempo_bpm"] <= 270
    assert any(w.startswith("grid_octave") for w in song["warnings"])


def test_the_analysis_cache_key_carries_the_analysis_version():
    """Analyses cached by other analysis code or models are never read back: the key names the
    version (``music.analysis.analysis_version``)."""
    from dancegraph.music.analysis import analysis_version

    sha = "ab" * 32
    assert pipeline.analysis_key(sha) == f"analysis/{analysis_version()}/{sha}.json"
    assert pipeline.analysis_key(sha, (150.0, 220.0)) == (
        f"analysis/{analysis_version()}/{sha}-150-220bpm.json"
    )
