"""Import a GaussianAvatars / VHAP (NeRSemble) export.

The layout (VHAP `export_as_nerf_dataset.py` / `combine_nerf_datasets.py`, read by
GaussianAvatars' `readCamerasFromTransforms`)::

    SRC/transforms_{train,val,test}.json   {"frames": [{file_path, transform_matrix, fl_x,
                                             fl_y, cx, cy, w, h, timestep_index, camera_index,
                                             camera_id?, flame_param_path, fg_mask_path?}],
                                             ...shared fl_x, fl_y, cx, cy, w, h}
    SRC/images/<timestep:05d>_<camera:02d>.png  (RGB, background already applied)
    SRC/fg_masks/<timestep:05d>_<camera:02d>.png
    SRC/flame_param/<timestep:05d>.npz     translation, rotation, neck_pose, jaw_pose, expr,
                                           eyes_pose [1, ...]; shape [S]; static_offset
                                           [1, V, 3]; dynamic_offset [1, V, 3] (optional)

A combined dataset (several sequences of one subject) points into sibling folders:
"../<sequence folder>/images/...". `transform_matrix` is camera-to-world with OpenGL axes
(x right, y up, z backward): flipping its y and z columns gives OpenCV axes. The intrinsics
are used as they are (VHAP renders with nvdiffrast, whose pixel centres sit at +0.5, the
engine's convention).

Sequences: timesteps of one source sequence that belong to different divisions (VHAP's
single-sequence export puts the first 70 % in train/val and the rest in test) become
separate sequences named by their divisions, "<seq>-train-val" / "<seq>-test", since a split
here holds whole sequences.
Splits: train -> "train", val -> "novel_view", test -> "self_reenactment".
"""

from __future__ import annotations

import json
import logging
import math
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...bounded_npz import read_npz
from ..format import PARAMS_NPZ_LIMITS, CameraSpec
from ..writer import DatasetWriter
from .common import (
    Progress,
    is_plain_rgb,
    mask_to_uint8,
    nearest_rotation,
    read_image,
    safe_name,
)

__all__ = ["DIVISIONS", "camera_from_nerf_frame", "import_vhap"]

log = logging.getLogger(__name__)

DIVISIONS = {"train": "train", "val": "novel_view", "test": "self_reenactment"}
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])  # camera axes: OpenGL (y up, z back) -> OpenCV
_PER_FRAME = ("translation", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "expr",
              "dynamic_offset")
_SHARED = ("shape", "static_offset")
_HEAD_MARGIN = 0.35  # metres around FLAME's translation that hold the head (generous)


@dataclass(frozen=True)
class _Frame:
    division: str
    sequence: str        # source sequence
    timestep: int
    camera: CameraSpec
    camera_index: int
    image: Path
    mask: Path | None
    flame: Path | None


def camera_from_nerf_frame(frame: dict[str, Any], shared: dict[str, Any], name: str, *,
                           size: tuple[int, int] | None = None) -> CameraSpec:
    """The OpenCV world->camera CameraSpec of one NeRF-style frame record (`shared`: the
    file's top-level defaults; `size` (W, H) when the record has no w/h)."""
    def get(key: str) -> Any:
        return frame.get(key, shared.get(key))

    c2w = np.array(frame["transform_matrix"], dtype=np.float64)
    if c2w.shape not in ((4, 4), (3, 4)):
        raise ValueError(f"transform_matrix of {frame.get('file_path')} must be 4x4")
    rot = nearest_rotation(c2w[:3, :3] @ _GL_TO_CV, f"rotation of {frame.get('file_path')}")
    R = rot.T
    t = -R @ c2w[:3, 3]
    w, h = get("w"), get("h")
    if w is None or h is None:
        if size is None:
            raise ValueError(f"{frame.get('file_path')}: no image size (w, h)")
        w, h = size
    fx, fy, cx, cy = get("fl_x"), get("fl_y"), get("cx"), get("cy")
    if fx is None:  # NeRF-synthetic style: a horizontal field of view, centred
        angle = get("camera_angle_x")
        if angle is None:
            raise ValueError(f"{frame.get('file_path')}: no fl_x or camera_angle_x")
        fx = 0.5 * w / math.tan(0.5 * angle)
    fy = fx if fy is None else fy
    cx = w / 2 if cx is None else cx
    cy = h / 2 if cy is None else cy
    K = [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
    return CameraSpec(name, K, R, t, int(w), int(h), role="front")


def _with_extension(rel: str) -> str:
    return rel if Path(rel).suffix else rel + ".png"  # as GaussianAvatars does


def _source_sequence(rel: str, default: str) -> str:
    parts = Path(rel).parts
    return safe_name(parts[1]) if len(parts) > 2 and parts[0] == ".." else default


def _read_frames(src: Path, default_seq: str) -> list[_Frame]:
    frames: list[_Frame] = []
    for division in DIVISIONS:
        path = src / f"transforms_{division}.json"
        if not path.is_file():
            continue
        doc = json.loads(path.read_text(encoding="utf-8"))
        shared = {k: v for k, v in doc.items() if k != "frames"}
        for rec in doc.get("frames", []):
            rel = _with_extension(rec["file_path"])
            index = int(rec["camera_index"])
            name = safe_name(str(rec.get("camera_id", f"cam{index:02d}")))
            mask = rec.get("fg_mask_path")
            flame = rec.get("flame_param_path")
            frames.append(_Frame(
                division, _source_sequence(rel, default_seq), int(rec["timestep_index"]),
                camera_from_nerf_frame(rec, shared, name), index, src / rel,
                None if mask is None else src / _with_extension(mask),
                None if flame is None else src / flame))
    if not frames:
        raise ValueError(f"{src}: no transforms_train/val/test.json with frames")
    return frames


def _cameras(frames: list[_Frame]) -> list[CameraSpec]:
    """One CameraSpec per camera, checked to be the same in every frame."""
    by_name: dict[str, tuple[int, CameraSpec]] = {}
    for f in frames:
        known = by_name.setdefault(f.camera.name, (f.camera_index, f.camera))[1]
        for a, b, what in ((known.K, f.camera.K, "K"), (known.R, f.camera.R, "R"),
                           (known.t, f.camera.t, "t")):
            if not np.allclose(a, b, rtol=0, atol=1e-6):
                raise ValueError(f"camera {f.camera.name} changes its {what} between frames "
                                 f"(at {f.image}); a moving camera is not supported")
    return [spec for _, spec in sorted(by_name.values(), key=lambda x: x[0])]


def _pieces(frames: list[_Frame]) -> dict[str, tuple[str, list[int], frozenset[str]]]:
    """Our sequences: name -> (source sequence, sorted timesteps, divisions)."""
    member: dict[tuple[str, int], set[str]] = defaultdict(set)
    for f in frames:
        member[(f.sequence, f.timestep)].add(f.division)
    groups: dict[tuple[str, frozenset[str]], list[int]] = defaultdict(list)
    for (seq, ts), divs in member.items():
        groups[(seq, frozenset(divs))].append(ts)
    out = {}
    for (seq, divs), steps in sorted(groups.items(), key=lambda g: (g[0][0], min(g[1]))):
        split_up = sum(1 for s, _ in groups if s == seq) > 1
        suffix = "-".join(d for d in DIVISIONS if d in divs)  # e.g. "train-val", "test"
        out[f"{seq}-{suffix}" if split_up else seq] = (seq, sorted(steps), divs)
    return out


def _shared_value(key: str, arr: np.ndarray) -> np.ndarray:
    if key == "shape":
        return arr.reshape(-1)  # [S] (or [1, S])
    return arr[0] if arr.ndim == 3 else arr  # static_offset [1, V, 3] (or [V, 3])


def _flame_params(paths: list[Path]) -> dict[str, np.ndarray]:
    """Per-timestep FLAME files -> our flame_* arrays ([T, ...], shared ones once)."""
    loaded = []
    for p in paths:
        arrays = read_npz(p, PARAMS_NPZ_LIMITS)
        loaded.append({k: np.asarray(v, dtype=np.float64) for k, v in arrays.items()})
    skipped = sorted(set().union(*loaded) - set(_PER_FRAME) - set(_SHARED))
    if skipped:
        log.warning("FLAME keys not imported: %s", skipped)
    out: dict[str, np.ndarray] = {}
    for key in (k for k in _PER_FRAME if k in loaded[0]):
        bad = [str(p) for p, d in zip(paths, loaded, strict=True) if d[key].shape[:1] != (1,)]
        if bad:
            raise ValueError(f"FLAME {key} must be [1, ...] per timestep file: {bad[0]}")
        out[f"flame_{key}"] = np.concatenate([d[key] for d in loaded])
    for key in (k for k in _SHARED if k in loaded[0]):
        values = [_shared_value(key, d[key]) for d in loaded]
        if all(np.array_equal(v, values[0]) for v in values):
            out[f"flame_{key}"] = values[0]
        elif key == "shape":  # a per-frame identity is allowed, if unusual
            out["flame_shape"] = np.stack(values)
        else:
            raise ValueError(f"FLAME {key} differs between timesteps; it must be shared")
    return out


def _bounds(params: list[dict[str, np.ndarray]]) -> list[list[float]] | None:
    trans = [p["flame_translation"] for p in params if "flame_translation" in p]
    if not trans:
        return None
    t = np.concatenate(trans)
    return [(t.min(0) - _HEAD_MARGIN).tolist(), (t.max(0) + _HEAD_MARGIN).tolist()]


def import_vhap(src: str | Path, out: str | Path, *, name: str | None = None,
                identity: str | None = None, fps: float = 25.0,
                progress: Progress | None = None, workers: int = 4) -> Path:
    """Convert the VHAP / GaussianAvatars export at `src` into a dataset at `out`."""
    src = Path(src)
    frames = _read_frames(src, safe_name(src.name))
    cameras = _cameras(frames)
    pieces = _pieces(frames)
    index = {(f.sequence, f.timestep, f.camera.name): f for f in frames}
    cam_names = [c.name for c in cameras]
    for seq_name, (seq, steps, _) in pieces.items():
        missing = [(ts, c) for ts in steps for c in cam_names if (seq, ts, c) not in index]
        if missing:
            raise ValueError(f"sequence {seq_name}: {len(missing)} views missing from the "
                             f"source, e.g. timestep {missing[0][0]} camera {missing[0][1]}")
    if any(f.flame is None for f in frames):
        raise ValueError("every frame needs a flame_param_path (export with flame_mode=param)")
    with_mask = {f.mask is not None for f in frames}
    if len(with_mask) > 1:
        raise ValueError("fg_mask_path is given for some frames only")
    ext = frames[0].image.suffix.lstrip(".").lower().replace("jpeg", "jpg")
    ext = ext if ext in ("png", "jpg") else "png"

    params = {}
    for seq_name, (seq, steps, _) in pieces.items():
        params[seq_name] = _flame_params([index[(seq, ts, cam_names[0])].flame for ts in steps])
    first = next(iter(params.values()))
    nb = first["flame_shape"].shape[-1] if "flame_shape" in first else 0
    ne = first["flame_expr"].shape[-1] if "flame_expr" in first else 0
    subject = identity or src.name.split("_")[0]
    writer = DatasetWriter(
        out, name=name or f"vhap-{src.name}", fps=fps, cameras=cameras, part_names=[],
        upper_body_parts=[], subject={"identity": subject, "source": str(src)},
        body_model={"type": "flame", "num_betas": int(nb), "num_expression": int(ne),
                    "source": "vhap"},
        image_format=ext, subject_bounds=_bounds(list(params.values())))

    def one(job: tuple[str, int, _Frame]) -> None:
        seq_name, frame, f = job
        alpha = None if f.mask is None else mask_to_uint8(f.mask)
        if is_plain_rgb(f.image, ext):  # the usual case: copied byte for byte
            writer.copy_view(seq_name, frame, f.camera.name, f.image, alpha)
            return
        rgb, own_alpha = read_image(f.image)  # RGBA: the alpha is the mask unless given
        writer.write_view(seq_name, frame, f.camera.name, rgb,
                          own_alpha if alpha is None else alpha)

    jobs = [(seq_name, i, index[(seq, ts, c)])
            for seq_name, (seq, steps, _) in pieces.items()
            for i, ts in enumerate(steps) for c in cam_names]
    with ThreadPoolExecutor(workers) as pool:
        for done, _ in enumerate(pool.map(one, jobs), 1):
            if progress:
                progress(done, len(jobs))
    for seq_name, (seq, steps, _) in pieces.items():
        writer.write_params(seq_name, params[seq_name],
                            {"source_sequence": seq, "source_frames": steps})
    splits = {}
    for division, split in DIVISIONS.items():
        seqs = [s for s, (_, _, divs) in pieces.items() if division in divs]
        cams = sorted({f.camera.name for f in frames if f.division == division},
                      key=cam_names.index)
        if seqs and cams:
            splits[split] = {"sequences": seqs, "cameras": cams}
    writer.write_splits(splits)
    return writer.close()
