"""Property-based API tests from ``openapi.yaml`` (schemathesis): for a bounded number of
generated requests per operation — valid and invalid — the API never answers 5xx, and every
error is a problem document with a code."""

from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.generation.modes import GenerationMode

from dancegraph.paths import REPO_ROOT

MAX_EXAMPLES = 15  # per operation and mode: bounded so the suite stays quick


def _cases():
    """(operation, mode) pairs; negative mode only where a request has something to get wrong."""
    schema = schemathesis.openapi.from_path(REPO_ROOT / "openapi.yaml")
    out = []
    for result in schema.get_all_operations():
        op = result.ok()
        raw = op.definition.raw
        modes = [GenerationMode.POSITIVE]
        if raw.get("parameters") or raw.get("requestBody") or raw.get("security"):
            modes.append(GenerationMode.NEGATIVE)
        out += [
            pytest.param(op, mode, id=f"{op.method.upper()} {op.path} {mode}") for mode in modes
        ]
    return out


@pytest.mark.parametrize(("operation", "mode"), _cases())
def test_no_server_errors(api, operation, mode):
    seen = []

    @given(case=operation.as_strategy(generation_mode=mode))
    @settings(
        max_examples=MAX_EXAMPLES,
        deadline=None,
        suppress_health_check=list(HealthCheck),
        database=None,
    )
    def run(case):
        response = case.call(app=api.app, headers=api.headers)
        seen.append(response.status_code)
        assert response.status_code < 500, (
            f"{case.method} {case.formatted_path}: {response.status_code} {response.text[:500]}"
        )
        ctype = response.headers.get("content-type") or [""]
        ctype = ctype[0] if isinstance(ctype, list) else ctype
        if response.status_code >= 400 and ctype.startswith("application/"):
            body = response.json()
            assert body["code"] and body["status"] == response.status_code

    run()
    assert seen
