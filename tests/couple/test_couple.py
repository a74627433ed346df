"""Couple dances end to end on real partner takes (cmu-salsa 60_03/61_03 and 60_04/61_04, read
from the shared datasets): the couple graph, a synthesized couple on a generated song passing
the couple checks, the real-pair against wrong-pair calibration, and the files."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from dancegraph.couple.graph import (
    build_couple_graph,
    follow_frames,
    open_couple_graph,
    pair_frames,
)
from dancegraph.couple.placement import place_follow, relative_placement
from dancegraph.couple.render import render_couple_path
from dancegraph.errors import DanceGraphError, NotFoundError
from dancegraph.metrics.couple import CoupleReference, couple_scores, segment_distance
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.dataset import import_dataset, load_dataset
from dancegraph.motion.retime import BEAT0
from dancegraph.store import FileStore
from tests.demo import demo_song
from tests.motion.rigs import make_rigs

PAIRS = [["60_03", "61_03"], ["60_04", "61_04"]]


def _read_glb(path: Path) -> tuple[dict, bytes]:
    """A GLB's JSON document and binary chunk (glTF 2.0 container, read by hand)."""
    data = path.read_bytes()
    magic, version, total = struct.unpack_from("<III", data)
    assert (magic, version, total) == (0x46546C67, 2, len(data))
    n_json, _ = struct.unpack_from("<II", data, 12)
    doc = json.loads(data[20 : 20 + n_json])
    n_bin, _ = struct.unpack_from("<II", data, 20 + n_json)
    return doc, data[28 + n_json : 28 + n_json + n_bin]


@pytest.fixture(scope="module")
def couple(salsa_dir: Path, tmp_path_factory):
    """A store with six salsa takes (two partner pairs, and 60_09/61_09 not declared as
    partners) and the couple graph of the two pairs."""
    root = tmp_path_factory.mktemp("couple")
    store = FileStore(root / "store")
    manifest = {
        "files": "6?_0[349]_scaled.bvh",
        "strip_suffix": "_scaled",
        "fps": 60,
        "fps_reason": "captured at 60 fps",
        "style": "salsa",
        "tempo_prior_bpm": [150, 220],
        "partners": PAIRS,
    }
    import_dataset(salsa_dir, "salsa6", store, manifest)
    report = build_couple_graph(store, "salsa6")
    return root, store, report, open_couple_graph(store, "salsa6")


def test_couple_graph_pairs_both_partners(couple):
    _, store, report, graph = couple
    ds = load_dataset(store, "salsa6")
    assert graph.manifest["couple"]["partners"] == PAIRS
    # originals and their mirrors, no blends or shuffles (they would part the hands)
    assert report["nodes_by_kind"]["blend"] == report["nodes_by_kind"]["shuffle"] == 0
    assert report["nodes_by_kind"]["mirror"] == report["nodes_by_kind"]["original"] > 25
    assert report["degree"]["min"] >= 1
    # a node is the same bar of both partners: the follow's frames are its take's same frames
    i = next(k for k, n in enumerate(graph.node_ids) if n.startswith("60_03:") and "~" not in n)
    lead, beats = graph.node_frames(i)
    follow, fbeats = follow_frames(graph, i)
    assert np.array_equal(beats, fbeats) and lead.n_frames == follow.n_frames
    start, end = graph.node_info(i)["frames"]
    take = ds.motion("61_03")
    lo = int(round(start - beats[BEAT0]))
    assert np.allclose(follow.root_positions[0], take.root_positions[lo], atol=1e-5)
    # the stored relative placement is the pair's own at the downbeat
    rel = relative_placement(
        ds.motion("60_03").root_positions[start],
        ds.motion("60_03").rotations[start, 0],
        take.root_positions[start],
        take.rotations[start, 0],
    )
    assert np.allclose(graph.rel_entry[i], rel, atol=0.05)
    # a mirror mirrors both: the follow stays on the other side, the distance is the same
    m = int(graph.mirror_of[i])
    assert graph.rel_entry[m][0] == pytest.approx(-graph.rel_entry[i][0], abs=1e-4)
    assert graph.rel_entry[m][1] == pytest.approx(graph.rel_entry[i][1], abs=1e-4)
    # every edge that is not a take continuing matches the placement within the tolerance
    tol = graph.manifest["couple"]["placement_tolerance"]
    assert 0.0 < tol["xz_m"] < 0.5 and 0.0 < tol["yaw_rad"] < np.pi


def test_placement_round_trip():
    rng = np.random.default_rng(0)
    from dancegraph.motion import quat

    lead_root, follow_root = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    lead_rot = quat.normalize(rng.normal(size=(50, 4)))
    follow_rot = quat.normalize(rng.normal(size=(50, 4)))
    rel = relative_placement(lead_root, lead_rot, follow_root, follow_rot)
    root, rot = place_follow(lead_root, lead_rot, follow_root + 3.0, follow_rot[::-1], rel)
    assert np.allclose(relative_placement(lead_root, lead_rot, root, rot), rel, atol=1e-9)
    assert np.allclose(root[:, 1], follow_root[:, 1] + 3.0)


def test_segment_distance_cases():
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    crossing = np.array([[0.5, -1.0, 0.2], [0.5, 1.0, 0.2]])
    apart = np.array([[2.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    point = np.array([[0.5, 0.3, 0.0], [0.5, 0.3, 0.0]])
    got = segment_distance(np.stack([a, a, a]), np.stack([crossing, apart, point]))
    assert np.allclose(got, [0.2, 1.0, 0.3])


def test_real_pair_against_wrong_pair(couple):
    """The checks tell a pair that danced together from two takes that did not."""
    _, store, _, graph = couple
    ds = load_dataset(store, "salsa6")
    frames = pair_frames(ds, [tuple(p) for p in PAIRS])
    ref = CoupleReference.from_pairs(frames)
    real = couple_scores(frames[0], ref)
    wrong = couple_scores(pair_frames(ds, [("60_03", "61_09")])[0], ref)
    assert real["hips_within"] >= 0.99 and real["body_below_p1"] <= 0.01
    assert wrong["hips_within"] <= 0.9 and wrong["body_below_p1"] >= 0.1


@pytest.fixture(scope="module")
def synthesized(couple, tmp_path_factory):
    """``dancegraph synthesize --couple`` of the generated test song, 2 alternatives."""
    from dancegraph.cli import main

    store = couple[1]
    out = tmp_path_factory.mktemp("couple_out")
    wav, song = demo_song(out)
    spec = out / "spec.json"
    spec.write_text(json.dumps({"output": {"formats": ["bvh"]}, "alternatives": 2}))
    rig = make_rigs(out / "rigs", blender=False) / "cmu_cm.bvh"  # centimetres, another body
    argv = ["synthesize", str(wav), "--dataset", "salsa6", "--couple", "--out", str(out / "r")]
    argv += ["--rig", str(rig), "--follow-rig", str(rig)]
    assert main([*argv, "--spec", str(spec), "--store", str(store.root)]) == 0
    return out / "r", song


def test_couple_files_share_frames_and_world(synthesized, couple):
    result, song = synthesized
    graph = couple[3]
    timeline = json.loads((result / "timeline.json").read_text())
    assert timeline["couple"] is True and len(timeline["alternatives"]) == 2
    n_frames = round(song.duration_s * 30)
    for alt in timeline["alternatives"]:
        k = alt["index"]
        lead = read_bvh(result / f"alternatives/{k}/lead.bvh")
        follow = read_bvh(result / f"alternatives/{k}/follow.bvh")
        assert lead.n_frames == follow.n_frames == n_frames
        assert lead.skeleton == follow.skeleton == graph.skeleton
        hips = np.linalg.norm(lead.root_positions - follow.root_positions, axis=1)
        assert 0.1 < np.median(hips) < 1.5  # one world frame: the two stand together
        for entry in alt["bars"]:
            partners = entry["partners"]
            assert [partners["lead"]["take"], partners["follow"]["take"]] in PAIRS
        # each partner on its own rig (here the same centimetre rig), frame for frame
        for partner, dancer in (("lead", lead), ("follow", follow)):
            on_rig = read_bvh(result / alt["files"][f"{partner}_rig.bvh"])
            assert on_rig.n_frames == dancer.n_frames and alt["rig"][partner]["unit_scale"] > 0
        # one GLB holds both dancers, each its own skeleton, animated as the BVH files
        doc, blob = _read_glb(result / alt["files"]["glb"])
        assert [doc["nodes"][n]["name"] for n in doc["scenes"][0]["nodes"]] == ["lead", "follow"]
        assert len(doc["nodes"]) == 2 + 2 * graph.skeleton.n_joints
        for name, dancer in (("lead", lead), ("follow", follow)):
            node = next(i for i, n in enumerate(doc["nodes"]) if n["name"] == f"{name}:hip")
            channel = next(
                c
                for c in doc["animations"][0]["channels"]
                if c["target"] == {"node": node, "path": "translation"}
            )
            acc = doc["accessors"][doc["animations"][0]["samplers"][channel["sampler"]]["output"]]
            view = doc["bufferViews"][acc["bufferView"]]
            root = np.frombuffer(blob, np.float32, acc["count"] * 3, view["byteOffset"])
            assert np.allclose(root.reshape(-1, 3), dancer.root_positions, atol=1e-4)


def test_synthesized_couple_passes_the_couple_checks(synthesized, couple, capsys):
    """``dancegraph eval --result`` of the couple: inside the library's bands, smooth seams
    for both partners, and better than the chance row (the lead of one alternative with the
    follow of the other)."""
    from dancegraph.cli import main

    result, _ = synthesized
    capsys.readouterr()
    assert main(["eval", "--result", str(result), "--store", str(couple[1].root)]) == 0
    printed = json.loads(capsys.readouterr().out)
    metrics = json.loads((result / "couple_metrics.json").read_text())
    assert printed["alternatives"] == metrics["alternatives"]
    for row in metrics["alternatives"]:
        assert row["couple"]["hips_within"] >= 0.97
        assert row["couple"]["body_below_p1"] <= 0.02
        for key in ("lead", "follow"):
            assert row[key]["seam_flagged_share"] <= 0.25
    chance = metrics["chance"]
    assert len(chance) == 2
    ours = np.mean([r["couple"]["hips_within"] for r in metrics["alternatives"]])
    assert np.mean([c["hips_within"] for c in chance]) < ours


def test_render_refuses_bad_paths(couple):
    graph = couple[3]
    bars = np.array([[0.0, 0.4, 0.8, 1.2, 1.6], [1.6, 2.0, 2.4, 2.8, 3.2]])
    with pytest.raises(DanceGraphError) as err:
        render_couple_path(graph, graph.node_ids[:1], bars, 30.0)
    assert err.value.code == "render_mismatch"
    with pytest.raises(DanceGraphError) as err:
        render_couple_path(graph, [graph.node_ids[0], "nope:1"], bars, 30.0)
    assert err.value.code == "unknown_node"


def test_no_couple_graph_is_named(couple, tmp_path):
    store = FileStore(tmp_path / "empty")
    with pytest.raises(NotFoundError) as err:
        open_couple_graph(store, "salsa6")
    assert err.value.code == "couple_graph_missing"


def test_partners_are_cut_where_both_match(couple):
    """The cut of a couple's hand-over is chosen on both partners' seam distances: the lead
    stitched with the follow as partner and the follow with the lead are cut alike, and the
    partner's distance changes the choice against the lead alone somewhere on a long path."""
    from dancegraph.motion.stitch import stitch
    from dancegraph.render import bar_frames

    graph = couple[3]
    rng = np.random.default_rng(3)
    nodes = [int(i) for i in rng.choice(graph.n_nodes, 24, replace=False)]
    lead = [graph.node_frames(i) for i in nodes]
    follow = [follow_frames(graph, i) for i in nodes]
    beat = 0.36 + 0.02 * rng.random(24 * 4)
    times = np.concatenate([[0.5], 0.5 + np.cumsum(beat)])
    bars = np.stack([times[4 * b : 4 * b + 5] for b in range(24)])
    frames = bar_frames(bars[:, [0, 4]], 30.0)
    _, both = stitch(lead, bars, frames, 30.0, partners=[follow])
    _, other = stitch(follow, bars, frames, 30.0, partners=[lead])
    _, alone = stitch(lead, bars, frames, 30.0)
    assert np.array_equal(both["cuts"], other["cuts"])
    assert not np.array_equal(both["cuts"], alone["cuts"])
    _, reused = stitch(follow, bars, frames, 30.0, cut_at=both)
    assert np.array_equal(reused["cuts"], both["cuts"])
