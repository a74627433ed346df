"""The worker's analysis cache keeps analyses made with a spec's own analysis parameters apart."""

from __future__ import annotations

from dancegraph.music.params import AnalysisParams, GroupParams
from services.worker import pipeline


def test_the_cache_key_names_non_default_params() -> None:
    sha = "ab" * 32
    plain = pipeline.analysis_key(sha)
    assert pipeline.analysis_key(sha, None, AnalysisParams()) == plain
    tuned = AnalysisParams(group=GroupParams(net_confident=0.75))
    key = pipeline.analysis_key(sha, (150.0, 220.0), tuned)
    assert key.endswith(f"-150-220bpm-p{tuned.digest()}.json") and key != plain
