"""Streaming an uploaded avatar zip to a temporary file, with the size limit enforced while the
bytes arrive (nothing is buffered whole in memory, nothing over the limit is kept).

Accepts ``multipart/form-data`` with a ``file`` part (and an optional ``name`` field), or the
zip as the raw body (``application/zip`` / ``application/octet-stream``).
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

from fastapi import HTTPException, Request
from python_multipart.multipart import MultipartParser, parse_options_header

from .private import private_dir

MAX_NAME_CHARS = 200


class UploadTooLarge(Exception):
    pass


@dataclass
class Upload:
    path: Path
    size: int
    name: str | None


class _LimitedFile:
    def __init__(self, fh, limit: int) -> None:
        self.fh, self.limit, self.size = fh, limit, 0

    def write(self, data: bytes) -> None:
        self.size += len(data)
        if self.size > self.limit:
            raise UploadTooLarge
        self.fh.write(data)


class _FormSink:
    """python-multipart callbacks: the ``file`` part goes to disk, ``name`` to a string."""

    def __init__(self, out: _LimitedFile) -> None:
        self.out = out
        self.header_field = b""
        self.header_value = b""
        self.part: str | None = None
        self.name = bytearray()
        self.files = 0

    def callbacks(self) -> dict:
        return {"on_part_begin": self.on_part_begin, "on_header_field": self.on_header_field,
                "on_header_value": self.on_header_value, "on_header_end": self.on_header_end,
                "on_part_data": self.on_part_data}

    def on_part_begin(self) -> None:
        self.part = None

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self.header_field += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self.header_value += data[start:end]

    def on_header_end(self) -> None:
        if self.header_field.lower() == b"content-disposition":
            _, options = parse_options_header(self.header_value)
            self.part = options.get(b"name", b"").decode("latin-1")
            if self.part == "file":
                self.files += 1
        self.header_field = self.header_value = b""

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self.part == "file" and self.files == 1:
            self.out.write(data[start:end])
        elif self.part == "name" and len(self.name) <= MAX_NAME_CHARS:
            self.name += data[start:end]


async def receive_upload(request: Request, tmp_dir: Path, limit: int) -> Upload:
    """The request's zip in a temporary file under ``tmp_dir`` (the caller deletes it).

    HTTP 413 past ``limit`` bytes (checked on Content-Length first, then as bytes arrive),
    400 for a malformed or empty body.
    """
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > limit + 64 * 1024:
        raise HTTPException(413, f"upload of {declared} bytes exceeds the limit of {limit}")
    ctype, options = parse_options_header(request.headers.get("content-type", ""))
    private_dir(tmp_dir)
    fd, name = tempfile.mkstemp(prefix="upload-", suffix=".zip", dir=tmp_dir)
    path = Path(name)
    try:
        with os.fdopen(fd, "wb") as fh:
            out = _LimitedFile(fh, limit)
            form_name = None
            if ctype == b"multipart/form-data":
                boundary = options.get(b"boundary")
                if not boundary:
                    raise HTTPException(400, "multipart body without a boundary")
                sink = _FormSink(out)
                parser = MultipartParser(boundary, sink.callbacks())
                async for chunk in request.stream():
                    parser.write(chunk)
                parser.finalize()
                if sink.files != 1:
                    raise HTTPException(400, "send exactly one form part named 'file'")
                form_name = sink.name.decode("utf-8", "replace").strip() or None
            else:
                async for chunk in request.stream():
                    out.write(chunk)
        if out.size == 0:
            raise HTTPException(400, "empty upload")
        return Upload(path, out.size, form_name)
    except UploadTooLarge:
        path.unlink(missing_ok=True)
        raise HTTPException(413, f"upload exceeds the limit of {limit} bytes") from None
    except HTTPException:
        path.unlink(missing_ok=True)
        raise
    except Exception as exc:
        path.unlink(missing_ok=True)
        raise HTTPException(400, f"malformed upload: {exc}") from exc
