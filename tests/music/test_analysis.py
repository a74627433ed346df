"""analyze(): beats → 4-beat bars (the bar rule) → structure → features → signatures, and the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dancegraph.cli import main
from dancegraph.errors import AudioError
from dancegraph.music.analysis import (
    MusicAnalysis,
    analysis_version,
    analyze,
    fit_tempo_range,
    four_beat_bars,
    phrase_unit,
)
from dancegraph.music.generator import generate, random_config, write_song


def _grid(n_beats: int, meter: int, pickup: int = 0, period: float = 0.5):
    beats = 1.0 + period * np.arange(n_beats)
    pos = (np.arange(n_beats) - pickup) % meter + 1
    return beats, pos


def test_bars_in_four_four_skip_the_pickup_and_complete_the_end():
    beats, pos = _grid(21, 4, pickup=2)  # 2 pickup beats, 4 bars, then 3 beats of a fifth
    bars, grid, warnings = four_beat_bars(beats, pos, 4, duration_s=beats[-1] + 2.0)
    assert bars.shape == (5, 2) and grid.shape == (5, 5)
    assert bars[0, 0] == beats[2]  # the first downbeat
    assert np.allclose(grid[:, 0], beats[pos == 1][:5])
    assert np.allclose(grid[-1, 3:], beats[-1] + 0.5 * np.array([1, 2]))  # completed
    assert warnings == []
    # If the audio stops, the unfinished bar is left out; so is a bar with only its downbeat.
    assert len(four_beat_bars(beats, pos, 4, duration_s=beats[-1] + 0.2)[0]) == 4
    assert len(four_beat_bars(beats[:19], pos[:19], 4, duration_s=beats[-1] + 5)[0]) == 4


def test_bars_in_three_four_realign_every_three_bars():
    beats, pos = _grid(37, 3)
    bars, grid, warnings = four_beat_bars(beats, pos, 3, duration_s=beats[-1])
    assert len(bars) == 9
    downs = set(np.round(beats[pos == 1], 6))
    starts_on_downbeat = [round(b, 6) in downs for b in bars[:, 0]]
    assert starts_on_downbeat == [True, False, False] * 3
    assert any("meter 3" in w for w in warnings)
    assert phrase_unit(3) == 3 and phrase_unit(4) == 4 and phrase_unit(2) == 4


def test_bars_in_two_four_pair_measures():
    beats, pos = _grid(17, 2)
    bars, grid, _ = four_beat_bars(beats, pos, 2, duration_s=beats[-1])
    assert len(bars) == 4 and np.allclose(np.diff(grid, axis=1), 0.5)


def test_a_downbeat_phase_change_is_absorbed_by_the_previous_bar():
    # 2 bars of 4/4, a 2-beat measure, then 2 bars: the tracker's downbeats shift by 2 beats.
    pos = np.array([1, 2, 3, 4, 1, 2, 3, 4, 1, 2, 1, 2, 3, 4, 1, 2, 3, 4, 1])
    beats = 0.5 * np.arange(len(pos))
    bars, grid, warnings = four_beat_bars(beats, pos, 4, duration_s=beats[-1])
    assert np.allclose(bars[:, 0], [0.0, 2.0, 5.0, 7.0])
    assert np.allclose(grid[1], np.linspace(2.0, 5.0, 5))  # 6 beats spread over the bar
    assert any("bar 1" in w for w in warnings)


def test_no_beats_no_bars():
    bars, grid, _ = four_beat_bars(np.array([1.0, 1.5]), np.array([1, 2]), 4, duration_s=1.6)
    assert bars.shape == (0, 2) and grid.shape == (0, 5)


@pytest.fixture(scope="module")
def analysed(tmp_path_factory):
    """A 4/4 song at 120 BPM, form intro A B A B, 4-bar sections (about 42 s), from its WAV."""
    cfg = random_config(
        12,
        meter=4,
        tempo_bpm=120,
        form=["intro", "A", "B", "A", "B"],
        section_bars={"intro": 4, "A": 4, "B": 4},
    )
    cfg.pickup_beats, cfg.hard_cases = 0, []
    song = generate(cfg)
    wav, _ = write_song(song, tmp_path_factory.mktemp("song"), "song")
    return song, wav, analyze(wav)


def test_analyze_a_generated_song(analysed):
    song, _, a = analysed
    t = song.truth
    assert a.meter == 4 and abs(a.tempo_bpm - 120) < 3
    assert abs(a.duration_s - song.duration_s) < 0.01
    ref = np.asarray(t["downbeats"])
    hits = np.mean([np.min(np.abs(ref - d)) < 0.07 for d in a.downbeats])
    assert hits >= 0.9
    b = a.n_bars
    assert b >= 18
    assert a.bars.shape == (b, 2) and a.bar_beats.shape == (b, 5)
    assert a.signature_scores.shape == (b, 13) and a.signature_topk.shape == (b, 3)
    assert a.bar_onset_rms.shape == (b, 2, 200) and len(a.tags) == b
    # Phrases tile the bars; A and B repeat.
    assert a.phrases[0]["start_bar"] == 0 and a.phrases[-1]["end_bar"] == b
    assert np.allclose(a.phrase_starts_s(), [a.bars[p["start_bar"], 0] for p in a.phrases])
    labels = "".join(p["label"] for p in a.phrases)
    assert labels[1:] in ("BCBC", "BCBCD") and len(set(labels[:3])) == 3


def test_signatures_come_from_the_accent_curve(analysed):
    # the rhythm signatures' onsets leave the hi-hats out (FrameFeatures.accent: below 4 kHz);
    # on generated 4/4 songs that finds the true accent signature in the top 3 of 82 % of bars,
    # the full-band onset in 72 % (docs/evaluation.md)
    from dancegraph.music.decode import load_audio
    from dancegraph.music.features import FEATURE_SR, frame_features
    from dancegraph.rhythm.music import music_signatures

    _, wav, a = analysed
    ff = frame_features(load_audio(wav, sr=FEATURE_SR)[0], FEATURE_SR)
    _, topk, _ = music_signatures(ff.accent, ff.frame_rate, a.bar_beats)
    _, full_band, _ = music_signatures(ff.onset, ff.frame_rate, a.bar_beats)
    assert np.array_equal(a.signature_topk, topk) and not np.array_equal(topk, full_band)


def test_to_dict_from_dict_and_summary(analysed):
    _, _, a = analysed
    d = json.loads(json.dumps(a.to_dict()))
    b = MusicAnalysis.from_dict(d)
    assert np.allclose(b.bars, a.bars, atol=1e-4) and np.allclose(
        b.bar_onset_rms, a.bar_onset_rms, atol=1e-4
    )
    assert b.phrases == a.phrases and b.tags == a.tags and b.meter == a.meter
    assert d["meters"] == {"music": 4, "dance": 4} and b.meters() == a.meters()
    assert np.array_equal(b.signature_topk, a.signature_topk)
    s = a.summary()
    assert s["meters"] == {"music": 4, "dance": 4}
    assert s["n_bars"] == a.n_bars and s["form"] == "".join(p["label"] for p in a.phrases)
    empty = MusicAnalysis.from_dict(
        {"duration_s": 1, "tempo_bpm": 0, "tempo_confidence": 0, "meter": 4}
    )
    assert empty.bars.shape == (0, 2) and empty.bar_onset_rms.shape == (0, 2, 200)


def test_cli_analyze(analysed, capsys, tmp_path):
    _, wav, a = analysed
    assert main(["analyze", str(wav), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["meter"] == a.meter and len(out["bars"]) == a.n_bars and "tags" in out
    bad = tmp_path / "notes.mp3"
    bad.write_text("this is not audio\n" * 50)
    assert main(["analyze", str(bad)]) == 2
    assert "audio_undecodable" in capsys.readouterr().err


def test_cli_analyze_many_files_as_json_lines(analysed, capsys, tmp_path):
    """One process, one line per file with its path; an unreadable file gives its error code
    and the files after it are still analysed."""
    _, wav, a = analysed
    bad = tmp_path / "notes.mp3"
    bad.write_text("this is not audio\n" * 50)
    missing = tmp_path / "missing.wav"
    assert main(["analyze", str(wav), str(bad), str(missing), str(wav), "--jsonl"]) == 2
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [x["path"] for x in lines] == [str(wav), str(bad), str(missing), str(wav)]
    assert lines[0]["n_bars"] == a.n_bars and lines[0] == lines[3]
    assert lines[1]["error"]["code"] == "audio_undecodable"
    assert lines[2]["error"]["code"].startswith("audio_")
    assert main(["analyze", str(wav), "--jsonl", "--json"]) == 0
    (full,) = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert full["path"] == str(wav) and len(full["bars"]) == a.n_bars
    with pytest.raises(SystemExit):  # several files only as JSON lines
        main(["analyze", str(wav), str(wav)])


def test_a_style_tempo_range_picks_the_octave_of_the_bar_grid(analysed):
    """The tracker's level stays unless a style's range holds its double or half: then the beats
    and bars count that octave, and the analysis says so (field and warning)."""
    beats = np.arange(0.0, 20.0, 0.6)  # 100 BPM, 4/4 from the first beat
    pos = np.arange(len(beats)) % 4 + 1
    same = fit_tempo_range(beats, pos, 4, (90.0, 130.0))
    assert same[0] is beats and same[3] == "x1" and not same[4]
    dbl, dpos, meter, octave, notes = fit_tempo_range(beats, pos, 4, (160.0, 220.0))
    assert octave == "x2" and meter == 4 and len(dbl) == 2 * len(beats) - 1
    assert np.allclose(dbl[dpos == 1], beats[(pos == 1) | (pos == 3)])
    assert notes[0].startswith("grid_octave")
    half, hpos, meter, octave, _ = fit_tempo_range(beats, pos, 4, (40.0, 60.0))
    assert octave == "x1/2" and meter == 2 and np.allclose(half, beats[::2])
    assert np.allclose(half[hpos == 1], beats[pos == 1])
    assert fit_tempo_range(beats, pos, 3, (40.0, 60.0))[3] == "x1"  # a waltz is not halved
    song, wav, a = analysed
    lo, hi = 1.8 * a.tempo_bpm, 2.2 * a.tempo_bpm
    fast = analyze(wav, tempo_range=(lo, hi))
    assert fast.grid_octave == "x2" and lo <= fast.tempo_bpm <= hi
    assert fast.n_bars >= 2 * a.n_bars - 2
    assert any(w.startswith("grid_octave") for w in fast.warnings)
    assert MusicAnalysis.from_dict(fast.to_dict()).grid_octave == "x2"
    assert a.grid_octave == "x1"


def test_array_input_needs_a_rate():
    with pytest.raises(AudioError) as e:
        analyze(np.zeros(22050, dtype=np.float32))
    assert e.value.field == "sr"


def test_array_input_int16_stereo_other_rate(analysed):
    import librosa

    song, _, a = analysed
    n = song.sr * 20
    y44 = librosa.resample(song.y[:n], orig_sr=song.sr, target_sr=44100)
    pcm = (np.stack([y44, y44]) * 32767).astype(np.int16)
    b = analyze(pcm, 44100)
    assert abs(b.duration_s - 20.0) < 0.01 and b.meter == a.meter
    assert abs(b.tempo_bpm - 120) < 3
    assert np.allclose(b.downbeats[:5], a.downbeats[:5], atol=0.03)


def test_analysis_version_names_the_models_in_use(tmp_path, monkeypatch):
    """The cache version is a stable fingerprint, and an analysis made without the BeatNet
    weights (the librosa fallback) gets another version than one made with them."""
    with_weights, without = tmp_path / "weights", tmp_path / "none"
    with_weights.mkdir()
    without.mkdir()
    for m in (1, 2, 3):
        (with_weights / f"model_{m}_weights.pt").write_bytes(b"")
    versions = {}
    for name, folder in (("with", with_weights), ("without", without), ("again", with_weights)):
        monkeypatch.setenv("DANCEGRAPH_BEATNET_WEIGHTS", str(folder))
        analysis_version.cache_clear()
        versions[name] = analysis_version()
    analysis_version.cache_clear()
    assert len(versions["with"]) == 12 and int(versions["with"], 16) >= 0
    assert versions["again"] == versions["with"] != versions["without"]


def test_two_four_music_is_danced_in_bars_of_four_with_its_own_meter_beside(cc_music_dir):
    """The Sugar Plum Fairy (2/4; CC BY 3.0, Kevin MacLeod): its measures paired into 4-beat
    dance bars (``meter`` 4), the music's own meter 2 said beside them, in the JSON too."""
    path = cc_music_dir / "Kevin_MacLeod_-_P_I_Tchaikovsky_Dance_of_the_Sugar_Plum_Fairy.hq.ogg"
    if not path.exists():
        pytest.skip(f"{path} not found (set DANCEGRAPH_SHARED)")
    a = analyze(path)
    assert a.meter == 4 and a.meters() == {"music": 2, "dance": 4}
    assert MusicAnalysis.from_dict(json.loads(json.dumps(a.to_dict()))).music_meter == 2
    assert a.summary()["meters"] == {"music": 2, "dance": 4}
