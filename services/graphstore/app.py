"""The graph-store service: prebuilt motion graphs in memory, path search, node and clip data.

A thin HTTP shell over :class:`services.graphstore.client.LocalGraphStore`, which loads each
dataset's current graph artifact from the object store (``dancegraph.graph.artifact``) and
reloads it when a new build lands (the old version keeps answering requests already holding it);
graphs load on first use and are evicted least-recently-used above
``DANCEGRAPH_GRAPHSTORE_MEMORY_BYTES``. Nothing lives only in one replica: any number of them
can serve the same object store.

Run: ``uvicorn services.graphstore.app:app`` (object store: ``DANCEGRAPH_STORE_URL`` for S3, else
the folder ``DANCEGRAPH_STORE_ROOT`` or ``$DANCEGRAPH_HOME/store``). Errors are RFC 9457 problem details with a stable ``code``: an
unknown graph is ``404 unknown_dataset``, an unknown node ``404 unknown_node``, a bad spec
``422 spec_invalid`` / ``spec_unknown_field``, a bad analysis ``422 analysis_invalid``.

Endpoints:

- ``GET /v1/graphs`` → ``{items: [{name, version, graph_key, nodes, edges, embedding, ...}], next_cursor}``
- ``GET /v1/graphs/{name}`` → version, stats, which embedding, build parameters, dataset
- ``POST /v1/graphs/{name}/search[?version=V]`` ``{analysis, spec}`` → ``SearchResult.to_dict()``
  (``version``: the graph version a job pinned; default the current one)
- ``GET /v1/graphs/{name}/skeleton`` → ``Skeleton.to_dict()``
- ``GET /v1/graphs/{name}/nodes/{node_id}`` → provenance (take, bar, frames, augmentation)
- ``GET /v1/graphs/{name}/nodes/{node_id}/motion`` → the bar's motion (fps, root, rotations)
- ``GET /healthz`` → liveness, the loaded graph versions and the memory budget's use
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import numpy as np
from fastapi import Body, FastAPI, Query
from fastapi.responses import JSONResponse

from dancegraph import __version__
from dancegraph.errors import DanceGraphError
from dancegraph.spec import parse_spec
from dancegraph.store import ObjectStore
from services.common.problems import install as install_problem_handlers
from services.config import get_settings, object_store
from services.graphstore.client import LocalGraphStore, parse_analysis

log = logging.getLogger("dancegraph.graphstore")


def create_app(store: ObjectStore | None = None, warm_up: bool = False) -> FastAPI:
    """The graph-store app over ``store`` (default: the embedded object store, opened lazily).
    ``warm_up``: at start-up compile the search kernel and load every current graph with its
    models, logging any that cannot be loaded (the served app does)."""

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        if warm_up:
            from dancegraph import jit
            from dancegraph.graph import artifact, search  # noqa: F401  (registers its kernels)

            jit.warm_up(["search"])
            local = graphs()
            for name in artifact.list_graphs(local.store):
                try:
                    local.graph(name)
                except DanceGraphError as exc:
                    log.error("graph %s cannot be loaded: [%s] %s", name, exc.code, exc.message)
        yield

    app = FastAPI(
        title="DanceGraph graph store",
        version=__version__,
        description="Prebuilt motion graphs per dataset: search, node and clip data.",
        lifespan=lifespan,
    )
    install_problem_handlers(app)
    state: dict[str, LocalGraphStore] = {}

    def graphs() -> LocalGraphStore:
        if "local" not in state:
            settings = get_settings()
            state["local"] = LocalGraphStore(
                store or object_store(settings), settings.graphstore_memory_bytes
            )
        return state["local"]

    app.state.graphs = graphs

    @app.get("/healthz")
    def healthz() -> dict:
        return {"status": "ok", "loaded": graphs().loaded(), "memory": graphs().memory()}

    @app.get("/v1/graphs")
    def list_graphs() -> dict:
        return {"items": graphs().list_graphs(), "next_cursor": None}

    @app.get("/v1/graphs/{name}")
    def graph_info(name: str) -> dict:
        return graphs().graph_info(name)

    @app.post("/v1/graphs/{name}/search")
    def search(
        name: str,
        analysis: dict = Body(..., description="MusicAnalysis.to_dict() of the song"),
        spec: dict | None = Body(None, description="the constraint spec (dancegraph.spec.Spec)"),
        version: str | None = Query(None, max_length=100, description="graph version (pinned)"),
    ) -> JSONResponse:
        # the path's dataset wins over the spec's; both bodies are parsed once, here
        result = graphs().search(
            parse_analysis(analysis), parse_spec(spec, dataset=name), version=version
        )
        return JSONResponse(_jsonable(result.to_dict()))

    @app.get("/v1/graphs/{name}/skeleton")
    def skeleton(name: str) -> dict:
        return graphs().skeleton(name).to_dict()

    @app.get("/v1/graphs/{name}/nodes/{node_id}")
    def node(name: str, node_id: str) -> dict:
        return graphs().node(name, node_id)

    @app.get("/v1/graphs/{name}/nodes/{node_id}/motion")
    def node_motion(name: str, node_id: str) -> dict:
        motion = graphs().node_motion(name, node_id)
        return {
            "node": node_id,
            "fps": motion.fps,
            "frames": motion.n_frames,
            "root_positions": np.round(motion.root_positions, 6).tolist(),
            "rotations": np.round(motion.rotations, 6).tolist(),
        }

    return app


def _jsonable(obj):
    """Numpy scalars and arrays inside a result → plain JSON types."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


app = create_app(warm_up=get_settings().warm_up)
