"""Style is a choice: which motion library dances a song (spec ``style: auto``, or a list of
libraries).

Each candidate library is scored on two terms, lower is better:

- ``tempo_cost``: how far the song's tempo lies outside the style's danced tempo range, in
  octaves (log2 units; 0 inside), taking the best of the song counted as tracked, at twice or
  at half its tempo (``octave`` x1 / x2 / x1/2; a counted octave other than x1 adds
  ``OCTAVE_COST``). The range is the library's ``style_tempo_bpm`` where its manifest declares
  one, else the 10th to 90th percentile of its own bars' tempi.
- ``style_distance``: the style embedding's music-to-motion distance — per song bar the
  distance from its music style (``problem.music_style``, the search's own music term) to the
  nearest of the library's node styles, averaged over the bars: the style part of the search's
  data term (C_d, ``λ12·‖z_M − z_D‖``) at its best.

``score = TEMPO_WEIGHT · tempo_cost + STYLE_WEIGHT · style_distance``; the lowest score is
chosen, and the reason string says by which term it won.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from dancegraph.errors import SpecError

if TYPE_CHECKING:
    from dancegraph.spec import Spec

#: Weight of one octave of tempo misfit in the score (a style danced an octave off its range
#: loses to any style it fits).
TEMPO_WEIGHT = 4.0
#: Weight of the mean music-to-motion style distance (32-d descriptor units).
STYLE_WEIGHT = 1.0
#: Extra tempo cost of counting the song at twice or half its tracked tempo (octaves).
OCTAVE_COST = 0.1
_OCTAVES = (("x1", 1.0), ("x2", 2.0), ("x1/2", 0.5))


@dataclass
class Candidate:
    """A library to choose from: ``name``, its ``style`` label, the danced ``tempo_range`` (lo, hi)
    BPM and where it came from (``range_source``: ``style_tempo_bpm`` | ``bars``), and the
    graph's node styles ``(N, 32)``."""

    name: str
    style: str
    tempo_range: tuple[float, float]
    range_source: str
    node_styles: np.ndarray


def candidate(graph) -> Candidate:
    """The candidate of a built graph (``artifact.MotionGraph``): its dataset's name and style
    (the manifest's ``style``, else the name), its declared style tempo range or its bars'
    tempo spread, its node styles."""
    bpm = 240.0 / np.maximum(np.asarray(graph.duration, dtype=float), 1e-6)
    declared = graph.tempo_range
    rng = declared or (float(np.percentile(bpm, 10)), float(np.percentile(bpm, 90)))
    style = (graph.manifest.get("dataset") or {}).get("style")
    return Candidate(
        name=graph.name,
        style=str(style or graph.name),
        tempo_range=(float(rng[0]), float(rng[1])),
        range_source="style_tempo_bpm" if declared else "bars",
        node_styles=np.asarray(graph.style, dtype=float),
    )


def tempo_cost(tempo_bpm: float, tempo_range: tuple[float, float]) -> tuple[float, str]:
    """``(cost in octaves, octave)``: the song's tempo (or twice, or half of it) to ``tempo_range``."""
    lo, hi = tempo_range
    best = (math.inf, "x1")
    for octave, factor in _OCTAVES:
        t = tempo_bpm * factor
        off = max(0.0, math.log2(lo / t), math.log2(t / hi))
        cost = off + (OCTAVE_COST if factor != 1.0 else 0.0)
        best = min(best, (cost, octave))
    return best


def style_distance(music_styles: np.ndarray, node_styles: np.ndarray) -> float:
    """Mean over the song's bars ``(B, 32)`` of the distance to the nearest node style ``(N, 32)``."""
    d2 = (
        np.sum(music_styles**2, axis=1)[:, None]
        - 2.0 * music_styles @ node_styles.T
        + np.sum(node_styles**2, axis=1)[None, :]
    )
    return float(np.mean(np.sqrt(np.maximum(d2.min(axis=1), 0.0))))


def song_styles(analysis) -> np.ndarray:
    """``(B, 32)`` descriptor style of each bar of a song's analysis (the search's music term)."""
    from dancegraph.graph.problem import music_style

    bars = np.asarray(analysis.bars, dtype=float).reshape(-1, 2)
    music = {"bars": bars, "n": len(bars), "onset": np.asarray(analysis.bar_onset_rms, dtype=float)}
    return music_style(music)


def choose_library(analysis, candidates: list[Candidate]) -> dict:
    """Score every candidate for the song of ``analysis`` (a ``MusicAnalysis``, tempo as tracked)
    and choose the lowest score.

    Returns ``{"chosen": name, "reason": str, "tempo_bpm": song tempo, "candidates": [{name,
    style, tempo_range, range_source, octave, tempo_cost, style_distance, score}, ...]}`` (best
    first). Raises ``SpecError`` (``style_no_candidate``) for an empty list.
    """
    if not candidates:
        raise SpecError(
            "no library to choose a style from", code="style_no_candidate", field="spec.style"
        )
    zm = song_styles(analysis)
    tempo = float(analysis.tempo_bpm)
    rows: list[dict[str, Any]] = []
    for c in candidates:
        cost, octave = tempo_cost(tempo, c.tempo_range)
        dist = style_distance(zm, c.node_styles)
        rows.append(
            {
                "name": c.name,
                "style": c.style,
                "tempo_range": [round(c.tempo_range[0], 1), round(c.tempo_range[1], 1)],
                "range_source": c.range_source,
                "octave": octave,
                "tempo_cost": round(cost, 4),
                "style_distance": round(dist, 4),
                "score": round(TEMPO_WEIGHT * cost + STYLE_WEIGHT * dist, 4),
            }
        )
    rows.sort(key=lambda r: float(r["score"]))
    return {
        "chosen": rows[0]["name"],
        "reason": _reason(tempo, rows),
        "tempo_bpm": round(tempo, 2),
        "candidates": rows,
    }


def resolve(spec: Spec, analysis, graphs: Mapping[str, Any]) -> tuple[Spec, dict | None]:
    """The spec danced on one library, and the choice that picked it (None: the spec named one).

    ``spec``: a spec whose ``dataset`` names one library and no ``style`` comes back as it is.
    Otherwise the candidates are ``graphs`` (name → built ``MotionGraph``: the libraries the
    spec lists, or for a ``style`` every library the caller may use), those of the spec's list
    when it gives one, and those whose style label is ``spec.style`` unless it is ``auto``;
    :func:`choose_library` picks among them and the chosen name replaces ``spec.dataset``.
    Raises ``SpecError`` ``style_unknown`` (422) when no candidate is left, naming the styles
    there are.
    """
    from dancegraph.spec import parse_spec

    if isinstance(spec.dataset, str) and spec.style is None:
        return spec, None
    names = spec.libraries() if isinstance(spec.dataset, list) else list(graphs)
    cands = [candidate(graphs[n]) for n in names if n in graphs]
    if spec.style not in (None, "auto"):
        cands = [c for c in cands if c.style == spec.style]
    if not cands:
        styles = sorted({candidate(g).style for g in graphs.values()})
        raise SpecError(
            f"no library of style {spec.style!r} among {names} (styles: {', '.join(styles)})",
            code="style_unknown",
            field="spec.style" if spec.style else "spec.dataset",
        )
    choice = choose_library(analysis, cands)
    return parse_spec(spec, dataset=choice["chosen"]), choice


def _reason(tempo: float, rows: list[dict]) -> str:
    """Why the first row won: the term that decided it against the runner-up."""
    best = rows[0]
    fit = (
        f"the song's {tempo:.1f} BPM (counted {best['octave']}) "
        + ("lies inside" if _inside(best) else "lies nearest to")
        + f" {best['style']}'s {best['tempo_range'][0]:.0f}-{best['tempo_range'][1]:.0f} BPM"
    )
    if len(rows) == 1:
        return f"{best['name']}: the only candidate; {fit}"
    other = rows[1]
    d_tempo = TEMPO_WEIGHT * (other["tempo_cost"] - best["tempo_cost"])
    d_style = STYLE_WEIGHT * (other["style_distance"] - best["style_distance"])
    by = "tempo" if d_tempo >= d_style else "style"
    return (
        f"{best['name']} (score {best['score']:.2f}) over {other['name']} ({other['score']:.2f}),"
        f" won on {by}: {fit}; style distance {best['style_distance']:.2f} vs"
        f" {other['style_distance']:.2f}"
    )


def _inside(row: dict) -> bool:
    """Whether a scored row's counted tempo lies inside its range (no cost beyond the octave's)."""
    return row["tempo_cost"] - (OCTAVE_COST if row["octave"] != "x1" else 0.0) <= 1e-6
