"""The render CLI's pipeline (``telesplat render``): avatar + motion + camera path -> frames.

Poses the avatar for each frame of a motion, renders it from each camera of a path and writes
the frames as PNGs or an MP4. Its inputs come from their own homes: the avatar from
:mod:`avatar_core.gaussians.loading`, the motion from :mod:`avatar_core.motion.files`, the
cameras from :mod:`avatar_core.render.camera_path`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import torch

from .gaussians.loading import LoadedAvatar, load_avatar
from .motion.files import motion_frames
from .render.camera import Camera
from .render.camera_path import cameras_for, framing_target
from .render.mp4_writer import Mp4Writer
from .render.rasterize import rasterize
from .render.types import RenderRequest, to_uint8

__all__ = ["render_frames", "render_sequence", "write_frames"]


def render_frames(loaded: LoadedAvatar, params: list[dict], cameras: list[Camera],
                  request: RenderRequest) -> Iterator[np.ndarray]:
    """uint8 RGB frames [H, W, 3]."""
    with torch.no_grad():
        for p, cam in zip(params, cameras, strict=True):
            posed = loaded.animator.pose(p)
            yield to_uint8(rasterize(posed.gaussians, cam, request).rgb)


def write_frames(frames: Iterator[np.ndarray], out: Path, fps: float, total: int,
                 progress: Callable[[int, int], None] | None = None) -> Path:
    """uint8 RGB frames as PNGs into a folder, or as an .mp4."""
    as_video = out.suffix.lower() == ".mp4"
    if not as_video:
        out.mkdir(parents=True, exist_ok=True)
    with Mp4Writer(out, fps) as video:
        for i, frame in enumerate(frames):
            if as_video:
                video.write(frame)
            elif not cv2.imwrite(str(out / f"frame_{i:05d}.png"), frame[..., ::-1]):
                raise OSError(f"could not write {out / f'frame_{i:05d}.png'}")
            if progress:
                progress(i + 1, total)
    return out


def render_sequence(avatar: str, motion: str, camera: str, out: Path, *, size: int = 512,
                    fps: float = 25.0, frames: int | None = None, model_dir: Path | None = None,
                    request: RenderRequest | None = None,
                    progress: Callable[[int, int], None] | None = None) -> Path:
    loaded = load_avatar(avatar, model_dir)
    model = loaded.animator.body_model
    params = motion_frames(motion, loaded.files, model, fps, frames)
    cams = cameras_for(camera, len(params), size, framing_target(model.joint_template))
    req = request or RenderRequest()
    return write_frames(render_frames(loaded, params, cams, req), out, fps, len(params), progress)

