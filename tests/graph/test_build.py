"""Graph build: nodes, augmentations, features and edges on the project's generated demo bars."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dancegraph.graph import artifact
from dancegraph.graph.build import BuildParams, _lower_body, build_arrays, compute_edges, pair_cost
from dancegraph.motion.retime import BEAT0
from dancegraph.motion.stitch import seam_distance


def test_node_ids_kinds_and_tags(demo_bars, demo_build):
    arrays, ids, manifest = demo_build
    nb = len(demo_bars.signature)
    kind = arrays["node_kind"]
    assert (kind[:nb] == 0).all() and (kind[nb : 2 * nb] == 1).all()
    assert ids[0] == "groove_100:0" and ids[nb] == "groove_100:0~m"
    assert len(set(ids)) == len(ids)
    tags = manifest["tags"]
    aug_bit = 1 << tags.index("augmented")
    assert ((arrays["node_tags"][kind > 0] & aug_bit) > 0).all()
    assert ((arrays["node_tags"][kind == 0] & aug_bit) == 0).all()
    for k, name in enumerate(artifact.KINDS):
        bit = 1 << tags.index(name)
        assert (((arrays["node_tags"] & bit) > 0) == (kind == k)).all()
    for i, nid in enumerate(ids):
        if kind[i] == 2:
            assert "~b" in nid
        if kind[i] == 3:
            assert "~s" in nid
    # blends and shuffles exist, are capped, and only join bars of one signature
    for k, ratio in ((2, 0.25), (3, 0.25)):
        assert 0 < (kind == k).sum() <= ratio * nb
        src = arrays["node_source"][kind == k]
        assert all(demo_bars.signature[a] == demo_bars.signature[b] for a, b in src)
        assert all(demo_bars.clip[a] != demo_bars.clip[b] for a, b in src)
    mirror_of = arrays["mirror_of"]
    assert (mirror_of[mirror_of[:nb]] == np.arange(nb)).all()
    assert (mirror_of[kind >= 2] == -1).all()


def _rows(arrays: dict, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Node i's stored root, rotations and beats."""
    r = int(arrays["motion_row"][i])
    a, b = arrays["motion_ptr"][r], arrays["motion_ptr"][r + 1]
    return arrays["root"][a:b], arrays["rotations"][a:b].astype(float), arrays["motion_beats"][r]


def test_augmented_motion_comes_from_its_sources(demo_bars, demo_build):
    arrays, ids, manifest = demo_build
    kind = arrays["node_kind"]
    lower = _lower_body(demo_bars.skeleton)
    assert lower[0] and lower.sum() == 9  # hips + two legs of 4 joints
    # a node stores its take's frames around the bar and where the bar's beats fall in them
    nb = len(demo_bars.signature)
    for i in (0, 5, nb - 1):
        root, rot, beats = _rows(arrays, i)
        a, b = demo_bars.ptr[i], demo_bars.ptr[i + 1]
        np.testing.assert_allclose(root, demo_bars.root[a:b], atol=1e-5)
        np.testing.assert_allclose(beats, demo_bars.beats[i], atol=1e-4)
    root, _, beats = _rows(arrays, 5)  # inside a take: a beat of frames either side of the bar
    fps = arrays["motion_fps"][5]
    assert 0 <= beats[BEAT0 - 1] <= 3 and len(root) - 4 <= beats[BEAT0 + 5] <= len(root) - 1
    assert beats[BEAT0] - beats[BEAT0 - 1] == pytest.approx(fps * 60 / 100, rel=1e-3)
    # blend: bar b's frames, root and lower body; bar a's upper body warped beat to beat onto them
    i = int(np.nonzero(kind == 2)[0][0])
    a, b = arrays["node_source"][i]
    root, rot, beats = _rows(arrays, i)
    b_root, b_rot, b_beats = _rows(arrays, b)
    a_root, a_rot, a_beats = _rows(arrays, a)
    np.testing.assert_allclose(root, b_root, atol=1e-5)
    np.testing.assert_allclose(beats, b_beats)
    assert np.allclose(rot[:, lower], b_rot[:, lower], atol=2e-3)
    for j in range(5):  # on every beat the upper body shows bar a's pose on its own beat
        got = rot[int(round(b_beats[BEAT0 + j]))][~lower]
        want = a_rot[int(round(a_beats[BEAT0 + j]))][~lower]
        assert np.abs(np.sum(got * want, axis=-1)).min() > 0.98
    # shuffle: bar a up to its beat 2, then bar b's joints (below the root) after the blend
    j = int(np.nonzero(kind == 3)[0][0])
    a, b = arrays["node_source"][j]
    root, rot, beats = _rows(arrays, j)
    a_root, a_rot, a_beats = _rows(arrays, a)
    b_root, b_rot, b_beats = _rows(arrays, b)
    two = int(np.floor(a_beats[BEAT0 + 2]))
    assert np.allclose(rot[: two + 1], a_rot[: two + 1], atol=2e-3)
    np.testing.assert_allclose(beats[: BEAT0 + 3], a_beats[: BEAT0 + 3])
    shift = round(b_beats[BEAT0 + 2] - a_beats[BEAT0 + 2])  # whole frames: b's own frames
    np.testing.assert_allclose(beats[BEAT0 + 3 :], b_beats[BEAT0 + 3 :] - shift, atol=1e-5)
    late = np.arange(int(beats[BEAT0 + 4]) - 3, len(rot))  # from just before the closing downbeat
    np.testing.assert_allclose(rot[late, 1:], b_rot[late + shift, 1:], atol=1e-3)
    # mirror: the root path is reflected in x
    root, _, _ = _rows(arrays, nb)
    assert np.allclose(root[:, 0], -_rows(arrays, 0)[0][:, 0], atol=1e-5)


def test_edges_follow_threshold_and_keep_takes_linked(demo_bars, demo_build):
    arrays, ids, manifest = demo_build
    n = len(ids)
    indptr, indices, costs = arrays["indptr"], arrays["indices"], arrays["costs"]
    src = np.repeat(np.arange(n), np.diff(indptr))
    assert (src != indices).all()  # no self loops
    assert (
        np.diff(indptr).min() >= 1 and np.bincount(indices, minlength=n).min() >= 1
    )  # no dead ends
    assert (
        np.diff(indptr) <= BuildParams().max_out_degree + 2 * BuildParams().min_degree + 2
    ).all()
    # every consecutive pair of a take (and of its mirror) is linked, its pose term ~0 (q's
    # lead-in is p's continuation): the cost is the style term
    nb = len(demo_bars.signature)
    edge = {(int(s), int(d)): float(c) for s, d, c in zip(src, indices, costs, strict=True)}
    style = arrays["style"].astype(float)
    for i in range(nb - 1):
        if demo_bars.clip[i] == demo_bars.clip[i + 1]:
            for p, q in ((i, i + 1), (i + nb, i + 1 + nb)):
                t_z = 1.5 * np.linalg.norm(style[p] - style[q])
                assert edge[(p, q)] == pytest.approx(t_z, abs=1e-3)
    blocks = manifest["feature_blocks"]
    t_d = pair_cost(
        arrays["exit"][[0]],
        arrays["entry"][[1]],
        arrays["style"][[0]],
        arrays["style"][[0]],
        blocks,
        1.0,
        0.0,
    )[0]
    assert t_d < 1e-3
    forced = (
        manifest["build"]["forced_out"]
        + manifest["build"]["forced_in"]
        + manifest["build"]["consecutive"]
    )
    assert (costs < 20.0).sum() >= len(costs) - 2 * forced


def test_chunked_edges_match_brute_force(demo_build):
    """Edges from chunks of rows over several cut offsets (NaN where a node has no frames) equal
    the brute-force least over the offsets of every pair."""
    arrays, ids, manifest = demo_build
    blocks = manifest["feature_blocks"]
    rng = np.random.default_rng(1)
    n = len(ids)
    entry = np.stack([arrays["entry"], arrays["entry"][rng.permutation(n)]])
    exit_ = np.stack([arrays["exit"], arrays["exit"][rng.permutation(n)]])
    entry[1, rng.random(n) < 0.3] = np.nan
    exit_[1, rng.random(n) < 0.3] = np.nan
    entry, exit_ = entry.astype(np.float32), exit_.astype(np.float32)
    style = arrays["style"]
    params = BuildParams(threshold=40.0, max_out_degree=n, chunk=7)
    s1, d1, c1, _ = compute_edges(entry, exit_, style, blocks, params, np.zeros((0, 2), int))
    p, q = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    p, q = p.ravel(), q.ravel()
    full = pair_cost(exit_[:, p], entry[:, q], style[p], style[q], blocks, 1.0, 1.5).reshape(n, n)
    offset0 = pair_cost(exit_[0, p], entry[0, q], style[p], style[q], blocks, 1.0, 1.5)
    assert (full.ravel() <= offset0 + 1e-6).all() and (full.ravel() < offset0 - 1e-3).any()
    np.fill_diagonal(full, np.inf)
    want = set(zip(*np.nonzero(full < 40.0), strict=True))
    got = {(int(a), int(b)) for a, b, c in zip(s1, d1, c1, strict=True) if c < 40.0}
    assert got == {(int(a), int(b)) for a, b in want}
    assert np.allclose(c1[c1 < 40.0], full[s1[c1 < 40.0], d1[c1 < 40.0]], rtol=1e-3, atol=1e-3)


def test_edge_cost_is_the_renderers_seam_distance(demo_bars, demo_build):
    """An edge's pose term is the least seam distance over the cut offsets (the renderer's own
    distance), with p dancing on past its bar and q at its lead-in, both at the same phase."""
    from dancegraph.graph.build import _Nodes, transition_features

    arrays, ids, manifest = demo_build
    b = demo_bars
    nodes = _Nodes(b.ptr, b.root.astype(float), b.rotations, b.beats.astype(float), b.fps)
    seam = manifest["seam"]
    offsets = np.asarray(seam["offsets"])
    assert offsets[0] == 0.0 and np.abs(offsets).max() == pytest.approx(1.0)
    exit_, entry, blocks = transition_features(demo_bars.skeleton, nodes, offsets, seam["beat_s"])
    nb = len(b.signature)
    np.testing.assert_allclose(exit_[0], arrays["exit"][:nb], atol=1e-5)
    rows = np.arange(len(arrays["indices"]))
    src = np.searchsorted(arrays["indptr"], rows, side="right") - 1
    dst = arrays["indices"][rows]
    rows = rows[(src < nb) & (dst < nb)]  # edges between original bars
    src, dst = src[rows], dst[rows]
    assert len(rows) > 50
    t_d = np.nanmin(seam_distance(exit_[:, src], entry[:, dst], blocks), axis=0)
    t_z = np.linalg.norm(arrays["style"][src] - arrays["style"][dst], axis=1)
    np.testing.assert_allclose(arrays["costs"][rows], t_d + 1.5 * t_z, rtol=1e-3, atol=1e-3)


def test_lower_threshold_gives_fewer_edges(demo_bars):
    few, _, m1 = build_arrays(
        demo_bars, BuildParams(threshold=8.0, mirror=False, blend_ratio=0, shuffle_ratio=0)
    )
    many, _, m2 = build_arrays(
        demo_bars, BuildParams(threshold=60.0, mirror=False, blend_ratio=0, shuffle_ratio=0)
    )
    assert len(few["indices"]) < len(many["indices"])
    assert m1["build"]["forced_out"] >= m2["build"]["forced_out"]


def test_bad_params_are_rejected():
    with pytest.raises(ValueError, match="frames_per_bar"):
        BuildParams(frames_per_bar=30)
    with pytest.raises(ValueError, match="threshold"):
        BuildParams(threshold=0)


@pytest.fixture(scope="module")
def demo_store(tmp_path_factory):
    """The generated demo library imported as dataset 'demo' (the project's own fixture)."""
    from dancegraph.motion.dataset import import_dataset
    from dancegraph.motion.demo import write_demo_library
    from dancegraph.store import FileStore

    root = tmp_path_factory.mktemp("demo")
    store = FileStore(root / "store")
    import_dataset(write_demo_library(root / "lib"), "demo", store)
    return store


def test_dataset_build_cli_prints_counts_and_stores_a_version(demo_store, capsys):
    from dancegraph.cli import main
    from dancegraph.motion.dataset import load_dataset

    assert (
        main(["dataset", "build", "demo", "--store", str(demo_store.root), "--threshold", "15"])
        == 0
    )
    out = capsys.readouterr().out
    for word in ("nodes", "edges", "out-degree", "build time"):
        assert word in out
    g = artifact.load_current(demo_store, "demo")
    ds = load_dataset(demo_store, "demo")
    assert g.manifest["dataset"] == {
        "name": "demo",
        "version": ds.version,
        "licence": ds.licence,
        "acknowledgement": ds.meta.get("acknowledgement"),
        "style_tempo_bpm": None,  # the demo library declares no style tempo range
        "style": None,  # nor one style for the library (its takes have three)
    }
    assert g.manifest["params"]["threshold"] == 15.0
    assert [n for n, k in zip(g.node_ids, g.node_kind, strict=True) if k == 0] == ds.node_ids()
    assert f"nodes {g.n_nodes}" in out and f"edges {g.n_edges}" in out
    # the node's stored motion is its bar: first frame equals the take's frame at the downbeat
    bar = ds.bars[3]
    m = ds.motion(bar.clip_id)
    node = g.node_motion(g.node_index(bar.node_id))
    frame = int(round(bar.beat_times[0] * m.fps))
    info = g.node_info(g.node_index(bar.node_id))
    assert info["frames"] == [bar.start_frame, bar.end_frame] and info["kind"] == "original"
    mirrored = g.node_info(g.node_index(bar.node_id + "~m"))
    assert mirrored["tags"] == ["mirror", "augmented"] + [
        t for t in info["tags"] if t != "original"
    ]
    assert np.allclose(node.root_positions[0], m.root_positions[frame], atol=0.02)


def test_dataset_build_of_unknown_dataset_names_it(demo_store, capsys):
    from dancegraph.cli import main

    assert main(["dataset", "build", "nosuch", "--store", str(demo_store.root)]) == 2
    assert "unknown_dataset" in capsys.readouterr().err


def test_compressed_features_keep_transition_costs(demo_build):
    arrays, ids, manifest = demo_build
    rng = np.random.default_rng(0)
    p, q = rng.integers(0, len(ids), 500), rng.integers(0, len(ids), 500)
    st = arrays["style"]
    full = pair_cost(
        arrays["exit"][p], arrays["entry"][q], st[p], st[q], manifest["feature_blocks"], 1.0, 1.5
    )
    pc = pair_cost(
        arrays["exit_pc"][p], arrays["entry_pc"][q], st[p], st[q], manifest["pc_blocks"], 1.0, 1.5
    )
    assert arrays["exit_pc"].shape[1] < arrays["exit"].shape[1]
    assert np.all(pc <= full + 1e-3)  # a projection never lengthens a difference
    assert np.median((full - pc) / full) < 0.05 and np.corrcoef(full, pc)[0, 1] > 0.98


def test_node_signatures_are_the_slot_patterns_of_their_own_beats(demo_bars, demo_build):
    from dancegraph.rhythm.signatures import nearest_common, to_bits, to_pattern, to_string

    # bar b of the first shuffle gets an accent on the half beat after beat 3 (slot 5): a pattern
    # no common signature has, with the same nearest one (so the same pairs are drawn)
    kind, src = demo_build[0]["node_kind"], demo_build[0]["node_source"]
    a0, b0 = src[kind == 3][0]
    sigs = list(demo_bars.signature)
    bits = to_bits(sigs[b0])
    bits[5] = 1 - bits[5]
    assert nearest_common(bits) == nearest_common(to_bits(sigs[b0]))
    sigs[b0] = to_string(bits)
    arrays, _, _ = build_arrays(dataclasses.replace(demo_bars, signature=sigs), BuildParams())
    nb = len(sigs)
    own = to_pattern(np.stack([to_bits(s) for s in sigs]))
    sig, kind, src = arrays["signature"], arrays["node_kind"], arrays["node_source"]
    assert sig.dtype == np.uint8
    assert (sig[:nb] == own).all() and (sig[nb : 2 * nb] == own).all()  # mirrors keep the timing
    blends = kind == 2
    assert (sig[blends] == own[src[blends, 0]]).all()
    # a shuffle dances beats 1-2 of bar a (slots 0-3) and beats 3-4 of bar b (slots 4-7)
    low, high = np.uint8(0x0F), np.uint8(0xF0)
    shuffles = kind == 3
    a, b = src[shuffles].T
    assert (sig[shuffles] == (own[a] & low) | (own[b] & high)).all()
    assert sig[shuffles][0] != own[a0] and (a[0], b[0]) == (a0, b0)
