"""Checks of the per-view files (images, masks, part labels) of a dataset.

Shallow checks need directory listings and the first bytes of each file (its header);
deep checks decode every file. The cost follows the files present, not the frame counts that
dataset.json declares: missing files are listed up to MAX_MISSING_LISTED per camera folder,
then counted (a declared count of 10^9 frames must not cost 10^9 problems).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from .format import KINDS, frame_file
from .imageio import decode_gray, decode_rgb, read_header
from .problems import WARNING, Problem, problem

__all__ = ["Kind", "check_files"]

_SINGULAR = {"images": "image", "masks": "mask", "parts": "parts"}
MAX_MISSING_LISTED = 20  # missing files named one by one per camera folder; the rest counted


@dataclass(frozen=True)
class Kind:
    """One kind of per-view file a dataset declares."""

    folder: str     # "images" | "masks" | "parts"
    ext: str        # "png" | "jpg"
    channels: int   # 3 for images, 1 for masks and parts


def _listdir(path: Path) -> list[str] | None:
    try:
        return os.listdir(path)
    except (FileNotFoundError, NotADirectoryError):
        return None


@dataclass(frozen=True)
class _File:
    kind: str
    sequence: str
    camera: str
    frame: int
    path: Path
    rel: str


def _walk(root: Path, sequences: Mapping[str, int], kinds: list[Kind], cam_names: list[str]
          ) -> tuple[list[_File], list[Problem]]:
    """Present files, and the missing / extra ones, from directory listings only."""
    files: list[_File] = []
    problems: list[Problem] = []
    seq_root = root / "sequences"
    for name in sorted(set(_listdir(seq_root) or []) - set(sequences)):
        problems.append(problem("extra_file", f"sequences/{name} is not a listed sequence",
                                WARNING, path=f"sequences/{name}"))
    declared = {k.folder for k in kinds}
    for seq, T in sequences.items():
        for kind in sorted(set(KINDS) - declared):
            if (seq_root / seq / kind).exists():
                problems.append(problem("extra_file", f"{kind} present but dataset.json "
                                        f"declares none", WARNING, sequence=seq,
                                        path=f"sequences/{seq}/{kind}"))
        for kind, ext in ((k.folder, k.ext) for k in kinds):
            kind_dir = seq_root / seq / kind
            for extra in sorted(set(_listdir(kind_dir) or []) - set(cam_names)):
                problems.append(problem("extra_file", f"{kind}/{extra} is not a camera",
                                        WARNING, sequence=seq,
                                        path=f"sequences/{seq}/{kind}/{extra}"))
            for cam in cam_names:
                listed = set(_listdir(kind_dir / cam) or [])
                present = _frames_in(listed, T, ext)
                for f in sorted(present):
                    rel = f"sequences/{seq}/{kind}/{cam}/{present[f]}"
                    files.append(_File(kind, seq, cam, f, root / rel, rel))
                problems += _missing(seq, kind, cam, ext, T, present)
                for fname in sorted(listed - set(present.values())):
                    problems.append(problem(
                        "extra_file", f"{fname} is not a frame of this sequence "
                        f"({T} frames, .{ext})", WARNING, sequence=seq, camera=cam,
                        path=f"sequences/{seq}/{kind}/{cam}/{fname}"))
    return files, problems


def _frames_in(listed: set[str], T: int, ext: str) -> dict[int, str]:
    """{frame: file name} of the listed names that are frames 0..T-1 (``00042.png``)."""
    out = {}
    for name in listed:
        stem, dot, suffix = name.rpartition(".")
        if dot and suffix == ext and stem.isascii() and stem.isdigit() and len(stem) <= 12:
            f = int(stem)
            if f < T and frame_file(f, ext) == name:
                out[f] = name
    return out


def _missing(seq: str, kind: str, cam: str, ext: str, T: int, present: dict[int, str]
             ) -> list[Problem]:
    """The first MAX_MISSING_LISTED missing frames of a camera folder, then one count."""
    code, out = f"missing_{_SINGULAR[kind]}", []
    missing = T - len(present)
    f = 0
    while len(out) < min(missing, MAX_MISSING_LISTED):  # ends: at most len(present) skipped
        if f not in present:
            rel = f"sequences/{seq}/{kind}/{cam}/{frame_file(f, ext)}"
            out.append(problem(code, f"{rel} is missing", sequence=seq, camera=cam,
                               frames=(f,), path=rel))
        f += 1
    if missing > len(out):
        rel = f"sequences/{seq}/{kind}/{cam}"
        out.append(problem(code, f"{rel}: {missing - len(out)} more of its {T} frames are "
                                 "missing", sequence=seq, camera=cam, path=rel))
    return out


def _header_problems(f: _File, size: tuple[int, int] | None, ext: str, channels: int
                     ) -> list[Problem]:
    where = {"sequence": f.sequence, "camera": f.camera, "frames": (f.frame,), "path": f.rel}
    try:
        h = read_header(f.path)
    except (OSError, ValueError) as exc:
        return [problem("unreadable_file", f"{f.rel}: {exc}", **where)]
    out = []
    if h.kind != ext or h.bit_depth != 8 or h.channels != channels or h.palette:
        want = "8-bit RGB" if channels == 3 else "8-bit single-channel"
        out.append(problem("bad_file_format", f"{f.rel} must be {want} {ext}, got "
                           f"{h.bit_depth}-bit {h.channels}-channel {h.kind}", **where))
    if size is not None and (h.width, h.height) != size:
        out.append(problem(f"{_SINGULAR[f.kind]}_size_mismatch",
                           f"{f.rel} is {h.width}x{h.height}, camera {f.camera} is "
                           f"{size[0]}x{size[1]}", **where))
    return out


def _decoded_problems(f: _File, size: tuple[int, int] | None, num_parts: int | None
                      ) -> tuple[list[Problem], bool]:
    """Problems of the decoded file, and whether it holds any foreground (masks)."""
    where = {"sequence": f.sequence, "camera": f.camera, "frames": (f.frame,), "path": f.rel}
    try:
        img = decode_rgb(f.path) if f.kind == "images" else decode_gray(f.path)
    except (OSError, ValueError) as exc:
        return [problem("unreadable_file", f"{f.rel}: {exc}", **where)], False
    out = []
    if size is not None and (img.shape[1], img.shape[0]) != size:
        out.append(problem(f"{_SINGULAR[f.kind]}_size_mismatch", f"{f.rel} decodes to "
                           f"{img.shape[1]}x{img.shape[0]}, camera {f.camera} is "
                           f"{size[0]}x{size[1]}", **where))
    if f.kind == "parts" and num_parts is not None and int(img.max()) > num_parts:
        out.append(problem("parts_bad_value", f"{f.rel} holds label {int(img.max())} but "
                           f"there are {num_parts} parts (labels 0..{num_parts})", **where))
    return out, bool(f.kind == "masks" and img.any())


def check_files(root: Path, sequences: Mapping[str, int], kinds: list[Kind],
                sizes: Mapping[str, tuple[int, int] | None], num_parts: int | None,
                deep: bool) -> list[Problem]:
    """Problems of the per-view files of every (sequence, camera, frame): missing, extra
    (warnings), unreadable, of the wrong format or size; with `deep`, decoded contents
    (part values, cameras whose masks are all empty). `sizes`: camera -> (W, H), None when
    its record is too broken to say."""
    if not sequences or not sizes:
        return []
    files, problems = _walk(root, sequences, kinds, sorted(sizes))
    fmt = {k.folder: (k.ext, k.channels) for k in kinds}
    for f in files:
        problems += _header_problems(f, sizes[f.camera], *fmt[f.kind])
    if not deep:
        return problems
    with ThreadPoolExecutor(4) as pool:  # cv2 decoding releases the GIL
        results = list(pool.map(lambda f: _decoded_problems(f, sizes[f.camera], num_parts),
                                files))
    masked: dict[str, bool] = {}
    for f, (more, foreground) in zip(files, results, strict=True):
        problems += more
        if f.kind == "masks":
            masked[f.camera] = masked.get(f.camera, False) or foreground
    problems += [problem("camera_masks_empty", f"every mask of camera {cam} is empty: it "
                         "never sees the subject", camera=cam)
                 for cam, seen in sorted(masked.items()) if not seen]
    return problems
