"""A strip of library motions at their peak, filmed by one studio camera: the actor at a
glance, without writing a dataset."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..body.skeleton import JOINT
from ..dataset.preview import grid, tile
from ..motion.library import motion
from ..motion.rig import model_rig
from ..render.camera import Camera
from .actor import Actor
from .model_writer import ensure_models
from .studio import StudioConfig, studio_rig

__all__ = ["motion_strip"]


def _face_camera(cam: Camera, head: np.ndarray, size: int) -> Camera:
    """The same camera, cropped to a square around the head and scaled to `size`."""
    uv, _ = cam.project(head[None])
    side = int(cam.height * 0.3)
    x0, y0 = (int(round(c - side / 2)) for c in uv[0])
    return cam.cropped(x0, y0 - side // 10, side, side).resized(size, size)


def motion_strip(names: Sequence[str], *, identity: int = 0, camera: str | None = None,
                 size: int = 256, columns: int = 8, focus: str = "body",
                 model_dir: Path | None = None,
                 progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """uint8 RGB grid: each motion at half its duration (where the library's clips hold their
    expression or gesture), seen by `camera` (default: the centre front camera), framed on
    the whole body or (focus="face") on the head."""
    if not names:
        raise ValueError("no motions given")
    if focus not in ("body", "face"):
        raise ValueError(f"focus must be 'body' or 'face', got {focus!r}")
    files = ensure_models(model_dir)
    actor = Actor.load(files, identity)
    rig = studio_rig(size if focus == "body" else 1080, StudioConfig())
    by_name = {c.name: c for c in rig}
    front = [c for c in rig if c.role == "front"]
    cam = by_name[camera] if camera else front[len(front) // 2]
    if camera and camera not in by_name:
        raise ValueError(f"unknown camera {camera!r}; the rig has {sorted(by_name)}")
    rig_params = model_rig(files, actor.model)
    tiles = []
    for i, name in enumerate(names):
        clip = motion(name)
        params = clip.sample(clip.duration / 2, rig_params)
        posed = actor.pose(params)
        shot = cam.camera
        if focus == "face":
            shot = _face_camera(shot, posed.joints[JOINT["head"]], size)
        view = actor.render(posed, shot)
        tiles.append(tile(view.rgb, name, size))
        if progress:
            progress(i + 1, len(names))
    return grid(tiles, columns)
