"""Where DanceGraph finds shared data and keeps its own (overridable by environment variables).

- ``DANCEGRAPH_HOME``: the data folder — object store (datasets, graphs, results), the embedded
  default's SQLite database and broker folder. Default: the per-user data folder
  (``platformdirs``: ``~/.local/share/dancegraph`` on Linux, ``~/Library/Application
  Support/dancegraph`` on macOS), so every working folder sees the same datasets.
- ``DANCEGRAPH_STORE_URL``: the object store, ``s3://bucket/prefix`` (default: the folder below).
- ``DANCEGRAPH_STORE_ROOT``: the filesystem object store root, or the S3 store's local scratch
  and cache (default: ``$DANCEGRAPH_HOME/store``).
- ``NUMBA_CACHE_DIR``: the compiled-kernel cache (default: the per-user cache folder's
  ``numba``, e.g. ``~/.cache/dancegraph/numba``): rebuildable, shared by every data folder, so
  a scratch ``DANCEGRAPH_HOME`` does not compile the kernels again.
- ``DANCEGRAPH_SHARED``: the shared datasets folder (default: ``../shared`` beside the repo).
"""

from __future__ import annotations

import os
from pathlib import Path

import platformdirs

REPO_ROOT = Path(__file__).resolve().parent.parent
APP_NAME = "dancegraph"


def shared_dir() -> Path:
    """The shared datasets root (it holds ``datasets/`` and ``reference/``); may not exist."""
    return Path(os.environ.get("DANCEGRAPH_SHARED", REPO_ROOT.parent / "shared")).resolve()


def home_dir() -> Path:
    """The data folder (``DANCEGRAPH_HOME``, else the per-user data folder), created on first use."""
    env = os.environ.get("DANCEGRAPH_HOME")
    home = Path(env if env else platformdirs.user_data_dir(APP_NAME, appauthor=False)).resolve()
    home.mkdir(parents=True, exist_ok=True)
    return home


def kernel_cache_dir() -> Path:
    """The compiled-kernel cache (``NUMBA_CACHE_DIR``, else the per-user cache folder's
    ``numba``); not created here (numba and ``jit.compile_lock`` create it when they write)."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return Path(env).resolve()
    return (Path(platformdirs.user_cache_dir(APP_NAME, appauthor=False)) / "numba").resolve()


def store_dir() -> Path:
    """Root of the filesystem object store of the embedded default."""
    return Path(os.environ.get("DANCEGRAPH_STORE_ROOT", home_dir() / "store")).resolve()


def default_store():
    """The object store the environment names: ``DANCEGRAPH_STORE_URL`` (S3, ``store_dir()`` as
    its scratch) or the folder ``store_dir()``."""
    from dancegraph.store import open_store

    return open_store(os.environ.get("DANCEGRAPH_STORE_URL") or store_dir(), store_dir())
