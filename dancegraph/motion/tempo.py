"""Tempo, beat grid and bar grid of a dance clip from its kinematics.

A dance's beat is often not periodic at the beat level: salsa's basic step moves on beats
1 2 3, 5 6 7 and pauses on 4 and 8, so the feet are periodic over a bar (4 beats) or two, not
over a beat, and a generic beat tracker run on a kinematic envelope lands anywhere from 80 to
157 BPM across the CMU salsa takes. The estimate here works at the *bar* level instead:

1. ``periodicity_signals``: left/right-symmetric kinematic signals (pelvis height, summed foot
   speed, summed hand speed relative to the pelvis, mean speed relative to the pelvis). Symmetric
   sums repeat every bar; a single foot repeats only every two bars.
2. ``mean_local_autocorrelation``: their autocorrelation in sliding windows, averaged (a dance
   changes figures within a take; windows keep one figure's periodicity from washing out
   another's).
3. ``estimate_tempo``: candidate tempi are 4 beats per peak lag of that autocorrelation (bar
   candidates) and 1 or 2 beats per peak lag of the kinematic-beat envelope's (pulse
   candidates). A tempo scores its bar term ``(A(L) + A(2L)) / 2`` (a bar that repeats also
   repeats two bars later, which rejects accidental short peaks) plus its pulse term, the
   envelope's autocorrelation at one and two beats (a dance whose bars never repeat but whose
   accents keep time, like the generated demo library, still has a tempo). The *tempo* is the
   fastest candidate inside the prior whose bar + 0.5 × pulse score reaches 0.9 × the best
   there. The *motion tempo* is 4 beats per the shortest
   strong bar lag (bar term ≥ 0.8 × the best) over 0.5–4 s, with no prior and no pulse: it
   measures how fast the body's bars actually repeat, so a clip read at twice its real frame
   rate moves twice as fast, its motion tempo leaves the prior and the clip is flagged
   ``tempo_outside_prior`` (CMU salsa read at its 120 fps header: about 330 BPM, 22 of 28 takes
   flagged; at 60 fps, 1). The confidence is the bar's (or, if clearer, bar and pulse's)
   autocorrelation *rise* above its trough over the half period before the peak, over
   ``FULL_CONFIDENCE_SCORE``: a slowly wandering, aperiodic signal correlates highly at every
   lag but rises nowhere. Below ``STEADY_MIN_CONFIDENCE``: ``no_steady_beat``.
4. ``track_beats``: dynamic-programming beat tracking (Ellis 2007) on the kinematic-beat
   envelope at the estimated period, which follows slow drift; ``bar_phase`` puts the downbeat
   on the beat position hit by kinematic beats most often (every common rhythm signature has
   its downbeat slot set).
5. ``bar_signature_bits``: a bar's rhythm signature from the kinematic beats nearest each of its
   8 half-beat slots.

Times are seconds, tempi beats per minute, frame rates frames per second.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import find_peaks

from dancegraph.rhythm.signatures import N_SLOTS

#: Tempo range assumed when neither the manifest nor the caller gives one (BPM).
DEFAULT_PRIOR_BPM: tuple[float, float] = (80.0, 200.0)
#: Bar lags searched for the prior-free motion tempo (s): 4 beats at 480 … 60 BPM.
FREE_BAR_RANGE_S: tuple[float, float] = (0.5, 4.0)
#: Periodicity rise (windowed autocorrelation above its trough) that counts as full confidence.
FULL_CONFIDENCE_SCORE = 0.25
#: Below this confidence a clip has no steady beat.
STEADY_MIN_CONFIDENCE = 0.3
#: A shorter bar lag wins the free estimate when its score is at least this share of the best.
SHORTEST_STRONG_RATIO = 0.8
#: Weight of the pulse term against the bar term when choosing the tempo.
PULSE_WEIGHT = 0.5
#: Inside the prior, the fastest candidate scoring at least this share of the best wins.
#: (Weight and share chosen on the CMU salsa partner takes, whose two dancers share one tempo,
#: and on the generated demo library, whose tempi are known.)
TEMPO_STRONG_RATIO = 0.9
#: The motion tempo counts as outside the prior beyond this relative margin.
PRIOR_MARGIN = 0.1


def periodicity_signals(
    positions: np.ndarray,
    fps: float,
    *,
    root: int,
    feet: tuple[int, int],
    hands: tuple[int, int],
) -> np.ndarray:
    """Left/right-symmetric kinematic signals whose period is a bar.

    ``positions``: ``(F, J, 3)`` world joint positions in metres (Y up); ``root``, ``feet``,
    ``hands``: joint indices into J. Returns ``(F, 4)``: pelvis height (m), summed foot speed
    (m/s), summed hand speed relative to the pelvis (m/s), mean joint speed relative to the
    pelvis (m/s), lightly smoothed (25 ms).
    """
    pos = np.asarray(positions, dtype=float)
    smooth = gaussian_filter1d(pos, sigma=max(1.0, 0.025 * fps), axis=0, mode="nearest")
    vel = np.gradient(smooth, axis=0) * fps
    rel = vel - vel[:, root : root + 1]
    return np.stack(
        [
            smooth[:, root, 1],
            np.linalg.norm(vel[:, list(feet)], axis=-1).sum(axis=1),
            np.linalg.norm(rel[:, list(hands)], axis=-1).sum(axis=1),
            np.linalg.norm(rel, axis=-1).mean(axis=1),
        ],
        axis=1,
    )


def mean_local_autocorrelation(
    signals: np.ndarray, fps: float, *, max_lag_s: float, hop_s: float = 1.0
) -> np.ndarray:
    """Normalised autocorrelation of each signal in sliding windows, averaged.

    ``signals``: ``(F, C)``. Windows are ``2.5 × max_lag_s`` long (at least 8 s, at most the
    clip), hop ``hop_s``. Each window's autocorrelation is mean-removed, normalised to 1 at lag
    0 and unbiased by the overlap; flat channels are skipped. Returns ``(L,)`` for lags
    ``0 … L-1`` frames, ``L = min(max_lag_s·fps, window/2) + 1``; all zeros when every channel is
    flat.
    """
    x = np.asarray(signals, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    n = x.shape[0]
    win = int(min(n, max(8.0, 2.5 * max_lag_s) * fps))
    n_lags = int(min(max_lag_s * fps, win // 2)) + 1
    hop = max(1, int(hop_s * fps))
    starts = range(0, max(1, n - win + 1), hop)
    overlap = (win - np.arange(n_lags)) / win
    total = np.zeros(n_lags)
    count = 0
    for s in starts:
        w = x[s : s + win] - x[s : s + win].mean(axis=0)
        spec = np.fft.rfft(w, 2 * win, axis=0)
        ac = np.fft.irfft(spec * np.conj(spec), axis=0)[:n_lags]
        ok = ac[0] > 1e-9 * win
        if not ok.any():
            continue
        total += (ac[:, ok] / ac[0, ok] / overlap[:, None]).sum(axis=1)
        count += int(ok.sum())
    return total / count if count else total


def _peak_lags(ac: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima of ``ac`` (frames, parabolic sub-frame refinement) and their heights."""
    idx, _ = find_peaks(ac)
    idx = idx[(idx > 0) & (idx < len(ac) - 1)]
    a, b, c = ac[idx - 1], ac[idx], ac[idx + 1]
    denom = a - 2 * b + c
    shift = np.where(np.abs(denom) > 1e-12, 0.5 * (a - c) / np.where(denom == 0, 1, denom), 0.0)
    shift = np.clip(shift, -0.5, 0.5)
    return idx + shift, b - 0.25 * (a - c) * shift


def _value_near(ac: np.ndarray, lag: float, tol: float = 0.04) -> float:
    """Largest autocorrelation within ``±tol`` (relative) of ``lag`` frames; NaN beyond range."""
    lo, hi = int(np.floor(lag * (1 - tol))), int(np.ceil(lag * (1 + tol)))
    if hi >= len(ac) or lo < 1:
        return float("nan")
    return float(ac[lo : hi + 1].max())


def _rise(ac: np.ndarray, lag: float) -> float:
    """Autocorrelation near ``lag`` above its lowest value over the half period before it.

    A periodic signal's autocorrelation dips between its peaks; a slowly wandering one decays
    smoothly and rises nowhere, so it scores about zero however high its correlation is.
    """
    peak = _value_near(ac, lag)
    if np.isnan(peak):
        return peak
    return peak - float(ac[int(lag * 0.5) : int(np.ceil(lag)) + 1].min())


def _refine_lag(ac: np.ndarray, lag: float) -> float:
    """Sharpen a bar lag with the farthest multiple that still shows a clear peak."""
    peaks, heights = _peak_lags(ac)
    best = lag
    base = _value_near(ac, lag)
    for m in (2, 3, 4):
        near = np.abs(peaks - m * lag) <= 0.04 * m * lag
        if not near.any():
            continue
        k = np.flatnonzero(near)[np.argmax(heights[near])]
        if heights[k] >= 0.5 * base:
            best = peaks[k] / m
    return float(best)


@dataclass
class TempoEstimate:
    """A clip's tempo from bar-level periodicity.

    - ``tempo_bpm``: beats per minute inside the prior (4 beats per ``bar_period_s``).
    - ``motion_tempo_bpm``: the prior-free estimate (shortest strong bar period); NaN if none.
    - ``confidence``: 0..1, ``score`` over ``FULL_CONFIDENCE_SCORE``.
    - ``score``: the periodicity rise at the chosen tempo (see the module docstring).
    - ``flags``: ``no_steady_beat``, ``tempo_outside_prior``, ``no_periodicity_in_prior``.
    """

    tempo_bpm: float
    motion_tempo_bpm: float
    bar_period_s: float
    confidence: float
    score: float
    prior_bpm: tuple[float, float]
    flags: list[str] = field(default_factory=list)

    @property
    def beat_period_s(self) -> float:
        return 60.0 / self.tempo_bpm


def _near(ac: np.ndarray, lags: np.ndarray, tol: float = 0.04) -> np.ndarray:
    """``_value_near`` for many lags (frames)."""
    return np.array([_value_near(ac, float(x), tol) for x in lags])


def _rises(ac: np.ndarray, lags: np.ndarray) -> np.ndarray:
    return np.array([_rise(ac, float(x)) for x in lags])


def _tempo_scores(
    ac: np.ndarray, env_ac: np.ndarray | None, fps: float, bpm: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bar score and rise, pulse score and rise, each ``(len(bpm),)``, per tempo.

    Bar: the signals' autocorrelation at one and two bars (4 and 8 beats). Pulse (when the
    kinematic-beat envelope's autocorrelation ``env_ac`` is given, else NaN): the envelope's
    autocorrelation at one and two beats. NaN where the lags run past the autocorrelation.
    """
    bar = 240.0 * fps / bpm
    one, two = _near(ac, bar), _near(ac, 2 * bar)
    score = np.where(np.isnan(two), one, 0.5 * (one + two))
    r1, r2 = _rises(ac, bar), _rises(ac, 2 * bar)
    rise = np.where(np.isnan(r2), r1, 0.5 * (r1 + r2))
    if env_ac is None:
        nan = np.full(len(bpm), np.nan)
        return score, rise, nan, nan
    beat = bar / 4
    pulse = 0.5 * (_near(env_ac, beat) + _near(env_ac, 2 * beat))
    pulse_rise = 0.5 * (_rises(env_ac, beat) + _rises(env_ac, 2 * beat))
    return score, rise, pulse, pulse_rise


def _strong_peaks(score: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Indices within ``mask`` of candidates scoring ≥ 0.8 × the best there (and above 0)."""
    s = np.where(np.isnan(score), -np.inf, score)
    peaks = np.flatnonzero(mask & (s > 0))
    if len(peaks) == 0:
        return peaks
    return peaks[s[peaks] >= SHORTEST_STRONG_RATIO * s[peaks].max()]


def estimate_tempo(
    signals: np.ndarray,
    fps: float,
    prior_bpm: tuple[float, float] | None = None,
    kinematic_beats: np.ndarray | None = None,
) -> TempoEstimate:
    """Tempo of a clip from ``periodicity_signals`` ``(F, C)`` sampled at ``fps``.

    ``prior_bpm``: ``(lo, hi)`` plausible tempo range (default ``DEFAULT_PRIOR_BPM``).
    ``kinematic_beats``: ``(K,)`` s (the pulse term; at least 4). The tempo is the fastest
    candidate inside the prior whose bar + ``PULSE_WEIGHT`` × pulse score reaches
    ``TEMPO_STRONG_RATIO`` × the best there (a periodic dance scores a bar and its double
    alike; the shorter is the bar); without kinematic beats, the same on bar candidates and
    the bar score. Without any periodicity in the prior: the motion tempo folded into the range
    by octaves (flagged ``no_periodicity_in_prior``, confidence 0).
    """
    lo_bpm, hi_bpm = prior_bpm or DEFAULT_PRIOR_BPM
    if not 0 < lo_bpm < hi_bpm:
        raise ValueError(f"tempo prior must be 0 < lo < hi, got {prior_bpm}")
    signals = np.asarray(signals, dtype=float)
    max_lag_s = 2 * max(FREE_BAR_RANGE_S[1], 240.0 / lo_bpm)
    ac = mean_local_autocorrelation(signals, fps, max_lag_s=max_lag_s)
    env_ac = None
    if kinematic_beats is not None and len(kinematic_beats) >= 4:
        env = beat_envelope(kinematic_beats, signals.shape[0], fps)
        env_ac = mean_local_autocorrelation(env, fps, max_lag_s=max_lag_s)
        if not env_ac.any():
            env_ac = None
    free_lo, free_hi = 240.0 / FREE_BAR_RANGE_S[1], 240.0 / FREE_BAR_RANGE_S[0]
    # Candidate tempi: 4 beats per peak lag of the signals' autocorrelation (bars), and 1 or 2
    # beats per peak lag of the kinematic-beat envelope's (pulse).
    bar_peaks, _ = _peak_lags(ac)
    cand = [240.0 * fps / bar_peaks]
    if env_ac is not None:
        env_peaks, _ = _peak_lags(env_ac)
        cand += [60.0 * fps / env_peaks, 120.0 * fps / env_peaks]
    bpm = np.unique(np.round(np.concatenate(cand), 2)) if cand else np.zeros(0)
    from_bar = np.isin(bpm, np.round(240.0 * fps / bar_peaks, 2))
    score, rise, pulse, pulse_rise = _tempo_scores(ac, env_ac, fps, bpm)

    # Prior-free motion tempo: the fastest strong bar periodicity over the free range (a
    # periodic dance scores a bar and its double alike; the shorter is the bar).
    free = _strong_peaks(score, from_bar & (bpm >= free_lo) & (bpm <= free_hi))
    motion_tempo = float(bpm[free].max()) if len(free) else float("nan")

    # Tempo: inside the prior, the fastest candidate whose bars repeat and whose beats the
    # kinematic beats keep nearly as well as the best's (bar + PULSE_WEIGHT × pulse score ≥
    # TEMPO_STRONG_RATIO × the best); without kinematic beats, the same on the bar score.
    flags: list[str] = []
    inside = (bpm >= lo_bpm * 0.98) & (bpm <= hi_bpm * 1.02)
    if env_ac is None:
        both = np.where(from_bar, np.nan_to_num(score, nan=-1.0), -1.0)
    else:
        both = np.nan_to_num(score, nan=-1.0) + PULSE_WEIGHT * np.nan_to_num(pulse, nan=-1.0)
    k = None
    conf_score = 0.0
    ok = np.flatnonzero(inside & (both > 0))
    if len(ok):
        strong = ok[both[ok] >= TEMPO_STRONG_RATIO * both[ok].max()]
        k = int(strong[np.argmax(bpm[strong])])
    if k is not None:
        bar_c = max(0.0, float(np.nan_to_num(min(score[k], rise[k]))))
        beat_c = max(0.0, float(np.nan_to_num(min(pulse[k], pulse_rise[k]))))
        # the bar's clarity, raised where the kinematic beats keep the beat more clearly
        conf_score = max(bar_c, 0.5 * (bar_c + beat_c))
    if k is not None:
        tempo_bpm = float(bpm[k])
    else:
        flags.append("no_periodicity_in_prior")
        tempo_bpm = motion_tempo if np.isfinite(motion_tempo) else float(np.sqrt(lo_bpm * hi_bpm))
        while tempo_bpm > hi_bpm:
            tempo_bpm /= 2
        while tempo_bpm < lo_bpm:
            tempo_bpm *= 2
    mix = ac if env_ac is None else 0.5 * (ac + env_ac)
    lag = _refine_lag(mix, 240.0 * fps / tempo_bpm)
    confidence = float(np.clip(conf_score / FULL_CONFIDENCE_SCORE, 0.0, 1.0))
    if confidence < STEADY_MIN_CONFIDENCE:
        flags.append("no_steady_beat")
    # Only a *faster* motion tempo is suspicious: periodicity over two bars (a slower motion
    # tempo) is ordinary in dance, a strong one at half a bar is not.
    if np.isfinite(motion_tempo) and motion_tempo > hi_bpm * (1 + PRIOR_MARGIN):
        flags.append("tempo_outside_prior")
    return TempoEstimate(
        tempo_bpm=240.0 * fps / lag,
        motion_tempo_bpm=motion_tempo,
        bar_period_s=lag / fps,
        confidence=confidence,
        score=conf_score,
        prior_bpm=(float(lo_bpm), float(hi_bpm)),
        flags=flags,
    )


def beat_envelope(
    beat_times: np.ndarray, n_frames: int, fps: float, sigma_s: float = 0.04
) -> np.ndarray:
    """``(F,)`` kinematic-beat envelope: unit impulses at ``beat_times`` (s), Gaussian-smoothed."""
    env = np.zeros(n_frames)
    idx = np.round(np.asarray(beat_times, dtype=float) * fps).astype(int)
    idx = idx[(idx >= 0) & (idx < n_frames)]
    np.add.at(env, idx, 1.0)
    return gaussian_filter1d(env, sigma=max(0.5, sigma_s * fps), mode="constant")


def track_beats(
    envelope: np.ndarray, fps: float, period_s: float, tightness: float = 200.0
) -> np.ndarray:
    """Beat times (s) at about ``period_s`` that follow ``envelope`` ``(F,)`` (Ellis 2007 DP).

    Each frame's score is its envelope value plus the best predecessor score between half and
    twice a period earlier, penalised by ``tightness · log(interval / period)²``. The beats are
    backtracked from the best frame in the last period and then extended with the period to
    both ends of the clip, so that a bar grid covers the whole take.
    """
    env = np.asarray(envelope, dtype=float)
    n = len(env)
    period = period_s * fps
    if n == 0 or period <= 1:
        return np.zeros(0)
    env = env / (env.std() + 1e-9)
    lo, hi = max(1, int(round(period / 2))), int(round(2 * period))
    offsets = np.arange(lo, hi + 1)
    penalty = -tightness * np.log(offsets / period) ** 2
    score = env.copy()
    back = np.full(n, -1)
    for t in range(lo, n):
        prev = t - offsets
        ok = prev >= 0
        cand = score[prev[ok]] + penalty[ok]
        k = int(np.argmax(cand))
        if cand[k] > 0:
            score[t] += cand[k]
            back[t] = prev[ok][k]
    tail = max(0, n - int(np.ceil(period)))
    t = tail + int(np.argmax(score[tail:]))
    frames = [t]
    while back[frames[-1]] >= 0:
        frames.append(int(back[frames[-1]]))
    beats = np.array(frames[::-1], dtype=float)
    # Extend with the period over the untracked head and tail.
    # A beat up to a quarter period beyond either end snaps onto the end frame.
    head = np.arange(beats[0] - period, -0.5 * period, -period)[::-1]
    end = np.arange(beats[-1] + period, n - 1 + 0.5 * period, period)
    head = np.maximum(head[head >= -0.25 * period], 0.0)
    end = np.minimum(end[end <= n - 1 + 0.25 * period], n - 1.0)
    beats = np.concatenate([head, beats, end])
    return beats / fps


def _nearest_distance(times: np.ndarray, events: np.ndarray) -> np.ndarray:
    """Distance from each of ``times`` (any shape) to the nearest of sorted-able ``events``."""
    ev = np.sort(np.asarray(events, dtype=float))
    t = np.asarray(times, dtype=float)
    if len(ev) == 0:
        return np.full(t.shape, np.inf)
    i = np.clip(np.searchsorted(ev, t), 1, len(ev) - 1) if len(ev) > 1 else np.zeros(t.shape, int)
    left = np.abs(t - ev[np.maximum(i - 1, 0)])
    right = np.abs(t - ev[i])
    return np.minimum(left, right)


def bar_phase(beats: np.ndarray, kinematic_beats: np.ndarray, period_s: float) -> tuple[int, float]:
    """Which beat of every four is the downbeat, and how clearly (0..1).

    ``beats``: ``(N,)`` s; ``kinematic_beats``: ``(K,)`` s. A beat is *hit* when a kinematic
    beat lies within an eighth of a beat of it; the downbeat phase ``r`` in 0..3 maximises the
    share of hit beats among ``beats[r::4]``, leaving out the first and last beat (a clip's ends
    cannot hold a detected speed minimum). Ties (accents on beats 1 and 3 alike) go to the
    earliest phase. The clarity is ``(best − second) / best``.
    """
    beats = np.asarray(beats, dtype=float)
    kb = np.asarray(kinematic_beats, dtype=float)
    if len(beats) < 4 or len(kb) == 0:
        return 0, 0.0
    hit = _nearest_distance(beats, kb) <= 0.125 * period_s
    inner = np.zeros(len(beats), dtype=bool)
    inner[1:-1] = True
    means = np.array(
        [hit[r::4][inner[r::4]].mean() if inner[r::4].any() else 0.0 for r in range(4)]
    )
    order = np.argsort(-means, kind="stable")
    best = means[order[0]]
    clarity = float((best - means[order[1]]) / best) if best > 0 else 0.0
    return int(order[0]), clarity


def grid_from_tempo(duration_s: float, tempo_bpm: float, first_beat_s: float = 0.0) -> np.ndarray:
    """Regular beat times (s) at ``tempo_bpm`` from ``first_beat_s`` to the end of the clip."""
    if tempo_bpm <= 0:
        raise ValueError(f"tempo must be positive, got {tempo_bpm}")
    period = 60.0 / tempo_bpm
    start = first_beat_s % period
    return np.arange(start, duration_s + 1e-9, period)


def bars_from_beats(beats: np.ndarray, first_downbeat: int = 0) -> np.ndarray:
    """``(B, 5)`` beat times of the complete 4-beat bars: the 4 beats and the next downbeat.

    ``beats``: ``(N,)`` s; bars start at ``beats[first_downbeat]`` and every 4th beat after.
    """
    beats = np.asarray(beats, dtype=float)
    starts = np.arange(first_downbeat, len(beats) - 4, 4)
    if len(starts) == 0:
        return np.zeros((0, 5))
    return np.stack([beats[s : s + 5] for s in starts])


def slot_times(bar_beats: np.ndarray) -> np.ndarray:
    """``(B, 8)`` times (s) of the 8 half-beat slots of bars given as ``(B, 5)`` beat times."""
    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    mids = 0.5 * (bb[:, :4] + bb[:, 1:])
    out = np.empty((len(bb), N_SLOTS))
    out[:, 0::2] = bb[:, :4]
    out[:, 1::2] = mids
    return out


def bar_signature_bits(
    kinematic_beats: np.ndarray, bar_beats: np.ndarray, tolerance: float = 0.5
) -> np.ndarray:
    """``(B, 8)`` int8 rhythm-signature bits (slot-indexed) of bars from kinematic beats.

    A slot is set when a kinematic beat lies within ``tolerance`` × half a half-beat of it, i.e.
    with the default 0.5 each kinematic beat sets the slot it is nearest to (within a quarter
    beat). ``kinematic_beats``: ``(K,)`` s; ``bar_beats``: ``(B, 5)`` s.
    """
    slots = slot_times(bar_beats)
    kb = np.asarray(kinematic_beats, dtype=float)
    if len(slots) == 0 or len(kb) == 0:
        return np.zeros((len(slots), N_SLOTS), dtype=np.int8)
    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    half = (bb[:, 4] - bb[:, 0]) / N_SLOTS  # half-beat length per bar
    nearest = _nearest_distance(slots, kb)
    return (nearest <= tolerance * half[:, None] + 1e-9).astype(np.int8)


def grid_fit(kinematic_beats: np.ndarray, bar_beats: np.ndarray) -> float:
    """Share of the kinematic beats inside the bars that lie within 1/8 beat of a half-beat slot.

    With kinematic beats at random times this is 0.5; on a dance locked to its grid, near 1.
    """
    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    kb = np.asarray(kinematic_beats, dtype=float)
    if len(bb) == 0:
        return 0.0
    kb = kb[(kb >= bb[0, 0]) & (kb < bb[-1, 4])]
    if len(kb) == 0:
        return 0.0
    slots = slot_times(bb).ravel()
    half = float(np.median(bb[:, 4] - bb[:, 0])) / N_SLOTS
    d = _nearest_distance(kb, slots)
    return float(np.mean(d <= 0.25 * half))
