"""Phrases and structure tags, on generated songs with exact ground truth and on toy matrices."""

from __future__ import annotations

import numpy as np
import pytest

from dancegraph.music.features import frame_features
from dancegraph.music.generator import bar_grid, generate_song
from dancegraph.music.structure import (
    analyze_structure,
    checkerboard_novelty,
    label_segments,
    merge_alike_neighbours,
    merge_units,
    meter_ids,
    segment,
)


@pytest.fixture(scope="module")
def song_abab():
    """intro A B A B outro, 4-bar sections, 4/4 at 150 BPM (about 40 s)."""
    return generate_song(
        21,
        meter=4,
        tempo_bpm=150,
        form=["intro", "A", "B", "A", "B", "outro"],
        section_bars={"intro": 4, "A": 4, "B": 4, "outro": 4},
    )


def test_generated_song_boundaries_and_labels(song_abab):
    truth = song_abab.truth
    bars, _ = bar_grid(truth)
    st = analyze_structure(frame_features(song_abab.y, song_abab.sr), bars, unit=4)
    starts = [p["start_bar"] for p in st.phrases]
    assert starts == [s["start_bar"] for s in truth["sections"]]
    labels = [p["label"] for p in st.phrases]
    # A and B repeat: same labels at positions 1/3 and 2/4; intro, A, B, outro all distinct.
    assert labels[1] == labels[3] and labels[2] == labels[4]
    assert len({labels[0], labels[1], labels[2], labels[5]}) == 4
    assert labels[0] == "A"  # named in order of first appearance
    assert [p["occurrence"] for p in st.phrases][1:5] == [0, 0, 1, 1]
    # Tags: one per bar, index counts within the phrase.
    assert len(st.tags) == len(bars)
    assert [t["index"] for t in st.tags[4:8]] == [0, 1, 2, 3]
    assert st.tags[12]["label"] == st.tags[4]["label"] and st.tags[12]["occurrence"] == 1


def test_eight_bar_sections_are_not_split_in_half():
    song = generate_song(
        6, meter=4, tempo_bpm=130, form=["A", "B", "A", "B"], section_bars={"A": 8, "B": 8}
    )
    bars, _ = bar_grid(song.truth)
    st = analyze_structure(frame_features(song.y, song.sr), bars, unit=4)
    assert [p["start_bar"] for p in st.phrases] == [0, 8, 16, 24]


def test_back_to_back_repeats_of_a_four_bar_section_stay_apart():
    """intro A A B A B outro with 4-bar sections: A also stands alone, so the first two A's
    are two phrases with one label, not one 8-bar phrase; a unit that always comes doubled
    (A A B A A B) is still one 8-bar section."""
    form = ["intro", "A", "A", "B", "A", "B", "outro"]
    song = generate_song(0, meter=4, tempo_bpm=128, form=form, section_bars=dict.fromkeys(form, 4))
    bars, _ = bar_grid(song.truth)
    st = analyze_structure(frame_features(song.y, song.sr), bars, unit=4)
    assert [p["start_bar"] for p in st.phrases] == [s["start_bar"] for s in song.truth["sections"]]
    labels = [p["label"] for p in st.phrases]
    assert labels[1] == labels[2] == labels[4] and labels[3] == labels[5]
    assert [p["occurrence"] for p in st.phrases][1:3] == [0, 1]
    doubled = generate_song(
        0,
        meter=4,
        tempo_bpm=128,
        form=["A", "A", "B", "A", "A", "B"],
        section_bars={"A": 4, "B": 8},
    )
    bars, _ = bar_grid(doubled.truth)
    st = analyze_structure(frame_features(doubled.y, doubled.sr), bars, unit=4)
    assert [p["start_bar"] for p in st.phrases] == [0, 8, 16, 24]


def test_three_four_uses_three_bar_units():
    # 3/4: 4 measures = 3 four-beat bars; sections of 4 measures.
    song = generate_song(
        8, meter=3, tempo_bpm=160, form=["A", "B", "A", "B"], section_bars={"A": 4, "B": 4}
    )
    beats = np.asarray(song.truth["beats"])
    first = int(np.flatnonzero(np.asarray(song.truth["beat_positions"]) == 1)[0])
    b = np.concatenate([beats[first:], [song.truth["bars"][-1]["end_s"]]])
    grid = np.stack([b[i : i + 5] for i in range(0, len(b) - 4, 4)])
    st = analyze_structure(frame_features(song.y, song.sr), grid[:, [0, 4]], unit=3)
    assert [p["start_bar"] for p in st.phrases] == [0, 3, 6, 9]
    labels = [p["label"] for p in st.phrases]
    assert labels == ["A", "B", "A", "B"]


def test_meter_ids_group_identical_bars(song_abab):
    # A drum-and-bass loop: identical bars share an id within a phrase.
    ids = meter_ids(
        np.array([[0, 0.1, 1, 0.1], [0.1, 0, 1, 0.2], [1, 1, 0, 1], [0.1, 0.2, 1, 0]]), 0, 4
    )
    assert ids == [0, 0, 1, 0]
    truth = song_abab.truth
    bars, _ = bar_grid(truth)
    st = analyze_structure(frame_features(song_abab.y, song_abab.sr), bars, unit=4)
    for p in st.phrases:
        contents = [truth["bars"][i]["content"] for i in range(p["start_bar"], p["end_bar"])]
        ids = [st.tags[i]["meter_id"] for i in range(p["start_bar"], p["end_bar"])]
        assert ids[0] == 0
        # Bars with different chords never share an id.
        for i in range(len(ids)):
            for j in range(i):
                if ids[i] == ids[j]:
                    assert eval(contents[i])[1] == eval(contents[j])[1]


def test_segment_snaps_to_units_and_label_toy_matrix():
    nov = np.zeros(16)
    nov[[4, 7, 8, 12]] = [0.9, 0.5, 0.8, 1.0]  # a stronger boundary at 8 than at the odd 7
    assert segment(nov, unit=4) == [0, 4, 8, 12, 16]
    assert segment(np.zeros(10), unit=4) == [0, 10] or segment(np.zeros(10), unit=4)[-1] == 10
    # Block matrix: bars 0-3 and 8-11 alike, 4-7 different.
    d = np.ones((12, 12))
    for blk in ([0, 1, 2, 3, 8, 9, 10, 11], [4, 5, 6, 7]):
        d[np.ix_(blk, blk)] = 0.1
    assert label_segments(d, [0, 4, 8, 12]) == ["A", "B", "A"]
    nov_cb = checkerboard_novelty(d, half=2)
    assert int(np.argmax(nov_cb)) in (4, 8)
    # Fragments of one section join; two whole alike 4-bar phrases stay apart here.
    assert merge_alike_neighbours([0, 8, 10, 14, 15], ["A", "B", "B", "B"], 4) == [0, 8, 15]
    assert merge_alike_neighbours([0, 4, 8], ["A", "A"], 4) == [0, 4, 8]
    # Two alike 4-bar halves become one 8-bar phrase.
    assert merge_units([0, 4, 8, 12], ["A", "A", "B"], 4, np.ones(12)) == [0, 8, 12]


def test_empty_and_tiny_inputs(song_abab):
    ff = frame_features(song_abab.y[: song_abab.sr * 4], song_abab.sr)
    assert analyze_structure(ff, np.zeros((0, 2))).phrases == []
    st = analyze_structure(ff, np.array([[0.5, 2.0]]))
    assert st.phrases == [{"label": "A", "occurrence": 0, "start_bar": 0, "end_bar": 1}]
    assert st.tags == [{"label": "A", "occurrence": 0, "index": 0, "meter_id": 0}]
