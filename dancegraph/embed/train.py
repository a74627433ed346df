"""Training of the style and rhythm models (``dancegraph train style|rhythm``).

Style: phase 1 (the first ``phase1_epochs``) trains each branch on its own labelled bars (Eq. 1);
phase 2 trains both on the paired bars with the MSE between Z_M and Z_D added (Eq. 2), its weight
λ5 warmed up linearly over the first ``PAIR_WARMUP`` phase-2 epochs, the learning rate lowered
to ``PHASE2_LR`` of phase 1's (at full rate the λ5 term threw the weights about: loss and paired
distance jumped back up between epochs), and a variance hinge that
keeps each branch's embeddings spread (``nets.variance_hinge``; without it phase 2 collapsed every
bar onto one point). Without pairs, every epoch is phase 1. Rhythm: both branches and the shared classifier on every labelled
bar (Eq. 3); the style vector fed to E_RS is the bar's descriptor style (``descriptor-v1``),
which the graph build and the music analysis both have without audio or a style model.

Determinism: every epoch reseeds torch and the batch order from ``(seed, epoch)``; the checkpoint
(``checkpoint.pt``, written after each epoch) holds the weights and the optimiser state, so a run
resumed from epoch k ends with the same weights as an uninterrupted one. Each epoch appends a line
to ``metrics.jsonl`` (loss, accuracy on the train and held-out bars, paired distance); the final
model file is ``<kind>-<hash12>.dgm`` (``model.save_model``), described by ``model.json``.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dancegraph.embed.data import TrainingDataError, TrainingSet, load_training_set
from dancegraph.embed.model import build_net, load_model, save_model
from dancegraph.embed.nets import LAMBDAS
from dancegraph.rhythm.signatures import COMMON_BITS, COMMON_SIGNATURES, SLOT_WEIGHTS

PAIR_WARMUP = 3  # phase-2 epochs over which λ5 rises linearly to its full value
PHASE2_LR = 0.25  # phase 2's learning rate as a fraction of ``lr``
CHECKPOINT = "checkpoint.pt"
METRICS = "metrics.jsonl"
Progress = Callable[[str], None]


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _check_style(ts: TrainingSet) -> list[str]:
    labels = [
        lab for b in (ts.music, ts.dance) for lab, t in zip(b.label, b.test, strict=True) if not t
    ]
    if not labels:
        raise TrainingDataError(
            "the training manifest has no training bars (no music or dance entries, or all held out)",
            code="training_data_empty",
        )
    classes = sorted(set(labels))
    if len(classes) < 2:
        raise TrainingDataError(
            f"the training manifest has a single style class ({classes[0]!r}): a style "
            "classifier needs at least two",
            code="training_data_single_class",
        )
    return classes


def _rhythm_targets(bits: list) -> np.ndarray:
    """Nearest common signature per bar (-1 where the bar has no signature)."""
    out = np.full(len(bits), -1)
    for i, b in enumerate(bits):
        if b is not None:
            out[i] = int(np.argmin((np.abs(COMMON_BITS - b) * SLOT_WEIGHTS).sum(1)))
    return out


def _check_rhythm(ts: TrainingSet) -> None:
    targets = [
        t
        for b in (ts.music, ts.dance)
        for t, test in zip(_rhythm_targets(b.bits), b.test, strict=True)
        if t >= 0 and not test
    ]
    if not targets:
        raise TrainingDataError(
            "the training manifest has no training bars with rhythm signatures",
            code="training_data_empty",
        )
    if len(set(targets)) < 2:
        raise TrainingDataError(
            f"every training bar has the signature {COMMON_SIGNATURES[targets[0]]}: the rhythm "
            "classifier needs at least two",
            code="training_data_single_class",
        )


def _bar(steps, desc: str):
    """A progress bar over the batches of an epoch (stderr; hidden when it is not a terminal)."""
    from tqdm import tqdm

    return tqdm(steps, desc=desc, file=sys.stderr, disable=None, leave=False)


def _batches(idx: np.ndarray, size: int, rng: np.random.Generator) -> list[np.ndarray]:
    idx = rng.permutation(idx)
    return [idx[i : i + size] for i in range(0, len(idx), size)]


def _t(xs: list, idx) -> torch.Tensor:
    return torch.as_tensor(np.stack([xs[i] for i in idx]).astype(np.float32))


@torch.no_grad()
def _embed(net, branch: str, xs: list, chunk: int = 32) -> torch.Tensor:
    parts = [
        getattr(net, branch)(_t(xs, range(i, min(i + chunk, len(xs)))))
        for i in range(0, len(xs), chunk)
    ]
    return torch.cat(parts) if parts else torch.zeros(0, 32)


@torch.no_grad()
def style_metrics(net, ts: TrainingSet, classes: list[str]) -> dict:
    """Accuracy of each branch's classifier on train and held-out bars; mean paired distance;
    ``<branch>_spread``: the mean over the 32 dimensions of the embeddings' standard deviation
    over all the branch's bars (about 1 when spread over the sphere of radius √32, 0 collapsed)."""
    net.eval()
    out: dict = {}
    z = {}
    for name in ("music", "dance"):
        br = getattr(ts, name)
        z[name] = _embed(net, name, br.style_x)
        if not len(br):
            continue
        if len(br) > 1:
            out[f"{name}_spread"] = round(float(z[name].std(0).mean()), 4)
        pred = getattr(net, f"{name}_cls")(z[name]).argmax(1).numpy()
        truth = np.array([classes.index(lab) if lab in classes else -1 for lab in br.label])
        test = np.array(br.test)
        for split, mask in (("train", ~test), ("test", test)):
            if mask.any():
                out[f"{name}_acc_{split}"] = round(float((pred[mask] == truth[mask]).mean()), 4)
    if len(ts.pairs):
        d = torch.linalg.vector_norm(z["music"][ts.pairs[:, 0]] - z["dance"][ts.pairs[:, 1]], dim=1)
        test = np.array(ts.music.test)[ts.pairs[:, 0]]
        for split, mask in (("train", ~test), ("test", test)):
            if mask.any():
                out[f"pair_dist_{split}"] = round(float(d[torch.as_tensor(mask)].mean()), 4)
    return out


@torch.no_grad()
def rhythm_metrics(net, ts: TrainingSet) -> dict:
    """Top-1 and top-3 accuracy (nearest common signature of the truth) per branch and split."""
    net.eval()
    out: dict = {}
    for name in ("music", "dance"):
        br = getattr(ts, name)
        target = _rhythm_targets(br.bits)
        keep = np.flatnonzero(target >= 0)
        if not keep.size:
            continue
        logits = net(name, _t(br.rhythm_x, keep), _t(br.desc, keep))
        top3 = torch.topk(logits, 3, dim=1).indices.numpy()
        hit1 = top3[:, 0] == target[keep]
        hit3 = (top3 == target[keep][:, None]).any(1)
        test = np.array(br.test)[keep]
        for split, mask in (("train", ~test), ("test", test)):
            if mask.any():
                out[f"{name}_top1_{split}"] = round(float(hit1[mask].mean()), 4)
                out[f"{name}_top3_{split}"] = round(float(hit3[mask].mean()), 4)
    return out


def _style_epoch(net, opt, ts, classes, phase, rng, batch, pair_weight) -> float:
    losses = []
    if phase == 1:
        steps = []
        for name in ("music", "dance"):
            br = getattr(ts, name)
            idx = np.flatnonzero(~np.array(br.test, dtype=bool)) if len(br) else np.zeros(0, int)
            steps += [(name, b) for b in _batches(idx, batch, rng) if len(b) > 1]
        for k in _bar(rng.permutation(len(steps)), "phase 1"):
            name, b = steps[k]
            br = getattr(ts, name)
            y = torch.as_tensor([classes.index(br.label[i]) for i in b])
            loss, _, _ = net.branch_loss(name, _t(br.style_x, b), y)
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
    else:
        train_pairs = np.flatnonzero(~np.array(ts.music.test, dtype=bool)[ts.pairs[:, 0]])
        for b in _bar(_batches(train_pairs, batch, rng), "phase 2"):
            if len(b) < 2:
                continue
            mi, di = ts.pairs[b, 0], ts.pairs[b, 1]
            ym = torch.as_tensor([classes.index(ts.music.label[i]) for i in mi])
            yd = torch.as_tensor([classes.index(ts.dance.label[i]) for i in di])
            loss, _ = net.paired_loss(
                _t(ts.music.style_x, mi), ym, _t(ts.dance.style_x, di), yd, pair_weight
            )
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
    return float(np.mean(losses)) if losses else float("nan")


def _rhythm_epoch(net, opt, ts, rng, batch) -> float:
    steps = []
    for name in ("music", "dance"):
        br = getattr(ts, name)
        target = _rhythm_targets(br.bits)
        idx = np.flatnonzero((target >= 0) & ~np.array(br.test, dtype=bool))
        steps += [(name, b) for b in _batches(idx, batch, rng)]
    losses = []
    for k in _bar(rng.permutation(len(steps)), "rhythm"):
        name, b = steps[k]
        br = getattr(ts, name)
        bits = torch.as_tensor(np.stack([br.bits[i] for i in b]).astype(np.float32))
        loss = net.rhythm_loss(net(name, _t(br.rhythm_x, b), _t(br.desc, b)), bits)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return float(np.mean(losses)) if losses else float("nan")


def train(
    kind: str,
    manifest: str | Path,
    out_dir: str | Path,
    *,
    epochs: int = 20,
    seed: int = 0,
    resume: bool = False,
    phase1_epochs: int | None = None,
    batch: int = 16,
    lr: float = 2e-3,
    progress: Progress | None = _stderr,
) -> dict:
    """Train a ``kind`` model on ``manifest`` into ``out_dir``; returns the ``model.json`` dict.

    ``phase1_epochs`` (style): epochs before paired training starts (default: half). ``resume``:
    continue from ``out_dir/checkpoint.pt`` (same manifest and settings) up to ``epochs``.
    """
    if kind not in ("style", "rhythm"):
        raise TrainingDataError(f"unknown model kind {kind!r} (style or rhythm)", field="kind")
    if epochs < 1:
        raise TrainingDataError("epochs must be at least 1", field="epochs")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda _line: None)
    t0 = time.perf_counter()
    ts = load_training_set(manifest, kind)
    config: dict[str, Any]
    if kind == "style":
        classes = _check_style(ts)
        config = {"classes": classes, "style_dims": ts.style_dims}
    else:
        _check_rhythm(ts)
        classes, config = (
            [],
            {"signatures": list(COMMON_SIGNATURES), "style_input": "descriptor-v1"},
        )
    phase1 = epochs // 2 if phase1_epochs is None else phase1_epochs
    if kind == "style" and not len(ts.pairs):
        phase1 = epochs
    settings = {"seed": seed, "epochs": epochs, "batch": batch, "lr": lr}
    if kind == "style":
        settings["phase1_epochs"] = phase1
    say(
        f"train {kind}: {len(ts.music)} music bars, {len(ts.dance)} dance bars, {len(ts.pairs)} "
        f"pairs, loaded in {time.perf_counter() - t0:.1f} s"
    )
    torch.manual_seed(seed)
    net = build_net(kind, config)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    start = 0
    ckpt_path = out / CHECKPOINT
    if resume and ckpt_path.exists():
        ckpt = torch.load(ckpt_path, weights_only=False)
        if ckpt["manifest_sha256"] != ts.sha256 or ckpt["kind"] != kind:
            raise TrainingDataError(
                f"{ckpt_path} was trained on another manifest or kind: cannot resume",
                code="checkpoint_mismatch",
            )
        net.load_state_dict(ckpt["net"])
        opt.load_state_dict(ckpt["opt"])
        start = int(ckpt["epoch"]) + 1
        say(f"resumed from {ckpt_path} after epoch {start}")
    elif not resume:
        (out / METRICS).unlink(missing_ok=True)
    metrics: dict = {}
    for epoch in range(start, epochs):
        te = time.perf_counter()
        torch.manual_seed(seed * 100_003 + epoch)
        rng = np.random.default_rng([seed, epoch])
        net.train()
        if kind == "style":
            phase = 1 if epoch < phase1 else 2
            # a function of the epoch alone, so a resumed run warms up as an uninterrupted one
            pair_weight = LAMBDAS["pair"] * min(1.0, max(0, epoch - phase1 + 1) / PAIR_WARMUP)
            for group in opt.param_groups:
                group["lr"] = lr * (PHASE2_LR if phase == 2 else 1.0)
            loss = _style_epoch(net, opt, ts, classes, phase, rng, batch, pair_weight)
            metrics = style_metrics(net, ts, classes)
        else:
            phase = 1
            loss = _rhythm_epoch(net, opt, ts, rng, batch)
            metrics = rhythm_metrics(net, ts)
        row = {"epoch": epoch + 1, "phase": phase, "loss": round(loss, 5), **metrics}
        row["seconds"] = round(time.perf_counter() - te, 2)
        with (out / METRICS).open("a") as fh:
            fh.write(json.dumps(row) + "\n")
        tmp = ckpt_path.with_suffix(".tmp")
        state = {"net": net.state_dict(), "opt": opt.state_dict(), "epoch": epoch}
        torch.save({**state, "kind": kind, "manifest_sha256": ts.sha256, "settings": settings}, tmp)
        os.replace(tmp, ckpt_path)
        say(
            f"epoch {epoch + 1}/{epochs} phase {phase} "
            + " ".join(f"{k}={v}" for k, v in row.items() if k not in ("epoch", "phase"))
        )
    training = {"manifest_sha256": ts.sha256, **settings}
    path = save_model(net, kind, config, training, out)
    model = load_model(path)
    summary = {**model.describe(), "path": path.name, "metrics": metrics}
    (out / "model.json").write_text(json.dumps(summary, indent=1) + "\n")
    say(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB) in {time.perf_counter() - t0:.1f} s")
    return summary
