"""A room's default view for its welcome: every seat's avatar posed at rest and placed, framed by
``avatar_core.render.framing``; the face is the performed seat's (a viewer's: seat 0's)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from avatar_core.body.cache import StageCache
from avatar_core.body.rest_pose import rest_body_pose
from avatar_core.gaussians.animate import AvatarAnimator
from avatar_core.gaussians.placement import placed_point, seat_transform
from avatar_core.render.camera_path import NECK_JOINT
from avatar_core.render.framing import frame_scene, head_box
from protocol import Framing

__all__ = ["room_framing"]


def _rest_geometry(animator: AvatarAnimator) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [V, 3], neck joint [3]) of the avatar at rest, in its own frame. A forward pass
    of its own (no stage cache): the shared animator and its caches are left alone."""
    model = animator.body_model
    params = {"body_pose": rest_body_pose()}
    if animator.betas is not None:
        params["betas"] = animator.betas
    with torch.no_grad():
        out = model(params, cache=StageCache(enabled=False))
    return (out.vertices[0].cpu().numpy().astype(np.float64),
            out.joints[0, NECK_JOINT].cpu().numpy().astype(np.float64))


def _placed(points: np.ndarray, placement: Any) -> np.ndarray:
    rotation, _ = seat_transform(placement.rotation, placement.translation, torch.float64, "cpu")
    shift = np.asarray(placement.translation, dtype=np.float64)
    return np.stack([placed_point(p, rotation, shift) for p in points])


def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
                     for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def room_framing(seats: Sequence[Any], face_seat: int,
                 animator_of: Callable[[str], AvatarAnimator]) -> Framing:
    """The framing of ``seats`` (SeatSpec: index, avatar, placement) at rest; ``animator_of``
    gives an avatar id's (shared) animator."""
    boxes, head = [], None
    for seat in seats:
        vertices, neck = _rest_geometry(animator_of(seat.avatar))
        for lo, hi, is_head in ((vertices.min(0), vertices.max(0), False),
                                (*head_box(vertices, neck), True)):
            corners = _placed(_corners(lo, hi), seat.placement)  # a rotated box's new box
            box = (corners.min(0), corners.max(0))
            if not is_head:
                boxes.append(box)
            elif seat.index == face_seat or head is None:
                head = box
    framing = frame_scene(boxes, head)
    return Framing(target=tuple(framing.target), distance=framing.distance,
                   fov_y_deg=framing.fov_y_deg, face=tuple(framing.face),
                   min_distance=framing.min_distance)
