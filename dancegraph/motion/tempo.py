"""Beat grid and bar grid of a dance take from its own motion: ``estimate_grid``.

A take without music has no beat to read; its grid is inferred from how the body repeats.
Dance steps are periodic at the bar and half-bar level more than at the beat: in the CMU salsa
takes the feet make one big step every two beats, so the strongest periodicity is at two
beats, then one bar, while a speed minimum on every beat is rare. The grid is therefore fitted
to the bar harmonics of a few step signals, coherently over whole sections of the take, which
gives a sub-frame tempo and phase and averages a dancer's step-to-step jitter out instead of
following it. The steps, over one :class:`GridParams`:

1. ``step_signals``: five standardised evidence channels: mean speed of the trunk and leg
   joints, summed speed of the foot points (ankles, toes), summed foot lift, the step onsets
   (both feet's contact starts) and the kinematic-beat envelope (pauses of the whole body,
   always the last channel). The arms enter only through the kinematic beats: partners of a
   couple dance hold hands, and arm speed itself would make two partners' grids agree through
   the hands rather than through the music.
2. ``bar_spectra``: for each tempo of a log-spaced grid over the prior, the Fourier sums of
   every channel at the bar harmonics ``k · tempo / 240`` Hz (k = 1 … 8), per one-second block
   on the take's time axis, accumulated: the coherent spectrum of any run of blocks is the
   difference of two cumulative sums.
3. ``channel_weights``: each channel counts by its clarity over the whole take (spectral
   peak over median, squared, per unit of median), so the channels that repeat clearly
   decide: the steps in a stepping dance, the pauses in a dance of held accents.
4. ``tempo_sections``: dynamic programming over block runs splits the take where the tempo
   changes. A section scores the prominence (peak − median) of its harmonic-sum spectrum
   ``Σ_k w_k Σ_c v_c |X_ck(T)|``; a split must add ``split_gain`` of the one-section score,
   every section lasts ``min_section_s``, is steady itself and differs from its neighbour by
   ``min_tempo_change`` in tempo.
5. ``refine_tempo`` and ``section_phase``, per section. Which cue leads (``pauses_lead``):
   the kinematic beats where their channel is clearer than the feet's, else the steps. Where
   the steps lead, the tempo is the peak of the ``step_harmonics`` alone (the two-beat step
   cycle, each channel weighted by its clarity there): the periodicity of a stepping dance
   that two partners share, while the bar and beat harmonics of one dancer's figures (turns,
   a lead) are not; where the pauses lead, the peak of the harmonic sum. Either is refined
   within ``refine_span`` to where the anchor harmonics are most coherent (the step cycle
   that places the beats stays in phase over the section). The beats sit where the folded
   activity (speeds, lift and onsets up, pauses down, each channel by its weight) is lowest
   at the stronger anchor harmonic (2: the two-beat step cycle, 4: the beat), i.e. pauses on
   the beat, the convention of kinematic beats. The downbeat, where the pauses lead: the
   beat the kinematic beats hit most often (every common rhythm signature
   has its downbeat slot set; of two that tie within ``downbeat_margin`` of the range, the
   first in the section, which starts on a bar). Where the steps lead: the beat at the low
   point of the feet's bar cycle (their first bar harmonic), the bar-level cue two partners of
   a couple dance share (their pauses and trunk differ: docs/mocap-beats.md).
6. ``estimate_grid`` assembles the sections' even beats in one list (a beat closer than half a
   period to the previous section's last is dropped) and bars wherever a downbeat has three
   beats and the next downbeat after it.

A section's confidence is its spectral prominence ratio (peak − median over median) mapped
from ``CONFIDENCE_RATIO`` onto 0..1; the take's is the duration-weighted mean, and below
``STEADY_MIN_CONFIDENCE`` the take is flagged ``no_steady_beat``. The *motion tempo* is a
prior-free check of the frame rate (``motion_tempo_bpm``): a take read at twice its real frame
rate moves twice as fast, leaves the prior and is flagged ``tempo_outside_prior``.

Times are seconds, tempi beats per minute, frame rates frames per second.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import find_peaks

from dancegraph.motion.contacts import point_contacts, step_onsets
from dancegraph.rhythm.signatures import N_SLOTS

#: Tempo range assumed when neither the manifest nor the caller gives one (BPM): the common
#: range of a dance's beat; faster dances (salsa, jive) declare theirs in the manifest.
DEFAULT_PRIOR_BPM: tuple[float, float] = (70.0, 160.0)
#: Bar harmonics whose Fourier sums are kept (k · tempo / 240 Hz).
N_HARMONICS = 8
#: Column of ``step_signals`` holding the summed foot speed.
FEET_CHANNEL = 1
#: Spectral prominence ratio (peak − median) / median mapped to confidence 0 and 1 (set so
#: that random walks stay below ``STEADY_MIN_CONFIDENCE``: docs/mocap-beats.md).
CONFIDENCE_RATIO: tuple[float, float] = (0.8, 2.3)
#: Below this confidence a take has no steady beat.
STEADY_MIN_CONFIDENCE = 0.3
#: Bar lags searched for the prior-free motion tempo (s): 4 beats at 480 … 60 BPM.
FREE_BAR_RANGE_S: tuple[float, float] = (0.5, 4.0)
#: A shorter bar lag wins the motion tempo when its score is at least this share of the best.
SHORTEST_STRONG_RATIO = 0.8
#: The motion tempo counts as outside the prior beyond this relative margin ...
PRIOR_MARGIN = 0.1
#: ... over the prior's top or this tempo (BPM), whichever is higher.
PLAUSIBLE_MAX_BPM = 200.0


@dataclass(frozen=True)
class GridParams:
    """Parameters of ``estimate_grid`` (chosen on partner takes and generated dances:
    docs/mocap-beats.md).

    - ``prior_bpm``: plausible tempo range (BPM); every section's tempo lies inside it.
    - ``tempo_step``: relative spacing of the tempo grid (0.0025 = 0.25 %).
    - ``refine_span``: a section's tempo is refined within this share of its grid peak.
    - ``tempo_weights``: weight of bar harmonics k = 1 … len in the tempo score.
    - ``step_harmonics``: bar harmonics whose peak is the tempo where the steps lead.
    - ``anchor_harmonics``: harmonics whose comb places the beats (the stronger one decides).
    - ``clarity_power``: exponent of a channel's clarity in its weight.
    - ``downbeat_margin``: below this share of the folded range, two beats tie for downbeat.
    - ``block_s``: block length of the sectioning (s).
    - ``min_section_s``: shortest section (s); a take shorter than two is one section.
    - ``split_gain``: each split must add this share of the one-section score.
    - ``min_tempo_change``: neighbouring sections' tempi differ by this share at least.
    - ``max_sections``: most sections per take.
    """

    prior_bpm: tuple[float, float] = DEFAULT_PRIOR_BPM
    tempo_step: float = 0.0025
    refine_span: float = 0.0075
    tempo_weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0)
    step_harmonics: tuple[int, ...] = (2,)
    anchor_harmonics: tuple[int, ...] = (2, 4)
    clarity_power: float = 2.0
    downbeat_margin: float = 0.25
    block_s: float = 1.0
    min_section_s: float = 10.0
    split_gain: float = 0.6
    min_tempo_change: float = 0.02
    max_sections: int = 3

    def __post_init__(self) -> None:
        lo, hi = self.prior_bpm
        if not 0 < lo < hi:
            raise ValueError(f"tempo prior must be 0 < lo < hi, got {self.prior_bpm}")
        if not 1 <= len(self.tempo_weights) <= N_HARMONICS:
            raise ValueError(f"tempo_weights: 1 to {N_HARMONICS} harmonics")
        for name in ("anchor_harmonics", "step_harmonics"):
            ks = getattr(self, name)
            if not ks or any(not 1 <= k <= N_HARMONICS for k in ks):
                raise ValueError(f"{name}: harmonics 1 to {N_HARMONICS}")
        if self.tempo_step <= 0 or self.block_s <= 0 or self.max_sections < 1:
            raise ValueError("tempo_step and block_s must be positive, max_sections at least 1")


@dataclass
class Section:
    """A stretch of steady tempo: ``[start_s, end_s)``, tempo (BPM), confidence 0..1, and the
    downbeat's clarity 0..1 (0: the evidence could not tell two beats apart)."""

    start_s: float
    end_s: float
    tempo_bpm: float
    confidence: float
    downbeat_clarity: float

    def to_dict(self) -> dict:
        return {
            "start_s": round(self.start_s, 4),
            "end_s": round(self.end_s, 4),
            "tempo_bpm": round(self.tempo_bpm, 3),
            "confidence": round(self.confidence, 3),
            "downbeat_clarity": round(self.downbeat_clarity, 3),
        }


@dataclass
class BeatGrid:
    """A take's grid.

    - ``beats``: ``(N,)`` beat times (s), increasing, sub-frame.
    - ``downbeats``: ``(N,)`` bool, True where a bar starts.
    - ``sections``: the stretches of steady tempo, in time order.
    - ``tempo_bpm``: the tempo of the longest section; ``confidence`` 0..1 (duration-weighted
      over sections); ``flags``: ``no_steady_beat``, ``tempo_changes``.
    """

    beats: np.ndarray
    downbeats: np.ndarray
    sections: list[Section]
    tempo_bpm: float
    confidence: float
    flags: list[str] = field(default_factory=list)

    @property
    def bars(self) -> np.ndarray:
        """``(B, 5)`` beat times of the complete bars (4 beats and the next downbeat)."""
        return bars_at_downbeats(self.beats, self.downbeats)


# --------------------------------------------------------------------------------------------
# 1. Evidence
# --------------------------------------------------------------------------------------------


def _standardise(x: np.ndarray, fps: float) -> np.ndarray:
    """Clip at the 98th percentile (marker glitches), remove a 2 s trend, unit variance."""
    top = np.percentile(x, 98)
    x = np.minimum(x, top) if top > 0 else x
    x = x - gaussian_filter1d(x, 2.0 * fps, mode="nearest")
    return x / (x.std() + 1e-9)


def event_envelope(times: np.ndarray, n_frames: int, fps: float, sigma_s: float = 0.03):
    """``(F,)`` unit impulses at ``times`` (s; split linearly between the two nearest frames),
    smoothed by a Gaussian of ``sigma_s``."""
    env = np.zeros(n_frames)
    t = np.asarray(times, dtype=float) * fps
    t = t[(t >= 0) & (t <= n_frames - 1)]
    i = np.floor(t).astype(int)
    frac = t - i
    np.add.at(env, i, 1.0 - frac)
    np.add.at(env, np.minimum(i + 1, n_frames - 1), frac)
    return gaussian_filter1d(env, max(0.5, sigma_s * fps), mode="constant")


def step_signals(
    body: np.ndarray, feet: np.ndarray, kinematic_beats: np.ndarray, fps: float
) -> np.ndarray:
    """``(F, 5)`` standardised step evidence of a take.

    ``body``: ``(F, J, 3)`` world positions (m, Y up) of the trunk and leg joints; ``feet``:
    ``(F, 4, 3)`` left ankle, left toe, right ankle, right toe; ``kinematic_beats``: ``(K,)`` s.
    Columns: mean body joint speed, summed foot-point speed, summed foot lift (per foot the
    lower of ankle and toe above its 5th height percentile), step-onset envelope (the contact
    starts of both feet, ``contacts.point_contacts``, 30 ms impulses), kinematic-beat envelope
    (the last column by contract: ``section_phase`` reads it as the pauses). Each is smoothed
    (25 ms), clipped at its 98th percentile, detrended (2 s) and scaled to unit variance.
    Raises ``ValueError`` for fewer than 3 frames.
    """
    body = np.asarray(body, dtype=float)
    if body.shape[0] < 3:
        raise ValueError("a take needs at least 3 frames")
    feet = np.asarray(feet, dtype=float)
    planted = point_contacts(feet.reshape(-1, 2, 2, 3), fps)
    onsets = event_envelope(step_onsets(planted, fps), body.shape[0], fps)
    sigma = max(1.0, 0.025 * fps)
    body = gaussian_filter1d(body, sigma, axis=0, mode="nearest")
    feet = gaussian_filter1d(feet, sigma, axis=0, mode="nearest")
    speed = np.linalg.norm(np.gradient(body, axis=0), axis=-1).mean(axis=1) * fps
    foot_speed = np.linalg.norm(np.gradient(feet, axis=0), axis=-1).sum(axis=1) * fps
    height = feet[..., 1] - np.percentile(feet[..., 1], 5, axis=0)
    lift = np.minimum(height[:, 0::2], height[:, 1::2]).sum(axis=1)
    pauses = event_envelope(kinematic_beats, body.shape[0], fps)
    return np.stack(
        [_standardise(s, fps) for s in (speed, foot_speed, lift, onsets, pauses)], axis=1
    )


# --------------------------------------------------------------------------------------------
# 2-3. Spectra and channel weights
# --------------------------------------------------------------------------------------------


def tempo_grid(prior_bpm: tuple[float, float], step: float) -> np.ndarray:
    """Log-spaced tempi (BPM) from ``prior_bpm[0]`` to at least ``prior_bpm[1]`` at ``step``."""
    lo, hi = prior_bpm
    n = int(np.ceil(np.log(hi / lo) / np.log1p(step))) + 1
    return lo * (1.0 + step) ** np.arange(n)


def _coefficients(
    signals: np.ndarray, fps: float, start: int, tempi: np.ndarray, n_harmonics: int = N_HARMONICS
) -> np.ndarray:
    """``(G, K, C)`` Fourier sums of ``signals (L, C)``, whose first frame is ``start``, at bar
    harmonics 1 … ``n_harmonics`` of ``tempi (G,)`` on the take's time axis (t = frame / fps)."""
    t = (start + np.arange(signals.shape[0])) / fps
    freq = np.outer(tempi / 240.0, np.arange(1, n_harmonics + 1))  # (G, K) Hz
    return np.exp(-2j * np.pi * freq[:, :, None] * t[None, None, :]) @ signals


def bar_spectra(signals: np.ndarray, fps: float, tempi: np.ndarray, block: int) -> np.ndarray:
    """``(B + 1, G, K, C)`` cumulative block Fourier sums of ``signals (F, C)``.

    Entry ``b`` sums frames ``[0, b · block)`` (the last block zero-padded); the coherent sums
    of blocks ``[i, j)`` are ``S[j] − S[i]``. One block's kernel serves all blocks, each turned
    by the phase of its start time.
    """
    n, c = signals.shape
    n_blocks = -(-n // block)
    padded = np.zeros((n_blocks * block, c))
    padded[:n] = signals
    freq = np.outer(tempi / 240.0, np.arange(1, N_HARMONICS + 1))  # (G, K) Hz
    kernel = np.exp(-2j * np.pi * freq[:, :, None] * (np.arange(block) / fps))  # (G, K, L)
    sums = np.einsum("gkl,blc->bgkc", kernel, padded.reshape(n_blocks, block, c))
    turn = np.exp(-2j * np.pi * freq[None] * (np.arange(n_blocks) * block / fps)[:, None, None])
    out = np.zeros((n_blocks + 1, len(tempi), N_HARMONICS, c), complex)
    np.cumsum(sums * turn[..., None], axis=0, out=out[1:])
    return out


def channel_weights(coef: np.ndarray, weights: np.ndarray, power: float) -> np.ndarray:
    """``(C,)`` weights ``clarity^power / median`` of the channels of Fourier sums ``(G, K, C)``.

    A channel's tempo score ``Σ_k w_k |X_kc|`` over the grid has a median (its noise level)
    and a clarity ``(max − median) / median``; dividing by the median puts the channels on
    one scale.
    """
    per = np.einsum("gkc,k->gc", np.abs(coef[:, : len(weights)]), weights)
    med = np.maximum(np.median(per, axis=0), 1e-12)
    clarity = (per.max(axis=0) - med) / med
    return clarity**power / med


def _tempo_score(coef: np.ndarray, weights: np.ndarray, channels: np.ndarray) -> np.ndarray:
    """``(G,)`` harmonic-sum score ``Σ_k w_k Σ_c v_c |X_kc|`` of Fourier sums ``(G, K, C)``."""
    return np.einsum("gkc,k,c->g", np.abs(coef[:, : len(weights)]), weights, channels)


def _prominence(score: np.ndarray) -> tuple[int, float, float]:
    """Best index, peak − median, and median of a tempo score."""
    g = int(np.argmax(score))
    med = float(np.median(score))
    return g, float(score[g]) - med, med


# --------------------------------------------------------------------------------------------
# 4. Sections
# --------------------------------------------------------------------------------------------


def tempo_sections(
    spectra: np.ndarray,
    tempi: np.ndarray,
    weights: np.ndarray,
    channels: np.ndarray,
    params: GridParams,
) -> list[tuple[int, int]]:
    """Block ranges ``[(i, j), ...]`` of steady tempo covering all blocks, in order.

    ``spectra``: ``bar_spectra`` output on the tempo grid ``tempi``; ``weights``,
    ``channels``: harmonic and channel weights. Dynamic programming over block boundaries: a
    section scores the prominence of its tempo score; ``s`` sections must beat one section by
    ``split_gain · (s − 1)`` of the one-section score and last ``min_section_s`` each. The
    best such split whose sections are all steady and whose neighbours' tempi differ by
    ``min_tempo_change`` wins; else one section.
    """
    n_blocks = spectra.shape[0] - 1
    min_len = max(1, int(np.ceil(params.min_section_s / params.block_s)))
    if n_blocks < 2 * min_len or params.max_sections < 2:
        return [(0, n_blocks)]
    cache: dict[tuple[int, int], float] = {}

    def score(i: int, j: int) -> float:
        if (i, j) not in cache:
            cache[(i, j)] = _prominence(_tempo_score(spectra[j] - spectra[i], weights, channels))[1]
        return cache[(i, j)]

    penalty = params.split_gain * max(score(0, n_blocks), 1e-12)
    n_sec = min(params.max_sections, n_blocks // min_len)
    best = np.full((n_sec + 1, n_blocks + 1), -np.inf)
    back = np.zeros((n_sec + 1, n_blocks + 1), dtype=int)
    best[0, 0] = 0.0
    for s in range(1, n_sec + 1):
        for j in range(s * min_len, n_blocks + 1):
            for i in range((s - 1) * min_len, j - min_len + 1):
                v = best[s - 1, i] + score(i, j)
                if v > best[s, j]:
                    best[s, j], back[s, j] = v, i
    totals = np.array([best[s, n_blocks] - penalty * (s - 1) for s in range(1, n_sec + 1)])
    for s in 1 + np.argsort(-totals, kind="stable"):
        if s == 1 or totals[s - 1] < totals[0]:
            break
        j, cuts = n_blocks, [n_blocks]
        for k in range(s, 0, -1):
            j = int(back[k, j])
            cuts.append(j)
        spans = list(zip(cuts[::-1][:-1], cuts[::-1][1:], strict=True))
        peaks = [
            _prominence(_tempo_score(spectra[j] - spectra[i], weights, channels)) for i, j in spans
        ]
        clear = all(
            confidence_from_ratio(p / max(m, 1e-12)) >= STEADY_MIN_CONFIDENCE for _, p, m in peaks
        )
        change = np.abs(np.diff(np.log(tempi[[g for g, _, _ in peaks]])))
        if clear and np.all(change >= np.log1p(params.min_tempo_change)):
            return spans
    return [(0, n_blocks)]


# --------------------------------------------------------------------------------------------
# 5. One section
# --------------------------------------------------------------------------------------------


def confidence_from_ratio(ratio: float) -> float:
    """Confidence 0..1 of a spectral prominence ratio (see ``CONFIDENCE_RATIO``)."""
    lo, hi = CONFIDENCE_RATIO
    return float(np.clip((ratio - lo) / (hi - lo), 0.0, 1.0))


def refine_tempo(
    signals: np.ndarray,
    fps: float,
    start: int,
    tempo: float,
    params: GridParams,
    channels: np.ndarray,
) -> float:
    """Tempo (BPM) within ``tempo · (1 ± refine_span)`` where the anchor harmonics are most
    coherent over the section, sub-grid.

    ``signals``: the section's ``(L, C)`` frames, the first being frame ``start``. The score
    is ``Σ_{k ∈ anchor} Σ_c v_c |X_kc|``: at that tempo the step cycle that places the beats
    stays in phase over the whole section. 51 tempi across the interval, then a parabola
    through the best and its neighbours.
    """
    tempi = tempo * (1.0 + np.linspace(-params.refine_span, params.refine_span, 51))
    coef = _coefficients(signals, fps, start, tempi, max(params.anchor_harmonics))
    score = np.einsum(
        "gkc,c->g", np.abs(coef[:, [k - 1 for k in params.anchor_harmonics]]), channels
    )
    g = int(np.argmax(score))
    if 0 < g < len(tempi) - 1:
        a, b, c = score[g - 1 : g + 2]
        denom = a - 2.0 * b + c
        shift = 0.5 * (a - c) / denom if denom < 0 else 0.0
        return float(tempi[g] + shift * (tempi[1] - tempi[0]))
    return float(tempi[g])


def pauses_lead(channels: np.ndarray) -> bool:
    """Whether the kinematic beats (the last channel) lead a take rather than its steps: their
    ``channel_weights`` entry (of ``(C,)``) is at least the feet's (``FEET_CHANNEL``). The two
    are the downbeat's bar cues; the clearer one decides."""
    return bool(channels[-1] >= channels[FEET_CHANNEL])


def section_phase(
    signals: np.ndarray,
    fps: float,
    start: int,
    tempo: float,
    params: GridParams,
    channels: np.ndarray,
) -> tuple[float, int, float]:
    """Beat phase and downbeat of a section at ``tempo``.

    ``signals``: the section's ``(L, C)`` frames, the first being frame ``start``, the last
    column the kinematic-beat envelope; ``channels``: ``channel_weights``. Returns
    ``(t0, down, clarity)``: the section's first beat ``t0`` (s; at most a quarter period
    before its first frame), which beat ``t0 + j · 60 / tempo`` (j = 0 … 3) starts the bars,
    and the downbeat's clarity: the gap between the two most downbeat-like beats over the
    range of the four (pause hits, or the feet's bar cycle; see the module docstring), 0 for
    a tie.
    """
    coef = _coefficients(signals, fps, start, np.array([tempo]))[0]  # (K, C)
    signs = np.ones(coef.shape[1])
    signs[-1] = -1.0  # every channel rises with motion but the last, the pauses
    act = coef @ (signs * channels)  # (K,)
    psi = np.arange(4096) / 4096.0  # phase within the bar
    harmonics = np.arange(1, N_HARMONICS + 1)
    folded = np.real(act[None, :] * np.exp(2j * np.pi * np.outer(psi, harmonics)))
    strongest = max(params.anchor_harmonics, key=lambda k: abs(act[k - 1]))
    beat_phase = psi[int(np.argmin(folded[:, strongest - 1]))] % 0.25
    bar_s = 240.0 / tempo
    period = bar_s / 4.0
    t_start = start / fps
    # the four beat phases, ordered by their first time from the section start on (a beat up
    # to a quarter period before it counts as at the start)
    first = t_start - 0.25 * period + ((beat_phase * bar_s - t_start + 0.25 * period) % period)
    cand = first + period * np.arange(4)
    index = np.round((cand / bar_s) % 1.0 * 4096).astype(int) % 4096
    lead = pauses_lead(channels)
    if lead:
        # pauses lead: the beat the kinematic beats (the last channel) hit most often, read at
        # every bar but the first and last beat period (a take's ends hold no speed minimum)
        edge = period * fps
        last = signals.shape[0] - 1
        bars = np.arange(int(np.ceil(signals.shape[0] / fps / bar_s)) + 1) * bar_s
        level = np.zeros(4)
        for k, t in enumerate((cand[:, None] + bars[None, :] - t_start) * fps):
            t = t[(t >= edge) & (t <= last - edge)]
            if len(t):
                level[k] = -np.interp(t, np.arange(last + 1), signals[:, -1]).mean()
    else:
        # steps lead: the low point of the feet's bar cycle (their bar harmonic)
        level = np.real(coef[0, FEET_CHANNEL] * np.exp(2j * np.pi * psi))[index]
    order = np.argsort(level)
    spread = float(level.max() - level.min())
    clarity = float(level[order[1]] - level[order[0]]) / spread if spread > 0 else 0.0
    if lead and clarity < params.downbeat_margin:
        # hit counts tie: the earliest of the tied beats (a section starts on a bar)
        down = int(np.flatnonzero(level - level[order[0]] <= params.downbeat_margin * spread)[0])
        return float(first), down, 0.0
    return float(first), int(order[0]), clarity


# --------------------------------------------------------------------------------------------
# 6. The take
# --------------------------------------------------------------------------------------------


def bars_at_downbeats(beats: np.ndarray, downbeats: np.ndarray) -> np.ndarray:
    """``(B, 5)`` bars: the 4 beats from each downbeat and the next downbeat, 4 beats on.

    A downbeat followed by another within 3 beats (a section boundary) starts no bar.
    """
    beats = np.asarray(beats, dtype=float)
    down = np.asarray(downbeats, dtype=bool)
    rows = [
        beats[i : i + 5]
        for i in np.flatnonzero(down)
        if i + 4 < len(beats) and down[i + 4] and not down[i + 1 : i + 4].any()
    ]
    return np.stack(rows) if rows else np.zeros((0, 5))


def estimate_grid(
    signals: np.ndarray,
    fps: float,
    params: GridParams | None = None,
    tempo_bpm: float | None = None,
) -> BeatGrid:
    """The beat and bar grid of a take from its ``step_signals`` ``(F, C)`` at ``fps``.

    ``tempo_bpm``: a known tempo (one section at that tempo; phase and downbeat estimated).
    Otherwise the pipeline of the module docstring. The frame-rate check is separate
    (``motion_tempo_bpm``). Raises ``ValueError`` for less than two seconds of frames or
    a non-positive tempo.
    """
    params = params or GridParams()
    signals = np.asarray(signals, dtype=float)
    n = signals.shape[0]
    if n < 2.0 * fps:
        raise ValueError(f"{n / fps:.2f} s is too short to estimate a beat grid (2 s at least)")
    if tempo_bpm is not None and not tempo_bpm > 0:
        raise ValueError(f"tempo must be positive, got {tempo_bpm}")
    weights = np.asarray(params.tempo_weights, dtype=float)
    block = max(1, int(round(params.block_s * fps)))
    tempi = tempo_grid(params.prior_bpm, params.tempo_step)
    spectra = bar_spectra(signals, fps, tempi, block)
    channels = channel_weights(spectra[-1], weights, params.clarity_power)
    # where the steps lead, the tempo is read at the step harmonics, channels weighted there
    steps_lead = not pauses_lead(channels)
    step_weights = np.zeros(max(params.step_harmonics))
    step_weights[[k - 1 for k in params.step_harmonics]] = 1.0
    tempo_channels = (
        channel_weights(spectra[-1], step_weights, params.clarity_power) if steps_lead else channels
    )
    if tempo_bpm is None:
        spans = tempo_sections(spectra, tempi, weights, channels, params)
    else:
        spans = [(0, spectra.shape[0] - 1)]

    sections: list[Section] = []
    beats: list[np.ndarray] = []
    downs: list[np.ndarray] = []
    last_t = (n - 1) / fps
    for i, j in spans:
        f0, f1 = i * block, min(n, j * block)
        seg = signals[f0:f1]
        if tempo_bpm is None:
            coef = spectra[j] - spectra[i]
            g, prom, med = _prominence(_tempo_score(coef, weights, channels))
            if steps_lead:
                g = int(np.argmax(_tempo_score(coef, step_weights, tempo_channels)))
            tempo = refine_tempo(seg, fps, f0, float(tempi[g]), params, tempo_channels)
            conf = confidence_from_ratio(prom / max(med, 1e-12))
        else:
            tempo, conf = float(tempo_bpm), 1.0
        t0, down, clarity = section_phase(seg, fps, f0, tempo, params, channels)
        period = 60.0 / tempo
        # beat m of the section sits at t0 + m · period; the first section reaches back to 0 s
        m_lo = -int(np.floor(t0 / period + 1e-9)) if i == 0 else 0
        hi = f1 / fps if j < spectra.shape[0] - 1 else last_t
        m = np.arange(m_lo, int(np.floor((hi - t0) / period + 1e-9)) + 1)
        b, d = t0 + m * period, (m - down) % 4 == 0
        if beats and len(beats[-1]):
            keep = b >= beats[-1][-1] + 0.5 * period
            b, d = b[keep], d[keep]
        sections.append(Section(f0 / fps, f1 / fps, tempo, conf, clarity))
        beats.append(b)
        downs.append(d)

    durations = np.array([s.end_s - s.start_s for s in sections])
    confidence = float(np.average([s.confidence for s in sections], weights=durations))
    flags: list[str] = []
    if confidence < STEADY_MIN_CONFIDENCE:
        flags.append("no_steady_beat")
    if len(sections) > 1:
        flags.append("tempo_changes")
    return BeatGrid(
        beats=np.concatenate(beats),
        downbeats=np.concatenate(downs),
        sections=sections,
        tempo_bpm=sections[int(np.argmax(durations))].tempo_bpm,
        confidence=confidence,
        flags=flags,
    )


def partner_agreement(
    beats_a: np.ndarray,
    downbeats_a: np.ndarray,
    tempo_a: float,
    beats_b: np.ndarray,
    downbeats_b: np.ndarray,
    tempo_b: float,
) -> dict:
    """How well the grids of two takes danced together (one capture, one music) agree.

    ``beats_*``: ``(N,)`` s; ``downbeats_*``: ``(D,)`` bar start times (s); ``tempo_*``: BPM.
    Over the span both grids cover, both directions pooled: ``tempo_diff_pct`` (relative to
    the mean tempo), ``median_offset_ms`` (each beat to the other grid's nearest beat),
    ``downbeat_agreement`` (share of downbeats with one of the other's within 1/8 beat) and
    ``downbeat_shift_beats`` (after a downbeat of ``a``, how many beats on, 0 … 3, the next
    bar of ``b`` most often starts: 0 when they agree, 2 for half a bar). A 4-beat bar has no
    8-count phase: bars that agree may still differ by 4 beats in an 8-count. NaN where the
    grids share no span.
    """
    a, b = np.sort(np.asarray(beats_a, dtype=float)), np.sort(np.asarray(beats_b, dtype=float))
    da = np.sort(np.asarray(downbeats_a, dtype=float))
    db = np.sort(np.asarray(downbeats_b, dtype=float))
    mean_tempo = 0.5 * (tempo_a + tempo_b)
    beat = 60.0 / mean_tempo
    out = {
        "tempo_diff_pct": float(abs(tempo_a - tempo_b) / mean_tempo * 100.0),
        "median_offset_ms": float("nan"),
        "downbeat_agreement": float("nan"),
        "downbeat_shift_beats": 0,
    }
    if not (len(a) and len(b)) or min(a[-1], b[-1]) <= max(a[0], b[0]):
        return out
    lo, hi = max(a[0], b[0]), min(a[-1], b[-1])

    def inside(t: np.ndarray) -> np.ndarray:
        return t[(t >= lo) & (t <= hi)]

    offsets = np.concatenate([nearest_distance(inside(a), b), nearest_distance(inside(b), a)])
    out["median_offset_ms"] = float(np.median(offsets) * 1000.0)
    hits = np.concatenate(
        [nearest_distance(inside(da), db) <= beat / 8, nearest_distance(inside(db), da) <= beat / 8]
    )
    if len(hits):
        out["downbeat_agreement"] = float(hits.mean())
    starts = inside(da)
    nxt = np.searchsorted(db, starts - beat / 8)
    ok = nxt < len(db)
    if ok.any():
        shift = np.round((db[nxt[ok]] - starts[ok]) / beat).astype(int) % 4
        out["downbeat_shift_beats"] = int(np.bincount(shift, minlength=4).argmax())
    return out


# --------------------------------------------------------------------------------------------
# The frame-rate check: prior-free motion tempo
# --------------------------------------------------------------------------------------------


def periodicity_signals(
    positions: np.ndarray,
    fps: float,
    *,
    root: int,
    feet: tuple[int, int],
    hands: tuple[int, int],
) -> np.ndarray:
    """Left/right-symmetric kinematic signals whose period is a bar (for ``motion_tempo_bpm``).

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
    overlap = (win - np.arange(n_lags)) / win
    total = np.zeros(n_lags)
    count = 0
    for s in range(0, max(1, n - win + 1), hop):
        w = x[s : s + win] - x[s : s + win].mean(axis=0)
        spec = np.fft.rfft(w, 2 * win, axis=0)
        ac = np.fft.irfft(spec * np.conj(spec), axis=0)[:n_lags]
        ok = ac[0] > 1e-9 * win
        if not ok.any():
            continue
        total += (ac[:, ok] / ac[0, ok] / overlap[:, None]).sum(axis=1)
        count += int(ok.sum())
    return total / count if count else total


def _value_near(ac: np.ndarray, lag: float, tol: float = 0.04) -> float:
    """Largest autocorrelation within ``±tol`` (relative) of ``lag`` frames; NaN beyond range."""
    lo, hi = int(np.floor(lag * (1 - tol))), int(np.ceil(lag * (1 + tol)))
    if hi >= len(ac) or lo < 1:
        return float("nan")
    return float(ac[lo : hi + 1].max())


def motion_tempo_bpm(signals: np.ndarray, fps: float) -> float:
    """Prior-free tempo (BPM): 4 beats per the shortest strong bar lag of ``signals (F, C)``
    (``periodicity_signals``).

    Bar lags are the autocorrelation peaks over ``FREE_BAR_RANGE_S`` scored
    ``(A(L) + A(2L)) / 2`` (a bar that repeats also repeats two bars on, which rejects chance
    short peaks); the shortest lag scoring ``SHORTEST_STRONG_RATIO`` × the best wins. NaN when
    nothing repeats.
    """
    ac = mean_local_autocorrelation(signals, fps, max_lag_s=2 * FREE_BAR_RANGE_S[1])
    idx, _ = find_peaks(ac)
    lags = idx[(idx >= FREE_BAR_RANGE_S[0] * fps) & (idx <= FREE_BAR_RANGE_S[1] * fps)]
    if len(lags) == 0:
        return float("nan")
    one = np.array([_value_near(ac, float(lag)) for lag in lags])
    two = np.array([_value_near(ac, 2.0 * lag) for lag in lags])
    score = np.where(np.isnan(two), one, 0.5 * (one + two))
    ok = score > 0
    if not ok.any():
        return float("nan")
    strong = lags[ok & (score >= SHORTEST_STRONG_RATIO * score[ok].max())]
    return float(240.0 * fps / strong.min())


def outside_prior(motion_tempo: float, prior_bpm: tuple[float, float]) -> bool:
    """Whether a motion tempo is too fast for the prior and for dance (flag
    ``tempo_outside_prior``): beyond ``PRIOR_MARGIN`` over the prior's top or
    ``PLAUSIBLE_MAX_BPM``, whichever is higher.

    Only a faster one is suspicious: periodicity over two bars (a slower motion tempo) is
    ordinary in dance, and so is a half-bar pattern of a slow dance under a narrow prior; a
    body that repeats faster than 4 beats at 220 BPM is not.
    """
    limit = max(prior_bpm[1], PLAUSIBLE_MAX_BPM) * (1 + PRIOR_MARGIN)
    return bool(np.isfinite(motion_tempo) and motion_tempo > limit)


# --------------------------------------------------------------------------------------------
# Bars from given beats, slots and signature labels
# --------------------------------------------------------------------------------------------


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


def nearest_distance(times: np.ndarray, events: np.ndarray) -> np.ndarray:
    """Distance (s) from each of ``times`` (any shape) to the nearest of ``events`` (inf
    without events)."""
    ev = np.sort(np.asarray(events, dtype=float))
    t = np.asarray(times, dtype=float)
    if len(ev) == 0:
        return np.full(t.shape, np.inf)
    i = np.clip(np.searchsorted(ev, t), 1, len(ev) - 1) if len(ev) > 1 else np.zeros(t.shape, int)
    left = np.abs(t - ev[np.maximum(i - 1, 0)])
    right = np.abs(t - ev[i])
    return np.minimum(left, right)


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
    nearest = nearest_distance(slots, kb)
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
    d = nearest_distance(kb, slots)
    return float(np.mean(d <= 0.25 * half))
