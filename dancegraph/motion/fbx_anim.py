"""Animated FBX takes: the first animation stack of an FBX → a :class:`Motion` on the file's rig.

Like :mod:`dancegraph.motion.ufbx_reader` the ufbx binding runs only in a child process
(``python -m dancegraph.motion.fbx_anim IN.fbx OUT.npz FPS``; a crash or a broken file is a
``MotionFileError`` ``fbx_invalid``): ufbx converts the scene to metres, Y up, evaluates it at
every frame of the stack (``FPS``, default the file's own frame rate) and writes each node's
world matrix. The parent reads the rig with :func:`dancegraph.motion.rig.load_rig` and turns
its joints' world matrices into the library's BVH convention
(:func:`dancegraph.motion.gltf_anim.motion_from_world`).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from dancegraph.errors import MotionFileError

READ_TIMEOUT_S = 300.0
#: Most frames a take is evaluated at (two hours at 120 fps).
MAX_FRAMES = 864_000


def read_fbx_motion(
    path: str | Path, *, fps: float | None = None, mapping: dict[str, str] | None = None
):
    """``(Motion, Rig)`` of an animated FBX take (see the module docstring).

    ``fps``: the sampling rate (default: the file's). Raises ``MotionFileError``
    (``fbx_invalid``, ``take_no_animation``) and the ``RigError`` codes of ``load_rig``.
    """
    from dancegraph.motion.gltf_anim import motion_from_world, take_rig

    path = Path(path)
    rig = take_rig(path, mapping, "fbx_invalid")
    with tempfile.TemporaryDirectory(prefix="dg-fbx-anim-") as tmp:
        out = Path(tmp) / "anim.npz"
        cmd = [sys.executable, "-m", "dancegraph.motion.fbx_anim", str(path), str(out)]
        try:
            proc = subprocess.run(
                [*cmd, str(fps or 0.0)], capture_output=True, text=True, timeout=READ_TIMEOUT_S
            )
        except subprocess.TimeoutExpired:
            raise MotionFileError(
                f"reading the animation took longer than {READ_TIMEOUT_S:g} s",
                path=path.name,
                code="fbx_invalid",
            ) from None
        if proc.returncode != 0 or not out.is_file():
            tail = (proc.stderr.strip().splitlines() or ["no message"])[-1]
            code = "take_no_animation" if "no animation" in tail else "fbx_invalid"
            raise MotionFileError(tail[:200], path=path.name, code=code)
        with np.load(out, allow_pickle=False) as data:
            names = [str(n) for n in data["names"]]
            world, rate = data["world"], float(data["fps"])
    index = {n: k for k, n in enumerate(names)}
    missing = [n for n in rig.skeleton.names if n not in index]
    if missing:
        raise MotionFileError(
            f"joints {missing[:3]} have no animated node", path=path.name, code="fbx_invalid"
        )
    cols = [index[n] for n in rig.skeleton.names]
    return motion_from_world(rig, world[:, cols], rate, path.name, "fbx_invalid"), rig


def _matrix(m) -> np.ndarray:
    out = np.eye(4)
    for k, col in enumerate((m.c0, m.c1, m.c2, m.c3)):
        out[:3, k] = (col.x, col.y, col.z)
    return out


def _evaluate(path: str, fps: float, keep: list) -> dict[str, np.ndarray]:  # pragma: no cover
    """Every named node's world matrix at every frame of the first animation stack. Every ufbx
    object is kept in ``keep`` (the binding crashes when a scene is freed before them)."""
    import ufbx

    scene = ufbx.load_file(
        path,
        target_axes=ufbx.axes_right_handed_y_up,
        target_unit_meters=1.0,
        space_conversion=ufbx.SpaceConversion.ADJUST_TRANSFORMS,
    )
    stacks = scene.anim_stacks
    keep.extend([scene, stacks])
    if len(stacks) == 0:
        raise SystemExit("the file holds no animation")
    stack = stacks[0]
    anim = stack.anim
    rate = fps or float(scene.settings.frames_per_second) or 30.0
    n = int(np.floor((stack.time_end - stack.time_begin) * rate + 1e-6)) + 1
    if n < 2 or n > MAX_FRAMES:
        raise SystemExit(f"the animation has {n} frames: no animation to read")
    keep.extend([stack, anim])
    names = None
    world = []
    for k in range(n):
        ev = ufbx.evaluate_scene(scene, anim, stack.time_begin + k / rate)
        nodes_list = ev.nodes
        nodes = [nodes_list[i] for i in range(len(nodes_list))]
        keep.extend([ev, nodes_list, nodes])
        named = [nd for nd in nodes if nd.name]
        names = names or [nd.name for nd in named]
        mats = [nd.node_to_world for nd in named]
        keep.extend(mats)
        world.append(np.stack([_matrix(m) for m in mats]))
    return {"names": np.array(names, dtype=str), "world": np.stack(world), "fps": np.array(rate)}


if __name__ == "__main__":  # pragma: no cover - the child process
    alive: list = []
    arrays = _evaluate(sys.argv[1], float(sys.argv[3]), alive)
    tmp = sys.argv[2] + ".tmp.npz"
    np.savez(tmp, **arrays)  # type: ignore[arg-type]  # numpy's stub types allow_pickle first
    Path(tmp).replace(sys.argv[2])
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)  # the binding can crash while its objects are garbage-collected at exit
