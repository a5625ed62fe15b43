"""Reading a dataset: cameras, sequences, splits, per-sequence parameters and single views."""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..bounded_npz import NpzLimits, read_npz
from ..render.camera import Camera
from .format import (
    CAMERAS_JSON,
    DATASET_JSON,
    MASK_FORMAT,
    PARAMS_NPZ,
    PARAMS_NPZ_LIMITS,
    SPLITS_JSON,
    CameraSpec,
    inside,
    view_path,
)
from .imageio import decode_gray, decode_rgb
from .params import frame_slice
from .problems import DatasetError, Problem, Where, errors_of
from .validate import check_meta, read_json, validate_dataset

__all__ = ["Dataset", "Split", "View", "ViewKey", "load_dataset"]


class ViewKey(NamedTuple):
    sequence: str
    frame: int
    camera: str


@dataclass(frozen=True)
class Split:
    name: str
    sequences: tuple[str, ...]
    cameras: tuple[str, ...]
    dataset: str | None = None          # another dataset (relative path) the names refer to
    extra: dict[str, Any] = field(default_factory=dict)  # any other fields, e.g. "identity"


@dataclass(frozen=True, eq=False)
class View:
    """One image of one camera at one frame, in the engine's conventions."""

    key: ViewKey
    rgb: np.ndarray                 # float32 [H, W, 3] in [0, 1]
    alpha: np.ndarray | None        # float32 [H, W] in [0, 1], None without masks
    parts: np.ndarray | None        # int16 [H, W]: part index, -1 background; None without
    camera: Camera
    params: dict[str, np.ndarray]   # this frame's parameters (shared arrays as stored)
    upper_body_ids: tuple[int, ...] = ()  # part indices of the upper body

    @property
    def upper_body_mask(self) -> np.ndarray | None:
        """bool [H, W]: pixels of upper-body parts; None without part labels."""
        if self.parts is None:
            return None
        return np.isin(self.parts, np.asarray(self.upper_body_ids, dtype=np.int16))


def _read_only(arr: np.ndarray) -> np.ndarray:
    arr.flags.writeable = False
    return arr


class Dataset:
    """A loaded dataset. Parameters are read once per sequence and cached (read-only)."""

    def __init__(self, root: Path, meta: dict[str, Any], cameras: dict[str, CameraSpec],
                 splits: dict[str, Split], npz_limits: NpzLimits = PARAMS_NPZ_LIMITS) -> None:
        self.root = root
        self.npz_limits = npz_limits
        self.meta = meta
        self.cameras = cameras
        self.sequences = {s: int(e["num_frames"]) for s, e in meta["sequences"].items()}
        self.splits = splits
        self._params: dict[str, dict[str, np.ndarray]] = {}
        self._lock = threading.Lock()

    def __repr__(self) -> str:
        return (f"Dataset({str(self.root)!r}, {len(self.cameras)} cameras, "
                f"{len(self.sequences)} sequences, {sum(self.sequences.values())} frames)")

    # -- metadata shortcuts ----------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.meta["name"]

    @property
    def fps(self) -> float:
        return float(self.meta["fps"])

    @property
    def part_names(self) -> tuple[str, ...]:
        return tuple(self.meta["part_names"])

    @property
    def upper_body_ids(self) -> tuple[int, ...]:
        upper = set(self.meta["upper_body_parts"])
        return tuple(i for i, n in enumerate(self.part_names) if n in upper)

    @property
    def has_masks(self) -> bool:
        return bool(self.meta["masks"])

    @property
    def has_parts(self) -> bool:
        return bool(self.meta["parts"])

    @property
    def subject_bounds(self) -> np.ndarray | None:
        b = self.meta.get("subject_bounds")
        return None if b is None else np.array(b, dtype=np.float64)

    # -- parameters ------------------------------------------------------------------------
    def _check_sequence(self, sequence: str) -> int:
        if sequence not in self.sequences:
            raise KeyError(f"unknown sequence {sequence!r}; sequences: {sorted(self.sequences)}")
        return self.sequences[sequence]

    def params(self, sequence: str) -> dict[str, np.ndarray]:
        """All arrays of the sequence's params.npz ([T, ...]; shared ones without T)."""
        self._check_sequence(sequence)
        with self._lock:
            cached = self._params.get(sequence)
        if cached is None:
            arrays = read_npz(self.root / "sequences" / sequence / PARAMS_NPZ, self.npz_limits)
            cached = {k: _read_only(v) for k, v in arrays.items()}
            with self._lock:
                self._params[sequence] = cached
        return dict(cached)

    def frame_params(self, sequence: str, frame: int) -> dict[str, np.ndarray]:
        """One frame's parameters: per-frame arrays at `frame`; shared ones (betas [B]) as
        stored, so every frame sees the same identity."""
        T = self._check_sequence(sequence)
        if not 0 <= frame < T:
            raise IndexError(f"frame {frame} outside sequence {sequence} (0..{T - 1})")
        return frame_slice(self.params(sequence), frame)

    # -- views -----------------------------------------------------------------------------
    def view(self, sequence: str, frame: int, camera: str) -> View:
        T = self._check_sequence(sequence)
        if not 0 <= frame < T:
            raise IndexError(f"frame {frame} outside sequence {sequence} (0..{T - 1})")
        if camera not in self.cameras:
            raise KeyError(f"unknown camera {camera!r}; cameras: {sorted(self.cameras)}")

        def path(kind: str, ext: str) -> Path:
            return view_path(self.root, sequence, kind, camera, frame, ext)

        rgb = decode_rgb(path("images", self.meta["image_format"])).astype(np.float32) / 255.0
        alpha = parts = None
        if self.has_masks:
            alpha = decode_gray(path("masks", MASK_FORMAT)).astype(np.float32) / 255.0
        if self.has_parts:
            parts = decode_gray(path("parts", MASK_FORMAT)).astype(np.int16) - 1
        return View(ViewKey(sequence, frame, camera), rgb, alpha, parts,
                    self.cameras[camera].camera, self.frame_params(sequence, frame),
                    self.upper_body_ids)

    def views(self, split: str) -> list[ViewKey]:
        """Every (sequence, frame, camera) of a split, sequence-major then frame then camera.
        A split with a "dataset" names views of that dataset: see `source`."""
        s = self._split(split)
        source = self.source(split)
        return [ViewKey(seq, f, cam) for seq in s.sequences
                for f in range(source.sequences[seq]) for cam in s.cameras]

    def _split(self, split: str) -> Split:
        if split not in self.splits:
            raise KeyError(f"unknown split {split!r}; splits: {sorted(self.splits)}")
        return self.splits[split]

    def source(self, split: str) -> Dataset:
        """The dataset a split's views come from: this one, or the one its "dataset" names."""
        s = self._split(split)
        if s.dataset is None:
            return self
        folder = inside(self.root, s.dataset)
        if folder is None:
            raise ValueError(f"split {split!r}: its dataset must be a relative path inside "
                             "this dataset")
        return load_dataset(folder, npz_limits=self.npz_limits)


def _split_of(name: str, entry: Mapping[str, Any]) -> Split:
    extra = {k: v for k, v in entry.items() if k not in ("sequences", "cameras", "dataset")}
    return Split(name, tuple(entry["sequences"]), tuple(entry["cameras"]),
                 entry.get("dataset"), extra)


def load_dataset(root: str | Path, *, validate: bool = True, deep: bool = False,
                 npz_limits: NpzLimits = PARAMS_NPZ_LIMITS) -> Dataset:
    """Open the dataset at `root`. With `validate` (the default) every problem is checked
    first and DatasetError lists all errors; without it only what loading needs is.
    Parameter files are read within `npz_limits`."""
    root = Path(root)
    if validate:
        problems = errors_of(validate_dataset(root, deep=deep, npz_limits=npz_limits))
        if problems:
            raise DatasetError(root, problems)
    meta, problems = read_json(root / DATASET_JSON, "missing_dataset_json")
    cams_doc, more = read_json(root / CAMERAS_JSON, "missing_cameras_json")
    problems += more
    splits_doc, more = read_json(root / SPLITS_JSON, "missing_splits_json")
    problems += more
    if meta is not None:
        problems += errors_of(check_meta(meta))
    if problems:
        raise DatasetError(root, problems)
    try:
        cameras = {c["name"]: CameraSpec.from_dict(c) for c in cams_doc["cameras"]}
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(root, [Problem("camera_bad_field", Where(path=CAMERAS_JSON),
                                          f"cannot read the cameras: {exc}")]) from exc
    try:
        splits = {n: _split_of(n, e) for n, e in (splits_doc or {}).items()}
    except (KeyError, TypeError, AttributeError) as exc:
        raise DatasetError(root, [Problem("split_bad_entry", Where(path=SPLITS_JSON),
                                          f"cannot read the splits: {exc}")]) from exc
    return Dataset(root, meta, cameras, splits, npz_limits)
