"""EWA projection of 3D Gaussians to screen-space conics (pure PyTorch, differentiable).

gsplat / 3DGS conventions (``gsplat/cuda/_torch_impl.py: _fully_fused_projection``):

* world -> camera with the 4x4 view matrix; ``depth`` is camera-space z. Gaussians with
  ``z <= near`` or ``z >= far`` are culled (radius 0).
* the Jacobian of the pinhole projection is evaluated at the mean with x/z and y/z clamped to
  the frustum widened by 30% of the half-FOV tangents on each side (``lim = (W - cx) / fx +
  0.3 * tan_fovx``: 1.3 x the half-FOV tangent for a centred principal point), which keeps
  off-screen Gaussians from blowing up;
* ``cov2d = J W Sigma W^T J^T + eps2d * I`` (the 0.3 px low-pass dilation); with
  ``antialiased`` the opacity is scaled by ``sqrt(det(cov2d - eps2d I) / det(cov2d))``;
* ``conic = cov2d^-1`` stored as (a, b, c) = (inv[0, 0], inv[0, 1], inv[1, 1]);
* ``radius = ceil(3 * sqrt(lambda_max))`` pixels; Gaussians with a non-positive determinant
  or whose radius box misses the image get radius 0.

Absurd but finite Gaussians are culled before any product can overflow: a projected mean
farther than ``MAX_SCREEN_PX`` from the origin, a footprint bound ``f / z (1 + lim) max(scale)``
above ``MAX_BOUND_PX``, a 2D standard deviation above ``max_sigma_px`` (``MAX_SIGMA_PX``), or a
conic that is not positive definite in the working precision. What passes keeps every later
quantity (radius, tile range, pixel offsets) small enough for float32 and int32.

Culled rows stay finite (means, conics and gradients): divisions use guarded denominators and
absurd rows are replaced before the products, so no NaN leaks through ``torch.where`` in the
backward pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .contract import (
    EIG_FLOOR,
    EPS2D,
    FAR_PLANE,
    FRUSTUM_MARGIN,
    MAX_BOUND_PX,
    MAX_SCREEN_PX,
    MAX_SIGMA_PX,
    NEAR_PLANE,
    RADIUS_SIGMAS,
)

__all__ = [
    "Projected",
    "check_finite",
    "covariance_3d",
    "depth_key",
    "project_gaussians",
    "quat_to_rotmat",
]

_QUAT_EPS = 1e-12
_QUAT_TINY = 1e-30  # floor of the max-abs rescale in quat_to_rotmat


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities (all [N, ...], culled rows have ``radii == 0``)."""

    means2d: Tensor    # [N, 2] pixels, gsplat convention (pixel centres at +0.5)
    conics: Tensor     # [N, 3] (a, b, c) of the inverse 2D covariance
    depths: Tensor     # [N] camera-space z
    radii: Tensor      # [N] int32, 3-sigma radius in pixels, 0 = culled
    opacities: Tensor  # [N] after the antialiasing compensation (if any)
    valid: Tensor      # [N] bool, radii > 0

    @property
    def num_visible(self) -> int:
        return int(self.valid.sum())


def check_finite(**tensors: Tensor) -> None:
    """Raise ``ValueError`` naming the first input holding NaN or Inf."""
    for name, t in tensors.items():
        if t is None or not t.numel():
            continue
        # NaN / Inf propagate through a sum, so a finite sum proves all are finite (and is
        # ~30x cheaper than isfinite().all()); a non-finite one may be overflow: check
        if not bool(torch.isfinite(t.detach().sum())) and not bool(torch.isfinite(t).all()):
            raise ValueError(f"rasterizer input {name!r} contains NaN or Inf values")


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """(w, x, y, z) quaternions [N, 4] -> rotation matrices [N, 3, 3]; normalised here, a zero
    quaternion gives the identity."""
    # rescaled by the largest component first, so the norm of a huge quaternion cannot
    # overflow (float32 squares overflow above ~1.8e19)
    amax = quats.detach().abs().amax(-1, keepdim=True)  # [N, 1]
    q1 = quats / amax.clamp_min(_QUAT_TINY)
    n1 = q1.norm(dim=-1, keepdim=True)
    ok = amax * n1 > _QUAT_EPS
    unit = torch.where(ok, q1 / n1.clamp_min(_QUAT_EPS), torch.zeros_like(quats))
    w, x, y, z = unit.unbind(-1)  # zero quaternion -> all zero -> identity below
    R = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1)
    return R.reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariance ``R S S R^T`` [N, 3, 3] from quaternions [N, 4] and scales [N, 3]."""
    M = quat_to_rotmat(quats) * scales[:, None, :]  # [N, 3, 3] = R @ diag(s)
    return M @ M.transpose(-1, -2)


def project_gaussians(
    means: Tensor,       # [N, 3]
    quats: Tensor,       # [N, 4]
    scales: Tensor,      # [N, 3]
    opacities: Tensor,   # [N]
    viewmat: Tensor,     # [4, 4] world -> camera
    K: Tensor,           # [3, 3]
    width: int,
    height: int,
    near: float = NEAR_PLANE,
    antialiased: bool = False,
    *,
    far: float = FAR_PLANE,
    eps2d: float = EPS2D,
    max_sigma_px: float = MAX_SIGMA_PX,
    validate: bool = True,
) -> Projected:
    """Project Gaussians to the image (see the module docstring for the conventions).

    ``validate`` checks the inputs for NaN/Inf (``ValueError``); the render entries check once
    themselves (:mod:`checks`) and pass ``False``.
    """
    if validate:
        check_finite(means=means, quats=quats, scales=scales, opacities=opacities,
                     viewmat=viewmat, K=K)
    dtype = means.dtype
    viewmat = viewmat.to(dtype)
    K = K.to(dtype)
    n = means.shape[0]
    Rw, tw = viewmat[:3, :3], viewmat[:3, 3]
    means_c = means @ Rw.T + tw  # [N, 3]
    tz_raw = means_c[:, 2]
    # camera-space factor Mc = Rw R S (cov_c = Mc Mc^T), as one [3N, 3] x [3, 3] product;
    # P[n, k] is column k of Mc[n] (batched 3x3 matmuls are slow on CPU)
    M = quat_to_rotmat(quats) * scales[:, None, :]  # [N, 3, 3] = R diag(s)
    P = (M.transpose(1, 2).reshape(-1, 3) @ Rw.T).reshape(n, 3, 3)

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    margin_x, margin_y = FRUSTUM_MARGIN * tan_fovx, FRUSTUM_MARGIN * tan_fovy
    lim_x_pos, lim_x_neg = (width - cx) / fx + margin_x, cx / fx + margin_x
    lim_y_pos, lim_y_neg = (height - cy) / fy + margin_y, cy / fy + margin_y

    sane = _sane_rows(means_c, scales, K, (lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg),
                      near, far)
    # culled rows get harmless stand-ins before any product, so nothing overflows forward and
    # where() passes them zero gradients backward
    means_c = torch.where(sane[:, None], means_c, means_c.new_tensor([0.0, 0.0, 1.0]))
    P = torch.where(sane[:, None, None], P, torch.zeros_like(P))
    tx, ty, tz = means_c.unbind(-1)  # [N]
    in_depth = sane
    tz_s = torch.where(in_depth, tz, torch.ones_like(tz))  # guarded denominator
    u = torch.maximum(torch.minimum(tx / tz_s, lim_x_pos), -lim_x_neg)  # clamped x / z
    v = torch.maximum(torch.minimum(ty / tz_s, lim_y_pos), -lim_y_neg)
    # J = [[fx / z, 0, -fx u / z], [0, fy / z, -fy v / z]]; T = J Mc [N, 2, 3] row by row
    inv_z = (1.0 / tz_s)[:, None]
    T0 = (fx * inv_z) * (P[:, :, 0] - u[:, None] * P[:, :, 2])  # [N, 3]
    T1 = (fy * inv_z) * (P[:, :, 1] - v[:, None] * P[:, :, 2])
    cov2d_00, cov2d_01, cov2d_11 = (T0 * T0).sum(-1), (T0 * T1).sum(-1), (T1 * T1).sum(-1)

    means2d = (means_c @ K[:2].T) / tz_s[:, None]  # [N, 2] = (K x)[:2] / z

    c00, c01, c11 = cov2d_00, cov2d_01, cov2d_11
    det_orig = c00 * c11 - c01 * c01
    c00, c11 = c00 + eps2d, c11 + eps2d
    det = c00 * c11 - c01 * c01
    valid = in_depth & (det > 0) & torch.isfinite(det)
    det_s = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c11 / det_s, -c01 / det_s, c00 / det_s], dim=-1)  # [N, 3]
    with torch.no_grad():  # positive definite as stored, or the kernels' extents break down
        ca, cb, cc = conics.unbind(-1)
        valid = valid & (ca > 0) & (cc > 0) & (ca * cc - cb * cb > 0)
    conics = torch.where(valid[:, None], conics, torch.zeros_like(conics))

    if antialiased:
        # sqrt(max(r, 0)) with a zero gradient where r <= 0 (sqrt's own is Inf at 0: NaN)
        ratio = det_orig / det_s
        pos = ratio > 0
        comp = torch.where(pos, torch.sqrt(torch.where(pos, ratio, torch.ones_like(ratio))),
                           torch.zeros_like(ratio))
        opacities = opacities * torch.where(valid, comp, torch.zeros_like(comp))

    with torch.no_grad():
        b = 0.5 * (c00 + c11)
        lam_max = b + torch.sqrt(torch.clamp_min(b * b - det, EIG_FLOOR))
        radius = torch.ceil(RADIUS_SIGMAS * torch.sqrt(lam_max.clamp_min(0.0)))
        mx, my = means2d[:, 0], means2d[:, 1]
        inside = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) \
            & (my - radius < height)
        keep = valid & inside & (radius > 0) & (lam_max <= max_sigma_px * max_sigma_px)
        radius = torch.where(keep, radius, torch.zeros_like(radius))
        radii = radius.clamp_max(2**30).to(torch.int32)

    depths = torch.where(sane, tz_raw, torch.zeros_like(tz))  # culled: 0, never Inf
    return Projected(means2d=means2d, conics=conics, depths=depths, radii=radii,
                     opacities=opacities, valid=radii > 0)


def _sane_rows(means_c: Tensor, scales: Tensor, K: Tensor, lims: tuple, near: float,
               far: float) -> Tensor:
    """[N] bool: in the depth range, the projected mean within ``MAX_SCREEN_PX`` and the
    footprint bound within ``MAX_BOUND_PX``; evaluated in float64 so that the test itself
    cannot overflow (NaN compares false: culled)."""
    with torch.no_grad():
        m = means_c.detach().double()
        k = K.detach().double()
        x, y, z = m.unbind(-1)
        zs = torch.where(z > 0, z, torch.ones_like(z))
        mx = (k[0, 0] * x + k[0, 1] * y + k[0, 2] * z) / zs
        my = (k[1, 1] * y + k[1, 2] * z) / zs
        f = torch.maximum(k[0, 0].abs(), k[1, 1].abs())
        lim = 1.0 + torch.stack([v.detach().double() for v in lims]).abs().max()
        s_max = scales.detach().double().abs().amax(-1)
        bound = f / zs * lim * s_max
        return (z > near) & (z < far) & (mx.abs() <= MAX_SCREEN_PX) \
            & (my.abs() <= MAX_SCREEN_PX) & (bound <= MAX_BOUND_PX)


def depth_key(means: Tensor, viewmat) -> Tensor:
    """[N] float64 camera z, the front-to-back sort key of every backend: formed element by
    element in float64 in one fixed order from the means as given and the float64 view
    matrix, so each backend gets the same bits and breaks no near-tie differently (a key
    rounded to float32 turns pairs 5e-8 m apart into ties)."""
    m = means.detach().double()
    v = torch.as_tensor(viewmat, dtype=torch.float64, device=m.device)
    return m[:, 0] * v[2, 0] + m[:, 1] * v[2, 1] + m[:, 2] * v[2, 2] + v[2, 3]

