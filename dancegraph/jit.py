"""Compiled kernels (numba): where their on-disk cache lives, and a warm-up that fills it safely.

A new process would otherwise spend ~25 s compiling the beat decoder, librosa's beat kernels and
the graph search on its first song. :func:`warm_up` compiles (or loads) all of them once; a worker
calls it at start, before its pool forks, so every child inherits the compiled code.

numba's cache is not safe when two processes compile the same gufunc at the same moment
(numba issue #10128: the ``.nbc`` files of one function and of its gufunc wrapper can come from
different processes, and the next load segfaults). Compilation into the shared cache therefore
happens under an inter-process file lock (:func:`compile_lock`).

Cache folder: ``NUMBA_CACHE_DIR`` when set, else ``$DANCEGRAPH_HOME/numba_cache``.
"""

from __future__ import annotations

import fcntl
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["cache_dir", "configure_cache", "compile_lock", "warm_up"]


def cache_dir() -> Path:
    """The folder numba caches compiled kernels in (created on first use)."""
    from dancegraph.paths import home_dir

    env = os.environ.get("NUMBA_CACHE_DIR")
    path = Path(env) if env else home_dir() / "numba_cache"
    path.mkdir(parents=True, exist_ok=True)
    return path


def configure_cache() -> Path:
    """Point numba's cache at :func:`cache_dir` for kernels decorated from now on (also reaches
    librosa's kernels when librosa is imported later, through ``NUMBA_CACHE_DIR``)."""
    import numba

    path = cache_dir()
    if not numba.config.CACHE_DIR:
        numba.config.CACHE_DIR = str(path)
    os.environ.setdefault("NUMBA_CACHE_DIR", numba.config.CACHE_DIR)
    return Path(numba.config.CACHE_DIR)


@contextmanager
def compile_lock() -> Iterator[None]:
    """Hold the cache folder's inter-process lock (blocks until other compiling processes end)."""
    lock_path = configure_cache() / ".compile.lock"
    with open(lock_path, "a+b") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


_warm: set[str] = set()
_warm_lock = threading.Lock()


def _warm_music() -> None:
    from dancegraph.music import beats

    beats.warm_up()


def _warm_search() -> None:
    from dancegraph.graph import search

    search.warm_up()


_WARMERS = {"music": _warm_music, "search": _warm_search}


def warm_up(music: bool = True, search: bool = True) -> None:
    """Compile or load the kernels a job uses — ``music``: beat decoding with librosa's kernels
    and the BeatNet model; ``search``: the graph search — under :func:`compile_lock`.

    Once per process and part: the entry points (``beats.track_beats``, ``search.search``) call
    it first, so no process compiles into the shared cache outside the lock. Cheap afterwards.
    """
    parts = [p for p, on in (("music", music), ("search", search)) if on and p not in _warm]
    if not parts:
        return
    with _warm_lock, compile_lock():
        for part in parts:
            if part in _warm:
                continue
            # marked first: the warm-up runs through the same guarded entry points
            _warm.add(part)
            try:
                _WARMERS[part]()
            except BaseException:
                _warm.discard(part)
                raise
