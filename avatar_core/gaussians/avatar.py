"""The Gaussian avatar: Gaussians living in their parent triangle's frame.

Each Gaussian has a parent triangle, a local mean, a log-scale, a unit quaternion (w, x, y, z),
an opacity logit and SH coefficients (degree 0-3). World space is derived every frame from the
triangle frames (R, T, k) of the posed mesh (``binding``): mean' = k R mean + T,
rotation' = R rotation, scale' = k scale. It is never stored, except by the .ply export.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from ..render.sh import rgb_to_sh0, sh_degree_from_bases
from ..render.types import GaussianSet
from .binding import FaceFrames, bind_gaussians, bind_gaussians_torch

# A fresh Gaussian is a thin disc on its triangle: in-plane sigma 0.4 k, 0.05 k along the normal.
INIT_LOCAL_SCALE = (0.4, 0.4, 0.05)
INIT_OPACITY = 0.9
DEFAULT_COLOR = (0.7, 0.7, 0.7)


@dataclass
class GaussianAvatar:
    parents: Tensor         # [N] long, triangle index
    local_means: Tensor     # [N, 3]
    log_scales: Tensor      # [N, 3]
    quats: Tensor           # [N, 4] (w, x, y, z)
    opacity_logits: Tensor  # [N]
    sh: Tensor              # [N, K, 3], K = (degree + 1) ** 2

    def __post_init__(self) -> None:
        n = self.parents.shape[0]
        shapes = {"parents": (n,), "local_means": (n, 3), "log_scales": (n, 3), "quats": (n, 4),
                  "opacity_logits": (n,)}
        for name, shape in shapes.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"GaussianAvatar.{name}: expected shape {list(shape)}, "
                                 f"got {list(getattr(self, name).shape)}")
        if self.sh.dim() != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3 or \
                self.sh.shape[1] not in (1, 4, 9, 16):
            raise ValueError(f"GaussianAvatar.sh: expected [N, K in (1, 4, 9, 16), 3], "
                             f"got {list(self.sh.shape)}")

    @property
    def num(self) -> int:
        return self.parents.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[1])

    def tensors(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to(self, device=None, dtype=None) -> GaussianAvatar:
        out = {}
        for name, t in self.tensors().items():
            out[name] = t.to(device=device) if name == "parents" else t.to(device, dtype)
        return GaussianAvatar(**out)

    @classmethod
    def from_mesh(cls, faces: np.ndarray | Tensor, vertex_colors: np.ndarray | None = None,
                  *, texture: np.ndarray | None = None, uvs: np.ndarray | None = None,
                  face_uvs: np.ndarray | None = None, sh_degree: int = 3,
                  dtype: torch.dtype = torch.float32) -> GaussianAvatar:
        """One Gaussian per triangle at its local origin (the centroid), coloured from the
        texture at the triangle's mean UV when given (`texture` [H, W, 3] in [0, 1], `uvs`
        [T, 2] with v up, `face_uvs` [F, 3] as SMPL-X's `vt`/`ft`), else by the mean of its
        corners' vertex colours, else grey."""
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
        faces = torch.as_tensor(np.asarray(faces), dtype=torch.long)
        n = faces.shape[0]
        if texture is not None:
            if uvs is None or face_uvs is None or len(face_uvs) != n:
                raise ValueError("a texture needs uvs and one face_uvs row per face")
            rgb = torch.as_tensor(sample_texture(texture, np.asarray(uvs)[np.asarray(face_uvs)]
                                                 .mean(1)), dtype=dtype)
        elif vertex_colors is None:
            rgb = torch.tensor(DEFAULT_COLOR, dtype=dtype).expand(n, 3)
        else:
            colors = torch.as_tensor(np.asarray(vertex_colors), dtype=dtype)
            rgb = colors[faces].mean(1)  # [N, 3]
        sh = torch.zeros(n, (sh_degree + 1) ** 2, 3, dtype=dtype)
        sh[:, 0] = rgb_to_sh0(rgb)
        logit = float(np.log(INIT_OPACITY / (1 - INIT_OPACITY)))
        return cls(parents=torch.arange(n), local_means=torch.zeros(n, 3, dtype=dtype),
                   log_scales=torch.log(torch.tensor(INIT_LOCAL_SCALE, dtype=dtype)).expand(
                       n, 3).clone(),
                   quats=torch.tensor([1.0, 0, 0, 0], dtype=dtype).expand(n, 4).clone(),
                   opacity_logits=torch.full((n,), logit, dtype=dtype), sh=sh)


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup. texture [H, W, 3], uv [N, 2] in [0, 1] (v up) -> [N, 3]."""
    h, w = texture.shape[:2]
    x = np.clip(uv[:, 0], 0, 1) * (w - 1)
    y = (1 - np.clip(uv[:, 1], 0, 1)) * (h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    tex = np.asarray(texture, dtype=np.float64)
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def to_world(avatar: GaussianAvatar, rot: Tensor, trans: Tensor, scale: Tensor) -> GaussianSet:
    """World-space Gaussians from triangle frames rot [F, 3, 3], trans [F, 3], scale [F]
    (binding's torch reference)."""
    world = bind_gaussians_torch(FaceFrames.of_frames(rot, trans, scale), avatar.parents,
                                 avatar.local_means, avatar.quats, torch.exp(avatar.log_scales))
    return _gaussian_set(avatar, *world)


def pose_gaussians(avatar: GaussianAvatar, vertices: Tensor, faces: Tensor, *,
                   backend: str = "auto") -> GaussianSet:
    """World-space Gaussians on a posed mesh. vertices [V, 3], faces [F, 3]; ``backend`` as
    :func:`binding.bind_gaussians` ("auto": the numba twin on the CPU without gradients, else
    the differentiable torch reference)."""
    world = bind_gaussians(vertices, faces, avatar.parents, avatar.local_means, avatar.quats,
                           torch.exp(avatar.log_scales), backend=backend)
    return _gaussian_set(avatar, *world)


def _gaussian_set(avatar: GaussianAvatar, means: Tensor, quats: Tensor, scales: Tensor
                  ) -> GaussianSet:
    return GaussianSet(means=means, quats=quats, scales=scales,
                       opacities=torch.sigmoid(avatar.opacity_logits), sh=avatar.sh)
