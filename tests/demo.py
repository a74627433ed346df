"""The project's own test material: the demo dance library in a store, and a generated song."""

from __future__ import annotations

import json
from pathlib import Path

from dancegraph.graph.build import build_graph
from dancegraph.motion.dataset import import_dataset, load_dataset
from dancegraph.motion.demo import write_demo_library
from dancegraph.music.generator import Song, generate_song, write_song
from dancegraph.store import FileStore, ObjectStore


def demo_store(root: Path, build: bool = True) -> ObjectStore:
    """A store under ``root/store`` holding the demo library as dataset ``demo`` (and, with
    ``build``, its graph)."""
    store = FileStore(root / "store")
    lib = write_demo_library(root / "lib")
    import_dataset(lib, "demo", store, json.loads((lib / "manifest.json").read_text()))
    if build:
        build_graph(load_dataset(store, "demo"), store)
    return store


def demo_song(root: Path, form: tuple[str, ...] = ("A", "B", "A")) -> tuple[Path, Song]:
    """The generated test song (seed 21, 124 BPM, 4/4, 4-bar sections) as ``root/song.wav``."""
    song = generate_song(
        21, meter=4, tempo_bpm=124.0, form=list(form), section_bars={"A": 4, "B": 4}
    )
    wav, _ = write_song(song, root, "song")
    return wav, song


def demo_cli(command: str, audio: Path, store: ObjectStore, out: Path, *options: str) -> int:
    """Run ``dancegraph COMMAND AUDIO --dataset demo --out OUT [OPTIONS] --store STORE`` in this
    process; its exit code."""
    from dancegraph.cli import main

    argv = [command, str(audio), "--dataset", "demo", "--out", str(out), *options]
    return main([*argv, "--store", str(store.root)])
