"""A search spec compiled against a graph and a song: the typed inputs of the graph search's DP.

``compile_spec(graph, analysis, spec) -> Problem`` runs no DP: it turns the music into data terms
(style and rhythm per bar and node), the user's controls into allowed sets and penalties, the
repeat/mirror rules into tied variables and the DP's chain, the stage and waypoints into the
kernel's ``Track``, and the graph's arrays into the kernel's ``Graph``. ``search.run`` runs it.
See ``search`` for the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dancegraph import jit
from dancegraph.embed import descriptor
from dancegraph.errors import NotFoundError, SpecError
from dancegraph.graph import _dp, choreography
from dancegraph.graph.artifact import MotionGraph
from dancegraph.rhythm.signatures import PATTERN_DISTANCES
from dancegraph.spec import Spec

KBEST_NODES = 4096  # graphs up to this size keep k-best histories under structure ties
STATE_BUDGET = 1 << 26  # most back pointers (chain steps × nodes × slots) one pass stores
DENSE_LIMIT = 64  # variables with at most this many allowed nodes are relaxed from a short list
STAGE_WEIGHT = 1.0e5  # per metre outside the stage: effectively hard
WAYPOINT_WEIGHT = 1.0e5  # per metre beyond a waypoint's tolerance: effectively hard
POSITION_SLOTS = 4  # states kept per node when stage or waypoints are set
POSITION_CELL = 0.1  # metres (L1) that make two states' root positions different
RECREATE_WEIGHT = 100.0  # per bar whose motif differs from the reference take's
#: the rhythm term's cost, in units of G_r, per unit of a node's anchoring below the graph's
#: best-anchored node's (``anchor_costs``); 0 switches the anchoring off (docs/rendering.md,
#: Anchoring)
ANCHOR_WEIGHT = 4.0


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
    """C_d for every bar and node ``(T, N) float32``: λ10·(λ12‖z_M − z_D‖ + λ13 (min_k G_r +
    A_n)), A_n the node's anchoring cost (``anchor_costs``).

    ``zm (T, 32)`` music style; ``sig_cost (T, 256)`` (``rhythm_costs``) per slot pattern the
    rhythm distance G_r of a node whose signature is that pattern. One matrix product, then one
    fused pass (the hot path of a query).
    """
    from dancegraph.graph import search  # registers the search kernels' warm-up

    jit.ensure(search.KERNELS)
    w = spec.weights
    zm = zm.astype(np.float32)
    dot = zm @ np.asarray(graph.style, dtype=np.float32).T
    return _dp.data_terms(
        dot,
        (zm * zm).sum(1),
        _style_sq(graph),
        (w.rhythm * sig_cost).astype(np.float32),
        _ro(graph.signature, np.uint8),
        (w.rhythm * anchor_costs(graph)).astype(np.float32),
        float(w.style),
        float(w.data),
    )


def anchor_costs(graph: MotionGraph) -> np.ndarray:
    """``(N,)``: the rhythm term's anchoring part per node, in units of G_r,
    ``ANCHOR_WEIGHT``·(max ``anchoring`` − ``anchoring``): 0 for the graph's best-anchored
    node, more the fewer of a node's stops sit on its beats and the more fall between them
    (``build.node_anchoring``); zeros for a graph built without the ``anchoring`` array. Every
    path pays the offset once per bar, so it changes no choice. Why: the renderer lands a
    node's beats on the song's, so its stops land on the song's beats only as far as they sit
    on its own."""
    anchoring = getattr(graph, "anchoring", None)
    n_nodes = len(graph.signature)
    if anchoring is None or ANCHOR_WEIGHT == 0 or n_nodes == 0:
        return np.zeros(n_nodes)
    anchoring = np.asarray(anchoring, dtype=np.float64)
    return ANCHOR_WEIGHT * (anchoring.max() - anchoring)


def rhythm_costs(topk: np.ndarray) -> np.ndarray:
    """``(T, 256)``: the rhythm term's G_r for each music bar and each slot pattern a node's
    kinematic beats can make, the distance to the nearest of the bar's top-K signatures
    ``topk (T, K)`` (indices into ``COMMON_SIGNATURES``), ChoreoMaster's min_k G_r(R_M^k, R_D)."""
    return PATTERN_DISTANCES[np.asarray(topk, dtype=int)].min(axis=1)


# --------------------------------------------------------------------------------------------
# the spec's fields


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


def _blame(spec: Spec, t: int) -> str:
    for i, m in enumerate(spec.motifs):
        if m.bar == t:
            return f"motifs[{i}]"
    return "exclude"


# --------------------------------------------------------------------------------------------
# structure ties: union-find with parity, and the DP's chain


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


# --------------------------------------------------------------------------------------------
# the graph's arrays for the kernel (cached per loaded graph)


def _cached(graph: MotionGraph, key, make):
    """``make()`` computed once per loaded graph and ``key`` (a graph version never changes)."""
    cache = graph.__dict__.setdefault("_cache", {})
    if key not in cache:
        cache[key] = make()
    return cache[key]


def _ro(a, dtype) -> np.ndarray:
    """A read-only contiguous view (or converted copy) of a graph array for the kernel.

    Memory-mapped artifacts are read-only; marking in-memory graphs' arrays the same way keeps
    one compiled specialisation of the numba kernel for both.
    """
    out = np.ascontiguousarray(a, dtype=dtype).view()
    out.flags.writeable = False
    return out


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


# --------------------------------------------------------------------------------------------
# the compiled problem


@dataclass
class Problem:
    """A spec compiled against one graph and one song: the typed inputs of the DP.

    Music: ``music`` (``bars (T, 2)`` s, ``n``, ``topk (T, K)``, ``tags``, ``style_source``),
    ``zm (T, 32)`` its style, ``sig_cost (T, 256)`` its rhythm cost per slot pattern
    (``rhythm_costs``), ``data (T, N) float32`` the per-bar data terms (with the recreate
    penalty). Ties: bar t is danced by variable ``var[t]``, mirrored where ``parity[t]`` is 1;
    ``pairs`` the tied bar pairs ``(a, b, parity, rule)``, ``contradictions`` those the rules
    could not tie. DP: ``unary (V, N) float32`` per variable (inf: not allowed), ``chain`` and
    ``step (T,)`` (each bar's chain step), the kernel's ``dp`` graph and ``track``, ``slots``
    states per node, ``dense (V,)`` variables relaxed from a short list (pins). Choreography:
    ``motif (N,)``, ``recreate (T,)`` the reference take's motifs and ``target (k,)`` the motif
    signature to follow (None when not asked). ``report``: pins, excluded bars, structure pairs,
    conflicts, counts, the music's style source.
    """

    music: dict
    zm: np.ndarray
    sig_cost: np.ndarray
    data: np.ndarray
    var: np.ndarray
    parity: np.ndarray
    pairs: list[tuple[int, int, int, str]]
    contradictions: list[tuple[int, int, int, str]]
    unary: np.ndarray
    chain: _dp.Chain
    step: np.ndarray
    dp: _dp.Graph
    track: _dp.Track
    slots: int
    dense: np.ndarray
    motif: np.ndarray
    recreate: np.ndarray | None
    target: np.ndarray | None
    report: dict

    @property
    def n_vars(self) -> int:
        return int(self.unary.shape[0])


def compile_spec(graph: MotionGraph, analysis, spec: Spec) -> Problem:
    """Compile ``spec`` for ``analysis``'s bars on ``graph`` (no DP is run). Steps: the music's
    data terms (``_music_terms``); the user's node restrictions (``_restrictions``: excludes,
    motif pins, recreate, pins); the structure ties (``_tie_bars``); per-variable costs with the
    restrictions (``_variable_costs``); the chain (``_chain``); the trajectory terms (``_track``);
    the kernel's graph (``_kernel_graph``). Raises ``SpecError`` / ``NotFoundError`` naming the
    field a control cannot be met by."""
    music, zm, sig_cost, data = _music_terms(graph, analysis, spec)
    allowed, pinned, recreate, target, report = _restrictions(graph, spec, music, data)
    var, parity, pairs, contradictions = _tie_bars(music["tags"], spec)
    report["structure_pairs"] = len(pairs)
    unary = _variable_costs(graph, spec, data, var, parity, allowed, pinned)
    chain, step = _chain(var, parity)
    n_nodes = graph.n_nodes
    # on small graphs, several states per node: different root positions (trajectory terms) or
    # different predecessors (tied copies, whose costs depend on the history); the back pointers
    # (C × N × slots int32) stay within STATE_BUDGET
    track = _track(graph, spec, music["bars"])
    slots = (
        POSITION_SLOTS if n_nodes <= KBEST_NODES and (track.on or unary.shape[0] < var.size) else 1
    )
    slots = max(1, min(slots, STATE_BUDGET // max(1, chain.var.size * n_nodes)))
    report.update(
        conflicts=[
            {
                "bars": [int(a), int(b)],
                "rule": rule,
                "reason": "the repeat and mirror rules contradict each other here",
            }
            for a, b, _, rule in contradictions
        ],
        variables=int(unary.shape[0]),
        bars=int(music["n"]),
        music_style=music["style_source"],
    )
    return Problem(
        music=music,
        zm=zm,
        sig_cost=sig_cost,
        data=data,
        var=var,
        parity=parity,
        pairs=pairs,
        contradictions=contradictions,
        unary=unary,
        chain=chain,
        step=step,
        dp=_kernel_graph(graph, spec),
        track=track,
        slots=slots,
        # a short allowed set (pins, motif pins) is relaxed from every state, not along edges
        dense=np.isfinite(unary).sum(axis=1) <= DENSE_LIMIT,
        motif=np.asarray(graph.motif),
        recreate=recreate,
        target=target,
        report=report,
    )


def _music_terms(
    graph: MotionGraph, analysis, spec: Spec
) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    """``(music, zm (T, 32), sig_cost (T, 256), data (T, N))`` of the song on ``graph``."""
    music = _music_arrays(analysis)
    zm, music = music_inputs(music, graph, analysis)
    sig_cost = rhythm_costs(music["topk"])
    return music, zm, sig_cost, data_costs(graph, zm, sig_cost, spec)


class _Allowed:
    """Nodes allowed per bar: one mask for every bar and masks of single bars (None: all)."""

    def __init__(self, n_bars: int, n_nodes: int):
        self.n_bars, self.n_nodes = n_bars, n_nodes
        self.every: np.ndarray | None = None
        self.bar: dict[int, np.ndarray] = {}

    def restrict(self, bars: np.ndarray, keep: np.ndarray) -> None:
        if bars.size == self.n_bars:
            self.every = keep if self.every is None else self.every & keep
            return
        for t in bars.tolist():
            self.bar[t] = keep if t not in self.bar else self.bar[t] & keep

    def at(self, t: int) -> np.ndarray:
        ok = np.ones(self.n_nodes, dtype=bool) if self.every is None else self.every.copy()
        if t in self.bar:
            ok &= self.bar[t]
        return ok

    def restricted(self, t: int) -> bool:
        return self.every is not None or t in self.bar


def _restrictions(
    graph: MotionGraph, spec: Spec, music: dict, data: np.ndarray
) -> tuple[_Allowed, dict[int, tuple[int, str]], np.ndarray | None, np.ndarray | None, dict]:
    """The user's controls on nodes: excludes and motif pins (``_Allowed``), the recreate
    penalty (added to ``data`` in place; its motif sequence returned), the motif signature to
    follow, and pins ``{bar: (node, field)}`` (a pin with a bar range takes the range's
    cheapest bar). Returns them with the report's ``pins`` and ``excluded_bars``."""
    n_bars, n_nodes = music["n"], graph.n_nodes
    allowed = _Allowed(n_bars, n_nodes)
    report: dict = {"pins": [], "excluded_bars": 0, "structure_pairs": 0, "conflicts": []}
    for i, ex in enumerate(spec.exclude):
        fname = f"exclude[{i}]"
        nodes = match_nodes(graph, ex.node, ex.tag, f"{fname}.{'tag' if ex.tag else 'node'}")
        bars = bars_in(ex.bars, ex.seconds, music["bars"], fname)
        keep = np.ones(n_nodes, dtype=bool)
        keep[nodes] = False
        allowed.restrict(bars, keep)
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
        allowed.restrict(np.array([mp.bar]), motif == mp.motif)
    target = None
    if spec.signature is not None:
        target = target_signature(graph, spec.signature.target, "signature.target")
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

    pinned: dict[int, tuple[int, str]] = {}
    for i, inc in enumerate(spec.include):
        fname = f"include[{i}]"
        node = match_nodes(graph, inc.node, None, f"{fname}.node")[0]
        bars = bars_in(inc.bars, inc.seconds, music["bars"], fname)
        ok = np.array([t for t in bars.tolist() if allowed.at(t)[node]], dtype=np.int64)
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
    return allowed, pinned, recreate, target, report


def _tie_bars(
    tags: list[dict], spec: Spec
) -> tuple[
    np.ndarray, np.ndarray, list[tuple[int, int, int, str]], list[tuple[int, int, int, str]]
]:
    """Structure ties: ``(var (T,), parity (T,) int8, pairs, contradictions)``; variables are
    numbered by their first bar, which has parity 0."""
    n_bars = len(tags)
    ties = _Ties(n_bars)
    pairs = structure_pairs(tags, spec.structure.repeat, spec.structure.mirror)
    contradictions = [p for p in pairs if not ties.union(p[0], p[1], p[2])]
    roots = np.empty(n_bars, dtype=np.int64)
    parity = np.empty(n_bars, dtype=np.int8)
    for t in range(n_bars):
        roots[t], parity[t] = ties.find(t)
    # the root is the smallest bar of its group (union keeps the smaller root): parity 0 there
    _, var = np.unique(roots, return_inverse=True)
    return var, parity, pairs, contradictions


def _variable_costs(
    graph: MotionGraph,
    spec: Spec,
    data: np.ndarray,
    var: np.ndarray,
    parity: np.ndarray,
    allowed: _Allowed,
    pinned: dict[int, tuple[int, str]],
) -> np.ndarray:
    """``(V, N) float32``: per variable the data terms of all its bars (a mirrored bar scores
    each node's mirror), inf where a restriction or pin of any of its bars rules a node out.
    Raises ``SpecError`` where pins and ties disagree or no node is left."""
    n_bars, n_nodes = data.shape
    n_vars = int(var.max()) + 1
    mirror_of = _ro(graph.mirror_of, np.int64)
    has_mirror = mirror_of >= 0
    safe_mirror = np.where(has_mirror, mirror_of, 0)
    if n_vars == n_bars and not parity.any():
        unary = data  # no ties: one variable per bar
    else:
        unary = _dp.variable_costs(data, var, parity, mirror_of, n_vars)
    var_ok: dict[int, np.ndarray] = {}
    for t in range(n_bars):
        if parity[t] == 0 and not allowed.restricted(t):
            continue
        ok = allowed.at(t)
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
    empty = np.nonzero(np.isfinite(unary).sum(axis=1) == 0)[0]
    if empty.size:
        members = np.nonzero(var == empty[0])[0]
        t = int(members[0])
        if parity[members].any() and all(allowed.at(int(m)).any() for m in members):
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
    return unary


def _track(graph: MotionGraph, spec: Spec, bars: np.ndarray) -> _dp.Track:
    """The trajectory terms: the stage (the dancer starts at its centre) and the waypoints, each
    at its bar and root-path sample. Raises ``SpecError`` for a waypoint after the last bar."""
    n_bars = bars.shape[0]
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
    on = spec.stage is not None or bool(spec.waypoints)
    reach = 0.0
    if graph.n_nodes:
        reach = float(max(np.hypot(graph.disp[:, 0], graph.disp[:, 1]).max(), np.max(graph.radius)))
    return _dp.Track(
        on=on,
        cell=POSITION_CELL if on else -1.0,
        start=start,
        stage=np.append(stage, STAGE_WEIGHT),
        wp_bar=np.array(wp_bar, dtype=np.int64),
        wp_idx=np.array(wp_idx, dtype=np.int64),
        wp_pos=np.array(wp_pos, dtype=np.float64).reshape(-1, 2),
        wp_tol=np.array(wp_tol, dtype=np.float64),
        wp_w=WAYPOINT_WEIGHT,
        reach=reach,
    )


def _kernel_graph(graph: MotionGraph, spec: Spec) -> _dp.Graph:
    """The kernel's ``_dp.Graph``: the edges below δT (and by target), the feature rows that
    cost transitions which are not edges, mirrors, per-node motion records and root paths."""
    indptr, indices, costs = edges_below(graph, spec.transition_threshold)
    in_ptr, in_src, in_cost = _in_edges(graph, spec.transition_threshold, indptr, indices, costs)
    params = graph.manifest.get("params", {})
    return _dp.Graph(
        indptr=_ro(indptr, np.int64),
        indices=_ro(indices, np.int32),
        costs=_ro(costs, np.float32),
        in_ptr=in_ptr,
        in_src=in_src,
        in_cost=in_cost,
        # transitions that are not edges are costed from the compressed features
        **_feature_rows(graph),
        blocks=_ro(graph.manifest["pc_blocks"], np.int64),
        mirror_of=_ro(graph.mirror_of, np.int64),
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
