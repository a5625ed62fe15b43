"""A room's default view for its welcome: every seat's avatar posed at rest and placed, framed by
``avatar_core.render.framing``; the face is the performed seat's (a viewer's: seat 0's).

The rest geometry is kept per animator (the registry's shared one lives as long as the avatar
is loaded): a join after the first costs no forward pass (bench/page_view.py)."""

from __future__ import annotations

import threading
import weakref
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

__all__ = ["pose_at_rest", "rest_boxes", "room_framing"]


Box = tuple[np.ndarray, np.ndarray]  # lo [3], hi [3]
_REST: weakref.WeakKeyDictionary[AvatarAnimator, tuple[Box, Box]] = weakref.WeakKeyDictionary()
_REST_LOCK = threading.Lock()


def rest_boxes(animator: AvatarAnimator) -> tuple[Box, Box]:
    """(the body's box, the head's box) at rest in the avatar's own frame, kept per animator."""
    with _REST_LOCK:
        kept = _REST.get(animator)
    if kept is None:
        kept = pose_at_rest(animator)
        with _REST_LOCK:
            _REST[animator] = kept
    return kept


def pose_at_rest(animator: AvatarAnimator) -> tuple[Box, Box]:
    """The boxes, from a forward pass of its own (no stage cache: the shared animator and its
    caches are left alone)."""
    params = {"body_pose": rest_body_pose()}
    if animator.betas is not None:
        params["betas"] = animator.betas
    with torch.no_grad():
        out = animator.body_model(params, cache=StageCache(enabled=False))
    vertices = out.vertices[0].cpu().numpy().astype(np.float64)
    neck = out.joints[0, NECK_JOINT].cpu().numpy().astype(np.float64)
    return (vertices.min(0), vertices.max(0)), head_box(vertices, neck)


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
        body, head_rest = rest_boxes(animator_of(seat.avatar))
        for (lo, hi), is_head in ((body, False), (head_rest, True)):
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
