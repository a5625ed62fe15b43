"""Average keypoint distance (AKD, pixels) per body region: face, hands, torso.

Groups (``keypoint_groups`` names their members; ``body_keypoints`` gathers them):

* ``torso``: the upper body that drives the arms: spine1-3, neck, both collars, shoulders,
  elbows and wrists (12 SMPL-X joints; the pelvis and legs are outside the upper-body
  avatar).
* ``hands``: per hand (left, then right) the wrist and its 15 finger joints (32 joints), and
  with ``fingertips=True`` the 10 fingertip vertices the ``smplx`` package reads as extra
  joints (thumb, index, middle, ring, pinky; left then right).
* ``face``: every row of ``BodyOutput.landmarks`` (51 static landmarks, 68 with the face
  contour), named ``face_00``, ``face_01``, ... Absent when the model has no landmarks.

The wrists belong to both ``torso`` and ``hands``: each group is scored on its own.

``project_keypoints`` maps 3-D points to pixels with ``Camera.project`` (gsplat's pixel
convention: the image spans ``[0, W] x [0, H]``) and marks a point visible when it is in
front of the camera (z > 0) and inside the image. ``akd`` averages the Euclidean pixel
distance over the keypoints marked visible; with none visible it is NaN.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..body.models import BodyOutput
from ..body.skeleton import JOINT, LEFT_HAND_JOINTS, RIGHT_HAND_JOINTS, SMPLX_JOINT_NAMES
from ..render.camera import Camera
from ._common import as_tensor, check_finite

__all__ = ["FINGERTIP_VERTICES", "GROUPS", "akd", "body_akd", "body_keypoints",
           "keypoint_groups", "project_keypoints"]

GROUPS = ("face", "hands", "torso")

TORSO_JOINTS = (
    "spine1", "spine2", "spine3", "neck", "left_collar", "right_collar", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)  # fmt: skip
HAND_JOINTS = (
    "left_wrist", *(SMPLX_JOINT_NAMES[j] for j in LEFT_HAND_JOINTS),
    "right_wrist", *(SMPLX_JOINT_NAMES[j] for j in RIGHT_HAND_JOINTS),
)  # fmt: skip
# SMPL-X vertex of each fingertip (`smplx.vertex_ids.vertex_ids['smplx']`), in smplx's order.
FINGERTIP_VERTICES = {
    "left_thumb_tip": 5361, "left_index_tip": 4933, "left_middle_tip": 5058,
    "left_ring_tip": 5169, "left_pinky_tip": 5286,
    "right_thumb_tip": 8079, "right_index_tip": 7669, "right_middle_tip": 7794,
    "right_ring_tip": 7905, "right_pinky_tip": 8022,
}  # fmt: skip
NUM_STATIC_LANDMARKS = 51


def keypoint_groups(*, num_landmarks: int = NUM_STATIC_LANDMARKS,
                    fingertips: bool = False) -> dict[str, tuple[str, ...]]:
    """Group -> keypoint names, in the order ``body_keypoints`` stacks them. Joint names are
    ``SMPLX_JOINT_NAMES``; fingertips are ``FINGERTIP_VERTICES`` keys; face landmark ``i`` is
    ``face_{i:02d}`` (row ``i`` of ``BodyOutput.landmarks``)."""
    hands = HAND_JOINTS + (tuple(FINGERTIP_VERTICES) if fingertips else ())
    return {
        "face": tuple(f"face_{i:02d}" for i in range(num_landmarks)),
        "hands": hands,
        "torso": TORSO_JOINTS,
    }


def body_keypoints(output: BodyOutput, *, fingertips: bool = False,
                   vertex_ids: Any = None) -> dict[str, Tensor]:
    """Group -> 3-D keypoints ``[B, K, 3]`` of a posed body (see ``keypoint_groups``).

    ``fingertips=True`` adds the fingertip vertices to ``hands``; they are SMPL-X vertex
    indices, so the mesh must be in SMPL-X vertex order or ``vertex_ids`` must give the
    SMPL-X index of each of its vertices (``UpperBodyModel.vertex_ids``). ``face`` is left
    out when ``output.landmarks`` is None.
    """
    joints = output.joints  # [B, J, 3]
    rows = {"torso": [JOINT[n] for n in TORSO_JOINTS], "hands": [JOINT[n] for n in HAND_JOINTS]}
    out = {}
    if output.landmarks is not None:
        out["face"] = output.landmarks  # [B, L, 3]
    out["hands"] = joints[:, rows["hands"]]
    if fingertips:
        tips = _fingertip_rows(output.vertices.shape[1], vertex_ids)
        out["hands"] = torch.cat([out["hands"], output.vertices[:, tips]], dim=1)
    out["torso"] = joints[:, rows["torso"]]
    return out


def _fingertip_rows(num_vertices: int, vertex_ids: Any) -> list[int]:
    """Rows of the fingertip vertices in a mesh of ``num_vertices`` vertices."""
    wanted = list(FINGERTIP_VERTICES.values())
    if vertex_ids is None:
        if num_vertices <= max(wanted):
            raise ValueError(f"the mesh has {num_vertices} vertices, too few for SMPL-X's "
                             "fingertip vertices; pass vertex_ids for a cut mesh")
        return wanted
    ids = np.asarray(vertex_ids).reshape(-1)
    if len(ids) != num_vertices:
        raise ValueError(f"vertex_ids has {len(ids)} entries for a mesh of {num_vertices} "
                         "vertices")
    row_of = {int(v): i for i, v in enumerate(ids)}
    missing = [name for name, v in FINGERTIP_VERTICES.items() if v not in row_of]
    if missing:
        raise ValueError(f"the mesh lacks the fingertip vertices {missing}")
    return [row_of[v] for v in wanted]


def project_keypoints(points: Any, camera: Camera) -> tuple[Tensor, Tensor]:
    """World points ``[..., K, 3]`` -> pixels ``uv [..., K, 2]`` and ``visible [..., K]``.

    Visible: in front of the camera (z > 0) and inside the image ``[0, W) x [0, H)``.
    Points behind the camera get NaN ``uv`` so they cannot be used by mistake. Differentiable
    in ``points``.
    """
    pts = as_tensor(points, "points")
    if not pts.is_floating_point():
        pts = pts.to(torch.float64)
    if pts.ndim < 2 or pts.shape[-1] != 3:
        raise ValueError(f"'points' must have shape [..., K, 3], got {tuple(pts.shape)}")
    check_finite("points", pts)
    uv, z = camera.project(pts)
    in_front = z > 0
    uv = torch.where(in_front[..., None], uv, torch.full_like(uv, float("nan")))
    u, v = uv.unbind(-1)
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    return uv, in_front & inside


def akd(pred_2d: Any, gt_2d: Any, visible: Any = None) -> float:
    """Average keypoint distance in pixels: mean ``||pred - gt||`` over visible keypoints.

    ``pred_2d``, ``gt_2d``: ``[..., K, 2]``; ``visible``: bool ``[..., K]`` (None: all).
    Coordinates must be finite where visible (elsewhere, e.g. NaN behind the camera, they
    are ignored). NaN when nothing is visible.
    """
    p = as_tensor(pred_2d, "pred_2d")
    g = as_tensor(gt_2d, "gt_2d")
    for t, name in ((p, "pred_2d"), (g, "gt_2d")):
        if t.ndim < 2 or t.shape[-1] != 2 or not t.is_floating_point():
            raise ValueError(f"{name!r} must be float keypoints [..., K, 2], got "
                             f"{tuple(t.shape)} {t.dtype}")
    if p.shape != g.shape:
        raise ValueError(f"'pred_2d' and 'gt_2d' must have the same shape, got "
                         f"{tuple(p.shape)} and {tuple(g.shape)}")
    vis = _visibility(visible, p.shape[:-1], p.device)
    dtype = torch.promote_types(p.dtype, g.dtype)
    p, g = p.detach().to(dtype)[vis], g.detach().to(dtype=dtype, device=p.device)[vis]  # [N, 2]
    check_finite("pred_2d", p)
    check_finite("gt_2d", g)
    if not len(p):
        return float("nan")
    return float(torch.linalg.vector_norm(p - g, dim=-1).mean())


def _visibility(visible: Any, shape: torch.Size, device: torch.device) -> Tensor:
    if visible is None:
        return torch.ones(shape, dtype=torch.bool, device=device)
    vis = as_tensor(visible, "visible")
    if vis.dtype != torch.bool:
        raise ValueError(f"'visible' must be bool, got dtype {vis.dtype}")
    if vis.shape != shape:
        raise ValueError(f"'visible' must have shape {list(shape)}, got {list(vis.shape)}")
    return vis.to(device)


def body_akd(pred: BodyOutput, gt: BodyOutput, camera: Camera, *, fingertips: bool = False,
             vertex_ids: Any = None) -> dict[str, float]:
    """AKD per group between two posed bodies seen by ``camera``.

    A keypoint counts where it is visible in the ground truth and the prediction is in front
    of the camera (a prediction outside the image is still measured, so leaving the frame is
    penalised, not excused).
    """
    kp_pred = body_keypoints(pred, fingertips=fingertips, vertex_ids=vertex_ids)
    kp_gt = body_keypoints(gt, fingertips=fingertips, vertex_ids=vertex_ids)
    scores = {}
    for group in GROUPS:
        if group not in kp_pred or group not in kp_gt:
            continue
        uv_pred, _ = project_keypoints(kp_pred[group], camera)
        uv_gt, vis_gt = project_keypoints(kp_gt[group], camera)
        counted = vis_gt & torch.isfinite(uv_pred).all(dim=-1)
        scores[group] = akd(uv_pred, uv_gt, counted)
    return scores
