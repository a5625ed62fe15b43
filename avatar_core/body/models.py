"""Body-model objects: `forward(params) -> vertices, joints, landmarks` for each family.

`LBSModel` holds the model data as tensors and runs linear blend skinning in cached stages:
shape (betas) -> expression -> pose (rotations, pose correctives) -> joint transforms ->
skinning. A stage whose inputs did not change since the last call is reused, so when only the
expression changes the pose correctives (the largest matmul) are not recomputed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from . import lbs
from .cache import StageCache
from .model_data import ModelData
from .params import FLAMEParams, MANOParams, SMPLXParams, normalize_params
from .skeleton import SMPLX_NUM_BODY_JOINTS


@dataclass
class BodyOutput:
    vertices: Tensor            # [B, V, 3]
    joints: Tensor              # [B, J, 3] posed joints
    landmarks: Tensor | None    # [B, L, 3] face landmarks (static, then contour if enabled)
    full_pose: Tensor           # [B, J, 3] axis-angle actually applied (hand mean included)


def _rot_y_angle(rot: Tensor) -> Tensor:
    """Rotation about y of a rotation matrix, as the face-contour look-up table expects."""
    sy = torch.sqrt(rot[:, 0, 0] ** 2 + rot[:, 1, 0] ** 2)
    return torch.atan2(-rot[:, 2, 0], sy)


class LBSModel(nn.Module):
    """Family-independent skinning with a stage cache. Subclasses assemble the full pose."""

    def __init__(self, data: ModelData, *, dtype: torch.dtype = torch.float32,
                 device: torch.device | str | None = None, cache: bool = True,
                 face_contour: bool = False) -> None:
        super().__init__()
        self.data = data
        self.parents = data.parents

        def buf(name: str, arr: np.ndarray | None, as_dtype: torch.dtype = dtype) -> None:
            t = None if arr is None else torch.as_tensor(np.asarray(arr), dtype=as_dtype,
                                                         device=device)
            self.register_buffer(name, t, persistent=False)

        buf("v_template", data.v_template)
        buf("shapedirs", data.shapedirs)
        buf("exprdirs", data.exprdirs)
        # Rows of all-zero correctives (e.g. leg joints on the upper body) are dropped: exact.
        features = lbs.active_pose_features(torch.as_tensor(data.posedirs))
        buf("pose_feature_ids", features.numpy(), torch.long)
        buf("posedirs", data.posedirs[features.numpy()])
        buf("weights", data.weights)
        buf("joint_template", data.joint_template)
        buf("joint_shapedirs", data.joint_shapedirs)
        buf("joint_exprdirs", data.joint_exprdirs)
        buf("joint_regressor", data.joint_regressor)
        buf("faces", data.faces, torch.long)
        buf("lmk_faces", data.lmk_faces, torch.long)
        buf("lmk_bary", data.lmk_bary)
        self.face_contour = face_contour and data.dynamic_lmk_faces is not None
        buf("dynamic_lmk_faces", data.dynamic_lmk_faces if self.face_contour else None, torch.long)
        buf("dynamic_lmk_bary", data.dynamic_lmk_bary if self.face_contour else None)
        self.cache = StageCache(enabled=cache)

    def _apply(self, fn, recurse=True):  # .to(), .double(), ...: cached tensors are stale
        self.cache.clear()
        return super()._apply(fn, recurse)

    @property
    def dtype(self) -> torch.dtype:
        return self.v_template.dtype

    @property
    def device(self) -> torch.device:
        return self.v_template.device

    @property
    def num_vertices(self) -> int:
        return self.v_template.shape[0]

    @property
    def num_betas(self) -> int:
        return self.shapedirs.shape[-1]

    @property
    def num_expression(self) -> int:
        return self.exprdirs.shape[-1]

    def _normalize(self, params: Any, spec: dict, family: str) -> dict[str, Tensor]:
        return normalize_params(params, spec, dtype=self.dtype, device=self.device, family=family)

    def _shape_stage(self, betas: Tensor, offsets: Tensor | None,
                     cache: StageCache) -> tuple[Tensor, Tensor]:
        def compute() -> tuple[Tensor, Tensor]:
            verts = self.v_template + lbs.blend_shapes(betas, self.shapedirs)  # [B, V, 3]
            joints = self.joint_template + lbs.blend_shapes(betas, self.joint_shapedirs)
            if offsets is not None:
                verts = verts + offsets
                joints = joints + lbs.vertices_to_joints(self.joint_regressor, offsets)
            return verts, joints

        return cache.get("shape", (betas, offsets), compute)

    def skin(self, betas: Tensor, expression: Tensor, full_pose: Tensor, transl: Tensor,
             offsets: Tensor | None = None, cache: StageCache | None = None) -> BodyOutput:
        """Skinning in cached stages. betas [B, S], expression [B, E], full_pose [B, J, 3],
        transl [B, 3], offsets [B, V, 3] or None. ``cache``: the caller's own stage cache
        (e.g. one per streaming session sharing this model); None: the model's."""
        cache = self.cache if cache is None else cache
        v_shape, j_shape = self._shape_stage(betas, offsets, cache)

        def expression_stage() -> tuple[Tensor, Tensor]:
            if expression.shape[-1] == 0:
                return v_shape, j_shape
            return (v_shape + lbs.blend_shapes(expression, self.exprdirs),
                    j_shape + lbs.blend_shapes(expression, self.joint_exprdirs))

        v_shaped, joints = cache.get("expression", (betas, offsets, expression),
                                     expression_stage)

        def pose_stage() -> tuple[Tensor, Tensor]:
            rot = lbs.rodrigues(full_pose)  # [B, J, 3, 3]
            return rot, lbs.pose_offsets(rot, self.posedirs, self.pose_feature_ids)

        rot_mats, corrective = cache.get("pose", (full_pose,), pose_stage)

        def transform_stage() -> tuple[Tensor, Tensor]:
            posed_joints, transforms = lbs.rigid_transforms(rot_mats, joints, self.parents)
            return posed_joints, lbs.blend_transforms(self.weights, transforms)

        posed_joints, vertex_transforms = cache.get("transforms", (full_pose, joints),
                                                    transform_stage)
        vertices = lbs.skin_vertices(v_shaped + corrective, vertex_transforms)
        vertices = vertices + transl[:, None]
        return BodyOutput(vertices=vertices, joints=posed_joints + transl[:, None],
                          landmarks=self._landmarks(vertices, rot_mats), full_pose=full_pose)

    def _landmarks(self, vertices: Tensor, rot_mats: Tensor) -> Tensor | None:
        if self.lmk_faces is None:
            return None
        static = lbs.vertices_to_landmarks(vertices, self.faces, self.lmk_faces, self.lmk_bary)
        if not self.face_contour:
            return static
        idx = self._contour_rows(rot_mats)  # [B]
        contour = lbs.vertices_to_landmarks(vertices, self.faces, self.dynamic_lmk_faces[idx],
                                            self.dynamic_lmk_bary[idx])
        return torch.cat([static, contour], dim=1)

    def _contour_rows(self, rot_mats: Tensor) -> Tensor:
        """Row of the contour look-up table for each sample's head yaw (the SMPL-X recipe)."""
        chain = self.contour_chain()
        rel = rot_mats[:, chain[0]]
        for j in chain[1:]:
            rel = rot_mats[:, j] @ rel
        deg = torch.round(torch.clamp(-_rot_y_angle(rel) * 180.0 / np.pi, max=39)).long()
        return torch.where(deg < 0, torch.where(deg < -39, 78, 39 - deg), deg)

    def contour_chain(self) -> list[int]:
        """Joints from the head-yaw joint up to the root."""
        raise NotImplementedError(f"{type(self).__name__} has no face contour")


def _register_hand(module: nn.Module, prefix: str, comps: np.ndarray, mean: np.ndarray,
                   hand_pca: int | None, flat_hand_mean: bool) -> None:
    """Buffers `{prefix}hand_components` [n, 45] and `{prefix}hand_mean` [15, 3] for a hand."""
    if hand_pca is not None and not 1 <= hand_pca <= comps.shape[0]:
        raise ValueError(f"hand_pca must be in [1, {comps.shape[0]}], got {hand_pca}")
    dt, dev = module.v_template.dtype, module.v_template.device
    module.register_buffer(f"{prefix}hand_components", torch.as_tensor(
        comps[: hand_pca or comps.shape[0]], dtype=dt, device=dev), False)
    mean = np.zeros(45) if flat_hand_mean else mean
    module.register_buffer(f"{prefix}hand_mean",
                           torch.as_tensor(mean, dtype=dt, device=dev).reshape(15, 3), False)


def _full_hand_pose(pose: Tensor, components: Tensor, mean: Tensor, pca: bool) -> Tensor:
    """Absolute axis-angle finger pose [B, 15, 3] from PCA coefficients or a relative pose."""
    if pca:
        pose = (pose @ components).reshape(-1, 15, 3)
    return pose + mean


class SMPLXModel(LBSModel):
    """SMPL-X. Options follow `smplx.SMPLX`: `hand_pca` (number of PCA coefficients per hand,
    None for the full 45-D pose) and `flat_hand_mean` (False adds the relaxed mean hand)."""

    family = "SMPL-X"

    def __init__(self, data: ModelData, *, hand_pca: int | None = None,
                 flat_hand_mean: bool = False, **kwargs: Any) -> None:
        super().__init__(data, **kwargs)
        self.hand_pca = hand_pca
        self.flat_hand_mean = flat_hand_mean
        for side in ("left", "right"):
            _register_hand(self, f"{side}_", data.hand_components[side], data.hand_mean[side],
                           hand_pca, flat_hand_mean)

    def param_spec(self) -> dict[str, tuple[int, ...]]:
        hand = (self.hand_pca,) if self.hand_pca else (15, 3)
        return {"betas": (self.num_betas,), "expression": (self.num_expression,),
                "global_orient": (3,), "body_pose": (SMPLX_NUM_BODY_JOINTS, 3),
                "jaw_pose": (3,), "leye_pose": (3,), "reye_pose": (3,),
                "left_hand_pose": hand, "right_hand_pose": hand, "transl": (3,),
                "vertex_offsets": (self.num_vertices, 3)}

    def hand_pose_full(self, side: str, pose: Tensor) -> Tensor:
        """Absolute axis-angle finger pose [B, 15, 3] from this model's hand parameters."""
        return _full_hand_pose(pose, getattr(self, f"{side}_hand_components"),
                               getattr(self, f"{side}_hand_mean"), bool(self.hand_pca))

    def full_pose(self, p: dict[str, Tensor]) -> Tensor:
        """Full axis-angle pose [B, 55, 3] from normalized (equally batched) parameters."""
        parts = [p["global_orient"][:, None], p["body_pose"], p["jaw_pose"][:, None],
                 p["leye_pose"][:, None], p["reye_pose"][:, None],
                 self.hand_pose_full("left", p["left_hand_pose"]),
                 self.hand_pose_full("right", p["right_hand_pose"])]
        return torch.cat(parts, dim=1)

    def forward(self, params: SMPLXParams | dict[str, Any] | None = None,
                cache: StageCache | None = None) -> BodyOutput:
        raw = params.to_dict() if isinstance(params, SMPLXParams) else dict(params or {})
        has_offsets = raw.get("vertex_offsets") is not None
        spec = self.param_spec()
        if not has_offsets:
            spec.pop("vertex_offsets")
        p = self._normalize(raw, spec, self.family)
        return self.skin(p["betas"], p["expression"], self.full_pose(p), p["transl"],
                         p["vertex_offsets"] if has_offsets else None, cache)

    def contour_chain(self) -> list[int]:
        chain, j = [], 12  # the neck, then its ancestors up to the pelvis
        while j != -1:
            chain.append(j)
            j = self.parents[j]
        return chain


class FLAMEModel(LBSModel):
    """FLAME: pose = [rotation, neck, jaw, left eye, right eye]."""

    family = "FLAME"

    def param_spec(self) -> dict[str, tuple[int, ...]]:
        return {"shape": (self.num_betas,), "expr": (self.num_expression,), "rotation": (3,),
                "neck_pose": (3,), "jaw_pose": (3,), "eyes_pose": (6,), "translation": (3,)}

    def forward(self, params: FLAMEParams | dict[str, Any] | None = None) -> BodyOutput:
        p = self._normalize(params or {}, self.param_spec(), self.family)
        pose = torch.cat([p["rotation"], p["neck_pose"], p["jaw_pose"], p["eyes_pose"]], dim=1)
        return self.skin(p["shape"], p["expr"], pose.reshape(-1, 5, 3), p["translation"])

    def contour_chain(self) -> list[int]:
        return [1, 0]


class MANOModel(LBSModel):
    """MANO, one hand. Options as `smplx.MANO`: `hand_pca` and `flat_hand_mean`."""

    family = "MANO"

    def __init__(self, data: ModelData, *, hand_pca: int | None = None,
                 flat_hand_mean: bool = False, **kwargs: Any) -> None:
        super().__init__(data, **kwargs)
        (self.side,) = data.hand_components
        self.hand_pca = hand_pca
        self.flat_hand_mean = flat_hand_mean
        _register_hand(self, "", data.hand_components[self.side], data.hand_mean[self.side],
                       hand_pca, flat_hand_mean)

    def param_spec(self) -> dict[str, tuple[int, ...]]:
        hand = (self.hand_pca,) if self.hand_pca else (15, 3)
        return {"betas": (self.num_betas,), "global_orient": (3,), "hand_pose": hand,
                "transl": (3,)}

    def hand_pose_full(self, pose: Tensor) -> Tensor:
        """Absolute axis-angle finger pose [B, 15, 3] from this model's hand parameters."""
        return _full_hand_pose(pose, self.hand_components, self.hand_mean, bool(self.hand_pca))

    def forward(self, params: MANOParams | dict[str, Any] | None = None) -> BodyOutput:
        p = self._normalize(params or {}, self.param_spec(), self.family)
        pose = torch.cat([p["global_orient"][:, None], self.hand_pose_full(p["hand_pose"])], 1)
        no_expression = p["betas"].new_zeros(p["betas"].shape[0], 0)
        return self.skin(p["betas"], no_expression, pose, p["transl"])

