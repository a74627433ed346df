"""Phrases and structure tags from bar-synchronous features.

Method (after Serra, Müller, Grosche & Arcos 2012/2014, "Unsupervised music structure annotation
by time series structure features and segment similarity"), at bar resolution:

1. Per bar, chroma (harmony) and MFCC (timbre) averaged over 4 equal parts of the bar, each
   block standardised; their concatenation is the bar's feature vector.
2. Bar distance matrix ``D`` (Euclidean, divided by its median off-diagonal value).
3. Structure features: a mutual k-nearest-neighbour recurrence matrix, read in time-lag form
   (circular lag), smoothed with a Gaussian along time; their change from bar to bar is the
   *repetition novelty*. A Foote checkerboard kernel on the bars' timbre similarity (mean
   MFCC, ``exp(-Dt)``) gives the *homogeneity novelty*. The two, each scaled to [0, 1], are
   averaged (``NOVELTY_MIX`` can favour their maximum).
4. Boundaries by dynamic programming over bar boundaries: each boundary earns its novelty less a
   threshold, each phrase pays a length prior that prefers ``unit`` and ``2 * unit`` bars
   (4 and 8 bars in 4/4), so boundaries snap to bars and phrases to 4/8-bar units. Two
   adjacent ``unit``-bar phrases that always come as a pair and are alike, or sound alike
   (timbre), become one ``2 * unit``-bar phrase (a unit that also occurs alone stays a phrase
   of its own, so back-to-back repeats of a 4-bar section are kept apart) (a section made of a repeated or answered
   4-bar pattern); fragments shorter than ``unit`` join a same-label neighbour.
5. Labels: segment distance = mean, along the best-aligned diagonal, of the distances between
   bar-long windows starting at each beat (bar offsets, and shifts of up to 3 beats so a repeat
   whose downbeat was tracked off still matches), plus a length-mismatch penalty;
   average-linkage clustering at ``LABEL_THRESHOLD``; labels A, B, … in order of first
   appearance, so repeats of a section share a label. Occurrence counts from 0.
6. Meter identity within each phrase: bars whose coarse log-mel spectrograms and chroma are
   near-identical (both distances below ``METER_ID_THRESHOLD`` × the song's median bar
   distance) share an id (0, 1, … in order of first appearance inside the phrase).

Bar indices refer to the bars given (the analysis' 4-beat bars); ``end_bar`` is exclusive.
"""

from __future__ import annotations

import string
from dataclasses import dataclass

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.distance import cdist, squareform

from dancegraph.music.features import FrameFeatures, bar_synchronous

#: DP boundary threshold on the combined novelty (scaled to [0, 1]).
BOUNDARY_THRESHOLD = 0.3
#: Timbre distance below which two different adjacent 4-bar phrases may be halves of one.
PAIR_TIMBRE_THRESHOLD = 0.75
#: Weight of max(rep, hom) against their mean in the combined novelty.
NOVELTY_MIX = 0.0
#: Segment distance below which two phrases get the same label (``D`` is median-scaled).
LABEL_THRESHOLD = 0.65
#: Bar spectrogram distance (fraction of the median) below which bars share a meter id.
METER_ID_THRESHOLD = 0.2


@dataclass
class Structure:
    """Phrases and per-bar tags of a song.

    ``phrases``: list of ``{label, occurrence, start_bar, end_bar}`` (end exclusive);
    ``tags``: per bar ``{label, occurrence, index, meter_id}``; ``novelty`` (B,) the boundary
    evidence at the start of each bar; ``distance`` (B, B) the bar distance matrix.
    """

    phrases: list[dict]
    tags: list[dict]
    novelty: np.ndarray
    distance: np.ndarray


def _standardise(x: np.ndarray) -> np.ndarray:
    x = x - x.mean(axis=0, keepdims=True)
    sd = x.std(axis=0, keepdims=True)
    return x / np.where(sd > 1e-9, sd, 1.0)


def bar_feature_matrix(ff: FrameFeatures, bars: np.ndarray, n_sub: int = 4) -> np.ndarray:
    """``(B, n_sub * 32)``: standardised bar-synchronous chroma (12) and MFCC (20), the two
    blocks weighted equally."""
    chroma = bar_synchronous(ff.chroma, ff.times, bars, n_sub)
    mfcc = bar_synchronous(ff.mfcc[1:], ff.times, bars, n_sub)  # MFCC 0 is loudness: left out
    blocks = [_standardise(chroma), _standardise(mfcc)]
    return np.concatenate([b / np.sqrt(b.shape[1]) for b in blocks], axis=1)


def distance_matrix(x: np.ndarray) -> np.ndarray:
    """``(B, B)`` Euclidean distances between rows of ``x``, divided by the median off-diagonal one."""
    d = cdist(x, x)
    off = d[~np.eye(len(d), dtype=bool)]
    med = float(np.median(off)) if off.size else 1.0
    return d / (med if med > 1e-9 else 1.0)


def repetition_novelty(d: np.ndarray, k: int | None = None, sigma: float = 1.0) -> np.ndarray:
    """Serra structure-feature novelty ``(B,)``: change of the time-lag recurrence at each bar."""
    n = len(d)
    if n < 3:
        return np.zeros(n)
    k = k or max(2, int(round(0.08 * n)))
    k = min(k, n - 1)
    order = np.argsort(d + np.eye(n) * 1e9, axis=1)[:, :k]
    knn = np.zeros((n, n), dtype=bool)
    knn[np.repeat(np.arange(n), k), order.ravel()] = True
    rec = (knn & knn.T).astype(float)
    lag = np.stack([np.roll(rec[i], -i) for i in range(n)])  # lag[i, l] = rec[i, i + l]
    lag = gaussian_filter1d(lag, sigma, axis=0, mode="nearest")
    nov = np.zeros(n)
    nov[1:] = np.sqrt(((lag[1:] - lag[:-1]) ** 2).sum(axis=1))
    return nov


def checkerboard_novelty(d: np.ndarray, half: int = 4) -> np.ndarray:
    """Foote novelty ``(B,)`` of the similarity ``exp(-d)`` with a Gaussian-tapered checkerboard
    kernel of ``half`` bars each side; value i is the evidence of a boundary before bar i."""
    n = len(d)
    s = np.exp(-d)
    pad = np.pad(s, half, mode="edge")
    u = np.arange(-half, half) + 0.5
    taper = np.exp(-((u / half) ** 2) * 2)
    kern = np.sign(u)[:, None] * np.sign(u)[None, :] * taper[:, None] * taper[None, :]
    nov = np.zeros(n)
    for i in range(1, n):
        c = i + half
        nov[i] = (pad[c - half : c + half, c - half : c + half] * kern).sum()
    return np.maximum(nov, 0.0)


def _unit_scale(x: np.ndarray) -> np.ndarray:
    m = float(x.max()) if x.size else 0.0
    return x / m if m > 1e-9 else np.zeros_like(x)


def timbre_distance(ff: FrameFeatures, bars: np.ndarray) -> np.ndarray:
    """``(B, B)`` median-scaled distances of the bars' mean MFCCs (1..19): the sound of a bar,
    whatever its chord; homogeneous within a section, changing between sections."""
    return distance_matrix(_standardise(bar_synchronous(ff.mfcc[1:], ff.times, bars, 1)))


def combined_novelty(d: np.ndarray, unit: int, dt: np.ndarray | None = None) -> np.ndarray:
    """Boundary evidence ``(B,)`` in [0, 1] from the repetition novelty of ``d`` and the
    homogeneity novelty of the timbre distances ``dt`` (default ``d``), each scaled to [0, 1]:
    their maximum (weight ``NOVELTY_MIX``) and mean. A section repeated together with its
    neighbour (``A B A B``) leaves the time-lag structure unchanged at A|B; the change of
    sound still marks it."""
    rep = _unit_scale(repetition_novelty(d))
    hom = _unit_scale(checkerboard_novelty(d if dt is None else dt, half=unit))
    return NOVELTY_MIX * np.maximum(rep, hom) + (1 - NOVELTY_MIX) * 0.5 * (rep + hom)


def length_prior(length: int, unit: int) -> float:
    """Cost of a phrase of ``length`` bars: 0 for 1 or 2 units, more for other lengths."""
    if length in (unit, 2 * unit):
        return 0.0
    if length in (3 * unit, 4 * unit):
        return 0.15
    if unit % 2 == 0 and length % (unit // 2) == 0:
        return 0.35
    return 0.6


def segment(novelty: np.ndarray, unit: int = 4, threshold: float = BOUNDARY_THRESHOLD) -> list[int]:
    """Phrase boundaries (bar indices, from 0 to B inclusive) maximising
    ``Σ (novelty[b] − threshold) − Σ length_prior`` with phrases at most ``4 * unit`` bars."""
    n = len(novelty)
    if n == 0:
        return [0]
    max_len = max(4 * unit, 1)
    best = np.full(n + 1, -np.inf)
    back = np.zeros(n + 1, dtype=int)
    best[0] = 0.0
    for j in range(1, n + 1):
        for i in range(max(0, j - max_len), j):
            gain = best[i] - length_prior(j - i, unit)
            if i > 0:
                gain += novelty[i] - threshold
            if gain > best[j]:
                best[j], back[j] = gain, i
    bounds = [n]
    while bounds[-1] > 0:
        bounds.append(int(back[bounds[-1]]))
    return bounds[::-1]


def beat_distance(ff: FrameFeatures, bars: np.ndarray, sub: int = 4) -> np.ndarray:
    """``(B*sub, B*sub)`` distances between one-bar windows that start at each beat.

    The features of each quarter of a bar (chroma and MFCC, standardised, equally weighted) are
    compared (median-scaled Euclidean distance) and averaged along the diagonal over ``sub``
    steps, so entry (i, j) compares the bar-long stretches starting at beats i and j. Labels
    use this so that a repeat whose downbeat was tracked a beat or two off still matches.
    """
    n = len(bars)
    chroma = bar_synchronous(ff.chroma, ff.times, bars, sub).reshape(n * sub, -1)
    mfcc = bar_synchronous(ff.mfcc[1:], ff.times, bars, sub).reshape(n * sub, -1)
    x = np.concatenate(
        [b / np.sqrt(b.shape[1]) for b in (_standardise(chroma), _standardise(mfcc))], axis=1
    )
    db = distance_matrix(x)
    m = len(db)
    out = np.zeros_like(db)
    for t in range(sub):
        idx = np.minimum(np.arange(m) + t, m - 1)
        out += db[np.ix_(idx, idx)]
    return out / sub


def diagonal_cumsum(d: np.ndarray) -> np.ndarray:
    """``(n+1, n+1)`` sums along the diagonals: ``c[i+k, j+k] - c[i, j] = sum_t<k d[i+t, j+t]``."""
    n = len(d)
    c = np.zeros((n + 1, n + 1))
    c[1:, 1:] = d
    for i in range(1, n + 1):
        c[i, 1:] += c[i - 1, :-1]
    return c


def segment_distance(
    d: np.ndarray,
    a: tuple[int, int],
    b: tuple[int, int],
    sub: int = 1,
    max_shift: int = 0,
    csum: np.ndarray | None = None,
) -> float:
    """Distance of segments ``a`` and ``b`` (start, end bars) on a distance matrix ``d`` with
    ``sub`` rows per bar: the mean along the best aligned diagonal (bar offsets of the shorter
    in the longer, and shifts of up to ``max_shift`` rows that stay inside ``d``), plus 0.3 ×
    the relative length difference. ``csum``: ``diagonal_cumsum(d)``, if already computed."""
    c = diagonal_cumsum(d) if csum is None else csum
    la, lb = a[1] - a[0], b[1] - b[0]
    short, long_ = (a, b) if la <= lb else (b, a)
    ls, ll = short[1] - short[0], long_[1] - long_[0]
    n, m = ls * sub, len(d)
    i0 = short[0] * sub
    j0 = (long_[0] + np.arange(ll - ls + 1))[:, None] * sub + np.arange(-max_shift, max_shift + 1)[
        None, :
    ]
    j0 = j0[(j0 >= 0) & (j0 + n <= m)]
    best = float(((c[i0 + n, j0 + n] - c[i0, j0]) / n).min())
    return best + 0.3 * (ll - ls) / ll


def _label_name(i: int) -> str:
    letters = string.ascii_uppercase
    return letters[i] if i < 26 else letters[i // 26 - 1] + letters[i % 26]


def label_segments(
    d: np.ndarray,
    bounds: list[int],
    threshold: float = LABEL_THRESHOLD,
    sub: int = 1,
    max_shift: int = 0,
) -> list[str]:
    """Labels A, B, … per segment (order of first appearance); similar segments share one.

    ``d``: distances with ``sub`` rows per bar (a bar matrix, or ``beat_distance``);
    ``max_shift``: rows a repeat may be displaced by (see ``segment_distance``)."""
    segs = list(zip(bounds[:-1], bounds[1:], strict=True))
    if len(segs) == 1:
        return ["A"]
    n = len(segs)
    sd = np.zeros((n, n))
    csum = diagonal_cumsum(d)
    for i in range(n):
        for j in range(i + 1, n):
            sd[i, j] = sd[j, i] = segment_distance(d, segs[i], segs[j], sub, max_shift, csum)
    clusters = fcluster(
        linkage(squareform(sd, checks=False), method="average"), t=threshold, criterion="distance"
    )
    names: dict[int, str] = {}
    out = []
    for c in clusters:
        if c not in names:
            names[c] = _label_name(len(names))
        out.append(names[c])
    return out


def _pair_kinds(
    segs: list[tuple[int, int]],
    labels: list[str],
    unit: int,
    novelty: np.ndarray,
    dt: np.ndarray | None,
) -> list[tuple[float, list[int]]]:
    """The kinds of adjacent unit-phrase pairs that may be joined (see :func:`merge_units`):
    (score, the indices of each pair's first phrase), the weakest internal boundary lowest."""
    n = len(segs)
    is_unit = [e - s == unit for s, e in segs]
    occ: dict[tuple[str, str], list[int]] = {}
    for i in range(n - 1):
        if is_unit[i] and is_unit[i + 1]:
            occ.setdefault((labels[i], labels[i + 1]), []).append(i)
    kinds = []
    dt_sum = diagonal_cumsum(dt) if dt is not None else None
    for (x, y), where in occ.items():
        if x == y:
            # A 4-bar unit that also stands alone inside the song (``A A B A B``) is a
            # section of its own: its back-to-back repeats stay separate phrases. Only a unit
            # that always comes doubled is half of an 8-bar section. The first and last
            # phrases do not count: the song's edges cut sections short.
            alone = [
                i
                for i in range(1, n - 1)
                if labels[i] == x and is_unit[i] and labels[i - 1] != x and labels[i + 1] != x
            ]
            if alone:
                continue
        else:
            xs = [i for i in range(n) if labels[i] == x and is_unit[i]]
            ys = [i for i in range(n) if labels[i] == y and is_unit[i]]
            # Every X is followed by Y and every Y preceded by X (a one-off pair counts too).
            consistent = len(xs) == len(where) and len(ys) == len(where)
            if not consistent:
                continue
            if dt is not None:
                sound = np.mean(
                    [segment_distance(dt, segs[i], segs[i + 1], csum=dt_sum) for i in where]
                )
                if sound >= PAIR_TIMBRE_THRESHOLD:
                    continue
        score = float(np.mean([novelty[segs[i + 1][0]] for i in where])) - (1.0 if x == y else 0.0)
        kinds.append((score, where))
    return kinds


def merge_units(
    bounds: list[int],
    labels: list[str],
    unit: int,
    novelty: np.ndarray,
    dt: np.ndarray | None = None,
) -> list[int]:
    """Join pairs of adjacent ``unit``-bar phrases into one ``2 * unit``-bar phrase.

    The halves of an 8-bar section often repeat a 4-bar pattern, or differ only in melody, and
    the novelty sees a boundary between them. A pair of labels (X, Y) is joined when X == Y and
    X never stands alone as a single unit inside the song (else ``A A`` are two 4-bar
    sections), or
    when every unit-length X is followed by a Y and every unit-length Y preceded by an X (once
    or more often), and the two sound alike (mean timbre distance ``dt`` below
    ``PAIR_TIMBRE_THRESHOLD``: the same instruments, another melody or chord turn). Pair kinds are taken weakest internal boundary first (mean novelty at the
    joins; alike pairs first), and every occurrence of a kind is joined at once, so repeats
    stay parallel.
    """
    segs = list(zip(bounds[:-1], bounds[1:], strict=True))
    n = len(segs)
    kinds = _pair_kinds(segs, labels, unit, novelty, dt)
    taken = [False] * n
    joined = set()
    for _, where in sorted(kinds, key=lambda k: k[0]):
        for i in where:
            if not taken[i] and not taken[i + 1]:
                taken[i] = taken[i + 1] = True
                joined.add(i)
    out = [bounds[0]]
    i = 0
    while i < n:
        i += 2 if i in joined else 1
        out.append(segs[i - 1][1])
    return out


def merge_alike_neighbours(bounds: list[int], labels: list[str], unit: int) -> list[int]:
    """Join adjacent phrases with the same label while the joined phrase stays within
    ``2 * unit`` bars (fragments of one section that the novelty cut, e.g. 2 + 4 + 1 bars)."""
    segs = list(zip(bounds[:-1], bounds[1:], strict=True))
    out = [list(segs[0])]
    labs = [labels[0]]
    for (s0, e0), lab in zip(segs[1:], labels[1:], strict=True):
        if (
            lab == labs[-1]
            and e0 - out[-1][0] <= 2 * unit
            and (e0 - s0 < unit or out[-1][1] - out[-1][0] < unit)
        ):
            out[-1][1] = e0
        else:
            out.append([s0, e0])
            labs.append(lab)
    return [out[0][0]] + [e for _, e in out]


def meter_ids(
    spec: np.ndarray, start: int, end: int, threshold: float = METER_ID_THRESHOLD
) -> list[int]:
    """Meter identity ids for bars ``start:end`` from a median-scaled bar spectrogram distance
    matrix ``spec`` (B, B): greedy, a bar joins the first earlier id whose first bar is near."""
    ids: list[int] = []
    heads: list[int] = []
    for b in range(start, end):
        for k, h in enumerate(heads):
            if spec[b, h] < threshold:
                ids.append(k)
                break
        else:
            heads.append(b)
            ids.append(len(heads) - 1)
    return ids


def analyze_structure(ff: FrameFeatures, bars: np.ndarray, unit: int = 4) -> Structure:
    """Phrases and structure tags for the bars ``(B, 2)`` (seconds) of a song.

    ``unit``: the preferred phrase length in bars (4 for 4-beat bars of 4/4 or 2/4 music; 3 for
    3/4, where 4 measures make 3 four-beat bars).
    """
    bars = np.asarray(bars, dtype=float).reshape(-1, 2)
    n = len(bars)
    if n == 0:
        return Structure([], [], np.zeros(0), np.zeros((0, 0)))
    x = bar_feature_matrix(ff, bars)
    d = distance_matrix(x)
    dt = timbre_distance(ff, bars)
    nov = combined_novelty(d, unit, dt)
    bounds = segment(nov, unit=unit)
    db = beat_distance(ff, bars)
    bounds = merge_units(bounds, label_segments(db, bounds, sub=4, max_shift=3), unit, nov, dt)
    labels = label_segments(db, bounds, sub=4, max_shift=3)
    merged = merge_alike_neighbours(bounds, labels, unit)
    if merged != bounds:
        bounds, labels = merged, label_segments(db, merged, sub=4, max_shift=3)
    # Near-identical bars: alike in sound (coarse log-mel, 8 steps per bar) and in harmony.
    spec = np.maximum(
        distance_matrix(bar_synchronous(ff.mel_db, ff.times, bars, n_sub=8)),
        distance_matrix(bar_synchronous(ff.chroma, ff.times, bars, n_sub=4)),
    )
    phrases, tags = [], []
    seen: dict[str, int] = {}
    for (s, e), lab in zip(zip(bounds[:-1], bounds[1:], strict=True), labels, strict=True):
        occ = seen.get(lab, 0)
        seen[lab] = occ + 1
        phrases.append({"label": lab, "occurrence": occ, "start_bar": int(s), "end_bar": int(e)})
        for i, mid in enumerate(meter_ids(spec, s, e)):
            tags.append({"label": lab, "occurrence": occ, "index": i, "meter_id": int(mid)})
    return Structure(phrases, tags, nov, d)
