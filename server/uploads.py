"""Streaming uploads to a temporary file, with the size limit enforced while the bytes arrive
(nothing is buffered whole in memory, nothing over the limit is kept).

:func:`receive_upload` (an avatar zip) accepts ``multipart/form-data`` with a ``file`` part
(and an optional ``name`` field), or the zip as the raw body (``application/zip`` /
``application/octet-stream``). :func:`receive_form` is the multipart part of it for any file
part names, each with its own limit (``POST /v1/jobs``: a dataset ``archive`` or a ``video``).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from fastapi import HTTPException, Request
from python_multipart.multipart import MultipartParser, parse_options_header

from .private import private_dir

MAX_NAME_CHARS = 200
FORM_SLACK = 64 * 1024  # boundaries and text fields around the file part


class UploadTooLarge(Exception):
    def __init__(self, part: str = "", limit: int = 0) -> None:
        super().__init__(part)
        self.part, self.limit = part, limit


@dataclass
class Upload:
    path: Path
    size: int
    name: str | None


@dataclass
class FormUpload:
    """A multipart form's one file part (on disk) and its text fields."""

    part: str                  # the file part's name
    path: Path
    size: int
    filename: str | None       # as the client named it (never used as a path)
    fields: dict[str, str]     # text fields, each cut at its limit (see ``overflow``)
    overflow: set[str]         # text fields that were longer than their limit


class _LimitedFile:
    def __init__(self, fh, limit: int, part: str = "") -> None:
        self.fh, self.limit, self.part, self.size = fh, limit, part, 0

    def write(self, data: bytes) -> None:
        self.size += len(data)
        if self.size > self.limit:
            raise UploadTooLarge(self.part, self.limit)
        self.fh.write(data)


class _FormSink:
    """python-multipart callbacks: the first file part named in ``files`` (name -> byte
    limit) goes to ``out`` (opened when it begins), the text parts named in ``texts`` (name
    -> character limit) to strings; other parts are skipped."""

    def __init__(self, files: dict[str, int], texts: dict[str, int], open_out) -> None:
        self.file_limits, self.text_limits, self.open_out = files, texts, open_out
        self.header_field = b""
        self.header_value = b""
        self.part: str | None = None
        self.filename: str | None = None
        self.out: _LimitedFile | None = None
        self.writing = False
        self.texts: dict[str, bytearray] = {}
        self.file_parts: list[str] = []

    def callbacks(self) -> dict:
        return {"on_part_begin": self.on_part_begin, "on_header_field": self.on_header_field,
                "on_header_value": self.on_header_value, "on_header_end": self.on_header_end,
                "on_part_data": self.on_part_data}

    def on_part_begin(self) -> None:
        self.part, self.writing = None, False

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self.header_field += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self.header_value += data[start:end]

    def on_header_end(self) -> None:
        if self.header_field.lower() == b"content-disposition":
            _, options = parse_options_header(self.header_value)
            self.part = options.get(b"name", b"").decode("latin-1")
            if self.part in self.file_limits:
                self.file_parts.append(self.part)
                if len(self.file_parts) == 1:  # only the first file part is kept
                    self.writing = True
                    self.filename = options.get(b"filename", b"").decode("utf-8", "replace")
                    self.out = self.open_out(self.part, self.file_limits[self.part])
        self.header_field = self.header_value = b""

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self.writing:
            self.out.write(data[start:end])
        elif self.part in self.text_limits:
            text = self.texts.setdefault(self.part, bytearray())
            if len(text) <= self.text_limits[self.part]:
                text += data[start:end]


async def receive_form(request: Request, tmp_dir: Path, files: dict[str, int],
                       texts: dict[str, int], suffix: str = "") -> FormUpload:
    """A ``multipart/form-data`` request's one file part (one of ``files``: name -> byte
    limit) in a temporary file under ``tmp_dir`` (the caller deletes it), and its text parts
    (``texts``: name -> character limit). HTTP 413 as soon as the file passes its limit (or
    the declared Content-Length passes the largest limit), 400 for a malformed body, none or
    several file parts, or an empty file."""
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > max(files.values()) + FORM_SLACK:
        raise HTTPException(413, f"upload of {declared} bytes exceeds the limit of "
                                 f"{max(files.values())}")
    ctype, options = parse_options_header(request.headers.get("content-type", ""))
    if ctype != b"multipart/form-data" or not options.get(b"boundary"):
        raise HTTPException(400, "send multipart/form-data with a boundary")
    private_dir(tmp_dir)
    fd, name = tempfile.mkstemp(prefix="upload-", suffix=suffix, dir=tmp_dir)
    path = Path(name)
    try:
        with os.fdopen(fd, "wb") as fh:
            sink = _FormSink(files, texts, lambda part, limit: _LimitedFile(fh, limit, part))
            parser = MultipartParser(options[b"boundary"], sink.callbacks())
            # the whole body too: parts that are skipped (unknown names, a second file) are
            # not stored, but they must not stream on without end
            body_limit = max(files.values()) + sum(texts.values()) + FORM_SLACK
            received = 0
            async for chunk in request.stream():
                received += len(chunk)
                if received > body_limit:
                    raise UploadTooLarge("request body", body_limit)
                parser.write(chunk)
            parser.finalize()
        wanted = " or ".join(f"'{n}'" for n in files)
        if len(sink.file_parts) != 1:
            raise HTTPException(400, f"send exactly one file part, named {wanted}")
        if sink.out is None or sink.out.size == 0:
            raise HTTPException(400, "empty upload")
        fields = {k: v[:texts[k]].decode("utf-8", "replace") for k, v in sink.texts.items()}
        overflow = {k for k, v in sink.texts.items() if len(v) > texts[k]}
        return FormUpload(sink.file_parts[0], path, sink.out.size, sink.filename or None,
                          fields, overflow)
    except BaseException as exc:
        raise _refused(path, exc, lambda e: f"the {e.part} is larger than {e.limit} bytes"
                       ) from None


def _refused(path: Path, exc: BaseException,
             too_large: Callable[[UploadTooLarge], str]) -> BaseException:
    """A failed upload's partial file goes; the error to raise: 413 ``too_large`` past its
    limit, an HTTPException (or anything not an Exception) as it was, else 400 malformed."""
    path.unlink(missing_ok=True)
    if isinstance(exc, UploadTooLarge):
        return HTTPException(413, too_large(exc))
    if isinstance(exc, HTTPException) or not isinstance(exc, Exception):
        return exc
    return HTTPException(400, f"malformed upload: {exc}")


async def receive_upload(request: Request, tmp_dir: Path, limit: int) -> Upload:
    """The request's zip in a temporary file under ``tmp_dir`` (the caller deletes it).

    HTTP 413 past ``limit`` bytes (checked on Content-Length first, then as bytes arrive),
    400 for a malformed or empty body.
    """
    ctype, _ = parse_options_header(request.headers.get("content-type", ""))
    if ctype == b"multipart/form-data":
        try:
            form = await receive_form(request, tmp_dir, {"file": limit},
                                      {"name": MAX_NAME_CHARS}, suffix=".zip")
        except HTTPException as exc:
            if exc.status_code == 413:
                raise HTTPException(413, f"upload exceeds the limit of {limit} bytes") from None
            raise
        return Upload(form.path, form.size, form.fields.get("name", "").strip() or None)
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > limit + FORM_SLACK:
        raise HTTPException(413, f"upload of {declared} bytes exceeds the limit of {limit}")
    private_dir(tmp_dir)
    fd, name = tempfile.mkstemp(prefix="upload-", suffix=".zip", dir=tmp_dir)
    path = Path(name)
    try:
        with os.fdopen(fd, "wb") as fh:
            out = _LimitedFile(fh, limit)
            async for chunk in request.stream():
                out.write(chunk)
        if out.size == 0:
            raise HTTPException(400, "empty upload")
        return Upload(path, out.size, None)
    except BaseException as exc:
        raise _refused(path, exc, lambda _: f"upload exceeds the limit of {limit} bytes"
                       ) from None
