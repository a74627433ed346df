"""Bar-pointer state-space decoding of beats, downbeats and meter from beat/downbeat activations.

The model is the dynamic Bayesian network of Krebs, Böck & Widmer (ISMIR 2015/2016) as BeatNet's
offline mode uses it (through madmom's ``DBNDownBeatTrackingProcessor``): for each meter (beats
per bar) a state is (beat in the bar, beat interval in frames, position inside the beat); the
position advances one frame per frame, the tempo may change only at a beat boundary with
probability ``exp(-lambda |ratio - 1|)``, and the observation is the "downbeat" activation in the
first 1/16 of the first beat, the "beat" activation in the first 1/16 of the other beats and
``(1 - beat - downbeat) / 15`` elsewhere. Viterbi decoding, then each beat is placed on the
activation peak inside its beat range (madmom's ``correct``).

Two extensions, off in :data:`MADMOM` so that the decoder reproduces BeatNet's output exactly:
all meters share one state space, and at any beat boundary the bar may restart — jump to the
downbeat of the same meter with probability ``phase_change`` (a 2-beat bar, a dropped beat
between sections), or to another meter's downbeat with ``meter_change``. :data:`DEFAULT` allows
phase changes at 1e-20 per beat (about 46 nats: several bars of consistent contrary evidence are
needed, so the network's own mistakes over a section are not followed) and keeps one meter per
song.

Memory: the back-pointers are kept only for the first state of each beat (all others have a single
predecessor), (T, meters x beats x tempi) int16 — 33 MB for a 15-minute song at 50 fps.
The Viterbi kernel is compiled by numba and cached on disk (``NUMBA_CACHE_DIR``, by default
``$DANCEGRAPH_HOME/numba_cache``; see :mod:`dancegraph.jit`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from dancegraph import jit

__all__ = ["BarPointerParams", "MADMOM", "DEFAULT", "DecodedBeats", "decode", "warm_up"]


@dataclass(frozen=True)
class BarPointerParams:
    """Parameters of the bar-pointer model (defaults: BeatNet's offline decoder)."""

    meters: tuple[int, ...] = (2, 3, 4)
    fps: float = 50.0
    min_bpm: float = 55.0
    max_bpm: float = 205.0
    transition_lambda: float = 100.0
    observation_lambda: float = 16.0
    threshold: float = 0.05  # leading/trailing frames with all activations below are ignored
    phase_change: float = 0.0  # probability of restarting the bar (same meter) at a beat boundary
    meter_change: float = 0.0  # probability of switching to another meter's downbeat there


MADMOM = BarPointerParams()
DEFAULT = BarPointerParams(phase_change=1e-20, meter_change=0.0)


@dataclass
class DecodedBeats:
    """Decoder output: beat times (K,) s, position in bar (K,) int (1 = downbeat), meter per
    beat (K,) int, and the path's log probability."""

    times: np.ndarray
    positions: np.ndarray
    meters: np.ndarray
    log_prob: float


class _Space:
    """The joint state space of all meters, with per-state lookup arrays."""

    def __init__(self, p: BarPointerParams):
        min_iv = 60.0 * p.fps / p.max_bpm
        max_iv = 60.0 * p.fps / p.min_bpm
        # madmom: linear spacing of integer intervals (log spacing only above 60 tempi)
        self.intervals = np.arange(np.round(min_iv), np.round(max_iv) + 1).astype(np.int64)
        self.meters = np.asarray(p.meters, dtype=np.int64)
        k = len(self.intervals)
        s_beat = int(self.intervals.sum())
        self.s_beat = s_beat
        self.ioff = np.r_[0, np.cumsum(self.intervals)[:-1]].astype(np.int64)
        self.moff = np.r_[0, np.cumsum(self.meters * s_beat)[:-1]].astype(np.int64)
        self.slot_off = np.r_[0, np.cumsum(self.meters)[:-1]].astype(np.int64)
        n = int((self.meters * s_beat).sum())
        self.n_states = n
        self.st_meter = np.empty(n, np.int64)
        self.st_beat = np.empty(n, np.int64)
        self.st_k = np.empty(n, np.int64)
        self.st_p = np.empty(n, np.int64)
        border = 1.0 / p.observation_lambda
        self.pointer = np.zeros(n, np.int64)
        for m, nb in enumerate(self.meters):
            for b in range(nb):
                for ki, iv in enumerate(self.intervals):
                    s = self.moff[m] + b * s_beat + self.ioff[ki]
                    self.st_meter[s : s + iv] = m
                    self.st_beat[s : s + iv] = b
                    self.st_k[s : s + iv] = ki
                    self.st_p[s : s + iv] = np.arange(iv)
                    in_range = np.linspace(0, 1, iv, endpoint=False) < border
                    self.pointer[s : s + iv][in_range] = 2 if b == 0 else 1
        # tempo change at beat boundaries: rows = from interval, columns = to interval
        ratio = self.intervals[None, :] / self.intervals[:, None].astype(np.float64)
        prob = np.exp(-p.transition_lambda * np.abs(ratio - 1.0))
        prob[prob <= np.spacing(1)] = 0.0
        prob /= prob.sum(axis=1, keepdims=True)
        with np.errstate(divide="ignore"):
            self.log_tempo = np.log(prob)
        # madmom starts each meter's HMM from a uniform distribution over its own states
        self.log_init = np.array([-np.log(nb * s_beat * len(self.meters)) for nb in self.meters])
        if p.meter_change <= 0:
            self.log_init += np.log(len(self.meters))  # separate HMMs: exactly madmom's numbers
        self.k = k
        # slots: one per (meter, beat in the bar), in meter order
        self.slot_meter = np.repeat(np.arange(len(self.meters)), self.meters)
        self.slot_beat = np.concatenate([np.arange(nb) for nb in self.meters])
        self.slot_base = self.moff[self.slot_meter] + self.slot_beat * s_beat
        last = self.slot_off[self.slot_meter] + self.meters[self.slot_meter] - 1
        self.slot_prev = np.where(self.slot_beat > 0, np.arange(len(self.slot_beat)) - 1, last)
        self.slot_first = self.slot_beat == 0
        self.st_slot = self.slot_off[self.st_meter] + self.st_beat


def _forward_py(
    obs, pointer, intervals, ioff, slot_base, slot_prev, slot_meter, slot_first, log_tempo, v,
    log_stay, log_jump_same, log_jump_other,
):  # fmt: skip
    """The Viterbi forward pass over the joint bar-pointer space (numba-compiled): ``v`` (S,)
    holds the initial log probabilities and is left holding the last frame's. A slot is one
    (meter, beat in the bar); ``slot_base`` its first state, ``slot_prev`` the slot before it in
    the bar, ``slot_first`` whether it is a downbeat. Returns the back-pointers of the first state
    of each beat, (T, slots x tempi) int16 (every other state has one predecessor)."""
    n_frames, n_int, n_slots = obs.shape[0], intervals.shape[0], slot_base.shape[0]
    best_in = np.empty((n_slots, n_int))
    arg_in = np.empty((n_slots, n_int), np.int64)
    bp = np.empty((n_frames, n_slots * n_int), np.int16)
    jumps = log_jump_same > -np.inf or log_jump_other > -np.inf
    for t in range(n_frames):
        # best way into each tempo from the last state of each beat (beat boundary)
        for slot in range(n_slots):
            base = slot_base[slot]
            for k in range(n_int):
                best = -np.inf
                arg = 0
                for kp in range(n_int):
                    lt = log_tempo[kp, k]
                    if lt == -np.inf:
                        continue
                    val = v[base + ioff[kp] + intervals[kp] - 1] + lt
                    if val > best:
                        best = val
                        arg = kp
                best_in[slot, k] = best
                arg_in[slot, k] = slot * n_int + arg
        # advance the position inside each beat (in place, from the back)
        for slot in range(n_slots):
            base = slot_base[slot]
            for k in range(n_int):
                s0 = base + ioff[k]
                for q in range(intervals[k] - 1, 0, -1):
                    v[s0 + q] = v[s0 + q - 1] + obs[t, pointer[s0 + q]]
        # first state of each beat: the previous beat of the bar, or a bar restart
        for slot in range(n_slots):
            prev = slot_prev[slot]
            for k in range(n_int):
                best = best_in[prev, k] + log_stay
                arg = arg_in[prev, k]
                if slot_first[slot] and jumps:
                    for other in range(n_slots):
                        if other == prev:
                            continue
                        same = slot_meter[other] == slot_meter[slot]
                        val = best_in[other, k] + (log_jump_same if same else log_jump_other)
                        if val > best:
                            best = val
                            arg = arg_in[other, k]
                s0 = slot_base[slot] + ioff[k]
                v[s0] = best + obs[t, pointer[s0]]
                bp[t, slot * n_int + k] = arg
    return bp


def _backtrack_py(v, bp, st_p, st_slot, st_k, slot_base, intervals, ioff):
    """The most likely state path (T,) and its log probability from the last frame's ``v``
    (S,) and the forward pass's back-pointers ``bp`` (numba-compiled)."""
    n_int = intervals.shape[0]
    state = 0
    for s in range(v.shape[0]):
        if v[s] > v[state]:
            state = s
    log_prob = v[state]
    path = np.empty(bp.shape[0], np.int64)
    for t in range(bp.shape[0] - 1, -1, -1):
        path[t] = state
        if st_p[state] > 0:
            state = state - 1
        else:
            src = bp[t, st_slot[state] * n_int + st_k[state]]
            sl, kp = src // n_int, src % n_int
            state = slot_base[sl] + ioff[kp] + intervals[kp] - 1
    return path, log_prob


_KERNELS = None
_LOCK = threading.Lock()


def _kernels():
    """The numba-compiled forward pass and backtrack, compiled (or loaded from the disk cache)
    once, under the kernel cache's lock (``jit.ensure``)."""
    global _KERNELS
    with _LOCK:
        if _KERNELS is None:
            import numba

            jit.configure_cache()  # decorated after this, the kernels cache in the project's folder
            compile_ = numba.njit(cache=True, nogil=True)
            _KERNELS = (compile_(_forward_py), compile_(_backtrack_py))
    jit.ensure("barpointer")
    return _KERNELS


@lru_cache(maxsize=8)
def _space(p: BarPointerParams) -> _Space:
    """The state space of ``p``, built once per parameters (a few MB each)."""
    return _Space(p)


def _observations(act: np.ndarray, lam: float) -> np.ndarray:
    """(T, 3) log observation probabilities of (T, 2) activations: outside any beat range
    (``(1 - beat - downbeat) / (lam - 1)``), in a beat's range (beat), in a downbeat's (downbeat)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        obs = np.empty((len(act), 3))
        obs[:, 0] = np.log(np.maximum(1.0 - act.sum(axis=1), 1e-12) / (lam - 1.0))
        obs[:, 1] = np.log(np.maximum(act[:, 0], 1e-12))
        obs[:, 2] = np.log(np.maximum(act[:, 1], 1e-12))
    return obs


def decode(activations: np.ndarray, params: BarPointerParams = DEFAULT) -> DecodedBeats:
    """Decode beats, downbeats and meter from (T, 2) activations (beat, downbeat) at ``params.fps``.

    Returns beat times in seconds from the start of the activations, their positions in the bar
    (1 = downbeat) and the meter in force at each beat; empty arrays when no activation reaches
    ``params.threshold``.
    """
    act = np.asarray(activations, dtype=np.float64)
    if act.ndim != 2 or act.shape[1] != 2:
        raise ValueError(f"activations must be (T, 2), got {act.shape}")
    empty = DecodedBeats(np.empty(0), np.empty(0, np.int64), np.empty(0, np.int64), -np.inf)
    first = 0
    if params.threshold:
        idx = np.nonzero(act >= params.threshold)[0]
        if len(idx) == 0:
            return empty
        first, last = int(idx.min()), int(idx.max()) + 1
        act = act[first:last]
    if len(act) == 0 or not act.any():
        return empty
    sp = _space(params)
    obs = _observations(act, params.observation_lambda)
    # a bar restart: to the downbeat from any other beat of the same meter (nb - 1 ways), or
    # to another meter's downbeat from any beat
    pc, mc = params.phase_change, params.meter_change
    log_stay = float(np.log1p(-(pc + mc)))
    nb = int(sp.meters.max())
    n_other = int(sp.meters.sum()) - nb
    log_same = float(np.log(pc / (nb - 1))) if pc > 0 and nb > 1 else -np.inf
    log_other = float(np.log(mc / n_other)) if mc > 0 and n_other > 0 else -np.inf
    forward, backtrack = _kernels()
    v = sp.log_init[sp.st_meter]
    bp = forward(
        obs, sp.pointer, sp.intervals, sp.ioff, sp.slot_base, sp.slot_prev, sp.slot_meter,
        sp.slot_first, sp.log_tempo, v, log_stay, log_same, log_other,
    )  # fmt: skip
    path, log_prob = backtrack(
        v, bp, sp.st_p, sp.st_slot, sp.st_k, sp.slot_base, sp.intervals, sp.ioff
    )
    if not np.isfinite(log_prob):
        return empty
    # madmom's correction: one beat per beat range, on the activation peak inside it
    beat_range = sp.pointer[path] >= 1
    if not beat_range.any():
        return empty
    edges = np.nonzero(np.diff(beat_range.astype(np.int64)))[0] + 1
    if beat_range[0]:
        edges = np.r_[0, edges]
    if beat_range[-1]:
        edges = np.r_[edges, beat_range.size]
    frames = np.array(
        [np.argmax(act[a:b]) // 2 + a for a, b in edges.reshape(-1, 2)], dtype=np.int64
    )
    return DecodedBeats(
        times=(frames + first) / float(params.fps),
        positions=sp.st_beat[path[frames]] + 1,
        meters=sp.meters[sp.st_meter[path[frames]]],
        log_prob=float(log_prob),
    )


def warm_up() -> None:
    """Compile (or load from the numba cache) the Viterbi kernel; call once at worker start."""
    rng = np.random.default_rng(0)
    act = rng.uniform(0.0, 0.2, size=(200, 2))
    act[::25, 0] = 0.8
    decode(act, DEFAULT)


jit.register("barpointer", warm_up)
