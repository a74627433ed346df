"""Errors with stable, machine-readable codes.

Every failure a user can cause carries a ``code`` (snake_case, stable within API version v1) and,
where it applies, the offending ``field`` (spec path, file name or argument). The API turns these
into RFC 9457 problem details; a worker turns them into a job failure with the same code.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any


class DanceGraphError(Exception):
    """Base error: ``code`` is stable, ``message`` is for people, ``field`` names the culprit,
    ``errors`` (optional) lists every failure as ``{field, code, message}``."""

    code: str = "error"
    status: int = 400  # the HTTP status the API answers with

    def __init__(
        self,
        message: str,
        *,
        code: str | None = None,
        field: str | None = None,
        errors: list[dict[str, str]] | None = None,
    ):
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code
        self.field = field
        self.errors = errors

    def to_dict(self) -> dict:
        out = {"code": self.code, "message": self.message}
        if self.field is not None:
            out["field"] = self.field
        return out


class AudioError(DanceGraphError):
    """Audio that cannot be used: undecodable, too short, too long, no beat (codes audio_*, no_beat)."""

    code = "audio_undecodable"
    status = 422


class MotionFileError(DanceGraphError):
    """A motion file that cannot be read; ``field`` is the file name, ``line`` the line number."""

    code = "motion_file_invalid"
    status = 422

    def __init__(
        self, message: str, *, path: str, line: int | None = None, code: str | None = None
    ):
        where = f"{path}:{line}" if line is not None else path
        super().__init__(f"{where}: {message}", code=code, field=path)
        self.path = path
        self.line = line


class SpecError(DanceGraphError):
    """A constraint spec that is invalid or cannot be satisfied (codes spec_invalid, constraint_conflict, ...)."""

    code = "spec_invalid"
    status = 422


class NotFoundError(DanceGraphError):
    """A named thing (dataset, graph, node, model) that does not exist."""

    code = "not_found"
    status = 404


class ModelFileError(DanceGraphError):
    """A model file that is corrupted or of the wrong version."""

    code = "model_file_invalid"
    status = 500


def field_path(loc: Sequence[Any], prefix: str | None = None) -> str:
    """A validation error's location as the field path users see: ``spec.weights.rhythm``,
    ``spec.include[0].node``, ``query.limit``. With a ``prefix`` a leading ``body`` is dropped."""
    parts = [str(p) for p in loc if p != "body" or prefix is None]
    if prefix:
        parts = [prefix, *parts]
    out = ""
    for p in parts:
        if p.isdigit() and out:
            out += f"[{p}]"
        else:
            out += ("." if out else "") + p
    return out or (prefix or "request")


def field_errors(errors: Iterable[Mapping[str, Any]], prefix: str | None = None) -> list[dict]:
    """Pydantic's ``ValidationError.errors()`` as ``[{field, code, message}]`` (``code``: the
    pydantic error type, e.g. ``extra_forbidden``): the one mapping of validation failures."""
    return [
        {
            "field": field_path(err.get("loc", ()), prefix),
            "code": str(err.get("type", "invalid")),
            "message": str(err.get("msg", "invalid value")),
        }
        for err in errors
    ]
