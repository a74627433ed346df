"""Learned embeddings in a graph: node styles and signatures at build, music terms at search.

Build (``dancegraph dataset build NAME --embedding PATH [--rhythm-model PATH]``): each original
bar's style is E_D of the 8-s ``phrase_positions`` window from its downbeat, and (with a rhythm
model) its signature is the top-1 of E_DR + E_RS on its ``bar_rhythm_features``; augmented nodes
take the values of the bar they came from (``node_source[:, 0]``). The model files are copied
content-addressed into the object store (``models/<kind>-<hash12>.dgm``) and the manifest's
``embedding`` entry names them: ``version`` (the style model's, or ``descriptor-v1``),
``style_model`` / ``rhythm_model`` (kind, version, sha256, store key, classes, training).

Search (``graph.search.music_inputs``): where the song's audio is at hand (``render.synthesize``,
the worker's job pipeline, ``dancegraph eval``), ``add_music_terms`` puts the graph's learned music inputs into the
``MusicAnalysis``, keyed by each model's content hash: ``learned_style`` = E_M of the 8-s log-mel
window from each bar's start (the same window E_D sees for a dance bar), ``learned_topk`` = the
rhythm model's top-3 (E_MR + E_RS on ``bar_onset_rms`` and the bar's descriptor style). The
search uses them when the hashes match the graph's models. Otherwise (an analysis made without
the audio, or for another model) the music style is the *descriptor bridge*: a ridge map from the
descriptor space (``descriptor-v1``, shared by both modalities) into the learned space, fitted at
build on the graph's original bars (descriptor style → E_D style) and stored in the manifest; the
rhythm top-3 is then computed at search from ``bar_onset_rms``. The search reports which source
it used (``report["music_style"]``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dancegraph.embed import descriptor
from dancegraph.errors import SpecError

if TYPE_CHECKING:  # the model module loads torch: imported where a model is loaded
    from dancegraph.embed.model import LoadedModel

BRIDGE_RIDGE = 1e-2


def model_key(model: LoadedModel) -> str:
    """Object-store key of a model file (content-addressed)."""
    return f"models/{model.version}.dgm"


def dance_inputs(dataset, clips: list[str], clip: np.ndarray, bar: np.ndarray, kinds: set[str]):
    """Per bar of a ``BarSet`` (``clips``, ``clip (Nb,)``, ``bar (Nb,)``): the style input
    ``(Nb, 3, 18, 240)`` if 'style' in ``kinds``, the rhythm input ``(Nb, 5, 60)`` if 'rhythm'."""
    from dancegraph.motion.features import bar_rhythm_features, phrase_positions, rhythm_curves

    phrases, rhythm = [], []
    motions: dict[str, tuple] = {}
    for c, b in zip(clip, bar, strict=True):
        cid = clips[int(c)]
        if cid not in motions:
            motions.clear()  # bars of a clip are contiguous: keep one clip in memory
            m = dataset.motion(cid)
            motions[cid] = (m, rhythm_curves(m) if "rhythm" in kinds else None)
        motion, curves = motions[cid]
        beats = np.asarray(dataset.bar(f"{cid}:{int(b)}").beat_times, dtype=float)
        if "style" in kinds:
            phrases.append(phrase_positions(motion, beats[0]))
        if "rhythm" in kinds:
            rhythm.append(bar_rhythm_features(motion, beats[0], beats[4], curves))
    return (
        np.stack(phrases) if phrases else None,
        np.stack(rhythm) if rhythm else None,
    )


def fit_bridge(desc: np.ndarray, learned: np.ndarray) -> list[list[float]]:
    """Ridge map ``(33, 32)`` (last row: bias) from descriptor style to learned style."""
    x = np.hstack([desc, np.ones((len(desc), 1))]).astype(np.float64)
    reg = BRIDGE_RIDGE * len(x) * np.eye(x.shape[1])
    reg[-1, -1] = 0.0  # the bias is not shrunk
    w = np.linalg.solve(x.T @ x + reg, x.T @ learned.astype(np.float64))
    return np.round(w, 6).tolist()


def node_embeddings(
    dataset,
    clips: list[str],
    clip: np.ndarray,
    bar: np.ndarray,
    desc_style: np.ndarray,
    style_model: LoadedModel | None,
    rhythm_model: LoadedModel | None,
) -> dict:
    """Learned ``style (Nb, 32)`` and ``signature (Nb,)`` (index into ``COMMON_SIGNATURES``) of
    the original bars, either None when its model is absent, and the manifest entry parts."""
    kinds = {m.kind for m in (style_model, rhythm_model) if m is not None}
    phrases, rhythm_x = dance_inputs(dataset, clips, clip, bar, kinds)
    out: dict = {"style": None, "signature": None, "entry": {}}
    if style_model is not None:
        out["style"] = style_model.dance_style(phrases)
        out["entry"]["version"] = style_model.version
        out["entry"]["style_model"] = {**style_model.describe(), "key": model_key(style_model)}
        out["entry"]["bridge"] = fit_bridge(desc_style, out["style"])
    if rhythm_model is not None:
        scores = rhythm_model.signature_scores("dance", rhythm_x, desc_style)
        out["signature"] = scores.argmax(1)
        out["entry"]["rhythm_model"] = {**rhythm_model.describe(), "key": model_key(rhythm_model)}
    return out


def store_models(store, *models: LoadedModel | None) -> None:
    """Copy the model files into the object store under ``model_key`` (once per content)."""
    for m in models:
        if m is not None and not store.exists(model_key(m)):
            store.put_file(model_key(m), m.path)


def store_root(graph) -> Path | None:
    """The object store a graph artifact was loaded from (where its model files are)."""
    return graph.path.parents[2] if graph.path is not None else None


def load_graph_models(graph) -> list[LoadedModel]:
    """Load and validate the learned models a graph was built with (none for a descriptor
    graph), so a corrupted, modified or wrong-version model file fails when the graph is loaded
    (``ModelFileError`` naming the file), not in the middle of a job; cached per process."""
    from dancegraph.embed.model import load_model

    entry = graph.manifest.get("embedding") or {}
    records = [entry[k] for k in ("style_model", "rhythm_model") if entry.get(k)]
    root = store_root(graph)
    if not records or root is None:
        return []
    return [load_model(root / rec["key"], sha256=rec["sha256"]) for rec in records]


def bridged_style(entry: dict, music_desc: np.ndarray) -> np.ndarray:
    """Music style ``(T, 32)`` in a graph's space: the descriptor style itself, or bridged into
    the learned space when the graph's ``embedding`` entry has a style model."""
    if "bridge" not in entry:
        return music_desc
    w = np.asarray(entry["bridge"], dtype=np.float64)
    return (np.hstack([music_desc, np.ones((len(music_desc), 1))]) @ w).astype(np.float32)


def music_topk(
    record: dict, store_root: Path, bars: np.ndarray, onset_rms: np.ndarray, k: int = 3
) -> np.ndarray:
    """``(T, k)`` top signatures of the music bars ``bars (T, 2)`` s by the rhythm model of a
    manifest ``record``, from their ``bar_onset_rms (T, 2, 200)`` and descriptor style."""
    from dancegraph.embed.model import load_model

    bars = np.asarray(bars, dtype=float).reshape(-1, 2)
    desc = descriptor.embed_music(bars[:, 1] - bars[:, 0], onset_rms)
    model = load_model(Path(store_root) / record["key"], sha256=record["sha256"])
    scores = model.signature_scores("music", onset_rms, desc)
    return np.argsort(-scores, axis=1, kind="stable")[:, :k]


def add_music_terms(analysis, graph, audio):
    """``analysis`` (a ``MusicAnalysis``) with ``graph``'s learned music inputs added, keyed by
    model sha256: ``learned_style`` ``(B, 32)`` E_M of the 8-s window from each bar's start, and
    ``learned_topk`` ``(B, 3)`` the rhythm model's top-3. A copy; terms already there are kept,
    and a graph without learned models adds nothing. ``audio``: the song's file (decoded at
    16 kHz) or ``(y, sr)`` mono samples; read only for a style model."""
    import dataclasses

    entry = graph.manifest.get("embedding") or {}
    root = store_root(graph)
    style_rec, rhythm_rec = entry.get("style_model"), entry.get("rhythm_model")
    styles, topks = dict(analysis.learned_style), dict(analysis.learned_topk)
    bars = np.asarray(analysis.bars, dtype=float).reshape(-1, 2)
    if root is None or len(bars) == 0 or (style_rec is None and rhythm_rec is None):
        return analysis
    if style_rec is not None and style_rec["sha256"] not in styles:
        from dancegraph.embed.model import load_model
        from dancegraph.music.decode import load_audio
        from dancegraph.music.features import LOGMEL_SR, music_logmel

        model = load_model(root / style_rec["key"], sha256=style_rec["sha256"])
        y, sr = audio if isinstance(audio, tuple) else load_audio(audio, sr=LOGMEL_SR)
        styles[model.sha256] = model.music_style(music_logmel(y, sr), bars[:, 0])
    onset = np.asarray(analysis.bar_onset_rms, dtype=float)
    if rhythm_rec is not None and rhythm_rec["sha256"] not in topks and len(onset) == len(bars):
        topks[rhythm_rec["sha256"]] = music_topk(rhythm_rec, root, bars, onset)
    return dataclasses.replace(analysis, learned_style=styles, learned_topk=topks)


def analysis_terms(
    entry: dict, analysis, n_bars: int
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The E_M style ``(T, 32)`` and rhythm top-3 ``(T, 3)`` that ``analysis`` carries for the
    models of a graph's ``embedding`` entry; None where it carries none for that model (or the
    graph has none). A carried array of the wrong shape raises ``analysis_invalid``."""
    out: list[np.ndarray | None] = []
    for kind, attr, width in (
        ("style_model", "learned_style", 32),
        ("rhythm_model", "learned_topk", 3),
    ):
        rec = entry.get(kind)
        arr = (getattr(analysis, attr, None) or {}).get(rec["sha256"]) if rec else None
        if arr is not None and rec is not None:
            arr = np.asarray(arr)
            if arr.shape[0] != n_bars or arr.shape[1:] != (width,):
                raise SpecError(
                    f"analysis.{attr}[{rec['sha256'][:12]}] has shape {arr.shape}, expected "
                    f"({n_bars}, {width})",
                    code="analysis_invalid",
                    field=f"analysis.{attr}",
                )
        out.append(arr)
    return out[0], out[1]
