"""BeatNet's offline beat/downbeat activation network, reimplemented in the project's own code.

The model (``BDA``) and its input features follow BeatNet 1.1.3 (M. Heydari, F. Cwitkowitz,
Z. Duan, "BeatNet: CRNN and particle filtering for online joint beat downbeat and meter
tracking", ISMIR 2021; weights CC BY 4.0, see :mod:`dancegraph.music.weights`). Neither BeatNet
nor madmom is imported: the features are madmom's signal chain rewritten in numpy.

Features, 272 per 20 ms frame (50 fps) at 22,050 Hz:
  frames of 1411 samples (64 ms) centred on ``i * 441`` (zero padded), Hann window, |FFT| of the
  first 705 bins, a logarithmic triangular filterbank (24 bands per octave, 30 Hz - 17 kHz,
  A4 = 440 Hz reference, filters normalised to unit sum, duplicate bins merged: 136 bands),
  ``log10(1 + x)``, then the positive first difference over one frame stacked beside it.

Model: per frame Conv1d(1 -> 2, k = 10) over the 272 values, ReLU, max-pool 2, linear 262 -> 150,
a 2-layer unidirectional LSTM (150 cells) over time from a zero state, linear 150 -> 3.
Output classes in the model's own order: beat, downbeat, none (softmax over the three).
"""

from __future__ import annotations

import threading

import numpy as np
import torch
from torch import nn

from dancegraph.errors import ModelFileError
from dancegraph.music.weights import ATTRIBUTION, weight_path

SR = 22_050
WIN = 1411  # int(0.064 * 22050)
HOP = 441  # int(0.020 * 22050)
FPS = SR / HOP  # 50.0 frames per second
N_BINS = WIN >> 1  # 705 FFT bins, Nyquist excluded (as madmom)
BANDS_PER_OCTAVE = 24
FMIN, FMAX, FREF = 30.0, 17_000.0, 440.0
N_FEATURES = 272

__all__ = [
    "ATTRIBUTION",
    "BDA",
    "FPS",
    "SR",
    "activations",
    "beatnet_features",
    "load_model",
    "log_filterbank",
]


def log_filterbank() -> np.ndarray:
    """madmom's LogarithmicFilterbank for BeatNet: (705, 136) float32, columns sum to 1."""
    # madmom labels the bins as if the FFT had 2 * 705 points (not 1411): keep its labels
    bin_freqs = np.fft.fftfreq(2 * N_BINS, 1.0 / SR)[:N_BINS]
    left = np.floor(np.log2(FMIN / FREF) * BANDS_PER_OCTAVE)
    right = np.ceil(np.log2(FMAX / FREF) * BANDS_PER_OCTAVE)
    freqs = FREF * 2.0 ** (np.arange(left, right) / BANDS_PER_OCTAVE)
    freqs = freqs[np.searchsorted(freqs, FMIN) :]
    freqs = freqs[: np.searchsorted(freqs, FMAX, "right")]
    # nearest FFT bin of each frequency, duplicates merged
    idx = np.clip(bin_freqs.searchsorted(freqs), 1, len(bin_freqs) - 1)
    idx = idx - (freqs - bin_freqs[idx - 1] < bin_freqs[idx] - freqs)
    bins = np.unique(idx)
    fb = np.zeros((N_BINS, len(bins) - 2), dtype=np.float32)
    for band in range(len(bins) - 2):
        start, center, stop = (int(b) for b in bins[band : band + 3])
        if stop - start < 2:  # a filter too small for a triangle: one bin
            center, stop = start, start + 1
        c, s = center - start, stop - start
        tri = np.zeros(s, dtype=np.float32)
        tri[:c] = np.linspace(0, 1, c, endpoint=False)
        tri[c:] = np.linspace(1, 0, s - c, endpoint=False)
        tri /= tri.sum()
        stop = min(stop, N_BINS)
        fb[start:stop, band] = tri[: stop - start]
    return fb


_FB = log_filterbank()
_WINDOW = np.hanning(WIN)


def beatnet_features(y: np.ndarray, *, chunk_frames: int = 2048) -> np.ndarray:
    """BeatNet's input features of mono audio at 22,050 Hz.

    Args:
        y: (N,) float samples at :data:`SR` Hz.
        chunk_frames: frames per FFT batch (bounds memory for long songs).

    Returns:
        (ceil(N / 441), 272) float32: 136 log filterbank bands, then their positive difference.
    """
    y = np.asarray(y, dtype=np.float32)
    if y.ndim != 1:
        raise ValueError(f"beatnet_features needs mono audio (N,), got shape {y.shape}")
    n_frames = int(np.ceil(len(y) / HOP))
    half = WIN // 2
    # zero padding so that frame i spans samples [i*HOP - half, i*HOP - half + WIN)
    padded = np.zeros(n_frames * HOP + WIN, dtype=np.float32)
    padded[half : half + len(y)] = y
    spec = np.empty((n_frames, _FB.shape[1]), dtype=np.float32)
    frames_all = np.lib.stride_tricks.sliding_window_view(padded, WIN)[::HOP]
    for a in range(0, n_frames, chunk_frames):
        b = min(a + chunk_frames, n_frames)
        stft = np.fft.rfft(frames_all[a:b] * _WINDOW, axis=1)[:, :N_BINS]
        mag = np.abs(stft.astype(np.complex64))
        spec[a:b] = mag @ _FB
    np.log10(spec + 1.0, out=spec)
    diff = np.zeros_like(spec)
    diff[1:] = np.maximum(spec[1:] - spec[:-1], 0.0)
    return np.hstack([spec, diff])


class BDA(nn.Module):
    """BeatNet's beat/downbeat activation CRNN (parameter names as in the released weights)."""

    def __init__(self, dim_in: int = N_FEATURES, num_cells: int = 150, num_layers: int = 2):
        super().__init__()
        self.dim_in = dim_in
        self.conv1 = nn.Conv1d(1, 2, 10)
        self.linear0 = nn.Linear(2 * ((dim_in - 10 + 1) // 2), 150)
        self.lstm = nn.LSTM(150, num_cells, num_layers=num_layers, batch_first=True)
        self.linear = nn.Linear(num_cells, 3)

    def forward(
        self, feats: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """(B, T, 272) features -> ((B, T, 3) logits (beat, downbeat, none), LSTM state).

        ``state`` (h, c), each (2, B, 150), continues a previous chunk; None = zero state.
        """
        b, t, d = feats.shape
        x = feats.reshape(b * t, 1, d)
        x = nn.functional.max_pool1d(nn.functional.relu(self.conv1(x)), 2)
        x = self.linear0(x.reshape(b * t, -1)).reshape(b, t, -1)
        x, state = self.lstm(x, state)
        return self.linear(x), state


_MODELS: dict[int, BDA] = {}
_LOCK = threading.Lock()


def load_model(model: int = 1) -> BDA:
    """BeatNet model ``model`` (1, 2 or 3) in eval mode, loaded once per process.

    Raises ModelFileError (code ``model_missing``) when the weights were not installed, or
    ``model_file_invalid`` when the file does not load.
    """
    with _LOCK:
        if model in _MODELS:
            return _MODELS[model]
        path = weight_path(model)
        if not path.is_file():
            raise ModelFileError(
                f"BeatNet weights {path.name} are not installed in {path.parent}; run "
                "`python -m dancegraph.music.weights fetch` at install time",
                code="model_missing",
                field=path.name,
            )
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            net = BDA()
            net.load_state_dict(state, strict=True)
        except Exception as exc:
            raise ModelFileError(
                f"{path.name}: not a BeatNet state dict ({type(exc).__name__})", field=path.name
            ) from exc
        net.eval()
        _MODELS[model] = net
        return net


def logits(feats: np.ndarray, model: int = 1, *, chunk_frames: int = 3000) -> np.ndarray:
    """(T, 272) features -> (T, 3) logits of model ``model`` (beat, downbeat, none).

    The song runs through the LSTM in one pass from a zero state, fed ``chunk_frames`` at a
    time with the state carried over (same result, memory bounded: torch's LSTM would otherwise
    hold ~15 kB per frame, 650 MB for 15 minutes).
    """
    net = load_model(model)
    x = torch.from_numpy(np.ascontiguousarray(feats, dtype=np.float32))
    out = np.empty((len(feats), 3), dtype=np.float32)
    # the LSTM steps through time with 150-wide matrices: extra intra-op threads only spin
    # (7-10x more CPU on a busy machine), so run it on one thread and restore the setting
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        with torch.inference_mode():
            state = None
            for a in range(0, len(feats), chunk_frames):
                z, state = net(x[None, a : a + chunk_frames], state)
                out[a : a + chunk_frames] = z[0].numpy()
    finally:
        torch.set_num_threads(threads)
    return out


def activations(y: np.ndarray, models: tuple[int, ...] = (1,)) -> np.ndarray:
    """Beat and downbeat activations of mono 22,050 Hz audio, averaged over ``models``.

    Returns:
        (T, 2) float32 at :data:`FPS` frames per second: column 0 = P(beat, not downbeat),
        column 1 = P(downbeat) — the input of the bar-pointer decoder.
    """
    feats = beatnet_features(y)
    acc = np.zeros((len(feats), 2), dtype=np.float64)
    for m in models:
        z = logits(feats, m).astype(np.float64)
        z -= z.max(axis=1, keepdims=True)
        p = np.exp(z)
        p /= p.sum(axis=1, keepdims=True)
        acc += p[:, :2]
    return (acc / len(models)).astype(np.float32)
