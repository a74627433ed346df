"""Rendering search results: files parse back, bars sit on the music, the stage bound holds.

Graph: the demo bars built in memory (``demo_graph`` fixture); song: generated and analysed.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dancegraph.errors import DanceGraphError, SpecError
from dancegraph.graph.search import SearchResult, search
from dancegraph.motion import quat
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fbx import fbx_available
from dancegraph.music.analysis import analyze
from dancegraph.music.generator import generate_song
from dancegraph.render import bar_frames, render
from dancegraph.spec import Spec, parse_spec

FPS = 30


@pytest.fixture(scope="module")
def analysis():
    song = generate_song(
        5, meter=4, tempo_bpm=116.0, form=["A", "B", "A"], section_bars={"A": 4, "B": 4}
    )
    return analyze(song.y, song.sr)


def _spec(**kw) -> Spec:
    data = {"dataset": "demo", "alternatives": 2, "output": {"formats": ["bvh"], "fps": FPS}}
    data.update(kw)
    return Spec.model_validate(data)


def test_bar_frames_tile_the_song():
    bars = np.array([[0.5, 2.5], [2.5, 4.49], [4.6, 6.61]])
    frames = bar_frames(bars, 30)
    assert frames.tolist() == [[15, 75], [75, 138], [138, 198]]
    assert bar_frames(np.array([[0.0, 0.01]]), 30).tolist() == [[0, 1]]


@pytest.fixture(scope="module")
def rendered(demo_graph, analysis, tmp_path_factory):
    spec = _spec()
    found = search(demo_graph, analysis, spec)
    out = tmp_path_factory.mktemp("render")
    result = render(demo_graph, analysis, found, spec, out)
    return out, result, found.to_dict(), spec


def test_rendered_files_parse_and_follow_the_music_bars(demo_graph, analysis, rendered):
    out, result, found, spec = rendered
    assert sorted(result["files"]) == ["alternatives/0.bvh", "alternatives/1.bvh", "timeline.json"]
    timeline = json.loads((out / "timeline.json").read_text())
    n_frames = round(analysis.duration_s * FPS)
    frames = bar_frames(analysis.bars, FPS)
    for k, alt in enumerate(found["alternatives"]):
        motion = read_bvh(out / f"alternatives/{k}.bvh")
        assert motion.skeleton == demo_graph.skeleton
        assert motion.fps == pytest.approx(FPS, rel=1e-4)
        assert motion.n_frames == n_frames  # frame 0 is t = 0 of the song, to its end
        entry = timeline["alternatives"][k]
        assert entry["frames"] == n_frames and entry["files"]["bvh"] == f"alternatives/{k}.bvh"
        # every bar lasts as long as its music bar (to one frame)
        for b, bar in enumerate(timeline["bars"]):
            assert [bar["start_frame"], bar["end_frame"]] == frames[b].tolist()
            assert (
                abs((bar["end_frame"] - bar["start_frame"]) / FPS - (bar["end_s"] - bar["start_s"]))
                <= 1.5 / FPS
            )
            assert entry["bars"][b]["node"] == alt["nodes"][b]
        # the middle of each bar is the node's own motion, time-warped onto the bar
        _check_bars_hold_their_nodes(demo_graph, motion, alt["nodes"], frames)
        # seams: where a node hands over to another, within a beat of its bar line
        assert entry["seams"] == sorted(entry["seams"]) and entry["seams"]
        assert len(entry["seams"]) == len(entry["seam_bars"]) == len(entry["cut_beats"])
        for s, b, off in zip(entry["seams"], entry["seam_bars"], entry["cut_beats"], strict=True):
            beat = (analysis.bar_beats[b, 1] - analysis.bar_beats[b, 0]) * FPS
            assert abs(off) <= 1.0 + 1e-6 and abs(s - frames[b, 0]) <= beat + 1


def _check_bars_hold_their_nodes(graph, motion, nodes, frames):
    upper = [
        motion.skeleton.index(n) for n in ("spine", "chest", "left_elbow", "right_elbow", "head")
    ]
    for b, node_id in enumerate(nodes):
        src = graph.node_motion(graph.node_index(node_id))
        s, e = frames[b]
        u = 0.5
        got = motion.rotations[s + int(u * (e - s)), upper]
        want = src.rotations[int(round(u * src.n_frames)), upper]
        angle = np.linalg.norm(quat.to_rotvec(quat.multiply(quat.conjugate(want), got)), axis=-1)
        assert angle.max() < 0.25, (
            f"bar {b} ({node_id}): upper body differs by {angle.max():.2f} rad"
        )


def test_timeline_carries_provenance(demo_graph, analysis, rendered):
    out, result, found, spec = rendered
    timeline = json.loads((out / "timeline.json").read_text())
    assert timeline["fps"] == FPS and len(timeline["bars"]) == analysis.n_bars
    assert [p["label"] for p in timeline["phrases"]] == [p["label"] for p in analysis.phrases]
    prov = timeline["provenance"]
    assert prov["graph"]["version"] == demo_graph.version and prov["graph"]["params"]
    assert prov["models"]["style_embedding"] == demo_graph.manifest["embedding"]["version"]
    assert prov["models"]["beat_tracker"] == analysis.method
    assert Spec.model_validate(prov["spec"]) == spec
    for k, alt in enumerate(found["alternatives"]):
        entry = timeline["alternatives"][k]
        assert entry["cost"] == pytest.approx(alt["cost"])
        for bar in entry["bars"]:
            i = demo_graph.node_index(bar["node"])
            src = bar["source"]
            assert src["take"] == demo_graph.clips[int(demo_graph.node_clip[i])]
            assert src["bar"] == int(demo_graph.node_bar[i])
            assert src["frames"] is not None and src["frames"][1] > src["frames"][0]
            assert (src["augmentation"] is None) == ("~" not in bar["node"])
            assert set(bar["cost"]) >= {"style", "rhythm", "transition"}


def test_stage_bound_holds_on_rendered_root(demo_graph, analysis, rendered, tmp_path):
    """A small stage away from the origin: the file must dance inside it, where the search planned."""
    out, _, _, _ = rendered
    free = read_bvh(out / "alternatives/0.bvh").root_positions[:, [0, 2]]
    reach = np.abs(free - free[0]).max()
    x0, z0, size = 2.0, -3.0, max(0.6, 3 * reach)
    stage = {"x": [x0, x0 + size], "z": [z0, z0 + size]}
    outside = (
        (free[:, 0] < x0) | (free[:, 0] > x0 + size) | (free[:, 1] < z0) | (free[:, 1] > z0 + size)
    )
    assert outside.all(), "without the stage the dance is elsewhere: the test would mean nothing"
    spec = _spec(alternatives=1, stage=stage)
    found = search(demo_graph, analysis, spec)
    render(demo_graph, analysis, found, spec, tmp_path)
    root = read_bvh(tmp_path / "alternatives/0.bvh").root_positions[:, [0, 2]]
    tol = 1e-3
    assert x0 - tol <= root[:, 0].min() and root[:, 0].max() <= x0 + size + tol
    assert z0 - tol <= root[:, 1].min() and root[:, 1].max() <= z0 + size + tol
    timeline = json.loads((tmp_path / "timeline.json").read_text())
    assert timeline["alternatives"][0]["stage"]["outside_m"] == 0.0


@pytest.mark.skipif(not fbx_available(), reason="Blender's Python not installed")
def test_fbx_per_alternative(demo_graph, analysis, tmp_path):
    from tests.motion.test_fbx import read_fbx

    spec = _spec(alternatives=1, output={"formats": ["bvh", "fbx"], "fps": FPS})
    found = search(demo_graph, analysis, spec)
    result = render(demo_graph, analysis, found, spec, tmp_path)
    assert "alternatives/0.fbx" in result["files"]
    fbx = read_fbx(tmp_path / "alternatives/0.fbx", [0])
    assert fbx["fps"] == FPS
    assert round(fbx["time_end"] * FPS) + 1 == round(analysis.duration_s * FPS)
    assert sorted(fbx["joints"]) == sorted(demo_graph.skeleton.names)


def test_bad_paths_are_clear_errors(demo_graph, analysis, rendered, tmp_path: Path):
    _, _, found, spec = rendered
    alt = found["alternatives"][0]
    short = SearchResult.from_dict({"alternatives": [dict(alt, nodes=alt["nodes"][:-1])]})
    with pytest.raises(DanceGraphError) as err:
        render(demo_graph, analysis, short, spec, tmp_path)
    assert err.value.code == "render_mismatch"
    bogus = SearchResult.from_dict(
        {"alternatives": [dict(alt, nodes=["nope:1"] + alt["nodes"][1:])]}
    )
    with pytest.raises(DanceGraphError) as err:
        render(demo_graph, analysis, bogus, spec, tmp_path)
    assert err.value.code == "unknown_node" and err.value.field == "nodes[0]"
    with pytest.raises(DanceGraphError) as err:
        render(demo_graph, analysis, SearchResult([], {}), spec, tmp_path)
    assert err.value.code == "render_empty"


def test_beat_accent_reaches_the_renderer(demo_graph, analysis, tmp_path, monkeypatch):
    """``output.beat_accent`` and ``output.stops_on_beats`` reach the re-timing of every
    alternative (default 0 and off: the dance keeps its takes' pulse; the steps themselves:
    tests/graph/test_anchors.py), the timeline reports the accent asked, what the dance had,
    what was added and the pulse depth without and with it, and the spec refuses an accent
    that would stop the dance (0.8 at most)."""
    import dancegraph.render as render_module

    seen = []
    real = render_module.beat_timing

    def spy(*args, **kwargs):
        seen.append((kwargs["land_stops"], kwargs["accent"]))
        return real(*args, **kwargs)

    monkeypatch.setattr(render_module, "beat_timing", spy)
    spec = _spec(alternatives=2, output={"formats": ["bvh"], "fps": FPS, "beat_accent": 0.25})
    render(demo_graph, analysis, search(demo_graph, analysis, spec), spec, tmp_path)
    assert seen == [(False, 0.25), (False, 0.25)]
    for alt in json.loads((tmp_path / "timeline.json").read_text())["alternatives"]:
        retime = alt["retime"]
        assert retime["accent"] == 0.25 and retime["accent_had"] is not None
        assert retime["accent_added"] == pytest.approx(max(0.0, 0.25 - retime["accent_had"]))
        assert set(retime["pulse_depth"]) == {"without", "with"}
    assert Spec().output.beat_accent == 0.0 and Spec().output.stops_on_beats is False
    with pytest.raises(SpecError) as err:
        parse_spec({"dataset": "demo", "output": {"beat_accent": 0.9}})
    assert "beat_accent" in str(err.value.to_dict())


def test_stops_on_beats_switch_reaches_the_files(demo_graph, analysis, rendered, tmp_path):
    """``output.stops_on_beats`` (default off) re-times the written dance when asked: same
    frames and seams' bars as the default's files, other poses; the default's timeline reports
    no re-timing (no accent, speed factor 1)."""
    out, _, _, _ = rendered
    spec = _spec(output={"formats": ["bvh"], "fps": FPS, "stops_on_beats": True})
    found = search(demo_graph, analysis, spec)
    render(demo_graph, analysis, found, spec, tmp_path)
    on, off = read_bvh(out / "alternatives/0.bvh"), read_bvh(tmp_path / "alternatives/0.bvh")
    assert on.n_frames == off.n_frames
    assert not np.allclose(on.rotations, off.rotations, atol=1e-4)
    timelines = [json.loads((d / "timeline.json").read_text()) for d in (out, tmp_path)]
    bars = [t["alternatives"][0]["seam_bars"] for t in timelines]
    assert bars[0] == bars[1]
    default = timelines[0]["alternatives"][0]["retime"]
    assert default["accent_added"] == 0.0 and default["pulse_depth"] is None
    assert default["retime_speed_factor"] == [1.0, 1.0]
    assert 0.0 < default["speed_factor"][0] <= default["speed_factor"][1]
