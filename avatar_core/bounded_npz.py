"""Reading untrusted ``.npz`` files (and checking zips) within a memory budget.

``np.load`` trusts an archive: a member declaring a shape of 10**13 allocates before it reads,
and a few KB of deflated zeros unpack to gigabytes. :func:`read_npz` checks every member's
declared sizes and its ``.npy`` header (shape, dtype) before allocating, then reads exactly the
declared bytes (zipfile stops at the declared size, so a lying header only truncates).
Everything refused raises :class:`NpzError` naming the member and the sizes.
"""

from __future__ import annotations

import io
import math
import zipfile
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.lib import format as npy_format

__all__ = ["NpzError", "NpzLimits", "check_zip_members", "open_zip", "read_npz"]

_CHUNK = 1 << 20
# zipfile parses the whole central directory on open: bound its size by the member count
# (46 fixed bytes per entry plus a name and extras of a few hundred bytes on average).
CENTRAL_DIR_BYTES_PER_MEMBER = 320
_MAX_HEADER = 10_000      # numpy's own default bound on a .npy header
_NUMERIC_KINDS = "biufc"  # bool, ints, floats, complex: no objects, records or strings

# What reading a damaged archive or header can raise, besides our own checks.
_READ_ERRORS = (zipfile.BadZipFile, zlib.error, OSError, EOFError, ValueError, TypeError,
                SyntaxError, RecursionError, NotImplementedError, RuntimeError, OverflowError,
                KeyError, UnicodeDecodeError)


class NpzError(ValueError):
    """An ``.npz`` (or zip) that is malformed or over its limits; the message says which member
    and which sizes. ``over_limit``: refused for a limit (size, count, ratio), not as damaged."""

    def __init__(self, message: str, *, over_limit: bool = False) -> None:
        super().__init__(message)
        self.over_limit = over_limit


@dataclass(frozen=True)
class NpzLimits:
    max_members: int = 64                # arrays in one file
    max_array_bytes: int = 512 * 2**20   # one array, unpacked
    max_total_bytes: int = 1 * 2**30     # all arrays together, unpacked
    max_ratio: float = 100.0             # unpacked / packed size of one member...
    ratio_floor_bytes: int = 1 << 20     # ...once it unpacks to more than this

    def __post_init__(self) -> None:
        if min(self.max_members, self.max_array_bytes, self.max_total_bytes,
               self.ratio_floor_bytes) < 0 or not self.max_ratio >= 1:
            raise ValueError(f"bad npz limits: {self}")


def open_zip(source: str | Path | BinaryIO, max_members: int, *,
             what: str = "archive") -> zipfile.ZipFile:
    """A ZipFile, opened only once its end record shows at most ``max_members`` entries and a
    central directory of a size to match; NpzError otherwise (also when it is no zip)."""
    try:
        if isinstance(source, str | Path):
            with open(source, "rb") as fp:
                end = zipfile._EndRecData(fp)  # noqa: SLF001 (stable since Python 2)
        else:
            source.seek(0)
            end = zipfile._EndRecData(source)  # noqa: SLF001
            source.seek(0)
        if end is None:
            raise NpzError(f"the {what} is not a zip file (no end of central directory)")
        entries, cd_size = end[zipfile._ECD_ENTRIES_TOTAL], end[zipfile._ECD_SIZE]  # noqa: SLF001
        if entries > max_members or cd_size > max_members * CENTRAL_DIR_BYTES_PER_MEMBER:
            raise NpzError(f"the {what} declares {entries} members ({cd_size} bytes of "
                           f"directory), more than the {max_members} allowed", over_limit=True)
        return zipfile.ZipFile(source)
    except NpzError:
        raise
    except _READ_ERRORS as exc:
        raise NpzError(f"the {what} is not a readable zip: {type(exc).__name__}: {exc}"
                       ) from None


def check_zip_members(infos: Iterable[zipfile.ZipInfo], limits: NpzLimits, *,
                      what: str = "archive") -> int:
    """Refuse encrypted members and members whose declared unpacked / packed ratio is past
    ``limits.max_ratio`` (a decompression bomb); the declared unpacked total."""
    total = 0
    for info in infos:
        if info.flag_bits & 0x1:
            raise NpzError(f"{what} member {info.filename!r} is encrypted")
        if info.file_size > limits.ratio_floor_bytes and \
                info.file_size > limits.max_ratio * max(info.compress_size, 1):
            raise NpzError(f"{what} member {info.filename!r} unpacks {info.compress_size} bytes "
                           f"to {info.file_size} (more than {limits.max_ratio:g} times): "
                           "refused as a decompression bomb", over_limit=True)
        total += info.file_size
    return total


def _header(fp: BinaryIO, member: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    version = npy_format.read_magic(fp)
    if version == (1, 0):
        shape, fortran, dtype = npy_format.read_array_header_1_0(fp, _MAX_HEADER)
    elif version == (2, 0):
        shape, fortran, dtype = npy_format.read_array_header_2_0(fp, _MAX_HEADER)
    else:
        raise NpzError(f"npz member {member!r}: .npy format version {version} is not supported")
    if not isinstance(dtype, np.dtype) or dtype.kind not in _NUMERIC_KINDS or dtype.hasobject \
            or dtype.subdtype is not None or dtype.itemsize == 0:
        raise NpzError(f"npz member {member!r}: dtype {dtype} is not a plain number type")
    if not all(isinstance(n, int) and n >= 0 for n in shape):
        raise NpzError(f"npz member {member!r}: bad shape {shape}")
    return tuple(shape), bool(fortran), dtype


def _read_exactly(fp: BinaryIO, out: memoryview, member: str) -> None:
    done = 0
    while done < len(out):
        chunk = fp.read(min(_CHUNK, len(out) - done))
        if not chunk:
            raise NpzError(f"npz member {member!r} is truncated: {done} of {len(out)} bytes")
        out[done:done + len(chunk)] = chunk
        done += len(chunk)


def _read_member(z: zipfile.ZipFile, info: zipfile.ZipInfo, limits: NpzLimits,
                 spent: int) -> np.ndarray:
    member = info.filename
    with z.open(info) as fp:
        shape, fortran, dtype = _header(fp, member)
        nbytes = math.prod(shape) * dtype.itemsize  # Python ints: no overflow
        if nbytes > limits.max_array_bytes:
            raise NpzError(f"npz member {member!r} declares shape {shape} of {dtype} "
                           f"({nbytes} bytes), more than the {limits.max_array_bytes} allowed "
                           "per array", over_limit=True)
        if spent + nbytes > limits.max_total_bytes:
            raise NpzError(f"npz member {member!r} ({nbytes} bytes) takes the arrays past the "
                           f"{limits.max_total_bytes} bytes allowed in all", over_limit=True)
        if nbytes > info.file_size:
            raise NpzError(f"npz member {member!r} declares {nbytes} bytes of data in a "
                           f"{info.file_size}-byte member")
        flat = np.empty(math.prod(shape), dtype=dtype)
        _read_exactly(fp, memoryview(flat.view(np.uint8)), member)
    if fortran:
        return flat.reshape(shape[::-1]).transpose()
    return flat.reshape(shape)


def read_npz(source: str | Path | bytes | BinaryIO, limits: NpzLimits | None = None
             ) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` (keys without ``.npy``), each read only after its header and
    sizes pass ``limits``; NpzError otherwise (also for anything malformed)."""
    limits = limits or NpzLimits()
    if isinstance(source, bytes | bytearray | memoryview):
        source = io.BytesIO(source)
    try:
        with open_zip(source, limits.max_members, what="npz") as z:
            infos = [i for i in z.infolist() if not i.is_dir()]
            if len(infos) > limits.max_members:
                raise NpzError(f"the npz holds {len(infos)} members, more than the "
                               f"{limits.max_members} allowed", over_limit=True)
            check_zip_members(infos, limits, what="npz")
            arrays: dict[str, np.ndarray] = {}
            spent = 0
            for info in infos:
                if not info.filename.endswith(".npy"):
                    raise NpzError(f"npz member {info.filename!r} is not an .npy array")
                key = info.filename[:-4]
                if key in arrays:
                    raise NpzError(f"npz member {info.filename!r} appears twice")
                arrays[key] = _read_member(z, info, limits, spent)
                spent += arrays[key].nbytes
            return arrays
    except NpzError:
        raise
    except MemoryError as exc:  # within the limits, but the machine has less
        raise NpzError(f"not enough memory to read the npz: {exc}") from None
    except _READ_ERRORS as exc:
        raise NpzError(f"not a readable npz: {type(exc).__name__}: {exc}") from None
