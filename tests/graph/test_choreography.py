"""Choreography level: motifs, motif signatures, chi-square, and the search terms built on them."""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.graph import choreography
from dancegraph.graph.search import search
from dancegraph.spec import Spec

from .conftest import synthetic_analysis


def test_chi_square_and_signatures():
    a = np.array([0.5, 0.5, 0.0])
    assert choreography.chi_square(a, a) == 0.0
    assert choreography.chi_square(np.array([1.0, 0.0]), np.array([0.0, 1.0])) == pytest.approx(1.0)
    assert choreography.chi_square(a, np.array([0.25, 0.75, 0.0])) == pytest.approx(
        0.5 * (0.0625 / 0.75 + 0.0625 / 1.25)
    )
    sig = choreography.motif_signature(np.array([0, 0, 2, 1]), 4)
    assert np.allclose(sig, [0.5, 0.25, 0.25, 0.0])
    m = choreography.transition_matrix([np.array([0, 1, 0, 1, 1])], 3)
    assert (
        np.allclose(m[0], [0, 1, 0]) and np.allclose(m[1], [0.5, 0.5, 0]) and np.allclose(m[2], 0)
    )


def test_motif_plan_follows_the_target():
    cost = np.array([[0.0, 1.0], [0.0, 2.0], [0.0, 5.0], [0.0, np.inf]])
    plan = choreography.plan_motifs(cost, np.array([1, 1, 1, 1]), np.array([0.5, 0.5]))
    # two bars take motif 1: the two with the smallest regret that can have it
    assert plan.tolist() == [1, 1, 0, 0]
    plan = choreography.plan_motifs(cost, np.array([1, 1, 1, 1]), np.array([1.0, 0.0]))
    assert plan.tolist() == [0, 0, 0, 0]


def test_graph_motifs(demo_graph):
    mot = demo_graph.manifest["motifs"]
    k = mot["k"]
    labels = np.asarray(demo_graph.motif)
    assert labels.min() >= 0 and labels.max() < k and k >= 2
    assert sum(mot["signature"]) == pytest.approx(1.0)
    assert len(set(labels[np.asarray(demo_graph.node_kind) == 0].tolist())) == k  # every motif used
    tm = np.array(mot["transitions"])
    assert tm.shape == (k, k) and np.allclose(tm.sum(axis=1)[tm.sum(axis=1) > 0], 1.0)
    seq = choreography.take_motif_sequence(demo_graph, "pop_90")
    assert len(seq) == 8
    # motifs group similar words: bars of one style share motifs more than bars across styles
    kinds = np.asarray(demo_graph.node_kind)
    clips = np.asarray(demo_graph.node_clip)[kinds == 0]
    style = np.array([demo_graph.clips[c].split("_")[0] for c in clips])
    lab = labels[kinds == 0]
    same = np.mean(
        [
            lab[i] == lab[j]
            for i in range(len(lab))
            for j in range(i + 1, len(lab))
            if style[i] == style[j]
        ]
    )
    diff = np.mean(
        [
            lab[i] == lab[j]
            for i in range(len(lab))
            for j in range(i + 1, len(lab))
            if style[i] != style[j]
        ]
    )
    assert same > diff


@pytest.fixture(scope="module")
def song():
    return synthetic_analysis("ABCD", bars_per_phrase=4, meter_ids=(0, 1, 2, 3))


def test_motif_pins_are_honoured(demo_graph, song):
    free = search(demo_graph, song, Spec(alternatives=1)).alternatives[0]
    labels = np.asarray(demo_graph.motif)
    want = int(
        next(m for m in range(demo_graph.manifest["motifs"]["k"]) if m != labels[free.index[5]])
    )
    r = search(
        demo_graph,
        song,
        Spec.model_validate(
            {"alternatives": 2, "motifs": [{"bar": 5, "motif": want}, {"bar": 0, "motif": want}]}
        ),
    )
    for alt in r.alternatives:
        assert labels[alt.index[5]] == want and labels[alt.index[0]] == want


def test_following_a_signature_lowers_its_distance(demo_graph, song):
    target = "step_100"
    free = search(
        demo_graph,
        song,
        Spec.model_validate({"alternatives": 1, "signature": {"target": target, "weight": 0.0}}),
    ).alternatives[0]
    led = search(
        demo_graph,
        song,
        Spec.model_validate({"alternatives": 1, "signature": {"target": target, "weight": 5.0}}),
    ).alternatives[0]
    assert led.choreography["target"] == target
    assert led.choreography["signature_chi2"] < free.choreography["signature_chi2"]
    d = search(
        demo_graph,
        song,
        Spec.model_validate({"alternatives": 1, "signature": {"target": "dataset"}}),
    ).alternatives[0]
    assert 0.0 <= d.choreography["signature_chi2"] <= 1.0


def test_recreating_a_take_matches_its_motif_sequence(demo_graph, song):
    free = search(demo_graph, song, Spec(alternatives=1)).alternatives[0]
    seq = np.resize(choreography.take_motif_sequence(demo_graph, "pop_120"), song.n_bars)
    free_match = float(np.mean(np.asarray(demo_graph.motif)[free.index] == seq))
    alt = search(
        demo_graph, song, Spec.model_validate({"alternatives": 1, "recreate": "pop_120"})
    ).alternatives[0]
    assert alt.choreography["recreate_match"] > free_match
    assert alt.choreography["recreate_match"] >= 0.75
