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
  are clearly closer (:data:`METER_MARGIN`; toward 4, the commoner meter,
  :data:`METER_MARGIN_TO_4`) wins over the network's choice. It needs no accent on the
  downbeat at all; where the downbeat evidence below forms far clearer bars of 4 than of 3
  (:data:`CLARITY_MARGIN`), 4 needs no margin and 3 is not taken.
- Bar phase from a beat-level bar-pointer model (Viterbi over "position in the bar" states,
  one meter): per beat the downbeat evidence is BeatNet's downbeat logit plus
  :data:`HARMONY_WEIGHT` times the harmonic change into the beat (chroma above the bass, first
  half of each beat so an anticipated chord still counts) less :data:`BACKBEAT_WEIGHT` times
  the noise onsets in the snare band (snares and claps: the backbeat, on beats 2 and 4, or 3
  in half time, never on the downbeat; it still marks the bar where off-beat drums take the
  kick off the downbeat), each z-scored, minus its moving average over :data:`LOCAL_BEATS`
  beats (a section's overall level says nothing about where its bars start). Each beat either
  advances the position or
  restarts the bar with log probability :data:`LOG_RESTART`, so the phase can change between
  sections (an inserted 2-beat measure, a tracker slip) when several bars of evidence agree.
  Next to a glitch of the beat grid (an interval 15 % off the running median: where the tracker
  slid onto the off-beats and back, or dropped or doubled a beat) the count of beats itself is
  not to be trusted, so a restart there costs only :data:`LOG_RESTART_GLITCH` (about one bar of
  evidence): without it the bars after each slip stayed one beat off for many bars.
- A network sure of its downbeats keeps them: where BeatNet's mean downbeat activation at the
  downbeats of its own best bar path is at least :data:`NET_CONFIDENT`
  (:func:`network_confidence`), the bar phase comes from its evidence alone; the harmony and
  the backbeat still decide the meter. On real recordings the harmony and the backbeat moved
  right downbeats by two beats where the network was sure; on generated hard songs, built to
  mislead it, the network is never that sure (docs/music.md).
- Duple: when the network says 2 beats per bar and the meter test does not say 3, the beats are
  grouped in 4 when the 4-beat downbeats clearly beat the half-bar beats (:data:`DUPLE_MARGIN`:
  a 4/4 song with a strong backbeat, or 2/4 music whose measures audibly pair up); otherwise 2
  is kept. For a dance product 2/4 and 4/4 differ only in notation: the dance bar is 4 beats
  (two 2/4 measures, see :func:`dancegraph.music.analysis.four_beat_bars`), and what matters is
  which measure starts it. So 2/4 music is reported as 4 when the pairing is heard and as 2
  only when the two measures are alike (then the bars pair from the first downbeat).

The measurements behind each part and its constants, on real recordings and generated songs:
docs/music.md ("Measurements behind the steps").
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "bar_clarity",
    "beat_features",
    "downbeat_contrast",
    "downbeat_evidence",
    "fold_contrast",
    "grid_glitches",
    "group_beats",
    "half_bar_contrast",
    "harmonic_change",
    "lag_distance",
    "meter_distances",
    "network_confidence",
    "peak_near",
    "phase_viterbi",
    "restart_costs",
    "zscore",
]

#: mean lag-distance difference (feature units) by which 3 or 4 must win to override the network
#: (between the margins of right and wrong overrides on generated songs)
METER_MARGIN = 0.15
#: the same for a halved grid (no network prior; 3 must win against 4 by this)
HALVED_METER_MARGIN = 0.075
#: the margin by which 4 must win where the network counted 3: 4/4 is the commoner meter, so
#: less evidence overrides toward it
METER_MARGIN_TO_4 = 0.075
#: how much more clearly the downbeat evidence must form bars of 4 than bars of 3 (mean evidence
#: at the downbeats less that at the other beats, z-units) to outweigh the bar-length
#: self-similarity: the meter goes from the network's 3 to 4 when the self-similarity leans to 4
#: at all and the evidence is this much clearer in 4, and not from 4 to 3 when it is
CLARITY_MARGIN = 1.0
#: weight of the harmonic change against the network's downbeat logit (both z-scored): the
#: network follows kicks and bass accents, which the hard cases put off the downbeat. On real
#: recordings the network is the better judge (the less weight, the steadier their bars); 1.25
#: is the least that keeps every generated regression case (docs/music.md)
HARMONY_WEIGHT = 1.25
#: weight of the noise onsets in the snare band (snares, claps: the backbeat) against the
#: downbeat evidence, subtracted: the backbeat falls on beats 2 and 4 (3 in half time), never
#: on the downbeat — what marks the bar where the kick does not (off-beat drums)
BACKBEAT_WEIGHT = 0.75
#: the network's mean downbeat activation at its own downbeats above which its bar phase stands
#: (:func:`network_confidence`): the harmony and the backbeat do not outvote a network this sure.
#: On real recordings its phase is the better one at every confidence; the generated hard songs,
#: built to mislead it, need the harmony and reach 0.66 on the regression seeds (docs/music.md)
NET_CONFIDENT = 0.7
#: mean downbeat evidence (z-units) by which 4-beat downbeats must beat the half-bar beats
DUPLE_MARGIN = 0.3
#: log probability of restarting the bar at a beat (about 10 nats: several bars of evidence)
LOG_RESTART = -10.0
#: log probability of a bar restart next to a glitch of the beat grid (a tracker slip: the count
#: of beats is least trustworthy there)
LOG_RESTART_GLITCH = -2.0
#: a glitch: an interval off the running median interval by this share ...
GLITCH_DEV = 0.15
#: ... over this many intervals; beats this close to it may restart cheaply
GLITCH_CONTEXT = 33
GLITCH_REACH = 2
#: beats over which the evidence's moving average is removed
LOCAL_BEATS = 12


def zscore(v: np.ndarray) -> np.ndarray:
    """``v`` (K,) standardised: zero mean, unit standard deviation (all zeros if constant)."""
    return (v - v.mean()) / (v.std() + 1e-9)


def peak_near(curve: np.ndarray, frames: np.ndarray, reach: int = 2) -> np.ndarray:
    """(K,) the maximum of ``curve`` (T,) within ``reach`` frames of each of ``frames`` (K,),
    clipped to the curve: a detector's peak lags or leads the beat it belongs to by a frame."""
    fr = np.clip(np.asarray(frames, dtype=np.int64), 0, len(curve) - 1)
    return np.array([curve[max(f - reach, 0) : f + reach + 1].max() for f in fr], dtype=np.float64)


def _beat_spans(frames: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) frame indices of each beat (the last one lasts the median interval)."""
    starts = np.clip(np.asarray(frames, dtype=np.int64), 0, n - 1)
    last = int(np.median(np.diff(starts))) if len(starts) > 1 else 1
    ends = np.r_[starts[1:], min(n, starts[-1] + max(last, 1))]
    return starts, np.maximum(ends, starts + 1)


def harmonic_change(chroma: np.ndarray, frames: np.ndarray, k: int = 2) -> np.ndarray:
    """(K,) harmonic change into each beat: cosine distance between the mean beat-synchronous
    chroma (12, T) of the ``k`` beats before and the ``k`` beats from it on (chords change on
    bar lines).

    Each beat's chroma is taken over the first half of the beat only, so a chord anticipated by
    an eighth note (arriving on the "and" of the last beat) still counts for the downbeat.
    """
    n = chroma.shape[1]
    starts, ends = _beat_spans(frames, n)
    halves = starts + np.maximum((ends - starts) // 2, 1)
    bc = np.stack([chroma[:, a:b].mean(axis=1) for a, b in zip(starts, halves, strict=True)])
    out = np.zeros(len(starts))
    for i in range(1, len(starts)):
        a = bc[max(i - k, 0) : i].mean(axis=0)
        b = bc[i : i + k].mean(axis=0)
        out[i] = 1.0 - float(a @ b) / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-9)
    return out


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
    starts, ends = _beat_spans(frames, n)
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
) -> np.ndarray:
    """(K,) downbeat evidence per beat: z(logit of the peak BeatNet downbeat activation (T, 2)
    within ±2 frames) + :data:`HARMONY_WEIGHT` z(harmonic change into the beat) - with
    ``snare_onset`` (T,) :data:`BACKBEAT_WEIGHT` z(its peak within ±2 frames), minus its moving
    average over :data:`LOCAL_BEATS` beats.

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
        return net - uniform_filter1d(net, LOCAL_BEATS, mode="nearest")
    e = net + HARMONY_WEIGHT * zscore(harmonic_change(chroma, frames))
    if snare_onset is not None:
        e = e - BACKBEAT_WEIGHT * zscore(peak_near(snare_onset, frames))
    return e - uniform_filter1d(e, LOCAL_BEATS, mode="nearest")


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
) -> float:
    """How clearly a beat grid (``frames`` (K,) at 50 fps) forms bars: grouped by
    :func:`group_beats` with no prior (``act`` (T, 2), the curves (T,) and ``chroma`` (12, T)),
    the mean :func:`downbeat_evidence` at its downbeats minus that at its other beats. NaN-free:
    0.0 under 16 beats (too few to group)."""
    k = len(frames)
    if k < 16:
        return 0.0
    positions, _, _ = group_beats(
        np.ones(k, dtype=np.int64), np.full(k, 4), act, frames, onset_env, bass_onset, chroma,
        meter_prior=False, snare_onset=snare_onset,
    )  # fmt: skip
    return downbeat_contrast(
        downbeat_evidence(act, frames, chroma, snare_onset=snare_onset), positions
    )


def downbeat_contrast(evidence: np.ndarray, positions: np.ndarray) -> float:
    """Mean downbeat ``evidence`` (K,) at the downbeats of ``positions`` (K,) minus that at the
    other beats (NaN without both)."""
    first, other = positions == 1, positions != 1
    if not first.any() or not other.any():
        return float("nan")
    return float(evidence[first].mean() - evidence[other].mean())


def phase_viterbi(
    evidence: np.ndarray, meter: int, log_restart: float | np.ndarray = LOG_RESTART
) -> np.ndarray:
    """(K,) positions in the bar (1 = downbeat) of the most likely beat-level bar-pointer path.

    States: position 0..meter-1; each beat advances the position (log 0) or restarts the bar
    (``log_restart``: one value, or (K,) per beat, the cost of restarting at that beat); a beat at position 0 scores its ``evidence`` (log-likelihood ratio units),
    the others 0.
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


def grid_glitches(frames: np.ndarray) -> np.ndarray:
    """(K,) bool: beats within :data:`GLITCH_REACH` beats of an interval that differs by more
    than :data:`GLITCH_DEV` from the running median interval (:data:`GLITCH_CONTEXT` beats)."""
    from scipy.ndimage import median_filter

    f = np.asarray(frames, dtype=np.float64)
    out = np.zeros(len(f), dtype=bool)
    if len(f) < 3:
        return out
    ibi = np.diff(f)
    med = median_filter(ibi, GLITCH_CONTEXT, mode="nearest")
    bad = np.flatnonzero(np.abs(ibi / np.maximum(med, 1e-9) - 1.0) > GLITCH_DEV)
    for i in bad:  # interval i lies between beats i and i + 1
        out[max(i + 1 - GLITCH_REACH, 0) : i + 1 + GLITCH_REACH] = True
    return out


def restart_costs(frames: np.ndarray) -> np.ndarray:
    """(K,) log probability of a bar restart at each beat: :data:`LOG_RESTART`, and
    :data:`LOG_RESTART_GLITCH` around glitches of the beat grid (:func:`grid_glitches`)."""
    return np.where(grid_glitches(frames), LOG_RESTART_GLITCH, LOG_RESTART)


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
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Re-decide the meter and bar phase of a decoded beat grid (see the module docstring).

    ``positions``/``meters`` (K,): the decoder's; ``act`` (T, 2) BeatNet's beat/downbeat
    activations; ``frames`` (K,) the beats' frame indices; ``onset_env``, ``bass_onset`` (T,)
    and ``chroma`` (12, T) at the same 50 fps; ``tracked`` (K,) bool: the beats the network
    tracked itself (not moved by a mend; default all); ``meter_prior=False`` when the decoder
    counted other beats (a grid at twice the tactus, every other beat kept): its meter is then
    no prior; 4 unless 3-beat bars repeat better by :data:`HALVED_METER_MARGIN`. Returns
    (positions, meters, warnings): warnings ``meter_regrouped`` when the meter differs from the
    decoder's, ``downbeat_rephased`` when the downbeats differ on more than a tenth of the beats
    (not with ``meter_prior=False``: the decoder's downbeats were eighths, not these beats).
    """
    positions = np.asarray(positions, dtype=np.int64)
    meters = np.asarray(meters, dtype=np.int64)
    n = len(positions)
    if n < 16:
        return positions, meters, []
    values, counts = np.unique(meters, return_counts=True)
    decoded = int(values[np.argmax(counts)])
    dist = meter_distances(beat_features(onset_env, bass_onset, chroma, frames))
    if not meter_prior:  # the decoder counted eighths: 4, the commoner meter, is the prior
        decoded = 4
    margin = METER_MARGIN if meter_prior else HALVED_METER_MARGIN
    e = downbeat_evidence(act, frames, chroma, tracked, snare_onset)
    restarts = restart_costs(frames)
    paths = {m: phase_viterbi(e, m, restarts) for m in (3, 4)}
    meter = decoded
    clearer_in_4 = float("nan")
    if np.isfinite(dist[3]) and np.isfinite(dist[4]):
        # how much more clearly the evidence forms bars of 4 than bars of 3
        contrast = {m: downbeat_contrast(e, paths[m]) for m in (3, 4)}
        clearer_in_4 = float(np.nan_to_num(contrast[4] - contrast[3]))
        if decoded in (2, 4) and dist[3] < dist[4] - margin and clearer_in_4 < CLARITY_MARGIN:
            meter = 3
        elif decoded == 3 and (
            dist[4] < dist[3] - METER_MARGIN_TO_4
            or (dist[4] < dist[3] and clearer_in_4 >= CLARITY_MARGIN)
        ):
            meter = 4
    grouping = 4 if meter == 2 else meter
    new = paths[grouping] if grouping in paths else phase_viterbi(e, grouping, restarts)
    # 4/4 with a strong backbeat, or 2/4: do the bar's two halves differ?
    if meter == 2 and half_bar_contrast(e, new) > DUPLE_MARGIN:
        meter = 4
    # a network sure of its downbeats keeps them: the harmony and the backbeat do not outvote it
    own = downbeat_evidence(act, frames, chroma, tracked, network_only=True)
    if network_confidence(act, frames, own, grouping, restarts, tracked) >= NET_CONFIDENT:
        new = phase_viterbi(own, grouping, restarts)
    if meter == 2:
        new = (new - 1) % 2 + 1
    notes = []
    if meter != decoded:
        notes.append(
            f"meter_regrouped: {decoded} -> {meter} beats per bar "
            f"(bar-length self-similarity: 3 beats {dist[3]:.2f}, 4 beats {dist[4]:.2f}; "
            f"downbeats clearer in bars of 4 by {clearer_in_4:.2f})"
        )
    changed = int(np.sum((new == 1) != (positions == 1)))
    if meter_prior and meter == decoded and changed > 0.1 * n:
        notes.append(f"downbeat_rephased: the downbeat moved on {changed} of {n} beats")
    return new, np.full(n, meter, dtype=np.int64), notes
