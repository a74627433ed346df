"""Graph artifact: versioned immutable folders, memory-mapped loading, atomic 'current'."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from dancegraph.errors import ModelFileError, NotFoundError
from dancegraph.graph import artifact
from dancegraph.motion.retime import BEAT0, sample
from dancegraph.store import FileStore


def _write(store, demo_build, version):
    arrays, ids, manifest = demo_build
    return artifact.write_graph(store, "demo", arrays, manifest, node_ids=ids, version=version)


def test_roundtrip_is_memory_mapped_and_checksummed(tmp_path, demo_build):
    store = FileStore(tmp_path / "store")
    key = _write(store, demo_build, "v1")
    assert key == "graphs/demo/v1"
    g = artifact.load_graph(store.path(key), verify=True)
    arrays, ids, manifest = demo_build
    assert isinstance(g.indices, np.memmap) and isinstance(g.rotations, np.memmap)
    assert g.node_ids == ids
    for name in artifact.ARRAYS:
        assert np.array_equal(np.asarray(getattr(g, name)), arrays[name]), name
    man = json.loads((store.path(key) / "manifest.json").read_text())
    assert man["format"] == artifact.FORMAT_VERSION and set(man["checksums"]) >= {
        f"{a}.npy" for a in artifact.ARRAYS
    }
    assert man["embedding"]["version"] == "descriptor-v1"
    assert man["params"]["threshold"] == 20.0
    # the node's motion comes back as a Motion with the graph's skeleton: its bar at the take's
    # rate, and for the renderer the take's frames around the bar with the bar's beats in them
    m = g.node_motion(5)
    frames, beats = g.node_frames(5)
    assert frames.fps == m.fps == float(arrays["motion_fps"][5])
    assert m.n_frames == round(beats[BEAT0 + 4] - beats[BEAT0])
    assert frames.n_frames > m.n_frames + beats[BEAT0 + 1] - beats[BEAT0]  # a beat either side
    assert m.rotations.shape == (m.n_frames, g.skeleton.n_joints, 4)
    assert np.allclose(np.linalg.norm(m.rotations, axis=-1), 1.0)
    # the bar's frames are the stored ones from its downbeat on
    np.testing.assert_allclose(
        m.root_positions[1:4], sample(frames, beats[BEAT0] + np.arange(1, 4)).root_positions
    )
    assert g.node_motion(5, fps=30.0).n_frames == round(m.n_frames * 30.0 / m.fps)


def test_an_old_format_graph_asks_for_a_rebuild(tmp_path, demo_build):
    store = FileStore(tmp_path / "store")
    key = _write(store, demo_build, "v1")
    path = store.path(key) / "manifest.json"
    manifest = json.loads(path.read_text())
    path.write_text(json.dumps(dict(manifest, format=1)))
    with pytest.raises(ModelFileError) as err:
        artifact.load_graph(store.path(key))
    assert err.value.code == "graph_version"
    assert "rebuild it: dancegraph dataset build demo" in str(err.value)


def test_new_version_loads_while_old_keeps_answering(tmp_path, demo_build):
    store = FileStore(tmp_path / "store")
    _write(store, demo_build, "v1")
    old = artifact.load_current(store, "demo")
    old_edges = np.asarray(old.indices).copy()
    _write(store, demo_build, "v2")
    assert artifact.current_version(store, "demo") == "v2"
    new = artifact.load_current(store, "demo")
    assert new.version == "v2" and old.version == "v1"
    # the old graph's maps still read the old, untouched folder
    assert np.array_equal(np.asarray(old.indices), old_edges)
    assert artifact.list_versions(store, "demo") == ["v1", "v2"]
    assert artifact.list_graphs(store) == ["demo"]
    artifact.set_current(store, "demo", "v1")
    assert artifact.load_current(store, "demo").version == "v1"
    with pytest.raises(FileExistsError):
        _write(store, demo_build, "v1")


def test_same_build_twice_in_one_second_is_one_version(tmp_path, demo_build, monkeypatch):
    store = FileStore(tmp_path / "store")
    arrays, ids, manifest = demo_build
    frozen = time.gmtime()
    monkeypatch.setattr(artifact.time, "gmtime", lambda *_: frozen)  # both builds in one second
    first = artifact.write_graph(store, "demo", arrays, manifest, node_ids=ids)
    _write(store, demo_build, "other")  # current moves away
    second = artifact.write_graph(store, "demo", arrays, manifest, node_ids=ids)
    assert second == first  # same content, same second: the stored version is kept...
    assert artifact.current_version(store, "demo") == first.rsplit("/", 1)[1]  # ...and current
    assert sorted(artifact.list_versions(store, "demo")) == sorted(
        [first.rsplit("/", 1)[1], "other"]
    )
    assert not [p for p in store.path("graphs/demo").iterdir() if p.name.startswith(".tmp")]
    changed = {**arrays, "node_bar": np.asarray(arrays["node_bar"]) + 1}
    third = artifact.write_graph(store, "demo", changed, manifest, node_ids=ids)
    assert third != first  # other content in the same second: another version


def test_corrupt_and_missing_artifacts_are_named(tmp_path, demo_build):
    store = FileStore(tmp_path / "store")
    key = _write(store, demo_build, "v1")
    with pytest.raises(NotFoundError) as exc:
        artifact.load_current(store, "nosuch")
    assert exc.value.code == "unknown_dataset" and exc.value.field == "dataset"
    with pytest.raises(NotFoundError) as exc:
        artifact.set_current(store, "demo", "v9")
    assert exc.value.field == "version"
    target = store.path(key) / "costs.npy"
    data = bytearray(target.read_bytes())
    data[-1] ^= 0xFF
    target.write_bytes(bytes(data))
    with pytest.raises(ModelFileError) as exc:
        artifact.load_graph(store.path(key), verify=True)
    assert exc.value.field == "costs.npy"
    man = store.path(key) / "manifest.json"
    doc = json.loads(man.read_text())
    doc["format"] = 999
    man.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError) as exc:
        artifact.load_graph(store.path(key))
    assert exc.value.code == "graph_version"


def test_stats_report_degree_distribution(demo_graph):
    s = demo_graph.stats()
    assert s["nodes"] == demo_graph.n_nodes and s["edges"] == demo_graph.n_edges
    assert sum(s["degree"]["histogram"].values()) == demo_graph.n_nodes
    assert s["degree"]["min"] >= 1
