"""What a real studio's trackers would report for a synthetic take.

A real capture has no ground-truth SMPL-X: a body tracker fits SMPL-X with a weak face and
coarse hands, while a face tracker (FLAME) and hand trackers (MANO) see those parts well.
MVFGA fuses the three. The studio simulates that split, so that fusion and its ablation mean
the same here as on real data:

- SMPL-X (body tracker): the true body, but no expression, jaw or eye motion, hands projected
  onto the model's first `hand_pca` PCA components, and `noise_deg` of rotation noise on the
  neck, head and wrists (the joints a body tracker sees worst);
- FLAME (face tracker): exact `expr`, `jaw_pose`, `eyes_pose`, `neck_pose` (the SMPL-X head
  joint's local rotation) and `rotation` (the neck joint's world rotation);
- MANO (hand trackers): exact `hand_pose` (relative to the MANO mean, which the synthetic
  MANO files share with SMPL-X) and `global_orient` (the wrist's world rotation).

`avatar_core.body.fusion.fuse` with world-frame head and wrist rotations turns these back
into the true parameters (tested).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..body.skeleton import JOINT, SMPLX_PARENTS

__all__ = ["simulate_trackers", "world_rotation"]

_NOISY_JOINTS = ("neck", "head", "left_wrist", "right_wrist")


def _full_pose(p: dict[str, np.ndarray]) -> np.ndarray:
    """[T, 22, 3] root + body joints (enough for every chain up to the wrists)."""
    return np.concatenate([p["global_orient"][:, None], p["body_pose"]], axis=1)


def world_rotation(p: dict[str, np.ndarray], joint: int) -> np.ndarray:
    """Axis-angle [T, 3] of `joint`'s world rotation (root to joint, body joints only)."""
    full = _full_pose(p)
    chain, j = [], joint
    while j != -1:
        chain.append(j)
        j = SMPLX_PARENTS[j]
    rot = Rotation.from_rotvec(full[:, chain[-1]])
    for j in reversed(chain[:-1]):
        rot = rot * Rotation.from_rotvec(full[:, j])
    return rot.as_rotvec()


def _project_hand(pose: np.ndarray, components: np.ndarray, k: int) -> np.ndarray:
    """[T, 15, 3] pose relative to the mean, kept to its first k PCA components."""
    basis = components[:k]  # [k, 45]
    flat = pose.reshape(len(pose), 45)
    coeffs = flat @ np.linalg.pinv(basis)  # least squares: robust to non-orthonormal rows
    return (coeffs @ basis).reshape(-1, 15, 3)


def simulate_trackers(truth: dict[str, np.ndarray], hand_components: dict[str, np.ndarray],
                      *, hand_pca: int = 6, noise_deg: float = 2.0,
                      rng: np.random.Generator) -> dict[str, np.ndarray]:
    """params.npz arrays for a take whose true per-frame SMPL-X parameters are `truth`
    (arrays [T, ...], hands relative to the model's mean; `betas` shared)."""
    if hand_pca < 0 or noise_deg < 0:
        raise ValueError("hand_pca and noise_deg must be non-negative")
    t = len(truth["body_pose"])
    body = {k: np.array(v, dtype=np.float64, copy=True) for k, v in truth.items()}
    body["expression"] = np.zeros_like(body["expression"])
    for key in ("jaw_pose", "leye_pose", "reye_pose"):
        body[key] = np.zeros_like(body[key])
    for side in ("left", "right"):
        body[f"{side}_hand_pose"] = _project_hand(body[f"{side}_hand_pose"],
                                                  hand_components[side], hand_pca)
    for name in _NOISY_JOINTS:
        body["body_pose"][:, JOINT[name] - 1] += rng.normal(0.0, np.deg2rad(noise_deg), (t, 3))

    out = dict(body)
    out.update(
        flame_expr=np.array(truth["expression"], dtype=np.float64),
        flame_jaw_pose=np.array(truth["jaw_pose"], dtype=np.float64),
        flame_eyes_pose=np.concatenate([truth["leye_pose"], truth["reye_pose"]], axis=1),
        flame_neck_pose=np.array(truth["body_pose"][:, JOINT["head"] - 1], dtype=np.float64),
        flame_rotation=world_rotation(truth, JOINT["neck"]),
        flame_translation=np.zeros((t, 3)),
    )
    for side in ("left", "right"):
        out[f"mano_{side}_hand_pose"] = np.array(truth[f"{side}_hand_pose"], dtype=np.float64)
        out[f"mano_{side}_global_orient"] = world_rotation(truth, JOINT[f"{side}_wrist"])
    return out
