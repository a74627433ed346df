"""Decoding: formats, rates, channels, resampling, and every bad input with its error code."""

from __future__ import annotations

import struct
import tracemalloc
from pathlib import Path

import av
import numpy as np
import pytest
import soundfile as sf

from dancegraph.errors import AudioError
from dancegraph.music.decode import audio_info, load_audio, resample


def _tone(sr: int, seconds: float, hz: float = 440.0, channels: int = 1) -> np.ndarray:
    t = np.arange(int(sr * seconds)) / sr
    x = (0.4 * np.sin(2 * np.pi * hz * t)).astype(np.float32)
    return np.stack([x] * channels, axis=1) if channels > 1 else x


def _peak_hz(y: np.ndarray, sr: int) -> float:
    spec = np.abs(np.fft.rfft(y * np.hanning(len(y))))
    return float(np.argmax(spec) * sr / len(y))


def _wav_header(sr: int, channels: int, bits: int, n_bytes: int, fmt: int = 1) -> bytes:
    block = channels * bits // 8
    return (
        b"RIFF"
        + struct.pack("<I", 36 + n_bytes)
        + b"WAVEfmt "
        + struct.pack("<IHHIIHH", 16, fmt, channels, sr, sr * block, block, bits)
        + b"data"
        + struct.pack("<I", n_bytes)
    )


@pytest.mark.parametrize(
    "ext,subtype",
    [
        ("wav", "PCM_16"),
        ("wav", "PCM_24"),
        ("wav", "FLOAT"),
        ("flac", "PCM_16"),
        ("ogg", "VORBIS"),
        ("mp3", "MPEG_LAYER_III"),
    ],
)
def test_decodes_common_formats(tmp_path: Path, ext: str, subtype: str) -> None:
    path = tmp_path / f"tone.{ext}"
    sf.write(path, _tone(44100, 4.0), 44100, subtype=subtype)
    y, sr = load_audio(path, sr=22050)
    assert sr == 22050 and y.dtype == np.float32 and y.ndim == 1
    assert abs(len(y) / sr - 4.0) < 0.1  # mp3 adds encoder padding
    assert abs(_peak_hz(y, sr) - 440.0) < 2.0
    assert 0.3 < np.abs(y).max() < 0.5


def test_decodes_aac_in_mp4_through_ffmpeg(tmp_path: Path) -> None:
    path = tmp_path / "tone.m4a"
    x = _tone(48000, 5.0)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("aac", rate=48000)
        stream.layout = "stereo"
        frame = av.AudioFrame.from_ndarray(np.stack([x, x]), format="fltp", layout="stereo")
        frame.sample_rate = 48000
        for packet in stream.encode(frame):
            container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    info = audio_info(path)
    assert info.decoder == "av" and info.channels == 2 and info.sr == 48000
    y, sr = load_audio(path, sr=16000)
    assert sr == 16000 and abs(len(y) / sr - 5.0) < 0.1
    assert abs(_peak_hz(y, sr) - 440.0) < 2.0


@pytest.mark.parametrize("rate", [8000, 11025, 44100, 96000, 192000])
def test_any_rate_from_8_to_192_khz(tmp_path: Path, rate: int) -> None:
    path = tmp_path / "tone.wav"
    sf.write(path, _tone(rate, 3.5, hz=1000.0), rate)
    y, sr = load_audio(path, sr=22050)
    assert sr == 22050 and abs(len(y) - 3.5 * 22050) <= 2
    assert abs(_peak_hz(y, sr) - 1000.0) < 2.0
    native, nsr = load_audio(path)
    assert nsr == rate and len(native) == int(3.5 * rate)


def test_multichannel_downmix_and_keep(tmp_path: Path) -> None:
    path = tmp_path / "six.flac"
    x = _tone(48000, 3.5, channels=6)
    x[:, 1] = 0.0  # one silent channel: the mono mix is the mean of all six
    sf.write(path, x, 48000)
    mono, _ = load_audio(path)
    assert mono.shape == (len(x),)
    np.testing.assert_allclose(mono, x.mean(axis=1), atol=1e-4)
    multi, _ = load_audio(path, mono=False, sr=24000)
    assert multi.shape == (6, len(x) // 2) and np.abs(multi[1]).max() < 1e-6


def test_ogg_matches_librosa_load_exactly(cc_music_dir: Path, shared: Path) -> None:
    """The reference input of BeatNet was made with librosa.load at 22,050 Hz: same samples."""
    ref = np.load(shared / "reference" / "beatnet" / "vibe_ace.npz")["audio_22050"]
    y, sr = load_audio(cc_music_dir / "Kevin_MacLeod_-_Vibe_Ace.hq.ogg", sr=22050)
    assert sr == 22050 and y.shape == ref.shape
    assert np.abs(y - ref).max() < 1e-6


def test_resample_helper_shapes() -> None:
    x = _tone(44100, 1.0)
    assert resample(x, 44100, 22050).shape == (22050,)
    assert resample(np.stack([x, x]), 44100, 11025).shape == (2, 11025)
    assert resample(x, 44100, 44100) is not None


def test_non_finite_samples_become_zero(tmp_path: Path) -> None:
    x = _tone(22050, 4.0)
    x[100:200] = np.nan
    x[300] = np.inf
    path = tmp_path / "nan.wav"
    sf.write(path, x, 22050, subtype="FLOAT")
    y, _ = load_audio(path)
    assert np.all(np.isfinite(y)) and np.all(y[100:200] == 0)


# --- bad input: each a specific code, fast ------------------------------------------------


def test_two_hour_file_refused_from_header_with_bounded_memory(tmp_path: Path) -> None:
    path = tmp_path / "two_hours.wav"
    n = 2 * 3600 * 8000
    with open(path, "wb") as f:  # a real 2-hour 8 kHz file, sparse on disk (reads as silence)
        f.write(_wav_header(8000, 1, 16, n * 2))
        f.truncate(44 + n * 2)
    tracemalloc.start()
    with pytest.raises(AudioError) as err:
        load_audio(path, sr=22050)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert err.value.code == "audio_too_long" and err.value.field == "two_hours.wav"
    assert peak < 20_000_000


def test_fifteen_minute_song_is_accepted(tmp_path: Path) -> None:
    path = tmp_path / "fifteen.wav"
    n = 15 * 60 * 8000
    with open(path, "wb") as f:
        f.write(_wav_header(8000, 1, 16, n * 2))
        f.truncate(44 + n * 2)
    y, sr = load_audio(path)
    assert sr == 8000 and len(y) == n


def test_too_long_also_caught_while_decoding(tmp_path: Path) -> None:
    path = tmp_path / "long.wav"
    sf.write(path, _tone(8000, 30.0), 8000)
    with pytest.raises(AudioError) as err:
        load_audio(path, max_seconds=10.0)
    assert err.value.code == "audio_too_long"


def test_one_second_file_is_too_short(tmp_path: Path) -> None:
    path = tmp_path / "one.wav"
    sf.write(path, _tone(44100, 1.0), 44100)
    with pytest.raises(AudioError) as err:
        load_audio(path)
    assert err.value.code == "audio_too_short"
    y, _ = load_audio(path, min_seconds=None)  # the limit is the caller's choice
    assert len(y) == 44100


def test_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.wav"
    path.write_bytes(b"")
    with pytest.raises(AudioError) as err:
        load_audio(path)
    assert err.value.code == "audio_empty"


def test_header_only_wav_has_no_samples(tmp_path: Path) -> None:
    path = tmp_path / "header_only.wav"
    path.write_bytes(_wav_header(22050, 1, 16, 0))
    with pytest.raises(AudioError) as err:
        load_audio(path)
    assert err.value.code in ("audio_empty", "audio_undecodable")


def test_text_named_mp3(tmp_path: Path) -> None:
    path = tmp_path / "song.mp3"
    path.write_text("this is not an mp3 file\n" * 200)
    with pytest.raises(AudioError) as err:
        load_audio(path)
    assert err.value.code == "audio_undecodable" and err.value.field == "song.mp3"
    assert str(tmp_path) not in err.value.message  # no server paths in user-facing messages


def test_corrupted_header(tmp_path: Path) -> None:
    good = tmp_path / "good.wav"
    sf.write(good, _tone(22050, 4.0), 22050)
    data = bytearray(good.read_bytes())
    data[0:4] = b"RIFX"
    data[20:36] = b"\xff" * 16  # format chunk overwritten
    bad = tmp_path / "bad.wav"
    bad.write_bytes(bytes(data))
    with pytest.raises(AudioError) as err:
        load_audio(bad)
    assert err.value.code == "audio_undecodable"


def test_corrupted_ogg(tmp_path: Path, cc_music_dir: Path) -> None:
    data = (cc_music_dir / "Kevin_MacLeod_-_Vibe_Ace.hq.ogg").read_bytes()[:200_000]
    bad = tmp_path / "bad.ogg"
    bad.write_bytes(data[:100] + bytes(1000) + data[1100:])
    with pytest.raises(AudioError) as err:
        load_audio(bad)
    assert err.value.code == "audio_undecodable"


def test_unknown_codec(tmp_path: Path) -> None:
    path = tmp_path / "odd.wav"
    path.write_bytes(_wav_header(22050, 1, 16, 88200, fmt=0x3456) + bytes(88200))
    with pytest.raises(AudioError) as err:
        load_audio(path)
    assert err.value.code == "audio_unsupported_codec"


def test_unsupported_rate(tmp_path: Path) -> None:
    path = tmp_path / "low.wav"
    sf.write(path, _tone(4000, 4.0, hz=300.0), 4000)
    with pytest.raises(AudioError) as err:
        load_audio(path)
    assert err.value.code == "audio_unsupported_rate"


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(AudioError) as err:
        load_audio(tmp_path / "nope.wav")
    assert err.value.code == "audio_not_found"


def test_non_music_clips_decode(nonmusic_dir: Path) -> None:
    """Speech and whale song are ordinary audio for the decoder; the short robin is too short."""
    for path in sorted(nonmusic_dir.glob("*.ogg")):
        info = audio_info(path)
        if info.duration_s is not None and info.duration_s < 3.0:
            with pytest.raises(AudioError) as err:
                load_audio(path)
            assert err.value.code == "audio_too_short"
        else:
            y, sr = load_audio(path, sr=22050)
            assert len(y) > 3 * sr
