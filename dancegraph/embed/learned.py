"""Learned embeddings in a graph: node styles and signatures at build, music terms at search.

Build (``dancegraph dataset build NAME --embedding PATH [--rhythm-model PATH]``): each original
bar's style is E_D of the 8-s ``phrase_positions`` window from its downbeat, and (with a rhythm
model) its signature is the top-1 of E_DR + E_RS on its ``bar_rhythm_features``; augmented nodes
take the values of the bar they came from (``node_source[:, 0]``). The model files are copied
content-addressed into the object store (``models/<kind>-<hash12>.dgm``) and the manifest's
``embedding`` entry names them: ``version`` (the style model's, or ``descriptor-v1``),
``style_model`` / ``rhythm_model`` (kind, version, sha256, store key, classes, training).

Search: the music analysis carries per-bar ``bar_onset_rms`` but not the audio, so
- the rhythm model's top-3 for each music bar comes from E_MR + E_RS on ``bar_onset_rms`` and the
  bar's descriptor style;
- the music style of a graph with a learned style is the *descriptor bridge*: a ridge map from
  the descriptor space (``descriptor-v1``, shared by both modalities) into the learned space,
  fitted at build on the graph's original bars (descriptor style → E_D style) and stored in the
  manifest. E_M itself (``LoadedModel.music_style``) needs the song's log-mel windows, which the
  analysis does not carry yet.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dancegraph.embed.model import LoadedModel, load_model

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


def music_style(entry: dict, music_desc: np.ndarray) -> np.ndarray:
    """Music style ``(T, 32)`` in a graph's space: the descriptor style itself, or bridged into
    the learned space when the graph's ``embedding`` entry has a style model."""
    if "bridge" not in entry:
        return music_desc
    w = np.asarray(entry["bridge"], dtype=np.float64)
    return (np.hstack([music_desc, np.ones((len(music_desc), 1))]) @ w).astype(np.float32)


def music_topk(
    entry: dict, store_root: Path | None, onset_rms: np.ndarray, music_desc: np.ndarray, k: int = 3
) -> np.ndarray | None:
    """``(T, k)`` top signatures of the music bars by the graph's rhythm model; None without one
    (or without the bars' onset/RMS curves)."""
    rec = entry.get("rhythm_model")
    if (
        rec is None
        or store_root is None
        or onset_rms.ndim != 3
        or len(onset_rms) != len(music_desc)
    ):
        return None
    model = load_model(Path(store_root) / rec["key"], sha256=rec["sha256"])
    scores = model.signature_scores("music", onset_rms, music_desc)
    return np.argsort(-scores, axis=1, kind="stable")[:, :k]
