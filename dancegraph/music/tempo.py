"""Tempo from beat times, metrical-level relations (double/half, 3:2) and a confidence.

The tempo reported with a beat track is the one its beats imply (so bars and tempo never
disagree); the onset envelope's periodicity at the related metrical levels (x2, x1/2, x3/2, x2/3)
is checked to say how sure that level is. A tracker can lock onto twice or half the felt tempo,
or onto a dotted (3:2) pulse; the alternatives are reported with their evidence, and the
confidence drops when another level is about as well supported.

Tempo octave (:func:`dance_octave`): which of x1/2, x1, x2 of the tracked tempo a dancer would
count as the beat. A log-normal dance-tempo prior centred on 112 BPM (:class:`~dancegraph.music.
params.TempoParams`: 90-140 BPM lie within one standard deviation, 0.35 octave) is weighed against each level's pulse
salience in the onset envelope; the decision and its confidence (the posterior of the chosen
level) are reported (``TempoEstimate.octave``, and a ``tempo_octave`` warning when the decision
is not the tracked level). The beats and bars stay on the tracked level: whether 176 BPM is
danced as 176 (salsa, 160-200) or as 88 depends on the dance library, not on the song alone;
where the library declares its style's tempo range, the bars count the octave that fits it
(:func:`dancegraph.music.analysis.fit_tempo_range`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import median_filter

from dancegraph.music.params import TempoParams

__all__ = [
    "RELATIONS",
    "TempoEstimate",
    "dance_octave",
    "estimate_tempo",
    "metrical_relation",
    "pulse_salience",
    "tempo_from_beats",
]

#: metrical levels checked against the tracked tempo: (name, tempo ratio)
RELATIONS: tuple[tuple[str, float], ...] = (
    ("x2", 2.0),
    ("x1/2", 0.5),
    ("x3/2", 1.5),
    ("x2/3", 2.0 / 3.0),
)


@dataclass
class TempoEstimate:
    """Tempo in BPM (from the beat intervals), confidence in [0, 1], and the evidence.

    ``alternatives``: list of {relation, bpm, salience} for the related metrical levels;
    ``salience`` of the tracked level is ``salience`` (onset autocorrelation, 0..1);
    ``octave``: the dance-tempo decision of :func:`dance_octave` ({relation, bpm, confidence}).
    """

    bpm: float
    confidence: float
    regularity: float
    salience: float
    alternatives: list[dict] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    octave: dict = field(default_factory=dict)


def tempo_from_beats(beats: np.ndarray) -> tuple[float, float]:
    """(tempo BPM, regularity 0..1) from beat times (K,) s.

    The tempo is 60 / the mean of the inter-beat intervals within 10 % of their median: the
    median alone is robust to missed or extra beats but snaps to the decoder's 20 ms frames.
    Regularity is the share of
    intervals within 10 % of the local median (robust to a few missed or extra beats and to
    slow drifts).
    """
    beats = np.asarray(beats, dtype=np.float64)
    if len(beats) < 3:
        return 0.0, 0.0
    ibi = np.diff(beats)
    med = float(np.median(ibi))
    if med <= 0:
        return 0.0, 0.0
    mean = float(ibi[np.abs(ibi - med) <= 0.1 * med].mean())
    # local median over 9 intervals follows tempo drift and rubato
    local = median_filter(ibi, 9, mode="nearest")
    regular = np.abs(ibi - local) <= 0.1 * local
    return 60.0 / mean, float(regular.mean())


def metrical_relation(
    a_bpm: float, b_bpm: float, tol: float = TempoParams.relation_tol
) -> str | None:
    """The relation of tempo ``b`` to ``a`` within the relative ``tol``: 'x1', 'x2', 'x1/2',
    'x3/2', 'x2/3', or None."""
    if a_bpm <= 0 or b_bpm <= 0:
        return None
    r = b_bpm / a_bpm
    for name, ratio in (("x1", 1.0), *RELATIONS):
        if abs(r / ratio - 1.0) <= tol:
            return name
    return None


def pulse_salience(onset_env: np.ndarray, fps: float, bpm: float) -> float:
    """Normalised autocorrelation (0..1) of an onset envelope (T,) at the period of ``bpm``.

    The maximum over a +-4 % lag window, so small tempo drift does not hide the pulse.
    """
    x = np.asarray(onset_env, dtype=np.float64)
    if bpm <= 0 or len(x) < 4:
        return 0.0
    x = x - x.mean()
    denom = float(np.dot(x, x))
    if denom <= 0:
        return 0.0
    lag = 60.0 * fps / bpm
    lo, hi = int(np.floor(lag * 0.96)), int(np.ceil(lag * 1.04))
    best = 0.0
    for L in range(max(lo, 1), min(hi, len(x) - 1) + 1):
        best = max(best, float(np.dot(x[:-L], x[L:])) / denom)
    return max(best, 0.0)


def dance_octave(
    bpm: float, salience: dict[str, float], params: TempoParams = TempoParams()
) -> dict:
    """The dance-tempo level among x1/2, x1 and x2 of ``bpm``: ``{relation, bpm, confidence}``.

    ``salience``: pulse salience (0..1) per relation ('x1' required; 'x1/2', 'x2' if known).
    Score of a level = log prior (``params``: log-normal, ``dance_center_bpm``,
    ``dance_sigma_octaves``) + log salience relative to the best level; confidence = the chosen
    level's share of the normalised posterior.
    """
    if bpm <= 0:
        return {"relation": "x1", "bpm": 0.0, "confidence": 0.0}
    c, sd = np.log2(params.dance_center_bpm), params.dance_sigma_octaves
    top = max(max(salience.values()), 1e-6)
    names, scores = [], []
    for name, ratio in (("x1/2", 0.5), ("x1", 1.0), ("x2", 2.0)):
        if name not in salience:
            continue
        prior = -0.5 * ((np.log2(bpm * ratio) - c) / sd) ** 2
        names.append(name)
        scores.append(prior + np.log(max(salience[name], 1e-3 * top) / top))
    post = np.exp(np.asarray(scores) - max(scores))
    post /= post.sum()
    k = int(np.argmax(post))
    ratio = {"x1/2": 0.5, "x1": 1.0, "x2": 2.0}[names[k]]
    return {"relation": names[k], "bpm": float(bpm * ratio), "confidence": float(post[k])}


def estimate_tempo(
    beats: np.ndarray,
    onset_env: np.ndarray | None = None,
    fps: float = 50.0,
    params: TempoParams = TempoParams(),
) -> TempoEstimate:
    """Tempo and confidence of a beat track (K,) s, checked against an onset envelope (T,) at ``fps``.

    Confidence = regularity of the beat intervals, scaled by ``params.ambiguous_confidence``
    when a related metrical level (x3/2, x2/3; x1/2) has a clearly stronger pulse in the onset
    envelope than the tracked one (``params.dotted_competes``; ``params.half_competes``).
    """
    bpm, regularity = tempo_from_beats(beats)
    if bpm <= 0:
        return TempoEstimate(0.0, 0.0, 0.0, 0.0)
    est = TempoEstimate(bpm=bpm, confidence=regularity, regularity=regularity, salience=0.0)
    if onset_env is None:
        return est
    est.salience = pulse_salience(onset_env, fps, bpm)
    for name, ratio in RELATIONS:
        alt = bpm * ratio
        if not 30.0 <= alt <= 300.0:
            continue
        sal = pulse_salience(onset_env, fps, alt)
        est.alternatives.append({"relation": name, "bpm": alt, "salience": sal})
    # a faster level whose pulse is as strong is normal (subdivisions); a *competing* level is
    # one that is not a multiple of the tracked beat: x3/2 and x2/3, or a slower x1/2 that is
    # much stronger than the tracked beat.
    competing = [
        a
        for a in est.alternatives
        if (
            a["relation"] in ("x3/2", "x2/3")
            and a["salience"] > params.dotted_competes * est.salience
        )
        or (a["relation"] == "x1/2" and a["salience"] > params.half_competes * est.salience)
    ]
    if competing:
        strongest = max(competing, key=lambda a: a["salience"])
        est.confidence *= params.ambiguous_confidence
        est.warnings.append(
            f"tempo_ambiguous: the onset pulse at {strongest['bpm']:.1f} BPM "
            f"({strongest['relation']} of {bpm:.1f}) is stronger than the tracked beat's"
        )
    by_level = {"x1": est.salience} | {
        a["relation"]: a["salience"] for a in est.alternatives if a["relation"] in ("x2", "x1/2")
    }
    est.octave = dance_octave(bpm, by_level, params)
    if est.octave["relation"] != "x1":
        est.warnings.append(
            f"tempo_octave: a dancer would likely count {est.octave['bpm']:.1f} BPM "
            f"({est.octave['relation']} of the tracked {bpm:.1f}; confidence "
            f"{est.octave['confidence']:.2f}); beats and bars stay on the tracked level"
        )
    return est
