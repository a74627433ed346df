"""Naturalness: the default render adds no pulse, the importer's estimator finds the song's grid
in a rendered dance (and not another song's), and the two-sample test separates what differs.

Dance: the real salsa take 60_13 (60 fps; its partner 61_13 agrees with its grid) as a graph
of its own bars (its grid from the importer's estimator), rendered bar after bar by
``render.render_path`` on a generated song's exact beats (``music.generator``, 168 BPM).
"""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.graph.artifact import graph_from_arrays
from dancegraph.graph.build import BarSet, BuildParams, build_arrays
from dancegraph.metrics import naturalness as nat
from dancegraph.metrics.kinetic import smpl_positions
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.features import joint_speed
from dancegraph.motion.fk import forward_kinematics
from dancegraph.music.generator import generate_song
from dancegraph.render import beat_timing, render_path
from dancegraph.spec import Spec

FPS = 60.0
SALSA_PRIOR = 190.0  # the estimator's prior, one octave about it: salsa's 150-220 inside


def _song_bars(seed: int, tempo: float) -> np.ndarray:
    """``(B, 5)`` s: the generated song's exact bars (4 beats and the next downbeat)."""
    truth = generate_song(seed, tempo_bpm=tempo, meter=4).truth
    beats = np.asarray(truth["beats"])
    first = int(np.searchsorted(beats, truth["downbeats"][0] - 1e-6))
    n = (beats.size - first - 1) // 4
    return np.stack([beats[first + 4 * b : first + 4 * b + 5] for b in range(n)])


@pytest.fixture(scope="module")
def salsa_graph(salsa_dir):
    """A graph of one real take's bars on its importer grid, and the take."""
    take = read_bvh(salsa_dir / "60_13_scaled.bvh", fps=FPS)
    pos, world = forward_kinematics(take)
    grid = nat.recovered_grid(
        take.skeleton, pos, world, FPS, (0.0, take.n_frames / FPS), SALSA_PRIOR
    )
    bars = grid.bars
    frames = np.round(bars[:, [0, 4]] * FPS).astype(np.int64)
    row = (take, bars, np.arange(len(bars)), ["01010101"] * len(bars), frames)
    barset = BarSet.from_takes(take.skeleton, ["t0"], [row])
    arrays, ids, manifest = build_arrays(barset, BuildParams(blend_ratio=0, shuffle_ratio=0))
    g = graph_from_arrays(arrays, dict(manifest, name="salsa-one", version="test"))
    g.node_ids[:] = ids
    g._index = {n: i for i, n in enumerate(ids)}
    return g, take, len(bars)


def _render(salsa_graph, song_bars, **kw):
    g, _, n_bars = salsa_graph
    n = min(n_bars, len(song_bars))
    nodes = [f"t0:{b}" for b in range(n)]
    dance, report = render_path(g, nodes, song_bars[:n], FPS, foot_cleanup=False, **kw)
    if not kw.get("land_stops") and not kw.get("beat_accent"):
        # a steady take's bars on a steady song: the dancer's own pace throughout
        assert report["retime"]["speed_factor"] == pytest.approx([1.0, 1.0], abs=0.01)
    return dance, song_bars[:n]


def _depth(dance, bars) -> float:
    speed = joint_speed(forward_kinematics(dance)[0], FPS, 0.0)
    return nat.pulse_depth(nat.pulse_profile(speed, FPS, bars))


def test_the_default_render_adds_no_pulse(salsa_graph):
    """The default spec's render of real salsa on a generated song pulses no more than 1.5x the
    anchored-only render (the takes' own beats on the song's, nothing re-timed); the beat
    accent 0.4 (a stylization) makes it pulse far more, so the bound can fail."""
    song = _song_bars(3, 168.0)
    out = Spec().output
    default, bars = _render(
        salsa_graph, song, land_stops=out.stops_on_beats, beat_accent=out.beat_accent
    )
    anchored, _ = _render(salsa_graph, song, land_stops=False, beat_accent=0.0)
    accented, _ = _render(salsa_graph, song, land_stops=False, beat_accent=0.4)
    base = _depth(anchored, bars)
    assert 0.0 < base < 0.3
    assert _depth(default, bars) <= 1.5 * base
    assert _depth(accented, bars) > 2.0 * base


def test_the_recovered_grid_is_the_songs_and_not_another_songs(salsa_graph):
    """The importer's estimator, run on the rendered dance as a new take, finds the song's grid
    (tempo within 1 %, median offset <= 40 ms, downbeats >= 80 %); against another generated
    song's grid scaled to the same tempo (the chance row) the check fails."""
    song = _song_bars(3, 168.0)
    dance, bars = _render(salsa_graph, song, land_stops=False, beat_accent=0.0)
    pos, world = forward_kinematics(dance)
    span = (float(bars[0, 0]), float(bars[-1, 4]))
    grid = nat.recovered_grid(dance.skeleton, pos, world, FPS, span, 168.0)
    check = nat.grid_check(grid, bars)
    assert check["passed"], check
    other = nat.scaled_grid(_song_bars(6, 150.0), bars)
    chance = nat.grid_check(grid, other)
    assert chance["tempo_diff_pct"] <= 1.0  # same tempo: only the beats' places differ
    assert not chance["passed"], chance


def test_pulse_depth_of_a_known_pace():
    """A speed of ``1 − a·cos 2πφ`` on a steady grid folds to depth ``2ak / (1 + ak)``, k the
    mean of cos 2πφ over an eighth of a beat from the beat (bins start on the beat); a steady
    speed to 0."""
    bars = np.stack([0.5 + 0.4 * np.arange(4 * b, 4 * b + 5) for b in range(10)])
    t = np.arange(int(17 * FPS)) / FPS
    phase = (t - 0.5) / 0.4
    k = np.sin(np.pi / 4) / (np.pi / 4)
    for a in (0.2, 0.5):
        depth = nat.pulse_depth(nat.pulse_profile(1.0 - a * np.cos(2 * np.pi * phase), FPS, bars))
        assert depth == pytest.approx(2 * a * k / (1 + a * k), rel=0.01)
    assert nat.pulse_depth(nat.pulse_profile(np.ones_like(t), FPS, bars)) == pytest.approx(0.0)


def test_two_sample_test_tells_apart_what_differs_and_not_what_does_not(salsa_dir):
    """2-s windows of four real takes against four others: the balanced accuracy stays near
    chance (the library against itself); the same takes re-timed with the beat accent 0.4
    on a steady grid are told apart."""
    takes = []
    for name in ("60_01", "60_03", "60_05", "60_07", "60_09", "60_11", "60_13", "60_15"):
        take = read_bvh(salsa_dir / f"{name}_scaled.bvh", fps=FPS).slice(0, 1800)
        takes.append(take)

    def windows(m):
        pos, world = forward_kinematics(m)
        return nat.window_descriptors(smpl_positions(m.skeleton, pos, world), FPS)

    plain = [windows(t) for t in takes]
    assert plain[0].shape[1] == 37
    same = nat.two_sample_accuracy(plain[:4], plain[4:])
    bars = np.stack([0.3 + (60 / 168) * np.arange(4 * b, 4 * b + 5) for b in range(18)])
    accented = [
        windows(beat_timing(t, bars, 0, np.zeros(0), land_stops=False, accent=0.4)[0])
        for t in takes[:4]
    ]
    apart = nat.two_sample_accuracy(accented, plain[4:])
    assert same is not None and apart is not None
    assert same < 0.7
    assert apart > 0.8
    assert apart > same + 0.15
