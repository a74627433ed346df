"""Shared test fixtures: the shared datasets folder and per-test working folders."""

from __future__ import annotations

from pathlib import Path

import pytest

from dancegraph.paths import shared_dir

# Compiled kernels: the per-user cache (dancegraph.paths.kernel_cache_dir) that the install step
# filled, shared by the test process and every worker it starts whatever their DANCEGRAPH_HOME.


@pytest.fixture(scope="session")
def shared() -> Path:
    """The shared datasets root; tests that need it are skipped where it is absent."""
    root = shared_dir()
    if not (root / "datasets").is_dir():
        pytest.skip(f"shared datasets not found at {root} (set DANCEGRAPH_SHARED)")
    return root


@pytest.fixture(scope="session")
def salsa_dir(shared: Path) -> Path:
    return shared / "datasets" / "mocap" / "cmu-salsa"


@pytest.fixture(scope="session")
def modern_dir(shared: Path) -> Path:
    return shared / "datasets" / "mocap" / "cmu-modern"


@pytest.fixture(scope="session")
def cc_music_dir(shared: Path) -> Path:
    return shared / "datasets" / "music" / "cc"


@pytest.fixture(scope="session")
def nonmusic_dir(shared: Path) -> Path:
    return shared / "datasets" / "music" / "nonmusic"


@pytest.fixture()
def home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A fresh DANCEGRAPH_HOME for one test."""
    monkeypatch.setenv("DANCEGRAPH_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("DANCEGRAPH_STORE_ROOT", raising=False)
    return tmp_path / "home"
