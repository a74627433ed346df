"""The graph store at scale: graphs load on first use and are evicted least-recently-used under
the memory budget; a search can name the graph version a job pinned (over HTTP too); the list
reads manifests only. Graphs are the demo library's, written under several library names."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from dancegraph.graph import artifact
from dancegraph.music.analysis import MusicAnalysis, analyze
from dancegraph.music.generator import generate_song
from dancegraph.spec import parse_spec
from dancegraph.store import ObjectStore
from services.graphstore.app import create_app
from services.graphstore.client import HttpGraphStore, LocalGraphStore, graph_nbytes
from tests.demo import demo_store

NAMES = [f"lib-{i:020x}" for i in range(4)]


def copy_graph(store: ObjectStore, src: str, name: str, version: str | None = None) -> str:
    """Write graph ``src``'s current version again as ``name`` (a new version of it)."""
    g = artifact.load_current(store, src)
    arrays = {k: np.asarray(v) for k, v in g.arrays.items()}
    keep = {"format", "name", "version", "arrays", "checksums", "created", "node_ids_file"}
    manifest = {k: v for k, v in g.manifest.items() if k not in keep}
    key = artifact.write_graph(
        store, name, arrays, manifest, node_ids=list(g.node_ids), version=version
    )
    return key.rsplit("/", 1)[1]


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> ObjectStore:
    store = demo_store(tmp_path_factory.mktemp("graphstore"))
    for name in NAMES:
        copy_graph(store, "demo", name)
    return store


@pytest.fixture(scope="module")
def song() -> MusicAnalysis:
    y = generate_song(5, meter=4, tempo_bpm=120.0, form=["A", "B"], section_bars={"A": 4, "B": 4})
    return analyze(y.y, y.sr)


def test_graphs_past_the_budget_are_evicted_least_recently_used(store: ObjectStore, song):
    size = graph_nbytes(artifact.load_current(store, "demo"))
    local = LocalGraphStore(store, memory_budget_bytes=int(2.5 * size))
    for name in NAMES:
        local.graph(name)
        assert local.memory()["resident_bytes"] <= local.memory_budget_bytes
    assert list(local.loaded()) == NAMES[2:] and local.memory()["evictions"] == 2
    local.graph(NAMES[2])  # used: the next eviction takes NAMES[3]
    spec = parse_spec({"alternatives": 1}, dataset=NAMES[0])
    assert local.search(song, spec).graph_name == NAMES[0]  # loaded again on use
    assert list(local.loaded()) == [NAMES[2], NAMES[0]]
    assert local.memory() == {
        "budget_bytes": int(2.5 * size),
        "resident_bytes": 2 * size,
        "graphs": 2,
        "evictions": 3,
    }


def test_a_graph_larger_than_the_budget_still_serves(store: ObjectStore, song):
    local = LocalGraphStore(store, memory_budget_bytes=1)
    spec = parse_spec({"alternatives": 1}, dataset=NAMES[1])
    assert local.search(song, spec).graph_name == NAMES[1]
    assert list(local.loaded()) == [NAMES[1]]


def test_a_pinned_version_answers_after_a_new_one_is_current(
    store: ObjectStore, song, tmp_path: Path
):
    name = NAMES[3]
    old = artifact.current_version(store, name)
    new = copy_graph(store, "demo", name, version="v-next")
    assert artifact.current_version(store, name) == new != old
    http = HttpGraphStore("http://graphstore", client=TestClient(create_app(store)))
    spec = parse_spec({"alternatives": 1}, dataset=name)
    for client in (http, LocalGraphStore(store)):
        assert client.search(song, spec).graph_version == new
        assert client.search(song, spec, version=old).graph_version == old
    listed = {g["name"]: g for g in http.list_graphs()}
    assert listed[name]["version"] == new and listed[name]["nodes"] > 0
    health = http._call("GET", "/healthz")
    assert health["memory"]["resident_bytes"] > 0 and health["memory"]["budget_bytes"] > 0


def test_replicas_share_nothing_but_the_object_store(store: ObjectStore):
    """Two graph-store processes over one store: a build landing through either is served by
    both on their next call (each reads ``current`` from the store, nothing kept apart)."""
    name = NAMES[2]
    one, two = LocalGraphStore(store), LocalGraphStore(store)
    before = one.graph(name).version
    assert two.graph(name).version == before
    new = copy_graph(store, "demo", name, version="v-replicas")
    assert one.graph(name).version == two.graph(name).version == new != before
