"""The layers hold: the domain library never imports the services, and the services that are not
the API never import ``services.api`` (what they share lives in ``services.common``).

Every ``import`` statement is read from the source (module level and inside functions alike), so
a lazy import inside a function breaks the rule as surely as one at the top.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def imported_modules(path: Path) -> set[str]:
    """Every absolute module name an ``import``/``from … import`` in ``path`` names."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def offenders(package: str, forbidden: str) -> dict[str, list[str]]:
    """``{file: [modules]}`` of the files under ``package`` that import ``forbidden`` or below."""
    out = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        bad = sorted(
            m for m in imported_modules(path) if m == forbidden or m.startswith(forbidden + ".")
        )
        if bad:
            out[str(path.relative_to(ROOT))] = bad
    return out


@pytest.mark.parametrize(
    "package, forbidden",
    [
        ("dancegraph", "services"),
        ("services/common", "services.api"),
        ("services/common", "services.worker"),
        ("services/common", "services.graphstore"),
        ("services/graphstore", "services.api"),
        ("services/graphstore", "services.worker"),
        ("services/worker", "services.api"),
    ],
)
def test_layer_does_not_import(package: str, forbidden: str):
    assert offenders(package, forbidden) == {}


def test_the_check_sees_imports_inside_functions(tmp_path: Path):
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from services.api.problems import ApiError\n")
    assert "services.api.problems" in imported_modules(probe)


def test_one_command_offers_the_domain_and_the_service_commands():
    """``dancegraph`` keeps every command although the service ones live in ``services.cli``."""
    import argparse

    from dancegraph.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    domain = {"version", "convert", "synthesize", "analyze", "dataset", "motion", "eval", "train"}
    service = {"keys", "serve", "worker", "reaper", "quickstart", "preview"}
    assert domain | service <= set(sub.choices)
