"""A short animation of the posed synthetic upper body, for a person to look at.

The synthetic model family is generated (or reused from a cache folder), the upper-body model
goes through gestures and expressions, and a z-buffer mesh renderer draws each frame.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import torch

from ..body.model_data import load_smplx
from ..body.upper_body import UpperBodyModel, load_segmentation
from ..motion.library import demo_clip
from ..motion.rig import model_rig
from ..render.camera import look_at
from ..render.mp4_writer import Mp4Writer
from .mesh_render import render_mesh
from .model_writer import ensure_models


def render_demo(out: Path, *, model_dir: Path | None = None, frames: int = 96, size: int = 384,
                fps: int = 24, identity: int = 0,
                progress: Callable[[int, int], None] | None = None) -> Path:
    """Render the demo to an .mp4 video or a .png strip of frames; returns the path written."""
    if frames < 1 or size < 16:
        raise ValueError("frames must be >= 1 and size >= 16")
    files = ensure_models(model_dir)
    identities = files.identities()
    if not 0 <= identity < len(identities):
        raise ValueError(f"identity must be in [0, {len(identities)})")
    data = load_smplx(files.smplx_npz)
    model = UpperBodyModel(data, load_segmentation(files.segmentation, data.num_vertices),
                           dtype=torch.float32)
    with np.load(identities[identity]) as ident:
        betas, colors = ident["betas"], ident["vertex_colors"][model.vertex_ids]
    rig, clip = model_rig(files, model), demo_clip()
    head = data.joint_template[15]
    camera = look_at(eye=(0.6, head[1] + 0.05, 2.6), target=(0.0, head[1] - 0.28, 0.0),
                     width=size, height=size, fov_y_deg=32.0)
    faces = model.faces.cpu().numpy()
    images = []
    with torch.no_grad():
        for i in range(frames):
            t = clip.duration * i / max(frames - 1, 1)
            params = clip.sample(t, rig)
            params["betas"] = betas
            verts = model(params).vertices[0].cpu().numpy()
            rgb = render_mesh(verts, faces, camera, vertex_colors=colors,
                              background=(0.93, 0.94, 0.96)).rgb
            images.append((np.clip(rgb, 0, 1) * 255).astype(np.uint8))  # RGB
            if progress:
                progress(i + 1, frames)
    return _write(out, images, fps)


def _write(out: Path, images: list[np.ndarray], fps: int) -> Path:
    """An .mp4 of all frames, or a .png strip of up to 8 of them. images: uint8 RGB."""
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".png":
        step = max(1, len(images) // 8)
        strip = np.concatenate(images[::step][:8], axis=1)
        if not cv2.imwrite(str(out), strip[..., ::-1]):
            raise OSError(f"could not write {out}")
        return out
    if out.suffix.lower() != ".mp4":
        raise ValueError(f"output must be .mp4 or .png, got {out.suffix}")
    with Mp4Writer(out, fps) as writer:
        for img in images:
            writer.write(img)
    return out
