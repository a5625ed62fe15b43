"""The body model's keypoints in the fitter's layout, from SMPL-X parameters.

Only what the keypoints need is skinned: a sub-model holding the vertices of the landmark
triangles (static and the whole contour table) and the semantic vertices (nose, eyes, ears,
fingertips); the joints are those of the full model. That makes one forward pass cheap enough
for tens of optimizer iterations per frame.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ...body.models import SMPLXModel
from ...body.skeleton import JOINT
from . import correspondence as cor


def _semantic_local_ids(model: SMPLXModel) -> dict[str, int]:
    """Semantic vertex name -> this model's vertex index (absent: not in the cut mesh)."""
    ids = model.data.vertex_ids
    base = np.arange(model.num_vertices) if ids is None else np.asarray(ids)
    where = {int(v): i for i, v in enumerate(base)}
    return {name: where[v] for name, v in cor.SMPLX_SEMANTIC_VERTEX_IDS.items() if v in where}


class BodyKeypoints(torch.nn.Module):
    """`forward(params) -> [B, K, 3]` model-space keypoints (NaN where the model has none) and
    `available` [K] bool: the keypoints this model can produce."""

    def __init__(self, model: SMPLXModel, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        data = model.data
        semantic = _semantic_local_ids(model)
        needed = [data.faces[data.lmk_faces].ravel()] if data.lmk_faces is not None else []
        if data.dynamic_lmk_faces is not None:
            needed.append(data.faces[data.dynamic_lmk_faces].ravel())
        needed.append(np.array(sorted(semantic.values()), dtype=np.int64))
        keep = np.unique(np.concatenate(needed))
        sub = data.subset(keep)
        self.model = SMPLXModel(sub, dtype=dtype, cache=False, face_contour=True,
                                hand_pca=model.hand_pca, flat_hand_mean=model.flat_hand_mean)
        self.has_contour = self.model.face_contour
        remap = {int(old): new for new, old in enumerate(keep)}
        sub_semantic = {name: remap[i] for name, i in semantic.items()}
        self.num_landmarks = 0 if data.lmk_faces is None else len(data.lmk_faces)
        # Gather table into [joints(55) | vertices(V') | landmarks(L)]; -1: unavailable.
        n_j, n_v = len(data.parents), len(keep)
        table = np.full(cor.NUM_KEYPOINTS, -1, dtype=np.int64)
        if self.num_landmarks == 51:  # iBUG 17..67 static, then the 17-point contour
            table[cor.FACE_SLICE][17:] = n_j + n_v + np.arange(51)
            if self.has_contour:
                table[cor.FACE_SLICE][:17] = n_j + n_v + 51 + np.arange(17)
        elif self.num_landmarks == 68:
            table[cor.FACE_SLICE] = n_j + n_v + np.arange(68)
        for side, sl in (("left", cor.LEFT_HAND_SLICE), ("right", cor.RIGHT_HAND_SLICE)):
            for k, name in enumerate(cor.HAND_MP_TO_SMPLX):
                if name.startswith("tip:"):
                    vid = sub_semantic.get(side[0] + name[4:])
                    table[sl.start + k] = -1 if vid is None else n_j + vid
                else:
                    table[sl.start + k] = JOINT[f"{side}_{name}"]
        for k, name in enumerate(cor.POSE_MP_TO_SMPLX):
            if name is None:
                continue
            kind, key = name.split(":")
            if kind == "joint":
                table[cor.POSE_SLICE.start + k] = JOINT[key]
            elif key in sub_semantic:
                table[cor.POSE_SLICE.start + k] = n_j + sub_semantic[key]
        self.register_buffer("table", torch.as_tensor(np.maximum(table, 0)), persistent=False)
        self.register_buffer("available", torch.as_tensor(table >= 0), persistent=False)

    def forward(self, params: dict[str, Tensor]) -> Tensor:
        out = self.model(params)
        parts = [out.joints, out.vertices]
        if out.landmarks is not None:
            parts.append(out.landmarks)
        points = torch.cat(parts, dim=1)[:, self.table]  # [B, K, 3]
        return torch.where(self.available[None, :, None], points, torch.nan)
