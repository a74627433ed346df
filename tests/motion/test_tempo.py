"""Tempo, beat grid, bar phase and signature labels from kinematics (dancegraph.motion.tempo)."""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.motion import tempo
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.fk import forward_kinematics
from dancegraph.rhythm import signatures as sig


def _step_signals(bpm: float, fps: float, seconds: float, seed: int = 0) -> np.ndarray:
    """(F, 4) bar-periodic signals of a basic step: steps on beats 1 2 3, a pause on 4."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * fps)) / fps
    beat = 60.0 / bpm
    steps = np.array([k * beat for k in range(int(seconds / beat) + 2) if k % 4 != 3])
    pulse = np.exp(-0.5 * ((t[:, None] - steps[None, :]) / (0.12 * beat)) ** 2).sum(axis=1)
    sway = np.sin(2 * np.pi * t / (4 * beat))  # one body sway per bar
    cols = [0.9 + 0.03 * sway, pulse, 0.5 * pulse + 0.3 * sway, 0.4 * pulse]
    return np.stack(cols, axis=1) + 0.05 * rng.standard_normal((len(t), 4))


@pytest.mark.parametrize("bpm", [96.0, 128.0, 168.0])
def test_estimate_tempo_finds_the_bar_of_a_step_pattern(bpm):
    est = tempo.estimate_tempo(_step_signals(bpm, 60.0, 40.0), 60.0, (80.0, 200.0))
    assert est.tempo_bpm == pytest.approx(bpm, rel=0.01)
    assert est.bar_period_s == pytest.approx(240.0 / bpm, rel=0.01)
    assert est.confidence > 0.8
    assert est.flags == []


def test_frame_rate_read_twice_too_high_is_flagged():
    # The same frames read at 120 instead of 60 fps: the motion runs twice as fast.
    signals = _step_signals(168.0, 60.0, 40.0)
    right = tempo.estimate_tempo(signals, 60.0, (150.0, 220.0))
    wrong = tempo.estimate_tempo(signals, 120.0, (150.0, 220.0))
    assert right.motion_tempo_bpm == pytest.approx(168.0, rel=0.02)
    assert "tempo_outside_prior" not in right.flags
    assert wrong.motion_tempo_bpm == pytest.approx(336.0, rel=0.02)
    assert "tempo_outside_prior" in wrong.flags


def test_noise_has_no_steady_beat():
    rng = np.random.default_rng(3)
    noise = np.cumsum(rng.standard_normal((2400, 4)), axis=0)  # random walk, no period
    est = tempo.estimate_tempo(noise, 60.0, (80.0, 200.0))
    assert "no_steady_beat" in est.flags
    assert est.confidence < tempo.STEADY_MIN_CONFIDENCE


def test_track_beats_follows_a_drifting_pulse():
    fps = 60.0
    # 120 BPM slowing by 3 % over the take, kinematic beats on every beat (jittered).
    rng = np.random.default_rng(1)
    intervals = np.linspace(0.5, 0.515, 60)
    truth = 0.3 + np.concatenate([[0.0], np.cumsum(intervals)])
    kb = truth + rng.normal(0, 0.01, len(truth))
    n = int((truth[-1] + 0.4) * fps)
    beats = tempo.track_beats(tempo.beat_envelope(kb, n, fps), fps, 0.507)
    nearest = np.array([np.min(np.abs(beats - t)) for t in truth])
    assert np.all(nearest < 2.0 / fps)
    assert len(beats) == pytest.approx(len(truth), abs=1)


def test_bar_phase_puts_the_downbeat_on_the_accented_beat():
    beats = np.arange(40) * 0.5
    kb = beats[2::4] + 0.01  # kinematic beats on every third beat of four
    phase, clarity = tempo.bar_phase(beats, kb, 0.5)
    assert phase == 2
    assert clarity > 0.9
    bars = tempo.bars_from_beats(beats, phase)
    assert bars.shape == (9, 5)
    assert bars[0, 0] == pytest.approx(1.0)
    np.testing.assert_allclose(bars[:, 4], bars[:, 0] + 2.0)


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


def _salsa_signals(path, fps):
    motion = read_bvh(path, fps=fps)
    pos, _ = forward_kinematics(motion)
    sk = motion.skeleton
    ix = {
        k: sk.index(sk.canonical[k])
        for k in ("hips", "left_ankle", "right_ankle", "left_wrist", "right_wrist")
    }
    return tempo.periodicity_signals(
        pos,
        fps,
        root=ix["hips"],
        feet=(ix["left_ankle"], ix["right_ankle"]),
        hands=(ix["left_wrist"], ix["right_wrist"]),
    )


def test_real_salsa_tempo_near_168_at_60_fps_and_flagged_at_120(salsa_dir):
    takes = ["60_01", "60_03", "60_13", "60_15"]
    at60, at120 = [], []
    for take in takes:
        signals = _salsa_signals(salsa_dir / f"{take}_scaled.bvh", 60.0)
        at60.append(tempo.estimate_tempo(signals, 60.0, (150.0, 220.0)))
        at120.append(tempo.estimate_tempo(signals, 120.0, (150.0, 220.0)))
    tempi = np.array([e.tempo_bpm for e in at60])
    assert np.all((tempi > 155) & (tempi < 180)), tempi
    assert 160 < np.median([e.motion_tempo_bpm for e in at60]) < 176
    assert not any("tempo_outside_prior" in e.flags for e in at60)
    # Read at the header's 120 fps the same takes move at ~330 BPM: every one is flagged.
    assert all("tempo_outside_prior" in e.flags for e in at120)
    assert np.median([e.motion_tempo_bpm for e in at120]) > 300
