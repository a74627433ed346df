"""Dataset import, manifests, reports and load_dataset (dancegraph.motion.dataset)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from dancegraph.cli import main as cli_main
from dancegraph.errors import DanceGraphError, NotFoundError
from dancegraph.motion import tempo as tempo_mod
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.dataset import (
    import_dataset,
    list_datasets,
    load_dataset,
    load_manifest,
    parse_manifest,
)
from dancegraph.motion.demo import write_demo_library
from dancegraph.motion.tempo import STEADY_MIN_CONFIDENCE
from dancegraph.paths import REPO_ROOT
from dancegraph.rhythm.signatures import COMMON_SIGNATURES
from dancegraph.store import FileStore, ObjectStore

MANIFESTS = REPO_ROOT / "datasets" / "manifests"
LEADERS = ("60_01", "60_03", "60_13", "60_15")


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory) -> Path:
    return write_demo_library(tmp_path_factory.mktemp("demo"), seed=0)


@pytest.fixture(scope="module")
def demo_manifest(demo_dir) -> dict:
    return json.loads((demo_dir / "manifest.json").read_text())


def _store(tmp_path: Path) -> ObjectStore:
    return FileStore(tmp_path / "store")


def _link(src: Path, dst_dir: Path, name: str | None = None) -> Path:
    dst_dir.mkdir(parents=True, exist_ok=True)
    dst = dst_dir / (name or src.name)
    dst.symlink_to(src)
    return dst


def test_demo_import_follows_the_annotations(demo_dir, demo_manifest, tmp_path):
    store = _store(tmp_path)
    report = import_dataset(demo_dir, "demo", store)  # manifest.json found in the folder
    assert report.failed == [] and report.warnings == []
    ds = load_dataset(store, "demo")
    assert ds.version == report.version and ds.licence == demo_manifest["licence"]
    assert {c.id for c in ds.clips} == set(demo_manifest["clips"])
    for clip in ds.clips:
        truth = demo_manifest["clips"][clip.id]
        assert clip.beat_source == "annotation"
        assert clip.style == truth["style"]
        assert clip.tempo_bpm == pytest.approx(truth["tempo_bpm"], rel=1e-4)
        bars = [b for b in ds.bars if b.clip_id == clip.id]
        assert len(bars) == len(truth["bars"]) == clip.n_bars
        for bar, beats, signature in zip(bars, truth["bars"], truth["signatures"], strict=True):
            np.testing.assert_allclose(bar.beat_times, beats, atol=1e-6)
            assert bar.signature == bar.signature_raw == signature
            assert bar.start_frame == round(beats[0] * clip.fps)
            assert bar.end_frame == round(beats[4] * clip.fps)
    assert ds.bar("groove_100:3").node_id == "groove_100:3"
    assert sum(report.signature_counts.values()) == len(ds.bars)


def test_demo_kinematic_estimate_recovers_tempo_bars_and_signatures(
    demo_dir, demo_manifest, tmp_path
):
    manifest = copy.deepcopy(demo_manifest)
    for clip in manifest["clips"].values():
        for key in ("bars", "signatures", "tempo_bpm"):
            clip.pop(key)
    store = _store(tmp_path)
    import_dataset(demo_dir, "demo-est", store, manifest)
    ds = load_dataset(store, "demo-est")
    agree = total = starts_ok = 0
    for clip in ds.clips:
        truth = demo_manifest["clips"][clip.id]
        assert clip.beat_source == "kinematic"
        assert clip.tempo_bpm == pytest.approx(truth["tempo_bpm"], rel=0.005), clip.id
        assert clip.tempo_confidence > STEADY_MIN_CONFIDENCE, clip.id
        assert "no_steady_beat" not in clip.flags
        assert len(clip.sections) == 1
        true_starts = np.array([b[0] for b in truth["bars"]])
        signature_of = dict(zip(np.round(true_starts, 2), truth["signatures"], strict=True))
        for bar in (b for b in ds.bars if b.clip_id == clip.id):
            total += 1
            near = np.min(np.abs(true_starts - bar.start_s)) <= 1.5 / clip.fps
            starts_ok += near
            if near:
                key = true_starts[np.argmin(np.abs(true_starts - bar.start_s))].round(2)
                agree += bar.signature == signature_of[key]
    assert starts_ok / total >= 0.9  # bars start on the annotated downbeats
    assert agree / total >= 0.8  # and read the annotated rhythm signatures


def test_annotation_overrides_the_estimate(demo_dir, demo_manifest, tmp_path):
    manifest = copy.deepcopy(demo_manifest)
    clip = manifest["clips"]["step_100"]
    clip["signatures"] = ["11111111"] * len(clip["bars"])
    # An annotation on a clip the estimate would get right anyway: shift the grid by one beat.
    beat = 60.0 / clip["tempo_bpm"]
    clip["bars"] = [[t + beat for t in bar] for bar in clip["bars"][:-1]]
    clip["signatures"] = clip["signatures"][:-1]
    store = _store(tmp_path)
    import_dataset(demo_dir, "demo-ann", store, manifest)
    ds = load_dataset(store, "demo-ann")
    bars = [b for b in ds.bars if b.clip_id == "step_100"]
    assert len(bars) == 7
    assert all(b.signature == "11111111" for b in bars)
    assert bars[0].start_s == pytest.approx(beat)
    assert ds.clip("step_100").beat_source == "annotation"


def test_manifest_tempo_places_the_grid(demo_dir, demo_manifest, tmp_path):
    src = tmp_path / "src"
    for clip in ("groove_100", "pop_90"):
        _link(demo_dir / f"{clip}.bvh", src)
    manifest = {
        "clips": {
            "groove_100": {"tempo_bpm": 100.0, "style": "groove"},
            "pop_90": {"tempo_bpm": 90.0},
        }
    }
    store = _store(tmp_path)
    import_dataset(src, "demo-tempo", store, manifest)
    ds = load_dataset(store, "demo-tempo")
    for clip in ds.clips:
        assert clip.beat_source == "manifest_tempo"
        truth = demo_manifest["clips"][clip.id]
        assert clip.tempo_bpm == truth["tempo_bpm"]
        starts = np.array([b.start_s for b in ds.bars if b.clip_id == clip.id])
        true_starts = np.array([b[0] for b in truth["bars"]])
        hits = [np.min(np.abs(true_starts - t)) <= 1.5 / clip.fps for t in starts]
        assert np.mean(hits) >= 0.85, clip.id
    assert ds.clip("pop_90").style == "unknown"

    # Paths in a manifest cannot reach outside the import folder.
    manifest["clips"]["groove_100"]["audio"] = "../outside.ogg"
    (tmp_path / "outside.ogg").write_bytes(b"x")
    report = import_dataset(src, "demo-tempo", store, manifest)
    assert (
        report.failed[0]["code"] == "manifest_invalid"
        and report.failed[0]["file"] == "groove_100.bvh"
    )
    _link(demo_dir / "pop_120.bvh", tmp_path / "other")
    with pytest.raises(DanceGraphError) as err:
        import_dataset(src, "demo-tempo", store, {"files": "../other/*.bvh"})
    assert err.value.code == "dataset_empty"


def test_folder_with_bad_files_imports_the_good_ones(salsa_dir, tmp_path):
    src = tmp_path / "src"
    for take in LEADERS[:2]:
        _link(salsa_dir / f"{take}_scaled.bvh", src)
    text = (salsa_dir / "60_02_scaled.bvh").read_text()
    (src / "60_02_scaled.bvh").write_text(text[: len(text) // 2])  # truncated mid-frame
    (src / "junk_scaled.bvh").write_bytes(bytes(range(256)) * 40)  # binary junk
    head = text[: text.index("MOTION")]
    (src / "empty_scaled.bvh").write_text(head + "MOTION\nFrames: 0\nFrame Time: 0.008333\n")
    calls = []
    manifest = load_manifest(MANIFESTS / "cmu-salsa.yaml")
    store = _store(tmp_path)
    report = import_dataset(src, "salsa-bad", store, manifest, lambda d, t, f: calls.append((d, t)))
    assert [c.id for c in report.clips] == ["60_01", "60_03"]
    failed = {f["file"]: f["code"] for f in report.failed}
    assert failed == {
        "60_02_scaled.bvh": "bvh_truncated",
        "junk_scaled.bvh": "bvh_not_text",
        "empty_scaled.bvh": "bvh_no_frames",
    }
    assert all(f["error"] for f in report.failed)
    assert calls[-1] == (5, 5) and len(calls) == 5
    table = report.table()
    assert "FAILED 60_02_scaled.bvh: [bvh_truncated]" in table and "60_01" in table

    # load_dataset round trip: the stored motion is the file read at the manifest's 60 fps.
    ds = load_dataset(store, "salsa-bad")
    original = read_bvh(salsa_dir / "60_01_scaled.bvh", fps=60.0)
    motion = ds.motion("60_01")
    assert motion.fps == 60.0 and motion.skeleton == original.skeleton
    np.testing.assert_allclose(motion.root_positions, original.root_positions, atol=1e-5)
    np.testing.assert_allclose(motion.rotations, original.rotations, atol=1e-6)
    assert ds.motion("60_01") is motion  # cached
    bar = ds.bars[3]
    assert ds.bar_motion(bar.node_id).n_frames == bar.end_frame - bar.start_frame
    assert all(b.signature in COMMON_SIGNATURES for b in ds.bars)
    assert ds.beats("60_01").ndim == 1 and len(ds.kinematic_beats("60_01")) > 10
    assert ds.meta["fps_reason"] and "NSF EIA-0196217" in ds.meta["acknowledgement"]
    with pytest.raises(NotFoundError) as err:
        ds.motion("60_02")
    assert err.value.code == "unknown_clip"
    with pytest.raises(NotFoundError) as err:
        load_dataset(store, "nope")
    assert err.value.code == "unknown_dataset"

    # The same input gives the same version; the previous import's data folder is replaced.
    again = import_dataset(src, "salsa-bad", store, manifest)
    assert again.version == report.version
    data_dirs = {k.split("/")[2] for k in store.list("datasets/salsa-bad") if "/data-" in k}
    assert len(data_dirs) == 1
    assert list_datasets(store)[0]["clips"] == 2


def test_salsa_at_its_header_fps_gets_a_visible_warning(salsa_dir, tmp_path):
    src = tmp_path / "src"
    for take in LEADERS:
        _link(salsa_dir / f"{take}_scaled.bvh", src)
    manifest = load_manifest(MANIFESTS / "cmu-salsa.yaml")
    store = _store(tmp_path)
    right = import_dataset(src, "salsa60", store, manifest)
    assert right.warnings == []
    assert all("tempo_outside_prior" not in c.flags for c in right.clips)
    assert 160 < np.median([c.tempo_bpm for c in right.clips]) < 180

    manifest.pop("fps")
    wrong = import_dataset(src, "salsa120", store, manifest)
    assert all(c.fps == 120.0 for c in wrong.clips)
    assert all("tempo_outside_prior" in c.flags for c in wrong.clips)
    assert np.median([c.motion_tempo_bpm for c in wrong.clips]) > 300
    assert len(wrong.warnings) == 1 and "frame rate" in wrong.warnings[0]
    assert "At 60 fps" in wrong.warnings[0]
    assert "WARNING" in wrong.table()


def test_salsa_partners_are_compared_and_each_take_is_gridded_alone(salsa_dir, tmp_path):
    src = tmp_path / "src"
    for take in ("60_13", "61_13", "60_15", "61_15"):
        _link(salsa_dir / f"{take}_scaled.bvh", src)
    manifest = load_manifest(MANIFESTS / "cmu-salsa.yaml")
    store = _store(tmp_path)
    report = import_dataset(src, "salsa-pairs", store, manifest)
    rows = {tuple(p["pair"]): p for p in report.partners}
    assert len(rows) == 14  # every declared pair is listed ...
    assert rows[("60_01", "61_01")]["missing"] == ["60_01", "61_01"]  # ... absent ones as such
    for pair in (("60_13", "61_13"), ("60_15", "61_15")):
        row = rows[pair]
        assert row["agree"] and row["tempo_diff_pct"] < 1.0 and row["median_offset_ms"] < 40.0
        assert row["downbeat_agreement"] >= 0.8
    assert "partners 60_13/61_13: tempo" in report.table()
    ds = load_dataset(store, "salsa-pairs")
    assert ds.meta["partners"] == report.partners
    clip = ds.clip("60_13")
    assert clip.beat_source == "kinematic" and len(clip.sections) == 1
    assert 160.0 < clip.tempo_bpm < 170.0 and clip.tempo_confidence > 0.5
    # sub-frame, even beats within the section; bars are 4 beats and the next downbeat
    beats = ds.beats("60_13")
    assert np.ptp(np.diff(beats)) < 1e-9 and (np.diff(beats)[0] * clip.fps) % 1.0 > 1e-3
    for bar in (b for b in ds.bars if b.clip_id == "60_13"):
        assert np.max(tempo_mod.nearest_distance(bar.beat_times, beats)) < 1e-6
        assert bar.start_frame == round(bar.start_s * clip.fps)

    # The same take imported alone gets the same grid: nothing is shared between takes.
    alone = tmp_path / "alone"
    _link(salsa_dir / "60_13_scaled.bvh", alone)
    import_dataset(alone, "salsa-alone", store, manifest)
    np.testing.assert_array_equal(load_dataset(store, "salsa-alone").beats("60_13"), beats)


def test_old_format_store_fails_with_a_clear_message(demo_dir, tmp_path):
    store = _store(tmp_path)
    import_dataset(demo_dir, "demo", store)
    key = "datasets/demo/dataset.json"
    doc = json.loads(store.get_bytes(key))
    doc["format"] = 1
    store.put_bytes(key, json.dumps(doc).encode())
    with pytest.raises(DanceGraphError) as err:
        load_dataset(store, "demo")
    assert err.value.code == "dataset_format_old" and "import it again" in err.value.message


def test_modern_manifest_cuts_bars_from_its_tempo(modern_dir, tmp_path):
    src = tmp_path / "src"
    for take in ("05_01", "05_02", "05_03", "05_12"):
        _link(modern_dir / f"{take}.bvh", src)
    store = _store(tmp_path)
    report = import_dataset(src, "modern", store, load_manifest(MANIFESTS / "cmu-modern.yaml"))
    ds = load_dataset(store, "modern")
    assert ds.skeleton.n_joints == 31
    for clip in ds.clips:
        assert clip.beat_source == "manifest_tempo" and clip.tempo_bpm == 120.0
        assert "no_steady_beat" in clip.flags and clip.fps == 120.0
    walk = ds.clip("05_01")
    assert walk.style == "walk" and "walk" in walk.flags
    assert ds.clip("05_02").style == "modern"
    bars = [b for b in ds.bars if b.clip_id == "05_12"]
    assert len(bars) == int(ds.clip("05_12").duration_s // 2.0)
    assert all(b.end_s - b.start_s == pytest.approx(2.0) for b in bars)
    # CMU ASF units scaled to metres: a standing pelvis about a metre up
    assert 0.7 < float(np.median(ds.motion("05_02").root_positions[:, 1])) < 1.2
    assert report.warnings == []


def test_manifest_errors_name_the_field(demo_dir, demo_manifest, tmp_path):
    with pytest.raises(DanceGraphError) as err:
        parse_manifest({"fsp": 60})
    assert err.value.code == "manifest_invalid" and err.value.field == "fsp"
    with pytest.raises(DanceGraphError) as err:
        parse_manifest({"tempo_prior_bpm": [200, 100]})
    assert err.value.field == "tempo_prior_bpm"
    with pytest.raises(DanceGraphError) as err:
        parse_manifest({"style_tempo_bpm": [150]})
    assert err.value.field == "style_tempo_bpm"
    with pytest.raises(DanceGraphError) as err:
        parse_manifest({"clips": {"a": {"signatures": ["0000002"]}}})
    assert err.value.field.startswith("clips.a.signatures")
    for bad in ([["a", "b", "c"]], [["a", "a"]]):
        with pytest.raises(DanceGraphError) as err:
            parse_manifest({"partners": bad})
        assert err.value.code == "manifest_invalid" and err.value.field.startswith("partners")
    bad_yaml = tmp_path / "m.yaml"
    bad_yaml.write_text("fps: [60\n")
    with pytest.raises(DanceGraphError) as err:
        load_manifest(bad_yaml)
    assert err.value.code == "manifest_invalid"

    # A clip whose annotation is inconsistent fails alone; an excluded clip is listed.
    manifest = copy.deepcopy(demo_manifest)
    manifest["clips"]["pop_90"]["signatures"] = ["00000001"]
    manifest["clips"]["pop_120"]["exclude"] = True
    manifest["clips"]["pop_120"]["reason"] = "test"
    report = import_dataset(demo_dir, "demo-bad", _store(tmp_path), manifest)
    assert [f["file"] for f in report.failed] == ["pop_90.bvh"]
    assert report.failed[0]["code"] == "manifest_invalid"
    assert report.excluded == [{"file": "pop_120.bvh", "id": "pop_120", "reason": "test"}]
    assert len(report.clips) == 4

    with pytest.raises(NotFoundError) as err:
        import_dataset(tmp_path / "missing", "x", _store(tmp_path))
    assert err.value.code == "dataset_source_not_found"
    empty = tmp_path / "empty"
    (empty).mkdir()
    (empty / "junk.bvh").write_bytes(b"\x00\x01")
    with pytest.raises(DanceGraphError) as err:
        import_dataset(empty, "x", _store(tmp_path))
    assert err.value.code == "dataset_empty" and "bvh_not_text" in err.value.message
    with pytest.raises(DanceGraphError) as err:
        import_dataset(demo_dir, "../x", _store(tmp_path))
    assert err.value.code == "dataset_name_invalid"


def test_shared_manifests_are_valid():
    salsa = parse_manifest(load_manifest(MANIFESTS / "cmu-salsa.yaml"))
    assert salsa.fps == 60 and salsa.scale == 1.0 and salsa.style == "salsa"
    assert salsa.tempo_prior_bpm == [150, 220] and salsa.fps_reason
    assert salsa.style_tempo_bpm is None  # songs keep the tracked octave (docs/music.md)
    modern = parse_manifest(load_manifest(MANIFESTS / "cmu-modern.yaml"))
    assert modern.scale == pytest.approx(0.056444) and modern.fps == 120
    assert modern.steady_beat is False and modern.tempo_bpm
    assert modern.clips["05_01"].style == "walk"
    # the salsa partners: 14 trials, leader 60_NN with follower 61_NN
    assert len(salsa.partners) == 14
    assert all(a[:3] == "60_" and b == "61_" + a[3:] for a, b in salsa.partners)
    for m in (salsa, modern):
        assert "mocap.cs.cmu.edu" in m.acknowledgement and "NSF EIA-0196217" in m.acknowledgement
    # the files are plain YAML mappings
    assert isinstance(yaml.safe_load((MANIFESTS / "cmu-salsa.yaml").read_text()), dict)


def test_cli_import_and_list(demo_dir, tmp_path, capsys):
    store = str(tmp_path / "store")
    rc = cli_main(
        ["dataset", "import", str(demo_dir), "--name", "demo", "--store", store, "--json"]
    )
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_clips"] == 6 and out["n_bars"] == 48 and out["failed"] == []
    assert {c["beat_source"] for c in out["clips"]} == {"annotation"}
    rc = cli_main(["dataset", "import", str(demo_dir), "--name", "demo", "--store", store])
    assert rc == 0 and "groove_100" in capsys.readouterr().out
    assert cli_main(["dataset", "list", "--store", store]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [d["name"] for d in listed] == ["demo"] and listed[0]["bars"] == 48
    rc = cli_main(["dataset", "import", str(tmp_path / "nope"), "--name", "x", "--store", store])
    assert rc == 2 and "dataset_source_not_found" in capsys.readouterr().err


def test_cli_dataset_show_prints_the_grids(demo_dir, demo_manifest, tmp_path, capsys):
    store = str(tmp_path / "store")
    manifest = copy.deepcopy(demo_manifest)
    manifest["clips"]["pop_90"].pop("bars")  # one clip gridded from its motion
    manifest["clips"]["pop_90"].pop("signatures")
    manifest["clips"]["pop_90"].pop("tempo_bpm")
    (tmp_path / "m.json").write_text(json.dumps(manifest))
    args = ["dataset", "import", str(demo_dir), "--name", "demo", "--store", store]
    assert cli_main([*args, "--manifest", str(tmp_path / "m.json"), "--json"]) == 0
    capsys.readouterr()
    assert cli_main(["dataset", "show", "demo", "--store", store, "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    ds = load_dataset(FileStore(Path(store)), "demo")
    assert shown["name"] == "demo" and shown["version"] == ds.version
    assert [c["id"] for c in shown["clips"]] == [c.id for c in ds.clips]
    for c in shown["clips"]:
        clip = ds.clip(c["id"])
        assert c["fps"] == 60.0 and c["flags"] == clip.flags
        assert c["tempo_bpm"] == pytest.approx(clip.tempo_bpm, abs=1e-3)
        assert c["confidence"] == pytest.approx(clip.tempo_confidence, abs=1e-3)
        np.testing.assert_allclose(c["beats"], ds.beats(clip.id), atol=1e-4)
        bars = [b for b in ds.bars if b.clip_id == clip.id]
        np.testing.assert_allclose(c["bars"], [[b.start_s, b.end_s] for b in bars], atol=1e-4)
    pop = next(c for c in shown["clips"] if c["id"] == "pop_90")
    assert pop["beat_source"] == "kinematic" and pop["sections"][0]["tempo_bpm"] > 89.0
    assert cli_main(["dataset", "show", "demo", "--store", store]) == 0
    assert "pop_90" in capsys.readouterr().out
    assert cli_main(["dataset", "show", "nope", "--store", store]) == 2
    assert "unknown_dataset" in capsys.readouterr().err
