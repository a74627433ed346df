"""Decode audio files to float32 arrays, with bounded memory and specific error codes.

Decoders, in order: libsndfile through ``soundfile`` (WAV, FLAC, OGG/Vorbis/Opus, MP3, AIFF, ...),
then FFmpeg through PyAV (``av``) for every other container and codec it knows (AAC/M4A, WMA,
...). Any sample rate from 8 to 192 kHz, any channel count. The duration is read from the header
before anything is decoded, so a 2-hour upload is refused in milliseconds; where the header does
not tell (some streams), decoding stops as soon as the limit is passed. Resampling is streamed
(soxr, the same "HQ" filter as ``librosa.load``), so memory stays proportional to the output.

Error codes (all ``AudioError``, ``field`` = the file name):
``audio_not_found``, ``audio_empty`` (no bytes or no samples), ``audio_undecodable`` (not an
audio file, corrupted), ``audio_unsupported_codec`` (a container whose audio codec no decoder
knows), ``audio_unsupported_rate`` (sample rate outside 8-192 kHz), ``audio_too_short``,
``audio_too_long``.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import soundfile as sf
import soxr

from dancegraph.errors import AudioError

DEFAULT_MAX_SECONDS = 20 * 60.0  # a 15-minute song works; a 2-hour upload is refused
DEFAULT_MIN_SECONDS = 3.0  # below this no tempo or bar can be estimated
MIN_RATE = 8_000
MAX_RATE = 192_000
_BLOCK = 1 << 16  # frames per decode block

__all__ = [
    "DEFAULT_MAX_SECONDS",
    "DEFAULT_MIN_SECONDS",
    "AudioInfo",
    "audio_info",
    "load_audio",
    "resample",
]


class AudioInfo:
    """What the header says: sample rate (Hz), channels, duration (s, None if unknown), decoder."""

    def __init__(self, sr: int, channels: int, duration_s: float | None, decoder: str):
        self.sr = int(sr)
        self.channels = int(channels)
        self.duration_s = duration_s
        self.decoder = decoder

    def __repr__(self) -> str:
        return (
            f"AudioInfo(sr={self.sr}, channels={self.channels}, "
            f"duration_s={self.duration_s}, decoder={self.decoder!r})"
        )


def resample(y: np.ndarray, orig_sr: int, target_sr: int) -> np.ndarray:
    """Resample ``y`` ((N,) or (C, N) float) from ``orig_sr`` to ``target_sr`` Hz (soxr HQ).

    The same filter as ``librosa.load(..., sr=target_sr)`` uses, so results match it exactly.
    """
    y = np.asarray(y, dtype=np.float32)
    if int(orig_sr) == int(target_sr):
        return y
    if y.ndim == 1:
        return soxr.resample(y, orig_sr, target_sr, quality="soxr_hq").astype(np.float32)
    return soxr.resample(y.T, orig_sr, target_sr, quality="soxr_hq").T.astype(np.float32)


def _err(code: str, message: str, path: Path) -> AudioError:
    return AudioError(f"{path.name}: {message}", code=code, field=path.name)


def _why(exc: Exception, path: Path) -> str:
    """The decoder's own words, without the server-side folder."""
    return str(exc).replace(str(path), path.name) or type(exc).__name__


def _check_rate(sr: int, path: Path) -> None:
    if not MIN_RATE <= sr <= MAX_RATE:
        raise _err(
            "audio_unsupported_rate",
            f"sample rate {sr} Hz is outside {MIN_RATE}-{MAX_RATE} Hz",
            path,
        )


def _sf_info(path: Path) -> AudioInfo | None:
    try:
        info = sf.info(str(path))
    except Exception:  # libsndfile does not know this file: let FFmpeg try
        return None
    duration = info.frames / info.samplerate if info.frames > 0 and info.samplerate > 0 else None
    return AudioInfo(info.samplerate, info.channels, duration, "soundfile")


def _av_info(path: Path) -> AudioInfo:
    import av

    try:
        with av.open(str(path)) as container:
            streams = container.streams.audio
            if not streams:
                raise _err("audio_undecodable", "the file holds no audio stream", path)
            stream = streams[0]
            codec = stream.codec_context
            if codec is None or codec.name in (None, "", "none"):
                raise _err("audio_unsupported_codec", "unknown audio codec", path)
            sr = int(codec.sample_rate or stream.rate or 0)
            channels = int(codec.channels or 0)
            duration = None
            if stream.duration is not None and stream.time_base is not None:
                duration = float(stream.duration * stream.time_base)
            elif container.duration is not None:
                duration = container.duration / 1_000_000.0
    except AudioError:
        raise
    except av.error.DecoderNotFoundError as exc:
        raise _err(
            "audio_unsupported_codec", f"no decoder for this codec ({_why(exc, path)})", path
        ) from exc
    except Exception as exc:  # FFmpeg cannot parse it either
        raise _err(
            "audio_undecodable", f"not a readable audio file ({_why(exc, path)})", path
        ) from exc
    if sr <= 0:
        raise _err("audio_undecodable", "no sample rate in the header", path)
    return AudioInfo(sr, max(channels, 1), duration, "av")


def audio_info(path: str | os.PathLike) -> AudioInfo:
    """Read only the header of ``path``: sample rate, channels, duration (raises AudioError)."""
    p = Path(path)
    if not p.is_file():
        raise _err("audio_not_found", "no such file", p)
    if p.stat().st_size == 0:
        raise _err("audio_empty", "the file is empty (0 bytes)", p)
    return _sf_info(p) or _av_info(p)


def _sf_blocks(path: Path) -> Iterator[np.ndarray]:
    """(n, C) float32 blocks from libsndfile."""
    with sf.SoundFile(str(path)) as f:
        while True:
            block = f.read(_BLOCK, dtype="float32", always_2d=True)
            if len(block) == 0:
                return
            yield block


def _av_blocks(path: Path, channels: int) -> Iterator[np.ndarray]:
    """(n, C) float32 blocks decoded by FFmpeg (packed float, native rate and layout)."""
    import av

    try:
        with av.open(str(path)) as container:
            stream = container.streams.audio[0]
            layout = stream.layout.name if stream.layout is not None else None
            resampler = av.AudioResampler(format="flt", layout=layout, rate=stream.rate)
            for frame in container.decode(stream):
                for out in resampler.resample(frame):
                    yield out.to_ndarray().reshape(-1, channels).astype(np.float32, copy=False)
            for out in resampler.resample(None):
                yield out.to_ndarray().reshape(-1, channels).astype(np.float32, copy=False)
    except av.error.DecoderNotFoundError as exc:
        raise _err(
            "audio_unsupported_codec", f"no decoder for this codec ({_why(exc, path)})", path
        ) from exc
    except av.error.FFmpegError as exc:
        raise _err("audio_undecodable", f"decoding failed ({_why(exc, path)})", path) from exc


def _decoded_chunks(
    p: Path, info: AudioInfo, out_sr: int, mono: bool, max_seconds: float | None
) -> tuple[list[np.ndarray], int]:
    """The file decoded block by block (mixed to mono, resampled to ``out_sr`` as it streams):
    (float32 chunks, (n,) or (n, C), and the number of input frames). Raises ``AudioError``
    (``audio_too_long`` past ``max_seconds``, ``audio_undecodable`` for a corrupted body)."""
    n_out_ch = 1 if mono else info.channels
    stream = (
        soxr.ResampleStream(info.sr, out_sr, n_out_ch, dtype="float32", quality="HQ")
        if out_sr != info.sr
        else None
    )
    max_in = None if max_seconds is None else int(max_seconds * info.sr) + _BLOCK
    blocks = _sf_blocks(p) if info.decoder == "soundfile" else _av_blocks(p, info.channels)
    chunks: list[np.ndarray] = []
    n_in = 0
    try:
        for block in blocks:
            n_in += len(block)
            if max_in is not None and max_seconds is not None and n_in > max_in:
                raise _err(
                    "audio_too_long",
                    f"longer than the limit of {max_seconds / 60:.1f} min",
                    p,
                )
            x = block.mean(axis=1, dtype=np.float32) if mono else block
            if stream is not None:
                x = stream.resample_chunk(x if mono else np.ascontiguousarray(x))
            chunks.append(np.asarray(x, dtype=np.float32))
    except AudioError:
        raise
    except Exception as exc:  # a decoder failing mid-file: a corrupted body
        raise _err("audio_undecodable", f"decoding failed ({_why(exc, p)})", p) from exc
    if stream is not None:
        tail = np.zeros((0,) if mono else (0, n_out_ch), dtype=np.float32)
        chunks.append(np.asarray(stream.resample_chunk(tail, last=True), dtype=np.float32))
    return chunks, n_in


def load_audio(
    path: str | os.PathLike,
    *,
    sr: int | None = None,
    mono: bool = True,
    max_seconds: float | None = DEFAULT_MAX_SECONDS,
    min_seconds: float | None = DEFAULT_MIN_SECONDS,
) -> tuple[np.ndarray, int]:
    """Decode an audio file.

    Args:
        path: the file (any container/codec soundfile or FFmpeg reads).
        sr: target sample rate in Hz, or None for the file's own rate.
        mono: average the channels (as ``librosa.load`` does) and return (N,); else (C, N).
        max_seconds: refuse longer audio (``audio_too_long``) before decoding; None = no limit.
        min_seconds: refuse shorter audio (``audio_too_short``); None = no limit.

    Returns:
        (y, sr): float32 samples in [-1, 1] (non-finite samples set to 0), (N,) if ``mono``
        else (C, N), and the sample rate in Hz.
    """
    p = Path(path)
    info = audio_info(p)
    _check_rate(info.sr, p)
    if max_seconds is not None and info.duration_s is not None and info.duration_s > max_seconds:
        raise _err(
            "audio_too_long",
            f"{info.duration_s / 60:.1f} min is longer than the limit of {max_seconds / 60:.1f} min",
            p,
        )
    out_sr = int(sr) if sr is not None else info.sr
    if not MIN_RATE // 2 <= out_sr <= MAX_RATE:
        raise AudioError(
            f"target sample rate {out_sr} Hz is not supported",
            code="audio_unsupported_rate",
            field="sr",
        )
    chunks, n_in = _decoded_chunks(p, info, out_sr, mono, max_seconds)
    if n_in == 0:
        raise _err("audio_empty", "no audio samples in the file", p)
    y = np.concatenate(chunks, axis=0)
    if not mono:
        y = np.ascontiguousarray(y.T)
    if not np.all(np.isfinite(y)):
        y = np.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0)
    duration = n_in / info.sr
    if min_seconds is not None and duration < min_seconds:
        raise _err(
            "audio_too_short",
            f"{duration:.2f} s is shorter than the minimum of {min_seconds:g} s",
            p,
        )
    return y, out_sr
