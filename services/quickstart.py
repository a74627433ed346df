"""``dancegraph quickstart``: the README's main job, end to end on the embedded default.

1. Imports a motion library — CMU salsa (with the repo's manifest) where ``../shared`` is
   present, otherwise the project's generated demo library — and builds its motion graph.
2. Picks a song — a CC track from ``../shared`` or a song the project synthesises.
3. Starts the embedded service (API on uvicorn, a Celery worker child on the filesystem broker,
   the in-process graph store, SQLite), creates an API key, submits the song over HTTP, waits for
   the job, downloads every result file into ``--out`` in the layout of ``dancegraph synthesize``
   (``alternatives/<k>.bvh``, ``timeline.json``, the song), so ``dancegraph preview OUT`` plays
   it, and prints where they are.
Steps already done (dataset imported, graph built) are reused on the next run.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import threading
import time
from pathlib import Path

import httpx

from dancegraph.paths import REPO_ROOT, shared_dir
from dancegraph.store import FileStore, ObjectStore

SALSA_SONG = "Kevin_MacLeod_-_Vibe_Ace.hq.ogg"


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def prepare_library(store: ObjectStore, home: Path, say) -> tuple[str, Path]:
    """Import and build the dataset (once); returns ``(dataset name, song path)``."""
    from dancegraph.graph.build import BuildParams, build_dataset_graph
    from dancegraph.motion.dataset import import_dataset, list_datasets, load_manifest

    shared = shared_dir() / "datasets"
    salsa_dir = shared / "mocap" / "cmu-salsa"
    song = shared / "music" / "cc" / SALSA_SONG
    if salsa_dir.is_dir() and song.is_file():
        name = "cmu-salsa"
        source = salsa_dir
        manifest = load_manifest(REPO_ROOT / "datasets" / "manifests" / "cmu-salsa.yaml")
    else:
        from dancegraph.motion.demo import write_demo_library
        from dancegraph.music.generator import generate_song, write_song

        name = "demo"
        source = write_demo_library(home / "demo-library")
        manifest = None
        song, _ = write_song(generate_song(7), home / "demo-song", "demo-song")
    known = {d["name"] for d in list_datasets(store)}
    if name not in known:
        say(f"importing {name} from {source} ...")
        report = import_dataset(source, name, store, manifest)
        say(f"  {len(report.to_dict().get('clips', []))} clips imported")
    if not store.exists(f"graphs/{name}/current"):
        say(f"building the motion graph of {name} ...")
        built = build_dataset_graph(store, name, BuildParams())
        say(f"  {built['nodes']} nodes, {built['edges']} edges in {built['seconds']:.1f} s")
    return name, song


def download_result(client: httpx.Client, job: dict, out: Path, song: Path, say=print) -> None:
    """Write a succeeded job's files into ``out`` in the layout ``dancegraph synthesize`` writes
    (``alternatives/<k>.bvh|.fbx``, ``timeline.json``) plus a copy of the song, so
    ``dancegraph preview OUT`` shows it as it is."""
    downloads = [("timeline.json", job["timeline_url"])] if job.get("timeline_url") else []
    for alt in job["alternatives"]:
        downloads += [
            (f"alternatives/{alt['index']}.{fmt}", url) for fmt, url in alt["downloads"].items()
        ]
    (out / "alternatives").mkdir(parents=True, exist_ok=True)
    for name, url in downloads:
        target = out / name
        reply = client.get(url)
        reply.raise_for_status()
        target.write_bytes(reply.content)
        say(f"wrote {target} ({len(reply.content)} bytes)")
    if song.resolve() != (out / song.name).resolve():
        shutil.copyfile(song, out / song.name)  # the timeline names it; the preview finds it


def run(out_dir: str, formats: list[str], say=print) -> dict:
    """Run the main job end to end through the embedded service; returns the job's final record."""
    import uvicorn

    from services import embedded
    from services.keys import create_key_cli

    settings = embedded.embedded_settings()
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per poll is noise here
    os.environ.update(embedded.child_env(settings))
    embedded.prepare(settings)
    store = FileStore(settings.store_root)
    dataset, song = prepare_library(store, Path(settings.store_root).parent, say)

    port = _free_port()
    server = uvicorn.Server(
        uvicorn.Config("services.api.app:app", host="127.0.0.1", port=port, log_level="warning")
    )
    api_thread = threading.Thread(target=server.run, name="api", daemon=True)
    service = embedded.start_background(settings)
    api_thread.start()
    try:
        key = create_key_cli("quickstart", settings.database_url)["api_key"]
        base = f"http://127.0.0.1:{port}"
        with httpx.Client(base_url=base, headers={"X-API-Key": key}, timeout=60) as client:
            for _ in range(300):
                try:
                    if client.get("/healthz").status_code == 200:
                        break
                except httpx.TransportError:
                    time.sleep(0.1)
            spec = {"dataset": dataset, "alternatives": 2, "output": {"formats": formats}}
            say(f"submitting {song.name} to {base}/v1/jobs ...")
            with open(song, "rb") as fh:
                answer = client.post(
                    "/v1/jobs",
                    files={"audio": (song.name, fh, "application/octet-stream")},
                    data={"spec": json.dumps(spec)},
                )
            answer.raise_for_status()
            job_url = answer.headers["Location"]
            job = answer.json()
            last = None
            while job["status"] not in {"succeeded", "failed", "cancelled"}:
                time.sleep(1.0)
                job = client.get(job_url).json()
                if (job.get("stage"), job.get("progress")) != last:
                    last = (job.get("stage"), job.get("progress"))
                    say(f"  {job['status']}: {job.get('stage')} {job.get('progress')}%")
            if job["status"] != "succeeded":
                raise SystemExit(f"job {job['id']} {job['status']}: {job.get('error')}")
            download_result(client, job, Path(out_dir).resolve(), song, say)
            return job
    finally:
        server.should_exit = True
        api_thread.join(timeout=10)
        service.stop()
