"""Per-bar onset/RMS curves and log-mel windows."""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.music.features import (
    bar_onset_rms,
    bar_synchronous,
    frame_features,
    logmel_window,
    music_logmel,
    phrase_logmel_windows,
    resample_per_bar,
)
from dancegraph.music.generator import bar_grid, generate, random_config


@pytest.fixture(scope="module")
def drum_song():
    """A 4/4 song at 120 BPM, about 20 s, whose first section has a kick on every beat."""
    cfg = random_config(31, meter=4, tempo_bpm=120, form=["A", "B"], section_bars={"A": 4, "B": 4})
    cfg.drift, cfg.swing, cfg.pickup_beats = 0.0, 0.0, 0
    return generate(cfg)


def test_bar_onset_rms_shape_scale_and_alignment(drum_song):
    ff = frame_features(drum_song.y, drum_song.sr)
    bars, grid = bar_grid(drum_song.truth)
    x = bar_onset_rms(ff, bars)
    assert x.shape == (len(bars), 2, 200) and x.dtype == np.float32
    assert np.all(x >= 0) and 0.5 < np.percentile(x[:, 0], 99.5) < 3
    # Onsets peak at the beats: the mean curve is higher within 2 points of each beat
    # (points 0, 50, 100, 150) than a third of the way between beats.
    mean = x[:, 0].mean(axis=0)
    on = np.mean([mean[max(k - 2, 0) : k + 3].max() for k in (0, 50, 100, 150)])
    off = np.mean([mean[k] for k in (17, 67, 117, 167)])
    assert on > 2 * off


def test_resample_per_bar_and_bar_synchronous_are_exact_on_a_ramp():
    times = np.arange(0, 10, 0.01)
    ramp = times.copy()
    bars = np.array([[1.0, 3.0], [3.0, 5.0]])
    r = resample_per_bar(ramp, times, bars, n=4)
    assert np.allclose(r, [[1.0, 1.5, 2.0, 2.5], [3.0, 3.5, 4.0, 4.5]])
    m = bar_synchronous(np.stack([ramp, 2 * ramp]), times, bars, n_sub=2)
    assert m.shape == (2, 4)  # (B, n_sub * D): sub-part major, feature minor
    assert np.allclose(m[0], [1.495, 2.99, 2.495, 4.99], atol=0.01)


def test_logmel_windows(drum_song):
    mel = music_logmel(drum_song.y, drum_song.sr)
    assert mel.shape[0] == 96
    assert abs(mel.shape[1] - drum_song.duration_s * 100) <= 2  # hop 10 ms
    w = logmel_window(mel, 2.0)
    assert w.shape == (1, 96, 800) and w.dtype == np.float32
    assert np.array_equal(w[0], mel[:, 200:1000])
    # Past the end: floor-filled.
    tail = logmel_window(mel, drum_song.duration_s - 3.0)
    assert np.all(tail[0, :, 400:] == -100.0) and tail[0, :, :250].max() > -100.0
    ws = phrase_logmel_windows(drum_song.y, drum_song.sr, np.array([0.0, 8.0]))
    assert ws.shape == (2, 1, 96, 800)
    assert np.array_equal(ws[1], logmel_window(mel, 8.0))


def test_frame_features_at_other_rates(drum_song):
    import librosa

    y16 = librosa.resample(drum_song.y[: drum_song.sr * 5], orig_sr=drum_song.sr, target_sr=16000)
    ff = frame_features(y16, 16000)
    assert ff.sr == 22050 and ff.chroma.shape[0] == 12 and ff.mfcc.shape[0] == 20
    assert len(ff.times) == len(ff.onset) == len(ff.accent) == len(ff.rms) == ff.chroma.shape[1]
    assert abs(ff.times[-1] - 5.0) < 0.05
