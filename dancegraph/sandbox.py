"""Run a parser over an untrusted file in a child process held under memory, CPU and time limits.

A user's file (a rig, a take, an archive) may be built to crash a C extension, to loop forever
or to make a reader allocate gigabytes. :func:`run_sandboxed` runs the parsing function in a
fresh child process forked from a ``forkserver`` (a small single-threaded server that imported
the readers once, so a call costs a fork, not an interpreter start) and

- sets ``RLIMIT_AS`` (address space) and ``RLIMIT_CPU`` in the child before the function runs;
- waits at most ``wall_seconds`` and then kills the child's whole process group;
- returns the function's (picklable) result, or re-raises a ``DanceGraphError`` the function
  raised (same class, code, field and message), or raises :class:`SandboxError` with a ``code``:
  ``crashed`` (a signal, or an unexpected exception), ``timeout``, ``memory``, ``cpu``.

The calling thread never blocks longer than the wall-clock limit (plus a fork); a crashing
child cannot harm the parent, which shares no memory, threads or sockets with it. At most
:data:`MAX_CHILDREN` children run at once per process, so concurrent hostile uploads cannot
multiply the memory limit without bound; a call that waits longer than its wall-clock limit for
a free slot ends with ``timeout``.
"""

from __future__ import annotations

import importlib
import multiprocessing
import os
import resource
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any, TypeVar

from dancegraph.errors import DanceGraphError

T = TypeVar("T")

#: Modules the fork server imports once, so a child starts with the readers loaded (and with
#: the main module, which a child would otherwise import again on every call).
PRELOAD = (
    "__main__",
    "numpy",
    "scipy.spatial.transform",
    "dancegraph.motion.rig",
    "dancegraph.motion.gltf",
    "dancegraph.motion.bvh",
)
#: Children running at once per parent process.
MAX_CHILDREN = max(2, os.cpu_count() or 2)

_slots = threading.BoundedSemaphore(MAX_CHILDREN)
_context_lock = threading.Lock()
_context: Any = None


@dataclass(frozen=True)
class SandboxLimits:
    """Limits of one sandboxed call: address space (bytes), CPU time and wall-clock time (s)."""

    memory_bytes: int = 2 * 1024**3
    cpu_seconds: float = 30.0
    wall_seconds: float = 30.0


class SandboxError(DanceGraphError):
    """The sandboxed call did not finish: ``code`` is ``crashed``, ``timeout``, ``memory`` or
    ``cpu``; the message names the limit, never a path."""

    code = "crashed"
    status = 422


def _ctx():
    """The forkserver context, its server told to preload :data:`PRELOAD` (created once)."""
    global _context
    with _context_lock:
        if _context is None:
            ctx = multiprocessing.get_context("forkserver")
            ctx.set_forkserver_preload(list(PRELOAD))
            _context = ctx
        return _context


def _exception_state(exc: BaseException) -> tuple[str, str, dict] | None:
    """``(module, class name, attributes)`` of a ``DanceGraphError``, else None."""
    if not isinstance(exc, DanceGraphError):
        return None
    cls = type(exc)
    return cls.__module__, cls.__qualname__, dict(exc.__dict__)


def _rebuild(module: str, name: str, state: dict) -> DanceGraphError:
    """The child's ``DanceGraphError`` again, without calling its ``__init__`` (whose keyword-only
    arguments the default exception pickling loses)."""
    cls = getattr(importlib.import_module(module), name, None)
    if not (isinstance(cls, type) and issubclass(cls, DanceGraphError)):
        return SandboxError("the reader failed", code="crashed")
    exc = cls.__new__(cls)
    Exception.__init__(exc, state.get("message", ""))
    exc.__dict__.update(state)
    return exc


def _child(conn: Connection, limits: SandboxLimits, fn: Callable, args, kwargs) -> None:
    """The child's body: own process group, limits, the call, one message back."""
    os.setpgid(0, 0)
    resource.setrlimit(resource.RLIMIT_AS, (limits.memory_bytes, limits.memory_bytes))
    cpu = max(1, int(limits.cpu_seconds + 0.999))
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 1))
    try:
        message: tuple = ("ok", fn(*args, **kwargs))
    except MemoryError:
        message = ("limit", "memory")
    except BaseException as exc:  # noqa: BLE001 - every failure goes back as a message
        state = _exception_state(exc)
        message = ("raised", state) if state else ("limit", "crashed")
    try:
        conn.send(message)
    except MemoryError:
        conn.send(("limit", "memory"))
    conn.close()


_MESSAGES = {
    "crashed": "the file crashed its reader",
    "timeout": "reading the file took longer than {wall:g} s",
    "memory": "reading the file needed more than {mib} MiB of memory",
    "cpu": "reading the file needed more than {cpu:g} s of CPU time",
}


def _error(code: str, limits: SandboxLimits) -> SandboxError:
    text = _MESSAGES[code].format(
        wall=limits.wall_seconds, cpu=limits.cpu_seconds, mib=limits.memory_bytes // 2**20
    )
    return SandboxError(text, code=code)


def _kill_group(proc) -> None:
    for kill in (lambda: os.killpg(proc.pid, signal.SIGKILL), proc.kill):
        try:
            kill()
        except (ProcessLookupError, PermissionError, OSError):
            pass


def _exit_code(exitcode: int | None) -> str:
    """The error code of a child that ended without sending a message."""
    if exitcode == -signal.SIGXCPU:
        return "cpu"
    if exitcode == -signal.SIGKILL:  # the kernel's OOM killer (our own kill is a timeout)
        return "memory"
    return "crashed"


def run_sandboxed(
    fn: Callable[..., T], *args, limits: SandboxLimits = SandboxLimits(), **kwargs
) -> T:
    """``fn(*args, **kwargs)`` in a limited child process; its result (see the module docstring).

    ``fn`` must be a module-level function; arguments and result must pickle (pass paths, not
    open files). Raises the ``DanceGraphError`` ``fn`` raised, or :class:`SandboxError`.
    """
    deadline = time.monotonic() + limits.wall_seconds
    if not _slots.acquire(timeout=limits.wall_seconds):
        raise _error("timeout", limits)
    try:
        return _run(fn, args, kwargs, limits, deadline)
    finally:
        _slots.release()


def _run(fn: Callable, args, kwargs, limits: SandboxLimits, deadline: float):
    ctx = _ctx()
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, limits, fn, args, kwargs), daemon=True)
    proc.start()
    send.close()
    message, timed_out = None, False
    try:
        ready = wait([recv], timeout=max(0.0, deadline - time.monotonic()))
        if ready:
            try:
                message = recv.recv()
            except (EOFError, OSError):
                pass  # the child died without a (whole) message
        else:
            timed_out = True
    finally:
        recv.close()
        if message is not None:  # a child stuck on its way out is killed too
            proc.join(timeout=max(1.0, deadline - time.monotonic()))
        if proc.exitcode is None:
            _kill_group(proc)
        proc.join()
        exitcode = proc.exitcode
        proc.close()
    if message is None:
        raise _error("timeout" if timed_out else _exit_code(exitcode), limits)
    kind, value = message
    if kind == "ok":
        return value
    if kind == "raised":
        raise _rebuild(*value)
    raise _error(value, limits)
