"""The dataset catalog the API validates specs against: the ``datasets`` table. Public
libraries (``tenant_id`` NULL) are filled from the graph store (which knows the built graphs)
when a name is not known yet; tenants' libraries are rows of their own
(``services.common.libraries``), and their graphs (``lib-…``) are never listed as public."""

from __future__ import annotations

import logging
import threading
import time

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services import jobs
from services.common import libraries
from services.models import Dataset

log = logging.getLogger("dancegraph.api")

_REFRESH_EVERY_S = 5.0  # a miss asks the graph store at most this often
_last_refresh = 0.0
# One refresh at a time per process: a burst of requests naming a dataset the table does not
# know yet waits for the one refresh, then reads the table, instead of each being refused.
_refresh_lock = threading.Lock()


def refresh_catalog(session: Session, graphstore) -> int:
    """Copy the graph store's list of built graphs into the catalog; returns how many it listed."""
    global _last_refresh
    _last_refresh = time.monotonic()
    if graphstore is None:
        return 0
    try:
        graphs = graphstore.list_graphs()
    except Exception as exc:  # the catalog still answers from the table when the store is down
        log.warning("graph store did not list graphs: %s", exc)
        return 0
    items = graphs.get("graphs", graphs.get("items", [])) if isinstance(graphs, dict) else graphs
    n = 0
    for g in items or []:
        if isinstance(g, str):
            g = {"name": g}
        if not isinstance(g, dict) or not g.get("name") or libraries.is_library_graph(g["name"]):
            continue
        stats = (
            g.get("stats")
            if isinstance(g.get("stats"), dict)
            else {
                k: v for k, v in g.items() if isinstance(v, int | float) and not isinstance(v, bool)
            }
        )
        try:
            with session.begin_nested():
                jobs.upsert_dataset(
                    session,
                    name=str(g["name"])[:64],
                    version=str(g.get("version") or "unversioned")[:64],
                    graph_key=g.get("artifact_key") or g.get("graph_key") or g.get("key"),
                    stats=stats,
                    licence=str(g.get("licence") or g.get("license") or ""),
                    embedding=str(g.get("embedding") or "descriptor")[:64],
                )
        except IntegrityError:  # another API process registered the same version just now
            pass
        n += 1
    session.commit()
    return n


def find_dataset(
    session: Session, name: str, graphstore, tenant_id: str | None = None
) -> Dataset | None:
    """The library a job of ``tenant_id`` would use for ``name`` (its own newest built version,
    else the public one; ``libraries.usable_row``), asking the graph store for public graphs on
    a miss (rate-limited). None: no such library for this tenant."""
    row = libraries.usable_row(session, tenant_id, name)
    if row is not None:
        return row
    with _refresh_lock:
        if time.monotonic() - _last_refresh > _REFRESH_EVERY_S:
            refresh_catalog(session, graphstore)
    return libraries.usable_row(session, tenant_id, name)  # what this or the awaited refresh found


def reset() -> None:
    """Forget the refresh clock (tests)."""
    global _last_refresh
    _last_refresh = 0.0
