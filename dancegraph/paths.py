"""Where DanceGraph finds shared data and keeps its own (overridable by environment variables).

- ``DANCEGRAPH_SHARED``: the shared datasets folder (default: ``../shared`` beside the repo).
- ``DANCEGRAPH_STORE_URL``: the object store, ``s3://bucket/prefix`` (default: the folder below).
- ``DANCEGRAPH_STORE_ROOT``: the filesystem object store root, or the S3 store's local scratch
  and cache (default: ``$DANCEGRAPH_HOME/store``).
- ``DANCEGRAPH_HOME``: the working folder of the embedded default — object store, SQLite
  database, broker folder, models (default: ``./var`` in the current directory).
"""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def shared_dir() -> Path:
    """The shared datasets root (it holds ``datasets/`` and ``reference/``); may not exist."""
    return Path(os.environ.get("DANCEGRAPH_SHARED", REPO_ROOT.parent / "shared")).resolve()


def home_dir() -> Path:
    """The embedded default's working folder, created on first use."""
    home = Path(os.environ.get("DANCEGRAPH_HOME", Path.cwd() / "var")).resolve()
    home.mkdir(parents=True, exist_ok=True)
    return home


def store_dir() -> Path:
    """Root of the filesystem object store of the embedded default."""
    return Path(os.environ.get("DANCEGRAPH_STORE_ROOT", home_dir() / "store")).resolve()


def default_store():
    """The object store the environment names: ``DANCEGRAPH_STORE_URL`` (S3, ``store_dir()`` as
    its scratch) or the folder ``store_dir()``."""
    from dancegraph.store import open_store

    return open_store(os.environ.get("DANCEGRAPH_STORE_URL") or store_dir(), store_dir())
