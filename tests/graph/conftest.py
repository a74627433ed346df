"""Graph-test fixtures: bars from the project's own demo generator, built into small graphs."""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.graph.artifact import graph_from_arrays
from dancegraph.graph.build import BarSet, BuildParams, build_arrays
from dancegraph.motion.demo import DEMO_CLIPS, make_clip


def demo_barset(seed: int = 0) -> BarSet:
    """Every bar of the demo clips (generated, exact beats and signatures) as a ``BarSet``."""
    rng = np.random.default_rng(seed)
    clips, takes = [], []
    for recipe in DEMO_CLIPS:
        motion, bars, sigs = make_clip(recipe, rng)
        clips.append(recipe.id)
        beats = np.array(bars, dtype=float)
        frames = np.round(beats[:, [0, 4]] * motion.fps).astype(np.int64)
        takes.append((motion, beats, np.arange(len(bars)), list(sigs), frames))
    bars = BarSet.from_takes(
        motion.skeleton,
        clips,
        takes,
        {cid: [f"style:{r.style}"] for cid, r in zip(clips, DEMO_CLIPS, strict=True)},
    )
    bars.grid_from_motion = False  # annotated, as the demo library is imported: no anchoring
    return bars


@pytest.fixture(scope="session")
def demo_bars() -> BarSet:
    return demo_barset()


@pytest.fixture(scope="session")
def demo_build(demo_bars):
    """``(arrays, node_ids, manifest)`` of the demo bars with default parameters."""
    return build_arrays(demo_bars, BuildParams())


@pytest.fixture(scope="session")
def demo_graph(demo_build):
    arrays, ids, manifest = demo_build
    manifest = dict(manifest, name="demo", version="test")
    g = graph_from_arrays(arrays, manifest)
    g.node_ids[:] = ids
    g._index = {n: i for i, n in enumerate(ids)}
    return g


def synthetic_analysis(
    phrases: str = "AABA",
    bars_per_phrase: int = 4,
    tempo: float = 110.0,
    seed: int = 0,
    meter_ids=(0, 1, 0, 2),
):
    """A ``MusicAnalysis`` with a known phrase structure: ``phrases`` names the phrase label of
    each occurrence (e.g. "AABA"); within a phrase, bar i gets meter id ``meter_ids[i % len]``
    (equal ids in one occurrence → the mirror rule applies). Onset/RMS curves repeat with the
    phrase label so repeated phrases sound alike."""
    from dancegraph.music.analysis import MusicAnalysis

    rng = np.random.default_rng(seed)
    bar_s = 240.0 / tempo
    n = len(phrases) * bars_per_phrase
    starts = np.arange(n) * bar_s
    bars = np.stack([starts, starts + bar_s], axis=1)
    bar_beats = starts[:, None] + np.arange(5)[None, :] * bar_s / 4
    label_curve = {lab: rng.random((bars_per_phrase, 2, 200)) for lab in sorted(set(phrases))}
    tags, phr, onset = [], [], []
    seen: dict[str, int] = {}
    for p, lab in enumerate(phrases):
        occ = seen.get(lab, 0)
        seen[lab] = occ + 1
        phr.append(
            {
                "label": lab,
                "occurrence": occ,
                "start_bar": p * bars_per_phrase,
                "end_bar": (p + 1) * bars_per_phrase,
            }
        )
        for i in range(bars_per_phrase):
            tags.append(
                {
                    "label": lab,
                    "occurrence": occ,
                    "index": i,
                    "meter_id": int(meter_ids[i % len(meter_ids)]),
                }
            )
            onset.append(label_curve[lab][i])
    scores = rng.random((n, 13))
    beats = bar_beats[:, :4].reshape(-1)
    return MusicAnalysis(
        duration_s=float(n * bar_s),
        tempo_bpm=tempo,
        tempo_confidence=1.0,
        meter=4,
        beats=beats,
        beat_positions=np.tile([1, 2, 3, 4], n),
        downbeats=starts,
        bars=bars,
        bar_beats=bar_beats,
        phrases=phr,
        tags=tags,
        signature_scores=scores,
        signature_topk=np.argsort(-scores, axis=1)[:, :3],
        bar_onset_rms=np.stack(onset),
        method="synthetic",
    )
