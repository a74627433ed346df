"""Naturalness of a rendered dance beside its sync: does it carry the beat as the dancers did?

- **Pulse depth** (``pulse_profile``, ``pulse_depth``): the mean joint speed folded on a beat
  grid's phase (``PULSE_BINS`` bins, each bin's mean over the dance, divided by the largest),
  depth ``1 − min/max``. A dance that slows into every beat has a deep fold; the library's takes
  on their own grids are the reference (``library_pulse``).
- **Recovered grid** (``recovered_grid``, ``grid_check``): the importer's own beat estimator
  (``motion.dataset.step_evidence`` and ``motion.tempo.estimate_grid``) run on the dance as if
  it were a new mocap take, and the grid it finds compared with the song's (tempo within
  ``GRID_TEMPO_PCT``, median beat offset within ``GRID_OFFSET_MS``, downbeats matching
  ``GRID_DOWNBEATS``). Chance row: the song's grid replaced by another song's, scaled to the
  same tempo (``scaled_grid``).
- **Two-sample test** (``window_descriptors``, ``two_sample_accuracy``, ``library_chance``): a
  classifier told to separate 2-s windows of kinetic descriptors of the dances from the
  library's takes, whole files held out; its balanced accuracy (0.5: it cannot tell them apart).

Arrays in, numbers out; times in seconds, speeds in m/s, tempi in BPM.
"""

from __future__ import annotations

import numpy as np

from dancegraph.motion.retime import song_phase
from dancegraph.motion.tempo import BeatGrid, GridParams, estimate_grid, partner_agreement

#: Bins of the beat phase the joint speed is folded into (bin k: phase [k/8, (k+1)/8)).
PULSE_BINS = 8
#: The recovered grid's tempo may differ from the song's by this many per cent ...
GRID_TEMPO_PCT = 1.0
#: ... its beats lie this close to the song's (median, ms) ...
GRID_OFFSET_MS = 40.0
#: ... and this share of downbeats match (within 1/8 beat), for the check to pass.
GRID_DOWNBEATS = 0.8
#: The estimator's tempo prior is the song's tempo times / divided by this (one octave wide:
#: its double and half are outside, as a library's manifest prior keeps them).
GRID_PRIOR_SPAN = 2.0**0.5
#: Length (s) of the two-sample test's windows.
WINDOW_S = 2.0
#: SMPL-like joints (``metrics.kinetic.SMPL_JOINTS``) of each body part of the descriptors.
BODY_PARTS: dict[str, tuple[int, ...]] = {
    "trunk": (0, 3, 6, 9, 12, 15),
    "left_arm": (13, 16, 18, 20, 22),
    "right_arm": (14, 17, 19, 21, 23),
    "left_leg": (1, 4, 7, 10),
    "right_leg": (2, 5, 8, 11),
}
#: Bands (Hz) of the mean joint speed's spectrum in the descriptors.
SPECTRUM_BANDS = np.arange(0.5, 6.01, 0.5)


# --------------------------------------------------------------------------------------------
# pulse depth


def pulse_profile(speed: np.ndarray, fps: float, bar_beats: np.ndarray) -> np.ndarray:
    """``(PULSE_BINS,)`` the speed curve ``speed (F,)`` (frame 0 at t 0, ``fps``) folded on the
    beat phase of ``bar_beats (B, 5)`` s (``retime.song_phase``; only frames inside the bars),
    each bin's mean divided by the largest bin's; zeros where no frame is inside or the dance is
    still. Why: a dance that slows into every beat shows it here, whatever its stops."""
    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    s = np.asarray(speed, dtype=float).reshape(-1)
    out = np.zeros(PULSE_BINS)
    if len(bb) == 0 or s.size == 0:
        return out
    t = np.arange(s.size) / fps
    inside = (t >= bb[0, 0]) & (t < bb[-1, 4])
    if not inside.any():
        return out
    phase = np.mod(song_phase(bb)(t[inside]), 1.0)
    k = np.minimum((phase * PULSE_BINS).astype(np.int64), PULSE_BINS - 1)
    total = np.bincount(k, weights=s[inside], minlength=PULSE_BINS)
    count = np.bincount(k, minlength=PULSE_BINS)
    mean = np.where(count > 0, total / np.maximum(count, 1), 0.0)
    top = float(mean.max())
    return mean / top if top > 0 else out


def pulse_depth(profile: np.ndarray) -> float:
    """``1 − min/max`` of a ``pulse_profile`` (0: no pulse, 1: the dance stops at one phase)."""
    p = np.asarray(profile, dtype=float)
    top = float(p.max()) if p.size else 0.0
    return float(1.0 - p.min() / top) if top > 0 else 0.0


def library_pulse(takes: list[tuple[np.ndarray, float, np.ndarray]]) -> dict:
    """The library's own pulse: each take ``(speed (F,), fps, bar_beats (B, 5))`` folded on its
    own stored bars. Returns ``{median, mean, depths, profile}`` (``profile``: the takes'
    profiles averaged, depth of that in ``pooled``)."""
    profiles = [pulse_profile(s, fps, bb) for s, fps, bb in takes if len(bb)]
    depths = [pulse_depth(p) for p in profiles]
    mean_profile = np.mean(profiles, axis=0) if profiles else np.zeros(PULSE_BINS)
    return {
        "median": float(np.median(depths)) if depths else None,
        "mean": float(np.mean(depths)) if depths else None,
        "pooled": pulse_depth(mean_profile),
        "profile": [round(float(x), 4) for x in mean_profile],
        "takes": len(depths),
    }


# --------------------------------------------------------------------------------------------
# recovered grid


def beat_period(bar_beats: np.ndarray) -> float:
    """The regular beat (s) of bars ``bar_beats (B, 5)`` s: the mean of the beat intervals within
    10 % of their median (a beat tracker's intervals snap to its frames, so their median is
    biased; a stretched bar is no regular beat)."""
    d = np.diff(np.asarray(bar_beats, dtype=float).reshape(-1, 5), axis=1).ravel()
    med = float(np.median(d))
    return float(d[np.abs(d / med - 1.0) <= 0.1].mean())


def recovered_grid(
    skeleton,
    positions: np.ndarray,
    world: np.ndarray,
    fps: float,
    span: tuple[float, float],
    tempo_bpm: float,
) -> BeatGrid:
    """The importer's grid of a dance read back as a new mocap take: ``positions``, ``world``
    ``(F, J, 3/4)`` (frame 0 at t 0, ``fps``) cut to ``span`` (s: where it dances), evidence
    ``dataset.step_evidence``, grid ``tempo.estimate_grid`` with a prior one octave wide about
    ``tempo_bpm`` (``GRID_PRIOR_SPAN``); its beat times on the song's clock. Raises
    ``ValueError`` for a span under 2 s; ``DanceGraphError`` (``skeleton_unmapped``) for a
    skeleton without the canonical joints."""
    from dancegraph.motion.dataset import step_evidence

    lo = max(0, int(round(span[0] * fps)))
    hi = min(positions.shape[0], int(round(span[1] * fps)))
    _, signals = step_evidence(skeleton, positions[lo:hi], world[lo:hi], fps)
    if signals is None:
        raise ValueError(f"{(hi - lo) / fps:.2f} s is too short to recover a grid")
    prior = (tempo_bpm / GRID_PRIOR_SPAN, tempo_bpm * GRID_PRIOR_SPAN)
    grid = estimate_grid(signals, fps, GridParams(prior_bpm=prior))
    grid.beats = grid.beats + lo / fps
    return grid


def grid_check(grid: BeatGrid, bar_beats: np.ndarray) -> dict:
    """``grid`` (a ``recovered_grid``) against the song's bars ``bar_beats (B, 5)`` s:
    ``tempo_bpm`` (the grid's), ``song_tempo_bpm`` (``beat_period``), ``tempo_diff_pct``,
    ``median_offset_ms`` and ``downbeat_agreement`` (``tempo.partner_agreement``, over the span
    both cover), and ``passed`` (all three within ``GRID_TEMPO_PCT``, ``GRID_OFFSET_MS``,
    ``GRID_DOWNBEATS``)."""
    bb = np.asarray(bar_beats, dtype=float).reshape(-1, 5)
    beats = np.unique(bb.ravel())
    song_tempo = 60.0 / beat_period(bb)
    downs = np.unique(np.concatenate([bb[:, 0], bb[-1:, 4]]))
    found = partner_agreement(
        grid.beats, grid.beats[grid.downbeats], grid.tempo_bpm, beats, downs, song_tempo
    )
    out = {
        "tempo_bpm": round(float(grid.tempo_bpm), 3),
        "song_tempo_bpm": round(song_tempo, 3),
        "tempo_diff_pct": found["tempo_diff_pct"],
        "median_offset_ms": found["median_offset_ms"],
        "downbeat_agreement": found["downbeat_agreement"],
    }
    out["passed"] = bool(
        out["tempo_diff_pct"] <= GRID_TEMPO_PCT
        and out["median_offset_ms"] <= GRID_OFFSET_MS
        and out["downbeat_agreement"] >= GRID_DOWNBEATS
    )
    return out


def scaled_grid(
    other_bar_beats: np.ndarray, bar_beats: np.ndarray, seed: int | list[int] = 0
) -> np.ndarray:
    """Another song's bars ``other_bar_beats (B', 5)`` s scaled in time (about t 0) to the regular
    beat of ``bar_beats (B, 5)`` and moved by a phase drawn from ``seed`` (uniform over one
    4-beat bar): a grid of the same tempo that the dance was not laid on, at a phase of its own
    (songs that start alike, as generated ones do, would otherwise line up), the
    recovered-grid check's chance row."""
    ob = np.asarray(other_bar_beats, dtype=float).reshape(-1, 5)
    beat = beat_period(bar_beats)
    shift = np.random.default_rng(seed).uniform(0.0, 4.0) * beat
    return ob * (beat / beat_period(ob)) + shift


# --------------------------------------------------------------------------------------------
# two-sample classifier test


def window_descriptors(smpl: np.ndarray, fps: float, window_s: float = WINDOW_S) -> np.ndarray:
    """``(W, 37)`` descriptors of consecutive ``window_s`` windows of ``smpl (F, 24, 3)`` (m, at
    ``fps``; a trailing part shorter than a window is dropped): per body part (``BODY_PARTS``)
    the mean, standard deviation and 90th percentile of its joints' mean speed and the mean and
    90th percentile of their mean acceleration, then the spectrum of the mean joint speed in
    ``SPECTRUM_BANDS`` (each band's share of the power, log), and the window's mean speed."""
    pos = np.asarray(smpl, dtype=float)
    vel = np.gradient(pos, axis=0) * fps
    speed = np.linalg.norm(vel, axis=-1)  # (F, 24)
    acc = np.linalg.norm(np.gradient(vel, axis=0) * fps, axis=-1)
    w = int(round(window_s * fps))
    rows = []
    for s in range(0, pos.shape[0] - w + 1, w):
        row = []
        for joints in BODY_PARTS.values():
            v = speed[s : s + w, list(joints)].mean(axis=1)
            a = acc[s : s + w, list(joints)].mean(axis=1)
            row += [v.mean(), v.std(), np.percentile(v, 90), a.mean(), np.percentile(a, 90)]
        mean_speed = speed[s : s + w].mean(axis=1)
        power = np.abs(np.fft.rfft((mean_speed - mean_speed.mean()) * np.hanning(w))) ** 2
        freq = np.fft.rfftfreq(w, 1.0 / fps)
        band = np.digitize(freq, SPECTRUM_BANDS)
        share = np.bincount(band, weights=power, minlength=SPECTRUM_BANDS.size + 1)[1:-1]
        row += list(np.log(share / max(float(power.sum()), 1e-12) + 1e-6))
        row.append(mean_speed.mean())
        rows.append(row)
    return np.asarray(rows, dtype=float).reshape(len(rows), -1 if rows else 37)


def two_sample_accuracy(
    positive: list[np.ndarray], negative: list[np.ndarray], seed: int = 0
) -> float | None:
    """Balanced accuracy of a logistic regression telling windows of the ``positive`` files
    (one ``(W, D)`` array per file, e.g. rendered dances) from those of the ``negative`` files
    (the library's takes), every window predicted by a model that saw none of its file's
    windows (stratified group k-fold, k = min(5, files of the smaller side)). None with fewer
    than two files on a side or without scikit-learn. 0.5: the two cannot be told apart."""
    try:
        from sklearn.linear_model import LogisticRegression
        from sklearn.metrics import balanced_accuracy_score
        from sklearn.model_selection import StratifiedGroupKFold
        from sklearn.pipeline import make_pipeline
        from sklearn.preprocessing import StandardScaler
    except ImportError:
        return None
    pos = [p for p in positive if len(p)]
    neg = [n for n in negative if len(n)]
    if len(pos) < 2 or len(neg) < 2:
        return None
    x = np.concatenate(pos + neg)
    y = np.concatenate([np.ones(len(p)) for p in pos] + [np.zeros(len(n)) for n in neg])
    groups = np.concatenate([np.full(len(f), i) for i, f in enumerate(pos + neg)])
    folds = StratifiedGroupKFold(
        n_splits=min(5, len(pos), len(neg)), shuffle=True, random_state=seed
    )
    predicted = np.zeros_like(y)
    for train, test in folds.split(x, y, groups):
        model = make_pipeline(
            StandardScaler(), LogisticRegression(class_weight="balanced", max_iter=2000)
        )
        model.fit(x[train], y[train])
        predicted[test] = model.predict(x[test])
    return float(balanced_accuracy_score(y, predicted))


def library_chance(takes: list[np.ndarray], n_files: int, draws: int = 5) -> float | None:
    """The two-sample test's chance row: ``n_files`` of the library's takes (``(W, D)`` windows
    each; at least 2) drawn at random as if they were the dances, against the other takes; the
    mean balanced accuracy over ``draws`` draws (seeded). None when the library is too small."""
    k = max(2, n_files)
    if len(takes) < k + 2:
        return None
    rng = np.random.default_rng(0)
    scores = []
    for d in range(draws):
        pick = set(rng.choice(len(takes), size=k, replace=False).tolist())
        score = two_sample_accuracy(
            [t for i, t in enumerate(takes) if i in pick],
            [t for i, t in enumerate(takes) if i not in pick],
            seed=d,
        )
        if score is not None:
            scores.append(score)
    return float(np.mean(scores)) if scores else None
