"""Motion-test fixtures: the project's test rigs and a real salsa clip to retarget."""

from __future__ import annotations

from pathlib import Path

import pytest

from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.contacts import clean_foot_skate
from dancegraph.motion.fbx import fbx_available
from dancegraph.motion.skeleton import Motion
from tests.motion.rigs import make_rigs


@pytest.fixture(scope="session")
def rig_dir(tmp_path_factory) -> Path:
    """Every test rig (FBX/GLB ones only where Blender is installed), written once per session."""
    return make_rigs(tmp_path_factory.mktemp("rigs"), blender=fbx_available())


@pytest.fixture(scope="session")
def salsa_clip(salsa_dir: Path) -> Motion:
    """20 s of real salsa (CMU 60_01 at its true 60 fps), feet cleaned as a rendered dance's are."""
    motion = read_bvh(salsa_dir / "60_01_scaled.bvh", fps=60).slice(0, 1200)
    cleaned, _ = clean_foot_skate(motion)
    return cleaned
