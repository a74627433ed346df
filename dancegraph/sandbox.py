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

A call made inside a sandboxed child (a reader that sandboxes its own parse, called from a
sandboxed parse) runs inline, under the child's limits.

The calling thread never blocks longer than the wall-clock limit (plus a fork); a crashing
child cannot harm the parent, which shares no memory, threads or sockets with it. At most
:data:`MAX_CHILDREN` children run at once per process, so concurrent hostile uploads cannot
multiply the memory limit without bound; a call that waits longer than its wall-clock limit for
a free slot ends with ``busy`` (the server's state, not the file's: HTTP 503).
"""

from __future__ import annotations

import importlib
import io
import multiprocessing
import os
import resource
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing import context, forkserver, popen_forkserver, reduction, spawn, util
from multiprocessing.connection import Connection, wait
from typing import Any, TypeVar

from dancegraph.errors import DanceGraphError

T = TypeVar("T")

#: Modules the fork server imports once, so a child starts with the readers loaded.
PRELOAD = (
    "numpy",
    "scipy.spatial.transform",
    "dancegraph.motion.rig",
    "dancegraph.motion.gltf",
    "dancegraph.motion.bvh",
)
#: Children running at once per parent process.
MAX_CHILDREN = max(2, os.cpu_count() or 2)

_slots = threading.BoundedSemaphore(MAX_CHILDREN)
_inside = False  # True in a sandboxed child: a nested call runs inline, under its limits
_context_lock = threading.Lock()
_context: Any = None
_context_pid = 0  # the process whose fork server is up
#: Longest wait for the fork server to start and import :data:`PRELOAD`.
STARTUP_S = 120.0


def _forget_fork_server() -> None:
    """In a child ``os.fork``-ed from a process that started the fork server (a Celery pool
    worker): forget that server (the stdlib would ``waitpid`` on a process that is not its
    child); the child starts its own on its first call."""
    server: Any = forkserver._forkserver  # type: ignore[attr-defined]  # the stdlib's singleton
    if server._forkserver_alive_fd is not None:
        try:
            os.close(server._forkserver_alive_fd)
        except OSError:
            pass
    server._forkserver_address = None
    server._forkserver_alive_fd = None
    server._forkserver_pid = None
    server._lock = threading.Lock()


os.register_at_fork(after_in_child=_forget_fork_server)


class _Popen(popen_forkserver.Popen):
    """The stdlib's forkserver launch (Python 3.11) with a fresh authkey of the stdlib's type
    for the child (a Celery (billiard) pool worker's own key is billiard's type, which refuses
    to be pickled for a multiprocessing child) and without the caller's main module. Used
    directly, not through ``Process.start``, which refuses children to a daemonic process (a
    pool worker is one)."""

    def _launch(self, process_obj):
        process_obj.authkey = os.urandom(32)
        prep_data = spawn.get_preparation_data(process_obj._name)
        prep_data["authkey"] = process_obj.authkey
        # nor the caller's main module: the child would import it again on every call (an API
        # process's: hundreds of milliseconds; the fork server never preloads it in 3.11)
        prep_data.pop("init_main_from_path", None)
        prep_data.pop("init_main_from_name", None)
        buf = io.BytesIO()
        context.set_spawning_popen(self)
        try:
            reduction.dump(prep_data, buf)
            reduction.dump(process_obj, buf)
        finally:
            context.set_spawning_popen(None)
        self.sentinel, w = forkserver.connect_to_new_process(self._fds)
        _parent_w = os.dup(w)
        self.finalizer = util.Finalize(self, util.close_fds, (_parent_w, self.sentinel))
        with open(w, "wb", closefd=True) as f:
            f.write(buf.getbuffer())
        self.pid = forkserver.read_signed(self.sentinel)


@dataclass(frozen=True)
class SandboxLimits:
    """Limits of one sandboxed call: address space (bytes), CPU time and wall-clock time (s)."""

    memory_bytes: int = 2 * 1024**3
    cpu_seconds: float = 30.0
    wall_seconds: float = 30.0


class SandboxError(DanceGraphError):
    """The sandboxed call did not finish: ``code`` is ``crashed``, ``timeout``, ``memory`` or
    ``cpu`` (the file's doing: 422), or ``busy`` (no free slot: 503); the message names the
    limit, never a path."""

    code = "crashed"
    status = 422

    def __init__(self, message: str, *, code: str):
        super().__init__(message, code=code)
        self.status = 503 if code == "busy" else 422


def _ready() -> None:
    """A child's first call in a process: proves the fork server has loaded :data:`PRELOAD`."""


def _ctx():
    """The forkserver context, its server started and its :data:`PRELOAD` imported (once per
    process, before any call's wall clock starts: the start is not the file's time)."""
    global _context, _context_pid
    with _context_lock:
        if _context is None:
            _context = multiprocessing.get_context("forkserver")
            _context.set_forkserver_preload(list(PRELOAD))
        if _context_pid != os.getpid():
            start = SandboxLimits(wall_seconds=STARTUP_S, cpu_seconds=STARTUP_S)
            _run(_context, _ready, (), {}, start, time.monotonic() + STARTUP_S)
            _context_pid = os.getpid()
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
    global _inside
    _inside = True
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

    ``fn`` must be a module-level function of an importable module (not of a script run as
    ``__main__``); arguments and result must pickle (pass paths, not open files). Raises the ``DanceGraphError`` ``fn`` raised, or :class:`SandboxError`.
    Inside a sandboxed child ``fn`` runs inline, under that child's limits.
    """
    if _inside:
        return fn(*args, **kwargs)
    ctx = _ctx()
    deadline = time.monotonic() + limits.wall_seconds
    if not _slots.acquire(timeout=limits.wall_seconds):
        raise SandboxError(
            f"all {MAX_CHILDREN} sandbox slots stayed busy for {limits.wall_seconds:g} s",
            code="busy",
        )
    try:
        return _run(ctx, fn, args, kwargs, limits, deadline)
    finally:
        _slots.release()


def _run(ctx, fn: Callable, args, kwargs, limits: SandboxLimits, deadline: float):
    recv, send = ctx.Pipe(duplex=False)
    child = _Popen(ctx.Process(target=_child, args=(send, limits, fn, args, kwargs)))
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
            child.wait(timeout=max(1.0, deadline - time.monotonic()))
        if child.poll() is None:
            _kill_group(child)
        exitcode = child.wait()
        child.close()
    if message is None:
        raise _error("timeout" if timed_out else _exit_code(exitcode), limits)
    kind, value = message
    if kind == "ok":
        return value
    if kind == "raised":
        raise _rebuild(*value)
    raise _error(value, limits)
