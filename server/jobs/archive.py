"""Uploaded dataset archives: every member checked before anything is unpacked.

A member must be a plain file or folder with a relative path without ``..`` (no absolute
paths, drive letters, backslashes, symlinks, device files or encryption); the members are
bounded in number and in total unpacked size. Unpacking then counts the bytes actually
written, so a header that lies about a size cannot get more onto the disk. The dataset's root
is the archive's top level or its one top-level folder (where ``dataset.json`` is).
"""

from __future__ import annotations

import re
import shutil
import stat
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

__all__ = ["ArchiveError", "UploadLimits", "check_archive", "extract_archive"]

_DRIVE = re.compile(r"^[A-Za-z]:")
_CHUNK = 1 << 20


@dataclass(frozen=True)
class UploadLimits:
    max_upload_bytes: int = 512 * 2**20      # the request body
    max_unpacked_bytes: int = 8 * 2**30      # all members together, unpacked
    max_files: int = 100_000                 # members


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
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise ArchiveError(f"the upload is not a readable zip archive: {exc}") from exc
    if len(infos) > limits.max_files:
        raise ArchiveError(f"the archive has {len(infos)} members, more than the "
                           f"{limits.max_files} allowed", 413)
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
        total += info.file_size
        if total > limits.max_unpacked_bytes:
            raise ArchiveError(f"the archive unpacks to more than the "
                               f"{limits.max_unpacked_bytes} bytes allowed", 413)
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
        with zipfile.ZipFile(path) as z:
            for info in files:
                target = dest.joinpath(*PurePosixPath(info.filename).parts)
                target.parent.mkdir(parents=True, exist_ok=True)
                with z.open(info) as src, open(target, "xb") as out:
                    while chunk := src.read(_CHUNK):
                        written += len(chunk)
                        if written > limits.max_unpacked_bytes:
                            raise ArchiveError("the archive unpacks to more than the "
                                               f"{limits.max_unpacked_bytes} bytes allowed",
                                               413)
                        out.write(chunk)
    except ArchiveError:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, RuntimeError) as exc:
        shutil.rmtree(dest, ignore_errors=True)
        raise ArchiveError(f"the archive cannot be unpacked: {exc}") from exc
    return dest.joinpath(*root.parts) if root.parts else dest
