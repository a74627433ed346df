"""The kernel warm-up: it fills the numba cache folder, and the compile lock serialises processes."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from dancegraph import jit
from services.worker import celery_app


def test_install_step_fills_the_cache_folder(tmp_path: Path):
    # a fresh process: `python -m dancegraph.jit` is what scripts/install.sh runs
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "nc"), "DANCEGRAPH_HOME": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-m", "dancegraph.jit"],
        env=env,
        check=True,
        timeout=600,
        capture_output=True,
        text=True,
    )
    assert "barpointer" in out.stdout and "music" in out.stdout and "search" in out.stdout
    names = {p.name for p in (tmp_path / "nc").rglob("*.nbi")}
    assert any("beat_track_dp" in n for n in names), names  # librosa's beat kernels
    assert any("beat_local_score" in n for n in names), names  # its cache=False one, cached
    assert any("_forward_py" in n for n in names), names  # the bar-pointer decoder
    assert any("_backtrack_py" in n for n in names), names
    assert any(n.startswith("_dp.") for n in names), names  # the graph search


def test_kernels_register_themselves():
    """jit imports no kernel module; importing one registers its warm-up."""
    code = (
        "import sys\nfrom dancegraph import jit\n"
        "assert not any(m in sys.modules for m in jit.KERNEL_MODULES), 'jit imported a kernel module'\n"
        "assert jit._registry == {}\n"
        "import dancegraph.music.beats, dancegraph.graph.search\n"
        "print(sorted(jit._registry))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True
    )
    assert out.stdout.split() == ["['barpointer',", "'music',", "'search']"]


def test_no_kernel_path_skips_the_lock():
    """A process that did not warm up at start still compiles only under the lock: with the lock
    held here, a child calling the decoder (or the search's data terms) waits for it."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(jit.configure_cache())}
    calls = {
        "decoder": "from dancegraph.music import barpointer\nimport numba, numpy as np\n"
        "print('ready', flush=True)\nbarpointer.warm_up()\n",
        "search": "from dancegraph.graph import problem\nimport numpy as np\n"
        "from dancegraph.spec import Spec\n"
        "g = type('G', (), {'style': np.zeros((2, 32), np.float32), "
        "'signature': np.zeros(2, np.uint8)})()\n"
        "print('ready', flush=True)\n"
        "problem.data_costs(g, np.zeros((1, 32)), np.zeros((1, 256)), Spec())\n",
    }
    for name, code in calls.items():
        with jit.compile_lock():
            child = subprocess.Popen(
                [sys.executable, "-c", code + "print('done')"],
                stdout=subprocess.PIPE,
                text=True,
                env=env,
            )
            assert child.stdout.readline().strip() == "ready", name  # imported, kernel next
            time.sleep(4.0)  # without the lock the kernel runs and the child ends by now
            assert child.poll() is None, f"{name}: ran its kernel while the lock was held"
        out, _ = child.communicate(timeout=300)
        assert child.returncode == 0 and out.strip().endswith("done"), name


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
