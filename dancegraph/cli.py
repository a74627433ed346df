"""The ``dancegraph`` command.

Each subcommand is a thin shell: parse arguments, call the library, print a result. Subcommands
register themselves in ``build_parser`` through one ``_add_*`` function per area.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence

from dancegraph import __version__
from dancegraph.errors import DanceGraphError


def _print_json(obj) -> None:
    json.dump(obj, sys.stdout, indent=2, default=str)
    sys.stdout.write("\n")


def _read_spec(path: str | None) -> dict:
    """The constraint spec JSON object in ``path`` ({} without one); SpecError naming the file."""
    from dancegraph.errors import SpecError

    if not path:
        return {}
    try:
        with open(path, encoding="utf-8") as fh:
            spec = json.load(fh)
    except (OSError, ValueError) as exc:
        raise SpecError(f"cannot read the spec {path}: {exc}", field=path) from exc
    if not isinstance(spec, dict):
        raise SpecError(f"{path}: the spec must be a JSON object", field=path)
    return spec


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dancegraph", description="Music in, dance out.")
    parser.add_argument("--version", action="version", version=f"dancegraph {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (
        _add_version,
        _add_convert,
        _add_synthesize,
        _add_keys,
        _add_service,
        _add_analyze,
        _add_dataset,
        _add_motion,
        _add_quickstart,
        _add_eval,
        _add_preview,
        _add_train,
    ):
        add(sub)
    return parser


def _add_version(sub) -> None:
    p = sub.add_parser("version", help="print the version as JSON")
    p.set_defaults(func=lambda args: _print_json({"dancegraph": __version__}))


def _add_analyze(sub) -> None:
    p = sub.add_parser(
        "analyze", help="analyse songs: beats, meter, bars, phrases, per-bar features"
    )
    p.add_argument("audio", nargs="+", help="audio files (wav, flac, ogg, mp3, ...)")
    p.add_argument(
        "--json", action="store_true", help="print the full analysis (default: a summary)"
    )
    p.add_argument(
        "--tempo-range",
        type=float,
        nargs=2,
        metavar=("LO", "HI"),
        help="a dance style's tempo range (BPM): the bars count the octave that fits it",
    )
    p.add_argument(
        "--jsonl",
        action="store_true",
        help="one JSON object per line and file, with its path; a file that fails gives its "
        "error code and the rest go on (exit status 2 when any failed)",
    )

    def run(args) -> int:
        from dancegraph.music.analysis import analyze

        if not args.jsonl:
            if len(args.audio) > 1:
                p.error("several files need --jsonl")
            result = analyze(args.audio[0], tempo_range=args.tempo_range)
            _print_json(result.to_dict() if args.json else result.summary())
            return 0
        failed = 0
        for path in args.audio:  # one process: the models and kernels load once
            try:
                result = analyze(path, tempo_range=args.tempo_range)
                line = {"path": path, **(result.to_dict() if args.json else result.summary())}
            except DanceGraphError as exc:
                failed += 1
                line = {"path": path, "error": exc.to_dict()}
            except Exception as exc:  # a batch goes on past a file the library did not expect
                failed += 1
                line = {"path": path, "error": {"code": "analysis_failed", "message": str(exc)}}
            sys.stdout.write(json.dumps(line, default=str) + "\n")
            sys.stdout.flush()
        return 2 if failed else 0

    p.set_defaults(func=run)


def _add_dataset(sub) -> None:
    """``dataset import DIR --name NAME [--manifest FILE]`` and ``dataset list``."""
    p = sub.add_parser("dataset", help="motion datasets in the object store")
    ds_sub = p.add_subparsers(dest="dataset_command", required=True)

    def _store(args):
        from dancegraph.paths import store_dir
        from dancegraph.store import ObjectStore

        return ObjectStore(args.store or store_dir())

    imp = ds_sub.add_parser("import", help="import a folder of BVH files as a dataset")
    imp.add_argument("dir", help="folder with the motion files (and optionally manifest.yaml)")
    imp.add_argument("--name", required=True, help="dataset name (letters, digits, . _ -)")
    imp.add_argument("--manifest", default=None, help="manifest file (YAML or JSON)")
    imp.add_argument("--store", default=None, help="object store root (default: DANCEGRAPH_HOME's)")
    imp.add_argument(
        "--json", action="store_true", help="print the report as JSON (default: a table)"
    )

    def _import(args) -> int:
        from tqdm import tqdm

        from dancegraph.motion.dataset import import_dataset, load_manifest

        manifest = load_manifest(args.manifest) if args.manifest else None
        with tqdm(total=None, unit="file", file=sys.stderr, disable=None) as bar:

            def progress(done: int, total: int, name: str) -> None:
                bar.total = total
                bar.set_postfix_str(name, refresh=False)
                bar.update(done - bar.n)

            report = import_dataset(args.dir, args.name, _store(args), manifest, progress)
        if args.json:
            _print_json(report.to_dict())
        else:
            print(report.table())
        return 0

    imp.set_defaults(func=_import)

    ls = ds_sub.add_parser("list", help="list the stored datasets as JSON")
    ls.add_argument("--store", default=None, help="object store root (default: DANCEGRAPH_HOME's)")

    def _list(args) -> int:
        from dancegraph.motion.dataset import list_datasets

        _print_json(list_datasets(_store(args)))
        return 0

    ls.set_defaults(func=_list)

    bld = ds_sub.add_parser("build", help="build (a new version of) the dataset's motion graph")
    bld.add_argument("name", help="dataset name")
    bld.add_argument(
        "--threshold", type=float, default=20.0, help="δT: largest edge cost (default 20)"
    )
    bld.add_argument("--max-degree", type=int, default=24, help="most out-edges kept per node")
    bld.add_argument("--no-mirror", action="store_true", help="skip the mirrored bars")
    bld.add_argument(
        "--blend-ratio", type=float, default=0.25, help="blended bars per original bar, at most"
    )
    bld.add_argument(
        "--shuffle-ratio",
        type=float,
        default=0.25,
        help="beat-shuffled bars per original bar, at most",
    )
    bld.add_argument(
        "--embedding",
        default="descriptor",
        help="node style embedding: 'descriptor' or a learned style model file (.dgm)",
    )
    bld.add_argument(
        "--rhythm-model", default=None, help="learned rhythm model file (.dgm): node signatures"
    )
    bld.add_argument("--store", default=None, help="object store root (default: DANCEGRAPH_HOME's)")
    bld.add_argument("--json", action="store_true", help="print the report as JSON")

    def _build(args) -> int:
        from tqdm import tqdm

        from dancegraph.graph.build import BuildParams, build_dataset_graph

        params = BuildParams(
            threshold=args.threshold,
            max_out_degree=args.max_degree,
            mirror=not args.no_mirror,
            blend_ratio=args.blend_ratio,
            shuffle_ratio=args.shuffle_ratio,
        )
        with tqdm(total=100, unit="%", file=sys.stderr, disable=None) as bar:

            def progress(stage: str, fraction: float) -> None:
                bar.set_description_str(stage, refresh=False)
                bar.n = int(100 * fraction)  # each stage runs 0 → 100 %
                bar.refresh()

            report = build_dataset_graph(
                _store(args), args.name, params, progress, args.embedding, args.rhythm_model
            )
        if args.json:
            _print_json(report)
        else:
            print(f"graph {args.name} version {report['version']} ({report['embedding']})")
            print(f"nodes {report['nodes']}  {report['nodes_by_kind']}")
            b = report["build"]
            print(
                f"edges {report['edges']}  (forced: {b['forced_out']} out, {b['forced_in']} in;"
                f" consecutive {b['consecutive']})"
            )
            d = report["degree"]
            print(
                f"out-degree min {d['min']} median {d['median']:.0f} mean {d['mean']:.1f}"
                f" max {d['max']}"
            )
            print("  " + "  ".join(f"{k}:{v}" for k, v in d["histogram"].items()))
            print(f"build time {report['seconds']:.1f} s")
        return 0

    bld.set_defaults(func=_build)


def _add_motion(sub) -> None:
    p = sub.add_parser("motion", help="motion files: inspect a BVH, write the demo library")
    m_sub = p.add_subparsers(dest="motion_command", required=True)

    demo = m_sub.add_parser("demo", help="write the generated demo dance library (BVH + manifest)")
    demo.add_argument("out_dir", help="folder to write into")
    demo.add_argument("--seed", type=int, default=0)

    def run_demo(args) -> None:
        from dancegraph.motion.demo import write_demo_library

        out = write_demo_library(args.out_dir, seed=args.seed)
        _print_json({"dir": str(out), "files": sorted(f.name for f in out.iterdir())})

    demo.set_defaults(func=run_demo)

    info = m_sub.add_parser("info", help="read a BVH file; print skeleton and timing as JSON")
    info.add_argument("path")
    info.add_argument("--fps", type=float, default=None, help="override the header frame rate")
    info.add_argument("--scale", type=float, default=1.0, help="file units to metres")

    def run_info(args) -> None:
        from dancegraph.motion.bvh import read_bvh
        from dancegraph.motion.contacts import clean_foot_skate

        motion = read_bvh(args.path, fps=args.fps, scale=args.scale)
        sk = motion.skeleton
        _, skate = clean_foot_skate(motion)
        _print_json(
            {
                "file": args.path,
                "joints": sk.n_joints,
                "frames": motion.n_frames,
                "fps": motion.fps,
                "duration_s": round(motion.duration_s, 3),
                "root": sk.names[0],
                "canonical": sk.canonical,
                "mirror_pairs": [[sk.names[a], sk.names[b]] for a, b in sk.mirror_pairs()],
                "foot_contact_frames": skate["contact_frames"],
                "foot_sliding_m_s": round(skate["sliding_before_m_s"], 4),
            }
        )

    info.set_defaults(func=run_info)


def _add_convert(sub) -> None:
    p = sub.add_parser("convert", help="convert a BVH file to FBX (through Blender)")
    p.add_argument("input", help="the BVH file")
    p.add_argument("output", help="the FBX file to write")
    p.add_argument("--fps", type=float, default=None, help="frame rate (default: the BVH header's)")
    p.add_argument("--scale", type=float, default=1.0, help="file units to metres (default 1.0)")

    def run(args) -> None:
        from dancegraph.motion.fbx import bvh_to_fbx

        summary = bvh_to_fbx(args.input, args.output, fps=args.fps, scale=args.scale, validate=True)
        _print_json({"output": args.output, **summary})

    p.set_defaults(func=run)


def _add_keys(sub) -> None:
    p = sub.add_parser("keys", help="API keys of the service (stored hashed)")
    keys_sub = p.add_subparsers(dest="keys_command", required=True)
    c = keys_sub.add_parser("create", help="create an API key for a tenant; prints it once")
    c.add_argument("--tenant", required=True, help="tenant name (created if new)")
    c.add_argument("--database-url", default=None, help="override DANCEGRAPH_DATABASE_URL")

    def _create(args) -> int:
        # services code is imported here so the domain library never needs it
        from services.keys import create_key_cli

        _print_json(create_key_cli(args.tenant, args.database_url))
        return 0

    c.set_defaults(func=_create)


def _add_service(sub) -> None:
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
        import os

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
            _print_json(reaper.reap_once().to_dict())
            return 0
        reaper.run_forever(args.interval or reaper.default_interval())
        return 0

    p.set_defaults(func=_reaper)


def _add_synthesize(sub) -> None:
    p = sub.add_parser(
        "synthesize", help="song → dance: analysis, graph search, render (BVH, FBX, timeline)"
    )
    p.add_argument("audio", help="the song (any format ffmpeg/libsndfile decodes)")
    p.add_argument("--dataset", required=True, help="dataset whose graph to dance from")
    p.add_argument("--spec", default=None, help="constraint spec, JSON file (dancegraph.spec.Spec)")
    p.add_argument(
        "--out", required=True, help="output folder (alternatives/<k>.bvh|.fbx, timeline.json)"
    )
    p.add_argument(
        "--alternatives", type=int, default=None, help="number of alternatives (overrides the spec)"
    )
    p.add_argument("--store", default=None, help="object store root (default: DANCEGRAPH_HOME's)")

    def run(args) -> None:
        from dancegraph.paths import store_dir
        from dancegraph.render import synthesize
        from dancegraph.store import ObjectStore
        from services.graphstore.client import LocalGraphStore, parse_spec

        spec = _read_spec(args.spec)
        if args.alternatives is not None:
            spec["alternatives"] = args.alternatives
        parsed = parse_spec(args.dataset, spec)
        graph = LocalGraphStore(ObjectStore(args.store or store_dir())).graph(args.dataset)
        done = synthesize(args.audio, graph, parsed, args.out)
        timeline = done["timeline"]
        _print_json(
            {
                "out": args.out,
                "files": done["files"],
                "analysis": done["analysis"],
                "graph": {"name": graph.name, "version": graph.version},
                "music_style": done["search"]["constraints"].get("music_style"),
                "alternatives": [
                    {
                        "index": a["index"],
                        "cost": a["cost"],
                        "frames": a["frames"],
                        "violations": len(a["violations"]),
                    }
                    for a in timeline["alternatives"]
                ],
            }
        )

    p.set_defaults(func=run)


def _add_eval(sub) -> None:
    """``eval AUDIO... --dataset NAME --out DIR`` and ``eval --result DIR``."""
    from dancegraph.eval import ROWS

    p = sub.add_parser(
        "eval",
        help="evaluate dances: baselines and ablations on songs (metrics.json, report.html)",
    )
    p.add_argument("audio", nargs="*", help="songs to dance (not with --result)")
    p.add_argument("--dataset", default=None, help="dataset whose graph to dance from")
    p.add_argument("--out", default=None, help="output folder (metrics.json, report.html)")
    p.add_argument("--spec", default=None, help="constraint spec, JSON file (dancegraph.spec.Spec)")
    p.add_argument(
        "--rows", nargs="+", default=None, choices=ROWS, help="rows to run (default: all)"
    )
    p.add_argument(
        "--result", default=None, help="score an existing synthesize/job result folder instead"
    )
    p.add_argument("--audio-file", default=None, help="with --result: the song, for librosa beats")
    p.add_argument("--store", default=None, help="object store root (default: DANCEGRAPH_HOME's)")

    def run(args) -> int:
        from dancegraph.errors import SpecError
        from dancegraph.eval.harness import evaluate, evaluate_result, load_library, load_song
        from dancegraph.motion.dataset import load_dataset
        from dancegraph.paths import store_dir
        from dancegraph.store import ObjectStore
        from services.graphstore.client import LocalGraphStore, parse_spec

        store = ObjectStore(args.store or store_dir())
        if args.result:
            from dancegraph.preview import read_timeline

            prov = read_timeline(args.result).get("provenance", {})
            name = args.dataset or prov.get("dataset", {}).get("name")
            version = prov.get("graph", {}).get("version")
            graphs = LocalGraphStore(store)
            graph = graphs.graph_version(name, version) if version else graphs.graph(name)
            lib = load_library(graph, load_dataset(store, name))
            metrics = evaluate_result(args.result, lib, args.audio_file)
            _print_json({"out": args.result, "rows": metrics["rows"]})
            return 0
        if not args.audio or not args.dataset or not args.out:
            raise SpecError(
                "eval needs AUDIO..., --dataset and --out (or --result DIR)",
                code="eval_usage",
                field="audio",
            )
        parsed = parse_spec(args.dataset, _read_spec(args.spec))
        graph = LocalGraphStore(store).graph(args.dataset)
        songs = [load_song(a, graph=graph) for a in args.audio]  # bad audio: before the library
        lib = load_library(graph, load_dataset(store, args.dataset))
        metrics = evaluate(
            songs,
            lib,
            parsed,
            args.out,
            args.rows,
            progress=lambda song, row: print(f"{song}: {row}", file=sys.stderr),
        )
        _print_json({"out": args.out, "seconds": metrics["seconds"], "rows": metrics["rows"]})
        return 0

    p.set_defaults(func=run)


def _add_quickstart(sub) -> None:
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


def _add_preview(sub) -> None:
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


def _add_train(sub) -> None:
    p = sub.add_parser("train", help="train the learned style or rhythm embedding (CPU)")
    t_sub = p.add_subparsers(dest="train_command", required=True)
    for kind in ("style", "rhythm"):
        k = t_sub.add_parser(kind, help=f"train the {kind} model (docs/embeddings.md)")
        k.add_argument("--manifest", required=True, help="training manifest (JSON or YAML)")
        k.add_argument("--out", required=True, help="folder for checkpoint, metrics, model file")
        k.add_argument("--epochs", type=int, default=20)
        k.add_argument("--seed", type=int, default=0)
        k.add_argument("--resume", action="store_true", help="continue from --out/checkpoint.pt")
        if kind == "style":
            k.add_argument(
                "--phase1-epochs", type=int, default=None, help="unpaired epochs (default half)"
            )
        k.set_defaults(func=lambda args, kind=kind: _run_train(kind, args))
    d = t_sub.add_parser("make-data", help="generate the small paired training set")
    d.add_argument("--out", required=True)
    d.add_argument("--songs", type=int, default=10)
    d.add_argument("--bars", type=int, default=4, help="bars per song section")
    d.add_argument("--seed", type=int, default=0)

    def make_data(args) -> int:
        from dancegraph.embed.data import write_paired_set

        print(write_paired_set(args.out, args.songs, args.bars, args.seed))
        return 0

    d.set_defaults(func=make_data)


def _run_train(kind: str, args) -> int:
    from dancegraph.embed.train import train

    summary = train(
        kind,
        args.manifest,
        args.out,
        epochs=args.epochs,
        seed=args.seed,
        resume=args.resume,
        phase1_epochs=getattr(args, "phase1_epochs", None),
    )
    _print_json(summary)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        result = args.func(args)
    except DanceGraphError as exc:
        print(f"error [{exc.code}]: {exc.message}", file=sys.stderr)
        return 2
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
