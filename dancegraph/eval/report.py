"""The evaluation's ``report.html``: one self-contained page (inline PNG plots, no external files).

The table of rows × metrics comes first, then the sync table (every sync metric beside its
chance rows and the gain over each), then per song four plots of our dance (the first
alternative of the ``ours`` row, or of a scored result): music beats against kinematic beats on a
timeline, the bars and phrases with the chosen nodes, the per-bar costs, and the motif-signature
histogram against its target; then the seams of every alternative: a table and a timeline of each
seam's score with the flagged seams marked (``_seam_section``).
"""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import numpy as np

from dancegraph.eval.harness import AGGREGATES, ROW_TITLES, SCALARS

BEATS_PLOT_S = 16.0  # seconds of the beat timeline shown
COST_TERMS = ("style", "rhythm", "transition", "structure", "user")


def png_data_uri(fig) -> str:
    """A matplotlib figure as an inline ``data:image/png;base64,...`` URI (closes the figure)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=72, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"
    return html.escape(str(v))


def _table(rows: dict) -> str:
    cols = {**SCALARS, **AGGREGATES}
    head = "".join(f"<th>{html.escape(t)}</th>" for t in cols.values())
    body = []
    for row, entry in rows.items():
        cells = "".join(f"<td>{_fmt(entry.get(k))}</td>" for k in cols)
        body.append(f"<tr><th>{html.escape(ROW_TITLES.get(row, row))}</th>{cells}</tr>")
    return f"<table><tr><th>row</th>{head}</tr>{''.join(body)}</table>"


#: The sync table's metrics (``metrics.beats``) with the music points and motion beats each compares.
SYNC_TITLES: dict[str, str] = {
    "cm_accuracy": "CM beat acc. (rhythm points, Shiratori beats, ±0.1 s)",
    "beat_accuracy": "Beat acc. (all beats, kinematic beats, ±0.1 s)",
    "bas_bailando": "BAS (Bailando)",
    "bas_fact": "BAS (FACT)",
    "bas_beats": "BAS (Bailando's rule, the tracker's beats)",
    "phase_r": "Phase concentration R (Shiratori beats)",
}


def _sync_table(sync: dict) -> str:
    """Per metric and row: the value, the half-beat and other-song chance rows, and the gain
    over each (difference; for the accuracies also the ratio)."""
    head = (
        "<tr><th>metric</th><th>row</th><th>value</th><th>half-beat shift</th>"
        "<th>gain</th><th>× chance</th><th>other song</th><th>gain</th><th>× chance</th></tr>"
    )
    body = []
    for key, title in SYNC_TITLES.items():
        for row, entry in sync.items():
            cell = entry.get(key) or {}
            ratio = key.endswith("accuracy")
            cells = [cell.get("value")]
            for chance in ("half_beat", "other_song"):
                cells += [
                    cell.get(chance),
                    cell.get(f"gain_{chance}"),
                    cell.get(f"ratio_{chance}") if ratio else None,
                ]
            tds = "".join(f"<td>{_fmt(v)}</td>" for v in cells)
            body.append(
                f"<tr><th>{html.escape(title)}</th><th>{html.escape(ROW_TITLES.get(row, row))}"
                f"</th>{tds}</tr>"
            )
    return f"<table>{head}{''.join(body)}</table>"


def _beats_plot(song, dance) -> str:
    import matplotlib.pyplot as plt

    bars = np.asarray(song.analysis.bars)
    t0 = float(bars[0, 0]) if len(bars) else 0.0
    t1 = t0 + BEATS_PLOT_S
    speed, fps = dance.plot["speed"], dance.plot["fps"]
    t = np.arange(len(speed)) / fps
    sel = (t >= t0) & (t <= t1)
    fig, ax = plt.subplots(figsize=(12, 2.6))
    ax.plot(t[sel], speed[sel], color="0.4", lw=1, label="mean joint speed (m/s)")
    for k, b in enumerate(b for b in song.beats if t0 <= b <= t1):
        ax.axvline(b, color="tab:blue", lw=1, alpha=0.7, label="music beats" if k == 0 else None)
    kin = [b for b in dance.plot["kinematic_beats"] if t0 <= b <= t1]
    if kin:
        ax.plot(kin, np.interp(kin, t, speed), "v", color="tab:red", label="kinematic beats")
    ax.set_xlabel("time (s)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("Music beats vs kinematic beats")
    return png_data_uri(fig)


def _bars_plot(song, dance, node_ids: list[str]) -> str:
    import matplotlib.pyplot as plt

    bars = np.asarray(song.analysis.bars)
    fig, ax = plt.subplots(figsize=(14, 2.8))
    colours = plt.get_cmap("tab10")
    labels = sorted({p["label"] for p in song.analysis.phrases})
    for p in song.analysis.phrases:
        a, b = p["start_bar"], min(p["end_bar"], len(bars)) - 1
        if a > b:
            continue
        c = colours(labels.index(p["label"]) % 10)
        ax.axvspan(bars[a, 0], bars[b, 1], ymin=0.75, color=c, alpha=0.5)
        ax.text(bars[a, 0], 0.9, f"{p['label']}{p['occurrence']}", fontsize=8, va="center")
    for b, (start, _) in enumerate(bars):
        ax.axvline(start, color="0.7", lw=0.5)
        if dance.nodes is not None and b < len(dance.nodes):
            ax.text(start, 0.7, node_ids[int(dance.nodes[b])], rotation=90, fontsize=6, va="top")
    ax.set_ylim(0, 1)
    ax.set_yticks([])
    ax.set_xlim(bars[0, 0], bars[-1, 1])
    ax.set_xlabel("time (s)")
    ax.set_title("Phrases (top), bars and the chosen nodes")
    return png_data_uri(fig)


def _costs_plot(dance) -> str | None:
    import matplotlib.pyplot as plt

    per_bar = dance.plot.get("per_bar")
    if not per_bar:
        return None
    fig, ax = plt.subplots(figsize=(12, 2.6))
    x = np.arange(len(per_bar))
    bottom = np.zeros(len(per_bar))
    for term in COST_TERMS:
        v = np.array([float(r.get(term, 0.0) or 0.0) for r in per_bar])
        if np.any(v):
            ax.bar(x, v, bottom=bottom, label=term, width=0.9)
            bottom += v
    ax.set_xlabel("bar")
    ax.set_ylabel("cost")
    ax.set_title("Per-bar cost terms")
    ax.legend(fontsize=8, ncol=5)
    return png_data_uri(fig)


def _signature_plot(dance) -> str | None:
    import matplotlib.pyplot as plt

    sig = dance.plot.get("signature")
    if not sig:
        return None
    h, target = np.asarray(sig["histogram"]), np.asarray(sig["target"])
    x = np.arange(len(h))
    fig, ax = plt.subplots(figsize=(8, 2.6))
    ax.bar(x - 0.2, h, width=0.4, label="dance")
    ax.bar(x + 0.2, target, width=0.4, label="target")
    ax.set_xlabel("motif")
    ax.set_title(f"Motif signature vs target (χ² = {sig['chi2']:.3f})")
    ax.legend(fontsize=8)
    return png_data_uri(fig)


def _seam_section(dances) -> list[str]:
    """The seams of every alternative: a table (seams, share above the library's p99, median
    percentile, worst seam and its bar, foot sliding near seams against the library's own at
    contacts) and a timeline of every seam's percentile, flagged seams marked with their bar."""
    import matplotlib.pyplot as plt

    from dancegraph.metrics.smoothness import FLAG_PERCENTILE

    scored = [(k, d) for k, d in enumerate(dances) if d.plot.get("seams") is not None]
    if not scored:
        return []
    head = (
        "<tr><th>alt.</th><th>seams</th><th>&gt; p99</th><th>median pct.</th><th>worst (bar)</th>"
        "<th>skate ±0.2 s m/s</th><th>library skate m/s</th><th>bar lines &gt; p99 / median</th></tr>"
    )
    rows = []
    fig, ax = plt.subplots(figsize=(14, 2.2 + 0.3 * len(scored)))
    for k, d in scored:
        s = d.metrics.get("seams", {})
        worst = s.get("worst") or {}
        lines = s.get("bar_lines") or {}
        lib = s.get("library_skate") or {}
        rows.append(
            f"<tr><td>{k}</td><td>{_fmt(s.get('count'))}</td>"
            f"<td>{_fmt(s.get('flagged_share'))}</td><td>{_fmt(s.get('median_percentile'))}</td>"
            f"<td>{_fmt(worst.get('percentile'))} ({_fmt(worst.get('bar'))})</td>"
            f"<td>{_fmt((s.get('skate') or {}).get('mean_speed_m_s'))}</td>"
            f"<td>{_fmt(lib.get('mean_speed_m_s'))}</td>"
            f"<td>{_fmt(lines.get('flagged_share'))} / {_fmt(lines.get('median_percentile'))}</td></tr>"
        )
        seam_rows = d.plot["seams"]
        t = np.array([r["frame"] for r in seam_rows]) / d.plot["fps"]
        pct = np.array([r["percentile"] for r in seam_rows])
        ax.plot(t, pct, ".", ms=4, label=f"alternative {k}")
        for r, x in zip(seam_rows, t, strict=True):
            if r["flagged"]:
                ax.plot([x], [r["percentile"]], "x", color="red", ms=9, mew=2)
                ax.annotate(f"bar {r['bar']}", (x, r["percentile"]), fontsize=7, color="red")
    ax.axhline(FLAG_PERCENTILE, color="red", lw=0.8, ls="--", label="library p99 (flag)")
    chance = (scored[0][1].metrics.get("seams") or {}).get("chance") or {}
    if chance.get("median_percentile") is not None:
        ax.axhline(chance["median_percentile"], color="0.5", lw=0.8, ls=":", label="library median")
    ax.set_ylim(0, 101)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("seam percentile")
    ax.set_title("Seams on the timeline (red ×: above the library's p99)")
    ax.legend(fontsize=7, ncol=5, loc="lower right")
    return [
        "<h3>Seams</h3>",
        "<p>A seam is a frame where one node hands over to another (a take continuing into its "
        "own next bar is none); its percentile is the larger of its joint speed's and "
        "acceleration's in the library's own frames"
        + (
            f" (library frames scored the same way: median {chance['median_percentile']:.1f}, "
            f"{100 * chance['flagged_share']:.1f} % above p99)"
            if chance.get("median_percentile") is not None
            else ""
        )
        + ".</p>",
        f"<table>{head}{''.join(rows)}</table>",
        f"<img alt='seams' src='{png_data_uri(fig)}'>",
    ]


def write_report(path: Path, metrics: dict, songs, per_song, our_row: str = "ours") -> None:
    """Write the page: the table, then per song the plots of ``our_row``'s first dance."""
    import matplotlib

    matplotlib.use("Agg")
    graph = metrics["graph"]
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>DanceGraph evaluation</title>",
        "<style>body{font-family:sans-serif;margin:1em}table{border-collapse:collapse;"
        "font-size:13px}td,th{border:1px solid #bbb;padding:3px 6px;text-align:right}"
        "img{display:block;margin:6px 0;max-width:100%}</style></head><body>",
        f"<h1>DanceGraph evaluation: {html.escape(graph['name'])} "
        f"{html.escape(graph['version'])}</h1>",
        "<p>Means over songs and alternatives, every dance measured at 60 fps. BAS: Beat Align "
        "Score, σ = 3 frames (Bailando: averaged over music beats; FACT: over motion beats). "
        "FID_k: Fréchet distance of kinetic features (24 SMPL-like joints, 5 s windows) to the "
        "library's real dances, normalised by the library's statistics. Div.: mean pairwise "
        "distance of normalised kinetic features.</p>",
        _table(metrics["rows"]),
        "<h2>Sync against chance</h2>",
        "<p>Each sync metric of each row beside its chance rows: the same dances against the "
        "song's beats and rhythm points shifted by half a beat, and against another song's (the "
        "next song evaluated; none with one song). Phase R ignores a constant shift, so it has "
        "no half-beat row. CM beat acc.: ChoreoMaster's, over the rhythm points (active slots "
        "of each bar's top rhythm signature).</p>",
        _sync_table(metrics.get("sync", {})),
    ]
    for song, dances in zip(songs, per_song, strict=True):
        ours = dances.get(our_row) or []
        if not ours:
            continue
        dance = ours[0]
        parts.append(f"<h2>{html.escape(song.name)}</h2>")
        summary = song.analysis.summary()
        parts.append(
            f"<p>{summary['tempo_bpm']} BPM, {summary['n_bars']} bars, form "
            f"{html.escape(summary['form'])}</p>"
        )
        node_ids = dance.plot.get("node_ids") or []
        plots = [
            _beats_plot(song, dance),
            _bars_plot(song, dance, node_ids) if node_ids else None,
            _costs_plot(dance),
            _signature_plot(dance),
        ]
        parts.extend(f"<img alt='plot' src='{uri}'>" for uri in plots if uri)
        parts.extend(_seam_section(ours))
    parts.append("</body></html>")
    Path(path).write_text("\n".join(parts), encoding="utf-8")
