"""Posing an avatar: parameters -> posed upper-body mesh -> world-space Gaussians.

When the parameters have not changed since the last frame (only the camera moved), the posed
mesh and the world-space Gaussians are reused as they are; below that, the body model's own
stage cache reuses what an expression-only change leaves untouched.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..body.cache import StageCache
from ..body.model_data import load_smplx
from ..body.model_paths import BodyModelFiles
from ..body.params import SMPLXParams
from ..body.upper_body import UpperBodyModel, load_segmentation
from ..render.types import GaussianSet
from .avatar import GaussianAvatar, pose_gaussians
from .binding import bind_gaussians_numba, can_use_numba
from .package import AvatarPackage, BodyReference, faces_fingerprint


@dataclass
class PosedAvatar:
    vertices: Tensor       # [V, 3] posed upper-body mesh
    gaussians: GaussianSet


def _params_key(params: dict[str, Any]) -> bytes | None:
    """A digest of the parameter values, or None when they carry gradients (never cached)."""
    h = hashlib.blake2b(digest_size=16)
    for name in sorted(params):
        value = params[name]
        if value is None:
            continue
        if isinstance(value, Tensor):
            if value.requires_grad:
                return None
            value = value.detach().cpu().numpy()
        arr = np.ascontiguousarray(np.asarray(value, dtype=np.float64))
        h.update(name.encode())
        h.update(str(arr.shape).encode())
        h.update(arr.tobytes())
    return h.digest()


class AvatarAnimator:
    """Poses one avatar on one body model, frame after frame.

    ``cache``: the animator's own stage cache, so that animators sharing one (read-only) body
    model each keep theirs (a server's sessions); None: the body model's own."""

    def __init__(self, body_model: UpperBodyModel, avatar: GaussianAvatar,
                 betas: np.ndarray | None = None, cache: StageCache | None = None) -> None:
        if avatar.num and int(avatar.parents.max()) >= body_model.faces.shape[0]:
            raise ValueError("the avatar's parent triangles exceed the body model's faces")
        self.body_model = body_model
        self.cache = cache
        self.avatar = avatar.to(body_model.device, body_model.dtype)
        self.betas = None if betas is None else np.asarray(betas, dtype=np.float64)
        self.hits = self.misses = 0
        self._key: bytes | None = None
        self._last: PosedAvatar | None = None
        self._constants: tuple[tuple[int, int], Tensor, Tensor] | None = None

    def _scales_opacities(self) -> tuple[Tensor, Tensor]:
        """exp(log_scales) and sigmoid(opacity_logits): avatar constants, computed once (again
        only if someone changed the avatar's tensors in place since)."""
        a = self.avatar
        version = (a.log_scales._version, a.opacity_logits._version)
        if self._constants is None or self._constants[0] != version:
            with torch.no_grad():
                self._constants = (version, torch.exp(a.log_scales),
                                   torch.sigmoid(a.opacity_logits))
        return self._constants[1], self._constants[2]

    def _gaussians(self, vertices: Tensor) -> GaussianSet:
        a, faces = self.avatar, self.body_model.faces
        if not can_use_numba((a.parents, a.local_means, a.log_scales, a.quats,
                              a.opacity_logits), vertices, faces):
            return pose_gaussians(a, vertices, faces, backend="torch")  # autograd or CUDA
        scales, opacities = self._scales_opacities()
        means, quats, scales = bind_gaussians_numba(vertices, faces, a.parents, a.local_means,
                                                    a.quats, scales)
        return GaussianSet(means=means, quats=quats, scales=scales, opacities=opacities, sh=a.sh)

    def pose(self, params: SMPLXParams | dict[str, Any] | None = None) -> PosedAvatar:
        raw = params.to_dict() if isinstance(params, SMPLXParams) else dict(params or {})
        if self.betas is not None and raw.get("betas") is None:
            raw["betas"] = self.betas
        key = _params_key(raw)
        if key is not None and key == self._key and self._last is not None:
            self.hits += 1
            return self._last
        self.misses += 1
        out = self.body_model(raw, cache=self.cache)
        if out.vertices.shape[0] != 1:
            raise ValueError("the animator poses one frame at a time (batch 1)")
        vertices = out.vertices[0]
        posed = PosedAvatar(vertices, self._gaussians(vertices))
        self._key, self._last = key, posed
        return posed


def synthetic_package(model_dir: str | Path, identity: int = 0, *, sh_degree: int = 3,
                      seed: int = 0) -> tuple[AvatarPackage, UpperBodyModel]:
    """An untrained avatar on the synthetic upper body: one Gaussian per triangle, coloured by
    the identity's vertex colours. Returns the package and its body model."""
    files = BodyModelFiles(Path(model_dir))
    identities = files.identities()
    if not 0 <= identity < len(identities):
        raise ValueError(f"identity must be in [0, {len(identities)}), got {identity}")
    data = load_smplx(files.smplx_npz)
    model = UpperBodyModel(data, load_segmentation(files.segmentation, data.num_vertices))
    with np.load(identities[identity]) as ident:
        colors = ident["vertex_colors"][model.vertex_ids]
        betas, name = ident["betas"], str(ident["name"])
    faces = model.faces.cpu().numpy()
    avatar = GaussianAvatar.from_mesh(faces, colors, sh_degree=sh_degree)
    body = BodyReference(model=f"synthetic:seed{seed}", parts=list(model.keep_parts),
                         num_faces=len(faces), faces_sha256=faces_fingerprint(faces),
                         betas=[float(b) for b in betas])
    package = AvatarPackage(avatar=avatar, body=body, name=f"{name}-untrained",
                            metadata={"identity": identity, "trained": False})
    return package, model
