"""Uploaded dataset archives: every member checked before anything is unpacked.

A member must be a plain file or folder with a relative path without ``..`` (no absolute
paths, drive letters, backslashes, symlinks, device files or encryption); the members are
bounded in number (checked on the end record, before the directory is parsed), each in its
unpacked size and its unpacked / packed ratio (a decompression bomb), and all together in
unpacked size and against the owner's storage left. Unpacking then counts the bytes actually
written, per member and in all, so a header that lies about a size cannot get more onto the
disk. A damaged archive (truncated, bad CRC, unknown method) is a 400. The dataset's root is
the archive's top level or its one top-level folder (where ``dataset.json`` is).
"""

from __future__ import annotations

import re
import shutil
import stat
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from avatar_core.bounded_npz import NpzError, NpzLimits, check_zip_members, open_zip
from avatar_core.dataset.format import PARAMS_NPZ_LIMITS

__all__ = ["ArchiveError", "UploadLimits", "check_archive", "extract_archive"]

_DRIVE = re.compile(r"^[A-Za-z]:")
_CHUNK = 1 << 20


@dataclass(frozen=True)
class UploadLimits:
    max_upload_bytes: int = 512 * 2**20      # the request body
    max_unpacked_bytes: int = 8 * 2**30      # all members together, unpacked
    max_files: int = 100_000                 # members
    max_member_bytes: int = 1 * 2**30        # one member, unpacked
    max_json_bytes: int = 16 * 2**20         # one .json member (parsed whole, ~10x in memory)
    max_ratio: float = 100.0                 # unpacked / packed of a member past ratio_floor
    ratio_floor_bytes: int = 1 << 20
    quota_bytes: int | None = None           # the owner's storage left (None: no quota)
    max_npz_array_bytes: int = PARAMS_NPZ_LIMITS.max_array_bytes  # params.npz, when read
    max_npz_bytes: int = PARAMS_NPZ_LIMITS.max_total_bytes

    def ratio_limits(self) -> NpzLimits:
        return NpzLimits(max_ratio=self.max_ratio, ratio_floor_bytes=self.ratio_floor_bytes)

    def npz_limits(self) -> NpzLimits:
        """How the unpacked dataset's params.npz files are read."""
        return NpzLimits(max_array_bytes=self.max_npz_array_bytes,
                         max_total_bytes=self.max_npz_bytes, max_ratio=self.max_ratio,
                         ratio_floor_bytes=self.ratio_floor_bytes)

    @property
    def budget(self) -> int:
        """Bytes the archive may unpack to: the unpacked limit, or the quota left if less."""
        if self.quota_bytes is None:
            return self.max_unpacked_bytes
        return max(0, min(self.max_unpacked_bytes, self.quota_bytes))


def _over_budget(limits: UploadLimits) -> ArchiveError:
    if limits.quota_bytes is not None and limits.quota_bytes < limits.max_unpacked_bytes:
        return ArchiveError(f"the archive unpacks to more than the {max(0, limits.quota_bytes)} "
                            "bytes left of your storage quota", 413)
    return ArchiveError(f"the archive unpacks to more than the {limits.max_unpacked_bytes} "
                        "bytes allowed", 413)


class ArchiveError(ValueError):
    """An archive that is refused; ``status`` is the HTTP status to answer (400 or 413)."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


def _member_path(info: zipfile.ZipInfo) -> PurePosixPath:
    name = info.filename
    if not name or "\x00" in name or "\\" in name:
        raise ArchiveError(f"archive member {name!r}: bad characters in the name")
    if name.startswith("/") or _DRIVE.match(name):
        raise ArchiveError(f"archive member {name!r}: absolute paths are not allowed")
    path = PurePosixPath(name)
    if any(part == ".." for part in path.parts):
        raise ArchiveError(f"archive member {name!r}: '..' is not allowed in a path")
    mode = info.external_attr >> 16
    kind = stat.S_IFMT(mode)
    if kind == stat.S_IFLNK:
        raise ArchiveError(f"archive member {name!r}: symlinks are not allowed")
    if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
        raise ArchiveError(f"archive member {name!r}: only files and folders are allowed")
    if info.flag_bits & 0x1:
        raise ArchiveError(f"archive member {name!r}: encrypted members are not supported")
    return path


def check_archive(path: str | Path | BinaryIO, limits: UploadLimits) -> list[zipfile.ZipInfo]:
    """The file members of a zip that passes every check; ArchiveError otherwise."""
    try:
        with open_zip(path, limits.max_files, what="upload") as z:
            infos = z.infolist()
    except NpzError as exc:
        if exc.over_limit:
            raise ArchiveError(str(exc), 413) from None
        raise ArchiveError(f"the upload is not a readable zip archive: {exc}") from None
    if len(infos) > limits.max_files:
        raise ArchiveError(f"the archive has {len(infos)} members, more than the "
                           f"{limits.max_files} allowed", 413)
    try:
        check_zip_members(infos, limits.ratio_limits())
    except NpzError as exc:
        raise ArchiveError(str(exc), 413 if exc.over_limit else 400) from None
    seen: set[str] = set()
    total = 0
    files = []
    for info in infos:
        member = _member_path(info)
        key = str(member)
        if key in seen:
            raise ArchiveError(f"archive member {info.filename!r} appears twice")
        seen.add(key)
        if info.is_dir():
            continue
        if info.file_size > limits.max_member_bytes:
            raise ArchiveError(f"archive member {info.filename!r} unpacks to {info.file_size} "
                               f"bytes, more than the {limits.max_member_bytes} allowed", 413)
        if info.filename.endswith(".json") and info.file_size > limits.max_json_bytes:
            raise ArchiveError(f"archive member {info.filename!r} is {info.file_size} bytes of "
                               f"JSON, more than the {limits.max_json_bytes} allowed", 413)
        total += info.file_size
        if total > limits.budget:
            raise _over_budget(limits)
        files.append(info)
    if not files:
        raise ArchiveError("the archive is empty")
    return files


def _dataset_root(files: list[zipfile.ZipInfo]) -> PurePosixPath:
    paths = [PurePosixPath(i.filename) for i in files]
    if PurePosixPath("dataset.json") in paths:
        return PurePosixPath(".")
    tops = {p.parts[0] for p in paths}
    if len(tops) == 1 and all(len(p.parts) > 1 for p in paths):
        top = PurePosixPath(tops.pop())
        if top / "dataset.json" in paths:
            return top
    raise ArchiveError("no dataset.json at the top of the archive or in its one top-level "
                       "folder")


def extract_archive(path: str | Path | BinaryIO, dest: str | Path, limits: UploadLimits) -> Path:
    """Unpack a checked archive into ``dest`` (created; must not exist) and return the
    dataset's root inside it. On any error ``dest`` is removed and ArchiveError raised."""
    files = check_archive(path, limits)
    root = _dataset_root(files)
    dest = Path(dest)
    dest.mkdir(parents=True)
    written = 0
    try:
        with open_zip(path, limits.max_files, what="upload") as z:
            for info in files:
                target = dest.joinpath(*PurePosixPath(info.filename).parts)
                target.parent.mkdir(parents=True, exist_ok=True)
                with z.open(info) as src, open(target, "xb") as out:
                    member = 0  # never more than declared, whatever the stream holds
                    while chunk := src.read(min(_CHUNK, info.file_size - member + 1)):
                        member += len(chunk)
                        written += len(chunk)
                        if member > info.file_size:
                            raise ArchiveError(f"archive member {info.filename!r} unpacks to "
                                               "more than its declared size")
                        if written > limits.budget:
                            raise _over_budget(limits)
                        out.write(chunk)
    except ArchiveError:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    except (zipfile.BadZipFile, zlib.error, OSError, EOFError, ValueError, RuntimeError,
            NotImplementedError, NpzError) as exc:
        shutil.rmtree(dest, ignore_errors=True)
        # an OSError names a server path (the scratch folder): only its reason goes out
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise ArchiveError(f"the archive cannot be unpacked: {reason}") from exc
    return dest.joinpath(*root.parts) if root.parts else dest
