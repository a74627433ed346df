"""The service commands of ``dancegraph``: ``serve``, ``worker``, ``reaper``, ``keys``,
``quickstart``, ``preview``, and ``dataset push`` (a library uploaded to a running service).

They join the one ``dancegraph`` command (``dancegraph.cli``) through the ``dancegraph.commands``
entry-point group (``pyproject.toml``): the domain package never imports ``services``. Each
command is a thin shell over ``services/``; modules are imported when the command runs, so the
other commands do not pay for them.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from dancegraph.cli import print_json

Subparsers = argparse._SubParsersAction  # what ``ArgumentParser.add_subparsers`` returns


def add_commands(sub: Subparsers) -> None:
    """Register the service commands on the ``dancegraph`` parser's subcommands."""
    for add in (_add_keys, _add_service, _add_quickstart, _add_preview, _add_dataset_push):
        add(sub)


def _add_keys(sub: Subparsers) -> None:
    p = sub.add_parser("keys", help="API keys of the service (stored hashed)")
    keys_sub = p.add_subparsers(dest="keys_command", required=True)
    c = keys_sub.add_parser("create", help="create an API key for a tenant; prints it once")
    c.add_argument("--tenant", required=True, help="tenant name (created if new)")
    c.add_argument("--database-url", default=None, help="override DANCEGRAPH_DATABASE_URL")

    def _create(args) -> int:
        from services.keys import create_key_cli

        print_json(create_key_cli(args.tenant, args.database_url))
        return 0

    c.set_defaults(func=_create)


def _add_service(sub: Subparsers) -> None:
    """``serve``, ``worker``, ``reaper``: the service processes (thin: services/ does the work)."""
    p = sub.add_parser("serve", help="run API + worker + reaper (+ in-process graph store)")
    p.add_argument(
        "--embedded",
        action="store_true",
        help="SQLite, filesystem broker, in-process graph store under DANCEGRAPH_HOME (no servers)",
    )
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--concurrency", type=int, default=1, help="worker pool processes")

    def _serve(args):
        from services.embedded import serve

        return serve(args.host, args.port, embedded=args.embedded, concurrency=args.concurrency)

    p.set_defaults(func=_serve)

    p = sub.add_parser("worker", help="run a Celery worker (queues: analysis, fbx)")
    p.add_argument(
        "-Q", "--queues", default="analysis,fbx", help="comma-separated queues to consume"
    )
    p.add_argument("-c", "--concurrency", type=int, default=1, help="pool processes")
    p.add_argument("-n", "--name", default=None, help="worker node name (default: celery's)")

    def _worker(args):
        from services.embedded import worker_command

        cmd = worker_command(
            tuple(q for q in args.queues.split(",") if q), args.concurrency, args.name
        )
        os.execv(cmd[0], cmd)  # become the worker: signals reach Celery directly

    p.set_defaults(func=_worker)

    p = sub.add_parser("reaper", help="requeue or fail jobs stuck past the timeout (loop)")
    p.add_argument("--interval", type=float, default=None, help="seconds between sweeps")
    p.add_argument("--once", action="store_true", help="one sweep, print what it did, exit")

    def _reaper(args):
        from services.worker import logs, reaper

        logs.configure()
        if args.once:
            print_json(reaper.reap_once().to_dict())
            return 0
        reaper.run_forever(args.interval or reaper.default_interval())
        return 0

    p.set_defaults(func=_reaper)


def _add_quickstart(sub: Subparsers) -> None:
    p = sub.add_parser(
        "quickstart",
        help="the main job end to end on the embedded default: library → graph → job → files",
    )
    p.add_argument("--out", default="out", help="where to download the result files")
    p.add_argument("--formats", default="bvh,fbx", help="comma-separated output formats (bvh, fbx)")

    def run(args) -> int:
        from services.quickstart import run as quickstart

        job = quickstart(args.out, [f for f in args.formats.split(",") if f])
        print(f"job {job['id']} succeeded; results in {os.path.abspath(args.out)}")
        return 0

    p.set_defaults(func=run)


def _add_preview(sub: Subparsers) -> None:
    p = sub.add_parser(
        "preview", help="watch a synthesize output in the browser: the dance on the song"
    )
    p.add_argument("result_dir", help="a `dancegraph synthesize --out` folder (with timeline.json)")
    p.add_argument(
        "--audio", default=None, help="the song (default: found through timeline.json's provenance)"
    )
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8050)

    def run(args) -> int:
        from services.preview_server import serve

        serve(args.result_dir, args.audio, args.host, args.port)
        return 0

    p.set_defaults(func=run)


def _add_dataset_push(sub: Subparsers) -> None:
    """``dataset push DIR --server URL --key KEY``, beside the domain's ``dataset import``."""
    dataset = sub.choices.get("dataset")
    if dataset is None:
        return
    ds_sub = next(a for a in dataset._actions if isinstance(a, argparse._SubParsersAction))
    p = ds_sub.add_parser(
        "push", help="upload a folder of takes (+ manifest, music) to a running service and wait"
    )
    p.add_argument("dir", help="folder with the takes (.bvh/.glb/.fbx), manifest and audio")
    p.add_argument("--server", required=True, help="the service's base URL, e.g. http://host:8000")
    p.add_argument("--key", required=True, help="your API key")
    p.add_argument(
        "--name", default=None, help="library name (default: the manifest's, else DIR's)"
    )
    p.add_argument("--manifest", default=None, help="manifest file (default: DIR/manifest.*)")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds to wait for the build")

    def run(args) -> int:
        import httpx

        with httpx.Client(base_url=args.server, timeout=600.0) as client:
            out = push_library(
                client, args.dir, args.key, name=args.name, manifest=args.manifest,
                timeout_s=args.timeout,
            )  # fmt: skip
        print_json(out)
        return 0 if out.get("status") == "succeeded" else 1

    p.set_defaults(func=run)


def push_library(
    client,
    folder: str | os.PathLike,
    key: str,
    *,
    name: str | None = None,
    manifest: str | os.PathLike | None = None,
    timeout_s: float = 1800.0,
    poll_s: float = 1.0,
) -> dict:
    """``POST /v1/datasets`` the takes, audio and manifest of ``folder`` through ``client`` (an
    httpx client on the service), then poll ``GET /v1/datasets/{name}`` until the version is
    built or failed, printing its stage and percent on stderr; returns the last resource (or
    ``{"status": "refused", "problem": <problem details>}`` for a refused upload)."""
    from services.common.libraries import AUDIO_SUFFIXES, TAKE_SUFFIXES

    src = Path(folder)
    files = sorted(p for p in src.iterdir() if p.is_file())
    found = [p for p in files if p.name in ("manifest.yaml", "manifest.yml", "manifest.json")]
    mpath = Path(manifest) if manifest else (found[0] if found else None)
    if name is None and mpath is not None and mpath.suffix == ".json":
        name = json.loads(mpath.read_text()).get("name")
    name = name or src.resolve().name
    parts: list = [("name", (None, name))]
    handles = []
    try:
        sending = [("manifest", mpath)] if mpath is not None else []
        sending += [
            ("takes" if p.suffix.lower() in TAKE_SUFFIXES else "audio", p)
            for p in files
            if p.suffix.lower() in TAKE_SUFFIXES + AUDIO_SUFFIXES
        ]
        for role, path in sending:
            handles.append(open(path, "rb"))  # noqa: SIM115 - closed below, after the upload
            parts.append((role, (path.name, handles[-1], "application/octet-stream")))
        resp = client.post("/v1/datasets", files=parts, headers={"X-API-Key": key})
    finally:
        for fh in handles:
            fh.close()
    if resp.status_code != 202:
        return {"status": "refused", "problem": resp.json()}
    deadline = time.monotonic() + timeout_s
    body = resp.json()
    while body["status"] in ("queued", "running") and time.monotonic() < deadline:
        print(f"{name}: {body['stage']} {body['progress']:.0f} %", file=sys.stderr)
        time.sleep(poll_s)
        body = client.get(resp.headers["Location"], headers={"X-API-Key": key}).json()
    return body
