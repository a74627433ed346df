"""Descriptor style embedding: shared, interpretable descriptors for music and dance bars."""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.embed import descriptor


def _music_bar(tempo: float, loud: float = 1.0, offbeat: bool = False) -> tuple[float, np.ndarray]:
    s = 200
    onset = np.zeros(s)
    slots = range(1, 8, 2) if offbeat else range(0, 8, 2)
    for slot in slots:
        onset[int(slot * s / 8)] = 1.0
    rms = loud * (0.5 + 0.1 * np.sin(np.linspace(0, 8 * np.pi, s)) ** 2)
    return 240.0 / tempo, np.stack([onset * loud, rms])


def test_version_and_shapes():
    assert descriptor.VERSION == "descriptor-v1"
    d, x = _music_bar(120)
    z = descriptor.embed_music(np.array([d, d]), np.stack([x, x]))
    assert z.shape == (2, descriptor.DIM) and z.dtype == np.float32


def test_projection_preserves_distances():
    q = descriptor.PROJECTION
    assert np.allclose(q.T @ q, np.eye(len(descriptor.NAMES)), atol=1e-9)
    raw = np.random.default_rng(0).normal(size=(5, 8))
    z = descriptor.embed(raw, {"mean": [0.0] * 8, "std": [1.0] * 8})
    std = np.clip(raw.copy(), -4, 4)
    std[:, 0] = np.clip(raw[:, 0] / 0.35, -4, 4)
    std *= descriptor.WEIGHTS
    assert np.allclose(np.linalg.norm(z[0] - z[1]), np.linalg.norm(std[0] - std[1]), rtol=1e-4)


def test_music_descriptors_read_tempo_loudness_and_syncopation():
    bars = [
        _music_bar(90),
        _music_bar(150),
        _music_bar(120, loud=4.0),
        _music_bar(120, offbeat=True),
    ]
    raw = descriptor.music_descriptors(
        np.array([b[0] for b in bars]), np.stack([b[1] for b in bars])
    )
    names = descriptor.NAMES
    assert raw[1, names.index("tempo")] > raw[0, names.index("tempo")]
    assert raw[2, names.index("energy")] > raw[0, names.index("energy")]
    assert raw[3, names.index("syncopation")] > raw[0, names.index("syncopation")] + 0.5


def _dance_bar(speed: float, dur: float, n: int = 48) -> np.ndarray:
    t = np.linspace(0, dur, n, endpoint=False)
    pos = np.zeros((n, 3, 3))
    for j in range(3):
        pos[:, j, 0] = speed * dur / (2 * np.pi) * np.sin(2 * np.pi * t / dur * 2 + j)
        pos[:, j, 1] = 1.0 + 0.2 * j
    return pos


def test_dance_descriptors_read_speed_and_tempo():
    raw = descriptor.dance_descriptors(
        np.stack([_dance_bar(0.5, 2.0), _dance_bar(2.0, 2.0), _dance_bar(0.5, 1.5)]),
        np.array([2.0, 2.0, 1.5]),
    )
    names = descriptor.NAMES
    assert raw[1, names.index("energy")] > raw[0, names.index("energy")] + 1.0
    assert raw[2, names.index("tempo")] > raw[0, names.index("tempo")]


def test_tempo_is_shared_between_modalities():
    # a dance bar at 120 BPM is closer to a 120 BPM music bar than to a 75 BPM one
    dance = descriptor.embed_dance(np.stack([_dance_bar(1.0, 2.0)] * 2), np.array([2.0, 2.0]))
    m = [_music_bar(120), _music_bar(75)]
    music = descriptor.embed_music(np.array([b[0] for b in m]), np.stack([b[1] for b in m]))
    d = np.linalg.norm(music - dance[0], axis=1)
    assert d[0] < d[1]


def test_bad_shape_is_rejected():
    with pytest.raises(ValueError, match="bar_onset_rms"):
        descriptor.music_descriptors(np.array([2.0]), np.zeros((1, 200)))
