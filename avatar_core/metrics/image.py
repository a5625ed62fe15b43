"""Image metrics and losses: L1, PSNR, SSIM (and D-SSIM), optionally masked, differentiable.

Inputs are float images in [0, 1] with channels last, ``[H, W, C]`` or ``[B, H, W, C]``
(torch tensors or numpy arrays; C is usually 3). Values are not clipped: a render that
overshoots is measured as it is.

Batches and masks
-----------------
Each metric is computed per image and ``reduction='mean'`` averages the per-image values
(the 3DGS evaluation convention; ``'none'`` returns them, ``[B]``). ``mask`` is ``[H, W]``
(shared) or ``[B, H, W]``, bool or non-negative float weights; it weights pixels, and every
channel of a pixel alike. An image whose mask is all zero has no defined value: it gives NaN
(with a zero, finite gradient) and the batch mean skips it; the mean is NaN only when every
image is empty.

* ``l1``: mean |pred - target| over pixels and channels.
* ``psnr``: ``-10 log10(MSE)`` with data range 1. Identical images give ``+inf``, as
  scikit-image does; the batch mean is then ``+inf`` too. Not meant as a loss (use ``l1``).
* ``ssim``: Wang et al. 2004 as 3DGS and scikit-image compute it: an 11 x 11 Gaussian window
  with sigma 1.5 (separable, radius 5; scipy's ``truncate=3.5`` gives the same taps),
  ``K1 = 0.01``, ``K2 = 0.03``, population (not sample) variances, the SSIM map averaged
  over channels and pixels.

SSIM padding
------------
``padding='valid'`` (default) keeps only windows that lie wholly inside the image: the map is
``[H - 10, W - 10]``. This equals ``skimage.metrics.structural_similarity(a, b,
gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1,
channel_axis=-1)``, which filters with reflect padding and then crops 5 pixels per side, so
no padded value reaches the mean. Images must be at least 11 x 11.
``padding='same'`` zero-pads by 5 and averages the full ``[H, W]`` map: the numbers 3DGS's
``utils/loss_utils.ssim`` reports (they differ near the borders, where zeros enter the
windows).
A masked SSIM is the mean of the SSIM map under the mask, the map value at a pixel being
that of the window centred on it: windows still read the pixels around it, masked or not.
With ``'valid'`` the mask is cropped like the map, so a mask lying wholly within 5 pixels of
the border is empty (NaN).

Training loss
-------------
3DGS trains with ``(1 - lambda) * L1 + lambda * (1 - SSIM)``, lambda = 0.2
(``photometric_loss``). ``dssim_loss`` is the structural dissimilarity ``(1 - SSIM) / 2``
in [0, 1]; 3DGS's ``(1 - SSIM)`` term is twice it.
"""

from __future__ import annotations

from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from ._common import as_image_pair, as_mask, reduce_images, weighted_mean

__all__ = ["dssim_loss", "gaussian_kernel", "l1", "photometric_loss", "psnr", "ssim",
           "ssim_map"]

SSIM_SIGMA = 1.5
SSIM_RADIUS = 5  # 11 taps: int(3.5 * 1.5 + 0.5), scikit-image's window for sigma 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03
DSSIM_LAMBDA = 0.2  # 3DGS's lambda_dssim

Padding = Literal["valid", "same"]
Reduction = Literal["mean", "none"]


def l1(pred: Any, target: Any, mask: Any = None, *, reduction: Reduction = "mean") -> Tensor:
    """Mean absolute error over pixels and channels (masked: weighted by ``mask``)."""
    p, g, batched = as_image_pair(pred, target)
    weights = _weights(mask, p)
    per_image = weighted_mean((p - g).abs().mean(dim=-1), weights)  # [B]
    return reduce_images(per_image, reduction, batched)


def psnr(pred: Any, target: Any, mask: Any = None, *, reduction: Reduction = "mean") -> Tensor:
    """Peak signal-to-noise ratio in dB, data range 1; ``+inf`` for identical images."""
    p, g, batched = as_image_pair(pred, target)
    weights = _weights(mask, p)
    mse = weighted_mean((p - g).square().mean(dim=-1), weights)  # [B]
    return reduce_images(-10.0 * torch.log10(mse), reduction, batched)


def ssim(pred: Any, target: Any, mask: Any = None, *, padding: Padding = "valid",
         reduction: Reduction = "mean") -> Tensor:
    """Structural similarity (see the module docstring for the definition and padding)."""
    p, g, batched = as_image_pair(pred, target)
    weights = _weights(mask, p)
    smap = _ssim_map(p, g, padding)  # [B, H', W']
    if weights is not None and padding == "valid":
        r = SSIM_RADIUS
        weights = weights[:, r:-r, r:-r]  # the pixels at the centre of a whole window
    return reduce_images(weighted_mean(smap, weights), reduction, batched)


def ssim_map(pred: Any, target: Any, *, padding: Padding = "valid") -> Tensor:
    """The channel-averaged SSIM map, ``[B, H - 10, W - 10]`` (valid) or ``[B, H, W]`` (same);
    no batch axis for an unbatched input."""
    p, g, batched = as_image_pair(pred, target)
    smap = _ssim_map(p, g, padding)
    return smap if batched else smap[0]


def dssim_loss(pred: Any, target: Any, mask: Any = None, *,
               padding: Padding = "valid") -> Tensor:
    """Structural dissimilarity ``(1 - SSIM) / 2`` in [0, 1], mean over the batch."""
    return (1.0 - ssim(pred, target, mask, padding=padding)) / 2.0


def photometric_loss(pred: Any, target: Any, mask: Any = None, *,
                     lambda_dssim: float = DSSIM_LAMBDA, padding: Padding = "valid") -> Tensor:
    """3DGS's training loss ``(1 - lambda) * L1 + lambda * (1 - SSIM)``."""
    if not 0.0 <= lambda_dssim <= 1.0:
        raise ValueError(f"lambda_dssim must be in [0, 1], got {lambda_dssim}")
    return ((1.0 - lambda_dssim) * l1(pred, target, mask)
            + lambda_dssim * (1.0 - ssim(pred, target, mask, padding=padding)))


def gaussian_kernel(sigma: float = SSIM_SIGMA, radius: int = SSIM_RADIUS, *,
                    dtype: torch.dtype = torch.float32, device: Any = None) -> Tensor:
    """Normalised 1-D Gaussian taps ``[2 * radius + 1]`` (scipy's ``gaussian_filter1d``)."""
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).to(dtype=dtype, device=device)


def _weights(mask: Any, images: Tensor) -> Tensor | None:
    if mask is None:
        return None
    b, h, w, _ = images.shape
    return as_mask(mask, b, h, w, images)


def _blur(x: Tensor, kernel: Tensor, pad: int) -> Tensor:
    """Separable Gaussian filter of each channel of ``x [N, C, H, W]``, zero padding ``pad``
    (0: valid). Depthwise convs on a channels-last tensor: the fast CPU path (a single-channel
    conv over [N*C, 1, H, W] was ~20x slower at 512 x 512)."""
    n, c = kernel.numel(), x.shape[1]
    x = F.conv2d(x, kernel.view(1, 1, 1, n).expand(c, 1, 1, n), padding=(0, pad), groups=c)
    return F.conv2d(x, kernel.view(1, 1, n, 1).expand(c, 1, n, 1), padding=(pad, 0), groups=c)


def _ssim_map(p: Tensor, g: Tensor, padding: str) -> Tensor:
    """SSIM map of ``[B, H, W, C]`` images, averaged over channels -> ``[B, H', W']``."""
    if padding not in ("valid", "same"):
        raise ValueError(f"padding must be 'valid' or 'same', got {padding!r}")
    h, w = p.shape[1:3]
    win = 2 * SSIM_RADIUS + 1
    if padding == "valid" and (h < win or w < win):
        raise ValueError(f"ssim with padding='valid' needs images of at least {win} x {win}, "
                         f"got {h} x {w} (use padding='same')")
    # All five moments in one filter pass. [B, H, W, 5C] permuted to [B, 5C, H, W] is
    # channels-last in memory, which the depthwise conv wants.
    stats = torch.cat([p, g, p * p, g * g, p * g], dim=-1).permute(0, 3, 1, 2)
    kernel = gaussian_kernel(dtype=p.dtype, device=p.device)
    pad = 0 if padding == "valid" else SSIM_RADIUS
    # Back to plain NCHW: the element-wise maths below runs ~20% faster on contiguous maps.
    blurred = _blur(stats, kernel, pad).contiguous()  # [B, 5C, H', W']
    mx, my, mxx, myy, mxy = blurred.chunk(5, dim=1)  # [B, C, H', W'] each
    # Population (co)variances, as Wang et al. and 3DGS; data range 1.
    vx, vy, cxy = mxx - mx * mx, myy - my * my, mxy - mx * my
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    num = (2 * mx * my + c1) * (2 * cxy + c2)
    den = (mx * mx + my * my + c1) * (vx + vy + c2)  # >= c1 * c2 > 0 up to rounding
    return (num / den).mean(dim=1)  # [B, H', W']

