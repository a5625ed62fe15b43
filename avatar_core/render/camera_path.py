"""Where the camera looks and how it moves over a rendered sequence.

``framing_target`` is the point an orbit looks at to frame the avatar's upper body (the render
CLI's orbit and the server's default orbit); ``cameras_for`` reads a camera path.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from torch import Tensor

from protocol.cameras import (
    CAMERA_NAMES,
    CAMERA_PRESETS,
    DISTANCE_M,
    PITCH_DEG,
    orbit_yaws,
)

from .camera import Camera, orbit

__all__ = ["CHEST_DROP_M", "NECK_JOINT", "cameras_for", "framing_target"]

NECK_JOINT = 12  # SMPL-X joint index of the neck
CHEST_DROP_M = 0.2  # the framing target lies this far below the neck joint: the chest


def framing_target(joint_template: Tensor) -> np.ndarray:
    """[3] world point that frames the upper body: ``CHEST_DROP_M`` below the neck of a body
    model's template skeleton (``joint_template`` [J, 3])."""
    neck = joint_template[NECK_JOINT].cpu().numpy()
    return neck - np.array([0.0, CHEST_DROP_M, 0.0])


def cameras_for(spec: str, n: int, size: int, target: np.ndarray) -> list[Camera]:
    """A camera preset (protocol.cameras: 'front', 'left', 'right', or 'orbit', a sweep from
    left to right around the upper body whose single frame is the front) or a JSON camera /
    list of cameras."""
    if spec in CAMERA_PRESETS or spec == "orbit":
        yaws = orbit_yaws(n) if spec == "orbit" else [CAMERA_PRESETS[spec]["yaw_deg"]] * n
        return [orbit(target, yaw_deg=yaw, pitch_deg=PITCH_DEG, distance=DISTANCE_M,
                      width=size, height=size, fov_y_deg=30.0) for yaw in yaws]
    if not Path(spec).is_file():
        raise ValueError(f"camera {spec!r} is neither a preset ({', '.join(CAMERA_NAMES)}) "
                         "nor a JSON camera file")
    data = json.loads(Path(spec).read_text())
    cams = [Camera.from_dict(d) for d in (data if isinstance(data, list) else [data])]
    if len(cams) == 1:
        cams = cams * n
    if len(cams) != n:
        raise ValueError(f"{spec}: {len(cams)} cameras for {n} frames")
    return [c.resized(size, size * c.height // c.width) if c.width != size else c for c in cams]
