"""Path search: one graph node per music bar (ChoreoMaster §5, DESIGN.md §4).

``search(graph, analysis, spec)`` = ``run(graph, compile_spec(graph, analysis, spec), spec)``:
``problem.compile_spec`` turns the song and the spec into the DP's typed inputs (``Problem``:
data terms, allowed nodes, tied variables, chain, trajectory and kernel arrays) without running
it; ``run`` runs the DP once per alternative and costs each path (``explain.breakdown``).

Cost C = λ10 Σ C_d(i) + λ11 Σ C_t(i, i+1) + ζ Σ C_s + user terms, with
C_d(i) = λ12‖z_Mi − z_Di‖ + λ13 min_k G_r(R_Mi^k, R_Di) and C_t the edge cost T.

Structure constraints hold by construction, not by the penalty ζ alone: bars tied by the repeat
rule (same phrase label and index, different occurrences) or the mirror rule (same occurrence,
same meter identity; consecutive members alternate between a node and its mirror) are merged into
one *variable* with a parity (union-find with parity). The dynamic programme runs over the chain
of variables in song order of their first appearance, with the data terms of all tied bars summed
into their variable, so repeated phrases are solved jointly. Song bars that repeat an earlier
variable are filled from each DP state's own history, and their transitions, stage and waypoint
terms are costed exactly along the way (``_dp.forward``). Where the rules contradict each other
(an odd cycle of mirror and repeat ties) the pair is reported as violated with its reason and
charged ζ. Transitions between copies that are not graph edges are allowed at their true cost T
plus an off-graph penalty δT, so ties never make a song unsolvable.

User controls (``Spec``): include (pin a node at a bar, or the best bar of a range), exclude
(node, take wildcard or tag, optionally in a bar or time range), waypoints, stage bounds (on each
bar's root path, checked conservatively with the bar's largest root excursion), δT (edges above it
are not used), weights, motif pins, a target motif signature, re-creating a take's motif sequence.
Alternatives: the search runs again with a penalty on nodes (and their mirrors) used by earlier
alternatives, so alternatives share few nodes; each reports its own unpenalised cost. Within one
alternative a novelty cost (``NOVELTY_PENALTY``) falls on a transition into a node, or its mirror,
that the state's own history used at one of its last ``NOVELTY_WINDOW`` chain steps, so a dance
does not cycle through a few nodes; tied copies are not transitions the DP chooses and never pay
it. Like the reuse penalty it steers the search and is not part of the reported cost.

Speed and exactness: the DP keeps every node's cheapest state (no beam) and runs in a numba
kernel (``_dp``) over the CSR edges, so without ties, trajectory terms or the novelty cost (which
follows each state's own history) it is the exact Viterbi.
A state's copies and root pose follow its own best history (one history per node, as Viterbi
keeps), so tied copies and trajectories are costed exactly along the paths kept, not over all
histories; each distinct transition between copies is costed once per state, times its count
(with structure ties the result is the best path this DP keeps, not a proven global optimum).
States that can no longer reach a later waypoint at the graph's top speed are penalised early.
On graphs of up to ``KBEST_NODES`` nodes a node keeps up to ``POSITION_SLOTS`` states: with a
stage or waypoints, states that end in different places; with structure ties, states with
different predecessors (k-best histories: on the salsa graph this lowers the cost of a 148 s
song by about a quarter, at about 3× the search time). Larger graphs keep one state per node
(their many nodes already offer the variety; four states would cost four times the time).
Stage and waypoint terms are effectively hard (1e5 per metre); a best path that still misses one
raises ``SpecError(code='constraint_conflict')`` naming it. A target motif signature is followed
by planning a motif per bar whose histogram matches the target (an optimal assignment) and
searching with a penalty off the plan; the result keeps the better of planned and plain paths
by cost + χ² and reports its χ².
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dancegraph import jit
from dancegraph.errors import SpecError
from dancegraph.graph import _dp, choreography
from dancegraph.graph.artifact import MotionGraph
from dancegraph.graph.problem import DENSE_LIMIT, Problem, anchor_costs, compile_spec
from dancegraph.motion import quat
from dancegraph.motion.skeleton import Motion
from dancegraph.motion.stitch import turn_on_ground
from dancegraph.spec import Spec

MEMO_BUDGET = 1 << 23  # most (charged transition, state) costs kept across passes
DIVERSITY_PENALTY = 40.0  # per reuse of a node (or its mirror) of an earlier alternative
# within one alternative: a transition into a node (or its mirror) that the path used at one of
# its last NOVELTY_WINDOW chain steps costs NOVELTY_PENALTY, so a dance does not cycle through a
# few nodes (docs/rendering.md, Novelty)
NOVELTY_PENALTY = 30.0
NOVELTY_WINDOW = 8
SIGNATURE_SCALE = 100.0  # cost of a χ² of 1, per bar and per unit of signature.weight
SIGNATURE_STEPS = (8.0, 64.0)  # penalties per bar off the motif plan

#: the name under which the search's kernels register with ``dancegraph.jit``
KERNELS = "search"


@dataclass
class Alternative:
    """One path through the graph: ``nodes`` (T,) node ids and ``index`` (T,) their graph rows,
    one per music bar; ``cost`` the total C; ``per_bar`` each bar's cost terms; ``violations``
    the structure pairs it breaks; ``placements`` (T, 3) x, z (metres), yaw (radians) of each
    bar's first frame; ``choreography`` the motif report when the spec asked for one."""

    nodes: list[str]
    index: np.ndarray
    cost: float
    per_bar: list[dict]
    violations: list[dict]
    placements: np.ndarray  # (T, 3) x, z, yaw of each bar's first frame
    choreography: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "nodes": self.nodes,
            "index": np.asarray(self.index, dtype=int).tolist(),
            "cost": round(float(self.cost), 4),
            "per_bar": self.per_bar,
            "violations": self.violations,
            "placements": np.round(self.placements, 4).tolist(),
            "choreography": self.choreography,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Alternative:
        """Rebuild from ``to_dict`` output; KeyError/TypeError/ValueError on another shape."""
        nodes = [str(n) for n in d["nodes"]]
        return cls(
            nodes=nodes,
            index=np.asarray(d.get("index", []), dtype=np.int64).reshape(-1),
            cost=float(d["cost"]),
            per_bar=[dict(row) for row in d.get("per_bar", [])],
            violations=[dict(v) for v in d.get("violations", [])],
            placements=np.asarray(d.get("placements", []), dtype=float).reshape(-1, 3),
            choreography=dict(d.get("choreography") or {}),
        )


@dataclass
class SearchResult:
    """A search's answer: the ranked ``alternatives``, the constraint ``report``, and which graph
    (``graph_name``, ``graph_version``) answered it, so rendering uses that same version."""

    alternatives: list[Alternative]
    report: dict
    graph_name: str = ""
    graph_version: str = ""

    def to_dict(self) -> dict:
        return {
            "alternatives": [a.to_dict() for a in self.alternatives],
            "constraints": self.report,
            "graph": {"name": self.graph_name, "version": self.graph_version},
        }

    @classmethod
    def from_dict(cls, d: dict) -> SearchResult:
        """Rebuild from ``to_dict`` output; KeyError/TypeError/ValueError on another shape."""
        graph = d.get("graph") or {}
        return cls(
            alternatives=[Alternative.from_dict(a) for a in d["alternatives"]],
            report=dict(d.get("constraints") or {}),
            graph_name=str(graph.get("name") or ""),
            graph_version=str(graph.get("version") or ""),
        )


# --------------------------------------------------------------------------------------------
# the search


def search(graph: MotionGraph, analysis, spec: Spec) -> SearchResult:
    """Best path and ``spec.alternatives − 1`` diverse alternatives for ``analysis``'s bars:
    ``run(graph, compile_spec(graph, analysis, spec), spec)``."""
    jit.ensure(KERNELS)  # compiles into the shared kernel cache only under its lock
    return run(graph, compile_spec(graph, analysis, spec), spec)


def run(graph: MotionGraph, problem: Problem, spec: Spec) -> SearchResult:
    """Run the DP on a compiled ``problem``: one pass per alternative, each with a reuse penalty
    on the nodes (and mirrors) of the earlier ones; with a motif signature to follow, the best of
    the plain and the planned passes (``_follow_signature``); each alternative costed
    unpenalised by ``explain.breakdown``."""
    from dancegraph.graph.explain import breakdown  # imports this module's path helpers

    n_nodes = graph.n_nodes
    memo = _memo(problem, n_nodes)
    mirror_of = np.asarray(graph.mirror_of)
    bars_per_var = np.bincount(problem.var, minlength=problem.n_vars).astype(np.float32)
    penalty = np.zeros(n_nodes, dtype=np.float32)
    alternatives: list[Alternative] = []
    for _ in range(spec.alternatives):
        # the reuse penalty counts every bar a variable stands for
        u = problem.unary + bars_per_var[:, None] * penalty[None, :]
        if problem.target is not None:
            alt, nodes = _follow_signature(graph, problem, spec, u, memo)
        else:
            nodes = _pass(problem, u, spec, memo)
            alt = breakdown(graph, problem, spec, nodes)
        if problem.recreate is not None:
            alt.choreography["recreate_match"] = float(
                np.mean(problem.motif[nodes] == problem.recreate)
            )
        alternatives.append(alt)
        used = np.unique(nodes)
        penalty[used] += DIVERSITY_PENALTY
        mirrored = mirror_of[used]
        penalty[mirrored[mirrored >= 0]] += DIVERSITY_PENALTY
    return SearchResult(
        alternatives=alternatives,
        report=problem.report,
        graph_name=graph.name,
        graph_version=graph.version,
    )


def _memo(problem: Problem, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Per state the cost of each charged transition, kept across the passes (alternatives):
    ``_dp.forward``'s ``memo_node`` and ``memo_cost`` (no cache beyond ``MEMO_BUDGET``)."""
    n_charge = problem.chain.charge_n.size
    n_memo = n_charge if n_charge * n_nodes * problem.slots <= MEMO_BUDGET else 0
    return (
        np.full((n_nodes * problem.slots, n_memo, 2), -1, dtype=np.int32),
        np.zeros((n_nodes * problem.slots, n_memo), dtype=np.float32),
    )


def _pass(problem: Problem, unary: np.ndarray, spec: Spec, memo) -> np.ndarray:
    """One forward pass over the tied chain and its backtrack, with per-variable costs
    ``unary (V, N)``; returns the node of every song bar ``(T,)``."""
    unary = np.ascontiguousarray(unary, dtype=np.float32)
    with _dp.FORWARD_LOCK:
        back, final, dead = _dp.forward(
            unary,
            problem.chain,
            problem.dp,
            problem.track,
            float(spec.weights.transition),
            problem.dense,
            problem.slots,
            DENSE_LIMIT,
            memo[0],
            memo[1],
            NOVELTY_PENALTY,
            NOVELTY_WINDOW,
        )
    if dead >= 0:  # pragma: no cover - the dense fallback keeps every step reachable
        raise SpecError(
            f"no path reaches bar {int(problem.chain.bar[dead])}",
            code="constraint_conflict",
            field="include",
        )
    chain_nodes, _ = _dp.backtrack(back, final, problem.slots)
    nodes = chain_nodes[problem.step]
    flip = problem.parity == 1
    nodes[flip] = problem.dp.mirror_of[nodes[flip]]
    return nodes


def _follow_signature(
    graph: MotionGraph, problem: Problem, spec: Spec, unary: np.ndarray, memo
) -> tuple[Alternative, np.ndarray]:
    """The χ² to the target motif signature is not a per-bar cost: plan a motif per variable
    whose histogram follows the target (``choreography.plan_motifs``), search with penalties
    off the plan, and keep whichever path (plain or planned) has the lowest cost + scale·χ²."""
    from dancegraph.graph.explain import breakdown  # imports this module's path helpers

    target, motif, var = problem.target, problem.motif, problem.var
    assert target is not None and spec.signature is not None  # run() calls this only then
    scale = SIGNATURE_SCALE * spec.signature.weight * problem.music["n"]

    def scored(nodes: np.ndarray) -> tuple[float, Alternative, float, np.ndarray]:
        alt = breakdown(graph, problem, spec, nodes)
        chi2 = choreography.chi_square(
            choreography.motif_signature(motif[nodes], len(target)), target
        )
        return (alt.cost + scale * chi2, alt, chi2, nodes)

    best = scored(_pass(problem, unary, spec, memo))
    if spec.signature.weight > 0:
        k = len(target)
        best_by_motif = np.full((problem.n_vars, k), np.inf)
        for m in range(k):
            sel = motif == m
            if sel.any():
                best_by_motif[:, m] = unary[:, sel].min(axis=1)
        count = np.bincount(var, minlength=problem.n_vars)
        plan = choreography.plan_motifs(best_by_motif, count, target)
        for level in SIGNATURE_STEPS:
            off_plan = np.where(motif[None, :] != plan[:, None], np.float32(level), np.float32(0.0))
            cand = scored(_pass(problem, unary + off_plan, spec, memo))
            if cand[0] < best[0]:
                best = cand
    _, alt, chi2, nodes = best
    alt.choreography["signature_chi2"] = chi2
    alt.choreography["target"] = spec.signature.target
    return alt, nodes


def bar_terms(
    graph: MotionGraph, zm: np.ndarray, sig_cost: np.ndarray, nodes: np.ndarray, spec: Spec
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted style and rhythm terms ``(T,)`` of the chosen ``nodes (T,)`` (for explain); the
    rhythm term with the nodes' anchoring costs (``problem.anchor_costs``)."""
    w = spec.weights
    zd = np.asarray(graph.style)[nodes].astype(np.float64)
    style = w.data * w.style * np.linalg.norm(zm - zd, axis=1)
    g_r = sig_cost[np.arange(len(nodes)), np.asarray(graph.signature)[nodes].astype(int)]
    rhythm = w.data * w.rhythm * (g_r + anchor_costs(graph)[nodes])
    return style, rhythm


# --------------------------------------------------------------------------------------------
# placement


def root_trajectory(
    graph: MotionGraph, nodes: np.ndarray, start: np.ndarray | None = None
) -> np.ndarray:
    """Placement ``(T, 3)`` (x, z, yaw) of each bar's first frame when bars are chained by their
    root displacements, starting at ``start`` (default origin, yaw 0)."""
    pose = np.zeros(3) if start is None else np.asarray(start, dtype=float).copy()
    out = np.empty((len(nodes), 3))
    disp = np.asarray(graph.disp, dtype=float)
    for t, n in enumerate(nodes):
        out[t] = pose
        dx, dz, dyaw = disp[n]
        c, s = np.cos(pose[2]), np.sin(pose[2])
        pose = np.array([pose[0] + dx * c + dz * s, pose[1] - dx * s + dz * c, pose[2] + dyaw])
    return out


def placed_motion(
    graph: MotionGraph, node: int, placement: np.ndarray, fps: float | None = None
) -> Motion:
    """The node's bar turned and moved so its first frame's root sits at ``placement`` (x, z, yaw)."""
    m = graph.node_motion(node, fps)
    rot = m.rotations.copy()
    root, rot[:, 0] = turn_on_ground(
        m.root_positions,
        rot[:, 0],
        placement[2] - quat.heading_angle(m.rotations[0, 0]),
        m.root_positions[0],
        np.array([placement[0], 0.0, placement[1]]),
    )
    return Motion(skeleton=m.skeleton, fps=m.fps, root_positions=root, rotations=rot)


def warm_up() -> None:
    """Compile (or load from numba's cache) the search kernel on a two-node graph, so a service's
    first real query does not pay for it."""
    from types import SimpleNamespace

    from dancegraph.graph.artifact import bare_graph

    z = np.zeros
    graph = bare_graph(
        np.array([0, 1]),
        np.array([1, 0]),
        z(2),
        n_nodes=2,
        clips=["w"],
        mirror_of=np.array([1, 0], np.int32),
        node_source=z((2, 2), np.int32),
    )
    bars = np.array([[0.0, 2.0], [2.0, 4.0]])
    analysis = SimpleNamespace(
        bars=bars,
        signature_topk=z((2, 3), int),
        bar_onset_rms=np.ones((2, 2, 200)),
        tags=[{"label": "A", "occurrence": o, "index": 0, "meter_id": 0} for o in (0, 1)],
    )
    search(graph, analysis, Spec(alternatives=1))
    search(
        graph,
        analysis,
        Spec.model_validate({"alternatives": 1, "stage": {"x": [-9, 9], "z": [-9, 9]}}),
    )


jit.register(KERNELS, warm_up)
