"""Learned embeddings: training, model files, resume, bad input, graph build and search with them.

Everything runs on a tiny generated paired set (2 songs × 2 sections × 4 bars) for 1–2 epochs:
these tests check the machinery, not the accuracy (bench/bench_embed.py measures that).
"""

from __future__ import annotations

import json
import shutil
import struct

import numpy as np
import pytest

from dancegraph.embed import model as model_mod
from dancegraph.embed.data import TrainingDataError, load_training_set, write_paired_set
from dancegraph.embed.model import load_model
from dancegraph.embed.train import train
from dancegraph.errors import ModelFileError

QUIET = None  # no progress lines in tests


@pytest.fixture(scope="module")
def paired(tmp_path_factory):
    return write_paired_set(tmp_path_factory.mktemp("paired"), n_songs=2, bars=4, seed=0)


@pytest.fixture(scope="module")
def style_run(paired, tmp_path_factory):
    out = tmp_path_factory.mktemp("style")
    summary = train("style", paired, out, epochs=2, phase1_epochs=1, progress=QUIET)
    return out, summary


@pytest.fixture(scope="module")
def rhythm_run(paired, tmp_path_factory):
    out = tmp_path_factory.mktemp("rhythm")
    summary = train("rhythm", paired, out, epochs=2, progress=QUIET)
    return out, summary


def test_paired_set_has_styles_signatures_and_pairs(paired):
    ts = load_training_set(paired, "rhythm")
    assert len(ts.music) == len(ts.dance) == 16 and ts.pairs.shape == (16, 2)
    assert set(ts.music.label) == set(ts.dance.label) and len(set(ts.music.label)) >= 2
    # the dancer dances the song's own bar signatures
    for m, d in ts.pairs:
        assert np.array_equal(ts.music.bits[m], ts.dance.bits[d])
    assert np.stack(ts.music.rhythm_x).shape == (16, 2, 200)
    assert np.stack(ts.dance.rhythm_x).shape == (16, 5, 60)


def test_style_training_writes_a_loadable_versioned_model(style_run, paired):
    out, summary = style_run
    path = out / summary["path"]
    assert path.name == f"{summary['version']}.dgm" and summary["kind"] == "style"
    m = load_model(path)
    assert m.sha256 == summary["sha256"] and m.version.startswith("style-")
    assert m.header["format"] == model_mod.FORMAT
    assert m.header["training"]["epochs"] == 2
    assert len(m.header["config"]["classes"]) >= 2
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["phase"] for r in rows] == [1, 2]  # unpaired, then paired with the MSE term
    assert all("pair_dist_train" in r and "music_acc_train" in r for r in rows)
    assert load_model(path) is m  # loaded once per process
    # inference shapes: 8-s windows of a song's log-mel, phrases of dance
    mel = np.full((96, 3000), -60.0, np.float32)
    assert m.music_style(mel, np.array([0.0, 2.0, 29.0])).shape == (3, 32)
    assert m.dance_style(np.zeros((2, 3, 18, 240), np.float32)).shape == (2, 32)


def test_phase2_spreads_the_embeddings_instead_of_collapsing_them(paired, tmp_path):
    """λ5·MSE(Z_M, Z_D) alone sends every bar of both branches to one point of the sphere (here,
    without the variance hinge, λ5 warm-up and lower phase-2 rate, the spreads went 0.072 → 0.096
    and 0.032 → 0.009 while the pairs closed in); with them phase 2 spreads both branches out
    (to 0.153 and 0.083 here) while it pulls the pairs together."""
    train("style", paired, tmp_path, epochs=6, phase1_epochs=1, progress=QUIET)
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["phase"] for r in rows] == [1, 2, 2, 2, 2, 2]
    for branch in ("music", "dance"):
        spread = [r[f"{branch}_spread"] for r in rows]
        assert spread[-1] > 1.5 * spread[0], (branch, spread)
    assert rows[-1]["pair_dist_train"] < 0.75 * rows[0]["pair_dist_train"]


def test_rhythm_model_gives_top3_probabilities(rhythm_run):
    out, summary = rhythm_run
    m = load_model(out / summary["path"])
    p = m.signature_scores("music", np.zeros((4, 2, 200)), np.zeros((4, 32)))
    assert p.shape == (4, 13) and np.allclose(p.sum(1), 1.0, atol=1e-5)
    with pytest.raises(ModelFileError, match="not a style model"):
        m.dance_style(np.zeros((1, 3, 18, 240)))


def test_resume_continues_to_the_same_weights(paired, tmp_path, rhythm_run):
    _, straight = rhythm_run
    out = tmp_path / "r"
    first = train("rhythm", paired, out, epochs=1, progress=QUIET)
    assert first["training"]["epochs"] == 1
    resumed = train("rhythm", paired, out, epochs=2, resume=True, progress=QUIET)
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2]
    assert resumed["sha256"] == straight["sha256"]  # bit-identical to the uninterrupted run


def _rewrite(path, header_change=None, payload_cut=0, flip=None):
    blob = bytearray(path.read_bytes())
    (n,) = struct.unpack("<Q", blob[8:16])
    header = json.loads(blob[16 : 16 + n])
    payload = blob[16 + n :]
    if header_change:
        header.update(header_change)
    if flip is not None:
        payload[flip] ^= 0xFF
    if payload_cut:
        payload = payload[:-payload_cut]
    head = json.dumps(header).encode()
    return bytes(blob[:8]) + struct.pack("<Q", len(head)) + head + bytes(payload)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"header_change": {"format": 99}}, "format version 99"),
        ({"payload_cut": 100}, "truncated"),
        ({"flip": 500}, "corrupted"),
    ],
)
def test_bad_model_files_fail_at_load(rhythm_run, tmp_path, change, message):
    out, summary = rhythm_run
    bad = tmp_path / "bad.dgm"
    bad.write_bytes(_rewrite(out / summary["path"], **change))
    with pytest.raises(ModelFileError, match=message) as exc:
        load_model(bad)
    assert exc.value.code == "model_file_invalid"


def test_not_a_model_and_wrong_hash(rhythm_run, tmp_path):
    out, summary = rhythm_run
    junk = tmp_path / "junk.dgm"
    junk.write_bytes(b"hello")
    with pytest.raises(ModelFileError, match="bad magic"):
        load_model(junk)
    with pytest.raises(ModelFileError, match="expected"):
        load_model(out / summary["path"], sha256="0" * 64)
    with pytest.raises(ModelFileError, match="cannot be read"):
        load_model(tmp_path / "missing.dgm")


def _manifest(paired, tmp_path, edit):
    data = json.loads(paired.read_text())
    edit(data)
    path = paired.parent / f"m-{tmp_path.name}.json"
    path.write_text(json.dumps(data))
    return path


def test_empty_manifest_is_refused(paired, tmp_path):
    path = _manifest(paired, tmp_path, lambda d: d.update(music=[], dance=[], pairs=[]))
    for kind in ("style", "rhythm"):
        with pytest.raises(TrainingDataError) as exc:
            train(kind, path, tmp_path / kind, epochs=1, progress=QUIET)
        assert exc.value.code == "training_data_empty"


def test_single_class_manifest_is_refused(paired, tmp_path):
    def one_style(d):
        for e in d["music"] + d["dance"]:
            e["style"] = {"tempo": "slow", "quality": "pop"}
            e["signatures"] = ["01010101"] * len(e["bars"])

    path = _manifest(paired, tmp_path, one_style)
    for kind in ("style", "rhythm"):
        with pytest.raises(TrainingDataError, match="single|every training bar") as exc:
            train(kind, path, tmp_path / kind, epochs=1, progress=QUIET)
        assert exc.value.code == "training_data_single_class"


def test_train_cli_reports_errors_with_their_code(paired, tmp_path, capsys):
    from dancegraph.cli import main

    path = _manifest(paired, tmp_path, lambda d: d.update(music=[], dance=[], pairs=[]))
    rc = main(["train", "rhythm", "--manifest", str(path), "--out", str(tmp_path / "o")])
    assert rc == 2 and "training_data_empty" in capsys.readouterr().err


@pytest.fixture(scope="module")
def demo_store(tmp_path_factory):
    from dancegraph.motion.dataset import import_dataset
    from dancegraph.motion.demo import write_demo_library
    from dancegraph.store import FileStore

    root = tmp_path_factory.mktemp("demo")
    store = FileStore(root / "store")
    lib = write_demo_library(root / "lib")
    import_dataset(lib, "demo", store, json.loads((lib / "manifest.json").read_text()))
    return store


def test_graph_built_with_learned_models_reports_and_uses_them(
    demo_store, style_run, rhythm_run, capsys
):
    from dancegraph.cli import main
    from dancegraph.graph import artifact
    from dancegraph.graph.problem import music_inputs, music_style
    from services.graphstore.client import LocalGraphStore

    style_path = style_run[0] / style_run[1]["path"]
    rhythm_path = rhythm_run[0] / rhythm_run[1]["path"]
    args = ["dataset", "build", "demo", "--store", str(demo_store.root), "--json"]
    assert main([*args, "--embedding", str(style_path), "--rhythm-model", str(rhythm_path)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["embedding"] == style_run[1]["version"]
    g = artifact.load_current(demo_store, "demo")
    entry = g.manifest["embedding"]
    assert entry["style_model"]["sha256"] == style_run[1]["sha256"]
    assert entry["rhythm_model"]["version"] == rhythm_run[1]["version"]
    # node styles are E_D's: augmentations share their source bar's
    src = np.asarray(g.node_source)[:, 0]
    assert np.allclose(g.style, np.asarray(g.style)[src])
    m = load_model(style_path)
    originals = np.flatnonzero(np.asarray(g.node_kind) == 0)
    assert not np.allclose(g.style[originals[0]], g.style[originals[-1]])
    # the graphstore names the learned model
    info = LocalGraphStore(demo_store).graph_info("demo")
    assert info["embedding"] == m.version
    assert info["embedding_details"]["rhythm_model"]["version"] == rhythm_run[1]["version"]
    assert "bridge" not in info["embedding_details"]
    # search side: the music style lands in the learned space, top-3 from the rhythm model
    rng = np.random.default_rng(0)
    music = {
        "bars": np.stack([np.arange(6) * 2.0, np.arange(6) * 2.0 + 2.0], axis=1),
        "n": 6,
        "onset": rng.random((6, 2, 200)),
        "topk": np.zeros((6, 3), int),
    }
    z = music_style(music, g)
    assert z.shape == (6, 32) and not np.allclose(z, music_style(dict(music), None))
    z2, used = music_inputs(music, g)
    assert np.allclose(z, z2) and (music["topk"] == 0).all()  # the input is not changed
    assert used["topk"].shape == (6, 3) and (used["topk"][:, 0] != used["topk"][:, 1]).all()
    assert used["style_source"]["style"] == "bridge"
    assert used["style_source"]["signatures"] == "rhythm_model"


def test_build_refuses_a_bad_model_before_work(demo_store, tmp_path, capsys):
    from dancegraph.cli import main

    bad = tmp_path / "bad.dgm"
    bad.write_bytes(b"DGMODEL\n" + b"\x00" * 4)
    args = ["dataset", "build", "demo", "--store", str(demo_store.root), "--embedding", str(bad)]
    assert main(args) == 2
    assert "model_file_invalid" in capsys.readouterr().err


def test_build_refuses_a_model_of_the_wrong_kind(demo_store, rhythm_run, capsys):
    from dancegraph.cli import main

    rhythm_path = rhythm_run[0] / rhythm_run[1]["path"]
    args = ["dataset", "build", "demo", "--store", str(demo_store.root)]
    assert main([*args, "--embedding", str(rhythm_path)]) == 2
    assert "expected a style model" in capsys.readouterr().err


# --- E_M at search time: the music terms the audio gives, carried by the analysis ------------


@pytest.fixture(scope="module")
def learned_graph(demo_store, style_run, rhythm_run):
    from dancegraph.graph import artifact
    from dancegraph.graph.build import build_dataset_graph

    build_dataset_graph(
        demo_store,
        "demo",
        embedding=str(style_run[0] / style_run[1]["path"]),
        rhythm_model=str(rhythm_run[0] / rhythm_run[1]["path"]),
    )
    return artifact.load_current(demo_store, "demo")


def test_a_corrupted_stored_model_fails_when_the_graph_loads(learned_graph, demo_store, tmp_path):
    from dancegraph.errors import ModelFileError
    from dancegraph.store import FileStore
    from services.graphstore.client import LocalGraphStore

    copy = FileStore(shutil.copytree(demo_store.root, tmp_path / "store"))
    assert LocalGraphStore(copy).graph("demo").version == learned_graph.version
    record = learned_graph.manifest["embedding"]["style_model"]
    model_file = copy.path(record["key"])
    model_file.write_bytes(_rewrite(model_file, flip=500))
    with pytest.raises(ModelFileError) as err:
        LocalGraphStore(copy).graph("demo")  # a fresh graph store: fails at load, naming the file
    assert record["key"].split("/")[-1] in err.value.message


@pytest.fixture(scope="module")
def song(paired):
    """A generated song of the paired set (16 s) and its analysis."""
    from dancegraph.music.analysis import analyze

    path = paired.parent / json.loads(paired.read_text())["music"][0]["audio"]
    return path, analyze(path)


def test_search_uses_the_e_m_styles_the_analysis_carries(learned_graph, song, demo_store):
    import dataclasses

    from dancegraph.embed.learned import add_music_terms
    from dancegraph.errors import SpecError
    from dancegraph.graph.problem import _music_arrays, music_style
    from dancegraph.music.analysis import MusicAnalysis
    from dancegraph.spec import parse_spec
    from services.graphstore.client import LocalGraphStore

    path, analysis = song
    g = learned_graph
    sha = g.manifest["embedding"]["style_model"]["sha256"]
    full = add_music_terms(analysis, g, path)
    assert not analysis.learned_style  # a copy: the song's own analysis is not changed
    assert full.learned_style[sha].shape == (analysis.n_bars, 32)
    rsha = g.manifest["embedding"]["rhythm_model"]["sha256"]
    assert full.learned_topk[rsha].shape == (analysis.n_bars, 3)
    z_e = music_style(_music_arrays(full), g, full)
    z_b = music_style(_music_arrays(analysis), g, analysis)
    assert np.allclose(z_e, full.learned_style[sha]) and not np.allclose(z_e, z_b, atol=1e-3)

    # through the graph store, after a JSON round trip (the HTTP path carries the same dict)
    store = LocalGraphStore(demo_store)
    spec = parse_spec({"alternatives": 1}, dataset="demo")
    sent = MusicAnalysis.from_dict(json.loads(json.dumps(full.to_dict())))
    with_e_m = store.search(sent, spec).to_dict()
    bridged = store.search(analysis, spec).to_dict()
    src = with_e_m["constraints"]["music_style"]
    assert src["style"] == "e_m" and src["style_model"] == g.manifest["embedding"]["version"]
    assert src["signatures"] == "rhythm_model"
    assert bridged["constraints"]["music_style"]["style"] == "bridge"
    assert "no E_M style" in bridged["constraints"]["music_style"]["note"]
    style_cost = [
        [b["style"] for b in r["alternatives"][0]["per_bar"]] for r in (with_e_m, bridged)
    ]
    assert style_cost[0] != style_cost[1]

    # styles of another model are not used; a wrong shape is refused with its code
    other = dataclasses.replace(analysis, learned_style={"0" * 64: full.learned_style[sha]})
    assert store.search(other, spec).report["music_style"]["style"] == "bridge"
    bad = dataclasses.replace(analysis, learned_style={sha: full.learned_style[sha][:-1]})
    with pytest.raises(SpecError) as exc:
        store.search(bad, spec)
    assert exc.value.code == "analysis_invalid"
    # the analysis without learned terms serialises as before (the cache by audio hash holds)
    assert "learned_style" not in analysis.to_dict()


def test_synthesize_and_the_job_path_compute_the_learned_terms(
    learned_graph, song, demo_store, tmp_path
):
    from dancegraph.render import synthesize
    from dancegraph.spec import Spec
    from services.worker.pipeline import with_learned_terms

    path, analysis = song
    sha = learned_graph.manifest["embedding"]["style_model"]["sha256"]
    spec = Spec.model_validate({"dataset": "demo", "alternatives": 1})
    done = synthesize(path, learned_graph, spec, tmp_path / "out", analysis=analysis)
    assert done["search"]["constraints"]["music_style"]["style"] == "e_m"

    demo_store.put_file("uploads/song.wav", path)
    job = with_learned_terms(demo_store, "uploads/song.wav", analysis, "demo")
    assert job.learned_style[sha].shape == (analysis.n_bars, 32)
    assert not analysis.learned_style
    assert with_learned_terms(demo_store, "uploads/song.wav", analysis, "nope") is analysis
