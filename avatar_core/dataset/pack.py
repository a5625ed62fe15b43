"""`telesplat dataset zip`: a dataset folder as the archive `telesplat-client jobs submit
--archive` uploads.

The layout is what the server's archive reader (server/jobs/archive.py) expects: every file
of the dataset under one top-level folder named after it (``NAME/dataset.json``,
``NAME/cameras.json``, ...), plain files only (no symlinks, no absolute paths, no ``..``),
deflated. A dataset with validation errors (a missing image, a bad camera file: what
`telesplat dataset validate` lists) is refused before anything is written, as the server
would refuse it after the upload.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Callable
from pathlib import Path

from .problems import ERROR
from .validate import validate_dataset

__all__ = ["DatasetIncomplete", "zip_dataset"]


class DatasetIncomplete(ValueError):
    """The dataset has validation errors; ``problems`` lists them."""

    def __init__(self, root: Path, problems: list) -> None:
        shown = "\n  ".join(str(p) for p in problems[:10])
        more = f"\n  ... and {len(problems) - 10} more" if len(problems) > 10 else ""
        super().__init__(f"{root} is not a complete dataset ({len(problems)} error(s); "
                         f"'telesplat dataset validate {root}' lists them all):\n  "
                         f"{shown}{more}")
        self.problems = problems


def zip_dataset(root: str | Path, out: str | Path,
                progress: Callable[[int, int], None] | None = None) -> Path:
    """Write ``root`` (a valid dataset) to the zip ``out``; DatasetIncomplete if it has
    validation errors, ValueError for a symlink inside it. ``progress(done, total)`` counts
    files."""
    root, out = Path(root), Path(out)
    errors = [p for p in validate_dataset(root) if p.severity == ERROR]
    if errors:
        raise DatasetIncomplete(root, errors)
    files = []
    for dirpath, dirnames, filenames in os.walk(root):  # bounded: the dataset's own files
        dirnames.sort()
        for name in sorted(filenames):
            path = Path(dirpath) / name
            if path.is_symlink():
                raise ValueError(f"{path}: a symlink; the server accepts plain files only")
            if path.resolve() != out.resolve():
                files.append(path)
    top = root.resolve().name
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(out.name + ".partial")
    try:
        with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as z:
            for i, path in enumerate(files, 1):
                # PNG / JPEG are compressed already: stored, not deflated again
                kind = zipfile.ZIP_STORED if path.suffix in (".png", ".jpg", ".jpeg") \
                    else zipfile.ZIP_DEFLATED
                z.write(path, f"{top}/{path.relative_to(root).as_posix()}", kind)
                if progress is not None:
                    progress(i, len(files))
        partial.replace(out)
    finally:
        partial.unlink(missing_ok=True)
    return out
