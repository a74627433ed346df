"""Beat grids from a take's motion, partner agreement, bars and signature labels
(dancegraph.motion.tempo)."""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.motion import tempo
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.contacts import point_contacts, step_onsets
from dancegraph.motion.dataset import STEP_BODY_JOINTS, STEP_FOOT_JOINTS
from dancegraph.motion.features import MAIN_JOINTS, kinematic_beats
from dancegraph.motion.fk import canonical_positions, forward_kinematics
from dancegraph.rhythm import signatures as sig

FPS = 60.0


def _dance_signals(beats: np.ndarray, n_frames: int, seed: int = 0) -> np.ndarray:
    """``(F, 4)`` step evidence of a dance on ``beats`` (s), the first a downbeat.

    The body moves between beats and pauses on them, a big step every two beats and a small
    one between (a two-beat step cycle), the feet quietest around the downbeat; the kinematic
    beats (pauses) fall on every downbeat and on the third beat of every other bar.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / FPS
    move = np.zeros(n_frames)
    for i in range(len(beats) - 1):
        u = (t - beats[i]) / (beats[i + 1] - beats[i])
        inside = (u >= 0) & (u < 1)
        move[inside] += (1.0 if i % 2 == 0 else 0.4) * np.sin(np.pi * u[inside]) ** 2
    pauses = [b for i, b in enumerate(beats) if i % 4 == 0 or i % 8 == 2]
    bar_phase = np.interp(t, beats, np.arange(len(beats)) / 4.0)
    feet = move**2 * (1.0 - 0.5 * np.cos(2 * np.pi * bar_phase))  # quietest at the downbeat
    cols = [move, feet, 0.5 * move, tempo.event_envelope(np.array(pauses), n_frames, FPS)]
    x = np.stack(cols, axis=1) + 0.05 * rng.standard_normal((n_frames, 4))
    return (x - x.mean(axis=0)) / x.std(axis=0)


def _beats(bpm: float, start: float, end: float) -> np.ndarray:
    return np.arange(start, end, 60.0 / bpm)


@pytest.mark.parametrize(("bpm", "prior"), [(96.0, None), (128.0, None), (163.37, (150, 220))])
def test_grid_recovers_tempo_beats_and_downbeats_at_sub_frame_precision(bpm, prior):
    truth = _beats(bpm, 0.4137, 40.0)
    params = tempo.GridParams(prior_bpm=prior) if prior else None
    grid = tempo.estimate_grid(_dance_signals(truth, int(40 * FPS)), FPS, params)
    assert grid.tempo_bpm == pytest.approx(bpm, rel=2e-4)
    assert grid.confidence > 0.8 and grid.flags == []
    # every true beat has a grid beat within 3 ms (a frame is 16.7 ms) ...
    assert np.max(tempo.nearest_distance(truth[1:-1], grid.beats)) < 0.003
    # ... and the intervals are not whole frames
    assert (
        np.ptp(np.diff(grid.beats) * FPS % 1.0) < 1e-6 and np.diff(grid.beats)[0] * FPS % 1 > 0.01
    )
    bars = grid.bars
    assert np.max(tempo.nearest_distance(bars[:, 0], truth[::4])) < 0.003
    np.testing.assert_allclose(bars[:, 4] - bars[:, 0], 240.0 / grid.tempo_bpm)


def test_a_tempo_change_gives_sections_each_with_its_tempo():
    first = _beats(150.0, 0.2, 20.0)
    second = first[-1] + 60.0 / 175.0 * np.arange(1, 200)
    truth = np.concatenate([first, second[second < 40.0]])
    grid = tempo.estimate_grid(
        _dance_signals(truth, int(40 * FPS)), FPS, tempo.GridParams(prior_bpm=(130.0, 200.0))
    )
    assert [round(s.tempo_bpm) for s in grid.sections] == [150, 175]
    assert grid.sections[0].end_s == pytest.approx(20.0, abs=2.0)
    assert "tempo_changes" in grid.flags
    inner = truth[(truth > 1.0) & (truth < 39.0)]
    assert np.median(tempo.nearest_distance(inner, grid.beats)) < 0.005
    # one section when the manifest fixes the tempo
    fixed = tempo.estimate_grid(_dance_signals(truth, int(40 * FPS)), FPS, tempo_bpm=150.0)
    assert len(fixed.sections) == 1 and fixed.tempo_bpm == 150.0


def test_known_tempo_places_phase_and_downbeat():
    truth = _beats(110.0, 1.234, 30.0)
    grid = tempo.estimate_grid(_dance_signals(truth, int(30 * FPS)), FPS, tempo_bpm=110.0)
    assert np.max(tempo.nearest_distance(truth[1:-1], grid.beats)) < 0.003
    assert np.max(tempo.nearest_distance(grid.bars[:, 0], truth[::4])) < 0.003
    assert grid.sections[0].downbeat_clarity > 0.1


def test_noise_has_no_steady_beat():
    rng = np.random.default_rng(3)
    noise = np.cumsum(rng.standard_normal((2400, 4)), axis=0)  # random walks, no period
    grid = tempo.estimate_grid(noise - noise.mean(axis=0), FPS)
    assert "no_steady_beat" in grid.flags
    assert grid.confidence < tempo.STEADY_MIN_CONFIDENCE


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="too short"):
        tempo.estimate_grid(np.zeros((60, 4)), FPS)
    with pytest.raises(ValueError, match="prior"):
        tempo.GridParams(prior_bpm=(200.0, 100.0))
    with pytest.raises(ValueError, match="positive"):
        tempo.estimate_grid(np.zeros((600, 4)), FPS, tempo_bpm=0.0)


def test_partner_agreement():
    beats = _beats(165.0, 0.3, 30.0)
    down = beats[::4]
    same = tempo.partner_agreement(beats, down, 165.0, beats + 0.02, down + 0.02, 165.0)
    assert same["tempo_diff_pct"] == 0.0
    assert same["median_offset_ms"] == pytest.approx(20.0, abs=0.1)
    assert same["downbeat_agreement"] == 1.0 and same["downbeat_shift_beats"] == 0
    half_bar = tempo.partner_agreement(beats, down, 165.0, beats, beats[2::4], 166.0)
    assert half_bar["downbeat_agreement"] == 0.0 and half_bar["downbeat_shift_beats"] == 2
    assert half_bar["tempo_diff_pct"] == pytest.approx(100 / 165.5, rel=1e-6)
    apart = tempo.partner_agreement(beats, down, 165.0, beats + 100.0, down + 100.0, 165.0)
    assert np.isnan(apart["median_offset_ms"])


def test_bars_at_downbeats_skip_a_bar_cut_by_a_new_section():
    beats = np.arange(14) * 0.5
    down = np.zeros(14, bool)
    down[[0, 4, 6, 10]] = True  # a new section restarts the bars at beat 6
    bars = tempo.bars_at_downbeats(beats, down)
    np.testing.assert_allclose(bars[:, 0], [0.0, 3.0])


def test_signature_bits_from_kinematic_beats_at_half_beat_slots():
    bar = np.array([[10.0, 10.5, 11.0, 11.5, 12.0]])  # beat 0.5 s, half beat 0.25 s
    # Beats at slot 0 (downbeat), slot 3 (beat 1.5) and slot 4 (beat 2), slightly off-grid.
    kb = np.array([10.02, 10.74, 11.03])
    bits = tempo.bar_signature_bits(kb, bar)
    assert sig.to_string(bits[0]) == "00011001"
    # A kinematic beat midway between two slots belongs to neither with a tight tolerance.
    assert tempo.bar_signature_bits(np.array([10.125]), bar, tolerance=0.25).sum() == 0
    np.testing.assert_allclose(
        tempo.slot_times(bar)[0], [10.0, 10.25, 10.5, 10.75, 11.0, 11.25, 11.5, 11.75]
    )
    # Snapped to the nearest common signature: only the half-beat slot 3 differs.
    assert sig.COMMON_SIGNATURES[int(sig.nearest_common(bits)[0])] == "00010001"


def test_grid_from_tempo_and_grid_fit():
    beats = tempo.grid_from_tempo(10.0, 120.0, first_beat_s=0.25)
    assert beats[0] == pytest.approx(0.25)
    np.testing.assert_allclose(np.diff(beats), 0.5)
    bars = tempo.bars_from_beats(beats)
    on_grid = tempo.slot_times(bars).ravel()[::3]
    assert tempo.grid_fit(on_grid, bars) == 1.0
    off_grid = on_grid + 0.125  # a quarter beat off: between slots
    assert tempo.grid_fit(off_grid, bars) == 0.0


#: The salsa basic in an 8-count: (foot, forward move m, lift m) of the step landing on each
#: beat, None for the pauses on 4 and 8.
SALSA_BASIC = (
    ("L", 0.3, 0.08),
    ("R", 0.0, 0.06),
    ("L", -0.3, 0.08),
    None,
    ("R", -0.3, 0.08),
    ("L", 0.0, 0.06),
    ("R", 0.3, 0.08),
    None,
)


def _salsa_dance(bpm: float, first_s: float, duration_s: float, *, mirror=False, seed=0):
    """Body ``(F, 3, 3)`` (pelvis, knees), feet ``(F, 4, 3)`` (ankle, toe of left and right),
    the landing times (s) and kinematic beats (s) of a dancer doing the salsa basic at ``bpm``
    from ``first_s``: each step swings over the 0.8 beat before its beat and lands on it, a
    pause on 4 and 8; ``mirror`` swaps the feet (the partner's steps). The kinematic beats are
    the landings as a detector finds them in real salsa: 40 ms jitter, 30 % missed."""
    rng = np.random.default_rng(seed)
    n = int(duration_s * FPS)
    t = np.arange(n) / FPS
    period = 60.0 / bpm
    beats = np.arange(first_s, duration_s, period)
    x = {"L": np.zeros(n), "R": np.zeros(n)}
    lift = {"L": np.zeros(n), "R": np.zeros(n)}
    landings = []
    for i, beat in enumerate(beats):
        if SALSA_BASIC[i % 8] is None:
            continue
        foot, dx, height = SALSA_BASIC[i % 8]
        foot = {"L": "R", "R": "L"}[foot] if mirror else foot
        u = np.clip((t - beat + 0.8 * period) / (0.8 * period), 0.0, 1.0)
        x[foot] = x[foot] + dx * (u - np.sin(2 * np.pi * u) / (2 * np.pi))
        lift[foot] = lift[foot] + height * np.sin(np.pi * u) ** 2
        landings.append(beat)
    feet = np.zeros((n, 4, 3))
    for k, (foot, side) in enumerate((("L", -0.15), ("R", 0.15))):
        for j, (ahead, up) in enumerate(((0.0, 0.08), (0.15, 0.02))):
            feet[:, 2 * k + j] = np.stack([x[foot] + ahead, up + lift[foot], np.full(n, side)], 1)
    feet += 0.002 * rng.standard_normal(feet.shape)
    pelvis = np.stack([(x["L"] + x["R"]) / 2, 0.95 - 0.25 * (lift["L"] + lift["R"]), 0 * t], 1)
    body = np.stack([pelvis, (feet[:, 0] + pelvis) / 2, (feet[:, 2] + pelvis) / 2], axis=1)
    landings = np.array(landings)
    found = landings[rng.random(len(landings)) > 0.3]
    return body, feet, landings, np.sort(found + 0.04 * rng.standard_normal(len(found)))


def test_step_onsets_are_the_landings_of_both_feet():
    _, feet, landings, _ = _salsa_dance(171.3, 0.4137, 20.0)
    onsets = step_onsets(point_contacts(feet.reshape(-1, 2, 2, 3), FPS), FPS)
    assert np.all(np.diff(onsets) > 0)
    # every onset is a landing, at most two frames early (the contact's speed threshold) ...
    lag = onsets - landings[np.argmin(np.abs(onsets[:, None] - landings[None]), axis=1)]
    assert np.all((lag > -2.0 / FPS) & (lag <= 0.5 / FPS))
    # ... and every landing has its onset
    assert len(onsets) == len(landings)


def test_salsa_basic_tempo_phase_and_partner():
    params = tempo.GridParams(prior_bpm=(150.0, 220.0))
    period = 60.0 / 171.3

    def grid(first_s, **kw):
        body, feet, _, pauses = _salsa_dance(171.3, first_s, 40.0, **kw)
        return tempo.estimate_grid(tempo.step_signals(body, feet, pauses, FPS), FPS, params)

    lead = grid(0.4137)
    assert lead.tempo_bpm == pytest.approx(171.3, rel=0.002)
    assert lead.flags == [] and len(lead.sections) == 1
    # The beats sit in the middle of the quiet half of the two-beat step cycle (the swing to
    # the in-place step or to the pause, 0.4 beat before its landing), evenly: the steps lead.
    truth = np.arange(0.4137, 40.0, period)[2:-2]
    ahead = (truth - lead.beats[np.argmin(np.abs(truth[:, None] - lead.beats), axis=1)]) / period
    assert np.ptp(ahead) < 0.01 and np.median(ahead) == pytest.approx(0.4, abs=0.05)
    # The phase and bars follow the dance: started 0.123 s later, the grid is 0.123 s later.
    later = grid(0.4137 + 0.123)
    shifted = tempo.partner_agreement(
        lead.beats + 0.123, lead.bars[:, 0] + 0.123, lead.tempo_bpm,
        later.beats, later.bars[:, 0], later.tempo_bpm,
    )  # fmt: skip
    assert shifted["median_offset_ms"] < 5.0 and shifted["downbeat_agreement"] == 1.0
    # The partner mirrors the steps (other foot), 17 ms late: the two grids agree.
    partner = grid(0.4137 + 0.017, mirror=True, seed=1)
    agree = tempo.partner_agreement(
        lead.beats, lead.bars[:, 0], lead.tempo_bpm,
        partner.beats, partner.bars[:, 0], partner.tempo_bpm,
    )  # fmt: skip
    assert agree["tempo_diff_pct"] < 0.05 and agree["median_offset_ms"] < 20.0
    assert agree["downbeat_agreement"] == 1.0


def test_the_clearer_bar_cue_leads():
    # kinematic beats (last channel) against the feet (FEET_CHANNEL)
    assert tempo.pauses_lead(np.array([0.1, 0.2, 0.0, 0.3, 0.2]))
    assert not tempo.pauses_lead(np.array([0.4, 0.3, 0.1, 0.2, 0.1]))


def _salsa(path, fps):
    motion = read_bvh(path, fps=fps)
    pos, world = forward_kinematics(motion)
    sk = motion.skeleton
    main = canonical_positions(sk, pos, world, MAIN_JOINTS)
    ix = {k: sk.index(sk.canonical[k]) for k in ("hips", "left_ankle", "right_ankle")}
    ix |= {k: sk.index(sk.canonical[k]) for k in ("left_wrist", "right_wrist")}
    steps = tempo.step_signals(
        canonical_positions(sk, pos, world, STEP_BODY_JOINTS),
        canonical_positions(sk, pos, world, STEP_FOOT_JOINTS),
        kinematic_beats(main, fps),
        fps,
    )
    periodic = tempo.periodicity_signals(
        pos,
        fps,
        root=ix["hips"],
        feet=(ix["left_ankle"], ix["right_ankle"]),
        hands=(ix["left_wrist"], ix["right_wrist"]),
    )
    return steps, periodic


def test_real_salsa_partners_gridded_apart_agree(salsa_dir):
    # Two trials whose dancers' grids agree (docs/mocap-beats.md has all 14 pairs): each take
    # is gridded from its own motion only, at sub-frame precision.
    params = tempo.GridParams(prior_bpm=(150.0, 220.0))
    for trial in ("13", "15"):
        grids = [
            tempo.estimate_grid(
                _salsa(salsa_dir / f"{who}_{trial}_scaled.bvh", 60.0)[0], 60.0, params
            )
            for who in ("60", "61")
        ]
        a, b = grids
        agreement = tempo.partner_agreement(
            a.beats, a.bars[:, 0], a.tempo_bpm, b.beats, b.bars[:, 0], b.tempo_bpm
        )
        assert agreement["tempo_diff_pct"] < 1.0, trial
        assert agreement["median_offset_ms"] < 40.0, trial
        assert agreement["downbeat_agreement"] >= 0.8, trial
        assert 160.0 < a.tempo_bpm < 170.0


def test_real_salsa_motion_tempo_flags_the_header_frame_rate(salsa_dir):
    takes = ["60_01", "60_03", "60_13", "60_15"]
    at60, at120 = [], []
    for take in takes:
        periodic = _salsa(salsa_dir / f"{take}_scaled.bvh", 60.0)[1]
        at60.append(tempo.motion_tempo_bpm(periodic, 60.0))
        at120.append(tempo.motion_tempo_bpm(periodic, 120.0))
    assert 160 < np.median(at60) < 176
    assert not any(tempo.outside_prior(t, (150.0, 220.0)) for t in at60)
    # Read at the header's 120 fps the same takes move at ~330 BPM: every one is flagged.
    assert all(tempo.outside_prior(t, (150.0, 220.0)) for t in at120)
    assert np.median(at120) > 300
