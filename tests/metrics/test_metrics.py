"""Each metric on constructed cases with a known answer."""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.graph import choreography
from dancegraph.metrics import beats, diversity, kinetic, physical, smoothness, structure
from dancegraph.motion.features import kinematic_beats
from dancegraph.rhythm.motion import shiratori_beats
from dancegraph.spec import Spec, Stage

FPS = 60.0
BEAT_FRAMES = 30  # 120 BPM at 60 fps


def pulse(n_frames: int = 600, n_joints: int = 4) -> np.ndarray:
    """``(F, J, 3)`` joints swinging along x with speed ∝ |sin(π i / 30)| between frames i and
    i + 1: the displacement dips to zero once per beat, between frames 30·k and 30·k + 1."""
    i = np.arange(n_frames) - 0.5
    x = 0.3 * np.cos(np.pi * i / BEAT_FRAMES)
    pos = np.zeros((n_frames, n_joints, 3))
    pos[:, :, 0] = x[:, None] * np.linspace(0.5, 1.5, n_joints)[None, :]
    pos[:, :, 1] = 1.0 + 0.2 * np.arange(n_joints)[None, :]
    return pos


def test_beat_scores_on_beat_are_maximal_and_half_a_beat_off_is_low():
    pos = pulse()
    # the published codes index the displacement between frames i and i + 1 differently:
    # Bailando at frame i, FACT (a zero first row) at frame i + 1
    for variant, lag in (("bailando", 0), ("fact", 1)):
        on = (np.arange(1, 20) * BEAT_FRAMES + lag) / FPS
        off = on + 0.5 * BEAT_FRAMES / FPS
        mb = beats.motion_beats(pos, FPS, variant)
        assert np.allclose(np.diff(mb), BEAT_FRAMES / FPS)  # one minimum per beat
        assert beats.beat_align_score(on, mb, variant) == pytest.approx(1.0)
        assert beats.beat_align_score(off, mb, variant) < 1e-3
    kin = kinematic_beats(pos, FPS)
    music = (np.arange(1, 20) * BEAT_FRAMES) / FPS
    assert beats.beat_accuracy(music, kin) == 1.0
    assert beats.beat_accuracy(music + 0.25, kin) == 0.0


def _published_bas(keypoints: np.ndarray, music_frames: np.ndarray, variant: str) -> float:
    """The two published Beat Align Score procedures, step by step on frame indices at 60 fps
    (Bailando's utils/beat_align_score.py, FACT's tools/calculate_beat_scores.py), written
    independently of ``metrics.beats`` to check it."""
    from scipy.ndimage import gaussian_filter
    from scipy.signal import argrelextrema

    if variant == "bailando":
        step = np.sqrt(((keypoints[1:] - keypoints[:-1]) ** 2).sum(axis=2)).mean(axis=1)
        dance = argrelextrema(gaussian_filter(step, 5), np.less)[0]
        return float(np.mean([np.exp(-np.min((dance - m) ** 2) / 2 / 9) for m in music_frames]))
    velocity = np.zeros_like(keypoints)
    velocity[1:] = keypoints[1:] - keypoints[:-1]
    envelope = np.linalg.norm(velocity, axis=2).sum(axis=1)
    dance = argrelextrema(envelope, np.less, order=10)[0]
    return float(np.mean([np.exp(-np.min((music_frames - k) ** 2) / 2 / 9) for k in dance]))


def test_beat_align_scores_equal_the_published_procedures():
    rng = np.random.default_rng(1)
    for _ in range(40):
        n = int(rng.integers(200, 700))
        t = np.arange(n)[:, None, None]
        keypoints = np.cumsum(rng.normal(size=(n, 24, 3)) * 0.01, axis=0) + 0.1 * np.sin(
            2 * np.pi * t / rng.uniform(15, 40)
        ) * rng.normal(size=(1, 24, 3))
        music = np.sort(rng.choice(n, size=int(rng.integers(5, 40)), replace=False))
        for variant in ("bailando", "fact"):
            ours = beats.beat_align_score(
                music / FPS, beats.motion_beats(keypoints, FPS, variant), variant
            )
            assert ours == pytest.approx(_published_bas(keypoints, music, variant), abs=1e-9)


def test_beat_align_variants_average_over_different_sides():
    music = np.array([1.0, 2.0, 3.0, 4.0])
    dance = np.array([1.0])  # one motion beat, on a music beat
    # Bailando averages over music beats: 1 of 4 matched; FACT over motion beats: 1 of 1
    assert beats.beat_align_score(music, dance, "bailando") == pytest.approx(0.25)
    assert beats.beat_align_score(music, dance, "fact") == pytest.approx(1.0)
    assert beats.beat_align_score(music, [], "bailando") == 0.0
    with pytest.raises(ValueError):
        beats.beat_align_score(music, dance, "other")


def _demo_dance(recipe_index: int):
    """SMPL-like positions of one generated demo clip at 60 fps and its key-pose times (the
    accented slots of its bars' signatures: where the body holds still, by construction)."""
    from dancegraph.metrics.kinetic import smpl_positions
    from dancegraph.motion.demo import DEMO_CLIPS, make_clip
    from dancegraph.motion.fk import forward_kinematics
    from dancegraph.rhythm.music import rhythm_points
    from dancegraph.rhythm.signatures import COMMON_SIGNATURES

    motion, bars, sigs = make_clip(DEMO_CLIPS[recipe_index], np.random.default_rng(recipe_index))
    pos, world = forward_kinematics(motion)
    keys = rhythm_points(np.array(bars), np.array([COMMON_SIGNATURES.index(s) for s in sigs]))
    return smpl_positions(motion.skeleton, pos, world), motion.fps, np.array(bars), keys


@pytest.mark.parametrize("recipe_index", [0, 2, 4])
def test_shiratori_beats_find_the_demo_key_poses(recipe_index):
    smpl, fps, _, keys = _demo_dance(recipe_index)
    found = shiratori_beats(smpl, fps)
    inside = beats.within(keys, 0.2, len(smpl) / fps - 0.2)  # a stop needs a move either side
    assert beats.beat_accuracy(inside, found, 0.05) >= 0.9  # recall, within 3 frames
    assert beats.beat_accuracy(found, keys, 0.05) >= 0.95  # precision


def test_rhythm_points_are_the_active_slots_of_each_bar():
    from dancegraph.rhythm.music import rhythm_points
    from dancegraph.rhythm.signatures import COMMON_SIGNATURES

    bar_beats = np.array([[0.0, 0.5, 1.0, 1.5, 2.0], [2.0, 2.6, 3.2, 3.8, 4.4]])
    sigs = [COMMON_SIGNATURES.index("00010001"), COMMON_SIGNATURES.index("01000101")]
    # slots 0 and 4 (beats 1 and 3), then slots 0, 2 and 6 (beats 1, 2 and 4) 0.6 s apart
    assert rhythm_points(bar_beats, sigs) == pytest.approx([0.0, 1.0, 2.0, 2.6, 3.8])
    with pytest.raises(ValueError):
        rhythm_points(bar_beats, sigs[:1])


def test_phase_concentration_and_half_beat_shift():
    grid = np.arange(0.0, 20.0, 0.5)
    r, phase = beats.phase_concentration(grid, grid[:-1] + 0.125)  # a quarter beat late
    assert r == pytest.approx(1.0) and phase == pytest.approx(0.25)
    r, _ = beats.phase_concentration(grid, np.concatenate([grid, grid + 0.25])[:-2])
    assert r == pytest.approx(0.0, abs=0.03)  # on and off the beat alike: no concentration
    assert beats.phase_concentration(grid[:1], grid) == (0.0, 0.0)
    uneven = np.array([0.0, 0.4, 1.0, 1.6])
    assert beats.half_beat_shift([0.1, 0.5, 2.0], uneven) == pytest.approx([0.3, 0.8, 2.3])


def test_sync_scores_of_a_dance_on_its_key_poses_beat_every_chance_row():
    smpl, fps, bars, keys = _demo_dance(0)  # accents on the beats (and a half beat or two)

    grid = beats.SyncGrid(
        beats=np.unique(bars.ravel()),
        percussive_beats=np.unique(bars.ravel()),
        rhythm_points=keys,
        span=(float(bars[0, 0]), float(bars[-1, 4])),
    )
    dance = beats.DanceBeats.of(smpl, fps, kinematic_beats(smpl, fps))
    span = grid.span
    own = beats.sync_scores(dance, grid, span)
    half = beats.sync_scores(dance, grid.half_beat(), span)
    assert own["cm_accuracy"] >= 0.9 and own["cm_accuracy"] >= 1.5 * half["cm_accuracy"]
    assert own["bas_bailando"] >= half["bas_bailando"] + 0.15
    assert own["phase_r"] >= 0.5
    # another song at another tempo: the dance's beats scatter over its beat phase
    other = np.arange(0.0, span[1], 60.0 / 137.0)
    far = beats.SyncGrid(other, other, other, (0.0, span[1]))
    assert beats.sync_scores(dance, far, span)["phase_r"] < own["phase_r"] - 0.3
    no_points = beats.SyncGrid(grid.beats, grid.percussive_beats, np.zeros(0), span)
    assert beats.sync_scores(dance, no_points, span)["cm_accuracy"] is None
    # librosa's beats at another tempo: BAS (Bailando) no longer sees the sync, the BAS on the
    # tracker's beats still does, beside its own half-beat row
    elsewhere = beats.SyncGrid(grid.beats, other, grid.rhythm_points, span)
    mine = beats.sync_scores(dance, elsewhere, span)
    mine_half = beats.sync_scores(dance, elsewhere.half_beat(), span)
    assert mine["bas_beats"] == pytest.approx(own["bas_beats"])
    assert mine["bas_beats"] >= mine_half["bas_beats"] + 0.15
    assert mine["bas_bailando"] < own["bas_bailando"] - 0.15


def test_librosa_beats_find_a_click_track():
    sr = 22050
    y = np.zeros(sr * 8, dtype=np.float32)
    burst = np.random.default_rng(0).normal(size=2000) * np.exp(-np.arange(2000) / 300)
    for t in np.arange(0.5, 7.5, 0.5):  # 120 BPM noise bursts: percussive
        k = int(t * sr)
        y[k : k + 2000] = 0.5 * burst
    found = beats.librosa_beats(y, sr)
    assert len(found) >= 10
    assert np.median(np.diff(found)) == pytest.approx(0.5, abs=0.03)


def test_seam_with_a_pop_is_flagged_and_a_smooth_one_is_not():
    library = [pulse(900), pulse(700)]
    ref = smoothness.Reference.from_takes(library, FPS)
    dance = pulse(600)
    dance[300:] += np.array([0.15, 0.0, 0.0])  # a 15 cm pop at frame 300
    rep = smoothness.seam_report(dance, FPS, [150, 300], ref)
    smooth, popped = rep["seams"]
    assert popped["frame"] == 300 and popped["flagged"]
    assert popped["speed_percentile"] == 100.0
    assert not smooth["flagged"] and smooth["speed_percentile"] < 99.0
    assert rep["flagged"] == 1 and rep["flagged_share"] == 0.5


def test_the_chance_row_scores_every_library_frame_as_a_seam():
    rng = np.random.default_rng(0)
    library = [pulse(900) + rng.normal(0, 1e-3, (900, 4, 3)), pulse(700)]
    ref = smoothness.Reference.from_takes(library, FPS)
    scores = []
    for take in library:
        rows = smoothness.seam_report(take, FPS, np.arange(2, len(take)), ref)["seams"]
        scores += [max(r["speed_percentile"], r["acc_percentile"]) for r in rows]
    assert ref.chance["frames"] == len(scores)
    assert ref.chance["median_percentile"] == pytest.approx(np.median(scores))
    flagged = np.mean(np.array(scores) > smoothness.FLAG_PERCENTILE)
    assert ref.chance["flagged_share"] == pytest.approx(flagged) and 0.0 < flagged < 0.05


def test_foot_skating_counts_only_the_chosen_frames(salsa_dir):
    from dancegraph.motion.bvh import read_bvh
    from dancegraph.motion.fk import forward_kinematics

    take = read_bvh(salsa_dir / "60_03_scaled.bvh", fps=60).slice(0, 900)
    pos, world = forward_kinematics(take)
    whole = physical.foot_skating(pos, world, take.skeleton, FPS)
    same = physical.foot_skating(pos, world, take.skeleton, FPS, np.ones(900, dtype=bool))
    assert same == whole and whole["steps"] > 300
    half = np.zeros(900, dtype=bool)
    half[:450] = True
    first = physical.foot_skating(pos, world, take.skeleton, FPS, half)
    second = physical.foot_skating(pos, world, take.skeleton, FPS, ~half)
    assert first["steps"] + second["steps"] <= whole["steps"] and first["steps"] > 50
    pooled = first["mean_speed_m_s"] * first["steps"] + second["mean_speed_m_s"] * second["steps"]
    assert pooled / (first["steps"] + second["steps"]) == pytest.approx(
        whole["mean_speed_m_s"], rel=0.1
    )


def test_structure_counts_satisfied_and_violated_pairs():
    tags = [
        {"label": "A", "occurrence": o, "index": i, "meter_id": m}
        for o in (0, 1)
        for i, m in enumerate((0, 1, 0))
    ]
    mirror_of = np.array([1, 0, 3, 2, 5, 4, 7, 6])
    # repeat pairs (0,3) (1,4) (2,5); mirror pairs (0,2) (3,5) (same meter id in an occurrence)
    nodes = np.array([0, 2, 1, 0, 6, 1])
    st = structure.structure_satisfaction(nodes, tags, mirror_of)
    assert st["repeat"] == {"pairs": 3, "satisfied": 2, "share": pytest.approx(2 / 3)}
    assert st["mirror"] == {"pairs": 2, "satisfied": 2, "share": 1.0}
    assert [v["bars"] for v in st["violated"]] == [[1, 4]]


def test_stage_violation_is_counted():
    stage = Stage(x=[-1.0, 1.0], z=[-1.0, 1.0])
    xz = np.zeros((10, 2))
    xz[7:, 0] = [1.5, 2.0, 0.5]  # two of ten frames outside, 1 m at most
    rep = physical.stage_report(xz, stage)
    assert rep["inside_share"] == pytest.approx(0.8)
    assert rep["max_outside_m"] == pytest.approx(1.0)
    assert physical.stage_report(xz, None) is None


def test_chi_square_known_value():
    a = np.array([0.5, 0.5, 0.0])
    b = np.array([0.25, 0.25, 0.5])
    # ½ [2 · 0.25² / 0.75 + 0.5² / 0.5] = ½ (1/6 + 1/2)
    assert choreography.chi_square(a, b) == pytest.approx(1 / 3)


def test_signature_distance_and_controls_on_the_demo_graph(demo_graph):
    g = demo_graph
    motif = np.asarray(g.motif)
    k = int(motif.max()) + 1
    node = int(np.nonzero(motif == motif[0])[0][0])
    nodes = np.full(6, node)
    sig = structure.signature_distance(g, nodes)
    target = np.asarray(sig["target"])
    one_hot = np.eye(k)[motif[0]]
    assert sig["chi2"] == pytest.approx(choreography.chi_square(one_hot, target))
    assert sig["histogram"] == one_hot.tolist()

    bars = np.stack([np.arange(6) * 2.0, np.arange(6) * 2.0 + 2.0], axis=1)
    other = int(np.nonzero(np.asarray(g.node_clip) != g.node_clip[node])[0][0])
    spec = Spec.model_validate(
        {
            "include": [{"node": g.node_ids[node], "bars": [0, 2]}],
            "exclude": [{"node": g.node_ids[other]}],
            "stage": {"x": [-1, 1], "z": [-1, 1]},
            "waypoints": [{"second": 5.0, "position": [0.0, 0.0], "tolerance": 0.5}],
            "motifs": [{"bar": 1, "motif": int(motif[node])}],
            "signature": {"target": "dataset"},
        }
    )
    xz = np.zeros((12 * 60, 2))
    xz[-10:, 0] = 3.0  # leaves the stage at the end
    ctl = structure.control_satisfaction(g, spec, bars, nodes, xz, 60.0)
    ok = {it["control"]: it["satisfied"] for it in ctl["items"]}
    assert ok == {
        "include[0]": True,
        "exclude[0]": True,
        "waypoints[0]": True,
        "stage": False,
        "motifs[0]": True,
        "signature": None,  # a soft target: measured, not passed or failed
    }
    assert ctl["items"][-1]["chi2"] == pytest.approx(sig["chi2"])
    nodes2 = nodes.copy()
    nodes2[1] = other  # breaks the include and uses the excluded node
    ok2 = {
        it["control"]: it["satisfied"]
        for it in structure.control_satisfaction(g, spec, bars, nodes2, xz, 60.0)["items"]
    }
    assert not ok2["include[0]"] and not ok2["exclude[0]"]
    assert ctl["count"] == 5 and ctl["share"] == pytest.approx(0.8)


def test_kinetic_features_of_constant_motion():
    t = np.arange(120) / FPS
    pos = np.zeros((120, 2, 3))
    pos[:, 0, 0] = 2.0 * t  # 2 m/s horizontally
    pos[:, 1, 1] = -0.5 * t  # 0.5 m/s vertically
    f = kinetic.kinetic_features(pos, FPS).reshape(2, 3)
    assert f[0] == pytest.approx([4.0, 0.0, 0.0], abs=1e-9)
    assert f[1] == pytest.approx([0.0, 0.25, 0.0], abs=1e-9)


def test_fid_of_a_set_with_itself_is_zero_and_grows_with_a_perturbation():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(200, 6))
    assert kinetic.frechet_distance(a, a) == pytest.approx(0.0, abs=1e-6)
    d = [kinetic.frechet_distance(a, a + s) for s in (0.1, 0.5, 1.0)]
    assert 0 < d[0] < d[1] < d[2]
    assert d[2] == pytest.approx(6.0, rel=1e-6)  # a mean shift of 1 in 6 dims
    scaled = kinetic.frechet_distance(a, a * 2.0)
    assert scaled > 1.0


def test_smpl_positions_of_the_demo_skeleton(demo_bars):
    from dancegraph.motion.fk import fk_arrays

    sk = demo_bars.skeleton
    rows = slice(demo_bars.ptr[0], demo_bars.ptr[1])
    pos, world = fk_arrays(sk, demo_bars.root[rows], demo_bars.rotations[rows].astype(float))
    smpl = kinetic.smpl_positions(sk, pos, world)
    assert smpl.shape == (pos.shape[0], 24, 3)
    assert np.allclose(smpl[:, 0], pos[:, sk.index("hips")])
    assert np.all(np.isfinite(smpl))
    # left and right joints are distinct points
    left = [i for i, n in enumerate(kinetic.SMPL_JOINTS) if n.startswith("left_")]
    assert np.all(np.linalg.norm(smpl[:, left] - smpl[:, [i + 1 for i in left]], axis=-1) > 0.01)


def test_diversity():
    assert diversity.feature_diversity(np.array([[0.0, 0.0], [3.0, 4.0]])) == 5.0
    assert diversity.feature_diversity(np.zeros((1, 3))) is None
    assert diversity.path_diversity([np.array([1, 2, 3, 4]), np.array([1, 2, 5, 6])]) == 0.5
    assert diversity.path_diversity([np.array([1, 2])]) is None


def test_sync_table_puts_every_metric_beside_its_chance_rows():
    from dancegraph.eval.harness import Dance, sync_metrics, sync_table

    smpl, fps, bars, keys = _demo_dance(0)
    beat_grid = np.unique(bars.ravel())
    grid = beats.SyncGrid(beat_grid, beat_grid, keys, (float(bars[0, 0]), float(bars[-1, 4])))
    other = np.arange(0.0, grid.span[1], 60.0 / 137.0)
    far = beats.SyncGrid(other, other, other, (0.0, grid.span[1]))
    dance = beats.DanceBeats.of(smpl, fps, kinematic_beats(smpl, fps))
    m = sync_metrics(dance, grid.span, grid, far)
    assert m["phase_r_half"] is None and m["cm_accuracy_other"] is not None
    lone = sync_metrics(dance, grid.span, grid, None)
    assert lone["bas_bailando_other"] is None and lone["bas_bailando"] == m["bas_bailando"]
    blank = np.zeros((0, 72))
    per_song = [
        {"ours": [Dance(m, blank, blank[0:0], None, {}), Dance(lone, blank, blank, None, {})]}
    ]
    cell = sync_table(per_song, ["ours"])["ours"]["bas_bailando"]
    assert cell["value"] == pytest.approx(m["bas_bailando"])
    assert cell["gain_half_beat"] == pytest.approx(m["bas_bailando"] - m["bas_bailando_half"])
    # the other-song row only from the dance that has one
    assert cell["other_song"] == pytest.approx(m["bas_bailando_other"])
    assert cell["ratio_other_song"] == pytest.approx(m["bas_bailando"] / m["bas_bailando_other"])
    assert sync_table(per_song, ["ours"])["ours"]["phase_r"]["half_beat"] is None
