"""Explain a path: per bar the chosen node and its cost breakdown, plus the constraint check.

Per bar ``t``: ``style`` = λ10·λ12‖z_Mt − z_Dn‖, ``rhythm`` = λ10·λ13 min_k G_r, ``transition`` =
λ11·T(n_{t−1}, n_t) (the edge cost; an off-graph transition, only possible between structure
copies, costs its on-demand T plus δT and is flagged), ``structure`` = ζ per violated repeat/mirror
pair whose later bar is t, ``user`` = stage and waypoint penalties and choreography terms.
"""

from __future__ import annotations

import numpy as np

from dancegraph.errors import SpecError
from dancegraph.graph import _dp
from dancegraph.graph.artifact import MotionGraph
from dancegraph.graph.search import (
    RECREATE_WEIGHT,
    STAGE_WEIGHT,
    WAYPOINT_WEIGHT,
    Alternative,
    SearchContext,
    bar_terms,
    root_trajectory,
)
from dancegraph.spec import Spec

STAGE_TOLERANCE = 1e-6


def breakdown(
    graph: MotionGraph,
    music: dict,
    spec: Spec,
    nodes: np.ndarray,
    ctx: SearchContext,
    pairs: list,
    contradictions: list,
) -> Alternative:
    """Cost breakdown and constraint check of path ``nodes`` (one per bar); raises SpecError
    when the stage or a waypoint is missed (no path satisfied it)."""
    w = spec.weights
    n_bars = len(nodes)
    nodes = np.asarray(nodes, dtype=np.int64)
    st, rh = bar_terms(graph, ctx.zm, ctx.sig_cost, nodes, spec)
    user = np.zeros(n_bars)
    if ctx.recreate is not None:
        user += RECREATE_WEIGHT * (np.asarray(graph.motif)[nodes] != ctx.recreate)
    trans, offgraph = _dp.path_transitions(ctx.dp, nodes)
    trans *= w.transition
    structure = np.zeros(n_bars)
    violations = []
    mirror_of = np.asarray(graph.mirror_of)
    for a, b, par, rule in pairs:
        want = nodes[a] if par == 0 else mirror_of[nodes[a]]
        if nodes[b] != want:
            structure[b] += w.structure
            reason = (
                "the repeat and mirror rules contradict each other here"
                if (a, b, par, rule) in contradictions
                else f"bar {b} should {'repeat' if par == 0 else 'mirror'} bar {a}"
            )
            violations.append({"bars": [int(a), int(b)], "rule": rule, "reason": reason})
    # trajectory: stage and waypoints
    placements = root_trajectory(graph, nodes, ctx.start)
    stage = ctx.stage
    radius = ctx.radius
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
    wp_bar, wp_idx, wp_pos, wp_tol = ctx.waypoints
    path = ctx.root_path
    for i in range(len(wp_bar)):
        t = int(wp_bar[i])
        x, z, yaw = placements[t]
        px, pz = path[nodes[t], wp_idx[i]]
        c, s = np.cos(yaw), np.sin(yaw)
        d = float(np.hypot(x + px * c + pz * s - wp_pos[i, 0], z - px * s + pz * c - wp_pos[i, 1]))
        miss = max(0.0, d - wp_tol[i])
        user[t] += WAYPOINT_WEIGHT * miss
        if miss > 1e-6:
            raise SpecError(
                f"waypoints[{i}]: no path found that passes within {wp_tol[i]} m of {wp_pos[i].tolist()} (closest {d:.2f} m)",
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
