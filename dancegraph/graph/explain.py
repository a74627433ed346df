"""Explain a path: per bar the chosen node and its cost breakdown, plus the constraint check.

Per bar ``t``: ``style`` = λ10·λ12‖z_Mt − z_Dn‖, ``rhythm`` = λ10·λ13 (min_k G_r + A_n) (A_n the
node's anchoring cost, ``problem.anchor_costs``), ``transition`` = λ11·T(n_{t−1}, n_t) (the edge
cost; an off-graph transition, only possible between structure copies, costs its on-demand T plus
δT and is flagged), ``structure`` = ζ per violated repeat/mirror pair whose later bar is t,
``user`` = stage and waypoint penalties and choreography terms.
"""

from __future__ import annotations

import numpy as np

from dancegraph.errors import SpecError
from dancegraph.graph import _dp
from dancegraph.graph.problem import RECREATE_WEIGHT, STAGE_WEIGHT, WAYPOINT_WEIGHT, Problem
from dancegraph.graph.search import Alternative, bar_terms, root_trajectory

STAGE_TOLERANCE = 1e-6


def breakdown(graph, problem: Problem, spec, nodes) -> Alternative:
    """Per-bar costs and the constraint check of the path ``nodes (T,)`` on the compiled
    ``problem``; raises ``SpecError`` where it leaves the stage or misses a waypoint."""
    w = spec.weights
    n_bars = len(nodes)
    nodes = np.asarray(nodes, dtype=np.int64)
    st, rh = bar_terms(graph, problem.zm, problem.sig_cost, nodes, spec)
    user = np.zeros(n_bars)
    if problem.recreate is not None:
        user += RECREATE_WEIGHT * (np.asarray(graph.motif)[nodes] != problem.recreate)
    trans, offgraph = _dp.path_transitions(problem.dp, nodes)
    trans *= w.transition
    structure = np.zeros(n_bars)
    violations = []
    mirror_of = np.asarray(graph.mirror_of)
    for a, b, par, rule in problem.pairs:
        want = nodes[a] if par == 0 else mirror_of[nodes[a]]
        if nodes[b] != want:
            structure[b] += w.structure
            reason = (
                "the repeat and mirror rules contradict each other here"
                if (a, b, par, rule) in problem.contradictions
                else f"bar {b} should {'repeat' if par == 0 else 'mirror'} bar {a}"
            )
            violations.append({"bars": [int(a), int(b)], "rule": rule, "reason": reason})
    # trajectory: stage and waypoints
    track = problem.track
    placements = root_trajectory(graph, nodes, track.start)
    stage = track.stage[:4]
    radius = np.asarray(graph.radius, dtype=np.float64)
    if stage[0] < stage[1]:
        r = radius[nodes]
        x, z = placements[:, 0], placements[:, 1]
        over = (
            np.maximum(0, stage[0] - (x - r))
            + np.maximum(0, x + r - stage[1])
            + np.maximum(0, stage[2] - (z - r))
            + np.maximum(0, z + r - stage[3])
        )
        user += STAGE_WEIGHT * over
        if (over > STAGE_TOLERANCE).any():
            t = int(np.argmax(over))
            raise SpecError(
                f"stage: no path found that keeps the dancer on the stage (bar {t} leaves it by {over[t]:.2f} m)",
                code="constraint_conflict",
                field="stage",
            )
    path = problem.dp.path
    for i in range(len(track.wp_bar)):
        t = int(track.wp_bar[i])
        x, z, yaw = placements[t]
        px, pz = path[nodes[t], track.wp_idx[i]]
        c, s = np.cos(yaw), np.sin(yaw)
        wp_pos, wp_tol = track.wp_pos[i], track.wp_tol[i]
        d = float(np.hypot(x + px * c + pz * s - wp_pos[0], z - px * s + pz * c - wp_pos[1]))
        miss = max(0.0, d - wp_tol)
        user[t] += WAYPOINT_WEIGHT * miss
        if miss > 1e-6:
            raise SpecError(
                f"waypoints[{i}]: no path found that passes within {wp_tol} m of {wp_pos.tolist()} (closest {d:.2f} m)",
                code="constraint_conflict",
                field=f"waypoints[{i}]",
            )
    per_bar = []
    ids = graph.node_ids
    for t in range(n_bars):
        row = {
            "bar": t,
            "node": ids[nodes[t]],
            "style": round(float(st[t]), 4),
            "rhythm": round(float(rh[t]), 4),
            "transition": round(float(trans[t]), 4),
            "structure": round(float(structure[t]), 4),
            "user": round(float(user[t]), 4),
        }
        if offgraph[t]:
            row["offgraph"] = True
        per_bar.append(row)
    total = float(st.sum() + rh.sum() + trans.sum() + structure.sum() + user.sum())
    return Alternative(
        nodes=[ids[n] for n in nodes],
        index=nodes,
        cost=total,
        per_bar=per_bar,
        violations=violations,
        placements=placements,
    )


def format_table(alternative: dict) -> str:
    """A plain-text table of one alternative (``Alternative.to_dict()``): per bar the node and its
    cost terms, then the total and any violated structure pairs."""
    head = f"{'bar':>4}  {'node':<22}{'style':>8}{'rhythm':>8}{'trans':>8}{'struct':>8}{'user':>9}"
    lines = [head, "-" * len(head)]
    for row in alternative["per_bar"]:
        mark = " *" if row.get("offgraph") else ""
        lines.append(
            f"{row['bar']:>4}  {row['node']:<22}{row['style']:>8.2f}{row['rhythm']:>8.2f}"
            f"{row['transition']:>8.2f}{row['structure']:>8.1f}{row['user']:>9.2f}{mark}"
        )
    lines.append(f"total cost {alternative['cost']:.2f}")
    if any(r.get("offgraph") for r in alternative["per_bar"]):
        lines.append("* transition that is not a graph edge (between structure copies): T + δT")
    for v in alternative["violations"]:
        lines.append(f"violated {v['rule']} pair bars {v['bars'][0]}–{v['bars'][1]}: {v['reason']}")
    return "\n".join(lines)
