"""Where the camera looks and how it moves over a rendered sequence.

``framing_target`` is the point an orbit looks at to frame the avatar's upper body (the render
CLI's orbit and the server's default orbit); ``cameras_for`` reads a camera path.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from torch import Tensor

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
    """'orbit' (a half-circle sweep around the upper body) or a JSON camera / list of cameras."""
    if spec == "orbit":
        return [orbit(target, yaw_deg=-60.0 + 120.0 * i / max(n - 1, 1), pitch_deg=5.0,
                      distance=2.7, width=size, height=size, fov_y_deg=30.0) for i in range(n)]
    data = json.loads(Path(spec).read_text())
    cams = [Camera.from_dict(d) for d in (data if isinstance(data, list) else [data])]
    if len(cams) == 1:
        cams = cams * n
    if len(cams) != n:
        raise ValueError(f"{spec}: {len(cams)} cameras for {n} frames")
    return [c.resized(size, size * c.height // c.width) if c.width != size else c for c in cams]
