"""Synthetic Gaussian scenes for tests and benchmarks (no trained avatar needed).

* :func:`random_scene`: Gaussians scattered in a box in front of the camera.
* :func:`avatar_like_scene`: Gaussians on the surface of an upper body made of ellipsoids
  (torso, head, neck, arms, hands), flattened along the surface normal, a few mm to 2 cm
  across, mostly opaque, degree-3 SH: what a trained avatar looks like to the rasterizer.
  :func:`avatar_camera` frames it from 2 m with a 30 degree field of view.
"""

from __future__ import annotations

import numpy as np
import torch

from ..rotations import matrix_to_quaternion
from .camera import Camera, look_at
from .sh import rgb_to_sh0
from .types import GaussianSet

__all__ = ["avatar_camera", "avatar_like_scene", "random_scene"]

# (centre, semi-axes) of the body parts, metres; y up, +z toward the viewer
_BODY = [
    ((0.00, 0.05, 0.00), (0.17, 0.28, 0.11)),    # torso
    ((0.00, 0.36, 0.00), (0.055, 0.07, 0.055)),  # neck
    ((0.00, 0.50, 0.01), (0.085, 0.115, 0.10)),  # head
    ((-0.24, 0.12, 0.00), (0.055, 0.16, 0.055)),  # upper arms
    ((0.24, 0.12, 0.00), (0.055, 0.16, 0.055)),
    ((-0.27, -0.17, 0.04), (0.045, 0.14, 0.045)),  # forearms
    ((0.27, -0.17, 0.04), (0.045, 0.14, 0.045)),
    ((-0.28, -0.35, 0.07), (0.035, 0.06, 0.02)),   # hands
    ((0.28, -0.35, 0.07), (0.035, 0.06, 0.02)),
]


def avatar_like_scene(n: int, seed: int = 0, sh_degree: int = 3,
                      dtype: torch.dtype = torch.float32) -> GaussianSet:
    """``n`` Gaussians on an ellipsoid upper body (see the module docstring)."""
    rng = np.random.default_rng(seed)
    centres = np.array([c for c, _ in _BODY])
    axes = np.array([a for _, a in _BODY])
    # parts get Gaussians in proportion to their (approximate) surface area
    p = 1.6
    area = 4 * np.pi * (((axes[:, 0] * axes[:, 1]) ** p + (axes[:, 0] * axes[:, 2]) ** p
                         + (axes[:, 1] * axes[:, 2]) ** p) / 3) ** (1 / p)
    part = rng.choice(len(_BODY), size=n, p=area / area.sum())
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    means = centres[part] + u * axes[part]  # [n, 3] on the surface
    normal = u / axes[part]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    t1 = np.cross(normal, rng.normal(size=(n, 3)))
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normal, t1)
    frames = torch.as_tensor(np.stack([t1, t2, normal], axis=-1))
    quats = matrix_to_quaternion(frames).numpy()  # local z = normal
    size = np.exp(rng.uniform(np.log(0.003), np.log(0.02), size=(n, 1)))  # 3 mm .. 2 cm
    scales = size * np.concatenate([rng.uniform(0.6, 1.0, (n, 2)), rng.uniform(0.1, 0.3, (n, 1))],
                                   axis=1)
    opac = np.where(rng.random(n) < 0.85, rng.uniform(0.85, 1.0, n), rng.uniform(0.05, 0.85, n))
    skin = np.array([0.85, 0.62, 0.50])
    shirt = np.array([0.20, 0.35, 0.60])
    base = np.where((part == 0)[:, None] | (part == 3)[:, None] | (part == 4)[:, None], shirt,
                    skin)
    rgb = np.clip(base + rng.normal(0, 0.05, (n, 3)), 0, 1)
    k = (sh_degree + 1) ** 2
    sh = rng.normal(0, 0.05, (n, k, 3))
    sh[:, 0] = rgb_to_sh0(torch.as_tensor(rgb)).numpy()
    t = {name: torch.as_tensor(v, dtype=dtype) for name, v in
         dict(means=means, quats=quats, scales=scales, opacities=opac, sh=sh).items()}
    return GaussianSet(**t)


def avatar_camera(width: int = 512, height: int | None = None) -> Camera:
    """Front view from 2 m, 30 degree vertical FOV: the upper body fills the frame."""
    height = width if height is None else height
    return look_at((0.0, 0.08, 2.0), (0.0, 0.08, 0.0), width=width, height=height,
                   fov_y_deg=30.0)


def random_scene(n: int, seed: int = 0, sh_degree: int = 3, *, spread: float = 0.4,
                 scale: tuple[float, float] = (0.01, 0.08),
                 dtype: torch.dtype = torch.float32) -> GaussianSet:
    """``n`` random Gaussians around the origin (view them with a camera at ~+2.5 z):
    random rotations, anisotropic scales in ``scale``, opacities in (0, 1), random SH."""
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2
    lo, hi = scale
    return GaussianSet(
        means=(torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * spread,
        quats=torch.randn(n, 4, generator=g, dtype=torch.float64),
        scales=lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64),
        opacities=torch.rand(n, generator=g, dtype=torch.float64),
        sh=torch.randn(n, k, 3, generator=g, dtype=torch.float64) * 0.3,
    ) if dtype == torch.float64 else _cast(random_scene(n, seed, sh_degree, spread=spread,
                                                        scale=scale, dtype=torch.float64),
                                           dtype)


def _cast(g: GaussianSet, dtype: torch.dtype) -> GaussianSet:
    return GaussianSet(g.means.to(dtype), g.quats.to(dtype), g.scales.to(dtype),
                       g.opacities.to(dtype), g.sh.to(dtype))
