"""Style is a choice (issue 34): on the real CC songs and the two CMU libraries, a fast song
picks salsa and a slow one modern, with every candidate's scores and a reason."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from dancegraph.errors import SpecError
from dancegraph.graph.artifact import load_current
from dancegraph.graph.build import build_dataset_graph
from dancegraph.graph.style_choice import candidate, choose_library, resolve, tempo_cost
from dancegraph.motion.dataset import import_dataset
from dancegraph.music.analysis import analyze
from dancegraph.paths import REPO_ROOT
from dancegraph.spec import parse_spec
from dancegraph.store import FileStore

TAKES = {
    "cmu-salsa": ["60_01_scaled", "61_01_scaled", "60_03_scaled", "61_03_scaled"],
    "cmu-modern": ["05_02", "05_04", "05_06", "05_10", "05_12"],
}


@pytest.fixture(scope="module")
def graphs(shared: Path, tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("styles")
    store = FileStore(root / "store")
    for name, takes in TAKES.items():
        src = root / name
        src.mkdir()
        for take in takes:
            (src / f"{take}.bvh").symlink_to(shared / "datasets" / "mocap" / name / f"{take}.bvh")
        manifest = yaml.safe_load(
            (REPO_ROOT / "datasets" / "manifests" / f"{name}.yaml").read_text()
        )
        import_dataset(src, name, store, manifest)
        build_dataset_graph(store, name)
    return {name: load_current(store, name) for name in TAKES}


@pytest.fixture(scope="module")
def candidates(graphs) -> list:
    return [candidate(g) for g in graphs.values()]


@pytest.fixture(scope="module")
def fast_song(cc_music_dir):
    return analyze(cc_music_dir / "Karissa_Hobbs_-_Lets_Go_Fishin.hq.ogg")


@pytest.mark.parametrize(
    ("song", "chosen"),
    [
        ("Karissa_Hobbs_-_Lets_Go_Fishin.hq.ogg", "cmu-salsa"),  # 177 BPM
        ("Kevin_MacLeod_-_P_I_Tchaikovsky_Dance_of_the_Sugar_Plum_Fairy.hq.ogg", "cmu-modern"),
    ],
)
def test_the_song_tempo_and_style_choose_the_library(candidates, cc_music_dir, song, chosen):
    result = choose_library(analyze(cc_music_dir / song), candidates)
    assert result["chosen"] == chosen
    rows = {r["name"]: r for r in result["candidates"]}
    assert set(rows) == {"cmu-salsa", "cmu-modern"}
    best, other = rows[chosen], rows[next(n for n in rows if n != chosen)]
    assert best["score"] < other["score"]
    assert (
        best["tempo_cost"] < other["tempo_cost"]
        and best["style_distance"] < other["style_distance"]
    )
    assert result["reason"].startswith(chosen) and rows[chosen]["style"] in result["reason"]
    assert {c.style for c in candidates} == {"salsa", "modern"}


def test_resolve_gives_the_spec_one_library(graphs, fast_song):
    one = parse_spec({"dataset": "cmu-modern"})
    assert resolve(one, fast_song, graphs) == (one, None)
    for data in ({"style": "auto"}, {"dataset": ["cmu-modern", "cmu-salsa"]}):
        spec, choice = resolve(parse_spec(data), fast_song, graphs)
        assert spec.dataset == "cmu-salsa" and choice is not None
        assert [r["name"] for r in choice["candidates"]] == ["cmu-salsa", "cmu-modern"]
    spec, choice = resolve(parse_spec({"style": "modern"}), fast_song, graphs)
    assert spec.dataset == "cmu-modern" and choice is not None and len(choice["candidates"]) == 1
    with pytest.raises(SpecError) as err:
        resolve(parse_spec({"style": "tango"}), fast_song, graphs)
    assert err.value.code == "style_unknown" and "modern, salsa" in err.value.message


def test_tempo_fit_counts_half_and_double_time():
    assert tempo_cost(170.0, (150.0, 220.0)) == (0.0, "x1")
    cost, octave = tempo_cost(90.0, (150.0, 220.0))  # danced at double time
    assert octave == "x2" and cost == pytest.approx(0.1)
    assert tempo_cost(60.0, (150.0, 220.0)) == pytest.approx((0.1 + 0.3219, "x2"), abs=1e-3)
    with pytest.raises(SpecError) as err:
        choose_library(None, [])
    assert err.value.code == "style_no_candidate"


def test_spec_names_a_style_or_a_list_of_libraries():
    spec = parse_spec({"style": "auto", "dataset": ["cmu-salsa", "cmu-modern"]})
    assert spec.style == "auto" and spec.dataset == ["cmu-salsa", "cmu-modern"]
    assert parse_spec({}).style is None and parse_spec({}).dataset == "cmu-salsa"
    with pytest.raises(SpecError):
        parse_spec({"dataset": []})
