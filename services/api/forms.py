"""The API's request forms: a multipart/form-data body streamed to temporary files under byte
limits, its ``spec`` part parsed once (``dancegraph.spec.parse_spec``) and its ``audio`` parts.

The body is refused (413) at the first byte past a limit, so an over-limit upload never fills
memory or disk, and an ``audio`` part whose first bytes name no audio container is refused (415)
as they arrive; the audio parts are then checked by ``services.common.uploads.check_audio``.
"""

from __future__ import annotations

from collections.abc import AsyncIterator

from fastapi import Request

from dancegraph.spec import Spec, parse_spec
from dancegraph.store import ObjectStore
from services.api.multipart import MAX_TEXT_BYTES, Form, HeadCheck, read_form
from services.common.problems import ApiError
from services.common.uploads import FilePart, check_container, safe_filename
from services.config import Settings

# room for boundaries, part headers and a spec of the largest size around the audio parts
_FORM_OVERHEAD = MAX_TEXT_BYTES + 256 * 1024


async def _limited(stream: AsyncIterator[bytes], limit: int) -> AsyncIterator[bytes]:
    total = 0
    async for chunk in stream:
        total += len(chunk)
        if total > limit:
            raise ApiError(
                413, "upload_too_large", f"the upload is larger than {limit} bytes", field="audio"
            )
        yield chunk


async def read_multipart(
    request: Request, settings: Settings, store: ObjectStore, *, max_audio: int
) -> Form:
    """Stream a multipart/form-data body to temporary files, refusing it at the first byte past
    a limit (per file: ``max_upload_bytes``; whole body: that times ``max_audio`` plus room for
    the form). The caller owns the returned form's temporary files (``Form.discard``)."""
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("multipart/form-data"):
        raise ApiError(
            415,
            "content_type_unsupported",
            "send multipart/form-data with an 'audio' file part",
            field="header.Content-Type",
        )
    limit = settings.max_upload_bytes * max(1, max_audio) + _FORM_OVERHEAD
    declared = request.headers.get("content-length")
    if declared is not None and declared.isascii() and declared.isdigit() and int(declared) > limit:
        raise ApiError(
            413, "upload_too_large", f"the upload is larger than {limit} bytes", field="audio"
        )
    return await read_form(
        _limited(request.stream(), limit),
        ctype,
        store.scratch,
        max_file_bytes=settings.max_upload_bytes,
        max_files=max_audio + 1,  # the spec may come as a file part too
        too_many_code="batch_too_large" if max_audio > 1 else "audio_multiple",
        check_head=_sniff_audio(batch=max_audio > 1),
    )


def _sniff_audio(*, batch: bool) -> HeadCheck:
    """Refuse an ``audio`` part (415 ``audio_undecodable``, field ``audio[i]`` in a batch) whose
    first bytes name no audio container, before the rest of the body is read."""

    def check(form: Form, part: FilePart, head: bytes) -> None:
        if part.name == "audio":
            index = len(form.files_named("audio")) - 1
            field = f"audio[{index}]" if batch else "audio"
            check_container(head, safe_filename(part.filename), field)

    return check


def form_spec(form: Form) -> Spec:
    """The ``spec`` part (a text field, or a file as ``curl -F spec=@spec.json`` sends it) as a
    validated Spec (absent: all defaults); 413 ``spec_too_large``, else ``parse_spec``'s errors."""
    raw: str | bytes | None = form.text("spec")
    spec_files = form.files_named("spec")
    if raw is None and spec_files:
        raw = spec_files[0].read_text(MAX_TEXT_BYTES)
        if raw is None:
            raise ApiError(
                413, "spec_too_large", f"spec is larger than {MAX_TEXT_BYTES} bytes", field="spec"
            )
    return parse_spec(raw)


def audio_parts(form: Form) -> list[FilePart]:
    """The form's ``audio`` file parts; 422 ``audio_missing`` when there are none."""
    parts = form.files_named("audio")
    if not parts:
        if form.text("audio") is not None:
            raise ApiError(
                422, "audio_missing", "'audio' must be a file part, not a text field", field="audio"
            )
        raise ApiError(422, "audio_missing", "the request has no 'audio' file part", field="audio")
    return parts
