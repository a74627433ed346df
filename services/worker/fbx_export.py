"""One warm Blender per worker process for FBX export (Blender takes seconds to start).

``dancegraph.motion.fbx.shared_exporter()`` is started on first use in a pool child and closed
when the child exits (``worker_process_shutdown``), so an ``fbx``-queue worker pays Blender's
start-up once per process, not once per file.
"""

from __future__ import annotations

from pathlib import Path


def export(bvh: Path, fbx: Path, *, fps: float | None = None) -> dict:
    """Convert one BVH to FBX with this process's warm exporter (restarted if it died)."""
    from dancegraph.motion.fbx import shared_exporter

    return shared_exporter().convert(bvh, fbx, fps=fps)


def export_glb(glb: Path, fbx: Path, *, fps: float, frames: int) -> dict:
    """Convert an animated GLB (a couple's ``couple.glb``) to one FBX of all its armatures with
    this process's warm exporter (``FbxExporter.glb_to_fbx``)."""
    from dancegraph.motion.fbx import shared_exporter

    return shared_exporter().glb_to_fbx(glb, fbx, fps=fps, frames=frames)


def close_exporter() -> None:
    """Stop this process's Blender child, if one was started."""
    import sys

    fbx = sys.modules.get("dancegraph.motion.fbx")
    if fbx is not None and getattr(fbx, "_shared", None) is not None:
        fbx._shared.close()
