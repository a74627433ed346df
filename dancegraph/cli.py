"""The ``dancegraph`` command.

Each subcommand is a thin shell: parse arguments, call the library, print a result. The domain
commands register themselves in ``build_parser`` through one ``_add_*`` function per area; the
service commands (``serve``, ``worker``, ``reaper``, ``keys``, ``quickstart``, ``preview``) live
in ``services.cli`` and join through the ``dancegraph.commands`` entry-point group, so this
package never imports ``services`` and works without it.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any

from dancegraph import __version__
from dancegraph.errors import DanceGraphError

if TYPE_CHECKING:
    from dancegraph.spec import Spec

COMMAND_GROUP = "dancegraph.commands"  # entry points: callables add_commands(subparsers)


def print_json(obj: Any) -> None:
    """Print ``obj`` as indented JSON (non-JSON values as their ``str``), the commands' output."""
    json.dump(obj, sys.stdout, indent=2, default=str)
    sys.stdout.write("\n")


def _read_spec(path: str | None, dataset: str | None = None) -> Spec:
    """The constraint spec in the JSON file ``path`` (defaults without one), parsed once
    (``parse_spec``; ``dataset`` overrides the file's); SpecError naming an unreadable file."""
    from dancegraph.errors import SpecError
    from dancegraph.spec import parse_spec

    if not path:
        return parse_spec(None, dataset=dataset)
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as exc:
        raise SpecError(f"cannot read the spec {path}: {exc}", field=path) from exc
    return parse_spec(raw, dataset=dataset)


STORE_HELP = (
    "object store: a folder or s3://bucket/prefix "
    "(default: DANCEGRAPH_STORE_URL, else DANCEGRAPH_HOME's store)"
)


def open_cli_store(store: str | None):
    """The ``--store`` given (a folder or ``s3://``), else the one the environment names."""
    from dancegraph.paths import default_store, store_dir
    from dancegraph.store import open_store

    return open_store(store, store_dir()) if store else default_store()


def _warm_kernels(*modules: str) -> None:
    """Compile or load the kernels of ``modules`` (default: all) under the kernel cache's lock,
    at the start of a command that runs them (``dancegraph.jit``)."""
    from dancegraph import jit

    jit.warm_kernels(modules or jit.KERNEL_MODULES)


def build_parser() -> argparse.ArgumentParser:
    """Every command: the domain ones below, then those of the installed command groups."""
    parser = argparse.ArgumentParser(prog="dancegraph", description="Music in, dance out.")
    parser.add_argument("--version", action="version", version=f"dancegraph {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (
        _add_version,
        _add_convert,
        _add_retarget,
        _add_synthesize,
        _add_analyze,
        _add_dataset,
        _add_motion,
        _add_eval,
        _add_train,
    ):
        add(sub)
    for entry in sorted(entry_points(group=COMMAND_GROUP), key=lambda e: e.name):
        entry.load()(sub)
    return parser


def _add_version(sub) -> None:
    p = sub.add_parser("version", help="print the version as JSON")
    p.set_defaults(func=lambda args: print_json({"dancegraph": __version__}))


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
    p.add_argument(
        "--params",
        metavar="FILE",
        help="YAML or JSON file of analysis parameters to override (keys of "
        "dancegraph.music.params.AnalysisParams, nested; unknown keys are refused)",
    )

    def run(args) -> int:
        from dancegraph.music.analysis import analyze
        from dancegraph.music.params import load_params

        params = load_params(args.params) if args.params else None
        _warm_kernels("dancegraph.music.beats")
        if not args.jsonl:
            if len(args.audio) > 1:
                p.error("several files need --jsonl")
            result = analyze(args.audio[0], tempo_range=args.tempo_range, params=params)
            print_json(result.to_dict() if args.json else result.summary())
            return 0
        failed = 0
        for path in args.audio:  # one process: the models and kernels load once
            try:
                result = analyze(path, tempo_range=args.tempo_range, params=params)
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
    """``dataset import DIR --name NAME [--manifest FILE]``, ``dataset list``, ``dataset show``."""
    p = sub.add_parser("dataset", help="motion datasets in the object store")
    ds_sub = p.add_subparsers(dest="dataset_command", required=True)

    def _store(args):
        return open_cli_store(args.store)

    imp = ds_sub.add_parser("import", help="import a folder of BVH files as a dataset")
    imp.add_argument("dir", help="folder with the motion files (and optionally manifest.yaml)")
    imp.add_argument("--name", required=True, help="dataset name (letters, digits, . _ -)")
    imp.add_argument("--manifest", default=None, help="manifest file (YAML or JSON)")
    imp.add_argument("--store", default=None, help=STORE_HELP)
    imp.add_argument(
        "--json", action="store_true", help="print the report as JSON (default: a table)"
    )
    imp.add_argument(
        "--strict", action="store_true", help="publish nothing unless every take imports"
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

            report = import_dataset(
                args.dir, args.name, _store(args), manifest, progress, strict=args.strict
            )
        if args.json:
            print_json(report.to_dict())
        else:
            print(report.table())
        return 0

    imp.set_defaults(func=_import)

    ls = ds_sub.add_parser("list", help="list the stored datasets as JSON")
    ls.add_argument("--store", default=None, help=STORE_HELP)

    def _list(args) -> int:
        from dancegraph.motion.dataset import list_datasets

        print_json(list_datasets(_store(args)))
        return 0

    ls.set_defaults(func=_list)

    show = ds_sub.add_parser("show", help="a dataset's beat grids: tempo, beats and bars per clip")
    show.add_argument("name", help="dataset name")
    show.add_argument(
        "--store", default=None, help="object store root (default: DANCEGRAPH_HOME's)"
    )
    show.add_argument(
        "--json", action="store_true", help="print every beat and bar as JSON (default: a table)"
    )

    def _show(args) -> int:
        from dancegraph.motion.dataset import check_line, grid_report, load_dataset

        ds = load_dataset(_store(args), args.name)
        report = grid_report(ds)
        if args.json:
            print_json(report)
            return 0
        print(f"dataset {report['name']}  version {report['version'][:12]}")
        for c in report["clips"]:
            tempi = "/".join(f"{s['tempo_bpm']:.2f}" for s in c["sections"]) or c["tempo_bpm"]
            print(
                f"{c['id']:<14}{c['fps']:>6.0f} fps  tempo {tempi}  confidence {c['confidence']}"
                f"  {len(c['beats'])} beats  {len(c['bars'])} bars  {c['beat_source']}"
                f"  {','.join(c['flags'])}"
            )
        for clip in ds.clips:
            if clip.grid_check:
                print(check_line(clip))
        return 0

    show.set_defaults(func=_show)

    bld = ds_sub.add_parser("build", help="build (a new version of) the dataset's motion graph")
    bld.add_argument("name", help="dataset name")
    bld.add_argument(
        "--threshold", type=float, default=20.0, help="δT: largest edge cost (default 20)"
    )
    bld.add_argument("--max-degree", type=int, default=24, help="most out-edges kept per node")
    bld.add_argument("--no-mirror", action="store_true", help="skip the mirrored bars")
    bld.add_argument(
        "--no-accent-anchors",
        action="store_true",
        help="keep the takes' beat grids (do not move beats onto their kinematic beats)",
    )
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
    bld.add_argument("--store", default=None, help=STORE_HELP)
    bld.add_argument("--json", action="store_true", help="print the report as JSON")
    bld.add_argument(
        "--couple",
        action="store_true",
        help="build the couple graph of the takes the manifest declares danced together "
        "('partners'; stored as the graph NAME.couple) instead of the solo graph",
    )

    def _build(args) -> int:
        from tqdm import tqdm

        from dancegraph.graph.build import BuildParams, build_dataset_graph

        params = BuildParams(
            threshold=args.threshold,
            max_out_degree=args.max_degree,
            mirror=not args.no_mirror,
            accent_anchors=not args.no_accent_anchors,
            blend_ratio=args.blend_ratio,
            shuffle_ratio=args.shuffle_ratio,
        )
        if args.couple:
            from dancegraph.couple.graph import build_couple_graph

            print_json(build_couple_graph(_store(args), args.name, params))
            return 0
        with tqdm(total=100, unit="%", file=sys.stderr, disable=None) as bar:

            def progress(stage: str, fraction: float) -> None:
                bar.set_description_str(stage, refresh=False)
                bar.n = int(100 * fraction)  # each stage runs 0 → 100 %
                bar.refresh()

            report = build_dataset_graph(
                _store(args), args.name, params, progress, args.embedding, args.rhythm_model
            )
        if args.json:
            print_json(report)
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
    demo.add_argument("--takes", type=int, default=None, help="number of takes (default 6)")
    demo.add_argument(
        "--with-music",
        action="store_true",
        help="each take with the music it is danced to (.ogg, audio_offset_s, truth.json)",
    )

    def run_demo(args) -> None:
        from dancegraph.motion.demo import write_demo_library

        out = write_demo_library(
            args.out_dir, seed=args.seed, n_takes=args.takes, with_music=args.with_music
        )
        print_json({"dir": str(out), "files": sorted(f.name for f in out.iterdir())})

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
        print_json(
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

        summary = bvh_to_fbx(args.input, args.output, fps=args.fps, scale=args.scale)
        print_json({"output": args.output, **summary})

    p.set_defaults(func=run)


def _add_retarget(sub) -> None:
    p = sub.add_parser(
        "retarget",
        help="put a dance (BVH) on your own rig (FBX, GLB or BVH); write BVH, FBX or GLB",
    )
    p.add_argument("source", help="the dance, a BVH file (e.g. a synthesize result)")
    p.add_argument("--rig", required=True, help="the target rig: .fbx, .glb/.gltf or .bvh")
    p.add_argument(
        "--out", required=True, help="the file to write: .bvh, .fbx, .glb or .usd/.usda/.usdc"
    )
    p.add_argument("--map", default=None, help="joint mapping, JSON/YAML: role -> joint name")
    p.add_argument("--fps", type=float, default=None, help="source frame rate (default: header)")
    p.add_argument("--scale", type=float, default=1.0, help="source file units to metres")
    p.add_argument(
        "--rig-scale", type=float, default=None, help="rig metres per unit (default: from the file)"
    )
    p.add_argument(
        "--no-foot-ik", action="store_true", help="transfer rotations only: no foot planting"
    )
    p.add_argument(
        "--hand-ik",
        action="store_true",
        help="put the hands where the source's are (relative to the hips, scaled) by arm IK",
    )

    def run(args) -> None:
        from dancegraph.motion.bvh import read_bvh
        from dancegraph.motion.retarget import RetargetParams, retarget, write_on_rig
        from dancegraph.motion.rig import load_rig, read_mapping

        mapping = read_mapping(args.map) if args.map else None
        rig = load_rig(args.rig, mapping=mapping, scale=args.rig_scale)
        source = read_bvh(args.source, scale=args.scale, fps=args.fps)
        params = RetargetParams(foot_ik=not args.no_foot_ik, hand_ik=args.hand_ik)
        motion, report = retarget(source, rig, params)
        written = write_on_rig(motion, rig, args.rig, args.out)
        print_json({"out": args.out, "written": written, "rig": rig.summary(), "report": report})

    p.set_defaults(func=run)


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
    p.add_argument(
        "--rig", default=None, help="also write each alternative on this rig (.fbx, .glb, .bvh)"
    )
    p.add_argument("--map", default=None, help="with --rig: joint mapping file (role -> joint)")
    p.add_argument(
        "--couple",
        action="store_true",
        help="dance as a couple (spec couple: true): alternatives/<k>/lead.bvh and follow.bvh",
    )
    p.add_argument(
        "--follow-rig", default=None, help="with --couple: the follow's rig (--rig is the lead's)"
    )
    p.add_argument("--store", default=None, help=STORE_HELP)

    def run(args) -> None:
        from dancegraph.graph.artifact import open_graph
        from dancegraph.render import synthesize
        from dancegraph.spec import parse_spec

        spec = _read_spec(args.spec, dataset=args.dataset)
        if args.alternatives is not None:
            spec = parse_spec({**spec.model_dump(mode="json"), "alternatives": args.alternatives})
        on_rig = None
        if args.rig:
            from dancegraph.motion.retarget import RigOutput
            from dancegraph.motion.rig import load_rig, read_mapping

            mapping = read_mapping(args.map) if args.map else None
            rig = load_rig(args.rig, mapping=mapping)  # a bad rig fails before any work
            on_rig = RigOutput(rig, args.rig, [*spec.output.formats, "glb"])
        if args.couple or spec.couple:
            _synthesize_couple(args, spec, on_rig)
            return
        graph = open_graph(open_cli_store(args.store), args.dataset)
        _warm_kernels()
        done = synthesize(args.audio, graph, spec, args.out, on_rig=on_rig)
        timeline = done["timeline"]
        print_json(
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


def _synthesize_couple(args, spec: Spec, lead_rig) -> None:
    """``synthesize --couple``: the couple graph's search and the render for two; prints the
    files and each alternative's cost."""
    from dancegraph.couple.graph import open_couple_graph
    from dancegraph.couple.render import synthesize_couple
    from dancegraph.spec import parse_spec

    spec = parse_spec({**spec.model_dump(mode="json"), "couple": True})
    rigs = {"lead": lead_rig} if lead_rig is not None else {}
    if args.follow_rig:
        from dancegraph.motion.retarget import RigOutput
        from dancegraph.motion.rig import load_rig

        rigs["follow"] = RigOutput(
            load_rig(args.follow_rig), args.follow_rig, [*spec.output.formats, "glb"]
        )
    graph = open_couple_graph(open_cli_store(args.store), args.dataset)
    _warm_kernels()
    done = synthesize_couple(args.audio, graph, spec, args.out, on_rig=rigs)
    print_json(
        {
            "out": args.out,
            "files": done["files"],
            "analysis": done["analysis"],
            "graph": {"name": graph.name, "version": graph.version},
            "alternatives": [
                {"index": a["index"], "cost": a["cost"], "frames": a["frames"]}
                for a in done["timeline"]["alternatives"]
            ],
        }
    )


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
    p.add_argument("--store", default=None, help=STORE_HELP)

    def run(args) -> int:
        from dancegraph.errors import SpecError
        from dancegraph.eval.harness import evaluate, evaluate_result, load_library, load_song
        from dancegraph.graph.artifact import open_graph
        from dancegraph.motion.dataset import load_dataset

        store = open_cli_store(args.store)
        _warm_kernels()
        if args.result:
            from dancegraph.preview import read_timeline

            timeline = read_timeline(args.result)
            prov = timeline.get("provenance", {})
            name = args.dataset or prov.get("dataset", {}).get("name")
            if timeline.get("couple"):
                return _eval_couple(args.result, store, name)
            graph = open_graph(store, name, prov.get("graph", {}).get("version") or None)
            lib = load_library(graph, load_dataset(store, name))
            metrics = evaluate_result(args.result, lib, args.audio_file)
            print_json({"out": args.result, "rows": metrics["rows"], "library": metrics["library"]})
            return 0
        if not args.audio or not args.dataset or not args.out:
            raise SpecError(
                "eval needs AUDIO..., --dataset and --out (or --result DIR)",
                code="eval_usage",
                field="audio",
            )
        parsed = _read_spec(args.spec, dataset=args.dataset)
        graph = open_graph(store, args.dataset)
        # bad audio fails here, before the library is loaded
        songs = [load_song(a, graph=graph, spec=parsed) for a in args.audio]
        lib = load_library(graph, load_dataset(store, args.dataset))
        metrics = evaluate(
            songs,
            lib,
            parsed,
            args.out,
            args.rows,
            progress=lambda song, row: print(f"{song}: {row}", file=sys.stderr),
        )
        print_json(
            {
                "out": args.out,
                "seconds": metrics["seconds"],
                "rows": metrics["rows"],
                "library": metrics["library"],
            }
        )
        return 0

    p.set_defaults(func=run)


def _eval_couple(result: str, store, name: str) -> int:
    """``eval --result DIR`` of a couple result: the couple checks and each partner's seams
    (``eval.couple``), printed and written to DIR/couple_metrics.json."""
    from dancegraph.couple.graph import open_couple_graph
    from dancegraph.eval.couple import couple_reference, evaluate_couple_result
    from dancegraph.eval.harness import load_library
    from dancegraph.motion.dataset import load_dataset

    dataset = load_dataset(store, name)
    lib = load_library(open_couple_graph(store, name), dataset)
    metrics = evaluate_couple_result(result, lib, couple_reference(dataset))
    print_json({"out": result, **metrics})
    return 0


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
    print_json(summary)
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
