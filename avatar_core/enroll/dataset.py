"""The tracked take as a one-camera Format v1 dataset (docs/dataset.md): the video's frames at
the training resolution, the selfie masks as alpha, one shared ``betas`` and per-frame
parameters, and the fixed camera at the origin looking down -z (the fitter's webcam)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..body.model_paths import SYNTHETIC_SOURCE
from ..body.skeleton import SMPLX_PART_NAMES, UPPER_BODY_PARTS
from ..dataset.format import CameraSpec
from ..dataset.writer import DatasetWriter
from ..render.camera import Camera, look_at

CAMERA = "video"
SEQUENCE = "take"


def video_camera(width: int, height: int, focal_px: float) -> Camera:
    fov_y = 2 * math.degrees(math.atan(0.5 * height / focal_px))
    return look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), width=width, height=height,
                   fov_y_deg=fov_y)


def body_source(files) -> str:
    seed = files.synthetic_seed()
    return f"{SYNTHETIC_SOURCE}{seed}" if seed is not None else files.smplx_npz.name


def write_take(root: Path, frames: Sequence[np.ndarray], masks: Sequence[np.ndarray] | None,
               params: Sequence[dict[str, np.ndarray]], betas: np.ndarray, fps: float,
               focal_px: float, resolution: int, files, num_expression: int) -> Path:
    """Write the dataset; ``frames`` RGB uint8 at the video's size, ``focal_px`` at that
    size, ``masks`` float [h, w] at any size (resized here) or None."""
    h0, w0 = frames[0].shape[:2]
    s = min(1.0, resolution / max(w0, h0))
    w, h = max(1, round(w0 * s)), max(1, round(h0 * s))
    camera = video_camera(w, h, focal_px * s)
    writer = DatasetWriter(
        root, name="enrolled", fps=float(fps), cameras=[CameraSpec.from_camera(
            CAMERA, camera, role="front")],
        part_names=list(SMPLX_PART_NAMES), upper_body_parts=list(UPPER_BODY_PARTS),
        subject={"identity": "enrolled", "betas": [float(b) for b in betas]},
        body_model={"type": "smplx", "num_betas": int(len(betas)),
                    "num_expression": int(num_expression), "source": body_source(files),
                    "hand_pca": None, "flat_hand_mean": False, "trackers": "enroll"})
    for j, frame in enumerate(frames):
        rgb = cv2.resize(frame, (w, h), interpolation=cv2.INTER_AREA) if s < 1 else frame
        alpha = None
        if masks is not None:
            a = cv2.resize(masks[j], (w, h), interpolation=cv2.INTER_LINEAR)
            alpha = (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)
        writer.write_view(SEQUENCE, j, CAMERA, np.ascontiguousarray(rgb), alpha)
    stacked = {k: np.stack([p[k] for p in params]) for k in params[0] if k != "betas"}
    stacked["betas"] = np.asarray(betas, dtype=np.float64)
    writer.write_params(SEQUENCE, stacked)
    writer.write_splits({"train": {"sequences": [SEQUENCE], "cameras": [CAMERA]}})
    writer.close()
    return root
