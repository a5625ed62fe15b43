"""A strip of library motions at their peak, filmed by one studio camera: the actor at a
glance, without writing a dataset."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..dataset.preview import grid, tile
from .actor import Actor
from .body_demo import ensure_models, model_rig
from .motions import motion
from .studio import StudioConfig, studio_rig

__all__ = ["motion_strip"]


def motion_strip(names: Sequence[str], *, identity: int = 0, camera: str | None = None,
                 size: int = 256, columns: int = 8, model_dir: Path | None = None,
                 progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """uint8 RGB grid: each motion at half its duration (where the library's clips hold their
    expression or gesture), seen by `camera` (default: the centre front camera)."""
    if not names:
        raise ValueError("no motions given")
    files = ensure_models(model_dir)
    actor = Actor.load(files, identity)
    rig = studio_rig(size, StudioConfig())
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
        view = actor.render(actor.pose(params), cam.camera)
        tiles.append(tile(view.rgb, name, size))
        if progress:
            progress(i + 1, len(names))
    return grid(tiles, columns)
