"""The analysis parameters: one typed object, read from files and dicts, and what reaches the steps."""

from __future__ import annotations

import ast
import json
from dataclasses import FrozenInstanceError, replace
from pathlib import Path

import numpy as np
import pytest

from dancegraph.cli import main
from dancegraph.errors import AudioError, SpecError
from dancegraph.music.analysis import analyze
from dancegraph.music.beats import track_evidence
from dancegraph.music.evidence import beat_evidence
from dancegraph.music.generator import generate, random_config, write_song
from dancegraph.music.params import (
    BEATNET_1_1_3,
    AnalysisParams,
    DoubleParams,
    GroupParams,
    NoBeatParams,
    PulseLimits,
    load_params,
)

MUSIC = Path(__file__).resolve().parents[2] / "dancegraph" / "music"


def _song(tempo: float = 118.0):
    cfg = random_config(
        11, meter=4, tempo_bpm=tempo, form=["A", "B", "A", "B"], section_bars={"A": 4, "B": 4}
    )
    return generate(cfg)


def test_defaults_round_trip_and_are_frozen() -> None:
    p = AnalysisParams()
    assert AnalysisParams.from_dict(p.to_dict()) == p
    assert AnalysisParams.from_dict(json.loads(json.dumps(p.to_dict()))) == p
    assert AnalysisParams.from_dict(BEATNET_1_1_3.to_dict()) == BEATNET_1_1_3
    with pytest.raises(FrozenInstanceError):
        p.group.net_confident = 0.5  # type: ignore[misc]
    changed = AnalysisParams.from_dict({"group": {"net_confident": 0.8}, "steps": ["group"]})
    assert changed.group == GroupParams(net_confident=0.8) and changed.steps == {"group"}
    assert changed.no_beat == NoBeatParams()  # the rest keeps its defaults


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"no_beat": {"beatnet": {"min_strenght": 0.2}}}, "no_beat.beatnet.min_strenght"),
        ({"grup": {}}, "grup"),
        ({"group": {"net_confident": "high"}}, "group.net_confident"),
        ({"slip": {"window": 4.5}}, "slip.window"),
        ({"slip": {"same_level": [0.8]}}, "slip.same_level"),
        ({"steps": ["group", "no_such_step"]}, "steps"),
        ({"no_beat": 3}, "no_beat"),
    ],
)
def test_unknown_keys_and_wrong_types_are_refused_by_name(data: dict, field: str) -> None:
    with pytest.raises(SpecError) as err:
        AnalysisParams.from_dict(data)
    assert err.value.code == "analysis_params_invalid" and err.value.field == field
    assert field.split(".")[-1] in err.value.message


def test_params_files_yaml_and_json(tmp_path: Path) -> None:
    (tmp_path / "p.yaml").write_text("group:\n  harmony_weight: 1.5\nsteps: [group, slips]\n")
    (tmp_path / "p.json").write_text(json.dumps({"dotted": {"min_ratio": 2}}))
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    (tmp_path / "bad.json").write_text("{")
    assert load_params(tmp_path / "p.yaml").group.harmony_weight == 1.5
    assert load_params(tmp_path / "p.json").dotted.min_ratio == 2.0
    for name in ("list.yaml", "bad.json", "missing.yaml"):
        with pytest.raises(SpecError) as err:
            load_params(tmp_path / name)
        assert err.value.code == "analysis_params_invalid"


def test_the_steps_read_the_params_they_are_given() -> None:
    """One evidence, several parameter sets: a pulse floor above any song refuses it; the
    ``halve`` step keeps every other beat only where its subdivision threshold says nothing
    sounds between the beats (a normal song has eighths between them)."""
    song = _song(140.0)
    ev = beat_evidence(song.y, song.sr)
    base = track_evidence(ev)
    floor = NoBeatParams(beatnet=PulseLimits(min_strength=50.0))
    with pytest.raises(AudioError) as err:
        track_evidence(ev, AnalysisParams(no_beat=floor))
    assert err.value.code == "no_beat" and "strength" in err.value.message
    halve = AnalysisParams().with_steps("halve")
    kept = track_evidence(ev, halve)
    assert not any(w.startswith("beats_halved") for w in kept.warnings)
    np.testing.assert_array_equal(kept.beats, base.beats)
    halved = track_evidence(ev, replace(halve, double=DoubleParams(max_subdivision=100.0)))
    assert any(w.startswith("beats_halved") for w in halved.warnings)
    assert abs(len(halved.beats) - len(base.beats) / 2) <= 2


def test_analyze_and_the_cli_take_params(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    song = _song()
    wav, _ = write_song(song, tmp_path, "song")
    default = analyze(wav)
    same = analyze(wav, params=AnalysisParams())
    np.testing.assert_array_equal(default.beats, same.beats)
    (tmp_path / "refuse.yaml").write_text("no_beat:\n  beatnet:\n    min_strength: 50.0\n")
    assert main(["analyze", str(wav), "--params", str(tmp_path / "refuse.yaml")]) == 2
    assert "no_beat" in capsys.readouterr().err
    (tmp_path / "typo.yaml").write_text("no_beat:\n  beatnet:\n    min_strenght: 0.2\n")
    assert main(["analyze", str(wav), "--params", str(tmp_path / "typo.yaml")]) == 2
    err = capsys.readouterr().err
    assert "analysis_params_invalid" in err and "no_beat.beatnet.min_strenght" in err
    (tmp_path / "ok.json").write_text(json.dumps({"group": {"harmony_weight": 1.25}}))
    assert main(["analyze", str(wav), "--json", "--params", str(tmp_path / "ok.json")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["beats"] == default.to_dict()["beats"]


def test_no_module_level_mutable_tables_in_music() -> None:
    """Every public module-level name of ``dancegraph.music`` is immutable: thresholds live in
    the parameters, never in a dict, list or set a caller could change for everyone (private
    process caches, such as the loaded models, are not tables)."""
    mutable = (ast.Dict, ast.List, ast.Set, ast.DictComp, ast.ListComp, ast.SetComp)
    found = []
    for path in sorted(MUSIC.glob("*.py")):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.Assign):
                names = [t.id for t in node.targets if isinstance(t, ast.Name)]
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                names = [node.target.id]
            else:
                continue
            public = any(not n.startswith("_") for n in names)
            if public and isinstance(node.value, mutable):
                found.append(f"{path.name}:{node.lineno}")
    assert not found, f"module-level mutable tables: {found}"


def test_a_spec_carries_analysis_params_and_refuses_unknown_keys() -> None:
    from pydantic import ValidationError

    from dancegraph.spec import parse_spec

    spec = parse_spec({"analysis": {"group": {"net_confident": 0.75}, "steps": ["group"]}})
    params = spec.analysis_params()
    assert params is not None and params.group.net_confident == 0.75
    assert params.digest() != AnalysisParams().digest()
    assert parse_spec({}).analysis_params() is None
    with pytest.raises((SpecError, ValidationError)) as err:
        parse_spec({"analysis": {"group": {"net_confidnt": 0.75}}})
    assert "group.net_confidnt" in str(err.value)
