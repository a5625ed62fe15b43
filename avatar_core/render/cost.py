"""What a frame costs, known before any per-pair allocation: its (Gaussian, tile) pairs.

Every backend composites a splat in each 16 px tile of its radius box (gsplat's
``isect_tiles``: ``floor((m - r) / 16)`` up to ``ceil((m + r) / 16)``, clipped to the image;
the cpu backend then leaves out the tiles where the splat cannot reach ``alpha >= 1/255``, so
it never does more). Those pairs are what the tile lists allocate (4 to ~100 bytes each,
by backend), what the depth sort orders and what compositing walks, so their number is the
frame's cost. It is counted here from the projection alone, in O(N) and with no per-pair
memory: :func:`tile_pairs` is the torch reference, :func:`tile_pairs_np` its numba twin (the
cpu backend's no-gradient path); a test checks that they agree and that the torch
reference's lists hold exactly that many pairs.

A request's ``max_tile_pairs`` (None: the contract's ``MAX_TILE_PAIRS``) bounds it: the
quality budget (:mod:`budget`) drops the least important splats until the pairs fit, so an
over-budget frame is degraded, never an unbounded allocation. Compositors handed lists over
their bound directly (``bin_tiles``, ``isect_tiles``) raise :class:`RenderTooExpensive`
before they allocate.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from .camera import Camera
from .contract import MAX_TILE_PAIRS, NEAR_PLANE, TILE_SIZE
from .projection import project_gaussians
from .types import GaussianSet

__all__ = ["RenderTooExpensive", "check_pairs", "clamp_int", "frame_tile_pairs", "pair_bound",
           "tile_box", "tile_pairs", "tile_pairs_np"]

_TS = TILE_SIZE


class RenderTooExpensive(ValueError):
    """A frame would composite more (Gaussian, tile) pairs than its bound allows; raised
    before anything per pair is allocated."""


def pair_bound(max_tile_pairs: int | None) -> int:
    """The bound a request's ``max_tile_pairs`` sets (None: ``MAX_TILE_PAIRS``)."""
    return MAX_TILE_PAIRS if max_tile_pairs is None else int(max_tile_pairs)


def check_pairs(n_pairs: int, max_pairs: int | None, width: int, height: int) -> None:
    """:class:`RenderTooExpensive` when ``n_pairs`` exceeds ``pair_bound(max_pairs)``."""
    bound = pair_bound(max_pairs)
    if n_pairs > bound:
        raise RenderTooExpensive(
            f"a {width}x{height} frame of these splats needs {n_pairs} (Gaussian, tile) "
            f"pairs, more than the bound of {bound}")


def tile_pairs(means2d: Tensor, radii: Tensor, width: int, height: int,
               tile_size: int = TILE_SIZE) -> Tensor:
    """[N] int64: the tiles each splat's radius box covers in a ``width`` x ``height``
    image (0 where culled, ``radii <= 0``, or the mean is not finite). ``means2d`` [N, 2]
    pixels, ``radii`` [N] (``Projected``'s)."""
    tw, th = -(-width // tile_size), -(-height // tile_size)
    with torch.no_grad():
        m = means2d.detach().double()  # [N, 2]; float64 so the tile range is exact
        r = radii.detach().double()[:, None]  # [N, 1]
        ok = (radii > 0) & torch.isfinite(m).all(-1)  # [N]
        m = torch.where(ok[:, None], m, torch.zeros_like(m))
        lim = torch.tensor([tw, th], dtype=m.dtype, device=m.device)
        lo = torch.minimum(torch.floor((m - r) / tile_size).clamp_min(0), lim)  # [N, 2]
        hi = torch.minimum(torch.ceil((m + r) / tile_size).clamp_min(0), lim)
        n = ((hi - lo).clamp_min(0)).prod(-1).long()  # [N]
        return torch.where(ok, n, torch.zeros_like(n))


@njit(cache=True, inline="always")
def clamp_int(x, lo, hi):
    """int(x) clamped to [lo, hi], NaN giving lo: clamped while still a float, because a
    float -> int cast of NaN, Inf or anything out of range is undefined (LLVM poison)."""
    if not x >= lo:
        return lo
    if x > hi:
        return hi
    return int(x)


@njit(cache=True, inline="always")
def tile_box(mx, my, r, tw, th):
    """gsplat's tile range [x0, x1) x [y0, y1) of a splat with radius r (np.floor / np.ceil:
    math's return ints, converted before any clamp)."""
    x0 = clamp_int(np.floor((mx - r) / _TS), 0, tw)
    x1 = clamp_int(np.ceil((mx + r) / _TS), 0, tw)
    y0 = clamp_int(np.floor((my - r) / _TS), 0, th)
    y1 = clamp_int(np.ceil((my + r) / _TS), 0, th)
    return x0, x1, y0, y1


@njit(parallel=True, cache=True)
def _pairs_kernel(means2d, radii, width, height, out):
    tw, th = (width + _TS - 1) // _TS, (height + _TS - 1) // _TS
    for g in prange(means2d.shape[0]):
        mx, my = float(means2d[g, 0]), float(means2d[g, 1])
        out[g] = 0
        if radii[g] <= 0 or not (np.isfinite(mx) and np.isfinite(my)):
            continue
        x0, x1, y0, y1 = tile_box(mx, my, float(radii[g]), tw, th)
        out[g] = max(x1 - x0, 0) * max(y1 - y0, 0)


def tile_pairs_np(means2d: np.ndarray, radii: np.ndarray, width: int,
                  height: int) -> np.ndarray:
    """The numba twin of :func:`tile_pairs` (numpy in, [N] int64 out)."""
    out = np.empty(means2d.shape[0], np.int64)
    _pairs_kernel(means2d, radii, int(width), int(height), out)
    return out


def frame_tile_pairs(gaussians: GaussianSet, camera: Camera, antialiased: bool = False) -> int:
    """The (Gaussian, tile) pairs a frame of ``gaussians`` seen by ``camera`` would
    composite with no bound (projection and count only: nothing per pair is allocated). On
    CPU tensors the numba projection, elsewhere the torch reference; inputs are assumed
    finite (checked avatars)."""
    w, h = camera.width, camera.height
    if gaussians.means.device.type == "cpu":
        from .project_cpu import project_np

        def np32(t: Tensor) -> np.ndarray:
            return np.ascontiguousarray(t.detach().to(torch.float32).numpy())

        m2, _, _, radii, _ = project_np(np32(gaussians.means), np32(gaussians.quats),
                                        np32(gaussians.scales), np32(gaussians.opacities),
                                        camera.viewmat(), camera.K, w, h, NEAR_PLANE,
                                        antialiased)
        return int(tile_pairs_np(m2, radii, w, h).sum())
    viewmat, K = camera.to_torch(gaussians.means.device, gaussians.means.dtype)
    with torch.no_grad():
        p = project_gaussians(gaussians.means, gaussians.quats, gaussians.scales,
                              gaussians.opacities, viewmat, K, w, h, NEAR_PLANE, antialiased,
                              validate=False)
        return int(tile_pairs(p.means2d, p.radii, w, h).sum())
