"""Learned embeddings benchmark (issue 6; ChoreoMaster Tables 4–5 analogues).

1. Inference time on CPU for a 3-minute song at 120 BPM (90 bars): log-mel, E_M over the song's
   per-bar 8-s windows, E_MR + E_RS over its bars; E_D over 90 dance phrases.
2. Generated paired set (``write_paired_set``; every fifth song held out): style model trained
   (phase 1 then phase 2), rhythm model trained; held-out style accuracy (music, dance), mean
   paired distance ‖Z_M − Z_D‖ and embedding spread at the end of phase 1 and of phase 2,
   rhythm top-1/top-3.
3. CMU dance (salsa vs modern, bars on a fixed grid, every fourth take held out): E_D style
   accuracy of a dance-only style model.
4. A t-SNE image of held-out music and dance embeddings: ``docs/img/embeddings.png``.

Usage: ``python bench/bench_embed.py [--quick] [--out DIR] [--songs N] [--epochs N]``.
Prints a JSON summary. ``DANCEGRAPH_SHARED`` points at the shared datasets (default ../shared).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from dancegraph.embed.data import FORMAT, load_training_set, write_paired_set  # noqa: E402
from dancegraph.embed.model import load_model  # noqa: E402
from dancegraph.embed.train import train  # noqa: E402
from dancegraph.motion.bvh import read_bvh  # noqa: E402
from dancegraph.paths import shared_dir  # noqa: E402

CMU = {
    # dataset folder: style, fps used, bar seconds (4 beats; salsa at about 168 BPM)
    "cmu-salsa": ("salsa", 60.0, 4 * 60.0 / 168.0),
    "cmu-modern": ("modern", 120.0, 2.0),
}


def _median_time(fn, reps: int = 5) -> float:
    fn()  # warm-up: first calls allocate and pick kernels
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def inference_times(style, rhythm) -> dict:
    from dancegraph.music.features import music_logmel

    sr, dur = 16000, 180.0
    rng = np.random.default_rng(0)
    y = (0.1 * rng.standard_normal(int(sr * dur))).astype(np.float32)
    starts = np.arange(90) * 2.0
    mel = music_logmel(y, sr)
    out = {
        "logmel_3min_s": _median_time(lambda: music_logmel(y, sr), 3),
        "E_M_90_bars_s": _median_time(lambda: style.music_style(mel, starts)),
        "E_D_90_phrases_s": _median_time(
            lambda: style.dance_style(np.zeros((90, 3, 18, 240), np.float32))
        ),
        "rhythm_90_bars_s": _median_time(
            lambda: rhythm.signature_scores("music", rng.random((90, 2, 200)), np.zeros((90, 32)))
        ),
    }
    return {k: round(v, 3) for k, v in out.items()}


def cmu_manifest(out: Path, max_bars: int = 12) -> Path | None:
    datasets = shared_dir() / "datasets" / "mocap"
    dance = []
    for folder, (style, fps, bar_s) in CMU.items():
        files = sorted((datasets / folder).glob("*.bvh"))
        files = [f for f in files if not f.stem.startswith("05_01")]  # the walk
        for k, f in enumerate(files):
            m = read_bvh(f, fps=fps)
            n = min(max_bars, int((m.n_frames / fps) // bar_s) - 1)
            if n < 1:
                continue
            bars = [[round((b + i / 4) * bar_s, 6) for i in range(5)] for b in range(n)]
            dance.append(
                {
                    "id": f.stem,
                    "motion": str(f),
                    "fps": fps,
                    "scale": 0.056444 if folder == "cmu-modern" else 1.0,
                    "bars": bars,
                    "style": {"genre": style},
                    "split": "test" if k % 4 == 3 else "train",
                }
            )
    if not dance:
        return None
    path = out / "cmu.json"
    path.write_text(json.dumps({"format": FORMAT, "style_dims": ["genre"], "dance": dance}))
    return path


def analytic_rhythm_baseline(manifest: Path) -> dict:
    """Top-1/top-3 of the analytic music estimator (``rhythm.music``) on the held-out bars."""
    from dancegraph.music.decode import load_audio
    from dancegraph.music.features import frame_features
    from dancegraph.music.generator import bar_grid
    from dancegraph.rhythm.music import music_signatures
    from dancegraph.rhythm.signatures import nearest_common, to_bits

    data = json.loads(manifest.read_text())
    hit1, hit3 = [], []
    for e in data["music"]:
        if e.get("split") != "test":
            continue
        audio = manifest.parent / e["audio"]
        y, sr = load_audio(audio, min_seconds=None)
        ff = frame_features(y, sr)
        bars, grid = bar_grid(json.loads(audio.with_suffix(".json").read_text()))
        rows = [int(np.argmin(np.abs(bars[:, 0] - b[0]))) for b in e["bars"]]
        _, top3, _ = music_signatures(ff.onset, ff.frame_rate, grid[rows])
        truth = nearest_common(np.stack([to_bits(sg) for sg in e["signatures"]]))
        hit1 += list(top3[:, 0] == truth)
        hit3 += list((top3 == truth[:, None]).any(1))
    return {
        "music_top1_test": round(float(np.mean(hit1)), 4),
        "music_top3_test": round(float(np.mean(hit3)), 4),
    }


def _rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def tsne_image(style_path: Path, manifest: Path, image: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch
    from sklearn.manifold import TSNE

    model = load_model(style_path)
    ts = load_training_set(manifest, "style")
    with torch.no_grad():
        zm = model.net.music(torch.as_tensor(np.stack(ts.music.style_x))).numpy()
        zd = model.dance_style(np.stack(ts.dance.style_x))
    z2 = TSNE(2, perplexity=min(30, len(zm) // 3), random_state=0, init="pca").fit_transform(
        np.concatenate([zm, zd])
    )
    labels = ts.music.label + ts.dance.label
    classes = sorted(set(labels))
    colours = plt.get_cmap("tab10")
    fig, ax = plt.subplots(figsize=(7, 5.5))
    for ci, c in enumerate(classes):
        for part, marker, offset in (("music", "o", 0), ("dance", "^", len(zm))):
            idx = [i + offset for i, lab in enumerate(getattr(ts, part).label) if lab == c]
            ax.scatter(
                *z2[idx].T,
                s=18,
                marker=marker,
                color=colours(ci),
                alpha=0.75,
                label=f"{c} ({part})",
            )
    ax.set_title("t-SNE of learned style embeddings (o music, ^ dance), generated paired set")
    ax.legend(fontsize=7, ncol=2)
    image.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(image, dpi=110)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny run (a smoke test)")
    ap.add_argument("--out", default=None, help="keep data and models here")
    ap.add_argument("--songs", type=int, default=15)
    ap.add_argument("--bars", type=int, default=8, help="bars per song section")
    ap.add_argument("--epochs", type=int, default=16)
    ap.add_argument("--image", default=str(ROOT / "docs" / "img" / "embeddings.png"))
    args = ap.parse_args(argv)
    if args.quick:
        args.songs, args.bars, args.epochs = 5, 4, 2
    out = Path(args.out or tempfile.mkdtemp(prefix="bench-embed-"))
    result: dict = {"songs": args.songs, "bars_per_section": args.bars, "epochs": args.epochs}

    t = time.perf_counter()
    manifest = write_paired_set(out / "paired", args.songs, args.bars, seed=0)
    result["generate_s"] = round(time.perf_counter() - t, 1)
    t = time.perf_counter()
    style = train("style", manifest, out / "style", epochs=args.epochs, progress=None)
    result["train_style_s"] = round(time.perf_counter() - t, 1)
    rows = _rows(out / "style" / "metrics.jsonl")
    last1 = [r for r in rows if r["phase"] == 1][-1]
    result["style"] = {
        "held_out": {k: v for k, v in rows[-1].items() if k.endswith("_test")},
        "pair_dist_test_after_phase1": last1.get("pair_dist_test"),
        "pair_dist_test_after_phase2": rows[-1].get("pair_dist_test"),
        # mean per-dimension std of all bars' embeddings (about 1 spread over the sphere, 0
        # collapsed onto one point)
        "spread_after_phase1": {k: v for k, v in last1.items() if k.endswith("_spread")},
        "spread_after_phase2": {k: v for k, v in rows[-1].items() if k.endswith("_spread")},
        "train_acc": {k: v for k, v in rows[-1].items() if k.endswith("_train")},
    }
    t = time.perf_counter()
    rhythm = train(
        "rhythm", manifest, out / "rhythm", epochs=max(args.epochs, 2) * 2, progress=None
    )
    result["train_rhythm_s"] = round(time.perf_counter() - t, 1)
    rrow = _rows(out / "rhythm" / "metrics.jsonl")[-1]
    result["rhythm"] = {k: v for k, v in rrow.items() if "_top" in k}
    result["rhythm_analytic_baseline"] = analytic_rhythm_baseline(manifest)
    style_path, rhythm_path = out / "style" / style["path"], out / "rhythm" / rhythm["path"]
    result["model_bytes"] = {
        "style": style_path.stat().st_size,
        "rhythm": rhythm_path.stat().st_size,
    }
    result["inference"] = inference_times(load_model(style_path), load_model(rhythm_path))

    cmu = cmu_manifest(out, max_bars=4 if args.quick else 12)
    if cmu is not None:
        t = time.perf_counter()
        train("style", cmu, out / "cmu", epochs=args.epochs, progress=None)
        crow = _rows(out / "cmu" / "metrics.jsonl")[-1]
        result["cmu_dance"] = {
            "acc_test": crow.get("dance_acc_test"),
            "acc_train": crow.get("dance_acc_train"),
            "bars": sum(len(e["bars"]) for e in json.loads(cmu.read_text())["dance"]),
            "train_s": round(time.perf_counter() - t, 1),
        }
    if not args.quick:
        tsne_image(style_path, manifest, Path(args.image))
        result["image"] = args.image
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
