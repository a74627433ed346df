"""Mixed skeletons in one library (issue 34): cmu-modern (31 joints, CMU units, 120 fps) and
cmu-salsa (43 joints, metres, 60 fps) imported as one library on the salsa skeleton, built as
one graph and searched; its dances' seams as smooth as each library's alone, each judged against
the library's own frame-to-frame distribution (``metrics.smoothness``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.bench_library import dance_seams, library_folder
from dancegraph.graph.build import build_dataset_graph
from dancegraph.motion.dataset import import_dataset, load_dataset
from dancegraph.motion.fk import forward_kinematics
from dancegraph.music.analysis import analyze
from dancegraph.store import FileStore

SALSA = ("60_01", "61_01")
MODERN = ("05_02", "05_04", "05_06")
SONG = "Kevin_MacLeod_-_Vibe_Ace.hq.ogg"


@pytest.fixture(scope="module")
def built(shared: Path, tmp_path_factory) -> FileStore:
    root = tmp_path_factory.mktemp("mixed")
    store = FileStore(root / "store")
    for name, salsa, modern in (
        ("mixed", SALSA, MODERN),
        ("salsa", SALSA, ()),
        ("modern", (), MODERN),
    ):
        src, manifest = library_folder(root / name, salsa, modern)
        if not salsa:
            manifest.pop("skeleton")
        report = import_dataset(src, name, store, manifest)
        assert report.failed == []
        build_dataset_graph(store, name)
    return store


def test_other_skeletons_are_retargeted_onto_the_librarys(built):
    ds = load_dataset(built, "mixed")
    assert ds.skeleton.n_joints == 43 and ds.meta["skeleton_source"] == "take:60_01_scaled.bvh"
    rows = {c.id: c for c in ds.clips}
    assert all(rows[t].retarget["from_joints"] == 31 for t in MODERN)
    assert all(rows[t].retarget == {} and rows[t].fps == 60 for t in SALSA)
    assert all(rows[t].fps == 120 and rows[t].source_joints == 31 for t in MODERN)

    def stance(clip: str) -> tuple[float, float]:
        pos, _ = forward_kinematics(ds.motion(clip))
        return float(np.median(pos[:, 0, 1])), float(np.percentile(pos[:, :, 1].min(axis=1), 5))

    # the retargeted dancers stand where the library's own do: hips height and the floor
    hips, floor = np.array([stance(c) for c in SALSA]).mean(axis=0)
    for take in MODERN:
        h, f = stance(take)
        assert abs(h - hips) < 0.05 and abs(f - floor) < 0.05, take


def test_seams_of_the_mixed_graph_are_as_smooth_as_each_library_alone(built, cc_music_dir):
    analysis = analyze(cc_music_dir / SONG)
    alone = {name: dance_seams(built, name, analysis) for name in ("salsa", "modern")}
    mixed = dance_seams(built, "mixed", analysis)
    modern_in_mixed = dance_seams(built, "mixed", analysis, only="modern")
    assert modern_in_mixed["styles"] == {"modern": len(analysis.bars)}
    for row in (*alone.values(), mixed, modern_in_mixed):
        assert row["seams"] > 0 or row["styles"] == {"salsa": len(analysis.bars)}
        # no seam above the library's own p99 (its frames: about 2 % lie there by definition)
        assert row["flagged_share"] <= 0.05
        if row["seams"]:
            assert row["median_percentile"] <= row["chance_median_percentile"] + 15
    assert modern_in_mixed["flagged_share"] <= alone["modern"]["flagged_share"] + 0.05
    assert mixed["flagged_share"] <= max(a["flagged_share"] for a in alone.values()) + 0.05
