"""The kernel warm-up: it fills the numba cache folder, and the compile lock serialises processes."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from dancegraph import jit
from services.worker import celery_app


def test_warm_up_fills_the_cache_folder(tmp_path: Path):
    # a fresh process (the configured cache applies to kernels compiled after it is set)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "nc"), "DANCEGRAPH_HOME": str(tmp_path)}
    subprocess.run(
        [sys.executable, "-c", "from dancegraph import jit; jit.warm_up()"],
        env=env,
        check=True,
        timeout=600,
    )
    names = {p.name for p in (tmp_path / "nc").rglob("*.nbi")}
    assert any("beat_track_dp" in n for n in names), names  # librosa's beat kernels
    assert any("viterbi" in n for n in names), names  # the bar-pointer decoder
    assert any(n.startswith("_dp.") for n in names), names  # the graph search


def test_compile_lock_excludes_other_processes():
    # the child must lock the same folder as this process (whose numba may already be configured)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(jit.configure_cache())}
    code = (
        "import time\nfrom dancegraph import jit\n"
        "t = time.time()\nwith jit.compile_lock():\n    print(time.time() - t)\n"
    )
    with jit.compile_lock():
        child = subprocess.Popen(
            [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=env
        )
        time.sleep(1.5)
        assert child.poll() is None  # still waiting for the lock we hold
    out, _ = child.communicate(timeout=60)
    assert child.returncode == 0 and float(out) >= 1.0


def test_worker_warms_up_before_the_pool_forks():
    from celery import signals

    receivers = [r[1]() for r in signals.worker_init.receivers]
    assert celery_app._warm_up in receivers
