"""A streaming multipart/form-data reader for uploads.

File parts go straight to a temporary file in the object store's ``tmp/`` folder, hashed
(sha256) and size-checked as the bytes arrive: an over-limit file is refused (413) at the first
byte past the limit, nothing is buffered in memory, and the checked file can be moved into the
store without being read again. Text parts (the spec) are kept in memory up to a small limit.
Built on python-multipart's push parser (public API only).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header

from services.common.problems import ApiError
from services.common.uploads import SNIFF_BYTES, FilePart

if TYPE_CHECKING:
    from python_multipart.multipart import MultipartCallbacks

MAX_TEXT_BYTES = 1 << 20  # a spec is small; anything bigger is a mistake
MAX_TEXT_FIELDS = 16


@dataclass
class Form:
    """The parsed body: text fields by name (in order) and file parts (in order)."""

    fields: dict[str, list[str]] = field(default_factory=dict)
    files: list[FilePart] = field(default_factory=list)

    def text(self, name: str) -> str | None:
        values = self.fields.get(name)
        return values[0] if values else None

    def files_named(self, name: str) -> list[FilePart]:
        return [f for f in self.files if f.name == name]

    def discard(self) -> None:
        """Remove every temporary file (those handed on were moved away already)."""
        for f in self.files:
            f.discard()


# Called once per file part with the form so far (the part is its last file) and the part's first
# ``SNIFF_BYTES`` bytes (fewer when the part is shorter; not called for an empty part); it raises
# to refuse the part, and the rest of the body is then not read.
HeadCheck = Callable[[Form, FilePart, bytes], None]


class _Reader:
    def __init__(
        self,
        tmp_dir: Path,
        *,
        max_file_bytes: int,
        max_files: int,
        too_many_code: str,
        check_head: HeadCheck | None,
    ):
        self.tmp_dir = tmp_dir
        self.check_head = check_head
        self._head: bytearray | None = None  # a file part's first bytes until they are checked
        self.max_file_bytes = max_file_bytes
        self.max_files = max_files
        self.too_many_code = too_many_code
        self.form = Form()
        self._header_name = b""
        self._header_value = b""
        self._disposition = b""
        self._text: bytearray | None = None
        self._name = ""
        self._file: FilePart | None = None
        self._fh: BinaryIO | None = None
        self._digest: Any = None  # hashlib's sha256 object while a file part streams in
        self._n_text = 0

    # python-multipart callbacks -------------------------------------------------------------
    def on_part_begin(self) -> None:
        self._disposition = b""
        self._text = None
        self._file = None

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def on_header_end(self) -> None:
        if self._header_name.lower() == b"content-disposition":
            self._disposition = self._header_value
        self._header_name = b""
        self._header_value = b""

    def on_headers_finished(self) -> None:
        _, options = parse_options_header(self._disposition)
        if b"name" not in options:
            raise ApiError(
                400, "multipart_malformed", "a part has no Content-Disposition name", field="body"
            )
        self._name = options[b"name"].decode("utf-8", "replace")
        if b"filename" in options:
            if len(self.form.files) >= self.max_files:
                raise ApiError(
                    422,
                    self.too_many_code,
                    f"at most {self.max_files} file parts per request",
                    field=self._name,
                )
            fd, tmp = tempfile.mkstemp(dir=self.tmp_dir, prefix=".upload-")
            self._fh = os.fdopen(fd, "wb")
            self._digest = hashlib.sha256()
            self._head = bytearray() if self.check_head is not None else None
            self._file = FilePart(
                self._name, options[b"filename"].decode("utf-8", "replace"), Path(tmp)
            )
            self.form.files.append(self._file)  # listed at once, so an error removes it too
        else:
            self._n_text += 1
            if self._n_text > MAX_TEXT_FIELDS:
                raise ApiError(400, "multipart_malformed", "too many form fields", field="body")
            self._text = bytearray()

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        chunk = data[start:end]
        if self._file is not None:
            self._file.size += len(chunk)
            if self._file.size > self.max_file_bytes:
                raise ApiError(
                    413,
                    "upload_too_large",
                    f"{self._file.filename or 'the file'} is larger than {self.max_file_bytes} bytes",
                    field=self._name,
                )
            if self._head is not None:  # checked before the part's bytes are written
                self._head += chunk[: SNIFF_BYTES - len(self._head)]
                if len(self._head) >= SNIFF_BYTES:
                    self._check_head()
            assert self._fh is not None
            self._digest.update(chunk)
            self._fh.write(chunk)
        elif self._text is not None:
            if len(self._text) + len(chunk) > MAX_TEXT_BYTES:
                code = "spec_too_large" if self._name == "spec" else "field_too_large"
                raise ApiError(
                    413,
                    code,
                    f"form field {self._name!r} is larger than {MAX_TEXT_BYTES} bytes",
                    field=self._name,
                )
            self._text.extend(chunk)

    def _check_head(self) -> None:
        head, self._head = self._head, None
        if head and self.check_head is not None and self._file is not None:
            self.check_head(self.form, self._file, bytes(head))

    def on_part_end(self) -> None:
        if self._file is not None:
            self._check_head()  # a part shorter than SNIFF_BYTES
            assert self._fh is not None
            self._fh.close()
            self._fh = None
            self._file.sha256 = self._digest.hexdigest()
        elif self._text is not None:
            self.form.fields.setdefault(self._name, []).append(
                self._text.decode("utf-8", "replace")
            )
        self._file = None
        self._text = None

    def close(self) -> None:
        """Close the open temporary file, if any (it is being discarded: a failed flush, e.g. on
        a full disk, does not matter)."""
        if self._fh is not None:
            with contextlib.suppress(OSError):
                self._fh.close()
            self._fh = None


async def read_form(
    stream: AsyncIterator[bytes],
    content_type: str,
    tmp_dir: Path,
    *,
    max_file_bytes: int,
    max_files: int,
    too_many_code: str = "too_many_files",
    check_head: HeadCheck | None = None,
) -> Form:
    """Parse a multipart body from ``stream``; on any error every temporary file is removed.

    ``check_head`` (see ``HeadCheck``) refuses a file part by its first bytes while it streams
    in, so a refused part is never written whole. A full disk raises the ``OSError`` (ENOSPC),
    answered 503 ``store_full`` by ``services.common.problems``."""
    _, params = parse_options_header(content_type)
    boundary = params.get(b"boundary")
    if not boundary:
        raise ApiError(
            400,
            "multipart_malformed",
            "the multipart Content-Type has no boundary",
            field="header.Content-Type",
        )
    tmp_dir.mkdir(parents=True, exist_ok=True)
    reader = _Reader(
        tmp_dir,
        max_file_bytes=max_file_bytes,
        max_files=max_files,
        too_many_code=too_many_code,
        check_head=check_head,
    )
    callbacks: MultipartCallbacks = {
        "on_part_begin": reader.on_part_begin,
        "on_part_data": reader.on_part_data,
        "on_part_end": reader.on_part_end,
        "on_header_field": reader.on_header_field,
        "on_header_value": reader.on_header_value,
        "on_header_end": reader.on_header_end,
        "on_headers_finished": reader.on_headers_finished,
    }
    try:
        parser = MultipartParser(boundary, callbacks)
        async for chunk in stream:
            parser.write(chunk)  # disk writes of one chunk are short: no thread hop per chunk
        parser.finalize()
        if reader._fh is not None or reader._text is not None:
            raise ApiError(
                400, "multipart_malformed", "the multipart body ends inside a part", field="body"
            )
    except FormParserError as exc:
        reader.close()
        reader.form.discard()
        raise ApiError(
            400, "multipart_malformed", f"malformed multipart body: {exc}", field="body"
        ) from exc
    except BaseException:
        reader.close()
        reader.form.discard()
        raise
    return reader.form
