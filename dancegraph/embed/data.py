"""Training data for the learned embeddings: the manifest format, its loader, a paired generator.

Manifest (JSON, or YAML with the same keys; paths relative to the manifest's folder)::

    format: dancegraph-train/1
    style_dims: [tempo, quality]        # two style dimensions, as in ChoreoMaster's dataset
    music:                              # labelled music: one entry per stretch of one style
      - id: song000-A
        audio: music/song000.wav
        bars: [[0.25, 2.92], ...]       # (B, 2) start/end seconds of 4-beat bars
        style: {tempo: slow, quality: groove}
        signatures: ["01010101", ...]   # one 8-slot rhythm signature per bar (slot 0 rightmost)
        split: train                    # train | test (held out), default train
    dance:                              # labelled dance
      - id: song000-A-dance
        motion: dance/song000-A.bvh
        fps: 60                         # optional: overrides the file's frame rate
        scale: 1.0                      # optional: to metres
        bars: [[0.0, 0.5, 1.0, 1.5, 2.0], ...]   # (B, 5) the 4 beats and the next downbeat, s
        style: {tempo: slow, quality: groove}
        signatures: [...]               # optional for style training, needed for rhythm
        split: train
    pairs:                              # paired music + dance: bar i of one with bar i of other
      - {music: song000-A, dance: song000-A-dance}

A bar's style class is its style values joined by ``/`` in ``style_dims`` order (``slow/groove``).
The style inputs are an 8-s window from each bar's start: ``logmel_window`` (music) and
``phrase_positions`` (dance), the inputs the deployed models see; rhythm inputs are
``bar_onset_rms`` and ``bar_rhythm_features`` per bar, with the bar's descriptor style.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dancegraph.embed import descriptor
from dancegraph.errors import DanceGraphError

FORMAT = "dancegraph-train/1"

#: Generated paired set: drum groove → the demo dancer's movement quality.
GROOVE_QUALITY = {
    "rock": "groove",
    "half_time": "groove",
    "funk": "pop",
    "four_floor": "step",
    "disco": "step",
}
QUALITIES = ("groove", "pop", "step")
#: Generated paired set: tempo bands (BPM) of the style dimension ``tempo``.
TEMPO_BANDS = {"slow": (80.0, 100.0), "fast": (120.0, 140.0)}
PHRASE_S = 8.0  # the style windows' length


class TrainingDataError(DanceGraphError):
    """A training manifest that cannot be trained on (codes training_data_*)."""

    code = "training_data_invalid"
    status = 422


@dataclass
class Branch:
    """Per-bar samples of one modality: inputs, style class, signature bits, split, entry."""

    style_x: list[np.ndarray] = field(default_factory=list)
    rhythm_x: list[np.ndarray] = field(default_factory=list)
    desc: list[np.ndarray] = field(default_factory=list)
    label: list[str] = field(default_factory=list)
    bits: list[np.ndarray | None] = field(default_factory=list)
    test: list[bool] = field(default_factory=list)
    entry: dict[str, list[int]] = field(default_factory=dict)  # entry id → sample indices

    def __len__(self) -> int:
        return len(self.label)


@dataclass
class TrainingSet:
    """Loaded samples of a manifest; ``pairs (P, 2)`` music and dance sample indices."""

    sha256: str
    style_dims: list[str]
    music: Branch
    dance: Branch
    pairs: np.ndarray


def read_manifest(path: str | Path) -> tuple[dict, str]:
    """Parse and check a training manifest; returns ``(manifest, sha256 of its bytes)``."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise TrainingDataError(f"training manifest {p}: {exc.strerror}", field=str(p)) from None
    try:
        data = yaml.safe_load(raw) if p.suffix in (".yaml", ".yml") else json.loads(raw)
    except (yaml.YAMLError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise TrainingDataError(
            f"training manifest {p} is not valid: {exc}", field=str(p)
        ) from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise TrainingDataError(f"training manifest {p}: format must be {FORMAT!r}", field=str(p))
    dims = data.get("style_dims")
    if not isinstance(dims, list) or not dims:
        raise TrainingDataError(f"training manifest {p}: style_dims must be a non-empty list")
    for key in ("music", "dance", "pairs"):
        if not isinstance(data.get(key, []), list):
            raise TrainingDataError(f"training manifest {p}: {key} must be a list", field=key)
    return data, hashlib.sha256(raw).hexdigest()


def _label(entry: dict, dims: list[str]) -> str:
    style = entry.get("style") or {}
    missing = [d for d in dims if d not in style]
    if missing:
        raise TrainingDataError(f"entry {entry.get('id')!r} has no style value for {missing}")
    return "/".join(str(style[d]) for d in dims)


def _bits(entry: dict, n: int) -> list[np.ndarray | None]:
    from dancegraph.rhythm.signatures import to_bits

    sigs = entry.get("signatures")
    if sigs is None:
        return [None] * n
    if len(sigs) != n:
        raise TrainingDataError(f"entry {entry.get('id')!r}: {len(sigs)} signatures for {n} bars")
    try:
        return [to_bits(s) for s in sigs]
    except ValueError as exc:
        raise TrainingDataError(f"entry {entry.get('id')!r}: {exc}") from None


def _load_music(entries: list[dict], root: Path, dims: list[str], kind: str) -> Branch:
    from dancegraph.music.decode import load_audio
    from dancegraph.music.features import bar_onset_rms, frame_features, logmel_window, music_logmel

    out = Branch()
    current: tuple[Path | None, Any] = (None, None)  # entries of one song follow each other
    for e in entries:
        bars = np.asarray(e.get("bars", []), dtype=float).reshape(-1, 2)
        label = _label(e, dims)
        bits = _bits(e, len(bars))
        audio = root / str(e.get("audio"))
        if current[0] != audio:
            y, sr = load_audio(audio, min_seconds=None)
            current = (audio, music_logmel(y, sr) if kind == "style" else frame_features(y, sr))
        if kind == "style":
            out.style_x.extend(logmel_window(current[1], s) for s in bars[:, 0])
        else:
            xs = bar_onset_rms(current[1], bars)
            out.rhythm_x.extend(xs)
            out.desc.extend(descriptor.embed_music(bars[:, 1] - bars[:, 0], xs))
        out.entry[str(e["id"])] = list(range(len(out), len(out) + len(bars)))
        out.label.extend([label] * len(bars))
        out.bits.extend(bits)
        out.test.extend([e.get("split", "train") == "test"] * len(bars))
    return out


def _dance_positions(motion, beat_times: np.ndarray, frames: int = 48) -> np.ndarray:
    """``(B, frames, K, 3)`` beat-aligned main-joint positions of bars (the descriptor input):
    beat k at sample k·frames/4, through the renderer's beat warp (``retime.Warp``), as the graph
    build samples its nodes."""
    from dancegraph.motion.fk import canonical_positions, forward_kinematics
    from dancegraph.motion.retime import Warp
    from dancegraph.motion.stitch import main_joint_keys

    pos, rot = forward_kinematics(motion)
    pts = canonical_positions(motion.skeleton, pos, rot, main_joint_keys(motion.skeleton))
    t = np.arange(pts.shape[0]) / motion.fps
    flat = pts.reshape(len(t), -1)
    out = []
    for bt in beat_times:
        ts = Warp(np.arange(5.0), bt)(np.arange(frames) * 4.0 / frames)
        out.append(np.stack([np.interp(ts, t, c) for c in flat.T], axis=1))
    return np.stack(out).reshape(len(beat_times), frames, -1, 3)


def _load_dance(entries: list[dict], root: Path, dims: list[str], kind: str) -> Branch:
    from dancegraph.motion.bvh import read_bvh
    from dancegraph.motion.features import bar_rhythm_features, phrase_positions, rhythm_curves

    out = Branch()
    raw_desc = []
    for e in entries:
        beats = np.asarray(e.get("bars", []), dtype=float).reshape(-1, 5)
        label = _label(e, dims)
        bits = _bits(e, len(beats))
        motion = read_bvh(
            root / str(e.get("motion")), scale=float(e.get("scale", 1.0)), fps=e.get("fps")
        )
        if kind == "style":
            out.style_x.extend(phrase_positions(motion, b[0]) for b in beats)
        else:
            curves = rhythm_curves(motion)
            out.rhythm_x.extend(bar_rhythm_features(motion, b[0], b[4], curves) for b in beats)
            raw_desc.append(
                descriptor.dance_descriptors(
                    _dance_positions(motion, beats), beats[:, 4] - beats[:, 0]
                )
            )
        out.entry[str(e["id"])] = list(range(len(out), len(out) + len(beats)))
        out.label.extend([label] * len(beats))
        out.bits.extend(bits)
        out.test.extend([e.get("split", "train") == "test"] * len(beats))
    if raw_desc:
        raw = np.concatenate(raw_desc)
        out.desc = list(descriptor.embed(raw, descriptor.fit_stats(raw)))
    return out


def load_training_set(path: str | Path, kind: str) -> TrainingSet:
    """Load a manifest's samples for training a ``kind`` ('style' | 'rhythm') model."""
    data, sha = read_manifest(path)
    root = Path(path).parent
    dims = [str(d) for d in data["style_dims"]]
    music = _load_music(data.get("music", []), root, dims, kind)
    dance = _load_dance(data.get("dance", []), root, dims, kind)
    pairs: list[tuple[int, int]] = []
    for pr in data.get("pairs", []):
        m, d = music.entry.get(str(pr.get("music"))), dance.entry.get(str(pr.get("dance")))
        if m is None or d is None:
            raise TrainingDataError(f"pair {pr} names an entry that the manifest does not have")
        if len(m) != len(d):
            raise TrainingDataError(f"pair {pr}: {len(m)} music bars but {len(d)} dance bars")
        pairs.extend(zip(m, d, strict=True))
    return TrainingSet(sha, dims, music, dance, np.array(pairs, dtype=np.int64).reshape(-1, 2))


def write_paired_set(out_dir: str | Path, n_songs: int = 10, bars: int = 4, seed: int = 0) -> Path:
    """Generate a small paired set and its manifest (``manifest.json`` in ``out_dir``).

    Song k: a generated 4/4 song (form A B, ``bars`` bars per section) at a tempo drawn from the
    ``TEMPO_BANDS`` band of k (alternating slow, fast), section A in the quality k // 2 (cycled
    over ``QUALITIES``, section B as drawn); each section is one music entry with the
    style ``{tempo: band, quality: GROOVE_QUALITY[its drum groove]}`` and its bars' true accent
    signatures. Its dance partner is the demo dancer performing that section: the movement
    quality of the style, the song's tempo, and the song's bar signatures as key poses. Every
    fifth song is held out (``split: test``). Returns the manifest path.
    """
    from dancegraph.motion.bvh import write_bvh
    from dancegraph.motion.contacts import clean_foot_skate
    from dancegraph.motion.demo import DemoClip, make_clip
    from dancegraph.music.generator import generate, random_config, write_song

    out = Path(out_dir)
    (out / "music").mkdir(parents=True, exist_ok=True)
    (out / "dance").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    music, dance, pairs = [], [], []
    for k in range(n_songs):
        band = list(TEMPO_BANDS)[k % len(TEMPO_BANDS)]
        lo, hi = TEMPO_BANDS[band]
        tempo = float(rng.uniform(lo, hi))
        # balance the classes: section A's groove must give quality k // 2 (cycled); the
        # generator draws grooves from the seed, so try seeds until one does
        want = QUALITIES[(k // len(TEMPO_BANDS)) % len(QUALITIES)]
        for attempt in range(100):
            cfg = random_config(
                seed * 100_000 + k * 100 + attempt,
                meter=4,
                tempo_bpm=tempo,
                form=["A", "B"],
                section_bars={"A": bars, "B": bars},
            )
            cfg.drift, cfg.pickup_beats = 0.0, 0  # the dancer keeps a steady tempo from bar 1
            song = generate(cfg)
            if GROOVE_QUALITY[song.truth["sections"][0]["groove"]] == want:
                break
        name = f"song{k:03d}"
        write_song(song, out / "music", name)
        split = "test" if k % 5 == 4 else "train"
        for sec in song.truth["sections"]:
            quality = GROOVE_QUALITY[sec["groove"]]
            tb = song.truth["bars"][sec["start_bar"] : sec["end_bar"]]
            sigs = [b["accent_signature"] for b in tb]
            style = {"tempo": band, "quality": quality}
            mid = f"{name}-{sec['label']}"
            music.append(
                {
                    "id": mid,
                    "audio": f"music/{name}.wav",
                    "bars": [[b["start_s"], b["end_s"]] for b in tb],
                    "style": style,
                    "signatures": sigs,
                    "split": split,
                }
            )
            # danced on past the section (same quality, signatures cycled) so that the 8-s
            # window of its last bars is dance, not a held pose
            tempo = song.truth["tempo_bpm"]
            extra = int(np.ceil(PHRASE_S * tempo / 240.0))
            recipe = DemoClip(mid, quality, tempo, len(tb) + extra, tuple(sigs))
            motion, dbars, dsigs = make_clip(recipe, rng)
            dbars, dsigs = dbars[: len(tb)], dsigs[: len(tb)]
            motion, _ = clean_foot_skate(motion)
            write_bvh(motion, out / "dance" / f"{mid}.bvh")
            dance.append(
                {
                    "id": f"{mid}-dance",
                    "motion": f"dance/{mid}.bvh",
                    "bars": dbars,
                    "style": style,
                    "signatures": dsigs,
                    "split": split,
                }
            )
            pairs.append({"music": mid, "dance": f"{mid}-dance"})
    manifest = {
        "format": FORMAT,
        "description": f"generated paired set (seed {seed}, {n_songs} songs)",
        "style_dims": ["tempo", "quality"],
        "music": music,
        "dance": dance,
        "pairs": pairs,
    }
    path = out / "manifest.json"
    path.write_text(json.dumps(manifest, indent=1) + "\n")
    return path
