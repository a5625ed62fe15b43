"""Value ranges of a Gaussian avatar: what any trained avatar satisfies, with a wide margin.

Finite is not enough: a package with log-scales of 80 is finite and describes splats of 10^34
triangle sizes, each a veil over the whole picture. Loaders check ranges before an avatar is
stored or served (:func:`check_gaussian_ranges`), so an absurd package is refused up front,
with the field, the offending value and the allowed range in the message.

The defaults, and why they hold for trained avatars (``avatar_core.train``; measured: a
1,500-iteration demo-preset run ends with log-scales in [-14.6, -0.5], local-mean norms up to
4.3, opacity logits in [-7.6, 13.0], SH in [-1.9, 4.0] and quaternion norms in [0.36, 1.24]):

* log-scales (triangle-local, units of the triangle's size k): a fresh Gaussian starts at
  log 0.4 and log 0.05 (-0.9, -3.0); splits divide by 1.6 and densification prunes splats
  wider than a tenth of the scene, a few k; small ones keep shrinking in long runs (and are
  harmless). Allowed: [-50, 6] (e^6 ~ 400 triangle sizes).
* local means (units of k): start at the centroid (0) and stay near the surface, within a
  few k. Allowed: norm <= 1000.
* opacity logits: start at logit(0.9) = 2.2, reset to logit(0.01) = -4.6; float32 sigmoid
  saturates at +17 (its gradient is then 0), while faint ones may drift down in long runs.
  Allowed: |logit| <= 1000.
* SH coefficients: a colour in [0, 1] is a DC of at most 1.8, higher bands are small.
  Allowed: |c| <= 100.
* quaternions (stored unnormalised): Adam moves their norm slowly from 1. Allowed norm:
  [1e-6, 1e6] (the zero quaternion, the identity by convention, is allowed too).
* count: the trainer's default cap is 200,000 (``DensifyConfig.max_gaussians``). Allowed:
  1,000,000.

Those ranges are in the avatar's own units, so each is loose on purpose; what they allow
together can still be absurd for the body they dress: 16k splats of log-scale 6 are in range,
each hundreds of metres wide, and a frame of them costs a renderer seconds and gigabytes.
:func:`check_splat_extent` ties the splats' size to the body's: at the rest pose (world
units), no Gaussian's 3-sigma radius (3 x its largest standard deviation, the rasterizer's
extent, ``RADIUS_SIGMAS``) may exceed ``max_splat_body_ratio`` times the diagonal of the rest
mesh's bounding box. Default 1.0: a splat as large as the whole body. Trained splats are far
smaller (densification prunes any wider than a tenth of the scene; the synthetic avatar's
largest is 0.11 m against a 1.9 m diagonal).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..render.contract import RADIUS_SIGMAS

__all__ = ["GaussianRanges", "RangeError", "check_gaussian_ranges", "check_splat_extent"]


class RangeError(ValueError):
    """A Gaussian parameter outside its allowed range (the message names which)."""


@dataclass(frozen=True)
class GaussianRanges:
    """Allowed value ranges of an avatar's Gaussians (see the module docstring)."""

    max_gaussians: int = 1_000_000
    log_scale_min: float = -50.0
    log_scale_max: float = 6.0
    max_local_mean_norm: float = 1e3
    max_abs_opacity_logit: float = 1000.0
    max_abs_sh: float = 100.0
    quat_norm_min: float = 1e-6   # below it (and above 0) the rotation is numerically noise
    quat_norm_max: float = 1e6
    # at rest, a splat's 3-sigma radius over the rest mesh's bounding-box diagonal
    max_splat_body_ratio: float = 1.0


def check_gaussian_ranges(*, parents: Tensor, local_means: Tensor, log_scales: Tensor,
                          quats: Tensor, opacity_logits: Tensor, sh: Tensor,
                          num_faces: int | None = None,
                          ranges: GaussianRanges | None = None) -> None:
    """Raise :class:`RangeError` naming the first field outside ``ranges`` (defaults:
    :class:`GaussianRanges`), its worst value, the Gaussian's index and the allowed range.
    NaN and Inf fail every range. ``num_faces``: parents must index a mesh of this many."""
    r = ranges or GaussianRanges()
    n = int(parents.shape[0])
    if n > r.max_gaussians:
        raise RangeError(f"{n} Gaussians, more than the allowed {r.max_gaussians}")
    if n == 0:
        return
    if num_faces is not None:
        _check("parents", parents, 0, num_faces - 1)
    _check("log_scales", log_scales, r.log_scale_min, r.log_scale_max)
    _check("local_means (norm)", local_means.double().norm(dim=-1), 0.0,
           r.max_local_mean_norm)  # float64: a norm of float32 values can overflow
    _check("opacity_logits", opacity_logits, -r.max_abs_opacity_logit,
           r.max_abs_opacity_logit)
    _check("sh", sh, -r.max_abs_sh, r.max_abs_sh)
    norms = quats.double().norm(dim=-1)
    _check("quats (norm)", torch.where(norms == 0, torch.ones_like(norms), norms),
           r.quat_norm_min, r.quat_norm_max)


def check_splat_extent(scales: Tensor, vertices: Tensor,
                       ranges: GaussianRanges | None = None) -> None:
    """Raise :class:`RangeError` when a Gaussian at the rest pose is larger than the body:
    its 3-sigma radius (``scales`` [N, 3], world standard deviations) above
    ``ranges.max_splat_body_ratio`` times the bounding-box diagonal of the rest mesh
    (``vertices`` [V, 3]). Non-finite scales fail too."""
    r = ranges or GaussianRanges()
    if not scales.shape[0]:
        return
    v = vertices.detach().double()
    diagonal = float((v.amax(0) - v.amin(0)).norm()) if v.shape[0] else 0.0
    extent = RADIUS_SIGMAS * scales.detach().double().abs().amax(-1)  # [N]
    limit = r.max_splat_body_ratio * diagonal
    bad = torch.nonzero(~(extent <= limit)).squeeze(1)  # NaN fails
    if not bad.numel():
        return
    worst = int(bad[int(torch.argmax(torch.nan_to_num(extent[bad], nan=float("inf"))))])
    raise RangeError(
        f"Gaussian {worst} reaches {float(extent[worst]):.4g} m from its centre at the rest "
        f"pose (3-sigma radius), larger than the body: the allowed maximum is "
        f"max_splat_body_ratio "
        f"{r.max_splat_body_ratio:g} x the rest mesh's {diagonal:.3g} m bounding-box "
        f"diagonal = {limit:.3g} m ({bad.numel()} Gaussians exceed it)")


def _check(field: str, values: Tensor, lo: float, hi: float) -> None:
    v = values.detach().reshape(values.shape[0], -1)
    bad = torch.nonzero(~((v >= lo) & (v <= hi)))  # [B, 2]; NaN is never in range
    if not bad.numel():
        return
    vals = v[bad[:, 0], bad[:, 1]].double()
    outside = torch.nan_to_num(torch.maximum(vals - hi, lo - vals), nan=float("inf"))
    row, col = (int(i) for i in bad[int(torch.argmax(outside))])
    where = f"Gaussian {row}" + ("" if v.shape[1] == 1 else f", column {col}")
    raise RangeError(f"{field} = {float(v[row, col]):.6g} at {where} is outside the allowed "
                     f"range [{lo:g}, {hi:g}]")
