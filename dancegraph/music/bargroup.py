"""Bar grouping of a tracked beat grid: the meter and the downbeat of every beat.

The beat tracker's network (BeatNet) finds the beats well but leans to 4/4 and follows accents:
where the downbeat is marked neither by a kick nor by a chord change (syncopated bass, chords
anticipated by an eighth, off-beat drums, drumless sections) it often starts the bars on the
wrong beat or counts 4 beats in a waltz. :func:`group_beats` re-decides the grouping from the
tracked beats (K beats, 50 fps frame indices) with two kinds of evidence:

- Meter (3 or 4 beats per bar) from bar-length self-similarity: per beat a feature vector
  (onset strength and bass onset in 4 sub-beat slots, chroma over the beat), and the mean
  distance between beats ``L`` apart. Music repeats itself at the bar (rhythm patterns, chord
  per bar, melodic motifs), so the distance is lowest at multiples of the bar length: the meter
  whose lags (3, 6 against 4, 8 beats; the chroma at 6 and 8 only, see :func:`meter_distances`)
  are clearly closer (``meter_margin``; toward 4, the commoner meter,
  ``meter_margin_to_4``) wins over the network's choice. It needs no accent on the
  downbeat at all; where the downbeat evidence below forms far clearer bars of 4 than of 3
  (``clarity_margin``), 4 needs no margin and 3 is not taken.
- Bar phase from a beat-level bar-pointer model (Viterbi over "position in the bar" states,
  one meter): per beat the downbeat evidence is BeatNet's downbeat logit plus
  ``harmony_weight`` times the harmonic change into the beat (chroma above the bass, first
  half of each beat so an anticipated chord still counts) less ``backbeat_weight`` times
  the noise onsets in the snare band (snares and claps: the backbeat, on beats 2 and 4, or 3
  in half time, never on the downbeat; it still marks the bar where off-beat drums take the
  kick off the downbeat), each z-scored, minus its moving average over ``local_beats``
  beats (a section's overall level says nothing about where its bars start). Each beat either
  advances the position or
  restarts the bar with log probability ``log_restart``, so the phase can change between
  sections (an inserted 2-beat measure, a tracker slip) when several bars of evidence agree.
  Next to a glitch of the beat grid (an interval 15 % off the running median: where the tracker
  slid onto the off-beats and back, or dropped or doubled a beat) the count of beats itself is
  not to be trusted, so a restart there costs only ``log_restart_glitch`` (about one bar of
  evidence): without it the bars after each slip stayed one beat off for many bars.
- A network sure of its downbeats keeps them: where BeatNet's mean downbeat activation at the
  downbeats of its own best bar path is at least ``net_confident``
  (:func:`network_confidence`), the bar phase comes from its evidence alone; the harmony and
  the backbeat still decide the meter. On real recordings the harmony and the backbeat moved
  right downbeats by two beats where the network was sure; on generated hard songs, built to
  mislead it, the network is never that sure (docs/music.md).
- Duple: when the network says 2 beats per bar and the meter test does not say 3, the beats are
  grouped in 4 when the 4-beat downbeats clearly beat the half-bar beats (``duple_margin``:
  a 4/4 song with a strong backbeat, or 2/4 music whose measures audibly pair up); otherwise 2
  is kept. For a dance product 2/4 and 4/4 differ only in notation: the dance bar is 4 beats
  (two 2/4 measures, see :func:`dancegraph.music.analysis.four_beat_bars`), and what matters is
  which measure starts it. So 2/4 music is reported as 4 when the pairing is heard and as 2
  only when the two measures are alike (then the bars pair from the first downbeat).

The measurements behind each part and its constants, on real recordings and generated songs:
docs/music.md ("Measurements behind the steps").
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dancegraph.music.params import GroupParams
from dancegraph.music.signal import beat_spans, harmonic_change, peak_near, zscore

__all__ = [
    "bar_clarity",
    "beat_features",
    "downbeat_contrast",
    "downbeat_evidence",
    "fold_contrast",
    "Grouping",
    "grid_glitches",
    "group_beats",
    "half_bar_contrast",
    "lag_distance",
    "meter_distances",
    "network_confidence",
    "phase_viterbi",
    "restart_costs",
    "section_phases",
]


def beat_features(
    onset_env: np.ndarray,
    bass_onset: np.ndarray,
    chroma: np.ndarray,
    frames: np.ndarray,
    n_sub: int = 4,
) -> np.ndarray:
    """(K, 2 * n_sub + 12) per-beat features: the peak onset strength and bass onset (T,) in
    ``n_sub`` equal slots of the beat (its rhythm) and the mean chroma (12, T) over the beat
    (its harmony); each block standardised over the song and weighted equally."""
    n = min(len(onset_env), len(bass_onset), chroma.shape[1])
    starts, ends = beat_spans(frames, n)
    rows = []
    for a, b in zip(starts, ends, strict=True):
        b = min(max(b, a + n_sub), n)
        edges = a + (np.arange(n_sub + 1) * (b - a)) // n_sub
        slots = [(edges[j], max(edges[j + 1], edges[j] + 1)) for j in range(n_sub)]
        rows.append(
            np.r_[
                [onset_env[s:e].max() for s, e in slots],
                [bass_onset[s:e].max() for s, e in slots],
                chroma[:, a:b].mean(axis=1),
            ]
        )
    x = np.asarray(rows, dtype=np.float64)
    blocks = []
    for sl in (slice(0, n_sub), slice(n_sub, 2 * n_sub), slice(2 * n_sub, None)):
        blk = x[:, sl] - x[:, sl].mean(axis=0)
        blk = blk / np.where(blk.std(axis=0) > 1e-9, blk.std(axis=0), 1.0)
        blocks.append(blk / np.sqrt(blk.shape[1]))
    return np.concatenate(blocks, axis=1)


def meter_distances(x: np.ndarray) -> dict[int, float]:
    """Bar-length self-similarity of per-beat features ``x`` (K, F) from :func:`beat_features`
    (its last 12 columns the chroma): for meters 3 and 4 the mean Euclidean distance between
    beats one and two bars apart (lags 3, 6 and 4, 8). Lower = the music repeats at that bar
    length. NaN when the song is too short (under 4 bars of 4).

    The chroma counts at the two-bar lags only. With a chord per bar, beats one lag apart share
    the chord more often the shorter the lag (lag 3 in 4/4: a quarter of the pairs in one bar;
    lag 4: none), so at one bar the chroma of 4/4 music favours 3; at 6 and 8 beats every pair
    crosses a bar line in either meter."""
    rhythm = x[:, :-12]
    return {
        3: (lag_distance(rhythm, 3) + lag_distance(x, 6)) / 2,
        4: (lag_distance(rhythm, 4) + lag_distance(x, 8)) / 2,
    }


def lag_distance(x: np.ndarray, lag: int) -> float:
    """Mean Euclidean distance between per-beat features ``x`` (K, F) ``lag`` beats apart (NaN
    under ``lag + 9`` beats)."""
    return float(np.linalg.norm(x[lag:] - x[:-lag], axis=1).mean()) if len(x) > lag + 8 else np.nan


def downbeat_evidence(
    act: np.ndarray,
    frames: np.ndarray,
    chroma: np.ndarray,
    tracked: np.ndarray | None = None,
    snare_onset: np.ndarray | None = None,
    network_only: bool = False,
    p: GroupParams = GroupParams(),
) -> np.ndarray:
    """(K,) downbeat evidence per beat: z(logit of the peak BeatNet downbeat activation (T, 2)
    within ±2 frames) + ``harmony_weight`` z(harmonic change into the beat) - with
    ``snare_onset`` (T,) ``backbeat_weight`` z(its peak within ±2 frames), minus its moving
    average over ``local_beats`` beats (``p``: :class:`~dancegraph.music.params.GroupParams`).

    ``tracked`` (K,) bool: the beats the network itself tracked (default all). The network's
    downbeat activation belongs to its own beat grid, so at beats a mend moved (onto the other
    half of the beat) it says nothing: there the term is 0 (its mean) and the harmony decides.
    ``network_only``: the network's term alone (no harmony, no backbeat).
    """
    from scipy.ndimage import uniform_filter1d

    own = np.ones(len(frames), dtype=bool) if tracked is None else np.asarray(tracked, dtype=bool)
    d = np.clip(peak_near(act[:, 1], frames), 1e-3, 1 - 1e-3)
    logit = np.log(d) - np.log1p(-d)
    net = np.zeros(len(frames))
    if own.sum() > 1:
        net[own] = zscore(logit[own])
    if network_only:
        return net - uniform_filter1d(net, p.local_beats, mode="nearest")
    e = net + p.harmony_weight * zscore(harmonic_change(chroma, frames))
    if snare_onset is not None:
        e = e - p.backbeat_weight * zscore(peak_near(snare_onset, frames))
    return e - uniform_filter1d(e, p.local_beats, mode="nearest")


def network_confidence(
    act: np.ndarray,
    frames: np.ndarray,
    own: np.ndarray,
    meter: int,
    restarts: np.ndarray,
    tracked: np.ndarray | None = None,
) -> float:
    """How sure the network is of its downbeats: BeatNet's mean downbeat activation (``act``
    (T, 2), peak within ±2 frames of ``frames`` (K,)) at the downbeats of the bar path its own
    evidence ``own`` (K,) (:func:`downbeat_evidence` with ``network_only``) takes in ``meter``,
    over the beats it tracked (``tracked`` (K,) bool, default all). 0..1; 0.0 without such a
    downbeat."""
    path = phase_viterbi(own, meter, restarts)
    at = (path == 1) & (np.ones(len(frames), dtype=bool) if tracked is None else tracked)
    if not at.any():
        return 0.0
    return float(peak_near(act[:, 1], frames)[at].mean())


def half_bar_contrast(evidence: np.ndarray, positions: np.ndarray) -> float:
    """Mean downbeat ``evidence`` (K,) at the bars' first beats minus that at their third beats
    (``positions`` (K,) of 4-beat bars; NaN without both): small when the middle of the bar is
    marked as strongly as its start, i.e. when a "bar" holds two bars of music."""
    first, middle = evidence[positions == 1], evidence[positions == 3]
    if len(first) == 0 or len(middle) == 0:
        return float("nan")
    return float(first.mean() - middle.mean())


def fold_contrast(values: np.ndarray, cycle: np.ndarray, period: int) -> float:
    """Phase-free contrast of ``values`` (K,) folded over ``cycle`` (K,) ints 0..period-1: the
    largest mean at one place of the cycle minus the mean half a period away (``period`` even).
    Small when the cycle holds two alike halves (a "bar" that is two bars of the music)."""
    means = np.array(
        [values[cycle == c].mean() if (cycle == c).any() else np.nan for c in range(period)]
    )
    if np.isnan(means).any():
        return float("nan")
    best = int(np.argmax(means))
    return float(means[best] - means[(best + period // 2) % period])


def bar_clarity(
    act: np.ndarray,
    frames: np.ndarray,
    onset_env: np.ndarray,
    bass_onset: np.ndarray,
    chroma: np.ndarray,
    snare_onset: np.ndarray,
    p: GroupParams = GroupParams(),
) -> float:
    """How clearly a beat grid (``frames`` (K,) at 50 fps) forms bars: grouped by
    :func:`group_beats` with no prior (``act`` (T, 2), the curves (T,) and ``chroma`` (12, T);
    ``p`` the grouping's parameters),
    the mean :func:`downbeat_evidence` at its downbeats minus that at its other beats. NaN-free:
    0.0 under 16 beats (too few to group)."""
    k = len(frames)
    if k < 16:
        return 0.0
    positions = group_beats(
        np.ones(k, dtype=np.int64), np.full(k, 4), act, frames, onset_env, bass_onset, chroma,
        meter_prior=False, snare_onset=snare_onset, p=p,
    ).positions  # fmt: skip
    return downbeat_contrast(
        downbeat_evidence(act, frames, chroma, snare_onset=snare_onset, p=p), positions
    )


def downbeat_contrast(evidence: np.ndarray, positions: np.ndarray) -> float:
    """Mean downbeat ``evidence`` (K,) at the downbeats of ``positions`` (K,) minus that at the
    other beats (NaN without both)."""
    first, other = positions == 1, positions != 1
    if not first.any() or not other.any():
        return float("nan")
    return float(evidence[first].mean() - evidence[other].mean())


def phase_viterbi(
    evidence: np.ndarray, meter: int, log_restart: float | np.ndarray = GroupParams.log_restart
) -> np.ndarray:
    """(K,) positions in the bar (1 = downbeat) of the most likely beat-level bar-pointer path.

    States: position 0..meter-1; each beat advances the position (log 0) or restarts the bar
    (``log_restart``: one value, or (K,) per beat, the cost of restarting at that beat); a beat
    at position 0 scores its ``evidence`` (log-likelihood ratio units), the others 0.
    """
    e = np.asarray(evidence, dtype=np.float64)
    m, n = int(meter), len(e)
    restart = np.broadcast_to(np.asarray(log_restart, dtype=np.float64), (n,))
    advance = np.zeros((m, m), dtype=bool)  # from (rows) -> to (columns)
    advance[np.arange(m), (np.arange(m) + 1) % m] = True
    emit = np.zeros((n, m))
    emit[:, 0] = e
    v = emit[0].copy()
    back = np.zeros((n, m), dtype=np.int64)
    for i in range(1, n):
        cand = v[:, None] + np.where(advance, 0.0, restart[i])
        back[i] = np.argmax(cand, axis=0)
        v = cand[back[i], np.arange(m)] + emit[i]
    path = np.empty(n, dtype=np.int64)
    path[-1] = int(np.argmax(v))
    for i in range(n - 1, 0, -1):
        path[i - 1] = back[i, path[i]]
    return path + 1


def section_phases(
    evidence: np.ndarray,
    path: np.ndarray,
    meter: int,
    restarts: np.ndarray,
    min_gain_per_bar: float,
) -> np.ndarray:
    """(K,) positions in the bar (1 = downbeat): the bar-pointer ``path`` (K,) of
    :func:`phase_viterbi` with the jumps between its sections (runs of beats in one bar phase)
    judged by each section's own downbeat ``evidence`` (K,) in ``meter``. A jump stands where
    the sections on both sides prefer their own phase to the other's by at least
    ``min_gain_per_bar`` a bar on average; the weakest jump below that goes first, its two
    sections becoming one in the phase with more evidence over both, and the rest are judged
    again. A jump next to a grid glitch (``restarts`` (K,) above its least value, see
    :func:`restart_costs`) always stands: there the count of beats itself moved.

    Why: the path buys a jump where the evidence summed over the section after it beats a
    fixed cost, so whether a long section leaning weakly to another phase gets its own depends
    on how much of it was analysed (an excerpt of a song sees less of it); a mean gain a bar is
    the section's own (docs/music.md, "One bar phase through a song")."""
    e = np.asarray(evidence, dtype=np.float64)
    m, n = int(meter), len(e)
    pos = np.asarray(path, dtype=np.int64)
    if n == 0:
        return pos.copy()
    fixed = np.asarray(restarts, dtype=np.float64) > float(np.min(restarts))
    # a section: the beats between two jumps of the path, in one bar phase: [first, end, r],
    # its downbeats on the beats whose index is r mod meter
    starts = [0] + [i for i in range(1, n) if pos[i] != pos[i - 1] % m + 1]
    sections = [
        [a, b, int((a - pos[a] + 1) % m)] for a, b in zip(starts, [*starts[1:], n], strict=True)
    ]

    def score(a: int, b: int, r: int) -> float:
        return float(e[a:b][(np.arange(a, b) - r) % m == 0].sum())

    while True:
        weakest, at = min_gain_per_bar, -1
        for k in range(1, len(sections)):
            (a, mid, rx), (_, b, ry) = sections[k - 1], sections[k]
            if fixed[mid] or rx == ry:
                continue
            gx = (score(a, mid, rx) - score(a, mid, ry)) * m / (mid - a)
            gy = (score(mid, b, ry) - score(mid, b, rx)) * m / (b - mid)
            if min(gx, gy) < weakest:
                weakest, at = min(gx, gy), k
        if at < 0:
            break
        (a, _, rx), (_, b, ry) = sections[at - 1], sections[at]
        r = rx if score(a, b, rx) >= score(a, b, ry) else ry
        sections[at - 1 : at + 1] = [[a, b, r]]
    return _positions(sections, m, n)


def _positions(sections: list[list[int]], m: int, n: int) -> np.ndarray:
    """(n,) positions in bars of ``m`` of the beats of ``sections`` ([first, end, r] each,
    the downbeats on the beats whose index is r mod ``m``)."""
    out = np.empty(n, dtype=np.int64)
    for a, b, r in sections:
        out[a:b] = (np.arange(a, b) - r) % m + 1
    return out


def grid_glitches(frames: np.ndarray, p: GroupParams = GroupParams()) -> np.ndarray:
    """(K,) bool: beats within ``glitch_reach`` beats of an interval that differs by more
    than ``glitch_dev`` from the running median interval (``glitch_context`` beats)."""
    from scipy.ndimage import median_filter

    f = np.asarray(frames, dtype=np.float64)
    out = np.zeros(len(f), dtype=bool)
    if len(f) < 3:
        return out
    ibi = np.diff(f)
    med = median_filter(ibi, p.glitch_context, mode="nearest")
    bad = np.flatnonzero(np.abs(ibi / np.maximum(med, 1e-9) - 1.0) > p.glitch_dev)
    for i in bad:  # interval i lies between beats i and i + 1
        out[max(i + 1 - p.glitch_reach, 0) : i + 1 + p.glitch_reach] = True
    return out


def restart_costs(frames: np.ndarray, p: GroupParams = GroupParams()) -> np.ndarray:
    """(K,) log probability of a bar restart at each beat: ``log_restart``, and
    ``log_restart_glitch`` around glitches of the beat grid (:func:`grid_glitches`)."""
    return np.where(grid_glitches(frames, p), p.log_restart_glitch, p.log_restart)


class Grouping(NamedTuple):
    """The bar grouping of a beat grid: ``positions`` (K,) in the bar (1 = downbeat),
    ``meters`` (K,) beats per bar as reported, ``notes`` its warnings, and ``music_meter`` the
    music's own meter: 2 where 2/4 measures were paired into bars of 4 (the dance bar), else
    the reported one."""

    positions: np.ndarray
    meters: np.ndarray
    notes: list[str]
    music_meter: int


def _decide_meter(
    decoded: int,
    dist: dict[int, float],
    e: np.ndarray,
    paths: dict[int, np.ndarray],
    margin: float,
    p: GroupParams,
) -> tuple[int, float]:
    """The meter (2, 3 or 4) from the ``decoded`` one, the bar-length self-similarity ``dist``
    (:func:`meter_distances`) and the downbeat evidence ``e`` (K,) on its best bar ``paths`` of
    3 and 4: (meter, how much more clearly the evidence forms bars of 4 than of 3)."""
    meter = decoded
    clearer_in_4 = float("nan")
    if np.isfinite(dist[3]) and np.isfinite(dist[4]):
        contrast = {m: downbeat_contrast(e, paths[m]) for m in (3, 4)}
        clearer_in_4 = float(np.nan_to_num(contrast[4] - contrast[3]))
        if decoded in (2, 4) and dist[3] < dist[4] - margin and clearer_in_4 < p.clarity_margin:
            meter = 3
        elif decoded == 3 and (
            dist[4] < dist[3] - p.meter_margin_to_4
            or (dist[4] < dist[3] and clearer_in_4 >= p.clarity_margin)
        ):
            meter = 4
    return meter, clearer_in_4


def _grouping_notes(
    decoded: int, meter: int, dist: dict[int, float], clearer_in_4: float, changed: np.ndarray
) -> list[str]:
    """The warnings of a grouping: ``meter_regrouped`` when ``meter`` is not the ``decoded``
    one, ``downbeat_rephased`` when the downbeat ``changed`` (K,) bool on more than a tenth of
    the beats."""
    notes = []
    if meter != decoded:
        notes.append(
            f"meter_regrouped: {decoded} -> {meter} beats per bar "
            f"(bar-length self-similarity: 3 beats {dist[3]:.2f}, 4 beats {dist[4]:.2f}; "
            f"downbeats clearer in bars of 4 by {clearer_in_4:.2f})"
        )
    n, moved = len(changed), int(changed.sum())
    if meter == decoded and moved > 0.1 * n:
        notes.append(f"downbeat_rephased: the downbeat moved on {moved} of {n} beats")
    return notes


def group_beats(
    positions: np.ndarray,
    meters: np.ndarray,
    act: np.ndarray,
    frames: np.ndarray,
    onset_env: np.ndarray,
    bass_onset: np.ndarray,
    chroma: np.ndarray,
    tracked: np.ndarray | None = None,
    meter_prior: bool = True,
    snare_onset: np.ndarray | None = None,
    p: GroupParams = GroupParams(),
) -> Grouping:
    """Re-decide the meter and bar phase of a decoded beat grid (see the module docstring).

    ``positions``/``meters`` (K,): the decoder's; ``act`` (T, 2) BeatNet's beat/downbeat
    activations; ``frames`` (K,) the beats' frame indices; ``onset_env``, ``bass_onset`` (T,)
    and ``chroma`` (12, T) at the same 50 fps; ``tracked`` (K,) bool: the beats the network
    tracked itself (not moved by a mend; default all); ``meter_prior=False`` when the decoder
    counted other beats (a grid at twice the tactus, every other beat kept): its meter is then
    no prior; 4 unless 3-beat bars repeat better by ``p.halved_meter_margin``. Returns the
    :class:`Grouping`; warnings ``meter_regrouped`` when the meter differs from the decoder's,
    ``downbeat_rephased`` when the downbeats differ on more than a tenth of the beats (not with
    ``meter_prior=False``: the decoder's downbeats were eighths, not these beats)."""
    positions = np.asarray(positions, dtype=np.int64)
    meters = np.asarray(meters, dtype=np.int64)
    n = len(positions)
    values, counts = np.unique(meters, return_counts=True)
    if n < 16:
        return Grouping(positions, meters, [], int(values[np.argmax(counts)]) if n else 4)
    # without a prior the decoder counted eighths: 4, the commoner meter, is the prior
    decoded = int(values[np.argmax(counts)]) if meter_prior else 4
    dist = meter_distances(beat_features(onset_env, bass_onset, chroma, frames))
    margin = p.meter_margin if meter_prior else p.halved_meter_margin
    e = downbeat_evidence(act, frames, chroma, tracked, snare_onset, p=p)
    restarts = restart_costs(frames, p)
    paths = {m: phase_viterbi(e, m, restarts) for m in (3, 4)}
    meter, clearer_in_4 = _decide_meter(decoded, dist, e, paths, margin, p)
    grouping = 4 if meter == 2 else meter
    new = paths[grouping] if grouping in paths else phase_viterbi(e, grouping, restarts)
    music_meter = meter
    # 4/4 with a strong backbeat, or 2/4: do the bar's two halves differ?
    if meter == 2 and half_bar_contrast(e, new) > p.duple_margin:
        meter = 4
    # a network sure of its downbeats keeps them: the harmony and the backbeat do not outvote it
    own = downbeat_evidence(act, frames, chroma, tracked, network_only=True, p=p)
    if network_confidence(act, frames, own, grouping, restarts, tracked) >= p.net_confident:
        e, new = own, phase_viterbi(own, grouping, restarts)
    new = section_phases(e, new, grouping, restarts, p.min_section_gain)
    if meter == 2:
        new = (new - 1) % 2 + 1
    notes = _grouping_notes(
        decoded, meter, dist, clearer_in_4, changed=(new == 1) != (positions == 1)
    )
    if not meter_prior:
        notes = [x for x in notes if not x.startswith("downbeat_rephased")]
    return Grouping(new, np.full(n, meter, dtype=np.int64), notes, music_meter)
