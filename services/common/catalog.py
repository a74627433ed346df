"""The dataset catalog the API validates specs against: the ``datasets`` table, filled from the
graph store (which knows the built graphs) when a name is not known yet."""

from __future__ import annotations

import logging
import threading
import time

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services import jobs
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
        if not isinstance(g, dict) or not g.get("name"):
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


def find_dataset(session: Session, name: str, graphstore) -> Dataset | None:
    """The catalog entry of ``name``, asking the graph store on a miss (rate-limited)."""
    row = jobs.get_dataset(session, name)
    if row is not None:
        return row
    with _refresh_lock:
        if time.monotonic() - _last_refresh > _REFRESH_EVERY_S:
            refresh_catalog(session, graphstore)
    return jobs.get_dataset(session, name)  # what this refresh, or the one waited for, found


def reset() -> None:
    """Forget the refresh clock (tests)."""
    global _last_refresh
    _last_refresh = 0.0
