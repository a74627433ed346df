"""Numba kernels of the graph search (see ``search.py`` for the model).

One forward pass over the *chain* of tied variables (first appearances in song order), with no
beam: every node keeps its cheapest state (up to ``slots`` states when they end in different
places, or come from different predecessors), so without ties, trajectory terms and the novelty
cost the pass is the exact Viterbi. Each state carries its root pose so stage bounds and waypoints
are costed on the trajectory. Song bars that are not chain steps are copies of earlier variables
(repeat and mirror ties); their nodes come from the state's own history (back pointers). A chain
bar's incoming transition is relaxed along graph edges (times its count in the song: copies repeat
it); every other transition is *charged*: each distinct (variable, parity) → (variable, parity)
transition once, times its count, as soon as the state's history decides both of its ends. Charges
are kept per state in a cache that outlives the pass (``memo``): the passes for alternatives mostly
revisit the same histories. Copies' root poses are walked in song order. The novelty cost reads
each state's nodes at its last chain steps (``recent``, one row per state, rebuilt from the
predecessor's row after each step); where one state per node is pulled, a node checks the row of
its cheapest in-edge's state and only where that repeats a node pulls again with the cost (it only
raises a value), among the cheapest state of each source node, as the pull does without it.

The arrays travel in three named tuples (``Graph``, ``Chain``, ``Track``) instead of long
argument lists. The hot loops read the fields they need once, into locals, and give helpers plain
arrays: inside a loop, a tuple field read or a tuple handed to an inlined helper costs numba
reference counting (measured 2–3× slower on the 750k-edge benchmark graph).

On large graphs a step's states are readied (charges, copies) and its nodes relaxed on all
threads, in chunks (states and nodes are independent); and the feature rows a state's charges
read, at random on a large graph, are prefetched a few states ahead (the first pass on the
750k-edge benchmark graph: about a quarter faster).
"""

from __future__ import annotations

import os
import threading
from collections import namedtuple

import numba
import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

# numba's "workqueue" threads survive fork (a worker pool forks after the warm-up; GNU OpenMP's
# do not: the child is terminated), but must not run two parallel kernels at once: callers of
# ``forward`` hold ``FORWARD_LOCK``. NUMBA_THREADING_LAYER overrides; NUMBA_NUM_THREADS sets the
# thread count (default: every core).
if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"  # type: ignore[attr-defined]
FORWARD_LOCK = threading.Lock()

INF = np.float32(np.inf)
# steps with at least this many states (nodes) spread over threads; below, one thread is faster
PARALLEL_MIN = 4096
CHUNKS = 64  # parallel loops run in this many chunks: balances uneven chunks over threads
PREFETCH_AHEAD = 4  # states ahead whose transitions' feature rows are fetched early


@intrinsic
def _prefetch(typingctx, arr, row, col):
    """Hint the CPU to fetch the cache line of ``arr[row, col]`` (2-D array; no effect on
    results). LLVM's prefetch: numba has no call for it."""

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        idx = [
            context.cast(builder, v, t, types.intp)
            for v, t in zip(args[1:], signature.args[1:], strict=True)
        ]
        ptr = builder.bitcast(
            cgutils.get_item_pointer(context, builder, aryty, ary, idx), cgutils.voidptr_t
        )
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [cgutils.voidptr_t, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [ptr, i32(0), i32(3), i32(1)])  # read, keep in all levels, data
        return context.get_dummy_value()

    return types.void(arr, row, col), codegen


Graph = namedtuple(
    "Graph",
    [
        "indptr",  # (N+1,) int64 CSR out-edges
        "indices",  # (E,) int32 edge targets, sorted per row
        "costs",  # (E,) float32 edge costs T
        "in_ptr",  # (N+1,) int64 the same edges by target
        "in_src",  # (E,) int32 their sources
        "in_cost",  # (E,) float32 their costs
        # (N, D + 32) float32 per node, one row: compressed exit-pose features, style embedding
        "out_feat",
        # (N, D + 32) float32 compressed entry-pose features, style embedding
        "in_feat",
        "blocks",  # (B,) int64 pose feature block sizes (sum D)
        "mirror_of",  # (N,) int64 mirror node (-1: none)
        # (N, 8) float64 per node, one cache line: the root displacement over the bar dx, dz (m),
        # dyaw (rad), cos and sin of dyaw, the bar's largest root excursion (m), 2 unused
        "motion",
        "path",  # (N, P, 2) float64 root path samples in the bar's frame (m)
        "weights",  # (3,) float64 (λ8, λ9, penalty on a transition that is not an edge: δT)
    ],
)

Chain = namedtuple(
    "Chain",
    [
        "var",  # (C,) int64 variable of each chain step
        "bar",  # (C,) int64 song bar of each chain step
        "gap_ptr",  # (C+2,) copies before chain step c (trailing copies at C) in gap_*
        "gap_bar",  # song bar of each copy
        "gap_step",  # chain step of the copy's variable
        "gap_par",  # 1 when the copy mirrors its variable
        "charge_ptr",  # (C+2,) transitions charged to the states of step c-1 in charge_*
        "charge_a",  # chain step of the transition's first variable
        "charge_pa",  # its parity
        "charge_b",  # chain step of the second variable
        "charge_pb",  # its parity
        "charge_n",  # float64 count of the transition in the song
        "relax_n",  # (C,) float64 count of each chain bar's incoming transition in the song
    ],
)

Track = namedtuple(
    "Track",
    [
        "on",  # follow the root trajectory (stage or waypoints set); else poses stay 0
        "cell",  # metres (L1) that make two states' root positions different
        "start",  # (3,) start pose x, z, yaw
        "stage",  # (5,) xmin xmax zmin zmax (xmin >= xmax: none), penalty per metre off it
        "wp_bar",  # (W,) int64 song bar of each waypoint
        "wp_idx",  # (W,) int64 root path sample of each waypoint
        "wp_pos",  # (W, 2) float64 target x, z
        "wp_tol",  # (W,) float64 tolerance (m)
        "wp_w",  # penalty per metre beyond the tolerance
        "reach",  # largest root travel of any node in one bar (m): waypoint look-ahead
    ],
)


@njit(cache=True, inline="always")
def _edge_cost(indptr, indices, costs, p, q):
    lo = indptr[p]
    hi = indptr[p + 1]
    while lo < hi:
        mid = (lo + hi) // 2
        v = indices[mid]
        if v == q:
            return costs[mid]
        if v < q:
            lo = mid + 1
        else:
            hi = mid
    return np.float32(-1.0)


@njit(cache=True, inline="always")
def _reused(recent, s, mirror_of, q):
    """True when node q (or its mirror) is in row s of ``recent`` (state s's last chain-step
    nodes, -1 padded). Indexes the row rather than slicing it: a slice in a hot loop costs
    reference counting."""
    if recent.shape[1] == 0:
        return False
    mq = mirror_of[q]
    for j in range(recent.shape[1]):
        r = recent[s, j]
        if r == q or (r == mq and r >= 0):
            return True
    return False


@njit(cache=True, inline="always")
def _push_row(out, s, q, recent, i):
    """Row s of ``out``: node q, then row i of ``recent`` (the predecessor state's last
    chain-step nodes) without its oldest entry."""
    out[s, 0] = q
    for j in range(1, out.shape[1]):
        out[s, j] = recent[i, j - 1]


@njit(cache=True, fastmath=True, inline="always")
def _sq_dist(x, y):
    s = np.float32(0.0)
    for d in range(x.shape[0]):
        e = x[d] - y[d]
        s += e * e
    return s


@njit(cache=True, fastmath=True)
def _offgraph_cost(out_feat, in_feat, blocks, weights, p, q):
    """Cost of p→q when it is not an edge: the on-demand T from the compressed features,
    λ8·Σ_blocks ‖exit_p − entry_q‖ + λ9·‖z_p − z_q‖, plus the penalty δT.

    Not inlined: fastmath lets its reductions vectorise (over slices: about 4× faster than over
    index ranges) while the kernels keep strict inf semantics. One feature row per node and side
    (exit or entry, then style): on large graphs each row read is a cache miss."""
    x = out_feat[p]
    y = in_feat[q]
    t = np.float32(0.0)
    start = 0
    for b in range(blocks.shape[0]):
        stop = start + blocks[b]
        t += np.sqrt(_sq_dist(x[start:stop], y[start:stop]))
        start = stop
    style = np.sqrt(_sq_dist(x[start:], y[start:]))
    return np.float32(weights[0] * t + weights[1] * style + weights[2])


@njit(cache=True, inline="always")
def _placed(motion, stage, x, z, yaw, cy, sy, n):
    """Node n placed at (x, z) facing yaw (cos cy, sin sy): (stage penalty, pose after the bar as
    x, z, yaw, cos yaw, sin yaw; the turn composed without trigonometry). Plain arrays, not the
    tuples: a tuple passed into a hot loop's helper costs reference counting (about 3× slower)."""
    pen = 0.0
    if stage[0] < stage[1]:
        r = motion[n, 5]
        over = max(0.0, stage[0] - (x - r)) + max(0.0, (x + r) - stage[1])
        over += max(0.0, stage[2] - (z - r)) + max(0.0, (z + r) - stage[3])
        pen += stage[4] * over
    dx, dz = motion[n, 0], motion[n, 1]
    c, s = motion[n, 3], motion[n, 4]
    return (
        pen,
        x + dx * cy + dz * sy,
        z - dx * sy + dz * cy,
        yaw + motion[n, 2],
        cy * c - sy * s,
        sy * c + cy * s,
    )


@njit(cache=True)
def _waypoint_terms(tr, g, x, z, cy, sy, nx, nz, n, t):
    """Waypoint penalty of node n placed as song bar t at (x, z) facing yaw (cos cy, sin sy) and
    ending at (nx, nz): its root path missing a waypoint of bar t, and a later waypoint out of
    reach even at the graph's largest per-bar travel (a lower bound, so it never rules out a
    feasible path; it makes far-off states lose to feasible ones). Called only when there are
    waypoints."""
    pen = 0.0
    for w in range(tr.wp_bar.shape[0]):
        if tr.wp_bar[w] == t:
            k = tr.wp_idx[w]
            px = g.path[n, k, 0]
            pz = g.path[n, k, 1]
            wx = x + px * cy + pz * sy
            wz = z - px * sy + pz * cy
            d = np.sqrt((wx - tr.wp_pos[w, 0]) ** 2 + (wz - tr.wp_pos[w, 1]) ** 2)
            pen += tr.wp_w * max(0.0, d - tr.wp_tol[w])
        elif tr.wp_bar[w] > t:
            d = np.sqrt((nx - tr.wp_pos[w, 0]) ** 2 + (nz - tr.wp_pos[w, 1]) ** 2)
            need = d - tr.wp_tol[w] - tr.reach * (tr.wp_bar[w] - t)
            if need > 0:
                pen += tr.wp_w * need
    return pen


@njit(cache=True, inline="always")
def _offer(q, cand, i, x, z, yaw, cost, back, pose, n_slot, slots, cell):
    """Offer a candidate state (predecessor state i) for node q.

    With ``slots`` > 1 a node keeps up to that many states whose root positions differ by more
    than ``cell`` metres, so histories that end in different places survive (stage, waypoints);
    with ``cell`` < 0, states with different predecessors (k-best histories, for tied copies whose
    costs depend on the history).
    """
    n = n_slot[q]
    for k in range(n):
        if (
            slots == 1
            or (cell >= 0.0 and abs(pose[q, k, 0] - x) + abs(pose[q, k, 1] - z) < cell)
            or (cell < 0.0 and back[q, k] == i)
        ):
            if cand < cost[q, k]:
                cost[q, k] = cand
                back[q, k] = i
                pose[q, k, 0] = x
                pose[q, k, 1] = z
                pose[q, k, 2] = yaw
            return
    if n < slots:
        k = n
        n_slot[q] = n + 1
    else:
        k = 0
        for j in range(1, n):
            if cost[q, j] > cost[q, k]:
                k = j
        if cand >= cost[q, k]:
            return
    cost[q, k] = cand
    back[q, k] = i
    pose[q, k, 0] = x
    pose[q, k, 1] = z
    pose[q, k, 2] = yaw


@njit(cache=True)
def _short_list(row, short):
    """Up to ``short`` allowed (finite) nodes of a unary row, cheapest first."""
    order = np.argsort(row)
    n = 0
    while n < order.shape[0] and n < short and row[order[n]] < INF:
        n += 1
    return order[:n].astype(np.int64)


@njit(cache=True)
def _depth(ch, c):
    """The oldest chain step whose node the copies and charges of step c's states need."""
    depth = c - 1
    for j in range(ch.gap_ptr[c], ch.gap_ptr[c + 1]):
        depth = min(depth, ch.gap_step[j])
    for j in range(ch.charge_ptr[c], ch.charge_ptr[c + 1]):
        depth = min(depth, ch.charge_a[j], ch.charge_b[j])
    return depth


@njit(cache=True)
def _prepare(lo, hi, c, ch, g, tr, w_trans, slots, back, cost, pose, act, memo_node, memo_cost):
    """Ready the states ``act[0][lo:hi]`` of chain step c-1 to relax into step c: add their
    charges, walk their copies' poses, find the node the next chain bar follows. Writes
    ``act[1..3][a]`` (cost so far, source node, pose), or the final cost ``act[4][s]`` after the
    last step. States are independent: chunks of them run on different threads."""
    act_state, act_base, act_src, act_pose, final = act
    n_chain = ch.var.shape[0]
    prev = c - 1
    track = tr.on
    memo = memo_node.shape[1] > 0
    indptr, indices, costs = g.indptr, g.indices, g.costs
    out_feat, in_feat, blocks, weights = g.out_feat, g.in_feat, g.blocks, g.weights
    in_ptr, in_src, in_cost = g.in_ptr, g.in_src, g.in_cost
    mirror_of, motion, stage = g.mirror_of, g.motion, tr.stage
    n_wp = tr.wp_bar.shape[0]
    gap_step, gap_par, gap_bar = ch.gap_step, ch.gap_par, ch.gap_bar
    charge_a, charge_pa, charge_b, charge_pb = ch.charge_a, ch.charge_pa, ch.charge_b, ch.charge_pb
    charge_n = ch.charge_n
    g0, g1 = ch.gap_ptr[c], ch.gap_ptr[c + 1]
    h0, h1 = ch.charge_ptr[c], ch.charge_ptr[c + 1]
    depth = _depth(ch, c)
    # first each state's history (its nodes at steps depth..prev) and its charges' node pairs,
    # so that the feature rows of a later state's pairs can be fetched ahead (random reads)
    hist = np.empty((hi - lo, prev - depth + 1), np.int64)
    pair = np.empty((hi - lo, h1 - h0, 2), np.int64)
    for a in range(lo, hi):
        i = act_state[a]
        row = hist[a - lo]
        for j in range(prev, depth - 1, -1):
            row[j - depth] = i // slots
            i = back[j, i]
        for j in range(h0, h1):
            na = row[charge_a[j] - depth]
            nb = row[charge_b[j] - depth]
            pair[a - lo, j - h0, 0] = mirror_of[na] if charge_pa[j] == 1 else na
            pair[a - lo, j - h0, 1] = mirror_of[nb] if charge_pb[j] == 1 else nb
    width = out_feat.shape[1]
    for a in range(lo, hi):
        s = act_state[a]
        q = s // slots
        k = s - q * slots
        base = np.float64(cost[q, k])
        x, z, yaw = pose[q, k, 0], pose[q, k, 1], pose[q, k, 2]
        ahead = a + PREFETCH_AHEAD
        if ahead < hi:
            s2 = act_state[ahead]
            for j in range(h0, h1):
                na = pair[ahead - lo, j - h0, 0]
                nb = pair[ahead - lo, j - h0, 1]
                if not (memo and memo_node[s2, j, 0] == na and memo_node[s2, j, 1] == nb):
                    for col in range(0, width, 16):  # 16 float32: one 64-byte cache line
                        _prefetch(out_feat, na, col)
                        _prefetch(in_feat, nb, col)
        for j in range(h0, h1):
            na = pair[a - lo, j - h0, 0]
            nb = pair[a - lo, j - h0, 1]
            if memo and memo_node[s, j, 0] == na and memo_node[s, j, 1] == nb:
                t = memo_cost[s, j]
            else:
                # the edge list of the state's own node (in node order: in cache)
                if charge_a[j] == prev:
                    t = _edge_cost(indptr, indices, costs, na, nb)
                else:
                    t = _edge_cost(in_ptr, in_src, in_cost, nb, na)
                if t < 0:
                    t = _offgraph_cost(out_feat, in_feat, blocks, weights, na, nb)
                if memo:
                    memo_node[s, j, 0] = na
                    memo_node[s, j, 1] = nb
                    memo_cost[s, j] = t
            base += w_trans * charge_n[j] * t
        src = q  # the node of the bar before the next chain bar
        cy, sy = (np.cos(yaw), np.sin(yaw)) if track and g1 > g0 else (1.0, 0.0)
        for j in range(g0 if track else max(g0, g1 - 1), g1):
            src = hist[a - lo, gap_step[j] - depth]
            if gap_par[j] == 1:
                src = mirror_of[src]
            if track:
                x0, z0, cy0, sy0 = x, z, cy, sy
                pen, x, z, yaw, cy, sy = _placed(motion, stage, x, z, yaw, cy, sy, src)
                if n_wp > 0:
                    pen += _waypoint_terms(tr, g, x0, z0, cy0, sy0, x, z, src, gap_bar[j])
                base += pen
        if c == n_chain:
            final[s] = base
            continue
        act_base[a] = base
        act_src[a] = src
        act_pose[a, 0] = x
        act_pose[a, 1] = z
        act_pose[a, 2] = yaw


@njit(cache=True)
def _pull(lo, hi, unary_v, g, src_best, src_state, w_edge, cost, cur, n_slot, recent, novelty):
    """Nodes lo..hi-1 of a step with one state per node and no trajectory: each pulls its
    cheapest in-edge from ``src_best`` / ``src_state`` (the cheapest state continuing from each
    node), plus ``novelty`` where q repeats a node of that state's row of ``recent[0]`` (by
    state); writes the new state's row of ``recent[1]``. Reads the states at random, writes in
    order; nodes are independent."""
    in_ptr, in_src, in_cost = g.in_ptr, g.in_src, g.in_cost
    mirror_of = g.mirror_of
    rec, rec_out = recent
    window = rec.shape[1]
    for q in range(lo, hi):
        u = unary_v[q]
        if u == INF:
            continue
        best = np.inf
        arg = -1
        for e in range(in_ptr[q], in_ptr[q + 1]):
            p = in_src[e]
            val = src_best[p] + w_edge * in_cost[e]
            if val < best:
                best = val
                arg = src_state[p]
        if arg >= 0 and _reused(rec, arg, mirror_of, q):
            # the cheapest repeats a recent node: again with the penalty (it only raises a
            # value, so it is checked only where an edge would win)
            best = np.inf
            arg = -1
            for e in range(in_ptr[q], in_ptr[q + 1]):
                p = in_src[e]
                val = src_best[p] + w_edge * in_cost[e]
                if val < best and _reused(rec, src_state[p], mirror_of, q):
                    val += novelty
                if val < best:
                    best = val
                    arg = src_state[p]
        if arg >= 0:
            cost[q, 0] = best + u
            cur[q, 0] = arg
            n_slot[q] = 1
            if window > 0:
                _push_row(rec_out, q, q, rec, arg)


@njit(cache=True)
def _shift_recent(lo, hi, n_slot, cur, recent, out):
    """Rows of ``out`` for the states of nodes lo..hi-1 (``cur (N, slots)`` their predecessor
    states): the node, then the predecessor's row of ``recent`` without its oldest entry."""
    slots = cur.shape[1]
    for q in range(lo, hi):
        for k in range(n_slot[q]):
            _push_row(out, q * slots + k, q, recent, cur[q, k])


@njit(cache=True, parallel=True)
def _shift_recent_par(n_slot, cur, recent, out):
    """:func:`_shift_recent` over all nodes in chunks on all threads."""
    n = n_slot.shape[0]
    chunks = min(n, CHUNKS)
    for c in prange(chunks):
        _shift_recent(n * c // chunks, n * (c + 1) // chunks, n_slot, cur, recent, out)


@njit(cache=True, parallel=True)
def _prepare_par(n, c, ch, g, tr, w_trans, slots, back, cost, pose, act, memo_node, memo_cost):
    """:func:`_prepare` over ``n`` states in chunks on all threads."""
    chunks = min(n, CHUNKS)
    for i in prange(chunks):
        lo, hi = n * i // chunks, n * (i + 1) // chunks
        _prepare(lo, hi, c, ch, g, tr, w_trans, slots, back, cost, pose, act, memo_node, memo_cost)


@njit(cache=True, parallel=True)
def _pull_par(unary_v, g, src_best, src_state, w_edge, cost, cur, n_slot, recent, novelty):
    """:func:`_pull` over all nodes in chunks on all threads."""
    n = unary_v.shape[0]
    chunks = min(n, CHUNKS)
    for i in prange(chunks):
        lo, hi = n * i // chunks, n * (i + 1) // chunks
        _pull(lo, hi, unary_v, g, src_best, src_state, w_edge, cost, cur, n_slot, recent, novelty)


@njit(cache=True)
def forward(unary, ch, g, tr, w_trans, dense, slots, short, memo_node, memo_cost, novelty, window):
    """The forward pass.

    ``unary (V, N) float32``: cost of each node per variable (inf: not allowed); ``ch``, ``g``,
    ``tr``: the ``Chain``, ``Graph`` and ``Track`` tuples; ``w_trans``: λ11; ``dense (V,) bool``:
    the variable has a short allowed set (pins), relaxed from every state, not along edges;
    ``slots``: states per node; ``short``: length of the short list (pins, and the fallback
    when no edge reaches an allowed node); ``memo_node (N·slots, J, 2) int32`` and ``memo_cost
    (N·slots, J) float32``: charge j of state s was costed for that node pair (fill with -1 before
    the first pass; J = 0: no cache); ``novelty``: added to a relaxed transition into a node (or
    its mirror) that the state's history holds at one of its last ``window`` chain steps (0: no
    such cost; a take's consecutive bars are different nodes, so a take danced on never pays it,
    one danced again does). Copies of tied variables are not relaxed: the ties never pay it.

    Returns ``back (C, N·slots) int32`` (state s = node·slots + k; its predecessor state at the
    step before, -1 at step 0 and for unused states), ``final (N·slots,) float64`` (total cost of
    each final state, inf where unused) and the chain step no state reached (-1 when none).
    """
    n_nodes = unary.shape[1]
    n_chain = ch.var.shape[0]
    n_states = n_nodes * slots
    track = tr.on
    cell = tr.cell
    # the hot loops read tuple fields through locals (a field read costs reference counting)
    indptr, indices, costs = g.indptr, g.indices, g.costs
    out_feat, in_feat, blocks, weights = g.out_feat, g.in_feat, g.blocks, g.weights
    motion, stage = g.motion, tr.stage
    mirror_of = g.mirror_of
    n_wp = tr.wp_bar.shape[0]
    back = np.empty((n_chain, n_states), np.int32)
    # per state its nodes at its last ``window`` chain steps, newest first (-1: none), by state
    # id; built from the predecessor's row after each step (one read per state, no walk back)
    if novelty <= 0.0:
        window = 0
    recent = np.full((n_states, window), -1, np.int32)
    recent_next = np.full((n_states, window), -1, np.int32)
    cost = np.full((n_nodes, slots), INF, np.float32)
    pose = np.zeros((n_nodes, slots, 3))
    n_slot = np.zeros(n_nodes, np.int64)
    # the previous step's states, ready to relax: state id, cost so far, source node, pose; and
    # the final states' costs
    act = (
        np.empty(n_states, np.int64),
        np.empty(n_states),
        np.empty(n_states, np.int64),
        np.zeros((n_states, 3)),
        np.full(n_states, np.inf),
    )
    act_state, act_base, act_src, act_pose, final = act
    # pull pass: the cheapest state that continues from each node (float32, int32: the random
    # reads stay in cache on large graphs)
    src_best = np.empty(n_nodes, np.float32)
    src_state = np.empty(n_nodes, np.int32)

    # step 0: every allowed node, placed at the start pose
    cur = back[0].reshape((n_nodes, slots))
    cur[:] = -1
    v0 = ch.var[0]
    for q in range(n_nodes):
        u = unary[v0, q]
        if u < INF:
            pen, x, z, y = 0.0, 0.0, 0.0, 0.0
            if track:
                x, z, y = tr.start[0], tr.start[1], tr.start[2]
                cy, sy = np.cos(y), np.sin(y)
                x0, z0 = x, z
                pen, x, z, y, _, _ = _placed(motion, stage, x, z, y, cy, sy, q)
                if n_wp > 0:
                    pen += _waypoint_terms(tr, g, x0, z0, cy, sy, x, z, q, ch.bar[0])
            _offer(q, u + pen, -1, x, z, y, cost, cur, pose, n_slot, slots, cell)
    if window > 0:
        for s in range(n_states):
            recent[s, 0] = s // slots

    for c in range(1, n_chain + 1):
        # prepare: each state's charges, its copies' poses and the node the next bar follows
        n_act = 0
        for q in range(n_nodes):
            for k in range(n_slot[q]):
                act_state[n_act] = q * slots + k
                n_act += 1
        if n_act >= PARALLEL_MIN:
            _prepare_par(
                n_act, c, ch, g, tr, w_trans, slots, back, cost, pose, act, memo_node, memo_cost
            )
        else:
            _prepare(
                0, n_act, c, ch, g, tr, w_trans, slots, back, cost, pose, act, memo_node, memo_cost
            )
        if c == n_chain:
            break

        # relax into step c
        cost[:] = INF
        n_slot[:] = 0
        cur = back[c].reshape((n_nodes, slots))
        cur[:] = -1
        v = ch.var[c]
        cbar = ch.bar[c]
        w_edge = w_trans * ch.relax_n[c]
        reached = False
        shifted = False
        for rnd in range(2):
            # round 0: graph edges (or the short list when the variable is pinned);
            # round 1 only when nothing was reached: the short list, off-graph transitions allowed
            use_list = dense[v] or rnd == 1
            if rnd == 1 and (reached or dense[v]):
                break
            small = _short_list(unary[v], short) if use_list else np.empty(0, np.int64)
            pull = not use_list and slots == 1 and not track
            shifted = pull  # the pull writes its states' rows of ``recent_next``
            if pull:
                # one state per node, no trajectory: pull each node's cheapest in-edge (the
                # common case, about twice as fast as pushing along out-edges)
                src_best[:] = np.inf
                src_state[:] = -1
                for a in range(n_act):
                    src = act_src[a]
                    if act_base[a] < src_best[src]:
                        src_best[src] = act_base[a]
                        src_state[src] = act_state[a]
                rec = (recent, recent_next)
                args = (src_best, src_state, w_edge, cost, cur, n_slot, rec, novelty)
                if n_nodes >= PARALLEL_MIN:
                    _pull_par(unary[v], g, *args)
                else:
                    _pull(0, n_nodes, unary[v], g, *args)
            for a in range(0 if pull else n_act):
                i = act_state[a]
                base = act_base[a]
                src = act_src[a]
                x, z, yaw = act_pose[a, 0], act_pose[a, 1], act_pose[a, 2]
                cy, sy = (np.cos(yaw), np.sin(yaw)) if track else (1.0, 0.0)
                lo, hi = indptr[src], indptr[src + 1]
                if use_list:
                    lo, hi = 0, small.shape[0]
                for e in range(lo, hi):
                    if use_list:
                        q = small[e]
                        u = unary[v, q]
                        # transition and trajectory terms are not negative: a lower bound
                        if slots == 1 and base + u >= cost[q, 0]:
                            continue
                        t = _edge_cost(indptr, indices, costs, src, q)
                        if t < 0:
                            t = _offgraph_cost(out_feat, in_feat, blocks, weights, src, q)
                        cand = base + u + w_edge * t
                    else:
                        q = indices[e]
                        u = unary[v, q]
                        if u == INF:
                            continue
                        cand = base + w_edge * costs[e] + u
                    if slots == 1 and cand >= cost[q, 0]:
                        continue
                    if _reused(recent, i, mirror_of, q):
                        cand += novelty
                    nx, nz, ny = 0.0, 0.0, 0.0
                    if track:
                        pen, nx, nz, ny, _, _ = _placed(motion, stage, x, z, yaw, cy, sy, q)
                        if n_wp > 0:
                            pen += _waypoint_terms(tr, g, x, z, cy, sy, nx, nz, q, cbar)
                        cand += pen
                    _offer(q, cand, i, nx, nz, ny, cost, cur, pose, n_slot, slots, cell)
            for q in range(n_nodes):
                if n_slot[q] > 0:
                    reached = True
                    break
        if not reached:
            return back, final, c
        if window > 0 and not shifted:
            if n_nodes >= PARALLEL_MIN:
                _shift_recent_par(n_slot, cur, recent, recent_next)
            else:
                _shift_recent(0, n_nodes, n_slot, cur, recent, recent_next)
        recent, recent_next = recent_next, recent
    return back, final, -1


@njit(cache=True)
def path_transitions(g, nodes):
    """Transition cost into each bar of a path ``nodes (T,)``: ``(T,) float64`` (0 at bar 0) and
    ``(T,) bool``, True where it is not a graph edge (costed on demand, plus the penalty)."""
    n = nodes.shape[0]
    cost = np.zeros(n)
    offgraph = np.zeros(n, np.bool_)
    for t in range(1, n):
        p, q = nodes[t - 1], nodes[t]
        cost[t] = _edge_cost(g.indptr, g.indices, g.costs, p, q)
        offgraph[t] = cost[t] < 0
        if offgraph[t]:
            cost[t] = _offgraph_cost(g.out_feat, g.in_feat, g.blocks, g.weights, p, q)
    return cost, offgraph


def backtrack(back: np.ndarray, final: np.ndarray, slots: int) -> tuple[np.ndarray, float]:
    """Node per chain step ``(C,)`` of the cheapest final state, and its cost."""
    s = int(np.argmin(final))
    cost = float(final[s])
    out = np.empty(back.shape[0], dtype=np.int64)
    for c in range(back.shape[0] - 1, -1, -1):
        out[c] = s // slots
        s = int(back[c, s])
    return out, cost


@njit(cache=True, fastmath=True)
def data_terms(dot, zm_sq, zd_sq, sig_cost, signature, node_cost, w_style, w_data):
    """C_d in place of ``dot (T, N) float32`` (z_M·z_D): w_data·(w_style‖z_M − z_D‖ +
    ``sig_cost[t, signature[n]]`` + ``node_cost[n]``), one pass over the matrix (``sig_cost``
    and ``node_cost (N,)`` already weighted; every value is finite, so fastmath is safe and
    vectorises the square roots)."""
    ws = np.float32(w_style)
    wd = np.float32(w_data)
    for t in range(dot.shape[0]):
        row = dot[t]
        sig = sig_cost[t]
        zt = zm_sq[t]
        for n in range(dot.shape[1]):
            d2 = zt + zd_sq[n] - np.float32(2.0) * row[n]
            row[n] = wd * (
                ws * np.sqrt(max(d2, np.float32(0.0))) + sig[signature[n]] + node_cost[n]
            )
    return dot


@njit(cache=True)
def variable_costs(data, var, parity, mirror_of, n_vars):
    """``(V, N) float32``: per variable the sum of its bars' data rows ``data (T, N)``; a bar tied
    with parity 1 scores each node's mirror (inf where the node has none)."""
    n = data.shape[1]
    out = np.zeros((n_vars, n), np.float32)
    for t in range(data.shape[0]):
        row = out[var[t]]
        if parity[t] == 0:
            for q in range(n):
                row[q] += data[t, q]
        else:
            for q in range(n):
                m = mirror_of[q]
                row[q] += data[t, m] if m >= 0 else INF
    return out
