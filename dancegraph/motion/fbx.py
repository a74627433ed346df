"""FBX export through Blender, run as a separate process (Blender is GPL; ``bpy`` pins numpy<2).

DanceGraph never imports ``bpy``. A child process runs ``blender_worker.py`` under the Python of
Blender's own virtual environment and writes FBX files on request (a JSON-lines protocol on its
stdin/stdout, see that script): a rig file posed by a dance whose joint rotations DanceGraph
computed, keyed in bulk. A BVH is converted the same way: DanceGraph's reader reads it, its rest
pose (one frame) is the rig, its frames the dance. :class:`FbxExporter` keeps one such child warm and reuses it
for every file, because starting Blender costs seconds while a short clip converts in a fraction
of one. :func:`bvh_to_fbx` uses one shared exporter per process.

The written FBX: the BVH's skeleton as an armature (one FBX node per BVH joint, same names and
hierarchy, end sites dropped), its animation baked on every frame, the first frame at t = 0,
exactly as many frames as the BVH, the BVH's frame rate (a 6-decimal ``Frame Time`` such as
0.033333 is read as 30 fps), Y up, -Z forward, lengths in metres (``UnitScaleFactor`` 100).

Blender's Python is found by the environment variable ``DANCEGRAPH_BLENDER_PYTHON``, else at
``<repo>/.venv-blender/bin/python`` (made by ``scripts/install-blender.sh``).
"""

from __future__ import annotations

import atexit
import collections
import json
import os
import queue
import subprocess
import tempfile
import threading
import time
import weakref
from pathlib import Path

import numpy as np

from dancegraph.errors import DanceGraphError, MotionFileError
from dancegraph.motion.bvh import read_bvh, write_bvh
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.skeleton import Motion
from dancegraph.paths import REPO_ROOT

WORKER_SCRIPT = Path(__file__).with_name("blender_worker.py")
DEFAULT_START_TIMEOUT_S = 180.0  # a cold Blender import takes 2-5 s; a loaded machine much more
DEFAULT_CONVERT_TIMEOUT_S = 600.0  # a 15-minute song at 60 fps is about 54k frames
FPS_SNAP_TOLERANCE = 1e-3  # relative
DEFAULT_MAX_JOBS = 100  # files per Blender child before a fresh one (Blender's memory grows)


class FbxError(DanceGraphError):
    """FBX export failed (``fbx_export_failed``) or Blender is not installed (``fbx_unavailable``)."""

    code = "fbx_export_failed"
    status = 500


def snap_fps(fps: float) -> float:
    """A rate within 0.1 % of a whole number becomes that number (a BVH ``Frame Time`` printed
    to 6 decimals, 0.033333, reads as 30.0003 fps); 29.97 stays 29.97."""
    nearest = round(fps)
    if nearest > 0 and abs(fps - nearest) <= FPS_SNAP_TOLERANCE * nearest:
        return float(nearest)
    return fps


def blender_python() -> Path:
    """The Python interpreter that has ``bpy``: ``$DANCEGRAPH_BLENDER_PYTHON`` or the repo's venv."""
    configured = os.environ.get("DANCEGRAPH_BLENDER_PYTHON")
    if configured:
        return Path(configured)
    return REPO_ROOT / ".venv-blender" / "bin" / "python"


def fbx_available() -> bool:
    """Whether Blender's Python is where :func:`blender_python` says (not whether it starts)."""
    path = blender_python()
    return path.is_file() and os.access(path, os.X_OK)


class FbxExporter:
    """One warm Blender child process converting BVH files to FBX, one request at a time.

    Thread-safe (requests are serialised). The child starts on the first :meth:`convert` and is
    restarted after it dies or times out, and after ``max_jobs`` files (default
    ``$DANCEGRAPH_FBX_MAX_JOBS`` or 100), so a long-lived worker never carries a Blender that has
    grown with every scene it loaded. Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        python: str | os.PathLike | None = None,
        *,
        start_timeout_s: float = DEFAULT_START_TIMEOUT_S,
        convert_timeout_s: float | None = None,
        max_jobs: int | None = None,
    ):
        self.python = Path(python) if python is not None else blender_python()
        self.max_jobs = max(
            1, max_jobs or int(os.environ.get("DANCEGRAPH_FBX_MAX_JOBS", 0) or DEFAULT_MAX_JOBS)
        )
        self._jobs = 0  # files written by the current child
        self.start_timeout_s = start_timeout_s
        self.convert_timeout_s = convert_timeout_s or float(
            os.environ.get("DANCEGRAPH_FBX_TIMEOUT", DEFAULT_CONVERT_TIMEOUT_S)
        )
        self.blender_version: str | None = None
        self.starts = 0  # how many child processes this exporter has started
        self._proc: subprocess.Popen | None = None
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._stderr: collections.deque[str] = collections.deque(maxlen=200)
        self._lock = threading.Lock()
        self._next_id = 0
        self._finalizer = weakref.finalize(self, _kill, None)

    # -- process management -------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None and self.running else None

    def start(self) -> None:
        """Start the child (if not running) and wait until Blender has loaded."""
        with self._lock:
            self._ensure_started()

    def _ensure_started(self) -> None:
        if self.running:
            return
        self._stop_locked()
        if not (self.python.is_file() and os.access(self.python, os.X_OK)):
            raise FbxError(
                f"Blender's Python not found at {self.python}: run scripts/install-blender.sh "
                "or set DANCEGRAPH_BLENDER_PYTHON",
                code="fbx_unavailable",
                field="DANCEGRAPH_BLENDER_PYTHON",
            )
        env = dict(os.environ)
        env.pop("PYTHONPATH", None)  # the child must not see the main venv's packages
        env["PYTHONNOUSERSITE"] = "1"
        env["PYTHONUNBUFFERED"] = "1"
        try:
            proc = subprocess.Popen(
                [str(self.python), "-I", str(WORKER_SCRIPT)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                encoding="utf-8",
                errors="replace",
                bufsize=1,
                env=env,
                cwd=str(WORKER_SCRIPT.parent),
            )
        except OSError as exc:
            raise FbxError(
                f"cannot start Blender's Python {self.python}: {exc}", code="fbx_unavailable"
            ) from exc
        self._proc = proc
        self.starts += 1
        self._jobs = 0
        self._finalizer.detach()
        self._finalizer = weakref.finalize(self, _kill, proc)
        self._lines = queue.Queue()
        self._stderr.clear()
        threading.Thread(
            target=_pump, args=(proc.stdout, self._lines.put, True), daemon=True
        ).start()
        threading.Thread(
            target=_pump, args=(proc.stderr, self._stderr.append, False), daemon=True
        ).start()
        reply = self._read_reply(self.start_timeout_s, what="start")
        if not reply.get("ready"):
            self._stop_locked()
            raise FbxError(f"Blender worker did not start: {reply}", code="fbx_unavailable")
        self.blender_version = reply.get("blender")

    def close(self) -> None:
        """Ask the child to quit (kill it if it does not); a later convert starts a new one."""
        with self._lock:
            self._stop_locked()

    def _stop_locked(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.poll() is None:
            try:
                assert proc.stdin is not None  # started with stdin=PIPE
                proc.stdin.write(json.dumps({"id": -1, "op": "quit"}) + "\n")
                proc.stdin.flush()
                proc.wait(timeout=5)
            except (OSError, ValueError, subprocess.TimeoutExpired):
                pass
        _kill(proc)

    def __enter__(self) -> FbxExporter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- requests --------------------------------------------------------------------------------

    def _read_reply(self, timeout_s: float, *, what: str) -> dict:
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            try:
                line = self._lines.get(timeout=max(remaining, 0.001))
            except queue.Empty:
                proc, self._proc = self._proc, None
                _kill(proc)  # a stuck Blender does not answer 'quit' either
                raise FbxError(
                    f"Blender worker gave no answer to {what} within {timeout_s:g} s (stopped it)"
                ) from None
            if line is None:  # stdout closed: the child died
                proc = self._proc
                rc = proc.wait(timeout=5) if proc is not None else None
                self._proc = None
                time.sleep(0.05)  # let the stderr pump catch the last lines
                tail = " | ".join(list(self._stderr)[-5:])
                code = "fbx_unavailable" if what == "start" else "fbx_export_failed"
                raise FbxError(
                    f"Blender worker exited during {what} (exit code {rc}): {tail}", code=code
                )
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                continue  # not a protocol line; the worker only writes JSON there

    def _request(self, payload: dict, timeout_s: float) -> dict:
        counted = payload.get("op") == "animate_rig"
        if counted and self._jobs >= self.max_jobs:
            self._stop_locked()  # a fresh child for the next max_jobs files
        self._ensure_started()
        self._jobs += counted
        self._next_id += 1
        req_id = self._next_id
        assert self._proc is not None and self._proc.stdin is not None  # started above
        try:
            self._proc.stdin.write(json.dumps({"id": req_id, **payload}) + "\n")
            self._proc.stdin.flush()
        except (OSError, ValueError) as exc:
            self._stop_locked()
            raise FbxError(f"Blender worker is gone: {exc}") from exc
        while True:
            reply = self._read_reply(timeout_s, what=payload.get("op", "request"))
            if reply.get("id") == req_id:
                return reply

    def ping(self) -> bool:
        with self._lock:
            return bool(self._request({"op": "ping"}, 30.0).get("ok"))

    def convert(
        self,
        bvh_path: str | os.PathLike,
        fbx_path: str | os.PathLike,
        *,
        fps: float | None = None,
        scale: float = 1.0,
    ) -> dict:
        """Convert one BVH file to FBX; returns ``{frames, fps, joints, seconds}`` from the worker.

        ``fps`` overrides the BVH's frame rate; ``scale`` converts the BVH's units to metres
        (1.0 for DanceGraph's own files). The FBX is written atomically (temporary file, rename).
        """
        bvh = Path(bvh_path).resolve()
        fbx = Path(fbx_path).resolve()
        if not bvh.is_file():
            raise MotionFileError("no such file", path=str(bvh_path), code="motion_file_not_found")
        if fps is not None and not fps > 0:
            raise FbxError(
                f"fps must be positive, got {fps}", code="fbx_export_failed", field="fps"
            )
        if not scale > 0:
            raise FbxError(
                f"scale must be positive, got {scale}", code="fbx_export_failed", field="scale"
            )
        try:
            fbx.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise FbxError(
                f"cannot create the folder of {fbx_path}: {exc}", field=str(fbx_path)
            ) from exc
        summary = self._convert(bvh, fbx, fps, scale)
        return {k: summary[k] for k in ("frames", "fps", "joints", "seconds")}

    def _convert(self, bvh: Path, fbx: Path, fps: float | None, scale: float) -> dict:
        """The BVH read by DanceGraph's reader, its rest pose (one frame) as the rig Blender
        imports, the dance keyed on it in bulk (:meth:`animate_rig`)."""
        motion = read_bvh(bvh, scale=scale)  # a broken file: its precise MotionFileError
        rate = float(fps) if fps else snap_fps(motion.fps)
        sk = motion.skeleton
        still = np.zeros((1, sk.n_joints, 4))
        still[..., 3] = 1.0
        positions, g = forward_kinematics(motion)
        with tempfile.TemporaryDirectory(prefix="dg-fbx-") as tmp:
            rest = Path(tmp) / bvh.name  # the armature keeps the file's name
            write_bvh(Motion(sk, rate, sk.offsets[:1].copy(), still), rest)
            anim = Path(tmp) / "anim.npz"
            names = np.array(sk.names, dtype=str)
            np.savez(anim, names=names, g=g, positions=positions, fps=rate, unit_scale=1.0)
            return self.animate_rig(rest, anim, fbx)

    def animate_rig(
        self, rig_path: str | os.PathLike, anim_path: str | os.PathLike, fbx_path: str | os.PathLike
    ) -> dict:
        """Pose the rig file ``rig_path`` by the dance in ``anim_path`` (see ``blender_worker``'s
        ``animate_rig``) and write ``fbx_path`` with the rig's meshes; returns the worker's summary.
        """
        fbx = Path(fbx_path).resolve()
        fbx.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "op": "animate_rig",
            "rig": str(Path(rig_path).resolve()),
            "anim": str(Path(anim_path).resolve()),
            "fbx": str(fbx),
        }
        with self._lock:
            reply = self._request(payload, self.convert_timeout_s)
        if not reply.get("ok"):
            raise FbxError(
                f"FBX export on the rig {Path(rig_path).name} failed: {reply.get('error')}"
            )
        keys = ("frames", "fps", "joints", "meshes", "first_frame", "seconds")
        return {k: reply[k] for k in keys if k in reply}

    def glb_to_fbx(
        self, glb_path: str | os.PathLike, fbx_path: str | os.PathLike, *, fps: float, frames: int
    ) -> dict:
        """Write every armature of the animated GLB ``glb_path`` (a couple's ``couple.glb``: the
        lead and the follow) into one FBX ``fbx_path``, ``frames`` frames at ``fps`` from t = 0
        (``blender_worker.glb_to_fbx``); returns ``{frames, fps, armatures: {name: bones},
        seconds}``. Raises ``MotionFileError`` (``motion_file_not_found``) for a missing GLB and
        ``FbxError`` when Blender fails."""
        glb = Path(glb_path).resolve()
        if not glb.is_file():
            raise MotionFileError("no such file", path=str(glb_path), code="motion_file_not_found")
        fbx = Path(fbx_path).resolve()
        fbx.parent.mkdir(parents=True, exist_ok=True)
        payload: dict[str, object] = {"op": "glb_to_fbx", "glb": str(glb), "fbx": str(fbx)}
        payload.update(fps=float(fps), frames=int(frames))
        with self._lock:
            reply = self._request(payload, self.convert_timeout_s)
        if not reply.get("ok"):
            raise FbxError(f"FBX export of {glb.name} failed: {reply.get('error')}")
        return {k: reply[k] for k in ("frames", "fps", "armatures", "seconds")}


def _pump(stream, sink, mark_end: bool) -> None:
    """Copy lines from a child's pipe to ``sink``; then ``None`` marks the end if ``mark_end``."""
    try:
        for line in stream:
            sink(line.rstrip("\n"))
    except (OSError, ValueError):
        pass
    finally:
        if mark_end:
            sink(None)


def _kill(proc: subprocess.Popen | None) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.kill()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        pass


_shared: FbxExporter | None = None
_shared_lock = threading.Lock()


def shared_exporter() -> FbxExporter:
    """The process-wide warm exporter used by :func:`bvh_to_fbx` (closed at interpreter exit)."""
    global _shared
    with _shared_lock:
        if _shared is None:
            _shared = FbxExporter()
            atexit.register(_shared.close)
        return _shared


def bvh_to_fbx(
    bvh_path: str | os.PathLike,
    fbx_path: str | os.PathLike,
    *,
    fps: float | None = None,
    scale: float = 1.0,
    exporter: FbxExporter | None = None,
) -> dict:
    """Write ``fbx_path`` from ``bvh_path`` (units: ``scale`` × file units = metres).

    Uses ``exporter`` or the shared warm one. The file is read by DanceGraph's own BVH reader,
    so a user's broken file gets its precise error (code, file and line). Raises FbxError
    (``fbx_export_failed`` / ``fbx_unavailable``) or MotionFileError.
    """
    if Path(fbx_path).suffix.lower() != ".fbx":
        raise FbxError(f"the output must be a .fbx file, got {fbx_path}", field=str(fbx_path))
    return (exporter or shared_exporter()).convert(bvh_path, fbx_path, fps=fps, scale=scale)
