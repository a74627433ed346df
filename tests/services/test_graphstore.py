"""The graph-store service (FastAPI TestClient) and its two clients, on a real built demo graph.

The graph comes from the project's own pipeline: generated demo library → ``import_dataset`` →
``build_graph`` into a temporary object store; the song is generated and analysed for real.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from dancegraph.errors import NotFoundError, SpecError
from dancegraph.graph import artifact
from dancegraph.graph.search import SearchResult
from dancegraph.motion.dataset import load_dataset
from dancegraph.music.analysis import MusicAnalysis, analyze
from dancegraph.music.generator import generate_song
from dancegraph.spec import parse_spec
from dancegraph.store import FileStore, ObjectStore
from services.graphstore.app import create_app
from services.graphstore.client import HttpGraphStore, LocalGraphStore
from tests.demo import demo_store

PROBLEM = "application/problem+json"


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> ObjectStore:
    return demo_store(tmp_path_factory.mktemp("graphstore"))


@pytest.fixture(scope="module")
def analysis() -> dict:
    song = generate_song(
        11, meter=4, tempo_bpm=128.0, form=["A", "B", "A"], section_bars={"A": 4, "B": 4}
    )
    return analyze(song.y, song.sr).to_dict()


@pytest.fixture(scope="module")
def client(store: ObjectStore) -> TestClient:
    return TestClient(create_app(store))


def test_list_and_describe_graphs(client: TestClient, store: ObjectStore):
    listed = client.get("/v1/graphs")
    assert listed.status_code == 200
    items = listed.json()["items"]
    assert [g["name"] for g in items] == ["demo"]
    version = artifact.current_version(store, "demo")
    assert items[0]["version"] == version and items[0]["nodes"] > 0 and items[0]["edges"] > 0

    info = client.get("/v1/graphs/demo").json()
    graph = artifact.load_current(store, "demo")
    assert info["version"] == version
    assert info["stats"]["nodes"] == graph.n_nodes and info["stats"]["edges"] == graph.n_edges
    assert info["embedding"] == graph.manifest["embedding"]["version"]
    assert (
        info["dataset"]["name"] == "demo"
        and info["dataset"]["version"] == load_dataset(store, "demo").version
    )
    assert info["dataset"]["licence"]
    assert info["versions"] == [version]


def test_unknown_graph_is_a_404_problem(client: TestClient, analysis: dict):
    for resp in (
        client.get("/v1/graphs/no-such-set"),
        client.post("/v1/graphs/no-such-set/search", json={"analysis": analysis, "spec": {}}),
        client.get("/v1/graphs/no-such-set/nodes/x:0"),
    ):
        assert resp.status_code == 404
        assert resp.headers["content-type"].startswith(PROBLEM)
        body = resp.json()
        assert (
            body["code"] == "unknown_dataset"
            and body["status"] == 404
            and "no-such-set" in body["detail"]
        )


def test_search_answers_one_node_per_bar(client: TestClient, analysis: dict, store: ObjectStore):
    resp = client.post(
        "/v1/graphs/demo/search", json={"analysis": analysis, "spec": {"alternatives": 2}}
    )
    assert resp.status_code == 200, resp.text
    found = resp.json()
    graph = artifact.load_current(store, "demo")
    assert found["graph"] == {"name": "demo", "version": graph.version}
    assert len(found["alternatives"]) == 2
    n_bars = len(analysis["bars"])
    for alt in found["alternatives"]:
        assert len(alt["nodes"]) == n_bars and all(graph.has_node(n) for n in alt["nodes"])
        assert np.isfinite(alt["cost"])
    assert found["alternatives"][0]["nodes"] != found["alternatives"][1]["nodes"]

    # node provenance and clip data for rendering
    node_id = found["alternatives"][0]["nodes"][0]
    node = client.get(f"/v1/graphs/demo/nodes/{node_id}").json()
    i = graph.node_index(node_id)
    assert node["node"] == node_id and node["clip"] == graph.clips[int(graph.node_clip[i])]
    assert node["bar"] == int(graph.node_bar[i]) and len(node["frames"]) == 2
    motion = client.get(f"/v1/graphs/demo/nodes/{node_id}/motion").json()
    expected = graph.node_motion(i)
    assert motion["frames"] == expected.n_frames and motion["fps"] == pytest.approx(expected.fps)
    np.testing.assert_allclose(motion["rotations"], expected.rotations, atol=2e-6)


def test_bad_search_input_names_the_field(client: TestClient, analysis: dict):
    resp = client.post(
        "/v1/graphs/demo/search", json={"analysis": analysis, "spec": {"alternatves": 2}}
    )
    assert resp.status_code == 422 and resp.json()["code"] == "spec_unknown_field"
    assert resp.json()["field"] == "spec.alternatves"
    resp = client.post(
        "/v1/graphs/demo/search", json={"analysis": analysis, "spec": {"alternatives": 0}}
    )
    assert resp.status_code == 422 and resp.json()["field"] == "spec.alternatives"
    resp = client.post("/v1/graphs/demo/search", json={"analysis": {"bars": [[0, 1]]}, "spec": {}})
    assert resp.status_code == 422 and resp.json()["code"] == "analysis_invalid"
    resp = client.post("/v1/graphs/demo/search", json={"spec": {}})
    assert resp.status_code == 422 and resp.headers["content-type"].startswith(PROBLEM)
    resp = client.get("/v1/graphs/demo/nodes/nope:99")
    assert resp.status_code == 404 and resp.json()["code"] == "unknown_node"


def test_http_and_local_clients_agree(client: TestClient, store: ObjectStore, analysis: dict):
    http = HttpGraphStore("http://graphstore", client=client)
    local = LocalGraphStore(store)
    assert http.list_graphs() == local.list_graphs()
    assert http.graph_info("demo")["version"] == local.graph_info("demo")["version"]
    song = MusicAnalysis.from_dict(analysis)
    spec = parse_spec({"alternatives": 1, "seed": 3}, dataset="demo")
    over_http, in_process = http.search(song, spec), local.search(song, spec)
    assert (
        isinstance(over_http, SearchResult) and over_http.graph_version == in_process.graph_version
    )
    assert over_http.to_dict() == in_process.to_dict()
    node_id = local.graph("demo").node_ids[5]
    assert http.node("demo", node_id) == local.node("demo", node_id)
    assert http.skeleton("demo") == local.skeleton("demo")
    np.testing.assert_allclose(
        http.node_motion("demo", node_id).root_positions,
        local.node_motion("demo", node_id).root_positions,
        atol=2e-6,
    )
    for c in (http, local):
        with pytest.raises(NotFoundError) as err:
            c.graph_info("missing")
        assert err.value.code == "unknown_dataset"
        with pytest.raises(NotFoundError) as err:
            c.search(song, parse_spec({"recreate": "nope_99"}, dataset="demo"))
        assert err.value.code == "unknown_node" and err.value.field == "recreate"
        with pytest.raises(SpecError) as err:
            c.search(song, parse_spec({"motifs": [{"bar": 999, "motif": 0}]}, dataset="demo"))
        assert err.value.code == "constraint_conflict" and err.value.field == "motifs[0].bar"
        with pytest.raises(NotFoundError) as err:
            c.search(song, parse_spec({}, dataset="missing"))
        assert err.value.code == "unknown_dataset"


def test_new_version_loads_while_old_keeps_answering(store: ObjectStore, tmp_path: Path):
    local = LocalGraphStore(store)
    old = local.graph("demo")
    arrays = {k: np.asarray(v) for k, v in old.arrays.items()}
    manifest = {
        k: v
        for k, v in old.manifest.items()
        if k not in {"format", "name", "version", "arrays", "checksums", "created", "node_ids_file"}
    }
    artifact.write_graph(
        store, "demo", arrays, manifest, node_ids=list(old.node_ids), version="v2-test"
    )
    try:
        new = local.graph("demo")
        assert new.version == "v2-test" and old.version != "v2-test"
        assert local.graph_info("demo")["versions"] == sorted([old.version, "v2-test"])
        # the old graph object still answers (its folder is untouched)
        assert old.node_motion(0).n_frames == new.node_motion(0).n_frames
        assert local.graph_version("demo", old.version).version == old.version
    finally:
        artifact.set_current(store, "demo", old.version)


def test_start_up_loads_every_graph_and_logs_the_broken_ones(
    store: ObjectStore, tmp_path: Path, caplog: pytest.LogCaptureFixture
):
    import shutil

    copy = FileStore(shutil.copytree(store.root, tmp_path / "store"))
    broken = copy.path("graphs/broken")
    broken.mkdir(parents=True)
    (broken / "current").write_text("nosuch-version")
    with caplog.at_level("ERROR", logger="dancegraph.graphstore"):
        with TestClient(create_app(copy, warm_up=True)) as warm:
            # the good graph is in memory before the first request; the broken one is named
            assert set(warm.get("/healthz").json()["loaded"]) == {"demo"}
    assert "graph broken cannot be loaded" in caplog.text


def test_a_graph_of_an_old_format_asks_for_a_rebuild(
    store: ObjectStore, tmp_path: Path, analysis: dict
):
    """A graph built before format 2 (no node frames around the bar) is refused with a coded
    problem naming the rebuild, not a crash."""
    import json
    import shutil

    copy = FileStore(shutil.copytree(store.root, tmp_path / "old"))
    version = artifact.current_version(copy, "demo")
    path = copy.path(artifact.graph_key("demo", version)) / "manifest.json"
    path.write_text(json.dumps(dict(json.loads(path.read_text()), format=1)))
    with TestClient(create_app(copy)) as old:
        resp = old.post("/v1/graphs/demo/search", json={"analysis": analysis, "spec": {}})
    assert resp.headers["content-type"].startswith(PROBLEM)
    body = resp.json()
    assert body["code"] == "graph_version"
    assert "rebuild it: dancegraph dataset build demo" in body["detail"]
