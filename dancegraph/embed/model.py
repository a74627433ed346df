"""Model files of the learned embeddings: a versioned header, the weights, a content hash.

Layout of a ``.dgm`` file (all of it covered by the file's sha256, its *content hash*)::

    b"DGMODEL\\n"                    8 bytes, magic
    header length                    8 bytes, little-endian unsigned
    header                           UTF-8 JSON: format, kind ('style' | 'rhythm'), config
                                     (e.g. the style classes), training (manifest sha256, seed,
                                     epochs), payload_bytes, payload_sha256
    payload                          ``torch.save`` of the state dict

Trained files are named ``<kind>-<first 12 hex of the content hash>.dgm``; ``version`` (e.g.
``style-3f2a9c0d1b7e``) names the model in graph manifests and job results. ``load_model``
checks magic, format, length and both hashes and raises ``ModelFileError`` (code
``model_file_invalid``) naming the problem; a loaded model is cached per process by path, size
and modification time.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dancegraph.embed.nets import RhythmModel, StyleModel
from dancegraph.errors import ModelFileError

MAGIC = b"DGMODEL\n"
FORMAT = 1
KINDS = ("style", "rhythm")
_CACHE: dict[tuple, LoadedModel] = {}


@dataclass
class LoadedModel:
    """A validated model: its header, network (eval mode), content hash and version name."""

    path: str
    header: dict
    net: Any  # a StyleModel or a RhythmModel (``kind`` says which)
    sha256: str

    @property
    def kind(self) -> str:
        return self.header["kind"]

    @property
    def version(self) -> str:
        return f"{self.kind}-{self.sha256[:12]}"

    def describe(self) -> dict:
        """JSON-able summary for manifests: kind, version, sha256, format, classes, training."""
        return {
            "kind": self.kind,
            "version": self.version,
            "sha256": self.sha256,
            "format": self.header["format"],
            "config": self.header["config"],
            "training": self.header.get("training", {}),
        }

    # inference -----------------------------------------------------------------------------
    @torch.no_grad()
    def music_style(self, mel: np.ndarray, starts_s: np.ndarray) -> np.ndarray:
        """``(B, 32)`` float32 style of 8-s windows starting at ``starts_s (B,)`` seconds of a
        song's ``music_logmel`` output ``mel (96, T)`` (style models only)."""
        from dancegraph.music.features import LOGMEL_HOP, LOGMEL_SR

        self._need("style")
        starts = torch.as_tensor(np.asarray(starts_s, dtype=float) * LOGMEL_SR / LOGMEL_HOP)
        z = self.net.music.embed_song(torch.as_tensor(mel, dtype=torch.float32), starts)
        return z.numpy().astype(np.float32)

    @torch.no_grad()
    def dance_style(self, phrases: np.ndarray, batch: int = 64) -> np.ndarray:
        """``(N, 32)`` float32 style of ``phrase_positions`` inputs ``(N, 3, 18, 240)``."""
        self._need("style")
        x = torch.as_tensor(np.asarray(phrases, dtype=np.float32))
        out = [self.net.dance(x[i : i + batch]) for i in range(0, len(x), batch)]
        return torch.cat(out).numpy() if out else np.zeros((0, 32), np.float32)

    @torch.no_grad()
    def signature_scores(self, branch: str, x: np.ndarray, style: np.ndarray) -> np.ndarray:
        """``(N, 13)`` probabilities over ``COMMON_SIGNATURES`` (rhythm models only).

        ``branch`` 'music' with ``x (N, 2, 200)`` (``bar_onset_rms``) or 'dance' with
        ``x (N, 5, 60)`` (``bar_rhythm_features``); ``style (N, 32)`` the bars' descriptor style.
        """
        self._need("rhythm")
        logits = self.net(
            branch,
            torch.as_tensor(np.asarray(x, dtype=np.float32)),
            torch.as_tensor(np.asarray(style, dtype=np.float32)),
        )
        return torch.softmax(logits, 1).numpy()

    def _need(self, kind: str) -> None:
        if self.kind != kind:
            raise ModelFileError(f"{self.path} is a {self.kind} model, not a {kind} model")


def build_net(kind: str, config: dict) -> torch.nn.Module:
    """A fresh network of ``kind`` for ``config`` (style: ``{"classes": [...]}``)."""
    if kind == "style":
        return StyleModel(len(config["classes"]))
    if kind == "rhythm":
        return RhythmModel()
    raise ModelFileError(f"unknown model kind {kind!r} (expected one of {KINDS})")


def save_model(
    net: torch.nn.Module, kind: str, config: dict, training: dict, out_dir: Path
) -> Path:
    """Write ``net``'s weights as ``<out_dir>/<kind>-<hash12>.dgm``; returns the path."""
    buf = io.BytesIO()
    torch.save(net.state_dict(), buf)
    payload = buf.getvalue()
    header = {
        "format": FORMAT,
        "kind": kind,
        "config": config,
        "training": training,
        "payload_bytes": len(payload),
        "payload_sha256": hashlib.sha256(payload).hexdigest(),
    }
    head = json.dumps(header, sort_keys=True).encode()
    blob = MAGIC + struct.pack("<Q", len(head)) + head + payload
    path = Path(out_dir) / f"{kind}-{hashlib.sha256(blob).hexdigest()[:12]}.dgm"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(blob)
    os.replace(tmp, path)
    return path


def load_model(path: str | os.PathLike, sha256: str | None = None) -> LoadedModel:
    """Read and validate a model file (cached per process); ``sha256``: the expected content hash
    (a graph manifest's record), checked too. Raises ``ModelFileError`` naming the problem."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError as exc:
        raise ModelFileError(
            f"model file {p} cannot be read: {exc.strerror}", field=str(p)
        ) from None
    key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
    model = _CACHE.get(key)
    if model is None:
        model = _read(p)
        _CACHE[key] = model
    if sha256 is not None and model.sha256 != sha256:
        raise ModelFileError(
            f"model file {p} has content hash {model.sha256[:12]}, expected {sha256[:12]}: "
            "a different or modified model",
            field=str(p),
        )
    return model


def _read(p: Path) -> LoadedModel:
    def bad(why: str) -> ModelFileError:
        return ModelFileError(f"model file {p} is invalid: {why}", field=str(p))

    blob = p.read_bytes()
    if not blob.startswith(MAGIC):
        raise bad("not a DanceGraph model file (bad magic)")
    if len(blob) < len(MAGIC) + 8:
        raise bad("truncated header")
    (n,) = struct.unpack("<Q", blob[len(MAGIC) : len(MAGIC) + 8])
    start = len(MAGIC) + 8
    try:
        header = json.loads(blob[start : start + n].decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise bad("corrupted or truncated header") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        got = header.get("format") if isinstance(header, dict) else None
        raise bad(f"format version {got!r}, this build reads version {FORMAT}")
    if header.get("kind") not in KINDS:
        raise bad(f"unknown kind {header.get('kind')!r}")
    payload = blob[start + n :]
    if len(payload) != header.get("payload_bytes"):
        raise bad(f"truncated: {len(payload)} of {header.get('payload_bytes')} payload bytes")
    if hashlib.sha256(payload).hexdigest() != header.get("payload_sha256"):
        raise bad("corrupted: the weights do not match their hash")
    net = build_net(header["kind"], header["config"])
    try:
        state = torch.load(io.BytesIO(payload), weights_only=True)
        net.load_state_dict(state)
    except Exception as exc:  # a payload that passed the hash but does not fit the network
        raise bad(f"weights do not fit the {header['kind']} network: {exc}") from None
    net.eval()
    return LoadedModel(str(p), header, net, hashlib.sha256(blob).hexdigest())
