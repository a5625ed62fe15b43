"""Linear blend skinning as small pure functions (the math of SMPL, SMPL-X, FLAME and MANO).

Every function is batched, differentiable and works in float32 or float64 on any device.
Shapes: B batch, V vertices, J joints, K blend-shape coefficients, P = 9 * (J - 1) pose features.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..rotations import matrix_to_quaternion

# Below this squared angle Rodrigues switches to its Taylor series, where the closed form
# divides by ~0 and its gradient is NaN.
_SMALL_ANGLE_SQ = 1e-6


def blend_shapes(coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Displacements from blend-shape coefficients. coeffs [B, K], dirs [V, 3, K] -> [B, V, 3]."""
    return torch.einsum("bk,vck->bvc", coeffs, dirs)


def vertices_to_joints(regressor: Tensor, vertices: Tensor) -> Tensor:
    """Regress joints from vertices. regressor [J, V], vertices [B, V, 3] -> [B, J, 3]."""
    return torch.einsum("jv,bvc->bjc", regressor, vertices)


def skew(v: Tensor) -> Tensor:
    """Cross-product matrices. v [..., 3] -> [..., 3, 3]."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def rodrigues(rot_vecs: Tensor) -> Tensor:
    """Axis-angle to rotation matrices. rot_vecs [..., 3] -> [..., 3, 3].

    R = I + a(t) K + b(t) K^2 with K = skew(r), t = |r|, a = sin t / t, b = (1 - cos t) / t^2.
    Near t = 0 both factors use their Taylor series, so values and gradients stay finite there;
    b is evaluated as 2 sin^2(t/2) / t^2, which keeps its precision for small t in float32.
    """
    theta_sq = (rot_vecs * rot_vecs).sum(-1, keepdim=True)[..., None]  # [..., 1, 1]
    small = theta_sq < _SMALL_ANGLE_SQ
    safe_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    theta = torch.sqrt(safe_sq)
    half_sin = torch.sin(0.5 * theta)
    a = torch.where(small, 1.0 - theta_sq / 6.0 + theta_sq**2 / 120.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta_sq / 24.0 + theta_sq**2 / 720.0, 2.0 * half_sin**2 / safe_sq)
    k = skew(rot_vecs)
    eye = torch.eye(3, dtype=rot_vecs.dtype, device=rot_vecs.device)
    return eye + a * k + b * (k @ k)


def pose_features(rot_mats: Tensor) -> Tensor:
    """Pose-corrective features (R - I) of every non-root joint. [B, J, 3, 3] -> [B, 9 (J-1)]."""
    eye = torch.eye(3, dtype=rot_mats.dtype, device=rot_mats.device)
    return (rot_mats[:, 1:] - eye).reshape(rot_mats.shape[0], -1)


def pose_offsets(rot_mats: Tensor, posedirs: Tensor, features: Tensor | None = None) -> Tensor:
    """Pose-corrective displacements. rot_mats [B, J, 3, 3], posedirs [P, V * 3] -> [B, V, 3].

    With `features` [P'], posedirs holds only those rows (the others are all zero).
    """
    feats = pose_features(rot_mats)
    if features is not None:
        feats = feats[:, features]
    return (feats @ posedirs).reshape(rot_mats.shape[0], -1, 3)


def kinematic_levels(parents: Sequence[int]) -> list[tuple[list[int], list[int]]]:
    """Group non-root joints by depth: [(joints, their parents), ...] from the root outwards.

    Composing transforms one level at a time takes ~10 batched matmuls instead of one per joint.
    """
    depth = [0] * len(parents)
    for j in range(1, len(parents)):
        if not 0 <= parents[j] < j:
            raise ValueError(
                f"parents must list each joint after its parent; joint {j} has parent {parents[j]}"
            )
        depth[j] = depth[parents[j]] + 1
    levels = []
    for d in range(1, max(depth, default=0) + 1):
        joints = [j for j in range(len(parents)) if depth[j] == d]
        levels.append((joints, [parents[j] for j in joints]))
    return levels


def homogeneous(rot: Tensor, trans: Tensor) -> Tensor:
    """Rigid transforms as 4x4 matrices. rot [..., 3, 3], trans [..., 3] -> [..., 4, 4]."""
    top = torch.cat([rot, trans[..., None]], dim=-1)  # [..., 3, 4]
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def global_transforms(rot_mats: Tensor, joints: Tensor, parents: Sequence[int]) -> Tensor:
    """World transform of each joint frame.

    rot_mats [B, J, 3, 3], joints [B, J, 3] -> [B, J, 4, 4].
    """
    parent_idx = torch.as_tensor([0, *parents[1:]], device=joints.device)
    rel_joints = joints - torch.cat([torch.zeros_like(joints[:, :1]), joints[:, parent_idx[1:]]], 1)
    local = homogeneous(rot_mats, rel_joints)  # [B, J, 4, 4]
    world = local
    for level_joints, level_parents in kinematic_levels(parents):
        idx = torch.as_tensor(level_joints, device=joints.device)
        composed = world[:, level_parents] @ local[:, level_joints]
        world = world.index_copy(1, idx, composed)
    return world


def global_rotations(rot_mats: Tensor, parents: Sequence[int]) -> Tensor:
    """World rotation of each joint frame. [B, J, 3, 3] -> [B, J, 3, 3]."""
    world = rot_mats
    for level_joints, level_parents in kinematic_levels(parents):
        idx = torch.as_tensor(level_joints, device=rot_mats.device)
        world = world.index_copy(1, idx, world[:, level_parents] @ rot_mats[:, level_joints])
    return world


def rigid_transforms(
    rot_mats: Tensor, joints: Tensor, parents: Sequence[int]
) -> tuple[Tensor, Tensor]:
    """Posed joints and the skinning transforms that move rest-pose points with each joint.

    rot_mats [B, J, 3, 3], joints [B, J, 3] (rest)
    -> posed joints [B, J, 3], transforms [B, J, 4, 4].
    """
    world = global_transforms(rot_mats, joints, parents)
    posed_joints = world[..., :3, 3]
    # Remove the rest-pose joint position so each transform applies to rest-pose coordinates.
    offset = (world[..., :3, :3] @ joints[..., None])[..., 0]  # [B, J, 3]
    skin = torch.cat([world[..., :3, :3], (posed_joints - offset)[..., None]], dim=-1)
    return posed_joints, homogeneous(skin[..., :3], skin[..., 3])


def blend_transforms(weights: Tensor, transforms: Tensor) -> Tensor:
    """Per-vertex blended 3x4 transforms.

    weights [V, J], transforms [B, J, 4, 4] -> [B, V, 3, 4].
    """
    b, j = transforms.shape[:2]
    flat = transforms[:, :, :3, :].reshape(b, j, 12)
    return torch.matmul(weights, flat).reshape(b, -1, 3, 4)


def skin_vertices(vertices: Tensor, vertex_transforms: Tensor) -> Tensor:
    """Apply per-vertex 3x4 transforms. vertices [B, V, 3], transforms [B, V, 3, 4] -> [B, V, 3]."""
    t = vertex_transforms
    # Column by column: no [B, V, 3, 3] temporary and no batched tiny matmuls (4x faster on CPU).
    return (t[..., 0] * vertices[..., 0:1] + t[..., 1] * vertices[..., 1:2]
            + t[..., 2] * vertices[..., 2:3] + t[..., 3])


def active_pose_features(posedirs: Tensor) -> Tensor:
    """Indices of the pose features whose correctives are not all zero. [P, V * 3] -> [P']."""
    return torch.nonzero(posedirs.abs().amax(dim=1) > 0).flatten()


def vertices_to_landmarks(
    vertices: Tensor, faces: Tensor, lmk_faces: Tensor, lmk_bary: Tensor
) -> Tensor:
    """Barycentric surface points. vertices [B, V, 3], faces [F, 3], lmk_faces [L] or [B, L],
    lmk_bary [L, 3] or [B, L, 3] -> [B, L, 3]."""
    b = vertices.shape[0]
    lmk_faces = lmk_faces.expand(b, -1) if lmk_faces.dim() == 1 else lmk_faces
    lmk_bary = lmk_bary.expand(b, -1, -1) if lmk_bary.dim() == 2 else lmk_bary
    corner_idx = faces[lmk_faces]  # [B, L, 3]
    batch_idx = torch.arange(b, device=vertices.device)[:, None, None]
    corners = vertices[batch_idx, corner_idx]  # [B, L, 3, 3]
    return (lmk_bary[..., None] * corners).sum(-2)


def lbs(
    shape_coeffs: Tensor,
    full_pose: Tensor,
    v_template: Tensor,
    shapedirs: Tensor,
    posedirs: Tensor,
    joint_regressor: Tensor,
    parents: Sequence[int],
    weights: Tensor,
) -> tuple[Tensor, Tensor]:
    """The whole SMPL-family forward pass, the reference that the cached models must match.

    shape_coeffs [B, K], full_pose [B, J, 3] axis-angle, v_template [V, 3], shapedirs [V, 3, K],
    posedirs [P, V * 3], joint_regressor [J, V], weights [V, J]
    -> vertices [B, V, 3], joints [B, J, 3].
    """
    b = full_pose.shape[0]
    v_shaped = v_template + blend_shapes(shape_coeffs, shapedirs)
    joints = vertices_to_joints(joint_regressor, v_shaped)
    rot_mats = rodrigues(full_pose.reshape(b, -1, 3))
    v_posed = v_shaped + pose_offsets(rot_mats, posedirs)
    posed_joints, transforms = rigid_transforms(rot_mats, joints, parents)
    return skin_vertices(v_posed, blend_transforms(weights, transforms)), posed_joints


def rotation_to_axis_angle(rot: Tensor) -> Tensor:
    """Rotation matrices to axis-angle, stable at 0 and pi. [..., 3, 3] -> [..., 3]."""
    quat = matrix_to_quaternion(rot)  # w >= 0
    w, v = quat[..., 0], quat[..., 1:]
    n = torch.linalg.norm(v, dim=-1)
    small = n < 1e-6
    safe_n = torch.where(small, torch.ones_like(n), n)
    scale = torch.where(small, 2.0 / w.clamp(min=1e-6), 2.0 * torch.atan2(n, w) / safe_n)
    return v * scale[..., None]
