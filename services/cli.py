"""The service commands of ``dancegraph``: ``serve``, ``worker``, ``reaper``, ``keys``,
``quickstart``, ``preview``.

They join the one ``dancegraph`` command (``dancegraph.cli``) through the ``dancegraph.commands``
entry-point group (``pyproject.toml``): the domain package never imports ``services``. Each
command is a thin shell over ``services/``; modules are imported when the command runs, so the
other commands do not pay for them.
"""

from __future__ import annotations

import argparse
import os

from dancegraph.cli import print_json

Subparsers = argparse._SubParsersAction  # what ``ArgumentParser.add_subparsers`` returns


def add_commands(sub: Subparsers) -> None:
    """Register the service commands on the ``dancegraph`` parser's subcommands."""
    for add in (_add_keys, _add_service, _add_quickstart, _add_preview):
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
