"""Compiled kernels (numba): a registry of warm-ups, their on-disk cache, and the lock that
makes compiling into that cache safe.

A new process would otherwise spend ~25 s compiling the beat decoder, librosa's beat kernels and
the graph search on its first song. Each module that owns kernels registers a warm-up when it is
imported (:func:`register`: run the kernels once on a tiny input); this module imports none of
them. A process that serves songs — the worker (before its pool forks, so every child inherits
the compiled code), the graph store, the CLI commands that analyse or search — imports what it
uses and calls :func:`warm_up` at start.

numba's cache is not safe when two processes compile the same gufunc at the same moment
(numba issue #10128: the ``.nbc`` files of one function and of its gufunc wrapper can come from
different processes, and the next load segfaults). Every warm-up therefore runs under an
inter-process file lock (:func:`compile_lock`), and the kernels' entry points call
:func:`ensure` (a set lookup once warm), so a process that did not warm up at start — a library
user, a test — still compiles only under the lock: no path reaches a kernel outside it.

Cache folder: ``dancegraph.paths.kernel_cache_dir()`` (``NUMBA_CACHE_DIR`` when set).
Run ``python -m dancegraph.jit`` to compile every kernel once (the install step does).
"""

from __future__ import annotations

import fcntl
import importlib
import os
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import Any

__all__ = [
    "configure_cache",
    "compile_lock",
    "register",
    "ensure",
    "warm_up",
    "warm_kernels",
    "import_cached",
]

# the modules that register kernels (imported by warm_kernels)
KERNEL_MODULES = (
    "dancegraph.music.barpointer",
    "dancegraph.music.beats",
    "dancegraph.graph.search",
)

_registry: dict[str, Callable[[], None]] = {}
_warm: set[str] = set()
_warm_lock = threading.RLock()


def configure_cache() -> Path:
    """Point numba's cache at ``kernel_cache_dir()`` for kernels decorated from now on (also
    reaches librosa's kernels when librosa is imported later, through ``NUMBA_CACHE_DIR``)."""
    from numba.core import config  # its settings are module attributes set at run time

    from dancegraph.paths import kernel_cache_dir

    if not config.CACHE_DIR:  # type: ignore[attr-defined]
        config.CACHE_DIR = str(kernel_cache_dir())  # type: ignore[attr-defined]
    path = Path(config.CACHE_DIR)  # type: ignore[attr-defined]
    os.environ.setdefault("NUMBA_CACHE_DIR", str(path))
    path.mkdir(parents=True, exist_ok=True)
    return path


_held = threading.local()


@contextmanager
def compile_lock() -> Iterator[None]:
    """Hold the cache folder's inter-process lock (blocks until other compiling processes end).
    Re-entrant within a thread (a warm-up may reach another part's warm-up)."""
    if getattr(_held, "depth", 0):
        _held.depth += 1
        try:
            yield
        finally:
            _held.depth -= 1
        return
    lock_path = configure_cache() / ".compile.lock"
    with open(lock_path, "a+b") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        _held.depth = 1
        try:
            yield
        finally:
            _held.depth = 0
            fcntl.flock(fh, fcntl.LOCK_UN)


def register(name: str, warm: Callable[[], None]) -> None:
    """Register ``warm`` (compile or load ``name``'s kernels by running them once; it may call
    :func:`ensure` for its own name) — called by the owning module at import."""
    _registry[name] = warm


def ensure(name: str) -> None:
    """Make sure ``name``'s kernels are compiled in this process, warming them up under the lock
    if not yet (a set lookup once warm). Kernel entry points call this before a kernel runs."""
    if name not in _warm:
        warm_up([name])


def warm_up(names: Iterable[str] | None = None) -> list[str]:
    """Compile or load the kernels of ``names`` (default: every registered part) under
    :func:`compile_lock`, once per process and part; returns the parts warmed by this call.
    KeyError for a name no imported module registered."""
    wanted = list(_registry) if names is None else list(names)
    todo = [n for n in wanted if n not in _warm]
    if not todo:
        return []
    warmers = [(n, _registry[n]) for n in todo]
    done = []
    with _warm_lock, compile_lock():
        for name, warm in warmers:
            if name in _warm:
                continue
            _warm.add(name)  # first: the warm-up runs through the entry points that call ensure
            try:
                warm()
            except BaseException:
                _warm.discard(name)
                raise
            done.append(name)
    return done


def import_cached(module: str) -> ModuleType:
    """Import ``module`` with numba's ``guvectorize`` caching forced on, under the compile lock.

    librosa declares one beat-tracking gufunc ``cache=False`` (``librosa.beat``), so every
    process compiled it again (about 2.5 s of CPU per start): caching gufuncs races when two
    processes write the cache at once (numba issue #10128), which the lock rules out here. A
    module already imported is returned as it is.
    """
    if module in sys.modules:
        return sys.modules[module]
    import numba

    original = numba.guvectorize

    def cached(*args: Any, **kwargs: Any) -> Any:
        return original(*args, **{**kwargs, "cache": True})

    with compile_lock():
        numba.guvectorize = cached
        try:
            return importlib.import_module(module)
        finally:
            numba.guvectorize = original


def warm_kernels(modules: Iterable[str] = KERNEL_MODULES) -> list[str]:
    """Import ``modules`` (default: every kernel module) and warm every registered part: what a
    process calls at start (install step and worker: all; the CLI: what its command runs)."""
    for module in modules:
        importlib.import_module(module)
    return warm_up()


if __name__ == "__main__":
    import time

    from dancegraph import jit  # the registry lives in the imported module, not in __main__

    t0 = time.perf_counter()
    parts = jit.warm_kernels()
    print(
        f"kernels ready ({', '.join(parts) or 'already warm'}) in {time.perf_counter() - t0:.1f} s"
    )
