"""The music generator: determinism, ground-truth consistency, audio that matches the truth."""

from __future__ import annotations

import json

import librosa
import numpy as np
import soundfile as sf

from dancegraph.music.generator import (
    HARD_GROOVES,
    bar_grid,
    generate,
    generate_song,
    random_config,
    write_song,
)

SHORT = {"form": ["A", "B", "A", "B"], "section_bars": {"A": 4, "B": 4}}


def test_same_seed_same_song_and_other_seed_differs():
    a = generate_song(3, tempo_bpm=130, meter=4, **SHORT)
    b = generate_song(3, tempo_bpm=130, meter=4, **SHORT)
    c = generate_song(4, tempo_bpm=130, meter=4, **SHORT)
    assert np.array_equal(a.y, b.y)
    assert a.truth == b.truth
    assert len(a.y) != len(c.y) or not np.array_equal(a.y, c.y)


def test_truth_is_consistent():
    for seed, meter in ((1, 4), (2, 3)):
        song = generate_song(seed, meter=meter, tempo_bpm=150, **SHORT)
        t = song.truth
        beats = np.asarray(t["beats"])
        pos = np.asarray(t["beat_positions"])
        assert t["meter"] == meter
        assert np.all(np.diff(beats) > 0)
        assert set(pos.tolist()) == set(range(1, meter + 1))
        assert np.allclose(t["downbeats"], beats[pos == 1])
        assert abs(t["tempo_bpm"] - 150) < 10
        # Sections tile the bars, bars tile the song after the pickup.
        bars = t["bars"]
        assert len(bars) == 16
        assert [s["start_bar"] for s in t["sections"]] == [0, 4, 8, 12]
        assert [s["label"] for s in t["sections"]] == ["A", "B", "A", "B"]
        assert [s["occurrence"] for s in t["sections"]] == [0, 0, 1, 1]
        assert np.allclose([b["start_s"] for b in bars], t["downbeats"][: len(bars)])
        assert all(b0["end_s"] == b1["start_s"] for b0, b1 in zip(bars[:-1], bars[1:], strict=True))
        assert bars[-1]["end_s"] <= song.duration_s
        grid_bars, grid = bar_grid(t)
        assert grid.shape == (16, meter + 1)
        assert np.allclose(grid[:, 0], grid_bars[:, 0]) and np.allclose(
            grid[:, -1], grid_bars[:, 1]
        )


def test_repeats_carry_the_same_music():
    cfg = random_config(5, meter=4, tempo_bpm=120, **SHORT)
    cfg.drift = 0.0  # with a steady tempo a repeat is sample-for-sample the same
    song = generate(cfg)
    bars = song.truth["bars"]
    sr = song.sr
    # The second A is the first A again, apart from a fill or break in its last bar.
    for i in range(3):
        assert bars[i]["content"] == bars[8 + i]["content"]
    for i in (1, 2):  # inside the section the sound left over from the bar before is alike too
        a0, a1 = bars[i], bars[8 + i]
        x = song.y[round(a0["start_s"] * sr) : round(a0["end_s"] * sr)]
        y = song.y[round(a1["start_s"] * sr) : round(a1["start_s"] * sr) + len(x)]
        assert np.corrcoef(x, y)[0, 1] > 0.9
    # A and B differ.
    assert bars[0]["content"] != bars[4]["content"]


def test_onsets_fall_on_the_true_beats():
    song = generate_song(7, meter=4, tempo_bpm=110, **SHORT)
    env = librosa.onset.onset_strength(y=song.y, sr=song.sr, hop_length=256)
    fr = song.sr / 256
    beats = np.asarray(song.truth["beats"])
    at_beats = env[np.round(beats * fr).astype(int)].mean()
    # Between beats (at a third of a beat, never an eighth or sixteenth) there is much less.
    mids = beats[:-1] + np.diff(beats) / 3
    assert at_beats > 2 * env[np.round(mids * fr).astype(int)].mean()


def test_pickup_swing_drift_and_hard_cases():
    cfg = random_config(11, meter=4, tempo_bpm=100, **SHORT)
    cfg.pickup_beats, cfg.swing, cfg.drift = 2, 1 / 6, 0.05
    cfg.hard_cases = ["syncopated_bass", "anticipated_chords", "offbeat_drums"]
    song = generate(cfg)
    t = song.truth
    assert t["beat_positions"][:3] == [3, 4, 1]
    ibi = np.diff(t["beats"])
    assert ibi[-1] < ibi[0] * 0.97  # 5 % faster at the end
    # Offbeat drums: no kick on a downbeat; syncopated bass: no bass note on beat 1.
    for sec in t["sections"]:
        if sec["groove"] is not None:
            assert sec["groove"] in HARD_GROOVES[4] and 0 not in HARD_GROOVES[4][sec["groove"]][0]
        assert sec["bass"] == "synco"


def test_random_configs_cover_the_ranges():
    cfgs = [random_config(s, hard=s % 2 == 1) for s in range(40)]
    tempos = [c.tempo_bpm for c in cfgs]
    assert min(tempos) >= 70 and max(tempos) <= 180
    assert {c.meter for c in cfgs} == {3, 4}
    assert any(c.swing > 0 for c in cfgs) and any(c.drift != 0 for c in cfgs)
    assert any(c.pickup_beats > 0 for c in cfgs)
    assert all(len(c.hard_cases) >= 2 for c in cfgs[1::2])
    assert any(len(c.form) != len(set(c.form)) for c in cfgs)  # forms with repeats


def test_write_song(tmp_path):
    song = generate_song(2, meter=3, tempo_bpm=140, **SHORT)
    wav, js = write_song(song, tmp_path, "s")
    y, sr = sf.read(wav, dtype="float32")
    assert sr == song.sr and len(y) == len(song.y)
    assert np.abs(y - song.y).max() < 1e-3
    assert json.loads(js.read_text())["beats"] == song.truth["beats"]
