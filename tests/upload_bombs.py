"""Hostile archives for the upload tests: decompression bombs, impossible shapes, damage.

Bombs are written in chunks, so building one costs megabytes of memory, not gigabytes.
"""

from __future__ import annotations

import io
import zipfile
import zlib

import numpy as np
from numpy.lib import format as npy_format

CHUNK = 1 << 20


def npy_header(shape: tuple[int, ...], dtype: str = "<f4") -> bytes:
    buf = io.BytesIO()
    npy_format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False,
                                            "shape": shape})
    return buf.getvalue()


class _FlushedDeflate:
    """zlib's deflate with a full flush after every write: after one the compressor starts
    afresh, so a repeated chunk (the zeros) deflates to the same bytes, computed once. A GiB
    bomb then costs a CRC pass instead of deflating a GiB (tens of seconds on a busy CI)."""

    def __init__(self, level: int):
        self._deflate = zlib.compressobj(level, zlib.DEFLATED, -15)  # zipfile's raw stream
        self._seen: dict[bytes, bytes] = {}

    def compress(self, data: bytes) -> bytes:
        if data not in self._seen:
            self._seen.clear()  # one repeated chunk at a time
            self._seen[data] = self._deflate.compress(data) + self._deflate.flush(
                zlib.Z_FULL_FLUSH)
        return self._seen[data]

    def flush(self) -> bytes:
        return self._deflate.flush()


def zeros_member(z: zipfile.ZipFile, name: str, nbytes: int, *, header: bytes | None = None
                 ) -> None:
    """A deflated member: ``header`` (default: a float32 .npy header of the right shape)
    followed by ``nbytes`` zero bytes, written a chunk at a time."""
    header = npy_header((nbytes // 4,)) if header is None else header
    info = zipfile.ZipInfo(name)
    info.compress_type = zipfile.ZIP_DEFLATED
    with z.open(info, "w", force_zip64=True) as out:
        # zipfile has no public way to give a member's compressor; its writer calls
        # compress() per write and flush() at the end, as _FlushedDeflate does
        out._compressor = _FlushedDeflate(zlib.Z_DEFAULT_COMPRESSION)
        out.write(header)
        zeros = bytes(CHUNK)
        left = nbytes
        while left > 0:
            out.write(zeros[:min(CHUNK, left)])
            left -= CHUNK


def npz_bytes(arrays: dict[str, np.ndarray], *, bomb: tuple[str, int] | None = None,
              raw: dict[str, bytes] | None = None) -> bytes:
    """An npz of ``arrays``, plus a zeros member ``bomb = (key, nbytes)`` and members whose
    bytes are given as is (``raw``: key -> .npy bytes)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for key, arr in arrays.items():
            member = io.BytesIO()
            npy_format.write_array(member, np.asanyarray(arr), allow_pickle=False)
            z.writestr(f"{key}.npy", member.getvalue())
        for key, data in (raw or {}).items():
            z.writestr(f"{key}.npy", data)
        if bomb is not None:
            zeros_member(z, f"{bomb[0]}.npy", bomb[1])
    return buf.getvalue()


def impossible_shape_npy(shape: tuple[int, ...] = (10**13,)) -> bytes:
    """A .npy declaring ``shape`` and holding a few bytes of data."""
    return npy_header(shape) + b"\0" * 64


def zip_bomb(name: str, nbytes: int, extra: dict[str, bytes] | None = None) -> bytes:
    """A zip of small members ``extra`` and one member of ``nbytes`` zeros (no .npy header)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for member, data in (extra or {}).items():
            z.writestr(member, data)
        zeros_member(z, name, nbytes, header=b"")
    return buf.getvalue()


def corrupt(data: bytes, *, at: float = 0.5, span: int = 64) -> bytes:
    """``data`` with ``span`` bytes at fraction ``at`` inverted (damaged member data)."""
    out = bytearray(data)
    start = int(len(out) * at)
    for i in range(start, min(start + span, len(out))):
        out[i] ^= 0xFF
    return bytes(out)
