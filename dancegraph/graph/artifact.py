"""Motion-graph artifact: one immutable, versioned folder per build, loaded memory-mapped.

Layout in the object store::

    graphs/<name>/current                 text file: the version that answers now (atomic rename)
    graphs/<name>/<version>/manifest.json build params, dataset/embedding versions, checksums, stats
    graphs/<name>/<version>/<array>.npy   one plain .npy per array (see ``ARRAYS``)

A build writes a new ``<version>`` folder in full, then swaps ``current``; a server that loaded the
previous version keeps its memory maps (the old folder is never modified), so the old graph keeps
answering while the new one loads.

Arrays (N nodes, E edges, M motion rows, R stored frames, J joints, D transition features):

- ``node_clip (N,) int32`` index into ``manifest["clips"]``; ``node_bar (N,) int32`` bar index in
  its take; ``node_kind (N,) int8`` (``KINDS``); ``node_tags (N,) uint32`` bit mask of
  ``manifest["tags"]``; ``node_source (N, 2) int32`` original bars an augmentation came from
  (-1 when unused); ``mirror_of (N,) int32`` the mirrored node (-1: none).
- ``style (N, 32) float32`` style embedding; ``signature (N,) uint8`` the node's rhythm
  signature as a slot pattern (bit i = slot i, ``rhythm.signatures.to_pattern``); ``motif (N,)
  int32``.
- ``entry (N, D) float32`` / ``exit (N, D) float32`` transition features at the bar line (see
  ``build``), and ``entry_pc`` / ``exit_pc (N, P) float32`` their per-block PCA
  (``manifest["pc_blocks"]``) for on-demand costs of transitions that are not edges.
- ``disp (N, 3) float32`` root displacement over the bar: (dx, dz) metres in the bar's start heading
  frame and dyaw radians; ``radius (N,) float32`` largest horizontal distance (m) of the root from
  its start position during the bar; ``root_path (N, S, 2) float32`` the root's (x, z) in the start
  heading frame at S evenly spaced times; ``duration (N,) float32`` source bar length in seconds.
- ``indptr (N+1,) int64``, ``indices (E,) int32``, ``costs (E,) float32``: out-edges p → q in
  CSR form, ``indices`` sorted within each row.
- ``motion_row (N,) int32`` the node's motion row; row m's frames are ``motion_ptr[m] ..
  motion_ptr[m+1]`` (``motion_ptr (M+1,) int64``) of ``root (R, 3) float32`` (metres, world frame
  of the source take) and ``rotations (R, J, 4) float32`` (local joint rotations, x y z w), at
  ``motion_fps (M,) float32``: the take's frames from about a beat before the bar's downbeat to a
  beat after its closing downbeat; ``motion_beats (M, 9) float32`` the frames (fractional,
  counted from the row's first) of the bar's beats -2 .. 6 (``retime.NODE_BEATS``), what the
  renderer's time-warp and cut choice read (``node_frames``).

Optional: ``anchoring (N,) float32`` how well each node's stops sit on its beats
(``build.node_anchoring``; the search's rhythm term prefers well-anchored nodes). Graphs built
before it, from annotated beat grids, or on a skeleton without the canonical joints have none,
and the search then has no anchoring term; the format stays 2.

Format 2 (this one) stores the ragged frames around each bar; format 1 stored each bar resampled
to a fixed frame count and is refused with a request to rebuild (``load_graph``).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dancegraph.errors import ModelFileError, NotFoundError
from dancegraph.motion.retime import BEAT0, sample
from dancegraph.motion.skeleton import Motion, Skeleton
from dancegraph.store import ObjectStore, file_sha256

#: 2: nodes keep their take's frames around the bar with their beats (the renderer's warp and
#: cut), rotations in float32, ``signature`` a slot pattern (was an index into COMMON_SIGNATURES)
FORMAT_VERSION = 2

#: node kinds, index = ``node_kind`` value
KINDS = ("original", "mirror", "blend", "shuffle")

#: node tags every build knows; datasets may add clip flags after these
BASE_TAGS = ("original", "mirror", "blend", "shuffle", "augmented")

ARRAYS = (
    "node_clip",
    "node_bar",
    "node_kind",
    "node_tags",
    "node_source",
    "mirror_of",
    "style",
    "signature",
    "motif",
    "entry",
    "exit",
    "entry_pc",
    "exit_pc",
    "disp",
    "radius",
    "root_path",
    "duration",
    "indptr",
    "indices",
    "costs",
    "motion_row",
    "motion_ptr",
    "motion_beats",
    "motion_fps",
    "root",
    "rotations",
)

#: arrays indexed by motion row or stored frame, not by node
MOTION_ARRAYS = ("motion_ptr", "motion_beats", "motion_fps", "root", "rotations")

_VERSION_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


@dataclass
class MotionGraph:
    """A loaded motion graph: arrays (memory-mapped when loaded) plus the manifest."""

    manifest: dict
    arrays: dict[str, np.ndarray]
    path: Path | None = None
    node_ids: list[str] = field(default_factory=list)
    _index: dict[str, int] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if not self.node_ids:
            self.node_ids = make_node_ids(self)
        self._index = {nid: i for i, nid in enumerate(self.node_ids)}

    def __getattr__(self, name: str) -> np.ndarray:
        arrays = self.__dict__.get("arrays")
        if arrays is not None and name in arrays:
            return arrays[name]
        raise AttributeError(name)

    @property
    def n_nodes(self) -> int:
        return int(self.arrays["node_clip"].shape[0])

    @property
    def n_edges(self) -> int:
        return int(self.arrays["indices"].shape[0])

    @property
    def name(self) -> str:
        return self.manifest.get("name", "")

    @property
    def version(self) -> str:
        return self.manifest.get("version", "")

    @property
    def clips(self) -> list[str]:
        return list(self.manifest["clips"])

    @property
    def tags(self) -> list[str]:
        return list(self.manifest["tags"])

    @property
    def tempo_range(self) -> tuple[float, float] | None:
        """The dance style's tempo range (lo, hi) BPM of the counted beat that the graph's
        dataset declares (manifest ``style_tempo_bpm``): a song analysed for this graph counts
        the octave that fits it (``music.analysis.analyze(..., tempo_range=)``). None where the
        dataset declares none or the graph was built before the range was carried."""
        rng = (self.manifest.get("dataset") or {}).get("style_tempo_bpm")
        return (float(rng[0]), float(rng[1])) if rng else None

    @property
    def skeleton(self) -> Skeleton:
        return Skeleton.from_dict(self.manifest["skeleton"])

    def node_index(self, node_id: str) -> int:
        """Index of ``node_id``; raises ``KeyError`` when it does not exist."""
        return self._index[node_id]

    def has_node(self, node_id: str) -> bool:
        return node_id in self._index

    def tag_bit(self, tag: str) -> int:
        """Bit of ``tag`` in ``node_tags``; ``KeyError`` for an unknown tag."""
        return 1 << self.tags.index(tag)

    def out_edges(self, p: int) -> tuple[np.ndarray, np.ndarray]:
        """Targets ``(k,)`` and costs ``(k,)`` of node ``p``'s out-edges."""
        a, b = self.indptr[p], self.indptr[p + 1]
        return self.indices[a:b], self.costs[a:b]

    def degree_out(self) -> np.ndarray:
        return np.diff(np.asarray(self.indptr))

    def degree_in(self) -> np.ndarray:
        return np.bincount(np.asarray(self.indices), minlength=self.n_nodes)

    def node_frames(self, i: int) -> tuple[Motion, np.ndarray]:
        """The node's stored motion (its take's frames around the bar, at the take's rate) and the
        frames ``(9,)`` of its beats -2 .. 6 in it: what the renderer warps and cuts."""
        row = int(self.motion_row[i])
        a, b = int(self.motion_ptr[row]), int(self.motion_ptr[row + 1])
        root = np.asarray(self.root[a:b], dtype=np.float64)
        rot = np.asarray(self.rotations[a:b], dtype=np.float64)
        rot /= np.linalg.norm(rot, axis=-1, keepdims=True)
        motion = Motion(self.skeleton, float(self.motion_fps[row]), root, rot)
        return motion, np.asarray(self.motion_beats[row], dtype=np.float64)

    def node_motion(self, i: int, fps: float | None = None) -> Motion:
        """The node's bar as a ``Motion``: from its downbeat to its closing downbeat (exclusive),
        at its take's frame rate, or resampled to ``fps``; frame 0 is the downbeat."""
        motion, beats = self.node_frames(i)
        rate = motion.fps if fps is None else float(fps)
        n = max(1, int(round((beats[BEAT0 + 4] - beats[BEAT0]) * rate / motion.fps)))
        out = sample(motion, beats[BEAT0] + np.arange(n) * motion.fps / rate)
        out.fps = rate
        return out

    def node_info(self, i: int) -> dict:
        """JSON-able description of node ``i`` (for provenance and the graph-store API)."""
        clip = self.clips[int(self.node_clip[i])]
        src = [int(s) for s in self.node_source[i] if s >= 0]
        tags = [t for k, t in enumerate(self.tags) if int(self.node_tags[i]) >> k & 1]
        bars = self.manifest.get("bar_frames", {}).get(clip)
        info = {
            "node": self.node_ids[i],
            "clip": clip,
            "bar": int(self.node_bar[i]),
            "kind": KINDS[int(self.node_kind[i])],
            "tags": tags,
            "sources": [self.node_ids[s] for s in src],
            "motif": int(self.motif[i]),
            "duration_s": float(self.duration[i]),
        }
        # source frame range [start, end) of the bar in its take (JSON keys are strings)
        frames = (bars or {}).get(str(int(self.node_bar[i])))
        if frames is not None:
            info["frames"] = [int(f) for f in frames]
        return info

    def stats(self) -> dict:
        """Node and edge counts and the out-degree distribution."""
        deg = self.degree_out()
        kinds = np.bincount(np.asarray(self.node_kind), minlength=len(KINDS))
        return {
            "nodes": self.n_nodes,
            "edges": self.n_edges,
            "nodes_by_kind": {k: int(c) for k, c in zip(KINDS, kinds, strict=True)},
            "degree": degree_summary(deg),
        }


def degree_summary(deg: np.ndarray) -> dict:
    """Min, percentiles, mean and max of a degree array, plus a small histogram."""
    deg = np.asarray(deg)
    if deg.size == 0:
        return {"min": 0, "mean": 0.0, "max": 0}
    edges = [0, 1, 2, 4, 8, 16, 32, 64, 128, 1 << 30]
    hist, _ = np.histogram(deg, bins=edges)
    labels = [
        f"{a}" if b - a == 1 else f"{a}-{b - 1}"
        for a, b in zip(edges[:-2], edges[1:-1], strict=True)
    ]
    labels.append(f">={edges[-2]}")
    return {
        "min": int(deg.min()),
        "p10": float(np.percentile(deg, 10)),
        "median": float(np.median(deg)),
        "p90": float(np.percentile(deg, 90)),
        "mean": float(deg.mean()),
        "max": int(deg.max()),
        "histogram": {lab: int(h) for lab, h in zip(labels, hist, strict=True)},
    }


def make_node_ids(graph: MotionGraph) -> list[str]:
    """Node ids from the node table: ``<clip>:<bar>``, ``~m`` mirror, ``~b<k>`` blend, ``~s<k>``."""
    clips = graph.manifest["clips"]
    kind = np.asarray(graph.arrays["node_kind"])
    clip = np.asarray(graph.arrays["node_clip"])
    bar = np.asarray(graph.arrays["node_bar"])
    aug_no = graph.arrays.get("aug_index")
    ids = []
    counters = {2: 0, 3: 0}
    for i in range(kind.shape[0]):
        base = f"{clips[clip[i]]}:{bar[i]}"
        k = int(kind[i])
        if k == 0:
            ids.append(base)
        elif k == 1:
            ids.append(base + "~m")
        else:
            n = int(aug_no[i]) if aug_no is not None else counters[k]
            counters[k] += 1
            ids.append(f"{base}~{'b' if k == 2 else 's'}{n}")
    return ids


def graph_key(name: str, version: str | None = None) -> str:
    return f"graphs/{name}" if version is None else f"graphs/{name}/{version}"


def write_graph(
    store: ObjectStore,
    name: str,
    arrays: dict[str, np.ndarray],
    manifest: dict,
    *,
    node_ids: list[str] | None = None,
    version: str | None = None,
    make_current: bool = True,
) -> str:
    """Write a graph build as a new immutable version folder; returns its key.

    ``version`` defaults to a UTC timestamp plus a short content hash. The folder is written
    under a temporary name and renamed into place; ``current`` is then swapped atomically.
    The same build written twice within one second names the same default version: the stored
    one is kept (its arrays are identical) and made current. An explicit ``version`` that
    exists raises ``FileExistsError``.
    """
    missing = [a for a in ARRAYS if a not in arrays]
    if missing:
        raise ValueError(f"graph arrays missing: {missing}")
    tmp = store.temp_dir("build")
    try:
        checksums = {}
        digest = hashlib.sha256()
        for key, arr in arrays.items():
            path = tmp / f"{key}.npy"
            np.save(path, np.ascontiguousarray(arr), allow_pickle=False)
            checksums[f"{key}.npy"] = file_sha256(path)
            digest.update(checksums[f"{key}.npy"].encode())
        if node_ids is not None:
            if len(node_ids) != arrays["node_clip"].shape[0]:
                raise ValueError("node_ids must name every node")
            (tmp / "node_ids.txt").write_text("\n".join(node_ids))
            checksums["node_ids.txt"] = file_sha256(tmp / "node_ids.txt")
            digest.update(checksums["node_ids.txt"].encode())
        auto_named = version is None
        if version is None:
            version = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + digest.hexdigest()[:8]
        if not _VERSION_RE.match(version):
            raise ValueError(f"invalid graph version {version!r}")
        manifest = dict(manifest)
        manifest.update(
            {
                "format": FORMAT_VERSION,
                "name": name,
                "version": version,
                "arrays": sorted(arrays),
                "node_ids_file": "node_ids.txt" if node_ids is not None else None,
                "checksums": checksums,
                "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            }
        )
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1, default=_json_default))
        key = graph_key(name, version)
        # the manifest goes last and only if absent: a reader sees a whole version or none
        if not store.put_tree(key, tmp, last="manifest.json"):
            if not (auto_named and _same_checksums(store, key, checksums)):
                raise FileExistsError(f"graph version {name}/{version} already exists")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if make_current:
        set_current(store, name, version)
    return graph_key(name, version)


def _same_checksums(store: ObjectStore, key: str, checksums: dict) -> bool:
    try:
        stored = json.loads(store.get_bytes(f"{key}/manifest.json"))
    except (OSError, ValueError):
        return False
    return stored.get("checksums") == checksums


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj)}")


def set_current(store: ObjectStore, name: str, version: str) -> None:
    """Point ``graphs/<name>/current`` at ``version`` (atomic replace)."""
    if not store.exists(f"{graph_key(name, version)}/manifest.json"):
        raise NotFoundError(
            f"graph {name!r} has no version {version!r}", code="unknown_graph", field="version"
        )
    store.put_bytes(f"{graph_key(name)}/current", version.encode())


def current_version(store: ObjectStore, name: str) -> str:
    """The version ``current`` points at; NotFoundError(code='unknown_dataset') when none."""
    try:
        return store.get_bytes(f"{graph_key(name)}/current").decode().strip()
    except ValueError as exc:
        raise NotFoundError(
            f"invalid graph name {name!r}", code="unknown_dataset", field="dataset"
        ) from exc
    except FileNotFoundError:
        raise NotFoundError(
            f"no graph built for dataset {name!r}", code="unknown_dataset", field="dataset"
        ) from None


def list_versions(store: ObjectStore, name: str) -> list[str]:
    return store.children(graph_key(name))


def list_graphs(store: ObjectStore) -> list[str]:
    return [n for n in store.children("graphs") if store.exists(f"{graph_key(n)}/current")]


def graph_folder(store: ObjectStore, name: str, version: str) -> Path:
    """A local folder of the graph version (the store's own, or a download), with the learned
    model files its manifest names fetched beside it (``embed.learned.store_root``)."""
    folder = store.local_dir(graph_key(name, version))
    try:
        manifest = json.loads((folder / "manifest.json").read_text())
    except (OSError, ValueError):
        return folder  # load_graph names the problem
    entry = manifest.get("embedding") or {}
    for kind in ("style_model", "rhythm_model"):
        if isinstance(entry, dict) and isinstance(entry.get(kind), dict) and entry[kind].get("key"):
            store.local_path(entry[kind]["key"])
    return folder


def load_graph(path: str | os.PathLike, *, verify: bool = False, mmap: bool = True) -> MotionGraph:
    """Load a graph version folder, arrays memory-mapped read-only.

    ``verify`` checks every array's sha256 against the manifest (reads every byte). Raises
    NotFoundError for a missing folder, ModelFileError for a corrupt or foreign artifact.
    """
    folder = Path(path)
    manifest_path = folder / "manifest.json"
    if not manifest_path.is_file():
        raise NotFoundError(f"no graph artifact at {folder}", code="unknown_graph", field="path")
    try:
        manifest = json.loads(manifest_path.read_text())
    except json.JSONDecodeError as exc:
        raise ModelFileError(
            f"{manifest_path}: not JSON ({exc})", code="graph_corrupt", field=str(manifest_path)
        ) from exc
    if manifest.get("format") != FORMAT_VERSION:
        raise ModelFileError(
            f"{folder}: graph format {manifest.get('format')!r}, this code reads {FORMAT_VERSION}; "
            f"rebuild it: dancegraph dataset build {manifest.get('name') or '<dataset>'}",
            code="graph_version",
            field="format",
        )
    arrays = {}
    for key in manifest["arrays"]:
        file = folder / f"{key}.npy"
        if verify and file_sha256(file) != manifest["checksums"].get(f"{key}.npy"):
            raise ModelFileError(
                f"{file}: checksum mismatch", code="graph_corrupt", field=f"{key}.npy"
            )
        try:
            arrays[key] = np.load(file, mmap_mode="r" if mmap else None, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ModelFileError(
                f"{file}: unreadable ({exc})", code="graph_corrupt", field=f"{key}.npy"
            ) from exc
    node_ids = manifest.get("node_ids_file")
    ids = []
    if node_ids:
        ids = (folder / node_ids).read_text().split("\n")
    return MotionGraph(manifest=manifest, arrays=arrays, path=folder, node_ids=ids)


def load_current(store: ObjectStore, name: str, *, verify: bool = False) -> MotionGraph:
    """Load the version ``graphs/<name>/current`` points at."""
    version = current_version(store, name)
    return load_graph(graph_folder(store, name, version), verify=verify)


def open_graph(store: ObjectStore, name: str, version: str | None = None) -> MotionGraph:
    """Dataset ``name``'s graph ready to search: ``version`` (default: the current one) loaded
    and the learned models it was built with checked, so a bad model file fails here, not in a
    job. Raises NotFoundError (``unknown_dataset``; ``unknown_graph_version`` for a version that
    does not exist) or ModelFileError."""
    from dancegraph.embed.learned import load_graph_models

    if version is None:
        graph = load_current(store, name)
    else:
        try:
            graph = load_graph(graph_folder(store, name, version))
        except (ValueError, NotFoundError) as exc:
            raise NotFoundError(
                f"dataset {name!r} has no graph version {version!r}",
                code="unknown_graph_version",
                field="version",
            ) from exc
    load_graph_models(graph)
    return graph


def graph_from_arrays(arrays: dict[str, np.ndarray], manifest: dict) -> MotionGraph:
    """An in-memory graph (no folder), e.g. for tests and benchmarks."""
    return MotionGraph(manifest=dict(manifest), arrays=dict(arrays))


def bare_graph(
    src: np.ndarray,
    dst: np.ndarray,
    costs: np.ndarray,
    *,
    n_nodes: int,
    clips: list[str],
    **arrays: np.ndarray,
) -> MotionGraph:
    """An in-memory graph of ``n_nodes`` interchangeable one-beat nodes with neutral arrays
    (zero style, features, displacement and root path; signature 0; no source, no mirror; one
    still frame of one joint as their motion) and the edges ``src (E,)`` → ``dst (E,)`` at
    ``costs (E,)``; ``arrays`` replace any array by name (e.g. ``anchoring``, ``mirror_of``).
    ``clips``: the clip ids ``node_clip`` indexes. Why: the search's kernel warm-up and its
    tests need a graph that differs from nothing only where they say so."""
    n, d = n_nodes, 4
    z = np.zeros
    src = np.asarray(src, dtype=np.int64)
    order = np.argsort(src, kind="stable")
    base: dict[str, np.ndarray] = {
        "node_clip": z(n, np.int32),
        "node_bar": np.arange(n, dtype=np.int32),
        "node_kind": z(n, np.int8),
        "node_tags": z(n, np.uint32),
        "node_source": np.full((n, 2), -1, np.int32),
        "mirror_of": np.full(n, -1, np.int32),
        "style": z((n, 32), np.float32),
        "signature": z(n, np.uint8),
        "motif": z(n, np.int32),
        "entry": z((n, d), np.float32),
        "exit": z((n, d), np.float32),
        "entry_pc": z((n, d), np.float32),
        "exit_pc": z((n, d), np.float32),
        "disp": z((n, 3), np.float32),
        "radius": z(n, np.float32),
        "root_path": z((n, 8, 2), np.float32),
        "duration": np.ones(n, np.float32),
        "indptr": np.r_[0, np.cumsum(np.bincount(src, minlength=n))].astype(np.int64),
        "indices": np.asarray(dst, dtype=np.int32)[order],
        "costs": np.asarray(costs, dtype=np.float32)[order],
        "motion_row": z(n, np.int32),
        "root": z((1, 4, 3), np.float32),
        "rotations": z((1, 4, 1, 4), np.float16),
    }
    base.update({k: np.asarray(v) for k, v in arrays.items()})
    manifest = {
        "clips": list(clips),
        "tags": ["original"],
        "pc_blocks": [d],
        "feature_blocks": [d],
        "params": {},
    }
    return graph_from_arrays(base, manifest)
