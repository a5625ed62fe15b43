"""Validation of a dataset folder: every problem at once, each with a code and a location.

Shallow validation (the default) reads the three JSON files, lists the folders, reads each
image's header (size, channels, bit depth: a few bytes per file) and loads the parameters.
`deep=True` also decodes every image, mask and part map (part values, empty masks).
The codes are listed in docs/dataset.md.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..bounded_npz import NpzLimits, read_npz
from .format import (
    CAMERAS_JSON,
    DATASET_JSON,
    FORMAT_NAME,
    FORMAT_VERSION,
    IMAGE_FORMATS,
    MASK_FORMAT,
    PARAMS_NPZ,
    PARAMS_NPZ_LIMITS,
    ROOT_CONVENTIONS,
    SPLITS_JSON,
    check_name,
    inside,
    is_finite_number,
)
from .params import check_params, param_spec
from .problems import ERROR, WARNING, Problem, problem
from .validate_cameras import box_visible, check_cameras, check_visibility
from .validate_files import Kind, check_files

__all__ = ["box_visible", "check_documents", "check_meta", "read_json", "validate_dataset"]

_BODY_TYPES = ("smplx", "flame", "mano")


def read_json(path: Path, missing_code: str) -> tuple[Any, list[Problem]]:
    """(document, problems); the document is None when it is absent or unreadable."""
    name = path.name
    if not path.is_file():
        return None, [problem(missing_code, f"{name} is missing", path=name)]
    try:
        return json.loads(path.read_text(encoding="utf-8")), []
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: bad UTF-8 or JSON
        return None, [problem("invalid_json", f"{name} cannot be read: {exc}", path=name)]


def validate_dataset(root: str | Path, *, deep: bool = False,
                     npz_limits: NpzLimits = PARAMS_NPZ_LIMITS) -> list[Problem]:
    """Every problem of the dataset at `root` (errors and warnings), in a stable order.
    Parameter files are read within `npz_limits` (a file past them is an error)."""
    root = Path(root)
    meta, problems = read_json(root / DATASET_JSON, "missing_dataset_json")
    cameras, more = read_json(root / CAMERAS_JSON, "missing_cameras_json")
    problems += more
    splits, more = read_json(root / SPLITS_JSON, "missing_splits_json")
    problems += more
    if meta is None or cameras is None:
        return problems
    return problems + check_documents(root, meta, cameras, splits or {}, deep=deep,
                                      npz_limits=npz_limits)


@dataclass(frozen=True)
class _Info:
    """What the file checks need from dataset.json (None: unusable, already reported)."""

    sequences: dict[str, int]
    image_format: str | None
    masks: bool
    parts: bool
    num_parts: int | None
    bounds: np.ndarray | None      # [2, 3]
    body_model: dict | None


def check_documents(root: Path, meta: Any, cameras_doc: Any, splits_doc: Any, *,
                    deep: bool = False, npz_limits: NpzLimits = PARAMS_NPZ_LIMITS
                    ) -> list[Problem]:
    """Validate parsed dataset.json / cameras.json / splits.json against the files under
    `root` (the writer calls this before it writes dataset.json)."""
    problems, info = _check_meta(meta)
    if info is None:
        return problems
    cams, sizes, more = check_cameras(cameras_doc)
    problems += more
    problems += check_visibility(cams, info.bounds)
    if info.image_format is not None:
        problems += check_files(Path(root), info.sequences, _kinds(info), sizes,
                                info.num_parts, deep)
    problems += _check_all_params(Path(root), info, npz_limits)
    problems += _check_splits(Path(root), splits_doc, set(info.sequences), set(sizes))
    return problems


# -- dataset.json ---------------------------------------------------------------------------

def check_meta(meta: Any) -> list[Problem]:
    """The problems of a dataset.json document alone (no files are read)."""
    return _check_meta(meta)[0]


def _is_int(x: Any, minimum: int) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and x >= minimum


def _check_meta(meta: Any) -> tuple[list[Problem], _Info | None]:
    def bad(key: str, message: str) -> None:
        problems.append(problem("bad_metadata", message, key=key, path=DATASET_JSON))

    problems: list[Problem] = []
    if not isinstance(meta, dict):
        bad("format", "dataset.json must hold a JSON object")
        return problems, None
    if meta.get("format") != FORMAT_NAME:
        problems.append(problem("unknown_format", f"format is {meta.get('format')!r}, "
                                f"expected {FORMAT_NAME!r}", key="format", path=DATASET_JSON))
        return problems, None
    version = meta.get("version")
    if _is_int(version, FORMAT_VERSION + 1):
        problems.append(problem(
            "newer_version", f"format version {version} is newer than this reader "
            f"({FORMAT_VERSION}); update Telesplat", key="version", path=DATASET_JSON))
        return problems, None
    if version != FORMAT_VERSION or isinstance(version, bool):
        bad("version", f"version must be the integer {FORMAT_VERSION}, got {version!r}")
        return problems, None

    if not isinstance(meta.get("name"), str) or not meta.get("name"):
        bad("name", "name must be a non-empty string")
    fps = meta.get("fps")
    if not (is_finite_number(fps) and fps > 0):
        bad("fps", f"fps must be a positive number, got {fps!r}")
    if not isinstance(meta.get("synthetic"), bool):
        bad("synthetic", "synthetic must be true or false")
    subject = meta.get("subject")
    if not isinstance(subject, dict) or not isinstance(subject.get("identity"), str):
        bad("subject", "subject must be an object with a string 'identity'")
    body_model = _check_body_model(meta.get("body_model"), bad)
    ext = meta.get("image_format")
    if ext not in IMAGE_FORMATS:
        bad("image_format", f"image_format must be one of {IMAGE_FORMATS}, got {ext!r}")
        ext = None
    for key in ("masks", "parts"):
        if not isinstance(meta.get(key), bool):
            bad(key, f"{key} must be true or false")
    num_parts = _check_parts(meta, bad)
    bounds = _check_bounds(meta.get("subject_bounds"), bad)
    sequences = _check_sequences(meta.get("sequences"), bad)
    info = _Info(sequences, ext, meta.get("masks") is True, meta.get("parts") is True,
                 num_parts, bounds, body_model)
    return problems, info


def _check_body_model(bm: Any, bad) -> dict | None:
    if not isinstance(bm, dict):
        bad("body_model", "body_model must be an object")
        return None
    ok = True
    if bm.get("type") not in _BODY_TYPES:
        bad("body_model.type", f"body_model.type must be one of {_BODY_TYPES}, "
                               f"got {bm.get('type')!r}")
        ok = False
    for key in ("num_betas", "num_expression"):
        if not _is_int(bm.get(key), 0):
            bad(f"body_model.{key}", f"body_model.{key} must be an integer >= 0")
            ok = False
    if not isinstance(bm.get("source"), str):
        bad("body_model.source", "body_model.source must be a string")
    if bm.get("hand_pca") is not None and not _is_int(bm.get("hand_pca"), 1):
        bad("body_model.hand_pca", "body_model.hand_pca must be null or an integer >= 1")
        ok = False
    if not isinstance(bm.get("flat_hand_mean", False), bool):
        bad("body_model.flat_hand_mean", "body_model.flat_hand_mean must be true or false")
    if bm.get("root", "smplx") not in ROOT_CONVENTIONS:
        bad("body_model.root", f"body_model.root must be one of {ROOT_CONVENTIONS}")
    return bm if ok else None


def _check_parts(meta: dict, bad) -> int | None:
    names = meta.get("part_names")
    if not (isinstance(names, list) and all(isinstance(n, str) and n for n in names)
            and len(set(names)) == len(names) and len(names) <= 255):
        bad("part_names", "part_names must list at most 255 distinct non-empty strings")
        return None
    upper = meta.get("upper_body_parts")
    if not isinstance(upper, list) or not set(upper) <= set(names):
        unknown = sorted(set(upper) - set(names)) if isinstance(upper, list) else upper
        bad("upper_body_parts", f"upper_body_parts must be a list of part names; not parts: "
                                f"{unknown}")
    return len(names)


def _check_bounds(bounds: Any, bad) -> np.ndarray | None:
    if bounds is None:
        return None
    try:
        box = np.array(bounds, dtype=np.float64)
    except (TypeError, ValueError):
        box = np.zeros(0)
    if box.shape != (2, 3) or not np.all(np.isfinite(box)) or np.any(box[0] > box[1]):
        bad("subject_bounds", "subject_bounds must be null or [[xmin, ymin, zmin], "
                              "[xmax, ymax, zmax]] (finite, min <= max)")
        return None
    return box


def _check_sequences(seqs: Any, bad) -> dict[str, int]:
    if not isinstance(seqs, dict) or not seqs:
        bad("sequences", "sequences must be a non-empty object {name: {num_frames}}")
        return {}
    out = {}
    for name, entry in seqs.items():
        try:
            check_name(name, "sequence")
        except ValueError as exc:
            bad(f"sequences.{name}", str(exc))
            continue
        n = entry.get("num_frames") if isinstance(entry, dict) else None
        if not _is_int(n, 1):
            bad(f"sequences.{name}", f"sequence {name}: num_frames must be an integer >= 1")
            continue
        out[name] = n
    return out


def _kinds(info: _Info) -> list[Kind]:
    """The per-view files this dataset declares."""
    out = [Kind("images", info.image_format, 3)]
    if info.masks:
        out.append(Kind("masks", MASK_FORMAT, 1))
    if info.parts:
        out.append(Kind("parts", MASK_FORMAT, 1))
    return out


# -- params.npz -----------------------------------------------------------------------------

def _check_all_params(root: Path, info: _Info, limits: NpzLimits) -> list[Problem]:
    problems = []
    for seq, T in info.sequences.items():
        rel = f"sequences/{seq}/{PARAMS_NPZ}"
        if not (root / rel).is_file():
            problems.append(problem("params_missing", f"{rel} is missing", sequence=seq,
                                    path=rel))
            continue
        try:
            params = read_npz(root / rel, limits)  # NpzError: a ValueError
        except (OSError, ValueError) as exc:
            problems.append(problem("params_unreadable", f"{rel}: {exc}", sequence=seq,
                                    path=rel))
            continue
        if not any(param_spec(k) is not None for k in params):
            problems.append(problem("params_empty", f"{rel} holds no known parameter",
                                    sequence=seq, path=rel))
        for issue in check_params(params, T, info.body_model):
            problems.append(problem(issue.code, f"sequence {seq}: {issue.message}",
                                    WARNING if issue.warning else ERROR, sequence=seq,
                                    key=issue.key, frames=issue.frames, path=rel))
    return problems


# -- splits.json ----------------------------------------------------------------------------

def _other_dataset(other: Path) -> tuple[set[str], set[str]] | None:
    """(sequences, cameras) of the dataset a split borrows, None when there is none."""
    try:
        meta = json.loads((other / DATASET_JSON).read_text(encoding="utf-8"))
        cams = json.loads((other / CAMERAS_JSON).read_text(encoding="utf-8"))
        return (set(meta["sequences"]), {c["name"] for c in cams["cameras"]})
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        return None


def _check_split(root: Path, name: str, entry: Any, sequences: set[str], cameras: set[str]
                 ) -> list[Problem]:
    out: list[Problem] = []

    def p(code: str, message: str, severity: str = ERROR, **where: Any) -> None:
        out.append(problem(code, f"split {name}: {message}", severity, key=name,
                           path=SPLITS_JSON, **where))

    if not isinstance(entry, dict) or not all(
            isinstance(entry.get(k), list) and all(isinstance(x, str) for x in entry[k])
            for k in ("sequences", "cameras")):
        p("split_bad_entry", "must be {\"sequences\": [names], \"cameras\": [names]}")
        return out
    if "dataset" in entry:
        folder = inside(root, entry["dataset"])
        if folder is None:  # refused before any file is looked at: nothing about it leaks
            p("split_outside_dataset", "dataset must be a relative path inside this dataset "
                                       "(no absolute path, no '..')")
            return out
        other = _other_dataset(folder)
        if other is None:
            p("split_unknown_dataset", f"dataset {entry['dataset']!r} is not a readable "
                                       "dataset (path relative to this one)")
            return out
        sequences, cameras = other
    if not entry["sequences"] or not entry["cameras"]:
        p("split_empty", "has no sequences or no cameras", WARNING)
    for s in entry["sequences"]:
        if s not in sequences:
            p("split_unknown_sequence", f"unknown sequence {s!r}", sequence=s)
    for c in entry["cameras"]:
        if c not in cameras:
            p("split_unknown_camera", f"unknown camera {c!r}", camera=c)
    return out


def _check_splits(root: Path, doc: Any, sequences: set[str], cameras: set[str]
                  ) -> list[Problem]:
    if not isinstance(doc, dict):
        return [problem("split_bad_entry", "splits.json must hold an object", path=SPLITS_JSON)]
    return [p for name, entry in doc.items()
            for p in _check_split(root, name, entry, sequences, cameras)]
