"""Sound for the generated songs (:mod:`dancegraph.music.generator`): drum and pitched
instruments as waveforms, and the buffer notes land in at beat positions. Units: seconds, Hz,
MIDI note numbers; waveforms float64 mono at ``sr`` Hz, each starting at its onset.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Renderer", "hat", "kick", "midi_hz", "snare", "tone"]


def midi_hz(m: float) -> float:
    return 440.0 * 2.0 ** ((m - 69) / 12)


def kick(sr: int) -> np.ndarray:
    t = np.arange(int(0.35 * sr)) / sr
    f = 48 + 110 * np.exp(-t * 35)
    return np.sin(2 * np.pi * np.cumsum(f) / sr) * np.exp(-t * 9)


def snare(sr: int, rng: np.random.Generator) -> np.ndarray:
    t = np.arange(int(0.2 * sr)) / sr
    noise = np.diff(rng.standard_normal(len(t) + 1))  # first difference: a bright noise
    return 0.45 * noise * np.exp(-t * 22) + 0.6 * np.sin(2 * np.pi * 190 * t) * np.exp(-t * 30)


def hat(sr: int, rng: np.random.Generator) -> np.ndarray:
    t = np.arange(int(0.06 * sr)) / sr
    noise = np.diff(rng.standard_normal(len(t) + 2), n=2)
    return 0.25 * noise * np.exp(-t * 70)


def tone(sr: int, hz: float, dur: float, kind: str) -> np.ndarray:
    """A pitched note of ``dur`` seconds: ``kind`` picks the timbre and the envelope."""
    n = max(int(dur * sr), 16)
    t = np.arange(n) / sr
    if kind == "sine_bass":
        w = np.sin(2 * np.pi * hz * t) + 0.25 * np.sin(4 * np.pi * hz * t)
        env = np.exp(-t * 2.5)
    elif kind == "saw_bass":
        w = sum((np.sin(2 * np.pi * hz * k * t) / k for k in range(1, 7)), np.zeros(n))
        env = np.exp(-t * 4)
    elif kind == "pad":
        w = sum((np.sin(2 * np.pi * hz * k * t) / k**1.5 for k in range(1, 5)), np.zeros(n))
        env = np.minimum(t / 0.06, 1.0) * 0.8
    elif kind == "piano":
        w = sum(
            (np.sin(2 * np.pi * hz * k * t) * np.exp(-t * k * 1.5) / k for k in range(1, 6)),
            np.zeros(n),
        )
        env = np.exp(-t * 3)
    elif kind == "organ":
        w = (
            np.sin(2 * np.pi * hz * t)
            + 0.5 * np.sin(4 * np.pi * hz * t)
            + 0.3 * np.sin(6 * np.pi * hz * t)
        )
        env = np.minimum(t / 0.01, 1.0) * 0.6
    elif kind == "square_lead":
        w = sum((np.sin(2 * np.pi * hz * k * t) / k for k in (1, 3, 5, 7)), np.zeros(n))
        env = np.minimum(t / 0.008, 1.0) * np.exp(-t * 2)
    elif kind == "pluck_lead":
        w = sum((np.sin(2 * np.pi * hz * k * t) / k**2 for k in range(1, 5)), np.zeros(n))
        env = np.exp(-t * 8)
    else:
        raise ValueError(f"unknown instrument {kind!r}")
    rel = min(n, int(0.015 * sr))  # short release: no clicks at note ends
    env = env * np.ones(n)
    env[-rel:] *= np.linspace(1.0, 0.0, rel)
    return w * env


class Renderer:
    """The audio buffer of one song and how notes land in it: global beat positions (0 = the
    first downbeat, offbeat eighths swung) to seconds on the song's beat ``times``."""

    def __init__(
        self,
        sr: int,
        times: np.ndarray,
        pickup_beats: int,
        swing: float,
        rng: np.random.Generator,
    ):
        """``times`` (n_beats + 1,) s: every beat's onset and the song's end; ``pickup_beats``
        before the first downbeat; offbeat eighths delayed by ``swing`` beat; the drums' noise
        drawn from ``rng``."""
        self.sr, self.times, self.n_beats = sr, times, len(times) - 1
        self.pickup_beats, self.swing = pickup_beats, swing
        self.y = np.zeros(int((times[-1] + 1.5) * sr) + 1)  # 1.5 s tail after the last beat
        self.kick, self.snare, self.hat = kick(sr), snare(sr, rng), hat(sr, rng)
        self._samples: dict[tuple, np.ndarray] = {}

    def t_of(self, beat: float) -> float:
        """Global beat position (0 = first downbeat) → seconds, with swing on offbeat eighths."""
        frac = beat - np.floor(beat)
        if abs(frac - 0.5) < 1e-6:
            beat = beat + self.swing
        pos = beat + self.pickup_beats
        times, n = self.times, self.n_beats
        right = times[-1] + (pos - n) * (times[-1] - times[-2])
        return float(np.interp(pos, np.arange(n + 1), times, right=right))

    def add(self, wave: np.ndarray, t: float, gain: float) -> None:
        """``wave`` times ``gain`` into the buffer from ``t`` s (cut at its end)."""
        i = int(round(t * self.sr))
        if i < 0 or i >= len(self.y):
            return
        j = min(len(self.y), i + len(wave))
        self.y[i:j] += gain * wave[: j - i]

    def note(self, kind: str, midi: float, beat: float, dur_beats: float, gain: float) -> None:
        """A ``kind`` note of MIDI pitch ``midi`` from global ``beat`` for ``dur_beats``."""
        t0, t1 = self.t_of(beat), self.t_of(beat + dur_beats)
        key = (kind, round(midi, 2), round(t1 - t0, 2))
        if key not in self._samples:
            self._samples[key] = tone(self.sr, midi_hz(midi), t1 - t0, kind)
        self.add(self._samples[key], t0, gain)
