"""Numba kernels of the graph search (see ``search.py`` for the model).

One forward pass over the *chain* of tied variables (first appearances in song order) with a beam
of at most ``beam`` states per chain step (exact when the graph has no more nodes than that).
Every state carries its root pose so stage bounds and waypoints are costed on the trajectory.
Song bars between two chain steps are copies of earlier variables (repeat/mirror ties): their
nodes come from the state's own history (backtracking), their transitions are costed exactly.
"""

from __future__ import annotations

import numpy as np
from numba import njit

INF = np.float32(np.inf)


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


@njit(cache=True, fastmath=False)
def pair_cost(
    indptr, indices, costs, exit_f, entry_f, style, blocks, w_pose, w_style, offgraph, p, q
):
    """Edge cost p→q when the edge exists, else the on-demand T plus the off-graph penalty."""
    c = _edge_cost(indptr, indices, costs, p, q)
    if c >= 0:
        return c
    t = 0.0
    start = 0
    for b in range(blocks.shape[0]):
        s = 0.0
        for d in range(start, start + blocks[b]):
            x = exit_f[p, d] - entry_f[q, d]
            s += x * x
        t += np.sqrt(s)
        start += blocks[b]
    s = 0.0
    for d in range(style.shape[1]):
        x = style[p, d] - style[q, d]
        s += x * x
    return np.float32(w_pose * t + w_style * np.sqrt(s) + offgraph)


@njit(cache=True, inline="always")
def _advance(x, z, yaw, dx, dz, dyaw):
    c = np.cos(yaw)
    s = np.sin(yaw)
    return x + dx * c + dz * s, z - dx * s + dz * c, yaw + dyaw


@njit(cache=True, inline="always")
def _pose_penalty(
    x, z, yaw, n, t, radius, path, stage, stage_w, wp_bar, wp_idx, wp_pos, wp_tol, wp_w
):
    """User penalty for placing node n at pose (x, z, yaw) as song bar t."""
    pen = 0.0
    if stage[0] < stage[1]:
        r = radius[n]
        over = 0.0
        over += max(0.0, stage[0] - (x - r)) + max(0.0, (x + r) - stage[1])
        over += max(0.0, stage[2] - (z - r)) + max(0.0, (z + r) - stage[3])
        pen += stage_w * over
    for w in range(wp_bar.shape[0]):
        if wp_bar[w] == t:
            k = wp_idx[w]
            px = path[n, k, 0]
            pz = path[n, k, 1]
            c = np.cos(yaw)
            s = np.sin(yaw)
            wx = x + px * c + pz * s
            wz = z - px * s + pz * c
            d = np.sqrt((wx - wp_pos[w, 0]) ** 2 + (wz - wp_pos[w, 1]) ** 2)
            pen += wp_w * max(0.0, d - wp_tol[w])
    return pen


@njit(cache=True, inline="always")
def _lookahead(x, z, t, wp_bar, wp_pos, wp_tol, reach, wp_w):
    """Penalty for a state whose next bar starts at (x, z) after song bar t when a later waypoint
    is out of reach even at the graph's largest per-bar travel ``reach`` (a lower bound, so it
    never rules out a feasible path; it makes far-off states lose the beam to feasible ones)."""
    pen = 0.0
    for w in range(wp_bar.shape[0]):
        if wp_bar[w] > t:
            d = np.sqrt((x - wp_pos[w, 0]) ** 2 + (z - wp_pos[w, 1]) ** 2)
            need = d - wp_tol[w] - reach * (wp_bar[w] - t)
            if need > 0:
                pen += wp_w * need
    return pen


@njit(cache=True)
def _walk_gap(
    i,
    prev,
    g0,
    g1,
    act_node,
    act_back,
    act_cost,
    act_pose,
    hist,
    gap_bar,
    gap_var,
    gap_par,
    var_chain,
    mirror_of,
    indptr,
    indices,
    costs,
    exit_f,
    entry_f,
    style,
    blocks,
    w_pose,
    w_style,
    w_trans,
    offgraph,
    disp,
    radius,
    path,
    stage,
    stage_w,
    wp_bar,
    wp_idx,
    wp_pos,
    wp_tol,
    wp_w,
    reach,
    track,
):
    """State i of step ``prev`` walked through the copies g0..g1: (cost, x, z, yaw, last node)."""
    src = act_node[prev, i]
    base = act_cost[prev, i]
    x = act_pose[prev, i, 0]
    z = act_pose[prev, i, 1]
    yaw = act_pose[prev, i, 2]
    if g1 > g0:
        depth = prev
        for g in range(g0, g1):
            if var_chain[gap_var[g]] < depth:
                depth = var_chain[gap_var[g]]
        k = i
        for s in range(prev, depth - 1, -1):
            hist[s] = act_node[s, k]
            k = act_back[s, k]
        for g in range(g0, g1):
            node = hist[var_chain[gap_var[g]]]
            if gap_par[g] == 1:
                node = mirror_of[node]
            base += w_trans * pair_cost(
                indptr,
                indices,
                costs,
                exit_f,
                entry_f,
                style,
                blocks,
                w_pose,
                w_style,
                offgraph,
                src,
                node,
            )
            if track:
                base += _pose_penalty(
                    x,
                    z,
                    yaw,
                    node,
                    gap_bar[g],
                    radius,
                    path,
                    stage,
                    stage_w,
                    wp_bar,
                    wp_idx,
                    wp_pos,
                    wp_tol,
                    wp_w,
                )
                x, z, yaw = _advance(x, z, yaw, disp[node, 0], disp[node, 1], disp[node, 2])
                base += _lookahead(x, z, gap_bar[g], wp_bar, wp_pos, wp_tol, reach, wp_w)
            src = node
    return base, x, z, yaw, src


@njit(cache=True, inline="always")
def _offer(q, cand, i, x, z, yaw, best, best_back, best_pose, n_slot, touched, nt, slots, cell):
    """Offer a candidate state for node q; returns the new touched count.

    With ``slots`` > 1 a node keeps up to that many states whose root positions differ by more
    than ``cell`` metres, so histories that end in different places survive (stage, waypoints);
    with ``cell`` < 0, states with different predecessors (k-best histories, for tied copies whose
    costs depend on the history).
    """
    n = n_slot[q]
    if n == 0:
        touched[nt] = q
        nt += 1
    for k in range(n):
        if (
            slots == 1
            or (cell >= 0.0 and abs(best_pose[q, k, 0] - x) + abs(best_pose[q, k, 1] - z) < cell)
            or (cell < 0.0 and best_back[q, k] == i)
        ):
            if cand < best[q, k]:
                best[q, k] = cand
                best_back[q, k] = i
                best_pose[q, k, 0] = x
                best_pose[q, k, 1] = z
                best_pose[q, k, 2] = yaw
            return nt
    if n < slots:
        k = n
        n_slot[q] = n + 1
    else:
        k = 0
        for j in range(1, n):
            if best[q, j] > best[q, k]:
                k = j
        if cand >= best[q, k]:
            return nt
    best[q, k] = cand
    best_back[q, k] = i
    best_pose[q, k, 0] = x
    best_pose[q, k, 1] = z
    best_pose[q, k, 2] = yaw
    return nt


@njit(cache=True)
def forward(
    unary,  # (V, N) float32 per variable
    chain_var,  # (C,) variable of each chain step
    chain_bar,  # (C,) song bar of each chain step
    gap_ptr,  # (C+2,) copies before chain step c (and trailing copies at C) in gap_bar/gap_var/gap_par
    gap_bar,
    gap_var,
    gap_par,
    var_chain,  # (V,) chain step of each variable
    indptr,
    indices,
    costs,
    exit_f,
    entry_f,
    style,
    blocks,
    mirror_of,
    disp,
    radius,
    path,
    w_pose,
    w_style,
    w_trans,
    offgraph,
    start_pose,  # (3,)
    stage,  # (4,) xmin xmax zmin zmax (xmin >= xmax: none)
    stage_w,
    wp_bar,
    wp_idx,
    wp_pos,
    wp_tol,
    wp_w,
    beam,
    var_dense,  # (V,) bool: the variable has a short allowed set (pins): relax from the list
    slots,
    cell,
    reach,  # largest root travel of any node in one bar (m): waypoint look-ahead
    track,  # follow the root trajectory (stage or waypoints set); else poses stay 0
    short,  # length of the short list (pinned variables, and the fallback)
):
    n_nodes = unary.shape[1]
    n_chain = chain_var.shape[0]
    act_node = np.full((n_chain, beam), -1, np.int32)
    act_back = np.full((n_chain, beam), -1, np.int32)
    act_cost = np.full((n_chain, beam), INF, np.float32)
    act_pose = np.zeros((n_chain, beam, 3), np.float64)
    act_n = np.zeros(n_chain, np.int64)

    best = np.full((n_nodes, slots), INF, np.float32)
    best_back = np.full((n_nodes, slots), -1, np.int32)
    best_pose = np.zeros((n_nodes, slots, 3), np.float64)
    n_slot = np.zeros(n_nodes, np.int64)
    touched = np.empty(n_nodes, np.int64)
    hist = np.empty(n_chain, np.int32)

    # step 0: every allowed node, placed at the start pose
    v0 = chain_var[0]
    nt = 0
    for q in range(n_nodes):
        u = unary[v0, q]
        if u < INF:
            pen = 0.0
            x = 0.0
            z = 0.0
            y = 0.0
            if track:
                pen = _pose_penalty(
                    start_pose[0],
                    start_pose[1],
                    start_pose[2],
                    q,
                    chain_bar[0],
                    radius,
                    path,
                    stage,
                    stage_w,
                    wp_bar,
                    wp_idx,
                    wp_pos,
                    wp_tol,
                    wp_w,
                )
                x, z, y = _advance(
                    start_pose[0], start_pose[1], start_pose[2], disp[q, 0], disp[q, 1], disp[q, 2]
                )
                pen += _lookahead(x, z, chain_bar[0], wp_bar, wp_pos, wp_tol, reach, wp_w)
            nt = _offer(
                q,
                u + pen,
                -1,
                x,
                z,
                y,
                best,
                best_back,
                best_pose,
                n_slot,
                touched,
                nt,
                slots,
                cell,
            )
    _select(
        0,
        nt,
        touched,
        best,
        best_back,
        best_pose,
        n_slot,
        act_node,
        act_back,
        act_cost,
        act_pose,
        act_n,
        beam,
    )

    for c in range(1, n_chain + 1):
        prev = c - 1
        g0 = gap_ptr[c]
        g1 = gap_ptr[c + 1]
        if c == n_chain:
            # trailing copies: each final state only collects their cost
            if g1 > g0:
                for i in range(act_n[prev]):
                    base, x, z, yaw, src = _walk_gap(
                        i,
                        prev,
                        g0,
                        g1,
                        act_node,
                        act_back,
                        act_cost,
                        act_pose,
                        hist,
                        gap_bar,
                        gap_var,
                        gap_par,
                        var_chain,
                        mirror_of,
                        indptr,
                        indices,
                        costs,
                        exit_f,
                        entry_f,
                        style,
                        blocks,
                        w_pose,
                        w_style,
                        w_trans,
                        offgraph,
                        disp,
                        radius,
                        path,
                        stage,
                        stage_w,
                        wp_bar,
                        wp_idx,
                        wp_pos,
                        wp_tol,
                        wp_w,
                        reach,
                        track,
                    )
                    act_cost[prev, i] = base
            break
        v = chain_var[c]
        cbar = chain_bar[c]
        dense = var_dense[v]
        nt = 0
        small = np.empty(0, np.int64)
        if dense:
            small = _short_list(unary[v], short)
        for rnd in range(2):
            # round 0: graph edges (or the short list when the variable is pinned);
            # round 1 only when nothing was reached: the short list, off-graph transitions allowed
            if rnd == 1:
                if nt > 0:
                    break
                small = _short_list(unary[v], short)
                if small.shape[0] == 0:
                    break
            use_list = dense or rnd == 1
            for i in range(act_n[prev]):
                if g1 > g0:
                    base, x, z, yaw, src = _walk_gap(
                        i,
                        prev,
                        g0,
                        g1,
                        act_node,
                        act_back,
                        act_cost,
                        act_pose,
                        hist,
                        gap_bar,
                        gap_var,
                        gap_par,
                        var_chain,
                        mirror_of,
                        indptr,
                        indices,
                        costs,
                        exit_f,
                        entry_f,
                        style,
                        blocks,
                        w_pose,
                        w_style,
                        w_trans,
                        offgraph,
                        disp,
                        radius,
                        path,
                        stage,
                        stage_w,
                        wp_bar,
                        wp_idx,
                        wp_pos,
                        wp_tol,
                        wp_w,
                        reach,
                        track,
                    )
                else:  # the common case, kept free of a call with many array arguments
                    src = act_node[prev, i]
                    base = act_cost[prev, i]
                    x = act_pose[prev, i, 0]
                    z = act_pose[prev, i, 1]
                    yaw = act_pose[prev, i, 2]
                if use_list:
                    for s in range(small.shape[0]):
                        q = small[s]
                        cand = (
                            base
                            + unary[v, q]
                            + w_trans
                            * pair_cost(
                                indptr,
                                indices,
                                costs,
                                exit_f,
                                entry_f,
                                style,
                                blocks,
                                w_pose,
                                w_style,
                                offgraph,
                                src,
                                q,
                            )
                        )
                        nx = 0.0
                        nz = 0.0
                        ny = 0.0
                        if track:
                            cand += _pose_penalty(
                                x,
                                z,
                                yaw,
                                q,
                                cbar,
                                radius,
                                path,
                                stage,
                                stage_w,
                                wp_bar,
                                wp_idx,
                                wp_pos,
                                wp_tol,
                                wp_w,
                            )
                            nx, nz, ny = _advance(x, z, yaw, disp[q, 0], disp[q, 1], disp[q, 2])
                            cand += _lookahead(nx, nz, cbar, wp_bar, wp_pos, wp_tol, reach, wp_w)
                        nt = _offer(
                            q,
                            cand,
                            i,
                            nx,
                            nz,
                            ny,
                            best,
                            best_back,
                            best_pose,
                            n_slot,
                            touched,
                            nt,
                            slots,
                            cell,
                        )
                else:
                    for e in range(indptr[src], indptr[src + 1]):
                        q = indices[e]
                        u = unary[v, q]
                        if u == INF:
                            continue
                        cand = base + w_trans * costs[e] + u
                        if slots == 1 and cand >= best[q, 0]:
                            continue
                        nx = 0.0
                        nz = 0.0
                        ny = 0.0
                        if track:
                            cand += _pose_penalty(
                                x,
                                z,
                                yaw,
                                q,
                                cbar,
                                radius,
                                path,
                                stage,
                                stage_w,
                                wp_bar,
                                wp_idx,
                                wp_pos,
                                wp_tol,
                                wp_w,
                            )
                            nx, nz, ny = _advance(x, z, yaw, disp[q, 0], disp[q, 1], disp[q, 2])
                            cand += _lookahead(nx, nz, cbar, wp_bar, wp_pos, wp_tol, reach, wp_w)
                        nt = _offer(
                            q,
                            cand,
                            i,
                            nx,
                            nz,
                            ny,
                            best,
                            best_back,
                            best_pose,
                            n_slot,
                            touched,
                            nt,
                            slots,
                            cell,
                        )
        _select(
            c,
            nt,
            touched,
            best,
            best_back,
            best_pose,
            n_slot,
            act_node,
            act_back,
            act_cost,
            act_pose,
            act_n,
            beam,
        )
        if act_n[c] == 0:
            return act_node, act_back, act_cost, act_n, c
    return act_node, act_back, act_cost, act_n, -1


@njit(cache=True)
def _short_list(row, short):
    """Up to ``short`` allowed (finite) nodes of a unary row, cheapest first."""
    order = np.argsort(row)
    n = 0
    while n < order.shape[0] and n < short and row[order[n]] < INF:
        n += 1
    return order[:n].astype(np.int64)


@njit(cache=True)
def _select(
    c,
    nt,
    touched,
    best,
    best_back,
    best_pose,
    n_slot,
    act_node,
    act_back,
    act_cost,
    act_pose,
    act_n,
    beam,
):
    """Keep the ``beam`` cheapest offered states as step c's active list; reset the buffers."""
    m = 0
    for j in range(nt):
        m += n_slot[touched[j]]
    vals = np.empty(m, np.float32)
    m = 0
    for j in range(nt):
        q = touched[j]
        for k in range(n_slot[q]):
            vals[m] = best[q, k]
            m += 1
    cut = np.partition(vals, beam - 1)[beam - 1] if m > beam else INF
    n = 0
    # below the cut first, then ties at the cut until the beam is full
    for rnd in range(2):
        for j in range(nt):
            q = touched[j]
            for k in range(n_slot[q]):
                if n >= beam:
                    break
                v = best[q, k]
                take = (m <= beam or v < cut) if rnd == 0 else (m > beam and v == cut)
                if take:
                    act_node[c, n] = q
                    act_back[c, n] = best_back[q, k]
                    act_cost[c, n] = v
                    act_pose[c, n, 0] = best_pose[q, k, 0]
                    act_pose[c, n, 1] = best_pose[q, k, 1]
                    act_pose[c, n, 2] = best_pose[q, k, 2]
                    n += 1
    for j in range(nt):
        q = touched[j]
        for k in range(n_slot[q]):
            best[q, k] = INF
            best_back[q, k] = -1
        n_slot[q] = 0
    act_n[c] = n


def backtrack(
    act_node: np.ndarray, act_back: np.ndarray, act_cost: np.ndarray, act_n: np.ndarray
) -> tuple[np.ndarray, float]:
    """Node per chain step ``(C,)`` of the cheapest final state, and its cost."""
    last = act_node.shape[0] - 1
    n = int(act_n[last])
    i = int(np.argmin(act_cost[last, :n]))
    cost = float(act_cost[last, i])
    out = np.empty(last + 1, dtype=np.int64)
    for c in range(last, -1, -1):
        out[c] = act_node[c, i]
        i = int(act_back[c, i])
    return out, cost
