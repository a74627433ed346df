"""The preview page's server side, shared by the API (``/v1/jobs/{id}/preview``) and the local
``dancegraph preview RESULT_DIR`` server.

The page itself is static: ``frontend/`` builds it (three.js bundled, nothing from a CDN) into
``services/preview_static/`` (gitignored; ``scripts/install-frontend.sh``). The server fills the
template with a JSON config naming the data URLs: the song, the timeline and per alternative a
pose track (``dancegraph.preview.pose_track``). ``static_router`` serves the bundle at
``/preview-static/``.

A pose track is computed once per BVH content and kept gzip-compressed in an object store
(``pose_json_gz``); the JSON routes send it gzip-encoded to clients that accept it and decoded
to the others (``json_response``; about 3× smaller on real mocap: 1.1 MB for 4 000 frames).
Only these routes compress: the song keeps plain byte-range answers for seeking.
"""

from __future__ import annotations

import gzip
import json
import mimetypes
import tempfile
from pathlib import Path
from typing import Literal

from fastapi import APIRouter, FastAPI, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, HTMLResponse, Response

from dancegraph.errors import DanceGraphError, NotFoundError
from dancegraph.preview import (
    POSE_FORMAT,
    find_audio,
    pose_track_file,
    read_timeline,
)
from dancegraph.render import TIMELINE
from dancegraph.store import FileStore, ObjectStore, file_sha256
from services.common import problems
from services.common.problems import ApiError

STATIC_DIR = Path(__file__).resolve().parent / "preview_static"
ASSETS_PATH = "/preview-static"
_ASSETS = {"preview.js": "text/javascript", "style.css": "text/css"}

static_router = APIRouter(include_in_schema=False)


@static_router.get(ASSETS_PATH + "/{name}")
def preview_asset(name: str):
    path = STATIC_DIR / name
    if name not in _ASSETS or not path.is_file():
        raise ApiError(404, "not_found", f"no preview asset {name!r}", field="name")
    return FileResponse(path, media_type=_ASSETS[name], headers={"Cache-Control": "no-cache"})


def render_page(
    *,
    title: str,
    audio: str,
    timeline: str,
    poses: list[str],
    assets: str = ASSETS_PATH,
    rig_poses: list[str] | None = None,
    rig_models: list[str] | None = None,
    follow_poses: list[str] | None = None,
) -> HTMLResponse:
    """The page with its config: URLs of the song, the timeline and each alternative's poses
    (``rig_poses``: the same alternatives on the user's rig, when the result has them;
    ``rig_models``: each alternative's ``.rig.glb``, the character the page draws;
    ``follow_poses``: a couple's follow, drawn beside ``poses``, the lead, in the same world).

    503 ``preview_not_built`` when the front end has not been built.
    """
    template = STATIC_DIR / "index.html"
    if not template.is_file():
        raise ApiError(
            503,
            "preview_not_built",
            "the preview page is not built on this server: run scripts/install-frontend.sh",
        )
    config = {"title": title, "audio": audio, "timeline": timeline, "poses": poses}
    if rig_poses:
        config["rig_poses"] = rig_poses
    if rig_models:
        config["rig_models"] = rig_models
    if follow_poses:
        config["follow_poses"] = follow_poses
    # '<' escaped so no string in the config can close the <script> element
    text = json.dumps(config).replace("<", "\\u003c")
    html = template.read_text(encoding="utf-8")
    html = html.replace("__CONFIG__", text).replace("__ASSETS__", assets)
    return HTMLResponse(html, headers={"Cache-Control": "no-store"})


# the upload checks' container names (services.common.uploads.sniff_container) → content types
_AUDIO_TYPES = {
    "wav": "audio/wav",
    "flac": "audio/flac",
    "ogg": "audio/ogg",
    "mp3": "audio/mpeg",
    "mp4": "audio/mp4",
    "m4a": "audio/mp4",
    "aac": "audio/aac",
    "aiff": "audio/aiff",
    "matroska": "audio/webm",
}


def audio_media_type(kind: str) -> str:
    """Content type for a song, by container name or file name (the browser's <audio> needs it)."""
    key = kind.rsplit(".", 1)[-1].lower()
    return _AUDIO_TYPES.get(key) or mimetypes.guess_type(kind)[0] or "application/octet-stream"


def accepts_gzip(accept_encoding: str) -> bool:
    """Whether an ``Accept-Encoding`` header value allows gzip (``gzip`` or ``*``, q above 0;
    an explicit ``gzip`` entry wins over ``*``)."""
    allowed: dict[str, bool] = {}
    for item in accept_encoding.lower().split(","):
        coding, *params = (part.strip() for part in item.split(";"))
        q = 1.0
        for param in params:
            name, _, value = param.partition("=")
            if name.strip() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        allowed[coding] = q > 0
    return allowed.get("gzip", allowed.get("x-gzip", allowed.get("*", False)))


def json_response(request: Request, gz: bytes) -> Response:
    """A JSON body given gzip-compressed: sent as is with ``Content-Encoding: gzip`` when the
    client accepts gzip, else decompressed."""
    headers = {"Vary": "Accept-Encoding"}
    if accepts_gzip(request.headers.get("accept-encoding", "")):
        headers["Content-Encoding"] = "gzip"
        return Response(gz, media_type="application/json", headers=headers)
    return Response(gzip.decompress(gz), media_type="application/json", headers=headers)


def _gzip(data: bytes) -> bytes:
    return gzip.compress(data, compresslevel=6, mtime=0)  # mtime 0: same input, same bytes


def json_bytes_response(request: Request, data: bytes) -> Response:
    """``json_response`` of a JSON document's bytes (compressed per request: a timeline is small)."""
    return json_response(request, _gzip(data))


def pose_cache_key(prefix: str, bvh: Path) -> str:
    """Where ``pose_json_gz`` keeps the track of ``bvh``: under ``prefix``, named by the BVH's
    content hash and the pose format, so a changed file or format never reads a stale track."""
    return f"{prefix}/{file_sha256(bvh)[:32]}.v{POSE_FORMAT}.json.gz"


def rig_unit_scale(timeline_path: Path, k: int, partner: str | None = None) -> float:
    """Metres per unit of alternative ``k``'s dance on the rig (its ``rig`` report in the
    timeline, a couple's per ``partner``; 1.0 when absent): a rig read from centimetres gets
    its BVH in centimetres."""
    try:
        alt = json.loads(timeline_path.read_text(encoding="utf-8"))["alternatives"][k]
        rig = alt.get("rig") or {}
        return float((rig.get(partner) or {} if partner else rig).get("unit_scale", 1.0))
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return 1.0


def couple_pose_file(k: int, partner: str) -> str:
    """A couple's dancer's BVH in a result: ``alternatives/<k>/<partner>.bvh``."""
    return f"alternatives/{k}/{partner}.bvh"


def pose_file(k: int, skeleton: str, partner: str | None) -> str:
    """The result file the pose route of alternative ``k`` reads: ``alternatives/<k>.bvh``
    (``skeleton`` ``rig``: ``<k>.rig.bvh``), or with ``partner`` (``lead``, ``follow``) that
    dancer of a couple (``<k>/<partner>.bvh``, ``.rig.bvh``)."""
    tail = ".rig.bvh" if skeleton == "rig" else ".bvh"
    return f"alternatives/{k}/{partner}{tail}" if partner else f"alternatives/{k}{tail}"


def pose_json_gz(
    bvh: Path, k: int, store: ObjectStore, prefix: str, *, scale: float = 1.0
) -> bytes:
    """Alternative ``k``'s pose track (``dancegraph.preview.pose_track``) as gzip-compressed
    compact JSON: read from ``store`` when computed before, else computed from ``bvh`` (``scale``
    metres per unit) and stored at ``pose_cache_key(prefix, bvh)``.

    404 ``result_not_found`` when ``bvh`` does not exist.
    """
    if not bvh.is_file():
        raise ApiError(404, "result_not_found", f"no alternative {k}", field="k")
    key = pose_cache_key(prefix, bvh)
    if store.exists(key):
        return store.get_bytes(key)
    text = json.dumps(pose_track_file(bvh, scale), separators=(",", ":"))
    gz = _gzip(text.encode())
    store.put_bytes(key, gz)
    return gz


def create_local_app(result_dir: str | Path, audio: str | Path | None = None) -> FastAPI:
    """The preview of a ``dancegraph synthesize`` output folder, served at ``/``.

    ``audio``: the song; default: found through ``timeline.json`` (``dancegraph.preview.find_audio``).
    Raises ``DanceGraphError`` for a folder without a timeline or a song that cannot be found.
    """
    folder = Path(result_dir)
    timeline = read_timeline(folder)
    if audio is None:
        song = find_audio(folder, timeline)
    else:
        song = Path(audio)
        if not song.is_file():
            raise NotFoundError(
                f"no audio file {song}", code="preview_audio_missing", field="--audio"
            )
    n_alternatives = len(timeline.get("alternatives") or [])
    if not n_alternatives:
        raise DanceGraphError(
            f"{folder / 'timeline.json'} lists no alternatives", code="timeline_invalid"
        )

    app = FastAPI(title="DanceGraph preview", openapi_url=None, docs_url=None, redoc_url=None)
    # the pose tracks' cache lives as long as the server (removed when the app is collected)
    app.state.pose_cache = tempfile.TemporaryDirectory(prefix="dancegraph-preview-")
    cache = FileStore(app.state.pose_cache.name)
    problems.install(app)
    app.include_router(static_router)

    couple = (folder / couple_pose_file(0, "lead")).is_file()
    on_rig = (folder / "alternatives" / "0.rig.bvh").is_file()
    models = on_rig and (folder / "alternatives" / "0.rig.glb").is_file()
    lead = "?partner=lead" if couple else ""

    @app.get("/", response_class=HTMLResponse)
    def page():
        return render_page(
            title=f"{song.name} · {folder.name}",
            audio="audio",
            timeline="timeline.json",
            poses=[f"poses/{k}.json{lead}" for k in range(n_alternatives)],
            follow_poses=[f"poses/{k}.json?partner=follow" for k in range(n_alternatives)]
            if couple
            else None,
            assets=ASSETS_PATH,
            rig_poses=[f"poses/{k}.json?skeleton=rig" for k in range(n_alternatives)]
            if on_rig
            else None,
            rig_models=[f"rig/{k}.glb" for k in range(n_alternatives)] if models else None,
        )

    @app.get("/rig/{k}.glb")
    def rig_model(k: int = PathParam(..., ge=0, le=99)):
        path = folder / "alternatives" / f"{k}.rig.glb"
        if not path.is_file():
            raise NotFoundError(f"no alternative {k} on a rig", code="result_not_found", field="k")
        return FileResponse(path, media_type="model/gltf-binary")

    @app.get("/timeline.json")
    def timeline_file(request: Request):
        return json_bytes_response(request, (folder / TIMELINE).read_bytes())

    @app.get("/poses/{k}.json")
    def poses(
        request: Request,
        k: int = PathParam(..., ge=0, le=99),
        skeleton: Literal["library", "rig"] = "library",
        partner: Literal["lead", "follow"] | None = None,
    ):
        scale = rig_unit_scale(folder / TIMELINE, k, partner) if skeleton == "rig" else 1.0
        bvh = folder / pose_file(k, skeleton, partner)
        return json_response(request, pose_json_gz(bvh, k, cache, "poses", scale=scale))

    @app.get("/audio")
    def song_file():
        return FileResponse(song, media_type=audio_media_type(song.name))

    return app


def serve(result_dir: str | Path, audio: str | Path | None, host: str, port: int) -> None:
    """Run the local preview server until interrupted (prints its URL first)."""
    import uvicorn

    app = create_local_app(result_dir, audio)
    print(f"preview of {result_dir}: http://{host}:{port}/  (Ctrl+C stops)", flush=True)
    uvicorn.run(app, host=host, port=port, log_level="warning")
