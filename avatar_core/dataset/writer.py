"""Writing a dataset: views from worker threads, parameters per sequence, then `close()`.

`close()` validates everything written (shallow: listings and image headers) and writes
dataset.json last, so a folder without dataset.json is recognisably unfinished.
"""

from __future__ import annotations

import io
import json
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .format import (
    CAMERAS_JSON,
    DATASET_JSON,
    FORMAT_NAME,
    FORMAT_VERSION,
    IMAGE_FORMATS,
    MASK_FORMAT,
    PARAMS_NPZ,
    SPLITS_JSON,
    CameraSpec,
    check_name,
    view_path,
)
from .imageio import encode, read_header, write_atomic
from .params import check_params, num_frames_of
from .problems import DatasetError, errors_of
from .validate import check_documents, check_meta

__all__ = ["DatasetWriter"]


def _json_bytes(doc: Any) -> bytes:
    return (json.dumps(doc, indent=1, allow_nan=False) + "\n").encode("utf-8")


def _uint8(name: str, arr: Any, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(arr)
    if a.dtype != np.uint8:
        raise ValueError(f"{name} must be uint8, got {a.dtype}")
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {list(shape)} (the camera's H x W), got "
                         f"{list(a.shape)}")
    return a


class DatasetWriter:
    """Writes a Format v1 dataset into `root` (which must not hold a finished dataset).

    `write_view` may be called from several threads at once (for different views);
    `write_params`, `write_splits` and `close` from any one thread. Bad input raises
    ValueError naming the problem; `close()` raises DatasetError listing every problem of
    the written dataset, leaving dataset.json unwritten.
    """

    def __init__(self, root: str | Path, *, name: str, fps: float,
                 cameras: Sequence[CameraSpec], part_names: Sequence[str],
                 upper_body_parts: Sequence[str], subject: Mapping[str, Any],
                 body_model: Mapping[str, Any], image_format: str = "png",
                 synthetic: bool = False, subject_bounds: Any = None) -> None:
        self.root = Path(root)
        if (self.root / DATASET_JSON).exists():
            raise ValueError(f"{self.root} already holds a dataset")
        if image_format not in IMAGE_FORMATS:
            raise ValueError(f"image_format must be one of {IMAGE_FORMATS}, got {image_format!r}")
        if not cameras or not all(isinstance(c, CameraSpec) for c in cameras):
            raise ValueError("cameras must be a non-empty list of CameraSpec")
        names = [c.name for c in cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names repeat: {names}")
        self.cameras = {c.name: c for c in cameras}
        self._meta: dict[str, Any] = {
            "format": FORMAT_NAME, "version": FORMAT_VERSION, "name": name, "fps": fps,
            "synthetic": synthetic, "subject": dict(subject), "body_model": dict(body_model),
            "image_format": image_format, "masks": False, "parts": False,
            "part_names": list(part_names), "upper_body_parts": list(upper_body_parts),
            "subject_bounds": None, "sequences": {},
        }
        try:
            json.dumps(self._meta, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"dataset metadata must be plain JSON: {exc}") from exc
        bad = [p for p in check_meta(self._meta) if p.where.key != "sequences"]
        if bad:
            raise ValueError("; ".join(p.message for p in bad))
        if subject_bounds is not None:
            self.set_subject_bounds(subject_bounds)
        self._lock = threading.Lock()
        self._views: dict[tuple[str, int, str], tuple[bool, bool]] = {}
        self._frames: dict[str, int] = {}
        self._info: dict[str, dict[str, Any]] = {}
        self._splits: dict[str, Any] = {}
        self._closed = False
        self.root.mkdir(parents=True, exist_ok=True)

    # -- context manager: close on success only ------------------------------------------
    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()

    @property
    def image_format(self) -> str:
        return self._meta["image_format"]

    def set_subject_bounds(self, bounds: Any) -> None:
        """The world box [[xmin, ymin, zmin], [xmax, ymax, zmax]] (metres) holding the subject
        in every frame; cameras that cannot see it are reported by validation."""
        box = np.array(bounds, dtype=np.float64)
        if box.shape != (2, 3) or not np.all(np.isfinite(box)) or np.any(box[0] > box[1]):
            raise ValueError(f"subject_bounds must be [[min xyz], [max xyz]], got {bounds}")
        self._meta["subject_bounds"] = box.tolist()

    # -- views -----------------------------------------------------------------------------
    def _reserve(self, sequence: str, frame: Any, camera_name: str, has_alpha: bool,
                 has_parts: bool) -> tuple[str, int, str]:
        check_name(sequence, "sequence")
        if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or frame < 0:
            raise ValueError(f"frame must be an integer >= 0, got {frame!r}")
        if camera_name not in self.cameras:
            raise ValueError(f"unknown camera {camera_name!r}; cameras: {sorted(self.cameras)}")
        key = (sequence, int(frame), camera_name)
        with self._lock:
            if self._closed:
                raise ValueError("the writer is closed")
            if key in self._views:
                raise ValueError(f"view {key} was already written")
            self._views[key] = (has_alpha, has_parts)
        return key

    def _release(self, key: tuple[str, int, str]) -> None:
        with self._lock:
            self._views.pop(key, None)

    def write_view(self, sequence: str, frame: int, camera_name: str, rgb_uint8: Any,
                   alpha_uint8: Any = None, parts_uint8: Any = None) -> None:
        """One view: RGB [H, W, 3] uint8, optional alpha [H, W] uint8 (255 = subject) and part
        labels [H, W] uint8 (0 background, i + 1 = part_names[i]); H x W is the camera's."""
        spec = self.cameras.get(camera_name)
        if spec is None:
            raise ValueError(f"unknown camera {camera_name!r}; cameras: {sorted(self.cameras)}")
        hw = (spec.height, spec.width)
        files = {"images": encode(_uint8("rgb", rgb_uint8, (*hw, 3)), self.image_format)}
        if alpha_uint8 is not None:
            files["masks"] = self._encode_gray("masks", alpha_uint8, hw)
        if parts_uint8 is not None:
            files["parts"] = self._encode_gray("parts", parts_uint8, hw)
        self._write_files(sequence, frame, camera_name, files)

    def copy_view(self, sequence: str, frame: int, camera_name: str, image: str | Path,
                  alpha: str | Path | np.ndarray | None = None,
                  parts: str | Path | np.ndarray | None = None) -> None:
        """Like `write_view` for an image file already stored as this dataset stores it
        (8-bit RGB in `image_format`): copied byte for byte after a header check, with no
        re-encoding. `alpha` / `parts` are arrays as in `write_view`, or 8-bit single-channel
        PNG files copied likewise."""
        spec = self.cameras.get(camera_name)
        if spec is None:
            raise ValueError(f"unknown camera {camera_name!r}; cameras: {sorted(self.cameras)}")
        hw = (spec.height, spec.width)
        files = {}
        for kind, src, ext, channels in (("images", image, self.image_format, 3),
                                         ("masks", alpha, MASK_FORMAT, 1),
                                         ("parts", parts, MASK_FORMAT, 1)):
            if src is None:
                continue
            if isinstance(src, np.ndarray):
                files[kind] = self._encode_gray(kind, src, hw)
                continue
            h = read_header(src)
            if (h.kind, h.bit_depth, h.channels, h.palette) != (ext, 8, channels, False):
                raise ValueError(f"{src}: expected 8-bit {channels}-channel {ext}, got "
                                 f"{h.bit_depth}-bit {h.channels}-channel {h.kind}")
            if (h.width, h.height) != (spec.width, spec.height):
                raise ValueError(f"{src} is {h.width}x{h.height}, camera {camera_name} is "
                                 f"{spec.width}x{spec.height}")
            files[kind] = Path(src).read_bytes()
        self._write_files(sequence, frame, camera_name, files)

    def _encode_gray(self, kind: str, arr: Any, hw: tuple[int, int]) -> bytes:
        a = _uint8("alpha" if kind == "masks" else "parts", arr, hw)
        n = len(self._meta["part_names"])
        if kind == "parts" and a.size and int(a.max()) > n:
            raise ValueError(f"parts holds label {int(a.max())}; labels are 0..{n}")
        return encode(a, MASK_FORMAT)

    def _write_files(self, sequence: str, frame: int, camera_name: str,
                     files: dict[str, bytes]) -> None:
        key = self._reserve(sequence, frame, camera_name, "masks" in files, "parts" in files)
        try:
            for kind, data in files.items():
                ext = self.image_format if kind == "images" else MASK_FORMAT
                write_atomic(view_path(self.root, sequence, kind, camera_name, int(frame), ext),
                             data)
        except BaseException:
            self._release(key)
            raise

    # -- parameters and splits -------------------------------------------------------------
    def write_params(self, sequence: str, params: Mapping[str, Any],
                     info: Mapping[str, Any] | None = None) -> None:
        """The sequence's parameters: arrays [T, ...] (shared ones such as betas may omit T);
        T becomes the sequence's frame count. `info` adds JSON fields to the sequence's
        entry in dataset.json (e.g. "source_frames")."""
        check_name(sequence, "sequence")
        arrays = {k: np.asarray(v) for k, v in params.items()}
        issues = check_params(arrays, None, self._meta["body_model"])
        if issues:
            raise ValueError(f"sequence {sequence}: " + "; ".join(i.message for i in issues))
        T = num_frames_of(arrays)
        if T is None or T < 1:
            raise ValueError(f"sequence {sequence}: no per-frame parameter array [T, ...]")
        extra = dict(info or {})
        if "num_frames" in extra:
            raise ValueError("info must not set num_frames (the parameters decide it)")
        json.dumps(extra, allow_nan=False)  # raises on non-JSON values
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        with self._lock:
            if self._closed:
                raise ValueError("the writer is closed")
            if sequence in self._frames:
                raise ValueError(f"parameters of sequence {sequence} were already written")
            self._frames[sequence] = T
            self._info[sequence] = extra
        write_atomic(self.root / "sequences" / sequence / PARAMS_NPZ, buf.getvalue())

    def write_splits(self, splits: Mapping[str, Mapping[str, Any]]) -> None:
        """{name: {"sequences": [...], "cameras": [...], optional "dataset": relative path of
        another dataset the names refer to, any other JSON fields}}; checked at close()."""
        doc = json.loads(json.dumps(dict(splits), allow_nan=False))
        for name, entry in doc.items():
            if not isinstance(entry, dict) or not all(
                    isinstance(entry.get(k), list) for k in ("sequences", "cameras")):
                raise ValueError(f"split {name} must be {{'sequences': [...], 'cameras': [...]}}")
            if "dataset" not in entry:
                unknown = sorted(set(entry["cameras"]) - set(self.cameras))
                if unknown:
                    raise ValueError(f"split {name} names unknown camera(s) {unknown}")
        self._splits = doc

    # -- finishing -------------------------------------------------------------------------
    def _documents(self) -> tuple[dict, dict, dict]:
        with self._lock:
            views = dict(self._views)
            frames = dict(self._frames)
            info = {k: dict(v) for k, v in self._info.items()}
        seqs = sorted({s for s, _, _ in views} | set(frames))
        meta = dict(self._meta)
        meta["masks"] = any(a for a, _ in views.values())
        meta["parts"] = any(p for _, p in views.values())
        meta["sequences"] = {}
        for s in seqs:
            n = frames.get(s, 1 + max((f for q, f, _ in views if q == s), default=0))
            meta["sequences"][s] = {"num_frames": n, **info.get(s, {})}
        cameras = {"cameras": [c.to_dict() for c in self.cameras.values()]}
        return meta, cameras, dict(self._splits)

    def close(self) -> Path:
        """Validate what was written and finish the dataset by writing dataset.json."""
        if self._closed:
            raise ValueError("the writer is closed")
        meta, cameras, splits = self._documents()
        write_atomic(self.root / CAMERAS_JSON, _json_bytes(cameras))
        write_atomic(self.root / SPLITS_JSON, _json_bytes(splits))
        problems = errors_of(check_documents(self.root, meta, cameras, splits))
        if problems:
            raise DatasetError(self.root, problems)
        write_atomic(self.root / DATASET_JSON, _json_bytes(meta))
        with self._lock:
            self._closed = True
        return self.root
