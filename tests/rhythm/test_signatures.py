import numpy as np

from dancegraph.rhythm import signatures as sig


def test_common_signatures_have_the_downbeat():
    assert len(sig.COMMON_SIGNATURES) == 13
    assert all(bits[0] == 1 for bits in sig.COMMON_BITS)


def test_string_round_trip_and_slot_order():
    bits = sig.to_bits("00000101")
    assert bits.tolist() == [1, 0, 1, 0, 0, 0, 0, 0]  # downbeat and beat 2 (slot 2)
    assert sig.to_string(bits) == "00000101"


def test_weighted_hamming():
    assert sig.distance("00000001", "00000101") == 1.0  # regular slot differs
    assert sig.distance("01010101", "01010111") == 0.5  # half slot differs
    assert sig.distance("00000001", "11111111") == 3 * 1.0 + 4 * 0.5
    assert np.allclose(np.diag(sig.COMMON_DISTANCES), 0)


def test_scores_rank_the_true_signature_first():
    evidence = sig.COMMON_BITS.astype(float)
    top = sig.top_k(sig.scores_from_slot_evidence(evidence), k=3)
    assert (top[:, 0] == np.arange(13)).all()


def test_slot_patterns_cover_every_bar_of_dance():
    assert sig.to_pattern("00000101") == 5  # slots 0 and 2
    assert (sig.PATTERN_BITS[sig.to_pattern(sig.COMMON_BITS)] == sig.COMMON_BITS).all()
    # on the common signatures the pattern table is the common table
    assert np.allclose(
        sig.PATTERN_DISTANCES[:, sig.to_pattern(sig.COMMON_BITS)], sig.COMMON_DISTANCES
    )
    # a pattern no common signature has: the downbeat and the half beat after beat 3
    off = sig.to_pattern("00100001")
    assert sig.PATTERN_DISTANCES[sig.COMMON_SIGNATURES.index("00000001"), off] == 0.5
    assert sig.PATTERN_DISTANCES[sig.COMMON_SIGNATURES.index("00010001"), off] == 1.5
