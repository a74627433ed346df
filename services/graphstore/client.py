"""Graph-store clients: one interface, in-process (`LocalGraphStore`) or over HTTP (`HttpGraphStore`).

The worker and the API talk to the graph store through :class:`GraphStoreClient`; the embedded
default uses :class:`LocalGraphStore` (graphs loaded in this process from the object store), a
production deployment :class:`HttpGraphStore` (the ``services.graphstore.app`` service). Both
answer the same typed methods (``MusicAnalysis`` and ``Spec`` in, ``SearchResult`` out; the HTTP
client sends their JSON forms) and raise the same ``DanceGraphError`` codes
(``unknown_dataset``, ``unknown_node``, ``spec_invalid``, ``analysis_invalid``, ...).
"""

from __future__ import annotations

import json
import threading
from abc import ABC, abstractmethod
from collections import OrderedDict

import numpy as np

from dancegraph.errors import DanceGraphError, NotFoundError, SpecError
from dancegraph.graph import artifact
from dancegraph.graph.search import SearchResult
from dancegraph.motion.skeleton import Motion, Skeleton
from dancegraph.music.analysis import MusicAnalysis
from dancegraph.spec import Spec
from dancegraph.store import ObjectStore


class GraphStoreClient(ABC):
    """What the worker and the API need from the graph store."""

    @abstractmethod
    def list_graphs(self) -> list[dict]:
        """Every dataset with a built graph: ``[{name, version, graph_key, stats, embedding, licence}]``."""

    @abstractmethod
    def graph_info(self, name: str) -> dict:
        """One graph: version, build parameters, stats, which embedding, the dataset it was built from."""

    @abstractmethod
    def search(
        self, analysis: MusicAnalysis, spec: Spec, version: str | None = None
    ) -> SearchResult:
        """Paths through the graph of ``spec.dataset`` (``version``: that version, pinned by the
        job; default the current one) for a song's analysis; the result names the graph version
        it was searched on (``graph_name``, ``graph_version``)."""

    @abstractmethod
    def node(self, dataset: str, node_id: str) -> dict:
        """Provenance of one node: take, bar, source frames, kind (augmentation), tags, motif."""

    @abstractmethod
    def skeleton(self, dataset: str) -> Skeleton:
        """The dataset's skeleton."""

    @abstractmethod
    def node_motion(self, dataset: str, node_id: str) -> Motion:
        """The node's bar as motion (frames spread evenly over the source bar's length)."""


def parse_analysis(data: object) -> MusicAnalysis:
    """A ``MusicAnalysis.to_dict()`` object sent over HTTP, checked; DanceGraphError
    ``analysis_invalid`` (422) naming what is wrong."""
    if not isinstance(data, dict):
        raise DanceGraphError(
            "analysis must be a JSON object", code="analysis_invalid", field="analysis"
        )
    try:
        analysis = MusicAnalysis.from_dict(data)
    except (KeyError, TypeError, ValueError) as exc:
        raise _analysis_error(
            f"analysis is not a MusicAnalysis.to_dict() result ({exc!r})"
        ) from exc
    bars = np.asarray(analysis.bars, dtype=float)
    if bars.ndim != 2 or bars.shape[1] != 2 or not np.all(np.isfinite(bars)):
        raise _analysis_error("analysis.bars must be (B, 2) finite start/end seconds")
    if bars.shape[0] and np.any(bars[:, 1] <= bars[:, 0]):
        raise _analysis_error("analysis.bars: every bar must end after it starts")
    return analysis


def _analysis_error(message: str) -> DanceGraphError:
    err = DanceGraphError(message, code="analysis_invalid", field="analysis")
    err.status = 422
    return err


class LocalGraphStore(GraphStoreClient):
    """Graphs loaded in this process from ``store`` (memory-mapped) on first use, kept under a
    memory budget least-recently-used first, reloaded when a build lands.

    Each ``graph(name)`` call reads ``graphs/<name>/current`` from the store (so replicas that
    share only the object store agree on what is current); a new version is loaded beside the
    old one, which keeps answering the calls already holding it. ``memory_budget_bytes``: the
    loaded graphs' arrays (``graph_nbytes``) above it are evicted, least recently used first,
    never the one just asked for (None: no budget).
    """

    def __init__(self, store: ObjectStore, memory_budget_bytes: int | None = None):
        self.store = store
        self.memory_budget_bytes = memory_budget_bytes
        self._graphs: OrderedDict[tuple[str, str], artifact.MotionGraph] = OrderedDict()
        self._lock = threading.Lock()
        self.evictions = 0

    def graph(self, name: str) -> artifact.MotionGraph:
        """The current graph of dataset ``name``; NotFoundError(code='unknown_dataset') if none."""
        return self.graph_version(name, artifact.current_version(self.store, name))

    def graph_version(self, name: str, version: str) -> artifact.MotionGraph:
        """A given version of ``name``'s graph (a job's pinned one, or the one a search answered
        from), loaded on first use; NotFoundError ``unknown_graph_version`` if it does not exist."""
        key = (name, version)
        with self._lock:
            cached = self._graphs.get(key)
            if cached is not None:
                self._graphs.move_to_end(key)
                return cached
        loaded = artifact.open_graph(self.store, name, version)
        with self._lock:
            self._graphs[key] = loaded
            self._graphs.move_to_end(key)
            self._evict(keep=key)
        return loaded

    def _evict(self, keep: tuple[str, str]) -> None:
        """Drop least-recently-used graphs while over the budget (caller holds the lock)."""
        if self.memory_budget_bytes is None:
            return
        while self.resident_bytes() > self.memory_budget_bytes and len(self._graphs) > 1:
            oldest = next(iter(self._graphs))
            if oldest == keep:
                break
            del self._graphs[oldest]
            self.evictions += 1

    def resident_bytes(self) -> int:
        """Bytes of the loaded graphs' arrays (their resident size once paged in)."""
        return sum(graph_nbytes(g) for g in list(self._graphs.values()))

    def loaded(self) -> dict[str, str]:
        """Dataset name → the most recently used loaded version."""
        with self._lock:
            return {name: version for name, version in self._graphs}

    def memory(self) -> dict:
        """The budget, the bytes the loaded graphs hold, how many, and evictions so far."""
        with self._lock:
            return {
                "budget_bytes": self.memory_budget_bytes,
                "resident_bytes": self.resident_bytes(),
                "graphs": len(self._graphs),
                "evictions": self.evictions,
            }

    def forget(self, name: str) -> None:
        """Unload every version of ``name`` (its library was deleted)."""
        with self._lock:
            for key in [k for k in self._graphs if k[0] == name]:
                del self._graphs[key]

    def list_graphs(self) -> list[dict]:
        """Every current graph's summary, read from its manifest alone (no arrays loaded)."""
        out = []
        for name in artifact.list_graphs(self.store):
            try:
                version = artifact.current_version(self.store, name)
                key = f"{artifact.graph_key(name, version)}/manifest.json"
                out.append(_manifest_summary(json.loads(self.store.get_bytes(key))))
            except (DanceGraphError, FileNotFoundError, ValueError):
                continue  # a broken build is left out of the list, not a failure of the list
        return out

    def graph_info(self, name: str) -> dict:
        graph = self.graph(name)
        info = _summary(graph)
        manifest = graph.manifest
        info.update(
            {
                "stats": graph.stats(),
                "created": manifest.get("created"),
                "params": manifest.get("params", {}),
                "embedding_details": {  # which models, not their numbers (stats, bridge)
                    k: v
                    for k, v in (manifest.get("embedding") or {}).items()
                    if k not in ("dance_stats", "bridge")
                },
                "dataset": manifest.get("dataset", {}),
                "tags": graph.tags,
                "clips": len(graph.clips),
                "skeleton": {"joints": graph.skeleton.n_joints, "root": graph.skeleton.names[0]},
                "motifs": (manifest.get("motifs") or {}).get("k"),
                "versions": artifact.list_versions(self.store, name),
            }
        )
        return info

    def search(
        self, analysis: MusicAnalysis, spec: Spec, version: str | None = None
    ) -> SearchResult:
        from dancegraph.graph.search import search

        name = single_library(spec)
        graph = self.graph_version(name, version) if version else self.graph(name)
        return search(graph, analysis, spec)

    def _node_index(self, graph: artifact.MotionGraph, node_id: str) -> int:
        try:
            return graph.node_index(node_id)
        except KeyError:
            raise NotFoundError(
                f"dataset {graph.name!r} has no node {node_id!r}",
                code="unknown_node",
                field="node_id",
            ) from None

    def node(self, dataset: str, node_id: str) -> dict:
        graph = self.graph(dataset)
        return node_provenance(graph, self._node_index(graph, node_id))

    def skeleton(self, dataset: str) -> Skeleton:
        return self.graph(dataset).skeleton

    def node_motion(self, dataset: str, node_id: str) -> Motion:
        graph = self.graph(dataset)
        return graph.node_motion(self._node_index(graph, node_id))


def single_library(spec: Spec) -> str:
    """The one library a search runs on; SpecError ``spec_invalid`` for a spec still naming a
    list (the worker resolves a list or a style to one library before it searches)."""
    if not isinstance(spec.dataset, str):
        raise SpecError(
            "a search runs on one library: choose one from the list first",
            code="spec_invalid",
            field="spec.dataset",
        )
    return spec.dataset


def graph_nbytes(graph: artifact.MotionGraph) -> int:
    """A loaded graph's resident size: the bytes of its arrays (memory-mapped or not)."""
    return int(sum(np.asarray(a).nbytes for a in graph.arrays.values()))


def _summary(graph: artifact.MotionGraph) -> dict:
    return {**_manifest_summary(graph.manifest), "nodes": graph.n_nodes, "edges": graph.n_edges}


def _manifest_summary(manifest: dict) -> dict:
    """Name, version, key, size, embedding and licence of a graph, from its manifest."""
    dataset = manifest.get("dataset") or {}
    embedding = manifest.get("embedding") or {}
    build = manifest.get("build") or {}
    name, version = manifest.get("name", ""), manifest.get("version", "")
    return {
        "name": name,
        "version": version,
        "graph_key": artifact.graph_key(name, version),
        "nodes": build.get("nodes"),
        "edges": build.get("edges"),
        "embedding": embedding.get("version", "unknown"),
        "dataset_version": dataset.get("version"),
        "licence": dataset.get("licence"),
    }


def node_provenance(graph: artifact.MotionGraph, i: int) -> dict:
    """Where node ``i`` comes from: take, bar, source frame range, augmentation kind and sources."""
    info = graph.node_info(i) if _bar_frames_ok(graph) else _node_info_fallback(graph, i)
    frames = _bar_frames(graph, info["clip"], info["bar"])
    if frames is not None:
        info["frames"] = frames
    info["augmentation"] = None if info["kind"] == "original" else info["kind"]
    return info


def _bar_frames_ok(graph: artifact.MotionGraph) -> bool:
    # node_info indexes manifest["bar_frames"][clip] by an int bar; JSON turns those keys into
    # strings, so only trust it when they are not dict keys.
    frames = graph.manifest.get("bar_frames") or {}
    return all(not isinstance(v, dict) for v in frames.values())


def _node_info_fallback(graph: artifact.MotionGraph, i: int) -> dict:
    clip = graph.clips[int(graph.node_clip[i])]
    src = [int(s) for s in graph.node_source[i] if s >= 0]
    tags = [t for k, t in enumerate(graph.tags) if int(graph.node_tags[i]) >> k & 1]
    return {
        "node": graph.node_ids[i],
        "clip": clip,
        "bar": int(graph.node_bar[i]),
        "kind": artifact.KINDS[int(graph.node_kind[i])],
        "tags": tags,
        "sources": [graph.node_ids[s] for s in src],
        "motif": int(graph.motif[i]),
        "duration_s": float(graph.duration[i]),
    }


def _bar_frames(graph: artifact.MotionGraph, clip: str, bar: int) -> list[int] | None:
    """``[start, end)`` frames of ``clip``'s bar ``bar`` in its source take, if recorded."""
    table = (graph.manifest.get("bar_frames") or {}).get(clip)
    if table is None:
        return None
    if isinstance(table, dict):
        entry = table.get(str(bar), table.get(bar))
    else:
        entry = table[bar] if 0 <= bar < len(table) else None
    return [int(x) for x in entry] if entry is not None else None


class HttpGraphStore(GraphStoreClient):
    """The graph-store service over HTTP (``services.graphstore.app``)."""

    def __init__(self, base_url: str, *, timeout_s: float = 120.0, client=None):
        import httpx

        self.base_url = base_url.rstrip("/")
        self._client = client or httpx.Client(base_url=self.base_url, timeout=timeout_s)
        self._skeletons: dict[str, Skeleton] = {}

    def close(self) -> None:
        self._client.close()

    def _call(self, method: str, path: str, **kwargs) -> dict:
        import httpx

        try:
            resp = self._client.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            err = DanceGraphError(
                f"graph store at {self.base_url} unreachable: {exc}", code="graphstore_unavailable"
            )
            err.status = 503
            raise err from exc
        if resp.status_code >= 400:
            raise _error_from_problem(resp)
        return resp.json()

    def list_graphs(self) -> list[dict]:
        return self._call("GET", "/v1/graphs")["items"]

    def graph_info(self, name: str) -> dict:
        return self._call("GET", f"/v1/graphs/{name}")

    def search(
        self, analysis: MusicAnalysis, spec: Spec, version: str | None = None
    ) -> SearchResult:
        body = {"analysis": analysis.to_dict(), "spec": spec.model_dump(mode="json")}
        params = {"version": version} if version else None
        data = self._call(
            "POST", f"/v1/graphs/{single_library(spec)}/search", json=body, params=params
        )
        try:
            return SearchResult.from_dict(data)
        except (KeyError, TypeError, ValueError) as exc:
            err = DanceGraphError(
                f"the graph store at {self.base_url} answered a search with another shape: {exc!r}",
                code="graphstore_invalid_answer",
            )
            err.status = 502
            raise err from exc

    def node(self, dataset: str, node_id: str) -> dict:
        return self._call("GET", f"/v1/graphs/{dataset}/nodes/{node_id}")

    def skeleton(self, dataset: str) -> Skeleton:
        if dataset not in self._skeletons:
            self._skeletons[dataset] = Skeleton.from_dict(
                self._call("GET", f"/v1/graphs/{dataset}/skeleton")
            )
        return self._skeletons[dataset]

    def node_motion(self, dataset: str, node_id: str) -> Motion:
        data = self._call("GET", f"/v1/graphs/{dataset}/nodes/{node_id}/motion")
        return Motion(
            skeleton=self.skeleton(dataset),
            fps=float(data["fps"]),
            root_positions=np.asarray(data["root_positions"], dtype=float),
            rotations=np.asarray(data["rotations"], dtype=float),
        )


def _error_from_problem(resp) -> DanceGraphError:
    """The DanceGraphError a problem+json answer stands for (same code, field and status)."""
    try:
        body = resp.json()
    except ValueError:
        body = {}
    code = body.get("code") or f"http_{resp.status_code}"
    message = body.get("detail") or resp.text[:500] or f"HTTP {resp.status_code}"
    field = body.get("field")
    if resp.status_code == 404:
        err: DanceGraphError = NotFoundError(message, code=code, field=field)
    elif code.startswith("spec_") or code == "constraint_conflict":
        err = SpecError(message, code=code, field=field)
    else:
        err = DanceGraphError(message, code=code, field=field)
    err.status = resp.status_code
    return err
