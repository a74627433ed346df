"""Path search: one graph node per music bar (ChoreoMaster §5, DESIGN.md §4).

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
alternatives, so alternatives share few nodes; each reports its own unpenalised cost.

Speed and exactness: the DP keeps every node's cheapest state (no beam) and runs in a numba
kernel (``_dp``) over the CSR edges, so without ties or trajectory terms it is the exact Viterbi.
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
from dancegraph.embed import descriptor
from dancegraph.errors import NotFoundError, SpecError
from dancegraph.graph import _dp, choreography
from dancegraph.graph.artifact import MotionGraph
from dancegraph.motion import quat
from dancegraph.motion.skeleton import Motion
from dancegraph.rhythm.signatures import COMMON_DISTANCES
from dancegraph.spec import Spec

KBEST_NODES = 4096  # graphs up to this size keep k-best histories under structure ties
STATE_BUDGET = 1 << 26  # most back pointers (chain steps × nodes × slots) one pass stores
MEMO_BUDGET = 1 << 23  # most (charged transition, state) costs kept across passes
DENSE_LIMIT = 64
STAGE_WEIGHT = 1.0e5  # per metre outside the stage: effectively hard
WAYPOINT_WEIGHT = 1.0e5  # per metre beyond a waypoint's tolerance: effectively hard
DIVERSITY_PENALTY = 40.0  # per reuse of a node (or its mirror) of an earlier alternative
POSITION_SLOTS = 4  # states kept per node when stage or waypoints are set
POSITION_CELL = 0.1  # metres (L1) that make two states' root positions different
SIGNATURE_SCALE = 100.0  # cost of a χ² of 1, per bar and per unit of signature.weight
SIGNATURE_STEPS = (8.0, 64.0)  # penalties per bar off the motif plan
RECREATE_WEIGHT = 100.0  # per bar whose motif differs from the reference take's


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


@dataclass
class SearchContext:
    """What the passes of one search share, and what explaining a path reads: the DP's arrays
    (``dp``, ``chain``, ``track``, ``slots`` states per node, ``dense`` variables relaxed from
    every state), each bar's chain ``step`` and mirror ``parity``, the trajectory terms
    (``stage`` bounds and weight, ``start`` pose, ``waypoints`` as (bar, path index, position,
    tolerance) arrays, node ``radius``, ``root_path``), the data terms' inputs (``zm`` (T, 32)
    music style, ``sig_cost`` (T, 13)), the motif sequence to re-create (or None), and the
    charge cache kept across passes (``memo``)."""

    dp: _dp.Graph
    chain: _dp.Chain
    track: _dp.Track
    slots: int
    step: np.ndarray
    parity: np.ndarray
    stage: np.ndarray
    start: np.ndarray
    waypoints: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    radius: np.ndarray
    root_path: np.ndarray
    zm: np.ndarray
    sig_cost: np.ndarray
    recreate: np.ndarray | None
    dense: np.ndarray
    memo: tuple[np.ndarray, np.ndarray]


# --------------------------------------------------------------------------------------------
# music side


def _music_arrays(analysis) -> dict:
    bars = np.asarray(analysis.bars, dtype=float).reshape(-1, 2)
    n = bars.shape[0]
    if n == 0:
        raise SpecError("the music has no bars to dance to", code="no_bars", field="analysis.bars")
    topk = np.asarray(analysis.signature_topk, dtype=int).reshape(n, -1)
    onset = np.asarray(analysis.bar_onset_rms, dtype=float)
    tags = list(analysis.tags) if analysis.tags is not None else []
    if len(tags) != n:
        tags = [{"label": f"x{t}", "occurrence": 0, "index": 0, "meter_id": t} for t in range(n)]
    return {"bars": bars, "n": n, "topk": topk, "onset": onset, "tags": tags}


def bars_in(spec_range, seconds, bars: np.ndarray, field_name: str) -> np.ndarray:
    """Bar indices covered by an inclusive bar range or a time range (all bars when neither)."""
    n = bars.shape[0]
    if spec_range is not None:
        a, b = spec_range
        if a >= n:
            raise SpecError(
                f"{field_name}: bar {a} is past the song's last bar {n - 1}",
                code="constraint_conflict",
                field=field_name,
            )
        return np.arange(a, min(b, n - 1) + 1)
    if seconds is not None:
        a, b = seconds
        sel = np.nonzero((bars[:, 1] > a) & (bars[:, 0] <= b))[0]
        if sel.size == 0:
            raise SpecError(
                f"{field_name}: no bar lies in [{a}, {b}] s",
                code="constraint_conflict",
                field=field_name,
            )
        return sel
    return np.arange(n)


# --------------------------------------------------------------------------------------------
# structure ties: union-find with parity


class _Ties:
    def __init__(self, n: int):
        self.parent = np.arange(n)
        self.parity = np.zeros(n, dtype=np.int8)  # parity relative to parent

    def find(self, a: int) -> tuple[int, int]:
        p = 0
        while self.parent[a] != a:
            p ^= int(self.parity[a])
            a = int(self.parent[a])
        return a, p

    def union(self, a: int, b: int, par: int) -> bool:
        """Tie bar b to bar a with parity ``par``; False when that contradicts earlier ties."""
        ra, pa = self.find(a)
        rb, pb = self.find(b)
        if ra == rb:
            return (pa ^ pb) == par
        if ra > rb:
            ra, rb, pa, pb = rb, ra, pb, pa
        self.parent[rb] = ra
        self.parity[rb] = pa ^ pb ^ par
        return True


def structure_pairs(
    tags: list[dict], repeat: bool, mirror: bool
) -> list[tuple[int, int, int, str]]:
    """Tied bar pairs ``(a, b, parity, rule)``: repeat pairs (parity 0) link consecutive
    occurrences of the same (label, index); mirror pairs (parity 1) link consecutive bars of one
    occurrence with the same meter identity."""
    pairs = []
    if repeat:
        groups: dict = {}
        for t, tag in enumerate(tags):
            groups.setdefault((tag.get("label"), tag.get("index")), []).append(
                (tag.get("occurrence"), t)
            )
        for members in groups.values():
            members.sort()
            for (oa, a), (ob, b) in zip(members, members[1:], strict=False):
                if oa != ob:
                    pairs.append((a, b, 0, "repeat"))
    if mirror:
        groups = {}
        for t, tag in enumerate(tags):
            if tag.get("meter_id") is None:
                continue
            groups.setdefault(
                (tag.get("label"), tag.get("occurrence"), tag.get("meter_id")), []
            ).append(t)
        for members in groups.values():
            for a, b in zip(members, members[1:], strict=False):
                pairs.append((a, b, 1, "mirror"))
    return pairs


# --------------------------------------------------------------------------------------------
# node matching


def match_nodes(
    graph: MotionGraph, node: str | None, tag: str | None, field_name: str
) -> np.ndarray:
    if tag is not None:
        if tag not in graph.tags:
            raise NotFoundError(
                f"{field_name}: unknown tag {tag!r} (known: {', '.join(graph.tags)})",
                code="unknown_tag",
                field=field_name,
            )
        bit = np.uint32(graph.tag_bit(tag))
        return np.nonzero(np.asarray(graph.node_tags) & bit)[0]
    assert node is not None  # the spec's validator: a node, or a tag
    take, _, rest = node.partition(":")
    if rest == "*":
        if take not in graph.clips:
            raise NotFoundError(
                f"{field_name}: unknown take {take!r}", code="unknown_node", field=field_name
            )
        return np.nonzero(np.asarray(graph.node_clip) == graph.clips.index(take))[0]
    if not graph.has_node(node):
        raise NotFoundError(
            f"{field_name}: node {node!r} does not exist in graph {graph.name}",
            code="unknown_node",
            field=field_name,
        )
    return np.array([graph.node_index(node)])


# --------------------------------------------------------------------------------------------
# the search


def music_style(music: dict, graph: MotionGraph | None = None, analysis=None) -> np.ndarray:
    """Style of each music bar ``(T, 32)`` in ``graph``'s style space (see ``music_inputs``)."""
    return music_inputs(music, graph, analysis)[0]


def music_inputs(music: dict, graph: MotionGraph | None, analysis=None) -> tuple[np.ndarray, dict]:
    """The music side of the data term for ``graph``: ``(zm (T, 32), music')``, ``music'`` a copy
    of ``music`` whose ``topk (T, 3)`` are the signatures the rhythm term uses and whose
    ``style_source`` says where both came from.

    Style: ``descriptor`` (``descriptor-v1`` graphs); ``e_m``, the graph's style model's E_M
    style that ``analysis.learned_style`` carries under the model's hash; else ``bridge``, the
    descriptor style mapped into the learned space (``embed.learned``). Signatures: the
    analysis's own (``analytic``), or with a rhythm model in the graph its top-3
    (``rhythm_model``: ``analysis.learned_topk`` under its hash, else computed here).
    """
    dur = music["bars"][:, 1] - music["bars"][:, 0]
    onset = music["onset"]
    if onset.ndim == 3 and onset.shape[0] == music["n"]:
        z = descriptor.embed_music(dur, onset)
    else:
        z = descriptor.embed(
            np.column_stack(
                [np.log2(240.0 / np.maximum(dur, 1e-3) / 120.0)] + [np.zeros(music["n"])] * 7
            )
        )
    entry = (graph.manifest.get("embedding") or {}) if graph is not None else {}
    source = {"style": "descriptor", "signatures": "analytic"}
    out = {**music, "style_source": source}
    if "style_model" not in entry and "rhythm_model" not in entry:
        return z, out
    from dancegraph.embed import learned  # loads torch only when a model is used

    style, topk = learned.analysis_terms(entry, analysis, music["n"])
    if "style_model" in entry:
        source["style_model"] = entry["style_model"]["version"]
        source["style"] = "e_m" if style is not None else "bridge"
        if style is None:
            source["note"] = (
                "the analysis carries no E_M style for this model (made without the audio): "
                "descriptor style bridged into the learned space"
            )
            style = learned.bridged_style(entry, z)
    else:
        style = z
    if "rhythm_model" in entry:
        if topk is None and onset.ndim == 3 and onset.shape[0] == music["n"]:
            root = learned.store_root(graph)
            if root is not None:
                topk = learned.music_topk(entry["rhythm_model"], root, music["bars"], onset)
        if topk is not None:
            out["topk"] = np.asarray(topk, dtype=int)
            source["signatures"] = "rhythm_model"
            source["rhythm_model"] = entry["rhythm_model"]["version"]
    return style, out


def data_costs(graph: MotionGraph, zm: np.ndarray, sig_cost: np.ndarray, spec: Spec) -> np.ndarray:
    """C_d for every bar and node ``(T, N) float32``: λ10·(λ12‖z_M − z_D‖ + λ13 min_k G_r).

    ``zm (T, 32)`` music style; ``sig_cost (T, 13)`` min over the bar's top-K signatures of the
    distance to each common signature. One matrix product, then one fused pass (the hot path of
    a query).
    """
    jit.ensure("search")
    w = spec.weights
    zm = zm.astype(np.float32)
    dot = zm @ np.asarray(graph.style, dtype=np.float32).T
    return _dp.data_terms(
        dot,
        (zm * zm).sum(1),
        _style_sq(graph),
        (w.rhythm * sig_cost).astype(np.float32),
        _ro(graph.signature, np.int8),
        float(w.style),
        float(w.data),
    )


def _cached(graph: MotionGraph, key, make):
    """``make()`` computed once per loaded graph and ``key`` (a graph version never changes)."""
    cache = graph.__dict__.setdefault("_cache", {})
    if key not in cache:
        cache[key] = make()
    return cache[key]


def _in_edges(
    graph: MotionGraph, threshold: float, indptr: np.ndarray, indices: np.ndarray, costs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The same edges by target (``in_ptr (N+1,)``, ``in_src (E,) int32``, ``in_cost (E,)``) for
    the DP's pull pass, cached on the graph per threshold."""

    def make():
        order = np.argsort(indices, kind="stable")
        in_ptr = np.zeros(graph.n_nodes + 1, dtype=np.int64)
        np.cumsum(np.bincount(indices, minlength=graph.n_nodes), out=in_ptr[1:])
        src = np.repeat(np.arange(graph.n_nodes, dtype=np.int32), np.diff(indptr))
        return (
            _ro(in_ptr, np.int64),
            _ro(src[order], np.int32),
            _ro(costs[order], np.float32),
        )

    return _cached(graph, ("in_edges", float(threshold)), make)


def _feature_rows(graph: MotionGraph) -> dict[str, np.ndarray]:
    """``out_feat`` and ``in_feat`` of ``_dp.Graph``: per node one row of exit (entry) features
    and style (cached on the graph)."""

    def make():
        style = np.asarray(graph.style, dtype=np.float32)
        return {
            side: _ro(np.concatenate([np.asarray(f, dtype=np.float32), style], axis=1), np.float32)
            for side, f in (("out_feat", graph.exit_pc), ("in_feat", graph.entry_pc))
        }

    return _cached(graph, "feature_rows", make)


def _motion_record(graph: MotionGraph) -> np.ndarray:
    """``(N, 8)`` per node: dx, dz, dyaw, cos dyaw, sin dyaw, radius, 0, 0 (``_dp.Graph.motion``:
    one cache line per node for the trajectory terms; cached on the graph)."""

    def make():
        disp = np.asarray(graph.disp, dtype=np.float64)
        rec = np.zeros((graph.n_nodes, 8))
        rec[:, :3] = disp
        rec[:, 3] = np.cos(disp[:, 2])
        rec[:, 4] = np.sin(disp[:, 2])
        rec[:, 5] = graph.radius
        return _ro(rec, np.float64)

    return _cached(graph, "motion", make)


def _style_sq(graph: MotionGraph) -> np.ndarray:
    """‖z_D‖² per node (cached on the graph)."""

    def make():
        zd = np.asarray(graph.style, dtype=np.float32)
        return (zd * zd).sum(1)

    return _cached(graph, "style_sq", make)


def bar_terms(
    graph: MotionGraph, zm: np.ndarray, sig_cost: np.ndarray, nodes: np.ndarray, spec: Spec
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted style and rhythm terms ``(T,)`` of the chosen ``nodes (T,)`` (for explain)."""
    w = spec.weights
    zd = np.asarray(graph.style)[nodes].astype(np.float64)
    style = w.data * w.style * np.linalg.norm(zm - zd, axis=1)
    rhythm = (
        w.data
        * w.rhythm
        * sig_cost[np.arange(len(nodes)), np.asarray(graph.signature)[nodes].astype(int)]
    )
    return style, rhythm


def search(graph: MotionGraph, analysis, spec: Spec) -> SearchResult:
    """Best path and ``spec.alternatives − 1`` diverse alternatives for ``analysis``'s bars."""
    from dancegraph.graph.explain import breakdown  # cost breakdown and constraint check of a path

    jit.ensure("search")  # compiles into the shared kernel cache only under its lock
    music = _music_arrays(analysis)
    n_bars, n_nodes = music["n"], graph.n_nodes
    zm, music = music_inputs(music, graph, analysis)
    sig_cost = COMMON_DISTANCES[music["topk"]].min(axis=1)  # (T, 13)
    data = data_costs(graph, zm, sig_cost, spec)
    # restrictions: a mask for all bars, and masks of single bars (None: everything allowed)
    every_ok: np.ndarray | None = None
    bar_ok: dict[int, np.ndarray] = {}
    report: dict = {"pins": [], "excluded_bars": 0, "structure_pairs": 0, "conflicts": []}

    def restrict(bars: np.ndarray, keep: np.ndarray) -> None:
        nonlocal every_ok
        if bars.size == n_bars:
            every_ok = keep if every_ok is None else every_ok & keep
            return
        for t in bars.tolist():
            bar_ok[t] = keep if t not in bar_ok else bar_ok[t] & keep

    def allowed_at(t: int) -> np.ndarray:
        ok = np.ones(n_nodes, dtype=bool) if every_ok is None else every_ok.copy()
        if t in bar_ok:
            ok &= bar_ok[t]
        return ok

    indptr, indices, costs = edges_below(graph, spec.transition_threshold)

    for i, ex in enumerate(spec.exclude):
        fname = f"exclude[{i}]"
        nodes = match_nodes(graph, ex.node, ex.tag, f"{fname}.{'tag' if ex.tag else 'node'}")
        bars = bars_in(ex.bars, ex.seconds, music["bars"], fname)
        keep = np.ones(n_nodes, dtype=bool)
        keep[nodes] = False
        restrict(bars, keep)
        report["excluded_bars"] += int(bars.size)

    motif = np.asarray(graph.motif)
    for i, mp in enumerate(spec.motifs):
        fname = f"motifs[{i}]"
        k = int(graph.manifest.get("motifs", {}).get("k", motif.max() + 1))
        if mp.motif >= k:
            raise NotFoundError(
                f"{fname}.motif: the graph has motifs 0..{k - 1}",
                code="unknown_motif",
                field=f"{fname}.motif",
            )
        if mp.bar >= n_bars:
            raise SpecError(
                f"{fname}.bar: the song has {n_bars} bars",
                code="constraint_conflict",
                field=f"{fname}.bar",
            )
        restrict(np.array([mp.bar]), motif == mp.motif)
    target_sig = None
    if spec.signature is not None:
        target_sig = target_signature(graph, spec.signature.target, "signature.target")
    recreate = None
    if spec.recreate is not None:
        try:
            seq = choreography.take_motif_sequence(graph, spec.recreate)
        except ValueError as exc:
            raise NotFoundError(
                f"recreate: unknown take {spec.recreate!r}", code="unknown_node", field="recreate"
            ) from exc
        recreate = np.resize(seq, n_bars)
        data += RECREATE_WEIGHT * (motif[None, :] != recreate[:, None])

    # pins
    pinned: dict[int, tuple[int, str]] = {}
    for i, inc in enumerate(spec.include):
        fname = f"include[{i}]"
        node = match_nodes(graph, inc.node, None, f"{fname}.node")[0]
        bars = bars_in(inc.bars, inc.seconds, music["bars"], fname)
        ok = np.array([t for t in bars.tolist() if allowed_at(t)[node]], dtype=np.int64)
        if ok.size == 0:
            raise SpecError(
                f"{fname}: node {inc.node} is excluded wherever it is asked for",
                code="constraint_conflict",
                field=fname,
            )
        t = int(ok[np.argmin(data[ok, node])]) if ok.size > 1 else int(ok[0])
        if t in pinned and pinned[t][0] != node:
            raise SpecError(
                f"{fname}: bar {t} is already pinned to {graph.node_ids[pinned[t][0]]} by {pinned[t][1]}",
                code="constraint_conflict",
                field=fname,
            )
        pinned[t] = (node, fname)
        report["pins"].append({"field": fname, "node": inc.node, "bar": t})

    # structure ties
    ties = _Ties(n_bars)
    pairs = structure_pairs(music["tags"], spec.structure.repeat, spec.structure.mirror)
    contradictions = []
    for a, b, par, rule in pairs:
        if not ties.union(a, b, par):
            contradictions.append((a, b, par, rule))
    report["structure_pairs"] = len(pairs)
    roots = np.empty(n_bars, dtype=np.int64)
    parity = np.empty(n_bars, dtype=np.int8)
    for t in range(n_bars):
        roots[t], parity[t] = ties.find(t)
    # the root is the smallest bar of its group (union keeps the smaller root): parity 0 there
    uniq, var = np.unique(roots, return_inverse=True)
    n_vars = uniq.size
    mirror_of = _ro(graph.mirror_of, np.int64)
    has_mirror = mirror_of >= 0
    safe_mirror = np.where(has_mirror, mirror_of, 0)

    # per variable: the data terms of all its bars (a mirrored bar scores the node's mirror)
    if n_vars == n_bars and not parity.any():
        unary = data  # no ties: one variable per bar
    else:
        unary = _dp.variable_costs(data, var, parity, mirror_of, n_vars)
    var_ok: dict[int, np.ndarray] = {}
    for t in range(n_bars):
        if parity[t] == 0 and every_ok is None and t not in bar_ok:
            continue
        ok = allowed_at(t)
        if parity[t] == 1:
            ok = has_mirror & ok[safe_mirror]
        v = int(var[t])
        var_ok[v] = ok if v not in var_ok else var_ok[v] & ok
    fixed: dict[int, tuple[int, str]] = {}
    for t, (node, fname) in pinned.items():
        v = int(var[t])
        want = node if parity[t] == 0 else int(mirror_of[node])
        if want < 0:
            raise SpecError(
                f"{fname}: bar {t} must mirror another bar but {graph.node_ids[node]} has no mirror",
                code="constraint_conflict",
                field=fname,
            )
        if v in fixed and fixed[v][0] != want:
            raise SpecError(
                f"{fname}: the repeat/mirror rules tie bar {t} to a bar pinned by {fixed[v][1]} to another node",
                code="constraint_conflict",
                field=fname,
            )
        if v in var_ok and not var_ok[v][want]:
            raise SpecError(
                f"{fname}: node {graph.node_ids[node]} is excluded at a bar tied to bar {t}",
                code="constraint_conflict",
                field=fname,
            )
        fixed[v] = (want, fname)
    for v, (want, _) in fixed.items():
        ok = np.zeros(n_nodes, dtype=bool)
        ok[want] = True
        var_ok[v] = ok
    if var_ok and unary is data:
        unary = data.copy()
    for v, ok in var_ok.items():
        unary[v, ~ok] = np.inf
    n_allowed = np.isfinite(unary).sum(axis=1)
    empty = np.nonzero(n_allowed == 0)[0]
    if empty.size:
        members = np.nonzero(var == empty[0])[0]
        t = int(members[0])
        if parity[members].any() and all(allowed_at(int(m)).any() for m in members):
            raise SpecError(
                f"bars {members.tolist()} must mirror each other (structure.mirror) but the excludes leave no node with an allowed mirror",
                code="constraint_conflict",
                field="structure.mirror",
            )
        raise SpecError(
            f"no node is allowed at bar {t}: the excludes (and motif pins) rule out every node",
            code="constraint_conflict",
            field=_blame(spec, t),
        )

    chain, step = _chain(var, parity)
    n_chain = chain.var.size

    # stage, waypoints
    stage = np.array([1.0, 0.0, 1.0, 0.0])
    start = np.zeros(3)
    if spec.stage is not None:
        stage = np.array(
            [spec.stage.x[0], spec.stage.x[1], spec.stage.z[0], spec.stage.z[1]], dtype=float
        )
        start[:2] = [stage[:2].mean(), stage[2:].mean()]
    wp_bar, wp_idx, wp_pos, wp_tol = [], [], [], []
    n_path = graph.root_path.shape[1]
    for i, wp in enumerate(spec.waypoints):
        bars = music["bars"]
        if wp.second > bars[-1, 1]:
            raise SpecError(
                f"waypoints[{i}]: {wp.second} s is after the song's last bar",
                code="constraint_conflict",
                field=f"waypoints[{i}].second",
            )
        t = int(np.clip(np.searchsorted(bars[:, 0], wp.second, side="right") - 1, 0, n_bars - 1))
        frac = (wp.second - bars[t, 0]) / max(bars[t, 1] - bars[t, 0], 1e-6)
        wp_bar.append(t)
        wp_idx.append(int(np.clip(round(frac * n_path), 0, n_path - 1)))
        wp_pos.append(wp.position)
        wp_tol.append(wp.tolerance)
    waypoints = (
        np.array(wp_bar, dtype=np.int64),
        np.array(wp_idx, dtype=np.int64),
        np.array(wp_pos, dtype=np.float64).reshape(-1, 2),
        np.array(wp_tol, dtype=np.float64),
    )

    params = graph.manifest.get("params", {})
    on = spec.stage is not None or bool(spec.waypoints)
    # on small graphs, several states per node: different root positions (trajectory terms) or
    # different predecessors (tied copies, whose costs depend on the history); the back pointers
    # (C × N × slots int32) stay within STATE_BUDGET
    slots = POSITION_SLOTS if n_nodes <= KBEST_NODES and (on or n_vars < n_bars) else 1
    slots = max(1, min(slots, STATE_BUDGET // max(1, n_chain * n_nodes)))
    in_ptr, in_src, in_cost = _in_edges(graph, spec.transition_threshold, indptr, indices, costs)
    dp_graph = _dp.Graph(
        indptr=_ro(indptr, np.int64),
        indices=_ro(indices, np.int32),
        costs=_ro(costs, np.float32),
        in_ptr=in_ptr,
        in_src=in_src,
        in_cost=in_cost,
        # transitions that are not edges are costed from the compressed features
        **_feature_rows(graph),
        blocks=_ro(graph.manifest["pc_blocks"], np.int64),
        mirror_of=mirror_of,
        motion=_motion_record(graph),
        path=_ro(graph.root_path, np.float64),
        weights=np.array(
            [
                float(params.get("w_pose", 1.0)),
                float(params.get("w_style", 1.5)),
                float(spec.transition_threshold),
            ]
        ),
    )
    reach = 0.0
    if n_nodes:
        reach = float(max(np.hypot(graph.disp[:, 0], graph.disp[:, 1]).max(), np.max(graph.radius)))
    track = _dp.Track(
        on=on,
        cell=POSITION_CELL if on else -1.0,
        start=start,
        stage=np.append(stage, STAGE_WEIGHT),
        wp_bar=waypoints[0],
        wp_idx=waypoints[1],
        wp_pos=waypoints[2],
        wp_tol=waypoints[3],
        wp_w=WAYPOINT_WEIGHT,
        reach=reach,
    )
    # per state the cost of each charged transition, kept across the passes (alternatives)
    n_memo = chain.charge_n.size if chain.charge_n.size * n_nodes * slots <= MEMO_BUDGET else 0
    ctx = SearchContext(
        dp=dp_graph,
        chain=chain,
        track=track,
        slots=slots,
        step=step,
        parity=parity,
        stage=stage,
        start=start,
        waypoints=waypoints,
        radius=_ro(graph.radius, np.float64),
        root_path=dp_graph.path,
        zm=zm,
        sig_cost=sig_cost,
        recreate=recreate,
        # a short allowed set (pins, motif pins) is relaxed from every state, not along edges
        dense=n_allowed <= DENSE_LIMIT,
        memo=(
            np.full((n_nodes * slots, n_memo, 2), -1, dtype=np.int32),
            np.zeros((n_nodes * slots, n_memo), dtype=np.float32),
        ),
    )
    alternatives: list[Alternative] = []
    bars_per_var = np.bincount(var, minlength=n_vars).astype(np.float32)
    penalty = np.zeros(n_nodes, dtype=np.float32)

    def run_with(unary_costs: np.ndarray) -> np.ndarray:
        # one DP pass over the tied chain; only the per-variable costs change between passes
        return _run(ctx, unary_costs, spec)

    for k in range(spec.alternatives):
        # the reuse penalty counts every bar a variable stands for
        u = unary + bars_per_var[:, None] * penalty[None, :]
        if target_sig is not None:
            assert spec.signature is not None  # target_sig is set only with it
            # the χ² to the target is not a per-bar cost: plan motifs (see below) and keep the
            # path with the best cost + scale·χ²
            scale = SIGNATURE_SCALE * spec.signature.weight * n_bars

            def scored(nodes, scale=scale):
                alt = breakdown(graph, music, spec, nodes, ctx, pairs, contradictions)
                chi2 = choreography.chi_square(
                    choreography.motif_signature(motif[nodes], len(target_sig)), target_sig
                )
                return (alt.cost + scale * chi2, alt, chi2, nodes)

            best = scored(run_with(u))
            if spec.signature.weight > 0:
                # plan a motif per variable whose histogram follows the target, then search with a
                # penalty on other motifs; keep whichever path has the lower cost + scale·χ²
                k = len(target_sig)
                best_by_motif = np.full((n_vars, k), np.inf)
                for m in range(k):
                    sel = motif == m
                    if sel.any():
                        best_by_motif[:, m] = u[:, sel].min(axis=1)
                count = np.bincount(var, minlength=n_vars)
                plan = choreography.plan_motifs(best_by_motif, count, target_sig)
                for level in SIGNATURE_STEPS:
                    off_plan = np.where(
                        motif[None, :] != plan[:, None], np.float32(level), np.float32(0.0)
                    )
                    cand = scored(run_with(u + off_plan))
                    if cand[0] < best[0]:
                        best = cand
            _, alt, chi2, nodes = best
            alt.choreography["signature_chi2"] = chi2
            alt.choreography["target"] = spec.signature.target
        else:
            nodes = run_with(u)
            alt = breakdown(graph, music, spec, nodes, ctx, pairs, contradictions)
        if recreate is not None:
            alt.choreography["recreate_match"] = float(np.mean(motif[nodes] == recreate))
        alternatives.append(alt)
        used = np.unique(nodes)
        penalty[used] += DIVERSITY_PENALTY
        mirrored = mirror_of[used]
        penalty[mirrored[mirrored >= 0]] += DIVERSITY_PENALTY
    report["conflicts"] = [
        {
            "bars": [int(a), int(b)],
            "rule": rule,
            "reason": "the repeat and mirror rules contradict each other here",
        }
        for a, b, _, rule in contradictions
    ]
    report["variables"] = int(n_vars)
    report["bars"] = int(n_bars)
    report["music_style"] = music["style_source"]
    return SearchResult(
        alternatives=alternatives, report=report, graph_name=graph.name, graph_version=graph.version
    )


def edges_below(graph: MotionGraph, threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The graph's CSR edges ``(indptr, indices, costs)`` with cost below ``threshold`` (δT, the
    novelty control), keeping consecutive bars of a take (and their mirrors), which are always
    linked. The graph's own arrays when its build threshold is not above ``threshold``."""
    indptr = np.asarray(graph.indptr, dtype=np.int64)
    indices = np.asarray(graph.indices, dtype=np.int32)
    costs = np.asarray(graph.costs, dtype=np.float32)
    if threshold >= graph.manifest.get("params", {}).get("threshold", np.inf) or costs.size == 0:
        return indptr, indices, costs
    src = np.repeat(np.arange(graph.n_nodes), np.diff(indptr))
    clip, bar, kind = (np.asarray(a) for a in (graph.node_clip, graph.node_bar, graph.node_kind))
    consecutive = (
        (clip[src] == clip[indices])
        & (bar[indices] == bar[src] + 1)
        & (kind[src] == kind[indices])
        & (kind[src] <= 1)
    )
    keep = (costs < threshold) | consecutive
    new_ptr = np.zeros_like(indptr)
    np.cumsum(np.bincount(src[keep], minlength=graph.n_nodes), out=new_ptr[1:])
    return new_ptr, indices[keep], costs[keep]


def _ro(a, dtype) -> np.ndarray:
    """A read-only contiguous view (or converted copy) of a graph array for the kernel.

    Memory-mapped artifacts are read-only; marking in-memory graphs' arrays the same way keeps
    one compiled specialisation of the numba kernel for both.
    """
    out = np.ascontiguousarray(a, dtype=dtype).view()
    out.flags.writeable = False
    return out


def warm_up() -> None:
    """Compile (or load from numba's cache) the search kernel on a two-node graph, so a service's
    first real query does not pay for it."""
    from dancegraph.graph.artifact import graph_from_arrays

    n, d = 2, 4
    z = np.zeros
    arrays: dict[str, np.ndarray] = {
        "node_clip": z(n, np.int32),
        "node_bar": np.arange(n, dtype=np.int32),
        "node_kind": z(n, np.int8),
        "node_tags": z(n, np.uint32),
        "node_source": z((n, 2), np.int32),
        "mirror_of": np.array([1, 0], np.int32),
        "style": z((n, 32), np.float32),
        "signature": z(n, np.int8),
        "motif": z(n, np.int32),
        "entry": z((n, d), np.float32),
        "exit": z((n, d), np.float32),
        "entry_pc": z((n, d), np.float32),
        "exit_pc": z((n, d), np.float32),
        "disp": z((n, 3), np.float32),
        "radius": z(n, np.float32),
        "root_path": z((n, 8, 2), np.float32),
        "duration": np.ones(n, np.float32),
        "indptr": np.array([0, 1, 2], np.int64),
        "indices": np.array([1, 0], np.int32),
        "costs": z(2, np.float32),
        "motion_row": z(n, np.int32),
        "root": z((1, 4, 3), np.float32),
        "rotations": z((1, 4, 1, 4), np.float16),
    }
    manifest = {
        "clips": ["w"],
        "tags": ["original"],
        "pc_blocks": [d],
        "feature_blocks": [d],
        "params": {},
    }
    graph = graph_from_arrays(arrays, manifest)
    from types import SimpleNamespace

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


def _blame(spec: Spec, t: int) -> str:
    for i, m in enumerate(spec.motifs):
        if m.bar == t:
            return f"motifs[{i}]"
    return "exclude"


def target_signature(graph: MotionGraph, target: str, field_name: str) -> np.ndarray:
    mot = graph.manifest.get("motifs", {})
    k = int(mot.get("k", int(np.max(graph.motif)) + 1))
    if target == "dataset":
        return np.asarray(
            mot.get(
                "signature",
                choreography.motif_signature(
                    np.asarray(graph.motif)[np.asarray(graph.node_kind) == 0], k
                ),
            )
        )
    if target not in graph.clips:
        raise NotFoundError(
            f"{field_name}: unknown take {target!r}", code="unknown_node", field=field_name
        )
    return choreography.motif_signature(choreography.take_motif_sequence(graph, target), k)


def _chain(var: np.ndarray, parity: np.ndarray) -> tuple[_dp.Chain, np.ndarray]:
    """The DP's chain for bars tied to variables ``var (T,)`` with parities ``parity (T,)``, and
    the chain step of each bar ``(T,)``.

    Chain steps are the variables' first appearances in song order; the other bars are copies.
    Transitions between consecutive bars, as (step, parity) pairs: a chain bar's incoming one is
    relaxed along graph edges, weighted by its count in the song; every other distinct one is
    charged once, times its count, to the states of the later of its two steps (their history
    decides both ends).
    """
    n_bars = var.size
    first_bar = np.full(int(var.max()) + 1, n_bars, dtype=np.int64)
    np.minimum.at(first_bar, var, np.arange(n_bars))
    is_first = first_bar[var] == np.arange(n_bars)
    chain_bar = np.nonzero(is_first)[0]
    n_chain = chain_bar.size
    var_chain = np.empty(first_bar.size, dtype=np.int64)
    var_chain[var[chain_bar]] = np.arange(n_chain)
    step = var_chain[var]
    gap_bar = np.nonzero(~is_first)[0]
    trans = np.column_stack([step[:-1], parity[:-1], step[1:], parity[1:]]).astype(np.int64)
    count = np.ones(0, dtype=np.int64)
    if n_bars > 1:
        trans, count = np.unique(trans, axis=0, return_counts=True)
    into = np.column_stack(
        [
            step[chain_bar[1:] - 1],
            parity[chain_bar[1:] - 1],
            step[chain_bar[1:]],
            np.zeros(n_chain - 1, dtype=np.int64),  # a first appearance has parity 0
        ]
    )
    relaxed = (trans[:, None, :] == into[None, :, :]).all(axis=2)  # (distinct, chain bars)
    relax_n = np.ones(n_chain)
    relax_n[1:] = (count[:, None] * relaxed).sum(axis=0)
    charged = ~relaxed.any(axis=1)
    trans, count = trans[charged], count[charged]
    when = np.maximum(trans[:, 0], trans[:, 2]) + 1
    order = np.argsort(when, kind="stable")
    trans, count, when = trans[order], count[order], when[order]

    def col(a: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(a, dtype=np.int64)

    chain = _dp.Chain(
        var=col(var[chain_bar]),
        bar=col(chain_bar),
        # copies before chain step c lie between chain_bar[c-1] and chain_bar[c] (C: trailing)
        gap_ptr=_ptr(np.searchsorted(chain_bar, gap_bar), n_chain),
        gap_bar=col(gap_bar),
        gap_step=col(step[gap_bar]),
        gap_par=col(parity[gap_bar]),
        charge_ptr=_ptr(when, n_chain),
        charge_a=col(trans[:, 0]),
        charge_pa=col(trans[:, 1]),
        charge_b=col(trans[:, 2]),
        charge_pb=col(trans[:, 3]),
        charge_n=count.astype(np.float64),
        relax_n=relax_n,
    )
    return chain, step


def _ptr(owner: np.ndarray, n_chain: int) -> np.ndarray:
    """``(C+2,)`` offsets of the entries owned by each chain step 0..C (``owner`` sorted)."""
    ptr = np.zeros(n_chain + 2, dtype=np.int64)
    ptr[1:] = np.cumsum(np.bincount(owner, minlength=n_chain + 1))
    return ptr


def _run(ctx: SearchContext, unary: np.ndarray, spec: Spec) -> np.ndarray:
    """One forward pass and backtrack; returns the node of every song bar ``(T,)``."""
    unary = np.ascontiguousarray(unary, dtype=np.float32)
    with _dp.FORWARD_LOCK:
        back, final, dead = _dp.forward(
            unary,
            ctx.chain,
            ctx.dp,
            ctx.track,
            float(spec.weights.transition),
            ctx.dense,
            ctx.slots,
            DENSE_LIMIT,
            *ctx.memo,
        )
    if dead >= 0:  # pragma: no cover - the dense fallback keeps every step reachable
        raise SpecError(
            f"no path reaches bar {int(ctx.chain.bar[dead])}",
            code="constraint_conflict",
            field="include",
        )
    chain_nodes, _ = _dp.backtrack(back, final, ctx.slots)
    nodes = chain_nodes[ctx.step]
    flip = ctx.parity == 1
    nodes[flip] = ctx.dp.mirror_of[nodes[flip]]
    return nodes


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
    yaw0 = quat.heading_angle(m.rotations[0, 0])
    turn = quat.from_y_angle(np.array(placement[2] - yaw0))
    rel = m.root_positions - m.root_positions[0] * np.array([1.0, 0.0, 1.0])
    root = quat.rotate(np.broadcast_to(turn, rel.shape[:-1] + (4,)), rel) + np.array(
        [placement[0], 0.0, placement[1]]
    )
    rot = m.rotations.copy()
    rot[:, 0] = quat.multiply(np.broadcast_to(turn, rot[:, 0].shape), rot[:, 0])
    return Motion(skeleton=m.skeleton, fps=m.fps, root_positions=root, rotations=rot)


jit.register("search", warm_up)
