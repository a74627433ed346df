"""``dancegraph.sandbox``: a child that crashes, hangs, allocates or spins ends in a coded
``SandboxError``; the parent lives on and keeps no thread or child behind."""

from __future__ import annotations

import ctypes
import os
import threading
import time

import pytest

from dancegraph.errors import MotionFileError
from dancegraph.motion.rig import RigError
from dancegraph.sandbox import SandboxError, SandboxLimits, run_sandboxed

SHORT = SandboxLimits(memory_bytes=1024**3, cpu_seconds=2.0, wall_seconds=3.0)


def _add(a: int, b: int = 0) -> dict:
    return {"sum": a + b, "pid": os.getpid()}


def _segfault() -> None:
    ctypes.string_at(0)


def _hang() -> None:
    while True:
        time.sleep(0.1)


def _spin() -> None:
    while True:
        pass


def _allocate() -> bytes:
    return b"x" * (4 * 1024**3)


def _hang_with_grandchild(marker: str) -> None:
    pid = os.fork()
    if pid == 0:
        while True:
            time.sleep(0.1)
    with open(marker, "w") as fh:
        fh.write(str(pid))
    _hang()


def _rig_error() -> None:
    raise RigError("two joints are named 'a'", code="rig_duplicate_joint", field="a")


def _motion_error() -> None:
    raise MotionFileError("bad frame", path="take.bvh", line=7, code="bvh_syntax")


def _bug() -> None:
    raise KeyError("/srv/store/secret/path")


def test_result_comes_back_from_another_process():
    out = run_sandboxed(_add, 2, b=3, limits=SHORT)
    assert out["sum"] == 5 and out["pid"] != os.getpid()


@pytest.mark.parametrize(
    "fn,code",
    [(_segfault, "crashed"), (_hang, "timeout"), (_spin, "cpu"), (_allocate, "memory")],
)
def test_failures_end_in_a_coded_error(fn, code):
    threads = threading.active_count()
    # the CPU limit is reached long before the wall clock's, even on a busy machine
    limits = SandboxLimits(1024**3, 1.0, 30.0) if code == "cpu" else SHORT
    with pytest.raises(SandboxError) as info:
        run_sandboxed(fn, limits=limits)
    assert info.value.code == code and info.value.status == 422
    assert "/" not in info.value.message
    assert threading.active_count() == threads
    assert run_sandboxed(_add, 1, limits=SHORT)["sum"] == 1  # the parent is unharmed


def test_timeout_kills_the_whole_process_group(tmp_path):
    marker = tmp_path / "grandchild"
    with pytest.raises(SandboxError) as info:
        run_sandboxed(_hang_with_grandchild, str(marker), limits=SHORT)
    assert info.value.code == "timeout"
    pid = int(marker.read_text())
    for _ in range(50):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        pytest.fail("the grandchild outlived the sandbox")


def test_library_errors_come_back_as_themselves():
    with pytest.raises(RigError) as rig:
        run_sandboxed(_rig_error, limits=SHORT)
    assert (rig.value.code, rig.value.field) == ("rig_duplicate_joint", "a")
    assert rig.value.message == "two joints are named 'a'" and rig.value.status == 422
    with pytest.raises(MotionFileError) as motion:
        run_sandboxed(_motion_error, limits=SHORT)
    assert (motion.value.code, motion.value.line, motion.value.path) == (
        "bvh_syntax",
        7,
        "take.bvh",
    )
    assert str(motion.value) == "take.bvh:7: bad frame"


def _in_a_daemon(conn) -> None:
    try:
        conn.send(run_sandboxed(_add, 20, b=22, limits=SHORT)["sum"])
    except BaseException as exc:  # noqa: BLE001 - reported to the test
        conn.send(repr(exc))


def test_works_in_a_celery_pool_worker():
    """A Celery pool worker (billiard's daemonic process, forked after this one started its
    fork server) can still sandbox: its own server, no 'daemonic processes' refusal, its
    billiard authkey not in the way."""
    import billiard

    run_sandboxed(_add, 1, limits=SHORT)  # this process's fork server is up
    ctx = billiard.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    worker = ctx.Process(target=_in_a_daemon, args=(send,), daemon=True)
    worker.start()
    assert recv.poll(60), "the daemonic worker did not answer"
    assert recv.recv() == 42
    worker.join(10)


def test_a_call_finding_every_slot_taken_is_busy():
    """Concurrent calls beyond ``MAX_CHILDREN`` wait for a slot; past their wall clock: busy."""
    from dancegraph import sandbox

    hold = SandboxLimits(1024**3, 30.0, 4.0)
    threads = [
        threading.Thread(
            target=lambda: pytest.raises(SandboxError, run_sandboxed, _hang, limits=hold)
        )
        for _ in range(sandbox.MAX_CHILDREN)
    ]
    for t in threads:
        t.start()
    while sandbox._slots._value:  # every slot taken by a hanging child
        time.sleep(0.05)
    with pytest.raises(SandboxError) as info:
        run_sandboxed(_add, 1, limits=SandboxLimits(1024**3, 1.0, 0.5))
    assert info.value.code == "busy" and info.value.status == 503
    for t in threads:
        t.join()


def test_an_unexpected_exception_is_a_crash_without_its_text():
    with pytest.raises(SandboxError) as info:
        run_sandboxed(_bug, limits=SHORT)
    assert info.value.code == "crashed" and "secret" not in info.value.message
