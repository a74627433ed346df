"""Graph search: every control changes the result, structure rules hold, errors name the field."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pydantic import ValidationError

from dancegraph.errors import NotFoundError, SpecError
from dancegraph.graph import _dp
from dancegraph.graph import search as search_module
from dancegraph.graph.artifact import graph_from_arrays
from dancegraph.graph.build import BuildParams, build_arrays
from dancegraph.graph.problem import compile_spec, structure_pairs
from dancegraph.graph.search import placed_motion, root_trajectory, run, search
from dancegraph.motion.retime import BEAT0
from dancegraph.render import render_path
from dancegraph.spec import Spec

from .conftest import demo_barset, synthetic_analysis


def _graph(bars, params=None):
    arrays, ids, manifest = build_arrays(bars, params or BuildParams())
    g = graph_from_arrays(arrays, dict(manifest, name="demo", version="t"))
    g.node_ids[:] = ids
    g._index = {n: i for i, n in enumerate(ids)}
    return g


@pytest.fixture(scope="module")
def song():
    return synthetic_analysis("AABA", bars_per_phrase=4, meter_ids=(0, 1, 0, 2))


@pytest.fixture(scope="module")
def travel_graph():
    """Demo bars whose root travels 0.3 m per bar: groove along +x, pop along -x, step in place."""
    bars = demo_barset()
    root = bars.root.copy()
    sign = np.array(
        [{"groove": 1.0, "pop": -1.0, "step": 0.0}[bars.clips[c].split("_")[0]] for c in bars.clip]
    )
    for i in range(len(bars.clip)):  # t: 0 at the bar's downbeat, 1 at its closing one
        a, b = bars.ptr[i], bars.ptr[i + 1]
        t = (np.arange(b - a) - bars.beats[i, BEAT0]) / (bars.duration[i] * bars.fps[i])
        root[a:b, 0] += 0.3 * sign[i] * t
    return _graph(dataclasses.replace(bars, root=root))


def _spec(**kw) -> Spec:
    return Spec.model_validate(kw)


def test_default_search_returns_alternatives_with_costs(demo_graph, song):
    r = search(demo_graph, song, Spec())
    d = r.to_dict()
    assert len(d["alternatives"]) == 3
    for alt in d["alternatives"]:
        assert len(alt["nodes"]) == song.n_bars
        assert all(demo_graph.has_node(n) for n in alt["nodes"])
        per = alt["per_bar"]
        total = sum(
            b["style"] + b["rhythm"] + b["transition"] + b["structure"] + b["user"] for b in per
        )
        assert total == pytest.approx(alt["cost"], rel=1e-3, abs=1e-2)
        assert alt["violations"] == []
    costs = [a["cost"] for a in d["alternatives"]]
    assert costs[0] <= min(costs[1:]) + 1e-6


def test_alternatives_differ(demo_graph, song):
    alts = search(demo_graph, song, Spec(alternatives=3)).alternatives
    for i in range(3):
        for j in range(i + 1, 3):
            a, b = set(alts[i].nodes), set(alts[j].nodes)
            assert len(a & b) <= 0.25 * min(len(a), len(b)), (alts[i].nodes, alts[j].nodes)


def test_repeated_phrases_get_identical_node_sequences(demo_graph, song):
    for alt in search(demo_graph, song, Spec()).alternatives:
        a0, a1, a2 = alt.nodes[0:4], alt.nodes[4:8], alt.nodes[12:16]
        assert a0 == a1 == a2


def test_mirrored_bars_get_mirrored_nodes(demo_graph, song):
    mirror_of = np.asarray(demo_graph.mirror_of)
    for alt in search(demo_graph, song, Spec()).alternatives:
        for start in (0, 4, 8, 12):  # meter ids (0, 1, 0, 2): bar 0 and bar 2 of each phrase
            a, b = alt.index[start], alt.index[start + 2]
            assert mirror_of[a] == b


def _cycling_problem(graph, analysis):
    """The search problem of ``analysis`` with its data terms replaced: 0 on the two nodes with
    the cheapest pair of edges between them (a → b → a), 10 on every other allowed node, so the
    cheapest path alternates the two for the whole song."""
    problem = compile_spec(graph, analysis, Spec(alternatives=1))
    dp = problem.dp
    pairs = [
        (dp.costs[e] + _dp._edge_cost(dp.indptr, dp.indices, dp.costs, b, a), a, b)
        for a in range(graph.n_nodes)
        for e in range(dp.indptr[a], dp.indptr[a + 1])
        if (b := int(dp.indices[e])) != a
        and _dp._edge_cost(dp.indptr, dp.indices, dp.costs, b, a) >= 0
    ]
    _, a, b = min(pairs)
    allowed = np.isfinite(problem.unary)
    unary = np.where(allowed, np.float32(10.0), np.float32(np.inf))
    unary[:, [a, b]] = np.where(allowed[:, [a, b]], np.float32(0.0), np.float32(np.inf))
    return dataclasses.replace(problem, unary=unary.astype(np.float32))


@pytest.mark.parametrize(("phrases", "meter_ids"), [("ABCD", (0, 1, 2, 3)), ("AABA", (0, 1, 0, 2))])
def test_novelty_breaks_a_two_node_cycle(demo_graph, phrases, meter_ids, monkeypatch):
    """The cheapest path cycles two nodes; with the novelty cost no node (or its mirror) comes
    back within NOVELTY_WINDOW chain steps, and repeat and mirror ties stay exact."""
    analysis = synthetic_analysis(phrases, bars_per_phrase=4, meter_ids=meter_ids)
    problem = _cycling_problem(demo_graph, analysis)
    mirror_of = np.asarray(demo_graph.mirror_of)
    default = search_module.NOVELTY_PENALTY

    def path(penalty):
        monkeypatch.setattr(search_module, "NOVELTY_PENALTY", penalty)
        alt = run(demo_graph, problem, Spec(alternatives=1)).alternatives[0]
        assert alt.violations == []
        nodes = np.asarray(alt.index)
        for t in range(len(nodes)):  # every bar is its variable's chain bar's node (or mirror)
            b = problem.chain.bar[problem.step[t]]
            flip = problem.parity[t] != problem.parity[b]
            assert nodes[t] == (mirror_of[nodes[b]] if flip else nodes[b])
        return nodes

    cycling = path(0.0)
    novel = path(default)
    if phrases == "ABCD":  # no ties: the two nodes throughout
        assert len(set(cycling.tolist())) == 2
    assert len(set(novel.tolist())) > len(set(cycling.tolist()))
    chain_nodes = novel[problem.chain.bar]
    w = search_module.NOVELTY_WINDOW
    for c in range(1, len(chain_nodes)):
        recent = chain_nodes[max(0, c - w) : c]
        assert chain_nodes[c] not in recent and mirror_of[chain_nodes[c]] not in recent


def test_structure_rules_can_be_switched_off(demo_graph, song):
    free = search(
        demo_graph, song, _spec(structure={"repeat": False, "mirror": False}, alternatives=1)
    ).alternatives[0]
    tied = search(demo_graph, song, Spec(alternatives=1)).alternatives[0]
    assert free.cost < tied.cost
    assert free.nodes[0:4] != free.nodes[4:8]


def test_contradicting_rules_are_reported_per_pair():
    # meter ids differ between occurrences: occurrence 0 mirrors bars 0/1, occurrence 1 does not,
    # and the repeat rule ties them: bar 5 must equal bar 1 = mirror(bar 0) = mirror(bar 4) ...
    tags = [
        {"label": "A", "occurrence": 0, "index": 0, "meter_id": 0},
        {"label": "A", "occurrence": 0, "index": 1, "meter_id": 0},
        {"label": "A", "occurrence": 1, "index": 0, "meter_id": 0},
        {"label": "A", "occurrence": 1, "index": 1, "meter_id": 1},
    ]
    pairs = structure_pairs(tags, True, True)
    assert (
        (0, 2, 0, "repeat") in pairs
        and (1, 3, 0, "repeat") in pairs
        and (0, 1, 1, "mirror") in pairs
    )


def test_contradiction_is_reported_with_reason(demo_graph):
    # occurrence 0: three bars of one meter id (node, mirror, node); occurrence 1: bars 0 and 2
    # share a meter id (node, mirror), but the repeat rule makes them equal: an odd cycle
    song = synthetic_analysis("AA", bars_per_phrase=3, meter_ids=(0, 0, 0))
    song.tags[4]["meter_id"] = 1
    r = search(demo_graph, song, Spec(alternatives=1))
    assert r.report["conflicts"] and r.report["conflicts"][0]["reason"].startswith(
        "the repeat and mirror rules contradict"
    )
    viol = r.alternatives[0].violations
    assert len(viol) == 1 and "contradict" in viol[0]["reason"]
    assert r.alternatives[0].per_bar[viol[0]["bars"][1]]["structure"] == Spec().weights.structure


def test_pinned_node_appears_at_its_bar(demo_graph, song):
    free = search(demo_graph, song, Spec(alternatives=1)).alternatives[0]
    node = next(n for n in demo_graph.node_ids if n not in free.nodes and "~" not in n)
    r = search(demo_graph, song, _spec(include=[{"node": node, "bars": [9, 9]}], alternatives=2))
    for alt in r.alternatives:
        assert alt.nodes[9] == node
    assert r.report["pins"] == [{"field": "include[0]", "node": node, "bar": 9}]


def test_pin_in_a_repeated_phrase_repeats(demo_graph, song):
    node = "pop_90:3"
    alt = search(
        demo_graph, song, _spec(include=[{"node": node, "bars": [1, 1]}], alternatives=1)
    ).alternatives[0]
    assert alt.nodes[1] == alt.nodes[5] == alt.nodes[13] == node


def test_excluded_nodes_never_appear(demo_graph, song):
    free = search(demo_graph, song, Spec(alternatives=1)).alternatives[0]
    take = free.nodes[0].split(":")[0]
    r = search(
        demo_graph,
        song,
        _spec(exclude=[{"node": f"{take}:*"}, {"tag": "blend"}, {"tag": "shuffle"}]),
    )
    kinds = np.asarray(demo_graph.node_kind)
    for alt in r.alternatives:
        assert not any(n.startswith(take + ":") for n in alt.nodes)
        assert (kinds[alt.index] <= 1).all()
    r = search(demo_graph, song, _spec(exclude=[{"tag": "augmented"}], structure={"mirror": False}))
    for alt in r.alternatives:
        assert (kinds[alt.index] == 0).all()
    # without mirrored nodes the mirror rule cannot hold: the error says so
    with pytest.raises(SpecError) as exc:
        search(demo_graph, song, _spec(exclude=[{"tag": "mirror"}]))
    assert exc.value.field == "structure.mirror"


def test_exclude_in_a_range_only_applies_there(demo_graph, song):
    free = search(
        demo_graph, song, _spec(alternatives=1, structure={"repeat": False, "mirror": False})
    ).alternatives[0]
    node = free.nodes[3]
    r = search(
        demo_graph,
        song,
        _spec(
            alternatives=1,
            structure={"repeat": False, "mirror": False},
            exclude=[{"node": node, "bars": [3, 3]}],
        ),
    )
    assert r.alternatives[0].nodes[3] != node
    bar_s = float(song.bars[0, 1] - song.bars[0, 0])
    r = search(
        demo_graph,
        song,
        _spec(
            alternatives=1,
            structure={"repeat": False, "mirror": False},
            exclude=[{"node": node, "seconds": [3 * bar_s + 0.1, 3 * bar_s + 0.2]}],
        ),
    )
    assert r.alternatives[0].nodes[3] != node


def _rendered_root(graph, alt) -> np.ndarray:
    return np.concatenate(
        [placed_motion(graph, n, alt.placements[t]).root_positions for t, n in enumerate(alt.index)]
    )


def test_stage_bound_holds_on_the_root_trajectory(travel_graph, song):
    free_spec = {"alternatives": 1, "structure": {"repeat": False, "mirror": False}}
    free = search(travel_graph, song, _spec(**free_spec)).alternatives[0]
    free_root = _rendered_root(travel_graph, free)
    stage = {"x": [-0.6, 0.6], "z": [-0.6, 0.6]}
    assert free_root[:, 0].max() > 0.6 or free_root[:, 0].min() < -0.6  # the control matters
    for structure in ({"repeat": False, "mirror": False}, {"repeat": True, "mirror": True}):
        r = search(travel_graph, song, _spec(alternatives=2, stage=stage, structure=structure))
        for alt in r.alternatives:
            root = _rendered_root(travel_graph, alt)
            assert root[:, 0].min() >= -0.6 and root[:, 0].max() <= 0.6
            assert root[:, 2].min() >= -0.6 and root[:, 2].max() <= 0.6
            # placements chain each bar's root displacement from the stage centre
            assert np.allclose(
                alt.placements, root_trajectory(travel_graph, alt.index, [0.0, 0.0, 0.0])
            )
            # and the renderer's file follows them: the bound holds on the rendered root too
            dance, _ = render_path(
                travel_graph, alt.nodes, song.bar_beats, 30.0, placements=alt.placements
            )
            xz = dance.root_positions[:, [0, 2]]
            assert xz.min() >= -0.6 - 1e-6 and xz.max() <= 0.6 + 1e-6


def test_waypoint_is_reached(travel_graph, song):
    free_spec = {"alternatives": 1, "structure": {"repeat": False, "mirror": False}}
    second = float(song.bars[8, 0])
    for target in ([1.2, 0.0], [-1.2, 0.0]):
        spec = _spec(
            waypoints=[{"second": second, "position": target, "tolerance": 0.3}], **free_spec
        )
        alt = search(travel_graph, song, spec).alternatives[0]
        first = sum(travel_graph.node_motion(n).n_frames for n in alt.index[:8])
        pos = _rendered_root(travel_graph, alt)[first][[0, 2]]
        assert np.hypot(*(pos - np.array(target))) <= 0.3 + 1e-6
    free = search(travel_graph, song, _spec(**free_spec)).alternatives[0]
    assert not (
        np.hypot(*(free.placements[8, :2] - [1.2, 0.0])) <= 0.3
        and np.hypot(*(free.placements[8, :2] - [-1.2, 0.0])) <= 0.3
    )


def test_impossible_constraints_name_the_constraint(travel_graph, demo_graph, song):
    with pytest.raises(SpecError) as exc:
        search(
            travel_graph,
            song,
            _spec(
                alternatives=1,
                waypoints=[{"second": 1.0, "position": [30.0, 0.0], "tolerance": 0.1}],
            ),
        )
    assert exc.value.code == "constraint_conflict" and exc.value.field == "waypoints[0]"
    with pytest.raises(SpecError) as exc:
        search(
            travel_graph,
            song,
            _spec(alternatives=1, stage={"x": [-0.01, 0.01], "z": [-0.01, 0.01]}),
        )
    assert exc.value.code == "constraint_conflict" and exc.value.field == "stage"
    with pytest.raises(SpecError) as exc:
        search(
            demo_graph,
            song,
            _spec(exclude=[{"tag": "original"}, {"tag": "augmented", "bars": [2, 5]}]),
        )
    assert exc.value.code == "constraint_conflict" and exc.value.field == "exclude"
    with pytest.raises(SpecError) as exc:
        search(
            demo_graph,
            song,
            _spec(include=[{"node": "pop_90:3", "bars": [2, 2]}], exclude=[{"node": "pop_90:*"}]),
        )
    assert exc.value.field == "include[0]"


def test_two_nodes_pinned_at_one_bar(demo_graph, song):
    with pytest.raises(SpecError) as exc:
        search(
            demo_graph,
            song,
            _spec(
                include=[{"node": "pop_90:3", "bars": [9, 9]}, {"node": "pop_90:4", "bars": [9, 9]}]
            ),
        )
    assert exc.value.code == "constraint_conflict" and exc.value.field == "include[1]"
    # the repeat rule ties bar 1 and bar 5: different pins there conflict too
    with pytest.raises(SpecError) as exc:
        search(
            demo_graph,
            song,
            _spec(
                include=[{"node": "pop_90:3", "bars": [1, 1]}, {"node": "pop_90:4", "bars": [5, 5]}]
            ),
        )
    assert exc.value.field == "include[1]" and "repeat/mirror" in exc.value.message


def test_unknown_names_are_not_found(demo_graph, song):
    cases = [
        ({"include": [{"node": "nosuch:1", "bars": [0, 0]}]}, "include[0].node"),
        ({"include": [{"node": "pop_90:999", "bars": [0, 0]}]}, "include[0].node"),
        ({"exclude": [{"node": "nosuch:*"}]}, "exclude[0].node"),
        ({"exclude": [{"tag": "floorwork"}]}, "exclude[0].tag"),
        ({"signature": {"target": "nosuch"}}, "signature.target"),
        ({"recreate": "nosuch"}, "recreate"),
        ({"motifs": [{"bar": 0, "motif": 999}]}, "motifs[0].motif"),
    ]
    for kw, field in cases:
        with pytest.raises(NotFoundError) as exc:
            search(demo_graph, song, _spec(alternatives=1, **kw))
        assert exc.value.field == field, kw
    with pytest.raises(SpecError) as exc:
        search(demo_graph, song, _spec(include=[{"node": "pop_90:3", "bars": [99, 99]}]))
    assert exc.value.field == "include[0]"


def test_waypoint_outside_the_stage_is_rejected():
    with pytest.raises(ValidationError, match="waypoints"):
        _spec(stage={"x": [-1, 1], "z": [-1, 1]}, waypoints=[{"second": 1, "position": [3, 0]}])


def test_novelty_threshold_and_weights_change_the_path(demo_graph, song):
    base = search(
        demo_graph,
        song,
        _spec(
            alternatives=1,
            structure={"repeat": False, "mirror": False},
            weights={"transition": 1.0},
        ),
    ).alternatives[0]
    heavy = search(
        demo_graph,
        song,
        _spec(
            alternatives=1,
            structure={"repeat": False, "mirror": False},
            weights={"transition": 20.0},
        ),
    ).alternatives[0]
    trans = lambda a: sum(b["transition"] for b in a.per_bar)  # noqa: E731
    assert trans(heavy) / 20.0 < trans(base) / 1.0  # λ11 up: cheaper transitions

    # novelty δT: edges at or above it are no longer used (consecutive bars of a take still are)
    def consecutive(p, q):
        return (
            demo_graph.node_clip[p] == demo_graph.node_clip[q]
            and demo_graph.node_bar[q] == demo_graph.node_bar[p] + 1
        )

    idx = base.index
    used = [
        base.per_bar[t]["transition"]
        for t in range(1, len(idx))
        if not base.per_bar[t].get("offgraph") and not consecutive(idx[t - 1], idx[t])
    ]
    cut = max(used) - 1e-3
    strict = search(
        demo_graph,
        song,
        _spec(
            alternatives=1,
            structure={"repeat": False, "mirror": False},
            transition_threshold=cut,
            weights={"transition": 1.0},
        ),
    ).alternatives[0]
    assert strict.nodes != base.nodes
    for t in range(1, len(strict.index)):
        b = strict.per_bar[t]
        assert (
            b["transition"] < cut
            or consecutive(strict.index[t - 1], strict.index[t])
            or b.get("offgraph")
        )


def test_fifteen_minute_song_works(demo_graph):
    song = synthetic_analysis("ABACABAD" * 6, bars_per_phrase=8, tempo=100.0)
    assert song.duration_s >= 15 * 60
    r = search(demo_graph, song, Spec(alternatives=3))
    for alt in r.alternatives:
        assert len(alt.nodes) == song.n_bars
        assert alt.violations == []
    # long songs tie many bars to one variable: alternatives must still differ
    sets = [set(a.nodes) for a in r.alternatives]
    for i in range(3):
        for j in range(i + 1, 3):
            assert len(sets[i] & sets[j]) <= 0.5 * min(len(sets[i]), len(sets[j]))


def test_explain_table_lists_every_bar(demo_graph, song):
    from dancegraph.graph.explain import format_table

    alt = search(demo_graph, song, Spec(alternatives=1)).to_dict()["alternatives"][0]
    text = format_table(alt)
    lines = text.splitlines()
    assert len(lines) >= 2 + song.n_bars + 1
    for t, node in enumerate(alt["nodes"]):
        assert lines[2 + t].split()[:2] == [str(t), node]
    assert f"total cost {alt['cost']:.2f}" in text


def test_warm_up_runs_the_kernel_on_a_tiny_graph():
    from dancegraph.graph.search import warm_up

    warm_up()  # the graph store calls this at start; it must work without any dataset


@pytest.fixture(scope="module")
def tiled_graph(demo_graph):
    # the demo graph tiled to about 6,400 nodes and 50k edges (as the search benchmark builds its
    # graphs): more nodes than any beam the search used to keep, so a pruned search can miss; and
    # more than the DP's threshold for spreading a step over threads
    from bench.bench_search import scale_graph

    arrays, ids, manifest = scale_graph(demo_graph, 50_000)
    g = graph_from_arrays(arrays, dict(manifest, name="tiled", version="t"))
    g.node_ids[:] = ids
    g._index = {n: i for i, n in enumerate(ids)}
    assert g.n_nodes > max(6000, _dp.PARALLEL_MIN)
    return g


def test_search_is_the_exact_viterbi_on_a_medium_graph(tiled_graph, monkeypatch):
    # the novelty cost depends on the history: without it the pass is the plain Viterbi
    monkeypatch.setattr(search_module, "NOVELTY_PENALTY", 0.0)
    from dancegraph.graph.problem import (
        _music_arrays,
        data_costs,
        edges_below,
        music_style,
        rhythm_costs,
    )

    g = tiled_graph
    song = synthetic_analysis("ABCDE", bars_per_phrase=4)
    spec = _spec(alternatives=1, structure={"repeat": False, "mirror": False})
    alt = search(g, song, spec).alternatives[0]

    # plain Viterbi over every node and edge, in float64
    music = _music_arrays(song)
    data = data_costs(g, music_style(music, g), rhythm_costs(music["topk"]), spec)
    indptr, indices, costs = edges_below(g, spec.transition_threshold)
    src = np.repeat(np.arange(g.n_nodes), np.diff(indptr))
    best = data[0].astype(np.float64)
    for t in range(1, song.n_bars):
        reach = np.full(g.n_nodes, np.inf)
        np.minimum.at(reach, indices, best[src] + spec.weights.transition * costs)
        best = reach + data[t]
    assert not any(b.get("offgraph") for b in alt.per_bar)
    assert alt.cost == pytest.approx(best.min(), rel=1e-5)


def test_threads_do_not_change_the_result(tiled_graph):
    # structure on: each thread costs the tied transitions of its own chunk of states
    import numba

    song = synthetic_analysis("AABA", bars_per_phrase=4)
    spec = _spec(alternatives=2)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        one = search(tiled_graph, song, spec)
    finally:
        numba.set_num_threads(threads)
    many = search(tiled_graph, song, spec)
    for a, b in zip(one.alternatives, many.alternatives, strict=True):
        assert np.array_equal(a.nodes, b.nodes)
        assert a.cost == b.cost


def test_rhythm_term_picks_nodes_whose_beats_fall_on_the_music_s_accents(demo_graph):
    from dancegraph.rhythm.signatures import COMMON_SIGNATURES, PATTERN_DISTANCES

    # every bar's music signature is known (top-3 all the same); no other term counts
    song = synthetic_analysis("ABCD", bars_per_phrase=4)
    want = [COMMON_SIGNATURES.index(s) for s in ("00010001", "01010101", "00000101", "01110111")]
    topk = np.repeat(np.array(want * 4)[:, None], 3, axis=1)
    song = dataclasses.replace(song, signature_topk=topk)
    rules = {"structure": {"repeat": False, "mirror": False}, "alternatives": 1}
    weights = {"style": 0.0, "transition": 0.0}
    pattern = np.asarray(demo_graph.signature)

    def misfit(rhythm: float) -> float:
        spec = _spec(weights={**weights, "rhythm": rhythm}, **rules)
        nodes = search(demo_graph, song, spec).alternatives[0].index
        return float(PATTERN_DISTANCES[topk[:, 0], pattern[nodes]].sum())

    # with the term, most bars are danced by a node with exactly the music's accents (where an
    # edge leads to one); without it, the accents fall anywhere
    assert misfit(1.5) <= 0.25 * misfit(0.0)


def test_compiling_a_spec_gives_the_dp_s_inputs_without_running_it(demo_graph, song):
    from dancegraph.graph.problem import DENSE_LIMIT, WAYPOINT_WEIGHT, compile_spec

    g = demo_graph
    pin = g.node_ids[7]
    spec = _spec(
        include=[{"node": pin, "bars": [2, 2]}],
        exclude=[{"node": "pop_90:*", "bars": [8, 11]}],
        waypoints=[{"second": 5.0, "position": [0.2, 0.0], "tolerance": 0.5}],
    )
    p = compile_spec(g, song, spec)
    n_bars = song.n_bars
    assert p.data.shape == (n_bars, g.n_nodes) and p.sig_cost.shape == (n_bars, 256)
    # AABA: the A occurrences repeat bar for bar; bars 0 and 2 of an occurrence
    # share a meter id, so bar 2 mirrors bar 0 (the pin at bar 2 pins bar 0 to its mirror)
    for a, b, par, rule in p.pairs:
        assert p.var[a] == p.var[b] and (p.parity[a] ^ p.parity[b]) == par, rule
    assert p.n_vars < n_bars and p.slots > 1  # ties: k-best histories
    v = p.var[2]
    want = g.node_index(pin) if p.parity[2] == 0 else g.mirror_of[g.node_index(pin)]
    assert np.isfinite(p.unary[v]).sum() == 1 and np.isfinite(p.unary[v, want])
    assert p.dense[v] and np.isfinite(p.unary[v]).sum() <= DENSE_LIMIT
    # the exclude holds at the variables of bars 8-11 (phrase B, tied to no bar outside it)
    pop = np.array([n.startswith("pop_90:") for n in g.node_ids])
    for t in range(8, 12):
        assert np.isinf(p.unary[p.var[t], pop]).all()
    assert np.isfinite(p.unary[p.var[1], pop]).any()  # an A bar: not in its range
    # the waypoint's bar and path sample, and the chain covers every variable once
    bar_s = song.bars[0][1] - song.bars[0][0]
    assert p.track.on and p.track.wp_bar.tolist() == [int(5.0 // bar_s)]
    assert p.track.wp_w == WAYPOINT_WEIGHT
    assert sorted(p.chain.var.tolist()) == list(range(p.n_vars))
    assert (p.chain.var[p.step] == p.var).all()
    assert p.report["pins"] == [{"field": "include[0]", "node": pin, "bar": 2}]
    assert p.report["excluded_bars"] == 4 and p.report["variables"] == p.n_vars


def _twins(anchoring: np.ndarray | None):
    """Four nodes equal in everything the search reads (style, signature, edges: every node to
    every other at the same cost), differing only in their ``anchoring`` (None: no array, a
    graph built before it)."""
    from dancegraph.graph.artifact import bare_graph

    n = 4
    src = np.repeat(np.arange(n), n - 1)
    dst = np.array([q for p in range(n) for q in range(n) if q != p])
    extra = {} if anchoring is None else {"anchoring": np.asarray(anchoring, np.float32)}
    return bare_graph(
        src,
        dst,
        np.full(dst.size, 5.0),
        n_nodes=n,
        clips=[f"c{k}" for k in range(n)],
        node_clip=np.arange(n, dtype=np.int32),
        node_bar=np.zeros(n, np.int32),
        node_tags=np.ones(n, np.uint32),
        signature=np.full(n, 0b01010101, np.uint8),
        **extra,
    )


def test_anchoring_term_prefers_well_anchored_nodes(monkeypatch):
    """Of otherwise equal nodes the search dances the well-anchored ones (whichever they are),
    and reports their anchoring cost in the rhythm term; off (weight 0, or no array in the
    graph) the paths cost the same."""
    from dancegraph.graph import problem

    song = synthetic_analysis("AB", bars_per_phrase=1)  # two bars: two nodes, no return
    rules = {"alternatives": 1, "structure": {"repeat": False, "mirror": False}}
    spec = _spec(**rules)
    for good in ([0, 1], [2, 3]):
        anchoring = np.full(4, -0.5)
        anchoring[good] = 1.0
        alt = search(_twins(anchoring), song, spec).alternatives[0]
        assert set(alt.index.tolist()) == set(good)
        # the others cost 1.5·ANCHOR_WEIGHT more per bar (G_r units, weighted by λ10 λ13), in
        # the rhythm term
        bad = np.setdiff1d(np.arange(4), good)
        without = [{"node": f"c{k}:0"} for k in good]
        worse = search(_twins(anchoring), song, _spec(**rules, exclude=without))
        worse = worse.alternatives[0]
        assert set(worse.index.tolist()) == set(bad.tolist())
        extra = spec.weights.data * spec.weights.rhythm * problem.ANCHOR_WEIGHT * 1.5
        assert worse.cost - alt.cost == pytest.approx(song.n_bars * extra, rel=1e-4)
        rhythm = sum(r["rhythm"] for r in worse.per_bar) - sum(r["rhythm"] for r in alt.per_bar)
        assert rhythm == pytest.approx(song.n_bars * extra, rel=1e-3)
    # off: the less anchored nodes cost what they cost in a graph without the array
    base = search(_twins(None), song, spec).alternatives[0].cost
    mixed, without = np.array([1.0, 1.0, -0.5, -0.5]), [{"node": "c0:0"}, {"node": "c1:0"}]
    assert search(_twins(mixed), song, _spec(**rules, exclude=without)).alternatives[0].cost > (
        base + 1.0
    )
    monkeypatch.setattr(problem, "ANCHOR_WEIGHT", 0.0)
    off = search(_twins(mixed), song, _spec(**rules, exclude=without)).alternatives[0].cost
    assert off == pytest.approx(base)
